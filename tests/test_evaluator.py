"""The shared evaluator: hand-computed returns, partial returns, host == jax paths."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bench.api import InformationError, Policy
from bench.evaluator import EvalConfig, Evaluator, eval_key, random_policy
from tasks import make_task


def _const(value):
    def act(params, obs, key, deterministic):
        return jnp.full((1,), value)
    return act


ZERO = _const(0.0)
PUSH = _const(1.0)


def test_pointmass_return_matches_a_hand_loop():
    task = make_task("pointmass")
    n = 4
    res = Evaluator(task, EvalConfig(num_episodes=n)).evaluate(Policy(ZERO, ()), seed=3)
    # Same reset keys as the evaluator: split(eval_key), then the first half of each split.
    keys = jax.random.split(eval_key(3), n)
    for i in range(n):
        s0 = task.env.reset(jax.random.split(keys[i])[0])
        x, v = float(s0.obs[0]), float(s0.obs[1])
        ret = 0.0
        for _ in range(128):  # zero force: x_{t+1} = x_t + 0.05 v_t, v constant
            x = x + 0.05 * v
            ret += -abs(x)
        assert res.returns[i] == pytest.approx(ret, rel=1e-4)
    assert (res.lengths == 128).all()


def test_early_termination_keeps_the_partial_return():
    task = make_task("inverted_pendulum")  # reward 1 per step until the pole passes 0.2 rad
    res = Evaluator(task, EvalConfig(num_episodes=8)).evaluate(Policy(PUSH, ()), seed=0)
    assert (res.lengths < 128).all() and (res.lengths > 0).all()
    np.testing.assert_array_equal(res.returns, res.lengths)


def test_normalized_score_uses_the_references():
    task = make_task("pointmass")
    ev = Evaluator(task, EvalConfig(num_episodes=4), expert_return=-20.0, random_return=-100.0)
    res = ev.evaluate(Policy(ZERO, ()), seed=0)
    np.testing.assert_allclose(res.normalized, (res.returns + 100.0) / 80.0)
    assert Evaluator(task).evaluate(Policy(ZERO, ()), 0).normalized is None


def test_host_policy_scores_like_the_same_jax_policy():
    task = make_task("pointmass")
    ev = Evaluator(task, EvalConfig(num_episodes=6))

    def jax_pd(params, obs, key, deterministic):
        return jnp.clip(-params * obs[..., :1] - obs[..., 1:], -1, 1)

    def host_pd(params, obs, rng, deterministic):
        assert isinstance(obs, np.ndarray) and obs.shape == (6, 2)
        return np.clip(-params * obs[:, :1] - obs[:, 1:], -1, 1)

    a = ev.evaluate(Policy(jax_pd, 2.0), seed=1)
    b = ev.evaluate(Policy(host_pd, 2.0, kind="host"), seed=1)
    np.testing.assert_allclose(a.returns, b.returns, rtol=1e-5)


def test_same_seed_same_episodes_other_seed_other_episodes():
    task = make_task("pointmass")
    ev = Evaluator(task, EvalConfig(num_episodes=4, deterministic=False))
    pol = random_policy(1)
    a, b, c = (ev.evaluate(pol, s).returns for s in (0, 0, 1))
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)


def test_state_policies_need_the_declaration():
    task = make_task("pointmass")

    def planner(params, state, key, deterministic):
        return -jnp.clip(state.pipeline_state[:1], -1, 1)

    pol = Policy(planner, (), kind="jax_state")
    with pytest.raises(InformationError, match="sim_at_test"):
        Evaluator(task).evaluate(pol, 0)
    assert Evaluator(task, allow_sim_at_test=True).evaluate(pol, 0).finite
