"""DAC: discriminator, gradient penalty, absorbing states, expert subsampling."""
import importlib
import sys

import numpy as np
import pytest
import torch

from bench.access import DemoView
from bench.api import Uses
from methods.common.sb3 import BraxVecEnv
from methods.dac.config import DACConfig
from tasks import make_task
from tasks.demo import load_demo
from tests.test_sb3 import Terminating

importlib.import_module("methods.dac")
dac = sys.modules["methods.dac.train"]


def test_gradient_penalty_linear_discriminator_hand_value():
    # D(x) = w.x + b has gradient w everywhere: GP = (|w| - 1)^2 = (5 - 1)^2 = 16.
    d = dac.Discriminator(obs_dim=1, act_dim=1, hidden=())
    with torch.no_grad():
        d.net[0].weight.copy_(torch.tensor([[3.0, 4.0]]))
    x_pol, x_exp = torch.randn(7, 2), torch.randn(7, 2)
    gp = dac.gradient_penalty(d.net, x_pol, x_exp, torch.rand(7, 1))
    assert gp.item() == pytest.approx(16.0, rel=1e-6)


def test_gradient_penalty_is_taken_at_the_interpolates():
    # D(x) = |x|^2 / 2 has gradient x, so GP = mean((|u x_p + (1-u) x_e| - 1)^2).
    x_pol = torch.tensor([[2.0, 0.0], [0.0, 4.0]])
    x_exp = torch.tensor([[0.0, 0.0], [0.0, 0.0]])
    u = torch.tensor([[0.25], [0.5]])
    # interpolates (0.5, 0) and (0, 2): norms 0.5 and 2 -> ((0.5-1)^2 + (2-1)^2) / 2 = 0.625
    gp = dac.gradient_penalty(lambda x: 0.5 * (x ** 2).sum(-1), x_pol, x_exp, u)
    assert gp.item() == pytest.approx(0.625, rel=1e-6)
    # ... and not at either end point (norms 2, 4 -> 5.0; norms 0, 0 -> 1.0)
    assert gp.item() not in (pytest.approx(5.0), pytest.approx(1.0))


def test_discriminator_separates_demo_from_random_transitions():
    # Demo (s, a) vs transitions of a uniformly random policy on the same task. The gradient
    # penalty keeps D 1-Lipschitz, so the margin is bounded; accuracy is what must rise.
    torch.manual_seed(0)
    task = make_task("pointmass")
    demo = DemoView(load_demo(task.spec.demo_path, task),
                    Uses(demo_states=True, demo_actions=True), "dac")
    exp_o, exp_a = dac.expert_transitions(demo, DACConfig(), np.random.default_rng(0))
    venv = BraxVecEnv(task.env, 8, 128, seed=1)
    o, rng, O, A = venv.reset(), np.random.default_rng(1), [], []
    for t in range(128):
        a = rng.uniform(-1, 1, (8, 1)).astype(np.float32)
        O.append(o), A.append(a)
        venv.step_async(a)
        o = venv.step_wait()[0]
    rand_o, rand_a = dac.add_indicator(np.concatenate(O)), np.concatenate(A)
    d = dac.Discriminator(3, 1)
    to = torch.as_tensor

    def accuracy():
        with torch.no_grad():
            return ((d.logits(to(exp_o), to(exp_a)) > 0).float().mean().item(),
                    (d.logits(to(rand_o), to(rand_a)) < 0).float().mean().item())

    before = accuracy()
    for it in range(300):
        i, j = rng.integers(len(exp_o), size=100), rng.integers(len(rand_o), size=100)
        stats = d.update(to(rand_o[j]), to(rand_a[j]), to(exp_o[i]), to(exp_a[i]))
    acc_exp, acc_rand = accuracy()
    assert min(before) < 0.6  # an untrained D does not separate them
    assert acc_exp > 0.85 and acc_rand > 0.75, (acc_exp, acc_rand)
    assert stats["disc/gp"] < 0.01  # the penalty holds the gradient norm near 1
    # The reward is the logit: higher on demo transitions.
    assert d.reward(to(exp_o), to(exp_a)).mean() > d.reward(to(rand_o), to(rand_a)).mean() + 0.5


def test_expert_subsampling_follows_the_original_rate():
    task = make_task("pointmass")
    demo = DemoView(load_demo(task.spec.demo_path, task),
                    Uses(demo_states=True, demo_actions=True), "dac")
    o, a = dac.expert_transitions(demo, DACConfig(), np.random.default_rng(0))
    assert len(o) == len(a) == 64  # rate 128 // 50 = 2
    assert np.all(o[:, -1] == 0)
    full, _ = dac.expert_transitions(demo, DACConfig(trajectory_size=128),
                                     np.random.default_rng(0))
    np.testing.assert_array_equal(full[:, :-1], np.asarray(demo.obs[0, :-1]))


def _collect(env, steps, action):
    """Run SB3's own collection (TD3 before learning starts) and return the buffer."""
    cfg = DACConfig(actor_hidden=(8,), critic_hidden=(8,), disc_hidden=(8,),
                    learning_starts=10 ** 6, num_envs=4, steps_per_collect=8)
    venv = dac.AbsorbingWrapper(BraxVecEnv(env, cfg.num_envs, 128, seed=0))
    model = dac.build_model(venv, cfg, np.zeros((1, 3), np.float32),
                            np.zeros((1, 1), np.float32), seed=0)
    model._sample_action = lambda *a, **k: (np.full((4, 1), action, np.float32),) * 2
    model.learn(total_timesteps=steps)
    buf = model.replay_buffer
    n = buf.pos
    return buf.observations[:n, 0], buf.next_observations[:n, 0], buf.actions[:n, 0], \
        buf.dones[:n, 0], buf


def test_absorbing_transitions_only_on_true_termination():
    # Full thrust terminates pointmass-with-a-wall within a few steps, every episode.
    obs, nxt, act, dones, buf = _collect(Terminating(make_task("pointmass").env), 400, 1.0)
    into = (obs[:, -1] == 0) & (nxt[:, -1] == 1)      # terminal transitions
    loops = (obs[:, -1] == 1)                          # absorbing self-loops
    assert into.sum() > 4 and into.sum() == loops.sum() == buf.absorbing_added
    assert np.all(nxt[loops, -1] == 1) and np.all(act[loops] == 0)
    assert np.all(nxt[loops, :-1] == 0) and np.all(obs[loops, :-1] == 0)
    assert np.all(dones == 0)  # every DAC transition bootstraps
    # Time limits only (no wall): 2 full episodes per env, no absorbing state anywhere.
    obs, nxt, _, dones, buf = _collect(make_task("pointmass").env, 2 * 128 * 4, 0.0)
    assert len(obs) == 1024 and buf.absorbing_added == 0
    assert np.all(obs[:, -1] == 0) and np.all(nxt[:, -1] == 0) and np.all(dones == 0)


def test_target_zeroes_the_next_action_on_absorbing_states():
    # Critics that read only the action (Q'(s, a) = sum(a) + 1) and a zero reward make the
    # target gamma * (sum(a') + 1): with a' zeroed on absorbing s' it is exactly gamma.
    from stable_baselines3.common.type_aliases import ReplayBufferSamples
    cfg = DACConfig(actor_hidden=(8,), critic_hidden=(8,), disc_hidden=(8,), num_envs=2,
                    steps_per_collect=2)
    venv = dac.AbsorbingWrapper(BraxVecEnv(make_task("pointmass").env, 2, 128))
    model = dac.build_model(venv, cfg, np.zeros((1, 3), np.float32),
                            np.zeros((1, 1), np.float32), seed=0)
    model.critic_target = lambda s, a: (a.sum(-1, keepdim=True) + 1,) * 2
    model.actor_target = lambda s: torch.full((len(s), 1), 0.7)
    model.discriminator.reward = lambda s, a: torch.zeros(len(s), 1)
    model.target_policy_noise = 0.0
    s_abs = torch.as_tensor(dac.absorbing_state(2))
    s_real = torch.tensor([0.5, 0.1, 0.0])
    obs = torch.stack([s_real, s_real, s_abs])
    nxt = torch.stack([s_real, s_abs, s_abs])            # normal, terminal, self-loop
    data = ReplayBufferSamples(obs, torch.zeros(3, 1), nxt, torch.zeros(3, 1),
                               torch.zeros(3, 1))
    _, target = model.td_target(data)
    np.testing.assert_allclose(target.numpy().ravel(), 0.99 * np.array([1.7, 1.0, 1.0]),
                               rtol=1e-6)


def test_arithmetic_bound_of_the_speed_ratio_by_hand():
    """Tiny nets, batch 1: actor (2,2,1) = 6 MACs, critic and D (3,2,1) = 8 each.
    TD3 = 6 + 2*8 + 3*2*8 + 3*(6+8) = 112; DAC adds the reward (8) and a D update:
    3*2*8 (fwd + bwd on a policy and an expert row) + 6*8 (gradient penalty) = 96."""
    from benchmarks.sb3_speed import dac_arithmetic_ratio
    c = DACConfig(actor_hidden=(2,), critic_hidden=(2,), disc_hidden=(2,), batch_size=1,
                  disc_batch=1, policy_delay=1)
    assert dac_arithmetic_ratio(1, 1, c) == pytest.approx(112 / (112 + 8 + 96))
    c2 = DACConfig(actor_hidden=(2,), critic_hidden=(2,), disc_hidden=(2,), batch_size=1,
                   disc_batch=1, policy_delay=1, disc_every=2)
    assert dac_arithmetic_ratio(1, 1, c2) == pytest.approx(112 / (112 + 8 + 48))


@pytest.mark.parametrize("every,expected", [(1, 256), (3, 85)])
def test_discriminator_updates_once_per_disc_every_td3_updates(every, expected):
    """disc_every=1 is the original (one D update per TD3 update); 3 runs 256/3 -> 85 D
    updates over two 128-update calls (the remainder carries to the next call)."""
    cfg = DACConfig(actor_hidden=(8,), critic_hidden=(8,), disc_hidden=(8,), num_envs=4,
                    steps_per_collect=8, disc_every=every, disc_batch=4, batch_size=4)
    venv = dac.AbsorbingWrapper(BraxVecEnv(make_task("pointmass").env, 4, 128, seed=0))
    model = dac.build_model(venv, cfg, np.zeros((4, 3), np.float32),
                            np.zeros((4, 1), np.float32), seed=0)
    model.learn(total_timesteps=32)          # random actions fill the buffer, no updates
    calls = []
    real = model.discriminator.update
    model.discriminator.update = lambda *a, **k: calls.append(k["stats"]) or real(*a, **k)
    model.train(128, cfg.batch_size)
    model.train(128, cfg.batch_size)
    assert model.disc_updates == len(calls) == expected
    assert model.critic_updates == 256
    assert sum(calls) == 2                  # loss statistics once per call
    assert np.isfinite(model.metrics["disc/loss"])
    assert model.metrics["train/disc_updates"] == expected
