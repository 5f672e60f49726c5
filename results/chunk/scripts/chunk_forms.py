"""Session 26's timing of the forms of an ILD chunk, one process, compiled once each and
timed alternately (min over 3 rounds of 2 calls of 4 updates, random goals as the speed
benchmark's):

    taskset -c 0 python results/chunk/scripts/chunk_forms.py TASK

  chunk            the trainer's `make_chunk(update, 4)`: a fori_loop over the updates left
  plain_scan       lax.scan of 4 updates
  one_per_call     one update per jitted call, 4 calls chained
  scan1_per_call   the trainer's chunk=1 program (a scan of one update), 4 calls chained

(hopper / ant, run at once on cores 0 / 1: chunk 0.436 / 1.674 s per update, plain_scan
0.444 / 1.607, one_per_call 0.512 / 2.054, scan1_per_call 0.535 / 1.999.)
"""
import resource
import sys
import time

import jax
import jax.numpy as jnp

from methods.ild.benchmark import speed_setup
from methods.ild.config import ILDConfig
from methods.ild.train import initial_state, make_chunk, make_update
from tasks import make_task

task = make_task(sys.argv[1])
K, B = 4, 32
cfg = ILDConfig(num_envs=B)
policy, goals, norm, params, k = speed_setup(task, cfg)
update, opt, _ = make_update(task, policy, goals, norm, cfg, k[2])
s = initial_state(params, opt, k[3], cfg)
n4 = jnp.int32(K)
plain = jax.jit(lambda s: jax.lax.scan(update, s, None, length=K)[0]).lower(s).compile()
chunk = jax.jit(lambda s, a, c=make_chunk(update, K): c(s, a)[0]).lower(s, n4).compile()
one = jax.jit(lambda s: update(s, None)[0]).lower(s).compile()
scan1 = jax.jit(lambda s, a, c=make_chunk(update, 1): c(s, a)[0]).lower(s, jnp.int32(1)).compile()


def chained(f):
    def run():
        x = s
        for _ in range(K):
            x = f(x)
        return x
    return run


calls = {"chunk": lambda: chunk(s, n4), "plain_scan": lambda: plain(s),
         "one_per_call": chained(one), "scan1_per_call": chained(lambda x: scan1(x, jnp.int32(1)))}
for f in calls.values():
    jax.block_until_ready(f())
sec = {n: [] for n in calls}
faults = {n: 0.0 for n in calls}
for _ in range(3):
    for n, f in calls.items():
        r0, t0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt, time.perf_counter()
        for _ in range(2):
            jax.block_until_ready(f())
        sec[n].append((time.perf_counter() - t0) / (2 * K))
        faults[n] += ((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - r0)
                      * resource.getpagesize() / 2**20 / (6 * K))
for n in calls:
    print(f"{n:15s} s/update per round {[round(x, 4) for x in sec[n]]}, min {min(sec[n]):.4f}, "
          f"faults {faults[n]:.1f} MiB/update")
