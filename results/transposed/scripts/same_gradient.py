"""ILD's loss and gradient with and without `transposed_backward`, bit for bit (session 31).

    python results/transposed/scripts/same_gradient.py acrobot,hopper [--batch 8]

For each task (with and without `substep_remat` where the task has brax substeps): one
jitted value-and-grad of ILD's rollout loss at the benchmark's seeded setup, flax's backward
(the policy vmapped per env) against the batched policy reading its kernels transposed once
(the default). Prints whether the losses are equal and the largest gradient difference.
Session 31, this machine: equal and 0.0 on pointmass and all 8 brax tasks (B = 8).
"""
import argparse
import dataclasses

import jax
import jax.numpy as jnp

from methods.ild.benchmark import speed_setup
from methods.ild.config import ILDConfig
from methods.ild.train import make_rollout_loss, rollout_physics
from tasks import make_task


def main():
    p = argparse.ArgumentParser()
    p.add_argument("tasks")
    p.add_argument("--batch", type=int, default=8)
    a = p.parse_args()
    for name in a.tasks.split(","):
        task = make_task(name)
        for extra in ({}, {"substep_remat": True}):
            base = ILDConfig(num_envs=a.batch, **extra)
            try:
                physics = rollout_physics(task, base)
            except ValueError:  # no brax substeps (pointmass)
                continue
            policy, goals, norm, params, k = speed_setup(task, base)
            init_keys = jax.random.split(k[2], a.batch)
            out = {}
            for t in (False, True):
                cfg = dataclasses.replace(base, transposed_backward=t)
                f = jax.jit(jax.value_and_grad(
                    make_rollout_loss(physics, policy, goals, norm, cfg), has_aux=True))
                (loss, _), g = f(params, k[3], init_keys)
                out[t] = (loss, g)
            diff = max(float(jnp.max(jnp.abs(x - y))) for x, y in
                       zip(jax.tree.leaves(out[False][1]), jax.tree.leaves(out[True][1])))
            print(f"{name} {extra or 'default'}: losses equal {bool(out[False][0] == out[True][0])}, "
                  f"largest gradient difference {diff}", flush=True)


if __name__ == "__main__":
    main()
