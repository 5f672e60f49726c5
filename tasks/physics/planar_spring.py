"""brax's spring control step for a scene that moves in the x-z plane, written as the scene
needs it: hopper's and walker2d's. ILD differentiates it in place of brax's step
(`planar_adjoint` on the spring backend, `tasks.physics.transforms.with_planar_adjoint`;
hopper's and walker2d's default, and in its form over all links at
once, `tasks.physics.planar_links`, which reads its constants from here), as
`tasks.physics.planar` does for brax's positional step.
What it buys, and how it is verified: docs/physics.md.

Hopper and walker2d move in the x-z plane: a planar root (slides along x and z, a hinge
about y), hinges about y, gravity along -z, capsules on links that touch a floor whose
normal is z. brax's spring substep (`brax.spring.pipeline.step`; in ILD
`tasks.physics.spring_adjoint.step`, the same values) computes all three entries of every vector,
all four of every quaternion and all nine of every inverse inertia, and reverse mode
differentiates them all. Here the same expressions are written over `tasks.physics.planar`'s
algebra (tuples whose out-of-plane entries are the Python constant 0.0, folded while
tracing), so XLA sees only the in-plane terms, and the contacts are written for the one
pair these scenes have (a capsule against a plane, MuJoCo MJX's `plane_capsule`: two
contacts at the capsule's ends).

`control_step` is one control step (`n_frames` substeps; the joint coordinates only at the
end, by brax's own `kinematics.inverse`, as `lean_substeps` computes them) as a function of
the state's centre-of-mass frames (`x_i`, `xd_i`) and the action: brax's substep reads the
rest of a state (link and joint frames, the inverse inertia) only as functions of those.
brax's quirk of reading each contact's inverse inertia as one entry of the flattened
(links, 3, 3) array (`state.i_inv.take(link_idx)`, no axis: `tasks.physics.spring_adjoint`
documents it) is kept: the entry is named per contact (`Contact.flat`).

`spring_scene(sys)` reads the scene's constants or says why the scene is not one this
models, and `spring_refusal` also traces a substep: an out-of-plane entry that it would make
non-zero refuses the scene.
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
from brax import kinematics, math
from brax.base import Motion, Transform

from tasks.physics.planar import (ORIGIN, OUTPUTS, _array, _const, _f32, _frames, plane_leaks, _is,
                                  _tuples, add, cross, div, dot, inv_inertia, matvec, mul, neg,
                                  quat_mul, rotate, sub, to_links, to_world, vadd, vscale, vsub,
                                  world_to_joint)

# ----------------------------------------------------------------------------------------
# The scene's constants.
# ----------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class SpringLink:
    """One link's constants (Python floats, float32 values; vectors as tuples). The fields
    `tasks.physics.planar`'s frame conversions read (`parent`, `transform`, `joint`, `neg_com`,
    `inertia_rot`, `inertia_inv`) mean what they mean there."""
    parent: int
    transform: tuple
    joint: tuple
    neg_com: tuple
    inertia_rot: tuple
    inertia_inv: tuple
    mass: float             # mass ** (1 - spring_mass_scale): brax divides forces by it
    stiffness: float        # link.constraint_stiffness
    vel_damping: float      # link.constraint_vel_damping
    ang_damping: float      # link.constraint_ang_damping
    limit_stiffness: float  # link.constraint_limit_stiffness
    root: bool              # a planar root (two slides, one hinge); else a hinge
    dofs: tuple             # its dofs' indices in qd (one for a hinge, three for a root)
    axes: tuple             # hinge: its joint frame's angular axes (a0, a1, a2)
    limit: tuple            # hinge: (lo, hi), or () where it has none
    slides: tuple           # root: ((row, axis), (row, axis)) of its two slides
    turn: int               # root: the row that turns
    turn_axis: tuple        # root: its torque axis in the joint frame, before j.rot
    turn_rotates: bool      #   ... rotated by j.rot (rows 1, 2: brax's child axes)
    turn_parity: float      #   ... and times the frame's parity (row 2)
    turn_motion: tuple      # root: dof.motion.ang of the turning row


@dataclasses.dataclass(frozen=True)
class Contact:
    """One contact of a capsule on link `link` against a plane fixed in the world."""
    link: int
    geom_pos: tuple
    geom_rot: tuple
    half: float             # the end's offset along the capsule's axis (+/- half-length)
    radius: float
    plane_pos: tuple
    normal: tuple
    friction: float
    elasticity: float
    flat: tuple             # (link, row, col): the i_inv entry brax's impulse reads


@dataclasses.dataclass(frozen=True)
class SpringScene:
    links: tuple
    gravity: tuple
    dt: float
    vel_damp: float         # exp(vel_damping dt)
    ang_damp: float         # exp(ang_damping dt)
    erp_dt: float           # baumgarte_erp / dt
    contacts: tuple
    actuators: tuple        # per actuator: (dof, gear, gain, ctrl lo, hi, force lo, hi)
    num_dofs: int


def _contacts(sys, spheres: bool = False):
    """The scene's contacts as `Contact`s, or why they are not (a string): every pair a
    plane fixed in the world (geom 1) against a capsule on a link (geom 2), two contacts
    per pair as MJX's `plane_capsule` makes them, or where `spheres` also a sphere on a
    link, one contact as MJX's `plane_sphere` makes it (a capsule end with no half-length:
    `half` 0.0, which the algebra folds away)."""
    from brax import contact
    from mujoco import mjx
    c = contact.get(sys, Transform.zero((sys.num_links(),)))
    if c is None:
        return ()
    g1, g2 = np.asarray(c.geom1), np.asarray(c.geom2)
    body = np.asarray(sys.geom_bodyid)
    types = np.asarray(sys.geom_type)
    plane, capsule = int(mjx.GeomType.PLANE), int(mjx.GeomType.CAPSULE)
    shapes = (capsule, int(mjx.GeomType.SPHERE)) if spheres else (capsule,)
    if np.any(types[g1] != plane) or np.any(body[g1] != 0):
        return "it has contacts other than against a plane fixed in the world"
    if np.any(~np.isin(types[g2], shapes)) or np.any(body[g2] == 0):
        return ("it has contacts of shapes other than capsules" +
                (" and spheres" if spheres else "") + " on its links")
    halves, k = [], 0
    while k < len(g2):  # a capsule's two ends, or a sphere
        if types[g2[k]] != capsule:
            halves.append(0.0)
            k += 1
            continue
        if k + 1 == len(g2) or g1[k] != g1[k + 1] or g2[k] != g2[k + 1]:
            return "its contacts do not come in one pair per capsule end"
        half = _f32(sys.geom_size[g2[k]][1])
        halves += [half, -half]
        k += 2
    n_links = sys.num_links()
    out = []
    for k, (a, b) in enumerate(zip(g1, g2)):
        link = int(body[b]) - 1
        normal = np.asarray(math.quat_to_3x3(jnp.asarray(sys.geom_quat[a])))[:, 2]
        flat = np.unravel_index(link, (n_links, 3, 3))
        out.append(Contact(
            link=link, geom_pos=_const(sys.geom_pos[b]), geom_rot=_const(sys.geom_quat[b]),
            half=halves[k], radius=_f32(sys.geom_size[b][0]),
            plane_pos=_const(sys.geom_pos[a]), normal=_const(normal),
            friction=_f32(np.asarray(c.friction)[k, 0]),
            elasticity=_f32(np.asarray(c.elasticity)[k]),
            flat=tuple(int(i) for i in flat)))
    return tuple(out)


def spring_constants(sys) -> tuple:
    """(mass, i_diag, lo, hi): each link's mass and inertia diagonal as brax's spring step
    scales them (m ** (1 - spring_mass_scale), diag(I) ** (1 - spring_inertia_scale)), and
    each dof's limits (infinite where the scene has none), float32."""
    msc, isc = float(sys.spring_mass_scale), float(sys.spring_inertia_scale)
    mass = np.asarray(sys.link.inertia.mass, np.float32) ** np.float32(1 - msc)
    i_diag = (np.diagonal(np.asarray(sys.link.inertia.i, np.float32), axis1=1, axis2=2)
              ** np.float32(1 - isc))
    lo, hi = ((np.asarray(a, np.float32) for a in sys.dof.limit) if sys.dof.limit is not None
              else (np.full(sys.qd_size(), -np.inf), np.full(sys.qd_size(), np.inf)))
    return mass, i_diag, lo, hi


def spring_scene(sys) -> SpringScene | str:
    """The constants `control_step` reads, or why the scene is not one it models (a
    string): a tree of links whose joints are hinges, and planar roots
    (`tasks.physics.spring_adjoint.planar_roots`), motors (no position or velocity bias), no fluid,
    contacts of capsules against a plane fixed in the world. That a substep keeps the scene
    in the x-z plane is checked by tracing it (`spring_refusal`)."""
    from tasks.physics.spring_adjoint import planar_roots

    if isinstance(sys.dof.motion.ang, jax.core.Tracer):
        return "its constants are traced (not known while tracing)"
    if sys.enable_fluid:
        return "it has fluid forces"
    if any(t not in "13" for t in sys.link_types):
        return "it has a joint that is neither one dof nor a planar root"
    motion_ang, motion_vel = np.asarray(sys.dof.motion.ang), np.asarray(sys.dof.motion.vel)
    roots = planar_roots(sys) if "3" in sys.link_types else None
    if "3" in sys.link_types and roots is None:
        return "it has a 3-dof joint that is not a planar root (two slides and a hinge)"
    act = sys.actuator
    if np.any(np.asarray(act.bias_q)) or np.any(np.asarray(act.bias_qd)):
        return "it has actuators with a position or velocity bias (servos)"
    if _const(sys.gravity)[1] != 0.0:
        return "its gravity is not in the x-z plane"
    contacts = _contacts(sys)
    if isinstance(contacts, str):
        return contacts
    mass, i_diag, lo, hi = spring_constants(sys)
    link_of_dof = np.asarray(sys.dof_link())
    links = []
    for i, typ in enumerate(sys.link_types):
        dofs = tuple(int(d) for d in np.flatnonzero(link_of_dof == i))
        motion = jax.tree.map(lambda a: a[dofs[0]:dofs[-1] + 1], sys.dof.motion)
        frame, parity = kinematics.link_to_joint_frame(motion)
        frame_ang = np.asarray(frame.ang)
        common = dict(
            parent=int(sys.link_parents[i]),
            transform=(_const(sys.link.transform.pos[i]), _const(sys.link.transform.rot[i])),
            joint=(_const(sys.link.joint.pos[i]), _const(sys.link.joint.rot[i])),
            neg_com=_const(-np.asarray(sys.link.inertia.transform.pos[i])),
            inertia_rot=_const(sys.link.inertia.transform.rot[i]),
            inertia_inv=_const(np.float32(1) / i_diag[i]), mass=_f32(mass[i]),
            stiffness=_f32(sys.link.constraint_stiffness[i]),
            vel_damping=_f32(sys.link.constraint_vel_damping[i]),
            ang_damping=_f32(sys.link.constraint_ang_damping[i]),
            limit_stiffness=_f32(sys.link.constraint_limit_stiffness[i]), dofs=dofs)
        if typ == "1":
            if not np.any(motion_ang[dofs[0]]) or np.any(motion_vel[dofs[0]]):
                return "it has a 1-dof joint that slides (a hinge is what it models)"
            bounds = (lo[dofs[0]], hi[dofs[0]])
            limit = (() if not np.all(np.isfinite(bounds))
                     else (_f32(bounds[0]), _f32(bounds[1])))
            links.append(SpringLink(
                **common, root=False, axes=tuple(_const(a) for a in frame_ang), limit=limit,
                slides=(), turn=0, turn_axis=ORIGIN, turn_rotates=False, turn_parity=1.0,
                turn_motion=ORIGIN))
        else:
            (s0, s1), turn = roots
            links.append(SpringLink(
                **common, root=True, axes=(), limit=(),
                slides=tuple((r, _const(motion_vel[dofs[r]])) for r in (s0, s1)),
                turn=turn, turn_axis=_const(frame_ang[turn]), turn_rotates=turn != 0,
                turn_parity=_f32(parity) if turn == 2 else 1.0,
                turn_motion=_const(motion_ang[dofs[turn]])))
    dt = _f32(sys.opt.timestep)
    damp = lambda d: _f32(np.exp(np.float32(d) * np.float32(dt)))  # noqa: E731
    actuators = tuple(
        (int(qd), _f32(g), _f32(k), *(_f32(v) for v in cr), *(_f32(v) for v in fr))
        for qd, g, k, cr, fr in zip(np.asarray(act.qd_id), np.asarray(act.gear),
                                    np.asarray(act.gain), np.asarray(act.ctrl_range),
                                    np.asarray(act.force_range)))
    return SpringScene(
        links=tuple(links), gravity=_const(sys.gravity), dt=dt,
        vel_damp=damp(sys.vel_damping), ang_damp=damp(sys.ang_damping),
        erp_dt=_f32(np.float32(sys.baumgarte_erp) / np.float32(dt)), contacts=contacts,
        actuators=actuators, num_dofs=int(sys.qd_size()))


# ----------------------------------------------------------------------------------------
# brax's spring pipeline, line by line, over the planar algebra.
# ----------------------------------------------------------------------------------------


def safe_norm(v):
    """brax.math.safe_norm: |v|, and 0 with a zero gradient where every entry is within
    1e-8 of zero (entry by entry where the entries are arrays over links:
    `tasks.physics.planar_links`)."""
    live = [a for a in v if not _is(a, 0.0)]
    if not live:
        return 0.0
    is_zero = jnp.all(jnp.stack([jnp.abs(a) <= 1e-8 for a in live]), axis=0)
    shifted = tuple(add(a, is_zero * 1.0) for a in v)
    return jnp.sqrt(dot(shifted, shifted)) * (1.0 - is_zero)


def normalize(v):
    """brax.math.normalize: v / |v| (v / 1e-6 at exactly zero)."""
    norm = safe_norm(v)
    if _is(norm, 0.0):
        return v
    scale = norm + 1e-6 * (norm == 0.0)
    return tuple(div(a, scale) for a in v)


def z_axis(q):
    """The third column of brax.math.quat_to_3x3(q) (MJX's capsule axis): q's turn of z,
    scaled as brax scales it (by 2 / |q|^2), so that the VJP in q is brax's off the unit
    sphere too."""
    w, x, y, z = q
    s = div(2.0, dot(q, q))
    xs, ys, zs = mul(x, s), mul(y, s), mul(z, s)
    return (add(mul(x, zs), mul(w, ys)), sub(mul(y, zs), mul(w, xs)),
            sub(1.0, add(mul(x, xs), mul(y, ys))))


def _excess(angle, lo, hi):
    """How far `angle` is past [lo, hi] (0 within), as brax's joint forces."""
    d = jnp.where(angle < lo, angle - lo, 0.0)
    return jnp.where(angle > hi, angle - hi, d)


def joint_force(ln: SpringLink, j, jd, tau):
    """A joint's force in its joint frame: (ang, vel). A hinge:
    `tasks.physics.spring_adjoint.hinge` (brax's `_one_dof` for a hinge); a planar root:
    `tasks.physics.spring_adjoint.planar_root` (brax's `_three_dof` for one)."""
    vel = vsub(vscale(neg(ln.stiffness), j[0]), vscale(ln.vel_damping, jd[0]))
    if not ln.root:
        a0, a1, a2 = ln.axes
        ang = vscale(mul(-1.0, ln.stiffness), cross(a0, rotate(a0, j[1])))
        ang = vsub(vadd(ang, vscale(tau[ln.dofs[0]], a0)), vscale(ln.ang_damping, jd[1]))
        if ln.limit:
            lon = normalize(cross(rotate(a2, j[1]), a0))
            psi = jnp.arctan2(dot(cross(a1, lon), a0), dot(a1, lon))
            dang = _excess(psi, *ln.limit)
            ang = vsub(ang, vscale(dang, vscale(ln.limit_stiffness, a0)))
        return ang, vel
    (r0, s0), (r1, s1) = ln.slides
    vel = vsub(vel, vadd(vscale(dot(s0, vel), s0), vscale(dot(s1, vel), s1)))
    ang = vscale(mul(-1.0, ln.ang_damping), jd[1])
    axis = rotate(ln.turn_axis, j[1]) if ln.turn_rotates else ln.turn_axis
    axis = vscale(ln.turn_parity, axis)
    ang = vadd(ang, vscale(tau[ln.dofs[ln.turn]], axis))
    vel = vadd(vel, vadd(vscale(tau[ln.dofs[r0]], s0), vscale(tau[ln.dofs[r1]], s1)))
    a = ln.turn_motion
    ang = vadd(ang, vscale(mul(-1.0, ln.stiffness), cross(a, rotate(a, j[1]))))
    return ang, vel


def joint_forces(sc: SpringScene, tau, jw, x_i):
    """brax.spring.joints.resolve: each joint's force moved to world frame, applied at its
    link's centre of mass and, opposite, at its parent's. (ang, vel) per link."""
    in_joint = [joint_force(ln, j, jd, tau) for ln, (j, jd, _, _) in zip(sc.links, jw)]
    return to_links(sc, in_joint, jw, x_i)


def joint_torques(sc: SpringScene, act):
    """brax.actuator.to_tau for motors: each dof's force."""
    tau = [0.0] * sc.num_dofs
    for k, (dof, gear, gain, c_lo, c_hi, f_lo, f_hi) in enumerate(sc.actuators):
        force = mul(gain, jnp.clip(act[k], c_lo, c_hi))
        if not (f_lo == -np.inf and f_hi == np.inf):
            force = jnp.clip(force, f_lo, f_hi)
        tau[dof] = add(tau[dof], mul(force, gear))
    return tau


def collisions(sc: SpringScene, x, x_i, xd_i, i_inv):
    """brax.spring.collisions.resolve for capsules on a plane: each contact's impulse
    (brax's `impulse`; the world's side carries no velocity, mass or inertia), moved to
    its link's centre of mass, averaged over the link's active contacts and turned into a
    delta-velocity. (vel, ang) per link."""
    acc = {}
    for c in sc.contacts:
        k = c.link
        pos, rot = x[k]
        centre = vadd(pos, rotate(c.geom_pos, rot))
        axis = z_axis(quat_mul(rot, c.geom_rot))
        end = vadd(centre, vscale(c.half, axis))
        dist = sub(dot(vsub(end, c.plane_pos), c.normal), c.radius)
        cpos = vsub(end, vscale(add(c.radius, mul(0.5, dist)), c.normal))
        rel_pos = vsub(cpos, x_i[k][0])
        contact_vel = tuple(neg(a) for a in vadd(xd_i[k][0], cross(xd_i[k][1], rel_pos)))
        nn = tuple(neg(a) for a in c.normal)
        normal_vel = dot(nn, contact_vel)
        flat = i_inv[c.flat[0]][c.flat[1]][c.flat[2]]
        ang = dot(nn, cross(vscale(flat, cross(rel_pos, nn)), rel_pos))
        inv_mass = div(1.0, sc.links[k].mass)
        impulse = (sub(mul(-(1.0 + c.elasticity), normal_vel), mul(sc.erp_dt, dist))
                   / add(inv_mass, ang))
        vel_d = vadd(contact_vel, vscale(normal_vel, c.normal))
        speed = safe_norm(vel_d)
        dir_d = tuple(div(a, 1e-6 + speed) for a in vel_d)
        ang_d = dot(dir_d, cross(vscale(flat, cross(rel_pos, dir_d)), rel_pos))
        impulse_d = jnp.minimum(speed / add(inv_mass, ang_d), c.friction * impulse)
        apply_n = ((dist < 0.0) & (normal_vel < 0) & (impulse > 0.0)).astype(impulse.dtype)
        apply_d = apply_n * (speed > 1e-3)
        f = vadd(vscale(mul(impulse, apply_n), nn), vscale(mul(neg(impulse_d), apply_d), dir_d))
        p = tuple(neg(a) for a in f)              # the link is the contact's second body
        vel, ang_p, n = acc.get(k, (ORIGIN, ORIGIN, 0.0))
        acc[k] = (vadd(vel, p), vadd(ang_p, cross(rel_pos, p)), add(n, apply_n))
    out = []
    for k, ln in enumerate(sc.links):
        if k not in acc:
            out.append((ORIGIN, ORIGIN))
            continue
        vel, ang, n = acc[k]
        scale = n + 1e-8
        vel, ang = tuple(div(a, scale) for a in vel), tuple(div(a, scale) for a in ang)
        out.append((tuple(div(a, ln.mass) for a in vel), matvec(i_inv[k], ang)))
    return out


def integrate(sc: SpringScene, x_i, xd_i, xdv_i):
    """brax.spring.integrator.integrate."""
    xs, xds = [], []
    for t, m, dv in zip(x_i, xd_i, xdv_i):
        vel = vadd(vscale(sc.vel_damp, m[0]), dv[0])
        ang = vadd(vscale(sc.ang_damp, m[1]), dv[1])
        spin = vscale(sc.dt, vscale(0.5, (0.0, *ang)))
        rot = vadd(t[1], quat_mul(spin, t[1]))
        norm = jnp.sqrt(dot(rot, rot))
        xs.append((vadd(t[0], vscale(sc.dt, vel)), tuple(div(a, norm) for a in rot)))
        xds.append((vel, ang))
    return xs, xds


def substep(sc: SpringScene, x_i, xd_i, tau):
    """brax.spring.pipeline.step from the centre-of-mass frames (the state's link and joint
    frames and inverse inertia are computed from them, as brax's previous substep or reset
    did)."""
    x, xd = to_world(sc, x_i, xd_i)
    jw = world_to_joint(sc, x, xd)
    i_inv = [inv_inertia(ln, xl[1]) for ln, xl in zip(sc.links, x)]
    forces = joint_forces(sc, tau, jw, x_i)
    xd_i = [(vadd(m[0], vscale(sc.dt, vadd(sc.gravity, tuple(div(a, ln.mass) for a in f[1])))),
             vadd(m[1], vscale(sc.dt, matvec(ii, f[0]))))
            for ln, m, f, ii in zip(sc.links, xd_i, forces, i_inv)]
    xdv_i = collisions(sc, x, x_i, xd_i, i_inv)
    return integrate(sc, x_i, xd_i, xdv_i)


# ----------------------------------------------------------------------------------------
# A control step on brax's arrays.
# ----------------------------------------------------------------------------------------


def control_step(sc: SpringScene, sys, x_i, xd_i, act: jax.Array, n_frames: int):
    """One control step (`n_frames` substeps) of one env from its centre-of-mass frames
    (brax Transform `x_i`, Motion `xd_i`) and action: (frames, q, qd) as
    `tasks.physics.planar.control_step` returns them (`OUTPUTS` order), the joint coordinates by
    brax's `kinematics.inverse` of the last substep's joint frames. brax's values to
    float32 round-off for a planar scene (`spring_refusal` None). The substeps are unrolled,
    each from and to arrays, as `tasks.physics.planar.control_step`'s (and for its reasons),
    with an optimization barrier between substeps: without it XLA's CPU backend fused hopper's four
    substeps into loops that recompute each substep's values in every consumer, and the
    forward ran hundreds of times slower."""
    dtype = x_i.pos.dtype
    tau = joint_torques(sc, act)
    arrays = (x_i.pos, x_i.rot, xd_i.vel, xd_i.ang)
    for _ in range(n_frames):
        xi, xdi = substep(sc, *_tuples(*arrays, stacked=True), tau)
        arrays = jax.lax.optimization_barrier(
            (_array([t[0] for t in xi], dtype), _array([t[1] for t in xi], dtype),
             _array([m[0] for m in xdi], dtype), _array([m[1] for m in xdi], dtype)))
    frames, _ = _frames(sc, *_tuples(*arrays, stacked=True))
    out = tuple((_array([f[0] for f in frames[name]], dtype),
                 _array([f[1] for f in frames[name]], dtype)) for name in OUTPUTS)
    j = Transform(pos=out[OUTPUTS.index("j")][0], rot=out[OUTPUTS.index("j")][1])
    jd = Motion(vel=out[OUTPUTS.index("jd")][0], ang=out[OUTPUTS.index("jd")][1])
    q, qd = kinematics.inverse(sys, j, jd)
    return out, q, qd


def spring_refusal(sys) -> str | None:
    """Why `control_step` does not model brax's spring step of `sys` (None where it does):
    `spring_scene`'s reasons, or a substep that moves some frame out of the x-z plane."""
    sc = spring_scene(sys)
    if isinstance(sc, str):
        return sc
    return plane_leaks(sys, lambda *a: substep(sc, *a), lambda act: joint_torques(sc, act),
                       sc)
