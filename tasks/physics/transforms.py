"""How each physics rewrite is applied to a task: `with_<rewrite>(task)` builds a fresh copy of
a brax task whose control step runs the rewrite (the same function, and the same gradient to
float32 round-off, as brax's step through XLA's reverse mode), and `<rewrite>_refusal(task)`
says why a task's scene does not fit it. The rewrites' own mathematics lives in the sibling
modules (`spring_adjoint`, `positional_joints`, `planar`, `planar_spring`, `planar_links`,
`spatial_links`, `small_dots`); which of them a task uses is its plan (`tasks.physics.plan`).
"""
from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from tasks.core import Task, _like, build_env, has_substep_loop


def with_substep_remat(task: Task) -> Task:
    """A fresh copy of brax task `task` (same `sys`, so a `without_joint_limits` copy stays
    one) whose physics step rematerializes each of its `n_frames` substeps in the backward
    pass: brax's `PipelineEnv.pipeline_step` scans the substeps and reverse mode stacks every
    substep's intermediate values into per-substep buffers (hundreds of arrays, one copy each
    per substep); checkpointed, a substep stores only its input state and recomputes the
    rest next to its backward. The same function and gradient (to float32 round-off: tested);
    what it buys is measured by `python -m benchmarks.ild_speed`. The
    registry's cached task is left as it is. Errors for a task with no brax substep loop."""
    return _rebuilt_substep_loop(task, remat=True, lean=False, option="substep_remat")


LEAN_BACKENDS = ("spring", "positional")
"""brax's maximal-coordinate pipelines: each substep ends by recovering joint coordinates
(`kinematics.inverse`) from the link frames it integrated, q and qd that the next substep reads
only in its actuator bias (`actuator.to_tau`)."""


def lean_substeps_refusal(task: Task) -> str | None:
    """Why `with_lean_substeps` cannot rewrite `task` (None where it can): it needs a brax
    spring or positional step whose actuators have no position or velocity bias (motors: the
    substeps' q and qd then reach nothing but `q * 0` and `qd * 0`)."""
    backend = getattr(task.spec, "backend", None)
    if not has_substep_loop(task) or backend not in LEAN_BACKENDS:
        return (f"task {task.name!r} steps {backend or 'its own'!s} physics; lean_substeps is "
                f"for brax's {' and '.join(LEAN_BACKENDS)} backends, whose substeps recompute "
                "joint coordinates (generalized ones integrate them): leave it False")
    act = task.env.unwrapped.sys.actuator
    if np.any(np.asarray(act.bias_q)) or np.any(np.asarray(act.bias_qd)):
        return (f"task {task.name!r} has actuators that read joint positions or velocities "
                "(non-zero bias_q / bias_qd: position or velocity servos), so every substep "
                "needs its q and qd: leave lean_substeps False")
    return None


def with_lean_substeps(task: Task, remat: bool = True) -> Task:
    """A fresh copy of brax task `task` whose control step skips what only the observation
    reads: brax's spring and positional substeps each end by recovering joint coordinates q,
    qd from the link frames (`kinematics.inverse`), and the next substep reads them only as
    `bias_q * q + bias_qd * qd` in its actuator forces, zero for motors. Here every substep
    but the last carries the control step's incoming q and qd instead, so XLA drops the
    inverse kinematics of the first `n_frames - 1` substeps, forward and backward; the last
    substep computes q and qd as brax does. The same function and gradient to float32
    round-off (tested; the forces are the same numbers, the fusions around them differ).
    `remat`: each substep checkpointed, as `with_substep_remat`. Errors for a task it does
    not fit (`lean_substeps_refusal`)."""
    why = lean_substeps_refusal(task)
    if why is not None:
        raise ValueError(why)
    return _rebuilt_substep_loop(task, remat=remat, lean=True, option="lean_substeps")


def hand_adjoint_refusal(task: Task) -> str | None:
    """Why `with_hand_adjoint` cannot rewrite `task` (None where it can): its hand-written
    VJPs are of brax's spring substep (`tasks.physics.spring_adjoint`)."""
    backend = getattr(task.spec, "backend", None)
    if backend != "spring":
        return (f"task {task.name!r} runs {backend!r} physics; hand_adjoint writes the VJP of "
                "brax's spring substep (hopper, walker2d, ant, humanoid); leave it False")
    return None


def with_hand_adjoint(task: Task, remat: bool = True, lean: bool = False,
                      hinges: bool = False, planar: bool = False,
                      rotary: bool = False, saved_residuals: bool = False) -> Task:
    """A fresh copy of brax spring task `task` whose substeps run
    `tasks.physics.spring_adjoint.step`: brax's spring substep with six pieces' VJPs written by
    hand (the same values and gradient to float32 round-off: tests/test_hand_adjoint.py).
    `remat` and `lean` as `with_substep_remat` and `with_lean_substeps`; `hinges`: its 1-dof
    joints' forces by `tasks.physics.spring_adjoint.hinge` (a scene whose 1-dof joints are all
    hinges); `planar`: its 3-dof joints' forces by `tasks.physics.spring_adjoint.planar_root`
    (a scene whose 3-dof joints are all planar roots); `rotary`: its 2- and 3-dof joints' forces by
    `tasks.physics.spring_adjoint.rotary_two` and `rotary_three` (a scene whose 2- and 3-dof joints
    only turn); `saved_residuals` (with `remat`): the substep checkpoint saves the residuals
    of `world_to_joint`'s and `inv_inertia`'s VJPs (`tasks.physics.spring_adjoint.SAVED_RESIDUALS`)
    instead of recomputing them (without `remat` every residual is saved anyway). Errors
    for a task it does not fit."""
    why = hand_adjoint_refusal(task)
    if why is None and lean:
        why = lean_substeps_refusal(task)
    if why is None and hinges:
        from tasks.physics.spring_adjoint import only_hinges
        if not only_hinges(task.env.unwrapped.sys):
            why = (f"task {task.name!r} has 1-dof joints that slide; hinge_forces models "
                   "hinges only: leave it False")
    if why is None and planar:
        from tasks.physics.spring_adjoint import planar_roots
        if planar_roots(task.env.unwrapped.sys) is None:
            why = (f"task {task.name!r} has no planar root (3-dof joints that are two "
                   "unlimited slides and an unlimited hinge, as hopper's); planar_root "
                   "models those only: leave it False")
    if why is None and rotary:
        from tasks.physics.spring_adjoint import rotary_joints
        if not rotary_joints(task.env.unwrapped.sys):
            why = (f"task {task.name!r} has no 2- or 3-dof joints, or some that slide; "
                   "rotary_joints models joints that only turn: leave it False")
    if why is not None:
        raise ValueError(why)
    return _rebuilt_substep_loop(task, remat=remat, lean=lean, option="hand_adjoint",
                                 hand_adjoint=True, hinges=hinges, planar=planar,
                                 rotary=rotary, saved_residuals=saved_residuals)


def positional_joints_refusal(task: Task) -> str | None:
    """Why `with_positional_joints` cannot rewrite `task` (None where it can): it is brax's
    positional substep for a scene whose joints are hinges and slides
    (`tasks.physics.positional_joints.joint_rows`), without fluid."""
    backend = getattr(task.spec, "backend", None)
    if backend != "positional" or not has_substep_loop(task):
        return (f"task {task.name!r} runs {backend!r} physics; positional_joints rewrites "
                "brax's positional substep (reacher, inverted_pendulum): leave it False")
    from tasks.physics.positional_joints import joint_rows
    sys = task.env.unwrapped.sys
    rows = joint_rows(sys)
    if isinstance(rows, str):
        return (f"task {task.name!r}: {rows}; positional_joints models hinges and slides "
                "only: leave it False")
    if sys.enable_fluid:
        return (f"task {task.name!r} has fluid forces, which positional_joints' step does "
                "not apply: leave it False")
    return None


def with_positional_joints(task: Task, remat: bool = True, lean: bool = False) -> Task:
    """A fresh copy of brax positional task `task` whose substeps run
    `tasks.physics.positional_joints.step`: brax's positional substep with the joints'
    position-level update and forces written for hinges and slides, and the conversions to link
    and joint frames, the inverse inertia, the joint forces' move to the links and the
    integration by `tasks.physics.spring_adjoint`'s hand-written VJPs. The same
    function and gradient to float32 round-off (tests/test_positional_joints.py). `remat`
    and `lean` as `with_substep_remat` and `with_lean_substeps`. Errors for a task it does
    not fit (`positional_joints_refusal`)."""
    why = positional_joints_refusal(task)
    if why is None and lean:
        why = lean_substeps_refusal(task)
    if why is not None:
        raise ValueError(why)
    return _rebuilt_substep_loop(task, remat=remat, lean=lean, option="positional_joints",
                                 positional=True)


def _rebuilt_substep_loop(task: Task, *, remat: bool, lean: bool, option: str,
                          hand_adjoint: bool = False, hinges: bool = False,
                          planar: bool = False, rotary: bool = False,
                          positional: bool = False, saved_residuals: bool = False) -> Task:
    """brax's `PipelineEnv.pipeline_step` (envs/base.py: a scan of `n_frames` substeps) built
    anew on a fresh copy of `task`, its substeps checkpointed (`remat`) and/or all but the
    last carrying the incoming q and qd (`lean`), and/or each substep
    `tasks.physics.spring_adjoint.step` (`hand_adjoint`) or `tasks.physics.positional_joints.step`
    (`positional`); with `saved_residuals` the checkpoint saves the hand-written VJPs'
    residuals named in `tasks.physics.spring_adjoint.SAVED_RESIDUALS`. `option`: the config field
    the errors name (and, after 'with_', the function to apply first)."""
    if not has_substep_loop(task):
        raise ValueError(f"task {task.name!r} has no brax physics pipeline to rebuild "
                         f"({option} is for brax PipelineEnv tasks; leave it False)")
    env = build_env(task.spec)
    inner, given = env.unwrapped, task.env.unwrapped
    if "pipeline_step" in vars(given):  # it would be dropped: this step is built from brax's
        raise ValueError(f"task {task.name!r} already has its own physics step (a "
                         "with_substep_remat, with_lean_substeps or with_small_dots copy); "
                         f"apply with_{option} first, to the task itself")
    inner.sys = given.sys
    # prevent_cse=False: inside a scan the CSE barrier only costs time
    policy = {}
    if saved_residuals:
        from tasks.physics.spring_adjoint import SAVED_RESIDUALS
        policy = {"policy": jax.checkpoint_policies.save_only_these_names(*SAVED_RESIDUALS)}
    wrap = (functools.partial(jax.checkpoint, prevent_cse=False, **policy) if remat
            else (lambda f: f))

    if hand_adjoint:
        from tasks.physics.spring_adjoint import step
        substep_fn = functools.partial(step, hinges=hinges, planar=planar, rotary=rotary)
    elif positional:
        from tasks.physics.positional_joints import joint_rows, step
        substep_fn = functools.partial(step, rows=joint_rows(given.sys), hand=True)
    else:
        substep_fn = inner._pipeline.step

    def pipeline_step(pipeline_state, action):
        def brax_substep(state, _):
            return substep_fn(inner.sys, state, action, inner._debug), None
        if not lean:
            return jax.lax.scan(wrap(brax_substep), pipeline_state, (), inner._n_frames)[0]
        q, qd = pipeline_state.q, pipeline_state.qd

        def lean_substep(state, _):  # its own q, qd are dead: XLA drops their computation
            return brax_substep(state, _)[0].replace(q=q, qd=qd), None
        state = jax.lax.scan(wrap(lean_substep), pipeline_state, (), inner._n_frames - 1)[0]
        return wrap(brax_substep)(state, None)[0]

    inner.pipeline_step = pipeline_step  # the instance's; brax's step calls self.pipeline_step
    return _like(task, Task(spec=task.spec, env=env))


def has_closed_form_adjoint(task: Task) -> bool:
    """Whether `task`'s env writes its control step in closed form (`closed_form_step`:
    acrobot), which `with_closed_form_adjoint` differentiates instead of brax's step."""
    return callable(getattr(task.env.unwrapped, "closed_form_step", None))


def with_closed_form_adjoint(task: Task) -> Task:
    """A fresh copy of `task` whose physics step runs brax's own step forward (the same values
    bit for bit) and, in reverse mode, the VJP of the env's `closed_form_step` (a double
    pendulum's equations of motion for acrobot) instead of brax's: the same derivative to
    float32 round-off, from a few dozen scalar operations per substep rather than the
    reverse of brax's general articulated-body algebra. The step is taken as a function of
    (q, qd, action), as its closed form is: cotangents of the output's position and
    velocity (`q`, `qd`, `x`, `xd`) go back to the input's `q`, `qd` and the action; the
    step's other outputs (inertia, mass matrix, bias forces, ...) are functions of q and qd
    that the next step recomputes in the closed form, so they carry none. Errors for a task
    without a closed form."""
    if not has_closed_form_adjoint(task):
        raise ValueError(f"task {task.name!r} has no closed-form step (closed_form_adjoint is "
                         "for tasks whose env defines closed_form_step: acrobot; leave it "
                         "False)")
    env = build_env(task.spec)
    inner, given = env.unwrapped, task.env.unwrapped
    if "pipeline_step" in vars(given):
        raise ValueError(f"task {task.name!r} already has its own physics step (a "
                         "with_substep_remat or with_small_dots copy); apply "
                         "with_closed_form_adjoint to the task itself")
    inner.sys = given.sys
    brax_step = inner.pipeline_step  # the class's, before the instance's below
    jax.eval_shape(inner.closed_form_step,  # refuses a scene it does not model, now
                   *(jax.ShapeDtypeStruct((n,), jnp.float32) for n in
                     (inner.sys.q_size(), inner.sys.qd_size(), inner.sys.act_size())))

    inner.pipeline_step = _step_with_adjoint(
        brax_step, ("q", "qd"), inner.closed_form_step,
        lambda ct: (ct.q, ct.qd, ct.x.pos, ct.x.rot, ct.xd.vel, ct.xd.ang))
    return _like(task, Task(spec=task.spec, env=env))


def _step_with_adjoint(forward, fields: tuple[str, str], closed_form, read_cotangent):
    """pipeline_step(state, action) with `forward`'s values and, in reverse mode, the VJP of
    `closed_form(state.<fields[0]>, state.<fields[1]>, action)` for the output's cotangent
    as `read_cotangent` reads it off the output state's; the state's other fields carry
    none. The forward stores only those two fields and the action."""
    a, b = fields

    @jax.custom_vjp
    def step(x, y, action, rest):
        return forward(rest.replace(**{a: x, b: y}), action)

    def fwd(x, y, action, rest):
        return step(x, y, action, rest), (x, y, action)

    def bwd(res, ct):
        _, vjp = jax.vjp(closed_form, *res)
        return (*vjp(read_cotangent(ct)), None)

    step.defvjp(fwd, bwd)
    return lambda ps, action: step(getattr(ps, a), getattr(ps, b), action, ps)


def planar_adjoint_refusal(task: Task, drop_normal_gravity: bool = False) -> str | None:
    """Why `with_planar_adjoint` cannot differentiate `task` (None where it can): it is for
    brax's positional step of a scene that moves in the x-z plane
    (`tasks.physics.planar.planar_refusal`) and brax's spring step of one
    (`tasks.physics.planar_spring.spring_refusal`)."""
    backend = getattr(task.spec, "backend", None)
    if backend not in ("positional", "spring") or not has_substep_loop(task):
        return (f"task {task.name!r} runs {backend!r} physics; planar_adjoint differentiates "
                "brax's positional or spring step of a planar scene (inverted_pendulum, "
                "hopper, walker2d): leave it False")
    if backend == "positional":
        from tasks.physics.planar import planar_refusal as refusal
    else:
        from tasks.physics.planar_spring import spring_refusal as refusal
    sys = task.env.unwrapped.sys
    why = refusal(sys, drop_normal_gravity) if backend == "positional" else refusal(sys)
    if why is not None:
        return (f"task {task.name!r}: {why}; planar_adjoint models a scene that moves in one "
                "plane: leave it False")
    return None


def with_planar_adjoint(task: Task, links: bool = False,
                        drop_normal_gravity: bool = False) -> Task:
    """A fresh copy of brax positional or spring task `task` whose control step runs
    `task`'s own (brax's, or a `with_lean_substeps` / `with_positional_joints` /
    `with_hand_adjoint` copy's: the same values) and, in reverse mode, the VJP of
    `tasks.physics.planar.control_step` (positional) or
    `tasks.physics.planar_spring.control_step` (spring) instead: brax's step written over the
    plane the scene moves in, its derivative the same to float32 round-off
    (tests/test_planar.py, tests/test_planar_spring.py). The step is taken as a function of the
    state's centre-of-mass frames (`x_i`, `xd_i`) and the action, as the planar form is: the
    state's other frames and joint coordinates are functions of those on every state a rollout
    visits (brax's substeps end, and its resets begin, by computing them from those frames), so
    the output's cotangents in all of them go back to the input's `x_i`, `xd_i` and the action,
    and the input's other fields carry none. Each step's backward recomputes the planar step
    from its input (what the forward stores), as `with_substep_remat` recomputes brax's
    substeps. `links`: the spring step with every link at once
    (`tasks.physics.planar_links.control_step`: the same values, its VJP faster). Errors for a
    task it does not fit (`planar_adjoint_refusal`)."""
    why = planar_adjoint_refusal(task, drop_normal_gravity)
    if why is not None:
        raise ValueError(why)
    if drop_normal_gravity and task.spec.backend != "positional":
        raise ValueError(f"task {task.name!r} runs {task.spec.backend!r} physics; "
                         "planar_normal_gravity is for brax's positional step (reacher): "
                         "leave it False")
    if links and task.spec.backend != "spring":
        raise ValueError(f"task {task.name!r} runs {task.spec.backend!r} physics; "
                         "planar_links writes brax's spring step over the links (hopper, "
                         "walker2d): leave it False")
    from tasks.physics.planar import control_step, cotangent, planar_scene
    env = build_env(task.spec)
    inner, given = env.unwrapped, task.env.unwrapped
    inner.sys, n_frames = given.sys, inner._n_frames
    if task.spec.backend == "positional":
        scene = planar_scene(given.sys, drop_normal_gravity)
        closed_form = lambda *a: control_step(scene, *a, n_frames)  # noqa: E731
    else:
        from tasks.physics.planar_spring import control_step as spring_step, spring_scene
        scene = spring_scene(given.sys)
        if links:
            from tasks.physics.planar_links import control_step as spring_step, link_scene
            scene = link_scene(scene)
        closed_form = lambda *a: spring_step(scene, given.sys, *a, n_frames)  # noqa: E731
    inner.pipeline_step = _step_with_adjoint(  # the task's own step: brax's or a rebuilt one
        given.pipeline_step, ("x_i", "xd_i"), closed_form, cotangent)
    return _like(task, Task(spec=task.spec, env=env))


def spatial_adjoint_refusal(task: Task) -> str | None:
    """Why `with_spatial_adjoint` cannot differentiate `task` (None where it can): it is for
    brax's spring step of a scene of free roots and joints that only turn (hinges, 2- and
    3-dof) with contacts against a plane (`tasks.physics.spatial_links.spatial_scene`: ant,
    humanoid)."""
    scene = _spatial_scene(task)
    return scene if isinstance(scene, str) else None


def _spatial_scene(task: Task):
    """`tasks.physics.spatial_links.spatial_scene` of `task`, or why `with_spatial_adjoint` cannot
    differentiate it (a string naming the task and the fix)."""
    backend = getattr(task.spec, "backend", None)
    if backend != "spring" or not has_substep_loop(task):
        return (f"task {task.name!r} runs {backend!r} physics; spatial_links differentiates "
                "brax's spring step of a scene of a free root and joints that only turn (ant, "
                "humanoid): leave it False")
    from tasks.physics.spatial_links import spatial_scene
    scene = spatial_scene(task.env.unwrapped.sys)
    if isinstance(scene, str):
        return (f"task {task.name!r}: {scene}; spatial_links models a free root and joints "
                "that only turn (ant, humanoid): leave it False")
    return scene


def with_spatial_adjoint(task: Task) -> Task:
    """A fresh copy of brax spring task `task` whose control step runs `task`'s own (brax's,
    or a `with_lean_substeps` / `with_hand_adjoint` copy's: the same values) and, in reverse
    mode, the VJP of `tasks.physics.spatial_links.control_step` instead: brax's spring step with
    every entry of every vector an array over the links, its derivative the same to float32
    round-off (tests/test_spatial_links.py). As `with_planar_adjoint`, the step is a
    function of the state's centre-of-mass frames and the action, and each step's backward
    recomputes the step from its input. Errors for a task it does not fit
    (`spatial_adjoint_refusal`)."""
    scene = _spatial_scene(task)  # read once: it traces brax's contacts
    if isinstance(scene, str):
        raise ValueError(scene)
    from tasks.physics.planar import cotangent
    from tasks.physics.spatial_links import control_step
    env = build_env(task.spec)
    inner, given = env.unwrapped, task.env.unwrapped
    inner.sys, n_frames = given.sys, inner._n_frames
    closed_form = lambda *a: control_step(scene, given.sys, *a, n_frames)  # noqa: E731
    inner.pipeline_step = _step_with_adjoint(  # the task's own step: brax's or a rebuilt one
        given.pipeline_step, ("x_i", "xd_i"), closed_form, cotangent)
    return _like(task, Task(spec=task.spec, env=env))


def with_small_dots(task: Task) -> Task:
    """A fresh copy of brax task `task` (same `sys`; composes with `without_joint_limits` and
    `with_substep_remat` copies) whose physics step computes its small matrix products as
    multiply-and-sum (`tasks.physics.small_dots.small_dots_as_sums`): the same function and
    gradient to float32 round-off (tested), which XLA's CPU backend runs faster where a step is
    made of tiny products (swimmer's generalized step). The
    registry's cached task is left as it is. Errors for a task with no brax physics step.
    Apply it after `with_substep_remat` (which builds its step from brax's substep and refuses
    a copy that has its own): the checkpointed substeps are then rewritten inside."""
    from tasks.physics.small_dots import small_dots_as_sums
    if not has_substep_loop(task):
        raise ValueError(f"task {task.name!r} has no brax physics step to rewrite "
                         "(small_dots is for brax PipelineEnv tasks; leave it False)")
    env = build_env(task.spec)
    inner, given = env.unwrapped, task.env.unwrapped
    inner.sys = given.sys
    inner.pipeline_step = small_dots_as_sums(given.pipeline_step)
    return _like(task, Task(spec=task.spec, env=env))
