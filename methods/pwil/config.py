"""PWIL config: the paper's reward constants and the original learner's settings, mapped to
SB3's TD3, with every change for one 128-step demo stated on the field it changes."""
from __future__ import annotations

import dataclasses

from methods.common.sb3 import check_collection


@dataclasses.dataclass(frozen=True)
class PWILConfig:
    # ---- reward (pwil/rewarder.py) ----
    alpha: float = 5.0
    """Reward scale (paper: 5)."""
    beta: float = 5.0
    """Reward sharpness (paper: 5); sigma = beta * T / sqrt(d)."""
    horizon: int = 128
    """T, the agent's mass 1/T per step. The original used 1000 (its episode length); here
    the episode is 128 steps, so T = 128."""
    use_actions: bool = True
    """Atoms are (s, a) (the original's default); False = state-only PWIL."""
    subsampling: int = 1
    """Keep every k-th demo step as an atom. The original subsampled 1000-step demos every 20
    steps; one 128-step demo would keep ~6 atoms, so we keep all 128 (k = 1)."""
    # ---- learner ----
    # The original learner is Acme's D4PG (distributional critic, n-step 5), which SB3 lacks.
    # We use SB3's TD3, the closest SB3 relative (deterministic actor, Gaussian exploration,
    # twin critics instead of the categorical one), with D4PG's sizes and rates below.
    actor_hidden: tuple[int, ...] = (256, 256, 256)
    """D4PG policy: LayerNormMLP(256, 256, 256) (we use a plain ReLU MLP)."""
    critic_hidden: tuple[int, ...] = (512, 512, 256)
    """D4PG critic torso (512, 512, 256)."""
    learning_rate: float = 1e-4
    """Adam 1e-4 for actor and critic (the original)."""
    gamma: float = 0.99
    n_step: int = 5
    """n-step returns (the original's D4PG n = 5; SB3's NStepReplayBuffer)."""
    tau: float = 0.005
    """Soft target updates (D4PG hard-copied every 100 learner steps)."""
    exploration_noise: float = 0.2
    """Gaussian exploration sigma 0.2, clipped to the action range (the original)."""
    batch_size: int = 256
    learning_starts: int = 1000
    """Minimum replay size before learning (the original: 1000)."""
    buffer_size: int = 1_000_000
    updates_per_step: float = 1.0
    """Update-to-data ratio (the original: samples_per_insert 256 at batch 256 = 1)."""
    prefill: int = 50_000
    """Demo transitions placed in replay before training, each with reward alpha (the
    original prefilled 50,000 from its subsampled demos; here the 128-step demo repeated)."""
    # ---- vectorized collection on a CPU ----
    num_envs: int = 16
    steps_per_collect: int = 128
    torch_threads: int = 0
    report_every: int = 2048

    def __post_init__(self):
        if self.torch_threads < 0:
            raise ValueError(f"torch_threads must be >= 0 (0: one per usable CPU), got "
                             f"{self.torch_threads}")
        for name in ("alpha", "beta", "learning_rate", "tau", "updates_per_step", "gamma"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not self.gamma < 1:
            raise ValueError(f"gamma must be < 1, got {self.gamma}")
        for name in ("horizon", "subsampling", "n_step", "batch_size", "buffer_size",
                     "num_envs", "steps_per_collect", "report_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.prefill < 0:
            raise ValueError(f"prefill must be >= 0, got {self.prefill}")
        check_collection(self)


PRESETS = {"paper": {}, "cpu": {}}


# T is the episode length: the cloth's episodes are 80 steps.
TASK_OVERRIDES: dict[str, dict] = {"cloth": {"horizon": 80}}
