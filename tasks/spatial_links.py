"""brax's spring control step for a 3-D scene of a free root and hinges, every link at once:
ant's. ILD differentiates it in place of brax's step (`spatial_links`,
`tasks.core.with_spatial_adjoint`), as `tasks.planar_links` does for hopper's and
walker2d's planar step.

It is `tasks.planar_links`' step with every entry of every vector and quaternion live (a
`Links` with `full`): each entry one array over the links (or the contacts), what a link
reads of another through products with constant one-hot matrices, and the constants that
are the same on every link (a zero, a one) folded while tracing. brax's own substep
(`brax.spring.pipeline.step`; in ILD `tasks.spring_adjoint.step`) works on arrays whose
last axis is a vector's 3 or a quaternion's 4 entries, and XLA's CPU backend spends much of
its reverse mode on layout copies and scatter-adds around those small axes (results/
JOURNAL.md, session 75: 308 scatter-adds in ant's compiled update). Here every array is
(batch, links).

What the scene needs and no more:
- the free root: brax's `_free` has no force; here it is a link whose joint constants
  (stiffness, damping, axes) are zero, so its joint force is zero;
- the hinges: brax's `_one_dof` for a joint that turns (`tasks.planar_links._joint_force`),
  their limits included;
- the contacts: spheres (ant's feet) and capsules against a plane fixed in the world
  (`tasks.planar_spring._contacts(spheres=True)`), brax's quirk of reading one entry of the
  flattened inverse inertias kept;
- the inverse inertia: with brax's `spring_inertia_scale` 1 (ant's) every link's inverse
  inertia is R I R^T = I, which brax computes to round-off and this writes as the
  identity (`Links.unit_inertia`). Its derivative differs from brax's only along the
  quaternion itself (brax's R I R^T is |q|^4 I off the unit sphere), a direction the
  previous `integrate`'s normalization takes out of every gradient it passes back.

`spatial_scene(sys)` reads the constants or says why the scene is not one this models;
`control_step` is `tasks.planar_links.control_step` on them, whose substeps for such a
scene are a scan of one checkpointed substep (`tasks.planar_links._scanned_substeps`).
Paired on one CPU core at B = 32 against the update through hand_adjoint's backward, ant's
update ran 1.41x as fast, update / forward 3.22x -> 2.19x (session 76,
results/spatial_links/paired_session76_scan_ant.csv); unrolled through arrays between
substeps, as the planar step runs, it ran 1.016x as fast.
"""
from __future__ import annotations

import jax
import numpy as np
from brax import kinematics

from tasks.planar import ORIGIN, _const, _f32
from tasks.planar_links import LinkScene, Links, _lc, _lv, contact_table
from tasks.planar_links import control_step  # noqa: F401  (the step, on a spatial_scene)
from tasks.planar_spring import SpringScene, _contacts, spring_constants


def spatial_scene(sys) -> LinkScene | str:
    """The constants `control_step` reads, or why the scene is not one it models (a string):
    free roots (links whose parent is the world) and hinges, motors (no position or velocity
    bias), no fluid, contacts of spheres or capsules against a plane fixed in the world."""
    if isinstance(sys.dof.motion.ang, jax.core.Tracer):
        return "its constants are traced (not known while tracing)"
    if sys.enable_fluid:
        return "it has fluid forces"
    parents = [int(p) for p in sys.link_parents]
    for i, typ in enumerate(sys.link_types):
        if typ not in "f1" or (typ == "f") != (parents[i] < 0):
            return ("it has a joint that is neither a free root nor a 1-dof joint below one "
                    "(this models a free root and hinges: ant)")
    motion_ang, motion_vel = np.asarray(sys.dof.motion.ang), np.asarray(sys.dof.motion.vel)
    act = sys.actuator
    if np.any(np.asarray(act.bias_q)) or np.any(np.asarray(act.bias_qd)):
        return "it has actuators with a position or velocity bias (servos)"
    contacts = _contacts(sys, spheres=True)
    if isinstance(contacts, str):
        return contacts
    mass, i_diag, lo, hi = spring_constants(sys)
    link_of_dof = np.asarray(sys.dof_link())
    num, zero = sys.num_links(), ORIGIN
    hinges = {}  # link -> (dof, its joint frame's angular axes, (lo, hi) or ())
    for i, typ in enumerate(sys.link_types):
        if typ != "1":
            continue
        d = int(np.flatnonzero(link_of_dof == i)[0])
        if not np.any(motion_ang[d]) or np.any(motion_vel[d]):
            return "it has a 1-dof joint that slides (a hinge is what it models)"
        frame, _ = kinematics.link_to_joint_frame(
            jax.tree.map(lambda a: a[d:d + 1], sys.dof.motion))
        bounds = (lo[d], hi[d])
        hinges[i] = (d, tuple(_const(a) for a in np.asarray(frame.ang)),
                     (_f32(bounds[0]), _f32(bounds[1])) if np.all(np.isfinite(bounds))
                     else ())
    limited = next((axes for _, axes, lim in hinges.values() if lim), None)
    parent = np.zeros((num, num), np.float32)
    for k, p in enumerate(parents):
        if p >= 0:
            parent[p, k] = 1.0
    link = sys.link

    def per_link(values, free=0.0):  # a hinge's value, the free root's `free`
        return _lc([values(i) if i in hinges else free for i in range(num)])

    def axis(i):
        return hinges[i][1][0] if i in hinges else zero

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
        spring_axis=_lv([axis(i) for i in range(num)]),
        fixed_axis=_lv([axis(i) for i in range(num)]),
        turned_axis=zero, slide0=zero, slide1=zero,
        limited=limited is not None,
        limit_axes=() if limited is None else tuple(
            _lv([hinges[i][1][k] if i in hinges and hinges[i][2] else limited[k]
                 for i in range(num)]) for k in range(3)),
        lo=per_link(lambda i: hinges[i][2][0] if hinges[i][2] else -np.inf, -np.inf),
        hi=per_link(lambda i: hinges[i][2][1] if hinges[i][2] else np.inf, np.inf),
        limit_stiffness=per_link(
            lambda i: _f32(link.constraint_limit_stiffness[i]) if hinges[i][2] else 0.0),
        dof_turn=tuple(hinges[i][0] if i in hinges else -1 for i in range(num)),
        dof_slides=((-1, -1),) * num,
        full=True, unit_inertia=bool(np.all(i_diag == 1.0)))
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
