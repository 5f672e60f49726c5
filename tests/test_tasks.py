"""Task dynamics: hand-computed values, gradients, and the acrobot rebuild."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tasks import TASKS, make_task
from tasks.core import Canonical, brax_matched_state, open_loop, strong


def test_pointmass_dynamics_by_hand():
    env = make_task("pointmass").env.unwrapped
    s = env.reset(jax.random.PRNGKey(0))
    s = s.replace(pipeline_state=jnp.array([1.0, 0.0]), obs=jnp.array([1.0, 0.0]))
    # dt 0.05, m 1, f = 2 * a: v1 = 0 + 0.05 * 2 * 0.5 = 0.05, x1 = 1 + 0.05 * 0 = 1
    s1 = env.step(s, jnp.array([0.5]))
    np.testing.assert_allclose(s1.obs, [1.0, 0.05], atol=1e-7)
    np.testing.assert_allclose(s1.reward, -1.0, atol=1e-7)
    # x2 = 1 + 0.05 * 0.05 = 1.0025, v2 = 0.05 + 0.05 * 2 * (-1) = -0.05 (action clipped)
    s2 = env.step(s1, jnp.array([-3.0]))
    np.testing.assert_allclose(s2.obs, [1.0025, -0.05], atol=1e-7)
    np.testing.assert_allclose(s2.reward, -1.0025, atol=1e-7)


def test_open_loop_is_the_step_by_step_loop():
    env = make_task("pointmass").env.unwrapped
    s = env.reset(jax.random.PRNGKey(0))
    s = s.replace(pipeline_state=jnp.array([1.0, 0.0]), obs=jnp.array([1.0, 0.0]))
    final, (obs, rew) = open_loop(env.step, s, jnp.array([[0.5], [-3.0]]),
                                  lambda s: (s.obs, s.reward))
    # the two hand-computed steps of test_pointmass_dynamics_by_hand, stacked
    np.testing.assert_allclose(obs, [[1.0, 0.05], [1.0025, -0.05]], atol=1e-7)
    np.testing.assert_allclose(rew, [-1.0, -1.0025], atol=1e-7)
    np.testing.assert_allclose(final.obs, obs[-1])
    acts = jax.random.uniform(jax.random.PRNGKey(3), (25, 1), minval=-1, maxval=1)
    final, none = open_loop(env.step, s, acts)
    assert none is None
    for a in acts:
        s = env.step(s, a)
    np.testing.assert_allclose(final.obs, s.obs, rtol=1e-6, atol=1e-7)


def test_pointmass_gradient_matches_finite_differences():
    env = make_task("pointmass").env
    s0 = env.reset(jax.random.PRNGKey(1))

    def final_x(actions):
        s, _ = jax.lax.scan(lambda s, a: (env.step(s, a), None), s0, actions)
        return s.obs[0]

    a = 0.3 * jnp.ones((10, 1))
    g = jax.grad(final_x)(a)
    # x_10 depends on a_t through v: dx_10/da_t = dt * dt * 2 * (10 - 1 - t)
    expected = 0.05 * 0.05 * 2.0 * (9 - np.arange(10))
    np.testing.assert_allclose(np.asarray(g)[:, 0], expected, rtol=1e-5, atol=1e-8)


def test_acrobot_starts_hanging_and_rewards_by_the_formula():
    task = make_task("acrobot")
    s = task.env.reset(jax.random.PRNGKey(0))
    theta = np.asarray(s.obs[:2])
    assert abs(abs(theta[0]) - np.pi) < 0.011 and abs(theta[1]) < 0.011
    s1 = jax.jit(task.env.step)(s, jnp.zeros(1))
    o = np.asarray(s1.obs)
    expected = 10 - (o[0] ** 2 + o[1] ** 2) - 1e-3 * (o[2] ** 2 + o[3] ** 2)
    np.testing.assert_allclose(s1.reward, expected, rtol=1e-5)
    assert abs(float(s1.reward) - (10 - np.pi ** 2)) < 0.1  # hanging earns ~0.13


def _acrobot_energy(q, qd):
    """Mechanical energy of brax v1's acrobot by hand (shared/reference/acrobot_facts.md):
    two links of mass 2.5 whose inertia about the centre of mass is v1's default 1 (a body
    with no inertia given got (1, 1, 1)), centres 0.451 from their hinges, hinges 0.902
    apart; angles from upright, the potential measured from the shoulder."""
    m, inertia, lc, length, g = 2.5, 1.0, 0.451, 0.902, 9.81
    (t1, t2), (w1, w2) = q, qd
    kinetic = (0.5 * inertia * w1 ** 2 + 0.5 * m * (lc * w1) ** 2
               + 0.5 * inertia * (w1 + w2) ** 2
               + 0.5 * m * (length ** 2 * w1 ** 2 + lc ** 2 * (w1 + w2) ** 2
                            + 2 * length * lc * w1 * (w1 + w2) * np.cos(t2)))
    potential = m * g * (lc * np.cos(t1) + length * np.cos(t1) + lc * np.cos(t1 + t2))
    return kinetic + potential


def test_acrobot_conserves_the_hand_computed_energy_without_torque():
    """No contacts, no damping: 128 unactuated steps from a tilted pose keep the energy that
    v1's masses and inertias give (within 1% of the energy above hanging: the integrator's
    drift), which also pins the inertia (the capsules' own, ~0.17, conserves a different sum);
    and the elbow motor moves the second link."""
    task = make_task("acrobot")
    env = task.env
    s = env.reset(jax.random.PRNGKey(0))
    ps = env.unwrapped.pipeline_init(jnp.array([np.pi - 1.0, 0.5]), jnp.zeros(2))
    s = s.replace(pipeline_state=ps, obs=env.unwrapped._get_obs(ps))
    step = jax.jit(env.step)
    e0 = _acrobot_energy(np.asarray(ps.q), np.asarray(ps.qd))
    above = e0 - _acrobot_energy(np.array([np.pi, 0.0]), np.zeros(2))
    drift = []
    for _ in range(128):
        s = step(s, jnp.zeros(1))
        drift.append(_acrobot_energy(np.asarray(s.pipeline_state.q),
                                     np.asarray(s.pipeline_state.qd)) - e0)
    assert np.isfinite(drift).all()
    assert np.max(np.abs(drift)) < 0.01 * above, (np.max(np.abs(drift)), above)
    s_t = step(s, jnp.ones(1))
    assert float(s_t.obs[3]) != pytest.approx(float(step(s, -jnp.ones(1)).obs[3]))


def test_matched_state_layout_is_13_per_body():
    task = make_task("inverted_pendulum")
    s = task.env.reset(jax.random.PRNGKey(0))
    nb = s.pipeline_state.x.pos.shape[0]
    m = task.matched_state(s)
    assert m.shape == (13 * nb,)
    np.testing.assert_array_equal(m[: 3 * nb], np.asarray(s.pipeline_state.x.pos).ravel())
    np.testing.assert_array_equal(m, brax_matched_state(s.pipeline_state))


def _grad_through(task_name, horizon):
    task = make_task(task_name)
    env = task.env
    s0 = env.reset(jax.random.PRNGKey(0))

    def loss(actions):
        def body(s, a):
            s = env.step(s, a)
            return s, task.matched_state(s)
        _, states = jax.lax.scan(body, s0, actions)
        return jnp.mean(states ** 2)

    a = 0.1 * jnp.ones((horizon, task.action_size))
    return jax.jit(jax.value_and_grad(loss))(a)


@pytest.mark.slow  # a 16-step unrolled gradient; the default run differentiates brax tasks
# in the physics and guarantee tests (tests/test_planar.py, tests/test_guarantees.py)
def test_a_brax_task_differentiates():
    v, g = _grad_through("inverted_pendulum", 16)
    assert np.isfinite(v) and np.isfinite(np.asarray(g)).all()
    assert np.abs(np.asarray(g)).sum() > 0


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(set(TASKS) - {"pointmass"}))
def test_every_task_steps_and_differentiates(name):
    v, g = _grad_through(name, 16)
    assert np.isfinite(v) and np.isfinite(np.asarray(g)).all()
    assert np.abs(np.asarray(g)).sum() > 0


def test_strong_removes_weak_types_and_keeps_values():
    tree = {"a": jnp.asarray(1.5), "b": jnp.arange(3, dtype=jnp.int32), "c": 2.0}
    out = strong(tree)
    assert tree["a"].weak_type and not out["a"].weak_type and not out["c"].weak_type
    assert [x.dtype for x in jax.tree.leaves(out)] == [jnp.float32, jnp.int32, jnp.float32]
    np.testing.assert_array_equal(out["b"], tree["b"])
    assert float(out["a"]) == 1.5 and float(out["c"]) == 2.0


def test_canonical_states_keep_one_type_from_reset_on(weak_metric, avals):
    """brax's hopper writes a Python float to metrics['reward_healthy'] on every step, so
    its stepped state is weakly typed where reset's is not; a jitted step carrying it
    compiles twice. Every task's env is Canonical: reset and step agree."""
    from tasks.pointmass import PointMass

    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    for env, weak in ((weak_metric(PointMass()), True),
                      (Canonical(weak_metric(PointMass())), False)):
        s0 = jax.vmap(env.reset)(keys)
        s1 = jax.vmap(env.step)(s0, jnp.zeros((2, 1)))
        assert (avals(s1) != avals(s0)) == weak
        assert float(s1.metrics["healthy"][0]) == 1.0
