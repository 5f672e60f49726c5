"""CEM-MPC config: receding-horizon cross-entropy planning (PETS/iCEM conventions)."""
from __future__ import annotations

import dataclasses

OBJECTIVES = ("reward", "track")


@dataclasses.dataclass(frozen=True)
class CEMConfig:
    objective: str = "reward"
    """'reward': sum of the true reward over the plan (the paper's reference, method
    `cem_mpc`); 'track': minus the squared distance of the plan's normalized matched states
    to the demo's at the same time indices t+1..t+H (no reward; method `cem_mpc_track`)."""
    population: int = 500
    """Action sequences sampled per iteration (PETS: 500)."""
    elites: int = 50
    """Top sequences the Gaussian is refit to (PETS: 50)."""
    iterations: int = 5
    """CEM iterations per control step (PETS: 5)."""
    horizon: int = 30
    """Planning horizon H in control steps (PETS: 25-30)."""
    init_std: float = 0.5
    """Std of the sampling Gaussian at each control step, in [-1, 1] action units."""
    momentum: float = 0.1
    """Smoothing: new = momentum * old + (1 - momentum) * elite statistic (PETS: 0.1)."""
    state_std_min: float = 0.1
    """Floor on the demo-state std used to normalize matched states ('track')."""
    small_dots: bool = False
    """Plan on a copy of the physics whose small matrix products are computed as
    multiply-and-sum (`tasks.physics.transforms.with_small_dots`; brax tasks only): the same
    function to float32 round-off, its forward faster on swimmer's generalized step on the CPU; the
    test episodes still run the task itself. Off by
    default: every recorded CEM-MPC cell ran without it."""

    def __post_init__(self):
        if self.objective not in OBJECTIVES:
            raise ValueError(f"objective must be one of {OBJECTIVES}, got {self.objective!r}")
        for name in ("population", "elites", "iterations", "horizon"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.elites > self.population:
            raise ValueError(f"elites ({self.elites}) must be <= population "
                             f"({self.population})")
        if not 0 <= self.momentum < 1:
            raise ValueError(f"momentum must be in [0, 1), got {self.momentum}")
        if not self.init_std > 0 or not self.state_std_min > 0:
            raise ValueError("init_std and state_std_min must be > 0")


@dataclasses.dataclass(frozen=True)
class CEMTrackConfig(CEMConfig):
    objective: str = "track"


PRESETS = {
    "paper": {},
    # iCEM-like (smaller population and elite set, 3 iterations), shorter horizon: a CPU
    # evaluation of 32 episodes x 128 steps then simulates ~12M steps instead of ~300M.
    "cpu": {"population": 64, "elites": 8, "iterations": 3, "horizon": 16},
}
