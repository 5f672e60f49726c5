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
    obs_std_min: float = 0.3
    """Floor on the observation normalizer's std (the statistics are fixed: no gradient).
    The original used 1e-3; with one demo that amplifies features the demo barely varies, and
    too high a floor leaves them unreadable. Measured with the frozen normalizer (bc v2),
    3 seeds, `ildbench sweep --methods bc --tasks T --seeds 3 --budget 60s --set
    obs_std_min=F --store results/tuning/bc_normalizer_floor/runs` (nominal normalized score):
    inverted_pendulum 0.1: 0.725 0.838 0.968 | 0.3: 1.000 1.000 1.000 | 1.0: 0.787 0.929 0.823;
    reacher 0.3: 0.843 0.722 0.822 | 1.0: 0.878 0.766 0.816; hopper 0.3: 1.004 0.922 1.007
    | 1.0: 0.882 0.977 0.772. (bc v1, whose normalizer Adam moved, scored 1.00 on inverted_pendulum
    at 1.0 and -0.01 at 1e-3..1e-1.)"""
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
