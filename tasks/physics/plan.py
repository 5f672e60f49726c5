"""The physics plan: which exact-equivalent rewrites of brax's step a task's differentiable
physics runs, per platform.

Every rewrite computes the same function as brax's step through XLA's reverse mode, with
the same gradient to float32 round-off (each module's docstring names the test that shows
it; docs/physics.md has the table and the speed each buys). So a plan changes what a
gradient costs, never what it is; but a whole-step backward hands a state's cotangent back
on fewer fields than brax's reverse mode, which a method that rescales that cotangent field
by field sees (ILD's per-step gradient normalization: docs/physics.md). The runner hands a
method that declares `sim_gradients` the task with its plan applied (`bench.access.TaskView`);
the evaluator, and every method that does not differentiate through the physics, step the task
itself. `--physics reference` runs the plain brax step (`REFERENCE`) instead, for comparison.

This module imports no JAX: `ildbench tasks` lists the plans from it. `apply` builds the
rewritten task (`tasks.physics.transforms`).
"""
from __future__ import annotations

import dataclasses

PLATFORMS = ("cpu", "gpu")
CHOICES = ("task", "reference")
"""`--physics`: the task's plan on this platform, or plain brax (`REFERENCE`)."""

HAND_ADJOINT_PIECES = ("hinge_forces", "planar_root", "rotary_joints", "saved_residuals")
"""Rewrites that are pieces of `hand_adjoint`'s spring substep: each needs it on."""
_WHOLE_STEP = ("closed_form_adjoint", "planar_adjoint", "spatial_links")
"""Rewrites that differentiate the whole control step in another form."""


@dataclasses.dataclass(frozen=True)
class Plan:
    """A set of rewrites of a task's differentiable physics step. The defaults are brax's
    step with each substep rematerialized in the backward (`substep_remat`, which has
    nothing to act on where a task has no brax substep loop); `REFERENCE` is brax's step
    as it is. A field that a task's scene does not fit is refused when the plan is applied
    (`apply`), naming the task and the rewrite."""

    substep_remat: bool = True
    """Each physics substep rematerialized in the backward pass
    (`transforms.with_substep_remat`): brax's substep scan stores only each substep's input
    state and recomputes the rest next to its backward; less memory, fewer page faults."""
    small_dots: bool = False
    """The step's small matrix products as multiply-and-sum (`small_dots`): faster where
    XLA's CPU backend runs a step as many tiny batched products (swimmer)."""
    lean_substeps: bool = False
    """Every substep but a control step's last skips the joint coordinates (q, qd) that
    brax's spring and positional substeps recover from their link frames, which the next
    substep reads only through its actuators' bias, zero for motors
    (`transforms.with_lean_substeps`)."""
    closed_form_adjoint: bool = False
    """The backward of the task's closed-form step (`closed_form_step`: acrobot's double
    pendulum) in place of brax's; the forward is brax's, bit for bit
    (`transforms.with_closed_form_adjoint`)."""
    hand_adjoint: bool = False
    """brax's spring substep with the VJPs of six of its pieces written by hand
    (`spring_adjoint.step`): fewer XLA operations, which is what an update costs on one CPU
    core."""
    hinge_forces: bool = False
    """With `hand_adjoint`: 1-dof joints' forces for hinges only (`spring_adjoint.hinge`)."""
    planar_root: bool = False
    """With `hand_adjoint`: 3-dof planar roots' forces (`spring_adjoint.planar_root`)."""
    rotary_joints: bool = False
    """With `hand_adjoint`: 2- and 3-dof joints that only turn
    (`spring_adjoint.rotary_two`, `rotary_three`)."""
    saved_residuals: bool = False
    """With `hand_adjoint` and `substep_remat`: the substep checkpoint saves the
    hand-written VJPs' residuals (`spring_adjoint.SAVED_RESIDUALS`) instead of recomputing
    them (another float32 program: a loss after two updates differs in the 5th digit)."""
    positional_joints: bool = False
    """brax's positional substep with the joints' update written for hinges and slides
    (`positional_joints.step`)."""
    planar_adjoint: bool = False
    """The backward of brax's step written over the plane the scene moves in (`planar`,
    `planar_spring`; `transforms.with_planar_adjoint`)."""
    planar_links: bool = False
    """With `planar_adjoint` on the spring backend: the planar step with every link at once
    (`planar_links`)."""
    spatial_links: bool = False
    """The backward of brax's spring step with every entry an array over the links, in 3-D
    (`spatial_links`; `transforms.with_spatial_adjoint`)."""
    planar_normal_gravity: bool = False
    """With `planar_adjoint` on the positional backend: a scene whose gravity is along the
    normal of its plane (reacher's) is differentiated without that gravity; the rollout
    keeps it. The one rewrite whose gradient is brax's only within a tested bound (6e-5 of
    each leaf's largest entry at reacher's rollout states: tests/test_planar.py)."""

    def __post_init__(self):
        checks = [
            (not (self.closed_form_adjoint and (self.small_dots or self.lean_substeps
                                                or self.hand_adjoint)),
             "closed_form_adjoint differentiates the closed-form step; small_dots, "
             "lean_substeps and hand_adjoint rewrite brax's: set one of them False"),
            *((self.hand_adjoint or not getattr(self, piece),
               f"{piece} is a piece of hand_adjoint's spring substep; set hand_adjoint True "
               f"or {piece} False") for piece in HAND_ADJOINT_PIECES),
            (not (self.positional_joints and (self.hand_adjoint or self.closed_form_adjoint)),
             "positional_joints rewrites brax's positional substep, hand_adjoint the spring "
             "one and closed_form_adjoint the whole step; set positional_joints False"),
            (sum(getattr(self, f) for f in _WHOLE_STEP) <= 1,
             f"{', '.join(_WHOLE_STEP)} each differentiate the whole step in another form; "
             "set all but one of them False"),
            (not ((self.planar_adjoint or self.spatial_links) and self.small_dots),
             "planar_adjoint and spatial_links differentiate the whole step, small_dots "
             "rewrites brax's products: set one of them False"),
            (self.planar_adjoint or not self.planar_links,
             "planar_links writes planar_adjoint's spring step over the links; set "
             "planar_adjoint True or planar_links False"),
            (self.planar_adjoint or not self.planar_normal_gravity,
             "planar_normal_gravity says how planar_adjoint models gravity off the plane; set "
             "planar_adjoint True or planar_normal_gravity False"),
        ]
        for ok, msg in checks:
            if not ok:
                raise ValueError(msg)

    @property
    def rewrites(self) -> tuple[str, ...]:
        """The rewrites this plan turns on, in field order."""
        return tuple(f.name for f in dataclasses.fields(self) if getattr(self, f.name))

    def identity(self) -> dict[str, bool]:
        """The fields that differ from `Plan()`: how the plan enters a run's id (beside the
        method's config identity, under the same names)."""
        base = Plan()
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)
                if getattr(self, f.name) != getattr(base, f.name)}

    def acting(self, substep_loop: bool = True) -> tuple[str, ...]:
        """The rewrites that act on a task (`substep_loop`: whether it steps through brax's
        substep loop): `substep_remat` has nothing to rematerialize without that loop, or
        where a whole-step backward never reads brax's substeps."""
        drop = not substep_loop or any(getattr(self, f) for f in _WHOLE_STEP)
        return tuple(r for r in self.rewrites if not (r == "substep_remat" and drop))

    def describe(self, substep_loop: bool = True) -> str:
        return ", ".join(self.acting(substep_loop)) or "none: the step as it is"


FIELDS = tuple(f.name for f in dataclasses.fields(Plan))
REFERENCE = Plan(substep_remat=False)
"""brax's step as it is, differentiated by XLA's reverse mode."""

_SPRING_PLANAR = Plan(lean_substeps=True, hand_adjoint=True, hinge_forces=True,
                      planar_root=True, planar_adjoint=True, planar_links=True)

# fmt: off
PLANS: dict[str, dict[str, Plan]] = {
    # task: {platform: plan}. A task absent here, or a platform absent for it, runs Plan().
    "inverted_pendulum": {"cpu": Plan(lean_substeps=True, positional_joints=True,
                                      planar_adjoint=True)},
    "reacher": {"cpu": Plan(lean_substeps=True, positional_joints=True, planar_adjoint=True,
                            planar_normal_gravity=True)},
    "acrobot": {"cpu": Plan(closed_form_adjoint=True)},
    "swimmer": {"cpu": Plan(small_dots=True)},
    "hopper": {"cpu": _SPRING_PLANAR},
    "walker2d": {"cpu": _SPRING_PLANAR},
    # On a GPU, ant and humanoid differentiate brax's spring substep by XLA's reverse mode:
    # the hand-written VJPs cut the number of XLA operations, which is what an update costs
    # on one CPU core; on one H200 they cost time (ant at 360 rollouts about 1.2x slower per
    # update with them, humanoid about 1.1x; benchmarks/gpu_speed_recipe.sh).
    "ant": {"cpu": Plan(lean_substeps=True, hand_adjoint=True, hinge_forces=True,
                        saved_residuals=True, spatial_links=True),
            "gpu": Plan(lean_substeps=True)},
    "humanoid": {"cpu": Plan(lean_substeps=True, hand_adjoint=True, hinge_forces=True,
                             rotary_joints=True, saved_residuals=True, spatial_links=True),
                 "gpu": Plan(lean_substeps=True)},
}
# fmt: on


def plan_for(task: str, platform: str) -> Plan:
    """The plan of task `task` on `platform` ('cpu', 'gpu'; a TPU runs the GPU's plan): what
    its row in `PLANS` says; the CPU's where the row names no GPU plan; `Plan()` for a task
    without a row."""
    row = PLANS.get(task, {})
    platform = "gpu" if platform == "tpu" else platform
    return row.get(platform, row.get("cpu", Plan()))


def choose(task: str, choice: str, platform: str) -> Plan:
    """The plan `--physics choice` means for `task` on `platform`."""
    if choice not in CHOICES:
        raise ValueError(f"unknown physics choice {choice!r}; choose one of "
                         f"{', '.join(CHOICES)} (task: the task's plan, docs/physics.md; "
                         "reference: brax's step as it is)")
    return plan_for(task, platform) if choice == "task" else REFERENCE


def apply(task, plan: Plan):
    """`task` (a `tasks.core.Task`) with `plan`'s rewrites, in the order they compose: a
    rebuilt substep loop (hand-written spring or positional substeps, lean, rematerialized),
    small products as sums, then a whole-step backward (closed form, planar, spatial).
    Raises ValueError naming the task and the rewrite where the scene does not fit one."""
    from tasks.core import has_substep_loop
    import tasks.physics.transforms as tr
    if plan.closed_form_adjoint:  # its backward never reads brax's substeps
        return tr.with_closed_form_adjoint(task)
    # the planar and spatial backwards never read brax's substeps: nothing to checkpoint
    remat = plan.substep_remat and not (plan.planar_adjoint or plan.spatial_links)
    if plan.hand_adjoint:
        task = tr.with_hand_adjoint(task, remat=remat, lean=plan.lean_substeps,
                                    hinges=plan.hinge_forces, planar=plan.planar_root,
                                    rotary=plan.rotary_joints,
                                    saved_residuals=plan.saved_residuals)
    elif plan.positional_joints:
        task = tr.with_positional_joints(task, remat=remat, lean=plan.lean_substeps)
    elif plan.lean_substeps:
        task = tr.with_lean_substeps(task, remat=remat)
    elif remat and has_substep_loop(task):
        task = tr.with_substep_remat(task)
    if plan.small_dots:
        task = tr.with_small_dots(task)
    if plan.planar_adjoint:
        task = tr.with_planar_adjoint(task, links=plan.planar_links,
                                      drop_normal_gravity=plan.planar_normal_gravity)
    if plan.spatial_links:
        task = tr.with_spatial_adjoint(task)
    return task
