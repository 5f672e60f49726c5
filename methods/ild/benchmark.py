"""ILD speed, measured side by side in one process on the same task, backend, batch,
horizon (128) and policy network (512-256 swish, tanh-Gaussian):

    python -m methods.ild.benchmark --task hopper --batch 32 [--out results/ild_speed.csv]

rows:
  forward      the batched 128-step rollout + Chamfer loss, value only
  ild          one full ILD update (rollout, Chamfer, backward through the physics with
               per-step gradient normalization and truncation 10, clip, Adam)
  ild_no_gn    the same without per-step gradient normalization
  ild_remat    the same with jax.checkpoint on every step (rematerialization)
  chamfer      Chamfer-alpha alone, value and gradient, on (B, 128, D) states
  apg          brax's own APG trainer (brax.training.agents.apg), horizon 128, same network;
               its steady-state 'training/sps' (a later epoch, compile excluded)
Each jitted function is compiled first (compile seconds reported) and then timed over
`--repeats` calls. Targets (issue 4): ild >= 1.2x apg env-steps/s; ild <= 3x forward.
Goals are random states of the task's matched-state size: speed does not depend on them.
"""
from __future__ import annotations

import argparse
import csv
import dataclasses
import os
import time

import jax
import jax.numpy as jnp

from methods.common.policy import ObsNorm, TanhGaussianPolicy
from methods.ild.config import ILDConfig
from methods.ild.losses import chamfer_alpha
from methods.ild.train import StateNorm, TrainingState, make_rollout_loss, make_update
from tasks import make_task


def _time(fn, args, repeats):
    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    compile_s = time.perf_counter() - t0
    jax.block_until_ready(compiled(*args))
    t0 = time.perf_counter()
    for _ in range(repeats):
        jax.block_until_ready(compiled(*args))
    return (time.perf_counter() - t0) / repeats, compile_s


def _apg_sps(task, batch, hidden):
    from brax.training.agents.apg import networks as apg_networks
    from brax.training.agents.apg import train as apg
    from flax import linen

    sps = []

    def factory(obs_size, action_size, preprocess_observations_fn):
        return apg_networks.make_apg_networks(obs_size, action_size,
                                              preprocess_observations_fn, hidden, linen.swish,
                                              layer_norm=False)

    apg.train(environment=task.env, episode_length=task.episode_length, policy_updates=3,
              horizon_length=task.episode_length, num_envs=batch, num_evals=4,
              num_eval_envs=batch, network_factory=factory,
              progress_fn=lambda it, m: sps.append(float(m["training/sps"]))
              if "training/sps" in m else None)
    return sps[-1]  # the last epoch: compiled already


def run(task_name: str, batch: int, repeats: int, with_apg: bool = True) -> list[dict]:
    task = make_task(task_name)
    T = task.episode_length
    base = ILDConfig(num_envs=batch)
    policy = TanhGaussianPolicy(task.obs_size, task.action_size, base.hidden)
    k = jax.random.split(jax.random.PRNGKey(0), 4)
    goals = jax.random.normal(k[0], (1, T, task.state_size))
    norm = StateNorm(jnp.zeros(task.state_size), jnp.ones(task.state_size))
    params = policy.init(k[1], ObsNorm(jnp.zeros(task.obs_size), jnp.ones(task.obs_size)))
    init_keys = jax.random.split(k[2], batch)
    steps = batch * T
    rows = []

    def row(name, sec, compile_s):
        rows.append({"task": task_name, "backend": task.spec.backend, "batch": batch,
                     "what": name, "seconds": round(sec, 4),
                     "env_steps_per_s": round(steps / sec, 1),
                     "compile_s": round(compile_s, 1)})
        print(rows[-1], flush=True)

    loss_fn = make_rollout_loss(task, policy, goals, norm, base)
    sec, c = _time(lambda p: loss_fn(p, k[3], init_keys)[0], (params,), repeats)
    row("forward", sec, c)
    for name, cfg in (("ild", base), ("ild_no_gn", dataclasses.replace(
            base, grad_normalization=False)), ("ild_remat", dataclasses.replace(base, remat=True))):
        update, opt, _ = make_update(task, policy, goals, norm, cfg, k[2])
        state = TrainingState(params, opt.init(params), k[3], jnp.zeros((), jnp.int32))
        sec, c = _time(lambda s: update(s, None)[0], (state,), repeats)
        row(name, sec, c)
    x = jax.random.normal(k[3], (batch, T, task.state_size))
    cham = jax.value_and_grad(lambda x: jnp.mean(jax.vmap(
        lambda xb: chamfer_alpha(xb, goals[0]).loss)(x)))
    sec, c = _time(cham, (x,), repeats)
    row("chamfer", sec, c)
    if with_apg:
        t0 = time.perf_counter()
        sps = _apg_sps(task, batch, base.hidden)
        row("apg", steps / sps, time.perf_counter() - t0)
    by = {r["what"]: r for r in rows}
    ratios = {"update_over_forward": by["ild"]["seconds"] / by["forward"]["seconds"],
              "chamfer_share_of_update": by["chamfer"]["seconds"] / by["ild"]["seconds"]}
    if "apg" in by:
        ratios["ild_over_apg_steps_per_s"] = (by["ild"]["env_steps_per_s"] /
                                              by["apg"]["env_steps_per_s"])
    print({k: round(v, 3) for k, v in ratios.items()}, flush=True)
    for r in rows:
        r.update({k: round(v, 3) for k, v in ratios.items()})
    return rows


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", default="hopper")
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--no-apg", action="store_true")
    p.add_argument("--out", default=None, help="append rows to this CSV")
    a = p.parse_args(argv)
    rows = run(a.task, a.batch, a.repeats, not a.no_apg)
    if a.out:
        new = not os.path.exists(a.out)
        with open(a.out, "a", newline="") as f:
            w = csv.DictWriter(f, list(rows[0]))
            if new:
                w.writeheader()
            w.writerows(rows)


if __name__ == "__main__":
    main()
