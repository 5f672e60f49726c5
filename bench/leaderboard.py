"""Leaderboard: the FINAL normalized score per task x method over seeds (mean, std and a 95%
percentile-bootstrap CI of the mean), transfer score, anytime metrics (area under the
normalized-score-vs-time curve, time to 50%/90% of expert) and the paper's return beside ours.

Runs pool over seeds only when method version, preset, config and evaluation settings are
equal (the 'variant' column, a short hash of them); the budget is shown so unequal budgets
are visible. A 'diverged' run counts with its last valid evaluation (or 0.0, random level, if
it never had one); 'failed' runs are listed in the `failed` column and not averaged.
Reference methods (which use the true reward or the simulator at test time) are marked.
"""
from __future__ import annotations

import hashlib
import json
import os

import pandas as pd

from bench import curves
from bench.api import Uses
from bench.budget import Budget
from bench.paper import paper_return
from bench.stats import bootstrap_ci
from bench.store import Store

COLUMNS = ["task", "method", "variant", "uses", "reference", "budget", "seeds",
           "normalized_mean", "normalized_std", "ci_lo", "ci_hi", "transfer_mean",
           "transfer_std", "auc_mean", "t50_mean", "t50_reached", "t90_mean", "t90_reached",
           "return_mean", "paper_return", "paper_expert", "diverged", "failed"]


def _transfer(record: dict) -> float | None:
    """Recomputed from the record's per-family entries with the current applicability rules
    (bench.perturb.inapplicable), at the default magnitudes."""
    from bench.transfer import default_summary
    from tasks import make_task
    transfer = record.get("transfer") or {}
    return default_summary(transfer, make_task(record["task"])) if transfer else None


def variant(record: dict) -> str:
    """Short id of (method version, preset, config identity, evaluation): runs pool over
    seeds only when equal. The config enters as bench.runner.config_identity (non-default
    fields), so a record made before a knob existed pools with one at the knob's default."""
    from bench.runner import record_config_identity
    key = json.dumps([record.get("method_version"), record.get("preset"),
                      record_config_identity(record), record.get("eval")], sort_keys=True,
                     default=str)
    return hashlib.sha256(key.encode()).hexdigest()[:6]


def records_frame(store: Store) -> pd.DataFrame:
    rows = []
    for r in store.records():
        norm = r.get("final_normalized")
        if r["status"] == "diverged" and norm is None:
            norm = 0.0
        horizon = (r.get("budget") or {}).get("seconds")
        curve = r.get("curve") or []
        rows.append({"task": r["task"], "method": r["method"], "variant": variant(r),
                     "seed": r["seed"], "status": r["status"], "normalized": norm,
                     "return": r.get("final_return"), "transfer": _transfer(r),
                     "uses": Uses(**r["uses"]).describe(),
                     "reference": bool(r.get("reference_method")),
                     "budget": Budget(**r["budget"]).describe(), "train_s": r.get("train_s"),
                     "auc": curves.auc(curve, horizon) if horizon else None,
                     "t50": curves.time_to(curve, 0.5), "t90": curves.time_to(curve, 0.9),
                     "curve": curve, "horizon": horizon, "started": r.get("started")})
    return pd.DataFrame(rows, columns=["task", "method", "variant", "seed", "status",
                                       "normalized", "return", "transfer", "uses",
                                       "reference", "budget", "train_s", "auc", "t50", "t90",
                                       "curve", "horizon", "started"])


def _mean(col: pd.Series) -> float:
    v = col.dropna().astype(float)
    return float(v.mean()) if len(v) else float("nan")


def leaderboard(store: Store) -> pd.DataFrame:
    return board(records_frame(store))


def board(df: pd.DataFrame) -> pd.DataFrame:
    """The leaderboard of a records_frame."""
    if df.empty:
        return pd.DataFrame(columns=COLUMNS)
    out = []
    for (task, method, var, uses, budget), g in df.groupby(["task", "method", "variant", "uses",
                                                            "budget"]):
        scored = g[g.status.isin(["ok", "diverged"])]
        norms = scored.normalized.astype(float).to_numpy()
        lo, hi = bootstrap_ci(norms) if len(norms) else (float("nan"), float("nan"))
        out.append({"task": task, "method": method, "variant": var, "uses": uses,
                    "reference": bool(g.reference.any()), "budget": budget,
                    "seeds": len(scored),
                    "normalized_mean": norms.mean() if len(norms) else float("nan"),
                    "normalized_std": scored.normalized.astype(float).std(ddof=1),
                    "ci_lo": lo, "ci_hi": hi,
                    "auc_mean": _mean(scored.auc),
                    "t50_mean": _mean(scored.t50), "t50_reached": int(scored.t50.notna().sum()),
                    "t90_mean": _mean(scored.t90), "t90_reached": int(scored.t90.notna().sum()),
                    "paper_return": paper_return(task, method),
                    "paper_expert": paper_return(task, "expert"),
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
    show["95% CI"] = [f"[{lo:.3f}, {hi:.3f}]" if pd.notna(lo) else "-"
                      for lo, hi in zip(show.ci_lo, show.ci_hi)]
    show["return"] = show.return_mean.map(lambda v: f"{v:.2f}")
    show["paper"] = [f"{p:.2f} (expert {e:.2f})" if pd.notna(p) else "-"
                     for p, e in zip(show.paper_return, show.paper_expert)]
    show["AUC"] = show.auc_mean.map(lambda v: "-" if pd.isna(v) else f"{v:.3f}")

    def _tt(m, n, seeds):
        return "-" if n == 0 else f"{m:.0f}s ({n}/{seeds})"
    show["t50%"] = [_tt(m, n, k) for m, n, k in zip(show.t50_mean, show.t50_reached, show.seeds)]
    show["t90%"] = [_tt(m, n, k) for m, n, k in zip(show.t90_mean, show.t90_reached, show.seeds)]
    show["method"] = [m + (" (ref)" if r else "") for m, r in zip(show.method, show.reference)]
    cols = ["task", "method", "variant", "normalized", "95% CI", "transfer", "AUC", "t50%",
            "t90%", "return", "paper", "seeds", "budget", "uses", "diverged", "failed"]
    return show[cols].to_markdown(index=False) + "\n"


def write(board: pd.DataFrame, out_dir: str) -> tuple[str, str]:
    os.makedirs(out_dir, exist_ok=True)
    md, csv = os.path.join(out_dir, "leaderboard.md"), os.path.join(out_dir, "leaderboard.csv")
    renders = sorted(n for n in os.listdir(out_dir)
                     if n.startswith("render_") and n.endswith(".html"))
    with open(md, "w") as f:
        f.write(to_markdown(board))
        if renders:  # made by `ildbench render`; linked here
            f.write("\nRenders (expert demo next to a final policy): " +
                    ", ".join(f"[{n[7:-5]}]({n})" for n in renders) + "\n")
    board.to_csv(csv, index=False)
    return md, csv
