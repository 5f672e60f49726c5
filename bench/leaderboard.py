"""Leaderboard: mean +/- std of the FINAL normalized score per task x method, over seeds.

Runs pool over seeds only when method version, preset and config are equal (the 'variant'
column, a short hash of them); the budget is shown so unequal budgets are visible. A
'diverged' run counts with its last valid evaluation (or 0.0, random level, if it never had
one); 'failed' runs are listed in the `failed` column and not averaged.
"""
from __future__ import annotations

import hashlib
import json
import os

import pandas as pd

from bench.api import Uses
from bench.budget import Budget
from bench.store import Store

COLUMNS = ["task", "method", "variant", "uses", "budget", "seeds", "normalized_mean", "normalized_std",
           "transfer_mean", "transfer_std", "return_mean", "diverged", "failed"]


def _transfer(record: dict) -> float | None:
    """Recomputed from the record's per-family entries with the current applicability rules
    (bench.perturb.inapplicable), at the default magnitudes."""
    from bench.transfer import default_summary
    from tasks import make_task
    transfer = record.get("transfer") or {}
    return default_summary(transfer, make_task(record["task"])) if transfer else None


def variant(record: dict) -> str:
    """Short id of (method version, preset, config): runs pool over seeds only when equal."""
    key = json.dumps([record.get("method_version"), record.get("preset"),
                      record.get("config")], sort_keys=True, default=str)
    return hashlib.sha256(key.encode()).hexdigest()[:6]


def records_frame(store: Store) -> pd.DataFrame:
    rows = []
    for r in store.records():
        norm = r.get("final_normalized")
        if r["status"] == "diverged" and norm is None:
            norm = 0.0
        rows.append({"task": r["task"], "method": r["method"], "variant": variant(r),
                     "seed": r["seed"],
                     "status": r["status"], "normalized": norm, "return": r.get("final_return"),
                     "transfer": _transfer(r),
                     "uses": Uses(**r["uses"]).describe() + (" (reference)" if r.get(
                         "reference_method") else ""),
                     "budget": Budget(**r["budget"]).describe(), "train_s": r.get("train_s")})
    return pd.DataFrame(rows, columns=["task", "method", "variant", "seed", "status",
                                       "normalized",
                                       "return", "transfer", "uses", "budget", "train_s"])


def leaderboard(store: Store) -> pd.DataFrame:
    df = records_frame(store)
    if df.empty:
        return pd.DataFrame(columns=COLUMNS)
    out = []
    for (task, method, var, uses, budget), g in df.groupby(["task", "method", "variant", "uses",
                                                            "budget"]):
        scored = g[g.status.isin(["ok", "diverged"])]
        out.append({"task": task, "method": method, "variant": var, "uses": uses,
                    "budget": budget,
                    "seeds": len(scored),
                    "normalized_mean": scored.normalized.astype(float).mean(),
                    "normalized_std": scored.normalized.astype(float).std(ddof=1),
                    "transfer_mean": scored.transfer.astype(float).mean(),
                    "transfer_std": scored.transfer.astype(float).std(ddof=1),
                    "return_mean": scored["return"].astype(float).mean(),
                    "diverged": int((g.status == "diverged").sum()),
                    "failed": int((g.status == "failed").sum())})
    return pd.DataFrame(out, columns=COLUMNS).sort_values(["task", "normalized_mean"],
                                                          ascending=[True, False])


def to_markdown(board: pd.DataFrame) -> str:
    if board.empty:
        return "_no finished runs in the store_\n"
    show = board.copy()
    show["normalized"] = [f"{m:.3f} ± {s:.3f}" if pd.notna(s) else f"{m:.3f}"
                          for m, s in zip(show.normalized_mean, show.normalized_std)]
    show["transfer"] = [f"{m:.3f} ± {s:.3f}" if pd.notna(s) else
                        ("-" if pd.isna(m) else f"{m:.3f}")
                        for m, s in zip(show.transfer_mean, show.transfer_std)]
    show["return"] = show.return_mean.map(lambda v: f"{v:.2f}")
    cols = ["task", "method", "variant", "normalized", "transfer", "return", "seeds", "budget",
            "uses", "diverged", "failed"]
    return show[cols].to_markdown(index=False) + "\n"


def write(board: pd.DataFrame, out_dir: str) -> tuple[str, str]:
    os.makedirs(out_dir, exist_ok=True)
    md, csv = os.path.join(out_dir, "leaderboard.md"), os.path.join(out_dir, "leaderboard.csv")
    with open(md, "w") as f:
        f.write(to_markdown(board))
    board.to_csv(csv, index=False)
    return md, csv
