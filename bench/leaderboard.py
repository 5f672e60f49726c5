"""Leaderboard: the FINAL normalized score per task x method over seeds (mean, std and a 95%
percentile-bootstrap CI of the mean), transfer score, anytime metrics (area under the
normalized-score-vs-time curve, time to 50%/90% of expert) and the paper's return beside ours.

Runs pool over seeds only when method version, preset, config and evaluation settings are
equal (the 'variant' column, a short hash of them); the budget is shown so unequal budgets
are visible. A 'diverged' run counts with its last valid evaluation (or 0.0, random level, if
it never had one); 'failed' runs are listed in the `failed` column and not averaged.
Reference methods (which use the true reward or the simulator at test time) are marked.

Every cell says what it did with its budget: the median env steps and learner updates of its
runs. Each task carries its floors (bench/floors.py: all-zero actions, and the demo's
actions replayed open loop) as rows of their own; a cell that does not beat `zero_action`
is marked, as is a cell whose median env steps are below its method's `min_env_steps`
(starved: its paper trains for far longer), as is a cell made by an older version of its
method than the registered one (stale: a sweep of the store would re-run it; once the
registered version's re-run has as many seeds, the stale row is left out and named under
the table), and a task whose `zero_action` floor scores above 0.8 is named weakly
discriminative under the table.
"""
from __future__ import annotations

import hashlib
import json
import os

import pandas as pd

from bench import curves
from bench.api import Uses
from bench.budget import Budget, format_steps
from bench.paper import paper_return
from bench.stats import bootstrap_ci
from bench.store import Store

COLUMNS = ["task", "method", "variant", "uses", "reference", "budget", "seeds",
           "normalized_mean", "normalized_std", "ci_lo", "ci_hi", "transfer_mean",
           "transfer_std", "auc_mean", "t50_mean", "t50_reached", "t90_mean", "t90_reached",
           "return_mean", "paper_return", "paper_expert", "diverged", "failed",
           "env_steps_median", "updates_median", "min_env_steps", "starved", "floor",
           "below_zero_action", "version", "stale", "dynamics", "nominal_mean",
           "length_mean", "random_length"]
DYNAMICS_COLUMNS = ["dynamics", "nominal_mean"]
"""Shown (markdown) and written (CSV) only for a store that holds runs trained in changed
dynamics (`--train-dynamics`)."""
NOMINAL = "nominal"
STARVED, NOT_ABOVE_ZERO, STALE = "†", "‡", "§"


def _transfer(record: dict) -> float | None:
    """Recomputed from the record's per-family entries with the current applicability rules
    (bench.perturb.inapplicable), at the default magnitudes."""
    from bench.transfer import default_summary
    from tasks import make_task
    transfer = record.get("transfer") or {}
    return default_summary(transfer, make_task(record["task"])) if transfer else None


def variant(record: dict) -> str:
    """Short id of (method version, preset, config identity, evaluation, training dynamics):
    runs pool over seeds only when equal. The config enters as
    bench.runner.config_identity (non-default fields), so a record made before a knob existed
    pools with one at the knob's default; the nominal training dynamics add nothing."""
    from bench.runner import record_config_identity
    parts = [record.get("method_version"), record.get("preset"),
             record_config_identity(record), record.get("eval")]
    if record.get("train_dynamics"):
        parts.append(record["train_dynamics"]["key"])
    key = json.dumps(parts, sort_keys=True, default=str)
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
                     "curve": curve, "horizon": horizon, "started": r.get("started"),
                     "env_steps": r.get("env_steps"),
                     "budget_steps": (r.get("budget") or {}).get("env_steps"),
                     "version": str(r.get("method_version")),
                     "updates": (r.get("train_metrics") or {}).get("train/updates"),
                     "dynamics": (r.get("train_dynamics") or {}).get("key", NOMINAL),
                     "nominal": (r.get("nominal") or {}).get("normalized"),
                     "transfer_by_key": {k: v["normalized"] for k, v in
                                         (r.get("transfer") or {}).items()
                                         if v.get("normalized") is not None},
                     "length": (curve[-1].get("length") if curve and r["status"] == "ok"
                                else None)})
    return pd.DataFrame(rows, columns=["task", "method", "variant", "seed", "status",
                                       "normalized", "return", "transfer", "uses",
                                       "reference", "budget", "train_s", "auc", "t50", "t90",
                                       "curve", "horizon", "started", "env_steps", "budget_steps",
                                       "version", "updates", "dynamics", "nominal",
                                       "transfer_by_key", "length"])


def _median(col: pd.Series) -> float:
    v = col.dropna().astype(float)
    return float(v.median()) if len(v) else float("nan")


def _spec(method: str):
    """The registered MethodSpec of `method`, None for a method not registered here."""
    from bench.plugins import all_methods
    return all_methods().get(method)


def _min_env_steps(method: str) -> int | None:
    spec = _spec(method)
    return None if spec is None else spec.min_env_steps


def _registered_version(method: str) -> str | None:
    spec = _spec(method)
    return None if spec is None else str(spec.version)


def task_floors(tasks, compute: bool = True) -> dict[str, dict]:
    """{task: floors entry} (bench/floors.py) for the tasks that have a demo."""
    from bench.floors import floors
    from tasks import make_task
    from tasks.demo import load_demo
    out = {}
    for name in sorted(set(tasks)):
        task = make_task(name)
        if task.spec.demo_path is None or task.spec.success_score:
            continue
        entry = floors(task, load_demo(task.spec.demo_path, task), compute=compute)
        if entry:
            out[name] = entry
    return out


def _mean(col: pd.Series) -> float:
    v = col.dropna().astype(float)
    return float(v.mean()) if len(v) else float("nan")


def leaderboard(store: Store) -> pd.DataFrame:
    frame, left_out = reporting_runs(records_frame(store))
    return board(frame, task_floors(frame.task), tuning_runs_left_out=left_out)


def reporting_runs(frame: pd.DataFrame) -> tuple[pd.DataFrame, int]:
    """The runs a report reads, and how many tuning runs it left out: a store that holds
    runs on reporting seeds reports those only (bench/seeds.py); a store of tuning runs only
    is its own report."""
    from bench.seeds import is_tuning
    if frame.empty:
        return frame, 0
    tuning = frame.seed.map(is_tuning).astype(bool)
    if tuning.all() or not tuning.any():
        return frame, 0
    return frame[~tuning].reset_index(drop=True), int(tuning.sum())


def main_variants(frame: pd.DataFrame) -> pd.DataFrame:
    """Rows of the variant with the most scored runs per (task, method); ties go to the
    variant with the newest run (then the variant id, so the choice is deterministic)."""
    scored = frame[frame.status.isin(["ok", "diverged"])]
    if scored.empty:
        return scored
    sizes = (scored.assign(newest=scored.started.fillna("").astype(str))
             .groupby(["task", "method", "variant"])
             .agg(n=("seed", "size"), newest=("newest", "max")).reset_index())
    best = sizes.sort_values(["n", "newest", "variant"], ascending=[False, False, True],
                             kind="stable").drop_duplicates(["task", "method"])
    keep = set(zip(best.task, best.method, best.variant))
    return scored[[k in keep for k in zip(scored.task, scored.method, scored.variant)]]


def board(df: pd.DataFrame, floors: dict[str, dict] | None = None,
          tuning_runs_left_out: int = 0) -> pd.DataFrame:
    """The leaderboard of a records_frame, with each task's floor rows (`floors`: task ->
    bench.floors entry) and the marks that read them; `tuning_runs_left_out` (from
    `reporting_runs`) is carried for the notes in the board's `attrs`."""
    if df.empty:
        return pd.DataFrame(columns=COLUMNS)
    floors = floors or {}
    out = []
    for (task, method, var, uses, budget, dyn), g in df.groupby(
            ["task", "method", "variant", "uses", "budget", "dynamics"]):
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
                    "failed": int((g.status == "failed").sum()),
                    "env_steps_median": _median(scored.env_steps),
                    "updates_median": _median(scored.updates),
                    "min_env_steps": _min_env_steps(method), "floor": False,
                    "version": g.version.iloc[0], "dynamics": dyn,
                    "nominal_mean": scored.nominal.astype(float).mean(),
                    "length_mean": scored.length.astype(float).mean()})
    for row in out:
        need, steps = row["min_env_steps"], row["env_steps_median"]
        row["starved"] = bool(need is not None and pd.notna(steps) and steps < need)
        current = _registered_version(row["method"])
        row["stale"] = bool(current is not None and row["version"] != current)
        # the floors are measured in the nominal dynamics
        zero = (floors.get(row["task"], {}).get("zero_action")
                if row["dynamics"] == NOMINAL else None)
        row["below_zero_action"] = bool(zero is not None and pd.notna(row["normalized_mean"])
                                        and row["normalized_mean"] <= zero["normalized"])
    out, superseded = _drop_superseded(out)
    for task, entry in floors.items():
        if task not in set(df.task):
            continue
        for name, v in entry.items():
            if name == "random":  # the normalization's zero: a row of 0.000 says nothing
                continue
            out.append({"task": task, "method": name, "variant": "-", "uses": "-",
                        "reference": False, "budget": "-", "seeds": 0,
                        "normalized_mean": v["normalized"], "return_mean": v["return"],
                        "floor": True, "starved": False, "below_zero_action": False,
                        "stale": False, "dynamics": NOMINAL, "length_mean": v.get("length"),
                        "t50_reached": 0, "t90_reached": 0, "diverged": 0, "failed": 0,
                        "paper_return": float("nan"), "paper_expert": float("nan")})
    for row in out:
        row["random_length"] = (floors.get(row["task"], {}).get("random", {}).get("length")
                                if row["dynamics"] == NOMINAL else None)  # nominal floors
    table = pd.DataFrame(out, columns=COLUMNS).sort_values(["task", "normalized_mean"],
                                                           ascending=[True, False])
    table.attrs["tuning_runs_left_out"] = int(tuning_runs_left_out)
    table.attrs["superseded"] = superseded
    return table


def _drop_superseded(rows: list[dict]) -> tuple[list[dict], list[str]]:
    """(rows, what was left out): a stale row (an older version of its method) goes when the
    registered version has a row of the same task, method, budget and dynamics with at least
    as many seeds: the cell has been re-run, and the aggregates read the re-run
    (`main_variants`). While the re-run has fewer seeds, both rows stay, the old one
    marked stale. Their records stay in the store."""
    def cell(r):
        return r["task"], r["method"], r["budget"], r["dynamics"]
    current = {}
    for r in rows:
        if not r["stale"]:
            current[cell(r)] = max(current.get(cell(r), 0), r["seeds"])
    keep, gone = [], []
    for r in rows:
        if r["stale"] and current.get(cell(r), -1) >= r["seeds"]:
            gone.append(f"{r['method']} version {r['version']} on {r['task']}")
        else:
            keep.append(r)
    return keep, sorted(gone)


def _count(v) -> str:
    return "-" if pd.isna(v) else format_steps(float(v))


def to_markdown(board: pd.DataFrame) -> str:
    if board.empty:
        return "_no finished runs in the store_\n"
    show = board.copy()
    floor = show.floor.fillna(False).astype(bool)
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
    show["method"] = [m + (" (ref)" if r else "") + (STARVED if st else "")
                      + (NOT_ABOVE_ZERO if bz else "") + (STALE if old else "")
                      for m, r, st, bz, old in zip(show.method, show.reference,
                                                   show.starved.fillna(False),
                                                   show.below_zero_action.fillna(False),
                                                   show.stale.fillna(False))]
    show["env steps"] = show.env_steps_median.map(_count)
    show["updates"] = show.updates_median.map(_count)
    show.loc[floor, "method"] = [f"_{m} (floor)_" for m in show.method[floor]]
    for col in ("95% CI", "transfer", "AUC", "t50%", "t90%", "paper", "env steps", "updates",
                "diverged", "failed"):
        show[col] = show[col].astype(object)
        show.loc[floor, col] = "-"
    show.loc[floor, "normalized"] = [f"{m:.3f}" for m in show.normalized_mean[floor]]
    cols = ["task", "method", "variant", "normalized", "95% CI", "transfer", "AUC", "t50%",
            "t90%", "return", "env steps", "updates", "paper", "seeds", "budget", "uses",
            "diverged", "failed"]
    if _changed_dynamics(board):  # the training dynamics, and the nominal score beside
        show["nominal"] = show.nominal_mean.map(lambda v: "-" if pd.isna(v) else f"{v:.3f}")
        cols[3:3] = ["dynamics"]
        cols[5:5] = ["nominal"]
    return show[cols].to_markdown(index=False) + "\n" + notes(board)


def _changed_dynamics(board: pd.DataFrame) -> bool:
    return bool((board.dynamics.fillna(NOMINAL) != NOMINAL).any())


def _below_random(row) -> str:
    """Why one cell scores below the random policy, read from episode lengths: a policy that
    ends its episodes earlier (a fall) loses the per-step reward that random actions keep
    collecting; one that lasts as long collects less reward per step."""
    cell = f"{row.method} on {row.task}"
    if pd.isna(row.length_mean):
        if row.stale:
            return (f"{cell} at version {row.version} (stale: its records hold no episode "
                    "lengths; the registered version's re-run is not complete)")
        return f"{cell} (its records hold no episode lengths)"
    if pd.isna(row.random_length):
        return f"{cell}: {row.length_mean:.0f} steps"
    why = ("it ends its episodes earlier" if row.length_mean < row.random_length - 0.5
           else "as long: less reward per step")
    return f"{cell}: {row.length_mean:.0f} steps vs {row.random_length:.0f}, {why}"


def notes(board: pd.DataFrame) -> str:
    """The table's footnotes: the marks, and the weakly discriminative tasks."""
    from bench.floors import WEAK_ABOVE
    lines = []
    starved = board[board.starved.fillna(False).astype(bool)]
    if len(starved):
        need = sorted({f"{m} {_count(n)}" for m, n in zip(starved.method,
                                                           starved.min_env_steps)})
        lines.append(f"{STARVED} starved: the cell's median env steps are below what its "
                     f"method's paper trains for ({', '.join(need)}); its score says how far "
                     "the method gets on this budget, not how far it can get.")
    stale = board[board.stale.fillna(False).astype(bool)]
    if len(stale):
        old = sorted({f"{m} version {v} (now {_registered_version(m)})"
                      for m, v in zip(stale.method, stale.version)})
        lines.append(f"{STALE} stale: made by an older version of the method than the "
                     f"registered one ({', '.join(old)}); a sweep of this store would re-run "
                     "the cell.")
    if board.below_zero_action.fillna(False).astype(bool).any():
        lines.append(f"{NOT_ABOVE_ZERO} not above the zero_action floor: all-zero actions "
                     "score as high; the method learned nothing useful on that task.")
    floors = board[board.floor.fillna(False).astype(bool)]
    weak = sorted(floors[(floors.method == "zero_action")
                         & (floors.normalized_mean > WEAK_ABOVE)].task)
    if len(floors):
        lines.append("Floors (bench/floors.py, the shared evaluator on the references' "
                     "episodes): zero_action = all-zero actions; demo_replay = the demo's "
                     "actions replayed open loop from each episode's own initial state.")
    if _changed_dynamics(board):
        lines.append("dynamics: what the cell trained in and is scored under (--train-dynamics; "
                     "'nominal': the task itself); its normalized score is against the expert "
                     "and the random policy in those dynamics, and 'nominal' is the same final "
                     "policies' score in the nominal dynamics. The floors are nominal ones.")
    below = board[~board.floor.fillna(False).astype(bool)
                  & ~board.reference.fillna(False).astype(bool)
                  & (board.normalized_mean.astype(float) < 0)]
    if len(below):
        lines.append("Below the random policy (normalized < 0), with the mean steps its "
                     "episodes last before termination against the random policy's: "
                     + "; ".join(_below_random(r) for r in below.itertuples()) + ".")
    superseded = board.attrs.get("superseded", [])
    if superseded:
        lines.append(f"Left out, superseded by a re-run of the registered version with as many "
                     f"seeds or more (their records stay in the store): "
                     f"{'; '.join(superseded)}.")
    left_out = board.attrs.get("tuning_runs_left_out", 0)
    if left_out:
        from bench.seeds import TUNING_SEED_START
        lines.append(f"{left_out} tuning run(s) (seeds {TUNING_SEED_START} and up) are left "
                     "out: the table reports the reporting seeds only (bench/seeds.py).")
    if weak:
        lines.append(f"Weakly discriminative (zero_action above {WEAK_ABOVE} normalized): "
                     f"{', '.join(weak)}.")
    return "".join(f"\n{line}\n" for line in lines)


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
    drop = [] if _changed_dynamics(board) else DYNAMICS_COLUMNS
    board.drop(columns=drop).to_csv(csv, index=False)
    return md, csv
