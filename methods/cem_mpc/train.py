"""CEM-MPC: plan in the simulator from a copy of the current state at every control step.

A reference that needs the simulator and the full state at TEST time (Uses.sim_at_test):
its policy is a 'jax_state' planner with memory (the previous plan, shifted by one step, warm-
starts the next; the time index picks the demo states to track). The planner simulates with
the nominal simulator it was handed, so under perturbed test dynamics it plans with the
wrong model, as a deployed MPC would. There is no training: `train` builds the planner,
measures its planning time per control step, and returns it.
"""
from __future__ import annotations

import time

import jax
import jax.numpy as jnp

from bench.api import Policy, TrainResult
from methods.cem_mpc.config import CEMConfig
from tasks.physics.transforms import with_small_dots


class CEMPlanner:
    def __init__(self, env, action_size: int, config: CEMConfig, matched_state=None,
                 goals=None, goal_mean=None, goal_std=None):
        self.env, self.A, self.cfg = env, action_size, config
        self.matched_state = matched_state
        if config.objective == "track":
            self.goals = (goals - goal_mean) / goal_std      # (T, D) normalized s_1..s_T
            self.goal_mean, self.goal_std = goal_mean, goal_std

    def score(self, state, seq, t):
        """Objective of one action sequence (H, A) from `state` at episode step t."""
        cfg = self.cfg

        def body(carry, xs):
            s, alive, total = carry
            a, k = xs
            # The planner's env may report other metrics than the state it was handed (a
            # reward-hiding view drops them), and brax's envs update the handed state's
            # metrics dict in place: step a copy, and keep the carry's structure.
            s2 = self.env.step(s.replace(metrics=dict(s.metrics)), a).replace(
                metrics=s.metrics)
            if cfg.objective == "reward":
                gain = alive * s2.reward
            else:
                # A cost must not stop at termination: masking it would make ending the
                # episode (a hopper falling) the cheapest plan. The terminal state is held
                # and charged against every later demo state, as the episode would be.
                s2 = jax.tree.map(lambda new, old: jnp.where(alive > 0, new, old), s2, s)
                idx = jnp.minimum(t + k, self.goals.shape[0] - 1)   # s_{t+k+1} vs goal t+k
                x = (self.matched_state(s2) - self.goal_mean) / self.goal_std
                gain = -jnp.sum((x - self.goals[idx]) ** 2)
            total = total + gain
            return (s2, alive * (1.0 - s2.done), total), None

        (_, _, total), _ = jax.lax.scan(body, (state, jnp.ones(()), jnp.zeros(())),
                                        (seq, jnp.arange(cfg.horizon)))
        return total

    def init_memory(self, params, key):
        return (jnp.zeros((self.cfg.horizon, self.A)), jnp.zeros((), jnp.int32))

    def act(self, params, state, key, deterministic, memory):
        """One control step: CEM iterations from the warm-started mean, first action out,
        plan shifted by one step for the next call."""
        cfg = self.cfg
        mean, t = memory
        std = jnp.full_like(mean, cfg.init_std)

        def iteration(carry, k):
            mean, std = carry
            eps = jax.random.normal(k, (cfg.population,) + mean.shape)
            seqs = jnp.clip(mean + std * eps, -1.0, 1.0)
            scores = jax.vmap(self.score, in_axes=(None, 0, None))(state, seqs, t)
            scores = jnp.where(jnp.isfinite(scores), scores, -jnp.inf)
            _, top = jax.lax.top_k(scores, cfg.elites)
            elite = seqs[top]
            m = cfg.momentum
            mean = m * mean + (1 - m) * elite.mean(0)
            std = m * std + (1 - m) * elite.std(0)
            return (mean, std), scores[top[0]]

        (mean, _), best = jax.lax.scan(iteration, (mean, std),
                                       jax.random.split(key, cfg.iterations))
        action = mean[0]
        shifted = jnp.concatenate([mean[1:], jnp.zeros((1, self.A))])
        return action, (shifted, t + 1)


def train(task, demo, config: CEMConfig, ctx, seed: int) -> TrainResult:
    if config.small_dots:  # the planner's model only: the test episodes run the task itself
        task = with_small_dots(task)
    kwargs = {}
    if config.objective == "track":
        states = jnp.asarray(demo.states[0])                      # s_0..s_T
        std = jnp.maximum(states.std(0), config.state_std_min)
        kwargs = dict(matched_state=task.matched_state, goals=states[1:],
                      goal_mean=states.mean(0), goal_std=std)
    planner = CEMPlanner(task.env, task.action_size, config, **kwargs)
    policy = Policy(act=planner.act, params=(), kind="jax_state",
                    init_memory=planner.init_memory)
    # Planning cost per control step, one env, compiled first (the compile is reported).
    step = jax.jit(lambda s, k, m: planner.act((), s, k, True, m))
    s = jax.jit(task.env.reset)(jax.random.PRNGKey(seed))
    mem = planner.init_memory((), None)
    t0 = time.perf_counter()
    jax.block_until_ready(step(s, jax.random.PRNGKey(0), mem))
    compile_s = time.perf_counter() - t0
    reps = 5
    t0 = time.perf_counter()
    for i in range(reps):
        a, mem = step(s, jax.random.PRNGKey(i), mem)
    jax.block_until_ready(a)
    per_step = (time.perf_counter() - t0) / reps
    sims = config.population * config.iterations * config.horizon
    metrics = {"plan/ms_per_step": 1e3 * per_step, "plan/compile_s": compile_s,
               "plan/sim_steps_per_control_step": float(sims),
               "plan/sim_steps_per_s": sims / per_step}
    ctx.log(f"  planning: {1e3 * per_step:.1f} ms per control step ({sims:,d} simulated "
            f"steps), objective {config.objective!r}")
    return TrainResult(policy, env_steps=0, metrics=metrics)


def make_train(objective: str):
    """train() for the method that plans on `objective` (its Uses declare what that reads)."""

    def _train(task, demo, config, ctx, seed):
        if config.objective != objective:
            other = "cem_mpc" if config.objective == "reward" else "cem_mpc_track"
            raise ValueError(f"this method plans on objective {objective!r} and declares only "
                             f"what that reads; for objective={config.objective!r} run the "
                             f"method {other!r}")
        return train(task, demo, config, ctx, seed)
    return _train

