"""`ildbench conform METHOD`: what a method plugin must do, checked on a cheap task.

A plugin author runs this before a sweep; tests/test_conformance.py runs it on every in-repo
method. The method is run (in this process, through the same runner as a sweep) on a cheap
task under an env-step budget, `repeats` times with one seed:

- runs:          the run finishes 'ok' with a finite final score;
- budget:        it stops near its env-step budget (at most twice the budget: one update or
                 chunk past the last `should_stop` check is normal); a failure says whether
                 the method ran on past `should_stop` or one update outgrew the budget (more
                 env steps per report than the whole budget: shrink the update or the preset);
- compiles once: no function is traced (and compiled) again once a report has followed its
                 first trace (the harness reads JAX's explanations of its tracing-cache
                 misses, which also say why: "now f32[]{weak_type=True} and before
                 f32[]"). One that is re-traces its update, which a wall-clock budget pays
                 for silently (SHAC lost 150 of 180 s on hopper to one extra compile of its
                 epoch before a weak type was fixed);
- deterministic: the same seed gives the same final return (on one machine, CPU).

A check that cannot apply (a planner reports nothing while it "trains") reads n/a.
"""
from __future__ import annotations

import dataclasses
import math
import tempfile
from typing import Any, Callable, Mapping

from bench.budget import Budget
from bench.evaluator import EvalConfig
from bench.runner import RunRequest, execute, prepare
from bench.store import Store


@dataclasses.dataclass(frozen=True)
class Finding:
    check: str
    passed: bool | None
    """None: does not apply to this method."""
    detail: str


def conform(method: str, task: str = "pointmass", env_steps: int = 20_000, evals: int = 2,
            overrides: Mapping[str, Any] | None = None, preset: str | None = None,
            repeats: int = 2, seed: int = 0, eval_episodes: int = 4,
            log: Callable[[str], None] = lambda s: None) -> list[Finding]:
    if repeats < 1:
        raise ValueError(f"repeats must be >= 1, got {repeats}")
    req = RunRequest(method=method, task=task, seed=seed,
                     budget=Budget(env_steps=env_steps, evals=evals), preset=preset,
                     overrides=dict(overrides or {}),
                     eval=EvalConfig(num_episodes=eval_episodes))
    prepared = prepare(req)  # bad names / configs raise here, before any work
    records = []
    with tempfile.TemporaryDirectory() as tmp:
        for _ in range(repeats):
            records.append(execute(prepared, Store(tmp), force=True, log=log)[0])
    return findings(records, env_steps)


def findings(records: list[dict], env_steps: int) -> list[Finding]:
    first = records[0]
    out = []
    ok = [r["status"] == "ok" and r["final_return"] is not None
          and math.isfinite(r["final_return"]) for r in records]
    if not all(ok):
        why = [r["status"] + ": " + (r["message"] or "").partition("\n")[0]
               for r, good in zip(records, ok) if not good]
        return [Finding("runs", False, "; ".join(why))]
    out.append(Finding("runs", True, f"ok, final normalized {first['final_normalized']:.3f}"))
    used = int(first["env_steps"])
    per_report = used / max(int(first.get("reports") or 0), 1)
    if used <= 2 * env_steps:
        hint = ""
    elif per_report > env_steps:  # it stopped when told, but one update outgrew the budget
        hint = (f": one report interval (an update) simulates {per_report:.0f} env steps on "
                f"average, more than the whole budget; make the update smaller (a smaller "
                f"preset such as --preset cpu, or --set) or give a larger --steps")
    else:
        hint = (": call ctx.should_stop(env_steps) before each update and pass the steps "
                "simulated so far")
    out.append(Finding("budget", used <= 2 * env_steps,
                       f"used {used} of {env_steps} env steps" + hint))
    again = first.get("retraced")
    if again is None:
        out.append(Finding("compiles once", None,
                           f"n/a: {first.get('reports', 0)} reports (a method without a "
                           "training loop)"))
    else:
        total = first["compiles"]["train"]
        out.append(Finding(
            "compiles once", not again,
            f"{total} computations compiled in training over {first['reports']} reports, "
            + ("none traced again" if not again else
               "traced again after a report: " + "; ".join(
                   f"{fun} {v['count']}x (JAX: {v['why']})" for fun, v in again.items())
               + ". Keep the carried state's dtypes, weak types and shapes fixed (cast "
               "Python scalars with jnp.float32), jit one function object once, keep static "
               "arguments constant")))
    if len(records) < 2:
        out.append(Finding("deterministic", None, "n/a: one repeat"))
    else:
        rets = [r["final_return"] for r in records]
        same = all(x == rets[0] for x in rets)
        out.append(Finding("deterministic", same,
                           f"final return {rets[0]:.6g} in all {len(rets)} runs" if same else
                           f"final returns differ for one seed: {rets}; derive every random "
                           "key/generator from the `seed` argument"))
    return out


def render(method: str, found: list[Finding]) -> str:
    mark = {True: "PASS", False: "FAIL", None: "n/a "}
    rows = [f"{mark[f.passed]}  {f.check:14s} {f.detail}" for f in found]
    verdict = "FAIL" if any(f.passed is False for f in found) else "PASS"
    return "\n".join([f"conformance of {method!r}:"] + rows + [f"verdict: {verdict}"])
