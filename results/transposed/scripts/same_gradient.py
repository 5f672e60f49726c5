"""ILD's loss and gradient with a speed option off and on, bit for bit (sessions 31, 33).

    python results/transposed/scripts/same_gradient.py acrobot,hopper [--batch 8]
        [--field transposed_backward|substep_remat]

For each task: one jitted value-and-grad of ILD's rollout loss at the benchmark's seeded
setup with `--field` False and True. Prints whether the losses are equal and the largest
gradient difference.
- `transposed_backward` (session 31; with and without `substep_remat` where the task has
  brax substeps): flax's backward (the policy vmapped per env) against the batched policy
  reading its kernels transposed once. Equal and 0.0 on pointmass and all 8 brax tasks (B = 8).
- `substep_remat` (session 33, when it became the default; brax tasks only): brax's substep
  scan against the same scan over checkpointed substeps. Losses equal on hopper, acrobot and
  reacher (walker2d's differs in the 7th digit); largest gradient difference 0.0 on acrobot,
  1.5e-8 on reacher, 5.7e-7 on hopper, 1.7e-6 on walker2d (B = 8): float32 round-off, not bit
  for bit, which is why making it the default was a version bump.
"""
import argparse
import dataclasses

import jax
import jax.numpy as jnp

from methods.ild.benchmark import speed_setup
from methods.ild.config import ILDConfig
from methods.ild.train import make_rollout_loss, rollout_physics
from tasks import make_task
from tasks.core import has_substep_loop


def main():
    p = argparse.ArgumentParser()
    p.add_argument("tasks")
    p.add_argument("--batch", type=int, default=8)
    p.add_argument("--field", default="transposed_backward",
                   choices=("transposed_backward", "substep_remat"))
    a = p.parse_args()
    for name in a.tasks.split(","):
        task = make_task(name)
        if a.field == "substep_remat":
            if not has_substep_loop(task):
                print(f"{name}: no brax substep loop, nothing to compare", flush=True)
                continue
            bases = [("default", ILDConfig(num_envs=a.batch))]
        else:
            bases = [("substep_remat=False", ILDConfig(num_envs=a.batch, substep_remat=False))]
            if has_substep_loop(task):
                bases.append(("substep_remat=True", ILDConfig(num_envs=a.batch)))
        for label, base in bases:
            policy, goals, norm, params, k = speed_setup(task, base)
            init_keys = jax.random.split(k[2], a.batch)
            out = {}
            for t in (False, True):
                cfg = dataclasses.replace(base, **{a.field: t})
                f = jax.jit(jax.value_and_grad(make_rollout_loss(
                    rollout_physics(task, cfg), policy, goals, norm, cfg), has_aux=True))
                (loss, _), g = f(params, k[3], init_keys)
                out[t] = (loss, g)
            diff = max(float(jnp.max(jnp.abs(x - y))) for x, y in
                       zip(jax.tree.leaves(out[False][1]), jax.tree.leaves(out[True][1])))
            print(f"{name} {a.field} off/on ({label}): losses equal "
                  f"{bool(out[False][0] == out[True][0])}, largest gradient difference {diff}",
                  flush=True)


if __name__ == "__main__":
    main()
