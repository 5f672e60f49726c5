"""Running a grid of prepared cells: the local executor (one cell at a time, each in a fresh
child process by default) and the Ray executor (cells as Ray tasks, each with the same
CPU/GPU request).

Process isolation: a long sweep in one process accumulates compiled executables (every
method x perturbed env compiles its own) until LLVM fails to map memory and the process
dies (seen on a 2-core box after ~6 cells with transfer evaluation: vm.max_map_count is
65530). A child per cell starts clean, and a hard crash (segfault, OOM kill) costs that cell
only: it is reported, left unrecorded, and re-run on resume. The persistent compilation
cache keeps the re-compiling cheap.

Both are idempotent: a cell whose content-hashed record is finished in the store is skipped,
so an interrupted sweep resumes where it stopped. Records are written by whichever process
ran the cell, atomically (bench.store), one file per run id: concurrent workers never share
a file, and a reader never sees half a record.

Compile warm-up: under a wall-clock budget that charges JIT compile time (the default), a
cell's score depended on the state of the persistent compilation cache: the first seed of a
configuration compiled from scratch (in a 3-minute grid, ILD on inverted_pendulum spent 179 of
its 180 s compiling and made 1 update; SHAC's 194 s left it none), later seeds loaded the
cache (~20 s). So before the first cell of each group of cells that share compiled training
graphs (same method, version, task, config and demo count) the sweep runs that cell once
more in a spawned process with a one-env-step budget, one evaluation and no transfer, into a
throwaway store: it fills the persistent cache, and every timed cell then pays the same
cache-load cost. This holds only if a method's training graph compiles once: SHAC's first
state carried weak types, its second epoch compiled again, uncached, and its first seed on
humanoid and walker2d spent 206 and 181 s of a 180-s budget compiling (fixed since,
per-epoch numbers unchanged; tests/test_shac.py checks that it compiles once). Skipped where
it cannot matter (env-step budgets, compile not charged) and with `warm=False` (`--no-warm`).

Parallel cells on one machine (`workers` > 1, `--workers N`): that many cells at a time, each
in its own spawned process pinned to one CPU of the sweep's affinity set, so every cell
gets the same single core (records say so in `resources`); the compile warm-ups run the same
way first. The store is safe for that: records are written atomically, one file per run id.

Progress (rich): cells done / skipped / left, each cell's score and env steps, and an ETA from
the sweep's own pace (elapsed time per cell run so far, warm-ups and parallel cells included).
"""
from __future__ import annotations

import dataclasses
import json
import shutil
import sys
import tempfile
import time
from typing import Callable, Sequence

from bench.budget import Budget, format_steps
from bench.runner import Prepared, RunRequest, execute, failed_record, prepare
from bench.store import Store, write_atomic


@dataclasses.dataclass
class Outcome:
    run_id: str
    method: str
    task: str
    seed: int
    status: str
    normalized: float | None
    skipped: bool
    wall_s: float
    env_steps: int | None = None


class Progress:
    """Counts, each cell's score and env steps, and an ETA; a rich live bar on a terminal,
    plain lines otherwise. The ETA: the cells left times the mean wall time of the cells
    run so far (their compile warm-ups included), over the `workers` that run them at once;
    `workers=None` (an executor whose parallelism is not known here, Ray) uses the sweep's
    own pace instead, the time since it started over the cells run so far. Skipped cells
    (finished before) cost nothing."""

    def __init__(self, total: int, to_run: int, log: Callable[[str], None] = print,
                 workers: int | None = 1, clock: Callable[[], float] = time.perf_counter):
        self.total, self.to_run, self.log = total, to_run, log
        self.workers, self.clock = workers, clock
        self.done = self.skipped = 0
        self.walls: list[float] = []
        self.t0 = clock()
        self._bar = None
        if sys.stdout.isatty():
            from rich.progress import (BarColumn, MofNCompleteColumn, Progress as RP,
                                       TextColumn, TimeElapsedColumn)
            self._bar = RP(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                           TimeElapsedColumn(), TextColumn("ETA {task.fields[eta]}"))
            self._bar.start()
            self._task = self._bar.add_task("sweep", total=total, eta="?")

    @property
    def ran(self) -> int:
        return len(self.walls)

    def eta_s(self) -> float | None:
        if not self.walls:
            return None
        left = self.to_run - self.ran
        if self.workers is None:
            return left * (self.clock() - self.t0) / self.ran
        return left * (sum(self.walls) / self.ran) / self.workers

    def update(self, o: Outcome) -> str:
        self.done += 1
        if o.skipped:
            self.skipped += 1
        else:
            self.walls.append(o.wall_s)
        eta = self.eta_s()
        eta_txt = "?" if eta is None else time.strftime("%H:%M:%S", time.gmtime(eta))
        score = "-" if o.normalized is None else f"{o.normalized:.3f}"
        steps = "" if o.env_steps is None else f", {format_steps(o.env_steps)} env steps"
        line = (f"[{self.done}/{self.total}] {o.method} on {o.task} seed {o.seed}: "
                f"{'skipped (finished before), ' if o.skipped else ''}{o.status}, normalized "
                f"{score}{steps} | run {self.ran}, skipped {self.skipped}, left "
                f"{self.total - self.done}, ETA {eta_txt}")
        if self._bar is not None:
            self._bar.update(self._task, advance=1, eta=eta_txt,
                             description=f"{o.method}/{o.task}/{o.seed}: {score}")
            self._bar.console.print(line)
        else:
            self.log(line)
        return line

    def close(self):
        if self._bar is not None:
            self._bar.stop()


def _outcome(p: Prepared, rec: dict, skipped: bool, wall: float) -> Outcome:
    r = p.request
    return Outcome(p.run_id, r.method, r.task, r.seed, rec["status"],
                   rec.get("final_normalized"), skipped, wall, rec.get("env_steps"))


CRASH_HOOK = "ILDBENCH_TEST_CRASH_CELL"
"""Test hook: a child whose cell is '<method>/<task>/<seed>' exits hard before running."""


def _cell(request: RunRequest, store_root: str, force: bool, jax_cache: str | None,
          log: Callable[[str], None]) -> tuple[Prepared, dict, bool]:
    """One cell in a fresh process (a spawned child or a Ray worker): re-validated there
    (the process imports the method's code itself), run, record written by that process."""
    from bench.runner import enable_compilation_cache
    enable_compilation_cache(jax_cache)
    p = prepare(request)
    rec, skipped = execute(p, Store(store_root), force=force, log=log)
    return p, rec, skipped


EXIT_PARENT_GONE = 75
"""The exit code of a spawned cell whose sweep ended before it (`exit_with_parent`)."""


def exit_with_parent() -> None:
    """In a spawned child: a daemon thread that ends this process as soon as its parent
    process ends, however it ends (SIGTERM, SIGKILL, a crash). A sweep stopped by a signal
    to its own process would otherwise leave its running cell behind, training on beside
    whatever runs next and writing its record into the store after the sweep is gone
    (two such cells once ran on, sharing the cores with the restarted sweep's).
    A cell ended this way writes no record (records are written whole, at the end), so it
    re-runs on resume. Nothing to do in a process that is no multiprocessing child."""
    import multiprocessing as mp
    import os
    import threading
    from multiprocessing.connection import wait
    parent = mp.parent_process()
    if parent is None:
        return

    def watch():
        wait([parent.sentinel])  # ready when the parent has ended
        os._exit(EXIT_PARENT_GONE)
    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def _child(request: RunRequest, store_root: str, force: bool, jax_cache: str | None,
           quiet: bool = False, cpu: int | None = None) -> None:
    import os
    exit_with_parent()
    if cpu is not None:  # one core of the sweep's, before torch or XLA size their pools
        os.sched_setaffinity(0, {cpu})
    r = request
    if os.environ.get(CRASH_HOOK) == f"{r.method}/{r.task}/{r.seed}":
        os._exit(70)
    _cell(request, store_root, force, jax_cache,
          log=(lambda s: None) if quiet else (lambda s: print(s, flush=True)))


def _spawn(request: RunRequest, store_root: str, force: bool, jax_cache: str | None,
           quiet: bool = False, cpu: int | None = None) -> int | None:
    """Run one cell in a fresh spawned process (pinned to `cpu` if given); returns its exit
    code."""
    import multiprocessing as mp
    proc = mp.get_context("spawn").Process(
        target=_child, args=(request, store_root, force, jax_cache, quiet, cpu))
    proc.start()
    proc.join()
    return proc.exitcode


def _run_isolated(p: Prepared, store: Store, force: bool, jax_cache: str | None,
                  log: Callable[[str], None], quiet: bool = False,
                  cpu: int | None = None) -> tuple[dict, bool]:
    import os
    code = _spawn(p.request, os.path.abspath(store.root), force, jax_cache, quiet, cpu)
    rec = store.get(p.run_id)
    if rec is not None and (code == 0 or rec.get("status") in ("ok", "diverged", "failed")):
        return rec, False
    why = f"signal {-code}" if code and code < 0 else f"exit code {code}"
    log(f"run {p.run_id}: the cell's process died ({why}) before writing a record; it is "
        "left unrecorded and re-runs on resume")
    return {"status": "crashed", "final_normalized": None}, False


def needs_warmup(p: Prepared) -> bool:
    """Compile time can change this cell's result: a wall-clock budget that charges it."""
    b = p.request.budget
    return b.seconds is not None and b.charge_compile


def compile_group(p: Prepared) -> str:
    """Cells with the same key share their compiled training graphs (the seed, budget and
    evaluation settings are not baked into them)."""
    r = p.request
    return json.dumps({"method": r.method, "version": p.spec.version, "task": r.task,
                       "config": dataclasses.asdict(p.config), "num_demos": r.num_demos,
                       "physics": r.physics, "train_dynamics": r.train_dynamics},
                      sort_keys=True, default=str)


def warmup_request(r: RunRequest) -> RunRequest:
    """The cell cut to one env step of training (one update or chunk) and one evaluation
    with the cell's own evaluation settings (the evaluator's graph is compiled per batch
    size), without transfer or robustness: enough to compile its training and evaluation
    graphs. (The perturbed envs of a transfer evaluation still compile in the first timed
    cell; evaluation compile is not charged to the training budget.)"""
    return dataclasses.replace(
        r, budget=Budget(env_steps=1, evals=1, charge_compile=r.budget.charge_compile),
        eval=dataclasses.replace(r.eval, transfer=False, robustness=False))


def warmup_groups(pending: Sequence[Prepared]) -> list[Prepared]:
    """The first cell of each compile group among `pending` whose result compile time can
    change (`needs_warmup`): the cells an executor warms up before running any."""
    groups: dict[str, Prepared] = {}
    for p in pending:
        if needs_warmup(p):
            groups.setdefault(compile_group(p), p)
    return list(groups.values())


def warm_up(p: Prepared, jax_cache: str | None, log: Callable[[str], None],
            cpu: int | None = None) -> None:
    """Run the warm-up cell in a spawned process (so only the persistent cache carries
    over, as between the sweep's own cells) into a throwaway store."""
    tmp = tempfile.mkdtemp(prefix="ildbench-warmup-")
    t0 = time.perf_counter()
    try:
        code = _spawn(warmup_request(p.request), tmp, True, jax_cache, quiet=True, cpu=cpu)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    r = p.request
    log(f"compile warm-up for {r.method} on {r.task}: {time.perf_counter() - t0:.0f}s"
        + ("" if code == 0 else f" (its process ended with code {code}; the cells run "
           "anyway)"))


def worker_cpus(workers: int) -> list[int]:
    """The first `workers` CPUs of this process's affinity set, one per parallel cell; a
    clear error where the set has fewer."""
    import os
    cpus = sorted(os.sched_getaffinity(0))
    if workers < 1:
        raise ValueError(f"--workers {workers}: give at least 1")
    if workers > len(cpus):
        raise ValueError(f"--workers {workers}: this process may use {len(cpus)} CPU(s) "
                         f"({cpus}); give at most {len(cpus)}, one core per cell")
    return cpus[:workers]


def run_parallel(prepared: Sequence[Prepared], store: Store, workers: int,
                 force: bool = False, log: Callable[[str], None] = print,
                 jax_cache: str | None = None, warm: bool = True) -> list[Outcome]:
    """`workers` cells at a time, each in a spawned process pinned to its own CPU (the first
    `workers` of the sweep's affinity set). Compile warm-ups run first, the same way, one per
    compile group; then the cells, in order, each to the next free CPU. The children run
    quietly: the sweep prints one line per finished cell."""
    import queue
    from concurrent.futures import ThreadPoolExecutor, as_completed
    cpus = worker_cpus(workers)
    free: queue.Queue = queue.Queue()
    for c in cpus:
        free.put(c)
    finished = {id(p): None if force else store.finished(p.run_id) for p in prepared}
    pending = [p for p in prepared if finished[id(p)] is None]
    progress = None

    def on_a_cpu(fn, *args):
        cpu = free.get()
        try:
            return fn(*args, cpu=cpu)
        finally:
            free.put(cpu)

    out = []
    try:
        with ThreadPoolExecutor(max_workers=workers) as pool:
            if warm:
                for f in as_completed([pool.submit(on_a_cpu, warm_up, p, jax_cache, log)
                                       for p in warmup_groups(pending)]):
                    f.result()
            progress = Progress(len(prepared), len(pending), log, workers=workers)
            for p in prepared:
                if finished[id(p)] is not None:
                    o = _outcome(p, finished[id(p)], True, 0.0)
                    progress.update(o)
                    out.append(o)

            def one(p: Prepared, cpu: int) -> Outcome:
                t0 = time.perf_counter()
                rec, skipped = _run_isolated(p, store, force, jax_cache, log, quiet=True,
                                             cpu=cpu)
                return _outcome(p, rec, skipped, time.perf_counter() - t0)

            for f in as_completed([pool.submit(on_a_cpu, one, p) for p in pending]):
                o = f.result()
                progress.update(o)
                out.append(o)
    finally:
        if progress is not None:
            progress.close()
    return out


def run_local(prepared: Sequence[Prepared], store: Store, force: bool = False,
              log: Callable[[str], None] = print, isolate: bool = True,
              jax_cache: str | None = None, warm: bool = True,
              workers: int = 1) -> list[Outcome]:
    """`isolate`: each cell in a fresh spawned process (default); False: in this process.
    `warm`: a compile warm-up before the first pending cell of each compile group.
    `workers` > 1: that many cells at a time, one CPU each (`run_parallel`)."""
    if workers > 1:
        if not isolate:
            raise ValueError("parallel cells (--workers > 1) each need their own process; "
                             "drop --in-process")
        return run_parallel(prepared, store, workers, force, log, jax_cache, warm)
    to_run = sum(force or store.finished(p.run_id) is None for p in prepared)
    progress = Progress(len(prepared), to_run, log)
    out = []
    warmed: set[str] = set()
    try:
        for p in prepared:
            t0 = time.perf_counter()
            done = None if force else store.finished(p.run_id)
            if done is None and warm and needs_warmup(p) and compile_group(p) not in warmed:
                warmed.add(compile_group(p))
                warm_up(p, jax_cache, log)  # in this cell's wall time: the ETA counts it
            if done is not None:
                rec, skipped = done, True
            elif isolate:
                rec, skipped = _run_isolated(p, store, force, jax_cache, log)
            else:
                rec, skipped = execute(p, store, force=force, log=log)
            o = _outcome(p, rec, skipped, time.perf_counter() - t0)
            progress.update(o)
            out.append(o)
    finally:
        progress.close()
    return out


def _ray_cell(request: RunRequest, jax_cache: str | None, cpus: float) -> dict:
    """A cell in a Ray worker, which records the CPUs the cell reserved. It runs into a
    private folder of the worker's and returns its record and side files (the render
    trajectory) to the driver, which writes them into its own store: the cluster needs no
    shared disk."""
    import os
    os.environ["ILDBENCH_CPUS_PER_RUN"] = str(cpus)
    t0 = time.perf_counter()
    tmp = tempfile.mkdtemp(prefix="ildbench-cell-")
    try:
        p, rec, _ = _cell(request, tmp, True, jax_cache, log=lambda s: None)
        files = {}
        for name in os.listdir(tmp):
            if name.startswith(p.run_id + ".") and not name.endswith(".json"):
                with open(os.path.join(tmp, name), "rb") as f:
                    files[name] = f.read()
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return {"record": rec, "files": files, "wall_s": time.perf_counter() - t0}


def write_returned(store: Store, record: dict, files: dict[str, bytes]) -> None:
    """Write a cell's record and side files, returned by a worker, into the driver's store
    (side files first, so a record never names a file that is not there yet)."""
    import os
    for name, data in files.items():
        write_atomic(os.path.join(store.root, os.path.basename(name)),
                     lambda f, d=data: f.write(d), binary=True)
    store.write(record)


def run_ray(prepared: Sequence[Prepared], store: Store, address: str | None = None,
            cpus_per_run: float = 1, gpus_per_run: float = 0, force: bool = False,
            jax_cache: str | None = None, log: Callable[[str], None] = print,
            init_kwargs: dict | None = None, warm: bool = True,
            on_submit: Callable[[Prepared, object], None] | None = None) -> list[Outcome]:
    """Cells as Ray tasks. `address`: an existing cluster ('auto' or 'ray://host:port');
    None starts a local Ray. Every cell requests the same CPUs/GPUs, so runs in one
    comparison get equal resources. Workers need no access to the store: each returns its
    record to this process, which writes it (`write_returned`). A cell whose worker dies is
    recorded as 'failed' with the reason, and re-runs on resume. `warm`: each compile
    group's warm-up runs as a Ray task before any cell is submitted. On a cluster the
    persistent compilation cache (`jax_cache`) must be a path every worker reaches, or a
    worker's first cell of a group still compiles from scratch. `on_submit(p, ref)`: called
    as each cell is submitted (tests kill a worker through it)."""
    import ray
    if not ray.is_initialized():
        ray.init(address=address, include_dashboard=False, log_to_driver=False,
                 **(init_kwargs or {}))
    cell = ray.remote(num_cpus=cpus_per_run, num_gpus=gpus_per_run, max_retries=0)(_ray_cell)
    if warm:
        groups = warmup_groups([p for p in prepared
                                if force or store.finished(p.run_id) is None])
        if groups:
            t0 = time.perf_counter()  # the warm-ups' returned records are dropped
            refs = [cell.remote(warmup_request(p.request), jax_cache, cpus_per_run)
                    for p in groups]
            for ref in refs:
                try:
                    ray.get(ref)
                except Exception as e:  # the cells run anyway and report their own
                    log(f"a compile warm-up failed in its Ray worker: {e}")
            log(f"compile warm-up of {len(groups)} group(s): {time.perf_counter() - t0:.0f}s")
    pending = {}
    skipped = []
    for p in prepared:
        done = None if force else store.finished(p.run_id)
        if done is not None:
            skipped.append(_outcome(p, done, True, 0.0))
        else:
            ref = cell.remote(p.request, jax_cache, cpus_per_run)
            pending[ref] = p
            if on_submit is not None:
                on_submit(p, ref)
    progress = Progress(len(prepared), len(pending), log, workers=None)
    out = []
    try:
        for o in skipped:
            progress.update(o)
            out.append(o)
        while pending:
            ready, _ = ray.wait(list(pending), num_returns=1)
            p = pending.pop(ready[0])
            try:
                res = ray.get(ready[0])
                rec, wall = res["record"], res["wall_s"]
                write_returned(store, rec, res["files"])
            except Exception as e:  # the worker died: the cell is recorded as failed
                first = str(e).strip().splitlines()[0] if str(e).strip() else ""
                why = type(e).__name__ + (f": {first}" if first else "")
                log(f"cell {p.run_id} ({p.request.method} on {p.request.task}) died in its "
                    f"Ray worker ({why}); recorded as failed, it re-runs on resume")
                rec, wall = failed_record(p, f"the Ray worker died: {why}"), 0.0
                store.write(rec)
            o = _outcome(p, rec, False, wall)
            progress.update(o)
            out.append(o)
    finally:
        progress.close()
    return out
