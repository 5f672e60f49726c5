"""The rollout's policy alone with `swish_remat` off and on (session 60): what keeping only
the hidden layers' pre-activations for the backward saves.

    python results/substep/scripts/swish_policy.py TASK [--batch 32] [--rounds 6]
        [--repeats 8] [--out CSV]

Times, interleaved round by round in one process (every program compiled first; the first
round is a warm-up and is not kept), `ratio_floor.py`'s policy programs (T steps of
`sample_batch` on fixed observations: the value, and the value and gradient in the
parameters and the observations) under TASK's config with `swish_remat=False` and `True`,
and prints the median seconds per call, each gradient over its forward, the speed-up
(median and range of the per-round ratios) and XLA's working memory of each gradient. Runs
under glibc's huge-page tunable, as the benchmark does (bench.malloc; ILDBENCH_HUGEPAGES=0:
without).
"""
from __future__ import annotations

import argparse
import dataclasses
import statistics

from bench.report import append_csv
from bench.runner import speed_settings
from methods.ild.benchmark import speed_setup, task_config, temp_bytes
from methods.ild.config import ILDConfig
from ratio_floor import policy_programs
from tasks import make_task
from timing import interleaved_seconds


def run(task_name: str, batch: int = 32, rounds: int = 6, repeats: int = 8) -> list[dict]:
    task = make_task(task_name)
    cfg = task_config(task_name, batch)
    setup = speed_setup(task, ILDConfig(num_envs=batch))
    programs, mib = {}, {}
    for remat in (False, True):
        fwd, (grad, args) = policy_programs(task, dataclasses.replace(cfg, swish_remat=remat),
                                            setup)
        compiled = grad.lower(*args).compile()  # timed as it is: compiled once, not twice
        programs[f"fwd_{remat}"], programs[f"grad_{remat}"] = fwd, (compiled, args)
        mib[remat] = temp_bytes(compiled) / 2 ** 20
    seconds = interleaved_seconds(programs, rounds, repeats)
    settings = speed_settings()
    return [{"task": task_name, "batch": batch, "swish_remat": remat,
             "program": name.split("_")[0], "round": r, "seconds": float(f"{s:.4g}"),
             "grad_temp_mib": round(mib[remat], 2), **settings}
            for remat in (False, True) for name in (f"fwd_{remat}", f"grad_{remat}")
            for r, s in enumerate(seconds[name])]


def summary_lines(rows: list[dict]) -> list[str]:
    sec = {}
    for r in rows:
        sec.setdefault((r["swish_remat"], r["program"]), []).append(r["seconds"])
    mib = {r["swish_remat"]: r["grad_temp_mib"] for r in rows}
    lines = []
    for remat in (False, True):
        over = [g / f for g, f in zip(sec[remat, "grad"], sec[remat, "fwd"])]
        lines.append(f"swish_remat={remat}: forward {statistics.median(sec[remat, 'fwd']):.4f} s, "
                     f"gradient {statistics.median(sec[remat, 'grad']):.4f} s "
                     f"({statistics.median(over):.2f}x its forward), working memory "
                     f"{mib[remat]:.1f} MiB")
    speed = [a / b for a, b in zip(sec[False, "grad"], sec[True, "grad"])]
    lines.append(f"gradient speed-up {statistics.median(speed):.3f}x "
                 f"({min(speed):.3f}-{max(speed):.3f}) over {len(speed)} rounds")
    return lines


def main(argv=None):
    p = argparse.ArgumentParser()
    p.add_argument("task")
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--rounds", type=int, default=6)
    p.add_argument("--repeats", type=int, default=8)
    p.add_argument("--out", default=None)
    a = p.parse_args(argv)
    rows = run(a.task, a.batch, a.rounds, a.repeats)
    print(f"{a.task}, B = {a.batch}:")
    for line in summary_lines(rows):
        print("  " + line)
    if a.out:
        append_csv(rows, a.out)


if __name__ == "__main__":
    from bench.malloc import reexec_with_hugepages
    reexec_with_hugepages()  # glibc's huge-page tunable, as `ildbench` and the benchmark run
    main()
