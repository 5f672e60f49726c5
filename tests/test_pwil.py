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
    assert dones.all() and np.allclose(env.rewarder.weights, 1 / 128)  # fresh episode


def test_prefill_puts_demo_transitions_with_reward_alpha():
    task = make_task("pointmass")
    demo = DemoView(load_demo(task.spec.demo_path, task),
                    Uses(demo_states=True, demo_actions=True), "pwil")
    cfg = PWILConfig(actor_hidden=(8,), critic_hidden=(8,), num_envs=4, steps_per_collect=4)
    _, obs, act = pwil.expert_atoms(demo, cfg)
    venv = BraxVecEnv(task.env, 4, 128)
    model = pwil.build_model(venv, cfg, seed=0)
    n = pwil.prefill(model, obs, act, cfg.alpha, 600)
    buf = model.replay_buffer
    assert n == 600 and buf.pos == 150
    np.testing.assert_array_equal(buf.observations[:128, 2], obs[:-1])
    np.testing.assert_array_equal(buf.next_observations[:128, 1], obs[1:])
    assert np.all(buf.rewards[:150] == cfg.alpha)
    assert buf.dones[127].all() and buf.timeouts[127].all() and not buf.dones[126].any()


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
