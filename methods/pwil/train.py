"""PWIL (Dadashi et al. 2021) on one demo: SB3's TD3 on the greedy-Wasserstein reward.

The reward is computed online from (o_t, a_t) before each env step (as the original), by a
VecEnv wrapper around the batched brax env; the learner is plain SB3 TD3 (n-step replay),
so the imitation reward is the only thing PWIL adds to the RL loop. The demo's transitions
(reward alpha) are stored once and sampled in the proportion of the original's prefill
scaled to the run's budget (`DemoMixReplay`).
"""
from __future__ import annotations

import copy
from typing import Callable

import numpy as np
import torch
from stable_baselines3 import TD3
from stable_baselines3.common.buffers import NStepReplayBuffer
from stable_baselines3.common.type_aliases import ReplayBufferSamples
from stable_baselines3.common.vec_env import VecEnvWrapper

from bench.api import TrainResult
from methods.common.sb3 import (BraxVecEnv, ObsNormalizer, learn_within_budget,
                                obs_normalizer, seed_everything, set_torch_threads, td3_kwargs,
                                torch_policy)
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
    """Replaces the (hidden) env reward with PWIL's; resets the coupling at episode ends.
    `stats()` says what the reward paid since it was last read: per step, and per finished
    episode (its PWIL return, at most alpha x T, and its length)."""

    def __init__(self, venv, rewarder: PWILRewarder, use_actions: bool,
                 normalizer: ObsNormalizer | None = None):
        super().__init__(venv)
        self.rewarder = rewarder
        self.use_actions = use_actions
        self.normalizer = normalizer
        self._obs = None
        self._rewards = None
        self._ep_return = np.zeros(self.num_envs)
        self._ep_length = np.zeros(self.num_envs, np.int64)
        self._clear_stats()

    def _clear_stats(self) -> None:
        self._paid, self._steps = 0.0, 0
        self._returns: list[float] = []
        self._lengths: list[int] = []

    def stats(self) -> dict:
        """Mean PWIL reward per env step, mean PWIL return and length of the episodes that
        ended, since the last call (keys only where there is something to average)."""
        out = {}
        if self._steps:
            out["train/pwil_reward_mean"] = self._paid / self._steps
        if self._returns:
            out["train/pwil_episode_return"] = float(np.mean(self._returns))
            out["train/episode_length"] = float(np.mean(self._lengths))
        self._clear_stats()
        return out

    STATE = ("_obs", "_rewards", "_ep_return", "_ep_length", "_paid", "_steps", "_returns",
             "_lengths")

    def state_dict(self) -> dict:
        """The coupling's remaining expert mass per env and the episodes' running sums, for a
        checkpoint (`learner_state`)."""
        return {"weights": self.rewarder.weights.copy(),
                **{k: copy.deepcopy(getattr(self, k)) for k in self.STATE}}

    def load_state_dict(self, state: dict) -> None:
        self.rewarder.weights[:] = state["weights"]
        for k in self.STATE:
            setattr(self, k, copy.deepcopy(state[k]))

    def reset(self):
        self._obs = self.venv.reset()
        self.rewarder.reset()
        self._ep_return[:] = 0.0
        self._ep_length[:] = 0
        if self.normalizer is not None:
            self.normalizer.update(self._obs)
        return self._obs

    def step_async(self, actions):
        self._rewards = self.rewarder.rewards(features(self._obs, actions, self.use_actions))
        self.venv.step_async(actions)

    def step_wait(self):
        obs, _, dones, infos = self.venv.step_wait()
        self.rewarder.reset(dones)
        self._paid += float(self._rewards.sum())
        self._steps += len(self._rewards)
        self._ep_return += self._rewards
        self._ep_length += 1
        for i in np.flatnonzero(dones):
            self._returns.append(float(self._ep_return[i]))
            self._lengths.append(int(self._ep_length[i]))
        self._ep_return[dones] = 0.0
        self._ep_length[dones] = 0
        if self.normalizer is not None:
            self.normalizer.update(obs)
        self._obs = obs
        return obs, self._rewards.astype(np.float32), dones, infos


class DemoMixReplay(NStepReplayBuffer):
    """The agent's n-step replay plus the demo's T transitions (reward alpha) stored once. A
    batch draws each row from the demo with probability D / (D + A), where A is the number of
    agent transitions stored and D = `demo_count()`, the number of demo transitions the
    replay stands for: the same distribution as one buffer prefilled with D copies of the
    demo's transitions, without storing them. Demo rows' n-step returns stay inside the
    demo (its last step is a time-limit end)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.demo: NStepReplayBuffer | None = None
        self.demo_count: Callable[[], float] = lambda: 0.0
        self.demo_rows_sampled = 0

    def set_demo(self, demo_obs: np.ndarray, demo_act: np.ndarray, reward: float,
                 demo_count: Callable[[], float]) -> None:
        T = len(demo_act)
        buf = NStepReplayBuffer(T, self.observation_space, self.action_space, self.device,
                                n_envs=1, n_steps=self.n_steps, gamma=self.gamma)
        for t in range(T):
            last = t == T - 1
            buf.add(demo_obs[t][None], demo_obs[t + 1][None], demo_act[t][None],
                    np.array([reward], np.float32), np.array([last]),
                    [{"TimeLimit.truncated": last}])
        self.demo, self.demo_count = buf, demo_count

    def demo_share(self) -> float:
        """The probability that a sampled row is a demo transition."""
        if self.demo is None:
            return 0.0
        d, a = float(self.demo_count()), float(self.size() * self.n_envs)
        return d / (d + a) if d + a > 0 else 0.0

    def sample(self, batch_size: int, env=None) -> ReplayBufferSamples:
        k = int(np.random.binomial(batch_size, self.demo_share()))
        if k == 0:
            return super().sample(batch_size, env)
        self.demo_rows_sampled += k
        demo = self.demo._get_samples(np.random.randint(0, self.demo.buffer_size, size=k), env)
        if k == batch_size:
            return demo
        agent = super().sample(batch_size - k, env)
        return ReplayBufferSamples(*(torch.cat([a, b]) for a, b in zip(agent, demo)))


def demo_count(config: PWILConfig, env_steps: Callable[[], int],
               spent: Callable[[int], float] | None) -> Callable[[], float]:
    """D, the demo transitions the replay stands for: min(prefill, prefill_fraction x the
    run's env steps), the run's env steps read from the budget's spent fraction (exact on an
    env-step budget, projected from the rate so far on a seconds budget); `prefill` where
    there is no budget to read."""
    if spent is None:
        return lambda: float(config.prefill)

    def count() -> float:
        steps = env_steps()
        frac = spent(steps)
        if frac <= 0:
            return float(config.prefill)
        return float(min(config.prefill, config.prefill_fraction * steps / frac))
    return count


def build_model(env, config: PWILConfig, seed: int,
                normalizer: ObsNormalizer | None = None) -> TD3:
    """The PWIL learner: plain SB3 TD3 with n-step replay (the reward arrives through the env
    wrapper); the demo part of the replay is set by `make_learner`."""
    return TD3(**td3_kwargs(env, config, config.learning_rate, seed, normalizer),
               replay_buffer_class=DemoMixReplay,
               replay_buffer_kwargs=dict(n_steps=config.n_step, gamma=config.gamma))


def make_learner(env, episode_length: int, demo, config: PWILConfig, seed: int,
                 spent: Callable[[int], float] | None = None):
    """(model, atoms): TD3 on `num_envs` copies of the (gated) brax env rewarded by PWIL,
    its replay mixing in the demo's transitions (`DemoMixReplay`, D from `demo_count`)."""
    atoms, demo_obs, demo_act = expert_atoms(demo, config)
    rewarder = PWILRewarder(atoms, config.num_envs, config.horizon, config.alpha, config.beta,
                            scale_floor=config.scale_floor)
    normalizer = obs_normalizer(config, demo_obs[:-1])
    venv = PWILReward(BraxVecEnv(env, config.num_envs, episode_length, seed), rewarder,
                      config.use_actions, normalizer)
    model = build_model(venv, config, seed, normalizer)
    model.replay_buffer.set_demo(demo_obs, demo_act, config.alpha,
                                 demo_count(config, lambda: model.num_timesteps, spent))
    return model, atoms


def train(task, demo, config: PWILConfig, ctx, seed: int) -> TrainResult:
    set_torch_threads(config.torch_threads)
    seed_everything(seed)
    if config.horizon != task.episode_length:
        raise ValueError(f"pwil horizon T={config.horizon} must equal task {task.name!r}'s "
                         f"episode length {task.episode_length} (the agent's mass is 1/T per "
                         f"step); fix: --set horizon={task.episode_length}")
    model, atoms = make_learner(task.env, task.episode_length, demo, config, seed, ctx.spent)

    def policy():
        return torch_policy(model.actor, noise_std=config.exploration_noise)

    def metrics():
        buf = model.replay_buffer
        return {"train/replay_size": buf.size() * model.n_envs,
                "train/demo_count": buf.demo_count(), "train/demo_share": buf.demo_share(),
                "train/demo_rows_sampled": buf.demo_rows_sampled, **model.env.stats()}

    cb = learn_within_budget(model, ctx, policy, config.report_every, metrics)
    return TrainResult(policy(), env_steps=int(model.num_timesteps),
                       metrics={**cb.metrics(), "train/expert_atoms": len(atoms)})
