"""Point mass: the paper's own example dynamics (Section 3), in pure JAX.

    x_{t+1} = x_t + dt * v_t
    v_{t+1} = v_t + dt * f_t / m,      f_t = force_scale * a_t,  a_t in [-1, 1]^2

A point (1-D by default, as the paper's example; `dim` for more) starts near x = 1 and should
reach the goal at the origin. Reward per step is -||x_{t+1} - goal||, so an episode's return
is minus the summed distance (higher is better). Milliseconds per run: this task is for tests.

Observation = matched state = pipeline state = (x, v), 2 * dim numbers.

The analytic expert is an under-damped saturated PD controller: its trajectory crosses the
goal a few times, so one demo covers both sides of the goal. (With an over-damped expert the
demo approaches from one side only, and BC from that one demo failed on 2 of 6 seeds as soon
as a test episode overshot; measured while building this task.)
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from brax.envs.base import Env, State


class PointMass(Env):
    def __init__(self, dt: float = 0.05, mass: float = 1.0, force_scale: float = 2.0,
                 dim: int = 1, start: float = 1.0, reset_noise_scale: float = 0.1):
        self.dt = dt
        self.mass = mass
        self.force_scale = force_scale
        self.dim = dim
        self.start = jnp.full((dim,), start, dtype=jnp.float32)
        self.goal = jnp.zeros(dim, dtype=jnp.float32)
        self.reset_noise_scale = reset_noise_scale

    def reset(self, rng: jax.Array) -> State:
        k_x, k_v = jax.random.split(rng)
        s = self.reset_noise_scale
        x = self.start + jax.random.uniform(k_x, (self.dim,), minval=-s, maxval=s)
        v = jax.random.uniform(k_v, (self.dim,), minval=-s, maxval=s)
        ps = jnp.concatenate([x, v])
        zero = jnp.zeros(())
        return State(pipeline_state=ps, obs=ps, reward=zero, done=zero, metrics={},
                     info={})

    def dynamics(self, ps: jax.Array, action: jax.Array) -> jax.Array:
        x, v = ps[:self.dim], ps[self.dim:]
        f = self.force_scale * jnp.clip(action, -1.0, 1.0)
        return jnp.concatenate([x + self.dt * v, v + self.dt * f / self.mass])

    def step(self, state: State, action: jax.Array) -> State:
        ps = self.dynamics(state.pipeline_state, action)
        reward = -jnp.linalg.norm(ps[:self.dim] - self.goal)
        return state.replace(pipeline_state=ps, obs=ps, reward=reward,
                             done=jnp.zeros_like(state.done))

    def matched_state(self, ps: jax.Array) -> jax.Array:
        return ps

    @property
    def observation_size(self) -> int:
        return 2 * self.dim

    @property
    def action_size(self) -> int:
        return self.dim

    @property
    def backend(self) -> str:
        return "analytic"


def pd_expert(obs: jax.Array, kp: float = 3.0, kd: float = 1.0) -> jax.Array:
    """Analytic expert: a saturated, under-damped PD controller to the origin (actions in
    [-1, 1])."""
    d = obs.shape[-1] // 2
    x, v = obs[..., :d], obs[..., d:]
    return jnp.clip(-kp * x - kd * v, -1.0, 1.0)
