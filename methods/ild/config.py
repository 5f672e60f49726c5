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
    long before `updates` (a 3-minute CPU run makes ~150-250 of the 5000); 'linear': decay
    over `updates` only, as the original intended (its schedule was dead code: the compiled
    update closed over the first optimizer), which barely decays within a CPU budget;
    'constant'. Measured (ild v4, 3 seeds, 3 min cpu, README ILD section): budget vs linear
    inverted_pendulum 0.841 0.933 0.450 vs 0.899 0.848 0.564, hopper 1.002 1.006 1.014 vs
    0.994 0.998 0.817, reacher 0.932 0.949 0.915 vs 0.945 0.947 0.925."""
    lr_warmup: int = 0
    """Updates over which the rate ramps linearly from learning_rate/lr_warmup up to the
    schedule's rate (0: none). Adam's first step moves every weight by the full rate
    whatever the gradient's size (lr x sign(g)): `python -m methods.ild.probe` measured that
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
    v1's batched state did (shared/reference), a norm up to sqrt(B) times an env's. The same
    gradient wherever nothing reaches norm 1, which is what `python -m methods.ild.probe`
    finds from the BC warm start on acrobot and hopper at B = 32 (largest norm per env 0.047
    and 0.111, over the batch 0.204 and 0.198; README ILD section, session 38)."""
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
    """Rematerialize each step in the backward pass (jax.checkpoint): less memory, more
    compute; measured by `python -m methods.ild.benchmark`."""
    substep_remat: bool = True
    """Rematerialize each physics substep inside a control step in the backward pass
    (`tasks.core.with_substep_remat`: brax's substep scan stores only each substep's input
    state and recomputes the rest next to its backward). The same function and gradient to
    float32 round-off (acrobot's bit for bit; hopper's differs by 6e-7 at B = 8), 1.21-1.51x
    faster on all brax tasks but swimmer (1.00x) with 1/2 to 1/7 of the working memory: on
    one CPU core at B = 32 an update took 0.377 s instead of 0.502 on hopper and 1.334 instead
    of 2.018 on ant (1.518 with whole-step `remat`; `python -m methods.ild.benchmark`,
    session 27). With glibc's huge-page tunable (`bench.malloc`) still 1.08-1.31x faster,
    for 1.09-1.24x (acrobot, hopper, reacher) to 1.46-1.50x (humanoid, ant) APG's env-steps/s
    against 1.02-1.22x without it (`python -m methods.ild.paired`, sessions 32-33;
    results/JOURNAL.md; swimmer 0.86x: its cost is elsewhere, `small_dots`). On by default
    since version 5 (session 33; versions 1-4 ran without it, so their records pool apart).
    Tasks without brax's substep loop (pointmass, cloth) have nothing to rematerialize: there
    it changes nothing."""
    small_dots: bool = False
    """Compute the physics step's small matrix products as multiply-and-sum in the training
    rollouts (`tasks.core.with_small_dots`): the same function and gradient to float32
    round-off, faster where XLA's CPU backend runs a step as many tiny batched products:
    swimmer's update with `substep_remat` took 0.651 s instead of 1.769 on one core at B = 32,
    while the spring tasks' and acrobot's updates gained nothing (0.91-1.04x; `python -m
    methods.ild.benchmark --rows forward,ild_substep,dots`, results/JOURNAL.md, session 29).
    Off in the class; swimmer's TASK_OVERRIDES turn it on (session 39, its cells re-run)."""
    lean_substeps: bool = False
    """In the training rollouts, every physics substep but a control step's last skips the
    joint coordinates (q, qd) that brax's spring and positional substeps recover from their
    link frames, which the next substep reads only through its actuators' bias (zero for
    motors) and the observation reads only at the step's end (`tasks.core.with_lean_substeps`).
    The same function and gradient to float32 round-off, 1.09-1.17x faster updates on the
    five spring and positional tasks with a reward gradient (one core, B = 32: hopper 0.214 s
    instead of 0.234, ant 0.775 instead of 0.909; 1.29-1.51x brax's APG instead of
    1.21-1.34x; `python -m methods.ild.paired --variant substep_remat --variant lean_substeps
    --apg-physics brax`, results/JOURNAL.md, session 40), for a longer compile (hopper's update
    70 s instead of 49). Tasks on brax's generalized backend, without brax physics, or with
    servo actuators refuse it. Off in the class; since session 41 the TASK_OVERRIDES of
    the tasks in `LEAN_SUBSTEP_TASKS` turn it on (their ILD cells re-run with it)."""
    transposed_backward: bool = True
    """The rollout's policy runs as one batched `TanhGaussianPolicy.sample_batch` per step,
    whose backward reads the kernels transposed once per update instead of transposing each
    at every step (XLA's CPU backend runs that per-step product at half speed). The same
    function and, measured here, the same loss and gradient bit for bit on pointmass and all
    8 brax tasks at B = 8, so recorded cells are unchanged; an update
    is 1.04-1.11x faster on acrobot, hopper and reacher (acrobot most: its policy is a third
    of a step's cost) and about as fast on walker2d and ant, whose physics dominate (README
    ILD speed, session 31, `python -m methods.ild.paired`). False: the policy vmapped per
    env, flax's backward."""
    swish_remat: bool = True
    """With `transposed_backward`, each of the policy's hidden activations and the product
    after it run as one `methods.common.policy.swish_dense_t`, whose backward keeps only the
    pre-activation and recomputes swish from it, instead of reverse mode's swish
    intermediates and output, which the rollout's scan stacks over every step (77% of
    hopper's update's working memory at B = 32, session 59). The same rollout and gradient
    bit for bit (tests/test_ild.py: pointmass, and the slow test's one update of each of the
    8 brax tasks), so recorded cells stand. On one core at B = 32 (session 60): the policy's
    gradient alone 1.26x faster on hopper in 14 MiB instead of 50
    (results/substep/scripts/swish_policy.py); the update 1.077x faster on hopper, 1.016x
    walker2d, 1.022x ant, 1.004x humanoid, 1.14x acrobot, 1.30x pointmass (`python -m
    methods.ild.paired --task T --variant task,swish_remat=false --variant task
    --apg-physics brax --forward`, results/swish_remat/): about 9-18 ms an update on the
    spring tasks, the policy's share. False: swish and the product apart, as before."""
    kernel_grad_group: int = 1
    """G > 1 (with `transposed_backward`): the rollout runs as T / G groups of G steps
    (`train.make_step_group`, G must divide the episode), whose backward makes each policy
    kernel's cotangent once per group, one product over G x B rows, instead of once per step
    over the batch's B rows (at B = 32 the 512 x 256 kernel's per-step product is bound by
    writing its output, 1.79x the forward's product: results/JOURNAL.md, session 57). The
    same function; its loss and gradient equal G = 1's to float32 round-off (the kernels'
    sums over steps in another order, and XLA compiles the grouped loop's physics apart:
    pointmass's loss bit for bit, tests/test_ild.py; the 8 brax tasks over 16 steps behind
    -m slow). Paired on one core at B = 32 with G = 8 (session 61, `python -m
    methods.ild.paired --task T --variant task --variant task,kernel_grad_group=8
    --apg-physics brax --forward`, results/kernel_grad_group/): the update 1.10x faster on
    acrobot and 1.08x on pointmass, whose policy is most of the update; 1.02-1.03x on hopper
    and humanoid, 0.99-1.01x on walker2d, ant and reacher. Off (1) by default: a task's
    recorded ILD cells stand until a task override turns it on and they are re-run."""
    closed_form_adjoint: bool = False
    """Differentiate the training rollouts' physics through the task's closed-form step
    (`tasks.core.with_closed_form_adjoint`; acrobot's double-pendulum equations) instead of
    brax's reverse mode: brax's step still computes every value (the same rollout bit for
    bit), and the gradient is the same to float32 round-off. Replaces `substep_remat` (the
    backward no longer reads brax's substeps). On one core at B = 32 acrobot's update took
    0.058 s instead of 0.117, 2.1x its forward rollout instead of 4.3x, 2.2x brax's APG
    (1.14x APG through the same closed-form backward; `python -m methods.ild.benchmark
    --task acrobot --rows forward,ild,closed_form,apg`, results/JOURNAL.md, session 38).
    Tasks without a closed form refuse it. Off in the class; acrobot's TASK_OVERRIDES turn
    it on (session 39: session 38's cells with it are the 10-minute grid's acrobot cells)."""
    hand_adjoint: bool = False
    """Run the training rollouts' spring substeps as `tasks.spring_adjoint.step`: brax's
    substep with the VJPs of six of its pieces (inverse inertia, joint forces and contact
    impulses moved to the links, integration, conversions to link and joint frames) written
    by hand instead of XLA's reverse mode of brax's code. The same rollout and gradient to
    float32 round-off (tests/test_hand_adjoint.py). Pieces of a hand-written adjoint of
    brax's physics, the route issue 4's update <= 3x forward needs (the physics' backward
    is 64-78% of the update: results/JOURNAL.md, sessions 46-48); paired on one core at
    B = 32 (`python -m methods.ild.paired --variant task --variant task,hand_adjoint
    --apg-physics brax`, session 48) the update ran 1.46x, 1.47x, 1.48x and 1.32x faster on
    hopper, walker2d, ant and humanoid, 1.76-2.07x brax's APG; update / forward 3.48-3.55x
    instead of 4.61-5.44x (README ILD speed); the pieces still in XLA's reverse mode could
    add at most 1.42-1.45x (session 49). On one core at the paper's batch 1.36-1.49x (session
    56); on one H200 (session 56, results/JOURNAL.md) 1.23-1.24x faster on hopper and
    walker2d at B = 360, 0.92x on humanoid, undecided on ant, and 0.71-0.99x at B = 2048: a
    CPU choice first. Tasks not on brax's spring backend refuse it.
    Off in the class; since session 50 the TASK_OVERRIDES of the tasks in
    `HAND_ADJOINT_TASKS` turn it on (their 3- and 10-minute ILD cells re-run with it)."""
    hinge_forces: bool = False
    """With `hand_adjoint`, on a scene whose 1-dof joints are all hinges (hopper, walker2d,
    ant, humanoid): their constraint forces by `tasks.spring_adjoint.hinge`, brax's
    `_one_dof` without the terms a hinge multiplies by zero and with only the one joint
    angle its limit reads. The same values, bit for bit in one call and to float32
    round-off over a rollout (XLA fuses the rest differently), in fewer operations (hopper's
    update 4% fewer): paired (`python -m methods.ild.paired --variant task --variant
    task,hinge_forces --apg-physics brax`, sessions 51-52) 1.085x faster on ant, 1.034x on
    walker2d, 1.03x on humanoid, 0.99-1.02x on hopper. Off in the class; since session 52
    the TASK_OVERRIDES of the tasks in `HINGE_FORCES_TASKS` turn it on (their 3- and
    10-minute ILD cells re-run with it); there `--set hand_adjoint=false` turns it off too
    (session 53: the method's `requires`)."""
    planar_root: bool = False
    """With `hand_adjoint`, on a scene whose 3-dof joints are all planar roots (two
    unlimited slides and one unlimited hinge: hopper's and walker2d's root): their
    constraint forces by `tasks.spring_adjoint.planar_root`, brax's `_three_dof` without
    the terms such a joint multiplies by zero (the Euler angles, the limits whose infinite
    bounds are never passed, the other rows' axes). The same values, in fewer operations
    (hopper's update 12% fewer: `results/substep/scripts/loop_ops.py`): paired (`python -m
    methods.ild.paired --variant task --variant task,planar_root --apg-physics brax`,
    session 53) 1.087x faster on hopper, 1.039x on walker2d. Off in the class; since
    session 53 the TASK_OVERRIDES of the tasks in `PLANAR_ROOT_TASKS` turn it on."""
    rotary_joints: bool = False
    """With `hand_adjoint`, on a scene whose 2- and 3-dof joints all only turn (humanoid's):
    their constraint forces by `tasks.spring_adjoint.rotary_two` and `rotary_three`, brax's
    `_two_dof` and `_three_dof` without the terms such joints multiply by zero (the slides'
    projections, forces and limits, the pins and single-axis torques). The same values, in
    fewer operations (humanoid's update 9% fewer): paired (`--variant task --variant
    task,rotary_joints`, session 53) 1.125x faster on humanoid. Off in the class; since
    session 53 the TASK_OVERRIDES of the tasks in `ROTARY_JOINTS_TASKS` turn it on."""
    saved_residuals: bool = False
    """With `hand_adjoint` and `substep_remat`: the substep checkpoint saves the residuals of
    the hand-written VJPs of `world_to_joint` and `inv_inertia` (the joint frames' rotations,
    offsets and motions; the links' rotations into their inertia frames) in the forward,
    instead of recomputing them next to the backward
    (`tasks.spring_adjoint.SAVED_RESIDUALS`). XLA's CPU backend fuses the recomputed
    quaternion and cross products into the VJPs' loops, which evaluate them again per
    output entry: ant's costliest physics fusion, a world_to_joint VJP loop, ran at 4-7x
    the time per instruction and element of the plain loops (session 73). The same
    function, the values saved rather than computed again, but another float32 program
    (ant's loss 2.402289 -> 2.402243 after two updates). Paired on one core at B = 32
    (`python -m methods.ild.paired --task T --variant task --variant task,saved_residuals
    --apg-physics none --forward`, session 73, results/saved_residuals/): the update 1.120x
    faster on ant, update / forward 3.20x -> 2.87x (every round 2.78-2.94x), and 1.125x on
    humanoid, 3.40x -> 3.02x (rounds 2.77-3.45x). Without `substep_remat` every residual is
    saved anyway. Off in the class; since session 74 the TASK_OVERRIDES of the tasks in
    `SAVED_RESIDUALS_TASKS` (ant, humanoid) turn it on (their 3- and 10-minute ILD cells
    re-run with it); there `--set hand_adjoint=false` turns it off too."""
    positional_joints: bool = False
    """On brax's positional backend, for a scene whose joints are hinges and slides
    (reacher, inverted_pendulum): each substep by `tasks.positional_joints.step`, brax's
    positional substep with the joints' position-level update written for those kinds
    alone (brax's treats every joint as a 3-dof one: three signed angles, clips, rotations
    and Euler angles, where a hinge has one free angle and a slide none), the joints'
    forces vectorized over the dofs, and the conversions to link and joint frames and the
    inverse inertia by `tasks.spring_adjoint`'s hand-written VJPs. The same function and
    gradient to float32 round-off (tests/test_positional_joints.py), in fewer operations.
    Paired on one core at B = 32 (`python -m methods.ild.paired --task T --variant task
    --variant task,positional_joints --apg-physics brax --forward`, inverted_pendulum with
    `--apg-physics none`; session 62, results/positional_joints/): the update 1.61x faster
    on reacher (update / forward 5.08x -> 3.15x, 3.03x in a second run; 2.19x brax's APG,
    1.40x without it) and
    1.68x on inverted_pendulum (5.93x -> 3.53x). Off in the class; since session 63 the
    TASK_OVERRIDES of the tasks in `POSITIONAL_JOINTS_TASKS` turn it on (their 3- and
    10-minute ILD cells re-run with it). Tasks on other backends, or with other joints,
    refuse it."""
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
    rollout and gradient to float32 round-off (tests/test_planar_links.py); the update
    1.17x (hopper) and 1.47x (walker2d) faster, paired (session 70). Off in the class;
    `PLANAR_LINKS_TASKS` turn it on. Needs `planar_adjoint`; positional tasks refuse it."""
    spatial_links: bool = False
    """On brax's spring backend, for a scene of a free root and joints that only turn
    (hinges, 2- and 3-dof joints) with contacts against a plane (ant, humanoid): the
    training rollouts' control step runs the task's own physics (with `lean_substeps` and
    `hand_adjoint` as set; `substep_remat` has nothing left to act on) and, in reverse
    mode, the VJP of brax's spring step written with every entry of every
    vector an array over the links (`tasks.spatial_links.control_step`;
    `tasks.core.with_spatial_adjoint`), in place of reverse mode through brax's arrays of
    3- and 4-vectors. The same rollout, and the same gradient to float32 round-off
    (tests/test_spatial_links.py); ant's update 1.41x faster, paired (session 76),
    humanoid's 1.14-1.21x (session 77). Tasks with joints that slide, roots that are not free,
    or other backends refuse it. Off in the class; `SPATIAL_LINKS_TASKS` turn it on, and on
    a GPU `PLATFORM_OVERRIDES` off."""
    planar_normal_gravity: bool = False
    """With `planar_adjoint` on the positional backend: a scene whose gravity is along the
    normal of the plane its hinges turn in (reacher's, along its hinges) is differentiated
    as that scene without gravity (`tasks.planar.planar_scene(drop_normal_gravity=True)`;
    the rollout keeps brax's gravity). Without it planar_adjoint refuses such a scene. The
    VJP at reacher's rollout states is within 6e-5 of each leaf's largest entry of the
    trained step's (session 71). Off in the class; `PLANAR_NORMAL_GRAVITY_TASKS` (reacher)
    turn it on: its update 1.72x faster, update / forward 3.55x -> 2.00x (session 72; in
    session 71, before `tasks.planar._through_arrays`, it was 5.4x slower). Needs
    `planar_adjoint`."""
    chunk: int = 1
    """Updates per jitted call between reports and budget checks (1: metrics every update).
    K > 1 pays XLA's per-call costs once per K updates (1.10-1.43x faster per update without
    remat; ~4% on ant, which rematerializes and so avoids most of them: results/JOURNAL.md);
    each call runs only the updates the budget has left, so it never overruns it."""
    joint_limits: bool = True
    """False: the training rollouts run on a copy of the task without its joint-range
    constraints (`tasks.core.without_joint_limits`), a smooth surrogate where brax solves
    limits like contacts and the loss through them is rough (swimmer, README ILD section).
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
    # Sized so updates are frequent on 2 CPU cores: ~0.7 s per update of B=32 on hopper
    # (spring), so a 10-minute budget buys several hundred updates.
    "cpu": {"num_envs": 32},
}

TASK_OVERRIDES: dict[str, dict] = {
    # inverted_pendulum: full BPTT. The pole is unstable, and the terms a truncated window
    # drops (how a push now tips the pole later) outweigh and oppose those it keeps: from the
    # BC warm start the truncated gradient's cosine with the true one is -0.992 at truncation
    # 10 and -0.993 at 1, 1.000 at 128 (`python -m methods.ild.probe --task
    # inverted_pendulum --num-envs 32 --truncation W`, session 9). Those cosines move with
    # round-off in the BC warm start (session 36, B = 16: 0.869 vs 0.999 on one CPU thread,
    # 0.316 vs 0.781 on two); 128 stayed the closer. The runs are the firmer reason: with
    # truncation 10 ILD climbed its own loss (0.05 -> 1-3) and fell from 1.00 to 0.841, 0.933,
    # 0.450 (grid, 3 min cpu); with 128 the loss falls (0.051 -> 0.024) and the score stays
    # 1.000 (README ILD section). test_truncated_bptt_climbs_inverted_pendulums_loss_and_
    # full_bptt_descends_it trains 40 updates of each from one warm start (B = 16): the loss
    # climbs 0.0105 -> ~3.4 at truncation 10 and settles at ~0.02 at 128 (session 37).
    "inverted_pendulum": {"truncation": 128},
    # acrobot: full BPTT too. From the BC warm start the truncation-10 gradient's cosine with
    # the true one is -0.389 and Adam's first step along it raises the loss (lr 1e-3: 2.00x),
    # at 128 the cosine is 1.000 (`python -m methods.ild.probe --task acrobot --num-envs 32
    # --truncation W`, session 11): a swing-up's early torques pay off many steps later.
    #
    # acrobot also differentiates its physics through its closed-form step (session 39): the
    # same rollout bit for bit and the same gradient to float32 round-off as brax's reverse
    # mode, in half the time (one core, B = 32: 0.058 s per update instead of 0.117, 2.1x
    # its forward rollout, 2.2x brax's APG; results/JOURNAL.md, session 38). The session-38
    # cells with it scored as the reverse-mode cells seed by seed (0.850 / 0.893 / 0.838)
    # with 5,000 updates in 299-305 s instead of 554-574; they are the grid's acrobot cells.
    "acrobot": {"truncation": 128, "closed_form_adjoint": True},
    # swimmer (session 13) has no truncation override: truncation-10's cosine with the true
    # gradient is 0.505 (0.802 at 128), but from the BC warm start every Adam first step at
    # lr >= 1e-4 raises the loss (1.8-4x) along either gradient, and central differences
    # disagree with the analytic derivative at every eps: a rough loss, not a truncation
    # effect (README).
    # Its override is speed: swimmer's step is many tiny batched products (3 links, fluid,
    # joint limits), which `small_dots` computes as multiply-and-sum: the same function and
    # gradient to float32 round-off, an update of 0.464 s instead of 1.314 on one core at
    # B = 32, 1.29x APG on the same rewritten physics where the default was 0.84x brax's
    # (`python -m methods.ild.paired`, session 37). Session 39 re-ran its cells with it.
    "swimmer": {"small_dots": True},
    # The original's cloth setting: 10 parallel rollouts (one update of 10 x 80 steps costs
    # ~4 s on one CPU core: 50 substeps per step) and Adam lr 1e-4. A preset wins over these
    # (the cpu preset sets num_envs 32): cloth runs pass --set num_envs=10.
    "cloth": {"num_envs": 10, "learning_rate": 1e-4},
    # ant ran with whole-step `remat` in versions 1-4 (1.34x faster than none: its per-step
    # residuals are 811 MiB per update, mapped afresh on every call; session 18). Since
    # version 5 every brax task rematerializes each substep by default, which is faster still
    # on ant (1.334 vs 1.518 s per update; 125-128 vs 105-114 updates in 3-minute cells,
    # session 27) in 123 MiB, so ant has no remat override.
}

# Lean substeps (session 41) on the spring and positional tasks: the same rollout and
# gradient to float32 round-off (tests/test_lean_substeps.py), with the inverse kinematics
# of every substep but a control step's last dropped; one core, B = 32, paired against
# brax's APG as shipped (session 40, results/lean/paired_lean_*.csv): updates 1.09-1.17x
# faster (hopper 0.234 -> 0.214 s, walker2d 0.375 -> 0.337, ant 0.909 -> 0.775, humanoid
# 1.197 -> 1.074, reacher 0.336 -> 0.305), 1.29-1.51x APG instead of 1.21-1.34x;
# inverted_pendulum 0.251 -> 0.228 s (benchmark). Session 41 re-ran these tasks' 3- and
# 10-minute ILD cells with it (results/JOURNAL.md). Merged into the entries above.
LEAN_SUBSTEP_TASKS = ("hopper", "walker2d", "ant", "humanoid", "reacher", "inverted_pendulum")


def _merge_overrides(names: tuple[str, ...], **fields) -> None:
    """Add `fields` to each named task's TASK_OVERRIDES entry (merged, not replaced)."""
    for name in names:
        TASK_OVERRIDES[name] = {**TASK_OVERRIDES.get(name, {}), **fields}


_merge_overrides(LEAN_SUBSTEP_TASKS, lean_substeps=True)

# Hand-written VJPs of brax's spring substep (session 50) on the four spring tasks: the same
# rollout and gradient to float32 round-off (tests/test_hand_adjoint.py); one core, B = 32,
# paired against the same lean update through XLA's reverse mode (session 48,
# results/hand_adjoint/paired_session48_*.csv): updates 1.46x (hopper), 1.47x (walker2d),
# 1.48x (ant) and 1.32x (humanoid) faster, 1.76-2.07x brax's APG. Session 50 re-ran these
# tasks' 3- and 10-minute ILD cells with it (results/JOURNAL.md). Not yet timed on a GPU
# (results/gpu/speed_recipe.sh's ild_hand row).
HAND_ADJOINT_TASKS = ("hopper", "walker2d", "ant", "humanoid")
_merge_overrides(HAND_ADJOINT_TASKS, hand_adjoint=True)

# Hinge-only joint forces (session 51) on the spring tasks whose 1-dof joints are all hinges
# (every one with hand_adjoint): the same values bit for bit in one call, to float32
# round-off over a rollout (tests/test_hand_adjoint.py); one core, B = 32, paired against
# the same update with brax's `_one_dof` (results/hand_adjoint/paired_session5[12]_*_hinges*
# .csv): ant 1.085x, walker2d 1.034x, hopper 0.99-1.02x, humanoid 1.03x (rounds 0.92-1.16x).
# Session 52 re-ran these tasks' 3- and 10-minute ILD cells with it (results/JOURNAL.md).
HINGE_FORCES_TASKS = HAND_ADJOINT_TASKS
_merge_overrides(HINGE_FORCES_TASKS, hinge_forces=True)

# The multi-dof joints' forces for the scene's kinds alone (session 53): hopper's and
# walker2d's planar root (two unlimited slides and a hinge), humanoid's 2- and 3-dof joints
# that only turn. The same values bit for bit in one call (tests/test_hand_adjoint.py), in
# 12% (hopper, walker2d) and 9% (humanoid) fewer operations per update (python
# results/substep/scripts/loop_ops.py T --variant task --variant task,planar_root); one core,
# B = 32, paired against the same update with brax's functions
# (results/hand_adjoint/paired_session53_*.csv): hopper 1.087x, walker2d 1.039x, humanoid
# 1.125x. Session 53 re-ran these tasks' 3- and 10-minute ILD cells with them.
PLANAR_ROOT_TASKS = ("hopper", "walker2d")
_merge_overrides(PLANAR_ROOT_TASKS, planar_root=True)
ROTARY_JOINTS_TASKS = ("humanoid",)
_merge_overrides(ROTARY_JOINTS_TASKS, rotary_joints=True)

# The positional substep with the joints' update written for hinges and slides and the
# shared pieces' hand-written VJPs (session 62) on the two positional tasks: the same rollout
# and gradient to float32 round-off (tests/test_positional_joints.py); one core, B = 32,
# paired against the same lean update through brax's positional step
# (results/positional_joints/paired_session62_*.csv): updates 1.61x (reacher) and 1.68x
# (inverted_pendulum) faster, update / forward 3.03-3.15x and 3.53x instead of 5.08x and
# 5.93x. Session 63 re-ran these tasks' 3- and 10-minute ILD cells with it.
POSITIONAL_JOINTS_TASKS = ("reacher", "inverted_pendulum")
_merge_overrides(POSITIONAL_JOINTS_TASKS, positional_joints=True)

# The positional step's backward through its planar form (session 66) on the positional task
# whose scene moves in the x-z plane: the same rollout, its gradient the same to float32
# round-off where the per-step normalization clips nothing (tests/test_planar.py); one core,
# B = 32, paired against the same update with positional_joints' backward
# (results/planar/paired_session66_*.csv): 1.33x faster with the huge-page tunable, 1.40x
# without; a 3-minute cell (seed 0) made 936 updates instead of 753. Session 66 re-ran its
# 3- and 10-minute ILD cells with it. Session 69 added the spring step's planar form
# (`tasks.planar_spring`, written in session 67 and left out then as no faster) for hopper
# and walker2d, whose forward stays hand_adjoint's: with the planar cotangents stacked rather
# than padded (`tasks.planar._rows`), paired against the same update with hand_adjoint's
# backward (results/planar_spring/paired_session69_*.csv), hopper's update 1.45x faster,
# update / forward 3.25x -> 2.18x. Their 3- and 10-minute ILD cells were recorded before it.
# Session 72 added reacher, whose gravity runs along its hinges: its planar form leaves that
# gravity out (`planar_normal_gravity`; the rollout keeps it), its VJP within 6.3e-5 of each
# leaf's largest entry of the trained step's at the rollout's states (session 71), and since
# `tasks.planar._through_arrays` (session 72) its update 1.72x faster, paired against
# positional_joints' backward (results/planar_reacher/paired_session72_reacher.csv), update
# / forward 3.55x -> 2.00x.
PLANAR_ADJOINT_TASKS = ("inverted_pendulum", "hopper", "walker2d", "reacher")
_merge_overrides(PLANAR_ADJOINT_TASKS, planar_adjoint=True)
PLANAR_NORMAL_GRAVITY_TASKS = ("reacher",)
_merge_overrides(PLANAR_NORMAL_GRAVITY_TASKS, planar_normal_gravity=True)

# The planar spring step with every link at once (session 70, `tasks.planar_links`): the same
# rollout, its gradient the same to float32 round-off (tests/test_planar_links.py); one core,
# B = 32, paired against the same update with the per-link planar step
# (results/planar_links/paired_session70_*.csv): updates 1.47x (walker2d) and 1.17x (hopper)
# faster, update / forward 2.84x -> 1.88x and 2.30x -> 1.98x. Session 70 re-ran their 3- and
# 10-minute ILD cells with it.
PLANAR_LINKS_TASKS = ("hopper", "walker2d")
_merge_overrides(PLANAR_LINKS_TASKS, planar_links=True)

# The substep checkpoint saving world_to_joint's and inv_inertia's VJP residuals (session 73)
# on the two spring tasks that still run hand_adjoint's full 3-D backward: the same step and
# gradient to float32 round-off (tests/test_hand_adjoint.py); one core, B = 32, paired
# against the same update recomputing them (results/saved_residuals/paired_session73_*.csv):
# ant 1.120x, humanoid 1.125x faster, update / forward 3.20x -> 2.87x and 3.40x -> 3.02x;
# paired with brax's APG between the rounds (results/saved_residuals/paired_session74_*.csv)
# ant 1.03x, humanoid 1.13x, update / forward 3.39x -> 3.26x and 3.35x -> 2.98x. Session 74
# re-ran their 3- and 10-minute ILD cells with it.
SAVED_RESIDUALS_TASKS = ("ant", "humanoid")
_merge_overrides(SAVED_RESIDUALS_TASKS, saved_residuals=True)

# ant's spring step with every link at once in 3-D (session 76, `tasks.spatial_links`), its
# substeps a scan of one checkpointed substep: the same rollout, its gradient the same to
# float32 round-off (tests/test_spatial_links.py: 1.25e-5 of each leaf's largest entry over
# 16 steps, measured on its first, unrolled form); one core, B = 32, paired against the
# same update with hand_adjoint's backward
# (results/spatial_links/paired_session76_scan_ant.csv): 1.41x faster, update / forward
# 3.22x -> 2.19x (every round under 3x). Humanoid's since session 77, its 2- and 3-dof
# joints written the same way (`tasks.spatial_links.Rotary`): paired the same way
# (results/spatial_links/paired_session77_humanoid*.csv, three runs) 1.14-1.21x faster,
# update / forward 3.52x -> 3.02x, 3.20x -> 2.67x and 3.20x -> 2.71x (session 78, a fourth
# run: 3.19x -> 2.69x). ant's and humanoid's 3- and 10-minute ILD cells were re-run with it
# in session 78.
# Not timed on a GPU, where both train through XLA's reverse mode (PLATFORM_OVERRIDES below
# turn it off there).
SPATIAL_LINKS_TASKS = ("ant", "humanoid")
_merge_overrides(SPATIAL_LINKS_TASKS, spatial_links=True)

# On a GPU, ant and humanoid differentiate brax's spring substep by XLA's reverse mode
# (`hand_adjoint` off, which takes its pieces `hinge_forces`, `saved_residuals` and
# `rotary_joints` along: `MethodSpec.requires`). The hand-written VJPs were tuned on one CPU
# core, where an update's time is mostly its number of XLA operations and they gain there
# at every batch (1.47x on ant at B = 360, session 56); on one H200 they cost ant and humanoid
# time (results/gpu/speed_session75/speed.csv, each timed section alone on the GPU, one
# timing of 3 updates each): ant at B = 360 0.5383 / 0.5238 s per update with them (two
# calls) against 0.4667 / 0.4105 s without, humanoid 0.6089 s against 0.5639 s, ant at
# B = 32 0.4457 s against 0.3849 s; session 56 saw humanoid's 8% the same way in two calls
# (ant's flipped there). The gradient is the same to float32 round-off either way, so this is
# a speed choice; `--set hand_adjoint=true` on a GPU brings the pieces back. ant's and
# humanoid's `spatial_links` (sessions 76-77, CPU-measured) are off there too.
PLATFORM_OVERRIDES: dict[str, dict[str, dict]] = {
    "gpu": {"ant": {"hand_adjoint": False, "spatial_links": False},
            "humanoid": {"hand_adjoint": False, "spatial_links": False}},
}
