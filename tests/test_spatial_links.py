"""`spatial_links`: brax's spring step of ant's and humanoid's scenes (a free root; hinges,
2- and 3-dof joints that only turn) with every entry of every vector an array over the
links (`tasks.physics.spatial_links`). Its constants, brax's joint forces, the same control step
and VJP as the step ILD trains with, the same rollout gradient, and the scenes and configs
it refuses."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tasks.physics.planar as planar
import tasks.physics.spatial_links as spatial_links
from tasks import make_task
from tasks.physics import Plan
from tasks.physics.transforms import spatial_adjoint_refusal, with_spatial_adjoint
from tests.test_planar_spring import _control_steps as control_steps
from tests.test_planar_spring import assert_same_rollout_gradient


def test_spatial_scene_reads_ant_over_its_links():
    """ant's nine links (torso; four hips, each with its ankle below): the parent matrix, the
    free root's joint constants all zero (brax's `_free` has no force) and its dofs unread,
    every hinge limited and held to its axis, masses and inverse inertias of one (ant's
    spring scales are 1, so brax divides by m ** 0 and turns I ** 0), the four feet spheres
    (no half-length, the Python 0.0) and the one entry of the flattened inverse inertias
    each foot's contact reads: link 0's (0, 2), (1, 1), (2, 0), (2, 2) for feet 2, 4, 6, 8
    (identity entries 0, 1, 0, 1)."""
    ls = spatial_links.spatial_scene(make_task("ant").env.unwrapped.sys)
    lk, cs, rj = ls.links, ls.contacts, ls.links.joints
    want = np.zeros((9, 9), np.float32)
    for child, parent in enumerate([-1, 0, 1, 0, 3, 0, 5, 0, 7]):
        if parent >= 0:
            want[parent, child] = 1
    np.testing.assert_array_equal(lk.parent, want)
    np.testing.assert_array_equal(lk.root, [1] + [0] * 8)
    assert lk.full and lk.unit_inertia and lk.mass == 1.0
    for field in (lk.stiffness, lk.vel_damping, lk.ang_damping, rj.limit_stiffness,
                  rj.align):
        assert field[0] == 0.0 and np.all(field[1:] > 0)
    assert rj.angles == 1 and not rj.two and rj.align2 == 0.0 and rj.parity == 1.0
    assert rj.rows == ((-1, *range(6, 14)),)
    frame = np.stack([np.stack([np.broadcast_to(a, 9) for a in row]) for row in rj.frame])
    np.testing.assert_allclose(frame[:, :, 0], np.eye(3))  # the root's: the identity's
    np.testing.assert_allclose(np.einsum("kil,mil->lkm", frame, frame),  # orthonormal
                               np.broadcast_to(np.eye(3), (9, 3, 3)), atol=1e-6)
    lo, hi = rj.lo[0], rj.hi[0]
    assert lo[0] == -np.inf and hi[0] == np.inf and np.all(lo[1:] < hi[1:])
    np.testing.assert_array_equal(cs.to_contacts.argmax(axis=0), [2, 4, 6, 8])
    assert cs.half == 0.0 and cs.inv_mass == 1.0
    assert cs.flat_entries == ((0, 2), (1, 1), (2, 0), (2, 2))
    assert ls.scene.gravity == (0.0, 0.0, planar._f32(-9.81))


def test_spatial_scene_reads_humanoid_over_its_links():
    """humanoid's eleven links: the free torso; the lower waist's 2-dof joint (dofs 6, 7)
    with the pelvis' hinge below it, two 3-dof hips (dofs 9-11, 13-15; brax's parity -1:
    their third axis is -(a0 x a1)) each with a knee hinge, two 2-dof shoulders (17-18,
    20-21) each with an elbow hinge. Every joint's angles limited (the knees to
    [-2.79, -0.035] rad); a hinge held to its axis by constraint_stiffness (27000), a 2-dof
    joint turned toward its plane by constraint_limit_stiffness (2500: brax's), a 3-dof
    joint by neither. Real masses (spring_mass_scale 0: the torso's 8.91), inverse
    inertias of one (spring_inertia_scale 1), the two feet spheres on the shins."""
    ls = spatial_links.spatial_scene(make_task("humanoid").env.unwrapped.sys)
    lk, cs, rj = ls.links, ls.contacts, ls.links.joints
    assert [int(p) for p in lk.parent.T @ np.arange(11) + (lk.root * -1)] == [
        -1, 0, 1, 2, 3, 2, 5, 0, 7, 0, 9]
    assert isinstance(rj, spatial_links.Rotary)  # no planar joint fields (PlanarJoints)
    assert lk.full and lk.unit_inertia and rj.angles == 3 and rj.two
    np.testing.assert_allclose(lk.mass[0], 8.907462, rtol=1e-6)
    hinges, twos, threes = [2, 4, 6, 8, 10], [1, 7, 9], [3, 5]
    np.testing.assert_array_equal(np.flatnonzero(rj.align), hinges)
    np.testing.assert_array_equal(rj.align[hinges], 27000.0)
    np.testing.assert_array_equal(np.flatnonzero(rj.align2), twos)
    np.testing.assert_array_equal(rj.align2[twos], 2500.0)
    np.testing.assert_array_equal(rj.parity, [1, 1, 1, -1, 1, -1, 1, 1, 1, 1, 1])
    assert rj.rows == ((-1, 6, 8, 9, 12, 13, 16, 17, 19, 20, 22),
                       (-1, 7, -1, 10, -1, 14, -1, 18, -1, 21, -1),
                       (-1, -1, -1, 11, -1, 15, -1, -1, -1, -1, -1))
    for k, links in enumerate((hinges + twos + threes, twos + threes, threes)):
        finite = np.isfinite(rj.lo[k]) & np.isfinite(rj.hi[k])
        np.testing.assert_array_equal(np.flatnonzero(finite), sorted(links))
    np.testing.assert_allclose(rj.lo[0][4], -2.7925267, rtol=1e-6)  # float32
    np.testing.assert_allclose(rj.hi[0][4], -0.03490658, rtol=1e-6)
    np.testing.assert_array_equal(cs.to_contacts.argmax(axis=0), [4, 6])
    assert cs.half == 0.0


def _control_steps(name: str = "ant", batch: int = 8):
    """`tests.test_planar_spring._control_steps` for `name` (ant, humanoid) and the form over
    the links: the step ILD trains with without spatial_links (hand_adjoint's spring
    substep, lean substeps) and `tasks.physics.spatial_links.control_step`."""
    def form(sys, n):
        ls = spatial_links.spatial_scene(sys)
        return lambda xi, xdi, a: spatial_links.control_step(ls, sys, xi, xdi, a, n)
    return control_steps(name, form, "spatial_links", batch)


def test_rotary_joint_forces_are_braxs_on_humanoid():
    """humanoid's joint forces at its links' centres of mass in world frame
    (`tasks.physics.planar_links._to_links` of `Rotary.force`) against brax's `joints.resolve`, in
    4 states whose joint angles are spread +-0.9 rad about the initial pose (many past their
    limits) and whose speeds are random: within 2e-5 of the largest entry (float32
    round-off), with the hinges', 2- and 3-dof joints' limit torques all in play."""
    from brax import actuator
    from brax.spring import joints, pipeline

    import tasks.physics.planar_links as pl
    sys = make_task("humanoid").env.unwrapped.sys
    ls = spatial_links.spatial_scene(sys)
    lk = ls.links
    k_q, k_qd, k_a = jax.random.split(jax.random.PRNGKey(0), 3)
    q = jnp.asarray(sys.init_q) + jnp.concatenate([
        jnp.zeros((4, 7)), jax.random.uniform(k_q, (4, sys.q_size() - 7), minval=-0.9,
                                              maxval=0.9)], axis=1)
    qd = jax.random.normal(k_qd, (4, sys.qd_size()))
    act = jax.random.uniform(k_a, (4, sys.act_size()), minval=-1.0, maxval=1.0)
    lo, hi = (np.asarray(b)[6:] for b in sys.dof.limit)
    past = (np.asarray(q)[:, 7:] < lo) | (np.asarray(q)[:, 7:] > hi)
    dof_link = np.asarray(sys.dof_link())[6:]
    assert {sys.link_types[i] for i in dof_link[past.any(axis=0)]} == {"1", "2", "3"}
    for b in range(4):
        state = pipeline.init(sys, q[b], qd[b])
        want = joints.resolve(sys, state, actuator.to_tau(sys, act[b], state.q, state.qd))
        read = lambda a, kind: pl._read(a, kind, True)  # noqa: E731
        x_i = (read(state.x_i.pos, "pos"), read(state.x_i.rot, "rot"))
        xd_i = (read(state.xd_i.vel, "vel"), read(state.xd_i.ang, "ang"))
        x, xd = pl._to_world(lk, x_i, xd_i)
        jw = pl._world_to_joint(lk, x, xd)
        tau = pl.joint_torques(ls.scene, act[b])
        ang, vel = pl._to_links(lk, *pl._joint_force(lk, tau, jw[0], jw[1]), jw, x_i)
        for w, g in ((want.ang, ang), (want.vel, vel)):
            got = pl._write(g, 11, jnp.float32)
            np.testing.assert_allclose(got, w, rtol=0, atol=2e-5 * float(jnp.abs(w).max()))


@pytest.mark.parametrize("name,vel_tol,q_tol", [
    ("ant", 3e-5, 5e-7), pytest.param("humanoid", 6e-5, 5e-6, marks=pytest.mark.slow)])
def test_spatial_control_step_is_the_trained_step(name, vel_tol, q_tol):
    """Every frame and joint coordinate of the step ILD trains with, to float32 round-off,
    feet on the floor: positions and rotations within 5e-7, velocities within `vel_tol`,
    joint angles within `q_tol` (measured: ant.5e-7, 1.0e-5 and 2.4e-7, joint
    velocities up to 1.5 rad/s; humanoid.8e-7, 2.4e-5 and 1.7e-6, up to 5.4
    rad/s)."""
    trained, ours, args, dist = _control_steps(name)
    assert int((dist < 0).sum()) >= (8 if name == "ant" else 4)  # contacts in play
    want, got = jax.jit(trained)(*args), jax.jit(ours)(*args)
    for out, w, g in zip(planar.OUTPUTS, want[0], got[0]):
        tol = vel_tol if out in ("xd", "xd_i", "jd") else 5e-7
        for wk, gk in zip(w, g):
            np.testing.assert_allclose(gk, wk, rtol=0, atol=tol, err_msg=out)
    np.testing.assert_allclose(got[1], want[1], rtol=0, atol=q_tol)
    np.testing.assert_allclose(got[2], want[2], rtol=0, atol=vel_tol)
    assert float(jnp.abs(got[2]).max()) > 0.5  # the envs move


def _tangent(rot, g):
    """`g` less its component along the unit quaternion `rot` (per link)."""
    return g - rot * jnp.sum(rot * g, axis=-1, keepdims=True)


# the trained step's reverse mode and the form's, compiled: ~1.5 minutes on one core (ant)
@pytest.mark.parametrize("name", ["ant", pytest.param("humanoid", marks=pytest.mark.slow)])
def test_spatial_control_step_vjp_is_the_trained_steps(name):
    """Feet on the floor: the VJP in the centre-of-mass frames and the action, for a sine
    cotangent of every output, within 1e-4 of each leaf's largest entry of the trained
    step's (hand_adjoint's VJPs), the input rotation's cotangent along the unit sphere (brax's
    inverse inertia R I R^T is |q|^4 I off it, which the form writes as I: the one direction
    they differ in, and one the previous step's normalization takes out of every gradient
    it passes back). Measured within 2.3e-6 (ant) and 1.9e-6 (humanoid)."""
    trained, ours, args, _ = _control_steps(name)
    _, want_pull = jax.vjp(trained, *args)
    got, got_pull = jax.vjp(ours, *args)
    ct = jax.tree.map(lambda v: jnp.sin(7.0 * jnp.arange(v.size, dtype=v.dtype)
                                        ).reshape(v.shape), got)
    (w_xi, w_xdi, w_a), (g_xi, g_xdi, g_a) = want_pull(ct), got_pull(ct)
    rot = args[0].rot
    for kind, w, g in (("pos", w_xi.pos, g_xi.pos),
                       ("rot", _tangent(rot, w_xi.rot), _tangent(rot, g_xi.rot)),
                       ("vel", w_xdi.vel, g_xdi.vel), ("ang", w_xdi.ang, g_xdi.ang),
                       ("act", w_a, g_a)):
        scale = float(jnp.abs(w).max())
        assert scale > 1e-2, kind
        np.testing.assert_allclose(g, w, rtol=0, atol=1e-4 * scale, err_msg=kind)


@pytest.mark.slow  # two rollout-gradient compiles: ~2-3 minutes on one core each task
@pytest.mark.parametrize("name,steps", [("ant", 16), ("humanoid", 4)])
def test_spatial_links_is_the_same_rollout_and_gradient(name, steps):
    """ILD's rollout loss and policy gradient over `steps` steps (B = 8, the task's config,
    spatial_links off and on): the same loss bit for bit (the task's own step computes the
    rollout) and every gradient leaf within 3e-5 of its largest entry. Measured: ant, 16 steps, 1.25e-5 (two of hidden_0's 512 bias entries over 1e-5);
    humanoid, 4 steps, 1.0e-5 (hand_adjoint on against off, two exact forms of
    brax's derivative: 2.7e-6). Over 16 steps humanoid's differ by 4.5e-4 (hand_adjoint on
    against off: 9.3e-5, the loss itself 2e-7 apart, each compiled its own way): both grow
    about 40x from 4 to 16 steps: round-off amplified by humanoid's stiff joints (27000),
    as it is between the two exact forms."""
    assert_same_rollout_gradient(name, {"spatial_links": False}, {"spatial_links": True},
                                 rel=3e-5, steps=steps)


@pytest.mark.parametrize("name", ["ant", "humanoid"])
def test_spatial_links_differentiates_ant_and_humanoid_through_the_links_form(name):
    """ant's and humanoid's CPU plans differentiate through `spatial_links`,
    and without it the plan's forward (hand_adjoint and its pieces) stays: the rollout
    physics differentiates through the form over the links (the step's forward is the
    task's own: brax's values)."""
    import dataclasses

    from tasks.physics import apply, plan_for
    on = plan_for(name, "cpu")
    off = dataclasses.replace(on, spatial_links=False)
    step = apply(make_task(name), on).env.unwrapped.pipeline_step
    assert "_step_with_adjoint" in step.__qualname__  # the task's step, the links' VJP
    step = apply(make_task(name), off).env.unwrapped.pipeline_step
    assert "_rebuilt_substep_loop" in step.__qualname__  # hand_adjoint's substeps


def test_spatial_links_is_refused_where_it_does_not_apply():
    """hopper (a planar root: a 3-dof root that slides, not a free one), humanoid with one
    shoulder axis turned into a slide, and inverted_pendulum (the positional backend) are
    refused by name, and the config refuses it beside another rewrite of the step's
    backward."""
    for name in ("ant", "humanoid"):
        assert spatial_adjoint_refusal(make_task(name)) is None
    for name, why in (("hopper", "a root that is not free"),
                      ("inverted_pendulum", "runs 'positional' physics")):
        with pytest.raises(ValueError, match=f"task {name!r}.*{why}.*leave it False"):
            with_spatial_adjoint(make_task(name))
    sys = make_task("humanoid").env.unwrapped.sys
    motion = sys.dof.motion.replace(vel=sys.dof.motion.vel.at[17].set(jnp.array([1.0, 0, 0])))
    assert spatial_links.spatial_scene(sys.replace(dof=sys.dof.replace(motion=motion))) == (
        "it has a joint that slides (hinges and 2- and 3-dof joints that only turn are what "
        "it models)")
    for other in ("planar_adjoint", "small_dots", "closed_form_adjoint"):
        with pytest.raises(ValueError, match=f"(?=.*spatial_links)(?=.*{other}).*False"):
            Plan(spatial_links=True, **{other: True})
    Plan(spatial_links=True, hand_adjoint=True, lean_substeps=True)
