"""One budgeted run: task -> demo -> method -> evaluation -> stored record.

Everything that can be wrong with the input (unknown names, invalid config or budget,
malformed or mismatched demo) is checked before any work starts and before anything is
written. A run that fails is recorded as 'failed' with its message; one that produces
non-finite numbers as 'diverged' with its last valid evaluation. Finished records
('ok'/'diverged') are never overwritten unless forced.
"""
from __future__ import annotations

import dataclasses
import datetime
import hashlib
import json
import os
import pickle
import time
import traceback
from typing import Any, Callable, Mapping

import jax
import numpy as np

from bench import __version__
from bench.access import DemoView, TaskView
from bench.api import Diverged, MethodSpec, Policy, TrainResult
from bench.budget import Budget, Clock
from bench.evaluator import EvalConfig, Evaluator
from bench.perturb import Perturbation, parse_dynamics
from bench.machine import git_revision, machine, resources
from bench.plugins import build_config, get_method
from bench.store import Store, write_atomic
from bench.transfer import default_summary
from tasks import make_task
from tasks.demo import Demo, library_versions, load_demo
from tasks.physics.plan import FIELDS as PLAN_FIELDS
from tasks.physics.plan import CHOICES, Plan, choose

_REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def enable_compilation_cache(path: str | None = None, min_compile_s: float = 0.5) -> str:
    """JAX's persistent compilation cache, so a repeated configuration skips most compiling.
    Location: `path`, else $ILDBENCH_JAX_CACHE, else ~/.cache/ildbench/jax. JAX fixes the
    location at the first compilation of the process: call this before any."""
    path = path or os.environ.get("ILDBENCH_JAX_CACHE") or os.path.join(
        os.path.expanduser("~"), ".cache", "ildbench", "jax")
    os.makedirs(path, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", min_compile_s)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return path


def _canonical(obj: Any) -> str:
    return json.dumps(obj, sort_keys=True, default=str)


def config_identity(config_cls: type | None, config: Mapping[str, Any]) -> dict:
    """A config as it identifies a run: the fields that differ from the config class's
    defaults (JSON-normalized, so a tuple equals the list a record stores). A knob added
    later with a default that reproduces the old behaviour then neither re-runs finished
    cells nor splits their variant (records made before it existed lack the field, which
    reads as the default); a change of behaviour bumps the method's `version` instead.
    `config_cls` None (a record of a method not registered here): the whole config."""
    norm = json.loads(_canonical(dict(config)))
    if config_cls is None:
        return norm
    defaults = {}
    for f in dataclasses.fields(config_cls):
        if f.default is not dataclasses.MISSING:
            defaults[f.name] = json.loads(_canonical(f.default))
        elif f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
            defaults[f.name] = json.loads(_canonical(f.default_factory()))  # type: ignore[misc]
    return {k: v for k, v in norm.items() if k not in defaults or v != defaults[k]}


def _run_key(method: str, version: str, config: dict, task: str, demo_sha: str, seed: int,
             budget: dict, eval_cfg: dict, num_demos: int, ildbench: str,
             train_dynamics: str | None = None) -> str:
    key = {"method": method, "method_version": version, "config": config, "task": task,
           "demo": demo_sha, "seed": seed, "budget": budget, "eval": eval_cfg,
           "num_demos": num_demos, "ildbench": ildbench}
    if train_dynamics is not None:  # absent for the nominal dynamics: those ids stay as they are
        key["train_dynamics"] = train_dynamics
    return hashlib.sha256(_canonical(key).encode()).hexdigest()[:16]


def run_id(method: MethodSpec, config, task: str, demo_sha: str, seed: int, budget: Budget,
           eval_cfg: EvalConfig, num_demos: int, plan: Plan | None = None,
           dynamics: Perturbation | None = None) -> str:
    """Content hash of everything that determines the result. The git revision is recorded
    but not hashed (it would re-run every cell after any commit); a method's `version`
    and the ildbench version are hashed instead: bump them when results change. The config
    enters as its `config_identity` (non-default fields only), with the physics plan's
    (`Plan.identity`: the rewrites that differ from `Plan()`) beside it for a method that
    differentiates through the physics. Changed training dynamics (`dynamics`) enter as
    their key (e.g. 'action_bias=0.2:fixed'); the nominal dynamics add nothing."""
    identity = config_identity(method.config_cls, dataclasses.asdict(config))
    if plan is not None:
        identity = {**identity, **plan.identity()}
    return _run_key(method.name, method.version, identity, task, demo_sha, seed,
                    dataclasses.asdict(budget), dataclasses.asdict(eval_cfg), num_demos,
                    __version__, None if dynamics is None else dynamics.key)


def record_config_identity(record: Mapping[str, Any]) -> dict:
    """`config_identity` of a stored record, against its method's config class if that
    method is registered here (else the whole config), with its physics plan's identity
    (`run_id`): the record's `physics` field, or, in a record that has none, the plan's
    fields its config holds (where the rewrites were config fields)."""
    from bench.plugins import all_methods
    spec = all_methods().get(record.get("method"))
    config = dict(record.get("config") or {})
    if spec is None or not spec.uses.sim_gradients:
        return config_identity(spec.config_cls if spec else None, config)
    in_config = {k: config.pop(k) for k in PLAN_FIELDS if k in config}
    physics = record.get("physics")
    plan = Plan(**(physics["plan"] if physics else in_config))
    return {**config_identity(spec.config_cls, config), **plan.identity()}


def record_run_id(record: Mapping[str, Any]) -> str:
    """The run id a record would get today (its stored fields under the current id scheme)."""
    return _run_key(record["method"], record["method_version"],
                    record_config_identity(record), record["task"],
                    record["demo"]["sha256"], record["seed"], record["budget"], record["eval"],
                    record["num_demos"], record["versions"]["ildbench"],
                    (record.get("train_dynamics") or {}).get("key"))


def reindex(store: Store, dry_run: bool = False, log: Callable[[str], None] = print
            ) -> list[tuple[str, str]]:
    """Rename a store's records to the current run-id scheme (`ildbench reindex`), so a
    sweep finds the cells that store already holds. Returns (old, new) pairs. The record
    keeps its old id under `previous_run_ids`. Two records that now share an id are the
    same cell run twice: the newer stays, the older moves to <store>/duplicates/."""
    from bench.store import write_json_atomic
    moves = []
    for rec in list(store.records()):
        if "run_id" not in rec or "versions" not in rec:
            log(f"reindex: {rec.get('run_id', '?')} is not a run record; left as is")
            continue
        new = record_run_id(rec)
        old = rec["run_id"]
        if new == old:
            continue
        moves.append((old, new))
        if dry_run:
            continue
        there = store.get(new)
        if there is not None and str(there.get("started", "")) >= str(rec.get("started", "")):
            _move_aside(store, old)
            log(f"reindex: {old} duplicates the newer {new}; moved to duplicates/")
            continue
        if there is not None:
            _move_aside(store, new)
            log(f"reindex: {new} duplicates the newer {old}; moved to duplicates/")
        rec = {**rec, "run_id": new,
               "previous_run_ids": list(rec.get("previous_run_ids", [])) + [old]}
        traj_old, traj_new = store.trajectory_path(old), store.trajectory_path(new)
        if os.path.exists(traj_old):
            os.replace(traj_old, traj_new)
        write_json_atomic(store.path(new), rec)
        os.remove(store.path(old))
    log(f"reindex: {len(moves)} of the records in {store.root} "
        f"{'would be' if dry_run else 'were'} renamed")
    return moves


def _move_aside(store: Store, run_id: str) -> None:
    dest = os.path.join(store.root, "duplicates")
    os.makedirs(dest, exist_ok=True)
    for path in (store.path(run_id), store.trajectory_path(run_id)):
        if os.path.exists(path):
            os.replace(path, os.path.join(dest, os.path.basename(path)))


def _fmt(x, digits: int) -> str:
    """A score or return for a log line: `digits` decimals, or as it is (None, NaN)."""
    return f"{x:.{digits}f}" if isinstance(x, (int, float)) and x == x else str(x)


def _finite_tree(tree) -> bool:
    leaves = [np.asarray(x) for x in jax.tree_util.tree_leaves(tree)]
    return all(np.isfinite(x).all() for x in leaves if np.issubdtype(x.dtype, np.inexact))


CHECKPOINT_EVERY_S = 300.0
"""Seconds of wall time between two checkpoints of a run that can take them."""


class RunContext:
    """Handed to a method's train(): its budget, its clock, the report hook, and (on an
    env-step budget run from a store) `checkpoint` / `resume`, so that a run stopped part way
    (a session that ends, a killed process) goes on from its last checkpoint."""

    def __init__(self, budget: Budget, evaluator: Evaluator, seed: int,
                 log: Callable[[str], None] = lambda s: None,
                 checkpoint_path: str | None = None,
                 checkpoint_every_s: float = CHECKPOINT_EVERY_S):
        self.budget = budget
        self.seed = seed
        self.clock = Clock(budget.charge_compile)
        self.curve: list[dict] = []
        self.last_metrics: dict = {}
        self.last_trajectory = None  # matched states of the last evaluation's first episode
        self.log = log
        self._evaluator = evaluator
        self._next_eval_s = 0.0 if budget.seconds is None else budget.seconds / budget.evals
        self._next_eval_steps = (None if budget.env_steps is None
                                 else budget.env_steps / budget.evals)
        self._checkpoint_path = checkpoint_path
        self._checkpoint_every_s = float(checkpoint_every_s)
        self._last_checkpoint = time.perf_counter()
        self.resumed: list[dict] = []
        """One entry per resume: the env steps it resumed from and the code that resumed."""

    # ------------------------------------------------------------------ checkpoints

    @property
    def checkpointing(self) -> bool:
        """True when this run may checkpoint: an env-step budget, run into a store. (A
        wall-clock budget is not resumed: its seconds are only comparable in one sitting.)"""
        return self._checkpoint_path is not None and self.budget.env_steps is not None

    def checkpoint_due(self) -> bool:
        """True when the last checkpoint (or the start) is `checkpoint_every_s` ago."""
        return self.checkpointing and (time.perf_counter() - self._last_checkpoint
                                       >= self._checkpoint_every_s)

    def checkpoint(self, method_state: Any, env_steps: int) -> None:
        """Save the method's state (any picklable object from which it can go on exactly as
        if never stopped) with the harness's own (curve, clock, evaluation schedule),
        atomically, with the method's clock paused. A no-op where not `checkpointing`."""
        if not self.checkpointing:
            return
        with self.clock.paused():
            c = self.clock
            harness = {"curve": self.curve, "last_metrics": self.last_metrics,
                       "last_trajectory": self.last_trajectory,
                       "next_eval": (self._next_eval_s, self._next_eval_steps),
                       "elapsed": self.elapsed(), "compile_s": dict(c.compile_s),
                       "compiles": dict(c.compiles), "interval": c.interval,
                       "retraced": c.retraced, "resumed": self.resumed}
            blob = {"env_steps": int(env_steps), "harness": harness, "method": method_state}
            os.makedirs(os.path.dirname(self._checkpoint_path), exist_ok=True)
            write_atomic(self._checkpoint_path,
                         lambda f: pickle.dump(blob, f, protocol=pickle.HIGHEST_PROTOCOL),
                         binary=True)
        self._last_checkpoint = time.perf_counter()
        self.log(f"  checkpoint at {env_steps} env steps")

    def resume(self) -> Any | None:
        """The method's state from this run's last checkpoint, with the harness's own state
        restored (the curve so far, the train clock, the evaluation schedule); None when
        there is none (a fresh run). Call once, before training."""
        if not self.checkpointing or not os.path.exists(self._checkpoint_path):
            return None
        with open(self._checkpoint_path, "rb") as f:
            blob = pickle.load(f)
        h, c = blob["harness"], self.clock
        self.curve, self.last_metrics = h["curve"], h["last_metrics"]
        self.last_trajectory = h["last_trajectory"]
        self._next_eval_s, self._next_eval_steps = h["next_eval"]
        c.compile_s, c.compiles = dict(h["compile_s"]), dict(h["compiles"])
        c.interval, c.retraced = h["interval"], h["retraced"]
        # The clock goes on from the saved train time (what this process compiles again on
        # resuming is charged like any other compile).
        c._start, c._paused = time.perf_counter() - h["elapsed"] - (
            0.0 if c.charge_compile else c.compile_s["train"]), 0.0
        self.resumed = list(h["resumed"]) + [{"env_steps": blob["env_steps"],
                                              "git_revision": git_revision()}]
        self._last_checkpoint = time.perf_counter()
        self.log(f"  resumed from the checkpoint at {blob['env_steps']} env steps")
        return blob["method"]

    def drop_checkpoint(self) -> None:
        if self._checkpoint_path is not None and os.path.exists(self._checkpoint_path):
            os.remove(self._checkpoint_path)

    def elapsed(self) -> float:
        return self.clock.elapsed()

    def spent(self, env_steps: int) -> float:
        """Fraction of the budget used so far (the larger of time and env steps), in [0, 1];
        for schedules that should finish within the budget."""
        b = self.budget
        parts = [0.0]
        if b.seconds is not None:
            parts.append(self.clock.elapsed() / b.seconds)
        if b.env_steps is not None:
            parts.append(env_steps / b.env_steps)
        return min(max(parts), 1.0)

    def remaining(self, env_steps: int) -> tuple[float | None, int | None]:
        """(seconds, env steps) left in the budget; None where the budget has no such limit.
        For methods that run several updates per call and must not overrun the budget."""
        b = self.budget
        return (None if b.seconds is None else b.seconds - self.clock.elapsed(),
                None if b.env_steps is None else b.env_steps - env_steps)

    def should_stop(self, env_steps: int) -> bool:
        """True once the budget is spent: the method must then return its final policy."""
        return any(left is not None and left <= 0 for left in self.remaining(env_steps))

    def report(self, policy: Policy, env_steps: int, metrics: Mapping[str, Any] | None = None,
               force_eval: bool = False) -> None:
        """Call from the method's outer loop. Records metrics; evaluates when due (clock
        paused). Raises Diverged if the metrics or the policy are non-finite."""
        self.clock.interval += 1  # = reports so far
        metrics = {k: float(v) for k, v in (metrics or {}).items()}
        self.last_metrics = metrics
        bad = [k for k, v in metrics.items() if not np.isfinite(v)]
        if bad or not _finite_tree(policy.params):
            raise Diverged(f"non-finite {'metrics ' + ', '.join(bad) if bad else 'parameters'} "
                           f"at env step {env_steps}, train time {self.elapsed():.1f}s")
        b = self.budget
        due = force_eval or (b.seconds is not None and self.elapsed() >= self._next_eval_s) or (
            self._next_eval_steps is not None and env_steps >= self._next_eval_steps)
        if due:
            self.evaluate(policy, env_steps)
            if b.seconds is not None:
                while self._next_eval_s <= self.elapsed():
                    self._next_eval_s += b.seconds / b.evals
            if self._next_eval_steps is not None:
                while self._next_eval_steps <= env_steps:
                    self._next_eval_steps += b.env_steps / b.evals

    @property
    def reports(self) -> int:
        """Reports the method has made (the clock counts them to date its traces)."""
        return self.clock.interval

    def retraced(self) -> dict[str, dict] | None:
        """Training functions JAX traced again after a report that followed their first
        trace: 'name (file:line)' -> {'count', 'why'} ('why': JAX's own explanation of the
        cache miss, e.g. "at x, now f32[]{weak_type=True} and before f32[]"). A method whose
        update compiles once has none: a warm start and the first update trace before, or
        between, its first reports, each once. An entry means that function was compiled
        again: a carried state whose dtypes, weak types or shapes change (brax's hopper
        writing a Python float into a metric made SHAC compile its epoch twice), a fresh
        `jax.jit` closure per update, a static argument that varies. None when the method
        never reported (a planner: nothing to compare)."""
        if self.reports < 1:
            return None
        return {k: dict(v) for k, v in self.clock.retraced.items()}

    def evaluate(self, policy: Policy, env_steps: int) -> dict:
        with self.clock.paused():
            res = self._evaluator.evaluate(policy, self.seed)
        if not res.finite:
            raise Diverged(f"non-finite evaluation return at env step {env_steps}")
        self.last_trajectory = res.trajectory
        point = {"train_s": round(self.elapsed(), 3), "env_steps": int(env_steps),
                 "return": res.mean_return, "normalized": res.mean_normalized,
                 "length": res.mean_length,
                 # the method's last reported training metrics: loss beside score over time
                 "train": dict(self.last_metrics)}
        self.curve.append(point)
        self.log(f"  eval @ {point['train_s']:.1f}s, {env_steps} env steps: return "
                 f"{_fmt(point['return'], 2)}, normalized {_fmt(point['normalized'], 3)}")
        return point


@dataclasses.dataclass(frozen=True)
class RunRequest:
    method: str
    task: str
    seed: int
    budget: Budget
    preset: str | None = None
    overrides: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    eval: EvalConfig = EvalConfig()
    num_demos: int = 1
    physics: str = "task"
    """For a method that differentiates through the physics: 'task' (the task's physics plan
    on this platform, `tasks.physics.plan`) or 'reference' (brax's step as it is)."""
    train_dynamics: str | None = None
    """The dynamics the method trains in and is scored under, `FAMILY[:MAGNITUDE]
    [:fixed|fresh]` (`bench.perturb.parse_dynamics`); None: the nominal task."""


@dataclasses.dataclass
class Prepared:
    request: RunRequest
    spec: MethodSpec
    config: Any
    demo: Demo
    run_id: str
    plan: Plan | None = None
    """The physics plan the method's env runs (None: a method that does not differentiate
    through the physics steps the task itself)."""
    platform: str | None = None
    dynamics: Perturbation | None = None
    """The changed training dynamics (None: nominal)."""


def prepare(req: RunRequest) -> Prepared:
    """Validate everything and compute the run id. No work, no writes."""
    spec = get_method(req.method)
    task = make_task(req.task)
    config = build_config(spec, req.task, req.preset, req.overrides)
    plan = platform = None
    if spec.uses.sim_gradients:
        from bench.plugins import current_platform
        platform = current_platform()
        plan = choose(req.task, req.physics, platform)
    elif req.physics not in CHOICES:
        choose(req.task, req.physics, "cpu")  # names the valid choices
    if task.spec.demo_path is None:
        raise FileNotFoundError(f"task {req.task!r} has no demo yet; create one with "
                                f"`ildbench expert train --task {req.task}` then "
                                f"`ildbench expert demo --task {req.task}`")
    dynamics = (None if req.train_dynamics is None
                else parse_dynamics(req.train_dynamics, task))
    demo = load_demo(task.spec.demo_path, task)
    if not 1 <= req.num_demos <= demo.num_demos:
        raise ValueError(f"num_demos must be in 1..{demo.num_demos} for {demo.path}, got "
                         f"{req.num_demos}")
    rid = run_id(spec, config, req.task, demo.sha256, req.seed, req.budget, req.eval,
                 req.num_demos, plan, dynamics)
    return Prepared(req, spec, config, demo, rid, plan, platform, dynamics)


def _record_head(p: Prepared) -> dict:
    """The fields of a record that say which cell it is (every record starts with them)."""
    req, spec = p.request, p.spec
    return {"run_id": p.run_id, "method": spec.name, "method_version": spec.version,
            "task": req.task, "seed": req.seed, "preset": req.preset,
            "config": dataclasses.asdict(p.config), "uses": dataclasses.asdict(spec.uses),
            "reference_method": spec.reference, "budget": dataclasses.asdict(req.budget),
            "eval": dataclasses.asdict(req.eval), "num_demos": req.num_demos,
            **({"physics": {"choice": req.physics, "platform": p.platform,
                            "plan": dataclasses.asdict(p.plan)}} if p.plan else {}),
            **({"train_dynamics": p.dynamics.describe()} if p.dynamics else {})}


def failed_record(p: Prepared, message: str) -> dict:
    """The record of a cell whose process died before it could write its own (a Ray worker
    killed mid-cell): status 'failed', so the leaderboard lists it and a sweep re-runs it."""
    now = datetime.datetime.now(datetime.timezone.utc).isoformat()
    return {**_record_head(p), "status": "failed", "message": message, "final_return": None,
            "final_normalized": None, "curve": [], "transfer": {}, "train_metrics": {},
            "env_steps": 0, "references": {"expert_return": p.demo.expert_return,
                                           "random_return": p.demo.random_return},
            "git_revision": git_revision(), "machine": machine(), "started": now,
            "finished": now}


def execute(p: Prepared, store: Store, force: bool = False,
            log: Callable[[str], None] = print,
            checkpoint_every_s: float = CHECKPOINT_EVERY_S) -> tuple[dict, bool]:
    """Run one prepared cell; returns (record, skipped). A cell with an env-step budget whose
    method checkpoints (DAC, PWIL) resumes from its last checkpoint in the store, if an
    earlier run of it was stopped; `force` starts it afresh."""
    if not force:
        done = store.finished(p.run_id)
        if done is not None:
            return done, True
    req, spec = p.request, p.spec
    task = make_task(req.task)
    r_exp, r_rand = p.demo.expert_return, p.demo.random_return
    scored = task
    if p.dynamics is not None:  # scored under the dynamics it trains in, against references
        from bench.perturb import perturbed_task  # measured under them
        from bench.transfer import references
        scored = perturbed_task(task, p.dynamics)
        r_exp, r_rand = references(task, p.demo, p.dynamics)
    evaluator = Evaluator(scored, req.eval, r_exp, r_rand,
                          allow_sim_at_test=spec.uses.sim_at_test)
    ctx = RunContext(req.budget, evaluator, req.seed, log=log,
                     checkpoint_path=store.checkpoint_path(p.run_id),
                     checkpoint_every_s=checkpoint_every_s)
    if force:
        ctx.drop_checkpoint()
    started = datetime.datetime.now(datetime.timezone.utc)
    t0 = time.perf_counter()
    status, message, result, transfer, nominal = "ok", "", None, {}, None
    log(f"run {p.run_id}: {spec.name} on {req.task}, seed {req.seed}, "
        f"budget {req.budget.describe()}" + (f", training dynamics {p.dynamics.key}"
                                             if p.dynamics else ""))
    try:
        out = spec.train(TaskView(task, spec.uses, spec.name, p.plan, p.dynamics),
                         DemoView(p.demo, spec.uses, spec.name, req.num_demos),
                         p.config, ctx, req.seed)
        if not isinstance(out, TrainResult):
            raise TypeError(f"method {spec.name!r} returned {type(out).__name__}, "
                            "expected bench.api.TrainResult")
        result = out
        if not _finite_tree(result.policy.params):
            raise Diverged("the final policy has non-finite parameters")
        train_s = ctx.elapsed()
        final = ctx.evaluate(result.policy, result.env_steps)
        if p.dynamics is not None:  # the nominal score beside the headline one
            with ctx.clock.paused():
                res = Evaluator(task, req.eval, p.demo.expert_return, p.demo.random_return,
                                allow_sim_at_test=spec.uses.sim_at_test).evaluate(
                                    result.policy, req.seed)
            nominal = {"return": res.mean_return, "normalized": res.mean_normalized,
                       "length": res.mean_length}
            log(f"  nominal dynamics: return {_fmt(nominal['return'], 2)}, normalized "
                f"{_fmt(nominal['normalized'], 3)}")
        if req.eval.transfer or req.eval.robustness:
            from bench import perturb
            from bench.transfer import evaluate_transfer
            todo = (perturb.grid_set(task) if req.eval.robustness
                        else perturb.default_set(task))
            log(f"  transfer: {len(todo)} perturbed evaluations")
            with ctx.clock.paused():  # harness work: its compiling is counted as 'eval'
                transfer = evaluate_transfer(task, p.demo, result.policy, req.seed, req.eval,
                                             todo, spec.uses.sim_at_test)
    except Diverged as e:
        status, message = "diverged", str(e)
    except Exception as e:  # recorded, never raised past the record
        status, message = "failed", f"{type(e).__name__}: {e}\n{traceback.format_exc(limit=8)}"
    if status != "ok":
        train_s = ctx.elapsed()
        final = ctx.curve[-1] if ctx.curve else {"return": None, "normalized": None,
                                                 "env_steps": 0, "train_s": train_s}
    ctx.clock.close()
    retraced = ctx.retraced()
    for fun, info in (retraced or {}).items():
        log(f"  warning: {spec.name} traced {fun} again {info['count']}x after a report "
            f"(compiled again, inside its budget); JAX says: {info['why']}")
    record = {
        **_record_head(p), "status": status, "message": message,
        "final_return": final["return"], "final_normalized": final["normalized"],
        "final_from": "final policy" if status == "ok" else "last valid evaluation",
        "curve": ctx.curve, "transfer": transfer,
        # The last report's metrics, updated with the final ones the method returned.
        "train_metrics": {**ctx.last_metrics, **({k: float(v) for k, v in
                                                  result.metrics.items()} if result else {})},
        "transfer_normalized": default_summary(transfer, task),
        "env_steps": int(result.env_steps) if result is not None else final.get("env_steps", 0),
        "train_s": round(train_s, 3), "wall_s": round(time.perf_counter() - t0, 3),
        "compile_s": {k: round(v, 3) for k, v in ctx.clock.compile_s.items()},
        "compiles": dict(ctx.clock.compiles), "retraced": retraced, "reports": ctx.reports,
        **({"resumed": ctx.resumed} if ctx.resumed else {}),
        "references": {"expert_return": r_exp, "random_return": r_rand},
        **({"nominal": nominal, "nominal_references": {
            "expert_return": p.demo.expert_return, "random_return": p.demo.random_return}}
           if p.dynamics is not None else {}),
        "demo": {"path": os.path.relpath(p.demo.path, _REPO), "sha256": p.demo.sha256},
        "versions": library_versions(), "git_revision": git_revision(), "machine": machine(),
        "resources": resources(),
        "started": started.isoformat(), "finished": datetime.datetime.now(
            datetime.timezone.utc).isoformat(),
    }
    if status == "ok" and ctx.last_trajectory is not None:
        store.write_trajectory(p.run_id, ctx.last_trajectory)
        record["trajectory"] = os.path.basename(store.trajectory_path(p.run_id))
    store.write(record)
    ctx.drop_checkpoint()
    log(f"run {p.run_id}: {status}, final return {_fmt(record['final_return'], 2)}, "
        f"normalized {_fmt(record['final_normalized'], 3)}, {record.get('env_steps')} env "
        "steps" + (f"\n{message}" if status == "failed" else ""))
    return record, False
