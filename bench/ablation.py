"""The paper's ILD ablations (Table 3: loss, truncation length, deviation factor; Table 7:
16 demos vs 1), run as ordinary budgeted cells and tabulated beside the paper's returns.

Our base setting is ILD's default (Chamfer-alpha, truncation 10, deviation factor 1, one
demo); every ablation changes one field. The paper's loss and truncation rows were run at
deviation factor 0.2 (its ablation base), ours at 1. "Direction" compares each setting with
the base in our runs and in the paper (up / down / same within 1%), since absolute numbers
at a CPU budget are not the paper's.
"""
from __future__ import annotations

import os

import pandas as pd

from bench.budget import Budget
from bench.paper import TABLE3
from bench.runner import RunRequest
from bench.store import Store

# (name, config overrides, num_demos, the paper's Table 3 column, the paper's base column)
SETTINGS = (
    ("base", {}, 1, "dev1", "dev1"),
    ("l2", {"loss": "l2"}, 1, "l2", "chamfer"),
    ("trunc1", {"truncation": 1}, 1, "trunc1", "trunc10"),
    ("trunc30", {"truncation": 30}, 1, "trunc30", "trunc10"),
    ("trunc100", {"truncation": 100}, 1, "trunc100", "trunc10"),
    ("dev0", {"alpha": 0.0}, 1, "dev0", "dev1"),
    ("dev0.2", {"alpha": 0.2}, 1, "dev0.2", "dev1"),
    ("dev5", {"alpha": 5.0}, 1, "dev5", "dev1"),
    ("16demos", {}, 16, None, None),
)


def requests(task: str, seconds: float, seeds=(0,), preset: str | None = "cpu",
             names: list[str] | None = None) -> list[RunRequest]:
    out = []
    for s in seeds:
        for name, over, k, _, _ in SETTINGS:
            if names and name not in names:
                continue
            out.append(RunRequest(method="ild", task=task, seed=s,
                                  budget=Budget(seconds=seconds, evals=5), preset=preset,
                                  overrides=over, num_demos=k))
    return out


def _setting_of(record: dict) -> str | None:
    c = record.get("config") or {}
    for name, over, k, _, _ in SETTINGS:
        base = {"loss": "chamfer", "truncation": 10, "alpha": 1.0}
        want = {**base, **over}
        if all(c.get(f) == v for f, v in want.items()) and record.get("num_demos", 1) == k:
            return name
    return None


def _direction(x: float, base: float) -> str:
    if abs(x - base) <= 0.01 * max(abs(base), 1e-9):
        return "same"
    return "up" if x > base else "down"


def ild_version(version: str | None = None) -> str:
    """`version`, or the registered ILD's."""
    if version is None:
        from bench.plugins import get_method
        version = get_method("ild").version
    return str(version)


def ild_runs(store: Store, task: str, version: str | None = None):
    """Finished ('ok'/'diverged') ILD records on `task` of ILD `version` only (default: the
    registered one), so seeds of an older ILD left in a store never pool with today's."""
    version = ild_version(version)
    for r in store.records():
        if (r["task"] == task and r["method"] == "ild"
                and r.get("status") in ("ok", "diverged")
                and str(r.get("method_version")) == version):
            yield r


def latest_per(records, key) -> dict:
    """{key(r): r}, each key's record the one finished last ('finished', else 'started'; ties
    to the later in `records`). A cell re-run after a speed default changed its config, and
    so its run id (e.g. a physics rewrite turned on by a task override), leaves two finished records of the same
    cell and seed in a store; the newer stands for it."""
    latest = {}
    for r in sorted(records, key=lambda r: str(r.get("finished") or r.get("started") or "")):
        latest[key(r)] = r
    return latest


def table(store: Store, task: str, seconds: float | None = None,
          version: str | None = None) -> pd.DataFrame:
    """Runs of ILD's `version` only (default: the registered one): `ild_runs`. A setting's
    seed counts once: where the store holds it twice (the cell re-run after a speed default
    changed its config and so its run id), the latest
    finished record stands for it."""
    version = ild_version(version)
    runs = (r for r in ild_runs(store, task, version)
            if seconds is None or (r.get("budget") or {}).get("seconds") == seconds)
    rows = [{"setting": name, "seed": seed, "normalized": r["final_normalized"] or 0.0,
             "return": r.get("final_return"), "transfer": r.get("transfer_normalized")}
            for (name, seed), r in latest_per(runs, lambda r: (_setting_of(r), r["seed"])).items()
            if name is not None]
    df = pd.DataFrame(rows, columns=["setting", "seed", "normalized", "return", "transfer"])
    if df.empty:
        raise ValueError(f"no ILD (version {version}) ablation runs on {task!r} in "
                         f"{store.root}; run "
                         f"`ildbench ablate --task {task} --budget 3m` first")
    g = df.groupby("setting").agg(seeds=("seed", "count"), normalized=("normalized", "mean"),
                                  normalized_std=("normalized", "std"),
                                  ret=("return", "mean")).reset_index()
    base = g.set_index("setting").normalized.get("base")
    paper = TABLE3.get(task, {})
    out = []
    for name, _, _, col, base_col in SETTINGS:
        if name not in set(g.setting):
            continue
        row = g[g.setting == name].iloc[0].to_dict()
        row["ours_vs_base"] = "-" if base is None or name == "base" else _direction(
            row["normalized"], base)
        p = paper.get(col) if col else None
        row["paper_return"] = p
        row["paper_vs_base"] = ("-" if p is None or name == "base" or base_col not in paper
                                else _direction(p, paper[base_col]))
        row["agrees"] = ("-" if "-" in (row["ours_vs_base"], row["paper_vs_base"])
                         else ("yes" if row["ours_vs_base"] == row["paper_vs_base"] else "no"))
        out.append(row)
    return pd.DataFrame(out)


def write(df: pd.DataFrame, task: str, out_dir: str) -> list[str]:
    from bench.report import write_table
    return write_table(df, os.path.join(out_dir, f"ablation_{task}"), floatfmt=".3f")
