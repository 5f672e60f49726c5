"""A built task: the unwrapped environment plus the functions the harness needs around it."""
from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from brax import envs as brax_envs
from brax.envs.base import Env, PipelineEnv, State, Wrapper

from tasks.registry import TaskSpec, get_spec


def brax_matched_state(pipeline_state) -> jax.Array:
    """[pos(nb*3), rot(nb*4), vel(nb*3), ang(nb*3)] from the world-frame transforms."""
    x, xd = pipeline_state.x, pipeline_state.xd
    return jnp.concatenate([x.pos.ravel(), x.rot.ravel(), xd.vel.ravel(), xd.ang.ravel()])


def env_matched_state(env, state: State) -> jax.Array:
    """The matched state of one env state: the env's own `matched_state` (tasks/ envs) or the
    brax layout above (wrappers forward attribute lookups to the inner env)."""
    own = getattr(env, "matched_state", None)
    if own is not None:
        return own(state.pipeline_state)
    return brax_matched_state(state.pipeline_state)


def _strong_leaf(x):
    a = jnp.asarray(x)
    return jax.lax.convert_element_type(a, a.dtype)


def strong(tree):
    """Every leaf as a strongly typed array of its own dtype (Python scalars as arrays).

    A weakly typed leaf (a Python float through `jnp.asarray`, or the Python float brax's
    hopper writes to `metrics['reward_healthy']` on every step) gives a jitted function's
    output another type signature than its input had, so the next call traces and compiles
    again: a one-update compile warm-up then caches only the first executable and the timed
    run pays for the second (SHAC on hopper: 150 s of a 180-s budget). Values
    are unchanged.
    """
    return jax.tree.map(_strong_leaf, tree)


class Canonical(Wrapper):
    """Rewards and done flags as float32 arrays (some brax envs return Python floats) and
    every other leaf strongly typed (`strong`), so a state has one fixed pytree type from
    reset on and scan carries and jitted training steps stay stable."""

    @staticmethod
    def _fix(s: State) -> State:
        return strong(s.replace(reward=jnp.asarray(s.reward, jnp.float32),
                                done=jnp.asarray(s.done, jnp.float32)))

    def reset(self, rng: jax.Array) -> State:
        return self._fix(self.env.reset(rng))

    def step(self, state: State, action: jax.Array) -> State:
        return self._fix(self.env.step(state, action))


def build_env(spec: TaskSpec, test_noise: float = 0.0) -> Env:
    """The task's environment; `test_noise` > 0 builds its declared test dynamics at that
    magnitude (TaskSpec.transfer, e.g. the cloth's action noise and bias)."""
    return Canonical(_build_env(spec, test_noise))


def _build_env(spec: TaskSpec, test_noise: float = 0.0) -> Env:
    kind, _, name = spec.env.partition(":")
    kwargs = spec.kwargs()
    if test_noise and "test_noise" not in dict(spec.transfer or ()):
        raise ValueError(f"task {spec.name!r} declares no test_noise dynamics "
                         "(TaskSpec.transfer)")
    if kind == "brax":
        from tasks.jax_compat import apply as jax_compat
        jax_compat()  # brax 0.14.2 on a newer JAX (the accelerator image); no-op on the pin
        return brax_envs.get_environment(name, backend=spec.backend, **kwargs)
    if kind == "ildbench" and name == "pointmass":
        from tasks.pointmass import PointMass
        return PointMass(**kwargs)
    if kind == "ildbench" and name == "acrobot":
        from tasks.acrobot import Acrobot
        return Acrobot(backend=spec.backend, **kwargs)
    if kind == "ildbench" and name == "cloth":
        from tasks.cloth.env import ClothHang
        from tasks.cloth.env import TEST_BIAS, TEST_NOISE
        return ClothHang(noise=TEST_NOISE * test_noise, bias=TEST_BIAS * test_noise, **kwargs)
    raise ValueError(f"task {spec.name!r}: cannot build env {spec.env!r}")


def open_loop(step, state, actions, emit=lambda s: None):
    """Step `state` through time-major `actions` (H, ...) with no policy in the loop (the
    backend probes, trajectory optimization, replays): `jax.lax.scan` of `step`. Returns
    (final state, `emit` of each of the H post-step states, stacked)."""
    def body(s, a):
        s = step(s, a)
        return s, emit(s)
    return jax.lax.scan(body, state, actions)


def env_obs_size(env: Env) -> int:
    """Observation width of a (possibly wrapped) env. brax's env.observation_size runs
    reset() op by op (seconds for humanoid); an abstract trace gives the same shape in
    milliseconds."""
    return int(jax.eval_shape(env.reset, jax.random.PRNGKey(0)).obs.shape[-1])


def reset_done(env: Env, state: State, done: jax.Array, key: jax.Array) -> State:
    """Batched `state` with the envs where `done` replaced by fresh resets (one key each,
    split from `key`); the resets are computed only when some env is done, and carry no
    gradient."""
    n = done.shape[0]

    def with_reset(_):
        fresh = jax.lax.stop_gradient(jax.vmap(env.reset)(jax.random.split(key, n)))
        return jax.tree.map(
            lambda f, x: jnp.where(done.reshape(done.shape + (1,) * (x.ndim - 1)), f, x),
            fresh, state)

    return jax.lax.cond(done.any(), with_reset, lambda _: state, None)


@dataclasses.dataclass(frozen=True, eq=False)
class Task:
    """A task ready to run. `env` is always the *unwrapped* environment (no auto-reset,
    no episode wrapper): episodes are exactly `episode_length` steps driven by the caller."""

    spec: TaskSpec
    env: Env

    @property
    def name(self) -> str:
        return self.spec.name

    @property
    def episode_length(self) -> int:
        return self.spec.episode_length

    @functools.cached_property
    def obs_size(self) -> int:
        return env_obs_size(self.env)

    @property
    def action_size(self) -> int:
        return int(self.env.action_size)

    def matched_state(self, state: State) -> jax.Array:
        """The vector imitation losses compare, for one (unbatched) env state."""
        return env_matched_state(self.env, state)

    @functools.cached_property
    def state_size(self) -> int:
        if getattr(self.env, "matched_state", None) is not None:
            s = jax.eval_shape(self.env.reset, jax.random.PRNGKey(0))
            return int(jax.eval_shape(self.matched_state, s).shape[0])
        return 13 * int(self.env.sys.num_links())  # brax_matched_state's layout


def task_with_backend(name: str, backend: str) -> Task:
    """A fresh task `name` on another physics backend (for backend measurements; not
    cached: the registry's pin stays what make_task returns)."""
    spec = dataclasses.replace(get_spec(name), backend=backend)
    return Task(spec=spec, env=build_env(spec))


def _like(given, copy: Task):
    """`copy` of `given` gated as `given` was: a method's task is a gated view
    (bench.access.TaskView: reward hidden, physics gradient cut, as its Uses declare) and the
    transforms below build a fresh env from the spec, which would hand the method an ungated
    one."""
    regated = getattr(given, "regated", None)
    return copy if regated is None else regated(copy)


def without_joint_limits(task: Task) -> Task:
    """A fresh copy of brax task `task` with its joint-range constraints removed (`sys.dof.limit
    = None`; the registry's cached task is left as it is). brax's generalized backend solves
    joint ranges like contacts, which makes a loss through them rough (swimmer: docs/methods/ild.md); the copy is the smooth surrogate. Errors for a task that has no limits."""
    env = build_env(task.spec)
    inner = env.unwrapped
    dof = getattr(getattr(inner, "sys", None), "dof", None)
    if dof is None or dof.limit is None:
        raise ValueError(f"task {task.name!r} has no brax joint limits to remove "
                         "(this is for brax tasks with limited joints)")
    inner.sys = inner.sys.replace(dof=dof.replace(limit=None))
    return _like(task, Task(spec=task.spec, env=env))


def has_substep_loop(task: Task) -> bool:
    """Whether `task` steps its physics through brax's substep loop (`PipelineEnv`): the
    tasks `with_substep_remat` and `with_small_dots` can rewrite (all 8 brax tasks; not
    pointmass's analytic step or the cloth's own solver)."""
    return isinstance(task.env.unwrapped, PipelineEnv)


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
    VJPs are of brax's spring substep (`tasks.spring_adjoint`)."""
    backend = getattr(task.spec, "backend", None)
    if backend != "spring":
        return (f"task {task.name!r} runs {backend!r} physics; hand_adjoint writes the VJP of "
                "brax's spring substep (hopper, walker2d, ant, humanoid); leave it False")
    return None


def with_hand_adjoint(task: Task, remat: bool = True, lean: bool = False,
                      hinges: bool = False, planar: bool = False,
                      rotary: bool = False, saved_residuals: bool = False) -> Task:
    """A fresh copy of brax spring task `task` whose substeps run `tasks.spring_adjoint.step`:
    brax's spring substep with six pieces' VJPs written by hand (the same values and
    gradient to float32 round-off: tests/test_hand_adjoint.py). `remat` and `lean` as
    `with_substep_remat` and `with_lean_substeps`; `hinges`: its 1-dof joints' forces by
    `tasks.spring_adjoint.hinge` (a scene whose 1-dof joints are all hinges); `planar`: its
    3-dof joints' forces by `tasks.spring_adjoint.planar_root` (a scene whose 3-dof joints
    are all planar roots); `rotary`: its 2- and 3-dof joints' forces by
    `tasks.spring_adjoint.rotary_two` and `rotary_three` (a scene whose 2- and 3-dof joints
    only turn); `saved_residuals` (with `remat`): the substep checkpoint saves the residuals
    of `world_to_joint`'s and `inv_inertia`'s VJPs (`tasks.spring_adjoint.SAVED_RESIDUALS`)
    instead of recomputing them (without `remat` every residual is saved anyway). Errors
    for a task it does not fit."""
    why = hand_adjoint_refusal(task)
    if why is None and lean:
        why = lean_substeps_refusal(task)
    if why is None and hinges:
        from tasks.spring_adjoint import only_hinges
        if not only_hinges(task.env.unwrapped.sys):
            why = (f"task {task.name!r} has 1-dof joints that slide; hinge_forces models "
                   "hinges only: leave it False")
    if why is None and planar:
        from tasks.spring_adjoint import planar_roots
        if planar_roots(task.env.unwrapped.sys) is None:
            why = (f"task {task.name!r} has no planar root (3-dof joints that are two "
                   "unlimited slides and an unlimited hinge, as hopper's); planar_root "
                   "models those only: leave it False")
    if why is None and rotary:
        from tasks.spring_adjoint import rotary_joints
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
    (`tasks.positional_joints.joint_rows`), without fluid."""
    backend = getattr(task.spec, "backend", None)
    if backend != "positional" or not has_substep_loop(task):
        return (f"task {task.name!r} runs {backend!r} physics; positional_joints rewrites "
                "brax's positional substep (reacher, inverted_pendulum): leave it False")
    from tasks.positional_joints import joint_rows
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
    `tasks.positional_joints.step`: brax's positional substep with the joints' position-level
    update and forces written for hinges and slides, and the conversions to link and joint
    frames, the inverse inertia, the joint forces' move to the links and the integration by
    `tasks.spring_adjoint`'s hand-written VJPs. The same
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
    `tasks.spring_adjoint.step` (`hand_adjoint`) or `tasks.positional_joints.step`
    (`positional`); with `saved_residuals` the checkpoint saves the hand-written VJPs'
    residuals named in `tasks.spring_adjoint.SAVED_RESIDUALS`. `option`: the config field
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
        from tasks.spring_adjoint import SAVED_RESIDUALS
        policy = {"policy": jax.checkpoint_policies.save_only_these_names(*SAVED_RESIDUALS)}
    wrap = (functools.partial(jax.checkpoint, prevent_cse=False, **policy) if remat
            else (lambda f: f))

    if hand_adjoint:
        from tasks.spring_adjoint import step
        substep_fn = functools.partial(step, hinges=hinges, planar=planar, rotary=rotary)
    elif positional:
        from tasks.positional_joints import joint_rows, step
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
    (`tasks.planar.planar_refusal`) and brax's spring step of one
    (`tasks.planar_spring.spring_refusal`)."""
    backend = getattr(task.spec, "backend", None)
    if backend not in ("positional", "spring") or not has_substep_loop(task):
        return (f"task {task.name!r} runs {backend!r} physics; planar_adjoint differentiates "
                "brax's positional or spring step of a planar scene (inverted_pendulum, "
                "hopper, walker2d): leave it False")
    if backend == "positional":
        from tasks.planar import planar_refusal as refusal
    else:
        from tasks.planar_spring import spring_refusal as refusal
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
    `tasks.planar.control_step` (positional) or `tasks.planar_spring.control_step` (spring)
    instead: brax's step written over the plane the scene moves in, its derivative the same
    to float32 round-off (tests/test_planar.py, tests/test_planar_spring.py). The step is
    taken as a function of the state's centre-of-mass frames (`x_i`, `xd_i`) and the
    action, as the planar form is: the state's other frames and joint coordinates are
    functions of those on every state a rollout visits (brax's substeps end, and its
    resets begin, by computing them from those frames), so the output's cotangents in all
    of them go back to the input's `x_i`, `xd_i` and the action, and the input's other
    fields carry none. Each step's backward recomputes the planar step from its input (what
    the forward stores), as `with_substep_remat` recomputes brax's substeps. `links`: the
    spring step with every link at once (`tasks.planar_links.control_step`: the same values,
    its VJP faster). Errors for a task it does not fit (`planar_adjoint_refusal`)."""
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
    from tasks.planar import control_step, cotangent, planar_scene
    env = build_env(task.spec)
    inner, given = env.unwrapped, task.env.unwrapped
    inner.sys, n_frames = given.sys, inner._n_frames
    if task.spec.backend == "positional":
        scene = planar_scene(given.sys, drop_normal_gravity)
        closed_form = lambda *a: control_step(scene, *a, n_frames)  # noqa: E731
    else:
        from tasks.planar_spring import control_step as spring_step, spring_scene
        scene = spring_scene(given.sys)
        if links:
            from tasks.planar_links import control_step as spring_step, link_scene
            scene = link_scene(scene)
        closed_form = lambda *a: spring_step(scene, given.sys, *a, n_frames)  # noqa: E731
    inner.pipeline_step = _step_with_adjoint(  # the task's own step: brax's or a rebuilt one
        given.pipeline_step, ("x_i", "xd_i"), closed_form, cotangent)
    return _like(task, Task(spec=task.spec, env=env))


def spatial_adjoint_refusal(task: Task) -> str | None:
    """Why `with_spatial_adjoint` cannot differentiate `task` (None where it can): it is for
    brax's spring step of a scene of free roots and joints that only turn (hinges, 2- and
    3-dof) with contacts against a plane (`tasks.spatial_links.spatial_scene`: ant,
    humanoid)."""
    scene = _spatial_scene(task)
    return scene if isinstance(scene, str) else None


def _spatial_scene(task: Task):
    """`tasks.spatial_links.spatial_scene` of `task`, or why `with_spatial_adjoint` cannot
    differentiate it (a string naming the task and the fix)."""
    backend = getattr(task.spec, "backend", None)
    if backend != "spring" or not has_substep_loop(task):
        return (f"task {task.name!r} runs {backend!r} physics; spatial_links differentiates "
                "brax's spring step of a scene of a free root and joints that only turn (ant, "
                "humanoid): leave it False")
    from tasks.spatial_links import spatial_scene
    scene = spatial_scene(task.env.unwrapped.sys)
    if isinstance(scene, str):
        return (f"task {task.name!r}: {scene}; spatial_links models a free root and joints "
                "that only turn (ant, humanoid): leave it False")
    return scene


def with_spatial_adjoint(task: Task) -> Task:
    """A fresh copy of brax spring task `task` whose control step runs `task`'s own (brax's,
    or a `with_lean_substeps` / `with_hand_adjoint` copy's: the same values) and, in reverse
    mode, the VJP of `tasks.spatial_links.control_step` instead: brax's spring step with
    every entry of every vector an array over the links, its derivative the same to float32
    round-off (tests/test_spatial_links.py). As `with_planar_adjoint`, the step is a
    function of the state's centre-of-mass frames and the action, and each step's backward
    recomputes the step from its input. Errors for a task it does not fit
    (`spatial_adjoint_refusal`)."""
    scene = _spatial_scene(task)  # read once: it traces brax's contacts
    if isinstance(scene, str):
        raise ValueError(scene)
    from tasks.planar import cotangent
    from tasks.spatial_links import control_step
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
    multiply-and-sum (`tasks.small_dots.small_dots_as_sums`): the same function and gradient
    to float32 round-off (tested), which XLA's CPU backend runs faster where a step is made
    of tiny products (swimmer's generalized step). The
    registry's cached task is left as it is. Errors for a task with no brax physics step.
    Apply it after `with_substep_remat` (which builds its step from brax's substep and refuses
    a copy that has its own): the checkpointed substeps are then rewritten inside."""
    from tasks.small_dots import small_dots_as_sums
    if not has_substep_loop(task):
        raise ValueError(f"task {task.name!r} has no brax physics step to rewrite "
                         "(small_dots is for brax PipelineEnv tasks; leave it False)")
    env = build_env(task.spec)
    inner, given = env.unwrapped, task.env.unwrapped
    inner.sys = given.sys
    inner.pipeline_step = small_dots_as_sums(given.pipeline_step)
    return _like(task, Task(spec=task.spec, env=env))


@functools.lru_cache(maxsize=None)
def make_task(name: str) -> Task:
    """Build (once per process) the task registered under `name`."""
    spec = get_spec(name)
    return Task(spec=spec, env=build_env(spec))
