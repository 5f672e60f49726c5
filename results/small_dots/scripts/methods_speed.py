"""SHAC's epoch and CEM-MPC's planning step with and without `small_dots` (session 30),
side by side in one process, each at the method's cpu preset for TASK:

    python results/small_dots/scripts/methods_speed.py TASK [--epochs 5]

SHAC: seconds per training epoch (`num_envs` x `horizon` env steps through the physics and
back, then the critic's fit), compiled first, then the best of 3 rounds of `--epochs` epochs
from the same state. CEM-MPC: milliseconds per control step of planning (population x
iterations x horizon simulated steps), as its `train` measures and records it
(`plan/ms_per_step`). Prints each time and the ratio without / with.
"""
import argparse
import dataclasses
import sys
import time
from types import SimpleNamespace

import jax

from bench.access import TaskView
from bench.plugins import build_config, get_method
from tasks import make_task
from tasks.core import with_small_dots


def shac_epoch_seconds(task, config, epochs: int) -> float:
    shac = sys.modules["methods.shac.train"]
    if config.small_dots:
        task = with_small_dots(task)
    agent = shac.SHAC(task.env, task.obs_size, task.action_size, task.episode_length, config)
    s0 = agent.init(jax.random.PRNGKey(0))
    jax.block_until_ready(agent.epoch(s0))
    best = float("inf")
    for _ in range(3):
        s, t0 = s0, time.perf_counter()
        for _ in range(epochs):
            s, _ = agent.epoch(s)
        jax.block_until_ready(s)
        best = min(best, (time.perf_counter() - t0) / epochs)
    return best


def cem_plan_ms(name, config) -> float:
    spec = get_method("cem_mpc")
    view = TaskView(make_task(name), spec.uses, spec.name)
    cem = sys.modules["methods.cem_mpc.train"]
    result = cem.train(view, None, config, SimpleNamespace(log=lambda s: None), seed=0)
    return result.metrics["plan/ms_per_step"]


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("task")
    ap.add_argument("--epochs", type=int, default=5)
    args = ap.parse_args()
    task = make_task(args.task)
    # get_method loads the in-repo methods, so their train modules are in sys.modules.
    shac_cfg = build_config(get_method("shac"), args.task, "cpu", {})
    cem_cfg = build_config(get_method("cem_mpc"), args.task, "cpu", {})
    shac = {d: shac_epoch_seconds(task, dataclasses.replace(shac_cfg, small_dots=d), args.epochs)
            for d in (False, True)}
    cem = {d: cem_plan_ms(args.task, dataclasses.replace(cem_cfg, small_dots=d))
           for d in (False, True)}
    print(f"{args.task}: SHAC epoch ({shac_cfg.num_envs} envs x {shac_cfg.horizon} steps) "
          f"{shac[False]:.3f} s -> {shac[True]:.3f} s with small_dots "
          f"({shac[False] / shac[True]:.2f}x)")
    print(f"{args.task}: CEM-MPC planning ({cem_cfg.population} x {cem_cfg.iterations} x "
          f"{cem_cfg.horizon} steps) {cem[False]:.1f} ms -> {cem[True]:.1f} ms per control "
          f"step with small_dots ({cem[False] / cem[True]:.2f}x)")


if __name__ == "__main__":
    main()
