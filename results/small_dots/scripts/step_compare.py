"""One brax control step of 32 envs: brax's own against `tasks.core.with_small_dots` (session 29).

    python results/small_dots/scripts/step_compare.py TASK [--unroll-newton-schulz]

Prints the largest difference of q and qd after one step from states 10 steps in, the relative
difference of the VJP's action cotangent (cotangent of ones), and each form's forward and VJP
microseconds per call (min over 3 rounds of 100 calls). `--unroll-newton-schulz` instead times
brax's generalized mass-matrix inverse with its Newton-Schulz `lax.scan` unrolled by hand (the
same arithmetic; results/JOURNAL.md, session 29: not the loop, the products cost).
"""
import argparse
import os
import sys

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "substep", "scripts"))
from timing import best_seconds, print_forward_and_vjp, states_in  # noqa: E402

from methods.ild.benchmark import vjp_of_ones  # noqa: E402
from tasks import make_task  # noqa: E402
from tasks.core import with_small_dots  # noqa: E402


def inv_unrolled(a, a_inv, num_iter=10):
    """brax.math.inv_approximate with its scan written out (same operations, same order)."""
    from brax import math as bmath
    eye = np.eye(a.shape[0])
    r = eye - a @ a_inv
    a_inv = jnp.where(bmath.safe_norm(r) > 1, 0.5 * a.T / jnp.trace(a @ a.T), a_inv)
    err = 1.0
    for _ in range(num_iter):
        nxt = a_inv @ (eye + r)
        r = eye - a @ nxt
        e = bmath.safe_norm(r)
        a_inv = jnp.where(e < err, nxt, a_inv)
        err = e
    return a_inv


def main(argv=None):
    p = argparse.ArgumentParser()
    p.add_argument("task")
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--unroll-newton-schulz", action="store_true")
    a = p.parse_args(argv)
    task = make_task(a.task)
    env = task.env.unwrapped
    ps, act = states_in(task, a.batch)
    if a.unroll_newton_schulz:
        from brax import math as bmath
        from brax.generalized import mass
        mx_inv = jax.vmap(lambda q: mass.matrix_inv(env.sys, q, env.sys.matrix_inv_iterations))
        t0 = best_seconds(jax.jit(mx_inv), ps, calls=100)
        bmath.inv_approximate = inv_unrolled  # brax.generalized.mass calls it through math
        t1 = best_seconds(jax.jit(mx_inv), ps, calls=100)
        print(f"mass.matrix_inv forward: brax's scan {t0 * 1e6:.1f} us, unrolled {t1 * 1e6:.1f} us")
        return
    forms = {"brax": env.pipeline_step,
             "small dots": with_small_dots(task).env.unwrapped.pipeline_step}
    out = {k: jax.jit(jax.vmap(f))(ps, act) for k, f in forms.items()}
    grads = {k: jax.jit(vjp_of_ones(jax.vmap(f)))(ps, act)[1] for k, f in forms.items()}
    print("max |q difference| %.3g, max |qd difference| %.3g, action VJP relative %.3g" % (
        float(jnp.max(jnp.abs(out["brax"].q - out["small dots"].q))),
        float(jnp.max(jnp.abs(out["brax"].qd - out["small dots"].qd))),
        float(jnp.max(jnp.abs(grads["brax"] - grads["small dots"]))
              / jnp.max(jnp.abs(grads["brax"])))))
    print_forward_and_vjp({f"{k} control step": f for k, f in forms.items()}, ps, act,
                          width=24)


if __name__ == "__main__":
    main()
