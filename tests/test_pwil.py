"""PWIL: greedy coupling reward vs hand values, vs the original loop, vs POT's exact EMD."""
import importlib
import sys

import numpy as np
import pytest

from bench.access import DemoView
from bench.api import Uses
from methods.common.sb3 import BraxVecEnv
from methods.pwil.config import PWILConfig
from methods.pwil.rewarder import PWILRewarder, exact_episode_cost, greedy_episode_cost
from tasks import make_task
from tasks.demo import load_demo

importlib.import_module("methods.pwil")
pwil = sys.modules["methods.pwil.train"]


def test_reward_equals_the_formula_on_a_hand_computed_coupling():
    # Atoms 0, 1, 2, 3 (mass 1/4 each), T = 2 (agent mass 1/2 per step), d = 1.
    r = PWILRewarder(np.array([[0.0], [1.0], [2.0], [3.0]]), num_envs=1, horizon=2)
    s = np.sqrt(1.25)  # the atoms' std: distances are in standardized units
    # Step 1 at x = 0.2 takes atoms 0 and 1: cost 1/4 * 0.2/s + 1/4 * 0.8/s.
    # Step 2 at x = 2.5 takes the remaining atoms 2 and 3: cost 1/4 * 0.5/s + 1/4 * 0.5/s.
    for x, cost in ((0.2, 0.25 / s), (2.5, 0.25 / s)):
        got = r.rewards(np.array([[x]]))
        assert got[0] == pytest.approx(5.0 * np.exp(-5.0 * 2 / np.sqrt(1) * cost), rel=1e-12)
    assert np.all(r.weights == 0)  # all expert mass used
    r.reset()
    assert np.allclose(r.weights, 0.25)


def _greedy_loop(atoms, weights, x, agent_mass):
    """The original's greedy loop, one atom at a time."""
    w = weights.copy()
    d = np.sqrt(((atoms - x) ** 2).sum(-1))
    cost, left = 0.0, agent_mass
    while left > 0 and (w > 0).any():
        k = np.argmin(np.where(w > 0, d, np.inf))
        take = min(w[k], left)
        cost += take * d[k]
        w[k] -= take
        left -= take
    return cost, w


def test_vectorized_coupling_equals_the_original_greedy_loop():
    rng = np.random.default_rng(0)
    atoms = rng.normal(size=(37, 5))
    r = PWILRewarder(atoms, num_envs=3, horizon=23)
    w_ref = np.full((3, 37), 1 / 37)
    for _ in range(23):
        x = rng.normal(size=(3, 5))
        cost = r.step_costs(x)
        for e in range(3):
            c, w_ref[e] = _greedy_loop(r.atoms, w_ref[e], r.standardize(x[e]), 1 / 23)
            assert cost[e] == pytest.approx(c, rel=1e-9, abs=1e-12)
        np.testing.assert_allclose(r.weights, w_ref, atol=1e-12)


@pytest.mark.parametrize("seed", range(5))
def test_greedy_cost_is_at_least_the_exact_emd(seed):
    rng = np.random.default_rng(seed)
    agent, expert = rng.normal(size=(40, 3)), rng.normal(size=(25, 3)) + 0.5
    assert greedy_episode_cost(agent, expert) >= exact_episode_cost(agent, expert) - 1e-9


def test_greedy_equals_emd_where_greedy_is_optimal():
    # Well-separated atoms, the agent visiting each one slightly off: every greedy choice is
    # the optimal assignment, so greedy cost == EMD == the mean offset (standardized).
    expert = np.arange(10.0)[:, None] * 10
    agent = expert + 0.3
    g, e = greedy_episode_cost(agent, expert), exact_episode_cost(agent, expert)
    assert g == pytest.approx(e, rel=1e-9)
    assert g == pytest.approx(0.3 / expert.std(), rel=1e-9)


def test_reward_is_highest_for_the_demo_itself():
    task = make_task("pointmass")
    demo = DemoView(load_demo(task.spec.demo_path, task),
                    Uses(demo_states=True, demo_actions=True), "pwil")
    cfg = PWILConfig()
    atoms, obs, act = pwil.expert_atoms(demo, cfg)
    rng = np.random.default_rng(0)
    feats = pwil.features(obs[:-1], act, True)
    candidates = {"demo": feats,
                  "noisy demo": feats + rng.normal(0, 0.05, feats.shape),
                  "first half twice": np.concatenate([feats[:64], feats[:64]]),
                  "random actions": pwil.features(obs[:-1], rng.uniform(-1, 1, act.shape),
                                                  True)}
    totals = {}
    for name, f in candidates.items():
        r = PWILRewarder(atoms, 1, cfg.horizon, cfg.alpha, cfg.beta)
        totals[name] = sum(r.rewards(x[None])[0] for x in f)
    assert totals["demo"] == pytest.approx(cfg.alpha * 128, rel=1e-9)  # cost 0 every step
    assert all(totals["demo"] > v for k, v in totals.items() if k != "demo"), totals
    # A coupling, not a tracker: the demo's steps in reverse order earn the same reward.
    r = PWILRewarder(atoms, 1, cfg.horizon, cfg.alpha, cfg.beta)
    assert sum(r.rewards(x[None])[0] for x in feats[::-1]) == pytest.approx(totals["demo"])


def test_env_wrapper_rewards_before_stepping_and_resets_at_episode_end():
    task = make_task("pointmass")
    demo = DemoView(load_demo(task.spec.demo_path, task),
                    Uses(demo_states=True, demo_actions=True), "pwil")
    atoms, obs, act = pwil.expert_atoms(demo, PWILConfig())
    env = pwil.PWILReward(BraxVecEnv(task.env, 2, 128), PWILRewarder(atoms, 2, 128), True)
    o = env.reset()
    ref = PWILRewarder(atoms, 2, 128)
    for t in range(128):
        a = np.full((2, 1), 0.3, np.float32)
        expect = ref.rewards(np.concatenate([o, a], -1))
        env.step_async(a)
        o, rew, dones, _ = env.step_wait()
        np.testing.assert_allclose(rew, expect, rtol=1e-5, atol=1e-30)  # stored as float32
        paid = rew if t == 0 else paid + rew
    assert dones.all() and np.allclose(env.rewarder.weights, 1 / 128)  # fresh episode
    # What the reward paid: per env step, and per finished episode (return and length).
    stats = env.stats()
    assert stats["train/pwil_episode_return"] == pytest.approx(paid.mean(), rel=1e-6)
    assert stats["train/pwil_reward_mean"] == pytest.approx(paid.sum() / 256, rel=1e-6)
    assert stats["train/episode_length"] == 128
    assert env.stats() == {}  # read once


def _pointmass_learner(**over):
    task = make_task("pointmass")
    demo = DemoView(load_demo(task.spec.demo_path, task),
                    Uses(demo_states=True, demo_actions=True), "pwil")
    cfg = PWILConfig(**{**dict(actor_hidden=(8,), critic_hidden=(8,), num_envs=4,
                               steps_per_collect=4), **over})
    model, _ = pwil.make_learner(task.env, 128, demo, cfg, seed=0)
    return model, cfg, demo


def test_demo_rows_are_sampled_in_the_prefill_proportion_with_n_step_returns_of_alpha():
    """Replaces a replay that held 50,000 demo copies whatever the budget: the demo is stored
    once and a batch row is a demo row with probability D / (D + A)."""
    model, cfg, demo = _pointmass_learner()
    buf = model.replay_buffer
    assert buf.demo.size() == 128 and buf.size() == 0
    # 75 agent rows x 4 envs = 300 agent transitions (reward 0, never done).
    obs = np.full((4, 2), 7.0, np.float32)
    for _ in range(75):
        buf.add(obs, obs, np.zeros((4, 1), np.float32), np.zeros(4, np.float32),
                np.zeros(4, bool), [{}] * 4)
    buf.demo_count = lambda: 100.0
    assert buf.demo_share() == pytest.approx(100 / 400)
    np.random.seed(0)
    batch = buf.sample(4000)
    is_demo = batch.observations[:, 0].numpy() != 7.0
    assert abs(is_demo.mean() - 0.25) < 0.02  # binomial sd 0.007
    # Every demo row: o_t of the demo with the n-step return of reward alpha, cut at T.
    d_obs = np.asarray(demo.obs[0, :-1])
    t = np.array([np.flatnonzero(np.all(d_obs == o, 1))[0]
                  for o in batch.observations[is_demo].numpy()])
    n = np.minimum(cfg.n_step, 128 - t)
    expect = cfg.alpha * (1 - cfg.gamma ** n) / (1 - cfg.gamma)
    np.testing.assert_allclose(batch.rewards[is_demo, 0].numpy(), expect, rtol=1e-5)
    np.testing.assert_allclose(batch.discounts[is_demo, 0].numpy(), cfg.gamma ** n, rtol=1e-5)
    assert np.all(batch.rewards[~is_demo].numpy() == 0)


@pytest.mark.parametrize("budget_steps,steps,expect", [
    (200_000, 5_000, 10_000),     # 5% of the budget, at any point of the run
    (200_000, 150_000, 10_000),
    (50_000, 1_000, 2_500),
    (1_000_000, 10, 50_000),      # the original's 50,000 at its 1M steps
    (4_000_000, 10, 50_000),      # never more than `prefill`
])
def test_demo_count_is_a_fixed_fraction_of_the_step_budget(budget_steps, steps, expect):
    from methods.pwil.train import demo_count
    count = demo_count(PWILConfig(), lambda: steps, lambda s: s / budget_steps)
    assert count() == pytest.approx(expect)


def test_demo_count_on_a_seconds_budget_projects_the_runs_env_steps():
    from methods.pwil.train import demo_count
    # Half the time spent after 30,000 steps: the run will take ~60,000; 5% of that.
    count = demo_count(PWILConfig(), lambda: 30_000, lambda s: 0.5)
    assert count() == pytest.approx(3_000)


HELD_OUT_TASKS = ["pointmass", "inverted_pendulum", "acrobot",
                  pytest.param("reacher", marks=pytest.mark.slow),
                  pytest.param("hopper", marks=pytest.mark.slow),
                  pytest.param("swimmer", marks=pytest.mark.slow),
                  pytest.param("walker2d", marks=pytest.mark.slow),
                  pytest.param("ant", marks=pytest.mark.slow),
                  pytest.param("humanoid", marks=pytest.mark.slow)]


@pytest.mark.parametrize("name", HELD_OUT_TASKS)
def test_reward_of_held_out_expert_episodes_is_far_above_a_random_policys(name):
    """The reward carries signal: the task's other expert episodes (demos 2..K, never shown
    to the method) earn at least a tenth of alpha per step on average and at least five
    times a uniformly random policy's mean reward. With the scale floor at 0 (a raw
    StandardScaler on one demo) reacher's held-out episodes earned 0.013 alpha."""
    import jax
    import jax.numpy as jnp

    task = make_task(name)
    demo = load_demo(task.spec.demo_path, task)
    T = demo.length
    cfg = PWILConfig(horizon=T)
    atoms, _, _ = pwil.expert_atoms(demo, cfg)  # demo 0 alone, as the method sees it

    def mean_reward(obs, act):
        r = PWILRewarder(atoms, len(obs), T, cfg.alpha, cfg.beta, cfg.scale_floor)
        return np.mean([r.rewards(pwil.features(obs[:, t], act[:, t], True)) for t in range(T)])

    held = mean_reward(np.asarray(demo.obs[1:, :-1]), np.asarray(demo.actions[1:]))
    n = 16
    acts = jax.random.uniform(jax.random.PRNGKey(0), (T, n, task.action_size), minval=-1,
                              maxval=1)

    @jax.jit
    def rollout(key, acts):
        def step(s, a):
            return jax.vmap(task.env.step)(s, a), s.obs
        return jax.lax.scan(step, jax.vmap(task.env.reset)(jax.random.split(key, n)), acts)[1]

    obs = np.swapaxes(np.asarray(rollout(jax.random.PRNGKey(1), acts)), 0, 1)
    rand = mean_reward(obs, np.swapaxes(np.asarray(acts), 0, 1))
    assert held >= 0.1 * cfg.alpha, (held, rand)
    assert held >= 5 * rand, (held, rand)


def test_pwil_horizon_is_the_tasks_episode_length():
    import types

    from bench.plugins import build_config, get_method
    train = importlib.import_module("methods.pwil.train").train
    spec = get_method("pwil")
    assert build_config(spec, "cloth", "cpu").horizon == 80
    assert build_config(spec, "hopper", "cpu").horizon == 128
    task = types.SimpleNamespace(name="cloth", episode_length=80)
    with pytest.raises(ValueError, match="horizon T=128 .* episode length 80.*--set horizon=80"):
        train(task, None, PWILConfig(horizon=128), None, 0)


def test_probe_masks_steps_after_termination_as_the_evaluator_does():
    from benchmarks.pwil_probe import alive_mask
    dones = np.array([[0, 0, 1, 0, 1], [0, 0, 0, 0, 0], [1, 0, 0, 0, 0]])
    np.testing.assert_array_equal(alive_mask(dones), [[1, 1, 1, 0, 0], [1, 1, 1, 1, 1],
                                                      [1, 0, 0, 0, 0]])


def test_probe_ranks_the_pointmass_ladder_by_pwil_return_as_by_task_score():
    """On pointmass the expert scores ~1 by the demo's references, and PWIL's return falls
    down the ladder (expert, expert with noise, zero action) with the task score. Planted
    fault it catches: rewards after termination or a second coupling per episode would
    change the returns; a wrong normalization the expert's score."""
    from benchmarks.pwil_probe import probe
    rows, rho = probe("pointmass", episodes=4, noise=(0.0, 1.0))
    by = {r["policy"]: r for r in rows}
    assert [r["policy"] for r in rows] == ["expert, noise 0", "expert, noise 1", "zero_action",
                                           "random"]
    assert by["expert, noise 0"]["normalized"] == pytest.approx(1.0, abs=0.02)
    ret = [by[k]["pwil_return"] for k in ("expert, noise 0", "expert, noise 1", "zero_action")]
    assert ret[0] > 2 * ret[1] > 0 and ret[1] > 10 * ret[2]
    assert by["expert, noise 0"]["pwil_per_step"] <= PWILConfig().alpha
    assert rho > 0.8 and all(r["length"] == 128 for r in rows)
