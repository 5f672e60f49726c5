"""SHAC config: the original's defaults (NVlabs/DiffRL shac.py + cfg/shac/*.yaml), per-task
values from its table, and a cpu preset."""
from __future__ import annotations

import dataclasses


@dataclasses.dataclass(frozen=True)
class SHACConfig:
    actor_hidden: tuple[int, ...] = (128, 64, 32)
    """Actor MLP, ELU + LayerNorm after each hidden layer (humanoid: 256-128)."""
    critic_hidden: tuple[int, ...] = (64, 64)
    """Critic MLP, ELU + LayerNorm, orthogonal init gain sqrt(2) (humanoid: 128-128)."""
    logstd_init: float = -1.0
    """State-independent log-std of the Gaussian before the tanh."""
    num_envs: int = 64
    """Parallel actors (hopper: 256)."""
    horizon: int = 32
    """Window length h: the actor's gradient is cut at each window start."""
    actor_lr: float = 2e-3
    critic_lr: float = 2e-3
    lr_end: float = 1e-5
    """Both learning rates decay linearly to this over `max_epochs` (the original)."""
    max_epochs: int = 2000
    """Length of the LR schedule and the most epochs to run (the budget may stop earlier)."""
    betas: tuple[float, float] = (0.7, 0.95)
    """Adam betas for actor and critic."""
    grad_clip: float = 1.0
    """Global gradient-norm clip for actor and critic."""
    gamma: float = 0.99
    lam: float = 0.95
    """TD-lambda for the critic targets."""
    critic_iterations: int = 16
    critic_minibatches: int = 4
    target_alpha: float = 0.2
    """Target critic update theta' <- alpha theta' + (1 - alpha) theta once per epoch."""
    reward_scale: float = 1.0
    obs_norm: bool = True
    """Running mean/std of observations (frozen within a window)."""

    def __post_init__(self):
        for name in ("actor_lr", "critic_lr", "lr_end", "grad_clip", "reward_scale"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        for name in ("gamma", "lam", "target_alpha"):
            if not 0 <= getattr(self, name) < 1:
                raise ValueError(f"{name} must be in [0, 1), got {getattr(self, name)}")
        for name in ("num_envs", "horizon", "max_epochs", "critic_iterations",
                     "critic_minibatches"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if (self.num_envs * self.horizon) % self.critic_minibatches:
            raise ValueError(f"num_envs * horizon ({self.num_envs * self.horizon}) must split "
                             f"into critic_minibatches ({self.critic_minibatches})")


TASK_OVERRIDES = {
    # The original's per-task table (cheetah omitted: not a task here).
    "ant": {"actor_lr": 2e-3, "critic_lr": 2e-3, "num_envs": 64, "target_alpha": 0.2},
    "hopper": {"actor_lr": 2e-3, "critic_lr": 2e-4, "num_envs": 256, "target_alpha": 0.2},
    "humanoid": {"actor_lr": 2e-3, "critic_lr": 5e-4, "num_envs": 64, "target_alpha": 0.995,
                 "actor_hidden": (256, 128), "critic_hidden": (128, 128)},
}

PRESETS = {
    "paper": {},
    # 2 CPU cores: fewer actors so that epochs (and LR decay) happen within minutes.
    "cpu": {"num_envs": 32},
}
