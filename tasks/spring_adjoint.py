"""brax's spring substep with hand-written VJPs for some of its pieces (`hand_adjoint`).

`step` computes what `brax.spring.pipeline.step` computes, in brax's order and with brax's
own functions, except three pieces written here with their VJP by hand (`jax.custom_vjp`):
the inverse inertia in world frame (`inv_inertia`, for `brax.com.inv_inertia`), the
integration (`integrate`, for `brax.spring.integrator.integrate`: damp the velocities, add
the collision's delta-velocity, advance positions, rotate and renormalize the quaternions)
and the conversion from centre-of-mass to link frames (`to_world`, for `brax.com.to_world`).
Their forward values are brax's to float32 round-off and their VJPs are the same linear
maps as XLA's reverse mode of brax's code, in the state and in the system fields they read
(tests/test_hand_adjoint.py, which a wrong sign in any one term fails).

What it is for: ILD's update is mostly brax's physics backward (64-78% of it:
results/JOURNAL.md, session 46), and these hand-written backwards cost less inside the
substep scan than XLA's reverse mode of the same lines. Jitted alone they gain less or
nothing (32 hopper envs, `python results/substep/scripts/step_vjp_parts.py hopper`: VJPs
of 79, 80 and 80 us against XLA's 105, 84 and 78; one substep's 652 against 718). Paired
on one core (session 47, `python -m methods.ild.paired --variant task --variant
task,hand_adjoint`), the update ran
1.07x (hopper) and 1.08x (walker2d) faster with `integrate` alone, 1.14x (hopper) with
`integrate` and `to_world`, and 1.19-1.23x on hopper, walker2d, ant and humanoid with all
three (README ILD speed; results/JOURNAL.md, session 47).

The VJP of `integrate`, per link, for cotangents (gp, gr, gv, gw) of the outputs
(pos', rot', vel', ang'):
    v' = a_v v + dv,  w' = a_w w + dw,  pos' = pos + dt v',
    u = rot + (dt / 2) (0, w') * rot,  rot' = u / |u|        (* the quaternion product)
    gu = (gr - rot' <rot', gr>) / |u|                        (the normalization's VJP)
    g_rot = gu - (dt / 2) (0, w') * gu                       (left product by a pure
                                                              quaternion is skew)
    g_w' = gw + (dt / 2) vec(gu * conj(rot))                 (right product's transpose)
    g_v' = gv + dt gp;  g_v = a_v g_v',  g_dv = g_v';  g_w = a_w g_w',  g_dw = g_w'
and in dt, a_v, a_w (system fields): <gp, v'> + <gu, (0, w') * rot> / 2, <g_v', v>, <g_w', w>.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
from brax import actuator, contact, fluid, kinematics, math
from brax.base import Motion, Transform
from brax.spring import collisions, joints


def _pure(w):
    """(..., 3) angular velocities as pure quaternions (..., 4)."""
    return jnp.concatenate([jnp.zeros(w.shape[:-1] + (1,), w.dtype), w], -1)


def _qmul(u, v):
    """Quaternion products of two (..., 4) arrays, row by row."""
    return jax.vmap(math.quat_mul)(u.reshape(-1, 4), v.reshape(-1, 4)).reshape(u.shape)


def integrate(sys, x_i: Transform, xd_i: Motion, xdv_i: Motion) -> tuple[Transform, Motion]:
    """`brax.spring.integrator.integrate(sys, x_i, xd_i, xdv_i)` with a hand-written VJP (the
    module docstring); links on the leading axis, as brax's."""
    dt = jnp.asarray(sys.opt.timestep, x_i.pos.dtype)
    a_v = jnp.exp(sys.vel_damping * dt)
    a_w = jnp.exp(sys.ang_damping * dt)
    return _integrate(x_i, xd_i, xdv_i, dt, a_v, a_w)


def _forward(pos, rot, vel, ang, dvel, dang, dt, a_v, a_w):
    v = a_v * vel + dvel
    w = a_w * ang + dang
    wq = _pure(w)
    wq_rot = _qmul(wq, rot)
    u = rot + 0.5 * dt * wq_rot
    n = jnp.linalg.norm(u, axis=-1, keepdims=True)
    r = u / n
    return (pos + dt * v, r, v, w), (rot, vel, ang, v, r, n, wq, wq_rot, dt, a_v, a_w)


@jax.custom_vjp
def _op(pos, rot, vel, ang, dvel, dang, dt, a_v, a_w):
    return _forward(pos, rot, vel, ang, dvel, dang, dt, a_v, a_w)[0]


def _op_bwd(res, g):
    rot, vel, ang, v, r, n, wq, wq_rot, dt, a_v, a_w = res
    gp, gr, gv, gw = g
    gu = (gr - r * jnp.sum(r * gr, -1, keepdims=True)) / n
    g_rot = gu - 0.5 * dt * _qmul(wq, gu)
    conj = rot * jnp.array([1.0, -1.0, -1.0, -1.0], rot.dtype)
    g_v = gv + dt * gp
    g_w = gw + 0.5 * dt * _qmul(gu, conj)[..., 1:]
    g_dt = jnp.sum(gp * v) + 0.5 * jnp.sum(gu * wq_rot)
    return (gp, g_rot, a_v * g_v, a_w * g_w, g_v, g_w, g_dt, jnp.sum(g_v * vel),
            jnp.sum(g_w * ang))


_op.defvjp(_forward, _op_bwd)


def _integrate(x_i, xd_i, xdv_i, dt, a_v, a_w):
    pos, rot, vel, ang = _op(x_i.pos, x_i.rot, xd_i.vel, xd_i.ang, xdv_i.vel, xdv_i.ang,
                             dt, a_v, a_w)
    return Transform(pos=pos, rot=rot), Motion(vel=vel, ang=ang)


def _rotate(vec, quat):
    """`brax.math.rotate` of rows of (..., 3) by rows of (..., 4): the same formula (for a
    quaternion of any norm), batched."""
    s, u = quat[..., :1], quat[..., 1:]
    r = 2 * (_dot(u, vec) * u) + (s * s - _dot(u, u)) * vec
    return r + 2 * s * jnp.cross(u, vec)


def _dot(a, b):
    return jnp.sum(a * b, -1, keepdims=True)


def to_world(sys, x_i: Transform, xd_i: Motion) -> tuple[Transform, Motion]:
    """`brax.com.to_world(sys, x_i, xd_i)` with a hand-written VJP (the module docstring):
    the link frames and motions at the links' origins from those at their centres of mass."""
    pos, rot, vel, ang = _to_world(x_i.pos, x_i.rot, xd_i.vel, xd_i.ang,
                                   -sys.link.inertia.transform.pos)
    return Transform(pos=pos, rot=rot), Motion(vel=vel, ang=ang)


def _to_world_forward(pos_i, rot_i, vel_i, ang_i, c):
    r = _rotate(c, rot_i)  # brax: x_i.do(Transform(pos=c)), then a transform by x.pos - x_i.pos
    pos = pos_i + r
    p = pos - pos_i
    identity = jnp.broadcast_to(jnp.array([1.0, 0.0, 0.0, 0.0], rot_i.dtype), rot_i.shape)
    rot = _qmul(rot_i, identity)
    return (pos, rot, vel_i - jnp.cross(p, ang_i), ang_i), (rot_i, ang_i, c, p)


@jax.custom_vjp
def _to_world(pos_i, rot_i, vel_i, ang_i, c):
    return _to_world_forward(pos_i, rot_i, vel_i, ang_i, c)[0]


def _to_world_bwd(res, g):
    rot_i, ang_i, c, p = res
    g_pos, g_rot, g_vel, g_ang = g
    g_r = g_pos + jnp.cross(g_vel, ang_i)
    s, u = rot_i[..., :1], rot_i[..., 1:]
    g_s = _dot(g_r, 2 * s * c + 2 * jnp.cross(u, c))
    g_u = (2 * c * _dot(u, g_r) + 2 * _dot(u, c) * g_r - 2 * u * _dot(c, g_r)
           + 2 * s * jnp.cross(c, g_r))
    conj = rot_i * jnp.array([1.0, -1.0, -1.0, -1.0], rot_i.dtype)
    return (g_pos, g_rot + jnp.concatenate([g_s, g_u], -1), g_vel,
            g_ang + jnp.cross(p, g_vel), _rotate(g_r, conj))


_to_world.defvjp(_to_world_forward, _to_world_bwd)


def _axial(a):
    """(a32 - a23, a13 - a31, a21 - a12) of (..., 3, 3): <a, [u]x> = u . axial(a)."""
    return jnp.stack([a[..., 2, 1] - a[..., 1, 2], a[..., 0, 2] - a[..., 2, 0],
                      a[..., 1, 0] - a[..., 0, 1]], -1)


def _rotation_matrix(q):
    """The matrix of `brax.math.rotate` by quaternion rows q (..., 4) of any norm:
    M = 2 u u^T + (s^2 - u.u) I + 2 s [u]x."""
    s, u = q[..., 0, None, None], q[..., 1:]
    zero = jnp.zeros_like(u[..., 0])
    ux = jnp.stack([jnp.stack([zero, -u[..., 2], u[..., 1]], -1),
                    jnp.stack([u[..., 2], zero, -u[..., 0]], -1),
                    jnp.stack([-u[..., 1], u[..., 0], zero], -1)], -2)
    return (2 * u[..., :, None] * u[..., None, :]
            + (s * s - _dot(u, u)[..., None]) * jnp.eye(3, dtype=q.dtype) + 2 * s * ux)


def inv_inertia(sys, x: Transform) -> jax.Array:
    """`brax.com.inv_inertia(sys, x)` with a hand-written VJP: per link, M D M^T with M the
    rotation (`_rotation_matrix`) by x.rot * the inertia frame's rotation and D the inverse
    principal inertia (raised to 1 - spring_inertia_scale, as brax does). Its VJP for a
    cotangent G: G_M = (G + G^T) M D, then through M's quaternion (s, u):
    g_s = 2 s tr G_M + 2 u . axial(G_M), g_u = 2 (G_M + G_M^T) u - 2 tr(G_M) u + 2 s axial(G_M),
    then through the product x.rot * r: g * conj(r) to x.rot, conj(x.rot) * g to r; and
    g_D = diag(M^T G M)."""
    i_rot = sys.link.inertia.transform.rot
    d = 1 / jnp.diagonal(sys.link.inertia.i, axis1=-2, axis2=-1) ** (
        1 - sys.spring_inertia_scale)
    return _inv_inertia(x.rot, i_rot, d)


def _inv_inertia_forward(x_rot, i_rot, d):
    ri = _qmul(x_rot, i_rot)

    def one(ri, d):  # brax's own sequence: rotate the rows, then the columns
        rows = jax.vmap(math.rotate, in_axes=[0, None])(jnp.diag(d), ri)
        return jax.vmap(math.rotate, in_axes=[0, None])(rows.T, ri)
    return jax.vmap(one)(ri, d), (x_rot, ri, i_rot, d)


@jax.custom_vjp
def _inv_inertia(x_rot, i_rot, d):
    return _inv_inertia_forward(x_rot, i_rot, d)[0]


def _inv_inertia_bwd(res, g):
    x_rot, ri, i_rot, d = res
    m = _rotation_matrix(ri)
    g_m = (g + jnp.swapaxes(g, -1, -2)) @ (m * d[..., None, :])
    s, u = ri[..., :1], ri[..., 1:]
    tr = jnp.trace(g_m, axis1=-2, axis2=-1)[..., None]
    ax = _axial(g_m)
    g_u = (2 * ((g_m + jnp.swapaxes(g_m, -1, -2)) @ u[..., None])[..., 0] - 2 * tr * u
           + 2 * s * ax)
    g_ri = jnp.concatenate([2 * s * tr + 2 * _dot(u, ax), g_u], -1)
    flip = jnp.array([1.0, -1.0, -1.0, -1.0], ri.dtype)  # conjugation
    g_d = jnp.einsum("...ik,...ij,...jk->...k", m, g, m)
    return _qmul(g_ri, i_rot * flip), _qmul(x_rot * flip, g_ri), g_d


_inv_inertia.defvjp(_inv_inertia_forward, _inv_inertia_bwd)


def step(sys, state, act, debug: bool = False):
    """`brax.spring.pipeline.step(sys, state, act)` (brax 0.14.2), its inverse inertia, its
    integration and its conversion to world frames through `inv_inertia`, `integrate` and
    `to_world` above; everything else is brax's own functions in brax's order."""
    state = state.replace(i_inv=inv_inertia(sys, state.x))
    tau = actuator.to_tau(sys, act, state.q, state.qd)
    xdd_i = Motion.create(vel=sys.gravity)
    xf_i = joints.resolve(sys, state, tau)
    if sys.enable_fluid:
        inertia = sys.link.inertia.i ** (1 - sys.spring_inertia_scale)
        xf_i += fluid.force(sys, state.x, state.xd, state.mass, inertia)
    xdd_i += Motion(
        ang=jax.vmap(lambda x, y: x @ y)(state.i_inv, xf_i.ang),
        vel=jax.vmap(lambda x, y: x / y)(xf_i.vel, state.mass),
    )
    state = state.replace(xd_i=state.xd_i + xdd_i * sys.opt.timestep)
    xdv_i = collisions.resolve(sys, state)
    x_i, xd_i = integrate(sys, state.x_i, state.xd_i, xdv_i)
    x, xd = to_world(sys, x_i, xd_i)
    state = state.replace(x=x, xd=xd, x_i=x_i, xd_i=xd_i)
    j, jd, a_p, a_c = kinematics.world_to_joint(sys, x, xd)
    q, qd = kinematics.inverse(sys, j, jd)
    return state.replace(q=q, qd=qd, a_p=a_p, a_c=a_c, j=j, jd=jd,
                         contact=contact.get(sys, x) if debug else None)
