"""`planar_links`: the planar spring step (`tasks.physics.planar_spring`) with every link at once
(`tasks.physics.planar_links`). Its constants over the links, the one-hot products that read across
links, and the same control step, VJP and rollout gradient as the per-link form and the
step ILD trains with."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tasks.physics.planar as planar
import tasks.physics.planar_links as planar_links
import tasks.physics.planar_spring as planar_spring
from tasks import make_task
from tasks.physics import Plan
from tasks.physics.transforms import with_planar_adjoint
from tests.test_planar import assert_same_step, assert_same_vjp
from tests.test_planar_spring import _control_steps, assert_same_rollout_gradient

F = planar._f32


def test_link_scene_reads_hopper_over_its_links():
    """hopper's four links (root, thigh, leg, foot) as entries over them: the parent matrix
    (link k's parent in column k; the root's column empty), the spring axis (the root's
    turning dof about +y, the hinges' a_0 about -y), the root's slides along x and z (zero
    for the hinges), the limits (none at the root: infinite bounds, zero stiffness). An
    entry that is the same on every link is one Python float, 0.0 where every link's is
    zero (so it folds). The foot's two contacts read entry (1, 0) of link 0's inverse
    inertia."""
    ls = planar_links.link_scene(planar_spring.spring_scene(
        make_task("hopper").env.unwrapped.sys))
    lk, cs, pj = ls.links, ls.contacts, ls.links.joints
    np.testing.assert_array_equal(lk.parent, [[0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1],
                                              [0, 0, 0, 0]])
    np.testing.assert_array_equal(lk.root, [1, 0, 0, 0])
    assert isinstance(pj, planar_links.PlanarJoints)
    assert pj.spring_axis[0] == 0.0 and pj.spring_axis[2] == 0.0
    np.testing.assert_array_equal(pj.spring_axis[1], [1, -1, -1, -1])
    assert pj.fixed_axis[0] == 0.0 and pj.fixed_axis[2] == 0.0
    np.testing.assert_array_equal(pj.fixed_axis[1], [0, -1, -1, -1])
    assert pj.turned_axis[:1] == (0.0,) and pj.turned_axis[2] == 0.0
    np.testing.assert_array_equal(pj.turned_axis[1], [1, 0, 0, 0])
    np.testing.assert_array_equal(pj.slide0[0], [1, 0, 0, 0])
    assert pj.slide0[1:] == (0.0, 0.0) and pj.slide1[:2] == (0.0, 0.0)
    assert pj.limited and pj.dof_turn == (2, 3, 4, 5)
    assert pj.dof_slides == ((0, 1), (-1, -1), (-1, -1), (-1, -1))
    np.testing.assert_array_equal(pj.lo, np.float32([-np.inf, -2.61799, -2.61799, -0.785398]))
    np.testing.assert_array_equal(pj.hi, np.float32([np.inf, 0.0, 0.0, 0.785398]))
    assert pj.limit_stiffness[0] == 0.0 and np.all(pj.limit_stiffness[1:] > 0)
    assert lk.transform[1] == (1.0, 0.0, 0.0, 0.0)  # every link's: the identity, folded
    np.testing.assert_array_equal(cs.to_contacts, [[0, 0], [0, 0], [0, 0], [1, 1]])
    assert cs.flat_entries == ((1, 0),) and cs.flat[:, 0].tolist() == [1, 0, 0, 0]
    assert cs.half[0] == F(0.195) and cs.half[1] == F(-0.195) and cs.friction == 2.0


def test_select_reads_across_links_by_one_product():
    """`_select` on hand-made entries: array entries are the matrix's columns' picks (a
    column with no row reads 0, one with two reads their sum), a constant entry stays the
    Python float where every column picks one row and becomes count x constant elsewhere,
    0.0 stays 0.0; all the array entries go through one product."""
    m = np.array([[0, 1, 1], [1, 0, 1], [0, 0, 0]], np.float32)  # col 0: row 1; col 2: rows 0, 1
    a = jnp.array([1.0, 2.0, 4.0])
    (v, w), = [planar_links._select([(a, 0.0, 3.0), (a * 10, 2.0, 0.0)], m)]
    np.testing.assert_array_equal(v[0], [2.0, 1.0, 3.0])
    assert v[1] == 0.0
    np.testing.assert_array_equal(v[2], [3.0, 3.0, 6.0])
    np.testing.assert_array_equal(w[0], [20.0, 10.0, 30.0])
    full = np.eye(3, dtype=np.float32)[:, [2, 0, 1]]
    (u,) = planar_links._select([(a, 5.0, 0.0)], full)
    np.testing.assert_array_equal(u[0], [4.0, 1.0, 2.0])
    assert u[1] == 5.0 and isinstance(u[1], float) and u[2] == 0.0
    ops = jax.make_jaxpr(lambda x: planar_links._select([(x, 1.0), (x, x)], m))(a)
    assert [e.primitive.name for e in ops.eqns].count("dot_general") == 1


def _link_steps(name: str):
    """(trained, per_link, links, args): `_control_steps`' pair and the link form."""
    trained, per_link, args, dist = _control_steps(name)
    env = make_task(name).env.unwrapped
    sys, n = env.sys, env._n_frames
    ls = planar_links.link_scene(planar_spring.spring_scene(sys))
    links = jax.vmap(lambda xi, xdi, a: planar_links.control_step(ls, sys, xi, xdi, a, n))
    return trained, per_link, links, args, dist


@pytest.mark.slow  # the default run checks the links' VJP against the per-link step's below
@pytest.mark.parametrize("name", ["hopper", "walker2d"])
def test_link_control_step_is_the_trained_step(name):
    """Every frame and joint coordinate of the step ILD trains with, to float32 round-off,
    with contacts active: positions within 5e-7 and velocities within 2e-5 (measured:
    hopper's and walker2d's within 1.2e-7 and 4.1e-6 of the per-link form's, whose own
    distance to the trained step test_planar_spring bounds the same way). Out-of-plane
    entries exactly zero."""
    trained, per_link, links, args, dist = _link_steps(name)
    assert int((dist < 0).sum()) >= 2  # contacts in play
    want, got, other = jax.jit(trained)(*args), jax.jit(links)(*args), jax.jit(per_link)(*args)
    assert_same_step(want, got, pos=5e-7, q=5e-7, moves=1.0)
    assert_same_step(other, got, pos=5e-7, q=5e-7, moves=1.0)


# the per-link step's VJP as the reference (itself tested against the trained step's in
# test_planar_spring): ~40 s on one core for hopper, ~2.5 minutes for walker2d
@pytest.mark.parametrize("name", ["hopper", pytest.param("walker2d", marks=pytest.mark.slow)])
def test_link_control_step_vjp_is_the_per_link_steps(name):
    """Contacts active: the VJP in the centre-of-mass frames and the action, for a sine
    cotangent of every output's in-plane entries, within 1e-4 of each leaf's largest entry
    of the per-link form's (finite where the root has no joint limit: its bounds are
    infinite and its limit force's zero stiffness meets a finite angle)."""
    _, per_link, links, args, _ = _link_steps(name)
    assert_same_vjp(per_link, links, args)


def test_planar_links_is_refused_where_it_does_not_apply():
    """The plan needs planar_adjoint; a positional task (inverted_pendulum) refuses it by
    name."""
    with pytest.raises(ValueError, match="planar_links writes planar_adjoint's spring step"):
        Plan(planar_links=True)
    Plan(planar_adjoint=True, planar_links=True)
    with pytest.raises(ValueError, match="'inverted_pendulum' runs 'positional' physics; "
                                         "planar_links writes brax's spring step"):
        with_planar_adjoint(make_task("inverted_pendulum"), links=True)


@pytest.mark.slow  # two rollout-gradient compiles: ~2 minutes on one core
def test_planar_links_is_the_same_rollout_and_gradient():
    """ILD's rollout loss and policy gradient over 16 steps on walker2d (B = 8, the task's
    config, planar_links off and on): the same loss bit for bit (the task's own step
    computes the rollout) and every gradient leaf within 1e-5 of its largest entry of the
    per-link form's."""
    assert_same_rollout_gradient("walker2d", {"planar_links": False}, {"planar_links": True})
