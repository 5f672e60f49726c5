"""`hand_adjoint`: brax's spring substep with the VJPs of three of its pieces (inverse inertia,
integration, conversion to link frames) written by hand (`tasks.spring_adjoint`). The same
values and the same VJPs as XLA's reverse mode of brax's code, piece by piece and (slow) for
a whole control step, and clear refusals where it does not fit."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from brax import com
from brax.spring import integrator

from methods.ild.config import ILDConfig
from methods.ild.train import rollout_physics
from tasks import make_task
from tasks.core import hand_adjoint_refusal, with_hand_adjoint, with_lean_substeps
from tasks.spring_adjoint import integrate, inv_inertia, to_world
from tests.test_lean_substeps import _step_and_vjp


def _hopper_states(batch=8, steps=10):
    """`batch` hopper envs `steps` control steps after reset under a varying action (the
    foot on the ground), and that action."""
    task = make_task("hopper")
    env = task.env
    s = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(3), batch))
    act = 0.9 * jnp.sin(jnp.arange(batch * task.action_size, dtype=jnp.float32)
                        ).reshape(batch, task.action_size)
    step = jax.jit(jax.vmap(env.step))
    for _ in range(steps):
        s = step(s, act)
    return task, s.pipeline_state, act


def test_hand_integrate_is_braxs_integrate_and_its_vjp():
    """On 8 hopper states mid-hop, with a delta-velocity and a cotangent that reach every
    output: `integrate`'s values and its hand-written VJP equal brax's integrate and XLA's
    reverse mode of it to float32 round-off (a wrong sign in the quaternion terms moves the
    rotation's and angular velocity's cotangents by ~dt |w| |g|, far past the tolerance)."""
    task, ps, _ = _hopper_states()
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
    task, ps, _ = _hopper_states()
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
    task, ps, _ = _hopper_states()
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


def test_ild_trains_through_the_hand_written_step_where_asked():
    """rollout_physics with `hand_adjoint` runs three custom VJPs (inverse inertia's,
    integration's, to-world's) in every substep of hopper's control step, lean or not;
    without it, none (traced, not compiled)."""
    task, ps, act = _hopper_states(batch=1, steps=0)
    ps1, a1 = jax.tree.map(lambda v: v[0], ps), act[0]

    def custom_vjps(cfg):
        step = rollout_physics(task, cfg).env.unwrapped.pipeline_step
        return str(jax.make_jaxpr(step)(ps1, a1)).count("custom_vjp_call")
    n_frames = task.env.unwrapped._n_frames
    assert n_frames > 1
    assert custom_vjps(ILDConfig(lean_substeps=True)) == 0
    # three per substep body: the scan's and the last substep's (lean)
    assert custom_vjps(ILDConfig(lean_substeps=True, hand_adjoint=True)) == 6
    assert custom_vjps(ILDConfig(substep_remat=False, hand_adjoint=True)) == 3


@pytest.mark.slow  # two compilations of a control step's VJP: ~2 minutes
def test_hand_adjoint_step_is_braxs_step_and_gradient():
    """One control step (4 substeps) of 8 hopper envs mid-hop through the copy ILD would
    train on with `hand_adjoint` (lean substeps, each checkpointed): the end state and the
    gradient of a function of it in the incoming state and the actions agree with the lean
    copy through XLA's reverse mode to float32 round-off."""
    task, ps, act = _hopper_states()
    want, want_grad = _step_and_vjp(
        with_lean_substeps(task).env.unwrapped.pipeline_step, ps, act)
    got, grad = _step_and_vjp(
        rollout_physics(task, ILDConfig(lean_substeps=True, hand_adjoint=True)
                        ).env.unwrapped.pipeline_step, ps, act)
    scale = max(float(jnp.max(jnp.abs(g))) for g in want_grad)
    assert scale > 1e-2
    for w, g in zip(want, got):
        np.testing.assert_allclose(g, w, rtol=1e-5, atol=1e-5)
    for w, g in zip(want_grad, grad):
        np.testing.assert_allclose(g, w, rtol=0, atol=1e-5 * scale)


def test_hand_adjoint_refuses_what_it_does_not_model():
    """Not brax's spring backend (reacher: positional; acrobot: generalized; pointmass):
    a ValueError naming the task and the field; with the closed-form adjoint: the config
    refuses the pair."""
    for name in ("reacher", "acrobot", "pointmass"):
        task = make_task(name)
        assert "hand_adjoint" in hand_adjoint_refusal(task)
        with pytest.raises(ValueError, match=f"{name}.*leave it False"):
            with_hand_adjoint(task)
    assert hand_adjoint_refusal(make_task("hopper")) is None
    with pytest.raises(ValueError, match="closed_form_adjoint and hand_adjoint"):
        ILDConfig(closed_form_adjoint=True, hand_adjoint=True)
