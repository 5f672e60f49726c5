"""ILD config. Defaults are the paper's (A.5, Table 2 setting); presets and per-task
overrides are data beside it."""
from __future__ import annotations

import dataclasses

LOSSES = ("chamfer", "l2")
DISTANCES = ("rms", "sq")
SCHEDULES = ("linear", "constant", "budget")
NORM_SCOPES = ("env", "batch")
PLANAR_ADJOINT_EXCLUDES = ("small_dots", "closed_form_adjoint")
"""ILDConfig fields that rewrite physics `planar_adjoint` does not run: a closed-form step's
backward, or brax's step as small products."""


HAND_ADJOINT_PIECES = ("hinge_forces", "planar_root", "rotary_joints",
                       "saved_residuals")
"""ILDConfig fields that are pieces of `hand_adjoint`'s spring substep: each needs it on
(the config's check; the method's `requires`)."""


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
    """'rms' (original code; default, see losses.py) or 'sq' (squared L2, the paper's text)."""
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
    more compute. `substep_remat` is the cheaper form on brax tasks."""
    substep_remat: bool = True
    """Rematerialize each physics substep inside a control step in the backward pass
    (`tasks.core.with_substep_remat`: brax's substep scan stores only each substep's input
    state and recomputes the rest next to its backward). The same function and gradient to
    float32 round-off, faster on every brax task but swimmer in a fraction of the working
    memory (docs/physics.md). Tasks without brax's substep loop (pointmass, cloth) have
    nothing to rematerialize: there it changes nothing."""
    small_dots: bool = False
    """Compute the physics step's small matrix products as multiply-and-sum in the training
    rollouts (`tasks.core.with_small_dots`): the same function and gradient to float32
    round-off, faster where XLA's CPU backend runs a step as many tiny batched products
    (swimmer); no gain on the spring tasks or acrobot. Off in the class; swimmer's
    TASK_OVERRIDES turn it on."""
    lean_substeps: bool = False
    """In the training rollouts, every physics substep but a control step's last skips the
    joint coordinates (q, qd) that brax's spring and positional substeps recover from their
    link frames, which the next substep reads only through its actuators' bias (zero for
    motors) and the observation reads only at the step's end (`tasks.core.with_lean_substeps`).
    The same function and gradient to float32 round-off, for a longer compile. Tasks on
    brax's generalized backend, without brax physics, or with servo actuators refuse it. Off
    in the class; the TASK_OVERRIDES of the tasks in `LEAN_SUBSTEP_TASKS` turn it on."""
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
    closed_form_adjoint: bool = False
    """Differentiate the training rollouts' physics through the task's closed-form step
    (`tasks.core.with_closed_form_adjoint`; acrobot's double-pendulum equations) instead of
    brax's reverse mode: brax's step still computes every value (the same rollout bit for
    bit), and the gradient is the same to float32 round-off. Replaces `substep_remat` (the
    backward no longer reads brax's substeps). Tasks without a closed form refuse it. Off in
    the class; acrobot's TASK_OVERRIDES turn it on."""
    hand_adjoint: bool = False
    """Run the training rollouts' spring substeps as `tasks.spring_adjoint.step`: brax's
    substep with the VJPs of six of its pieces (inverse inertia, joint forces and contact
    impulses moved to the links, integration, conversions to link and joint frames) written
    by hand instead of XLA's reverse mode of brax's code. The same rollout and gradient to
    float32 round-off (tests/test_hand_adjoint.py). A CPU choice: it cuts the number of XLA
    operations, which is what an update costs on one CPU core (docs/physics.md). Tasks not
    on brax's spring backend refuse it. Off in the class; the TASK_OVERRIDES of the tasks in
    `HAND_ADJOINT_TASKS` turn it on."""
    hinge_forces: bool = False
    """With `hand_adjoint`, on a scene whose 1-dof joints are all hinges (hopper, walker2d,
    ant, humanoid): their constraint forces by `tasks.spring_adjoint.hinge`, brax's
    `_one_dof` without the terms a hinge multiplies by zero and with only the one joint
    angle its limit reads. The same values, bit for bit in one call and to float32
    round-off over a rollout (XLA fuses the rest differently), in fewer operations. Off in
    the class; the TASK_OVERRIDES of the tasks in `HINGE_FORCES_TASKS` turn it on; there
    `--set hand_adjoint=false` turns it off too (the method's `requires`)."""
    planar_root: bool = False
    """With `hand_adjoint`, on a scene whose 3-dof joints are all planar roots (two
    unlimited slides and one unlimited hinge: hopper's and walker2d's root): their
    constraint forces by `tasks.spring_adjoint.planar_root`, brax's `_three_dof` without
    the terms such a joint multiplies by zero (the Euler angles, the limits whose infinite
    bounds are never passed, the other rows' axes). The same values, in fewer operations.
    Off in the class; the TASK_OVERRIDES of the tasks in `PLANAR_ROOT_TASKS` turn it on."""
    rotary_joints: bool = False
    """With `hand_adjoint`, on a scene whose 2- and 3-dof joints all only turn (humanoid's):
    their constraint forces by `tasks.spring_adjoint.rotary_two` and `rotary_three`, brax's
    `_two_dof` and `_three_dof` without the terms such joints multiply by zero (the slides'
    projections, forces and limits, the pins and single-axis torques). The same values, in
    fewer operations. Off in the class; the TASK_OVERRIDES of the tasks in
    `ROTARY_JOINTS_TASKS` turn it on."""
    saved_residuals: bool = False
    """With `hand_adjoint` and `substep_remat`: the substep checkpoint saves the residuals of
    the hand-written VJPs of `world_to_joint` and `inv_inertia` (the joint frames' rotations,
    offsets and motions; the links' rotations into their inertia frames) in the forward,
    instead of recomputing them next to the backward
    (`tasks.spring_adjoint.SAVED_RESIDUALS`). XLA's CPU backend fuses the recomputed
    quaternion and cross products into the VJPs' loops, which evaluate them again per
    output entry. The same function, the values saved rather than computed again, but
    another float32 program (a loss after two updates differs in the 5th digit). Without
    `substep_remat` every residual is saved anyway. Off in the class; the TASK_OVERRIDES of
    the tasks in `SAVED_RESIDUALS_TASKS` (ant, humanoid) turn it on; there `--set
    hand_adjoint=false` turns it off too."""
    positional_joints: bool = False
    """On brax's positional backend, for a scene whose joints are hinges and slides
    (reacher, inverted_pendulum): each substep by `tasks.positional_joints.step`, brax's
    positional substep with the joints' position-level update written for those kinds
    alone (brax's treats every joint as a 3-dof one: three signed angles, clips, rotations
    and Euler angles, where a hinge has one free angle and a slide none), the joints'
    forces vectorized over the dofs, and the conversions to link and joint frames and the
    inverse inertia by `tasks.spring_adjoint`'s hand-written VJPs. The same function and
    gradient to float32 round-off (tests/test_positional_joints.py), in fewer operations.
    Off in the class; the TASK_OVERRIDES of the tasks in `POSITIONAL_JOINTS_TASKS` turn it
    on. Tasks on other backends, or with other joints, refuse it."""
    planar_adjoint: bool = False
    """For a scene that moves in one plane, on brax's positional backend
    (inverted_pendulum; reacher, with `planar_normal_gravity`) or its spring backend
    (hopper, walker2d): the training rollouts'
    control step runs the task's own physics (with `lean_substeps`, `positional_joints`
    and `hand_adjoint` as set; `substep_remat` has nothing left to act on) and, in reverse
    mode, the VJP of brax's step written over the plane (`tasks.planar.control_step`,
    `tasks.planar_spring.control_step`; `tasks.core.with_planar_adjoint`), in place of
    reverse mode through every out-of-plane entry brax computes. The same rollout, and the
    same gradient to float32 round-off where the per-step normalization clips nothing
    (tests/test_planar.py, tests/test_planar_spring.py). Tasks whose scene leaves the plane
    (ant, humanoid; reacher, whose gravity is along its hinges, unless
    `planar_normal_gravity`) or other backends refuse it. Off in the class;
    `PLANAR_ADJOINT_TASKS` turn it on."""
    planar_links: bool = False
    """With `planar_adjoint` on the spring backend (hopper, walker2d): its planar step written
    with every link at once (`tasks.planar_links.control_step`: each entry an array over
    the links, what a link reads of another through products with constant one-hot
    matrices) instead of one scalar per link and entry (`tasks.planar_spring`). The same
    rollout and gradient to float32 round-off (tests/test_planar_links.py). Off in the
    class; `PLANAR_LINKS_TASKS` turn it on. Needs `planar_adjoint`; positional tasks refuse
    it."""
    spatial_links: bool = False
    """On brax's spring backend, for a scene of a free root and joints that only turn
    (hinges, 2- and 3-dof joints) with contacts against a plane (ant, humanoid): the
    training rollouts' control step runs the task's own physics (with `lean_substeps` and
    `hand_adjoint` as set; `substep_remat` has nothing left to act on) and, in reverse
    mode, the VJP of brax's spring step written with every entry of every vector an array
    over the links (`tasks.spatial_links.control_step`; `tasks.core.with_spatial_adjoint`),
    in place of reverse mode through brax's arrays of 3- and 4-vectors. The same rollout,
    and the same gradient to float32 round-off (tests/test_spatial_links.py). Tasks with
    joints that slide, roots that are not free, or other backends refuse it. Off in the
    class; `SPATIAL_LINKS_TASKS` turn it on, and on a GPU `PLATFORM_OVERRIDES` off."""
    planar_normal_gravity: bool = False
    """With `planar_adjoint` on the positional backend: a scene whose gravity is along the
    normal of the plane its hinges turn in (reacher's, along its hinges) is differentiated
    as that scene without gravity (`tasks.planar.planar_scene(drop_normal_gravity=True)`;
    the rollout keeps brax's gravity). Without it planar_adjoint refuses such a scene. The
    VJP at reacher's rollout states is within 6e-5 of each leaf's largest entry of the
    trained step's (tests/test_planar.py). Off in the class; `PLANAR_NORMAL_GRAVITY_TASKS`
    (reacher) turn it on. Needs `planar_adjoint`."""
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
            (not (self.closed_form_adjoint and self.small_dots),
             "closed_form_adjoint and small_dots both rewrite the physics step; set one of "
             "them False"),
            (not (self.closed_form_adjoint and self.lean_substeps),
             "closed_form_adjoint and lean_substeps both rewrite the physics step; set one of "
             "them False"),
            *((self.hand_adjoint or not getattr(self, piece),
               f"{piece} is a piece of hand_adjoint's spring substep; set hand_adjoint "
               f"True or {piece} False") for piece in HAND_ADJOINT_PIECES),
            (not (self.positional_joints and (self.hand_adjoint or self.closed_form_adjoint)),
             "positional_joints rewrites brax's positional substep, hand_adjoint the spring "
             "one and closed_form_adjoint the whole step; set positional_joints False"),
            *((not (self.planar_adjoint and getattr(self, other)),
               f"planar_adjoint differentiates brax's step through its planar form; {other} "
               f"rewrites another: set one of them False")
              for other in PLANAR_ADJOINT_EXCLUDES),
            *((not (self.spatial_links and getattr(self, other)),
               f"spatial_links differentiates brax's step through its form over the links; "
               f"{other} rewrites another: set one of them False")
              for other in PLANAR_ADJOINT_EXCLUDES + ("planar_adjoint",)),
            (self.planar_adjoint or not self.planar_links,
             "planar_links writes planar_adjoint's spring step over the links; set "
             "planar_adjoint True or planar_links False"),
            (self.planar_adjoint or not self.planar_normal_gravity,
             "planar_normal_gravity says how planar_adjoint models gravity off the plane; "
             "set planar_adjoint True or planar_normal_gravity False"),
            (not (self.closed_form_adjoint and self.hand_adjoint),
             "closed_form_adjoint and hand_adjoint both rewrite the physics step's backward; "
             "set one of them False"),
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
    # acrobot also differentiates its physics through its closed-form step (the same
    # rollout bit for bit, the same gradient to float32 round-off; docs/physics.md).
    "acrobot": {"truncation": 128, "closed_form_adjoint": True},
    # swimmer's step is many tiny batched products, which `small_dots` computes as
    # multiply-and-sum (docs/physics.md). Its loss is rough through brax's joint-limit
    # constraints, not because of truncation, so it keeps truncation 10.
    "swimmer": {"small_dots": True},
    # The original's cloth setting: 10 parallel rollouts and Adam lr 1e-4. A preset wins over
    # these (the cpu preset sets num_envs 32): cloth runs pass --set num_envs=10.
    "cloth": {"num_envs": 10, "learning_rate": 1e-4},
}


def _merge_overrides(names: tuple[str, ...], **fields) -> None:
    """Add `fields` to each named task's TASK_OVERRIDES entry (merged, not replaced)."""
    for name in names:
        TASK_OVERRIDES[name] = {**TASK_OVERRIDES.get(name, {}), **fields}


# The physics rewrites each task trains with on a CPU: each the same function and gradient
# to float32 round-off as brax's step through XLA's reverse mode (its test is named in
# docs/physics.md, which also has the speed each buys), so they change speed, not the
# objective. A task appears in a tuple only where the rewrite describes its scene; the
# rewrite refuses any other.
LEAN_SUBSTEP_TASKS = ("hopper", "walker2d", "ant", "humanoid", "reacher", "inverted_pendulum")
_merge_overrides(LEAN_SUBSTEP_TASKS, lean_substeps=True)
HAND_ADJOINT_TASKS = ("hopper", "walker2d", "ant", "humanoid")  # the spring tasks
_merge_overrides(HAND_ADJOINT_TASKS, hand_adjoint=True)
HINGE_FORCES_TASKS = HAND_ADJOINT_TASKS  # every 1-dof joint of theirs is a hinge
_merge_overrides(HINGE_FORCES_TASKS, hinge_forces=True)
PLANAR_ROOT_TASKS = ("hopper", "walker2d")  # two unlimited slides and a hinge
_merge_overrides(PLANAR_ROOT_TASKS, planar_root=True)
ROTARY_JOINTS_TASKS = ("humanoid",)  # 2- and 3-dof joints that only turn
_merge_overrides(ROTARY_JOINTS_TASKS, rotary_joints=True)
POSITIONAL_JOINTS_TASKS = ("reacher", "inverted_pendulum")  # hinges and slides
_merge_overrides(POSITIONAL_JOINTS_TASKS, positional_joints=True)
PLANAR_ADJOINT_TASKS = ("inverted_pendulum", "hopper", "walker2d", "reacher")  # x-z scenes
_merge_overrides(PLANAR_ADJOINT_TASKS, planar_adjoint=True)
# reacher's gravity runs along its hinges: its planar form is differentiated without it (the
# rollout keeps it), the one rewrite whose gradient is brax's only within a tested bound.
PLANAR_NORMAL_GRAVITY_TASKS = ("reacher",)
_merge_overrides(PLANAR_NORMAL_GRAVITY_TASKS, planar_normal_gravity=True)
PLANAR_LINKS_TASKS = ("hopper", "walker2d")
_merge_overrides(PLANAR_LINKS_TASKS, planar_links=True)
SAVED_RESIDUALS_TASKS = ("ant", "humanoid")  # the spring tasks with a 3-D backward
_merge_overrides(SAVED_RESIDUALS_TASKS, saved_residuals=True)
SPATIAL_LINKS_TASKS = ("ant", "humanoid")
_merge_overrides(SPATIAL_LINKS_TASKS, spatial_links=True)

# On a GPU, ant and humanoid differentiate brax's spring substep by XLA's reverse mode
# (`hand_adjoint` off, which takes its pieces along: `MethodSpec.requires`; and
# `spatial_links` off). The hand-written VJPs cut the number of XLA operations, which is
# what an update costs on one CPU core; on one H200 they cost ant and humanoid time (ant at
# B = 360 about 1.2x slower per update with them, humanoid about 1.1x;
# `benchmarks/gpu_speed_recipe.sh`). The gradient is the same either way, so
# this is a speed choice; `--set hand_adjoint=true` on a GPU brings the pieces back.
PLATFORM_OVERRIDES: dict[str, dict[str, dict]] = {
    "gpu": {"ant": {"hand_adjoint": False, "spatial_links": False},
            "humanoid": {"hand_adjoint": False, "spatial_links": False}},
}
