"""Aggregate statistics in the style of rliable (Agarwal et al., 2021), on numpy.

Scores of one method are a matrix of shape (runs, tasks): one row per seed, one column per
task, all cells filled. Comparisons refuse matrices that are ragged, hold NaN, or differ in
their task columns; `score_matrices` refuses unequal seed counts across the cells it is given,
naming the cell, because a stratified bootstrap over unequal strata would silently weight
tasks unequally.

- IQM: the mean of the middle 50% of all runs x tasks scores (scipy's trim_mean at 0.25:
  floor(0.25 n) values cut from each end).
- Stratified bootstrap: each replicate resamples runs with replacement *within each task*
  (the task columns are the strata), then recomputes the statistic; the CI is the percentile
  interval of the replicates.
- Probability of improvement P(X > Y): per task, the fraction of (run of X, run of Y) pairs
  where X scores higher, ties counting one half (a Mann-Whitney U statistic over m*n); then
  the mean over tasks.
"""
from __future__ import annotations

from typing import Callable, Mapping

import numpy as np
import pandas as pd


class ShapeError(ValueError):
    pass


class UnequalSeeds(ShapeError):
    """Cells of one comparison hold different numbers of seeds."""


def _matrix(x, name: str = "scores") -> np.ndarray:
    a = np.asarray(x, dtype=float)
    if a.ndim == 1:
        a = a[:, None]
    if a.ndim != 2 or a.shape[0] < 1 or a.shape[1] < 1:
        raise ShapeError(f"{name}: expected a (runs, tasks) matrix, got shape {a.shape}")
    if not np.isfinite(a).all():
        raise ShapeError(f"{name}: holds NaN/inf (a missing or diverged cell?); fill every "
                         "(seed, task) cell before aggregating")
    return a


def iqm(scores) -> float:
    """Interquartile mean of all entries (trim 25% from each end of the sorted scores)."""
    flat = np.sort(_matrix(scores).ravel())
    k = int(np.floor(0.25 * flat.size))
    return float(flat[k:flat.size - k].mean())


def mean(scores) -> float:
    return float(_matrix(scores).mean())


def median(scores) -> float:
    return float(np.median(_matrix(scores).ravel()))


def stratified_bootstrap(scores, stat: Callable[[np.ndarray], float], reps: int = 2000,
                         seed: int = 0) -> np.ndarray:
    """`reps` replicates of stat(resampled matrix); runs resampled within each task."""
    a = _matrix(scores)
    n, t = a.shape
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, n, size=(reps, n, t))                 # run drawn per (rep, slot, task)
    res = np.take_along_axis(np.broadcast_to(a, (reps, n, t)), idx, axis=1)
    if stat is mean:  # vectorized fast path (curves bootstrap every grid point)
        return res.mean(axis=(1, 2))
    return np.array([stat(r) for r in res])


def percentile_ci(replicates: np.ndarray, conf: float = 0.95) -> tuple[float, float]:
    lo, hi = np.percentile(replicates, [50 * (1 - conf), 50 * (1 + conf)])
    return float(lo), float(hi)


def bootstrap_ci(values, reps: int = 2000, conf: float = 0.95, seed: int = 0
                 ) -> tuple[float, float]:
    """Percentile CI of the mean of one cell's seeds (a single stratum). One seed gives a
    zero-width interval: a bootstrap cannot invent spread that was not measured."""
    return percentile_ci(stratified_bootstrap(np.asarray(values, float)[:, None], mean,
                                              reps, seed), conf)


def probability_of_improvement(x, y) -> float:
    """P(X > Y) averaged over tasks; x: (m, tasks), y: (n, tasks)."""
    a, b = _matrix(x, "x"), _matrix(y, "y")
    if a.shape[1] != b.shape[1]:
        raise ShapeError(f"x has {a.shape[1]} tasks, y has {b.shape[1]}: compare on the same "
                         "task columns")
    per_task = []
    for j in range(a.shape[1]):
        gt = (a[:, j][:, None] > b[:, j][None, :]).mean()
        eq = (a[:, j][:, None] == b[:, j][None, :]).mean()
        per_task.append(gt + 0.5 * eq)
    return float(np.mean(per_task))


def poi_ci(x, y, reps: int = 2000, conf: float = 0.95, seed: int = 0
           ) -> tuple[float, float, float]:
    """Probability of improvement with a stratified-bootstrap CI (x and y resampled
    independently within each task). Returns (point, lo, hi)."""
    a, b = _matrix(x, "x"), _matrix(y, "y")
    point = probability_of_improvement(a, b)
    rng = np.random.default_rng(seed)
    reps_out = np.empty(reps)
    for r in range(reps):
        ia = rng.integers(0, a.shape[0], size=a.shape)
        ib = rng.integers(0, b.shape[0], size=b.shape)
        reps_out[r] = probability_of_improvement(np.take_along_axis(a, ia, 0),
                                                 np.take_along_axis(b, ib, 0))
    return (point, *percentile_ci(reps_out, conf))


def shared_tasks(frame: pd.DataFrame) -> set[str]:
    """The tasks every method of `frame` (columns method, task) has runs on."""
    return set.intersection(*(set(g.task) for _, g in frame.groupby("method")))


def complete_tasks(frame: pd.DataFrame) -> tuple[list[str], int]:
    """(tasks, n): the tasks on which every method of `frame` (columns method, task, seed)
    holds n seeds, n being the most any (method, task) cell holds: the tasks a partly run
    store can already aggregate over with equal strata."""
    if frame.empty:
        return [], 0
    counts = (frame[frame.task.isin(shared_tasks(frame))]
              .groupby(["method", "task"]).seed.nunique())
    if counts.empty:
        return [], 0
    full = int(counts.max())
    per_task = counts[counts == full].reset_index().groupby("task").method.nunique()
    return sorted(per_task[per_task == frame.method.nunique()].index), full


def score_matrices(frame: pd.DataFrame, value: str = "normalized",
                   tasks: list[str] | None = None) -> dict[str, pd.DataFrame]:
    """Per method, a (seed x task) table of `value` from a frame with columns method, task,
    seed and `value`. Only tasks every method has are used (or `tasks`). Raises ShapeError
    when seed counts differ between cells or a cell has a duplicate seed."""
    if frame.empty:
        raise ShapeError("no runs to aggregate")
    dup = frame.duplicated(["method", "task", "seed"])
    if dup.any():
        r = frame[dup].iloc[0]
        raise ShapeError(f"{r.method} on {r.task} seed {r.seed} appears twice (two variants of "
                         "one method in one comparison?); filter to one variant first")
    if tasks is None:
        tasks = sorted(shared_tasks(frame))
    if not tasks:
        raise ShapeError("the methods share no task: nothing to aggregate")
    counts = frame[frame.task.isin(tasks)].groupby(["method", "task"]).seed.nunique()
    if counts.nunique() != 1:
        lo = counts.idxmin()
        few = counts.min()
        raise UnequalSeeds(f"unequal seed counts: {lo[0]} on {lo[1]} has {few} "
                           f"seed{'' if few == 1 else 's'}, others up to {counts.max()}; "
                           "finish the sweep (it resumes) "
                           "or aggregate over tasks with equal counts")
    out = {}
    for method, g in frame[frame.task.isin(tasks)].groupby("method"):
        wide = g.pivot(index="seed", columns="task", values=value)
        missing = [t for t in tasks if t not in wide.columns]
        if missing:
            raise ShapeError(f"{method} has no runs on {', '.join(missing)}")
        # Seeds are relabelled 0..n-1 per task: strata are per task, so seed ids need not
        # agree across tasks, only their counts.
        cols = {t: wide[t].dropna().to_numpy() for t in tasks}
        out[method] = pd.DataFrame(cols)
    return out


def aggregate_table(mats: Mapping[str, pd.DataFrame], reps: int = 2000, seed: int = 0,
                    conf: float = 0.95) -> pd.DataFrame:
    """IQM and mean with stratified-bootstrap CIs per method."""
    rows = []
    for method, m in mats.items():
        a = m.to_numpy()
        row = {"method": method, "runs": a.shape[0], "tasks": a.shape[1]}
        for name, fn in (("iqm", iqm), ("mean", mean)):
            lo, hi = percentile_ci(stratified_bootstrap(a, fn, reps, seed), conf)
            row.update({name: fn(a), f"{name}_lo": lo, f"{name}_hi": hi})
        rows.append(row)
    return pd.DataFrame(rows).sort_values("iqm", ascending=False, ignore_index=True)


def improvement_table(mats: Mapping[str, pd.DataFrame], of: str, reps: int = 2000,
                      seed: int = 0) -> pd.DataFrame:
    """P(`of` > each other method) with stratified-bootstrap CIs."""
    if of not in mats:
        raise ShapeError(f"no scores for {of!r}; methods present: {', '.join(sorted(mats))}")
    rows = []
    for other, m in mats.items():
        if other == of:
            continue
        p, lo, hi = poi_ci(mats[of].to_numpy(), m.to_numpy(), reps, seed=seed)
        rows.append({"comparison": f"P({of} > {other})", "p": p, "lo": lo, "hi": hi})
    return pd.DataFrame(rows, columns=["comparison", "p", "lo", "hi"])
