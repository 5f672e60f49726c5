"""`hand_adjoint`: brax's spring substep with the VJPs of six of its pieces (inverse inertia,
joint forces and contact impulses moved to the links, integration, conversions to link and
joint frames) written by hand (`tasks.physics.spring_adjoint`). The same values and the same VJPs
as XLA's reverse mode of brax's code, piece by piece and (slow) for a whole control step,
and clear refusals where it does not fit."""
import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax import com, kinematics
from brax.spring import collisions, integrator, joints

from tasks import make_task
from tasks.physics import Plan, apply, plan_for
from tasks.physics.transforms import hand_adjoint_refusal, with_hand_adjoint, with_lean_substeps
from tasks.physics.spring_adjoint import (collisions_resolve, integrate, inv_inertia,
                                          joints_resolve, only_hinges, planar_roots, rotary_joints,
                                          to_world, world_to_joint)
from tests.test_lean_substeps import _step_and_vjp


@functools.lru_cache  # once per task and process (its arrays are immutable: tests share them)
def _states(name, batch=8, steps=10):
    """`batch` envs of task `name` `steps` control steps after reset under a varying action,
    and that action."""
    task = make_task(name)
    env = task.env
    s = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(3), batch))
    act = 0.9 * jnp.sin(jnp.arange(batch * task.action_size, dtype=jnp.float32)
                        ).reshape(batch, task.action_size)
    step = jax.jit(jax.vmap(env.step))
    for _ in range(steps):
        s = step(s, act)
    return task, s.pipeline_state, act


def _same_values_and_vjp(want_fn, got_fn, *args):
    """`got_fn`'s values equal `want_fn`'s bit for bit and its VJP, for a sine cotangent,
    equals XLA's reverse mode of `want_fn` to float32 round-off (rtol 1e-5, atol 1e-6 of
    each leaf's largest entry); returns XLA's cotangent leaves (empty ones included)."""
    want, want_pull = jax.vjp(want_fn, *args)
    got, got_pull = jax.vjp(got_fn, *args)
    for w, g in zip(jax.tree.leaves(want), jax.tree.leaves(got), strict=True):
        np.testing.assert_array_equal(g, w)
    ct = jax.tree.map(lambda v: jnp.sin(7.0 * jnp.arange(v.size, dtype=v.dtype)
                                        ).reshape(v.shape), want)
    want_g, got_g = jax.tree.leaves(want_pull(ct)), jax.tree.leaves(got_pull(ct))
    assert len(want_g) == len(got_g)
    for w, g in zip(want_g, got_g):
        scale = float(jnp.max(jnp.abs(w))) if w.size else 0.0
        np.testing.assert_allclose(g, w, rtol=1e-5, atol=1e-6 * max(scale, 1.0))
    return want_g


def _reached(cotangents) -> int:
    """How many cotangent leaves are not all zero."""
    return sum(1 for w in cotangents if w.size and float(jnp.max(jnp.abs(w))) > 0)


def test_hand_integrate_is_braxs_integrate_and_its_vjp():
    """On 8 hopper states mid-hop, with a delta-velocity and a cotangent that reach every
    output: `integrate`'s values and its hand-written VJP equal brax's integrate and XLA's
    reverse mode of it to float32 round-off (a wrong sign in the quaternion terms moves the
    rotation's and angular velocity's cotangents by ~dt |w| |g|, far past the tolerance)."""
    task, ps, _ = _states("hopper")
    sys_ = task.env.unwrapped.sys
    args = (ps.x_i, ps.xd_i, jax.tree.map(lambda v: 0.3 * jnp.cos(3.0 * v), ps.xd_i))
    want_f = jax.vmap(lambda *a: integrator.integrate(sys_, *a))
    got_f = jax.vmap(lambda *a: integrate(sys_, *a))
    want, want_pull = jax.vjp(want_f, *args)
    got, got_pull = jax.vjp(got_f, *args)
    ct = jax.tree.map(lambda v: jnp.sin(7.0 * jnp.arange(v.size, dtype=v.dtype)
                                        ).reshape(v.shape), want)
    for w, g in zip(jax.tree.leaves(want), jax.tree.leaves(got)):
        np.testing.assert_allclose(g, w, rtol=1e-6, atol=1e-6)
    want_g, got_g = jax.tree.leaves(want_pull(ct)), jax.tree.leaves(got_pull(ct))
    assert len(want_g) == len(got_g) == 6  # pos, rot, vel, ang, dvel, dang
    for w, g in zip(want_g, got_g):
        assert float(jnp.max(jnp.abs(w))) > 1e-2
        np.testing.assert_allclose(g, w, rtol=1e-5, atol=1e-6)

    def through(fn):  # the same function of the system's timestep and dampings
        def loss(dt, vel_damping, ang_damping):
            s = sys_.tree_replace({"opt.timestep": dt, "vel_damping": vel_damping,
                                   "ang_damping": ang_damping})
            out = jax.vmap(lambda *a: fn(s, *a))(*args)
            return sum(jnp.sum(c * o) for c, o in zip(jax.tree.leaves(ct),
                                                       jax.tree.leaves(out)))
        return jax.grad(loss, argnums=(0, 1, 2))(
            sys_.opt.timestep, sys_.vel_damping, sys_.ang_damping)
    for w, g in zip(through(integrator.integrate), through(integrate)):
        assert abs(float(w)) > 1e-5  # dt-scaled for the dampings
        np.testing.assert_allclose(g, w, rtol=1e-4)


def test_hand_to_world_is_braxs_to_world_and_its_vjp():
    """`to_world` on 8 hopper states mid-hop: its values and hand-written VJP equal
    brax.com.to_world and XLA's reverse mode of it, in the link frames and motions and in the
    links' centre-of-mass offsets (a system field, through `tree_replace`)."""
    task, ps, _ = _states("hopper")
    sys_ = task.env.unwrapped.sys

    def through(fn):
        def f(ipos, x_i, xd_i):
            s = sys_.tree_replace({"link.inertia.transform.pos": ipos})
            return jax.vmap(lambda a, b: fn(s, a, b))(x_i, xd_i)
        return f
    args = (sys_.link.inertia.transform.pos, ps.x_i, ps.xd_i)
    want, want_pull = jax.vjp(through(com.to_world), *args)
    got, got_pull = jax.vjp(through(to_world), *args)
    ct = jax.tree.map(lambda v: jnp.sin(7.0 * jnp.arange(v.size, dtype=v.dtype)
                                        ).reshape(v.shape), want)
    for w, g in zip(jax.tree.leaves(want), jax.tree.leaves(got)):
        np.testing.assert_allclose(g, w, rtol=1e-6, atol=1e-6)
    want_g, got_g = jax.tree.leaves(want_pull(ct)), jax.tree.leaves(got_pull(ct))
    assert len(want_g) == len(got_g) == 5  # offsets, pos, rot, vel, ang
    for w, g in zip(want_g, got_g):
        assert float(jnp.max(jnp.abs(w))) > 1e-2
        np.testing.assert_allclose(g, w, rtol=1e-5, atol=1e-5)


def test_hand_inv_inertia_is_braxs_and_its_vjp():
    """`inv_inertia` on 8 hopper states mid-hop, with spring_inertia_scale 0.5 (the tasks
    run 1.0, where D is the identity): its values and hand-written VJP equal
    brax.com.inv_inertia and XLA's reverse mode of it, in the link rotations and in the
    system's principal inertias and inertia frames."""
    task, ps, _ = _states("hopper")
    sys_ = task.env.unwrapped.sys.tree_replace({"spring_inertia_scale": 0.5})

    def through(fn):
        def f(inertia, frame, x):
            s = sys_.tree_replace({"link.inertia.i": inertia,
                                   "link.inertia.transform.rot": frame})
            return jax.vmap(lambda a: fn(s, a))(x)
        return f
    args = (sys_.link.inertia.i, sys_.link.inertia.transform.rot, ps.x)
    want, want_pull = jax.vjp(through(com.inv_inertia), *args)
    got, got_pull = jax.vjp(through(inv_inertia), *args)
    assert float(jnp.max(jnp.abs(want - jnp.eye(3)))) > 0.1  # not the identity
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)
    ct = jnp.sin(7.0 * jnp.arange(want.size, dtype=want.dtype)).reshape(want.shape)
    want_g = [g for g in jax.tree.leaves(want_pull(ct)) if g.size]
    got_g = [g for g in jax.tree.leaves(got_pull(ct)) if g.size]
    assert len(want_g) == len(got_g) == 4  # inertia, frames, x.pos (zero), x.rot
    for w, g in zip(want_g, got_g):
        np.testing.assert_allclose(g, w, rtol=1e-4, atol=1e-4 * float(jnp.max(jnp.abs(w))))
    assert min(float(jnp.max(jnp.abs(w))) for i, w in enumerate(want_g) if i != 2) > 1e-2
    assert float(jnp.max(jnp.abs(want_g[2]))) == 0.0


@pytest.mark.parametrize("name", ["hopper", "ant"])
def test_hand_world_to_joint_is_braxs_and_its_vjp(name):
    """`world_to_joint` on 8 states mid-motion (hopper: a chain; ant: a torso with four
    two-link legs, so one parent gathers four children's cotangents): its values equal
    brax.kinematics.world_to_joint bit for bit, and its hand-written VJP equals XLA's reverse
    mode of brax's in the link frames and motions and in the system's link and joint frames
    (`link.transform`, `link.joint`, through `tree_replace`)."""
    task, ps, _ = _states(name)
    sys_ = task.env.unwrapped.sys
    fields = ("link.transform.pos", "link.transform.rot", "link.joint.pos", "link.joint.rot")

    def through(fn):
        def f(*a):
            s = sys_.tree_replace(dict(zip(fields, a[:4])))
            return jax.vmap(lambda x, xd: fn(s, x, xd))(*a[4:])
        return f
    args = (sys_.link.transform.pos, sys_.link.transform.rot, sys_.link.joint.pos,
            sys_.link.joint.rot, ps.x, ps.xd)
    want_g = _same_values_and_vjp(through(kinematics.world_to_joint), through(world_to_joint),
                                  *args)
    assert len(want_g) == 8  # four system fields, pos, rot, ang, vel
    assert min(float(jnp.max(jnp.abs(w))) for w in want_g) > 1.0


# humanoid's case (~70 s) is slow: humanoid trains with `rotary_joints`,
# whose test covers the same move to the links on its tree
@pytest.mark.parametrize("name", ["hopper", pytest.param("humanoid", marks=pytest.mark.slow)])
def test_hand_joints_resolve_is_braxs_and_its_vjp(name):
    """`joints_resolve` on 8 states mid-motion (hopper: hinges in a chain; humanoid: 1-, 2-
    and 3-dof joints in a tree) under joint forces tau, with the joint limits narrowed to
    0.2 rad about their middles so that joints are past them at both ends: its values equal
    brax.spring.joints.resolve bit for bit and its VJP (the per-type joint forces through
    XLA, their move to the links' centres of mass by hand) equals XLA's reverse mode of
    brax's in every state field it reads (joint frames and motions, a_p, a_c, x_i), tau and
    the system's joint springs, limits and axes (a limit's cotangent is non-zero only where
    a joint is past it: both ends are reached)."""
    task, ps, _ = _states(name)
    sys_ = task.env.unwrapped.sys
    tau = 50.0 * jnp.cos(jnp.arange(ps.qd.size, dtype=jnp.float32)).reshape(ps.qd.shape)
    fields = ("link.constraint_stiffness", "link.constraint_limit_stiffness", "dof.limit",
              "dof.motion.ang")
    lo, hi = sys_.dof.limit
    limited = jnp.isfinite(lo) & jnp.isfinite(hi)
    mid = jnp.where(limited, (lo + hi) / 2, 0.0)
    narrowed = (jnp.where(limited, mid - 0.1, lo), jnp.where(limited, mid + 0.1, hi))
    sys_args = (sys_.link.constraint_stiffness, sys_.link.constraint_limit_stiffness,
                narrowed, sys_.dof.motion.ang)

    def through(fn):
        def f(*a):
            s = sys_.tree_replace(dict(zip(fields, a[:4])))
            return jax.vmap(lambda p, t: fn(s, p, t))(*a[4:])
        return f
    want_g = _same_values_and_vjp(through(joints.resolve), through(joints_resolve), *sys_args,
                                  ps, tau)
    # five system fields (both limits); j, jd, a_p (pos, rot), a_c.pos, x_i.pos and tau
    assert _reached(want_g) == 14


def _narrowed_limits(sys_):
    """`sys_` with each finite joint limit narrowed to 0.2 rad about its middle (joints
    mid-motion are then past both ends), and the narrowed (lower, upper) limits."""
    lo, hi = sys_.dof.limit
    limited = np.isfinite(lo) & np.isfinite(hi)
    mid = np.where(limited, (lo + hi) / 2, 0.0)
    lo2, hi2 = np.where(limited, mid - 0.1, lo), np.where(limited, mid + 0.1, hi)
    return sys_.tree_replace({"dof.limit": (jnp.asarray(lo2, jnp.float32),
                                            jnp.asarray(hi2, jnp.float32))}), lo2, hi2


# what the scene-specific joint forces read (jd.vel only where the scene damps it), and
# what moves their forces to the links
SCENE_FORCES_READ = {"[0].j.pos", "[0].j.rot", "[0].jd.ang", "[1]", "[0].a_p.pos",
                     "[0].a_p.rot", "[0].a_c.pos", "[0].x_i.pos"}


def _scene_forces_are_braxs(sys_, ps, **pieces):
    """`joints_resolve(..., **pieces)` on states `ps` under joint forces tau: values equal
    brax's `joints.resolve` bit for bit and the VJP XLA's reverse mode of it; returns the
    names of the state and tau leaves its cotangent reaches."""
    tau = 50.0 * jnp.cos(jnp.arange(ps.qd.size, dtype=jnp.float32)).reshape(ps.qd.shape)

    def through(fn):
        return lambda p, t: jax.vmap(lambda p1, t1: fn(sys_, p1, t1))(p, t)
    want_g = _same_values_and_vjp(
        through(joints.resolve),
        through(lambda s1, p1, t1: joints_resolve(s1, p1, t1, **pieces)), ps, tau)
    names = [jax.tree_util.keystr(k) for k, _ in
             jax.tree_util.tree_leaves_with_path((ps, tau))]
    return {n for n, w in zip(names, want_g, strict=True)
            if w.size and float(jnp.max(jnp.abs(w))) > 0}


@pytest.mark.parametrize("name", [pytest.param("walker2d", marks=pytest.mark.slow), "ant"])
def test_hinges_forces_are_braxs_one_dof_forces_and_their_vjp(name):
    """On a scene whose 1-dof joints are all hinges (its system a constant, as ILD traces it),
    `joints_resolve(..., hinges=True)` computes them by `hinge` (brax's `_one_dof` without
    the terms a hinge multiplies by zero): values equal brax's `joints.resolve` bit for bit
    and the VJP XLA's reverse mode of it, in the joint frames and motions, a_p, a_c, x_i and
    tau, with the limits narrowed to 0.2 rad about their middles so that joints are past
    both ends."""
    task, ps, _ = _states(name)
    sys_, lo2, hi2 = _narrowed_limits(task.env.unwrapped.sys)
    assert only_hinges(sys_)
    q_at, qd_at = np.asarray(sys_.q_idx("1")), np.asarray(sys_.qd_idx("1"))  # 1-dof joints
    q = np.asarray(ps.q)[:, q_at]  # the hinges' angles
    assert np.all(np.isfinite(lo2[qd_at])) and np.any(q < lo2[qd_at]) and np.any(q > hi2[qd_at])
    assert SCENE_FORCES_READ <= _scene_forces_are_braxs(sys_, ps, hinges=True)


@pytest.mark.parametrize("name", ["hopper", "walker2d"])
def test_planar_root_forces_are_braxs_three_dof_forces_and_their_vjp(name):
    """On a scene whose 3-dof joints are planar roots (two unlimited slides and a hinge: the
    system a constant, as ILD traces it), `joints_resolve(..., planar=True)` computes their
    forces by `planar_root` (brax's `_three_dof` without what such a joint multiplies by
    zero): values equal brax's `joints.resolve` bit for bit and the VJP XLA's reverse mode
    of it, with the hinges' forces by `hinge` too and the states' root offset from its
    joint (the slides' pin and the hinge's alignment torque both pull)."""
    task, ps, _ = _states(name)
    sys_ = task.env.unwrapped.sys
    assert planar_roots(sys_) == ((0, 1), 2)
    ps = ps.replace(j=ps.j.replace(pos=ps.j.pos + 0.01 * jnp.cos(
        jnp.arange(ps.j.pos.size, dtype=jnp.float32)).reshape(ps.j.pos.shape)))
    assert SCENE_FORCES_READ <= _scene_forces_are_braxs(sys_, ps, hinges=True, planar=True)


@pytest.mark.slow  # humanoid's joint VJPs compiled: ~1.5 minutes; the default run checks
# the rotary forces' values (tests/test_spatial_links.py) and the hinges' VJP
def test_rotary_forces_are_braxs_two_and_three_dof_forces_and_their_vjp():
    """On humanoid, whose 2- and 3-dof joints only turn (its system a constant, as ILD traces
    it), `joints_resolve(..., hinges=True, rotary=True)` computes their forces by
    `rotary_two` and `rotary_three` (brax's `_two_dof` and `_three_dof` without what such
    joints multiply by zero): values equal brax's `joints.resolve` bit for bit and the VJP
    XLA's reverse mode of it, with the limits narrowed to 0.2 rad about their middles so
    that the 2- and 3-dof joints are past both ends."""
    task, ps, _ = _states("humanoid")
    sys_, lo2, hi2 = _narrowed_limits(task.env.unwrapped.sys)
    assert rotary_joints(sys_)
    multi = np.concatenate([np.asarray(sys_.q_idx(t)) for t in "23"])
    q = np.asarray(ps.q)[:, multi]  # the 2- and 3-dof joints' angles
    at = np.concatenate([np.asarray(sys_.qd_idx(t)) for t in "23"])
    assert np.any(q < lo2[at]) and np.any(q > hi2[at])
    assert SCENE_FORCES_READ <= _scene_forces_are_braxs(sys_, ps, hinges=True, rotary=True)


def test_planar_roots_reads_the_scene():
    """Planar roots: hopper's and walker2d's (rows 0 and 1 slide, row 2 turns); not ant's or
    humanoid's (free roots; humanoid's 3-dof joints turn about three axes), nor a hopper
    whose root is limited or whose axes are traced; and `joints_resolve` refuses such a
    scene by name."""
    for name in ("hopper", "walker2d"):
        assert planar_roots(make_task(name).env.unwrapped.sys) == ((0, 1), 2), name
    for name in ("ant", "humanoid"):
        assert planar_roots(make_task(name).env.unwrapped.sys) is None, name
    sys_ = make_task("hopper").env.unwrapped.sys
    lo, hi = (np.array(x) for x in sys_.dof.limit)
    lo[2] = -1.0
    limited = sys_.tree_replace({"dof.limit": (jnp.asarray(lo), jnp.asarray(hi))})
    assert planar_roots(limited) is None
    seen = []
    jax.jit(lambda ang: seen.append(planar_roots(sys_.tree_replace({"dof.motion.ang": ang})))
            )(sys_.dof.motion.ang)
    assert seen == [None]
    task, ps, _ = _states("ant")  # any ant state (the cached one other tests use)
    with pytest.raises(ValueError, match="3-dof joints are not all planar roots"):
        joints_resolve(task.env.unwrapped.sys, jax.tree.map(lambda v: v[0], ps),
                       jnp.zeros(ps.qd.shape[1:]), planar=True)
    # rotary joints: humanoid's only (hopper's root slides; ant has no 2- or 3-dof joint)
    assert rotary_joints(make_task("humanoid").env.unwrapped.sys)
    assert not rotary_joints(sys_) and not rotary_joints(task.env.unwrapped.sys)
    with pytest.raises(ValueError, match="2- and 3-dof joints do not all only turn"):
        joints_resolve(task.env.unwrapped.sys, jax.tree.map(lambda v: v[0], ps),
                       jnp.zeros(ps.qd.shape[1:]), rotary=True)


def test_only_hinges_reads_the_scene():
    """Hinges only: the four spring tasks (humanoid's 2- and 3-dof joints are other types);
    not a scene with a slide (inverted_pendulum's cart) nor one whose axes are traced."""
    for name in ("hopper", "walker2d", "ant", "humanoid"):
        assert only_hinges(make_task(name).env.unwrapped.sys), name
    pendulum = make_task("inverted_pendulum").env.unwrapped.sys
    assert not only_hinges(pendulum)
    sys_ = make_task("hopper").env.unwrapped.sys
    seen = []
    jax.jit(lambda ang: seen.append(only_hinges(sys_.tree_replace({"dof.motion.ang": ang})))
            )(sys_.dof.motion.ang)
    assert seen == [False]


@pytest.mark.parametrize("name", [pytest.param("hopper", marks=pytest.mark.slow), "ant"])
def test_hand_collisions_resolve_is_braxs_and_its_vjp(name):
    """`collisions_resolve` on 8 states mid-motion pushed 0.1 down into the floor and moving
    down at 1 m/s (so every env has contacts whose impulses apply), with masses and inverse
    inertias that differ between links and axes (and are not symmetric): its values equal
    brax.spring.collisions.resolve bit for bit and its VJP (brax's impulses through XLA,
    their move to the links' centres of mass, averaging and conversion to delta-velocities by
    hand) equals XLA's reverse mode of brax's in every state field it reads (x, x_i, xd_i,
    the inverse inertias and masses)."""
    task, ps, _ = _states(name)
    sys_ = task.env.unwrapped.sys
    down = jnp.array([0.0, 0.0, 0.1])
    n_links = ps.mass.shape[-1]  # the spring tasks' masses are 1 and inverse inertias I:
    scale = jnp.linspace(0.5, 2.0, n_links)  # make them tell the links apart
    skew = 0.2 * jnp.roll(jnp.eye(3), 1, axis=1)  # not symmetric: a transpose shows
    ps = ps.replace(mass=ps.mass * scale,
                    i_inv=(ps.i_inv * jnp.array([0.5, 1.0, 2.0]) + skew) / scale[:, None, None],
                    x=ps.x.replace(pos=ps.x.pos - down),
                    x_i=ps.x_i.replace(pos=ps.x_i.pos - down),
                    xd_i=ps.xd_i.replace(vel=ps.xd_i.vel - 10.0 * down
                                         + 0.5 * jnp.sin(ps.xd_i.vel)))

    def through(fn):
        return jax.vmap(lambda p: fn(sys_, p))
    assert bool(jnp.all(jnp.any(through(collisions.resolve)(ps).vel != 0.0, axis=(1, 2))))
    want_g = _same_values_and_vjp(through(collisions.resolve), through(collisions_resolve), ps)
    assert _reached(want_g) == 7  # x (pos, rot), x_i.pos, xd_i (ang, vel), i_inv, mass


def test_ild_trains_through_the_hand_written_step_where_asked():
    """A plan with `hand_adjoint` runs six custom VJPs (inverse inertia's, joint
    forces to links', contact impulses to links', integration's, to-world's,
    world-to-joint's) in every substep of hopper's control step, lean or not; without it,
    none (traced, not compiled)."""
    task, ps, act = _states("hopper")  # any state: traced, not run
    ps1, a1 = jax.tree.map(lambda v: v[0], ps), act[0]

    def custom_vjps(plan):
        step = apply(task, plan).env.unwrapped.pipeline_step
        return str(jax.make_jaxpr(step)(ps1, a1)).count("custom_vjp_call")
    n_frames = task.env.unwrapped._n_frames
    assert n_frames > 1
    assert custom_vjps(Plan(lean_substeps=True)) == 0
    # six per substep body: the scan's and the last substep's (lean)
    assert custom_vjps(Plan(lean_substeps=True, hand_adjoint=True)) == 12
    assert custom_vjps(Plan(substep_remat=False, hand_adjoint=True)) == 6


@pytest.mark.slow  # two compilations of a control step's VJP: ~1 minute each
@pytest.mark.parametrize("hinges,planar", [(False, False), (True, False), (True, True)])
def test_hand_adjoint_step_is_braxs_step_and_gradient(hinges, planar):
    """One control step (4 substeps) of 8 hopper envs mid-hop through the copy ILD would
    train on with `hand_adjoint` (lean substeps, each checkpointed), with and without
    `hinge_forces` and `planar_root`: the end state and the gradient of a
    function of it in the incoming state and the actions agree with the lean copy through
    XLA's reverse mode to float32 round-off."""
    task, ps, act = _states("hopper")
    want, want_grad = _step_and_vjp(
        with_lean_substeps(task).env.unwrapped.pipeline_step, ps, act)
    got, grad = _step_and_vjp(
        apply(task, Plan(lean_substeps=True, hand_adjoint=True, hinge_forces=hinges,
                         planar_root=planar)).env.unwrapped.pipeline_step,
        ps, act)
    scale = max(float(jnp.max(jnp.abs(g))) for g in want_grad)
    assert scale > 1e-2
    for w, g in zip(want, got):
        np.testing.assert_allclose(g, w, rtol=1e-5, atol=1e-5)
    for w, g in zip(want_grad, grad):
        np.testing.assert_allclose(g, w, rtol=0, atol=1e-5 * scale)


def test_hand_adjoint_refuses_what_it_does_not_model():
    """Not brax's spring backend (reacher: positional; acrobot: generalized; pointmass):
    a ValueError naming the task and the field; with the closed-form adjoint: the plan
    refuses the pair."""
    for name in ("reacher", "acrobot", "pointmass"):
        task = make_task(name)
        assert "hand_adjoint" in hand_adjoint_refusal(task)
        with pytest.raises(ValueError, match=f"{name}.*leave it False"):
            with_hand_adjoint(task)
    assert hand_adjoint_refusal(make_task("hopper")) is None
    with pytest.raises(ValueError, match="closed_form_adjoint differentiates.*hand_adjoint"):
        Plan(closed_form_adjoint=True, hand_adjoint=True)


def test_hinge_forces_refuses_what_it_does_not_model(monkeypatch):
    """`hinge_forces` without `hand_adjoint`: the plan refuses it; on a scene with a
    sliding 1-dof joint (none of the spring tasks has one: `only_hinges` stands in):
    `with_hand_adjoint` names the task and the field."""
    with pytest.raises(ValueError, match="hinge_forces is a piece of hand_adjoint"):
        Plan(hinge_forces=True)
    assert Plan(hand_adjoint=True, hinge_forces=True).hinge_forces
    monkeypatch.setattr("tasks.physics.spring_adjoint.only_hinges", lambda sys: False)
    with pytest.raises(ValueError, match="'hopper' has 1-dof joints that slide.*hinge_forces"):
        with_hand_adjoint(make_task("hopper"), hinges=True)


def test_planar_root_and_rotary_joints_refuse_what_they_do_not_model():
    """`planar_root` or `rotary_joints` without `hand_adjoint`: the plan refuses it,
    naming the field; on a scene without planar roots (ant) or without joints
    that only turn (hopper, ant), `with_hand_adjoint` names the task and the field."""
    for field in ("planar_root", "rotary_joints"):
        with pytest.raises(ValueError, match=f"{field} is a piece of hand_adjoint"):
            Plan(**{field: True})
        assert getattr(Plan(hand_adjoint=True, **{field: True}), field)
    with pytest.raises(ValueError, match="'ant' has no planar root.*planar_root"):
        with_hand_adjoint(make_task("ant"), planar=True)
    for name in ("hopper", "ant"):
        with pytest.raises(ValueError, match=f"'{name}' has no 2- or 3-dof.*rotary_joints"):
            with_hand_adjoint(make_task(name), rotary=True)


def _saved(fn, *args) -> list[str]:
    """The descriptions of what reverse mode of `fn` saves (`print_saved_residuals`)."""
    import contextlib
    import io
    from jax.ad_checkpoint import print_saved_residuals
    with contextlib.redirect_stdout(io.StringIO()) as out:
        print_saved_residuals(fn, *args)
    return out.getvalue().splitlines()


def test_saved_residuals_saves_what_world_to_joint_and_inv_inertia_name():
    """`saved_residuals`: ant's checkpointed substep, as `with_hand_adjoint`
    wraps it, saves for its backward its inputs only; with the policy
    `save_only_these_names(*SAVED_RESIDUALS)` it saves, beside them, exactly the ten arrays
    world_to_joint's forward names (five per-link rotations: the link's, its parent's and
    the three frames composed from them; five 3-vectors: offsets and motions) and the two
    inv_inertia's does (the rotation and its product with the inertia frames'), every one
    state-dependent, none of the system's constants. Tracing only."""
    from tasks.physics.spring_adjoint import SAVED_RESIDUALS, step
    task, ps, act = _states("ant", batch=1, steps=1)
    sys_ = task.env.unwrapped.sys
    ps1, act1 = jax.tree.map(lambda a: a[0], ps), act[0]

    def substep(x, x_i, xd_i, act):
        out = step(sys_, ps1.replace(x=x, x_i=x_i, xd_i=xd_i), act, hinges=True)
        return jnp.sum(out.x.pos) + jnp.sum(out.j.rot) + jnp.sum(out.jd.ang)
    args = (ps1.x, ps1.x_i, ps1.xd_i, act1)
    policy = jax.checkpoint_policies.save_only_these_names(*SAVED_RESIDUALS)
    plain = [s for s in _saved(jax.checkpoint(substep), *args) if "from a constant" not in s]
    saved = [s for s in _saved(jax.checkpoint(substep, policy=policy), *args)
             if "from a constant" not in s]
    assert plain and all("from the argument" in s for s in plain)
    named = {name: [s.split()[0] for s in saved if f"named '{name}'" in s]
             for name in SAVED_RESIDUALS}
    assert sorted(named[SAVED_RESIDUALS[0]]) == ["f32[9,3]"] * 5 + ["f32[9,4]"] * 5
    assert named[SAVED_RESIDUALS[1]] == ["f32[9,4]"] * 2
    assert sorted(plain) == sorted(s for s in saved if "named '" not in s)


def test_saved_residuals_is_a_piece_of_hand_adjoint():
    with pytest.raises(ValueError, match="saved_residuals is a piece of hand_adjoint"):
        Plan(saved_residuals=True)


@pytest.mark.slow  # two compilations of ant's control-step VJP: about 2 minutes on one core
def test_saved_residuals_is_the_same_step_and_gradient_to_round_off():
    """One control step of ant (10 substeps, 8 envs, 10 steps after reset) through the step
    ILD trains with, with and without `saved_residuals`: the end state and the gradient of
    a function of it in the incoming state and the actions agree to float32 round-off
    (saving a residual rather than computing it again is the same function; XLA fuses the
    two programs differently)."""
    task, ps, act = _states("ant")
    got = []
    for on in (False, True):
        plan = dataclasses.replace(plan_for("ant", "cpu"), saved_residuals=on)
        assert plan.hand_adjoint and plan.substep_remat
        got.append(_step_and_vjp(apply(task, plan).env.unwrapped.pipeline_step, ps, act))
    (want_v, want_g), (got_v, got_g) = got
    for w, g in zip(want_v + tuple(want_g), got_v + tuple(got_g), strict=True):
        scale = float(jnp.max(jnp.abs(w)))
        np.testing.assert_allclose(g, w, rtol=1e-5, atol=1e-5 * max(scale, 1.0))
