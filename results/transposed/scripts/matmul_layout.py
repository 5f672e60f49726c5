"""What the policy's middle layer costs on XLA's CPU backend in each operand layout (session 31).

    python results/transposed/scripts/matmul_layout.py

The 512-256 layer for 32 envs, jitted alone, microseconds per call (min over 3 rounds of 200
calls): the forward product x @ W; reverse mode's product for x's cotangent, g @ W.T, as
flax's backward emits it (the transpose folded into the dot) and against a transposed copy
of W made beforehand (what `dense_t` reads); and the kernel's cotangent x.T @ g.
results/JOURNAL.md, session 31: 110 / 233 / 104 / 137 us on this machine's EPYC (one core);
the three products do the same multiply-adds.
"""
import os
import sys

import jax

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "..", "substep", "scripts"))
from timing import best_seconds  # noqa: E402


def main():
    k1, k2, k3 = jax.random.split(jax.random.PRNGKey(0), 3)
    x = jax.random.normal(k1, (32, 512))
    w = jax.random.normal(k2, (512, 256))
    g = jax.random.normal(k3, (32, 256))
    w_t = jax.block_until_ready(w.T + 0.0)  # a copy in the transposed layout
    forms = {"x @ W (forward)": (lambda x, w: x @ w, x, w),
             "g @ W.T (flax's backward)": (lambda g, w: g @ w.T, g, w),
             "g @ W_t (transposed copy)": (lambda g, w_t: g @ w_t, g, w_t),
             "x.T @ g (kernel cotangent)": (lambda x, g: x.T @ g, x, g)}
    for name, (f, *args) in forms.items():
        us = 1e6 * best_seconds(jax.jit(f), *args, calls=200)
        print(f"{name:28s} {us:8.1f} us", flush=True)


if __name__ == "__main__":
    main()
