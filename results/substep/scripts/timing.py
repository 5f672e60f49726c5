"""What the step-VJP scripts beside it share (run them as scripts: this folder is then on
the import path)."""
from __future__ import annotations

import time

import jax
import jax.numpy as jnp


def best_seconds(f, *args, calls: int = 50, rounds: int = 3) -> float:
    """Seconds per call of `f(*args)`: compiled and run once first, then the minimum over
    `rounds` rounds of `calls` calls."""
    jax.block_until_ready(f(*args))
    best = float("inf")
    for _ in range(rounds):
        t0 = time.perf_counter()
        for _ in range(calls):
            jax.block_until_ready(f(*args))
        best = min(best, (time.perf_counter() - t0) / calls)
    return best


def vjp_of_ones(f):
    """Forward + backward of `f` with a cotangent of ones on every output."""
    def vjp(*args):
        out, pull = jax.vjp(f, *args)
        return pull(jax.tree.map(jnp.ones_like, out))
    return vjp
