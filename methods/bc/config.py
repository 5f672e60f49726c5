"""Behaviour cloning config: the paper's BC warm start (Alg. 1 line 3) as a method."""
from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class BCConfig:
    hidden: tuple[int, ...] = (512, 256)
    """Policy MLP hidden sizes (paper A.5: 512-256, swish)."""
    learning_rate: float = 1e-3
    """Adam learning rate (the original BC bootstrap used the ILD lr, 1e-3)."""
    max_grad_norm: float = 0.3
    """Global gradient-norm clip (as the original bootstrap)."""
    updates: int = 1000
    """Gradient updates (the original bootstrap ran 1000 on the Brax tasks)."""
    samples: int = 16
    """Reparameterized action samples per demo state in the loss."""
    obs_std_min: float = 1.0
    """Floor on the observation normalizer's std. The original used 1e-3; with one demo
    that amplifies features the demo barely varies: on inverted_pendulum (a near-motionless
    demo) BC scored -0.01 normalized with floors 1e-3..1e-1 and 1.00 with 1.0 (2 seeds each,
    `ildbench sweep --methods bc --tasks inverted_pendulum --seeds 2 --budget 60s`)."""
    chunk: int = 50
    """Updates per jitted chunk between reports (budget checks happen between chunks)."""

    def __post_init__(self):
        if not self.hidden or any(h < 1 for h in self.hidden):
            raise ValueError(f"hidden must be positive layer sizes, got {self.hidden}")
        for name in ("learning_rate", "max_grad_norm", "obs_std_min"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("updates", "samples", "chunk"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")


PRESETS = {"paper": {}, "cpu": {}}  # BC is cheap: the paper's settings run fine on a CPU
