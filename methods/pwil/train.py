"""PWIL (Dadashi et al. 2021) on one demo: SB3's TD3 on the greedy-Wasserstein reward.

The reward is computed online from (o_t, a_t) before each env step (as the original), by a
VecEnv wrapper around the batched brax env; the learner is plain SB3 TD3 (n-step replay),
so the imitation reward is the only thing PWIL adds to the RL loop.
"""
from __future__ import annotations

import numpy as np
from stable_baselines3 import TD3
from stable_baselines3.common.buffers import NStepReplayBuffer
from stable_baselines3.common.vec_env import VecEnvWrapper

from bench.api import TrainResult
from methods.common.sb3 import (BraxVecEnv, learn_within_budget, seed_everything,
                                set_torch_threads, td3_kwargs, torch_policy)
from methods.pwil.config import PWILConfig
from methods.pwil.rewarder import PWILRewarder


def features(obs: np.ndarray, actions: np.ndarray | None, use_actions: bool) -> np.ndarray:
    return np.concatenate([obs, actions], -1) if use_actions else np.asarray(obs)


def expert_atoms(demo, config: PWILConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(atoms, demo obs s_0..s_T, demo actions) of the top demo, subsampled for the atoms."""
    obs = np.asarray(demo.obs[0], np.float32)
    act = np.asarray(demo.actions[0], np.float32)
    idx = np.arange(0, len(act), config.subsampling)
    return features(obs[idx], act[idx], config.use_actions), obs, act


class PWILReward(VecEnvWrapper):
    """Replaces the (hidden) env reward with PWIL's; resets the coupling at episode ends."""

    def __init__(self, venv, rewarder: PWILRewarder, use_actions: bool):
        super().__init__(venv)
        self.rewarder = rewarder
        self.use_actions = use_actions
        self._obs = None
        self._rewards = None

    def reset(self):
        self._obs = self.venv.reset()
        self.rewarder.reset()
        return self._obs

    def step_async(self, actions):
        self._rewards = self.rewarder.rewards(features(self._obs, actions, self.use_actions))
        self.venv.step_async(actions)

    def step_wait(self):
        obs, _, dones, infos = self.venv.step_wait()
        self.rewarder.reset(dones)
        self._obs = obs
        return obs, self._rewards.astype(np.float32), dones, infos


def prefill(model: TD3, demo_obs, demo_act, reward: float, count: int) -> int:
    """Put `count` demo transitions (the demo repeated, in order, in every env column so that
    n-step returns stay inside one demo pass) into replay with a constant reward."""
    buf, n = model.replay_buffer, model.n_envs
    T = len(demo_act)
    rows = int(np.ceil(count / n))
    for r in range(rows):
        t = r % T
        last = t == T - 1
        buf.add(np.repeat(demo_obs[t][None], n, 0), np.repeat(demo_obs[t + 1][None], n, 0),
                np.repeat(demo_act[t][None], n, 0), np.full(n, reward, np.float32),
                np.full(n, last), [{"TimeLimit.truncated": last}] * n)
    return rows * n


def build_model(env, config: PWILConfig, seed: int) -> TD3:
    """The PWIL learner: plain SB3 TD3 with n-step replay (the reward arrives through the env
    wrapper)."""
    return TD3(**td3_kwargs(env, config, config.learning_rate, seed),
               replay_buffer_class=NStepReplayBuffer,
               replay_buffer_kwargs=dict(n_steps=config.n_step, gamma=config.gamma))


def make_learner(env, episode_length: int, demo, config: PWILConfig, seed: int):
    """(model, atoms, prefilled): TD3 on `num_envs` copies of the (gated) brax env rewarded
    by PWIL, replay prefilled with demo transitions."""
    atoms, demo_obs, demo_act = expert_atoms(demo, config)
    rewarder = PWILRewarder(atoms, config.num_envs, config.horizon, config.alpha, config.beta)
    venv = PWILReward(BraxVecEnv(env, config.num_envs, episode_length, seed), rewarder,
                      config.use_actions)
    model = build_model(venv, config, seed)
    filled = prefill(model, demo_obs, demo_act, config.alpha, config.prefill)
    return model, atoms, filled


def train(task, demo, config: PWILConfig, ctx, seed: int) -> TrainResult:
    set_torch_threads(config.torch_threads)
    seed_everything(seed)
    if config.horizon != task.episode_length:
        raise ValueError(f"pwil horizon T={config.horizon} must equal task {task.name!r}'s "
                         f"episode length {task.episode_length} (the agent's mass is 1/T per "
                         f"step); fix: --set horizon={task.episode_length}")
    model, atoms, filled = make_learner(task.env, task.episode_length, demo, config, seed)

    def policy():
        return torch_policy(model.actor, noise_std=config.exploration_noise)

    def metrics():
        return {"train/replay_size": model.replay_buffer.size() * model.n_envs}

    cb = learn_within_budget(model, ctx, policy, config.report_every, metrics)
    return TrainResult(policy(), env_steps=int(model.num_timesteps),
                       metrics={**cb.throughput(), **metrics(), "train/prefilled": filled,
                                "train/expert_atoms": len(atoms)})
