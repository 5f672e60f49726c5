"""Swing-up acrobot, the paper's brax-v1 task rebuilt as a minimal two-link MJCF.

Facts: shared/reference/acrobot_facts.md. Physics dt 0.0025 x 4 substeps = 0.01 s per step.
Each link's inertia about its centre of mass is brax v1's default for a body given none,
(1, 1, 1) (tasks/assets/acrobot.xml), not the capsule's own.

Observation: (theta1, theta2, dtheta1, dtheta2), angles wrapped to [-pi, pi] (as v1's
joint angles, read from relative rotations, were). Action: one elbow torque in [-1, 1]
(gear 25). Reward per step, on the state after the step:
    10 - (theta1^2 + theta2^2) - 1e-3 (dtheta1^2 + dtheta2^2)
Hanging (theta1 = pi) earns about 0.13 per step, upright earns 10. No termination.

`Acrobot.closed_form_step` is the same control step written as a double pendulum's
equations of motion (what this scene needs, nothing more):
`tasks.physics.transforms.with_closed_form_adjoint` differentiates it in place of brax's
reverse mode.
"""
from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np
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

    def closed_form_step(self, q: jax.Array, qd: jax.Array, action: jax.Array):
        """One control step (`n_frames` semi-implicit Euler substeps, as brax's generalized
        integrator) of this two-link chain in closed form, from (q, qd, action) to
        (q', qd', x.pos, x.rot, xd.vel, xd.ang) of the step's end state: brax's values to
        float32 round-off (tests/test_closed_form_adjoint.py). Its parameters are read from
        `sys`; a scene it does not describe (damping, armature, joint limits, other than two
        y-hinges in a chain) is refused."""
        sys = self.sys
        ok = (sys.num_links() == 2 and sys.qd_size() == 2 and sys.act_size() == 1
              and sys.dof.limit is None and not np.any(np.asarray(sys.dof.damping))
              and not np.any(np.asarray(sys.dof.armature)))
        if not ok:
            raise ValueError("Acrobot.closed_form_step models two undamped y-hinges in a chain "
                             "with no armature or joint limits; this scene differs: "
                             "leave closed_form_adjoint False")
        m1, m2 = sys.link.inertia.mass
        lc1, lc2 = sys.link.inertia.transform.pos[:, 2]
        i1, i2 = sys.link.inertia.i[:, 1, 1]
        base, l1 = sys.link.transform.pos[0], sys.link.transform.pos[1, 2]
        g, dt = -sys.gravity[2], sys.opt.timestep
        lo, hi = sys.actuator.ctrl_range[0]
        tau2 = sys.actuator.gear[0] * jnp.clip(action[0], lo, hi)

        def substep(carry, _):
            q, qd = carry
            c2, s2, s12 = jnp.cos(q[1]), jnp.sin(q[1]), jnp.sin(q[0] + q[1])
            m11 = i1 + i2 + m1 * lc1 ** 2 + m2 * (l1 ** 2 + lc2 ** 2 + 2 * l1 * lc2 * c2)
            m12 = i2 + m2 * (lc2 ** 2 + l1 * lc2 * c2)
            m22 = i2 + m2 * lc2 ** 2
            h = m2 * l1 * lc2 * s2
            f1 = (h * (2 * qd[0] * qd[1] + qd[1] ** 2) + (m1 * lc1 + m2 * l1) * g * jnp.sin(q[0])
                  + m2 * lc2 * g * s12)
            f2 = tau2 - h * qd[0] ** 2 + m2 * lc2 * g * s12
            det = m11 * m22 - m12 * m12
            qdd = jnp.stack([m22 * f1 - m12 * f2, m11 * f2 - m12 * f1]) / det
            qd = qd + qdd * dt
            return (q + qd * dt, qd), None

        (q, qd), _ = jax.lax.scan(substep, (q, qd), None, self._n_frames)
        a1, a2 = q[0], q[0] + q[1]
        zero = jnp.zeros_like(a1)
        pos = jnp.stack([base, base + l1 * jnp.stack([jnp.sin(a1), zero, jnp.cos(a1)])])
        rot = jnp.stack([jnp.stack([jnp.cos(a / 2), zero, jnp.sin(a / 2), zero])
                         for a in (a1, a2)])
        vel = jnp.stack([jnp.zeros(3), l1 * qd[0] * jnp.stack([jnp.cos(a1), zero, -jnp.sin(a1)])])
        ang = jnp.stack([jnp.stack([zero, w, zero]) for w in (qd[0], qd[0] + qd[1])])
        return q, qd, pos, rot, vel, ang

    def _get_obs(self, ps) -> jax.Array:
        return jnp.concatenate([wrap_angle(ps.q), ps.qd])
