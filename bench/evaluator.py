"""The one shared evaluator: every method's policy is scored by this code.

N episodes of exactly `episode_length` steps on the task's *unwrapped* env. An episode that
terminates early keeps its partial return (rewards after the first done are masked), as in
the paper. Score = raw return and normalized (R - R_random) / (R_expert - R_random) with
both references measured by this evaluator and stored in the task's demo.

The evaluation episodes are fixed by the eval seed (the run seed), so every method sees the
same initial states for the same seed, and every evaluation within a run uses the same
episodes (a smoother curve, no selection on lucky episodes).
"""
from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from bench.api import InformationError, Policy, act_step, start_memory
from tasks.core import Task, env_matched_state

EVAL_KEY_SALT = 0x5EED  # eval keys never collide with a method's training keys of that seed


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    num_episodes: int = 32
    """Parallel evaluation episodes."""
    deterministic: bool = True
    """Act with the policy's mode (True) or sample (False)."""
    transfer: bool = False
    """Also score the final policy under each perturbation family at its default magnitude
    (bench/perturb.py); the leaderboard's 'transfer' column."""
    robustness: bool = False
    """Also score it on each family's magnitude grid (robustness curves)."""

    def __post_init__(self):
        if self.num_episodes < 1:
            raise ValueError(f"eval num_episodes must be >= 1, got {self.num_episodes}")


@dataclasses.dataclass(frozen=True)
class EvalResult:
    returns: np.ndarray
    """(N,) raw episode returns."""
    lengths: np.ndarray
    """(N,) steps before termination (episode_length if none)."""
    normalized: np.ndarray | None
    """(N,) normalized returns, or None without references."""
    trajectory: np.ndarray | None = None
    """(T+1, state_dim) matched states of the first episode (renders, trajectory checks)."""

    @property
    def mean_return(self) -> float:
        return float(np.mean(self.returns))

    @property
    def mean_normalized(self) -> float | None:
        return None if self.normalized is None else float(np.mean(self.normalized))

    @property
    def mean_length(self) -> float:
        """Mean steps before termination: below the episode length where episodes end
        early (a fallen hopper, humanoid or ant), which explains a return below the
        random policy's better than the return can."""
        return float(np.mean(self.lengths))

    @property
    def finite(self) -> bool:
        return bool(np.isfinite(self.returns).all())


def eval_key(seed: int) -> jax.Array:
    return jax.random.fold_in(jax.random.PRNGKey(seed), EVAL_KEY_SALT)


def _step_masked(env, s, a, alive, ret, length):
    s = env.step(s, a)
    ret = ret + alive * s.reward
    length = length + alive
    alive = alive * (1.0 - s.done)
    return s, alive, ret, length


@functools.lru_cache(maxsize=64)
def _jax_episodes(env, act, kind, horizon: int, deterministic: bool, init_memory=None):
    """jit(vmap(one episode)) for a JAX policy; cached per (env, act) so it compiles once.
    A perturbable env (bench/perturb.py) takes its magnitudes as the argument `dyn`, so all
    perturbations of a task share this one compilation."""

    def episode(params, key, dyn):
        e = _bind(env, dyn)
        k_reset, k_act = jax.random.split(key)  # as before memory existed: same episodes
        s = e.reset(k_reset)

        def body(carry, k):
            (s, alive, ret, length), mem = carry
            x = s if kind == "jax_state" else s.obs
            a, mem = act_step(act, init_memory, params, x, k, deterministic, mem)
            nxt = _step_masked(e, s, a, alive, ret, length)
            return (nxt, mem), env_matched_state(e, nxt[0])

        mem = start_memory(init_memory, params, k_act)
        init = ((s, jnp.ones(()), jnp.zeros(()), jnp.zeros(())), mem)
        ((_, _, ret, length), _), states = jax.lax.scan(body, init,
                                                        jax.random.split(k_act, horizon))
        return ret, length, jnp.concatenate([env_matched_state(e, s)[None], states])

    def batch(params, keys, dyn):
        ret, length, states = jax.vmap(episode, in_axes=(None, 0, None))(params, keys, dyn)
        return ret, length, states[0]  # only the first episode's states leave the device
    return jax.jit(batch)


@functools.lru_cache(maxsize=16)
def _batched_env_fns(env):
    """Batched reset and masked step, each also returning the first episode's matched state
    (one device call per step); `dyn` as in _jax_episodes."""
    def first(s):
        return env_matched_state(env, jax.tree_util.tree_map(lambda x: x[0], s))

    def reset(keys, dyn):
        s = jax.vmap(_bind(env, dyn).reset)(keys)
        return s, first(s)

    def step(s, a, alive, ret, n, dyn):
        e = _bind(env, dyn)
        out = jax.vmap(lambda *xs: _step_masked(e, *xs))(s, a, alive, ret, n)
        return out + (first(out[0]),)
    return jax.jit(reset), jax.jit(step)


def _split_dynamics(env):
    """(env to compile on, magnitudes argument or None)."""
    template = getattr(env, "template", None)
    if template is None:
        return env, None
    return template, jnp.asarray(env.mags)


def _bind(env, dyn):
    """Inside a trace: the compiled-on env under magnitudes `dyn` (None: env itself)."""
    return env if dyn is None else env.bind(dyn)


def run_episodes(task: Task, policy: Policy, key: jax.Array, num_episodes: int,
                 deterministic: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(returns (N,), lengths (N,), matched states of the first episode (T+1, S))."""
    keys = jax.random.split(key, num_episodes)
    env, dyn = _split_dynamics(task.env)
    if policy.kind in ("jax", "jax_state"):
        f = _jax_episodes(env, policy.act, policy.kind, task.episode_length, deterministic,
                          policy.init_memory)
        ret, length, states = f(policy.params, keys, dyn)
        return (np.asarray(ret, np.float64), np.asarray(length, np.int64),
                np.asarray(states, np.float32))
    if policy.kind != "host":
        raise ValueError(f"unknown policy kind {policy.kind!r}; use 'jax', 'host' or 'jax_state'")
    # Host policy (torch/numpy): one batched jitted env call per step, one conversion each way.
    reset, step = _batched_env_fns(env)
    reset_keys = jax.vmap(lambda k: jax.random.split(k)[0])(keys)
    rng = np.random.default_rng(np.asarray(jax.random.key_data(key)).tolist())
    s, s0 = reset(reset_keys, dyn)
    alive = jnp.ones(num_episodes)
    ret = jnp.zeros(num_episodes)
    length = jnp.zeros(num_episodes)
    states = [s0]
    for _ in range(task.episode_length):
        a = policy.act(policy.params, np.asarray(s.obs), rng, deterministic)
        s, alive, ret, length, s_first = step(s, jnp.asarray(a, jnp.float32), alive, ret,
                                              length, dyn)
        states.append(s_first)
    return (np.asarray(ret, np.float64), np.asarray(length, np.int64),
            np.asarray(jnp.stack(states), np.float32))


class Evaluator:
    """Scores policies on one task with fixed references (R_expert, R_random)."""

    def __init__(self, task: Task, config: EvalConfig = EvalConfig(),
                 expert_return: float | None = None, random_return: float | None = None,
                 allow_sim_at_test: bool = False):
        self.task = task
        self.config = config
        self.expert_return = expert_return
        self.random_return = random_return
        self.allow_sim_at_test = allow_sim_at_test

    def normalize(self, returns):
        if self.expert_return is None or self.random_return is None:
            return None
        return (np.asarray(returns) - self.random_return) / (self.expert_return -
                                                             self.random_return)

    def evaluate(self, policy: Policy, seed: int) -> EvalResult:
        if policy.kind == "jax_state" and not self.allow_sim_at_test:
            raise InformationError("this policy acts on the simulator state; its method must "
                                   "declare Uses(sim_at_test=True)")
        ret, length, states = run_episodes(self.task, policy, eval_key(seed),
                                           self.config.num_episodes, self.config.deterministic)
        return EvalResult(returns=ret, lengths=length, normalized=self.normalize(ret),
                          trajectory=states)


def random_policy(action_size: int) -> Policy:
    """Uniform random actions in [-1, 1]: the R_random reference."""
    return Policy(act=_cached_random_act(action_size), params=())


@functools.lru_cache(maxsize=None)
def _cached_random_act(action_size: int):
    def act(params, obs, key, deterministic):
        return jax.random.uniform(key, (action_size,), minval=-1.0, maxval=1.0)
    return act
