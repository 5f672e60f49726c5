"""How many XLA operations ILD's update and the forward rollout execute, and what each costs
on average (session 49).

    python results/substep/scripts/op_count.py TASK [--variant task,hand_adjoint=false
        --variant task ...] [--batch 32] [--calls 3] [--out CSV]

(Session 49 ran `--variant task --variant task,hand_adjoint`, the same two updates before
`hand_adjoint` became the spring tasks' default in session 50; since then `task` includes it,
and since sessions 52-53 its scene-specific pieces too (`hinge_forces`, `planar_root`,
`rotary_joints`), whose task overrides `hand_adjoint=false` turns off with it.)

For the forward rollout and its loss through brax's step as shipped (the benchmark's
`forward`, the issue's yardstick) and for ILD's update under each `--variant` (named as
`methods.ild.paired` names them): seconds per call (min over 3 rounds of `--calls` calls,
no profiler), then, under `jax.profiler.trace`, the XLA CPU runtime's operations executed
per call (every event on XLA's threads but the executor's own, the "end: " events that
close some operations and the thread pool's region markers) and the real seconds per call
divided by them; then each call's seconds and operations over the forward's, and the ten
operation kinds (fusion names without their numbers) each update executes most often.
Time = operations x seconds per operation: at B = 32 the spring tasks' arrays hold a few
hundred floats, so the per-operation cost is under a microsecond and an update's time
is as much about how many operations XLA runs as about their flops (results/JOURNAL.md,
session 49).
"""
from __future__ import annotations

import argparse
import collections
import time

import jax

from bench.malloc import reexec_with_hugepages
from bench.report import append_csv
from methods.ild.benchmark import make_rollout_loss, speed_setup
from methods.ild.paired import compiled_chunk, parse_variant
from tasks import make_task
from timing import xla_op_events


def _seconds(fn, state, calls: int) -> float:
    best = float("inf")
    for _ in range(3):
        t0 = time.perf_counter()
        for _ in range(calls):
            state = fn(state)
        jax.block_until_ready(state)
        best = min(best, (time.perf_counter() - t0) / calls)
    return best


def _ops(fn, state, calls: int) -> collections.Counter:
    """XLA operations executed per call of `fn`, by kind, under the profiler."""
    def run():
        s = state
        for _ in range(calls):
            s = fn(s)
        jax.block_until_ready(s)
    count = xla_op_events(run, skip=("ThunkExecutor", "end: ", "ThreadpoolListener"))[1]
    return collections.Counter({k: v / calls for k, v in count.items()})


def main(argv=None):
    reexec_with_hugepages()  # as the benchmark and `ildbench` run (bench.malloc)
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("task")
    p.add_argument("--variant", action="append", default=None)
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--calls", type=int, default=3)
    p.add_argument("--out")
    a = p.parse_args(argv)
    variants = a.variant or ["task"]
    task = make_task(a.task)
    base = parse_variant("task", a.batch, a.task)
    setup = policy, goals, norm, params, k = speed_setup(task, base)
    init_keys = jax.random.split(k[2], a.batch)
    loss = jax.jit(make_rollout_loss(task, policy, goals, norm, base))

    def forward(q):  # the same parameters each call: wait for each loss
        jax.block_until_ready(loss(q, k[3], init_keys))
        return q
    fns, states = {"forward": forward}, {"forward": params}
    for v in variants:
        cfg = parse_variant(v, a.batch, a.task)
        if cfg.chunk != 1:
            p.error(f"variant {v!r} runs {cfg.chunk} updates per call; count chunk=1 variants")
        chunk, state, one = compiled_chunk(task, cfg, setup)
        fns[f"update {v}"] = (lambda c, n: lambda s: c(s, n)[0])(chunk, one)  # state in, out
        states[f"update {v}"] = state
    rows = []
    for name, fn in fns.items():
        jax.block_until_ready(fn(states[name]))  # compiles the forward; warms up each update
        sec = _seconds(fn, states[name], a.calls)
        ops = _ops(fn, states[name], a.calls)
        n_ops = sum(ops.values())
        rows.append({"task": a.task, "batch": a.batch, "call": name, "seconds": round(sec, 5),
                     "ops": round(n_ops), "ns_per_op": round(1e9 * sec / n_ops, 1)})
        print(f"{a.task} {name}: {sec:.4f} s, {n_ops:.0f} ops, {1e9 * sec / n_ops:.0f} ns per "
              "op", flush=True)
        if name != "forward":
            print("  " + ", ".join(f"{k_} {v_:.0f}" for k_, v_ in ops.most_common(10)))
    f_sec, f_ops = rows[0]["seconds"], rows[0]["ops"]
    for r in rows:
        r["seconds_over_forward"] = round(r["seconds"] / f_sec, 3)
        r["ops_over_forward"] = round(r["ops"] / f_ops, 3)
        print(f"{r['call']}: {r['seconds_over_forward']}x the forward's seconds, "
              f"{r['ops_over_forward']}x its ops")
    if a.out:
        append_csv(rows, a.out)


if __name__ == "__main__":
    main()
