"""One control step of ant (B = 32, 15 steps after reset, feet on the floor) as the step ILD
trains with (hand_adjoint's spring substep, lean substeps, the state's other fields computed
from x_i and xd_i) and as `tasks.spatial_links.control_step`: milliseconds per call of each
one's forward and of its value and VJP (a sine cotangent), jitted, medians over 11 rounds of
20 calls, then (without --no-profile) the form's VJP by XLA operation (session 76):

    PYTHONPATH=. taskset -c 1 python results/spatial_links/step_vjp.py [--task ant]
        [--batch 32] [--no-profile]

(--task humanoid: the same for humanoid's step, session 77.)
"""
import argparse
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, "results/substep/scripts")
from profile_update import report  # noqa: E402

from tests.test_spatial_links import _control_steps  # noqa: E402


def main():
    p = argparse.ArgumentParser()
    p.add_argument("--task", default="ant", choices=("ant", "humanoid"))
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--no-profile", action="store_true")
    a = p.parse_args()
    trained, ours, args, _ = _control_steps(a.task, a.batch)

    def vjp_of(f):
        def g(*args):
            out, pull = jax.vjp(f, *args)
            return pull(jax.tree.map(lambda v: jnp.sin(jnp.arange(v.size, dtype=v.dtype)
                                                       ).reshape(v.shape), out))
        return jax.jit(g)

    fns = {"trained_fwd": jax.jit(trained), "spatial_fwd": jax.jit(ours),
           "trained_vjp": vjp_of(trained), "spatial_vjp": vjp_of(ours)}
    for f in fns.values():
        jax.block_until_ready(f(*args))
    times = {k: [] for k in fns}
    for _ in range(11):
        for k, f in fns.items():
            t0 = time.perf_counter()
            for _ in range(20):
                out = f(*args)
            jax.block_until_ready(out)
            times[k].append((time.perf_counter() - t0) / 20 * 1e3)
    for k, v in times.items():
        print(f"{k}: {np.median(v):.3f} ms (rounds {min(v):.3f}-{max(v):.3f})")
    print(f"spatial_vjp / trained_vjp: "
          f"{np.median(times['spatial_vjp']) / np.median(times['trained_vjp']):.3f}")
    if not a.no_profile:
        f = fns["spatial_vjp"]
        report("spatial_vjp", lambda: f(*args), f.lower(*args).compile().as_text(), 12)


if __name__ == "__main__":
    main()
