"""ildbench command line.

    ildbench tasks                      registered tasks, backends, demos and references
    ildbench methods                    registered methods and what each uses
    ildbench run --method M --task T --seed S --budget 300s [--budget-steps N]
    ildbench sweep --methods M.. --tasks T.. --seeds N --budget 10m [--executor ray] [--dry-run]
    ildbench quick                      the main job: a quick leaderboard on the defaults
    ildbench leaderboard                table, aggregates and curves from the store
    ildbench check [--suite S] [--update]  CI regression gate (canary suite vs reference)
    ildbench reindex --store S          rename records to the current run-id scheme
    ildbench new-method NAME [--dir D]  a minimal method plugin package to start from
    ildbench render --task T --method M HTML: expert demo next to the method's final policy
    ildbench tradeoff backends|budget|ild|utd|substeps --task T   speed-accuracy tables, plots
    ildbench ablate --task T --budget 3m            the paper's ILD ablations vs Table 3
    ildbench plot-robustness --task T   robustness curves from runs made with --robustness
    ildbench plot-cloth --store S       the cloth's gripper paths and final cloth per run
    ildbench expert train --task T      train a PPO expert (progress, time left)
    ildbench expert demo --task T       roll the expert into the task's demo file
    ildbench expert calibrate --task T  per-task default transfer magnitudes (expert keeps 80%)
"""
from __future__ import annotations

import argparse
import itertools
import os
import sys
import warnings

EXIT_BAD_INPUT = 2


def _budget(args):
    from bench.budget import Budget, parse_seconds
    seconds = None if args.budget is None else parse_seconds(args.budget)
    return Budget(seconds=seconds, env_steps=args.budget_steps,
                  charge_compile=not args.no_charge_compile, evals=args.evals)


def _overrides(pairs, flag="--set"):
    out = {}
    for p in pairs or []:
        k, sep, v = p.partition("=")
        if not sep or not k:
            raise ValueError(f"{flag} expects key=value, got {p!r}")
        out[k.strip()] = v.strip()
    return out


def _print_table(title, columns, rows):
    from rich.console import Console
    from rich.table import Table
    t = Table(title=title)
    for c in columns:
        t.add_column(c)
    for r in rows:
        t.add_row(*[str(x) for x in r])
    # Piped output (logs, files, tests) is not wrapped to a guessed terminal width.
    Console(width=None if sys.stdout.isatty() else 200).print(t)


def cmd_tasks(args):
    from bench.perturb import TASK_DEFAULT, parse_dynamics
    from tasks import TASKS, make_task
    from tasks.core import has_substep_loop
    from tasks.demo import DemoError, load_demo
    from tasks.physics.plan import PLATFORMS, plan_for
    rows, plans = [], []
    for name, spec in TASKS.items():
        task = make_task(name)
        plans.append((name, *(plan_for(name, p).describe(has_substep_loop(task))
                              for p in PLATFORMS)))
        refs = "no demo yet"
        if spec.demo_path and os.path.exists(spec.demo_path):
            try:
                d = load_demo(spec.demo_path, task)
                refs = f"{d.num_demos} demos; expert {d.expert_return:.2f}, random " \
                       f"{d.random_return:.2f}"
            except DemoError as e:
                refs = f"INVALID: {e}"
        adapt = "-" if spec.adapt is None else parse_dynamics(TASK_DEFAULT, task).key
        rows.append((name, spec.backend, task.obs_size, task.action_size, task.state_size,
                     spec.episode_length, adapt, refs))
    _print_table("ildbench tasks", ["task", "backend", "obs", "act", "matched", "T",
                                    "adapt (--train-dynamics task)", "demo / references"],
                 rows)
    _print_table("physics plans: the rewrites a method that differentiates through the "
                 "physics runs (--physics reference: brax's step; docs/physics.md)",
                 ["task", *PLATFORMS], plans)


def cmd_methods(args):
    from bench.plugins import _SOURCES, all_methods
    rows = [(m.name, m.uses.describe(), "reference" if m.reference else "imitation",
             ", ".join(m.presets) or "-", _SOURCES[m.name], m.description)
            for m in all_methods().values()]
    _print_table("ildbench methods", ["method", "uses", "kind", "presets", "source",
                                      "description"], rows)


def _requests(args, methods, tasks, seeds):
    from bench.evaluator import EvalConfig
    from bench.plugins import get_method
    from bench.runner import RunRequest
    budget = _budget(args)
    ev = EvalConfig(num_episodes=args.eval_episodes, deterministic=not args.stochastic_eval,
                    transfer=args.transfer, robustness=args.robustness)

    def preset(m):  # quick: the cpu preset where a method has one
        if getattr(args, "preset_if_available", None):
            return args.preset_if_available if args.preset_if_available in get_method(
                m).presets else None
        return args.preset
    return [RunRequest(method=m, task=t, seed=s, budget=budget, preset=preset(m),
                       overrides=_overrides(args.set), eval=ev, num_demos=args.num_demos,
                       physics=args.physics,
                       train_dynamics=getattr(args, "train_dynamics", None))
            # seed-major: an interrupted sweep leaves whole seeds of the grid, not whole methods
            for s, t, m in itertools.product(seeds, tasks, methods)]


def _run_all(args, requests):
    from bench.runner import enable_compilation_cache, prepare
    from bench.store import Store
    prepared = [prepare(r) for r in requests]  # every input error surfaces before any work
    if getattr(args, "dry_run", False):
        n_done = 0
        for p in prepared:
            done = Store(args.store).finished(p.run_id)
            n_done += done is not None
            print(f"{p.run_id}  {p.request.method:10s} {p.request.task:18s} seed "
                  f"{p.request.seed}  {'done' if done else 'to run'}")
        b = prepared[0].request.budget if prepared else None
        print(f"plan: {len(prepared)} cells, {n_done} finished, {len(prepared) - n_done} to "
              f"run" + (f", {b.describe()} of training each" if b else ""))
        return 0
    store = Store(args.store)
    log = lambda s: print(s, flush=True)  # noqa: E731
    if getattr(args, "executor", "local") == "ray":
        from bench.sweep import run_ray
        outcomes = run_ray(prepared, store, address=args.ray_address,
                           cpus_per_run=args.cpus_per_run, gpus_per_run=args.gpus_per_run,
                           force=args.force, jax_cache=args.jax_cache, log=log,
                           warm=not getattr(args, "no_warm", False))
    else:
        from bench.sweep import run_local
        enable_compilation_cache(args.jax_cache)
        outcomes = run_local(prepared, store, force=args.force, log=log,
                             isolate=not getattr(args, "in_process", False),
                             jax_cache=args.jax_cache, warm=not getattr(args, "no_warm", False),
                             workers=getattr(args, "workers", 1) or 1)
    return 1 if any(o.status in ("failed", "crashed") for o in outcomes) else 0


def cmd_run(args):
    args.in_process = True  # one cell: no sweep-long accumulation to isolate from
    return _run_all(args, _requests(args, [args.method], [args.task], [args.seed]))


def cmd_sweep(args):
    seeds = list(range(args.seed_start, args.seed_start + args.seeds))
    if getattr(args, "tune", False):
        from bench.seeds import check_tuning_seeds
        check_tuning_seeds(seeds)
    code = _run_all(args, _requests(args, args.methods, args.tasks, seeds))
    if not args.dry_run:
        from bench.report import write_report
        from bench.store import Store
        _print_report(write_report(Store(args.store), args.out), args.out)
    return code


QUICK_TASKS = ("pointmass", "inverted_pendulum")
"""The cheap tasks with a demo. reacher is left out: doing nothing scores 0.89 there (weakly
discriminative), so a quick row on it says little."""


def cmd_quick(args):
    """All registered imitation methods (their cpu preset where they have one) x the cheap
    tasks x 2 seeds, cells in parallel, one per CPU this process may use. Afterwards a note
    names the methods whose quick cells simulated fewer env steps than the method declares
    it needs (`MethodSpec.min_env_steps`)."""
    from bench.plugins import all_methods
    from tasks import TASKS
    methods = [m for m in all_methods().values() if not m.reference]
    args.methods = [m.name for m in methods]
    args.tasks = [t for t in QUICK_TASKS
                  if TASKS[t].demo_path and os.path.exists(TASKS[t].demo_path)]
    if args.preset is None:
        args.preset_if_available = "cpu"
    if args.workers is None:
        args.workers = len(os.sched_getaffinity(0))
    code = cmd_sweep(args)
    if not args.dry_run:
        note = starved_note(args.store, methods, args.tasks)
        if note:
            print(note)
    return code


def starved_note(store_dir: str, methods, tasks) -> str:
    """A short note under quick's table: each method whose cells here used fewer env steps
    than its declared minimum, with the median it got."""
    import statistics
    from bench.store import Store
    lines = []
    recs = list(Store(store_dir).records())
    for m in methods:
        if not m.min_env_steps:
            continue
        steps = [r.get("env_steps") or 0 for r in recs
                 if r.get("method") == m.name and r.get("task") in tasks]
        median = statistics.median(steps) if steps else None
        if median is not None and median < m.min_env_steps:
            lines.append(f"  {m.name}: about {median:,.0f} env steps per cell here; its paper "
                         f"trains for {m.min_env_steps:,}")
    if not lines:
        return ""
    return ("note: these methods are starved at quick's budget (marked in the table); their "
            "rows show where they start, not where they end (see results/steps200k for them "
            "at 200k env steps):\n" + "\n".join(lines))


def cmd_leaderboard(args):
    from bench.report import write_report
    from bench.store import Store
    zero_shot = None
    if args.zero_shot is not None:
        if not os.path.isdir(args.zero_shot):
            print(f"error: --zero-shot store {args.zero_shot!r} is not a directory; name a "
                  "store of nominal-trained runs swept with --transfer (e.g. "
                  "results/grid/runs)", file=sys.stderr)
            return EXIT_BAD_INPUT
        zero_shot = Store(args.zero_shot)
    _print_report(write_report(Store(args.store), args.out, zero_shot=zero_shot), args.out)
    return 0


def _print_report(paths: list[str], out_dir: str) -> None:
    """The report's tables on stdout (leaderboard.md first), then the files written."""
    print(open(paths[0]).read())  # leaderboard.md
    for name in ("sample_matched.md", "aggregates.md", "adaptation.md"):
        path = os.path.join(out_dir, name)
        if path in paths:
            print(open(path).read())
    print("written: " + ", ".join(paths))


def cmd_reindex(args):
    from bench.runner import reindex
    from bench.store import Store
    for old, new in reindex(Store(args.store), dry_run=args.dry_run):
        print(f"{old} -> {new}")
    return 0


def cmd_check(args):
    from bench.check import REFERENCE, SUITE_FILE, check, load_suite
    from bench.runner import enable_compilation_cache
    suite = load_suite(args.suite or SUITE_FILE)  # a malformed suite stops before any run
    reference = args.reference
    if reference is None:  # ildbench's own reference, or <suite>_reference.json beside it
        reference = (REFERENCE if args.suite is None
                     else os.path.splitext(args.suite)[0] + "_reference.json")
    enable_compilation_cache(args.jax_cache)
    passed, report = check(reference, update=args.update, suite=suite,
                           log=(lambda s: print(s, flush=True)) if args.verbose else
                           (lambda s: None))
    print(report)
    return 0 if passed else 1


def cmd_new_method(args):
    from bench.scaffold import write
    folder = write(args.name, args.dir)
    print(f"wrote {folder}/ (method {args.name!r}); next:\n"
          f"  pip install -e {folder}\n"
          f"  ildbench conform --method {args.name}\n"
          f"  see {folder}/README.md and docs/adding-a-method.md")
    return 0


def cmd_conform(args):
    from bench.conformance import conform, render
    from bench.runner import enable_compilation_cache
    enable_compilation_cache(args.jax_cache)
    found = conform(args.method, task=args.task, env_steps=args.steps, evals=args.evals,
                    overrides=_overrides(args.set), preset=args.preset, repeats=args.repeats,
                    seed=args.seed, log=(lambda s: print(s, flush=True)) if args.verbose
                    else (lambda s: None))
    print(render(args.method, found))
    return 1 if any(f.passed is False for f in found) else 0


def cmd_render(args):
    from bench.render import render_cloth, render_pair
    from bench.store import Store
    from tasks import get_spec
    get_spec(args.task)
    if args.task == "cloth":
        path = render_cloth(Store(args.store), args.out, args.method, args.seed)
    elif args.method is None or len(args.method) != 1:
        raise ValueError(f"render --task {args.task} draws one method beside the demo: give "
                         "--method NAME (several methods side by side: --task cloth)")
    else:
        path = render_pair(Store(args.store), args.task, args.method[0], args.out, args.seed)
    print(f"written: {path}")
    return 0


def cmd_tradeoff(args):
    from bench import tradeoff as tr
    from bench.store import Store
    from tasks import get_spec
    get_spec(args.task)
    out = args.out or tr.OUT
    if args.part == "backends":
        df = tr.backends(args.task, batch=args.batch)
        paths = tr._save(df, args.task, "backends", out) + [tr.plot_backends(df, args.task, out)]
    elif args.part == "substeps":
        if args.task != "cloth":
            raise ValueError("tradeoff substeps measures the cloth simulator: use --task cloth")
        df = tr.cloth_substeps()
        paths = tr._save(df, args.task, "substeps", out)
    elif args.part == "budget":
        df = tr.budget_table(Store(args.store), args.task,
                             tuple(args.minutes) if args.minutes else tr.BUDGET_MINUTES,
                             tuple(Store(d) for d in args.with_store or ()))
        paths = tr._save(df, args.task, "budget", out) + [tr.plot_budget(df, args.task, out)]
    elif args.part == "utd":
        from bench.budget import parse_seconds
        seconds = parse_seconds(args.budget or "3m")
        ratios = tuple(args.ratios or tr.UTD_RATIOS)
        for u in ratios:
            if not u > 0:
                raise ValueError(f"tradeoff utd: every update-to-data ratio must be > 0, "
                                 f"got {u:g} in --ratios")
        if not args.table_only:
            _run_all(args, tr.utd_requests(args.task, seconds, ratios,
                                           seeds=range(args.seeds or 3)))
        df = tr.utd_table(Store(args.store), args.task, seconds)
        paths = (tr._save(df, args.task, "utd", out)
                 + [tr.plot_utd(df, args.task, seconds, out)])
    else:
        from bench.budget import parse_seconds
        if not args.table_only:
            _run_all(args, tr.ild_requests(args.task, parse_seconds(args.budget or "3m"),
                                           seeds=range(args.seeds or 1)))
        df = tr.ild_table(Store(args.store), args.task)
        paths = tr._save(df, args.task, "ild", out) + [tr.plot_ild(df, args.task, out)]
    print(open(paths[1]).read())
    print("written: " + ", ".join(paths))
    return 0


def cmd_ablate(args):
    from bench import ablation
    from bench.budget import parse_seconds
    from bench.store import Store
    seconds = parse_seconds(args.budget)
    if not args.table_only:
        _run_all(args, ablation.requests(args.task, seconds, seeds=range(args.seeds),
                                         names=args.settings))
    df = ablation.table(Store(args.store), args.task, seconds)
    paths = ablation.write(df, args.task, args.out)
    print(open(paths[1]).read())
    print("written: " + ", ".join(paths))
    return 0


def cmd_plot_robustness(args):
    from bench.plots import robustness_plot
    from bench.store import Store
    from tasks import get_spec
    get_spec(args.task)
    print(f"written: {robustness_plot(Store(args.store), args.task, args.out)}")
    return 0


def cmd_plot_train(args):
    from bench.plots import training_plot
    from bench.plugins import get_method
    from bench.store import Store
    from tasks import get_spec
    get_spec(args.task)
    version = None if args.any_version else get_method(args.method).version
    path = training_plot(Store(args.store), args.task, args.method, args.out, args.metrics,
                         version)
    print(f"written: {path}")
    return 0


def cmd_plot_cloth(args):
    from bench.plots import cloth_paths_plot
    from bench.store import Store
    print(f"written: {cloth_paths_plot(Store(args.store), args.out)}")
    return 0


def cmd_expert(args):
    from tasks import get_spec
    from bench.budget import parse_seconds
    from bench.expert import make_demo, train_expert
    get_spec(args.task)  # unknown task -> error listing valid ones
    if args.expert_cmd == "train":
        from bench.expert import default_algorithm, train_trajopt_expert
        algorithm = args.algorithm or default_algorithm(args.task)
        if algorithm == "trajopt":
            ppo_only = [flag for flag, v in (("--steps", args.steps), ("--time-limit", args.time_limit),
                                             ("--resume", args.resume), ("--set", args.set),
                                             ("--env-set", args.env_set)) if v]
            if ppo_only or args.preset != "cpu":
                raise ValueError(f"{', '.join(ppo_only or ['--preset'])}: PPO settings, but "
                                 f"{args.task!r} trains by trajectory optimization "
                                 f"(TRAJOPT_CONFIGS in bench/expert.py); drop them, or pass "
                                 f"--algorithm ppo")
            train_trajopt_expert(args.task, seed=args.seed, out_dir=args.out)
            return 0
        train_expert(args.task, seed=args.seed, num_timesteps=args.steps, preset=args.preset,
                     time_limit_s=parse_seconds(args.time_limit) if args.time_limit else None,
                     out_dir=args.out, resume=args.resume,
                     overrides=_overrides(args.set),
                     env_overrides=_overrides(args.env_set, "--env-set"),
                     algorithm=algorithm)
    elif args.expert_cmd == "inspect":
        from bench.expert import inspect_expert
        for k, v in inspect_expert(args.task, args.params, args.rollouts).items():
            print(f"{k:>18}: {v}")
    elif args.expert_cmd == "calibrate":
        from bench.calibrate import CAL_DIR, calibrate
        calibrate(args.task)
        print(f"written: {CAL_DIR}/{args.task}.md; put the transfer= tuple above into the "
              f"task's TaskSpec in tasks/registry.py")
    else:
        make_demo(args.task, rollouts=args.rollouts, keep=args.keep, seed=args.seed)
    return 0


def _add_run_options(p, budget_default=None):
    p.add_argument("--budget", default=budget_default,
                   help="training wall-clock per run: 300, 300s, 10m, 1h")
    p.add_argument("--budget-steps", type=int, default=None,
                   help="env-step budget (deterministic; with or instead of --budget)")
    p.add_argument("--no-charge-compile", action="store_true",
                   help="do not count JIT compile time against the budget")
    p.add_argument("--no-warm", action="store_true",
                   help="skip the compile warm-up before each configuration's first timed "
                        "cell (docs/protocol.md: Budget)")
    p.add_argument("--evals", type=int, default=10, help="evaluations spread over the budget")
    p.add_argument("--preset", default=None, help="method config preset (e.g. cpu, paper)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override a config field (repeatable)")
    p.add_argument("--eval-episodes", type=int, default=32)
    p.add_argument("--stochastic-eval", action="store_true")
    p.add_argument("--transfer", action="store_true",
                   help="also score the final policy under each perturbation family")
    p.add_argument("--robustness", action="store_true",
                   help="also score it on each family's magnitude grid")
    p.add_argument("--num-demos", type=int, default=1, help="demos handed to the method")
    p.add_argument("--physics", default="task", choices=["task", "reference"],
                   help="what a method that differentiates through the physics steps: the "
                        "task's physics plan on this platform (default; `ildbench tasks` "
                        "lists them) or brax's step as it is (reference)")
    p.add_argument("--train-dynamics", default=None, metavar="FAMILY[:MAGNITUDE][:fixed|fresh]",
                   help="train in changed dynamics and score under them, beside the nominal "
                        "score (the demo stays nominal): a perturbation family (init_noise, "
                        "action_noise, action_bias, obs_noise, actuator, mass, friction, "
                        "test_noise), its magnitude (default: the task's transfer default) "
                        "and, for the noisy families, one fixed noise sequence for every "
                        "episode or fresh noise per episode (default); `task`: each task's "
                        "own adaptation dynamics (`ildbench tasks`); docs/protocol.md")
    p.add_argument("--force", action="store_true", help="re-run finished cells")
    p.add_argument("--dry-run", action="store_true", help="print the plan only")
    p.add_argument("--jax-cache", default=None, help="persistent compilation cache dir")
    p.add_argument("--in-process", action="store_true",
                   help="run cells in this process (default: a fresh child process per cell)")


_OUT_HELP = ("where tables and plots go (default: X for the store X/runs, e.g. results/grid for "
             "results/grid/runs; results for the default store 'runs'; else the store's "
             "name + '_report', e.g. results/abc_report for results/abc)")


def default_out(store: str) -> str:
    """Tables of the store `X/runs` go to X and those of the default store `runs` to results;
    any other store S gets its own `S_report`, so a side sweep never writes over (or litters)
    results/'s tables."""
    parent, base = os.path.split(os.path.normpath(store))
    if base == "runs":
        return parent or "results"
    return os.path.join(parent, base + "_report")


def build_parser():
    ap = argparse.ArgumentParser(prog="ildbench", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--store", default=None,
                        help="results store dir (default: runs/ or $ILDBENCH_STORE)")
    sub = ap.add_subparsers(dest="cmd", required=True)
    _add = sub.add_parser
    sub.add_parser = lambda *a, **k: _add(*a, parents=[common], **k)
    sub.add_parser("tasks", help="list tasks").set_defaults(fn=cmd_tasks)
    sub.add_parser("methods", help="list methods").set_defaults(fn=cmd_methods)
    p = sub.add_parser("run", help="one budgeted run")
    p.add_argument("--method", required=True)
    p.add_argument("--task", required=True)
    p.add_argument("--seed", type=int, default=0)
    _add_run_options(p)
    p.set_defaults(fn=cmd_run)
    p = sub.add_parser("sweep", help="methods x tasks x seeds, skipping finished cells")
    p.add_argument("--methods", nargs="+", required=True)
    p.add_argument("--tasks", nargs="+", required=True)
    p.add_argument("--seeds", type=int, default=3)
    p.add_argument("--seed-start", type=int, default=0)
    p.add_argument("--tune", action="store_true",
                   help="a tuning sweep: it runs on tuning seeds only (100 and up, "
                        "--seed-start 100), disjoint from the seeds the tables report; "
                        "reporting seeds are refused (bench/seeds.py)")
    p.add_argument("--out", default=None, help=_OUT_HELP)
    p.add_argument("--executor", choices=["local", "ray"], default="local",
                   help="local: cells on this machine (--workers at a time); ray: cells as "
                        "Ray tasks")
    p.add_argument("--workers", type=int, default=1,
                   help="local executor: cells at a time, each pinned to its own CPU (default 1)")
    p.add_argument("--ray-address", default=None,
                   help="existing Ray cluster ('auto', 'ray://host:10001'); default: local Ray")
    p.add_argument("--cpus-per-run", type=float, default=1,
                   help="CPUs each Ray cell reserves (equal for every cell)")
    p.add_argument("--gpus-per-run", type=float, default=0)
    _add_run_options(p)
    p.set_defaults(fn=cmd_sweep)
    p = sub.add_parser("quick", help="the main job: quick leaderboard on embedded defaults")
    p.add_argument("--workers", type=int, default=None,
                   help="cells at a time, one CPU each (default: every CPU this process may use)")
    p.add_argument("--seeds", type=int, default=2)
    p.add_argument("--seed-start", type=int, default=0)
    p.add_argument("--out", default="results/quick")
    _add_run_options(p, budget_default="40s")
    p.set_defaults(fn=cmd_quick)
    p = sub.add_parser("leaderboard", help="aggregate the store into a table")
    p.add_argument("--out", default=None, help=_OUT_HELP)
    p.add_argument("--zero-shot", default=None, metavar="STORE",
                   help="a store of runs trained in the nominal dynamics and swept with "
                        "--transfer: writes adaptation.md, this store's changed-dynamics "
                        "runs beside those runs scored in the same dynamics")
    p.set_defaults(fn=cmd_leaderboard)
    p = sub.add_parser("reindex", help="rename a store's records to the current run-id "
                       "scheme (after an ildbench upgrade), so sweeps find them")
    p.add_argument("--dry-run", action="store_true", help="list the renames only")
    p.set_defaults(fn=cmd_reindex)
    p = sub.add_parser("check", help="CI regression gate: canary suite vs committed reference")
    p.add_argument("--suite", default=None,
                   help="canary suite file (TOML: method, task, env_steps, overrides, seeds, "
                        "tolerance per [[canary]]; default: ildbench's own, "
                        "bench/data/canary_suite.toml)")
    p.add_argument("--update", action="store_true",
                   help="rewrite the reference from this run (after an intended change)")
    p.add_argument("--reference", default=None, help="reference file (default: "
                   "bench/data/canary_reference.json for ildbench's suite, else "
                   "<suite>_reference.json beside the suite file)")
    p.add_argument("--verbose", action="store_true", help="print the runs' progress")
    p.add_argument("--jax-cache", default=None, help="persistent compilation cache dir")
    p.set_defaults(fn=cmd_check)
    p = sub.add_parser("conform", help="check a method plugin: runs, budget, compiles its "
                       "update once, deterministic (bench/conformance.py)")
    p.add_argument("--method", required=True)
    p.add_argument("--task", default="pointmass")
    p.add_argument("--steps", type=int, default=20_000, help="env-step budget per run")
    p.add_argument("--evals", type=int, default=2)
    p.add_argument("--repeats", type=int, default=2, help="runs with one seed (determinism)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--preset", default=None)
    p.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override a config field (repeatable), e.g. to make it small")
    p.add_argument("--verbose", action="store_true", help="print the runs' progress")
    p.add_argument("--jax-cache", default=None, help="persistent compilation cache dir")
    p.set_defaults(fn=cmd_conform)
    p = sub.add_parser("new-method", help="write a minimal, installable method plugin "
                       "(pyproject with the entry point, method, test, canary suite, CI)")
    p.add_argument("name", help="the method's name (a Python identifier, e.g. mymethod)")
    p.add_argument("--dir", default=None, help="where to write it (default ./ildbench-NAME)")
    p.set_defaults(fn=cmd_new_method)
    p = sub.add_parser("render", help="HTML: the expert demo next to a method's final policy "
                       "(cloth: an animation of every method, per training dynamics)")
    p.add_argument("--task", required=True)
    p.add_argument("--method", nargs="+", default=None,
                   help="the method (cloth: any number; default every method in the store)")
    p.add_argument("--seed", type=int, default=None, help="default: the best-scoring seed")
    p.add_argument("--out", default=None, help="default: results, or beside the store for cloth")
    p.set_defaults(fn=cmd_render)
    p = sub.add_parser("tradeoff", help="speed-accuracy trade-offs: backends, budget, ILD, "
                                              "update-to-data ratio")
    p.add_argument("part", choices=["backends", "budget", "ild", "utd", "substeps"])
    p.add_argument("--task", required=True)
    p.add_argument("--batch", type=int, default=16, help="backends: parallel rollouts")
    p.add_argument("--budget", default=None,
                   help="ild, utd: training budget per cell (default 3m)")
    p.add_argument("--seeds", type=int, default=None,
                   help="ild, utd: seeds per cell (default 1 for ild, 3 for utd)")
    p.add_argument("--ratios", type=float, nargs="+", default=None,
                   help="utd: the update-to-data ratios (default 1 0.5 0.25)")
    p.add_argument("--table-only", action="store_true",
                   help="ild, utd: tabulate the store's finished runs, run nothing")
    p.add_argument("--minutes", type=float, nargs="+", default=None,
                   help="budget: the budgets to read off the anytime curves (default 1 2 5 10)")
    p.add_argument("--with-store", action="append", metavar="DIR",
                   help="budget: also read the runs of this store (repeatable; e.g. ILD runs at "
                        "shorter budgets kept out of the leaderboard's store)")
    p.add_argument("--out", default=None, help="default results/tradeoff")
    p.add_argument("--jax-cache", default=None)
    p.set_defaults(fn=cmd_tradeoff, force=False)  # for _run_all (the ILD grid)
    p = sub.add_parser("ablate", help="the paper's ILD ablations (Table 3, Table 7)")
    p.add_argument("--task", required=True)
    p.add_argument("--budget", default="3m")
    p.add_argument("--seeds", type=int, default=1)
    p.add_argument("--settings", nargs="*", default=None, help="subset of settings")
    p.add_argument("--table-only", action="store_true", help="tabulate finished runs only")
    p.add_argument("--out", default="results/ablation")
    p.add_argument("--jax-cache", default=None)
    p.set_defaults(fn=cmd_ablate, force=False)  # for _run_all
    p = sub.add_parser("plot-robustness", help="normalized score vs perturbation magnitude")
    p.add_argument("--task", required=True)
    p.add_argument("--out", default=None, help=_OUT_HELP)
    p.set_defaults(fn=cmd_plot_robustness)
    p = sub.add_parser("plot-train", help="a method's score and training metrics (losses, "
                       "q_recent, PWIL's paid reward...) against env steps, one line per run")
    p.add_argument("--task", required=True)
    p.add_argument("--method", required=True)
    p.add_argument("--metrics", nargs="+", default=None,
                   help="metric keys to draw (default: all but speed/...)")
    p.add_argument("--any-version", action="store_true",
                   help="include runs of every method version (default: the registered one)")
    p.add_argument("--out", default=None, help=_OUT_HELP)
    p.set_defaults(fn=cmd_plot_train)
    p = sub.add_parser("plot-cloth", help="the cloth's gripper paths and final cloth per run")
    p.add_argument("--out", default=None, help=_OUT_HELP)
    p.set_defaults(fn=cmd_plot_cloth)
    p = sub.add_parser("expert", help="expert training and demos")
    esub = p.add_subparsers(dest="expert_cmd", required=True)
    _eadd = esub.add_parser
    esub.add_parser = lambda *a, **k: _eadd(*a, parents=[common], **k)
    e = esub.add_parser("train", help="train a task's expert (brax PPO; brax SAC for walker2d; "
                                      "open-loop trajectory optimization for acrobot and "
                                      "swimmer)")
    e.add_argument("--task", required=True)
    e.add_argument("--seed", type=int, default=0)
    e.add_argument("--algorithm", default=None, choices=["ppo", "sac", "trajopt"],
                   help="brax PPO, brax SAC (bench.expert.SAC_CONFIGS), or open-loop "
                        "trajectory optimization through the physics (default: the task's, "
                        "bench.expert.default_algorithm)")
    e.add_argument("--steps", type=int, default=None, help="override PPO num_timesteps")
    e.add_argument("--preset", default="cpu", choices=["cpu", "gpu"],
                   help="PPO recipe table: cpu (256 envs) or gpu (brax's recipes, 2048-4096 envs)")
    e.add_argument("--time-limit", default=None,
                   help="stop at the first evaluation past this wall-clock (e.g. 8m), keeping "
                        "the best evaluation's parameters")
    e.add_argument("--out", default=None,
                   help="folder for <task>_expert.msgpack/.json (default: tasks/data)")
    e.add_argument("--resume", default=None, metavar="FOLDER",
                   help="continue from the best evaluation of a run written there with --out")
    e.add_argument("--set", action="append", metavar="KEY=VALUE",
                   help="override a setting of the PPO/SAC recipe (repeatable)")
    e.add_argument("--env-set", action="append", metavar="KEY=VALUE",
                   help="training-only environment argument, e.g. healthy_reward=3 (reward "
                        "shaping of the demonstrator; demos and scores use the task's own env)")
    e = esub.add_parser("demo", help="roll the expert into the task's demo file")
    e.add_argument("--task", required=True)
    e.add_argument("--seed", type=int, default=0)
    e.add_argument("--rollouts", type=int, default=64)
    e.add_argument("--keep", type=int, default=16)
    e = esub.add_parser("inspect", help="what a demo would see of an expert: early ends, "
                                        "returns over 128 steps, R_expert and R_random")
    e.add_argument("--task", required=True)
    e.add_argument("--params", default=None, help="a parameter file (default: the task's)")
    e.add_argument("--rollouts", type=int, default=64)
    e = esub.add_parser("calibrate", help="per-task default transfer magnitudes from the "
                                          "expert's own returns under each family")
    e.add_argument("--task", required=True)
    p.set_defaults(fn=cmd_expert)
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if args.store is None:
        from bench.store import DEFAULT_ROOT
        args.store = DEFAULT_ROOT
    if getattr(args, "out", "") is None and args.cmd in ("sweep", "leaderboard",
                                                           "plot-robustness", "plot-cloth",
                                                           "plot-train"):
        args.out = default_out(args.store)
    if args.cmd == "render" and args.out is None:
        args.out = default_out(args.store) if args.task == "cloth" else "results"
    if args.cmd in ("run", "sweep", "quick") and args.budget is None and \
            args.budget_steps is None:
        print("error: give a budget: --budget 300s (wall-clock) and/or --budget-steps N",
              file=sys.stderr)
        return EXIT_BAD_INPUT
    warnings.filterwarnings("ignore", message="Brax System, piplines")
    from bench.api import InformationError
    from bench.budget import BudgetError
    from bench.plugins import ConfigError, UnknownMethodError
    from bench.scaffold import ScaffoldError
    from tasks.demo import DemoError
    from tasks.registry import UnknownTaskError
    try:
        return args.fn(args) or 0
    except (UnknownTaskError, UnknownMethodError, ConfigError, BudgetError, DemoError,
            InformationError, FileNotFoundError, ScaffoldError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return EXIT_BAD_INPUT


def entry() -> int:
    """The `ildbench` command: `main` in a process with glibc's huge-page tunable, which
    spares XLA's per-call working memory its page faults (bench.malloc; the same numbers;
    ILDBENCH_HUGEPAGES=0 runs without it)."""
    from bench.malloc import reexec_with_hugepages
    reexec_with_hugepages("bench.cli")
    return main()


if __name__ == "__main__":  # `python -m bench.cli` runs as `ildbench` does, tunable and all
    sys.exit(entry())
