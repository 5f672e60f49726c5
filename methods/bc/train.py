"""Behaviour cloning on the demo's (o_t, a_t) pairs."""
from __future__ import annotations

import functools

import flax.struct
import jax
import optax

from bench.api import Policy, TrainResult
from methods.bc.config import BCConfig
from methods.common.policy import (ObsNorm, TanhGaussianPolicy, bc_optimizer, bc_pairs,
                                   make_bc_step)


@flax.struct.dataclass
class TrainingState:
    params: dict
    opt_state: optax.OptState
    key: jax.Array


def train(task, demo, config: BCConfig, ctx, seed: int) -> TrainResult:
    obs, actions = bc_pairs(task, demo)
    policy = TanhGaussianPolicy(task.obs_size, task.action_size, config.hidden)
    # init_key: network weights; loop_key: the per-update sampling noise.
    init_key, loop_key = jax.random.split(jax.random.PRNGKey(seed))
    params = policy.init(init_key, ObsNorm.fit(obs, config.obs_std_min))
    opt = bc_optimizer(config.learning_rate, config.max_grad_norm)
    bc_step = make_bc_step(policy, opt, obs, actions, config.samples)
    state = TrainingState(params, opt.init(params), loop_key)

    def update(s: TrainingState, _):
        key, k = jax.random.split(s.key)
        params, opt_state, loss, gnorm = bc_step(s.params, s.opt_state, k)
        return TrainingState(params, opt_state, key), (loss, gnorm)

    @functools.partial(jax.jit, static_argnums=1)
    def chunk(s: TrainingState, length: int):
        return jax.lax.scan(update, s, None, length=length)

    done = 0
    act = policy.act
    while done < config.updates and not ctx.should_stop(0):
        n = min(config.chunk, config.updates - done)  # exactly `updates`, never a chunk more
        state, (loss, gnorm) = chunk(state, n)
        done += n
        ctx.report(Policy(act, state.params), env_steps=0,
                   metrics={"train/loss": loss[-1], "grad/norm_raw": gnorm[-1],
                            "train/updates": done})
    return TrainResult(Policy(act, state.params), env_steps=0,
                       metrics={"train/updates": done})
