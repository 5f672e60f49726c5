"""ILD training: BC warm start, then policy updates by backpropagating a Chamfer-alpha loss
between batched stochastic rollouts and the demo through the differentiable physics.

Alignment (the original compared s_0..s_127 with s_1..s_128, one step apart): here the
rollout's post-step states s_1..s_T are compared with the demo's s_1..s_T (demo.states[:,1:]);
s_0 is the reset state, which the policy does not choose. BC pairs o_t with a_t.
"""
from __future__ import annotations

import time

import flax.struct
import jax
import jax.numpy as jnp
import numpy as np
import optax

from bench.api import Policy, TrainResult
from methods.common.policy import (ObsNorm, TanhGaussianPolicy, bc_optimizer, bc_pairs,
                                   contract_leading, make_bc_step)
from methods.ild.config import ILDConfig
from methods.ild.losses import chamfer_alpha, multi_demo, normalize_grad, stepwise_l2
from tasks.core import without_joint_limits


@flax.struct.dataclass
class TrainingState:
    params: dict
    opt_state: optax.OptState
    key: jax.Array
    step: jax.Array
    lr: jax.Array
    """Learning rate of the next update under lr_schedule='budget' (set by the host from the
    fraction of the budget spent); unused by the step-count schedules."""


@flax.struct.dataclass
class StateNorm:
    """Normalizer of matched states for the loss: fixed demo statistics, no clipping (a
    clip would zero the gradient of every feature outside its range)."""
    mean: jax.Array
    std: jax.Array

    def __call__(self, s):
        return (s - self.mean) / self.std

    @staticmethod
    def fit(states: jax.Array, std_min: float) -> "StateNorm":
        """Statistics of `states` (..., D), the std floored at `std_min`."""
        flat = states.reshape(-1, states.shape[-1])
        return StateNorm(mean=flat.mean(0),
                         std=jnp.sqrt(jnp.clip(flat.var(0), std_min ** 2, 1e6)))


def sample_actions(policy: TanhGaussianPolicy, params, obs: jax.Array, key: jax.Array,
                   kernels_t, swish_remat: bool = True, taps=None) -> jax.Array:
    """One rollout step's actions for a batch of observations (B, obs_size), from B per-env
    keys split off `key`: `sample_batch` with the kernels transposed once outside the loop
    (`kernels_t`, `transposed_backward`; its hidden layers keep only their pre-activations
    for the backward with `swish_remat`), or the policy vmapped per env (`kernels_t` None);
    the same values either way."""
    keys = jax.random.split(key, obs.shape[0])
    if kernels_t is None:
        return jax.vmap(policy.sample, in_axes=(None, 0, 0))(params, obs, keys)
    return policy.sample_batch(params, obs, keys, kernels_t, swish_remat=swish_remat,
                               taps=taps)


def make_physics_step(task, config: ILDConfig):
    """step(s, a, t) -> (s', matched states, actions as stepped): one step of a batch of
    training rollouts after the policy. The per-step gradient normalization of the actions
    and of the stepped states (per env or over the batch, `grad_norm_scope`), the task's
    physics, its matched states, and at the end of each truncation window the state's
    gradient cut (truncated BPTT)."""
    env = task.env
    gn = normalize_grad if config.grad_normalization else (lambda x: x)
    # The normalization's scope: per env inside the vmaps below ('env'), or over the whole
    # batch after them ('batch', the original's), where the per-env one is the identity.
    batch_gn, gn = (gn, lambda x: x) if config.grad_norm_scope == "batch" else (
        lambda x: x, gn)

    def step(s, a, t):
        a = batch_gn(jax.vmap(gn)(a))
        s2 = batch_gn(jax.vmap(lambda s_, a_: gn(env.step(s_, a_)))(s, a))
        m = jax.vmap(task.matched_state)(s2)
        cut = (t + 1) % config.truncation == 0  # truncated BPTT window boundary
        s2 = jax.tree.map(lambda x: jnp.where(cut, jax.lax.stop_gradient(x), x), s2)
        return s2, m, a

    return step


def make_rollout_step(policy: TanhGaussianPolicy, physics_step, config: ILDConfig):
    """step(s, (t, key), params, kernels_t, tap=None) -> (s', (matched, actions, done)): one
    step of the training rollout, the policy's sample (through `tap`, `sample_batch`'s
    taps, for `make_step_group`) and then `physics_step`."""
    def step(s, xs, params, kernels_t, tap=None):
        t, k = xs
        a = sample_actions(policy, params, s.obs, k, kernels_t, config.swish_remat, tap)
        s2, m, a = physics_step(s, a, t)
        return s2, (m, a, s2.done)

    return step


def scan_body(body, config: ILDConfig):
    """A rollout scan's body as the loop runs it: rematerialized in the backward with
    `remat`. prevent_cse=False: inside a scan the body is not unrolled, so the CSE barrier
    jax.checkpoint adds by default only costs time (the same gradient either way)."""
    return jax.checkpoint(body, prevent_cse=False) if config.remat else body


def make_step_group(policy: TanhGaussianPolicy, step, config: ILDConfig):
    """group(s, (ts, keys), params, kernels_t) -> (s', (matched, actions, dones)): G =
    `config.kernel_grad_group` rollout steps (`make_rollout_step`'s `step`) as a lax.scan
    in a custom VJP. Its forward runs the policy through `sample_batch`'s taps, so the
    backward of each of the G steps hands out each layer's input and output cotangent
    instead of adding x^T g into the kernel's cotangent; the group's backward then makes
    each kernel's cotangent once, one product over the G x B rows. The same function:
    values and gradient to float32 round-off (the kernels' sums over steps in another
    order, and the loop's body compiled apart)."""
    G = config.kernel_grad_group

    def run(s, xs, params, kernels_t, taps):
        body = scan_body(lambda s_, x: step(s_, x[0], params, kernels_t, x[1]), config)
        return jax.lax.scan(body, s, (xs, taps))

    def zero_taps(s, kernels_t):
        return policy.zero_taps((G, s.obs.shape[0]), kernels_t[0].dtype)

    @jax.custom_vjp
    def group(s, xs, params, kernels_t):
        return run(s, xs, params, kernels_t, zero_taps(s, kernels_t))

    def fwd(s, xs, params, kernels_t):
        taps = zero_taps(s, kernels_t)
        out, vjp = jax.vjp(lambda s_, p_, tp: run(s_, xs, p_, kernels_t, tp), s, params,
                           taps)
        return out, vjp

    def bwd(vjp, ct):
        ct_s, ct_p, ct_taps = vjp(ct)
        # the taps' cotangents are each layer's (input, output cotangent) at the G steps:
        # the kernel's cotangent is their product over the G x B rows
        layers = dict(ct_p["net"]["params"])
        for i, factors in enumerate(ct_taps):
            layer = layers[f"hidden_{i}"]
            layers[f"hidden_{i}"] = {**layer,
                                     "kernel": layer["kernel"] + contract_leading(*factors)}
        return ct_s, None, {**ct_p, "net": {**ct_p["net"], "params": layers}}, None

    group.defvjp(fwd, bwd)
    return group


def episode_loss(x: jax.Array, alive: jax.Array, goals: jax.Array, config: ILDConfig):
    """The update's loss of a batch of normalized episodes x (B, T, D) against the goals
    (K, T, D), `alive` (B, T) masking states after a termination: (loss, raw loss, per-env
    LossTerms); loss = tanh(raw) with `tanh_loss`."""
    if config.loss == "chamfer":
        per_env = jax.vmap(lambda xb, mb: multi_demo(chamfer_alpha, xb, goals,
                                                     alpha=config.alpha, mask=mb,
                                                     distance=config.distance))(x, alive)
    else:
        per_env = jax.vmap(lambda xb, mb: multi_demo(stepwise_l2, xb, goals, mask=mb,
                                                     distance=config.distance))(x, alive)
    raw = jnp.mean(per_env.loss)
    return (jnp.tanh(raw) if config.tanh_loss else raw), raw, per_env


def make_rollout_loss(task, policy: TanhGaussianPolicy, goals: jax.Array, norm: StateNorm,
                      config: ILDConfig):
    """loss(params, key) over a batch of `num_envs` rollouts of the task's episode length.
    goals: (K, T, D) normalized demo states s_1..s_T."""
    env, T = task.env, task.episode_length
    if T % config.kernel_grad_group:
        raise ValueError(f"kernel_grad_group={config.kernel_grad_group} does not divide "
                         f"{task.spec.name}'s episode of {T} steps; set it to a divisor of "
                         f"{T} (1: off)")
    step = make_rollout_step(policy, make_physics_step(task, config), config)
    group = make_step_group(policy, step, config) if config.kernel_grad_group > 1 else None

    def loss_fn(params, key, init_keys):
        k_act = key
        s0 = jax.vmap(env.reset)(init_keys)
        # Made once here, outside the loop: the policy's backward then reads them as they are.
        kernels_t = policy.kernels_t(params) if config.transposed_backward else None

        steps = (jnp.arange(T), jax.random.split(k_act, T))
        if group is not None:
            G = config.kernel_grad_group
            steps = jax.tree.map(lambda v: v.reshape(T // G, G, *v.shape[1:]), steps)
            _, out = jax.lax.scan(lambda s, xs: group(s, xs, params, kernels_t), s0, steps)
            ms, acts, dones = jax.tree.map(lambda v: v.reshape(T, *v.shape[2:]), out)
        else:
            body = scan_body(lambda s, xs: step(s, xs, params, kernels_t), config)
            _, (ms, acts, dones) = jax.lax.scan(body, s0, steps)
        x = norm(jnp.swapaxes(ms, 0, 1))  # (B, T, D)
        # alive[b, t]: no termination before step t (the terminating state itself counts).
        before = jnp.cumsum(jnp.swapaxes(dones, 0, 1), axis=1) - jnp.swapaxes(dones, 0, 1)
        alive = (before == 0) if config.mask_after_done else jnp.ones_like(before, bool)
        loss, raw, per_env = episode_loss(x, alive, goals, config)
        aux = {"train/loss": loss, "train/loss_raw": raw,
               "train/coverage": jnp.mean(per_env.coverage),
               "train/deviation": jnp.mean(per_env.deviation),
               "train/action_abs": jnp.mean(jnp.abs(acts)),
               "train/alive_frac": jnp.mean(alive.astype(jnp.float32))}
        return loss, aux

    return loss_fn


def make_update(task, policy, goals, norm, config: ILDConfig, reset_key):
    """One ILD update as a pure function (TrainingState, _) -> (TrainingState, metrics), for
    lax.scan; also used by the speed benchmark. Returns (update, optimizer, schedule)."""
    if config.lr_schedule == "constant":
        lr = optax.constant_schedule(config.learning_rate)
    else:  # 'budget' also decays over `updates` if those run out before the budget
        lr = optax.linear_schedule(config.learning_rate, config.lr_end, config.updates)
    # Adam's direction, then the step size (optax.adam(lr) is the same two transforms).
    opt = optax.chain(optax.clip_by_global_norm(config.max_grad_norm), optax.scale_by_adam())
    loss_fn = make_rollout_loss(task, policy, goals, norm, config)
    fixed_init = jax.random.split(reset_key, config.num_envs)

    def update(s: TrainingState, _):
        key, k_roll, k_init = jax.random.split(s.key, 3)
        init_keys = (jax.random.split(k_init, config.num_envs) if config.resample_init
                     else fixed_init)
        (loss, aux), g = jax.value_and_grad(loss_fn, has_aux=True)(s.params, k_roll,
                                                                    init_keys)
        leaves = jax.tree_util.tree_leaves(g)
        nonfinite = sum(jnp.sum(~jnp.isfinite(x)) for x in leaves)
        g = jax.tree.map(lambda x: jnp.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0), g)
        raw = optax.global_norm(g)
        upd, opt_state = opt.update(g, s.opt_state, s.params)
        rate = s.lr if config.lr_schedule == "budget" else lr(s.step)
        if config.lr_warmup > 0:
            rate = rate * jnp.minimum(1.0, (s.step + 1) / config.lr_warmup)
        upd = jax.tree.map(lambda u: u * -rate, upd)
        metrics = {**aux, "grad/norm_raw": raw,
                   "grad/norm_clipped": jnp.minimum(raw, config.max_grad_norm),
                   "grad/nonfinite": nonfinite.astype(jnp.float32), "train/lr": rate}
        return TrainingState(optax.apply_updates(s.params, upd), opt_state, key,
                             s.step + 1, s.lr), metrics

    return update, opt, lr


def initial_state(params, opt, key, config: ILDConfig) -> TrainingState:
    return TrainingState(params, opt.init(params), key, jnp.zeros((), jnp.int32),
                         jnp.float32(config.learning_rate))


def budget_lr(config: ILDConfig, spent: float) -> float:
    """lr_schedule='budget': linear from learning_rate to lr_end over the fraction of the
    run's budget spent (time or env steps, whichever runs out first)."""
    f = min(max(spent, 0.0), 1.0)
    return config.learning_rate + f * (config.lr_end - config.learning_rate)


def make_chunk(update, n: int):
    """Up to `n` updates in one jitted call: chunk(state, active) -> (state, metrics averaged
    over the updates run). Only min(active, n) updates run (a loop with that trip count), so
    a budget or an update count that ends inside a chunk is met as one update per call
    would meet it. n = 1 is the plain one-update call (metrics stacked over its one update)."""
    if n == 1:
        return jax.jit(lambda s, active: jax.lax.scan(update, s, None, length=1))

    def run(s, active):
        _, shapes = jax.eval_shape(update, s, None)
        total = jax.tree.map(lambda x: jnp.zeros(x.shape, jnp.float32), shapes)

        def body(_, carry):
            s, total = carry
            s, m = update(s, None)
            return s, jax.tree.map(lambda t, x: t + x.astype(jnp.float32), total, m)

        k = jnp.clip(active, 1, n)
        s, total = jax.lax.fori_loop(0, k, body, (s, total))
        return s, jax.tree.map(lambda x: x / k.astype(jnp.float32), total)

    return jax.jit(run)


def updates_this_call(config: ILDConfig, done: int, per_update: int, left_s: float | None,
                      left_steps: int | None, update_s: float | None) -> int:
    """How many of a chunk's updates to run: what is left of `updates`, of an env-step
    budget (exact) and of a time budget (at the last call's seconds per update, rounded up:
    a call overruns the time by at most one update, as one update per call does). Under a
    time budget, a call with no time per update measured yet (the first, which compiles, and
    the one after it) runs one update."""
    n = min(config.chunk, config.updates - done)
    if left_steps is not None:
        n = min(n, -(-left_steps // per_update))
    if left_s is not None:
        n = min(n, int(np.ceil(max(left_s, 0.0) / update_s))) if update_s else 1
    return max(n, 1)


def rollout_physics(task, config: ILDConfig):
    """The task the training rollouts differentiate through (evaluation always uses the task
    itself): the task as the method was handed it, whose physics runs the task's plan
    (`tasks.physics.plan`), or a copy of it without joint limits (`joint_limits` False), to
    which the view applies the same plan."""
    return task if config.joint_limits else without_joint_limits(task)


def bc_warm_start(policy, params, obs, actions, config: ILDConfig, key):
    """Alg. 1 line 3: BC on (o_t, a_t) with its own Adam (same lr and clipping)."""
    opt = bc_optimizer(config.learning_rate, config.max_grad_norm)
    bc_step = make_bc_step(policy, opt, obs, actions, config.bc_samples)

    def update(carry, k):
        p, o, loss, _ = bc_step(*carry, k)
        return (p, o), loss

    (params, _), losses = jax.jit(lambda p, k: jax.lax.scan(
        update, (p, opt.init(p)), jax.random.split(k, config.bc_updates)))(params, key)
    return params, losses[-1]


def train(task, demo, config: ILDConfig, ctx, seed: int) -> TrainResult:
    T = task.episode_length
    obs, actions = bc_pairs(task, demo)
    demo_states = jnp.asarray(demo.states[:, 1:])                            # s_1..s_T
    norm = StateNorm.fit(demo_states, config.state_std_min)
    goals = norm(demo_states)
    policy = TanhGaussianPolicy(task.obs_size, task.action_size, config.hidden)
    # init_key: network weights; bc_key: BC sampling noise; loop_key: rollouts' action noise;
    # reset_key: initial states (fixed for all updates unless resample_init).
    init_key, bc_key, loop_key, reset_key = jax.random.split(jax.random.PRNGKey(seed), 4)
    params = policy.init(init_key, ObsNorm.fit(obs, config.obs_std_min))
    act = policy.act

    if config.bc_updates > 0:
        params, bc_final = bc_warm_start(policy, params, obs, actions, config, bc_key)
        ctx.report(Policy(act, params), 0, {"bc/loss": bc_final}, force_eval=True)

    update, opt, lr = make_update(rollout_physics(task, config), policy, goals, norm, config,
                                  reset_key)
    chunk = make_chunk(update, config.chunk)
    state = initial_state(params, opt, loop_key, config)
    env_steps, done = 0, 0
    per_update = config.num_envs * T
    update_s = None  # seconds per update of the last call (the first one compiles)
    while done < config.updates and not ctx.should_stop(env_steps):
        if config.lr_schedule == "budget":
            spent = max(ctx.spent(env_steps), done / config.updates)
            state = state.replace(lr=jnp.float32(budget_lr(config, spent)))
        n = updates_this_call(config, done, per_update, *ctx.remaining(env_steps), update_s)
        t0 = time.perf_counter()
        state, m = chunk(state, jnp.int32(n))
        m = jax.device_get(m)
        dt = time.perf_counter() - t0
        update_s = None if done == 0 else dt / n
        done += n
        env_steps += n * per_update
        metrics = {k: float(np.mean(v)) for k, v in m.items()}
        metrics.update({"train/updates": done, "time/updates_per_s": n / dt,
                        "time/env_steps_per_s": n * per_update / dt})
        ctx.report(Policy(act, state.params), env_steps, metrics)
    return TrainResult(Policy(act, state.params), env_steps=env_steps,
                       metrics={"train/updates": done})
