"""One control step's forward and VJP under forms of brax's substep loop (session 28).

    python results/substep/scripts/substep_unroll.py TASK FORM [--batch 32]

FORM: brax (its own `lax.scan` over the substeps), ckpt (each substep checkpointed, as
`substep_remat`), unroll (the scan unrolled), ckpt_unroll (both), ckpt_unroll_cse (both,
checkpoint with prevent_cse=True). Milliseconds per call, min over 3 rounds of 50 calls.
results/JOURNAL.md, session 28: unrolling is slower than the scan (hopper 2.8-5.8 ms per step
VJP against 2.55).
"""
from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp

from methods.ild.benchmark import vjp_of_ones
from tasks import make_task
from tasks.core import build_env
from timing import best_seconds

FORMS = {"brax": None, "ckpt": (True, 1, False), "unroll": (False, True, False),
         "ckpt_unroll": (True, True, False), "ckpt_unroll_cse": (True, True, True)}


def main(argv=None):
    p = argparse.ArgumentParser()
    p.add_argument("task")
    p.add_argument("form", choices=sorted(FORMS))
    p.add_argument("--batch", type=int, default=32)
    a = p.parse_args(argv)
    task = make_task(a.task)
    env = build_env(task.spec)
    inner = env.unwrapped
    if FORMS[a.form] is not None:
        ckpt, unroll, cse = FORMS[a.form]

        def pipeline_step(state, action):
            def substep(s, _):
                return inner._pipeline.step(inner.sys, s, action, inner._debug), None
            if ckpt:
                substep = jax.checkpoint(substep, prevent_cse=cse)
            return jax.lax.scan(substep, state, (), inner._n_frames, unroll=unroll)[0]
        inner.pipeline_step = pipeline_step
    step = jax.vmap(env.step)
    s0 = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(0), a.batch))
    a0 = jnp.full((a.batch, task.action_size), 0.3)

    for name, f in {"forward": jax.jit(step), "vjp": jax.jit(vjp_of_ones(step))}.items():
        best = best_seconds(f, s0, a0)
        print(f"{a.task} {a.form} {name}: {best * 1e3:.3f} ms per call", flush=True)


if __name__ == "__main__":
    main()
