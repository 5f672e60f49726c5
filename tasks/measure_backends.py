"""Measure forward and gradient env-steps/s of each candidate physics backend per task.

    python -m tasks.measure_backends [--tasks hopper ant] [--batch 32] [--out results/backends.csv]

For every (task, backend): a jitted, vmapped 128-step rollout of B envs under fixed random
actions (forward), and the gradient of a scalar of the matched states w.r.t. those actions
through the whole rollout (gradient, reverse mode). Each is compiled first (compile seconds
recorded) and timed over repeats after a warm-up; the gradient is checked finite. Rows are
appended as they finish, and rows already in the file are skipped, so it can be resumed.
"""
from __future__ import annotations

import argparse
import csv
import os
import time

import jax
import jax.numpy as jnp
import numpy as np

from tasks import TASKS, get_spec
from tasks.core import Task, open_loop, task_with_backend

CANDIDATES = ("generalized", "positional", "spring")
FIELDS = ["task", "backend", "batch", "horizon", "fwd_steps_per_s", "grad_steps_per_s",
          "grad_over_fwd", "fwd_compile_s", "grad_compile_s", "grad_finite", "error"]


def _rollout_fn(task: Task, horizon: int):
    env = task.env

    def rollout(actions, key):  # actions (H, act)
        return open_loop(env.step, env.reset(key), actions, task.matched_state)[1]

    return rollout


def measure(task: Task, batch: int, horizon: int, repeats: int = 3,
            action_scale: float = 0.3) -> dict:
    rollout = _rollout_fn(task, horizon)
    keys = jax.random.split(jax.random.PRNGKey(0), batch)
    # Moderate random actions: at full scale some tasks (inverted_pendulum) drive the state
    # itself to NaN within 128 steps, which would time NaN arithmetic, not physics.
    actions = action_scale * jax.random.uniform(
        jax.random.PRNGKey(1), (batch, horizon, task.action_size), minval=-1, maxval=1)
    fwd = jax.jit(jax.vmap(rollout))
    loss = lambda a: jnp.mean(jax.vmap(rollout)(a, keys) ** 2)
    grad = jax.jit(jax.grad(loss))

    def timed(f, *args):
        t0 = time.perf_counter()
        compiled = f.lower(*args).compile()
        c = time.perf_counter() - t0
        jax.block_until_ready(compiled(*args))  # warm-up
        t0 = time.perf_counter()
        for _ in range(repeats):
            out = jax.block_until_ready(compiled(*args))
        return out, c, (time.perf_counter() - t0) / repeats

    _, fwd_c, fwd_t = timed(fwd, actions, keys)
    g, grad_c, grad_t = timed(grad, actions)
    steps = batch * horizon
    return dict(fwd_steps_per_s=round(steps / fwd_t, 1), grad_steps_per_s=round(steps / grad_t, 1),
                grad_over_fwd=round(grad_t / fwd_t, 2), fwd_compile_s=round(fwd_c, 1),
                grad_compile_s=round(grad_c, 1),
                grad_finite=bool(np.isfinite(np.asarray(g)).all()), error="")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tasks", nargs="*", default=[n for n in TASKS if n != "pointmass"])
    p.add_argument("--backends", nargs="*", default=list(CANDIDATES))
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--horizon", type=int, default=128)
    p.add_argument("--out", default="results/backends.csv")
    a = p.parse_args(argv)
    done = set()
    if os.path.exists(a.out):
        with open(a.out) as f:
            done = {(r["task"], r["backend"]) for r in csv.DictReader(f)}
    new = not os.path.exists(a.out)
    with open(a.out, "a", newline="") as f:
        w = csv.DictWriter(f, FIELDS)
        if new:
            w.writeheader()
        for name in a.tasks:
            get_spec(name)  # an unknown task stops here, not as an error row
            for backend in a.backends:
                if (name, backend) in done:
                    continue
                row = dict(task=name, backend=backend, batch=a.batch, horizon=a.horizon)
                try:
                    task = task_with_backend(name, backend)
                    row.update(measure(task, a.batch, a.horizon))
                except Exception as e:  # an unsupported backend is a row, not a crash
                    row["error"] = f"{type(e).__name__}: {e}"[:200]
                print(row, flush=True)
                w.writerow(row)
                f.flush()


if __name__ == "__main__":
    main()
