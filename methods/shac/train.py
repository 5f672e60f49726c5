"""SHAC (Xu et al. 2022): short-horizon actor-critic through the differentiable simulator,
on the TRUE task reward (a reference, not an imitation method; ILD paper A.3).

One epoch: roll the current env states (gradient cut at the window start) for `horizon`
steps; actor loss = -(discounted rewards + gamma^k V_target(s_end)) per episode segment,
V = 0 on true termination and V_target(pre-reset obs) at the time limit; backprop through the
physics; then fit the critic to TD-lambda targets and soft-update the target critic.
"""
from __future__ import annotations

import functools
from typing import Sequence

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import linen

from bench.api import Policy, TrainResult
from methods.shac.config import SHACConfig
from tasks.core import reset_done, strong


class MLP(linen.Module):
    hidden: Sequence[int]
    out: int
    ortho: bool = False

    @linen.compact
    def __call__(self, x):
        init = (linen.initializers.orthogonal(np.sqrt(2)) if self.ortho
                else linen.initializers.lecun_normal())
        for h in self.hidden:
            x = linen.LayerNorm()(linen.elu(linen.Dense(h, kernel_init=init)(x)))
        return linen.Dense(self.out, kernel_init=init)(x)


@flax.struct.dataclass
class RMS:
    """Running mean/std (count starts at 1e-4, normalization epsilon 1e-5, the original)."""
    mean: jax.Array
    var: jax.Array
    count: jax.Array

    @staticmethod
    def init(d):
        # float32 explicitly: a weakly typed count (jnp.asarray(1e-4)) turns strong after the
        # first update, so `epoch` would compile a second time.
        return RMS(jnp.zeros(d), jnp.ones(d), jnp.asarray(1e-4, jnp.float32))

    def update(self, x):
        x = x.reshape(-1, x.shape[-1])
        n, m, v = x.shape[0], x.mean(0), x.var(0)
        tot = self.count + n
        delta = m - self.mean
        mean = self.mean + delta * n / tot
        var = (self.var * self.count + v * n + delta ** 2 * self.count * n / tot) / tot
        return RMS(mean, var, tot)

    def __call__(self, x):
        return (x - self.mean) / jnp.sqrt(self.var + 1e-5)


def td_lambda(rewards, next_values, done_mask, gamma, lam):
    """TD-lambda targets over a window (the original's recursion), arrays (H, N).
    next_values[t] = V_target(s_{t+1}) (0 on termination); done_mask[t] = 1 where the episode
    segment ends at t (termination, time limit, or the window's last step)."""

    def body(carry, x):
        A, B, lam_t = carry
        r, v, d = x
        lam_t = lam_t * lam * (1.0 - d) + d
        A = (1.0 - d) * (lam * gamma * A + gamma * v + (1.0 - lam_t) / (1.0 - lam) * r)
        B = gamma * (v * d + B * (1.0 - d)) + r
        return (A, B, lam_t), (1.0 - lam) * A + lam_t * B

    z = jnp.zeros_like(rewards[0])
    _, targets = jax.lax.scan(body, (z, z, jnp.ones_like(z)), (rewards, next_values, done_mask),
                              reverse=True)
    return targets


@flax.struct.dataclass
class State:
    actor: dict
    critic: dict
    target: dict
    actor_opt: optax.OptState
    critic_opt: optax.OptState
    rms: RMS
    env_state: object
    t: jax.Array
    key: jax.Array
    epoch: jax.Array


class SHAC:
    def __init__(self, env, obs_size: int, action_size: int, episode_length: int,
                 config: SHACConfig):
        self.env, self.cfg, self.T = env, config, episode_length
        self.obs_size, self.action_size = obs_size, action_size
        self.actor_net = MLP(config.actor_hidden, action_size)
        self.critic_net = MLP(config.critic_hidden, 1, ortho=True)
        b1, b2 = config.betas
        # One actor update per epoch: its optax step count is the epoch.
        self.actor_tx = optax.chain(
            optax.clip_by_global_norm(config.grad_clip),
            optax.adam(optax.linear_schedule(config.actor_lr, config.lr_end, config.max_epochs),
                       b1=b1, b2=b2))
        # The critic takes critic_iterations * minibatches steps per epoch; its LR decays by
        # epoch as the original's (it sets the LR once per epoch).
        self.critic_lr = optax.linear_schedule(config.critic_lr, config.lr_end,
                                               config.max_epochs)
        self.critic_tx = optax.chain(
            optax.clip_by_global_norm(config.grad_clip),
            optax.inject_hyperparams(optax.adam)(learning_rate=config.critic_lr, b1=b1, b2=b2))

    # ---------------------------------------------------------------- networks
    def init(self, key) -> State:
        k_a, k_c, k_env, key = jax.random.split(key, 4)
        actor = {"net": self.actor_net.init(k_a, jnp.zeros(self.obs_size)),
                 "logstd": jnp.full(self.action_size, self.cfg.logstd_init, jnp.float32)}
        critic = self.critic_net.init(k_c, jnp.zeros(self.obs_size))
        env_state = jax.vmap(self.env.reset)(jax.random.split(k_env, self.cfg.num_envs))
        return strong(State(actor, critic, critic, self.actor_tx.init(actor),
                            self.critic_tx.init(critic), RMS.init(self.obs_size), env_state,
                            jnp.zeros(self.cfg.num_envs, jnp.int32), key,
                            jnp.zeros((), jnp.int32)))

    def norm(self, rms, obs):
        return rms(obs) if self.cfg.obs_norm else obs

    def action(self, actor, rms, obs, key):
        mu = self.actor_net.apply(actor["net"], self.norm(rms, obs))
        return jnp.tanh(mu + jnp.exp(actor["logstd"]) * jax.random.normal(key, mu.shape))

    def value(self, critic, obs_n):
        return self.critic_net.apply(critic, obs_n)[..., 0]

    # ---------------------------------------------------------------- actor
    def actor_loss(self, actor, s: State):
        cfg, T, N = self.cfg, self.T, self.cfg.num_envs
        rms = s.rms  # frozen within the window
        env_state = jax.lax.stop_gradient(s.env_state)  # gradient cut at the window start

        def step(carry, xs):
            es, t, gam, acc, loss = carry
            i, k = xs
            k_act, k_reset = jax.random.split(k)
            a = jax.vmap(self.action, in_axes=(None, None, 0, 0))(
                actor, rms, es.obs, jax.random.split(k_act, N))
            nxt = jax.vmap(self.env.step)(es, a)
            r = nxt.reward * cfg.reward_scale
            t1 = t + 1
            term = nxt.done > 0
            done = term | (t1 >= T)
            v = jnp.where(term, 0.0, self.value(s.target, self.norm(rms, nxt.obs)))
            acc = acc + gam * r
            seg_end = done | (i == cfg.horizon - 1)
            loss = loss + jnp.sum(jnp.where(seg_end, -acc - cfg.gamma * gam * v, 0.0))
            gam = jnp.where(done, 1.0, gam * cfg.gamma)
            acc = jnp.where(done, 0.0, acc)
            es2 = reset_done(self.env, nxt, done, k_reset)
            out = (self.norm(rms, es.obs), jax.lax.stop_gradient(r),
                   jax.lax.stop_gradient(v), seg_end.astype(jnp.float32), es.obs, done)
            return (es2, jnp.where(done, 0, t1), gam, acc, loss), out

        z = jnp.zeros(N)
        carry = (env_state, s.t, jnp.ones(N), z, jnp.zeros(()))
        keys = jax.random.split(s.key, cfg.horizon)
        (es, t, _, _, loss), traj = jax.lax.scan(step, carry, (jnp.arange(cfg.horizon), keys))
        return loss / (cfg.horizon * N), (es, t, traj)

    # ---------------------------------------------------------------- one epoch
    @functools.partial(jax.jit, static_argnums=0)
    def epoch(self, s: State):
        cfg = self.cfg
        key, k_epoch = jax.random.split(s.key)
        s = s.replace(key=k_epoch)
        (aloss, (es, t, traj)), g = jax.value_and_grad(self.actor_loss, has_aux=True)(s.actor, s)
        nonfinite = sum(jnp.sum(~jnp.isfinite(x)) for x in jax.tree.leaves(g))
        g = jax.tree.map(jnp.nan_to_num, g)
        gnorm = optax.global_norm(g)
        upd, actor_opt = self.actor_tx.update(g, s.actor_opt, s.actor)
        actor = optax.apply_updates(s.actor, upd)

        obs_n, rew, v_next, seg_end, raw_obs, dones = traj
        targets = td_lambda(rew, v_next, seg_end, cfg.gamma, cfg.lam)
        x = obs_n.reshape(-1, self.obs_size)
        y = targets.reshape(-1)
        mb = x.shape[0] // cfg.critic_minibatches
        lr = self.critic_lr(s.epoch)
        clip_state, adam_state = s.critic_opt
        critic_opt = (clip_state, adam_state._replace(
            hyperparams={**adam_state.hyperparams, "learning_rate": lr}))

        def critic_step(carry, j):
            c, opt = carry
            xb = jax.lax.dynamic_slice_in_dim(x, j * mb, mb)
            yb = jax.lax.dynamic_slice_in_dim(y, j * mb, mb)
            loss, cg = jax.value_and_grad(
                lambda p: jnp.mean((self.value(p, xb) - yb) ** 2))(c)
            cg = jax.tree.map(jnp.nan_to_num, cg)
            u, opt = self.critic_tx.update(cg, opt, c)
            return (optax.apply_updates(c, u), opt), loss

        # The original: critic_iterations passes over the (unshuffled) minibatches.
        order = jnp.tile(jnp.arange(cfg.critic_minibatches), cfg.critic_iterations)
        (critic, critic_opt), closs = jax.lax.scan(critic_step, (s.critic, critic_opt), order)
        a = cfg.target_alpha
        target = jax.tree.map(lambda tp, p: a * tp + (1 - a) * p, s.target, critic)
        rms = s.rms.update(raw_obs) if cfg.obs_norm else s.rms
        s = s.replace(actor=actor, critic=critic, target=target, actor_opt=actor_opt,
                      critic_opt=critic_opt, rms=rms, env_state=es, t=t, key=key,
                      epoch=s.epoch + 1)
        s = strong(s)  # the types it came in with: the next epoch reuses this executable
        metrics = {"train/actor_loss": aloss, "train/critic_loss": closs[-1],
                   "grad/norm_raw": gnorm, "grad/nonfinite": nonfinite,
                   "train/episodes_ended": jnp.sum(dones)}
        return s, metrics

    # ---------------------------------------------------------------- policy
    def act(self, params, obs, key, deterministic):
        actor, rms = params
        if deterministic:
            return jnp.tanh(self.actor_net.apply(actor["net"], self.norm(rms, obs)))
        return self.action(actor, rms, obs, key)


def train(task, demo, config: SHACConfig, ctx, seed: int) -> TrainResult:
    agent = SHAC(task.env, task.obs_size, task.action_size, task.episode_length, config)
    s = agent.init(jax.random.PRNGKey(seed))
    steps_per_epoch = config.num_envs * config.horizon
    steps, metrics = 0, {}
    act = agent.act
    while int(s.epoch) < config.max_epochs and not ctx.should_stop(steps):
        s, m = agent.epoch(s)
        steps += steps_per_epoch
        metrics = {**{k: float(v) for k, v in m.items()}, "train/epochs": int(s.epoch)}
        ctx.report(Policy(act, (s.actor, s.rms)), env_steps=steps, metrics=metrics)
    return TrainResult(Policy(act, (s.actor, s.rms)), env_steps=steps, metrics=metrics)
