"""ILD's update against brax's APG, interleaved in one process so that both see the same
machine: APG trains epochs of `--repeats` updates (brax times each epoch itself), and
between two epochs each ILD variant is timed over `--repeats` updates. One row per variant
and round; the summary is the median over rounds of each variant's seconds per update and
of its per-round env-steps/s over APG's (the benchmark's single APG epoch per process swung
by up to 10% between runs on this 2-core VM, which the 1.2x target cannot absorb):

    python -m benchmarks.ild_paired --task acrobot --rounds 6 \\
        --variant substep_remat,transposed_backward=false,chunk=4 \\
        --variant substep_remat,chunk=4

A variant is comma-separated ILDConfig or physics-plan fields (tasks/physics/plan.py; a bare
name sets a bool field True); its
`chunk` is the updates per jitted call, as the trainer runs them. APG and every variant share
one network (the paper's 512-256) and one batch (`--batch`), so a variant may not set
`hidden` or `num_envs`. With `small_dots` APG trains on the same rewritten physics (like with
like, as the benchmark's `apg_dots` row), with `closed_form_adjoint` through the same
closed-form backward (`apg_closed_form`) and with `lean_substeps` on the same lean substeps
(`apg_lean`), so the variants of one call either all set such a
field or none does. `--apg-physics brax` times brax's APG as shipped instead, whatever the
variants set (the issue's comparison: ILD's update, rewrites and all, against brax's own
trainer). A variant that starts with `task` is ILD's config and physics plan as the task
trains with them (its TASK_OVERRIDES and plan: acrobot's closed form and full BPTT,
swimmer's small dots),
and the fields after it on top:

    python -m benchmarks.ild_paired --task swimmer --variant task --variant task,chunk=4 \\
        --apg-physics brax

`--forward` also times, in each round before the variants, the benchmark's `forward` row (a
forward rollout of the same batch through brax's physics as shipped, no gradient), and each
variant's row gets that round's `forward_seconds` and `over_forward` (its seconds per update
over them): issue 4's update <= 3x forward, as a median over rounds that each time both
within seconds of each other, not from two timings minutes apart:

    python -m benchmarks.ild_paired --task hopper --variant task --apg-physics brax --forward

`--apg-physics none` times the variants (and `--forward`) without APG, round after round:
for a task whose reward has no gradient (inverted_pendulum), where APG has nothing to train.

The summary also gives update / forward from the fastest rounds (the fastest update over
the fastest forward): noise only adds time, and on this machine the per-round ratios of one
hopper run spread over 3.0-3.9x. `--summarize CSV ...` prints the summary of rows an
earlier run appended (`--out`), for rows written before it existed too:

    python -m benchmarks.ild_paired --summarize paired_hopper_*.csv
"""
from __future__ import annotations

import argparse
import statistics
import time

import jax

from bench.malloc import reexec_with_hugepages
from bench.plugins import ConfigError
from bench.machine import speed_settings
from benchmarks.ild_speed import Setup, apg_epochs, reward_gradient_norm, speed_setup, task_config
from methods.ild.config import ILDConfig
from methods.ild.train import initial_state, make_chunk, make_rollout_loss, make_update
from tasks import make_task

REWRITES = ("small_dots", "closed_form_adjoint", "lean_substeps")
"""Physics-plan fields that rewrite the physics step; APG then trains on the same rewrite
(`apg_env`)."""


def apg_env(task, physics: str):
    """The task brax's APG trains on for `apg_physics`'s answer: the task itself for 'brax',
    else the REWRITES field's physics as ILD's rollouts run it without substep
    remat (brax's APG does not rematerialize), as the benchmark's apg_* rows do."""
    if physics == "brax":
        return task
    return Setup(ILDConfig()).replace(substep_remat=False, **{physics: True}).physics(task)


def parse_variant(text: str, batch: int, task_name: str = "") -> Setup:
    """'substep_remat,chunk=4' -> ILDConfig(num_envs=batch, chunk=4) on Plan(substep_remat=True)
    (the paper's defaults otherwise, as the benchmark's rows; no per-task overrides);
    'task,chunk=4' -> the config and plan `task_name` trains with (its TASK_OVERRIDES, its
    physics plan) with chunk=4."""
    parts = [p for p in text.split(",") if p]
    of_task = bool(parts) and parts[0] == "task"
    fields = dict(p.partition("=")[::2] if "=" in p else (p, "true") for p in parts[of_task:])
    return task_config(task_name if of_task else "", batch, fields)


def apg_physics(configs: dict[str, Setup], base: Setup, brax: bool = False) -> str:
    """The physics APG trains on: a REWRITES field that every variant sets ('small_dots',
    'closed_form_adjoint') or 'brax' (the task's own, where none does, or always with
    `brax`: APG as shipped). ValueError, naming the variant and the fix, for a variant whose
    network or batch is not APG's, or (without `brax`) for variants that mix a rewrite on
    and off."""
    for v, cfg in configs.items():
        if cfg.hidden != base.hidden:
            raise ValueError(f"variant {v!r} sets hidden={cfg.hidden}: ILD and brax's APG are "
                             f"timed on one network, {base.hidden}; leave hidden out")
        if cfg.num_envs != base.num_envs:
            raise ValueError(f"variant {v!r} sets num_envs={cfg.num_envs}: set the batch of "
                             f"ILD and APG with --batch (now {base.num_envs}) instead")
    if brax:
        return "brax"
    for field in REWRITES:
        on = {v: getattr(cfg, field) for v, cfg in configs.items()}
        if len(set(on.values())) > 1:
            raise ValueError(f"variants {sorted(v for v, d in on.items() if d)} set {field} "
                             f"and {sorted(v for v, d in on.items() if not d)} do not: APG "
                             "trains on one physics, so time them in separate calls (or "
                             "all against brax's APG as shipped: --apg-physics brax)")
        if any(on.values()):
            return field
    return "brax"


def compiled_chunk(task, cfg: Setup, setup):
    """ILD's update under `cfg` on `task`, `cfg.chunk` updates per jitted call as the trainer
    runs them, from `speed_setup`'s (policy, goals, norm, params, keys): (chunk, state, n),
    chunk(state, n) -> (state, metrics), compiled by one call before it returns."""
    policy, goals, norm, params, k = setup
    update, opt, _ = make_update(cfg.physics(task), policy, goals, norm, cfg.config, k[2])
    chunk = make_chunk(update, cfg.chunk)
    state = initial_state(params, opt, k[3], cfg.config)
    n = jax.numpy.int32(cfg.chunk)
    jax.block_until_ready(chunk(state, n))
    return chunk, state, n


def compiled_forward(task, base: Setup, setup):
    """The benchmark's `forward` row's call (a forward rollout of `base.num_envs` envs through
    `task`'s physics with ILD's loss, no gradient), compiled by one call before it returns:
    (forward, params)."""
    policy, goals, norm, params, k = setup
    loss_fn = make_rollout_loss(task, policy, goals, norm, base.config)
    init_keys = jax.random.split(k[2], base.num_envs)
    forward = jax.jit(lambda p: loss_fn(p, k[3], init_keys)[0])
    jax.block_until_ready(forward(params))
    return forward, params


def run(task_name: str, variants: list[str], batch: int = 32, rounds: int = 6,
        repeats: int = 8, apg_as_shipped: bool = False, forward: bool = False,
        apg: bool = True) -> list[dict]:
    """`apg=False` (`--apg-physics none`): the variants (and the forward) alone, round after
    round, for a task whose reward has no gradient (inverted_pendulum); rows get no APG
    columns' values (NaN)."""
    base = Setup(ILDConfig(num_envs=batch))
    configs = {v: parse_variant(v, batch, task_name) for v in variants}
    physics = apg_physics(configs, base, brax=apg_as_shipped) if apg else "none"
    task = make_task(task_name)
    if apg and reward_gradient_norm(task) == 0.0:
        raise ValueError(f"task {task_name!r}: its reward has no gradient, so brax's APG "
                         "would time a forward rollout; pick a task with a reward gradient, "
                         "or time the variants alone with --apg-physics none")
    setup = speed_setup(task, base)
    steps = batch * task.episode_length
    timed = {}
    for v, cfg in configs.items():  # compile every variant before anything is timed
        chunk, state, n = compiled_chunk(task, cfg, setup)
        timed[v] = (chunk, state, n, -(-repeats // cfg.chunk))  # calls: >= repeats updates
    seconds = {v: [] for v in variants}
    fwd = compiled_forward(task, base, setup) if forward else None
    fwd_seconds = []

    def time_ild(_):
        if fwd is not None:
            t0 = time.perf_counter()
            for _ in range(repeats):
                jax.block_until_ready(fwd[0](fwd[1]))
            fwd_seconds.append((time.perf_counter() - t0) / repeats)
        for v, (chunk, state, n, calls) in timed.items():
            t0 = time.perf_counter()
            for _ in range(calls):
                state = chunk(state, n)[0]
            jax.block_until_ready(state)
            seconds[v].append((time.perf_counter() - t0) / (calls * configs[v].chunk))

    if apg:
        apg_task = apg_env(task, physics)
        # apg_epochs leaves out APG's warm-up epochs (they compile); time_ild runs after
        # those too, and only its last `rounds` timings, made beside APG's steady epochs,
        # are rounds.
        sps = apg_epochs(apg_task, batch, base.hidden, repeats, rounds, time_ild)
        apg_s = [steps / x for x in sps]
    else:  # round 0 warms up, as APG's first epochs would
        for r in range(rounds + 1):
            time_ild(r)
        apg_s = [float("nan")] * rounds
    ild = {v: s[-len(apg_s):] for v, s in seconds.items()}  # the rounds after APG compiled
    fwd_s = fwd_seconds[-len(apg_s):]
    settings = speed_settings()
    rows = []
    for v in variants:
        for r, (s, a) in enumerate(zip(ild[v], apg_s)):
            rows.append({"task": task_name, "backend": task.spec.backend, "batch": batch,
                         "variant": v, "round": r, "seconds": float(f"{s:.4g}"),
                         "apg_seconds": float(f"{a:.4g}"),
                         "over_apg": round(a / s, 3) if a == a else a,
                         "apg_physics": physics,
                         **({"forward_seconds": float(f"{fwd_s[r]:.4g}"),
                             "over_forward": round(s / fwd_s[r], 3)} if forward else {}),
                         **settings})
    for line in summary_lines(rows):
        print(line, flush=True)
    return rows


def summarize(rows: list[dict]) -> list[dict]:
    """Per task and variant of paired rows (this run's or a CSV's): the rounds, the median
    seconds per update and APG's, over APG as median and range of the per-round ratios
    and, where the forward was timed, update / forward the same way and `fastest_over_forward`:
    the fastest round's update over the fastest round's forward. Noise on a shared machine
    only adds time, so the fastest rounds give a second estimate, free of what one slow
    side adds to a round's ratio. Every variant
    after a task's first gets `speedup` (with its min and max): the median over the rounds
    both ran of the first variant's seconds over this one's, round by round."""
    groups = {}
    for r in rows:
        groups.setdefault((r["task"], r["variant"]), []).append(r)
    first = {}
    for task, variant in groups:
        first.setdefault(task, variant)
    out = []
    for (task, variant), rs in groups.items():
        secs = [r["seconds"] for r in rs]
        apg = [r["over_apg"] for r in rs]
        row = {"task": task, "variant": variant, "rounds": len(rs),
               "seconds": statistics.median(secs),
               "apg_seconds": statistics.median(r["apg_seconds"] for r in rs),
               "over_apg": statistics.median(apg), "over_apg_min": min(apg),
               "over_apg_max": max(apg)}
        fwd = [r.get("forward_seconds") for r in rs]
        if all(f == f and f is not None for f in fwd):  # NaN: a CSV row timed without it
            over = [r["over_forward"] for r in rs]
            row.update(forward_seconds=statistics.median(fwd),
                       over_forward=statistics.median(over), over_forward_min=min(over),
                       over_forward_max=max(over), fastest_over_forward=min(secs) / min(fwd))
        if variant != first[task]:
            by_round = {r.get("round"): r["seconds"] for r in groups[task, first[task]]}
            ups = [by_round[r.get("round")] / r["seconds"] for r in rs
                   if r.get("round") in by_round]
            if ups:
                row.update(speedup=statistics.median(ups), speedup_min=min(ups),
                           speedup_max=max(ups), speedup_over=first[task])
        out.append(row)
    return out


def summary_lines(rows: list[dict]) -> list[str]:
    """One printed line per task and variant of `summarize(rows)`."""
    lines = []
    for s in summarize(rows):
        line = f"{s['task']} {s['variant']}: {s['seconds']:.4f} s/update"
        if s["apg_seconds"] == s["apg_seconds"]:  # NaN: timed without APG
            line += (f" (APG {s['apg_seconds']:.4f}), over APG median {s['over_apg']:.3f} "
                     f"[{s['over_apg_min']:.3f}, {s['over_apg_max']:.3f}]")
        if "over_forward" in s:
            line += (f"; update / forward ({s['forward_seconds']:.4f} s) median "
                     f"{s['over_forward']:.3f} [{s['over_forward_min']:.3f}, "
                     f"{s['over_forward_max']:.3f}], fastest rounds "
                     f"{s['fastest_over_forward']:.3f}")
        line += f" over {s['rounds']} rounds"
        if "speedup" in s:
            line += (f"; {s['speedup']:.3f}x as fast as {s['speedup_over']} "
                     f"[{s['speedup_min']:.3f}, {s['speedup_max']:.3f}]")
        lines.append(line)
    return lines


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", default="acrobot")
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--rounds", type=int, default=6)
    p.add_argument("--repeats", type=int, default=8, help="updates per APG epoch and per "
                   "ILD block")
    p.add_argument("--summarize", nargs="+", metavar="CSV", default=None,
                   help="print the summary of rows an earlier run wrote (--out) and exit")
    p.add_argument("--variant", action="append", default=None,
                   help="comma-separated ILDConfig or physics-plan fields; a leading 'task' "
                        "starts from the task's own config and plan (its TASK_OVERRIDES, "
                        "its physics plan)")
    p.add_argument("--apg-physics", choices=("auto", "brax", "none"), default="auto",
                   help="auto: APG on the physics the variants rewrite (like with like); "
                        "brax: brax's APG as shipped, whatever the variants set; none: no "
                        "APG, the variants (and --forward) alone")
    p.add_argument("--forward", action="store_true",
                   help="also time the forward rollout (the benchmark's forward row) in each "
                        "round: every row gets that round's update / forward")
    p.add_argument("--out", default=None, help="append rows to this CSV")
    a = p.parse_args(argv)
    if a.summarize:
        import pandas as pd
        for path in a.summarize:
            try:
                rows = pd.read_csv(path).to_dict("records")
            except (OSError, ValueError) as e:
                p.error(f"--summarize {path}: {e}")
            if not rows or not {"task", "variant", "seconds", "apg_seconds",
                                "over_apg"} <= set(rows[0]):
                p.error(f"--summarize {path}: not rows of benchmarks.ild_paired (--out)")
            print("\n".join(summary_lines(rows)))
        return
    if not a.variant:
        p.error("--variant is required (one or more), unless --summarize")
    if min(a.batch, a.rounds, a.repeats) < 1:
        p.error(f"--batch, --rounds and --repeats must be >= 1, got {a.batch}, {a.rounds}, "
                f"{a.repeats}")
    try:
        rows = run(a.task, a.variant, a.batch, a.rounds, a.repeats,
                   apg_as_shipped=a.apg_physics == "brax", forward=a.forward,
                   apg=a.apg_physics != "none")
    except (ValueError, ConfigError) as e:
        p.error(str(e))
    if a.out:
        from bench.report import append_csv
        append_csv(rows, a.out)


if __name__ == "__main__":
    reexec_with_hugepages("benchmarks.ild_paired")  # as `ildbench` runs (bench.malloc)
    main()
