"""What a batched tiny matrix product costs on XLA's CPU backend (session 29).

    python results/small_dots/scripts/dot_cost.py      # XLA_FLAGS=... to try a flag

Twenty chained products of 32 5x5 matrices (`tanh` between them), once as `a @ b` (a batched
`dot_general`: one library call per product) and once as a broadcast multiply and a sum
(`tasks.small_dots`' rewrite, by hand): microseconds per call (min over 3 rounds of 500
calls) and the largest difference between the two results. results/JOURNAL.md, session 29:
380 vs 86 us, the same numbers to the bit, and no XLA flag of jaxlib 0.7.2 moves the dots.
"""
import os
import sys

import jax
import jax.numpy as jnp

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "substep", "scripts"))
from timing import best_seconds  # noqa: E402


def chain_dot(a, b):
    for _ in range(20):
        b = jnp.tanh(a @ b)
    return b


def chain_sum(a, b):
    for _ in range(20):
        b = jnp.tanh(jnp.sum(a[:, :, :, None] * b[:, None, :, :], axis=2))
    return b


if __name__ == "__main__":
    a = jax.random.normal(jax.random.PRNGKey(0), (32, 5, 5))
    b = jax.random.normal(jax.random.PRNGKey(1), (32, 5, 5))
    print("XLA_FLAGS", os.environ.get("XLA_FLAGS"))
    print("dots x20          %.1f us" % (1e6 * best_seconds(jax.jit(chain_dot), a, b, calls=500)))
    print("multiply-sum x20  %.1f us" % (1e6 * best_seconds(jax.jit(chain_sum), a, b, calls=500)))
    print("max |difference|  %.3g" % float(jnp.max(jnp.abs(jax.jit(chain_dot)(a, b)
                                                            - jax.jit(chain_sum)(a, b)))))
