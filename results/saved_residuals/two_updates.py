"""Session 73 probe: two ILD updates (B = 32, one start) under each config variant, compared
with the first bit for bit, and the second update's loss:

    python results/saved_residuals/two_updates.py ant task task,saved_residuals
"""
import os, sys
import jax, jax.numpy as jnp, numpy as np
from methods.ild.benchmark import speed_setup
from methods.ild.config import ILDConfig
from methods.ild.paired import compiled_chunk, parse_variant
from tasks import make_task
task_name = sys.argv[1]; variants = sys.argv[2:]
task = make_task(task_name)
setup = speed_setup(task, ILDConfig(num_envs=32))
outs = {}
for v in variants:
    chunk, state, n = compiled_chunk(task, parse_variant(v, 32, task_name), setup)
    st = state
    for _ in range(2):
        st, m = chunk(st, n)
    outs[v] = (jax.tree.leaves(st), m)
ref = outs[variants[0]]
for v, (leaves, m) in outs.items():
    same = all(np.array_equal(np.asarray(a), np.asarray(b)) for a, b in zip(leaves, ref[0]))
    md = max(float(np.max(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64)))) for a, b in zip(leaves, ref[0]) if np.asarray(a).dtype.kind == "f")
    print(task_name, repr(v), "bit-identical state after 2 updates:", same, "max abs diff", md,
          {k: np.asarray(x).tolist() for k, x in m.items() if "loss" in k}, flush=True)
