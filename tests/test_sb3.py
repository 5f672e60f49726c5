"""The SB3 adapter: batched brax VecEnv, single gymnasium env, gating, budgets via callbacks."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
from brax.envs.base import Wrapper

from bench.access import TaskView
from bench.api import Uses
from bench.budget import Budget
from bench.evaluator import EvalConfig
from bench.runner import RunRequest, execute, prepare
from methods.common.sb3 import BraxGymEnv, BraxVecEnv, torch_policy
from tasks import make_task

T = 128


class Terminating(Wrapper):
    """pointmass that truly terminates once x > 1.2 (the tests' early-termination task)."""

    def step(self, state, action):
        s = self.env.step(state, action)
        return s.replace(done=jnp.asarray(s.obs[0] > 1.2, jnp.float32))


def test_vecenv_truncates_at_the_time_limit_and_matches_a_plain_rollout():
    task = make_task("pointmass")
    venv = BraxVecEnv(task.env, num_envs=4, episode_length=T, seed=3)
    obs = venv.reset()
    assert obs.shape == (4, task.obs_size) and obs.dtype == np.float32
    # Reference: the same first states stepped by the unwrapped env with the same actions.
    state = venv._carry[0]
    rng = np.random.default_rng(0)
    for t in range(T):
        a = rng.uniform(-1, 1, (4, task.action_size)).astype(np.float32)
        ref = jax.vmap(task.env.step)(state, jnp.asarray(a))
        state = ref
        venv.step_async(a)
        obs, rew, dones, infos = venv.step_wait()
        if t < T - 1:
            assert not dones.any()
            np.testing.assert_allclose(obs, np.asarray(ref.obs), atol=1e-6)
            np.testing.assert_allclose(rew, np.asarray(ref.reward), atol=1e-6)
    assert dones.all()
    for i in range(4):
        assert infos[i]["TimeLimit.truncated"] and not infos[i]["terminated"]
        np.testing.assert_allclose(infos[i]["terminal_observation"], np.asarray(ref.obs[i]),
                                   atol=1e-6)
    # Auto-reset: the returned observation starts a new episode (x near the start 1.0).
    assert np.all(np.abs(obs[:, 0] - 1.0) < 0.5)
    assert not np.allclose(obs, np.asarray(ref.obs))


def test_vecenv_true_termination_is_not_truncation():
    env = Terminating(make_task("pointmass").env)
    venv = BraxVecEnv(env, num_envs=3, episode_length=T, seed=0)
    venv.reset()
    seen = []
    for t in range(40):
        venv.step_async(np.ones((3, 1), np.float32))  # full thrust: x passes 1.2 quickly
        obs, _, dones, infos = venv.step_wait()
        for i in np.flatnonzero(dones):
            seen.append((t, infos[i]["terminated"], infos[i]["TimeLimit.truncated"],
                         infos[i]["terminal_observation"][0]))
    assert seen, "full thrust never crossed x = 1.2"
    assert all(term and not trunc and x > 1.2 for _, term, trunc, x in seen)
    assert seen[0][0] < T - 1


def test_gated_env_hides_the_reward_from_an_imitation_learner():
    task = make_task("pointmass")
    view = TaskView(task, Uses(demo_states=True, demo_actions=True), "dac")
    venv = BraxVecEnv(view.env, num_envs=2, episode_length=T)
    venv.reset()
    venv.step_async(np.zeros((2, 1), np.float32))
    _, rew, _, _ = venv.step_wait()
    assert np.isnan(rew).all()


def test_single_gym_env_passes_sb3_checker_and_truncates():
    from stable_baselines3.common.env_checker import check_env
    env = BraxGymEnv(Terminating(make_task("pointmass").env), episode_length=T)
    check_env(env, warn=True)
    env.reset(seed=1)
    for t in range(T):
        _, r, term, trunc, _ = env.step(np.zeros(1, np.float32))  # no thrust: never past 1.2
        assert np.isfinite(r) and not term
        assert trunc == (t == T - 1)
    env.reset(seed=1)
    for t in range(T):
        _, _, term, trunc, _ = env.step(np.ones(1, np.float32))
        if term:
            break
    assert term and not trunc


def test_torch_policy_snapshot_is_frozen_and_checkable():
    import torch
    net = torch.nn.Sequential(torch.nn.Linear(2, 1), torch.nn.Tanh())
    pol = torch_policy(net, noise_std=0.5)
    obs = np.ones((3, 2), np.float32)
    a0 = pol.act(pol.params, obs, np.random.default_rng(0), True)
    with torch.no_grad():
        net[0].weight.add_(1.0)  # training after the snapshot must not change it
    np.testing.assert_array_equal(pol.act(pol.params, obs, np.random.default_rng(0), True), a0)
    noisy = pol.act(pol.params, obs, np.random.default_rng(0), False)
    assert noisy.shape == a0.shape and np.all(np.abs(noisy) <= 1) and not np.allclose(noisy, a0)


TINY = dict(actor_hidden="32,32", critic_hidden="32,32", learning_starts=256, batch_size=32,
            num_envs=8, steps_per_collect=64, report_every=256)


@pytest.mark.parametrize("method,extra", [
    ("dac", dict(disc_hidden="32,32", disc_batch=32, actor_start_updates=64)),
    ("pwil", dict(prefill=512)),
])
def test_rl_imitation_methods_respect_the_step_budget_and_record_throughput(store, method,
                                                                           extra):
    req = RunRequest(method=method, task="pointmass", seed=0,
                     budget=Budget(env_steps=1024, evals=2), overrides={**TINY, **extra},
                     eval=EvalConfig(num_episodes=4))
    rec, _ = execute(prepare(req), store, log=lambda s: None)
    assert rec["status"] == "ok", rec.get("message")
    assert 1024 <= rec["env_steps"] < 1024 + 8  # stops within one vector step of the budget
    assert rec["train_metrics"]["speed/env_steps_per_s"] > 0
    assert rec["train_metrics"]["speed/updates_per_s"] > 0
    # UTD 1: one update per env step after learning starts (to within one collection).
    assert abs(rec["train_metrics"]["train/updates"] - (1024 - 256)) <= 64
    assert rec["curve"] and rec["final_from"] == "final policy"
    assert np.isfinite(rec["final_return"])
    # The learner's state beside its score: losses and the critic's value of recent play.
    last = rec["train_metrics"]
    assert {"train/critic_loss", "train/actor_loss", "train/q_recent"} <= set(last)
    assert all(np.isfinite(last[k]) for k in ("train/critic_loss", "train/q_recent"))
    assert "train/q_recent" in rec["curve"][-1]["train"]
    if method == "pwil":  # 8 envs x 128 steps: every env finished one episode at the end
        assert last["train/episode_length"] == 128
        assert 0 < last["train/pwil_episode_return"] <= 5.0 * 128
        assert 0 < last["train/pwil_reward_mean"] <= 5.0


def small_learner(method: str, task_name: str, common: dict, dac: dict, seed: int,
                  pwil: dict | None = None):
    """(DAC or PWIL learner on `task_name` with the `common` config fields and the method's
    own, the demo view it was built from)."""
    import importlib
    import sys

    from bench.access import DemoView
    from methods.dac.config import DACConfig
    from methods.pwil.config import PWILConfig
    from tasks.demo import load_demo
    importlib.import_module(f"methods.{method}")
    mod = sys.modules[f"methods.{method}.train"]
    task = make_task(task_name)
    demo = DemoView(load_demo(task.spec.demo_path, task),
                    Uses(demo_states=True, demo_actions=True), method)
    if method == "dac":
        return mod.make_learner(task.env, T, demo, DACConfig(**common, **dac), seed=seed), demo
    model, _ = mod.make_learner(task.env, T, demo, PWILConfig(**common, **(pwil or {})),
                                seed=seed)
    return model, demo


def test_keep_last_logger_keeps_the_last_value_of_each_key_past_a_dump():
    from methods.common.sb3 import KeepLastLogger
    log = KeepLastLogger()
    log.record("train/critic_loss", 2.5)
    log.record("train/actor_loss", -1.0)
    log.dump(1)
    assert log.name_to_value == {}  # SB3's dump clears its table
    log.record("train/critic_loss", 0.5)
    assert log.values() == {"train/critic_loss": 0.5, "train/actor_loss": -1.0}


def test_recent_q_is_the_critics_mean_over_the_last_stored_transitions_and_draws_nothing():
    import importlib
    import sys

    from bench.access import DemoView
    from methods.common.sb3 import recent_q
    from methods.pwil.config import PWILConfig
    from tasks.demo import load_demo
    importlib.import_module("methods.pwil")
    pwil = sys.modules["methods.pwil.train"]
    task = make_task("pointmass")
    demo = DemoView(load_demo(task.spec.demo_path, task),
                    Uses(demo_states=True, demo_actions=True), "pwil")
    model, _ = pwil.make_learner(task.env, T, demo, PWILConfig(
        actor_hidden=(8,), critic_hidden=(8,), num_envs=4, steps_per_collect=4), seed=0)
    buf = model.replay_buffer
    assert recent_q(model) == {}
    # Row r of 75 holds, for env e, observation (r, e) and action e / 4.
    for r in range(75):
        obs = np.array([[r, e] for e in range(4)], np.float32)
        buf.add(obs, obs, np.arange(4, dtype=np.float32)[:, None] / 4, np.zeros(4, np.float32),
                np.zeros(4, bool), [{}] * 4)
    # The last 10 transitions: rows 74 and 73 (4 envs each), then row 72's envs 0 and 1.
    want_obs = np.array([[r, e] for r in (74, 73) for e in range(4)] + [[72, 0], [72, 1]],
                        np.float32)
    want_act = (want_obs[:, 1:] / 4).astype(np.float32)
    with torch.no_grad():
        want = model.critic.q1_forward(torch.from_numpy(want_obs),
                                       torch.from_numpy(want_act)).mean().item()
    np_state, torch_state = np.random.get_state(), torch.get_rng_state()
    got = recent_q(model, k=10)["train/q_recent"]
    assert got == pytest.approx(want, rel=1e-6)
    assert np.array_equal(np.random.get_state()[1], np_state[1])
    assert torch.equal(torch.get_rng_state(), torch_state)
    # `real` drops the rows it marks False (DAC's absorbing states); none kept: no value.
    odd = recent_q(model, k=10, real=lambda o: o[:, 1] % 2 == 1)["train/q_recent"]
    with torch.no_grad():
        keep = want_obs[:, 1] % 2 == 1
        want_odd = model.critic.q1_forward(torch.from_numpy(want_obs[keep]),
                                           torch.from_numpy(want_act[keep])).mean().item()
    assert odd == pytest.approx(want_odd, rel=1e-6) and odd != pytest.approx(got)
    assert recent_q(model, k=10, real=lambda o: o[:, 0] < 0) == {}


def test_obs_normalizer_equals_the_statistics_of_everything_it_was_given():
    from methods.common.sb3 import ObsNormalizer
    rng = np.random.default_rng(0)
    parts = [rng.normal(3.0, 50.0, (129, 4)), rng.normal(-1.0, 0.1, (16, 4)),
             rng.normal(0.0, 1.0, (1, 4))]
    norm = ObsNormalizer(4, init=parts[0])
    for p in parts[1:]:
        norm.update(p)
    x = np.concatenate(parts)
    np.testing.assert_allclose(norm.var, x.var(0), rtol=1e-10)
    np.testing.assert_allclose(norm.mean.numpy(), x.mean(0), rtol=1e-6)
    # Applied: clip((x - mean) / sqrt(var + eps), -10, 10); a trailing indicator passes.
    y = np.concatenate([x, np.ones((len(x), 1))], 1).astype(np.float32)
    z = norm(torch.from_numpy(y)).numpy()
    want = np.clip((x - x.mean(0)) / np.sqrt(x.var(0) + 1e-4), -10, 10)
    np.testing.assert_allclose(z[:, :4], want, rtol=1e-4, atol=1e-5)
    assert np.all(z[:, 4] == 1.0)


@pytest.mark.parametrize("method", ["dac", "pwil"])
def test_learners_networks_read_observations_normalized_by_shared_running_statistics(method):
    """Replaces learners that fed raw observations (hopper's reach |x| = 5.7, humanoid's
    139) to the actor, the critics and DAC's discriminator: every network now reads
    (o - mean) / std with one set of statistics, the demo's observations and every collected
    one, and an evaluation snapshot keeps the statistics of its moment."""
    model, demo = small_learner(method, "hopper", dict(
        actor_hidden=(16,), critic_hidden=(16,), num_envs=4, steps_per_collect=4,
        learning_starts=64, batch_size=16), dict(disc_hidden=(16,), disc_batch=16), seed=0)
    seen = []
    venv = model.get_env()
    inner = venv.venv  # the batched brax env under the method's wrapper
    wait, reset = inner.step_wait, inner.reset

    def record():
        out = wait()
        seen.append(out[0])
        return out

    def record_reset():
        out = reset()
        seen.append(out)
        return out
    inner.step_wait, inner.reset = record, record_reset
    model.learn(total_timesteps=96)
    norm = model.actor.features_extractor
    everything = np.concatenate([np.asarray(demo.obs[0, :-1])] + seen).astype(np.float64)
    np.testing.assert_allclose(norm.obs_mean.numpy(), everything.mean(0), rtol=1e-4,
                               atol=1e-5)
    np.testing.assert_allclose(norm.obs_inv_std.numpy(), 1 / np.sqrt(everything.var(0) + 1e-4),
                               rtol=1e-3)
    nets = [model.actor, model.actor_target, model.critic, model.critic_target]
    for net in nets:  # one set of statistics, not copies
        assert net.features_extractor.obs_mean.data_ptr() == norm.obs_mean.data_ptr()
    x = torch.from_numpy(everything.astype(np.float32))
    if method == "dac":
        x = torch.cat([x, torch.zeros(len(x), 1)], 1)
        assert model.discriminator.normalizer.mean.data_ptr() == norm.obs_mean.data_ptr()
        assert np.all(norm(x).numpy()[:, -1] == 0)  # the absorbing indicator passes through
    z = norm(x).numpy()[:, :make_task("hopper").obs_size]
    assert np.abs(z.mean(0)).max() < 1e-3 and np.all(np.abs(z) <= 10)
    # A snapshot keeps its statistics while the learner's move on.
    pol = torch_policy(model.actor)
    before = pol.params["features_extractor.obs_mean"].copy()
    model.learn(total_timesteps=32, reset_num_timesteps=False)
    assert not np.allclose(norm.obs_mean.numpy(), before)
    np.testing.assert_array_equal(pol.params["features_extractor.obs_mean"], before)
