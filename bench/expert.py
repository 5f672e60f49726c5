"""Experts and demos: `ildbench expert train --task T` and `ildbench expert demo --task T`.

Experts are brax PPO policies trained on the task's own unwrapped env (pointmass has an
analytic PD expert instead): the `cpu` recipes use 128-step episodes and 256 envs, the `gpu`
recipes brax's published settings (thousands of envs, 1000-step episodes). A trained expert
is stored as tasks/data/<task>_expert.msgpack (observation normalizer + policy parameters of
the best evaluation, a few KB) with tasks/data/<task>_expert.json (PPO config, seed,
evaluation history, wall-clock, hardware, library versions). Training is deterministic for a
given seed on one machine, so an interrupted training can be rerun from its seed, or
continued from its best evaluation with `resume`.

A demo file is made by rolling the deterministic expert from `rollouts` initial states,
dropping episodes that terminated early, and keeping the best `keep` by return (index 0
is the one-demo protocol's demo), as the original release did. The references R_expert
(expert, deterministic) and R_random (uniform random actions) are measured by the shared
evaluator on REFERENCE_EPISODES fixed episodes and stored in the demo.
"""
from __future__ import annotations

import functools
import json
import os
import shutil
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np
from flax import serialization

from tasks.core import Task, make_task, open_loop
from tasks.demo import FORMAT_VERSION, Demo, library_versions, save_demo
from tasks.registry import DATA_DIR

_print = functools.partial(print, flush=True)
REFERENCE_EPISODES = 128
REFERENCE_SEED = 0

# PPO settings per task (brax PPO keyword arguments). Base: the ILD release's expert
# recipe (episode_length 128, lr 3e-4, entropy 1e-2, discount 0.95, reward scaling 10,
# normalized observations) with batch sizes raised for CPU throughput.
_PPO_BASE = dict(num_timesteps=5_000_000, episode_length=128, num_envs=256, batch_size=256,
                 num_minibatches=8, num_updates_per_batch=4, unroll_length=10,
                 learning_rate=3e-4, entropy_cost=1e-2, discounting=0.95, reward_scaling=10.0,
                 normalize_observations=True, num_evals=20, num_eval_envs=64)
PPO_CONFIGS: dict[str, dict] = {
    "inverted_pendulum": dict(_PPO_BASE, num_timesteps=1_000_000, discounting=0.97),
    "reacher": dict(_PPO_BASE, num_timesteps=1_500_000, reward_scaling=5.0,
                    entropy_cost=1e-3),
    # acrobot (its expert is open-loop trajopt, TRAJOPT_CONFIGS; this PPO recipe stays for
    # comparison): on the old capsule-inertia model, discounting 0.97 reached 96.6 in 10M
    # steps (random 82.0) and 0.99 did worse; on the corrected model (v1's inertia)
    # discounting 0.99 peaked at 84.7 (random 67.7) at 0.5M steps and fell to 63 by 2.1M.
    "acrobot": dict(_PPO_BASE, num_timesteps=10_000_000, discounting=0.97,
                    reward_scaling=1.0),
    "swimmer": dict(_PPO_BASE, num_timesteps=10_000_000, discounting=0.995),
    "hopper": dict(_PPO_BASE, num_timesteps=3_000_000),
    # walker2d: trained with 128-step episodes (the base recipe) the expert reached eval
    # return 269 in 10M steps (1857 s, 2 CPU cores) but every rollout falls at step ~106:
    # it lunges forward because nothing after step 128 is ever seen. On 1000-step episodes
    # with discounting 0.95 (10M steps, 1662 s, 1 core) it still falls in all 64 rollouts:
    # eval return 239 over 1000 steps, below the untrained policy's 299 (standing earns the
    # healthy reward): a 20-step horizon makes the lunge pay. Discounting 0.99 (this recipe,
    # 1 core) did not help either: eval return 302, 327, 323, ... 239, 273, 310, 288
    # over 7M steps (stopped at 6.9M, 1170 s), never clear of the untrained 299. SAC solved
    # it (SAC_CONFIGS, walker2d's default algorithm).
    "walker2d": dict(_PPO_BASE, num_timesteps=10_000_000, episode_length=1000,
                     discounting=0.99),
    "ant": dict(_PPO_BASE, num_timesteps=10_000_000),
    "humanoid": dict(_PPO_BASE, num_timesteps=20_000_000),
}


_HANDMADE = {"pointmass": "analytic PD controller",
             "cloth": "the original release's hand-crafted open-loop actions "
                      "(lift 20, carry 40, lower 20 steps)"}


def expert_paths(task: str) -> tuple[str, str]:
    base = os.path.join(DATA_DIR, f"{task}_expert")
    return base + ".msgpack", base + ".json"


def _ppo_networks(task: Task):
    from brax.training.acme import running_statistics
    from brax.training.agents.ppo import networks as ppo_networks
    return ppo_networks.make_ppo_networks(
        task.obs_size, task.action_size,
        preprocess_observations_fn=running_statistics.normalize)


# Accelerator recipes (`ildbench expert train --preset gpu`): brax's own published PPO
# settings for these bodies (thousands of parallel envs, 1000-step episodes so that nothing
# learned depends on the 128-step cut), for a GPU where 10^8 env steps take minutes.
_GPU_BASE = dict(_PPO_BASE, num_timesteps=100_000_000, episode_length=1000, num_envs=2048,
                 batch_size=1024, num_minibatches=32, num_updates_per_batch=4,
                 unroll_length=10, discounting=0.97, num_evals=50, num_eval_envs=128)
PPO_GPU_CONFIGS: dict[str, dict] = {
    "ant": dict(_GPU_BASE, num_envs=4096, batch_size=2048, unroll_length=5),
    "humanoid": dict(_GPU_BASE, reward_scaling=0.1, entropy_cost=1e-3,
                     num_updates_per_batch=8),
    "walker2d": dict(_GPU_BASE, reward_scaling=5.0, learning_rate=6e-4, batch_size=512,
                     unroll_length=20, num_updates_per_batch=8, discounting=0.997),
    "swimmer": dict(_GPU_BASE, discounting=0.995),
    "hopper": dict(_GPU_BASE, reward_scaling=5.0, learning_rate=6e-4, batch_size=512,
                   unroll_length=20, num_updates_per_batch=8, discounting=0.997),
    "acrobot": dict(_GPU_BASE, episode_length=128, num_envs=4096, batch_size=2048,
                    discounting=0.99, reward_scaling=1.0),
    "reacher": dict(_GPU_BASE, episode_length=128, reward_scaling=5.0, entropy_cost=1e-3,
                    num_timesteps=20_000_000),
    "inverted_pendulum": dict(_GPU_BASE, episode_length=128, num_timesteps=10_000_000),
}
PRESETS = {"cpu": PPO_CONFIGS, "gpu": PPO_GPU_CONFIGS}

# SAC settings per task (brax SAC keyword arguments; `ildbench expert train --algorithm sac`),
# for tasks where PPO found no expert (walker2d: PPO lunges and falls, or only stands; docs/tasks.md). 1000-step episodes so that falling always costs the rest of the episode; one
# gradient update per 16 env steps (grad_updates_per_step 8 with 128 envs) keeps training on
# one CPU core at ~850-1450 env steps/s. walker2d (one core): eval return 106.9
# untrained -> 671 at 1.4M steps -> 1154.8 at 2.63M (the kept expert: 128-step R_expert 293.3,
# no early ends in 64 rollouts; paper 289); stopped by hand at 3.24M steps, 3704 s.
SAC_CONFIGS: dict[str, dict] = {
    "walker2d": dict(num_timesteps=10_000_000, episode_length=1000, num_envs=128,
                     batch_size=256, learning_rate=6e-4, discounting=0.99, reward_scaling=5.0,
                     normalize_observations=True, grad_updates_per_step=8,
                     min_replay_size=8192, max_replay_size=1_000_000, num_evals=100,
                     num_eval_envs=32, deterministic_eval=True),
}
RECIPES = {"ppo": PRESETS, "sac": {"cpu": SAC_CONFIGS}}

# Open-loop experts: trajectory optimization through the task's own differentiable physics,
# for tasks whose reset noise is small and where brax's trainers measured no better than
# random (acrobot: PPO and brax's APG stayed at random's level, docs/tasks.md) or than a
# constant action (swimmer: PPO's 10.6 over 128 steps vs 13.9 for a constant 0.5; the
# sinusoid gait below earns 55.0, 488 s on one CPU core). `starts`
# torque sequences a * sin(w t + phase) (w spread over [min_freq, max_freq] rad/s, random
# phases; tanh-squashed) are each optimized with Adam on the 128-step return from one
# initial state; the kept one has the best mean return over `select_episodes` fresh initial
# states. The expert then plays that action table regardless of the observation.
TRAJOPT_CONFIGS: dict[str, dict] = {
    "acrobot": dict(starts=32, steps=300, learning_rate=0.1, amplitude=3.0, min_freq=2.0,
                    max_freq=12.0, select_episodes=16),
    "swimmer": dict(starts=16, steps=200, learning_rate=0.1, amplitude=3.0, min_freq=1.0,
                    max_freq=8.0, select_episodes=16),
}


def default_algorithm(task_name: str) -> str:
    """How a task's committed expert was trained: trajopt (acrobot, swimmer), SAC (walker2d),
    else PPO."""
    if task_name in TRAJOPT_CONFIGS:
        return "trajopt"
    return "sac" if task_name in SAC_CONFIGS else "ppo"


def train_trajopt_expert(task_name: str, seed: int = 0, log=_print,
                         out_dir: str | None = None, config: dict | None = None) -> str:
    """Optimize an open-loop action table (TRAJOPT_CONFIGS) and store it as the task's
    expert (<task>_expert.msgpack: {'actions': (T, action_size)}, json beside it)."""
    import optax

    from bench.machine import machine
    cfg = dict(config if config is not None else TRAJOPT_CONFIGS.get(task_name, {}))
    if not cfg:
        raise ValueError(f"no trajectory-optimization recipe for task {task_name!r}; recipes "
                         f"exist for {', '.join(sorted(TRAJOPT_CONFIGS))}")
    task = make_task(task_name)
    env, T, A, n = task.env, task.episode_length, task.action_size, int(cfg["starts"])
    t0 = time.perf_counter()

    def episode_return(u, key):  # u: (T, A) unsquashed torques
        return open_loop(lambda s, a: env.step(s, jnp.tanh(a)), env.reset(key), u,
                         lambda s: s.reward)[1].sum()

    k_phase, k_fit, k_select = jax.random.split(jax.random.PRNGKey(seed), 3)
    t = jnp.arange(T, dtype=jnp.float32) * float(env.dt)
    freq = jnp.linspace(cfg["min_freq"], cfg["max_freq"], n)
    phase = jax.random.uniform(k_phase, (n, A), maxval=2 * np.pi)
    u = cfg["amplitude"] * jnp.sin(freq[:, None, None] * t[None, :, None] + phase[:, None, :])
    fit_keys = jax.random.split(k_fit, n)
    loss_grad = jax.vmap(jax.value_and_grad(lambda u, k: -episode_return(u, k)))
    opt = optax.adam(cfg["learning_rate"])

    @jax.jit
    def update(u, opt_state):
        loss, g = loss_grad(u, fit_keys)
        upd, opt_state = jax.vmap(opt.update)(g, opt_state)
        return optax.apply_updates(u, upd), opt_state, -loss

    opt_state = jax.vmap(opt.init)(u)
    history = []
    for i in range(int(cfg["steps"])):
        u, opt_state, rets = update(u, opt_state)
        if i % 50 == 49 or i == int(cfg["steps"]) - 1:
            rets = np.asarray(rets)
            history.append({"step": i + 1, "best": round(float(rets.max()), 3),
                            "median": round(float(np.median(rets)), 3)})
            log(f"[{task_name}] trajopt step {i + 1}/{cfg['steps']}: return best "
                f"{rets.max():.2f}, median {np.median(rets):.2f}  elapsed "
                f"{time.perf_counter() - t0:.0f}s")
    select_keys = jax.random.split(k_select, int(cfg["select_episodes"]))
    held_out = np.asarray(jax.jit(jax.vmap(jax.vmap(episode_return, (None, 0)), (0, None)))(
        u, select_keys)).mean(axis=1)
    best = int(np.argmax(held_out))
    actions = np.asarray(jnp.tanh(u[best]), np.float32)
    param_path, meta_path = _output_paths(task_name, out_dir)
    with open(param_path, "wb") as f:
        f.write(serialization.msgpack_serialize({"actions": actions}))
    with open(meta_path, "w") as f:
        json.dump({"task": task_name, "algorithm": "trajopt", "seed": seed, "trajopt": cfg,
                   "chosen_start": best, "select_returns": [round(float(r), 3) for r in held_out],
                   "complete": True, "wall_clock_s": round(time.perf_counter() - t0, 1),
                   "machine": machine(), "versions": library_versions(), "history": history},
                  f, indent=1, sort_keys=True)
    log(f"[{task_name}] open-loop expert saved to {param_path} (start {best}: mean return "
        f"{held_out[best]:.2f} over {len(select_keys)} held-out initial states; "
        f"{time.perf_counter() - t0:.0f}s)")
    return param_path


class _TimeUp(Exception):
    pass


def ppo_config(task_name: str, preset: str = "cpu", num_timesteps: int | None = None,
               overrides: dict | None = None, algorithm: str = "ppo") -> dict:
    """The recipe of `algorithm` (ppo or sac) for a task, with --steps/--set applied."""
    if algorithm not in RECIPES:
        raise ValueError(f"unknown expert algorithm {algorithm!r} for these recipes; "
                         f"algorithms: {', '.join(RECIPES)} (trajopt has TRAJOPT_CONFIGS)")
    algo = algorithm.upper()
    presets = RECIPES[algorithm]
    if preset not in presets:
        raise ValueError(f"unknown {algo} expert preset {preset!r}; presets: "
                         f"{', '.join(presets)}")
    table = presets[preset]
    if task_name not in table:
        raise ValueError(f"no {algo} expert recipe for task {task_name!r} in preset {preset!r}; "
                         f"recipes exist for {', '.join(sorted(table))} (pointmass and cloth "
                         f"have hand-made experts)")
    cfg = dict(table[task_name])
    if num_timesteps is not None:
        if int(num_timesteps) <= 0:
            raise ValueError(f"--steps must be positive, got {num_timesteps}")
        cfg["num_timesteps"] = int(num_timesteps)
    for k, v in (overrides or {}).items():
        if k not in cfg:
            raise ValueError(f"unknown {algo} setting {k!r} for the {preset} recipe of "
                             f"{task_name!r}; "
                             f"settings: {', '.join(sorted(cfg))}")
        if isinstance(cfg[k], bool):
            if str(v).lower() not in ("true", "false"):
                raise ValueError(f"{algo} setting {k!r} takes true or false, got {v!r}")
            cfg[k] = str(v).lower() == "true"
        else:
            cfg[k] = type(cfg[k])(float(v)) if isinstance(cfg[k], int) else type(cfg[k])(v)
    return cfg


def training_env_kwargs(task_name: str, env_overrides: dict | None = None) -> dict:
    """Training-only environment arguments (`--env-set`: reward shaping of the demonstrator,
    values parsed as numbers or true/false), checked against the task env's constructor.
    Demos, references and every score use the task's own environment."""
    import inspect

    env = make_task(task_name).env.unwrapped
    fixed = ("self", "sys", "backend", "kwargs")
    accepted = [a for a in inspect.signature(type(env).__init__).parameters if a not in fixed]
    kw = {}
    for k, v in (env_overrides or {}).items():
        if k not in accepted:
            raise ValueError(f"--env-set: {make_task(task_name).spec.env} takes no argument "
                             f"{k!r}; it takes {', '.join(accepted)}")
        low = str(v).lower()
        kw[k] = low == "true" if low in ("true", "false") else float(v)
    return kw


def _output_paths(task_name: str, out_dir: str | None) -> tuple[str, str]:
    """(parameter file, json) of an expert being trained: tasks/data, or `out_dir`."""
    paths = expert_paths(task_name)
    if out_dir is not None:
        paths = tuple(os.path.join(out_dir, os.path.basename(p)) for p in paths)
    os.makedirs(os.path.dirname(paths[0]), exist_ok=True)
    return paths


def train_expert(task_name: str, seed: int = 0, num_timesteps: int | None = None,
                 log=_print, preset: str = "cpu", time_limit_s: float | None = None,
                 out_dir: str | None = None, resume: str | None = None,
                 overrides: dict | None = None, env_overrides: dict | None = None,
                 algorithm: str = "ppo") -> str:
    """Train a PPO (or SAC: `algorithm="sac"`) expert and store it; returns the parameter
    file path.

    The stored parameters are those of the best evaluation so far (brax's eval return over
    the recipe's episode length), written at every improvement, so an interrupted or
    time-limited training (`time_limit_s`: stop at the first evaluation past it) leaves a
    usable expert; its json says `complete: false` until training ends normally. Beside a
    PPO expert, <task>_expert_value.msgpack holds the value network (not committed: only
    `resume`, a folder of an earlier run, reads it to continue training from its best
    evaluation). brax's SAC hands out no parameters during training, so a SAC run writes
    brax checkpoints at each evaluation into a scratch folder and keeps the best one's
    normalizer and policy (SAC runs cannot resume: the replay buffer is not saved).
    """
    if algorithm == "sac" and resume is not None:
        raise ValueError("--resume continues PPO runs only (brax SAC's replay buffer is not "
                         "saved); rerun SAC from its seed")
    from brax.training.agents.ppo import train as ppo

    from tasks.jax_compat import apply as jax_compat
    shims = jax_compat()
    if shims:
        log(f"[{task_name}] jax {jax.__version__}: restored {', '.join(shims)} for brax")
    cfg = ppo_config(task_name, preset, num_timesteps, overrides, algorithm)
    task = make_task(task_name)
    train_env = training_env_kwargs(task_name, env_overrides)
    env = task.env
    if train_env:
        import dataclasses

        from tasks.core import build_env
        spec = task.spec
        env = build_env(dataclasses.replace(
            spec, env_kwargs=tuple({**spec.kwargs(), **train_env}.items())))
        log(f"[{task_name}] training environment shaped: {train_env} (demos and scores use "
            f"the task's own)")
    param_path, meta_path = _output_paths(task_name, out_dir)
    from bench.machine import machine
    t0 = time.perf_counter()
    history: list[dict] = []
    best = {"ret": -np.inf, "step": None}

    value_path = param_path.replace("_expert.msgpack", "_expert_value.msgpack")
    restore, resumed = None, None
    if resume is not None:
        restore, resumed = _load_for_resume(task, task_name, resume)
        log(f"[{task_name}] resuming from {resume} (its best evaluation: step "
            f"{resumed['best_eval_step']:,d}, return {resumed['best_eval_return']:.2f})")

    def write_meta(complete, stopped=None):
        with open(meta_path, "w") as f:
            json.dump({"task": task_name, "algorithm": f"brax {algorithm.upper()}", "seed": seed,
                       "preset": preset, algorithm: cfg, "train_env": train_env,
                       "best_eval_step": best["step"],
                       "best_eval_return": best["ret"], "complete": complete,
                       "stopped": stopped,
                       "resumed_from": resumed,
                       "wall_clock_s": round(time.perf_counter() - t0, 1),
                       "machine": machine(), "versions": library_versions(),
                       "evals": history}, f, indent=1, sort_keys=True)

    def write(params):
        state = jax.tree.map(np.asarray, serialization.to_state_dict(
            {"normalizer": params[0], "policy": params[1]}))
        if algorithm == "sac":
            state["algorithm"] = "sac"  # a plain string: msgpack stores it as such
        with open(param_path, "wb") as f:
            f.write(serialization.msgpack_serialize(state))
        if len(params) > 2:  # PPO's value network, for --resume (SAC hands out none)
            with open(value_path, "wb") as f:
                f.write(serialization.msgpack_serialize(
                    serialization.to_state_dict(jax.tree.map(np.asarray, params[2]))))
        write_meta(complete=False)

    # brax calls policy_params_fn(step, ...) and progress_fn(step, eval of those params) in
    # either order (initial evaluation first; in the loop, parameters first): pair them by step.
    pending: dict = {}

    def consider():
        if "params" in pending and "ret" in pending and pending["p_step"] == pending["r_step"]:
            ret = pending["ret"]
            if np.isfinite(ret) and ret > best["ret"]:
                best.update(ret=ret, step=pending["p_step"])
                write(pending["params"])
            pending.clear()

    ckpt_dir = tempfile.mkdtemp(prefix=f"ildbench-{task_name}-sac-") if algorithm == "sac" else None

    def sac_checkpoint(step, ret):
        """brax SAC saved this evaluation's (normalizer, policy) under ckpt_dir/<step>
        (nothing at step 0, the untrained policy's evaluation)."""
        path = os.path.join(ckpt_dir, f"{step:012d}")
        if step and os.path.isdir(path):
            if np.isfinite(ret) and ret > best["ret"]:
                from brax.training import checkpoint
                best.update(ret=ret, step=step)
                write(tuple(checkpoint.load(path)))
            shutil.rmtree(path)

    def progress(step, metrics):
        el = time.perf_counter() - t0
        ret = float(metrics.get("eval/episode_reward", np.nan))
        history.append({"step": int(step), "eval_return": round(ret, 3), "elapsed_s": round(el, 1)})
        left = el / max(step, 1) * (cfg["num_timesteps"] - step) if step else float("nan")
        log(f"[{task_name}] steps {step:>11,d}/{cfg['num_timesteps']:,d}  eval return "
            f"{ret:9.2f}  elapsed {el:6.0f}s  left ~{left:6.0f}s")
        if algorithm == "sac":
            sac_checkpoint(int(step), ret)
        else:
            pending.update(ret=ret, r_step=int(step))
            consider()
        if step and time_limit_s is not None and el > time_limit_s:
            raise _TimeUp

    def on_params(step, make_policy, params):
        pending.update(params=jax.tree.map(np.asarray, params), p_step=int(step))
        consider()

    try:
        if algorithm == "sac":
            from brax.training.agents.sac import train as sac
            sac.train(environment=env, seed=seed, progress_fn=progress,
                      checkpoint_logdir=ckpt_dir, **cfg)
        else:
            ppo.train(environment=env, seed=seed, progress_fn=progress,
                      policy_params_fn=on_params, restore_params=restore, **cfg)
        complete, stopped = True, None
    except _TimeUp:
        complete, stopped = False, f"time limit {time_limit_s:.0f}s"
        log(f"[{task_name}] time limit {time_limit_s:.0f}s reached; keeping the best "
            f"evaluation's parameters")
    except KeyboardInterrupt:  # Ctrl-C: a usable expert and an honest record, not a traceback
        complete, stopped = False, "interrupted"
        log(f"[{task_name}] interrupted; keeping the best evaluation's parameters")
    finally:
        if ckpt_dir is not None:
            shutil.rmtree(ckpt_dir, ignore_errors=True)
    if not np.isfinite(best["ret"]):
        raise RuntimeError(f"[{task_name}] no finite evaluation return; nothing saved")
    write_meta(complete, stopped)  # the final status (parameters: the best evaluation's)
    log(f"[{task_name}] expert saved to {param_path} (best eval return {best['ret']:.2f} at "
        f"step {best['step']:,d}; {time.perf_counter() - t0:.0f}s)")
    return param_path


def _load_for_resume(task: Task, task_name: str, folder: str):
    """(normalizer, policy, value) of an earlier run's best evaluation, and its record."""
    base = os.path.join(folder, f"{task_name}_expert")
    paths = [base + ".msgpack", base + "_value.msgpack", base + ".json"]
    missing = [p for p in paths if not os.path.exists(p)]
    if missing:
        raise FileNotFoundError(f"cannot resume {task_name!r} from {folder}: missing "
                                f"{', '.join(missing)} (written by `ildbench expert train "
                                f"--out {folder}`)")
    nets, pol = _restore_ppo_params(task, paths[0])
    with open(paths[1], "rb") as f:
        value = serialization.from_state_dict(nets.value_network.init(jax.random.PRNGKey(0)),
                                              serialization.msgpack_restore(f.read()))
    with open(paths[2]) as f:
        meta = json.load(f)
    return (pol["normalizer"], pol["policy"], value), {
        "folder": folder, "best_eval_step": meta["best_eval_step"],
        "best_eval_return": meta["best_eval_return"], "previous": meta.get("resumed_from")}


@functools.lru_cache(maxsize=None)
def expert_policy(task_name: str):
    """The task's expert as a bench.api.Policy (deterministic = its mode)."""
    from bench.api import Policy

    if task_name == "pointmass":
        return Policy(act=_pd_act, params=())
    if task_name == "cloth":  # the original's hand-crafted open-loop expert
        from tasks.cloth.env import expert_actions
        return Policy(act=_open_loop_act, params=jnp.asarray(expert_actions()),
                      init_memory=_step_zero)
    param_path, _ = expert_paths(task_name)
    if not os.path.exists(param_path):
        raise FileNotFoundError(f"task {task_name!r} has no expert at {param_path}; train one "
                                f"with `ildbench expert train --task {task_name}`")
    return load_expert_policy(task_name, param_path)


def load_expert_policy(task_name: str, param_path: str):
    """An expert parameter file as a bench.api.Policy: an open-loop action table
    (trajopt experts) or PPO's normalizer + policy."""
    from bench.api import Policy
    with open(param_path, "rb") as f:
        raw = serialization.msgpack_restore(f.read())
    if "actions" in raw:
        actions = np.asarray(raw["actions"])
        task = make_task(task_name)
        if actions.shape != (task.episode_length, task.action_size):
            raise ValueError(f"{param_path}: an open-loop expert for {task_name!r} needs actions "
                             f"of shape {(task.episode_length, task.action_size)}, found "
                             f"{actions.shape}; retrain it with `ildbench expert train --task "
                             f"{task_name}`")
        return Policy(act=_open_loop_act, params=jnp.asarray(actions), init_memory=_step_zero)
    if raw.get("algorithm") == "sac":
        return load_sac_policy(task_name, param_path)
    return load_ppo_policy(task_name, param_path)


def _sac_networks(task: Task):
    from brax.training.acme import running_statistics
    from brax.training.agents.sac import networks as sac_networks
    return sac_networks.make_sac_networks(
        task.obs_size, task.action_size,
        preprocess_observations_fn=running_statistics.normalize)


def _restore_policy_params(task: Task, nets, param_path: str) -> dict:
    """{'normalizer', 'policy'} of a brax expert file (PPO or SAC), restored into the shapes
    of `nets`' policy network (a SAC file's `algorithm` tag is not a parameter)."""
    from brax.training.acme import running_statistics
    template = {"normalizer": running_statistics.init_state(
        jax.ShapeDtypeStruct((task.obs_size,), jnp.float32)),
        "policy": nets.policy_network.init(jax.random.PRNGKey(0))}
    with open(param_path, "rb") as f:
        raw = serialization.msgpack_restore(f.read())
    raw.pop("algorithm", None)
    return serialization.from_state_dict(template, raw)


def load_sac_policy(task_name: str, param_path: str):
    """A SAC expert parameter file (normalizer + policy) as a bench.api.Policy."""
    from bench.api import Policy
    from brax.training.agents.sac import networks as sac_networks

    task = make_task(task_name)
    nets = _sac_networks(task)
    params = _restore_policy_params(task, nets, param_path)
    inference = sac_networks.make_inference_fn(nets)
    return Policy(act=_PPOAct(inference), params=(params["normalizer"], params["policy"]))


def _restore_ppo_params(task: Task, param_path: str):
    """(networks, {'normalizer', 'policy'}) from a PPO expert parameter file."""
    nets = _ppo_networks(task)
    return nets, _restore_policy_params(task, nets, param_path)


def load_ppo_policy(task_name: str, param_path: str):
    """A PPO expert parameter file (normalizer + policy) as a bench.api.Policy."""
    from bench.api import Policy
    from brax.training.agents.ppo import networks as ppo_networks

    nets, params = _restore_ppo_params(make_task(task_name), param_path)
    inference = ppo_networks.make_inference_fn(nets)
    return Policy(act=_PPOAct(inference), params=(params["normalizer"], params["policy"]))


def _pd_act(params, obs, key, deterministic):
    from tasks.pointmass import pd_expert
    return pd_expert(obs)


def _open_loop_act(params, obs, key, deterministic, t):
    """Action t of an open-loop table (the step counter is the policy's memory)."""
    return params[jnp.minimum(t, params.shape[0] - 1)], t + 1


def _step_zero(params, key):
    return jnp.zeros((), jnp.int32)


class _PPOAct:
    """Hashable wrapper so the evaluator's compile cache keys on one object per task."""

    def __init__(self, inference):
        self._inference = inference

    def __call__(self, params, obs, key, deterministic):
        return self._inference(params, deterministic=deterministic)(obs, key)[0]


def rollout(task: Task, policy, keys: jax.Array, deterministic: bool = True) -> dict:
    """Roll `policy` from env.reset(key) for each key; arrays as in the demo format."""
    from bench.api import act_step, start_memory
    env, T = task.env, task.episode_length

    def episode(key):
        k_reset, k_act = jax.random.split(key)
        s0 = env.reset(k_reset)

        def body(carry, k):
            s, mem = carry
            a, mem = act_step(policy.act, policy.init_memory, policy.params, s.obs, k,
                              deterministic, mem)
            a = jnp.clip(a, -1.0, 1.0)
            s2 = env.step(s, a)
            return (s2, mem), (s.obs, task.matched_state(s), a, s2.reward, s2.done)

        mem = start_memory(policy.init_memory, policy.params, k_act)
        (sT, _), (obs, states, actions, rewards, dones) = jax.lax.scan(
            body, (s0, mem), jax.random.split(k_act, T))
        obs = jnp.concatenate([obs, sT.obs[None]])
        states = jnp.concatenate([states, task.matched_state(sT)[None]])
        return dict(obs=obs, states=states, actions=actions, rewards=rewards, dones=dones)

    out = jax.jit(jax.vmap(episode))(keys)
    return {k: np.asarray(v) for k, v in out.items()}


def _candidates(task: Task, policy, rollouts: int, seed: int):
    """Deterministic 128-step rollouts from `rollouts` initial states: (init_keys, rollout
    arrays, which ended early, returns)."""
    init_keys = jax.random.split(jax.random.PRNGKey(seed), rollouts)
    r = rollout(task, policy, init_keys)
    return init_keys, r, r["dones"].astype(bool).any(axis=1), r["rewards"].sum(1)


def _references(task: Task, policy) -> tuple[float, float]:
    """(R_expert, R_random): the shared evaluator on REFERENCE_EPISODES fixed episodes."""
    from bench.evaluator import EvalConfig, Evaluator, random_policy
    ev = Evaluator(task, EvalConfig(num_episodes=REFERENCE_EPISODES, deterministic=True))
    return (ev.evaluate(policy, REFERENCE_SEED).mean_return,
            ev.evaluate(random_policy(task.action_size), REFERENCE_SEED).mean_return)


def inspect_expert(task_name: str, param_path: str | None = None, rollouts: int = 64,
                   seed: int = 0) -> dict:
    """What `make_demo` would see of an expert parameter file (default: the task's own):
    how many of `rollouts` deterministic 128-step rollouts end early (the first termination
    step of each that does), the best and mean return of those that do not, and the shared
    evaluator's R_expert and R_random. `ildbench expert inspect` prints it."""
    task = make_task(task_name)
    param_path = param_path or expert_paths(task_name)[0]
    policy = load_expert_policy(task_name, param_path)
    _, r, ended, ret = _candidates(task, policy, rollouts, seed)
    dones = r["dones"].astype(bool)
    r_expert, r_random = _references(task, policy)
    return {"task": task_name, "params": param_path, "rollouts": rollouts,
            "ended_early": int(ended.sum()),
            "first_done_steps": sorted(int(np.argmax(d)) + 1 for d in dones[ended]),
            "best_return_kept": float(ret[~ended].max()) if (~ended).any() else None,
            "mean_return_kept": float(ret[~ended].mean()) if (~ended).any() else None,
            "expert_return": r_expert, "random_return": r_random}


def make_demo(task_name: str, rollouts: int = 64, keep: int = 16, seed: int = 0,
              log=_print) -> str:
    """Roll the expert, keep the best `keep` non-terminated episodes, measure references,
    and write tasks/data/<demo file>. Returns the path."""
    task = make_task(task_name)
    if task.spec.demo is None:
        raise ValueError(f"task {task_name!r} names no demo file in tasks/registry.py; add "
                         f"demo='{task_name}.npz' to its TaskSpec first")
    policy = expert_policy(task_name)
    # init_keys: one per candidate episode. The rollout splits each key into (reset, action)
    # keys: store the reset key (env.reset(reset_key) is the demo's s_0).
    init_keys, r, ended, returns = _candidates(task, policy, rollouts, seed)
    reset_keys = np.asarray(jax.vmap(lambda k: jax.random.split(k)[0])(init_keys))
    order = [i for i in np.argsort(-returns) if not ended[i]][:keep]
    if not order:
        raise RuntimeError(f"task {task_name!r}: every expert rollout terminated early; the "
                           "expert is not good enough for a demo")
    r_expert, r_random = _references(task, policy)
    _, meta_path = expert_paths(task_name)
    if task_name in _HANDMADE:
        expert_meta = {"source": _HANDMADE[task_name]}
    else:
        record = json.load(open(meta_path))
        source = {"trajopt": "open-loop trajectory optimization through the task's physics"}
        expert_meta = {"source": source.get(record.get("algorithm"),
                                            record.get("algorithm", "brax PPO")),
                       **{k: v for k, v in record.items()
                          if k in ("seed", "ppo", "sac", "trajopt", "train_env", "wall_clock_s")}}
    demo = Demo(
        obs=r["obs"][order].astype(np.float32), states=r["states"][order].astype(np.float32),
        actions=r["actions"][order].astype(np.float32),
        rewards=r["rewards"][order].astype(np.float32),
        init_keys=reset_keys[order].astype(np.uint32),
        returns=r["rewards"][order].sum(1).astype(np.float32),
        meta={"format_version": FORMAT_VERSION, "task": task_name,
              "backend": task.spec.backend, "episode_length": task.episode_length,
              "versions": library_versions(),
              "expert": {**expert_meta, "demo_seed": seed, "rollouts": rollouts,
                         "kept": len(order), "deterministic": True},
              "reference": {"expert_return": r_expert, "random_return": r_random,
                            "num_episodes": REFERENCE_EPISODES, "eval_seed": REFERENCE_SEED,
                            "deterministic": True}})
    path = task.spec.demo_path
    save_demo(path, demo)
    log(f"[{task_name}] demo saved to {path}: {len(order)} of {rollouts} rollouts kept "
        f"(top return {demo.returns[0]:.2f}); R_expert {r_expert:.2f}, R_random {r_random:.2f}")
    return path
