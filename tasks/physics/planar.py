"""brax's positional control step for a scene that moves in one plane, written as the scene
needs it: inverted_pendulum's, and reacher's without its gravity along its hinges
(`planar_scene(drop_normal_gravity=True)`, in axes turned so that its plane is the model's
x-z). ILD differentiates it in place of brax's step (`planar_adjoint`,
`tasks.physics.transforms.with_planar_adjoint`).

A scene whose links all move in the x-z plane (slides along in-plane axes, hinges about y,
gravity in the plane, no contacts, every constant transform a turn about y) keeps every
link's position in the plane, its rotation a turn about y and its angular velocity along
y. brax's positional substep (`brax.positional.pipeline.step`, with
`tasks.physics.positional_joints`' joint update, brax's for hinges and slides) still computes all
three entries of every vector and all four of every quaternion, and its reverse mode
differentiates them all: on inverted_pendulum the physics' gradient cost about 4x brax's
forward, most of an update.

Here the same expressions are written over tuples whose out-of-plane entries are the Python
constant 0.0 (the planar algebra below: a product with it is 0.0 and a sum with it the other
term, decided while tracing), so each line of brax's 3-D code keeps its form and XLA sees
only its in-plane terms: per link a position (x, z), a quaternion (w, y), a velocity (x, z)
and an angular velocity (y). The out-of-plane entries brax computes are round-off (within
about 1e-8 of zero on inverted_pendulum); here they are
zero. The in-plane values are brax's to float32 round-off (tests/test_planar.py: positions
within 1.5e-8, velocities within 3.3e-6 over a control step). A control step's value and
VJP cost several times less than brax's (docs/physics.md).

`control_step` is one control step (`n_frames` substeps, the joint coordinates only at the
end, as `lean_substeps` computes them) as a function of the state's centre-of-mass frames
(`x_i`, `xd_i`) and the action. Those frames determine the rest of a state (link and joint
frames, joint coordinates) on every state a rollout visits: brax's substeps end, and its
resets begin, by computing the rest from them.

`planar_scene(sys)` reads the scene's constants or says why the scene is not one this
models, and `planar_refusal` also traces a substep: an out-of-plane entry that it would
make non-zero refuses the scene.
"""
from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from brax import kinematics

# ----------------------------------------------------------------------------------------
# Planar algebra: scalars that may be the static 0.0, 3-vectors and quaternions as tuples.
# ----------------------------------------------------------------------------------------


def _is(a, value: float) -> bool:
    return isinstance(a, float) and a == value


def add(a, b):
    if _is(a, 0.0):
        return b
    if _is(b, 0.0):
        return a
    return a + b


def neg(a):
    return 0.0 if _is(a, 0.0) else -a


def sub(a, b):
    return add(a, neg(b))


def mul(a, b):
    if _is(a, 0.0) or _is(b, 0.0):
        return 0.0
    if _is(a, 1.0):
        return b
    if _is(b, 1.0):
        return a
    return a * b


def div(a, b):
    return 0.0 if _is(a, 0.0) else a / b


def vadd(u, v):
    return tuple(add(a, b) for a, b in zip(u, v))


def vsub(u, v):
    return tuple(sub(a, b) for a, b in zip(u, v))


def vscale(s, v):
    return tuple(mul(s, a) for a in v)


def dot(u, v):
    total = 0.0
    for a, b in zip(u, v):
        total = add(total, mul(a, b))
    return total


def cross(u, v):
    return (sub(mul(u[1], v[2]), mul(u[2], v[1])),
            sub(mul(u[2], v[0]), mul(u[0], v[2])),
            sub(mul(u[0], v[1]), mul(u[1], v[0])))


def rotate(v, q):
    """brax.math.rotate: 2 (u . v) u + (s^2 - u . u) v + 2 s (u x v)."""
    s, u = q[0], q[1:]
    r = vadd(vscale(mul(2.0, dot(u, v)), u), vscale(sub(mul(s, s), dot(u, u)), v))
    return vadd(r, vscale(mul(2.0, s), cross(u, v)))


def quat_inv(q):
    return (q[0], neg(q[1]), neg(q[2]), neg(q[3]))


def inv_rotate(v, q):
    return rotate(v, quat_inv(q))


def quat_mul(u, v):
    return (sub(sub(sub(mul(u[0], v[0]), mul(u[1], v[1])), mul(u[2], v[2])), mul(u[3], v[3])),
            sub(add(add(mul(u[0], v[1]), mul(u[1], v[0])), mul(u[2], v[3])), mul(u[3], v[2])),
            add(add(sub(mul(u[0], v[2]), mul(u[1], v[3])), mul(u[2], v[0])), mul(u[3], v[1])),
            add(sub(add(mul(u[0], v[3]), mul(u[1], v[2])), mul(u[2], v[1])), mul(u[3], v[0])))


def vec_quat_mul(u, v):
    """brax.math.vec_quat_mul: the quaternion product (0, u) v."""
    return (sub(sub(neg(mul(u[0], v[1])), mul(u[1], v[2])), mul(u[2], v[3])),
            sub(add(mul(u[0], v[0]), mul(u[1], v[3])), mul(u[2], v[2])),
            add(add(neg(mul(u[0], v[3])), mul(u[1], v[0])), mul(u[2], v[1])),
            add(sub(mul(u[0], v[2]), mul(u[1], v[1])), mul(u[2], v[0])))


def _norm(v):
    return jnp.sqrt(dot(v, v))


def safe_normalize(v):
    """brax.math.normalize (with `safe_norm`): (v / |v|, |v|), and (v / 1e-6, 0) with a zero
    gradient where every entry is within 1e-8 of zero, as brax's."""
    live = [a for a in v if not _is(a, 0.0)]
    if not live:
        return v, 0.0
    is_zero = jnp.all(jnp.stack([jnp.abs(a) <= 1e-8 for a in live]))
    shifted = tuple(add(a, is_zero * 1.0) for a in v)
    norm = _norm(shifted) * (1.0 - is_zero)
    scale = norm + 1e-6 * (norm == 0.0)
    return tuple(div(a, scale) for a in v), norm


def plain_normalize(v):
    """`tasks.physics.positional_joints._normalize`: v / |v| (v / 1e-6 at exactly zero)."""
    live = [a for a in v if not _is(a, 0.0)]
    if not live:
        return v
    norm = _norm(v)
    scale = norm + 1e-6 * (norm == 0.0)
    return tuple(div(a, scale) for a in v)


def _f32(x) -> float:
    return float(np.float32(x))


def _const(x) -> tuple:
    """A constant vector or quaternion of the scene as Python floats (float32 values, so a
    product with a float32 array is the same product as brax's)."""
    return tuple(_f32(a) for a in np.asarray(x).ravel())


IDENTITY = (1.0, 0.0, 0.0, 0.0)
ORIGIN = (0.0, 0.0, 0.0)


# ----------------------------------------------------------------------------------------
# The scene's constants.
# ----------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Link:
    """One link's constants, as Python floats (float32 values); vectors and quaternions as
    tuples, their zero entries the exact 0.0 the algebra above folds away."""
    parent: int            # -1: the world
    dof: int               # its (first) dof's index in q and qd
    transform: tuple       # (pos, rot), brax's `link.transform` (parent frame to link's)
    joint: tuple           # (pos, rot), `link.joint` (link frame to joint's)
    neg_com: tuple         # -`link.inertia.transform.pos` (com_to_world's offset)
    inertia_rot: tuple     # `link.inertia.transform.rot` (IDENTITY where `inertia_inv` is rows)
    inertia_inv: tuple     # 1 / diag(i) ** (1 - spring_inertia_scale), or the rows of that
                           # inverse inertia turned into the link's frame (`_link_frame_inertia`)
    mass_inv: float        # 1 / mass ** (1 - spring_mass_scale)
    ang_damping: float     # `link.constraint_ang_damping`
    vel_damping: float     # `link.constraint_vel_damping`
    hinge: bool            # its one dof turns; else it slides
    motion: tuple          # the dof's axis: `dof.motion.ang` of a hinge, `.vel` of a slide
    axes: tuple            # the joint frame's angular axes a_0, a_1, a_2 (`joint_rows`)
    lo0: float             # a_0's limits (0, 0 where locked)
    hi0: float
    slides: tuple          # ((v_k, lo_k, hi_k), ...) the slide axes and their limits
    keep: tuple            # 1 - (any slide along that coordinate)
    frame: tuple           # brax's `link_to_joint_frame` angular axes (joint coordinates)
    motions: tuple = ()    # every dof's axis, `motion` first (several: a joint of slides)


@dataclasses.dataclass(frozen=True)
class Scene:
    links: tuple
    gravity: tuple
    dt: float
    vel_damp: float        # exp(vel_damping dt)
    ang_damp: float        # exp(ang_damping dt)
    joint_scale_pos: float
    joint_scale_ang: float
    actuators: tuple       # per actuator: (link of its dof, gear, gain, ctrl lo, hi, force lo, hi)
    perm: tuple = (0, 1, 2)  # the world axis each of the model's x, y, z is (`_turned`)


def planar_scene(sys, drop_normal_gravity: bool = False) -> Scene | str:
    """The constants `control_step` reads, or why the scene is not one it models (a string):
    a tree of links whose joints are hinges (one dof) or slides (one or more dofs, none
    actuated where more than one), gravity in the plane of motion, motors (no position or
    velocity bias), no contacts, no fluid. That a step keeps the scene in its plane is
    checked by tracing it (`planar_refusal`).

    The plane is the one normal to every hinge's axis: x-z (hinges about y, inverted
    pendulum's) or another, whose constants are then written in turned axes (`_turned`) so
    that the model's plane is x-z. Gravity along the plane's normal (reacher's, along its
    hinges) refuses the scene unless `drop_normal_gravity`: then the model leaves it out,
    as a scene without it (it only presses the links against their joints: in reacher's
    128-step rollout q moved 3.6e-4 rad without it)."""
    from brax import contact
    from brax.base import Transform
    from tasks.physics.positional_joints import joint_rows

    if isinstance(sys.dof.motion.ang, jax.core.Tracer):
        return "its constants are traced (not known while tracing)"
    if sys.enable_fluid:
        return "it has fluid forces"
    rows = joint_rows(sys)
    if isinstance(rows, str):
        return rows
    num = sys.num_links()
    if contact.get(sys, Transform.zero((num,))) is not None:
        return "it has contacts"
    act = sys.actuator
    if np.any(np.asarray(act.bias_q)) or np.any(np.asarray(act.bias_qd)):
        return "it has actuators with a position or velocity bias (servos)"
    motion_ang, motion_vel = np.asarray(sys.dof.motion.ang), np.asarray(sys.dof.motion.vel)
    dof_link = np.asarray(sys.dof_link())
    actuated = set(dof_link[np.asarray(act.qd_id)].tolist())
    for i in range(num):
        dofs = np.flatnonzero(dof_link == i)
        if len(dofs) > 1 and (np.any(motion_ang[dofs]) or i in actuated):
            return ("it has a joint with more than one dof that turns or is actuated (this "
                    "models those of slides alone, unactuated)")
    perm = _plane_axes(motion_ang[np.any(motion_ang, axis=1)])
    if isinstance(perm, str):
        return perm
    gravity = tuple(_const(sys.gravity)[k] for k in perm)
    if gravity[1] != 0.0:
        if not drop_normal_gravity:
            return "its gravity is not in the plane its hinges turn in"
        gravity = (gravity[0], 0.0, gravity[2])
    msc, isc = float(sys.spring_mass_scale), float(sys.spring_inertia_scale)
    mass = np.asarray(sys.link.inertia.mass, np.float32) ** np.float32(1 - msc)
    i_diag = (np.diagonal(np.asarray(sys.link.inertia.i, np.float32), axis1=1, axis2=2)
              ** np.float32(1 - isc))
    links = []
    for i in range(num):
        dofs = np.flatnonzero(dof_link == i)
        d = int(dofs[0])
        hinge = bool(np.any(motion_ang[d]))
        frame = kinematics.link_to_joint_frame(
            jax.tree.map(lambda a: a[d:d + 1], sys.dof.motion))[0].ang
        slides = tuple((_const(rows.slides[i, k]), _f32(rows.slide_lo[i, k]),
                        _f32(rows.slide_hi[i, k]))
                       for k in range(3) if np.any(rows.slides[i, k]))
        links.append(Link(
            parent=int(sys.link_parents[i]), dof=d,
            transform=(_const(sys.link.transform.pos[i]), _const(sys.link.transform.rot[i])),
            joint=(_const(sys.link.joint.pos[i]), _const(sys.link.joint.rot[i])),
            neg_com=_const(-np.asarray(sys.link.inertia.transform.pos[i])),
            inertia_rot=_const(sys.link.inertia.transform.rot[i]),
            inertia_inv=_const(np.float32(1) / i_diag[i]),
            mass_inv=_f32(np.float32(1) / mass[i]),
            ang_damping=_f32(sys.link.constraint_ang_damping[i]),
            vel_damping=_f32(sys.link.constraint_vel_damping[i]),
            hinge=hinge, motion=_const(motion_ang[d] if hinge else motion_vel[d]),
            axes=tuple(_const(a) for a in rows.axes[i]),
            lo0=_f32(rows.lo0[i]), hi0=_f32(rows.hi0[i]), slides=slides,
            keep=_const(rows.keep[i]), frame=tuple(_const(a) for a in np.asarray(frame)),
            motions=tuple(_const(motion_ang[e] if hinge else motion_vel[e]) for e in dofs)))
    links = [_turned(ln, perm) for ln in links]
    dt = _f32(sys.opt.timestep)
    damp = lambda d: _f32(np.exp(np.float32(d) * np.float32(dt)))  # noqa: E731
    actuators = tuple(
        (int(dof_link[qd]), _f32(g), _f32(k), *(_f32(v) for v in cr), *(_f32(v) for v in fr))
        for qd, g, k, cr, fr in zip(np.asarray(act.qd_id), np.asarray(act.gear),
                                    np.asarray(act.gain), np.asarray(act.ctrl_range),
                                    np.asarray(act.force_range)))
    return Scene(links=tuple(links), gravity=gravity, dt=dt, vel_damp=damp(sys.vel_damping),
                 ang_damp=damp(sys.ang_damping), joint_scale_pos=_f32(sys.joint_scale_pos),
                 joint_scale_ang=_f32(sys.joint_scale_ang), actuators=actuators, perm=perm)


def _plane_axes(hinge_axes) -> tuple | str:
    """The world axes the model's x, y, z are, so that every hinge turns about the model's y:
    (0, 1, 2) for hinges about y (and a scene with none), a turn of the axes, (1, 2, 0), for
    hinges about z (the model's y is the world's z) and (2, 0, 1) for hinges about x."""
    if len(hinge_axes) == 0:
        return (0, 1, 2)
    for normal, perm in ((1, (0, 1, 2)), (2, (1, 2, 0)), (0, (2, 0, 1))):
        if np.all(np.delete(hinge_axes, normal, axis=1) == 0):
            return perm
    return "its hinges do not all turn about one of the world's axes"


def _turned(ln: Link, perm: tuple) -> Link:
    """Link `ln`'s constants written in the axes `perm` (a cyclic turn of x, y, z, so cross
    products and the quaternions' vector parts turn with the vectors), its inverse inertia
    turned into its frame where its inertia's frame is not a turn about the model's y, and
    a root's offset from the world along the plane's normal dropped (a translation along
    the normal: the model reads the state's positions in the plane, and nothing it models
    acts along the normal)."""
    v = lambda u: tuple(u[k] for k in perm)  # noqa: E731
    q = lambda u: (u[0], *v(u[1:]))  # noqa: E731
    pos = v(ln.transform[0])
    if ln.parent < 0:
        pos = (pos[0], 0.0, pos[2])
    inertia_rot, inertia_inv = q(ln.inertia_rot), v(ln.inertia_inv)
    if inertia_rot[1] != 0.0 or inertia_rot[3] != 0.0:
        inertia_rot, inertia_inv = IDENTITY, _link_frame_inertia(inertia_rot, inertia_inv)
    return dataclasses.replace(
        ln, transform=(pos, q(ln.transform[1])), joint=(v(ln.joint[0]), q(ln.joint[1])),
        neg_com=v(ln.neg_com), inertia_rot=inertia_rot, inertia_inv=inertia_inv,
        motion=v(ln.motion), axes=tuple(v(a) for a in ln.axes),
        slides=tuple((v(u), lo, hi) for u, lo, hi in ln.slides), keep=v(ln.keep),
        frame=tuple(v(a) for a in ln.frame), motions=tuple(v(m) for m in ln.motions))


def _link_frame_inertia(rot: tuple, diag: tuple) -> tuple:
    """The rows of R diag R^T (R the turn `rot`) as float32 Python floats, its entries under
    1e-6 of the largest the static 0.0: for an inertia whose principal axes lie along the
    link's (reacher's capsules, turned 90 and 120 degrees onto x), the off-axis entries are
    round-off of the float32 quaternion, exactly zero in the scene."""
    w, x, y, z = (float(a) for a in rot)
    r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                  [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                  [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])
    m = r @ np.diag(np.asarray(diag, np.float64)) @ r.T
    m[np.abs(m) < 1e-6 * np.abs(m).max()] = 0.0
    return tuple(tuple(_f32(a) for a in row) for row in m)


# ----------------------------------------------------------------------------------------
# brax's positional pipeline, line by line, over the planar algebra. A transform is a
# (pos, rot) pair, a motion a (vel, ang) pair; a frame list has one entry per link.
# ----------------------------------------------------------------------------------------

ZERO_T = (ORIGIN, IDENTITY)   # brax's Transform.zero: a root's parent
ZERO_M = (ORIGIN, ORIGIN)


def compose(a, b):
    """Transform.do(Transform): a then b in a's frame."""
    return vadd(a[0], rotate(b[0], a[1])), quat_mul(a[1], b[1])


def shift_motion(pos, m):
    """Transform.create(pos=pos).do(Motion): the motion seen from a point offset by pos."""
    return vsub(m[0], cross(pos, m[1])), m[1]


def to_world(sc: Scene, x_i, xd_i):
    """brax.com.to_world: centre-of-mass frames to link frames."""
    x, xd = [], []
    for ln, t, m in zip(sc.links, x_i, xd_i):
        xl = compose(t, (ln.neg_com, IDENTITY))
        x.append(xl)
        xd.append(shift_motion(vsub(xl[0], t[0]), m))
    return x, xd


def _parent(frames, ln: Link, zero):
    return zero if ln.parent < 0 else frames[ln.parent]


def joint_frames(ln, x_p, xd_p, xl, xdl):
    """brax.kinematics.world_to_joint of link `ln` (its `transform` and `joint`) from its
    parent's frames and its own: (j, jd, a_p, a_c). Also of every link at once, over
    entries that are arrays over the links (`tasks.physics.planar_links`)."""
    a_p = compose(compose(x_p, ln.transform), ln.joint)
    a_c = compose(xl, ln.joint)
    inv = quat_inv(a_p[1])
    j = (rotate(vsub(a_c[0], a_p[0]), inv), quat_mul(inv, a_c[1]))
    wj = shift_motion(vsub(x_p[0], a_p[0]), xd_p)
    jd = (inv_rotate(vsub(xdl[0], wj[0]), a_p[1]), inv_rotate(vsub(xdl[1], wj[1]), a_p[1]))
    return j, jd, a_p, a_c


def world_to_joint(sc: Scene, x, xd):
    """brax.kinematics.world_to_joint: (j, jd, a_p, a_c) per link."""
    return [joint_frames(ln, _parent(x, ln, ZERO_T), _parent(xd, ln, ZERO_M), xl, xdl)
            for ln, xl, xdl in zip(sc.links, x, xd)]


def inv_inertia(ln: Link, rot):
    """brax.com.inv_inertia of one link (rows of the 3 x 3 matrix)."""
    ri = quat_mul(rot, ln.inertia_rot)
    eye = ln.inertia_inv
    if not isinstance(eye[0], tuple):   # the diagonal
        eye = ((eye[0], 0.0, 0.0), (0.0, eye[1], 0.0), (0.0, 0.0, eye[2]))
    rows = [rotate(r, ri) for r in eye]
    return tuple(rotate(tuple(r[k] for r in rows), ri) for k in range(3))


def matvec(m, v):
    return tuple(dot(r, v) for r in m)


def _clip(a, lo: float, hi: float):
    if lo == -np.inf and hi == np.inf:
        return a
    return jnp.clip(a, lo, hi)


def joint_forces(sc: Scene, tau, jw, x_i):
    """brax.positional.joints.acceleration_update (as tasks.physics.positional_joints writes it):
    per link, its dof's force along its axis less the constraint damping of the joint
    motion, in world frame, applied at the link's centre of mass and, opposite, at its
    parent's. Returns (ang, vel) per link."""
    in_joint = []
    for ln, t, (_, jd, _, _) in zip(sc.links, tau, jw):
        ang = vscale(t, ln.motion) if ln.hinge else ORIGIN
        vel = ORIGIN if ln.hinge else vscale(t, ln.motion)
        in_joint.append((vsub(ang, vscale(ln.ang_damping, jd[1])),
                         vsub(vel, vscale(ln.vel_damping, jd[0]))))
    return to_links(sc, in_joint, jw, x_i)


def to_links(sc, in_joint, jw, x_i):
    """Each joint's force (ang, vel) in its joint frame moved to world frame and applied at
    its link's centre of mass and, opposite, at its parent's (brax's joint-force
    resolution, both backends): (ang, vel) per link."""
    out, moved = [], []
    for ln, (ang, vel), (_, _, a_p, a_c), xi in zip(sc.links, in_joint, jw, x_i):
        vel, ang = rotate(vel, a_p[1]), rotate(ang, a_p[1])
        out.append([vadd(ang, cross(vsub(a_c[0], xi[0]), vel)), vel])
        if ln.parent >= 0:
            moved.append((ln.parent, vadd(ang, cross(vsub(a_p[0], x_i[ln.parent][0]), vel)),
                          vel))
    for p, ang, vel in moved:
        out[p] = [vsub(out[p][0], ang), vsub(out[p][1], vel)]
    return out


def joint_update(ln: Link, j):
    """`tasks.physics.positional_joints.joint_update` of one link: (dx, dq) in its joint frame."""
    a0, a1, a2 = ln.axes
    c0, c1, c2 = (rotate(a, j[1]) for a in ln.axes)
    n = plain_normalize(cross(c2, a0))
    m = plain_normalize(vadd(vscale(dot(a0, c0), c0), vscale(dot(a0, c1), c1)))
    sine = dot(cross(a1, n), a0)
    if _is(sine, 0.0) and ln.lo0 == ln.hi0 == 0.0:
        # A joint locked about a_0 whose frame keeps a_1 and n both on the plane's normal
        # (a slide's: a_0 = x, a_1 = y): ph = atan2(0, a_1 . n) is 0 or pi, and
        # sin(ph - clip(ph, 0, 0)) is 0 or sin(pi) (-8.7e-8 in float32), with a zero
        # derivative either way: zero.
        off = 0.0
    else:
        ph = jnp.arctan2(sine, dot(a1, n))
        off = jnp.sin(ph - jnp.clip(ph, ln.lo0, ln.hi0))
    dq = vscale(-1.0, vadd(vadd(vscale(off, a0), cross(a0, m)), cross(n, c1)))
    dx = vscale(-1.0, tuple(mul(p, k) for p, k in zip(j[0], ln.keep)))
    for v, lo, hi in ln.slides:
        xp = dot(v, j[0])
        dx = vsub(dx, vscale(xp - jnp.clip(xp, lo, hi), v))
    return dx, dq


def translation_update(pos_p, xi_p, i_inv_p, m_inv_p, pos_c, xi_c, i_inv_c, m_inv_c, dx):
    """brax.positional.joints._translation_update: (parent's, child's) (pos, rot) deltas."""
    pos_p, pos_c = vsub(pos_p, xi_p[0]), vsub(pos_c, xi_c[0])
    n, c = safe_normalize(dx)
    cr1, cr2 = cross(pos_p, n), cross(pos_c, n)
    w1 = add(m_inv_p, dot(cr1, matvec(i_inv_p, cr1)))
    w2 = add(m_inv_c, dot(cr2, matvec(i_inv_c, cr2)))
    dlambda = neg(c) / (add(w1, w2) + 1e-6)
    p = vscale(dlambda, n)
    rot_p = vscale(-0.5, vec_quat_mul(matvec(i_inv_p, cross(pos_p, p)), xi_p[1]))
    rot_c = vscale(0.5, vec_quat_mul(matvec(i_inv_c, cross(pos_c, p)), xi_c[1]))
    return ((vscale(neg(m_inv_p), p), rot_p), (vscale(m_inv_c, p), rot_c))


def rotation_update(xi_p, i_inv_p, xi_c, i_inv_c, dq):
    """brax.positional.joints._rotation_update: (parent's, child's) rotation deltas."""
    n, th = safe_normalize(dq)
    w1, w2 = dot(n, matvec(i_inv_p, n)), dot(n, matvec(i_inv_c, n))
    dlambda = neg(th) / (add(w1, w2) + 1e-6)
    p = vscale(neg(dlambda), n)
    rot_p = vscale(-0.5, vec_quat_mul(matvec(i_inv_p, p), xi_p[1]))
    rot_c = vscale(0.5, vec_quat_mul(matvec(i_inv_c, p), xi_c[1]))
    return rot_p, rot_c


ZERO_I = ((0.0,) * 3,) * 3   # a root's parent's inverse inertia (brax masks it to zero)


def position_update(sc: Scene, x_i, x, xd):
    """brax.positional.joints.position_update (tasks.physics.positional_joints' joint update): the
    centre-of-mass frames after one pass of the joints' position-level corrections."""
    jw = world_to_joint(sc, x, xd)
    i_inv = [inv_inertia(ln, xl[1]) for ln, xl in zip(sc.links, x)]
    s_pos, s_ang = sc.joint_scale_pos, sc.joint_scale_ang
    delta = [[ORIGIN, (0.0,) * 4] for _ in sc.links]
    for k, (ln, (j, _, a_p, a_c)) in enumerate(zip(sc.links, jw)):
        root = ln.parent < 0
        xi_p = ZERO_T if root else x_i[ln.parent]
        i_inv_p = ZERO_I if root else i_inv[ln.parent]
        m_inv_p = 0.0 if root else sc.links[ln.parent].mass_inv
        dx, dq = joint_update(ln, j)
        dx_w, dq_w = rotate(dx, a_p[1]), rotate(dq, a_p[1])
        (tp, tc) = translation_update(a_p[0], xi_p, i_inv_p, m_inv_p, a_c[0], x_i[k],
                                      i_inv[k], ln.mass_inv, vscale(-1.0, dx_w))
        rp, rc = rotation_update(xi_p, i_inv_p, x_i[k], i_inv[k], dq_w)
        child = (vscale(s_pos, tc[0]),                       # the rotation update's pos is 0
                 vadd(vscale(s_pos, tc[1]), vscale(s_ang, rc)))
        delta[k] = [vadd(delta[k][0], child[0]), vadd(delta[k][1], child[1])]
        if not root:
            par = (vscale(s_pos, tp[0]), vadd(vscale(s_pos, tp[1]), vscale(s_ang, rp)))
            p = ln.parent
            delta[p] = [vadd(delta[p][0], par[0]), vadd(delta[p][1], par[1])]
    return [(vadd(t[0], d[0]), vadd(t[1], d[1])) for t, d in zip(x_i, delta)]


def integrate(sc: Scene, x_i, xd_i, xdd_i):
    """brax.positional.integrator.integrate_xdd."""
    xs, xds = [], []
    for t, m, a in zip(x_i, xd_i, xdd_i):
        vel = vscale(sc.vel_damp, vadd(m[0], vscale(sc.dt, a[0])))
        ang = vscale(sc.ang_damp, vadd(m[1], vscale(sc.dt, a[1])))
        spin = vscale(sc.dt, vscale(0.5, (0.0, *ang)))
        rot, _ = safe_normalize(vadd(t[1], quat_mul(spin, t[1])))
        xs.append((vadd(t[0], vscale(sc.dt, vel)), rot))
        xds.append((vel, ang))
    return xs, xds


def project_xd(sc: Scene, x_i, x_i_prev):
    """brax.positional.integrator.project_xd, then integrate_xdv with no contact."""
    out = []
    for t, tp in zip(x_i, x_i_prev):
        vel = tuple(div(d, sc.dt) for d in vsub(t[0], tp[0]))
        dq = quat_mul(t[1], quat_inv(tp[1]))
        scale = jnp.where(dq[0] >= 0.0, 1.0, -1.0)
        ang = tuple(mul(scale, div(mul(2.0, d), sc.dt)) for d in dq[1:])
        out.append((vscale(sc.vel_damp, vel), vscale(sc.ang_damp, ang)))
    return out


def joint_coordinates(sc: Scene, jw):
    """brax.kinematics.inverse for one-dof joints: (q, qd) per link."""
    q, qd = [], []
    for ln, (j, jd, _, _) in zip(sc.links, jw):
        if ln.hinge:
            j_rot = j[1] if ln.parent < 0 else IDENTITY
            ang = inv_rotate(jd[1], j_rot)
            f0, f1, f2 = ln.frame
            c0, c2 = rotate(f0, j[1]), rotate(f2, j[1])
            nodes, _ = safe_normalize(cross(c2, f0))
            q.append(jnp.arctan2(dot(cross(f1, nodes), f0), dot(f1, nodes)))
            qd.append(dot(c0, ang))
        else:
            q.extend(dot(m, j[0]) for m in ln.motions)
            qd.extend(dot(m, jd[0]) for m in ln.motions)
    return q, qd


def joint_torques(sc: Scene, act):
    """brax.actuator.to_tau for motors: per link, its dof's force."""
    tau = [0.0] * len(sc.links)
    for k, (link, gear, gain, c_lo, c_hi, f_lo, f_hi) in enumerate(sc.actuators):
        force = _clip(mul(gain, jnp.clip(act[k], c_lo, c_hi)), f_lo, f_hi)
        tau[link] = add(tau[link], mul(force, gear))
    return tau


def _through_arrays(x_i, xd_i):
    """The frames `integrate` returns, stacked into arrays and read back: the same values.
    In reverse mode this keeps XLA's CPU backend from fusing position_update's scalar VJP
    graph into the loops that pad the input arrays' cotangents, which evaluate that graph
    per array element (and, by their cost, what the entries share once per entry): on
    reacher one such loop, the input quaternions' cotangent, took most of a substep VJP.
    Read back from arrays, its cotangent is padded once here, after position_update's VJP,
    and integrate's VJP reads it: the same values to float32 round-off, in a fraction of the
    time."""
    dtype = jnp.result_type(*(a for t in x_i for a in t[0] + t[1] if not isinstance(a, float)))
    return _tuples(*_stacked(x_i, xd_i, dtype))


def _stacked(x_i, xd_i, dtype) -> tuple:
    """Centre-of-mass frames (per link, tuples) as brax's arrays: (pos, rot, vel, ang)."""
    return (_array([t[0] for t in x_i], dtype), _array([t[1] for t in x_i], dtype),
            _array([m[0] for m in xd_i], dtype), _array([m[1] for m in xd_i], dtype))


def substep(sc: Scene, x_i, xd_i, tau):
    """brax.positional.pipeline.step without contacts, from the centre-of-mass frames (the
    state's link and joint frames are computed from them, as brax's previous substep or
    reset did)."""
    x, xd = to_world(sc, x_i, xd_i)
    jw = world_to_joint(sc, x, xd)
    forces = joint_forces(sc, tau, jw, x_i)
    xdd = [(vadd(sc.gravity, vscale(ln.mass_inv, f[1])), matvec(inv_inertia(ln, xl[1]), f[0]))
           for ln, f, xl in zip(sc.links, forces, x)]
    x_i_prev = x_i
    x_i, xd_i = _through_arrays(*integrate(sc, x_i, xd_i, xdd))
    x, xd = to_world(sc, x_i, xd_i)
    x_i = position_update(sc, x_i, x, xd)
    xd_i = project_xd(sc, x_i, x_i_prev)
    return x_i, xd_i


# ----------------------------------------------------------------------------------------
# A control step on brax's arrays.
# ----------------------------------------------------------------------------------------

LIVE = {"pos": (0, 2), "rot": (0, 2), "vel": (0, 2), "ang": (1,)}
"""The entries of each kind of array that a planar state moves: a position's and a
velocity's x and z, a quaternion's w and y (a turn about y), an angular velocity's y."""


def _array(rows, dtype) -> jax.Array:
    return jnp.stack([jnp.stack([jnp.asarray(a, dtype) for a in r]) for r in rows])


OUTPUTS = ("x", "xd", "x_i", "xd_i", "j", "jd", "a_p", "a_c")
"""The state's frames `control_step` returns (and `cotangent` reads), each a (Transform or
Motion) pair of arrays, then q and qd."""


def _frames(sc: Scene, x_i, xd_i):
    """Every frame of a state, from its centre-of-mass frames, as brax's substep ends."""
    x, xd = to_world(sc, x_i, xd_i)
    jw = world_to_joint(sc, x, xd)
    return {"x": x, "xd": xd, "x_i": x_i, "xd_i": xd_i, "j": [w[0] for w in jw],
            "jd": [w[1] for w in jw], "a_p": [w[2] for w in jw], "a_c": [w[3] for w in jw]}, jw


WIDTH = {"pos": 3, "rot": 4, "vel": 3, "ang": 3}


@functools.partial(jax.custom_vjp, nondiff_argnums=(1,))
def _rows(a, kind: str):
    """Each row of array `a` (one link's) as a tuple of its `LIVE[kind]` entries."""
    return tuple(tuple(a[r, k] for k in LIVE[kind]) for r in range(a.shape[0]))


def _rows_fwd(a, kind):
    return _rows(a, kind), None


def _rows_bwd(kind, res, ct):
    """The array's cotangent stacked from its entries' (zeros off the plane). Reverse mode
    of the entries' slices would pad each entry's cotangent to the array's shape and sum
    the pads, and XLA's CPU backend fuses those pads, with the scalar computations that
    produce the cotangents, into loops over the whole array that compute every one of them
    once per array element: on hopper's spring step 98 such fusions per control step, 11.6
    us each at B = 32, 0.17 s of a 0.38 s update. Stacked, each entry's
    computation runs once."""
    zero = jnp.zeros_like(ct[0][0])
    rows = []
    for row in ct:
        live = dict(zip(LIVE[kind], row))
        rows.append(jnp.stack([live.get(k, zero) for k in range(WIDTH[kind])]))
    return (jnp.stack(rows),)


_rows.defvjp(_rows_fwd, _rows_bwd)


def in_plane(entry, kind: str) -> tuple:
    """A vector or quaternion of `kind` as a tuple: `entry(k)` for each in-plane entry k,
    the static 0.0 for the others."""
    return tuple(entry(k) if k in LIVE[kind] else 0.0 for k in range(WIDTH[kind]))


def _from_rows(a, kind: str) -> list:
    """One link's row of a brax array per link as a tuple, its out-of-plane entries 0.0."""
    return [in_plane(lambda k, row=row: row[LIVE[kind].index(k)], kind)
            for row in _rows(a, kind)]


def _planar(a, kind: str) -> tuple:
    """One link's row of a brax array as a tuple, its out-of-plane entries 0.0."""
    return in_plane(lambda k: a[k], kind)


def _tuples(pos, rot, vel, ang, stacked: bool = False):
    """The arrays' rows as tuples over the planar algebra. `stacked`: read through `_rows`,
    whose backward stacks the entries' cotangents (the spring step, whose substeps an
    optimization barrier separates). The positional step reads them by slicing: its
    unrolled substeps have no barrier, and with `_rows` XLA's CPU backend
    compiled inverted_pendulum's 16-step gradient into a program that ran for minutes in
    8.5 GiB."""
    if not stacked:
        return ([(_planar(p, "pos"), _planar(r, "rot")) for p, r in zip(pos, rot)],
                [(_planar(v, "vel"), _planar(w, "ang")) for v, w in zip(vel, ang)])
    return (list(zip(_from_rows(pos, "pos"), _from_rows(rot, "rot"))),
            list(zip(_from_rows(vel, "vel"), _from_rows(ang, "ang"))))


def control_step(sc: Scene, x_i, xd_i, act: jax.Array, n_frames: int):
    """One control step (`n_frames` substeps) of one env from its centre-of-mass frames
    (brax Transform `x_i`, Motion `xd_i`) and action: (frames, q, qd), `frames` a tuple of
    (first, second) array pairs in `OUTPUTS` order (pos and rot of a Transform, vel and ang
    of a Motion), q and qd in dof order, as brax's step ends (the joint coordinates of the
    last substep only, as `lean_substeps`). brax's values to float32 round-off for a
    planar scene (`planar_refusal` None).

    The substeps are unrolled, each from and to arrays: as a scan, XLA's CPU runtime ran
    the step's VJP more than twice as slowly, and as one graph of scalars from input to
    output (no arrays between substeps) ILD's update took minutes to compile. Each substep also passes
    through arrays after `integrate` (`_through_arrays`)."""
    dtype = x_i.pos.dtype
    tau = joint_torques(sc, act)
    arrays = _in_axes(sc.perm, (x_i.pos, x_i.rot, xd_i.vel, xd_i.ang))
    for _ in range(n_frames):
        xi, xdi = substep(sc, *_tuples(*arrays), tau)
        arrays = _stacked(xi, xdi, dtype)
    frames, jw = _frames(sc, *_tuples(*arrays))
    q, qd = joint_coordinates(sc, jw)
    out = tuple(_in_axes(np.argsort(sc.perm), (
        _array([f[0] for f in frames[name]], dtype), _array([f[1] for f in frames[name]], dtype)))
        for name in OUTPUTS)
    order = np.argsort([ln.dof + k for ln in sc.links for k in range(len(ln.motions) or 1)])
    q = jnp.stack([jnp.asarray(q[k], dtype) for k in order])
    qd = jnp.stack([jnp.asarray(qd[k], dtype) for k in order])
    return out, q, qd


def _in_axes(perm, arrays: tuple) -> tuple:
    """Arrays of vectors (last axis 3) and quaternions (4) with their entries in the axes
    `perm` (`Scene.perm`; the vector part of a quaternion turns as a vector): the arrays
    themselves for the world's own axes."""
    perm = tuple(int(k) for k in perm)
    if perm == (0, 1, 2):
        return arrays
    return tuple(a[..., list(perm)] if a.shape[-1] == 3 else a[..., [0, *(1 + k for k in perm)]]
                 for a in arrays)


def cotangent(ct_state):
    """The cotangent of `control_step`'s output, read off a brax positional State's."""
    pairs = []
    for name in OUTPUTS:
        f = getattr(ct_state, name)
        pairs.append((f.pos, f.rot) if hasattr(f, "pos") else (f.vel, f.ang))
    return tuple(pairs), ct_state.q, ct_state.qd


def planar_refusal(sys, drop_normal_gravity: bool = False) -> str | None:
    """Why `control_step` does not model brax's positional step of `sys` (None where it
    does): `planar_scene`'s reasons, or a substep that moves some frame out of the x-z plane
    (an entry `LIVE` leaves out that the traced substep does not keep 0.0: a constant
    transform that turns about another axis, a slide or a force out of the plane)."""
    sc = planar_scene(sys, drop_normal_gravity)
    if isinstance(sc, str):
        return sc
    return plane_leaks(sys, lambda *a: substep(sc, *a), lambda act: joint_torques(sc, act),
                       sc)


def plane_leaks(sys, step, torques, sc) -> str | None:
    """Why one traced substep `step(x_i, xd_i, tau)` (over the planar algebra, `torques(act)`
    its forces) leaves the x-z plane, or None: the entries `LIVE` leaves out of each of the
    frames `_frames` computes from its output that it does not keep the static 0.0 (a
    constant transform that turns about another axis, a slide or a force out of the plane).
    It traces one substep on tuples: control_step's arrays between substeps keep only the
    plane's entries, so a leak shows here, not there."""
    leaks = []

    def probe(pos, rot, vel, ang, act):
        frames, _ = _frames(sc, *step(*_tuples(pos, rot, vel, ang), torques(act)))
        for name, rows in frames.items():
            for k, (first, second) in enumerate(rows):
                kinds = ("vel", "ang") if name in ("xd", "xd_i", "jd") else ("pos", "rot")
                for kind, t in zip(kinds, (first, second)):
                    if any(not _is(a, 0.0) for i, a in enumerate(t) if i not in LIVE[kind]):
                        leaks.append(f"link {k}'s {name}.{kind}")
        return jnp.zeros(())

    num, f32 = sys.num_links(), jnp.float32
    jax.eval_shape(probe, *(jax.ShapeDtypeStruct((num, n), f32) for n in (3, 4, 3, 3)),
                   jax.ShapeDtypeStruct((sys.act_size(),), f32))
    if leaks:
        return ("a substep moves it out of the x-z plane (" + ", ".join(leaks[:4]) +
                (", ..." if len(leaks) > 4 else "") + ")")
    return None
