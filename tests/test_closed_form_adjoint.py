"""Acrobot's closed-form step and `closed_form_adjoint`: brax's values, brax's gradient, a
cheaper backward, and clear refusals where a scene has no closed form."""
import jax
import jax.experimental
import jax.numpy as jnp
import numpy as np
import pytest

from benchmarks.ild_speed import speed_setup, temp_bytes
from methods.ild.config import ILDConfig
from methods.ild.train import initial_state, make_update
from tasks import make_task
from tasks.core import open_loop
from tasks.physics import Plan, apply
from tasks.physics.transforms import with_closed_form_adjoint, with_substep_remat


def _states(n, key, q_max=7.0, qd_scale=4.0, a_max=1.5):
    """n random (q, qd, action): angles past +/-2 pi, fast spins, saturated actions."""
    kq, kqd, ka = jax.random.split(key, 3)
    return (jax.random.uniform(kq, (n, 2), minval=-q_max, maxval=q_max),
            qd_scale * jax.random.normal(kqd, (n, 2)),
            jax.random.uniform(ka, (n, 1), minval=-a_max, maxval=a_max))


# brax's actuator adds float64 forces into a float32 array under x64 (its own mix of types)
@pytest.mark.filterwarnings("ignore:scatter inputs have incompatible types:FutureWarning")
def test_acrobots_closed_form_step_is_braxs_step():
    """One control step (4 substeps) from 64 random states: q', qd' and the world-frame
    pose and motion of both links agree with brax's generalized pipeline to float32
    round-off, saturated actions included (both clip at the control range)."""
    env = make_task("acrobot").env.unwrapped
    q, qd, a = _states(64, jax.random.PRNGKey(0))

    def brax(q, qd, a):
        ps = env.pipeline_step(env.pipeline_init(q, qd), a)
        return ps.q, ps.qd, ps.x.pos, ps.x.rot, ps.xd.vel, ps.xd.ang

    want = jax.jit(jax.vmap(brax))(q, qd, a)
    got = jax.jit(jax.vmap(env.closed_form_step))(q, qd, a)
    for name, w, g in zip(("q", "qd", "pos", "rot", "vel", "ang"), want, got):
        np.testing.assert_allclose(g, w, rtol=1e-5, atol=2e-5, err_msg=name)
    assert float(jnp.max(jnp.abs(want[1] - qd))) > 0.1  # the step moved the velocities
    # a saturated action acts as the bound: the same step at 1.5 and at 1.0
    one = jax.vmap(env.closed_form_step)(q, qd, jnp.ones_like(a))
    more = jax.vmap(env.closed_form_step)(q, qd, 1.5 * jnp.ones_like(a))
    np.testing.assert_array_equal(one[1], more[1])
    # the same function, not a float32-sized approximation of it: in float64 the two agree
    # to ~1e-8 (measured: q 2e-10, qd 3e-8, world frames <= 2e-8; brax keeps some float32)
    with jax.experimental.enable_x64():
        q64, qd64, a64 = (jnp.asarray(x, jnp.float64) for x in (q, qd, a))
        want = jax.jit(jax.vmap(brax))(q64, qd64, a64)
        got = jax.jit(jax.vmap(env.closed_form_step))(q64, qd64, a64)
        assert got[1].dtype == want[1].dtype == jnp.float64
        for name, w, g in zip(("q", "qd", "pos", "rot", "vel", "ang"), want, got):
            np.testing.assert_allclose(g, w, rtol=1e-8, atol=1e-7, err_msg=name)


@pytest.mark.slow  # a rollout gradient compiled twice; the default run checks the step's
# VJP above and one ILD update through it below
def test_closed_form_adjoint_is_braxs_rollout_and_gradient():
    """30 open-loop steps of 4 envs, loss on the matched states (world-frame pose and motion)
    and observations: the same values bit for bit (brax still computes them) and the same
    gradient in the actions to float32 round-off, brax's reverse mode against the closed
    form's, with less of the backward's working memory."""
    task = make_task("acrobot")
    cf = with_closed_form_adjoint(task)
    assert "pipeline_step" not in vars(task.env.unwrapped)  # the cached env is untouched
    s0 = jax.vmap(task.env.reset)(jax.random.split(jax.random.PRNGKey(0), 4))
    acts = 0.8 * jax.random.normal(jax.random.PRNGKey(1), (30, 4, 1))  # some past +/-1

    def total(t):
        def f(a):
            _, (m, o) = open_loop(jax.vmap(t.env.step), s0, a,
                                  lambda s: (jax.vmap(t.matched_state)(s), s.obs))
            return jnp.sum(jnp.sin(0.3 * m)) + jnp.sum(o ** 2) * 1e-2
        return f

    grad = {n: jax.jit(jax.value_and_grad(total(t)))
            for n, t in (("brax", task), ("remat", with_substep_remat(task)), ("cf", cf))}
    (v0, g0), (v1, g1) = grad["brax"](acts), grad["cf"](acts)
    assert float(v0) == float(v1)
    np.testing.assert_allclose(g1, g0, rtol=2e-4, atol=2e-5)
    assert float(jnp.abs(g0).max()) > 1.0
    assert float(jnp.sum(g0[jnp.abs(acts) > 1.0] ** 2)) == 0.0  # clipped: no gradient
    mem = {n: temp_bytes(f.lower(acts).compile()) for n, f in grad.items()}
    assert mem["cf"] < mem["remat"] < mem["brax"]


def test_ild_update_through_the_closed_form_is_the_update_through_braxs_step():
    """One ILD update of B = 8 (truncation 10, per-step gradient normalization, clip, Adam)
    with `closed_form_adjoint` against the default (brax's reverse mode, substep remat): the
    same loss bit for bit and the same gradient norm and new parameters to round-off."""
    task = make_task("acrobot")
    base = ILDConfig(num_envs=8)
    policy, goals, norm, params, k = speed_setup(task, base)
    out = {}
    for cf in (False, True):
        phys = apply(task, Plan(closed_form_adjoint=cf))
        update, opt, _ = make_update(phys, policy, goals, norm, base, k[2])
        out[cf] = jax.jit(update)(initial_state(params, opt, k[3], base), None)
    (s0, m0), (s1, m1) = out[False], out[True]
    assert float(m0["train/loss"]) == float(m1["train/loss"])
    assert float(m1["grad/norm_raw"]) == pytest.approx(float(m0["grad/norm_raw"]), rel=1e-4)
    assert float(m0["grad/norm_raw"]) > 1e-3
    for a, b in zip(jax.tree.leaves(s0.params), jax.tree.leaves(s1.params)):
        np.testing.assert_allclose(b, a, rtol=1e-4, atol=1e-6)


def test_closed_form_adjoint_refuses_what_it_does_not_model():
    with pytest.raises(ValueError, match="hopper.*closed_form_adjoint"):
        with_closed_form_adjoint(make_task("hopper"))
    with pytest.raises(ValueError, match="closed_form_adjoint differentiates.*small_dots"):
        Plan(closed_form_adjoint=True, small_dots=True)
    with pytest.raises(ValueError, match="already has its own physics step"):
        with_closed_form_adjoint(with_substep_remat(make_task("acrobot")))
    # a scene the equations do not describe (a damped elbow) is refused, not mis-modelled
    damped = with_closed_form_adjoint.__globals__["build_env"](make_task("acrobot").spec)
    inner = damped.unwrapped
    inner.sys = inner.sys.replace(dof=inner.sys.dof.replace(
        damping=inner.sys.dof.damping.at[1].set(0.1)))
    with pytest.raises(ValueError, match="undamped.*closed_form_adjoint False"):
        inner.closed_form_step(jnp.zeros(2), jnp.zeros(2), jnp.zeros(1))
