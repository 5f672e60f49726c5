"""Stable-Baselines3 glue shared by the RL-based imitation methods (DAC, PWIL).

- `BraxVecEnv`: an SB3 VecEnv over B copies of a task, stepped by ONE jitted, vmapped brax
  call per vector step (one device->host conversion per step). Auto-reset happens inside the
  jitted call (and only when some env finished). True termination and time-limit truncation
  stay distinct: `infos[i]["TimeLimit.truncated"]` is True only for the time limit, and
  `infos[i]["terminal_observation"]` holds the pre-reset observation (SB3's convention).
- `BraxGymEnv`: the same task as a single gymnasium.Env (reset/step, terminated vs truncated).
- `BudgetCallback`: stops SB3's learn() when the harness budget is spent and reports to the
  RunContext (which evaluates with the method's clock paused), with env-steps/s and updates/s.
- `torch_policy`: a torch module snapshot as a harness 'host' Policy for the shared evaluator.
- `ObsNormalizer` / `NormalizedObs`: running observation statistics shared by the actor, the
  critics (and DAC's discriminator), applied inside the networks so that the replay keeps
  raw observations and every sample is normalized with the current statistics.
- `KeepLastLogger` / `recent_q`: the learner's state beside its score in every curve point
  (critic and actor losses, the critic's value of what the agent did last), read without
  touching any random stream, so that a run that fails late can be read from its record.

The env handed in is the method's gated TaskView env: without Uses(true_reward) its rewards
are NaN, so a learner can only ever train on the imitation reward its method computes.
"""
from __future__ import annotations

from typing import Callable

import gymnasium as gym
import jax
import jax.numpy as jnp
import numpy as np
import torch
from stable_baselines3.common.callbacks import BaseCallback
from stable_baselines3.common.noise import NormalActionNoise
from stable_baselines3.common.logger import Logger
from stable_baselines3.common.torch_layers import BaseFeaturesExtractor
from stable_baselines3.common.vec_env import VecEnv

from bench.api import Policy
from tasks.core import env_obs_size, reset_done


def _spaces(env):
    obs = gym.spaces.Box(-np.inf, np.inf, (env_obs_size(env),), np.float32)
    act = gym.spaces.Box(-1.0, 1.0, (int(env.action_size),), np.float32)
    return obs, act


class BraxVecEnv(VecEnv):
    """`num_envs` copies of a brax env with episodes of `episode_length` steps."""

    render_mode = None

    def __init__(self, env, num_envs: int, episode_length: int, seed: int = 0):
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        obs_space, act_space = _spaces(env)
        super().__init__(num_envs, obs_space, act_space)
        self.episode_length = int(episode_length)
        n, T = num_envs, self.episode_length

        def reset(key):
            key, sub = jax.random.split(key)
            return jax.vmap(env.reset)(jax.random.split(sub, n)), jnp.zeros(n, jnp.int32), key

        def step(state, t, key, action):
            nxt = jax.vmap(env.step)(state, action)
            terminated = nxt.done > 0
            t1 = t + 1
            truncated = (t1 >= T) & ~terminated
            done = terminated | truncated
            key, sub = jax.random.split(key)
            merged = reset_done(env, nxt, done, sub)
            out = (merged.obs, nxt.obs, nxt.reward, terminated, truncated)
            return merged, jnp.where(done, 0, t1), key, out

        self._reset_fn = jax.jit(reset)
        self._step_fn = jax.jit(step)
        self._key = jax.random.PRNGKey(seed)
        self._carry = None
        self._actions = None

    def seed(self, seed: int | None = None):
        if seed is not None:
            self._key = jax.random.PRNGKey(seed)
        return [seed] * self.num_envs

    def state_dict(self) -> dict:
        """Where the envs are (every leaf of their states, their step counters) and the key:
        enough to go on exactly (`load_state_dict`, into an env of the same task)."""
        leaves = (None if self._carry is None
                  else [np.asarray(x) for x in jax.tree_util.tree_leaves(self._carry)])
        return {"carry": leaves, "key": np.asarray(self._key)}

    def load_state_dict(self, state: dict) -> None:
        self._key = jnp.asarray(state["key"])
        if state["carry"] is None:
            self._carry = None
            return
        shape = jax.eval_shape(self._reset_fn, self._key)[:2]  # the (state, t) structure
        treedef = jax.tree_util.tree_structure(shape)
        self._carry = jax.tree_util.tree_unflatten(treedef,
                                                   [jnp.asarray(x) for x in state["carry"]])

    def reset(self):
        state, t, self._key = self._reset_fn(self._key)
        self._carry = (state, t)
        return np.asarray(state.obs, np.float32)

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = jnp.asarray(np.asarray(actions, np.float32).reshape(self.num_envs, -1))

    def step_wait(self):
        if self._carry is None:
            raise RuntimeError("BraxVecEnv.step before reset(); call reset() first")
        state, t = self._carry
        state, t, self._key, out = self._step_fn(state, t, self._key, self._actions)
        self._carry = (state, t)
        obs, term_obs, reward, terminated, truncated = jax.device_get(out)
        dones = terminated | truncated
        infos = [{} for _ in range(self.num_envs)]
        for i in np.flatnonzero(dones):
            infos[i] = {"terminal_observation": np.asarray(term_obs[i], np.float32),
                        "TimeLimit.truncated": bool(truncated[i]),
                        "terminated": bool(terminated[i])}
        return (np.asarray(obs, np.float32), np.asarray(reward, np.float32), dones, infos)

    def close(self) -> None:
        pass

    def get_attr(self, attr_name, indices=None):
        return [getattr(self, attr_name)] * len(self._indices(indices))

    def set_attr(self, attr_name, value, indices=None) -> None:
        setattr(self, attr_name, value)

    def env_method(self, method_name, *args, indices=None, **kwargs):
        raise AttributeError(f"BraxVecEnv has no per-env method {method_name!r}")

    def env_is_wrapped(self, wrapper_class, indices=None):
        return [False] * len(self._indices(indices))

    def _indices(self, indices):
        if indices is None:
            return range(self.num_envs)
        return [indices] if isinstance(indices, int) else indices


class BraxGymEnv(gym.Env):
    """One copy of a brax env as a gymnasium.Env (no auto-reset; time limit = truncated)."""

    metadata = {"render_modes": []}

    def __init__(self, env, episode_length: int):
        self.observation_space, self.action_space = _spaces(env)
        self.episode_length = int(episode_length)
        self._reset = jax.jit(env.reset)
        self._step = jax.jit(env.step)
        self._state = None
        self._t = 0
        self._key = jax.random.PRNGKey(0)

    def reset(self, *, seed: int | None = None, options=None):
        super().reset(seed=seed)
        if seed is not None:
            self._key = jax.random.PRNGKey(seed)
        self._key, sub = jax.random.split(self._key)
        self._state = self._reset(sub)
        self._t = 0
        return np.asarray(self._state.obs, np.float32), {}

    def step(self, action):
        if self._state is None:
            raise RuntimeError("BraxGymEnv.step before reset(); call reset() first")
        self._state = self._step(self._state, jnp.asarray(action, jnp.float32))
        self._t += 1
        terminated = bool(self._state.done > 0)
        truncated = (self._t >= self.episode_length) and not terminated
        return (np.asarray(self._state.obs, np.float32), float(self._state.reward), terminated,
                truncated, {})


class ObsNormalizer:
    """Running mean and variance of the first `dim` features of an observation (Chan's
    parallel update, float64 on the host), applied as clip((x - mean) / sqrt(var + eps),
    -clip, clip). Features past `dim` (DAC's absorbing indicator) pass through unchanged.

    The statistics live in two float32 tensors that every `NormalizedObs` and the
    discriminator share (updated in place), so one update reaches all of them and a module's
    `state_dict()` (an evaluation snapshot) holds the values of that moment. They start from
    the demo's observations (information every imitation method is given) and take in every
    observation the learner collects."""

    def __init__(self, dim: int, init: np.ndarray | None = None, clip: float = 10.0,
                 eps: float = 1e-4, device: str = "cpu"):
        if clip <= 0 or eps <= 0:
            raise ValueError(f"clip and eps must be > 0, got clip={clip}, eps={eps}")
        self.dim, self.clip, self.eps = int(dim), float(clip), float(eps)
        self.count = 0.0
        self._mean = np.zeros(self.dim)
        self._m2 = np.zeros(self.dim)
        # On the learner's device from the start: moving a module there keeps these tensors.
        self.mean = torch.zeros(self.dim, device=device)
        self.inv_std = torch.ones(self.dim, device=device) / np.sqrt(1.0 + self.eps)
        if init is not None:
            self.update(init)

    def update(self, x: np.ndarray) -> None:
        x = np.asarray(x, np.float64).reshape(-1, self.dim)
        n = len(x)
        if n == 0:
            return
        mean, m2 = x.mean(0), ((x - x.mean(0)) ** 2).sum(0)
        total = self.count + n
        delta = mean - self._mean
        self._mean = self._mean + delta * n / total
        self._m2 = self._m2 + m2 + delta ** 2 * self.count * n / total
        self.count = total
        self._publish()

    def _publish(self) -> None:
        """Write the host statistics into the tensors the networks read."""
        self.mean.copy_(torch.from_numpy(self._mean.astype(np.float32)))
        self.inv_std.copy_(torch.from_numpy(
            (1.0 / np.sqrt(self._m2 / self.count + self.eps)).astype(np.float32)))

    @property
    def var(self) -> np.ndarray:
        return self._m2 / max(self.count, 1.0)

    def state_dict(self) -> dict:
        return {"count": self.count, "mean": self._mean.copy(), "m2": self._m2.copy()}

    def load_state_dict(self, state: dict) -> None:
        self.count = state["count"]
        self._mean, self._m2 = state["mean"].copy(), state["m2"].copy()
        if self.count > 0:  # as `update` leaves them
            self._publish()

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        return normalize_features(x, self.mean, self.inv_std, self.clip)


def obs_normalizer(config, demo_obs: np.ndarray) -> ObsNormalizer | None:
    """The learner's observation normalizer on its config's device, started from the demo's
    observations (rows of features); None where the config's `normalize_obs` is off."""
    if not config.normalize_obs:
        return None
    demo_obs = np.asarray(demo_obs, np.float32)
    return ObsNormalizer(demo_obs.shape[-1], init=demo_obs.reshape(-1, demo_obs.shape[-1]),
                         device=torch_device(config.device))


def normalize_features(x: torch.Tensor, mean: torch.Tensor, inv_std: torch.Tensor,
                       clip: float) -> torch.Tensor:
    d = mean.shape[-1]
    z = ((x[..., :d] - mean) * inv_std).clamp(-clip, clip)
    return z if x.shape[-1] == d else torch.cat([z, x[..., d:]], -1)


class NormalizedObs(BaseFeaturesExtractor):
    """SB3 features extractor: the observation normalized by a shared `ObsNormalizer`. Its
    two statistics are buffers of this module that are the normalizer's own tensors."""

    def __init__(self, observation_space: gym.spaces.Box, normalizer: ObsNormalizer):
        super().__init__(observation_space, int(observation_space.shape[0]))
        self.clip = normalizer.clip
        self.register_buffer("obs_mean", normalizer.mean, persistent=True)
        self.register_buffer("obs_inv_std", normalizer.inv_std, persistent=True)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return normalize_features(obs.float(), self.obs_mean, self.obs_inv_std, self.clip)


def torch_policy(module: torch.nn.Module, obs_fn: Callable[[np.ndarray], np.ndarray] = None,
                 noise_std: float = 0.0) -> Policy:
    """Snapshot `module` (obs -> action in [-1, 1]) as a 'host' Policy.

    Parameters are copied to numpy (the harness checks them for NaN); acting runs the module
    functionally on those arrays (no copy back). `obs_fn` maps env observations to the
    module's input (e.g. DAC's absorbing indicator). Stochastic evaluation adds the method's
    exploration noise `noise_std` and clips, as the learner acts while collecting."""
    params = {k: v.detach().cpu().numpy().copy() for k, v in module.state_dict().items()}
    return Policy(act=_TorchAct(module, obs_fn, noise_std), params=params, kind="host")


class _TorchAct:
    def __init__(self, module, obs_fn, noise_std):
        self.module, self.obs_fn, self.noise_std = module, obs_fn, noise_std

    def __call__(self, params, obs, rng, deterministic):
        x = np.array(obs, np.float32)  # a writable copy (jax hands out read-only arrays)
        if self.obs_fn is not None:
            x = self.obs_fn(x)
        device = next(iter(self.module.state_dict().values())).device
        tensors = {k: torch.from_numpy(v).to(device) for k, v in params.items()}
        with torch.no_grad():
            a = torch.func.functional_call(self.module, tensors,
                                           (torch.from_numpy(x).to(device),))
        a = a.cpu().numpy()
        if not deterministic and self.noise_std > 0:
            a = np.clip(a + rng.normal(0.0, self.noise_std, a.shape), -1.0, 1.0)
        return a.astype(np.float32)


class KeepLastLogger(Logger):
    """SB3's logger with no output that keeps the last value of every key past each dump
    (SB3 dumps, and clears, every few episodes), so a report reads the learner's latest
    losses whenever it comes."""

    def __init__(self):
        super().__init__(folder=None, output_formats=[])
        self.last: dict = {}

    def dump(self, step: int = 0) -> None:
        self.last.update(self.name_to_value)
        super().dump(step)

    def values(self) -> dict:
        return {**self.last, **self.name_to_value}


LOSSES = ("train/critic_loss", "train/actor_loss")


def learner_losses(model) -> dict:
    """The last critic and actor losses SB3's TD3 logged (none before its first update)."""
    logger = model.logger if model._custom_logger else None
    vals = logger.values() if isinstance(logger, KeepLastLogger) else {}
    return {k: float(vals[k]) for k in LOSSES if k in vals}


@torch.no_grad()
def recent_q(model, k: int = 256, real: Callable[[np.ndarray], np.ndarray] | None = None
             ) -> dict:
    """{'train/q_recent': mean Q1(s, a)} over the last `k` agent transitions stored in the
    replay (read in place: no sampling, so no random stream moves), `real` keeping the rows
    it marks True (DAC: not absorbing); {} while the replay holds none."""
    buf = model.replay_buffer
    n_rows = buf.size()
    if n_rows == 0:
        return {}
    rows = (buf.pos - 1 - np.arange(min(n_rows, -(-k // buf.n_envs)))) % buf.buffer_size
    obs = buf.observations[rows].reshape(-1, buf.obs_shape[-1])[:k]
    act = buf.actions[rows].reshape(-1, buf.action_dim)[:k]
    if real is not None:
        keep = real(obs)
        obs, act = obs[keep], act[keep]
    if len(obs) == 0:
        return {}
    q = model.critic.q1_forward(torch.as_tensor(obs, device=model.device),
                                torch.as_tensor(act, device=model.device))
    return {"train/q_recent": float(q.mean())}


class BudgetCallback(BaseCallback):
    """Ends learn() when the harness budget is spent; reports to the RunContext every
    `report_every` env steps with throughput metrics (env-steps/s, updates/s), the learner's
    last losses and `recent_q`, and the method's own metrics (which win on a shared key)."""

    def __init__(self, ctx, make_policy: Callable[[], Policy], report_every: int,
                 metrics_fn: Callable[[], dict] = lambda: {},
                 q_real: Callable[[np.ndarray], np.ndarray] | None = None):
        super().__init__()
        self.ctx = ctx
        self.q_real = q_real
        self.make_policy = make_policy
        self.report_every = int(report_every)
        self.metrics_fn = metrics_fn
        self._next = 0
        self._t0 = None

    def _on_training_start(self) -> None:
        if self._t0 is None:  # learn() runs once per collection (`learn_within_budget`)
            self._t0 = self.ctx.elapsed()

    def throughput(self) -> dict:
        dt = max(self.ctx.elapsed() - (self._t0 or 0.0), 1e-9)
        return {"speed/env_steps_per_s": self.model.num_timesteps / dt,
                "speed/updates_per_s": self.model._n_updates / dt,
                "train/updates": self.model._n_updates}

    def metrics(self) -> dict:
        return {**self.throughput(), **learner_losses(self.model),
                **recent_q(self.model, real=self.q_real), **self.metrics_fn()}

    def _on_step(self) -> bool:
        steps = self.model.num_timesteps
        if steps >= self._next:
            self._next = steps + self.report_every
            self.ctx.report(self.make_policy(), env_steps=steps, metrics=self.metrics())
        return not self.ctx.should_stop(steps)


def check_collection(config) -> None:
    """A collection of `steps_per_collect` env steps must be whole vector steps."""
    if config.steps_per_collect % config.num_envs:
        raise ValueError(f"steps_per_collect ({config.steps_per_collect}) must be a multiple "
                         f"of num_envs ({config.num_envs})")


def td3_kwargs(env, config, learning_rate: float, seed: int,
               normalizer: ObsNormalizer | None = None) -> dict:
    """SB3 TD3 arguments the TD3-based learners share, from their configs' common fields:
    `steps_per_collect` env steps over `num_envs` envs per collection, then
    updates_per_step x that many updates; Gaussian exploration; actor/critic sizes; the
    observation normalizer (if any) inside the actor and critics; the config's device."""
    act_dim = env.action_space.shape[0]
    extractor = ({} if normalizer is None else
                 dict(features_extractor_class=NormalizedObs,
                      features_extractor_kwargs=dict(normalizer=normalizer)))
    return dict(
        policy="MlpPolicy", env=env, learning_rate=learning_rate,
        buffer_size=config.buffer_size, learning_starts=config.learning_starts,
        batch_size=config.batch_size, tau=config.tau, gamma=config.gamma,
        train_freq=(config.steps_per_collect // config.num_envs, "step"),
        gradient_steps=max(1, round(config.updates_per_step * config.steps_per_collect)),
        action_noise=NormalActionNoise(np.zeros(act_dim),
                                       config.exploration_noise * np.ones(act_dim)),
        policy_kwargs=dict(net_arch=dict(pi=list(config.actor_hidden),
                                         qf=list(config.critic_hidden)), **extractor),
        seed=seed, device=torch_device(getattr(config, "device", "cpu")), verbose=0)


def torch_device(name: str) -> str:
    """The torch device for a learner's `device` field: 'cpu', 'cuda', or 'auto' (CUDA when
    torch sees a GPU, else the CPU)."""
    if name not in ("auto", "cpu", "cuda"):
        raise ValueError(f"device must be 'auto', 'cpu' or 'cuda', got {name!r}")
    if name == "auto":
        return "cuda" if torch.cuda.is_available() else "cpu"
    return name


REPLAY_ARRAYS = ("observations", "next_observations", "actions", "rewards", "dones",
                 "timeouts")
REPLAY_COUNTERS = ("pos", "full", "absorbing_added", "demo_rows_sampled")


def _replay_state(buf) -> dict:
    n = buf.buffer_size if buf.full else buf.pos  # only the rows written
    return {**{k: getattr(buf, k)[:n].copy() for k in REPLAY_ARRAYS
               if getattr(buf, k, None) is not None},
            **{k: getattr(buf, k) for k in REPLAY_COUNTERS if hasattr(buf, k)}}


def _load_replay_state(buf, state: dict) -> None:
    for k in REPLAY_ARRAYS:
        if k in state:
            getattr(buf, k)[:len(state[k])] = state[k]
    for k in REPLAY_COUNTERS:
        if k in state:
            setattr(buf, k, state[k])


def _env_chain(model):
    """The model's VecEnv and every env it wraps (outermost first)."""
    env = model.env
    while env is not None:
        yield env
        env = getattr(env, "venv", None)


def _has_state(env) -> bool:
    # On the class: a VecEnvWrapper hands unknown attributes to the env it wraps.
    return getattr(type(env), "state_dict", None) is not None


def _normalizer(model) -> ObsNormalizer | None:
    """The observation normalizer a wrapper of the model's env updates (None: off)."""
    return next((e.normalizer for e in _env_chain(model)
                 if getattr(e, "normalizer", None) is not None), None)


def learner_state(model) -> dict:
    """Everything a TD3-based learner needs to go on exactly as if never stopped: networks
    and optimizers, counters, the replay, the envs (and their wrappers' state), the
    observation normalizer, the learner's own extras (`extra_state`), and every random
    stream it draws from (numpy's global, torch's, the action space's)."""
    norm = _normalizer(model)
    return {
        "policy": {k: v.detach().cpu().clone() for k, v in model.policy.state_dict().items()},
        "actor_opt": model.actor.optimizer.state_dict(),
        "critic_opt": model.critic.optimizer.state_dict(),
        "counters": {k: getattr(model, k) for k in ("num_timesteps", "_n_updates",
                                                    "_episode_num")},
        "last_obs": None if model._last_obs is None else np.array(model._last_obs),
        "replay": _replay_state(model.replay_buffer),
        "envs": [e.state_dict() if _has_state(e) else None for e in _env_chain(model)],
        "normalizer": None if norm is None else norm.state_dict(),
        "extra": model.extra_state() if hasattr(model, "extra_state") else None,
        "rng": {"numpy": np.random.get_state(), "torch": torch.get_rng_state(),
                "cuda": torch.cuda.get_rng_state_all() if torch.cuda.is_available() else None,
                "action_space": model.action_space.np_random.bit_generator.state},
    }


def load_learner_state(model, state: dict) -> None:
    """Put a freshly built learner (same config, task and seed) where `learner_state` was."""
    for env, st in zip(_env_chain(model), state["envs"]):
        if st is not None and _has_state(env):
            env.load_state_dict(st)
    norm = _normalizer(model)
    if norm is not None and state["normalizer"] is not None:
        norm.load_state_dict(state["normalizer"])
    model.policy.load_state_dict(state["policy"])
    model.actor.optimizer.load_state_dict(state["actor_opt"])
    model.critic.optimizer.load_state_dict(state["critic_opt"])
    for k, v in state["counters"].items():
        setattr(model, k, v)
    model._last_obs = state["last_obs"]
    _load_replay_state(model.replay_buffer, state["replay"])
    if state["extra"] is not None:
        model.load_extra_state(state["extra"])
    np.random.set_state(state["rng"]["numpy"])
    torch.set_rng_state(state["rng"]["torch"])
    if state["rng"]["cuda"] is not None and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["rng"]["cuda"])
    model.action_space.np_random.bit_generator.state = state["rng"]["action_space"]


def learn_within_budget(model, ctx, make_policy: Callable[[], Policy], report_every: int,
                        metrics_fn: Callable[[], dict] = lambda: {},
                        q_real: Callable[[np.ndarray], np.ndarray] | None = None
                        ) -> BudgetCallback:
    """Train until the harness budget is spent (env steps, or seconds through the callback);
    returns the callback for its throughput numbers and `metrics()`.

    SB3's learn() runs once per collection (`steps_per_collect` env steps, then its
    updates), which is the same sequence as one learn() over the whole budget, so that
    between two collections the learner can be checkpointed (`learner_state`, when the run
    can: `ctx.checkpointing`) and a stopped run resumed from there with the same result."""
    if not model._custom_logger:
        model.set_logger(KeepLastLogger())
    cb = BudgetCallback(ctx, make_policy, report_every, metrics_fn=metrics_fn, q_real=q_real)
    saved = ctx.resume() if getattr(ctx, "checkpointing", False) else None
    if saved is not None:
        load_learner_state(model, saved["learner"])
        cb._next, cb._t0 = saved["callback"]
    collect = model.train_freq.frequency * model.n_envs
    while not ctx.should_stop(model.num_timesteps):
        model.learn(total_timesteps=collect, callback=cb, reset_num_timesteps=False)
        if ctx.should_stop(model.num_timesteps):
            break
        if getattr(ctx, "checkpointing", False) and ctx.checkpoint_due():
            ctx.checkpoint({"learner": learner_state(model), "callback": (cb._next, cb._t0)},
                           model.num_timesteps)
    return cb


def usable_cpus() -> int:
    from bench.machine import resources
    return resources()["cpus"]


def set_torch_threads(n: int) -> None:
    """Deliberate torch intra-op threads (the learner's updates set the pace on a CPU);
    0 means one per CPU this process may use (its affinity, e.g. under taskset)."""
    if n < 0:
        raise ValueError(f"torch_threads must be >= 0 (0: one per usable CPU), got {n}")
    torch.set_num_threads(int(n) or usable_cpus())


def seed_everything(seed: int) -> None:
    np.random.seed(seed)  # SB3's replay sampling uses the global numpy RNG
    torch.manual_seed(seed)
