"""Where ILD's whole update spends its time against the forward rollout's, by XLA operation
(session 56): the task's update as it trains (`task_config`, one update per call) and the
benchmark's `forward` row, each traced over 5 calls under `jax.profiler` (CPU):

    python results/substep/scripts/profile_update.py hopper [--batch 32] [--top 15]
        [--variant task,FIELD=VALUE]

Prints seconds per call without the profiler first (min over 3 rounds of 10 calls), then per
program the op events per call, the top operation kinds (the name without its number) and
the top single operations with their output shape from the optimized HLO. The profiler's
per-operation overhead inflates the totals (compare shares), and at this size its
durations are not what an operation costs without it (session 51). Runs under glibc's
huge-page tunable, as the benchmark does (bench.malloc; ILDBENCH_HUGEPAGES=0: without).
"""
from __future__ import annotations

import argparse
import collections
import re

import jax

from methods.ild.benchmark import speed_setup
from methods.ild.config import ILDConfig
from methods.ild.paired import compiled_chunk, compiled_forward, parse_variant
from tasks import make_task
from timing import best_seconds, op_kind, xla_op_events


def report(label: str, f, hlo: str, top: int, calls: int = 5) -> None:
    time_ns, count = xla_op_events(lambda: [jax.block_until_ready(f()) for _ in range(calls)],
                                   by_name=True)
    total = sum(time_ns.values())
    kinds, kind_count = collections.Counter(), collections.Counter()
    for name, ns in time_ns.items():  # the kinds xla_op_events gives without by_name
        kind = op_kind(name)
        kinds[kind] += ns
        kind_count[kind] += count[name]
    print(f"== {label}: {total / calls / 1e6:.1f} ms per call profiled, "
          f"{sum(count.values()) // calls} op events per call")
    print("  by kind:")
    for k, ns in kinds.most_common(top):
        print(f"    {k:42s} {ns / calls / 1e3:9.1f} us {100 * ns / total:5.1f}% "
              f"x{kind_count[k] // calls}")
    print("  single operations:")
    for name, ns in time_ns.most_common(top):
        m = re.search(r"\n\s*(?:ROOT )?%" + re.escape(name) + r" = (\S+)", hlo)
        print(f"    {name[:42]:42s} {ns / calls / 1e3:9.1f} us {100 * ns / total:5.1f}% "
              f"x{count[name] // calls:<5d} {m.group(1) if m else ''}")


def main(argv=None):
    p = argparse.ArgumentParser()
    p.add_argument("task")
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--top", type=int, default=15)
    p.add_argument("--variant", default="task",
                   help="the update's config, as methods.ild.paired's --variant")
    a = p.parse_args(argv)
    task = make_task(a.task)
    base = ILDConfig(num_envs=a.batch)
    setup = speed_setup(task, base)
    chunk, state, n = compiled_chunk(task, parse_variant(a.variant, a.batch, a.task), setup)
    forward, params = compiled_forward(task, base, setup)
    update_s = best_seconds(lambda: chunk(state, n), calls=10)
    forward_s = best_seconds(lambda: forward(params), calls=10)
    print(f"{a.task}, B = {a.batch}: update {update_s:.4f} s, forward {forward_s:.4f} s, "
          f"update / forward {update_s / forward_s:.2f}x (unprofiled)")
    report("update", lambda: chunk(state, n), chunk.lower(state, n).compile().as_text(),
           a.top)
    report("forward", lambda: forward(params), forward.lower(params).compile().as_text(),
           a.top)


if __name__ == "__main__":
    from bench.malloc import reexec_with_hugepages
    reexec_with_hugepages()  # glibc's huge-page tunable, as `ildbench` and the benchmark run
    main()
