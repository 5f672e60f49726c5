"""brax's spring substep with hand-written VJPs for some of its pieces (`hand_adjoint`).

`step` computes what `brax.spring.pipeline.step` computes, in brax's order and with brax's
own functions, except six pieces written here with their VJP by hand (`jax.custom_vjp`):
- the inverse inertia in world frame (`inv_inertia`, for `brax.com.inv_inertia`);
- the joint forces' move from joint frames to the links' centres of mass, the tail of
  `brax.spring.joints.resolve` (`joints_resolve`; the per-joint-type forces stay brax's);
- the contact impulses' move to the links' centres of mass, their averaging and conversion
  to delta-velocities, the tail of `brax.spring.collisions.resolve` (`collisions_resolve`;
  the contacts and each contact's impulse stay brax's);
- the integration (`integrate`, for `brax.spring.integrator.integrate`: damp the
  velocities, add the collision's delta-velocity, advance positions, rotate and renormalize
  the quaternions);
- the conversion from centre-of-mass to link frames (`to_world`, for `brax.com.to_world`);
- the conversion to joint frames and motions (`world_to_joint`, for
  `brax.kinematics.world_to_joint`).
Their forward values are brax's (bit for bit, or to float32 round-off for the inverse
inertia, integration and conversion to link frames) and their VJPs are the same linear
maps as XLA's reverse mode of brax's code, in the state and in the system fields they read
(tests/test_hand_adjoint.py, which a wrong sign or a swapped factor in any one term
fails).

What it is for: an update through the physics is mostly brax's physics backward, and these
hand-written backwards cost less inside the substep scan than XLA's reverse mode of the same
lines (what each buys: docs/physics.md; what did not pay:
docs/decisions/physics-rewrites.md). `hinge` (`step(..., hinges=True)`, the plan's
`hinge_forces`) is brax's 1-dof joint force for a hinge alone, the same values in fewer
operations (XLA's reverse mode, no hand-written VJP). In the same way, `planar_root` is
brax's `_three_dof` for a planar root (hopper's and walker2d's: two unlimited slides and a
hinge, `step(..., planar=True)`, the plan's `planar_root`), which needs none of the Euler
angles brax computes for it, and `rotary_two` and `rotary_three` are brax's `_two_dof` and
`_three_dof` for joints that only turn (humanoid's: `step(..., rotary=True)`, the plan's
`rotary_joints`): the same values in fewer operations.

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

import functools

import jax
import jax.numpy as jnp
import numpy as np
from brax import actuator, contact, fluid, kinematics, math, scan
from brax.base import QD_WIDTHS, Force, Motion, Transform
from brax.spring import joints
from jax.ad_checkpoint import checkpoint_name


_W2J, _INV = "spring_adjoint.world_to_joint", "spring_adjoint.inv_inertia"
SAVED_RESIDUALS = (_W2J, _INV)
"""The `jax.checkpoint` names of the residuals `world_to_joint`'s and `inv_inertia`'s forwards
hand their VJPs. A substep checkpoint whose policy saves them
(`jax.checkpoint_policies.save_only_these_names(*SAVED_RESIDUALS)`,
`tasks.physics.transforms.with_hand_adjoint(saved_residuals=True)`, the plan's
`saved_residuals`) stores them in the forward instead of recomputing them next to the
backward, where XLA's CPU backend fuses their quaternion products and cross products into
the VJPs' loops and evaluates them again per output entry. Without such a policy the names
do nothing."""


def _named(name: str, residuals: tuple) -> tuple:
    """The state-dependent `residuals` of a piece, named `name` for a checkpoint policy (the
    system's constants beside them are left unnamed: a policy need not store them)."""
    return tuple(checkpoint_name(r, name) for r in residuals)


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
    pos, rot, vel, ang = _integrate(x_i.pos, x_i.rot, xd_i.vel, xd_i.ang, xdv_i.vel,
                                    xdv_i.ang, dt, a_v, a_w)
    return Transform(pos=pos, rot=rot), Motion(vel=vel, ang=ang)


def _integrate_forward(pos, rot, vel, ang, dvel, dang, dt, a_v, a_w):
    v = a_v * vel + dvel
    w = a_w * ang + dang
    wq = _pure(w)
    wq_rot = _qmul(wq, rot)
    u = rot + 0.5 * dt * wq_rot
    n = jnp.linalg.norm(u, axis=-1, keepdims=True)
    r = u / n
    return (pos + dt * v, r, v, w), (rot, vel, ang, v, r, n, wq, wq_rot, dt, a_v, a_w)


@jax.custom_vjp
def _integrate(pos, rot, vel, ang, dvel, dang, dt, a_v, a_w):
    return _integrate_forward(pos, rot, vel, ang, dvel, dang, dt, a_v, a_w)[0]


def _integrate_bwd(res, g):
    rot, vel, ang, v, r, n, wq, wq_rot, dt, a_v, a_w = res
    gp, gr, gv, gw = g
    gu = (gr - r * _dot(r, gr)) / n
    g_rot = gu - 0.5 * dt * _qmul(wq, gu)
    g_v = gv + dt * gp
    g_w = gw + 0.5 * dt * _qmul(gu, math.quat_inv(rot))[..., 1:]
    g_dt = jnp.sum(gp * v) + 0.5 * jnp.sum(gu * wq_rot)
    return (gp, g_rot, a_v * g_v, a_w * g_w, g_v, g_w, g_dt, jnp.sum(g_v * vel),
            jnp.sum(g_w * ang))


_integrate.defvjp(_integrate_forward, _integrate_bwd)


def _rotate(vec, quat):
    """`brax.math.rotate` of rows of (..., 3) by rows of (..., 4): the same formula (for a
    quaternion of any norm), batched."""
    s, u = quat[..., :1], quat[..., 1:]
    r = 2 * (_dot(u, vec) * u) + (s * s - _dot(u, u)) * vec
    return r + 2 * s * jnp.cross(u, vec)


def _dot(a, b):
    return jnp.sum(a * b, -1, keepdims=True)


def _rotate_vjp_quat(vec, quat, g):
    """The VJP of `_rotate(vec, quat)` in the quaternion (s, u), for a cotangent g of the
    rotated vector: g_s = g . (2 s vec + 2 u x vec),
    g_u = 2 vec (u . g) + 2 (u . vec) g - 2 u (vec . g) + 2 s vec x g. (In the vector it is
    `_rotate(g, quat_inv(quat))`: the transpose of the rotation matrix.)"""
    s, u = quat[..., :1], quat[..., 1:]
    g_s = _dot(g, 2 * s * vec + 2 * jnp.cross(u, vec))
    g_u = (2 * vec * _dot(u, g) + 2 * _dot(u, vec) * g - 2 * u * _dot(vec, g)
           + 2 * s * jnp.cross(vec, g))
    return jnp.concatenate([g_s, g_u], -1)


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
    return (g_pos, g_rot + _rotate_vjp_quat(c, rot_i, g_r), g_vel,
            g_ang + jnp.cross(p, g_vel), _rotate(g_r, math.quat_inv(rot_i)))


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
    return jax.vmap(one)(ri, d), (*_named(_INV, (x_rot, ri)), i_rot, d)


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
    g_d = jnp.einsum("...ik,...ij,...jk->...k", m, g, m)
    return _qmul(g_ri, math.quat_inv(i_rot)), _qmul(math.quat_inv(x_rot), g_ri), g_d


_inv_inertia.defvjp(_inv_inertia_forward, _inv_inertia_bwd)


def world_to_joint(sys, x: Transform, xd: Motion
                   ) -> tuple[Transform, Motion, Transform, Transform]:
    """`brax.kinematics.world_to_joint(sys, x, xd)` with a hand-written VJP: per link, its
    parent's frame and motion (x_p, xd_p: the world's, zero, for a root), the joint frame on
    the parent a_p = x_p . link.transform . link.joint and on the link
    a_c = x . link.joint, the joint transform j = a_c in a_p's basis, and the joint motion
    jd = R(a_p)^T (xd - xd_p + (x_p.pos - a_p.pos) x xd_p.ang, xd.ang - xd_p.ang). Its VJP
    chains those compositions backwards (`_rotate_vjp_quat`, the quaternion product's
    transposes), the gathers from the parents becoming sums into them; it also covers the
    system's link and joint frames (`link.transform`, `link.joint`)."""
    out = _world_to_joint(tuple(sys.link_parents), x.pos, x.rot, xd.vel, xd.ang,
                          sys.link.transform.pos, sys.link.transform.rot,
                          sys.link.joint.pos, sys.link.joint.rot)
    j_pos, j_rot, jd_vel, jd_ang, ap_pos, ap_rot, ac_pos, ac_rot = out
    return (Transform(pos=j_pos, rot=j_rot), Motion(vel=jd_vel, ang=jd_ang),
            Transform(pos=ap_pos, rot=ap_rot), Transform(pos=ac_pos, rot=ac_rot))


def _compose(pos, rot, t_pos, t_rot):
    """`Transform(pos, rot).do(Transform(t_pos, t_rot))`, batched."""
    return pos + _rotate(t_pos, rot), _qmul(rot, t_rot)


def _world_to_joint_forward(parents, pos, rot, vel, ang, lt_pos, lt_rot, lj_pos, lj_rot):
    xp_pos = _from_parents(parents, pos)  # brax: the world's row, taken with mode='wrap'
    xp_rot = _from_parents(parents, rot, world=[1.0, 0.0, 0.0, 0.0])
    xdp_vel, xdp_ang = _from_parents(parents, vel), _from_parents(parents, ang)
    t1_pos, t1_rot = _compose(xp_pos, xp_rot, lt_pos, lt_rot)
    ap_pos, ap_rot = _compose(t1_pos, t1_rot, lj_pos, lj_rot)
    ac_pos, ac_rot = _compose(pos, rot, lj_pos, lj_rot)
    cap = math.quat_inv(ap_rot)
    d = ac_pos - ap_pos
    p = xp_pos - ap_pos
    e_v = vel - (xdp_vel - jnp.cross(p, xdp_ang))
    e_w = ang - xdp_ang
    out = (_rotate(d, cap), _qmul(cap, ac_rot), _rotate(e_v, cap), _rotate(e_w, cap),
           ap_pos, ap_rot, ac_pos, ac_rot)
    return out, (*_named(_W2J, (rot, xp_rot, t1_rot, ap_rot, ac_rot, d, p, e_v, e_w,
                                xdp_ang)), lt_pos, lt_rot, lj_pos, lj_rot)


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _world_to_joint(parents, pos, rot, vel, ang, lt_pos, lt_rot, lj_pos, lj_rot):
    return _world_to_joint_forward(parents, pos, rot, vel, ang, lt_pos, lt_rot, lj_pos,
                                   lj_rot)[0]


def _compose_bwd(rot, t_pos, t_rot, g_pos, g_rot):
    """The VJP of `_compose(pos, rot, t_pos, t_rot)` in (rot, t_pos, t_rot); in pos it is
    g_pos."""
    inv = math.quat_inv(rot)
    return (_rotate_vjp_quat(t_pos, rot, g_pos) + _qmul(g_rot, math.quat_inv(t_rot)),
            _rotate(g_pos, inv), _qmul(inv, g_rot))


def _world_to_joint_bwd(parents, res, g):
    rot, xp_rot, t1_rot, ap_rot, ac_rot, d, p, e_v, e_w, xdp_ang, lt_pos, lt_rot, lj_pos, \
        lj_rot = res
    gj_pos, gj_rot, gjd_vel, gjd_ang, g_ap_pos, g_ap_rot, g_ac_pos, g_ac_rot = g
    cap = math.quat_inv(ap_rot)
    # j.pos = R(cap) d, j.rot = cap * a_c.rot, jd = R(cap) e: R(cap)^T = R(a_p.rot)
    g_d, g_ev, g_ew = _rotate(gj_pos, ap_rot), _rotate(gjd_vel, ap_rot), _rotate(gjd_ang, ap_rot)
    g_cap = (_rotate_vjp_quat(d, cap, gj_pos) + _rotate_vjp_quat(e_v, cap, gjd_vel)
             + _rotate_vjp_quat(e_w, cap, gjd_ang) + _qmul(gj_rot, math.quat_inv(ac_rot)))
    g_ac_rot = g_ac_rot + _qmul(ap_rot, gj_rot)
    g_ap_rot = g_ap_rot + math.quat_inv(g_cap)
    # d = a_c.pos - a_p.pos; e_v = vel - (xd_p.vel - p x xd_p.ang), p = x_p.pos - a_p.pos
    g_p = jnp.cross(xdp_ang, g_ev)
    g_ac_pos = g_ac_pos + g_d
    g_ap_pos = g_ap_pos - g_d - g_p
    g_xdp_ang = jnp.cross(g_ev, p) - g_ew
    # a_c = x . link.joint; a_p = t1 . link.joint; t1 = x_p . link.transform
    g_rot, g_lj_pos, g_lj_rot = _compose_bwd(rot, lj_pos, lj_rot, g_ac_pos, g_ac_rot)
    g_t1_rot, g_lj_pos_p, g_lj_rot_p = _compose_bwd(t1_rot, lj_pos, lj_rot, g_ap_pos, g_ap_rot)
    g_xp_rot, g_lt_pos, g_lt_rot = _compose_bwd(xp_rot, lt_pos, lt_rot, g_ap_pos, g_t1_rot)
    # the gathers from the parents: each link's cotangent flows into its parent's row
    to_parents = functools.partial(_to_parents, parents)
    return (g_ac_pos + to_parents(g_p + g_ap_pos), g_rot + to_parents(g_xp_rot),
            g_ev - to_parents(g_ev), g_ew + to_parents(g_xdp_ang), g_lt_pos, g_lt_rot,
            g_lj_pos + g_lj_pos_p, g_lj_rot + g_lj_rot_p)


_world_to_joint.defvjp(_world_to_joint_forward, _world_to_joint_bwd)


def joints_resolve(sys, state, tau: jax.Array, hinges: bool = False,
                   planar: bool = False, rotary: bool = False) -> Force:
    """`brax.spring.joints.resolve(sys, state, tau)`: the joints' constraint forces in joint
    frames by brax's own per-type functions (XLA's reverse mode), then moved to the links'
    centres of mass in world frame with a hand-written VJP (`_joint_to_link_forces`).
    `hinges`: the 1-dof joints' forces by `hinge` instead of brax's `_one_dof` (for a scene
    whose 1-dof joints are all hinges: `only_hinges`). `planar`: the 3-dof joints' forces by
    `planar_root` instead of brax's `_three_dof` (for a scene whose 3-dof joints are all
    planar roots: `planar_roots`). `rotary`: the 2- and 3-dof joints' forces by `rotary_two`
    and `rotary_three` (for a scene whose 2- and 3-dof joints only turn: `rotary_joints`)."""
    one_dof = hinge if hinges else joints._one_dof
    two_dof, three_dof = joints._two_dof, joints._three_dof
    if rotary:
        if planar or not rotary_joints(sys):
            raise ValueError("rotary: the scene's 2- and 3-dof joints do not all only turn")
        two_dof, three_dof = rotary_two, rotary_three
    if planar:
        rows = planar_roots(sys)
        if rows is None:
            raise ValueError("planar: the scene's 3-dof joints are not all planar roots "
                             "(two unlimited slides and one unlimited hinge, in one order)")
        three_dof = functools.partial(planar_root, slides=rows[0], turn=rows[1])

    def j_fn(typ, link, j, jd, dof, tau):  # brax's, as in joints.resolve
        reshape_fn = lambda x: x.reshape((j.pos.shape[0], -1) + x.shape[1:])  # noqa: E731
        tau, dof = jax.tree.map(reshape_fn, (tau, dof))
        j_fn_map = {"f": joints._free, "1": one_dof, "2": two_dof, "3": three_dof}
        return jax.vmap(j_fn_map[typ])(link, j, jd, dof, tau)
    jf = scan.link_types(sys, j_fn, "llldd", "l", sys.link, state.j, state.jd, sys.dof, tau)
    ang, vel = _joint_to_link_forces(tuple(sys.link_parents), jf.ang, jf.vel,
                                     state.a_p.rot, state.a_p.pos, state.a_c.pos,
                                     state.x_i.pos)
    return Force(ang=ang, vel=vel)


def _dof_types(sys, types: str):
    """A (dofs,) bool mask of the dofs whose joint's type is in `types` ('1', '23', ...), or
    None where the dof axes are traced (not known while tracing)."""
    if any(isinstance(x, jax.core.Tracer) for x in (sys.dof.motion.vel, sys.dof.motion.ang)):
        return None
    return np.array([t in types for t in sys.link_types for _ in range(QD_WIDTHS[t])], bool)


def only_hinges(sys) -> bool:
    """Whether every 1-dof joint of `sys` is a hinge (rotates, does not slide), from its
    dof axes: where `hinge` may stand for brax's `_one_dof`. False where the axes are traced
    (not known while tracing)."""
    one = _dof_types(sys, "1")
    if one is None:
        return False
    vel, ang = np.asarray(sys.dof.motion.vel)[one], np.asarray(sys.dof.motion.ang)[one]
    return bool(np.all(vel == 0) and np.all(np.any(ang != 0, axis=-1)))


def hinge(link, j: Transform, jd: Motion, dof, tau: jax.Array) -> Force:
    """`brax.spring.joints._one_dof` for a hinge: brax's formula with the terms that a
    hinge multiplies by zero (the slide's projections, force and limit, the second axis's
    pin) left out, and only the one joint angle the limit reads computed (`psi` of
    `kinematics.axis_angle_ang`). The same values as brax's, bit for bit in one call
    (tests/test_hand_adjoint.py; fused into a whole rollout, to float32 round-off), in
    fewer operations forward and in XLA's reverse mode (hopper's update about 4% fewer)."""
    frame, _ = kinematics.link_to_joint_frame(dof.motion)
    a0, a1, a2 = frame.ang[0], frame.ang[1], frame.ang[2]
    vel = -j.pos * link.constraint_stiffness - jd.vel * link.constraint_vel_damping
    ang = -1 * link.constraint_stiffness * jnp.cross(a0, math.rotate(a0, j.rot))
    ang = ang + tau * a0 - link.constraint_ang_damping * jd.ang
    if dof.limit is not None:
        lon, _ = math.normalize(jnp.cross(math.rotate(a2, j.rot), a0))
        dang = _limit_excess(math.signed_angle(a0, a1, lon), dof.limit)
        ang = ang - link.constraint_limit_stiffness * a0 * dang
    return Force(ang=ang, vel=vel)


def planar_roots(sys):
    """For a scene whose 3-dof joints are all planar roots, as hopper's and walker2d's (two
    slides and one hinge, none limited, their rows in the same order in every such joint):
    (the slides' rows, the hinge's row) of each joint's three dofs, read from the system's
    dof axes and limits; None for any other scene, one without 3-dof joints, or one whose
    axes or limits are traced (not known while tracing)."""
    three = _dof_types(sys, "3")
    if three is None or not three.any() or any(
            isinstance(x, jax.core.Tracer) for x in sys.dof.limit or ()):
        return None
    vel = np.asarray(sys.dof.motion.vel)[three].reshape(-1, 3, 3)
    ang = np.asarray(sys.dof.motion.ang)[three].reshape(-1, 3, 3)
    slide, turn = np.any(vel != 0, -1), np.any(ang != 0, -1)  # (joints, 3 rows)
    if np.any(slide & turn) or np.any(slide.sum(-1) != 2) or np.any(turn.sum(-1) != 1):
        return None
    if np.any(slide != slide[0]):  # one order of rows for every 3-dof joint
        return None
    if sys.dof.limit is not None:
        lo, hi = (np.asarray(x)[three] for x in sys.dof.limit)
        if np.any(np.isfinite(lo)) or np.any(np.isfinite(hi)):
            return None
    rows = np.flatnonzero(slide[0])
    return (int(rows[0]), int(rows[1])), int(np.flatnonzero(turn[0])[0])


def planar_root(link, j: Transform, jd: Motion, dof, tau: jax.Array, slides: tuple,
                turn: int) -> Force:
    """`brax.spring.joints._three_dof` for a planar root (rows `slides` slide, row `turn`
    turns, no limits: `planar_roots`): brax's formula without the terms such a joint
    multiplies by zero (the other rows' axes, the Euler angles and the limits, whose
    infinite bounds are never passed), the same values as brax's in fewer operations."""
    frame, parity = kinematics.link_to_joint_frame(dof.motion)
    vel = -j.pos * link.constraint_stiffness
    vel += -jd.vel * link.constraint_vel_damping
    s0, s1 = dof.motion.vel[slides[0]], dof.motion.vel[slides[1]]
    vel -= jnp.dot(s0, vel) * s0 + jnp.dot(s1, vel) * s1
    ang = -1.0 * link.constraint_ang_damping * jd.ang
    # the hinge's torque axis: brax's axis_angle_ang's axes are (frame x, child y, child z)
    axis = frame.ang[0] if turn == 0 else math.rotate(frame.ang[turn], j.rot)
    axis = axis * parity if turn == 2 else axis
    ang += tau[turn] * axis
    vel += tau[slides[0]] * s0 + tau[slides[1]] * s1
    a = dof.motion.ang[turn]
    ang += -1 * link.constraint_stiffness * jnp.cross(a, math.rotate(a, j.rot))
    return Force(ang=ang, vel=vel)


def rotary_joints(sys) -> bool:
    """Whether the scene has 2- or 3-dof joints and every one of them only turns (each of
    its rows an axis of rotation, none a slide), as humanoid's: where `rotary_two` and
    `rotary_three` may stand for brax's `_two_dof` and `_three_dof`. False where the axes
    are traced (not known while tracing)."""
    multi = _dof_types(sys, "23")
    if multi is None:
        return False
    vel, ang = np.asarray(sys.dof.motion.vel)[multi], np.asarray(sys.dof.motion.ang)[multi]
    return bool(multi.any() and np.all(vel == 0) and np.all(np.any(ang != 0, axis=-1)))


def _limit_excess(angle, limit):
    """How far each angle is past its limits (0 within them), as brax's joint forces."""
    limit_min, limit_max = limit
    dang = jnp.where(angle < limit_min, angle - limit_min, 0)
    return jnp.where(angle > limit_max, angle - limit_max, dang)


def rotary_two(link, j: Transform, jd: Motion, dof, tau: jax.Array) -> Force:
    """`brax.spring.joints._two_dof` for a joint that turns about both its axes
    (`rotary_joints`): brax's formula without the terms such a joint multiplies by zero (the
    slides' projections, forces and limits, the pin of the third axis) and the selections
    they feed; the same values in fewer operations."""
    frame, parity = kinematics.link_to_joint_frame(dof.motion)
    vel = -j.pos * link.constraint_stiffness
    vel += -jd.vel * link.constraint_vel_damping
    axis_c, angles, _ = kinematics.axis_angle_ang(j, frame, parity)
    axis_1, axis_2 = frame.ang[0], axis_c[1]
    axis_c_proj = axis_2 - jnp.dot(axis_2, axis_1) * axis_1
    axis_c_proj = axis_c_proj / math.safe_norm(axis_c_proj)
    ang = -1.0 * link.constraint_limit_stiffness * jnp.cross(axis_c_proj, axis_2)
    ang_axis = jnp.array([axis_1, axis_2])
    ang += jnp.sum(ang_axis * tau[:, None], axis=0)
    if dof.limit is not None:
        dang = _limit_excess(jnp.array(angles)[:2], dof.limit)
        ang -= link.constraint_limit_stiffness * jnp.sum(
            jax.vmap(jnp.multiply)(ang_axis, dang), 0)
    ang -= link.constraint_ang_damping * jd.ang
    return Force(ang=ang, vel=vel)


def rotary_three(link, j: Transform, jd: Motion, dof, tau: jax.Array) -> Force:
    """`brax.spring.joints._three_dof` for a joint that turns about all three of its axes
    (`rotary_joints`): brax's formula without the terms such a joint multiplies by zero (the
    slides' projections, forces and limits, the single-axis alignment torque); the same
    values in fewer operations."""
    vel = -j.pos * link.constraint_stiffness
    vel += -jd.vel * link.constraint_vel_damping
    ang = -1.0 * link.constraint_ang_damping * jd.ang
    frame, parity = kinematics.link_to_joint_frame(dof.motion)
    axis_c, angles, _ = kinematics.axis_angle_ang(j, frame, parity)
    ang_axis = jnp.array((frame.ang[0], axis_c[1], axis_c[2]))
    ang += jnp.sum(ang_axis * tau[:, None], axis=0)
    if dof.limit is not None:
        dang = _limit_excess(jnp.array(angles), dof.limit)
        ang -= link.constraint_limit_stiffness * jnp.sum(
            jax.vmap(jnp.multiply)(ang_axis, dang), 0)
    return Force(ang=ang, vel=vel)


def _joint_to_link_forces_forward(parents, jf_ang, jf_vel, ap_rot, ap_pos, ac_pos, xi_pos):
    """Per link: the joint force jf rotated to world frame by a_p.rot, applied at the
    link's centre of mass (offset a_c.pos - x_i.pos) and, opposite, at its parent's
    (offset a_p.pos - x_i[parent].pos), summed into the parent (brax's resolve's tail)."""
    vel = _rotate(jf_vel, ap_rot)
    ang = _rotate(jf_ang, ap_rot)
    pc = ac_pos - xi_pos
    pp = ap_pos - jnp.take(xi_pos, jnp.array(parents), axis=0, mode="wrap")
    out = (ang + jnp.cross(pc, vel) - _to_parents(parents, ang + jnp.cross(pp, vel)),
           vel - _to_parents(parents, vel))
    return out, (jf_ang, jf_vel, ap_rot, vel, pc, pp)


def _to_parents(parents, x):
    """Each link's row summed into its parent's (brax's segment_sum; a root's, parent -1,
    goes nowhere): the transpose of `_from_parents`."""
    return jax.ops.segment_sum(x, jnp.array(parents), len(parents))


def _from_parents(parents, x, world=None):
    """Row parents[k] of x for each k, the row `world` (default zero) where parents[k] is -1
    (a root's parent, a contact's world side): with zero, the transpose of `_to_parents`."""
    row = (jnp.zeros((1,) + x.shape[1:], x.dtype) if world is None
           else jnp.broadcast_to(jnp.array(world, x.dtype), (1,) + x.shape[1:]))
    return jnp.take(jnp.concatenate([x, row]), jnp.asarray(parents), axis=0, mode="wrap")


@functools.partial(jax.custom_vjp, nondiff_argnums=(0,))
def _joint_to_link_forces(parents, jf_ang, jf_vel, ap_rot, ap_pos, ac_pos, xi_pos):
    return _joint_to_link_forces_forward(parents, jf_ang, jf_vel, ap_rot, ap_pos, ac_pos,
                                         xi_pos)[0]


def _joint_to_link_forces_bwd(parents, res, g):
    jf_ang, jf_vel, ap_rot, vel, pc, pp = res
    g_ang, g_vel = g
    g_fp = -_from_parents(parents, g_ang)  # the parent's share, ang + pp x vel, negated
    g_ang_w = g_ang + g_fp
    g_vel_w = g_vel - _from_parents(parents, g_vel) + jnp.cross(g_ang, pc) + jnp.cross(g_fp, pp)
    g_pc, g_pp = jnp.cross(vel, g_ang), jnp.cross(vel, g_fp)
    inv = math.quat_inv(ap_rot)
    return (_rotate(g_ang_w, inv), _rotate(g_vel_w, inv),
            _rotate_vjp_quat(jf_ang, ap_rot, g_ang_w) + _rotate_vjp_quat(jf_vel, ap_rot, g_vel_w),
            g_pp, g_pc, -g_pc - _to_parents(parents, g_pp))


_joint_to_link_forces.defvjp(_joint_to_link_forces_forward, _joint_to_link_forces_bwd)


def collisions_resolve(sys, state) -> Motion:
    """`brax.spring.collisions.resolve(sys, state)`: each contact's impulse by brax's own
    formulas (XLA's reverse mode; `_impulse` is brax's closure, copied), then the impulses
    moved to the links' centres of mass, averaged over each link's active contacts and
    turned into delta-velocities with a hand-written VJP (`_impulses_to_links`). As brax
    does, `state.i_inv.take(link_idx)` takes from the flattened inverse inertias (no axis):
    each contact side gets one scalar, entry link_idx of that flat array, not its link's
    matrix; the values and VJPs here are brax's, that quirk included."""
    c = contact.get(sys, state.x)
    if c is None:
        return Motion.zero((sys.num_links(),))
    link_idx = jnp.array(c.link_idx).T
    x_i, xd_i = state.x_i.take(link_idx), state.xd_i.take(link_idx)
    i_inv = state.i_inv.take(link_idx) * (link_idx > -1)
    i_mass = 1 / state.mass.take(link_idx) * (link_idx > -1)
    p, is_contact = jax.vmap(functools.partial(_impulse, sys))(c, link_idx, x_i, xd_i, i_inv,
                                                               i_mass)
    ang, vel = _impulses_to_links(p.ang, p.vel, jax.lax.stop_gradient(is_contact), c.pos,
                                  jnp.concatenate(c.link_idx), state.x_i.pos, state.mass,
                                  state.i_inv)
    return Motion(ang=ang, vel=vel)


def _impulse(sys, c, link_idx, x_i, xd_i, i_inv, i_mass):
    """brax.spring.collisions.resolve's `impulse` (brax 0.14.2), unchanged: one contact's
    velocity-level impulse with Baumgarte stabilization and friction, and whether it
    applies."""
    rel_pos = c.pos - x_i.pos
    rel_vel = xd_i.vel + jax.vmap(jnp.cross)(xd_i.ang, rel_pos)
    rel_vel *= (link_idx > -1).reshape(-1, 1)
    contact_vel = rel_vel[0] - rel_vel[1]
    normal_vel = jnp.dot(-c.frame[0], contact_vel)
    temp = jax.vmap(jnp.dot)(i_inv, jnp.cross(rel_pos, -c.frame[0]))
    ang = jnp.dot(-c.frame[0], jnp.sum(jnp.cross(temp, rel_pos), axis=0))
    baumgarte_vel = sys.baumgarte_erp / sys.opt.timestep * c.dist
    impulse = (-1.0 * (1.0 + c.elasticity) * normal_vel - baumgarte_vel) / (
        i_mass[0] + i_mass[1] + ang)
    impulse_vec = impulse * -c.frame[0]
    vel_d = contact_vel + normal_vel * c.frame[0]
    dir_d = vel_d / (1e-6 + math.safe_norm(vel_d))
    temp = jax.vmap(jnp.dot)(i_inv, jnp.cross(rel_pos, dir_d))
    ang_d = jnp.dot(dir_d, jnp.sum(jnp.cross(temp, rel_pos), axis=0))
    impulse_d = math.safe_norm(vel_d) / (i_mass[0] + i_mass[1] + ang_d)
    impulse_d = jnp.minimum(impulse_d, c.friction[0] * impulse)
    impulse_d_vec = -1.0 * impulse_d * dir_d
    apply_n = (c.dist < 0.0) & (normal_vel < 0) & (impulse > 0.0)
    apply_d = apply_n * (math.safe_norm(vel_d) > 1e-3)
    f = Force.create(vel=impulse_vec * apply_n + impulse_d_vec * apply_d)
    return f, jnp.array(apply_n, dtype=jnp.float32)


def _impulses_to_links_forward(p_ang, p_vel, is_contact, c_pos, idx, xi_pos, mass, i_inv):
    """brax's resolve's tail: contact k's impulse p_k acts on its first link and -p_k on its
    second (index -1: the world, dropped), at the contact point relative to the link's
    centre of mass; each link's sum is divided by its number of active contacts (+1e-8),
    then by its mass (linear) and through its inverse inertia (angular)."""
    n_links = xi_pos.shape[0]
    vel2 = jnp.concatenate([p_vel, -p_vel])
    ang2 = jnp.concatenate([p_ang, -p_ang])
    r = jnp.tile(c_pos, (2, 1)) - jnp.take(xi_pos, idx, axis=0, mode="wrap")
    total_vel = jax.ops.segment_sum(vel2, idx, n_links)
    total_ang = jax.ops.segment_sum(ang2 + jnp.cross(r, vel2), idx, n_links)
    den = jax.ops.segment_sum(jnp.tile(is_contact, 2), idx, n_links).reshape(-1, 1) + 1e-8
    xa, xv = total_ang / den, total_vel / den
    out = (jax.vmap(lambda a, b: a @ b)(i_inv, xa), jax.vmap(lambda a, b: a / b)(xv, mass))
    return out, (vel2, r, idx, den, xa, xv, mass, i_inv)


@jax.custom_vjp
def _impulses_to_links(p_ang, p_vel, is_contact, c_pos, idx, xi_pos, mass, i_inv):
    return _impulses_to_links_forward(p_ang, p_vel, is_contact, c_pos, idx, xi_pos, mass,
                                      i_inv)[0]


def _impulses_to_links_bwd(res, g):
    vel2, r, idx, den, xa, xv, mass, i_inv = res
    g_ang, g_vel = g
    n = vel2.shape[0] // 2
    g_xa = jnp.einsum("lij,li->lj", i_inv, g_ang)
    g_xv = g_vel / mass[:, None]
    g_a = _from_parents(idx, g_xa / den)  # the cotangent of ang2 + r x vel2
    g_vel2 = _from_parents(idx, g_xv / den) + jnp.cross(g_a, r)
    g_r = jnp.cross(vel2, g_a)
    return (g_a[:n] - g_a[n:], g_vel2[:n] - g_vel2[n:], None, g_r[:n] + g_r[n:], None,
            -jax.ops.segment_sum(g_r, idx, mass.shape[0]), -jnp.sum(g_xv * xv, -1) / mass,
            g_ang[:, :, None] * xa[:, None, :])


_impulses_to_links.defvjp(_impulses_to_links_forward, _impulses_to_links_bwd)


def step(sys, state, act, debug: bool = False, hinges: bool = False, planar: bool = False,
         rotary: bool = False):
    """`brax.spring.pipeline.step(sys, state, act)` (brax 0.14.2) with the six pieces above
    (`inv_inertia`, `joints_resolve`, `collisions_resolve`, `integrate`, `to_world`,
    `world_to_joint`); everything else is brax's own functions in brax's order. `hinges`,
    `planar`, `rotary`: the 1-dof joints' forces by `hinge`, the 3-dof ones' by
    `planar_root`, the 2- and 3-dof ones' by `rotary_two` and `rotary_three`
    (`joints_resolve`)."""
    state = state.replace(i_inv=inv_inertia(sys, state.x))
    tau = actuator.to_tau(sys, act, state.q, state.qd)
    xdd_i = Motion.create(vel=sys.gravity)
    xf_i = joints_resolve(sys, state, tau, hinges, planar, rotary)
    if sys.enable_fluid:
        inertia = sys.link.inertia.i ** (1 - sys.spring_inertia_scale)
        xf_i += fluid.force(sys, state.x, state.xd, state.mass, inertia)
    xdd_i += Motion(
        ang=jax.vmap(lambda x, y: x @ y)(state.i_inv, xf_i.ang),
        vel=jax.vmap(lambda x, y: x / y)(xf_i.vel, state.mass),
    )
    state = state.replace(xd_i=state.xd_i + xdd_i * sys.opt.timestep)
    xdv_i = collisions_resolve(sys, state)
    x_i, xd_i = integrate(sys, state.x_i, state.xd_i, xdv_i)
    x, xd = to_world(sys, x_i, xd_i)
    state = state.replace(x=x, xd=xd, x_i=x_i, xd_i=xd_i)
    j, jd, a_p, a_c = world_to_joint(sys, x, xd)
    q, qd = kinematics.inverse(sys, j, jd)
    return state.replace(q=q, qd=qd, a_p=a_p, a_c=a_c, j=j, jd=jd,
                         contact=contact.get(sys, x) if debug else None)
