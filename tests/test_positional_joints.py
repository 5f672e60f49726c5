"""`positional_joints`: brax's positional substep with the joints' position-level update
written for hinges and slides (`tasks.physics.positional_joints`), the joints' forces vectorized
and the frame conversions, inverse inertia and integration by `tasks.physics.spring_adjoint`'s
hand-written VJPs. The same values and gradient as brax's, piece by piece and for a control
step and a rollout; clear refusals where it does not fit."""
import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax import kinematics
from brax.positional import joints as brax_joints

from methods.ild.train import make_rollout_loss
from tasks import make_task
from tasks.physics import Plan, apply
from tasks.core import Task
from tasks.physics.transforms import (positional_joints_refusal, with_lean_substeps,
                                      with_positional_joints)
from tasks.physics.positional_joints import joint_rows, joint_update
from tests.test_hand_adjoint import _states


def test_joint_rows_reads_the_scene():
    """reacher: two hinges about z (the first unlimited, the second within +-3 rad) and the
    target's two slides along x and y (+-0.27); inverted_pendulum: the cart's slide along x
    (+-1) and the pole's hinge about y (+-pi/2). A slide's angular axes are all locked, a
    hinge's second and third; the coordinates a slide frees are left out of the pull back."""
    r = joint_rows(make_task("reacher").env.unwrapped.sys)
    np.testing.assert_array_equal(r.lo0, [-np.inf, -3.0, 0.0])
    np.testing.assert_array_equal(r.hi0, [np.inf, 3.0, 0.0])
    np.testing.assert_array_equal(r.axes[0, 0], [0, 0, 1])
    np.testing.assert_array_equal(r.slides[2], [[1, 0, 0], [0, 1, 0], [0, 0, 0]])
    np.testing.assert_allclose(r.slide_hi[2, :2], [0.27, 0.27])
    np.testing.assert_array_equal(r.keep, [[1, 1, 1], [1, 1, 1], [0, 0, 1]])
    p = joint_rows(make_task("inverted_pendulum").env.unwrapped.sys)
    np.testing.assert_allclose(p.lo0, [0.0, -np.pi / 2])
    np.testing.assert_array_equal(p.axes[1, 0], [0, 1, 0])
    np.testing.assert_array_equal(p.keep, [[0, 1, 1], [1, 1, 1]])
    np.testing.assert_allclose(p.slide_lo[0, 0], -1.0)
    assert "turns and slides" in joint_rows(make_task("hopper").env.unwrapped.sys)


def _joint_frames(name, turn: float):
    """The joint transforms of 8 envs of task `name` 10 steps after reset, each link's
    rotation turned by `turn` radians about a fixed oblique axis (0: as they are)."""
    task, ps, _ = _states(name)
    sys = task.env.unwrapped.sys
    j = jax.vmap(lambda s: kinematics.world_to_joint(sys, s.x, s.xd)[0])(ps)
    axis = jnp.array([0.6, -0.48, 0.64])
    dq = jnp.concatenate([jnp.cos(turn / 2) * jnp.ones(1), jnp.sin(turn / 2) * axis])
    from brax import math
    rot = jax.vmap(jax.vmap(lambda q: math.quat_mul(dq, q)))(j.rot)
    return sys, j.replace(rot=rot)


@pytest.mark.parametrize("name", [pytest.param("reacher", marks=pytest.mark.slow),
                                  "inverted_pendulum"])
def test_joint_update_is_braxs_and_its_vjp(name):
    """`joint_update` against brax's `_three_dof_joint_update` on its `_sphericalize`d joint
    data (what `position_update` computes per link): the same displacements to float32
    round-off at the rollout's joint frames, and, at those frames turned off their axes by
    0.05 rad (so no locked angle is exactly zero), the same VJP for a sine cotangent. At an
    exactly zero locked angle brax's reverse mode picks up jnp.clip's tie rule (the clip of
    an angle to [0, 0] is a constant, yet maximum and minimum at a tie pass half the
    cotangent each), which these scenes' out-of-plane rotations meet every step; the
    rollout's policy gradient is unaffected (test below)."""
    sys, j0 = _joint_frames(name, 0.0)
    rows = joint_rows(sys)

    def brax_fn(j):
        return jax.vmap(lambda jj: jax.vmap(brax_joints._three_dof_joint_update)(
            jj, *brax_joints._sphericalize(sys, jj)))(j)

    def ours(j):
        return jax.vmap(lambda jj: joint_update(jj, rows))(j)

    for w, g in zip(jax.tree.leaves(jax.jit(brax_fn)(j0)), jax.tree.leaves(jax.jit(ours)(j0))):
        np.testing.assert_allclose(g, w, rtol=1e-5, atol=1e-6)
    _, j = _joint_frames(name, 0.05)
    want, want_pull = jax.vjp(brax_fn, j)
    got, got_pull = jax.vjp(ours, j)
    for w, g in zip(jax.tree.leaves(want), jax.tree.leaves(got)):
        np.testing.assert_allclose(g, w, rtol=1e-5, atol=1e-6)
    assert float(jnp.abs(want.rot).max()) > 1e-2  # the turn is pulled back
    ct = jax.tree.map(lambda v: jnp.sin(7.0 * jnp.arange(v.size, dtype=v.dtype)
                                        ).reshape(v.shape), want)
    for w, g in zip(jax.tree.leaves(want_pull(ct)), jax.tree.leaves(got_pull(ct))):
        scale = float(jnp.abs(w).max())
        assert scale > 0
        np.testing.assert_allclose(g, w, rtol=0, atol=1e-5 * scale)


@pytest.mark.slow  # two compilations of a control step's VJP per task: ~2 minutes each
@pytest.mark.parametrize("name", ["reacher", "inverted_pendulum"])
def test_positional_step_is_braxs_step_and_action_gradient(name):
    """One control step (4 substeps, lean, each checkpointed) of 8 envs 10 steps after
    reset, through the copy ILD trains on with `positional_joints` against the lean copy
    through brax's own substep: the end state to float32 round-off, and the gradient of a
    smooth function of it in the actions (within 1e-4 of its largest entry: reacher's differ
    by 1.2e-5 of it, float32 round-off through four substeps' corrections)."""
    task, ps, act = _states(name)

    def end_and_grad(step):
        def loss(a):
            out = jax.vmap(step)(ps, a)
            return (jnp.sum(jnp.sin(out.q)) + 0.1 * jnp.sum(jnp.tanh(out.qd))
                    + jnp.sum(jnp.cos(out.x.pos)) + 0.1 * jnp.sum(jnp.tanh(out.xd.ang))), out
        (_, out), g = jax.jit(jax.value_and_grad(loss, has_aux=True))(act)
        return (out.q, out.qd, out.x.pos, out.x.rot, out.xd.vel, out.xd.ang), g

    want, want_g = end_and_grad(with_lean_substeps(task).env.unwrapped.pipeline_step)
    plan = Plan(lean_substeps=True, positional_joints=True)
    got, g = end_and_grad(apply(task, plan).env.unwrapped.pipeline_step)
    for w, o in zip(want, got):
        np.testing.assert_allclose(o, w, rtol=1e-5, atol=1e-5)
    scale = float(jnp.abs(want_g).max())
    assert scale > 1e-3
    np.testing.assert_allclose(g, want_g, rtol=0, atol=1e-4 * scale)


@pytest.mark.slow  # two rollout-gradient compiles per task: ~2 minutes each on one core
@pytest.mark.parametrize("name", ["reacher", "inverted_pendulum"])
def test_positional_joints_is_the_same_rollout_gradient(name):
    """ILD's rollout loss and policy gradient, B = 8 over a 16-step episode with the config
    the task trains with (its TASK_OVERRIDES) but `planar_adjoint` (whose backward would
    stand in for both), with and without `positional_joints`: the loss to rtol 1e-5 and
    every gradient leaf within 1e-4 of its largest entry."""
    from benchmarks.ild_speed import speed_setup, task_config
    task = make_task(name)
    task = Task(spec=dataclasses.replace(task.spec, episode_length=16), env=task.env)
    out = {}
    for on in (False, True):
        cfg = task_config(name, 8, {"positional_joints": on, "planar_adjoint": False})
        assert not cfg.planar_adjoint and cfg.positional_joints is on
        policy, goals, norm, params, k = speed_setup(task, cfg)
        loss = make_rollout_loss(cfg.physics(task), policy, goals, norm, cfg.config)
        init_keys = jax.random.split(k[2], 8)
        out[on] = jax.jit(jax.value_and_grad(lambda p: loss(p, k[3], init_keys)[0]))(params)
    np.testing.assert_allclose(float(out[True][0]), float(out[False][0]), rtol=1e-5)
    flat = jax.tree_util.tree_flatten_with_path(out[False][1])[0]
    for (path, a), b in zip(flat, jax.tree_util.tree_leaves(out[True][1])):
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-4 * float(jnp.abs(a).max()),
                                   err_msg=jax.tree_util.keystr(path))
    assert float(jnp.abs(out[False][1]["net"]["params"]["hidden_1"]["kernel"]).sum()) > 0


def test_positional_joints_refuses_what_it_does_not_model(monkeypatch):
    """Another backend (hopper: spring; acrobot: generalized; pointmass): a ValueError naming
    the task and the field; a positional scene with another joint kind (`joint_rows`
    stands in): the same, with the reason; with hand_adjoint or closed_form_adjoint: the
    config refuses the pair."""
    for name in ("hopper", "acrobot", "pointmass"):
        with pytest.raises(ValueError, match=f"{name}.*positional_joints.*leave it False"):
            with_positional_joints(make_task(name))
    assert positional_joints_refusal(make_task("reacher")) is None
    monkeypatch.setattr("tasks.physics.positional_joints.joint_rows",
                        lambda sys: "it has a free joint")
    with pytest.raises(ValueError, match="'reacher': it has a free joint; positional_joints"):
        with_positional_joints(make_task("reacher"))
    for other in ("hand_adjoint", "closed_form_adjoint"):
        with pytest.raises(ValueError, match="set positional_joints False"):
            Plan(positional_joints=True, **{other: True})
