"""Speed of the SB3-based imitation methods vs plain SB3 TD3, side by side in one run.

    python -m methods.common.sb3_benchmark --task hopper --steps 1024 [--repeats 2]
                                           [--threads 2] [--out results/sb3_speed.csv]
                                           [--methods dac,pwil,dac_disc3]

For each method (dac, pwil) the plain learner is SB3's own TD3 with the SAME settings
(networks, batch, update-to-data ratio, vectorized env) on the task's true reward; the method
adds its imitation reward (and DAC its discriminator updates and absorbing states). Each
measures env-steps/s over `steps` env steps after learning has started (warm-up excluded);
runs alternate plain/method `repeats` times so machine drift hits both. Target: method /
plain >= 0.8 (the imitation reward must not dominate the cost). `dac_disc3` is DAC with
one discriminator update per 3 TD3 updates (`disc_every=3`, not the original schedule).
"""
from __future__ import annotations

import argparse
import importlib
import sys
import time

import numpy as np

from bench.access import TaskView
from bench.api import Uses
from methods.common.sb3 import BraxVecEnv, seed_everything, set_torch_threads
from methods.dac.config import DACConfig
from methods.pwil.config import PWILConfig
from tasks import make_task
from tasks.demo import load_demo

importlib.import_module("methods.dac")
importlib.import_module("methods.pwil")
dac = sys.modules["methods.dac.train"]
pwil = sys.modules["methods.pwil.train"]

IMITATION = Uses(demo_states=True, demo_actions=True)


def _mlp_macs(sizes) -> int:
    """Multiply-accumulates of one forward pass of an MLP with these layer widths."""
    return sum(a * b for a, b in zip(sizes[:-1], sizes[1:]))


def dac_arithmetic_ratio(obs_dim: int, act_dim: int, c: DACConfig = DACConfig()) -> float:
    """DAC / plain TD3 speed that the arithmetic alone allows (the learner bound, env time
    ignored), counting multiply-accumulates per update with backward = 2 x forward:
    TD3: target actor + 2 target critics + 2 critics (fwd + bwd) + every `policy_delay`-th
    update the actor through Q1 (fwd + bwd); DAC adds the reward (D forward on the TD3 batch)
    and one discriminator update: forward + backward on policy + expert rows, and the
    gradient penalty on the interpolates (forward, input gradient, and the double backward
    through both = 2 x (forward + input gradient))."""
    o = obs_dim + 1  # the absorbing indicator
    actor = _mlp_macs((o, *c.actor_hidden, act_dim))
    critic = _mlp_macs((o + act_dim, *c.critic_hidden, 1))
    disc = _mlp_macs((o + act_dim, *c.disc_hidden, 1))
    td3 = c.batch_size * (actor + 2 * critic + 3 * 2 * critic
                          + 3 * (actor + critic) / c.policy_delay)
    reward = c.batch_size * disc
    d_update = 3 * 2 * c.disc_batch * disc + (2 + 2 * 2) * c.disc_batch * disc
    return td3 / (td3 + reward + d_update / c.disc_every)


def _time(model, steps: int, warmup: int) -> float:
    model.learn(total_timesteps=warmup)
    t0 = time.perf_counter()
    model.learn(total_timesteps=steps, reset_num_timesteps=False)
    return steps / (time.perf_counter() - t0)


def builders(task_name: str):
    """name -> (plain TD3 with the method's settings on the true reward, the method)."""
    from stable_baselines3 import TD3
    task = make_task(task_name)
    demo = load_demo(task.spec.demo_path, task)
    gated = TaskView(task, IMITATION, "bench").env
    T = task.episode_length

    def dac_plain():
        c = DACConfig()
        return TD3(**dac.td3_settings(BraxVecEnv(task.env, c.num_envs, T), c, 0)), c

    def dac_method(disc_every=1):
        c = DACConfig(disc_every=disc_every)
        return dac.make_learner(gated, T, demo, c, 0), c

    def pwil_plain():
        c = PWILConfig()
        return pwil.build_model(BraxVecEnv(task.env, c.num_envs, T), c, 0), c

    def pwil_method():
        c = PWILConfig()
        return pwil.make_learner(gated, T, demo, c, 0)[0], c

    return {"dac": (dac_plain, dac_method), "pwil": (pwil_plain, pwil_method),
            # not the original schedule: one discriminator update per 3 TD3 updates
            "dac_disc3": (dac_plain, lambda: dac_method(disc_every=3))}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--task", default="hopper")
    ap.add_argument("--methods", default="dac,pwil")
    ap.add_argument("--steps", type=int, default=1024)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--out", default=None, help="append rows to this CSV")
    args = ap.parse_args(argv)
    set_torch_threads(args.threads)
    rows = []
    task = make_task(args.task)
    for name, (plain, method) in builders(args.task).items():
        if name not in args.methods.split(","):
            continue
        rates = {"plain": [], "method": []}
        for _ in range(args.repeats):
            for kind, build in (("plain", plain), ("method", method)):
                seed_everything(0)
                model, cfg = build()
                rates[kind].append(_time(model, args.steps, cfg.learning_starts + 256))
        p, m = np.median(rates["plain"]), np.median(rates["method"])
        bound = (dac_arithmetic_ratio(task.obs_size, task.action_size, cfg)
                 if name.startswith("dac") else float("nan"))
        rows.append(dict(task=args.task, method=name, threads=args.threads, steps=args.steps,
                         plain_td3_steps_per_s=round(p, 1), method_steps_per_s=round(m, 1),
                         ratio=round(m / p, 3), arithmetic_ratio=round(bound, 3)))
        print(f"{args.task:>10s} {name:>5s}: plain TD3 {p:7.1f} env-steps/s, {name} {m:7.1f} "
              f"env-steps/s, ratio {m / p:.2f} (target >= 0.8; threads {args.threads}; "
              f"the arithmetic alone allows {bound:.2f})", flush=True)
    if args.out:
        from bench.report import append_csv
        append_csv(rows, args.out)
    return rows


if __name__ == "__main__":
    main()
