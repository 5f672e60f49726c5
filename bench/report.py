"""The leaderboard report: table, aggregates across tasks, anytime curves (files under out/).

    leaderboard.md / .csv   per task x method (bench.leaderboard)
    aggregates.md / .csv    IQM and mean over tasks with stratified-bootstrap 95% CIs, and
                            the probability that ILD improves on each other method, for the
                            final nominal score and for the transfer score
    curves_<task>.png       normalized score vs training seconds (mean, 95% CI band)
    curves_aggregate.png    mean over tasks vs fraction of the budget
    steps_<task>.png        normalized score vs env steps
    sample_matched.md/.csv  every learning method at equal env-step budgets
                            (bench.sample_matched; from step-budgeted runs)
    paper_comparison.md/.csv
                            our scores beside the paper's Table 2, one table per budget
                            (bench.paper.comparison)
    adaptation.md/.csv      with a zero-shot store: runs trained in changed dynamics beside
                            nominal-trained runs scored in the same dynamics
                            (bench.adaptation)

Aggregates use one variant per (method, task): the one with the most scored seeds, and
among equals the one with the newest run (a store may hold older or differently-configured
runs). They never average unequal strata: where cells hold different seed counts, they are
taken over the tasks on which every method has the most seeds any cell holds, and the report
names the tasks left out and the cell that is short; with no such task it says so instead.
"""
from __future__ import annotations

import os

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from bench import curves, leaderboard as lb, stats  # noqa: E402
from bench.plots import save_figure  # noqa: E402
from bench.store import Store  # noqa: E402

GRID_POINTS = 60


def write_table(df: pd.DataFrame, base: str, floatfmt: str = ".4g") -> list[str]:
    """<base>.csv and <base>.md (markdown) of one table; returns both paths."""
    os.makedirs(os.path.dirname(os.path.abspath(base)), exist_ok=True)
    df.to_csv(base + ".csv", index=False)
    with open(base + ".md", "w") as f:
        f.write(df.to_markdown(index=False, floatfmt=floatfmt) + "\n")
    return [base + ".csv", base + ".md"]


def append_csv(rows: list[dict], path: str) -> None:
    """Add rows to a CSV, keeping its earlier rows (columns added since stay empty in them)."""
    df = pd.DataFrame(rows)
    if os.path.exists(path):
        df = pd.concat([pd.read_csv(path), df], ignore_index=True)
    df.to_csv(path, index=False)


def _weak_reference(task: str) -> str | None:
    """TaskSpec.weak_reference of a registered task (None for unknown names)."""
    from tasks import TASKS
    return TASKS[task].weak_reference if task in TASKS else None


def aggregates(frame: pd.DataFrame, of: str = "ild", reps: int = 2000
               ) -> tuple[pd.DataFrame, pd.DataFrame, list[str]]:
    """(aggregate table, improvement table, notes) for 'normalized' and 'transfer'."""
    chosen = lb.main_variants(frame)
    imitation = chosen[~chosen.reference.astype(bool)]
    tables, improvements, notes = [], [], []
    weak = {t: _weak_reference(t) for t in sorted(imitation.task.unique())
            if _weak_reference(t)}
    for t, why in weak.items():
        notes.append(f"{t}: left out of the aggregates (its table rows stay): {why}")
    imitation = imitation[~imitation.task.isin(list(weak))]
    for value in ("normalized", "transfer"):
        part = imitation.dropna(subset=[value])
        if part.empty:
            continue
        scores = part.assign(**{value: part[value].astype(float)})
        try:
            mats = stats.score_matrices(scores, value)
        except stats.UnequalSeeds as e:
            # A partly run store: aggregate over the tasks whose cells are all complete, and
            # name the ones left out.
            tasks, full = stats.complete_tasks(scores)
            if not tasks:
                notes.append(f"{value}: not aggregated: {e}")
                continue
            mats = stats.score_matrices(scores, value, tasks=tasks)
            notes.append(f"{value}: over the tasks where every method has {full} seeds "
                         f"({', '.join(tasks)}); left out until their cells are complete: "
                         f"{', '.join(sorted(set(scores.task) - set(tasks)))} ({e})")
        except stats.ShapeError as e:
            notes.append(f"{value}: not aggregated: {e}")
            continue
        tasks = list(next(iter(mats.values())).columns)
        agg = stats.aggregate_table(mats, reps=reps)
        agg.insert(0, "score", value)
        agg["task_set"] = ", ".join(tasks)
        tables.append(agg)
        if of in mats and len(mats) > 1:
            imp = stats.improvement_table(mats, of, reps=reps)
            imp.insert(0, "score", value)
            improvements.append(imp)
    agg = pd.concat(tables, ignore_index=True) if tables else pd.DataFrame()
    imp = pd.concat(improvements, ignore_index=True) if improvements else pd.DataFrame()
    return agg, imp, notes


def aggregates_markdown(agg: pd.DataFrame, imp: pd.DataFrame, notes: list[str]) -> str:
    out = ["# Aggregates over tasks (imitation methods; references excluded)", ""]
    if not agg.empty:
        show = agg.copy()
        for k in ("iqm", "mean"):
            show[k] = [f"{v:.3f} [{lo:.3f}, {hi:.3f}]" for v, lo, hi in
                       zip(show[k], show[f"{k}_lo"], show[f"{k}_hi"])]
        out += ["IQM and mean of the final normalized score with stratified-bootstrap 95% "
                "CIs (runs resampled within each task). `transfer` is the mean normalized "
                "score over the perturbation families at their default magnitudes.", "",
                show[["score", "method", "iqm", "mean", "runs", "tasks", "task_set"]]
                .to_markdown(index=False), ""]
    if not imp.empty:
        show = imp.copy()
        show["P(X > Y)"] = [f"{p:.3f} [{lo:.3f}, {hi:.3f}]"
                            for p, lo, hi in zip(show.p, show.lo, show.hi)]
        out += ["Probability of improvement (per task P over run pairs, ties 1/2; mean over "
                "tasks; stratified-bootstrap 95% CI):", "",
                show[["score", "comparison", "P(X > Y)"]].to_markdown(index=False), ""]
    out += [f"- {n}" for n in notes]
    if agg.empty and not notes:
        out.append("_no scored runs_")
    return "\n".join(out) + "\n"


def _curve_band(runs: list[list[dict]], grid: np.ndarray, x: str = "train_s"
                ) -> tuple[np.ndarray, ...]:
    vals = np.stack([curves.value_at(c, grid, x) for c in runs])  # (runs, grid)
    mean = vals.mean(0)
    if len(runs) == 1:
        return mean, mean, mean
    ci = np.array([stats.bootstrap_ci(vals[:, j], reps=500) for j in range(grid.size)])
    return mean, ci[:, 0], ci[:, 1]


def curve_plots(frame: pd.DataFrame, out_dir: str) -> list[str]:
    """Anytime curves of the main variant per (task, method), runs with a wall-clock budget;
    the aggregate curve leaves out tasks with a weak expert reference (TaskSpec)."""
    chosen = lb.main_variants(frame)
    chosen = chosen[chosen.horizon.notna()]
    paths = []
    frac = np.linspace(0, 1, GRID_POINTS)
    agg: dict[str, list[np.ndarray]] = {}
    for task, per_task in chosen.groupby("task"):
        fig, ax = plt.subplots(figsize=(5, 3.4))
        for method, g in per_task.groupby("method"):
            grid = frac * g.horizon.max()
            mean, lo, hi = _curve_band(list(g.curve), grid)
            ref = " (ref)" if g.reference.any() else ""
            ax.plot(grid, mean, label=f"{method}{ref} (n={len(g)})",
                    ls="--" if ref else "-")
            ax.fill_between(grid, lo, hi, alpha=0.2)
            if not ref and not _weak_reference(task):
                agg.setdefault(method, []).append(mean)
        paths.append(_finish(fig, ax, "training wall-clock (s)",
                             f"{task}: anytime score (1 = expert, 0 = random)", out_dir,
                             f"curves_{task}.png"))
    if agg:
        fig, ax = plt.subplots(figsize=(5, 3.4))
        for method, per_task in sorted(agg.items()):
            ax.plot(frac, np.mean(per_task, 0), label=f"{method} ({len(per_task)} tasks)")
        ax.axhline(1.0, color="grey", lw=0.5, ls=":")
        ax.set_xlabel("fraction of the training budget")
        ax.set_ylabel("mean normalized score over tasks")
        ax.set_title("aggregate anytime score (imitation methods)")
        ax.legend(fontsize=7)
        paths.append(save_figure(fig, out_dir, "curves_aggregate.png"))
    return paths + step_curve_plots(frame, out_dir)


def _max_steps(curve) -> float:
    return max((float(p.get("env_steps") or 0) for p in curve or []), default=0.0)


def step_curve_plots(frame: pd.DataFrame, out_dir: str) -> list[str]:
    """Anytime curves against env steps (log axis) of the main variant per (task, method),
    for methods that step the env (BC, which never does, is left out)."""
    chosen = lb.main_variants(frame)
    paths = []
    for task, per_task in chosen.groupby("task"):
        fig, ax = plt.subplots(figsize=(5, 3.4))
        drawn = 0
        for method, g in per_task.groupby("method"):
            top = max(_max_steps(c) for c in g.curve)
            if top <= 0:
                continue
            grid = np.geomspace(min(1e3, top), top, GRID_POINTS)
            mean, lo, hi = _curve_band(list(g.curve), grid, "env_steps")
            ref = " (ref)" if g.reference.any() else ""
            ax.plot(grid, mean, label=f"{method}{ref} (n={len(g)})", ls="--" if ref else "-")
            ax.fill_between(grid, lo, hi, alpha=0.2)
            drawn += 1
        if not drawn:
            plt.close(fig)
            continue
        ax.set_xscale("log")
        ax.axhline(0.0, color="grey", lw=0.5, ls=":")
        paths.append(_finish(fig, ax, "env steps",
                             f"{task}: score vs env steps",
                             out_dir, f"steps_{task}.png"))
    return paths


def _finish(fig, ax, xlabel: str, title: str, out_dir: str, name: str) -> str:
    """A per-task curve figure's expert line, labels and legend; saved as `name`."""
    ax.axhline(1.0, color="grey", lw=0.5, ls=":")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("normalized score")
    ax.set_title(title)
    ax.legend(fontsize=7)
    return save_figure(fig, out_dir, name)


def _most_seeds(df: pd.DataFrame, keys: list[str]) -> pd.DataFrame:
    """One row per `keys`: the variant with the most seeds (ties: the first variant id)."""
    return (df.sort_values(["seeds", "variant"], ascending=[False, True], kind="stable")
            .drop_duplicates(keys))


def _scores(part: pd.DataFrame) -> dict[str, dict[str, float]]:
    """{task: {method: mean normalized score}} of table rows."""
    scores: dict[str, dict[str, float]] = {}
    for t, m, v in zip(part.task, part.method, part.normalized_mean):
        scores.setdefault(t, {})[m] = float(v)
    return scores


def paper_tables(board: pd.DataFrame, matched: pd.DataFrame) -> dict[str, list[dict]]:
    """{budget label: bench.paper.comparison rows}: one per wall-clock budget of the board
    and one per sample-matched env-step budget (a step-only budget of the board is read
    there, at its own and the other step budgets). Each (budget, task, method) is read from
    its variant with the most seeds."""
    from bench.budget import format_steps
    from bench.paper import comparison
    scored = board[~board.floor.fillna(False).astype(bool) & ~board.reference.astype(bool)
                   & (board.seeds > 0)]
    tables = {}
    for budget, part in _most_seeds(scored, ["budget", "task", "method"]).groupby("budget"):
        if not (budget.endswith("env steps") and "/" not in budget):
            tables[f"{budget} of training (wall-clock)"] = comparison(_scores(part))
    if not matched.empty:
        best = _most_seeds(matched, ["env_steps_budget", "task", "method"])
        for budget, part in best.groupby("env_steps_budget"):
            tables[f"{format_steps(budget)} env steps (sample-matched)"] = comparison(
                _scores(part))
    return tables


def write_report(store: Store, out_dir: str, reps: int = 2000,
                 zero_shot: Store | None = None) -> list[str]:
    """Every report file from one read of the store; leaderboard.md comes first. With
    `zero_shot` (a store of nominal-trained runs with transfer evaluations), the adaptation
    table of the store's changed-dynamics runs as well."""
    from bench import sample_matched
    from bench.paper import comparison_markdown
    frame, left_out = lb.reporting_runs(lb.records_frame(store))
    floors = lb.task_floors(frame.task)
    board = lb.board(frame, floors, tuning_runs_left_out=left_out)
    paths = list(lb.write(board, out_dir))
    if not frame.empty:
        matched = sample_matched.table(frame)
        if not matched.empty:
            p = os.path.join(out_dir, "sample_matched.md")
            with open(p, "w") as f:
                f.write(sample_matched.to_markdown(matched, floors))
            matched.to_csv(os.path.join(out_dir, "sample_matched.csv"), index=False)
            paths += [p, os.path.join(out_dir, "sample_matched.csv")]
        tables = paper_tables(board, matched)
        if any(tables.values()):
            p = os.path.join(out_dir, "paper_comparison.md")
            with open(p, "w") as f:
                f.write(comparison_markdown(tables))
            pd.DataFrame([{"budget": k, **r} for k, rows in tables.items() for r in rows]
                         ).to_csv(os.path.join(out_dir, "paper_comparison.csv"), index=False)
            paths += [p, os.path.join(out_dir, "paper_comparison.csv")]
        agg, imp, notes = aggregates(frame, reps=reps)
        p = os.path.join(out_dir, "aggregates.md")
        with open(p, "w") as f:
            f.write(aggregates_markdown(agg, imp, notes))
        paths.append(p)
        if not agg.empty:
            p = os.path.join(out_dir, "aggregates.csv")
            pd.concat([agg, imp], ignore_index=True).to_csv(p, index=False)
            paths.append(p)
        paths += curve_plots(frame, out_dir)
        if zero_shot is not None:
            from bench import adaptation
            adapted = adaptation.table(frame, lb.records_frame(zero_shot))
            if not adapted.empty:
                p = os.path.join(out_dir, "adaptation.md")
                with open(p, "w") as f:
                    f.write(adaptation.to_markdown(adapted))
                adapted.to_csv(os.path.join(out_dir, "adaptation.csv"), index=False)
                paths += [p, os.path.join(out_dir, "adaptation.csv")]
    return paths
