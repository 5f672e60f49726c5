"""Reporting seeds and tuning seeds, kept disjoint.

Seeds below `TUNING_SEED_START` report: the tables' seeds are 0..N-1. Seeds from it tune.
A sweep that tunes (`ildbench sweep --tune`) refuses reporting seeds, and a leaderboard of a
store that holds reporting runs leaves its tuning runs out (and says how many), so a setting
chosen by score is never scored on the seeds it was chosen on.
"""
from __future__ import annotations

from typing import Iterable

TUNING_SEED_START = 100


def is_tuning(seed: int) -> bool:
    return int(seed) >= TUNING_SEED_START


def check_tuning_seeds(seeds: Iterable[int]) -> None:
    """Raise ValueError (the CLI's exit 2) naming the reporting seeds among `seeds`."""
    low = sorted(int(s) for s in seeds if not is_tuning(s))
    if low:
        raise ValueError(
            f"--tune: seeds {low} are reporting seeds (below {TUNING_SEED_START}), the ones "
            f"the tables report; a tuning sweep runs on seeds {TUNING_SEED_START} and up: add "
            f"--seed-start {TUNING_SEED_START}")
