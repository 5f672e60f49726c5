"""`tasks.physics.planar_spring`'s control step with every link at once: each entry of a link's
vector or quaternion is one array over the links (over the contacts in the collision step)
instead of one scalar per link, so XLA sees each line of brax's spring substep once per
step rather than once per link (`planar_links`, with `planar_adjoint` on the spring
backend: `tasks.physics.transforms.with_planar_adjoint`).

The algebra is `tasks.physics.planar`'s: an entry whose constant is 0.0 on every link is the
Python 0.0 and folds away while tracing, an entry that differs between links is a float32
array over them. What a link reads of another (its parent's frames, the joint force it
passes to its parent, a contact's link and the inverse-inertia entry brax's impulse reads)
goes through products with constant one-hot matrices: exact selections and sums, one
product for all the entries read at one place, whose reverse mode is a product too.

The expressions are `tasks.physics.planar_spring`'s, which says what each is in brax; a root's
joint force and a hinge's are one expression here, each link reading the terms of its
kind (the other kind's constants are zero), and a link without a joint limit reads no
limit force (its limit stiffness is zero, its bounds infinite).
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from brax import kinematics
from brax.base import Motion, Transform

from tasks.physics.planar import (IDENTITY, OUTPUTS, _is, add, compose, cross, div, dot, in_plane,
                                  inv_inertia, joint_frames, matvec, mul, neg, quat_mul, rotate,
                                  shift_motion, sub, vadd, vscale, vsub)
from tasks.physics.planar_spring import (SpringScene, _excess, integrate, joint_torques, normalize,
                                         safe_norm, z_axis)


def _lc(values):
    """Per-link (or per-contact) constants as one: a Python float where every one is the
    same (so that 0.0 and 1.0 fold), else a float32 array over them."""
    a = np.asarray(values, np.float32)
    return float(a.flat[0]) if np.all(a == a.flat[0]) else a


UNIT = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
"""The identity's rows: every link's inverse inertia where `Links.unit_inertia`, and a free
root's joint frame in `tasks.physics.spatial_links.Rotary`."""


def _lv(vectors):
    """Per-link vectors (tuples) as one tuple of `_lc` entries."""
    return tuple(_lc([v[i] for v in vectors]) for i in range(len(vectors[0])))


@dataclasses.dataclass(frozen=True, eq=False)
class Links:
    """Every link's constants, entry by entry over the links (`_lc`): what every scene's
    substep reads, and its joints' (`joints`: a planar scene's `PlanarJoints`, a 3-D
    scene's `tasks.physics.spatial_links.Rotary`), each of which models only its kind of scene."""
    num: int
    parent: np.ndarray      # (L, L): [p, k] = 1 where p is link k's parent
    root: np.ndarray        # (L,): 1 at a link whose parent is the world
    transform: tuple
    joint: tuple
    neg_com: tuple
    inertia_rot: tuple
    inertia_inv: tuple
    mass: object
    stiffness: object
    vel_damping: object
    ang_damping: object
    joints: object           # `force(lk, tau, j, jd)`: every link's joint force
    full: bool = False       # every entry of a vector is live (a 3-D scene:
                             # `tasks.physics.spatial_links`), not only the x-z plane's
    unit_inertia: bool = False  # every link's inverse inertia is the identity (brax's
                                # spring_inertia_scale 1): R I R^T, written as I


@dataclasses.dataclass(frozen=True, eq=False)
class PlanarJoints:
    """A planar scene's joint forces over the links (`tasks.physics.planar_spring.joint_force`): a
    root's slides and turning dof, a hinge's spring toward its axis, each link reading the
    terms of its kind (the other kind's constants are zero), and a limit force where a
    link has a joint limit."""
    spring_axis: tuple      # a hinge's a_0, a root's turning dof's motion
    fixed_axis: tuple       # the turning torque's axis where it does not turn with j.rot
    turned_axis: tuple      #   ... and where it does (a root's rows 1 and 2)
    slide0: tuple           # a root's slide axes (zero for a hinge)
    slide1: tuple
    limited: bool           # any link has a joint limit
    limit_axes: tuple       # (a0, a1, a2) for the limit's angle (a limited link's where
                            # a link has none: its limit force is zero either way)
    lo: object
    hi: object
    limit_stiffness: object  # zero where a link has no limit
    dof_turn: tuple          # per link, the dof whose force turns it
    dof_slides: tuple        # per link, its slides' dofs (-1 for a hinge)

    def force(self, lk: Links, tau, j, jd):
        """Every link's joint force (ang, vel) in its joint frame."""
        vel = vsub(vscale(neg(lk.stiffness), j[0]), vscale(lk.vel_damping, jd[0]))
        vel = vsub(vel, vadd(vscale(dot(self.slide0, vel), self.slide0),
                             vscale(dot(self.slide1, vel), self.slide1)))
        s0 = _per_link(tau, [d[0] for d in self.dof_slides])
        s1 = _per_link(tau, [d[1] for d in self.dof_slides])
        vel = vadd(vel, vadd(vscale(s0, self.slide0), vscale(s1, self.slide1)))
        a = self.spring_axis
        ang = vscale(mul(-1.0, lk.stiffness), cross(a, rotate(a, j[1])))
        axis = vadd(self.fixed_axis, rotate(self.turned_axis, j[1]))
        ang = vadd(ang, vscale(_per_link(tau, self.dof_turn), axis))
        ang = vsub(ang, vscale(lk.ang_damping, jd[1]))
        if self.limited:
            a0, a1, a2 = self.limit_axes
            lon = normalize(cross(rotate(a2, j[1]), a0))
            psi = jnp.arctan2(dot(cross(a1, lon), a0), dot(a1, lon))
            dang = _excess(psi, self.lo, self.hi)
            ang = vsub(ang, vscale(dang, vscale(self.limit_stiffness, a0)))
        return ang, vel


@dataclasses.dataclass(frozen=True, eq=False)
class Contacts:
    """Every contact's constants, entry by entry over the contacts."""
    to_contacts: np.ndarray  # (L, K): [l, k] = 1 where contact k is on link l
    flat: np.ndarray         # (E * L, K): selects the i_inv entry contact k reads
    flat_entries: tuple      # the (row, col) entries of i_inv, E of them, `flat` reads
    geom_pos: tuple
    geom_rot: tuple
    half: object
    radius: object
    plane_pos: tuple
    normal: tuple
    friction: object
    elasticity: object
    inv_mass: object


@dataclasses.dataclass(frozen=True, eq=False)
class LinkScene:
    scene: SpringScene
    links: Links
    contacts: Contacts | None


def link_scene(sc: SpringScene) -> LinkScene:
    """`tasks.physics.planar_spring.spring_scene`'s constants over the links and contacts."""
    lns, num = sc.links, len(sc.links)
    parent = np.zeros((num, num), np.float32)
    for k, ln in enumerate(lns):
        if ln.parent >= 0:
            parent[ln.parent, k] = 1.0
    limited = next((ln.axes for ln in lns if ln.limit), None)
    zero = (0.0, 0.0, 0.0)
    f32 = lambda v, p: tuple(np.float32(p) * np.float32(a) for a in v)  # noqa: E731
    links = Links(
        num=num, parent=parent,
        root=np.asarray([float(ln.parent < 0) for ln in lns], np.float32),
        transform=(_lv([ln.transform[0] for ln in lns]), _lv([ln.transform[1] for ln in lns])),
        joint=(_lv([ln.joint[0] for ln in lns]), _lv([ln.joint[1] for ln in lns])),
        neg_com=_lv([ln.neg_com for ln in lns]),
        inertia_rot=_lv([ln.inertia_rot for ln in lns]),
        inertia_inv=_lv([ln.inertia_inv for ln in lns]),
        mass=_lc([ln.mass for ln in lns]), stiffness=_lc([ln.stiffness for ln in lns]),
        vel_damping=_lc([ln.vel_damping for ln in lns]),
        ang_damping=_lc([ln.ang_damping for ln in lns]),
        joints=PlanarJoints(
            spring_axis=_lv([ln.turn_motion if ln.root else ln.axes[0] for ln in lns]),
            fixed_axis=_lv([(zero if ln.turn_rotates else f32(ln.turn_axis, ln.turn_parity))
                            if ln.root else ln.axes[0] for ln in lns]),
            turned_axis=_lv([f32(ln.turn_axis, ln.turn_parity) if ln.root and ln.turn_rotates
                             else zero for ln in lns]),
            slide0=_lv([ln.slides[0][1] if ln.root else zero for ln in lns]),
            slide1=_lv([ln.slides[1][1] if ln.root else zero for ln in lns]),
            limited=limited is not None,
            limit_axes=() if limited is None else tuple(
                _lv([ln.axes[i] if ln.limit else limited[i] for ln in lns]) for i in range(3)),
            lo=_lc([ln.limit[0] if ln.limit else -np.inf for ln in lns]),
            hi=_lc([ln.limit[1] if ln.limit else np.inf for ln in lns]),
            limit_stiffness=_lc([ln.limit_stiffness if ln.limit else 0.0 for ln in lns]),
            dof_turn=tuple(ln.dofs[ln.turn] if ln.root else ln.dofs[0] for ln in lns),
            dof_slides=tuple(tuple(ln.dofs[r] for r, _ in ln.slides) if ln.root else (-1, -1)
                             for ln in lns)))
    contacts = contact_table(sc.contacts, [ln.mass for ln in lns], num)
    return LinkScene(scene=sc, links=links, contacts=contacts)


def contact_table(cs, masses, num: int) -> Contacts | None:
    """`tasks.physics.planar_spring.Contact`s over the contacts (None where there are none), on
    links whose masses (as brax divides by them) are `masses`."""
    if not cs:
        return None
    to_contacts = np.zeros((num, len(cs)), np.float32)
    for k, c in enumerate(cs):
        to_contacts[c.link, k] = 1.0
    entries = tuple(sorted({c.flat[1:] for c in cs}))
    flat = np.zeros((len(entries) * num, len(cs)), np.float32)
    for k, c in enumerate(cs):
        flat[entries.index(c.flat[1:]) * num + c.flat[0], k] = 1.0
    return Contacts(
        to_contacts=to_contacts, flat=flat, flat_entries=entries,
        geom_pos=_lv([c.geom_pos for c in cs]), geom_rot=_lv([c.geom_rot for c in cs]),
        half=_lc([c.half for c in cs]), radius=_lc([c.radius for c in cs]),
        plane_pos=_lv([c.plane_pos for c in cs]), normal=_lv([c.normal for c in cs]),
        friction=_lc([c.friction for c in cs]),
        elasticity=_lc([c.elasticity for c in cs]),
        inv_mass=_lc([1.0 / masses[c.link] for c in cs]))


# ----------------------------------------------------------------------------------------
# Reading across links: one product with a constant one-hot matrix per place.
# ----------------------------------------------------------------------------------------


def _select(vectors, matrix, unstack: bool = False):
    """Each of `vectors` (tuples of entries over the rows of `matrix`) times `matrix`: its
    entries over the columns, one product for all of them; a constant entry stays the
    constant it is only where every column selects exactly one row (else it is scaled by
    the column's count). `unstack`: the product's rows are read by `_unstack` (the same
    values and cotangents; a 3-D scene's, `Links.full`)."""
    live = [a for v in vectors for a in v if not isinstance(a, float)]
    counts = matrix.sum(axis=0)
    product = (jnp.stack([jnp.broadcast_to(a, (matrix.shape[0],)) for a in live]) @ matrix
               if live else None)
    out_live = iter(() if product is None else _unstack(product) if unstack else product)
    out = []
    for v in vectors:
        out.append(tuple((next(out_live) if not isinstance(a, float)
                          else (a if _is(a, 0.0) else _lc(a * counts))) for a in v))
    return out


@jax.custom_vjp
def _unstack(a):
    """The rows of `a`, whose cotangent is their cotangents stacked (a concatenation) rather
    than reverse mode's sum of one padded row each, which XLA's CPU backend fused into one
    loop that evaluates every row's cotangent for every entry (most of ant's control-step VJP
    went to that loop in the parent product's)."""
    return tuple(a[k] for k in range(a.shape[0]))


def _unstack_fwd(a):
    return _unstack(a), None


def _unstack_bwd(_, cts):
    return (jnp.stack(cts),)


_unstack.defvjp(_unstack_fwd, _unstack_bwd)


# ----------------------------------------------------------------------------------------
# The substep over the links.
# ----------------------------------------------------------------------------------------


def _to_world(lk: Links, x_i, xd_i):
    x = compose(x_i, (lk.neg_com, IDENTITY))
    return x, shift_motion(vsub(x[0], x_i[0]), xd_i)


def _world_to_joint(lk: Links, x, xd):
    pos_p, rot_p, vel_p, ang_p = _select([x[0], x[1], xd[0], xd[1]], lk.parent, lk.full)
    rot_p = (add(rot_p[0], lk.root), *rot_p[1:])  # the world: the identity
    return joint_frames(lk, (pos_p, rot_p), (vel_p, ang_p), x, xd)


def _per_link(values, dofs):
    """Per link, the force of its dof in `dofs` (-1: none), over the links."""
    picked = [0.0 if d < 0 else values[d] for d in dofs]
    live = [a for a in picked if not isinstance(a, float)]
    if not live:
        return _lc(picked)
    return jnp.stack([jnp.full_like(live[0], a) if isinstance(a, float) else a
                      for a in picked])


def _joint_force(lk: Links, tau, j, jd):
    """`tasks.physics.planar_spring.joint_force` of every link: (ang, vel) in its joint frame, as
    the scene's joints model it (`PlanarJoints`, `tasks.physics.spatial_links.Rotary`)."""
    return lk.joints.force(lk, tau, j, jd)


def _to_links(lk: Links, ang, vel, jw, x_i):
    """`tasks.physics.planar.to_links` over the links: each joint's force in world frame at its
    link's centre of mass and, opposite, at its parent's."""
    _, _, a_p, a_c = jw
    vel, ang = rotate(vel, a_p[1]), rotate(ang, a_p[1])
    own = vadd(ang, cross(vsub(a_c[0], x_i[0]), vel))
    (pos_p,) = _select([x_i[0]], lk.parent, lk.full)
    moved = vadd(ang, cross(vsub(a_p[0], pos_p), vel))
    to_parent = lk.parent.T
    back_ang, back_vel = _select([moved, vel], to_parent, lk.full)
    return vsub(own, back_ang), vsub(vel, back_vel)


def _flat(cs: Contacts, i_inv, num: int):
    """Per contact, the entry of the flattened (links, 3, 3) inverse inertias brax's
    impulse reads (`tasks.physics.planar_spring.Contact.flat`)."""
    rows = [i_inv[r][c] for r, c in cs.flat_entries]
    if all(_is(a, 0.0) for a in rows):
        return 0.0
    if all(isinstance(a, float) for a in rows):  # the same on every link: per contact's entry
        return _lc([rows[e] for e in cs.flat.argmax(axis=0) // num])
    like = next(a for a in rows if not isinstance(a, float))
    stacked = jnp.concatenate([jnp.broadcast_to(jnp.asarray(a, like.dtype), (num,))
                               for a in rows])
    return stacked @ cs.flat


def _collisions(ls: LinkScene, x, x_i, xd_i, i_inv):
    """`tasks.physics.planar_spring.collisions` over the contacts, summed over each link's."""
    lk, c, sc = ls.links, ls.contacts, ls.scene
    pos, rot, pos_i, vel_i, ang_i = _select([x[0], x[1], x_i[0], xd_i[0], xd_i[1]],
                                            c.to_contacts, lk.full)
    centre = vadd(pos, rotate(c.geom_pos, rot))
    axis = z_axis(quat_mul(rot, c.geom_rot))
    end = vadd(centre, vscale(c.half, axis))
    dist = sub(dot(vsub(end, c.plane_pos), c.normal), c.radius)
    cpos = vsub(end, vscale(add(c.radius, mul(0.5, dist)), c.normal))
    rel_pos = vsub(cpos, pos_i)
    contact_vel = tuple(neg(a) for a in vadd(vel_i, cross(ang_i, rel_pos)))
    nn = tuple(neg(a) for a in c.normal)
    normal_vel = dot(nn, contact_vel)
    flat = _flat(c, i_inv, lk.num)
    ang = dot(nn, cross(vscale(flat, cross(rel_pos, nn)), rel_pos))
    impulse = (sub(mul(-(1.0 + c.elasticity), normal_vel), mul(sc.erp_dt, dist))
               / add(c.inv_mass, ang))
    vel_d = vadd(contact_vel, vscale(normal_vel, c.normal))
    speed = safe_norm(vel_d)
    dir_d = tuple(div(a, 1e-6 + speed) for a in vel_d)
    ang_d = dot(dir_d, cross(vscale(flat, cross(rel_pos, dir_d)), rel_pos))
    impulse_d = jnp.minimum(speed / add(c.inv_mass, ang_d), c.friction * impulse)
    apply_n = ((dist < 0.0) & (normal_vel < 0) & (impulse > 0.0)).astype(impulse.dtype)
    apply_d = apply_n * (speed > 1e-3)
    f = vadd(vscale(mul(impulse, apply_n), nn), vscale(mul(neg(impulse_d), apply_d), dir_d))
    p = tuple(neg(a) for a in f)              # the link is the contact's second body
    vel, ang_p, (n,) = _select([p, cross(rel_pos, p), (apply_n,)], c.to_contacts.T,
                                 lk.full)
    scale = n + 1e-8
    vel, ang_p = tuple(div(a, scale) for a in vel), tuple(div(a, scale) for a in ang_p)
    return tuple(div(a, lk.mass) for a in vel), matvec(i_inv, ang_p)


def substep(ls: LinkScene, x_i, xd_i, tau):
    """`tasks.physics.planar_spring.substep` with every link at once: (x_i, xd_i) as (pos, rot) and
    (vel, ang) tuples of entries over the links."""
    lk, sc = ls.links, ls.scene
    x, xd = _to_world(lk, x_i, xd_i)
    jw = _world_to_joint(lk, x, xd)
    i_inv = UNIT if lk.unit_inertia else inv_inertia(lk, x[1])
    f_ang, f_vel = _to_links(lk, *_joint_force(lk, tau, jw[0], jw[1]), jw, x_i)
    xd_i = (vadd(xd_i[0], vscale(sc.dt, vadd(sc.gravity, tuple(div(a, lk.mass)
                                                                for a in f_vel)))),
            vadd(xd_i[1], vscale(sc.dt, matvec(i_inv, f_ang))))
    xdv_i = ((0.0,) * 3,) * 2 if ls.contacts is None else _collisions(ls, x, x_i, xd_i, i_inv)
    (x_i,), (xd_i,) = integrate(sc, [x_i], [xd_i], [xdv_i])
    return x_i, xd_i


def _scanned_substeps(ls: LinkScene, t, tau, n_frames: int):
    """`n_frames` substeps of a 3-D scene (`Links.full`, every entry an array) as a scan of
    one checkpointed substep whose carry is the entries themselves: no arrays between
    substeps to stack and read back, whose cotangents XLA's CPU backend sums from padded
    entries in loops that recompute every entry per element, and no fusion across substeps
    (what the planar step's optimization barrier is for; on ant the compiled program kept
    no barrier). The backward stores each substep's input entries and recomputes the
    substep. On ant this scan is faster than the substeps unrolled through arrays
    (docs/physics.md)."""
    def body(carry, _):
        return substep(ls, *carry, tau), None
    return jax.lax.scan(jax.checkpoint(body, prevent_cse=False), t, None,
                        length=n_frames)[0]


def _read(a, kind: str, full: bool = False):
    """Every link's row of a brax array, entry by entry over the links: its in-plane
    entries (`in_plane`), or all of them where `full`."""
    if full:
        return tuple(a[:, k] for k in range(a.shape[-1]))
    return in_plane(lambda k: a[:, k], kind)


def _write(t, num: int, dtype):
    return jnp.stack([jnp.broadcast_to(jnp.asarray(a, dtype), (num,)) for a in t], axis=-1)


def control_step(ls: LinkScene, sys, x_i, xd_i, act: jax.Array, n_frames: int):
    """`tasks.physics.planar_spring.control_step`, every link at once: the same outputs (the
    state's frames in `tasks.physics.planar.OUTPUTS` order, q, qd) to float32 round-off. A 3-D
    scene's substeps are a scan (`_scanned_substeps`). A planar scene's are unrolled, and
    between them the frames go through arrays and an optimization barrier, as there: without
    it one control step's value and VJP cost more than the per-link step's on hopper and
    walker2d; with it, less."""
    dtype, num = x_i.pos.dtype, ls.links.num
    tau = joint_torques(ls.scene, act)
    full = ls.links.full
    t = ((_read(x_i.pos, "pos", full), _read(x_i.rot, "rot", full)),
         (_read(xd_i.vel, "vel", full), _read(xd_i.ang, "ang", full)))
    if full:  # a 3-D scene: its substeps scanned (`_scanned_substeps`)
        t, n_frames = _scanned_substeps(ls, t, tau, n_frames), 0
    for _ in range(n_frames):
        t = substep(ls, *t, tau)
        arrays = jax.lax.optimization_barrier(
            (_write(t[0][0], num, dtype), _write(t[0][1], num, dtype),
             _write(t[1][0], num, dtype), _write(t[1][1], num, dtype)))
        t = ((_read(arrays[0], "pos", full), _read(arrays[1], "rot", full)),
             (_read(arrays[2], "vel", full), _read(arrays[3], "ang", full)))
    x_i, xd_i = t
    x, xd = _to_world(ls.links, x_i, xd_i)
    j, jd, a_p, a_c = _world_to_joint(ls.links, x, xd)
    frames = {"x": x, "xd": xd, "x_i": x_i, "xd_i": xd_i, "j": j, "jd": jd, "a_p": a_p,
              "a_c": a_c}
    out = tuple((_write(frames[name][0], num, dtype), _write(frames[name][1], num, dtype))
                for name in OUTPUTS)
    jt = Transform(pos=out[OUTPUTS.index("j")][0], rot=out[OUTPUTS.index("j")][1])
    jdm = Motion(vel=out[OUTPUTS.index("jd")][0], ang=out[OUTPUTS.index("jd")][1])
    q, qd = kinematics.inverse(sys, jt, jdm)
    return out, q, qd
