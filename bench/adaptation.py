"""Adaptation beside zero-shot transfer: which methods adapt to changed dynamics, and which
only generalize to them.

Two stores meet in one table, per task and method, for one changed dynamics per task:

- `adapted`: runs trained in the changed dynamics (`--train-dynamics`) and scored in them
  (the record's headline score); `adapted_nominal` is the same final policies scored in
  the nominal dynamics;
- `zero_shot`: runs trained in the nominal dynamics (a store swept with `--transfer`) and
  scored in the same changed dynamics (the record's transfer entry of that key);
  `zero_shot_nominal` is their own nominal score;
- `gain` = adapted - zero_shot: what training in the changed dynamics bought.

Both sides are normalized against the expert and the random policy measured in the changed
dynamics (`bench.transfer.references`), so they share one scale. Each side pools the seeds
of one variant per (task, method): the one with the most scored seeds, ties to the newest
run, on the reporting seeds (bench/seeds.py). The demo is the nominal one on both sides.
The budgets are printed per side, and the notes say where they differ.
"""
from __future__ import annotations

import numpy as np
import pandas as pd

COLUMNS = ["task", "dynamics", "method", "seeds", "adapted_mean", "adapted_std",
           "adapted_nominal", "zero_shot_seeds", "zero_shot_mean", "zero_shot_std",
           "zero_shot_nominal", "gain", "budget", "zero_shot_budget"]


def _stats(values: pd.Series) -> tuple[float, float]:
    v = values.astype(float).to_numpy()
    if not len(v):
        return float("nan"), float("nan")
    return float(v.mean()), float(v.std(ddof=1)) if len(v) > 1 else float("nan")


def _budgets(g: pd.DataFrame) -> str:
    return ", ".join(sorted(set(g.budget)))


def table(adapted: pd.DataFrame, zero_shot: pd.DataFrame) -> pd.DataFrame:
    """One row per (task, method) that has runs trained in changed dynamics in `adapted`;
    the zero-shot columns are NaN where `zero_shot` holds no nominal run of that method on
    that task with a transfer entry for the same dynamics. Both are
    bench.leaderboard.records_frame's; each side keeps its reporting runs
    (`leaderboard.reporting_runs`) and its main variant (`leaderboard.main_variants`)."""
    from bench.leaderboard import NOMINAL, main_variants, reporting_runs
    a = reporting_runs(adapted)[0]
    a = main_variants(a[(a.status == "ok") & (a.dynamics != NOMINAL)])
    keys = {(t, m): k for t, m, k in zip(a.task, a.method, a.dynamics)}
    z = reporting_runs(zero_shot)[0]
    z = z.assign(zero_shot=[(entries or {}).get(keys.get((t, m))) for t, m, entries in
                            zip(z.task, z.method, z.transfer_by_key)])
    z = main_variants(z[(z.status == "ok") & (z.dynamics == NOMINAL) & z.zero_shot.notna()])
    rows = []
    for (task, method), g in a.groupby(["task", "method"]):
        zs = z[(z.task == task) & (z.method == method)]
        a_mean, a_std = _stats(g.normalized)
        z_mean, z_std = _stats(zs.zero_shot)
        rows.append({
            "task": task, "dynamics": keys[(task, method)], "method": method,
            "seeds": len(g), "adapted_mean": a_mean, "adapted_std": a_std,
            "adapted_nominal": _stats(g.nominal.dropna())[0],
            "zero_shot_seeds": len(zs), "zero_shot_mean": z_mean, "zero_shot_std": z_std,
            "zero_shot_nominal": _stats(zs.normalized)[0],
            "gain": a_mean - z_mean, "budget": _budgets(g), "zero_shot_budget": _budgets(zs)})
    return pd.DataFrame(rows, columns=COLUMNS)


def _pm(mean: float, std: float) -> str:
    if np.isnan(mean):
        return "-"
    return f"{mean:.2f}" + ("" if np.isnan(std) else f" ± {std:.2f}")


def _f(v: float, signed: bool = False) -> str:
    return "-" if np.isnan(v) else (f"{v:+.2f}" if signed else f"{v:.2f}")


def to_markdown(df: pd.DataFrame) -> str:
    """The table with its reading notes."""
    show = pd.DataFrame({
        "task": df.task, "dynamics": df.dynamics, "method": df.method, "seeds": df.seeds,
        "adapted": [_pm(m, s) for m, s in zip(df.adapted_mean, df.adapted_std)],
        "adapted, nominal": df.adapted_nominal.map(_f),
        "zero-shot": [_pm(m, s) for m, s in zip(df.zero_shot_mean, df.zero_shot_std)],
        "zero-shot, nominal": df.zero_shot_nominal.map(_f),
        "gain": df.gain.map(lambda v: _f(v, signed=True))})
    notes = [
        "`adapted`: trained and scored in the task's changed dynamics (mean ± std over "
        "seeds); `adapted, nominal`: the same policies in the nominal dynamics. `zero-shot`: "
        "policies trained in the nominal dynamics, scored in the changed ones; `zero-shot, "
        "nominal`: their nominal score. `gain` = adapted - zero-shot. Scores in changed "
        "dynamics are normalized against the expert and the random policy measured in them; "
        "the demo is the nominal one throughout."]
    budgets = {(b, z) for b, z in zip(df.budget, df.zero_shot_budget) if z}
    if any(b != z for b, z in budgets):
        notes.append("The two sides' budgets differ: " + "; ".join(
            f"adapted {b}, zero-shot {z}" for b, z in sorted(budgets) if b != z) + ".")
    elif budgets:
        notes.append(f"Both sides trained for {sorted(budgets)[0][0]} per run.")
    missing = df[df.zero_shot_seeds == 0]
    if len(missing):
        notes.append("No zero-shot runs for: " + ", ".join(
            f"{m} on {t}" for t, m in zip(missing.task, missing.method)) + ".")
    table_md = show.to_markdown(index=False, disable_numparse=True)  # "0.20" stays as written
    return table_md + "\n\n" + "\n".join(f"- {n}" for n in notes) + "\n"
