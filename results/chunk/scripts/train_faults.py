"""Session 26's in-process check of ILD's chunk in training: one run through the harness's
own runner on an env-step budget, with the page faults and kernel seconds it cost.

    taskset -c 1 python results/chunk/scripts/train_faults.py TASK CHUNK [UPDATES]

(ant 1 / ant 4 with 24 updates: 1.66 / 1.60 s per update, 2.0 GiB of faults per whole run
either way, ant rematerializing by task override; hopper 1 with 20 updates: 8.2 GiB.)
"""
import resource
import sys
import tempfile
import time

from bench.budget import Budget
from bench.evaluator import EvalConfig
from bench.runner import RunRequest, execute, prepare
from bench.store import Store
from tasks import make_task

task, chunk = sys.argv[1], int(sys.argv[2])
updates = int(sys.argv[3]) if len(sys.argv) > 3 else 24
per_update = 32 * make_task(task).episode_length  # the cpu preset's B = 32 rollouts
req = RunRequest(method="ild", task=task, seed=0,
                 budget=Budget(env_steps=per_update * updates, evals=3), preset="cpu",
                 overrides={"chunk": chunk, "bc_updates": 0}, eval=EvalConfig(num_episodes=4))
r0, t0 = resource.getrusage(resource.RUSAGE_SELF), time.perf_counter()
with tempfile.TemporaryDirectory() as tmp:
    rec, _ = execute(prepare(req), Store(tmp), log=print)
r1 = resource.getrusage(resource.RUSAGE_SELF)
print("wall", round(time.perf_counter() - t0, 1), "s; faults",
      round((r1.ru_minflt - r0.ru_minflt) * resource.getpagesize() / 2**20), "MiB; sys",
      round(r1.ru_stime - r0.ru_stime, 2), "s; updates", rec["train_metrics"]["train/updates"])
c = rec["curve"]
a, b = c[1], c[-1]  # from the first evaluation after the first call (compiled by then)
if b["env_steps"] > a["env_steps"]:
    print("s per update between evaluations:", round(
        (b["train_s"] - a["train_s"]) / ((b["env_steps"] - a["env_steps"]) / per_update), 3))
else:
    print("too few updates between evaluations for a rate: give more UPDATES")
