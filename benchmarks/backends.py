"""Measure forward and gradient env-steps/s of each candidate physics backend per task.

    python -m benchmarks.backends [--tasks hopper ant] [--batch 32] [--out results/speed/backends.csv]

For every (task, backend): a jitted, vmapped 128-step rollout of B envs under fixed random
actions (forward), and the gradient of a scalar of the matched states w.r.t. those actions
through the whole rollout (gradient, reverse mode). Each is compiled first (compile seconds
recorded) and timed over repeats after a warm-up; the gradient is checked finite. Rows are
appended as they finish, and rows already in the file are skipped, so it can be resumed.
"""
from __future__ import annotations

import argparse
import csv
import os

from tasks import TASKS, get_spec
from tasks.core import task_with_backend

from bench.tradeoff import measure

CANDIDATES = ("generalized", "positional", "spring")
FIELDS = ["task", "backend", "batch", "horizon", "fwd_steps_per_s", "grad_steps_per_s",
          "grad_over_fwd", "fwd_compile_s", "grad_compile_s", "grad_finite", "error"]


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tasks", nargs="*", default=[n for n in TASKS if n != "pointmass"])
    p.add_argument("--backends", nargs="*", default=list(CANDIDATES))
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--horizon", type=int, default=128)
    p.add_argument("--out", default="results/speed/backends.csv")
    a = p.parse_args(argv)
    done = set()
    if os.path.exists(a.out):
        with open(a.out) as f:
            done = {(r["task"], r["backend"]) for r in csv.DictReader(f)}
    new = not os.path.exists(a.out)
    with open(a.out, "a", newline="") as f:
        w = csv.DictWriter(f, FIELDS)
        if new:
            w.writeheader()
        for name in a.tasks:
            get_spec(name)  # an unknown task stops here, not as an error row
            for backend in a.backends:
                if (name, backend) in done:
                    continue
                row = dict(task=name, backend=backend, batch=a.batch, horizon=a.horizon)
                try:
                    task = task_with_backend(name, backend)
                    row.update(measure(task, a.batch, a.horizon))
                except Exception as e:  # an unsupported backend is a row, not a crash
                    row["error"] = f"{type(e).__name__}: {e}"[:200]
                print(row, flush=True)
                w.writerow(row)
                f.flush()


if __name__ == "__main__":
    main()
