"""ILD config. Defaults are the paper's (A.5, Table 2 setting); presets and per-task
overrides are data beside it. The physics ILD differentiates through is the task's
(`tasks.physics.plan`), not a config choice."""
from __future__ import annotations

import dataclasses

LOSSES = ("chamfer", "l2")
DISTANCES = ("rms", "sq", "msq")
SCHEDULES = ("linear", "constant", "budget")
NORM_SCOPES = ("env", "batch")


@dataclasses.dataclass(frozen=True)
class ILDConfig:
    hidden: tuple[int, ...] = (512, 256)
    """Policy MLP hidden sizes (A.5: 512-256, swish; tanh-Gaussian head)."""
    num_envs: int = 360
    """Batch of parallel rollouts per update (A.5: 360 on an A100)."""
    updates: int = 5000
    """Policy updates after the BC warm start (A.5: 5000); the budget may stop earlier."""
    learning_rate: float = 1e-3
    """Adam learning rate at the start (A.5)."""
    lr_schedule: str = "budget"
    """'budget' (default): decay linearly to lr_end over the fraction of the run's budget
    spent (or over `updates`, if sooner), so the decay completes when a budget stops the run
    long before `updates`; 'linear': decay over `updates` only, as the original intended
    (its schedule was dead code: the compiled update closed over the first optimizer),
    which barely decays within a CPU budget; 'constant'. The comparison that chose it:
    docs/decisions/ild-learning-rate.md."""
    lr_warmup: int = 0
    """Updates over which the rate ramps linearly from learning_rate/lr_warmup up to the
    schedule's rate (0: none). Adam's first step moves every weight by the full rate
    whatever the gradient's size (lr x sign(g)): `python -m benchmarks.ild_probe` measured that
    first step at lr 1e-3 raising inverted_pendulum's loss 588x from the BC warm start."""
    lr_end: float = 1e-5
    """Final learning rate of the linear schedule (the original's value)."""
    max_grad_norm: float = 0.3
    """Global gradient-norm clip (A.5)."""
    truncation: int = 10
    """Truncated BPTT window: the state is stop_gradient'ed every `truncation` steps."""
    loss: str = "chamfer"
    """'chamfer' (Chamfer-alpha, Eq. 3) or 'l2' (the step-wise ablation)."""
    alpha: float = 1.0
    """Deviation factor: multiplies the deviation term (Eq. 3, A.5: 1)."""
    distance: str = "rms"
    """'rms' (original code; default, see losses.py), 'sq' (squared L2, the paper's text) or
    'msq' (squared L2 over the state's width, the original's cloth loss)."""
    tanh_loss: bool = False
    """Wrap the loss in tanh as the original code did. Off by default: the paper's Eq. 3 has
    no tanh, and in float32 tanh(L) == 1 exactly for a raw loss L above ~9, so the gradient
    is exactly zero whenever the policy is far from the demo (e.g. ILD without BC at init;
    tests/test_ild.py::test_tanh_loss_saturates_to_a_zero_gradient)."""
    grad_normalization: bool = True
    """Per-step gradient normalization through the dynamics (the original's stabilizer)."""
    grad_norm_scope: str = "env"
    """What one norm of the per-step normalization spans: 'env' (default) each env's action
    and next-state cotangent on its own, so one env's exploding contact cannot shrink the
    others' gradients; 'batch' all B envs' at once, as the original's `norm_grad` on brax
    v1's batched state did, a norm up to sqrt(B) times an env's. The same gradient wherever
    nothing reaches norm 1, which is what `python -m benchmarks.ild_probe` finds from the BC
    warm start on acrobot and hopper at B = 32."""
    bc_updates: int = 1000
    """BC warm-start updates (Alg. 1 line 3; the original ran 1000); 0 disables it."""
    bc_samples: int = 16
    """Reparameterized samples per demo state in the BC loss."""
    obs_std_min: float = 0.3
    """Observation-normalizer std floor, as BC's (the warm start; methods/bc/config.py has
    the measurement)."""
    state_std_min: float = 0.1
    """Std floor of the matched-state normalizer of the loss: the demo's spread defines the
    metric, and features it barely varies are not amplified past 1/0.1."""
    mask_after_done: bool = False
    """Exclude rollout states after an early termination from the loss. Off by default:
    a fallen robot's states far from the demo are ILD's only signal against falling. With
    the mask on, Chamfer (order-free) is indifferent to falling when the demo's states are
    all alike: on inverted_pendulum (a near-motionless demo) 5-minute cpu runs ended at 0.68
    normalized with the mask and 0.78 without (from a BC warm start at 1.00)."""
    resample_init: bool = True
    """Draw fresh initial states every update. The original reset once and reused the same
    states for all 5000 updates; fresh ones fit the test distribution instead."""
    remat: bool = False
    """Rematerialize each control step in the backward pass (jax.checkpoint): less memory,
    more compute. The physics plan's `substep_remat` is the cheaper form on brax tasks."""
    transposed_backward: bool = True
    """The rollout's policy runs as one batched `TanhGaussianPolicy.sample_batch` per step,
    whose backward reads the kernels transposed once per update instead of transposing each
    at every step (XLA's CPU backend runs that per-step product at half speed). The same
    loss and gradient bit for bit on pointmass and all 8 brax tasks (tests/test_ild.py).
    False: the policy vmapped per env, flax's backward."""
    swish_remat: bool = True
    """With `transposed_backward`, each of the policy's hidden activations and the product
    after it run as one `methods.common.policy.swish_dense_t`, whose backward keeps only the
    pre-activation and recomputes swish from it, instead of reverse mode's swish
    intermediates and output, which the rollout's scan stacks over every step (most of
    hopper's update's working memory at B = 32). The same rollout and gradient bit for bit
    (tests/test_ild.py: pointmass, and the slow test's one update of each of the 8 brax
    tasks). False: swish and the product apart."""
    kernel_grad_group: int = 1
    """G > 1 (with `transposed_backward`): the rollout runs as T / G groups of G steps
    (`train.make_step_group`, G must divide the episode), whose backward makes each policy
    kernel's cotangent once per group, one product over G x B rows, instead of once per step
    over the batch's B rows. The same function; its loss and gradient equal G = 1's to
    float32 round-off (the kernels' sums over steps in another order: pointmass's loss bit
    for bit, tests/test_ild.py; the 8 brax tasks over 16 steps behind -m slow). Off (1) by
    default: it gains little outside acrobot (docs/decisions/physics-rewrites.md)."""
    chunk: int = 1
    """Updates per jitted call between reports and budget checks (1: metrics every update).
    K > 1 pays XLA's per-call costs once per K updates; each call runs only the updates the
    budget has left, so it never overruns it."""
    joint_limits: bool = True
    """False: the training rollouts run on a copy of the task without its joint-range
    constraints (`tasks.core.without_joint_limits`), a smooth surrogate where brax solves
    limits like contacts and the loss through them is rough (swimmer; docs/methods/ild.md).
    The policy is still evaluated on the task itself, limits and all."""

    def __post_init__(self):
        checks = [
            (self.loss in LOSSES, f"loss must be one of {LOSSES}, got {self.loss!r}"),
            (self.distance in DISTANCES,
             f"distance must be one of {DISTANCES}, got {self.distance!r}"),
            (self.grad_norm_scope in NORM_SCOPES,
             f"grad_norm_scope must be one of {NORM_SCOPES}, got {self.grad_norm_scope!r}"),
            (self.lr_schedule in SCHEDULES,
             f"lr_schedule must be one of {SCHEDULES}, got {self.lr_schedule!r}"),
            (self.alpha >= 0, f"alpha must be >= 0, got {self.alpha}"),
            (self.bc_updates >= 0, f"bc_updates must be >= 0, got {self.bc_updates}"),
            (bool(self.hidden) and all(h >= 1 for h in self.hidden),
             f"hidden must be positive layer sizes, got {self.hidden}"),
        ]
        for name in ("learning_rate", "lr_end", "max_grad_norm", "obs_std_min",
                     "state_std_min"):
            checks.append((getattr(self, name) > 0, f"{name} must be > 0, got "
                                                     f"{getattr(self, name)}"))
        checks.append((self.lr_warmup >= 0,
                       f"lr_warmup must be >= 0 updates, got {self.lr_warmup}"))
        checks.append((self.kernel_grad_group == 1 or self.transposed_backward,
                       "kernel_grad_group > 1 groups sample_batch's kernel cotangents; set "
                       "transposed_backward True or kernel_grad_group 1"))
        for name in ("num_envs", "updates", "truncation", "bc_samples", "chunk",
                     "kernel_grad_group"):
            checks.append((getattr(self, name) >= 1, f"{name} must be >= 1, got "
                                                      f"{getattr(self, name)}"))
        for ok, msg in checks:
            if not ok:
                raise ValueError(msg)


PRESETS = {
    # The paper's scale: for an accelerator (one update is ~11x the cpu preset's work).
    "paper": {},
    # Sized so updates are frequent on one CPU core: a 10-minute budget buys several
    # hundred updates on hopper.
    "cpu": {"num_envs": 32},
}

TASK_OVERRIDES: dict[str, dict] = {
    # Full BPTT where a truncated window's gradient points uphill from the BC warm start:
    # inverted_pendulum (an unstable pole: cosine with the full-BPTT gradient -0.99 at
    # truncation 10, 1.000 at 128, `python -m benchmarks.ild_probe --task inverted_pendulum
    # --num-envs 32 --truncation W`) and acrobot (a swing-up's early torques pay off many
    # steps later: -0.39 at 10, 1.000 at 128). How they were chosen: docs/methods/ild.md.
    # test_truncated_bptt_climbs_inverted_pendulums_loss_and_full_bptt_descends_it trains
    # both windows from one warm start.
    "inverted_pendulum": {"truncation": 128},
    "acrobot": {"truncation": 128},
    # The original's cloth configuration (../shared facts, docs/methods/ild.md): 10 parallel
    # rollouts, Adam lr 1e-4, 2000 BC warm-start updates, a Chamfer of raw states under the
    # mean squared distance and a policy on unnormalized observations (the demo's cloth
    # coordinates have stds below 0.19, so std floors of 1 leave both unscaled), the
    # per-step gradient norm over the whole batch, and the tanh on the loss (below 1e-2
    # here, where tanh is the identity to 1e-4). Not here: its average of 5 gradient samples
    # per update. A preset wins over these (the cpu preset sets num_envs 32): cloth runs
    # pass --set num_envs=10.
    "cloth": {"num_envs": 10, "learning_rate": 1e-4, "bc_updates": 2000, "distance": "msq",
              "state_std_min": 1.0, "obs_std_min": 1.0, "grad_norm_scope": "batch",
              "tanh_loss": True},
}

