"""What XLA counts in one ILD step's forward and its VJP (no timing: XLA's own cost model).

    python results/xla_cost/scripts/step_cost.py hopper,acrobot [--batch 32] [--out CSV]

For each task, on B envs: one physics step (`vmap(task.env.step)`, brax's; and with each
substep rematerialized, `tasks.core.with_substep_remat`) and one policy sample as ILD's
rollout runs it (`TanhGaussianPolicy.sample_batch`, kernels transposed beforehand), each
compiled forward and as a VJP (forward + backward, `vjp_of_ones`). Per compiled function:
`flops` and `bytes` (XLA's `cost_analysis()`: a while loop's body is counted once, so brax's
substep scan counts one substep in the forward and in the VJP alike and the ratios compare
like with like) and `kernels` (the operations left outside fusions in the optimized HLO,
bookkeeping ops excluded: each is one piece of work XLA's CPU runtime runs on its own).
"""
from __future__ import annotations

import argparse
import collections
import re

import jax
import jax.numpy as jnp

from bench.report import append_csv
from methods.ild.benchmark import speed_setup, vjp_of_ones
from methods.ild.config import ILDConfig
from tasks import make_task
from tasks.core import with_substep_remat

BOOKKEEPING = {"parameter", "get-tuple-element", "constant", "tuple", "bitcast"}


def kernels(hlo_text: str) -> int:
    """Operations outside fused computations in optimized HLO text, bookkeeping excluded."""
    count, fused = collections.Counter(), False
    for line in hlo_text.splitlines():
        head = re.match(r"^(ENTRY )?%?([\w.\-]+) .*\{\s*$", line)
        if head:
            fused = "fused" in head.group(2)
            continue
        op = re.match(r"\s*(ROOT )?%?[\w.\-]+ = .*? ([a-z\-]+)\(", line)
        if op and not fused:
            count[op.group(2)] += 1
    return sum(n for name, n in count.items() if name not in BOOKKEEPING)


def measure(f, *args) -> dict:
    compiled = jax.jit(f).lower(*args).compile()
    cost = compiled.cost_analysis()
    cost = cost[0] if isinstance(cost, list) else cost
    return {"flops": cost["flops"], "bytes": cost["bytes accessed"],
            "kernels": kernels(compiled.as_text())}


def task_rows(name: str, batch: int) -> list[dict]:
    task = make_task(name)
    s = jax.vmap(task.env.reset)(jax.random.split(jax.random.PRNGKey(0), batch))
    a = jnp.full((batch, task.action_size), 0.1)
    policy, _, _, params, k = speed_setup(task, ILDConfig(num_envs=batch))
    keys, kernels_t = jax.random.split(k[3], batch), policy.kernels_t(params)

    def sample(p, obs):
        return policy.sample_batch(p, obs, keys, kernels_t)

    parts = [("step", jax.vmap(task.env.step), (s, a))]
    try:
        parts.append(("step_substep_remat", jax.vmap(with_substep_remat(task).env.step),
                      (s, a)))
    except ValueError as e:  # no brax substep loop (pointmass)
        print(f"{name}: step_substep_remat left out: {e}", flush=True)
    parts.append(("policy", sample, (params, s.obs)))
    rows = []
    for part, f, args in parts:
        fwd, vjp = measure(f, *args), measure(vjp_of_ones(f), *args)
        rows.append({"task": name, "backend": task.spec.backend, "batch": batch, "part": part,
                     **{f"forward_{m}": fwd[m] for m in fwd},
                     **{f"vjp_{m}": vjp[m] for m in vjp},
                     **{f"{m}_ratio": round(vjp[m] / fwd[m], 2) for m in fwd}})
        r = rows[-1]
        print(f"{name} {part}: VJP / forward flops {r['flops_ratio']}x, bytes "
              f"{r['bytes_ratio']}x, kernels {r['kernels_ratio']}x ({fwd['kernels']} -> "
              f"{vjp['kernels']})", flush=True)
    return rows


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("tasks", help="comma-separated task names")
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--out", default=None, help="append rows to this CSV")
    a = p.parse_args(argv)
    for name in a.tasks.split(","):
        rows = task_rows(name, a.batch)
        if a.out:  # task by task: a long run keeps what it measured
            append_csv(rows, a.out)


if __name__ == "__main__":
    main()
