"""CEM-MPC: reaches the goal on pointmass, deterministic for a fixed seed, honest about the
simulator at test time, and the tracking variant reads no reward."""
import dataclasses
import importlib
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bench.api import Policy
from bench.budget import Budget
from bench.evaluator import EvalConfig, Evaluator
from bench.runner import RunRequest, execute, prepare
from methods.cem_mpc.config import CEMConfig
from tasks import make_task

importlib.import_module("methods.cem_mpc")
cem = sys.modules["methods.cem_mpc.train"]
SMALL = CEMConfig(population=64, elites=8, iterations=3, horizon=16)


def _episode(planner, key, steps=128):
    env = make_task("pointmass").env
    s = env.reset(jax.random.PRNGKey(7))
    mem = planner.init_memory((), None)
    act = jax.jit(lambda s, k, m: planner.act((), s, k, True, m))
    xs, actions = [], []
    for k in jax.random.split(key, steps):
        a, mem = act(s, k, mem)
        s = env.step(s, a)
        xs.append(float(s.obs[0]))
        actions.append(np.asarray(a))
    return np.array(xs), np.array(actions), mem


def test_cem_on_the_true_reward_reaches_the_goal():
    planner = cem.CEMPlanner(make_task("pointmass").env, 1, SMALL)
    xs, _, (plan, t) = _episode(planner, jax.random.PRNGKey(0))
    assert abs(xs[0]) > 0.5           # starts away from the goal at 0
    assert np.all(np.abs(xs[-20:]) < 0.05), xs[-20:]
    assert int(t) == 128 and plan.shape == (16, 1)


def test_planning_is_deterministic_for_a_fixed_seed():
    planner = cem.CEMPlanner(make_task("pointmass").env, 1, SMALL)
    _, a1, _ = _episode(planner, jax.random.PRNGKey(3), steps=10)
    _, a2, _ = _episode(planner, jax.random.PRNGKey(3), steps=10)
    _, a3, _ = _episode(planner, jax.random.PRNGKey(4), steps=10)
    np.testing.assert_array_equal(a1, a2)
    assert not np.array_equal(a1, a3)


def test_warm_start_shifts_the_plan():
    env = make_task("pointmass").env
    s = env.reset(jax.random.PRNGKey(0))
    mem = (jnp.arange(16.0)[:, None] / 16, jnp.zeros((), jnp.int32))
    cfg = CEMConfig(population=8, elites=8, iterations=1, horizon=16, momentum=0.999)
    p = cem.CEMPlanner(env, 1, cfg)
    a, (plan, t) = p.act((), s, jax.random.PRNGKey(0), True, mem)
    # Momentum ~1 keeps the mean: the action is the old plan's first step and the new plan
    # is the old one shifted by one step with a zero appended.
    assert float(a[0]) == pytest.approx(0.0, abs=2e-3)
    np.testing.assert_allclose(np.asarray(plan[:-1, 0]), np.arange(1, 16) / 16, atol=2e-3)
    assert float(plan[-1, 0]) == 0.0 and int(t) == 1


def test_the_planner_needs_sim_at_test_to_be_scored():
    task = make_task("pointmass")
    planner = cem.CEMPlanner(task.env, 1, SMALL)
    pol = Policy(planner.act, (), kind="jax_state", init_memory=planner.init_memory)
    with pytest.raises(PermissionError, match="sim_at_test"):
        Evaluator(task, EvalConfig(num_episodes=2)).evaluate(pol, 0)


@pytest.mark.parametrize("method", ["cem_mpc", "cem_mpc_track"])
def test_cem_methods_run_and_record_planning_time(store, method):
    req = RunRequest(method=method, task="pointmass", seed=0, budget=Budget(seconds=60),
                     preset="cpu", eval=EvalConfig(num_episodes=4))
    rec, _ = execute(prepare(req), store, log=lambda s: None)
    assert rec["status"] == "ok", rec["message"]
    assert rec["reference_method"] and rec["uses"]["sim_at_test"]
    # track reads no reward (its env's rewards are NaN: a reward-reading planner would fail)
    assert rec["uses"]["true_reward"] == (method == "cem_mpc")
    assert rec["config"]["objective"] == ("reward" if method == "cem_mpc" else "track")
    assert rec["train_metrics"]["plan/ms_per_step"] > 0
    assert rec["final_normalized"] > 0.9


def test_objective_must_match_the_method(store):
    req = RunRequest(method="cem_mpc", task="pointmass", seed=0, budget=Budget(seconds=60),
                     preset="cpu", overrides={"objective": "track"},
                     eval=EvalConfig(num_episodes=2))
    rec, _ = execute(prepare(req), store, log=lambda s: None)
    assert rec["status"] == "failed" and "cem_mpc_track" in rec["message"]


def test_planning_through_a_reward_hiding_view_of_a_task_with_metrics():
    """Brax tasks report reward terms in state.metrics; the tracking planner sees the env
    through HideReward (metrics dropped), yet is handed the evaluator's full state. The
    scan carry must keep one structure (this failed on reacher and hopper)."""
    from bench.access import HideReward
    from methods.cem_mpc.train import CEMPlanner
    task = make_task("pointmass")
    cfg = CEMConfig(objective="track", horizon=4, population=8, elites=2, iterations=2)
    goals = jnp.zeros((task.episode_length, task.state_size))
    planner = CEMPlanner(HideReward(task.env), task.action_size, cfg,
                         matched_state=task.matched_state, goals=goals,
                         goal_mean=jnp.zeros(task.state_size), goal_std=jnp.ones(task.state_size))
    s = task.env.reset(jax.random.PRNGKey(0))
    s = s.replace(metrics={"reward_dist": jnp.zeros(()), "reward_ctrl": jnp.zeros(())})
    a, _ = planner.act((), s, jax.random.PRNGKey(1), True, planner.init_memory((), None))
    assert a.shape == (task.action_size,) and bool(jnp.isfinite(a).all())


def test_planning_from_a_gated_state_when_the_env_mutates_metrics_in_place():
    """brax's envs do `state.metrics.update(...)` on the state they are handed. From a state
    of the gated view (metrics {}), that in-place update would grow the scan carry's own
    dict mid-trace (failed: cem_mpc_track's planning-time probe on reacher and hopper)."""
    from brax.envs.base import Wrapper
    from bench.access import HideReward
    from methods.cem_mpc.train import CEMPlanner

    class MutatesMetrics(Wrapper):  # what brax's reacher/hopper step does
        def step(self, state, action):
            state.metrics.update(reward_dist=jnp.zeros(()))
            return self.env.step(state, action)

    task = make_task("pointmass")
    cfg = CEMConfig(objective="track", horizon=4, population=8, elites=2, iterations=2)
    env = HideReward(MutatesMetrics(task.env))
    planner = CEMPlanner(env, task.action_size, cfg, matched_state=task.matched_state,
                         goals=jnp.zeros((task.episode_length, task.state_size)),
                         goal_mean=jnp.zeros(task.state_size), goal_std=jnp.ones(task.state_size))
    s = env.reset(jax.random.PRNGKey(0))
    assert s.metrics == {}
    a, _ = jax.jit(lambda s: planner.act((), s, jax.random.PRNGKey(1), True,
                                         planner.init_memory((), None)))(s)
    assert a.shape == (task.action_size,) and bool(jnp.isfinite(a).all())


def test_tracking_never_prefers_ending_the_episode():
    """A cost summed only while alive makes termination free: on hopper the tracking planner
    fell on purpose (normalized -0.24, below random). The terminal state is held and charged
    against every later goal, so a plan that terminates scores worse than one that tracks."""
    from brax.envs.base import Wrapper
    from methods.cem_mpc.train import CEMPlanner

    class EndsLeftOfMinusHalf(Wrapper):
        def step(self, state, action):
            s = self.env.step(state, action)
            return s.replace(done=(s.obs[0] < -0.5).astype(jnp.float32))

    task = make_task("pointmass")
    env = EndsLeftOfMinusHalf(task.env)
    s0 = env.reset(jax.random.PRNGKey(0))
    x0 = np.asarray(task.matched_state(s0))
    # Goals: the start state held, a perfect tracker pays nothing; push left and end instead.
    goals = jnp.tile(jnp.asarray(x0), (task.episode_length, 1))
    cfg = CEMConfig(objective="track", horizon=40)
    planner = CEMPlanner(env, task.action_size, cfg, matched_state=task.matched_state,
                         goals=goals, goal_mean=jnp.zeros(task.state_size),
                         goal_std=jnp.ones(task.state_size))
    at_rest = jnp.array([-0.45, 0.0])                 # (x, v): zero action holds it
    s0 = s0.replace(pipeline_state=at_rest, obs=at_rest)
    hold = jnp.zeros((40, task.action_size))
    end = jnp.zeros((40, task.action_size)).at[:8, 0].set(-1.0)
    score_hold = float(planner.score(s0, hold, 0))
    score_end = float(planner.score(s0, end, 0))
    # by hand: holding (x, v) = (-0.45, 0) against goal x0 costs 40 * |(-0.45, 0) - x0|^2;
    # ending after a few steps would cost only those steps if the cost were masked
    d = np.array([-0.45, 0.0]) - x0
    assert score_hold == pytest.approx(-40 * float(d @ d), rel=1e-5)
    assert score_end < score_hold


def test_small_dots_plans_on_the_rewritten_physics_to_the_same_action():
    """`small_dots=True` hands the planner `tasks.physics.transforms.with_small_dots`'s copy of
    the physics (gated like the task it was given); the plan is the same to float32 round-off."""
    from types import SimpleNamespace

    from bench.access import TaskView
    from bench.api import Uses
    task = make_task("acrobot")
    view = TaskView(task, Uses(true_reward=True, sim_at_test=True), "cem_mpc")
    cfg = CEMConfig(population=16, elites=4, iterations=2, horizon=4)
    s = task.env.reset(jax.random.PRNGKey(0))
    actions = []
    for small_dots in (False, True):
        policy = cem.train(view, None, dataclasses.replace(cfg, small_dots=small_dots),
                           SimpleNamespace(log=lambda s: None), seed=0).policy
        planner_env = policy.act.__self__.env
        assert ("pipeline_step" in vars(planner_env.unwrapped)) == small_dots
        a, _ = policy.act((), s, jax.random.PRNGKey(1), True, policy.init_memory((), None))
        actions.append(np.asarray(a))
    np.testing.assert_allclose(actions[1], actions[0], atol=1e-4)


def test_small_dots_on_a_task_without_brax_physics_fails_the_run_by_name(store):
    req = RunRequest(method="cem_mpc", task="pointmass", seed=0, budget=Budget(seconds=60),
                     preset="cpu", overrides={"small_dots": True},
                     eval=EvalConfig(num_episodes=2))
    rec, _ = execute(prepare(req), store, log=lambda s: None)
    assert rec["status"] == "failed"
    assert "pointmass" in rec["message"] and "small_dots" in rec["message"]
