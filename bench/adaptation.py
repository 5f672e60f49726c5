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

from collections import defaultdict
from typing import Iterable

import numpy as np
import pandas as pd

COLUMNS = ["task", "dynamics", "method", "seeds", "adapted_mean", "adapted_std",
           "adapted_nominal", "zero_shot_seeds", "zero_shot_mean", "zero_shot_std",
           "zero_shot_nominal", "gain", "budget", "zero_shot_budget"]


def _scored(record: dict) -> bool:
    return record.get("status") == "ok"


def _reporting(records: Iterable[dict]) -> list[dict]:
    """The records on reporting seeds where there are any (bench/seeds.py)."""
    from bench.seeds import is_tuning
    records = list(records)
    report = [r for r in records if not is_tuning(r["seed"])]
    return report or records


def _main(groups: dict[tuple, list[dict]]) -> dict[tuple, list[dict]]:
    """Per (task, method): the variant group with the most records, ties to the newest."""
    best: dict[tuple, list[dict]] = {}
    for (task, method, _), recs in sorted(groups.items()):
        cur = best.get((task, method))
        rank = (len(recs), max(r.get("started") or "" for r in recs))
        if cur is None or rank > (len(cur), max(r.get("started") or "" for r in cur)):
            best[(task, method)] = recs
    return best


def _budget(recs: list[dict]) -> str:
    from bench.budget import Budget
    return ", ".join(sorted({Budget(**r["budget"]).describe() for r in recs}))


def _stats(values: list[float]) -> tuple[float, float]:
    v = np.asarray(values, float)
    return float(v.mean()), float(v.std(ddof=1)) if len(v) > 1 else float("nan")


def table(adapted: Iterable[dict], zero_shot: Iterable[dict]) -> pd.DataFrame:
    """One row per (task, method) that has runs trained in changed dynamics in `adapted`
    (records); the zero-shot columns are NaN where `zero_shot` (records) holds no nominal run
    of that method on that task with a transfer entry for the same dynamics."""
    from bench.leaderboard import variant
    adapted, zero_shot = _reporting(adapted), _reporting(zero_shot)
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for r in adapted:
        if _scored(r) and r.get("train_dynamics"):
            groups[(r["task"], r["method"], variant(r))].append(r)
    main = _main(groups)
    keys = {(t, m): recs[0]["train_dynamics"]["key"] for (t, m), recs in main.items()}
    zgroups: dict[tuple, list[dict]] = defaultdict(list)
    for r in zero_shot:
        key = keys.get((r.get("task"), r.get("method")))
        if (key is None or not _scored(r) or r.get("train_dynamics")
                or ((r.get("transfer") or {}).get(key) or {}).get("normalized") is None):
            continue
        zgroups[(r["task"], r["method"], variant(r))].append(r)
    zmain = _main(zgroups)
    rows = []
    for (task, method), recs in sorted(main.items()):
        key = keys[(task, method)]
        a_mean, a_std = _stats([r["final_normalized"] for r in recs])
        nominal = [(r.get("nominal") or {}).get("normalized") for r in recs]
        nominal = [v for v in nominal if v is not None]
        zs = zmain.get((task, method), [])
        z_mean, z_std = (_stats([r["transfer"][key]["normalized"] for r in zs]) if zs
                         else (float("nan"), float("nan")))
        rows.append({
            "task": task, "dynamics": key, "method": method, "seeds": len(recs),
            "adapted_mean": a_mean, "adapted_std": a_std,
            "adapted_nominal": float(np.mean(nominal)) if nominal else float("nan"),
            "zero_shot_seeds": len(zs), "zero_shot_mean": z_mean, "zero_shot_std": z_std,
            "zero_shot_nominal": (float(np.mean([r["final_normalized"] for r in zs])) if zs
                                  else float("nan")),
            "gain": a_mean - z_mean, "budget": _budget(recs),
            "zero_shot_budget": _budget(zs) if zs else ""})
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
