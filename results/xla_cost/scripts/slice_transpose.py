"""Does the transpose of brax's static slices cost a step's VJP its time? (session 33)

    python results/xla_cost/scripts/slice_transpose.py TASK MODE    (MODE: base|none|slice)

Times one physics step of 32 envs (each substep rematerialized, ILD's default) forward and
as a VJP (`vjp_of_ones`), min over 7 rounds of 50 calls. `profile_step_vjp.py hopper
--substep-remat` puts ~30% of hopper's step-VJP op time in pads and concatenates, the
transposes of the many static slices brax takes of its states (`x[..., 0]`, quaternion
parts): one pad per slice, then adds. MODE `slice` evaluates the step through
`tasks.small_dots`' jaxpr interpreter with every static floating-point slice replaced by a
custom_vjp whose backward, for a one-element slice, broadcasts the cotangent and masks it
with an iota compare (elementwise, fusable) instead of padding it; `none` runs the
interpreter with nothing rewritten (its own cost), `base` brax's step as it is.
Session 33, hopper, core 0 (a run alone and one beside a benchmark on core 1): base
1.92-2.26 ms, none 1.90-2.12 ms, slice 2.40-3.46 ms per VJP (forward 0.33-0.41 ms in all):
the masked broadcasts cost more than the pads, so the pads are not a cost a rewrite of the
slices removes.
"""
from __future__ import annotations

import sys
import time

import jax
import jax.numpy as jnp
from jax import lax

import tasks.small_dots as sd
from methods.ild.benchmark import vjp_of_ones
from tasks import make_task
from tasks.core import with_substep_remat


def masked_slice(start, limit, shape):
    """lax.slice whose backward, for a one-element slice on one axis, is a masked broadcast."""
    axes = [i for i, (s, l, n) in enumerate(zip(start, limit, shape)) if (s, l) != (0, n)]
    single = len(axes) == 1 and limit[axes[0]] - start[axes[0]] == 1

    @jax.custom_vjp
    def f(x):
        return lax.slice(x, start, limit)

    def bwd(_, g):
        if single:
            b = jnp.broadcast_to(g, shape)
            iota = lax.broadcasted_iota(jnp.int32, shape, axes[0])
            return (jnp.where(iota == start[axes[0]], b, jnp.zeros_like(b)),)
        return (lax.pad(g, jnp.zeros((), g.dtype),
                        [(s, n - l, 0) for s, l, n in zip(start, limit, shape)]),)

    f.defvjp(lambda x: (f(x), None), bwd)
    return f


def rewriting(mode: str):
    """tasks.small_dots' equation evaluator with MODE's rewrite (dots left as dots)."""
    def eval_eqn(eqn, invals, max_terms):
        name, p = eqn.primitive.name, eqn.params
        aval = eqn.invars[0].aval if eqn.invars else None
        if (mode == "slice" and name == "slice" and p.get("strides") is None
                and jnp.issubdtype(aval.dtype, jnp.floating)):
            return masked_slice(tuple(p["start_indices"]), tuple(p["limit_indices"]),
                                tuple(aval.shape))(invals[0])
        if name == "dot_general":
            subfuns, params = eqn.primitive.get_bind_params(p)
            return eqn.primitive.bind(*subfuns, *invals, **params)
        return original(eqn, invals, max_terms)
    return eval_eqn


original = sd._eval_eqn


def main():
    name, mode = sys.argv[1], sys.argv[2]
    task = make_task(name)
    s = jax.vmap(task.env.reset)(jax.random.split(jax.random.PRNGKey(0), 32))
    a = jnp.full((32, task.action_size), 0.1)
    sub = with_substep_remat(task)
    if mode != "base":
        sd._eval_eqn = rewriting(mode)  # this process only
        sub.env.unwrapped.pipeline_step = sd.small_dots_as_sums(sub.env.unwrapped.pipeline_step)
    f = jax.vmap(sub.env.step)
    res = {}
    for label, g in (("forward", f), ("vjp", vjp_of_ones(f))):
        c = jax.jit(g)
        jax.block_until_ready(c(s, a))
        best = float("inf")
        for _ in range(7):
            t = time.perf_counter()
            for _ in range(50):
                out = c(s, a)
            jax.block_until_ready(out)
            best = min(best, (time.perf_counter() - t) / 50)
        res[label] = best
    print(f"{name} {mode}: forward {res['forward'] * 1e3:.3f} ms, VJP {res['vjp'] * 1e3:.3f} ms, "
          f"ratio {res['vjp'] / res['forward']:.2f}", flush=True)


if __name__ == "__main__":
    main()
