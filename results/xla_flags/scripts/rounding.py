"""How far XLA_FLAGS moves a rollout and a gradient (session 28): run it twice and compare.

    python results/xla_flags/scripts/rounding.py TASK OUT_PREFIX
    XLA_FLAGS=--xla_cpu_use_fusion_emitters=false python results/xla_flags/scripts/rounding.py TASK OUT2
    python results/xla_flags/scripts/rounding.py --compare OUT_PREFIX OUT2

Saves the observations of 8 envs over 128 steps of fixed random actions (OUT.obs.npy) and
the gradient of the first observation coordinate summed after 10 steps with respect to the
actions (OUT.grad.npy); --compare prints the largest differences and the first step at
which the observations differ.
"""
from __future__ import annotations

import sys

import numpy as np


def record(task_name: str, out: str) -> None:
    import jax
    import jax.numpy as jnp

    from tasks import make_task
    from tasks.core import open_loop
    task = make_task(task_name)
    step = jax.vmap(task.env.step)
    s = jax.vmap(task.env.reset)(jax.random.split(jax.random.PRNGKey(0), 8))
    acts = jax.random.uniform(jax.random.PRNGKey(1), (128, 8, task.action_size),
                              minval=-1, maxval=1)
    obs = jax.jit(lambda st: open_loop(step, st, acts, emit=lambda x: x.obs)[1])(s)
    grad = jax.jit(jax.grad(lambda u: jnp.sum(open_loop(step, s, u)[0].obs[:, 0])))(
        acts[:10])
    np.save(out + ".obs.npy", np.asarray(obs))
    np.save(out + ".grad.npy", np.asarray(grad))


def compare(a: str, b: str) -> None:
    oa, ob = np.load(a + ".obs.npy"), np.load(b + ".obs.npy")
    per_step = np.abs(oa - ob).reshape(len(oa), -1).max(1)
    differ = np.nonzero(per_step > 0)[0]
    print(f"observations: max |diff| {per_step.max():.3g} at step {per_step.argmax()}, "
          f"first differing step {differ[0] if len(differ) else None}")
    ga, gb = np.load(a + ".grad.npy"), np.load(b + ".grad.npy")
    print(f"gradient: max |diff| {np.abs(ga - gb).max():.3g} of max |grad| "
          f"{np.abs(ga).max():.3g}")


if __name__ == "__main__":
    if sys.argv[1] == "--compare":
        compare(sys.argv[2], sys.argv[3])
    else:
        record(sys.argv[1], sys.argv[2])
