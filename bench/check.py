"""CI regression gate: a canary suite with env-step budgets, compared with a reference.

A suite is a TOML file (bench/data/canary_suite.toml is ildbench's own; a plugin author
writes one for their method): per canary the method (any registered one, a plugin's
included), the task, an env-step budget, config overrides, seeds and a tolerance. The
canary cells use env-step budgets (not wall-clock), fixed seeds and fixed evaluation
episodes, so on a CPU they are deterministic up to floating-point differences between
machines. `ildbench check` runs them into a fresh store, averages each canary over its seeds
and compares with the reference file:

    fail if  mean_now < mean_ref - tol,   tol = max(tolerance, z * std_ref / sqrt(n))

`tolerance` covers cross-machine float drift; the statistical term widens the band where the
reference seeds disagree (z = 3: a ~0.1% one-sided false alarm rate under a normal model).
An improvement never fails; `ildbench check --update` rewrites the reference after an
intended change (commit it with the change that explains it).
"""
from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import tempfile
import tomllib
from typing import Callable, Mapping, Sequence

import numpy as np

from bench.budget import Budget
from bench.evaluator import EvalConfig
from bench.runner import RunRequest, prepare
from bench.store import Store, write_json_atomic

_DATA = os.path.join(os.path.dirname(os.path.abspath(__file__)), "data")
SUITE_FILE = os.path.join(_DATA, "canary_suite.toml")
REFERENCE = os.path.join(_DATA, "canary_reference.json")
ABS_TOL = 0.05
Z = 3.0
SEEDS = (0, 1)
EVAL_EPISODES = 16


class SuiteError(ValueError):
    """A malformed canary suite file; the message names the file, the line and the fix."""


@dataclasses.dataclass(frozen=True)
class Canary:
    method: str
    task: str
    env_steps: int
    overrides: tuple[tuple[str, object], ...] = ()
    seeds: tuple[int, ...] = SEEDS
    eval_episodes: int = EVAL_EPISODES
    tolerance: float = ABS_TOL
    name: str | None = None

    @property
    def key(self) -> str:
        return self.name or f"{self.method}/{self.task}"

    @property
    def definition(self) -> dict:
        """What the reference's numbers were measured with (stored beside them), as JSON
        reads it back (a tuple-valued override compares equal to the list it is stored as)."""
        return json.loads(json.dumps({"env_steps": self.env_steps,
                                      "overrides": dict(self.overrides),
                                      "seeds": list(self.seeds),
                                      "eval_episodes": self.eval_episodes}))


@dataclasses.dataclass(frozen=True)
class Suite:
    canaries: tuple[Canary, ...]
    z: float = Z
    path: str | None = None


_TOP_KEYS = {"seeds", "eval_episodes", "tolerance", "z", "canary"}
_CANARY_KEYS = {"method", "task", "env_steps", "overrides", "seeds", "eval_episodes",
                "tolerance", "name"}


def _seeds(v, where: str) -> tuple[int, ...]:
    if not (isinstance(v, list) and v and all(isinstance(x, int) and not isinstance(x, bool)
                                               and x >= 0 for x in v)):
        raise SuiteError(f"{where}: seeds must be a non-empty list of whole numbers >= 0, "
                         f"e.g. seeds = [0, 1]; got {v!r}")
    if len(set(v)) != len(v):
        raise SuiteError(f"{where}: seeds repeat ({v}); list each seed once")
    return tuple(v)


def _number(v, name: str, where: str, low: float, whole: bool = False):
    ok = isinstance(v, int if whole else (int, float)) and not isinstance(v, bool) and v >= low
    if not ok:
        kind = "a whole number" if whole else "a number"
        raise SuiteError(f"{where}: {name} must be {kind} >= {low:g}, got {v!r}")
    return v


def load_suite(path: str) -> Suite:
    """Read and validate a suite file: every method and task registered, every budget a
    positive whole number of env steps, every override a field of the method's config, keys
    unique. SuiteError names the file, the line of the offending [[canary]] and the fix."""
    from bench.plugins import ConfigError, UnknownMethodError, build_config, get_method
    from tasks.registry import TASKS
    try:
        with open(path, "rb") as f:
            raw = f.read()
    except FileNotFoundError:
        raise SuiteError(f"no canary suite at {path}; write one (docs/adding-a-method.md, "
                         f"'A canary suite') or drop --suite for ildbench's own") from None
    try:
        data = tomllib.loads(raw.decode())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise SuiteError(f"{path}: not valid TOML ({e})") from None
    unknown = sorted(set(data) - _TOP_KEYS)
    if unknown:
        raise SuiteError(f"{path}: unknown key(s) {unknown}; a suite has "
                         f"{', '.join(sorted(_TOP_KEYS - {'canary'}))} and [[canary]] tables")
    seeds = _seeds(data.get("seeds", list(SEEDS)), f"{path}")
    episodes = _number(data.get("eval_episodes", EVAL_EPISODES), "eval_episodes", path, 1, True)
    tol = _number(data.get("tolerance", ABS_TOL), "tolerance", path, 0)
    z = _number(data.get("z", Z), "z", path, 0)
    entries = data.get("canary", [])
    if not isinstance(entries, list) or not entries:
        raise SuiteError(f"{path}: no canaries; add [[canary]] tables with method, task and "
                         "env_steps")
    lines = [i + 1 for i, line in enumerate(raw.decode().splitlines())
             if re.match(r"\s*\[\[\s*canary\s*\]\]", line)]
    out, keys = [], {}
    for i, c in enumerate(entries):
        where = f"{path} line {lines[i] if i < len(lines) else '?'} ([[canary]] {i + 1})"
        bad = sorted(set(c) - _CANARY_KEYS)
        if bad:
            raise SuiteError(f"{where}: unknown key(s) {bad}; a canary has "
                             f"{', '.join(sorted(_CANARY_KEYS))}")
        missing = [k for k in ("method", "task", "env_steps") if k not in c]
        if missing:
            raise SuiteError(f"{where}: missing {', '.join(missing)}; e.g. method = \"bc\", "
                             "task = \"pointmass\", env_steps = 20000")
        try:
            spec = get_method(str(c["method"]))
        except UnknownMethodError as e:
            raise SuiteError(f"{where}: {e}; install the plugin that provides it or fix the "
                             "name") from None
        if c["task"] not in TASKS:
            raise SuiteError(f"{where}: unknown task {c['task']!r}; valid tasks: "
                             f"{', '.join(sorted(TASKS))}")
        steps = _number(c["env_steps"], "env_steps", where, 1, True)
        over = c.get("overrides", {})
        if not isinstance(over, dict):
            raise SuiteError(f"{where}: overrides must be a table, e.g. overrides = "
                             f"{{ updates = 300 }}; got {over!r}")
        try:
            build_config(spec, c["task"], overrides=over)
        except ConfigError as e:
            raise SuiteError(f"{where}: {e}") from None
        canary = Canary(spec.name, c["task"], steps, tuple(sorted(over.items())),
                        _seeds(c["seeds"], where) if "seeds" in c else seeds,
                        _number(c.get("eval_episodes", episodes), "eval_episodes", where, 1,
                                True),
                        _number(c.get("tolerance", tol), "tolerance", where, 0),
                        str(c["name"]) if "name" in c else None)
        if canary.key in keys:
            raise SuiteError(f"{where}: canary {canary.key!r} is already defined at "
                             f"{keys[canary.key]}; give one of them a distinct name = \"...\"")
        keys[canary.key] = where
        out.append(canary)
    return Suite(tuple(out), z=float(z), path=path)


def default_suite() -> Suite:
    """ildbench's own gate (bench/data/canary_suite.toml)."""
    return load_suite(SUITE_FILE)


def requests(suite: Sequence[Canary],
             extra: Mapping[str, Mapping[str, object]] | None = None
             ) -> list[tuple[str, RunRequest]]:
    """(canary key, request) per canary and seed. `extra`: per canary key, config overrides
    added on top (tests plant regressions)."""
    out = []
    for c in suite:
        over = {**dict(c.overrides), **dict((extra or {}).get(c.key, {}))}
        for s in c.seeds:
            out.append((c.key, RunRequest(method=c.method, task=c.task, seed=s,
                                          budget=Budget(env_steps=c.env_steps, evals=1),
                                          overrides=over,
                                          eval=EvalConfig(num_episodes=c.eval_episodes))))
    return out


def run_suite(reqs: Sequence[tuple[str, RunRequest]], store: Store,
              log: Callable[[str], None] = lambda s: None) -> dict[str, list[float | None]]:
    """{canary key: [normalized score per seed]} (None for a failed run)."""
    from bench.sweep import run_local
    prepared = [(key, prepare(r)) for key, r in reqs]
    key_of = {p.run_id: key for key, p in prepared}
    scores: dict[str, list[float | None]] = {}
    for o in run_local([p for _, p in prepared], store, log=log, isolate=False):
        ok = o.status == "ok" and o.normalized is not None
        scores.setdefault(key_of[o.run_id], []).append(float(o.normalized) if ok else None)
    return scores


def summarize(scores: Mapping[str, Sequence[float | None]]) -> dict[str, dict]:
    out = {}
    for key, vals in scores.items():
        v = np.array([np.nan if x is None else x for x in vals], float)
        out[key] = {"scores": [None if not np.isfinite(x) else float(x) for x in v],
                    "mean": float(np.mean(v)) if np.isfinite(v).all() else None,
                    "std": float(np.std(v, ddof=1)) if len(v) > 1 and np.isfinite(v).all()
                    else 0.0, "n": int(len(v))}
    return out


@dataclasses.dataclass
class Verdict:
    key: str
    reference: float | None
    now: float | None
    tolerance: float
    passed: bool
    why: str


def compare(reference: Mapping[str, dict], now: Mapping[str, dict], abs_tol: float = ABS_TOL,
            z: float = Z, tolerances: Mapping[str, float] | None = None) -> list[Verdict]:
    """`tolerances`: per canary key, its own absolute tolerance (else `abs_tol`)."""
    out = []
    for key in sorted(set(reference) | set(now)):
        ref, cur = reference.get(key), now.get(key)
        if ref is None:
            out.append(Verdict(key, None, cur and cur["mean"], 0.0, True,
                               "new canary, no reference yet (run `ildbench check --update`)"))
            continue
        tol = max((tolerances or {}).get(key, abs_tol), z * ref.get("std", 0.0) / math.sqrt(max(ref.get("n", 1), 1)))
        if cur is None:
            out.append(Verdict(key, ref["mean"], None, tol, False,
                               "canary missing from this run"))
        elif ref.get("canary") is not None and ref["canary"] != cur.get("canary"):
            # a canary whose budget or overrides changed since its reference was written is
            # not comparable with it: fail, naming both and the fix
            out.append(Verdict(key, ref["mean"], cur["mean"], tol, False, (
                f"canary changed since its reference (reference: {ref['canary']}, now: "
                f"{cur.get('canary')}); run `ildbench check --update` and commit the reference")))
        elif cur["mean"] is None:
            out.append(Verdict(key, ref["mean"], None, tol, False,
                               "a run failed or diverged: " + str(cur["scores"])))
        elif cur["mean"] < ref["mean"] - tol:
            out.append(Verdict(key, ref["mean"], cur["mean"], tol, False,
                               f"dropped {ref['mean'] - cur['mean']:.3f} > tolerance {tol:.3f}"))
        else:
            out.append(Verdict(key, ref["mean"], cur["mean"], tol, True, "ok"))
    return out


def render(verdicts: Sequence[Verdict]) -> str:
    def f(x):
        return "-" if x is None else f"{x:.3f}"
    rows = [f"{'canary':28s} {'reference':>9s} {'now':>7s} {'delta':>7s} {'tol':>6s}  result"]
    for v in verdicts:
        delta = "-" if v.reference is None or v.now is None else f"{v.now - v.reference:+.3f}"
        rows.append(f"{v.key:28s} {f(v.reference):>9s} {f(v.now):>7s} {delta:>7s} "
                    f"{v.tolerance:6.3f}  {'PASS' if v.passed else 'FAIL'}: {v.why}")
    return "\n".join(rows)


def load_reference(path: str = REFERENCE, suite_path: str | None = None) -> dict:
    fix = (f"ildbench check --suite {suite_path} --reference {path} --update"
           if suite_path else "ildbench check --update")
    try:
        with open(path) as f:
            data = json.load(f)
    except FileNotFoundError:
        raise FileNotFoundError(f"no canary reference at {path}; create it with `{fix}` "
                                "and commit it") from None
    except json.JSONDecodeError as e:
        raise ValueError(f"canary reference {path} is not valid JSON ({e}); restore it from "
                         f"git or regenerate it with `{fix}`") from None
    if not isinstance(data, dict) or not isinstance(data.get("canaries"), dict):
        raise ValueError(f"canary reference {path} has no 'canaries' table; regenerate it "
                         f"with `{fix}`")
    return data["canaries"]


def check(reference_path: str = REFERENCE, update: bool = False, store_dir: str | None = None,
          extra: Mapping[str, Mapping[str, object]] | None = None,
          suite: Suite | Sequence[Canary] | None = None,
          log: Callable[[str], None] = print) -> tuple[bool, str]:
    """Run the suite (default: ildbench's own); compare (or write the reference). Returns
    (passed, report). Canaries of the reference that are not in the suite are not
    compared. The reference is read before any run, so a missing one costs nothing."""
    suite = default_suite() if suite is None else suite
    if not isinstance(suite, Suite):
        suite = Suite(tuple(suite))
    ref = None if update else load_reference(reference_path, suite.path)
    with tempfile.TemporaryDirectory() as tmp:
        store = Store(store_dir or tmp)
        now = summarize(run_suite(requests(suite.canaries, extra=extra), store, log=log))
    for c in suite.canaries:  # what these numbers were measured with, beside the reference's
        now[c.key]["canary"] = c.definition
    if update:
        write_json_atomic(reference_path, {
            "about": "ildbench canary reference: normalized final scores per canary over "
                     "its seeds; written by `ildbench check --update`",
            "suite": os.path.basename(suite.path) if suite.path else None,
            "z": suite.z, "canaries": now})
        return True, f"reference written: {reference_path}\n" + json.dumps(now, indent=1)
    keys = {c.key for c in suite.canaries}
    verdicts = compare({k: v for k, v in ref.items() if k in keys}, now, z=suite.z,
                       tolerances={c.key: c.tolerance for c in suite.canaries})
    passed = all(v.passed for v in verdicts)
    return passed, render(verdicts) + f"\n\ncanary gate: {'PASS' if passed else 'FAIL'}"
