"""brax's positional substep with the joints' position-level update written for the scene's
joint kinds alone (`positional_joints`): hinges and slides, as reacher's and
inverted_pendulum's joints are.

`brax.positional.joints.position_update` treats every joint as a 3-dof one
(`_sphericalize`): it computes the joint's intrinsic Euler construction
(`kinematics.axis_angle_ang`) and then, for each of the three angular axes, a signed angle
(an arctangent), its clip to the axis's limit, the quaternion of the clipped angle, a
rotation by it and a cross product (`limit_angle`), and for each of three slide axes a
clipped projection. For a hinge two of the three angular axes are locked (their limits are
[0, 0]) and for a slide all three are; on a locked axis the clipped angle is 0, its
quaternion the identity, and the axis's term is the cross product of its two reference
axes. On the hinge's own axis a0, with the joint frame (a0, a1, a2) right-handed and
orthonormal, the line of nodes n lies in a0's normal plane, n = cos(ph) a1 + sin(ph) a2, so
the term cross(rotate(a1, clip(ph) about a0), n) is sin(ph - clip(ph)) a0. Written so, per
link and vectorized over links (`joint_update`):

    c_k = rotate(a_k, j.rot)                           (the child's joint axes)
    n = normalize(cross(c_2, a_0))                     (the line of nodes)
    m = normalize((a_0 . c_0) c_0 + (a_0 . c_1) c_1)   (a_0 in the child's x-y plane)
    ph = atan2(cross(a_1, n) . a_0, a_1 . n)
    dq = -(sin(ph - clip(ph, lo_0, hi_0)) a_0 + cross(a_0, m) + cross(n, c_1))
    dx = -j.pos * (1 - any slide along that coordinate)
         - sum_k v_k (v_k . j.pos - clip(v_k . j.pos, lo_k, hi_k))

(lo_0 = hi_0 = 0 for a slide, whose angular axes are all locked; v_k the slide axes). These
are brax's values in exact arithmetic: the same function, to float32 round-off
(tests/test_positional_joints.py), except where brax's `normalize` meets a vector within
1e-8 of zero (a child axis turned 90 degrees off its hinge), which these scenes' joints do
not reach. The rest of the substep is brax's own code, in brax's order.

`step` also computes the joints' forces (`acceleration_update`) vectorized over the dofs
instead of brax's per-type `scan.link_types`, and (`hand=True`, as the plan's
`positional_joints` runs it) the conversions to link and joint frames, the inverse inertia,
the joint forces' move to the links and the integration by `tasks.physics.spring_adjoint`'s
hand-written VJPs, which brax's positional substep shares with the spring one.

What it is for: fewer XLA operations per substep, forward and in reverse mode, so a faster
update through the physics (on one CPU core the update's time at B = 32 is roughly its operation count
times a constant cost per operation; what it buys: docs/physics.md). The joints' position
corrections (`_translation_update`, `_rotation_update`) written over rows of links with
multiply-and-sum products gained nothing and were left out.

At a locked angle that is exactly zero (these planar scenes' out-of-plane rotations, every
step), brax's reverse mode passes part of the cotangent through `jnp.clip(angle, 0, 0)`,
a constant (JAX's maximum and minimum split a tie's cotangent): there the state's
cotangents differ from the ones here, which are the derivative of the function. The
policy's gradient through a rollout is the same to float32 round-off (tested).
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from brax import actuator, com, contact, kinematics
from brax.base import Force, Motion, Transform
from brax.positional import collisions, integrator
from brax.positional import joints as brax_joints
from brax.positional.base import State

import tasks.physics.spring_adjoint as sa
from tasks.physics.spring_adjoint import _dot, _rotate


class JointRows(NamedTuple):
    """Per link (leading axis), the constants `joint_update` reads, from the scene."""
    axes: np.ndarray      # (L, 3, 3) the joint frame's angular axes a_0, a_1, a_2
    lo0: np.ndarray       # (L,) the first angular axis's limits (0, 0 where locked)
    hi0: np.ndarray
    slides: np.ndarray    # (L, 3, 3) the slide axes v_k (zero rows where none)
    slide_lo: np.ndarray  # (L, 3) their limits
    slide_hi: np.ndarray
    keep: np.ndarray      # (L, 3) 1 - (any slide along that coordinate)


def joint_rows(sys) -> JointRows | str:
    """The scene's `JointRows`, or why `joint_update` does not model it (a string): every
    joint must be a hinge (one angular axis, no slide) or slides alone (no angular axis), on
    brax's right-handed joint frames; no free joint. Needs `sys`'s joint data concrete (not
    traced)."""
    if isinstance(sys.dof.motion.ang, jax.core.Tracer):
        return "its joint axes are traced (not known while tracing)"
    if "f" in sys.link_types:
        return "it has a free joint"
    num_links = sys.num_links()
    zero = Transform.zero((num_links,))
    limit, motion, frame, parity = jax.device_get(brax_joints._sphericalize(sys, zero))
    lo, hi = (np.asarray(x, np.float64) for x in limit)
    vel, ang = np.asarray(motion.vel), np.asarray(motion.ang)
    axes = np.asarray(frame.ang)
    slide_row = np.any(vel != 0, axis=-1)                     # (L, 3)
    turn_row = np.any(ang != 0, axis=-1)
    hinge = turn_row[:, 0] & ~turn_row[:, 1:].any(-1) & ~slide_row.any(-1)
    slide_only = ~turn_row.any(-1)
    if not np.all(hinge | slide_only):
        return "it has a joint that turns about more than one axis, or turns and slides"
    ang_lo = np.where(slide_row, 0.0, lo)                    # brax's padded angular limits
    ang_hi = np.where(slide_row, 0.0, hi)
    if np.any(ang_lo[:, 1:] != 0) or np.any(ang_hi[:, 1:] != 0):
        return "a joint's second or third angular axis is not locked"
    if np.any(np.asarray(parity) != 1):
        return "a joint frame is left-handed"
    right = np.cross(axes[:, 0], axes[:, 1])
    if not (np.allclose(right, axes[:, 2], atol=1e-6)
            and np.allclose(np.einsum("lij,lkj->lik", axes, axes), np.eye(3), atol=1e-6)):
        return "a joint frame is not orthonormal and right-handed"
    f32 = lambda x: np.asarray(x, np.float32)  # noqa: E731
    return JointRows(axes=f32(axes), lo0=f32(ang_lo[:, 0]), hi0=f32(ang_hi[:, 0]),
                     slides=f32(vel), slide_lo=f32(lo), slide_hi=f32(hi),
                     keep=f32(1 - np.any(vel != 0, axis=1)))


def _normalize(x):
    """brax.math.normalize of rows (..., 3) away from zero: x / |x|."""
    n = jnp.sqrt(jnp.sum(x * x, -1, keepdims=True))
    return x / (n + 1e-6 * (n == 0.0))


def joint_update(j: Transform, rows: JointRows) -> Transform:
    """The position-level displacements of `brax.positional.joints._three_dof_joint_update`
    in joint frames (links on the leading axis) for hinges and slides (the module
    docstring)."""
    a = jnp.asarray(rows.axes, j.pos.dtype)
    a0, a1 = a[:, 0], a[:, 1]
    c = _rotate(a, j.rot[:, None, :])
    n = _normalize(jnp.cross(c[:, 2], a0))
    m = _normalize(_dot(a0, c[:, 0]) * c[:, 0] + _dot(a0, c[:, 1]) * c[:, 1])
    ph = jnp.arctan2(jnp.sum(jnp.cross(a1, n) * a0, -1), jnp.sum(a1 * n, -1))
    off = jnp.sin(ph - jnp.clip(ph, rows.lo0, rows.hi0))
    dq = -(off[:, None] * a0 + jnp.cross(a0, m) + jnp.cross(n, c[:, 1]))
    v = jnp.asarray(rows.slides, j.pos.dtype)
    xp = jnp.sum(v * j.pos[:, None, :], -1)                   # (L, 3)
    past = xp - jnp.clip(xp, rows.slide_lo, rows.slide_hi)
    dx = -j.pos * rows.keep - jnp.sum(v * past[..., None], 1)
    return Transform(pos=dx, rot=dq)


def position_update(sys, state: State, rows: JointRows, hand: bool = False) -> Transform:
    """`brax.positional.joints.position_update(sys, state)` with the joints' displacements
    by `joint_update`; the rest is brax's code (`hand`: as `step`'s)."""
    p_idx = jnp.array(sys.link_parents)
    xi_p = state.x_i.concatenate(Transform.zero((1,))).take(p_idx)
    w2j = sa.world_to_joint if hand else kinematics.world_to_joint
    j, _, a_p, a_c = w2j(sys, state.x, state.xd)
    d_j = joint_update(j, rows)
    d_w = jax.tree.map(lambda x: _rotate(x, a_p.rot), d_j)
    i_inv = (sa.inv_inertia if hand else com.inv_inertia)(sys, state.x)
    i_inv_p = jax.vmap(jnp.multiply)(i_inv[p_idx], p_idx > -1)
    mass_inv = 1 / (sys.link.inertia.mass ** (1 - sys.spring_mass_scale))
    mass_inv_p = mass_inv[p_idx] * (p_idx > -1)
    dp_p_pos, dp_c_pos = jax.vmap(brax_joints._translation_update)(
        a_p, xi_p, i_inv_p, mass_inv_p, a_c, state.x_i, i_inv, mass_inv, -d_w.pos)
    dp_p_ang, dp_c_ang = jax.vmap(brax_joints._rotation_update)(
        xi_p, i_inv_p, state.x_i, i_inv, d_w.rot)
    dp_c = dp_c_pos * sys.joint_scale_pos + dp_c_ang * sys.joint_scale_ang
    dp_p = dp_p_pos * sys.joint_scale_pos + dp_p_ang * sys.joint_scale_ang
    dp_p = jax.tree.map(lambda f: jax.ops.segment_sum(f, p_idx, sys.num_links()), dp_p)
    return state.x_i + dp_c + dp_p


def acceleration_update(sys, state: State, tau: jax.Array, hand: bool = False) -> Force:
    """`brax.positional.joints.acceleration_update(sys, state, tau)` for a scene without free
    joints, vectorized over the dofs: per link, the sum of its dofs' tau times their axes,
    less the constraint damping of the joint motion (brax's `_damp`), then moved to the
    links' centres of mass by brax's tail as `tasks.physics.spring_adjoint` writes it (the spring
    substep's is the same): `_joint_to_link_forces` with its hand-written VJP (`hand`), or
    its forward through XLA's reverse mode."""
    link = jnp.asarray(sys.dof_link())
    num = sys.num_links()
    ang = jax.ops.segment_sum(tau[:, None] * sys.dof.motion.ang, link, num)
    vel = jax.ops.segment_sum(tau[:, None] * sys.dof.motion.vel, link, num)
    ang = ang - sys.link.constraint_ang_damping[:, None] * state.jd.ang
    vel = vel - sys.link.constraint_vel_damping[:, None] * state.jd.vel
    args = (tuple(sys.link_parents), ang, vel, state.a_p.rot, state.a_p.pos, state.a_c.pos,
            state.x_i.pos)
    a, v = (sa._joint_to_link_forces(*args) if hand
            else sa._joint_to_link_forces_forward(*args)[0])  # XLA's reverse mode of it
    return Force(ang=a, vel=v)


def integrate_xdd(sys, x_i: Transform, xd_i: Motion, xdd_i: Motion
                  ) -> tuple[Transform, Motion]:
    """`brax.positional.integrator.integrate_xdd(sys, x_i, xd_i, xdd_i)` by
    `tasks.physics.spring_adjoint`'s integration with its hand-written VJP: brax's positional
    integration, v' = a_v (v + dt a), w' = a_w (w + dt alpha) with a = exp(damping dt),
    then the positions and quaternions advanced by v' and w', is the spring integration
    with the delta-velocities a_v dt a and a_w dt alpha (the same values to float32
    round-off)."""
    dt = jnp.asarray(sys.opt.timestep, x_i.pos.dtype)
    a_v = jnp.exp(sys.vel_damping * dt)
    a_w = jnp.exp(sys.ang_damping * dt)
    pos, rot, vel, ang = sa._integrate(x_i.pos, x_i.rot, xd_i.vel, xd_i.ang,
                                       a_v * dt * xdd_i.vel, a_w * dt * xdd_i.ang, dt, a_v,
                                       a_w)
    return Transform(pos=pos, rot=rot), Motion(vel=vel, ang=ang)


def step(sys, state: State, act: jax.Array, debug: bool = False, *,
         rows: JointRows, hand: bool = False) -> State:
    """`brax.positional.pipeline.step` with `position_update` for the joints' position-level
    update and `acceleration_update` for their forces; every other line brax's (no fluid:
    a scene with fluid is refused upstream). `hand`: brax's `com.to_world`,
    `com.inv_inertia`, `kinematics.world_to_joint` and the integration by their hand-VJP
    versions in `tasks.physics.spring_adjoint` (the same values to float32 round-off)."""
    to_world = sa.to_world if hand else com.to_world
    inv_inertia = sa.inv_inertia if hand else com.inv_inertia
    world_to_joint = sa.world_to_joint if hand else kinematics.world_to_joint
    x_i_prev = state.x_i
    tau = actuator.to_tau(sys, act, state.q, state.qd)
    xdd_i = Motion.create(vel=sys.gravity)
    xf_i = acceleration_update(sys, state, tau, hand)
    xdd_i += Motion(
        ang=jax.vmap(lambda x, y: x @ y)(inv_inertia(sys, state.x), xf_i.ang),
        vel=jax.vmap(lambda x, y: x * y)(1 / state.mass, xf_i.vel))
    x_i, xd_i = (integrate_xdd if hand else integrator.integrate_xdd)(
        sys, state.x_i, state.xd_i, xdd_i)
    x, xd = to_world(sys, x_i, xd_i)
    state = state.replace(x=x, xd=xd, x_i=x_i, xd_i=xd_i)
    x_i = position_update(sys, state, rows, hand)
    x, _ = to_world(sys, x_i, xd_i)
    state = state.replace(x=x, x_i=x_i)
    c = contact.get(sys, x)
    x_i, dlambda = collisions.resolve_position(sys, state, x_i_prev, c)
    xd_i_prev = xd_i
    xd_i = integrator.project_xd(sys, x_i, x_i_prev)
    x, xd = to_world(sys, x_i, xd_i)
    state = state.replace(x=x, xd=xd, x_i=x_i, xd_i=xd_i)
    xdv_i = collisions.resolve_velocity(sys, state, xd_i_prev, c, dlambda)
    xd_i = integrator.integrate_xdv(sys, xd_i, xdv_i)
    x, xd = to_world(sys, x_i, xd_i)
    j, jd, a_p, a_c = world_to_joint(sys, x, xd)
    q, qd = kinematics.inverse(sys, j, jd)
    c = contact.get(sys, x) if debug else None
    return State(q, qd, x, xd, c, x_i, xd_i, j, jd, a_p, a_c, state.mass)
