"""DAC config: the original code's values (google-research `dac/`, Kostrikov et al. 2019),
with every change needed for one 128-step demo stated on the field it changes."""
from __future__ import annotations

import dataclasses

from methods.common.sb3 import check_collection


@dataclasses.dataclass(frozen=True)
class DACConfig:
    # ---- discriminator (gail.py) ----
    disc_hidden: tuple[int, ...] = (256, 256)
    """Discriminator MLP on (s, a) with the absorbing indicator in s: tanh, orthogonal init."""
    disc_lr: float = 1e-3
    """Adam (TF default lr, as the original)."""
    gp_weight: float = 10.0
    """Gradient penalty lambda on uniform interpolates between policy and expert (s, a)."""
    disc_batch: int = 100
    """Policy and expert samples per discriminator update (100 + 100)."""
    # ---- TD3 (ddpg_td3.py) ----
    actor_hidden: tuple[int, ...] = (400, 300)
    critic_hidden: tuple[int, ...] = (400, 300)
    actor_lr: float = 1e-3
    """Halved every `actor_lr_halving_steps` env steps (the original's schedule)."""
    actor_lr_halving_steps: int = 100_000
    critic_lr: float = 1e-3
    gamma: float = 0.99
    tau: float = 0.005
    target_noise: float = 0.2
    target_noise_clip: float = 0.5
    policy_delay: int = 2
    actor_grad_clip: float = 40.0
    exploration_noise: float = 0.1
    batch_size: int = 100
    learning_starts: int = 1000
    """Uniformly random actions until the buffer holds this many samples."""
    actor_start_updates: int = 1000
    """Actor updates begin after this many critic updates (the original's schedule)."""
    buffer_size: int = 1_000_000
    updates_per_step: float = 1.0
    """Update-to-data ratio (the original: one TD3 and one discriminator update per env
    step, run as L updates after each L-step episode)."""
    disc_every: int = 1
    """One discriminator update per `disc_every` TD3 updates. 1 is the original schedule;
    larger values trade discriminator training for speed (the discriminator update is ~0.6x
    of a TD3 update's arithmetic: `dac_arithmetic_ratio` in methods/common/sb3_benchmark)."""
    # ---- one-demo setting ----
    trajectory_size: int = 50
    """The original subsamples each demo to ~50 transitions: subsampling rate
    T // trajectory_size with a random offset. For one 128-step demo that is rate 2 (64
    expert transitions); set 128 to keep all of them."""
    # ---- vectorized collection on a CPU ----
    num_envs: int = 16
    """Envs stepped by one batched brax call. Collection of `steps_per_collect` env steps
    (one 128-step episode's worth) is followed by the same number of updates, as the
    original's per-episode schedule."""
    steps_per_collect: int = 128
    torch_threads: int = 0
    """torch intra-op threads (0: the CPUs this process may use); the learner sets the pace
    on a CPU (see the benchmark)."""
    report_every: int = 2048
    """Env steps between reports to the harness (evaluation happens there when due)."""
    normalize_obs: bool = True
    """Running observation normalization inside the actor, the critics and the discriminator
    (`methods.common.sb3.ObsNormalizer`; the absorbing indicator passes through). The
    original fed raw observations; Brax observations reach |x| = 139 (humanoid), where
    tanh discriminator units and ReLU critics at the original's rates saturate."""
    device: str = "auto"
    """torch device of the learner: 'auto' (CUDA where torch sees a GPU, else the CPU), 'cpu'
    or 'cuda'. The pinned torch is the CPU build; a CUDA build of the same version puts the
    learner on the GPU with nothing else to change."""

    def __post_init__(self):
        if self.torch_threads < 0:
            raise ValueError(f"torch_threads must be >= 0 (0: one per usable CPU), got "
                             f"{self.torch_threads}")
        for name in ("disc_lr", "actor_lr", "critic_lr", "tau", "gamma", "updates_per_step",
                     "actor_grad_clip"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be > 0, got {getattr(self, name)}")
        if not self.gamma < 1:
            raise ValueError(f"gamma must be < 1, got {self.gamma}")
        for name in ("disc_batch", "batch_size", "num_envs", "steps_per_collect", "policy_delay",
                     "trajectory_size", "report_every", "buffer_size",
                     "actor_lr_halving_steps", "disc_every"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        check_collection(self)
        if self.device not in ("cpu", "cuda", "auto"):
            raise ValueError(f"device must be 'cpu', 'cuda' or 'auto', got {self.device!r}")
        if self.gp_weight < 0:
            raise ValueError(f"gp_weight must be >= 0, got {self.gp_weight}")


PRESETS = {"paper": {}, "cpu": {}}
"""The original's settings already fit a CPU (the learner, not the env, sets the pace)."""
