"""What the policy's largest layer costs forward and backward inside a rollout's loop on XLA's
CPU backend (session 57): the products ILD's update runs per step for the 512 x 256 kernel,
each over T = 128 steps of a `lax.scan`, at batch B:

    python results/substep/scripts/kernel_grad_gemm.py [--batch 32] [--rounds 8] [--calls 10]

- forward: y = x @ W, x (B, 512): the forward rollout's product;
- input_grad: g @ W^T with W^T made once outside the loop (`dense_t`'s backward), g (B, 256);
- kernel_grad: the kernel's cotangent x^T g, added into a (512, 256) carry every step, as
  reverse mode through the loop runs it;
- kernel_grad_xt: the same with x stored transposed (an ordinary product per step);
- kernel_grad_pairs: two steps' rows per product (K = 2B), half the adds;
- kernel_grad_after: one product over all T x B rows after the loop (the cotangents stacked:
  session 51's taps), as a 2-D `dot_general`.
Each product has the same floating-point work, 2 T B 512 256. Prints per program the median
milliseconds per call over rounds (the first a warm-up), its ratio to `forward` and GFLOP/s.
ILD's update runs forward, input_grad and kernel_grad for this layer; forward alone runs
the first, so this layer's gradient / forward is 1 + (input_grad + kernel_grad) / forward.
"""
from __future__ import annotations

import argparse
import statistics

import jax
import jax.numpy as jnp
from timing import interleaved_seconds

T, IN, OUT = 128, 512, 256


def _acc(x, g):
    return jax.lax.dot_general(x, g, (((0,), (0,)), ((), ())))


def programs(batch: int) -> dict:
    k = jax.random.split(jax.random.PRNGKey(0), 3)
    x = jax.random.normal(k[0], (T, batch, IN))
    g = jax.random.normal(k[1], (T, batch, OUT))
    w = jax.random.normal(k[2], (IN, OUT)) * 0.05
    wt = w.T + 0.0
    zero = jnp.zeros((IN, OUT))

    def forward(x, w):
        return jax.lax.scan(lambda c, xt: (c + jnp.sum(xt @ w), None), 0.0, x)[0]

    def input_grad(g, wt):
        return jax.lax.scan(lambda c, gt: (c + jnp.sum(gt @ wt), None), 0.0, g)[0]

    def kernel_grad(x, g):
        return jax.lax.scan(lambda a, xg: (a + _acc(*xg), None), zero, (x, g))[0]

    def kernel_grad_xt(x, g):
        xt = jnp.swapaxes(x, 1, 2)
        return jax.lax.scan(lambda a, xg: (a + xg[0] @ xg[1], None), zero, (xt, g))[0]

    def kernel_grad_pairs(x, g):
        x2, g2 = x.reshape(T // 2, 2 * batch, IN), g.reshape(T // 2, 2 * batch, OUT)
        return jax.lax.scan(lambda a, xg: (a + _acc(*xg), None), zero, (x2, g2))[0]

    def kernel_grad_after(x, g):
        return _acc(x.reshape(T * batch, IN), g.reshape(T * batch, OUT))

    return {"forward": (forward, (x, w)), "input_grad": (input_grad, (g, wt)),
            "kernel_grad": (kernel_grad, (x, g)), "kernel_grad_xt": (kernel_grad_xt, (x, g)),
            "kernel_grad_pairs": (kernel_grad_pairs, (x, g)),
            "kernel_grad_after": (kernel_grad_after, (x, g))}


def run(batch: int, rounds: int = 8, calls: int = 10) -> dict[str, float]:
    """Median seconds per call of each program (round 0 a warm-up)."""
    progs = {name: (jax.jit(f), args) for name, (f, args) in programs(batch).items()}
    return {name: statistics.median(s)
            for name, s in interleaved_seconds(progs, rounds, calls).items()}


def main(argv=None):
    p = argparse.ArgumentParser()
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--rounds", type=int, default=8)
    p.add_argument("--calls", type=int, default=10)
    a = p.parse_args(argv)
    med = run(a.batch, a.rounds, a.calls)
    flops = 2 * T * a.batch * IN * OUT
    print(f"B = {a.batch}, T = {T}, {IN} x {OUT} kernel; median ms per call:")
    for name, s in med.items():
        print(f"  {name:18s} {s * 1e3:8.2f} ms {s / med['forward']:5.2f}x forward "
              f"{flops / s / 1e9:6.1f} GFLOP/s")
    layer = 1 + (med["input_grad"] + med["kernel_grad"]) / med["forward"]
    print(f"  this layer's gradient / forward as the update runs it: {layer:.2f}x")


if __name__ == "__main__":
    main()
