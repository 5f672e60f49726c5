"""Anytime metrics from a run's evaluation curve (normalized score vs training seconds, or
vs env steps with x="env_steps").

A run's score at training time t is its latest evaluation at or before t (the policy a user
would hold if training stopped at t), and 0.0 (random level) before its first evaluation.

- `auc`: the time-average of that step function over [0, horizon], in normalized-score units
  (1.0 = expert level during the whole budget); it rewards reaching a score early.
- `time_to`: the training seconds of the first evaluation at or above a level (None if the
  run never reached it).
"""
from __future__ import annotations

import numpy as np


def _points(curve, x: str = "train_s") -> tuple[np.ndarray, np.ndarray]:
    if x not in ("train_s", "env_steps"):
        raise ValueError(f"a curve's x is 'train_s' or 'env_steps', got {x!r}")
    pts = [(float(p[x]), float(p["normalized"])) for p in curve or []
           if p.get("normalized") is not None and np.isfinite(p["normalized"])]
    pts.sort()
    if not pts:
        return np.zeros(0), np.zeros(0)
    t, s = map(np.asarray, zip(*pts))
    return t, s


def value_at(curve, times, x: str = "train_s") -> np.ndarray:
    """The step function at each time (or env step count, x="env_steps") in `times`."""
    t, s = _points(curve, x)
    times = np.asarray(times, float)
    if t.size == 0:
        return np.zeros_like(times)
    i = np.searchsorted(t, times, side="right") - 1
    return np.where(i >= 0, s[np.clip(i, 0, None)], 0.0)


def auc(curve, horizon: float) -> float:
    """(1 / horizon) * integral over [0, horizon] of the step function."""
    if not horizon > 0:
        raise ValueError(f"horizon must be > 0, got {horizon}")
    t, s = _points(curve)
    if t.size == 0:
        return 0.0
    edges = np.clip(np.append(t, horizon), 0.0, horizon)
    return float(np.sum(s * np.diff(edges)) / horizon)


def time_to(curve, level: float) -> float | None:
    t, s = _points(curve)
    hit = np.nonzero(s >= level)[0]
    return float(t[hit[0]]) if hit.size else None
