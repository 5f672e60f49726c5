#!/usr/bin/env python3
"""Mutation testing of the guarantee modules (docs/ci.md, "Mutation testing").

    python .ci/mutation.py sample store=40 budget=40 ...   # seeded sample of unchecked mutants
    python .ci/mutation.py verify                          # each triaged kill, re-run
    python .ci/mutation.py score                           # the table in docs/ci.md

Run from the repository root after `mutmut run` (mutmut 3.8.1; `[tool.mutmut]` in
pyproject.toml). The verdicts come from mutmut's own state (`mutmut results --all true`);
.ci/mutation_triage.toml says what became of each surviving mutant: the test added to kill
it, or why it is equivalent. `verify` runs each named test against its mutant in mutmut's
mutants/ tree (after checking that it passes there with no mutant active), so a kill in the
table is one that was seen, not assumed.
"""
from __future__ import annotations

import math
import os
import random
import re
import subprocess
import sys
import tomllib

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
TRIAGE = os.path.join(ROOT, ".ci", "mutation_triage.toml")
MODULES = ("budget", "access", "store", "stats", "check", "runner")
# runner.py is mutated in its budget and record parts only (issue scope): the run context,
# run ids and record identity, reindexing, the record head, failed records, execute().
RUNNER_PARTS = re.compile(
    r"bench\.runner\.(xǁRunContextǁ|x_(run_id|_run_key|_canonical|config_identity|"
    r"record_config_identity|record_run_id|reindex|_move_aside|_record_head|failed_record|"
    r"_finite_tree|execute)__)")
KILLED = {"killed", "timeout", "segfault"}  # a hang or a crash is a detected mutant too


def _results() -> dict[str, str]:
    out = subprocess.run(["mutmut", "results", "--all", "true"], capture_output=True,
                         text=True, cwd=ROOT, check=True).stdout
    rows = (line.strip().rsplit(": ", 1) for line in out.splitlines() if "__mutmut_" in line)
    return {name: status for name, status in rows}


def _module(name: str) -> str | None:
    mod = name.split(".")[1]
    if mod not in MODULES or (mod == "runner" and not RUNNER_PARTS.match(name)):
        return None
    return mod


def _triage() -> dict[str, dict]:
    with open(TRIAGE, "rb") as f:
        data = tomllib.load(f)
    for name, entry in data.items():
        if ("killed_by" in entry) == ("equivalent" in entry):
            sys.exit(f"{TRIAGE}: {name!r} needs exactly one of killed_by or equivalent")
    return data


def sample(args: list[str]) -> None:
    want = dict(a.split("=") for a in args)
    results = _results()
    rng = random.Random(0)
    for key, k in want.items():   # a module (store) or a function's prefix (bench.runner.x_execute)
        pool = sorted(n for n, s in results.items() if s == "not checked" and (
            n.startswith(key + "__mutmut_") if "." in key else _module(n) == key))
        for name in rng.sample(pool, min(int(k), len(pool))):
            print(name)


def verify(args: list[str]) -> int:
    triage = _triage()
    names = args or [n for n, e in triage.items() if "killed_by" in e]
    env = {**os.environ}
    bad = 0
    clean = {}
    for name in names:
        test = triage[name]["killed_by"]
        if test not in clean:
            env["MUTANT_UNDER_TEST"] = ""
            clean[test] = _pytest(test, env) == 0
            if not clean[test]:
                print(f"FAILS WITH NO MUTANT: {test}")
        env["MUTANT_UNDER_TEST"] = name
        rc = _pytest(test, env) if clean[test] else None
        ok = rc == 1
        bad += not ok
        print(f"{'killed' if ok else 'NOT KILLED (rc=%s)' % rc}: {name} by {test}")
    return 1 if bad else 0


def _pytest(test: str, env: dict) -> int:
    return subprocess.run([sys.executable, "-m", "pytest", "-x", "-q", "-p", "no:cacheprovider",
                           test], cwd=os.path.join(ROOT, "mutants"), env=env,
                          stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL).returncode


def _wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    if n == 0:
        return float("nan"), float("nan")
    p = k / n
    c = (p + z * z / (2 * n)) / (1 + z * z / n)
    h = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return c - h, c + h


def score(args: list[str]) -> int:
    results, triage = _results(), _triage()
    rows, untriaged = [], []
    for mod in MODULES:
        mine = {n: s for n, s in results.items() if _module(n) == mod}
        checked = {n: s for n, s in mine.items() if s != "not checked"}
        suite = sum(s in KILLED for s in checked.values())
        added = eq = 0
        for n, s in checked.items():
            if s in KILLED:
                continue
            entry = triage.get(n)
            if entry is None:
                untriaged.append(f"{n}: {s}")
            elif "killed_by" in entry:
                added += 1
            else:
                eq += 1
        n = len(checked)
        k = suite + added
        lo, hi = _wilson(k, n)
        rows.append(f"| `bench/{mod}.py`{' (budget and record parts)' if mod == 'runner' else ''}"
                    f" | {len(mine)} | {n} | {suite} | {added} | {eq} | {n - k - eq} | "
                    f"{100 * k / n:.1f}% | {100 * lo:.0f}-{100 * hi:.0f}% |" if n else
                    f"| `bench/{mod}.py` | {len(mine)} | 0 | - | - | - | - | - | - |")
    print("| module | mutants | checked | killed by the suite | killed by tests added for "
          "survivors | equivalent | survived, untriaged | score | 95% interval |")
    print("|---|---|---|---|---|---|---|---|---|")
    print("\n".join(rows))
    if untriaged:
        print("\nsurvivors without a triage entry:\n  " + "\n  ".join(untriaged))
        return 1
    return 0


if __name__ == "__main__":
    cmd, rest = sys.argv[1], sys.argv[2:]
    sys.exit({"sample": sample, "verify": verify, "score": score}[cmd](rest) or 0)
