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
    joint ranges like contacts, which makes a loss through them rough (swimmer:
    docs/methods/ild.md); the copy is the smooth surrogate. Errors for a task that has no
    limits."""
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


@functools.lru_cache(maxsize=None)
def make_task(name: str) -> Task:
    """Build (once per process) the task registered under `name`."""
    spec = get_spec(name)
    return Task(spec=spec, env=build_env(spec))
