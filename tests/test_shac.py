"""SHAC: TD-lambda targets, gradients at the extremes, learning signal on pointmass."""
import importlib
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bench.budget import Budget
from bench.evaluator import EvalConfig
from bench.runner import RunRequest, execute, prepare
from methods.shac.config import SHACConfig
from tasks import make_task

importlib.import_module("methods.shac")
shac = sys.modules["methods.shac.train"]


def _lambda_returns_loop(r, v, d, gamma, lam):
    """The textbook recursion, one env at a time:
    G_t = r_t + gamma * V_{t+1}                              where the segment ends at t
    G_t = r_t + gamma * ((1 - lam) V_{t+1} + lam G_{t+1})    otherwise."""
    H, N = r.shape
    G = np.zeros((H, N))
    for n in range(N):
        nxt = None
        for t in reversed(range(H)):
            if d[t, n] or nxt is None:
                G[t, n] = r[t, n] + gamma * v[t, n]
            else:
                G[t, n] = r[t, n] + gamma * ((1 - lam) * v[t, n] + lam * nxt)
            nxt = G[t, n]
    return G


def test_td_lambda_equals_a_hand_written_loop():
    rng = np.random.default_rng(0)
    H, N = 9, 4
    r, v = rng.normal(size=(H, N)), rng.normal(size=(H, N))
    d = np.zeros((H, N))
    d[3, 0] = d[5, 1] = d[0, 2] = 1
    d[-1] = 1  # the window's last step ends every segment
    got = np.asarray(shac.td_lambda(jnp.asarray(r), jnp.asarray(v), jnp.asarray(d), 0.99, 0.95))
    np.testing.assert_allclose(got, _lambda_returns_loop(r, v, d, 0.99, 0.95), rtol=1e-5,
                               atol=1e-5)


def test_td_lambda_hand_values():
    # Two steps, one env: G_1 = r_1 + g v_1; G_0 = r_0 + g((1-l) v_0 + l G_1).
    r, v, d = np.array([[1.0], [2.0]]), np.array([[10.0], [20.0]]), np.array([[0.0], [1.0]])
    got = np.asarray(shac.td_lambda(jnp.asarray(r), jnp.asarray(v), jnp.asarray(d), 0.5, 0.5))
    assert got[1, 0] == pytest.approx(2 + 0.5 * 20)
    assert got[0, 0] == pytest.approx(1 + 0.5 * (0.5 * 10 + 0.5 * 12))


def _agent(task, **over):
    cfg = SHACConfig(num_envs=8, actor_hidden=(16,), critic_hidden=(16,), **over)
    return shac.SHAC(task.env, task.obs_size, task.action_size, task.episode_length, cfg)


@pytest.mark.parametrize("horizon,logstd,bias", [(128, -1.0, 0.0), (128, 3.0, 50.0)])
def test_actor_gradient_is_finite_at_the_extremes(horizon, logstd, bias):
    # A full-episode window (4x the default) and, second, saturated tanh actions (huge
    # pre-tanh mean and std): the gradient must stay finite and, unsaturated, non-zero.
    task = make_task("pointmass")
    agent = _agent(task, horizon=horizon, logstd_init=logstd)
    s = agent.init(jax.random.PRNGKey(0))
    actor = jax.tree.map(lambda x: x, s.actor)
    actor["net"]["params"]["Dense_1"]["bias"] = actor["net"]["params"]["Dense_1"]["bias"] + bias
    (loss, _), g = jax.value_and_grad(agent.actor_loss, has_aux=True)(actor, s)
    leaves = jax.tree.leaves(g)
    assert np.isfinite(float(loss)) and all(np.isfinite(np.asarray(x)).all() for x in leaves)
    norm = float(jnp.sqrt(sum(jnp.sum(x ** 2) for x in leaves)))
    assert norm > 1e-6
    if bias:  # the actions really are saturated
        a = agent.action(actor, s.rms, s.env_state.obs[0], jax.random.PRNGKey(3))
        assert float(jnp.abs(a).min()) > 0.999


def test_epoch_is_deterministic_and_reports_finite_metrics():
    task = make_task("pointmass")
    agent = _agent(task)
    a = agent.epoch(agent.init(jax.random.PRNGKey(1)))
    b = agent.epoch(agent.init(jax.random.PRNGKey(1)))
    for x, y in zip(jax.tree.leaves(a[0].actor), jax.tree.leaves(b[0].actor)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert all(np.isfinite(float(v)) for v in a[1].values())
    assert float(a[1]["grad/nonfinite"]) == 0


def test_epoch_compiles_once(avals):
    """The initial state has the types of every later state: weak types in it (a Python
    float through jnp.full / jnp.asarray) made `epoch` compile twice, and a sweep's one-epoch
    compile warm-up cached only the first (walker2d: 184 s of a 60-s budget compiling)."""
    task = make_task("pointmass")
    agent = _agent(task)
    s0 = agent.init(jax.random.PRNGKey(0))
    s1, _ = agent.epoch(s0)
    assert avals(s1) == avals(s0)
    compiled = agent.epoch._cache_size()  # shared by every SHAC built in this process
    agent.epoch(s1)
    assert agent.epoch._cache_size() == compiled


def test_epoch_compiles_once_when_the_env_state_comes_back_weakly_typed(weak_metric, avals):
    """SHAC on hopper compiled a second `epoch` (150 s of a 180-s budget): its env's step
    writes a weakly typed metric. `strong` keeps the carried state at one signature."""
    task = make_task("pointmass")
    env = weak_metric(task.env)
    assert jax.vmap(env.step)(jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(0), 2)),
                              jnp.zeros((2, task.action_size))).metrics["healthy"].weak_type
    cfg = SHACConfig(num_envs=8, actor_hidden=(16,), critic_hidden=(16,))
    agent = shac.SHAC(env, task.obs_size, task.action_size, task.episode_length, cfg)
    s0 = agent.init(jax.random.PRNGKey(0))
    s1, _ = agent.epoch(s0)
    assert avals(s1) == avals(s0)
    compiled = agent.epoch._cache_size()
    agent.epoch(s1)
    assert agent.epoch._cache_size() == compiled


def test_shac_improves_pointmass_return_within_a_small_budget(store):
    req = RunRequest(method="shac", task="pointmass", seed=0,
                     budget=Budget(env_steps=8 * 32 * 40, evals=2),
                     overrides=dict(num_envs=8, actor_hidden="32,32", critic_hidden="32,32"),
                     eval=EvalConfig(num_episodes=8))
    rec, _ = execute(prepare(req), store, log=lambda s: None)
    assert rec["status"] == "ok", rec["message"]
    # The same initial policy, untrained, scored by the same evaluator.
    from bench.api import Policy
    from bench.evaluator import Evaluator
    task = make_task("pointmass")
    refs = rec["references"]
    agent = shac.SHAC(task.env, task.obs_size, task.action_size, task.episode_length,
                      SHACConfig(num_envs=8, actor_hidden=(32, 32), critic_hidden=(32, 32)))
    s = agent.init(jax.random.PRNGKey(0))
    ev = Evaluator(task, EvalConfig(num_episodes=8), refs["expert_return"],
                   refs["random_return"])
    first = ev.evaluate(Policy(agent.act, (s.actor, s.rms)), 0).mean_return
    # Untrained (zero force) already scores about the expert's -20.6 on this task; SHAC on
    # the true reward must beat the PD expert clearly (measured: -21.9 -> -14.2).
    assert rec["final_return"] > first + 5 and rec["final_normalized"] > 1.02, (first, rec)


def test_shac_trains_on_the_views_physics_plan_behind_the_same_gates(monkeypatch):
    """SHAC differentiates through the physics (`sim_gradients`), so its view runs the
    task's physics plan: on acrobot the closed-form backward (its own pipeline_step), with
    the view's gates kept; without a plan, brax's step; the task itself (which evaluation
    runs) is left as it is."""
    from bench.access import TaskView
    from bench.api import Uses
    from tasks.physics import plan_for
    built = []

    class Stop(Exception):
        pass

    def capture(env, *args):
        built.append(env)
        raise Stop

    monkeypatch.setattr(shac, "SHAC", capture)
    task = make_task("acrobot")
    uses = Uses(true_reward=True, sim_gradients=True)
    for plan in (None, plan_for("acrobot", "cpu")):
        view = TaskView(task, uses, "shac", plan)
        with pytest.raises(Stop):
            shac.train(view, None, SHACConfig(), None, seed=0)
        assert built[-1] is view.env
    plain, fast = built
    assert "pipeline_step" not in vars(plain.unwrapped)
    assert "pipeline_step" not in vars(task.env.unwrapped)
    assert "pipeline_step" in vars(fast.unwrapped) and fast.unwrapped.sys is task.env.unwrapped.sys
    hidden = TaskView(task, Uses(sim_gradients=True), "shac", plan_for("acrobot", "cpu"))
    with pytest.raises(Stop):
        shac.train(hidden, None, SHACConfig(), None, seed=0)
    assert np.isnan(built[-1].reset(jax.random.PRNGKey(0)).reward)
