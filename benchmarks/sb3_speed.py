"""Speed of the SB3-based imitation methods vs plain SB3 TD3, side by side in one run.

    python -m benchmarks.sb3_speed --tasks hopper humanoid [--utd 1 0.25]
        [--steps 1024] [--repeats 2] [--threads 1] [--methods dac,pwil]
        [--out results/speed/sb3/throughput.csv]

For each method (dac, pwil) the plain learner is SB3's own TD3 with the SAME settings
(networks, observation normalizer, batch, update-to-data ratio, vectorized env) on the
task's true reward; the method adds its imitation reward (DAC: its discriminator updates
and absorbing states; PWIL: the coupling and the demo rows of its replay). Each run measures
env steps/s and learner updates/s over `steps` env steps after learning has started
(warm-up excluded); runs alternate plain/method `repeats` times so machine drift hits both,
and the medians are printed side by side with their ratio. Target: method / plain >= 0.75
at the original's update-to-data ratio (1) on one core. `--utd 0.25` measures the speed
knob `updates_per_step` (results/speed/sb3/README.md). `dac_disc3` is DAC with
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
from stable_baselines3.common.buffers import NStepReplayBuffer

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


def _time(model, steps: int, warmup: int) -> tuple[float, float]:
    """(env steps/s, updates/s) over `steps` env steps after a `warmup`-step start."""
    model.learn(total_timesteps=warmup)
    n0, t0 = model._n_updates, time.perf_counter()
    model.learn(total_timesteps=steps, reset_num_timesteps=False)
    dt = time.perf_counter() - t0
    return steps / dt, (model._n_updates - n0) / dt


def builders(task_name: str, utd: float = 1.0):
    """name -> (plain TD3 with the method's settings on the true reward, the method)."""
    from stable_baselines3 import TD3

    from methods.common.sb3 import ObsNormalizer
    task = make_task(task_name)
    demo = load_demo(task.spec.demo_path, task)
    gated = TaskView(task, IMITATION, "bench").env
    T = task.episode_length
    demo_obs = np.asarray(demo.obs[0, :-1])

    def dac_plain():
        c = DACConfig(updates_per_step=utd)
        norm = ObsNormalizer(task.obs_size, init=demo_obs)
        return TD3(**dac.td3_settings(BraxVecEnv(task.env, c.num_envs, T), c, 0, norm)), c

    def dac_method(disc_every=1):
        c = DACConfig(disc_every=disc_every, updates_per_step=utd)
        return dac.make_learner(gated, T, demo, c, 0), c

    def pwil_plain():
        c = PWILConfig(updates_per_step=utd, horizon=T)
        norm = ObsNormalizer(task.obs_size, init=demo_obs)
        return TD3(**pwil.td3_kwargs(BraxVecEnv(task.env, c.num_envs, T), c, c.learning_rate, 0,
                                     norm), replay_buffer_class=NStepReplayBuffer,
                   replay_buffer_kwargs=dict(n_steps=c.n_step, gamma=c.gamma)), c

    def pwil_method():
        c = PWILConfig(updates_per_step=utd, horizon=T)
        return pwil.make_learner(gated, T, demo, c, 0)[0], c

    return {"dac": (dac_plain, dac_method), "pwil": (pwil_plain, pwil_method),
            # not the original schedule: one discriminator update per 3 TD3 updates
            "dac_disc3": (dac_plain, lambda: dac_method(disc_every=3))}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tasks", nargs="+", default=["hopper"])
    ap.add_argument("--methods", default="dac,pwil")
    ap.add_argument("--utd", nargs="+", type=float, default=[1.0])
    ap.add_argument("--steps", type=int, default=1024)
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--out", default=None, help="append rows to this CSV")
    args = ap.parse_args(argv)
    set_torch_threads(args.threads)
    rows = []
    for task_name in args.tasks:
        task = make_task(task_name)
        for utd in args.utd:
            for name, (plain, method) in builders(task_name, utd).items():
                if name not in args.methods.split(","):
                    continue
                rates = {"plain": [], "method": []}
                for _ in range(args.repeats):
                    for kind, build in (("plain", plain), ("method", method)):
                        seed_everything(0)
                        model, cfg = build()
                        rates[kind].append(_time(model, args.steps, cfg.learning_starts + 256))
                (ps, pu), (ms, mu) = (np.median(rates[k], axis=0) for k in ("plain", "method"))
                bound = (dac_arithmetic_ratio(task.obs_size, task.action_size, cfg)
                         if name.startswith("dac") else float("nan"))
                rows.append(dict(task=task_name, method=name, utd=utd, threads=args.threads,
                                 steps=args.steps, plain_env_steps_per_s=round(ps, 1),
                                 plain_updates_per_s=round(pu, 1),
                                 method_env_steps_per_s=round(ms, 1),
                                 method_updates_per_s=round(mu, 1), ratio=round(ms / ps, 3),
                                 arithmetic_ratio=round(bound, 3)))
                print(f"{task_name:>10s} {name:>9s} utd {utd:<5g}: plain TD3 {ps:6.1f} env "
                      f"steps/s {pu:6.1f} updates/s | {name} {ms:6.1f} env steps/s {mu:6.1f} "
                      f"updates/s | ratio {ms / ps:.2f} (target >= 0.75; the arithmetic alone "
                      f"allows {bound:.2f}; threads {args.threads})", flush=True)
    if args.out:
        from bench.report import append_csv
        append_csv(rows, args.out)
    return rows


if __name__ == "__main__":
    main()
