"""The timing the step-VJP scripts beside it share (run them as scripts: this folder is then
on the import path); their VJP of ones is `methods.ild.benchmark.vjp_of_ones`, the
benchmark's own."""
from __future__ import annotations

import time

import jax


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

