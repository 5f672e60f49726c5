"""Where one physics step's VJP spends its time, by XLA op kind (session 27).

    python results/substep/scripts/profile_step_vjp.py TASK [--substep-remat] [--batch 32]

Traces 20 calls of the jitted VJP of one batched env step (`jax.profiler.trace`, CPU) and
sums the XLA CPU runtime's op events by op kind (the fusion name without its number):
microseconds per call under the profiler (the profiler's per-op overhead inflates the total;
compare shares), share of the op time, and ops executed per call. On hopper brax's own
pipeline_step (a `lax.scan` over 4 substeps) spends much of its VJP in
dynamic-update-slice fusions (the substeps' residuals stacked into per-substep buffers, one
op per residual array per substep) and the pads that read them back. Prints seconds per call
without the profiler first (min over 3 rounds of 50 calls).
"""
from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp

from methods.ild.benchmark import vjp_of_ones
from tasks import make_task
from tasks.core import with_substep_remat
from timing import best_seconds, xla_op_events


def main(argv=None):
    p = argparse.ArgumentParser()
    p.add_argument("task")
    p.add_argument("--substep-remat", action="store_true")
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--top", type=int, default=12)
    a = p.parse_args(argv)
    task = make_task(a.task)
    if a.substep_remat:
        task = with_substep_remat(task)
    step = jax.vmap(task.env.step)
    s0 = jax.vmap(task.env.reset)(jax.random.split(jax.random.PRNGKey(0), a.batch))
    a0 = jnp.full((a.batch, task.action_size), 0.3)

    fns = {"forward": jax.jit(step), "vjp": jax.jit(vjp_of_ones(step))}
    for name, f in fns.items():
        best = best_seconds(f, s0, a0)
        print(f"{a.task} {'substep-remat' if a.substep_remat else 'brax'} {name}: "
              f"{best * 1e3:.3f} ms per call")
    calls = 20

    def run():
        for _ in range(calls):
            jax.block_until_ready(fns["vjp"](s0, a0))
    time_ns, count = xla_op_events(run)
    total = sum(time_ns.values())
    print(f"VJP op time under the profiler: {total / calls / 1e3:.0f} us per call, "
          f"{sum(count.values()) / calls:.0f} ops per call")
    for kind, ns in time_ns.most_common(a.top):
        print(f"  {100 * ns / total:5.1f}%  {count[kind] / calls:7.1f} per call  {kind}")


if __name__ == "__main__":
    main()
