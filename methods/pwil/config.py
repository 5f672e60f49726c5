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
    scale_floor: float = 0.2
    """Floor on each feature's standardization scale, in the feature's own units. One
    128-step demo shows almost no spread in some features that differ between expert
    episodes, and 1/std there lets one feature decide every distance: on reacher the
    fingertip-to-target offset (std 0.012 within the demo) gave held-out expert episodes a
    mean reward of 0.06 out of alpha = 5. With 0.2, held-out expert episodes score far above a
    random policy's on every task (tests/test_pwil.py). 0 is the original's StandardScaler."""
    subsampling: int = 1
    """Keep every k-th demo step as an atom. The original subsampled 1000-step demos every 20
    steps; one 128-step demo would keep ~6 atoms, so we keep all 128 (k = 1)."""
    # ---- learner ----
    # The original learner is Acme's D4PG (distributional critic, n-step 5), which SB3 lacks.
    # We use SB3's TD3, the closest SB3 relative (deterministic actor, Gaussian exploration,
    # twin critics instead of the categorical one), at TD3's own sizes and rate: see below.
    actor_hidden: tuple[int, ...] = (256, 256)
    """TD3's actor (Fujimoto et al.). D4PG's policy is LayerNormMLP(256, 256, 256)."""
    critic_hidden: tuple[int, ...] = (256, 256)
    """TD3's twin critics. D4PG's critic torso is (512, 512, 256) before a 201-atom head;
    twin (512, 512, 256) critics at batch 256 make an update about 4.5x the arithmetic of
    (256, 256) ones, which on one CPU core would make 200k env steps at the original's
    update-to-data ratio take over 1.5 hours per run: the
    budgets here are 10-100x below the original's 1M steps, so the learner is sized for them
    (`python -m benchmarks.sb3_speed` measures the learner's rate)."""
    learning_rate: float = 3e-4
    """Adam for actor and critic: TD3's 3e-4. The original's 1e-4 went with D4PG and 1M env
    steps; at 50k-200k steps the smaller rate leaves the critic far from converged."""
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
    """Most demo transitions the replay counts, each with reward alpha (the original
    prefilled 50,000 beside its 1M agent steps)."""
    prefill_fraction: float = 0.05
    """Demo transitions per env step of the budget: the original's 50,000 per 1M. The replay
    counts min(prefill, prefill_fraction x the run's env steps) demo transitions, so the demo's
    share of replay follows the same course over a run of any length as over the original's
    (on a seconds budget the run's env steps are projected from the rate so far). The demo is
    stored once and sampled in that proportion (`methods.pwil.train.DemoMixReplay`)."""
    normalize_obs: bool = True
    """Running observation normalization inside the actor and critics
    (`methods.common.sb3.ObsNormalizer`): Brax observations reach |x| = 139 (humanoid)."""
    device: str = "auto"
    """torch device of the learner: 'auto' (CUDA where torch sees a GPU, else the CPU), 'cpu'
    or 'cuda'. The pinned torch is the CPU build; a CUDA build of the same version puts the
    learner on the GPU with nothing else to change."""
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
        if not 0 <= self.prefill_fraction <= 1:
            raise ValueError(f"prefill_fraction must be in [0, 1], got {self.prefill_fraction}")
        if self.scale_floor < 0:
            raise ValueError(f"scale_floor must be >= 0, got {self.scale_floor}")
        if self.device not in ("cpu", "cuda", "auto"):
            raise ValueError(f"device must be 'cpu', 'cuda' or 'auto', got {self.device!r}")
        check_collection(self)


PRESETS = {"paper": {}, "cpu": {}}


# T is the episode length: the cloth's episodes are 80 steps.
TASK_OVERRIDES: dict[str, dict] = {"cloth": {"horizon": 80}}
