"""`planar_adjoint`: brax's positional control step written over the plane a scene moves in
(`tasks.physics.planar`), differentiated in place of brax's reverse mode. The same values and
derivative as brax's, step by step and through a rollout; clear refusals where a scene
leaves the plane."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax import com, kinematics
from brax.positional import pipeline

import tasks.physics.planar as planar
from benchmarks.ild_speed import speed_setup, task_config
from methods.ild.train import make_rollout_loss
from tasks import make_task
from tasks.physics import Plan
from tasks.core import Task
from tasks.physics.transforms import planar_adjoint_refusal, with_planar_adjoint
from tests.test_hand_adjoint import _states


def test_planar_algebra_folds_the_static_zero_and_keeps_braxs_expressions():
    """Products with the static 0.0 are 0.0 and sums with it the other term (decided
    without tracing), products with 1.0 the other factor; on arrays the tuple forms compute
    brax.math's rotate, quat_mul and vec_quat_mul, and `safe_normalize` brax's normalize
    (its safe_norm's zero branch included: an all-tiny vector has norm 0 and gradient 0)."""
    x = jnp.float32(2.5)
    assert planar.mul(0.0, x) == 0.0 and isinstance(planar.mul(x, 0.0), float)
    assert planar.add(0.0, x) is x and planar.sub(x, 0.0) is x and planar.mul(1.0, x) is x
    assert planar.cross((1.0, 0.0, 0.0), (0.0, 0.0, 1.0)) == (0.0, -1.0, 0.0)
    from brax import math
    k = jax.random.split(jax.random.PRNGKey(0), 3)
    v, q, u = (jax.random.normal(kk, (n,)) for kk, n in zip(k, (3, 4, 3)))
    np.testing.assert_allclose(jnp.stack(planar.rotate(tuple(v), tuple(q))),
                               math.rotate(v, q), rtol=1e-6)
    np.testing.assert_allclose(jnp.stack(planar.quat_mul(tuple(q), tuple(q[::-1]))),
                               math.quat_mul(q, q[::-1]), rtol=1e-6)
    np.testing.assert_allclose(jnp.stack(planar.vec_quat_mul(tuple(u), tuple(q))),
                               math.vec_quat_mul(u, q), rtol=1e-6)
    for w in (v, jnp.array([3e-9, 0.0, -5e-9])):
        n, norm = planar.safe_normalize(tuple(w))
        want_n, want_norm = math.normalize(w)
        np.testing.assert_allclose(jnp.stack(n), want_n, rtol=1e-6)
        np.testing.assert_allclose(norm, want_norm, rtol=1e-6)
    g = jax.grad(lambda w: planar.safe_normalize((w[0], 0.0, w[1]))[1])(
        jnp.array([3e-9, -5e-9]))
    np.testing.assert_array_equal(g, [0.0, 0.0])


def test_planar_scene_reads_inverted_pendulum():
    """inverted_pendulum's cart slides along x under the world, its pole hinges about y on
    the cart; gravity -9.81 along z, 0.005-s substeps, one motor of gear 100 on the slide;
    every link's inertia is the identity (spring_inertia_scale 1)."""
    sc = planar.planar_scene(make_task("inverted_pendulum").env.unwrapped.sys)
    cart, pole = sc.links
    assert (cart.parent, pole.parent) == (-1, 0)
    assert (cart.hinge, pole.hinge) == (False, True)
    assert cart.motion == (1.0, 0.0, 0.0) and pole.motion == (0.0, 1.0, 0.0)
    assert sc.gravity == (0.0, 0.0, planar._f32(-9.81)) and sc.dt == planar._f32(0.005)
    assert sc.actuators == ((0, 100.0, 1.0, -3.0, 3.0, -np.inf, np.inf),)
    assert cart.inertia_inv == pole.inertia_inv == (1.0, 1.0, 1.0)
    assert planar.planar_refusal(make_task("inverted_pendulum").env.unwrapped.sys) is None


def _consistent(sys, ps, x_i, xd_i):
    """`ps` with every frame and joint coordinate computed from `x_i`, `xd_i`, as brax's
    substep ends (the function of the centre-of-mass frames the closed form is)."""
    x, xd = com.to_world(sys, x_i, xd_i)
    j, jd, a_p, a_c = kinematics.world_to_joint(sys, x, xd)
    q, qd = kinematics.inverse(sys, j, jd)
    return ps.replace(x=x, xd=xd, x_i=x_i, xd_i=xd_i, j=j, jd=jd, a_p=a_p, a_c=a_c, q=q,
                      qd=qd)


def _control_steps(x_i=None):
    """(brax's, ours): one control step (4 substeps) of 8 inverted_pendulum envs 10 steps
    after reset, as functions of (x_i, xd_i, action) returning `control_step`'s outputs
    (brax's positional step with the state's other fields computed from x_i, xd_i), and
    their arguments there (`x_i`: those frames replaced)."""
    task, ps, act = _states("inverted_pendulum")
    env = task.env.unwrapped
    sys, sc, n = env.sys, planar.planar_scene(env.sys), env._n_frames
    ours = jax.vmap(lambda xi, xdi, a: planar.control_step(sc, xi, xdi, a, n))

    def brax_fn(xi, xdi, a):
        step = lambda p_, xi_, xdi_, a_: env.pipeline_step(  # noqa: E731
            _consistent(sys, p_, xi_, xdi_), a_)
        return planar.cotangent(jax.vmap(step)(ps, xi, xdi, a))

    return brax_fn, ours, (ps.x_i if x_i is None else x_i(ps.x_i), ps.xd_i, act)


def test_control_step_is_braxs_step():
    """Every frame and joint coordinate brax's positional step computes, to float32
    round-off: positions within 1e-7 and velocities, which divide a position change by the
    0.005-s substep, within 2e-5 (measured: 1.5e-8 and 3.3e-6). Out-of-plane entries are
    exactly zero here (brax's are round-off)."""
    brax_fn, ours, args = _control_steps()
    want, got = jax.jit(brax_fn)(*args), jax.jit(ours)(*args)
    assert_same_step(want, got, pos=1e-7, q=1e-6, moves=0.1)


def assert_same_step(want, got, pos: float, q: float, moves: float, vel: float = 2e-5):
    """`got`, a `control_step`'s output (frames in `planar.OUTPUTS` order, q, qd), equals
    `want` entry by entry: position and rotation frames within `pos`, velocity frames
    (a position change over a substep) within `vel`, q within `q` and qd within `vel`;
    `got`'s out-of-plane entries (x.pos's y) exactly zero, and some joint velocity over
    `moves` (the envs move)."""
    for name, w, g in zip(planar.OUTPUTS, want[0], got[0]):
        tol = vel if name in ("xd", "xd_i", "jd") else pos
        for wk, gk in zip(w, g):
            np.testing.assert_allclose(gk, wk, rtol=0, atol=tol, err_msg=name)
    np.testing.assert_allclose(got[1], want[1], rtol=0, atol=q)
    np.testing.assert_allclose(got[2], want[2], rtol=0, atol=vel)
    assert float(jnp.abs(got[0][0][0][..., 1]).max()) == 0.0  # x.pos's y: exactly zero
    assert float(jnp.abs(got[2]).max()) > moves


def _in_plane(kind, v, live=planar.LIVE):
    """`v` with the entries `live[kind]` leaves out set to zero."""
    mask = np.zeros(v.shape[-1], np.float32)
    mask[list(live[kind])] = 1.0
    return v * mask


@pytest.mark.slow  # brax's control-step VJP, op by op: ~1.5 minutes on one core
def test_control_step_vjp_is_braxs():
    """The VJP in the centre-of-mass frames and the action, for a sine cotangent of the
    in-plane entries of every output, against XLA's reverse mode of brax's step as a
    function of those frames, within 1e-4 of each leaf's largest entry, at the links turned
    about y by a few milliradians each: the cart's rotation off its slide is ~1e-9 in the
    rollout, where brax's safe_norm (zero when every entry is within 1e-8 of zero) makes
    the rotation correction's derivative 0 or of order 1 by round-off (one of 8 envs
    differed there, by 60% of the cart's rotation cotangent)."""
    half = 0.5 * jnp.array([2e-3, -1.5e-3])
    turn = jnp.stack([jnp.cos(half), 0 * half, jnp.sin(half), 0 * half], -1)
    from brax import math
    brax_fn, ours, args = _control_steps(lambda x_i: x_i.replace(
        rot=jax.vmap(jax.vmap(math.quat_mul), (None, 0))(turn, x_i.rot)))
    assert_same_vjp(brax_fn, ours, args)


def assert_same_vjp(want_fn, got_fn, args, in_plane=_in_plane):
    """`got_fn`'s VJP in (x_i, xd_i, action) equals `want_fn`'s within 1e-4 of each leaf's
    largest entry (in-plane entries), for a sine cotangent of the in-plane entries of every
    output of `got_fn` (a `control_step`); `in_plane(kind, v)` keeps a world-axes array's
    in-plane entries."""
    _, want_pull = jax.vjp(want_fn, *args)
    got, got_pull = jax.vjp(got_fn, *args)
    leaves = jax.tree.map(lambda v: jnp.sin(7.0 * jnp.arange(v.size, dtype=v.dtype)
                                            ).reshape(v.shape), got)
    ct = (tuple((in_plane(k0, a), in_plane(k1, b)) for name, (a, b) in zip(
        planar.OUTPUTS, leaves[0]) for k0, k1 in [
        ("vel", "ang") if name in ("xd", "xd_i", "jd") else ("pos", "rot")]),
        leaves[1], leaves[2])
    w_xi, w_xdi, w_a = want_pull(ct)
    g_xi, g_xdi, g_a = got_pull(ct)
    for kind, w, g in (("pos", w_xi.pos, g_xi.pos), ("rot", w_xi.rot, g_xi.rot),
                       ("vel", w_xdi.vel, g_xdi.vel), ("ang", w_xdi.ang, g_xdi.ang),
                       ("act", w_a, g_a)):
        w = w if kind == "act" else in_plane(kind, w)
        scale = float(jnp.abs(w).max())
        assert scale > 1e-2, kind
        np.testing.assert_allclose(g, w, rtol=0, atol=1e-4 * scale, err_msg=kind)


def _rollout_gradients(steps: int, a: dict, b: dict, name: str = "inverted_pendulum"):
    """ILD's rollout loss and policy gradient on task `name`, B = 8 over a `steps`-step
    episode, with the config it trains with (its TASK_OVERRIDES; inverted_pendulum's:
    truncation 128, positional_joints, lean substeps, planar_adjoint) updated by `a` and by
    `b`."""
    task = make_task(name)
    task = Task(spec=dataclasses.replace(task.spec, episode_length=steps), env=task.env)
    out = []
    assert task_config(name, 8, a) != task_config(name, 8, b)
    for over in (a, b):
        cfg = task_config(name, 8, over)
        policy, goals, norm, params, k = speed_setup(task, cfg)
        loss = make_rollout_loss(cfg.physics(task), policy, goals, norm, cfg.config)
        init_keys = jax.random.split(k[2], 8)
        out.append(jax.jit(jax.value_and_grad(lambda p: loss(p, k[3], init_keys)[0]))(params))
    return out


def _same_gradient(want, got, atol: float):
    flat = jax.tree_util.tree_flatten_with_path(want)[0]
    for (path, w), g in zip(flat, jax.tree_util.tree_leaves(got)):
        np.testing.assert_allclose(g, w, rtol=0, atol=atol * float(jnp.abs(w).max()),
                                   err_msg=jax.tree_util.keystr(path))
    assert float(jnp.abs(want["net"]["params"]["hidden_1"]["kernel"]).sum()) > 0


def test_planar_adjoint_is_the_same_rollout_and_gradient():
    """Over 16 steps: the same loss bit for bit (the task's own step computes the rollout)
    and every gradient leaf within 1e-5 of its largest entry (measured: 2.4e-6)."""
    (want_l, want), (got_l, got) = _rollout_gradients(16, {"planar_adjoint": False},
                                                      {"planar_adjoint": True})
    assert float(got_l) == float(want_l)
    _same_gradient(want, got, 1e-5)


@pytest.mark.slow  # two rollout gradients compiled: ~2 minutes; the default run checks the
# planar rollout gradient on inverted_pendulum above
def test_reacher_planar_adjoint_is_the_same_rollout_and_nearly_its_gradient():
    """reacher as it trains (planar_adjoint with planar_normal_gravity, truncation 10) against
    it without planar_adjoint (positional_joints' backward, gravity included), over 16 steps:
    the same loss bit for bit (brax's step computes the rollout either way) and every
    gradient leaf within 1e-4 of its largest entry (measured: 1.2e-5): the
    gravity along the hinges that the planar backward leaves out moves it less than that."""
    (want_l, want), (got_l, got) = _rollout_gradients(16, {"planar_adjoint": False}, {},
                                                      name="reacher")
    assert float(got_l) == float(want_l)
    _same_gradient(want, got, 1e-4)


@pytest.mark.slow  # two 128-step rollout-gradient compiles: ~1.5 minutes on one core
def test_planar_adjoint_is_the_same_full_bptt_gradient_where_nothing_clips():
    """Over the whole 128-step episode (inverted_pendulum trains with full BPTT), without
    the per-step gradient normalization: every leaf within 5e-4 of its largest entry
    (measured: 9.4e-5). With it the two differ (1.1e-2 measured): each step's cotangent
    norm is taken over the state's fields, which brax's reverse mode (and
    positional_joints' at 3x the difference, 5.5e-1) spreads over every frame and this
    one puts on the centre-of-mass frames, so a norm above 1 is clipped differently."""
    off = {"grad_normalization": False}
    (want_l, want), (got_l, got) = _rollout_gradients(
        128, {**off, "planar_adjoint": False}, {**off, "planar_adjoint": True})
    assert float(got_l) == float(want_l)
    _same_gradient(want, got, 5e-4)


def test_planar_adjoint_refuses_what_it_does_not_model():
    """Another backend (acrobot: generalized; pointmass; the spring scenes:
    tests/test_planar_spring.py), a positional scene with gravity along its hinges
    (reacher's, unless dropped by `planar_normal_gravity`), gravity out of the plane or a
    motor that pushes the cart along y (inverted_pendulum's constants changed): a
    ValueError naming the task, the reason and the field; with closed_form_adjoint or
    small_dots the config refuses the pair; beside lean_substeps and positional_joints (the
    forward it runs) it builds."""
    for name in ("acrobot", "pointmass"):
        with pytest.raises(ValueError, match=f"{name}.*planar_adjoint.*leave it False"):
            with_planar_adjoint(make_task(name))
    with pytest.raises(ValueError, match="'reacher': its gravity is not in the plane its "
                                         "hinges turn in"):
        with_planar_adjoint(make_task("reacher"))
    with pytest.raises(ValueError, match="'hopper' runs 'spring' physics; planar_normal_grav"):
        with_planar_adjoint(make_task("hopper"), drop_normal_gravity=True)
    with pytest.raises(ValueError, match="set planar_adjoint True or planar_normal_gravity"):
        Plan(planar_normal_gravity=True)
    task = make_task("inverted_pendulum")
    assert planar_adjoint_refusal(task) is None
    sys = task.env.unwrapped.sys
    assert planar.planar_scene(sys.replace(gravity=jnp.array([0.0, -9.81, 0.0]))) == (
        "its gravity is not in the plane its hinges turn in")
    assert planar.planar_scene(sys.replace(gravity=jnp.array([0.0, -9.81, 0.0])),
                               drop_normal_gravity=True).gravity == (0.0, 0.0, 0.0)
    motion = sys.dof.motion.replace(vel=sys.dof.motion.vel.at[0].set(jnp.array([0.0, 1, 0])))
    why = planar.planar_refusal(sys.replace(dof=sys.dof.replace(motion=motion)))
    assert why.startswith("a substep moves it out of the x-z plane (link 0's"), why
    for other in ("closed_form_adjoint", "small_dots"):
        with pytest.raises(ValueError, match=f"(?=.*planar_adjoint)(?=.*{other}).*False"):
            Plan(planar_adjoint=True, **{other: True})
    Plan(planar_adjoint=True, lean_substeps=True, positional_joints=True)


def test_link_frame_inertia_by_hand():
    """A turn of 90 degrees about y (float32 sqrt(1/2)) carries diag(1, 2, 3) to diag(3, 2,
    1); the off-axis round-off of the quaternion (~1e-7) becomes the static 0.0."""
    h = planar._f32(np.sqrt(0.5))
    rows = planar._link_frame_inertia((h, 0.0, h, 0.0), (1.0, 2.0, 3.0))
    np.testing.assert_allclose(np.array(rows), np.diag([3.0, 2.0, 1.0]), rtol=1e-6, atol=0)
    assert all(rows[i][j] == 0.0 and isinstance(rows[i][j], float)
               for i in range(3) for j in range(3) if i != j)


def test_planar_scene_reads_reacher_in_turned_axes():
    """reacher's hinges turn about z: the model's axes are (y, z, x) of the world's (its y
    the world's z), its gravity (along z) refused or dropped, its roots' height 0.01 above
    the world dropped, the target's two slides read as one link of two dofs (q entries 2
    and 3), and the capsules' inverse inertia as link-frame rows."""
    sys = make_task("reacher").env.unwrapped.sys
    assert planar.planar_scene(sys) == "its gravity is not in the plane its hinges turn in"
    sc = planar.planar_scene(sys, drop_normal_gravity=True)
    assert sc.perm == (1, 2, 0) and sc.gravity == (0.0, 0.0, 0.0)
    arm0, arm1, target = sc.links
    assert arm0.motion == arm1.motion == (0.0, 1.0, 0.0)   # the world's z
    assert arm0.transform[0] == (0.0, 0.0, 0.0)             # the world's (0, 0, 0.01)
    assert arm1.transform[0] == (0.0, 0.0, planar._f32(0.1))  # the world's (0.1, 0, 0)
    assert (target.dof, target.motions) == (2, ((0.0, 0.0, 1.0), (1.0, 0.0, 0.0)))
    assert arm0.inertia_rot == planar.IDENTITY and isinstance(arm0.inertia_inv[0], tuple)
    assert planar.planar_refusal(sys, drop_normal_gravity=True) is None


def _reacher_steps(gravity: bool):
    """(brax's, ours, args, state): one control step of 8 reacher envs 10 steps after reset as
    functions of (x_i, xd_i, action), brax's with the world's gravity or none; the frames
    put back on the plane (z = 0.01, turns about z) for the gravity-free comparison."""
    task = make_task("reacher")
    env = task.env.unwrapped
    s = jax.vmap(task.env.reset)(jax.random.split(jax.random.PRNGKey(0), 8))
    act = 0.5 * jnp.sin(jnp.arange(16, dtype=jnp.float32)).reshape(8, 2)
    step = jax.jit(jax.vmap(task.env.step))
    for _ in range(10):
        s = step(s, act)
    ps = s.pipeline_state
    sc, n = planar.planar_scene(env.sys, drop_normal_gravity=True), env._n_frames
    ours = jax.vmap(lambda xi, xdi, a: planar.control_step(sc, xi, xdi, a, n))
    sys = env.sys if gravity else env.sys.replace(gravity=jnp.zeros(3))

    def brax_fn(xi, xdi, a):
        def one(p_, xi_, xdi_, a_):
            p_ = _consistent(sys, p_, xi_, xdi_)
            for _ in range(n):
                p_ = pipeline.step(sys, p_, a_)
            return p_
        return planar.cotangent(jax.vmap(one)(ps, xi, xdi, a))

    x_i, xd_i = ps.x_i, ps.xd_i
    if not gravity:
        rot = x_i.rot * jnp.array([1.0, 0.0, 0.0, 1.0])
        x_i = x_i.replace(pos=x_i.pos.at[..., 2].set(0.01),
                          rot=rot / jnp.linalg.norm(rot, axis=-1, keepdims=True))
        xd_i = xd_i.replace(vel=xd_i.vel.at[..., 2].set(0.0),
                            ang=xd_i.ang * jnp.array([0.0, 0.0, 1.0]))
    return brax_fn, ours, (x_i, xd_i, act), ps


REACHER_LIVE = {"pos": [0, 1], "rot": [0, 3], "vel": [0, 1], "ang": [2]}
"""reacher's in-plane entries in the world's axes (the plane x-y, turns about z)."""


def _in_reacher_plane(kind, v):
    return _in_plane(kind, v, live=REACHER_LIVE)


@pytest.mark.slow  # brax's control step compiled: ~1 minute (the default run checks reacher's
# planar form through ILD's 16-step gradient, test_reacher_planar_adjoint_is_the_same_...)
def test_reacher_control_step_is_braxs_step_without_gravity():
    """From frames on the plane, every in-plane entry of every frame and the joint
    coordinates of brax's positional step of reacher without gravity, to float32 round-off
    (measured: positions 6e-8, velocities 9e-6, q 1.2e-7, qd 8.6e-6): the turned axes, the
    target's two slides and the link-frame inertia are brax's scene."""
    brax_fn, ours, args, _ = _reacher_steps(gravity=False)
    want, got = jax.jit(brax_fn)(*args), jax.jit(ours)(*args)
    for name, w, g in zip(planar.OUTPUTS, want[0], got[0]):
        kinds = ("vel", "ang") if name in ("xd", "xd_i", "jd") else ("pos", "rot")
        for kind, wk, gk in zip(kinds, w, g):
            tol = 2e-5 if kind in ("vel", "ang") else 2e-7
            np.testing.assert_allclose(_in_reacher_plane(kind, gk), _in_reacher_plane(
                kind, wk), rtol=0, atol=tol, err_msg=f"{name}.{kind}")
    np.testing.assert_allclose(got[1], want[1], rtol=0, atol=5e-7)
    np.testing.assert_allclose(got[2], want[2], rtol=0, atol=2e-5)
    assert float(jnp.abs(got[2][:, :2]).max()) > 0.1  # the arm moves


@pytest.mark.slow  # the trained step's VJP and the planar one compiled: ~3 minutes
def test_reacher_planar_vjp_is_the_trained_steps_with_gravity():
    """At reacher's rollout states (sagged ~2 mm under gravity along its hinges), the planar
    VJP without gravity against the trained step's with it, for a sine cotangent of the
    in-plane entries: within 1e-4 of each leaf's largest entry (measured 6.3e-5): the gravity
    planar_normal_gravity leaves out moves the gradient less than that."""
    _, ours, args, ps = _reacher_steps(gravity=True)
    task = make_task("reacher")
    env = task.env.unwrapped
    # reacher's step without planar_adjoint: positional_joints' backward, gravity in
    cfg = task_config("reacher", 8, {"planar_adjoint": "false"})
    assert not cfg.planar_normal_gravity and cfg.positional_joints
    trained_step = cfg.physics(task).env.unwrapped.pipeline_step

    def trained(xi, xdi, a):
        def one(p_, xi_, xdi_, a_):
            return trained_step(_consistent(env.sys, p_, xi_, xdi_), a_)
        return planar.cotangent(jax.vmap(one)(ps, xi, xdi, a))

    assert_same_vjp(trained, ours, args, in_plane=_in_reacher_plane)
