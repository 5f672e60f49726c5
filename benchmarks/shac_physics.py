"""SHAC's update against its forward rollout, on brax's step and on the task's physics plan,
side by side in one process per task:

    python -m benchmarks.shac_physics [--tasks hopper ant ...] [--repeats 3]
        [--out results/speed/shac_physics.csv]

For each task and each physics (`reference`: brax's step as it is; `plan`: the task's
physics plan on this platform, `tasks.physics.plan`), with SHAC's config as it trains the
task (the cpu preset: 32 actors, 32-step windows):
  forward   the actor's window without a gradient: the 32-step rollout of every actor,
            the policy's samples, rewards and the target critic's values (SHAC's
            `actor_loss`, value only)
  update    one SHAC epoch: the actor's gradient through that window and the physics, its
            Adam step, then the critic's TD-lambda iterations (`SHAC.epoch`)
Each is compiled first (compile seconds reported) and timed over `--repeats` calls (the
median). The summary prints, per task, update / forward on each physics and the plan's
update speed-up over brax's step: the measure of what the plan buys a method that
differentiates through the physics without being written for it. A plan changes what a
gradient costs, never what it is (docs/physics.md).
"""
from __future__ import annotations

import argparse
import csv
import os
import statistics
import time

import jax

from bench.plugins import build_config, current_platform, get_method
from tasks import make_task
from tasks.physics import REFERENCE, apply, plan_for

TASKS = ("inverted_pendulum", "reacher", "acrobot", "swimmer", "hopper", "walker2d", "ant",
         "humanoid")


def _time(fn, args, repeats: int) -> tuple[float, float]:
    """(median seconds per call, compile seconds) of jitted `fn` on `args`."""
    t0 = time.perf_counter()
    jax.block_until_ready(fn(*args))
    compile_s = time.perf_counter() - t0
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t0)
    return statistics.median(times), compile_s


def measure(task_name: str, repeats: int = 3, preset: str = "cpu") -> list[dict]:
    """One row per (physics, what) on `task_name`."""
    from methods.shac.train import SHAC
    config = build_config(get_method("shac"), task_name, preset)
    base = make_task(task_name)
    rows = []
    plans = {"reference": REFERENCE, "plan": plan_for(task_name, current_platform())}
    for physics, plan in plans.items():
        task = apply(base, plan)
        agent = SHAC(task.env, task.obs_size, task.action_size, task.episode_length, config)
        s = agent.init(jax.random.PRNGKey(0))
        forward = jax.jit(lambda actor, st: agent.actor_loss(actor, st)[0])
        for what, fn, args in (("forward", forward, (s.actor, s)),
                               ("update", agent.epoch, (s,))):
            sec, comp = _time(fn, args, repeats)
            rows.append({"task": task_name, "physics": physics,
                         "rewrites": plan.describe(), "what": what,
                         "num_envs": config.num_envs, "horizon": config.horizon,
                         "seconds": float(f"{sec:.4g}"), "compile_s": round(comp, 1)})
            print(rows[-1], flush=True)
    return rows


def summary(rows: list[dict]) -> list[str]:
    """Per task: update / forward on each physics, and the plan's update speed-up."""
    by = {(r["task"], r["physics"], r["what"]): r["seconds"] for r in rows}
    lines = ["| task | update / forward, brax's step | update / forward, plan | "
             "plan's update speed-up |", "|---|---|---|---|"]
    for task in dict.fromkeys(r["task"] for r in rows):
        ref = by[task, "reference", "update"] / by[task, "reference", "forward"]
        plan = by[task, "plan", "update"] / by[task, "plan", "forward"]
        speed = by[task, "reference", "update"] / by[task, "plan", "update"]
        lines.append(f"| {task} | {ref:.2f} | {plan:.2f} | {speed:.2f}x |")
    return lines


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--tasks", nargs="+", default=list(TASKS))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--out", default=None, help="CSV of the rows (appended per task)")
    a = ap.parse_args(argv)
    rows = []
    for task in a.tasks:
        new = measure(task, a.repeats, a.preset)
        rows += new
        if a.out:
            os.makedirs(os.path.dirname(a.out) or ".", exist_ok=True)
            fresh = not os.path.exists(a.out)
            with open(a.out, "a", newline="") as f:
                w = csv.DictWriter(f, fieldnames=list(new[0]))
                if fresh:
                    w.writeheader()
                w.writerows(new)
    print("\n".join(summary(rows)))
    return rows


if __name__ == "__main__":
    main()
