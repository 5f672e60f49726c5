"""Throwaway probe (session 75): tasks.spring_adjoint's gathers from and sums into the
parents (`_from_parents`, `_to_parents`) as products with one-hot matrices instead of
take / segment_sum (whose reverse modes and batched forms are XLA scatters and gathers).
Two variants of the same config in one process; the second compiled with the patch:

    GLIBC_TUNABLES=glibc.malloc.hugetlb=1 taskset -c 1 python \
        results/saved_residuals/onehot_parents.py ant \
        results/saved_residuals/onehot_parents_session75_ant.csv 10

(task, CSV, rounds). Session 75, ant alone on core 1: 0.964x as fast (rounds 0.880-1.145x),
no gain (results/JOURNAL.md, Session 75)."""
import sys
import jax
import jax.numpy as jnp
import tasks.spring_adjoint as sa
from methods.ild import paired

ORIG = (sa._to_parents, sa._from_parents)


def _onehot(idx, n, dtype):
    idx = jnp.asarray(idx)
    return (idx[:, None] == jnp.arange(n)[None, :]).astype(dtype)  # [len(idx), n]


def to_parents(parents, x):
    P = _onehot(parents, len(parents), x.dtype)  # [k, p]: 1 where parents[k] == p
    return jnp.tensordot(P.T, x, axes=1)


def from_parents(parents, x, world=None):
    n = x.shape[0]
    idx = jnp.asarray(parents)
    out = jnp.tensordot(_onehot(idx, n, x.dtype), x, axes=1)
    if world is not None:
        w = jnp.broadcast_to(jnp.array(world, x.dtype), x.shape[1:])
        out = out + (idx == -1).astype(x.dtype).reshape((-1,) + (1,) * (x.ndim - 1)) * w
    return out


variants = ["task", "task,saved_residuals"]
orig = paired.compiled_chunk
calls = [0]


def compiled_chunk(task, cfg, setup):
    calls[0] += 1
    patched = calls[0] == 2
    jax.clear_caches()
    if patched:
        sa._to_parents, sa._from_parents = to_parents, from_parents
    print("compile", calls[0], "one-hot" if patched else "take/segment_sum", flush=True)
    try:
        return orig(task, cfg, setup)
    finally:
        sa._to_parents, sa._from_parents = ORIG


paired.compiled_chunk = compiled_chunk
args = ["--task", sys.argv[1], "--rounds", sys.argv[3], "--repeats", "8", "--apg-physics",
        "none", "--forward", "--out", sys.argv[2]]
for v in variants:
    args += ["--variant", v]
paired.main(args)
