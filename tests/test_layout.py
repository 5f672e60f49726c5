"""The package layering: `tasks/` (the task registry, envs, physics and demo format) imports
nothing from `bench/` (the harness), no installed module imports the measurement tools in
`benchmarks/`, and the installed packages hold no import cycle (lazy imports inside
functions included: a cycle hidden in a function body is still one); and importing the
mutation run's test modules starts no JAX backend."""
from __future__ import annotations

import ast
import os

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
INSTALLED = ("bench", "methods", "tasks")


def _modules(packages) -> dict[str, str]:
    mods = {}
    for pkg in packages:
        for root, _, files in os.walk(os.path.join(ROOT, pkg)):
            for f in files:
                if f.endswith(".py"):
                    path = os.path.join(root, f)
                    name = os.path.relpath(path, ROOT)[:-3].replace(os.sep, ".")
                    mods[name.removesuffix(".__init__")] = path
    return mods


def import_graph(packages=INSTALLED + ("benchmarks",)) -> dict[str, set[str]]:
    """{module: modules of `packages` it imports anywhere in its body}."""
    mods = _modules(packages)

    def resolve(name: str) -> str | None:
        while name and name not in mods:
            name = name.rpartition(".")[0]
        return name or None

    graph = {}
    for mod, path in mods.items():
        with open(path) as f:
            tree = ast.parse(f.read(), path)
        names = set()
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names.update(a.name for a in node.names)
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = mod if path.endswith("__init__.py") else mod.rpartition(".")[0]
                    for _ in range(node.level - 1):
                        base = base.rpartition(".")[0]
                    module = base + ("." + node.module if node.module else "")
                else:
                    module = node.module
                names.add(module)
                names.update(f"{module}.{a.name}" for a in node.names)
        graph[mod] = {r for r in map(resolve, names) if r and r != mod}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components of more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_cycle_finder_finds_a_planted_cycle_and_only_it():
    g = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}, "e": set()}
    assert cycles(g) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_tasks_import_nothing_from_bench():
    graph = import_graph()
    bad = sorted((m, d) for m, deps in graph.items() if m.split(".")[0] == "tasks"
                 for d in deps if d.split(".")[0] == "bench")
    assert bad == [], f"tasks/ imports bench/: {bad}"


def test_installed_packages_do_not_import_the_measurement_tools():
    graph = import_graph()
    bad = sorted((m, d) for m, deps in graph.items() if m.split(".")[0] in INSTALLED
                 for d in deps if d.split(".")[0] == "benchmarks")
    assert bad == [], bad


def test_installed_packages_hold_no_import_cycle():
    graph = import_graph(INSTALLED)
    assert cycles(graph) == []


def test_packaging_installs_the_three_packages_and_their_runtime_data():
    """pyproject's package list names bench, methods and tasks exactly (a glob such as
    "bench*" would also install benchmarks/), and ships the references and the canary
    reference the harness reads at run time."""
    tomllib = pytest.importorskip("tomllib")
    with open(os.path.join(ROOT, "pyproject.toml"), "rb") as f:
        cfg = tomllib.load(f)["tool"]["setuptools"]
    from setuptools import find_packages
    found = set(find_packages(ROOT, include=cfg["packages"]["find"]["include"]))
    assert {p.split(".")[0] for p in found} == set(INSTALLED)
    data = cfg["package-data"]
    assert "data/references/*.json" in data["tasks"] and "data/*.json" in data["bench"]
    assert "data/*.toml" in data["bench"]
    from bench.check import REFERENCE, SUITE_FILE
    assert os.path.isfile(SUITE_FILE) and os.path.dirname(SUITE_FILE) == os.path.dirname(REFERENCE)
    from bench.transfer import REF_DIR
    assert os.path.isfile(REFERENCE)
    assert os.path.isfile(os.path.join(REF_DIR, "hopper.json"))
    assert os.path.commonpath([REFERENCE, os.path.join(ROOT, "bench")]) == os.path.join(ROOT, "bench")


def test_collecting_the_mutation_tests_starts_no_jax_backend():
    """Fault it catches: a test module of the mutation run that runs a JAX computation when it
    is imported (a jnp default argument, a module-level array). mutmut's fork server collects
    those modules, so its workers would fork from a live XLA backend, whose threads do not
    survive fork: every mutant whose tests compute with JAX would hang to a timeout, which
    mutmut counts as killed (docs/ci.md)."""
    import subprocess
    import sys
    import tomllib
    with open(os.path.join(ROOT, "pyproject.toml"), "rb") as f:
        selection = tomllib.load(f)["tool"]["mutmut"]["pytest_add_cli_args_test_selection"]
    probe = ("import importlib, sys\n"
             "sys.path.insert(0, '.')\n"
             "from jax._src import xla_bridge\n"
             "for path in sys.argv[1:]:\n"
             "    importlib.import_module(path[:-3].replace('/', '.'))\n"
             "print('backends started:', bool(xla_bridge._backends))\n")
    out = subprocess.run([sys.executable, "-c", probe, *selection], cwd=ROOT,
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.strip().splitlines()[-1] == "backends started: False"
