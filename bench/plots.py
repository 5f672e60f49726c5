"""Plots from the results store (matplotlib, headless)."""
from __future__ import annotations

import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import pandas as pd  # noqa: E402

from bench.perturb import FAMILIES  # noqa: E402
from bench.store import Store  # noqa: E402


def save_figure(fig, out_dir: str, name: str) -> str:
    """Lay out, write <out_dir>/<name> (PNG, 100 dpi) and close the figure."""
    fig.tight_layout()
    os.makedirs(out_dir, exist_ok=True)
    path = os.path.join(out_dir, name)
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def robustness_frame(store: Store, task: str) -> pd.DataFrame:
    """One row per (method, seed, family, magnitude) from runs' transfer entries."""
    rows = []
    for r in store.records():
        if r["task"] != task or r["status"] not in ("ok", "diverged"):
            continue
        rows.append({"method": r["method"], "seed": r["seed"], "family": "nominal",
                     "magnitude": 0.0, "normalized": r["final_normalized"]})
        for v in (r.get("transfer") or {}).values():
            rows.append({"method": r["method"], "seed": r["seed"], "family": v["family"],
                         "magnitude": v["magnitude"], "normalized": v["normalized"]})
    return pd.DataFrame(rows, columns=["method", "seed", "family", "magnitude", "normalized"])


def robustness_plot(store: Store, task: str, out_dir: str) -> str:
    """Normalized score vs perturbation magnitude, one panel per family, one line per
    method (mean over seeds, min-max band). Magnitude 0 is the nominal score."""
    df = robustness_frame(store, task)
    if df.empty:
        raise ValueError(f"no finished runs for task {task!r} in {store.root}; run with "
                         "--robustness (or --transfer) first")
    nominal = df[df.family == "nominal"]
    fams = [f for f in FAMILIES if (df.family == f).any()]
    fig, axes = plt.subplots(1, max(len(fams), 1), figsize=(3.2 * max(len(fams), 1), 3),
                             sharey=True, squeeze=False)
    for ax, fam in zip(axes[0], fams):
        part = pd.concat([df[df.family == fam], nominal.assign(family=fam)])
        for method, g in part.groupby("method"):
            s = g.groupby("magnitude").normalized.agg(["mean", "min", "max"]).sort_index()
            ax.plot(s.index, s["mean"], marker="o", label=method)
            ax.fill_between(s.index, s["min"], s["max"], alpha=0.2)
        ax.set_title(fam)
        ax.set_xlabel("magnitude")
        ax.axhline(1.0, color="grey", lw=0.5, ls="--")
    axes[0][0].set_ylabel("normalized score")
    axes[0][-1].legend(fontsize=8)
    fig.suptitle(f"{task}: robustness (1.0 = expert under the same perturbation)")
    return save_figure(fig, out_dir, f"robustness_{task}.png")
