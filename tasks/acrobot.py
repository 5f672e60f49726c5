"""Swing-up acrobot, the paper's brax-v1 task rebuilt as a minimal two-link MJCF.

Facts: shared/reference/acrobot_facts.md. Physics dt 0.0025 x 4 substeps = 0.01 s per step.
Each link's inertia about its centre of mass is brax v1's default for a body given none,
(1, 1, 1) (tasks/assets/acrobot.xml), not the capsule's own.

Observation: (theta1, theta2, dtheta1, dtheta2), angles wrapped to [-pi, pi] (as v1's
joint angles, read from relative rotations, were). Action: one elbow torque in [-1, 1]
(gear 25). Reward per step, on the state after the step:
    10 - (theta1^2 + theta2^2) - 1e-3 (dtheta1^2 + dtheta2^2)
Hanging (theta1 = pi) earns about 0.13 per step, upright earns 10. No termination.
"""
from __future__ import annotations

import os

import jax
import jax.numpy as jnp
from brax.envs.base import PipelineEnv, State
from brax.io import mjcf

ASSET = os.path.join(os.path.dirname(__file__), "assets", "acrobot.xml")


def wrap_angle(q: jax.Array) -> jax.Array:
    return jnp.arctan2(jnp.sin(q), jnp.cos(q))


class Acrobot(PipelineEnv):
    def __init__(self, backend: str = "generalized", velocity_cost: float = 1e-3,
                 reset_noise_scale: float = 0.01, **kwargs):
        sys = mjcf.load(ASSET)
        kwargs.setdefault("n_frames", 4)
        super().__init__(sys=sys, backend=backend, **kwargs)
        self._velocity_cost = velocity_cost
        self._reset_noise_scale = reset_noise_scale

    def reset(self, rng: jax.Array) -> State:
        k_q, k_qd = jax.random.split(rng)
        s = self._reset_noise_scale
        q = jnp.array([jnp.pi, 0.0]) + jax.random.uniform(k_q, (2,), minval=-s, maxval=s)
        qd = jax.random.uniform(k_qd, (2,), minval=-s, maxval=s)
        ps = self.pipeline_init(q, qd)
        zero = jnp.zeros(())
        return State(ps, self._get_obs(ps), zero, zero, {}, {})

    def step(self, state: State, action: jax.Array) -> State:
        ps = self.pipeline_step(state.pipeline_state, jnp.clip(action, -1.0, 1.0))
        obs = self._get_obs(ps)
        theta, dtheta = obs[:2], obs[2:]
        reward = 10.0 - jnp.sum(theta ** 2) - self._velocity_cost * jnp.sum(dtheta ** 2)
        return state.replace(pipeline_state=ps, obs=obs, reward=reward)

    def _get_obs(self, ps) -> jax.Array:
        return jnp.concatenate([wrap_angle(ps.q), ps.qd])
