"""brax's spring control step for a 3-D scene of a free root and joints that only turn, every
link at once: ant's (hinges) and humanoid's (hinges, 2- and 3-dof joints). ILD
differentiates it in place of brax's step (`spatial_links`,
`tasks.physics.transforms.with_spatial_adjoint`), as `tasks.physics.planar_links` does for
hopper's and walker2d's planar step.

It is `tasks.physics.planar_links`' step with every entry of every vector and quaternion live (a
`Links` with `full`, whose `joints` are a `Rotary`): each entry one array over the links
(or the contacts), what a link reads of another through products with constant one-hot
matrices, and the constants that are the same on every link (a zero, a one) folded while
tracing. brax's own substep
(`brax.spring.pipeline.step`; in ILD `tasks.physics.spring_adjoint.step`) works on arrays whose
last axis is a vector's 3 or a quaternion's 4 entries, and XLA's CPU backend spends much of
its reverse mode on layout copies and scatter-adds around those small axes (hundreds of
scatter-adds in ant's compiled update). Here every array is
(batch, links).

What the scenes need and no more:
- the free root: brax's `_free` has no force; here it is a link whose joint constants
  (stiffness, damping, torque rows) are zero, so its joint force is zero;
- the joints (`Rotary`): brax's `_one_dof` for a hinge, `_two_dof` and `_three_dof` for
  joints whose every axis turns (`tasks.physics.spring_adjoint.rotary_two` / `rotary_three`),
  as one expression over the links: every link's joint frame and Euler angles, each term a joint
  does not have read through a zero constant, each limit it does not have infinite;
- the contacts: spheres (ant's and humanoid's feet) and capsules against a plane fixed in
  the world (`tasks.physics.planar_spring._contacts(spheres=True)`), brax's quirk of reading one
  entry of the flattened inverse inertias kept;
- the inverse inertia: with brax's `spring_inertia_scale` 1 (ant's, humanoid's) every
  link's inverse inertia is R I R^T = I, which brax computes to round-off and this writes
  as the identity (`Links.unit_inertia`). Its derivative differs from brax's only along
  the quaternion itself (brax's R I R^T is |q|^4 I off the unit sphere), a direction the
  previous `integrate`'s normalization takes out of every gradient it passes back.

`spatial_scene(sys)` reads the constants or says why the scene is not one this models;
`control_step` is `tasks.physics.planar_links.control_step` on them, whose substeps for such a
scene are a scan of one checkpointed substep (`tasks.physics.planar_links._scanned_substeps`).
What it buys, and how it is verified against XLA's reverse mode: docs/physics.md.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from brax import kinematics
from brax.math import safe_arccos

from tasks.physics.planar import (_const, _f32, add, cross, dot, mul, neg, rotate, vadd, vscale,
                                  vsub)
from tasks.physics.planar_links import UNIT, LinkScene, Links, _lc, _lv, _per_link, contact_table
from tasks.physics.planar_links import control_step  # noqa: F401  (the step, on a spatial_scene)
from tasks.physics.planar_spring import (SpringScene, _contacts, _excess, normalize,
                                         spring_constants)


@dataclasses.dataclass(frozen=True, eq=False)
class Rotary:
    """The joint forces of a 3-D scene's links, entry by entry over the links (`_lc`): brax's
    `_one_dof` for a hinge, `_two_dof` and `_three_dof` for joints that only turn (as
    `tasks.physics.spring_adjoint.rotary_two` and `rotary_three` write them), `_free` (no
    force) for a root. Each link's joint frame (brax's `kinematics.link_to_joint_frame`) and Euler
    angles (`kinematics.axis_angle_ang`: psi, theta, phi) are one expression over the links;
    a term a link's joint does not have reads a zero constant, a limit it does not have
    infinite bounds."""
    frame: tuple       # (f0, f1, f2): each link's joint frame rows; a root's the identity's
    parity: object     # a 3-dof joint's handedness (brax's parity), 1 elsewhere
    align: object      # a hinge's constraint_stiffness (its torque to hold its axis)
    align2: object     # a 2-dof joint's constraint_limit_stiffness (brax's torque toward its
                       # joint plane), 0 elsewhere
    rows: tuple        # per Euler angle k, per link, the dof whose force turns about axis k
    lo: tuple          # per Euler angle, per link, its limit (-inf, inf where none)
    hi: tuple
    limit_stiffness: object
    angles: int        # the most Euler angles a joint reads: 1 (hinges), 2 or 3
    two: bool          # some joint is a 2-dof one

    def force(self, lk: Links, tau, j, jd):
        """Every link's joint force (ang, vel) in its joint frame. A root's rotation is read as
        the identity here (its force is zero either way), so that the angles a root does not
        read have well-defined derivatives wherever its body turns."""
        vel = vsub(vscale(neg(lk.stiffness), j[0]), vscale(lk.vel_damping, jd[0]))
        keep = np.float32(1.0) - lk.root
        rot = (add(mul(j[1][0], keep), lk.root), *(mul(a, keep) for a in j[1][1:]))
        f0, f1, f2 = self.frame
        c0, c2 = rotate(f0, rot), rotate(f2, rot)  # the child's frame (brax's child_frame)
        ang = vsub(vscale(neg(self.align), cross(f0, c0)), vscale(lk.ang_damping, jd[1]))
        lon = normalize(cross(c2, f0))  # the line of nodes
        axes = [f0]
        angles = [jnp.arctan2(dot(cross(f1, lon), f0), dot(f1, lon))]  # psi
        if self.angles >= 2:
            c1 = rotate(f1, rot)
            plane = normalize(vadd(vscale(dot(f0, c0), c0), vscale(dot(f0, c1), c1)))
            angles.append(safe_arccos(jnp.clip(dot(plane, f0), -1.0, 1.0))
                          * jnp.sign(dot(f0, c2)))  # theta
            axes.append(c1)
            if self.two:
                proj = normalize(vsub(c1, vscale(dot(c1, f0), f0)))
                ang = vsub(ang, vscale(self.align2, cross(proj, c1)))
        if self.angles == 3:
            c2p = vscale(self.parity, c2)
            down = tuple(neg(a) for a in c2p)  # brax's yc_n_normal
            angles.append(jnp.arctan2(dot(cross(c1, lon), down), dot(c1, lon)))  # phi
            axes.append(c2p)
        for axis, angle, rows, lo, hi in zip(axes, angles, self.rows, self.lo, self.hi):
            ang = vadd(ang, vscale(_per_link(tau, rows), axis))
            excess = _excess(angle, lo, hi)
            ang = vsub(ang, vscale(mul(self.limit_stiffness, excess), axis))
        return ang, vel


def spatial_scene(sys) -> LinkScene | str:
    """The constants `control_step` reads, or why the scene is not one it models (a string):
    free roots (links whose parent is the world), hinges, and 2- and 3-dof joints that only
    turn; motors (no position or velocity bias), no fluid, contacts of spheres or capsules
    against a plane fixed in the world."""
    if isinstance(sys.dof.motion.ang, jax.core.Tracer):
        return "its constants are traced (not known while tracing)"
    if sys.enable_fluid:
        return "it has fluid forces"
    parents = [int(p) for p in sys.link_parents]
    for i, typ in enumerate(sys.link_types):
        if (typ == "f") != (parents[i] < 0):
            return ("it has a free joint below another link or a root that is not free (this "
                    "models free roots with joints below them: ant, humanoid)")
    motion_ang, motion_vel = np.asarray(sys.dof.motion.ang), np.asarray(sys.dof.motion.vel)
    act = sys.actuator
    if np.any(np.asarray(act.bias_q)) or np.any(np.asarray(act.bias_qd)):
        return "it has actuators with a position or velocity bias (servos)"
    contacts = _contacts(sys, spheres=True)
    if isinstance(contacts, str):
        return contacts
    mass, i_diag, lo, hi = spring_constants(sys)
    link_of_dof = np.asarray(sys.dof_link())
    num = sys.num_links()
    joints = {}  # link -> (its dofs, joint frame rows, parity, per-angle (lo, hi))
    for i, typ in enumerate(sys.link_types):
        if typ == "f":
            continue
        dofs = [int(d) for d in np.flatnonzero(link_of_dof == i)]
        if np.any(motion_vel[dofs]) or not np.all(np.any(motion_ang[dofs], axis=-1)):
            return ("it has a joint that slides (hinges and 2- and 3-dof joints that only "
                    "turn are what it models)")
        frame, parity = kinematics.link_to_joint_frame(
            jax.tree.map(lambda a: a[dofs[0]:dofs[-1] + 1], sys.dof.motion))
        bounds = [(_f32(lo[d]), _f32(hi[d])) for d in dofs]  # +-inf where a side has none
        joints[i] = (dofs, tuple(_const(a) for a in np.asarray(frame.ang)), _f32(parity),
                     bounds)
    size = lambda i: len(joints[i][0]) if i in joints else 0  # noqa: E731
    parent = np.zeros((num, num), np.float32)
    for k, p in enumerate(parents):
        if p >= 0:
            parent[p, k] = 1.0
    link = sys.link

    def per_link(values, free=0.0):  # a joint's value, a free root's `free`
        return _lc([values(i) if i in joints else free for i in range(num)])

    def bound(k, side):  # Euler angle k's limit of every link
        return _lc([joints[i][3][k][side] if size(i) > k else (-np.inf, np.inf)[side]
                    for i in range(num)])

    angles = max(size(i) for i in range(num)) if joints else 1
    rotary = Rotary(
        frame=tuple(_lv([joints[i][1][k] if i in joints else UNIT[k]
                         for i in range(num)]) for k in range(3)),
        parity=per_link(lambda i: joints[i][2], 1.0),
        align=per_link(lambda i: _f32(link.constraint_stiffness[i]) if size(i) == 1 else 0.0),
        align2=per_link(
            lambda i: _f32(link.constraint_limit_stiffness[i]) if size(i) == 2 else 0.0),
        rows=tuple(tuple(joints[i][0][k] if size(i) > k else -1 for i in range(num))
                   for k in range(angles)),
        lo=tuple(bound(k, 0) for k in range(angles)),
        hi=tuple(bound(k, 1) for k in range(angles)),
        limit_stiffness=per_link(lambda i: _f32(link.constraint_limit_stiffness[i])),
        angles=angles, two=any(size(i) == 2 for i in range(num)))
    links = Links(
        num=num, parent=parent,
        root=np.asarray([float(p < 0) for p in parents], np.float32),
        transform=(_lv([_const(link.transform.pos[i]) for i in range(num)]),
                   _lv([_const(link.transform.rot[i]) for i in range(num)])),
        joint=(_lv([_const(link.joint.pos[i]) for i in range(num)]),
               _lv([_const(link.joint.rot[i]) for i in range(num)])),
        neg_com=_lv([_const(-np.asarray(link.inertia.transform.pos[i])) for i in range(num)]),
        inertia_rot=_lv([_const(link.inertia.transform.rot[i]) for i in range(num)]),
        inertia_inv=_lv([_const(np.float32(1) / i_diag[i]) for i in range(num)]),
        mass=_lc([_f32(m) for m in mass]),
        stiffness=per_link(lambda i: _f32(link.constraint_stiffness[i])),
        vel_damping=per_link(lambda i: _f32(link.constraint_vel_damping[i])),
        ang_damping=per_link(lambda i: _f32(link.constraint_ang_damping[i])),
        joints=rotary, full=True, unit_inertia=bool(np.all(i_diag == 1.0)))
    dt = _f32(sys.opt.timestep)
    damp = lambda d: _f32(np.exp(np.float32(d) * np.float32(dt)))  # noqa: E731
    scene = SpringScene(
        links=(), gravity=_const(sys.gravity), dt=dt, vel_damp=damp(sys.vel_damping),
        ang_damp=damp(sys.ang_damping),
        erp_dt=_f32(np.float32(sys.baumgarte_erp) / np.float32(dt)), contacts=contacts,
        actuators=tuple(
            (int(qd), _f32(g), _f32(k), *(_f32(v) for v in cr), *(_f32(v) for v in fr))
            for qd, g, k, cr, fr in zip(np.asarray(act.qd_id), np.asarray(act.gear),
                                        np.asarray(act.gain), np.asarray(act.ctrl_range),
                                        np.asarray(act.force_range))),
        num_dofs=int(sys.qd_size()))
    return LinkScene(scene=scene, links=links,
                     contacts=contact_table(contacts, [_f32(m) for m in mass], num))
