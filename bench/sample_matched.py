"""The sample-matched table: every learning method at equal env-step budgets.

The wall-clock tables rank methods at equal training time; this one ranks them at equal
samples, the axis where the off-policy learners are strong. It is read from the anytime
evaluations of step-budgeted runs (`--budget-steps`), so one 200k-step run gives its
score at 50k as well:

- a run whose whole training used at most S env steps (BC, which never steps the env; a
  run whose step budget is S) counts at S with its final score;
- otherwise its evaluation nearest to S within `TOLERANCE` (10%, relative) counts at S. A
  method reports in chunks (ILD: one update of batch x horizon steps, 4,096 on hopper, so
  its evaluation for 50k lands at 53,248; DAC, PWIL: a chunk of env steps), so an
  evaluation lands near, not on, the multiple of budget/evals; the table prints the median
  env steps of the evaluations it read;
- a run with no evaluation that close to S is left out of that budget (the `seeds` column
  says how many runs each cell has).

Wall-clock-budgeted runs are not read: where their clock stopped them depends on the
machine, and the table is about samples.
"""
from __future__ import annotations

import numpy as np
import pandas as pd

from bench.budget import format_steps

TOLERANCE = 0.10
BUDGETS = (50_000, 200_000)
COLUMNS = ["env_steps_budget", "task", "method", "variant", "seeds", "normalized_mean",
           "normalized_std", "env_steps_read", "updates_median"]


def point_at(curve: list[dict], total_steps: int, budget: int,
             tolerance: float = TOLERANCE) -> dict | None:
    """The evaluation of a run (its `curve`, `total_steps` env steps in all) that stands for
    it at `budget` env steps, or None (the rules in the module docstring)."""
    pts = [p for p in curve or [] if p.get("normalized") is not None
           and np.isfinite(p["normalized"])]
    if not pts:
        return None
    if total_steps <= budget:
        return max(pts, key=lambda p: (p.get("env_steps") or 0, p.get("train_s") or 0))
    best = min(pts, key=lambda p: abs((p.get("env_steps") or 0) - budget))
    return best if abs((best.get("env_steps") or 0) - budget) <= tolerance * budget else None


def table(frame: pd.DataFrame, budgets=BUDGETS) -> pd.DataFrame:
    """Per (step budget, task, method, variant): the mean and std of the normalized score at
    that budget over the runs that reach it, the median env steps of the points read and the
    median learner updates there. `frame` is bench.leaderboard.records_frame's."""
    steps = frame[frame.budget_steps.notna() & frame.status.isin(["ok", "diverged"])
                  & ~frame.reference.astype(bool)]
    rows = []
    for budget in budgets:
        for (task, method, var), g in steps.groupby(["task", "method", "variant"]):
            pts = [point_at(c, int(total or 0), budget) for c, total in
                   zip(g.curve, g.env_steps)]
            pts = [p for p in pts if p is not None]
            if not pts:
                continue
            norms = np.array([p["normalized"] for p in pts], float)
            updates = [(p.get("train") or {}).get("train/updates") for p in pts]
            updates = [u for u in updates if u is not None]
            rows.append({"env_steps_budget": budget, "task": task, "method": method,
                         "variant": var, "seeds": len(pts), "normalized_mean": float(norms.mean()),
                         "normalized_std": float(norms.std(ddof=1)) if len(pts) > 1
                         else float("nan"),
                         "env_steps_read": float(np.median([p.get("env_steps") or 0
                                                            for p in pts])),
                         "updates_median": float(np.median(updates)) if updates
                         else float("nan")})
    out = pd.DataFrame(rows, columns=COLUMNS)
    return out.sort_values(["env_steps_budget", "task", "normalized_mean"],
                           ascending=[True, True, False]).reset_index(drop=True)


def gaps(df: pd.DataFrame) -> dict[int, list[tuple[str, str, int]]]:
    """Per step budget, the (task, method, seeds) cells that hold fewer runs than the most
    any cell of that budget holds, counting a method that some task has and another lacks
    as 0 seeds there: what the store is still missing before the budget's table is
    complete. A method's variants count together (the most seeds of any of them)."""
    out = {}
    for budget, part in df.groupby("env_steps_budget"):
        seeds = part.groupby(["task", "method"]).seeds.max()
        want = int(seeds.max())
        tasks, methods = sorted(part.task.unique()), sorted(part.method.unique())
        out[int(budget)] = [(t, m, int(seeds.get((t, m), 0))) for t in tasks for m in methods
                            if seeds.get((t, m), 0) < want]
    return out


def _gap_note(missing: list[tuple[str, str, int]], want: int) -> str:
    by_task: dict[str, list[str]] = {}
    for task, method, n in missing:
        by_task.setdefault(task, []).append(f"{method} {n}")
    return (f"Incomplete (runs out of {want}): "
            + "; ".join(f"{t} {', '.join(ms)}" for t, ms in by_task.items()) + ".")


def _fmt_steps(v) -> str:
    return "-" if pd.isna(v) else format_steps(float(v))


def to_markdown(df: pd.DataFrame, floors: dict[str, dict] | None = None) -> str:
    """One table per step budget, with each task's zero_action floor beside its rows and,
    under it, the cells that hold fewer runs than the fullest (`gaps`)."""
    if df.empty:
        return "_no step-budgeted runs in the store (`ildbench sweep --budget-steps N`)_\n"
    floors = floors or {}
    missing = gaps(df)
    out = ["# Sample-matched scores (equal env steps)", "",
           "Normalized score (1 = expert, 0 = random policy) at each env-step budget, read "
           "from the anytime evaluations of step-budgeted runs (bench/sample_matched.py). "
           "`env steps read`: median env steps of the evaluations read; `updates`: median "
           "learner updates by then. BC never steps the env: its score is the same at every "
           "budget.", ""]
    for budget, part in df.groupby("env_steps_budget"):
        show = part.copy()
        show["normalized"] = [f"{m:.3f} ± {s:.3f}" if pd.notna(s) else f"{m:.3f}"
                              for m, s in zip(show.normalized_mean, show.normalized_std)]
        show["zero_action"] = [f"{floors[t]['zero_action']['normalized']:.3f}"
                               if "zero_action" in floors.get(t, {}) else "-"
                               for t in show.task]
        show["env steps read"] = show.env_steps_read.map(_fmt_steps)
        show["updates"] = show.updates_median.map(_fmt_steps)
        out += [f"## {format_steps(budget)} env steps", "",
                show[["task", "method", "normalized", "seeds", "env steps read", "updates",
                      "zero_action"]].to_markdown(index=False), ""]
        if missing.get(int(budget)):
            out += [_gap_note(missing[int(budget)], int(part.seeds.max())), ""]
    return "\n".join(out) + "\n"
