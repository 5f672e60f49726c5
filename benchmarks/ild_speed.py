"""ILD speed, measured side by side in one process on the same task, backend, batch,
horizon (128) and policy network (512-256 swish, tanh-Gaussian):

    python -m benchmarks.ild_speed --task hopper --batch 32 [--out results/speed/ild_speed.csv]

rows:
  forward      the batched 128-step rollout + Chamfer loss, value only
  ild          one full ILD update with ILDConfig's defaults (rollout, Chamfer, backward
               through the physics with per-step gradient normalization and truncation 10,
               clip, Adam) on `Plan()`'s physics (each brax physics substep rematerialized)
  ild_task     one ILD update as ILD trains this task: the `ild` config with the task's
               TASK_OVERRIDES (methods/ild/config.py) on the task's physics plan
               (tasks/physics/plan.py), so acrobot's through its closed form with full BPTT,
               swimmer's with small dots, inverted_pendulum's with full BPTT, the spring and
               positional tasks' with lean substeps, the spring tasks' with `hand_adjoint`
               too; where a task has neither, `ild`'s timing again. `--set FIELD=VALUE`
               (repeatable) puts ILDConfig or plan fields on top, for this row (then named
               ild_task:FIELD=VALUE;...) and ild_hand's, e.g. `--set hinge_forces=false`
               times the update without one piece of the task's hand-written adjoint
  ild_plain    the same without substep remat (`--set substep_remat=false`: brax's step as
               it is); the remat, dots and untransposed rows below start from it
  ild_no_gn    the default update without per-step gradient normalization
  ild_remat    ild_plain with jax.checkpoint on every step (rematerialization)
  ild_substep  ild_plain with jax.checkpoint on every physics substep inside a step (brax
               tasks only; the same setup as `ild`, kept for the CSVs' rows: a row whose
               setup another row has timed reports that timing)
  ild_both     both: each step checkpointed and each substep inside it (the outer scan then
               stores one state per step, not one per substep)
  dots         the physics step's small matrix products as multiply-and-sum
               (`--set small_dots=true`, `tasks.physics.transforms.with_small_dots`; brax tasks
               only): forward_dots, ild_dots, ild_substep_dots (with substep remat) and apg_dots
               (brax's APG on the same rewritten physics, so the ILD / APG ratio compares
               like with like); each of the four is also a row group of its own
  closed_form  the physics differentiated through the task's closed-form step
               (`--set closed_form_adjoint=true`,
               `tasks.physics.transforms.with_closed_form_adjoint`; acrobot only):
               ild_closed_form, and apg_closed_form (brax's APG on the same closed-form
               backward, like with like); each is also a row group of its own
  lean         every substep but a control step's last without its joint coordinates
               (`--set lean_substeps=true`, `tasks.physics.transforms.with_lean_substeps`;
               brax's spring and positional tasks with motors): forward_lean (the forward
               rollout on that physics), ild_lean (the `ild` config with it) and apg_lean
               (brax's APG on the same lean physics, like with like); each is also a row group
               of its own
  ild_hand     the ild_task config with `hand_adjoint` (`tasks.physics.spring_adjoint`: brax's
               spring substep with hand-written VJPs for six of its pieces: inverse inertia,
               joint forces and contact impulses moved to the links, integration,
               conversions to link and joint frames), and ild_xla, the same config without
               it (XLA's reverse mode of brax's substep; without its scene-specific pieces
               too: `hinge_forces`, `planar_root`, `rotary_joints`; the spring tasks train
               with `hand_adjoint`, so there ild_hand is ild_task); brax's spring tasks
               only, left out elsewhere
  untransposed the ild and ild_substep rows with `transposed_backward=false`: the policy
               vmapped per env, flax's backward transposing each kernel at every step
               (ILD's default reads the kernels transposed once per update, the same
               gradient bit for bit)
  ild_chunkK, ild_remat_chunkK, ild_substep_chunkK   K (`--chunk`) updates in one jitted call
               of the ild, ild_remat and ild_substep configs, the trainer's
               own chunk (`make_chunk`, as `--set chunk=K` trains; brax's APG scans an epoch);
               seconds and env-steps/s per update
  chamfer      Chamfer-alpha alone, value and gradient, on (B, 128, D) states
               (its time and working memory as shares of an update's: issue 4 asks that
               it not dominate either at the paper's batch, B = 360)
  step_forward, step_vjp      ONE physics step of B envs, forward / forward + backward
  policy_forward, policy_vjp  one policy sample for B envs, forward / forward + backward
               (their env-steps/s count B steps per call)
  policy_vjp_transposed       the same VJP as ILD's rollout runs it by default (batched,
               the kernels' transposes made beforehand: `transposed_backward`)
  apg          brax's own APG trainer (brax.training.agents.apg), horizon 128, same network;
               its steady-state 'training/sps' (its third epoch, `--repeats` updates in
               one jitted scan; the first epoch compiles, and on newer JAX the second
               too); left
               out where the task's reward has no gradient (inverted_pendulum's constant
               reward: APG's backward pass is then empty and it would time a forward rollout)
Each jitted function is compiled first (compile seconds reported) and then timed over
`--repeats` calls; each row also reports XLA's working memory for one call (`temp_mib`,
the compiled function's temporaries: arguments and outputs excluded) and what the operating
system charged per call: `fault_mib` (minor page faults x 4 KiB) and `sys_s` (kernel seconds).
XLA's CPU runtime mallocs a call's working memory afresh each call and glibc maps and unmaps
it, so an update that stores the backward pass's residuals pays a page fault per 4 KiB of them
on every call; K updates per call pay it once, and glibc's huge-page tunable, which this
module sets as `ildbench` does (bench.malloc; ILDBENCH_HUGEPAGES=0: without), one per 2 MiB
page. Targets (issue 4): ild >= 1.2x apg env-steps/s; ild <= 3x forward.
Goals are random states of the task's matched-state size: speed does not depend on them.
Several processes on one accelerator (results/gpu/speed_recipe.sh): `--time-lock PATH` makes
them compile side by side and time one at a time (TimingLock).
"""
from __future__ import annotations

import argparse
import dataclasses
import fcntl
import resource
import time

import jax
import jax.numpy as jnp

from bench.plugins import ConfigError
from methods.common.policy import ObsNorm, TanhGaussianPolicy
from methods.ild.config import ILDConfig
from methods.ild.losses import chamfer_alpha
from methods.ild.train import (StateNorm, initial_state, make_chunk, make_rollout_loss,
                               make_update, rollout_physics)
from tasks import make_task
from tasks.core import has_substep_loop, open_loop
from tasks.physics import Plan, apply, plan_for
from tasks.physics.plan import FIELDS as PLAN_FIELDS
from tasks.physics.plan import HAND_ADJOINT_PIECES
from tasks.physics.transforms import hand_adjoint_refusal


@dataclasses.dataclass(frozen=True)
class Setup:
    """An ILD update as the benchmarks time it: the method's config and the physics plan its
    rollouts differentiate through (`tasks.physics.plan`). A field reads from either, and
    `replace` sets fields of either by name."""
    config: ILDConfig
    plan: Plan = Plan()

    def __getattr__(self, name):
        if name in PLAN_FIELDS:
            return getattr(self.plan, name)
        return getattr(self.config, name)

    def replace(self, **fields) -> "Setup":
        plan = {k: v for k, v in fields.items() if k in PLAN_FIELDS}
        config = {k: v for k, v in fields.items() if k not in PLAN_FIELDS}
        return Setup(dataclasses.replace(self.config, **config),
                     dataclasses.replace(self.plan, **plan))

    def physics(self, task):
        """The task the training rollouts differentiate through: ILD's (`rollout_physics`)
        with this plan applied."""
        return apply(rollout_physics(task, self.config), self.plan)


def temp_bytes(compiled) -> int:
    """XLA's working memory for one call of a compiled function (its temporaries: for an
    update, the residuals the backward pass reads), arguments and outputs excluded."""
    return int(compiled.memory_analysis().temp_size_in_bytes)


@dataclasses.dataclass(frozen=True)
class Timing:
    seconds: float       # per call
    compile_s: float
    temp: int            # XLA working memory of one call, bytes
    fault_mib: float     # minor page faults per call x 4 KiB (the kernel zero-fills each)
    sys_s: float         # kernel seconds per call


class TimingLock:
    """A lock on a file (`--time-lock PATH`) held around each timed section, so that
    several benchmark processes sharing one accelerator compile side by side but are timed
    one at a time: a timed section (its warm-up call and timed calls) holds the lock
    exclusively; device work that is not timed but cannot be kept apart from compiling
    (brax's APG trainer compiles and runs its first epochs in one call) holds it shared, so
    no timed section runs beside it. Without a path it does nothing (one process per CPU
    core needs none)."""

    def __init__(self, path: str | None = None):
        self.path, self._file = path, None

    def acquire(self, shared: bool = False) -> None:
        """Take the lock (exclusive, or shared); on a shared one, take it exclusive."""
        if self.path is None:
            return
        if self._file is None:
            self._file = open(self.path, "a")
        fcntl.flock(self._file, fcntl.LOCK_SH if shared else fcntl.LOCK_EX)

    def release(self) -> None:
        if self._file is not None:
            fcntl.flock(self._file, fcntl.LOCK_UN)
            self._file.close()
            self._file = None

    def __enter__(self):
        self.acquire()
        return self

    def __exit__(self, *exc):
        self.release()


TIME_LOCK = TimingLock()
"""The timed sections' lock (`--time-lock`); a no-op unless main() is given a path."""


def _time(fn, args, repeats) -> Timing:
    t0 = time.perf_counter()
    compiled = jax.jit(fn).lower(*args).compile()
    compile_s = time.perf_counter() - t0
    with TIME_LOCK:  # compiled outside it: other processes' timing goes on meanwhile
        jax.block_until_ready(compiled(*args))
        r0 = resource.getrusage(resource.RUSAGE_SELF)
        t0 = time.perf_counter()
        for _ in range(repeats):
            jax.block_until_ready(compiled(*args))
        sec = (time.perf_counter() - t0) / repeats
        r1 = resource.getrusage(resource.RUSAGE_SELF)
    return Timing(sec, compile_s, temp_bytes(compiled),
                  (r1.ru_minflt - r0.ru_minflt) * resource.getpagesize() / 2**20 / repeats,
                  (r1.ru_stime - r0.ru_stime) / repeats)


def vjp_of_ones(f):
    """Forward + backward of `f` with a cotangent of ones on every output (the step and
    policy VJP rows)."""
    def vjp(*args):
        out, pull = jax.vjp(f, *args)
        return pull(jax.tree.map(jnp.ones_like, out))
    return vjp


APG_WARMUP_EPOCHS = 2
"""APG epochs that compile and are timed by nobody: brax compiles its epoch on the first call,
and on JAX newer than the pin (0.10.2 checked with JAX_LOG_COMPILES) its pmapped epoch is
compiled again on the second call, which then ran at 23 env-steps/s against 4,700 on the
third. On the pinned JAX the second is already steady: dropping it costs one epoch and biases
nothing."""


def apg_epochs(task, batch, hidden, updates, rounds, after_epoch=lambda it: None):
    """brax's own APG trainer (horizon 128, our network): APG_WARMUP_EPOCHS + `rounds` epochs
    of `updates` updates each (brax times an epoch as one jitted scan). Returns the
    'training/sps' of the `rounds` steady epochs, the warm-up ones left out. `after_epoch(it)`
    runs after every epoch, warm-up ones included, outside brax's timing
    (benchmarks.ild_paired times ILD's updates there; _apg_sps takes the timing lock)."""
    if rounds < 1:
        raise ValueError(f"apg_epochs: rounds={rounds}; at least 1 steady epoch is timed")
    from brax.training.agents.apg import networks as apg_networks
    from brax.training.agents.apg import train as apg
    from flax import linen

    from tasks.jax_compat import apply as jax_compat
    jax_compat()  # brax's trainer on a newer JAX, whatever the task's env (acrobot is ours)

    epochs = APG_WARMUP_EPOCHS + rounds
    sps = []

    def factory(obs_size, action_size, preprocess_observations_fn):
        return apg_networks.make_apg_networks(obs_size, action_size,
                                              preprocess_observations_fn, hidden, linen.swish,
                                              layer_norm=False)

    def progress(it, m):
        if "training/sps" in m:
            sps.append(float(m["training/sps"]))
            after_epoch(it)

    apg.train(environment=task.env, episode_length=task.episode_length,
              policy_updates=epochs * updates, horizon_length=task.episode_length,
              num_envs=batch, num_evals=epochs + 1,
              num_eval_envs=batch, network_factory=factory, progress_fn=progress)
    if len(sps) != epochs:
        raise RuntimeError(f"brax's APG reported 'training/sps' for {len(sps)} epochs, "
                           f"expected {epochs}: its progress_fn contract changed")
    return sps[APG_WARMUP_EPOCHS:]


def _apg_sps(task, batch, hidden, repeats):
    # One steady epoch of `repeats` updates, timed as ILD's rows are, after the
    # APG_WARMUP_EPOCHS that compile. The timing lock is held shared over the warm-up
    # epochs (they compile and run in one call: no other process's timed section runs
    # beside them) and exclusively over the steady one (brax times it in apg.train).
    ends, t0 = [], time.perf_counter()

    def after_epoch(it):
        ends.append(it)
        print(f"apg: epoch {len(ends)} of {APG_WARMUP_EPOCHS + 1} done "
              f"{time.perf_counter() - t0:.1f} s after the start", flush=True)
        if len(ends) == APG_WARMUP_EPOCHS:
            TIME_LOCK.acquire()  # shared -> exclusive
        elif len(ends) == APG_WARMUP_EPOCHS + 1:
            TIME_LOCK.release()
    TIME_LOCK.acquire(shared=True)
    try:
        return apg_epochs(task, batch, hidden, repeats, 1, after_epoch)[0]
    finally:
        TIME_LOCK.release()


def reward_gradient_norm(task, batch: int = 4, steps: int = 8) -> float:
    """Norm of d(sum of rewards over `steps` steps)/d(actions) from reset states. Zero means
    APG's loss (minus the mean reward) has no gradient on this task (inverted_pendulum: a
    constant reward of 1 per step), so XLA drops its backward pass and its 'training/sps'
    times a forward rollout: no comparison for ILD's update."""
    def total(actions):
        s0 = jax.vmap(task.env.reset)(jax.random.split(jax.random.PRNGKey(0), batch))
        return jnp.sum(open_loop(jax.vmap(task.env.step), s0, actions, lambda s: s.reward)[1])

    # one jitted program (run op by op, the reset and the gradient take several times as long)
    g = jax.jit(jax.grad(total))(jnp.full((steps, batch, task.action_size), 0.1))
    return float(jnp.linalg.norm(g))


ROWS = ("forward", "ild", "ild_task", "ild_plain", "ild_no_gn", "ild_remat", "ild_substep",
        "ild_both", "ild_chunk", "ild_remat_chunk", "ild_substep_chunk", "dots", "closed_form",
        "lean", "ild_hand", "untransposed", "step", "policy", "chamfer", "apg")
"""Row groups `--rows` picks from ('ild_chunk' names the ild_chunkK row; 'step' and
'policy' are the forward + VJP pairs; 'dots' is the four DOTS_ROWS, 'closed_form' the two
CLOSED_FORM_ROWS, 'lean' the three LEAN_ROWS)."""
DOTS_ROWS = ("forward_dots", "ild_dots", "ild_substep_dots", "apg_dots")
"""The small-dots rows, each selectable alone (a GPU call that times ILD's rows and APG's in
separate processes asks for ild_substep_dots in one and apg_dots in the other)."""
CLOSED_FORM_ROWS = ("ild_closed_form", "apg_closed_form")
"""The closed-form-adjoint rows (tasks with a closed-form step: acrobot), each selectable
alone."""
LEAN_ROWS = ("forward_lean", "ild_lean", "apg_lean")
"""The lean-substep rows (brax's spring and positional tasks with motors), each selectable
alone."""
GROUPS = {"dots": DOTS_ROWS, "closed_form": CLOSED_FORM_ROWS, "lean": LEAN_ROWS}
SUBSTEP_ROWS = ("ild_plain", "ild_substep", "ild_both", "ild_substep_chunk")
"""Row groups that differ from `ild` only where a task has brax's substep loop: left out
elsewhere (pointmass), where they would time the same update again."""


def check_rows(only) -> None:
    """ValueError naming any of `only` that is not a row group of ROWS."""
    unknown = set(only) - set(ROWS) - set(DOTS_ROWS) - set(CLOSED_FORM_ROWS) - set(LEAN_ROWS)
    if unknown:
        raise ValueError(f"unknown benchmark rows {sorted(unknown)}; choose from "
                         f"{ROWS + DOTS_ROWS + CLOSED_FORM_ROWS + LEAN_ROWS}")


def expand_rows(only) -> tuple[str, ...]:
    """`only` with the groups 'dots', 'closed_form' and 'lean' replaced by their rows
    (DOTS_ROWS, CLOSED_FORM_ROWS, LEAN_ROWS), order kept, no repeats."""
    out = []
    for r in only:
        for x in GROUPS.get(r, (r,)):
            if x not in out:
                out.append(x)
    return tuple(out)


def _rewritten_physics(task, config: Setup, group: str, only: tuple[str, ...]):
    """(`config.physics(task)`, `only`) where `only` asks for a row of `group`
    (GROUPS); (None, `only` without the group's rows), saying so, where the task refuses the
    rewrite (small_dots without a brax physics step, closed_form_adjoint without a closed
    form, lean_substeps off brax's spring and positional backends) or no row of the group is
    asked for."""
    rows = GROUPS[group]
    if set(rows) & set(only):
        try:
            return config.physics(task), only
        except ValueError as e:
            print(f"{group}: left out on {task.name}: {e}", flush=True)
    return None, tuple(r for r in only if r not in rows)


def task_config(task_name: str, batch: int, overrides=None) -> Setup:
    """ILD's config and physics plan as it trains `task_name` (the class defaults with the
    task's TASK_OVERRIDES and its plan on this platform; '' for none: `Plan()`), at `batch`
    envs, `overrides` on top ({field: text}, ILDConfig's or the plan's fields; turning
    `hand_adjoint` off turns its pieces off, `planar_adjoint` off `planar_links` and
    `planar_normal_gravity`): the `ild_task` row's and `benchmarks.ild_paired`'s variants.
    ConfigError for a field neither has."""
    from bench.plugins import build_config, current_platform, get_method
    overrides = dict(overrides or {})
    phys = {k: str(overrides.pop(k)).lower() in ("1", "true", "yes", "on")
            for k in list(overrides) if k in PLAN_FIELDS}
    for needed, pieces in (("hand_adjoint", HAND_ADJOINT_PIECES),
                           ("planar_adjoint", ("planar_links", "planar_normal_gravity"))):
        if phys.get(needed) is False:
            phys = {**{f: False for f in pieces}, **phys}
    config = build_config(get_method("ild"), task_name, None,
                          {"num_envs": batch, **overrides})
    plan = plan_for(task_name, current_platform()) if task_name else Plan()
    try:
        return Setup(config, dataclasses.replace(plan, **phys))
    except ValueError as e:
        raise ConfigError(f"physics plan: {e}") from e


def speed_setup(task, config: ILDConfig):
    """What a speed measurement of ILD's update needs, seeded: (policy, goals, norm, params,
    keys). Goals are random states of the task's matched-state size with an identity
    normalizer (speed does not depend on them); keys[2] is the reset key and keys[3] the
    training-state key."""
    policy = TanhGaussianPolicy(task.obs_size, task.action_size, config.hidden)
    k = jax.random.split(jax.random.PRNGKey(0), 4)
    goals = jax.random.normal(k[0], (1, task.episode_length, task.state_size))
    norm = StateNorm(jnp.zeros(task.state_size), jnp.ones(task.state_size))
    params = policy.init(k[1], ObsNorm(jnp.zeros(task.obs_size), jnp.ones(task.obs_size)))
    return policy, goals, norm, params, k


def run(task_name: str, batch: int, repeats: int, with_apg: bool = True,
        chunk: int = 4, only: tuple[str, ...] = ROWS, overrides=None) -> list[dict]:
    """The rows of `only` (ROWS' groups); `overrides` ({field: text}, `--set`) on top of the
    task's config: the ild_task row (named ild_task:FIELD=VALUE;...) and ild_hand's."""
    check_rows(only)
    only = expand_rows(only)
    task = make_task(task_name)
    T = task.episode_length
    base = Setup(ILDConfig(num_envs=batch))
    policy, goals, norm, params, k = speed_setup(task, base)
    init_keys = jax.random.split(k[2], batch)
    steps = batch * T
    rows = []

    def row(name, t: Timing | None, n=steps, per_call=1, sec=None, compile_s=None):
        """One row; `per_call` updates per timed call: seconds and env-steps/s per update,
        memory, faults and kernel time per call."""
        sec = t.seconds / per_call if t is not None else sec
        rows.append({"task": task_name, "backend": task.spec.backend, "batch": batch,
                     "what": name, "seconds": float(f"{sec:.4g}"),
                     "env_steps_per_s": round(n / sec, 1),
                     "compile_s": round(t.compile_s if t is not None else compile_s, 1),
                     "updates_per_call": per_call,
                     "temp_mib": round(t.temp / 2**20, 3) if t is not None else None,
                     "fault_mib": round(t.fault_mib, 1) if t is not None else None,
                     "sys_s": float(f"{t.sys_s:.3g}") if t is not None else None})
        print(rows[-1], flush=True)

    loss_fn = make_rollout_loss(task, policy, goals, norm, base.config)
    if "forward" in only:
        row("forward", _time(lambda p: loss_fn(p, k[3], init_keys)[0], (params,), repeats))
    plain = base.replace(substep_remat=False)  # ILD's default before version 5
    remat = plain.replace(remat=True)
    substep = plain.replace(substep_remat=True)
    dots = plain.replace(small_dots=True)
    closed = base.replace(closed_form_adjoint=True)
    lean = base.replace(lean_substeps=True)
    lean_plain = plain.replace(lean_substeps=True)  # forward_lean's, apg_lean's
    trained = task_config(task_name, batch, overrides)  # the ild_task row's: as it trains
    spring = hand_adjoint_refusal(task) is None
    hand = trained.replace(hand_adjoint=True) if spring else None  # ild_hand's
    # ild_xla's: --set hand_adjoint=false, which turns its pieces off with it
    xla = (task_config(task_name, batch, {**(overrides or {}), "hand_adjoint": "false",
                                          **{f: "false" for f in HAND_ADJOINT_PIECES}})
           if spring else None)
    task_row = "ild_task" + (":" + ";".join(f"{f}={v}" for f, v in overrides.items())
                             if overrides else "")
    dots_task, only = _rewritten_physics(task, dots, "dots", only)
    closed_task, only = _rewritten_physics(task, closed, "closed_form", only)
    lean_task, only = _rewritten_physics(task, lean_plain, "lean", only)
    for name, physics, cfg in (("forward_dots", dots_task, dots),
                               ("forward_lean", lean_task, lean_plain)):
        if name in only:
            fwd = make_rollout_loss(physics, policy, goals, norm, cfg.config)
            row(name, _time(lambda p, f=fwd: f(p, k[3], init_keys)[0], (params,), repeats))
    timed = {}  # (config, updates per call) -> Timing: a row naming a config already timed
    # (ild_substep is ild's config since version 5) reports that timing, not a second one
    for group, name, cfg, n in (
            ("ild", "ild", base, 1), ("ild_task", task_row, trained, 1),
            ("ild_plain", "ild_plain", plain, 1),
            ("ild_no_gn", "ild_no_gn", base.replace(grad_normalization=False), 1),
            ("ild_remat", "ild_remat", remat, 1), ("ild_substep", "ild_substep", substep, 1),
            ("ild_both", "ild_both", substep.replace(remat=True), 1),
            ("ild_chunk", f"ild_chunk{chunk}", base, chunk),
            ("ild_remat_chunk", f"ild_remat_chunk{chunk}", remat, chunk),
            ("ild_substep_chunk", f"ild_substep_chunk{chunk}", substep, chunk),
            ("ild_dots", "ild_dots", dots, 1),
            ("ild_substep_dots", "ild_substep_dots",
             substep.replace(small_dots=True), 1),
            ("ild_closed_form", "ild_closed_form", closed, 1),
            ("ild_lean", "ild_lean", lean, 1),
            ("ild_hand", "ild_xla", xla, 1), ("ild_hand", "ild_hand", hand, 1),
            ("untransposed", "ild_untransposed",
             plain.replace(transposed_backward=False), 1),
            ("untransposed", "ild_substep_untransposed",
             substep.replace(transposed_backward=False), 1)):
        if (n > 1 and chunk == 1) or group not in only:
            continue
        if group in SUBSTEP_ROWS and not has_substep_loop(task):
            print(f"{name}: left out on {task_name}: no brax substep loop to rewrite",
                  flush=True)
            continue
        if cfg is None:  # ild_hand's rows off brax's spring backend
            print(f"{name}: left out on {task_name}: {hand_adjoint_refusal(task)}", flush=True)
            continue
        if (cfg, n) in timed:
            row(name, timed[cfg, n], per_call=n)
            continue
        update, opt, _ = make_update(cfg.physics(task), policy, goals, norm, cfg.config, k[2])
        state = initial_state(params, opt, k[3], cfg.config)
        if n == 1:
            t = _time(lambda s: update(s, None)[0], (state,), repeats)
        else:  # the trainer's chunk: n updates in one jitted scan, all n active
            t = _time(lambda s, a, c=make_chunk(update, n): c(s, a)[0],
                      (state, jnp.int32(n)), -(-repeats // n))  # at least `repeats` updates
        timed[cfg, n] = t
        row(name, t, per_call=n)
    # Where an update's time goes, per control step of B envs: the physics step and the
    # policy sample, each forward and as a VJP (forward + backward with a cotangent), so the
    # backend's own reverse-mode cost shows beside ILD's.
    s0 = jax.vmap(task.env.reset)(init_keys)
    a0 = jnp.zeros((batch, task.action_size))
    step = jax.vmap(task.env.step)
    if "step" in only:
        row("step_forward", _time(step, (s0, a0), 5 * repeats), batch)
        row("step_vjp", _time(vjp_of_ones(step), (s0, a0), 5 * repeats), batch)
    if "policy" in only:
        sample = jax.vmap(policy.sample, in_axes=(None, 0, 0))
        pkeys = jax.random.split(k[3], batch)
        row("policy_forward", _time(sample, (params, s0.obs, pkeys), 5 * repeats), batch)
        row("policy_vjp", _time(vjp_of_ones(lambda p, o: sample(p, o, pkeys)),
                                (params, s0.obs), 5 * repeats), batch)
        kernels_t = policy.kernels_t(params)  # made once per update, outside the loop
        row("policy_vjp_transposed", _time(vjp_of_ones(
            lambda p, o: policy.sample_batch(p, o, pkeys, kernels_t)), (params, s0.obs),
            5 * repeats), batch)
    if "chamfer" in only:
        x = jax.random.normal(k[3], (batch, T, task.state_size))
        cham = jax.value_and_grad(lambda x: jnp.mean(jax.vmap(
            lambda xb: chamfer_alpha(xb, goals[0]).loss)(x)))
        row("chamfer", _time(cham, (x,), repeats))
    apg_rows = [(name, physics) for name, physics in
                (("apg", task), ("apg_dots", dots_task), ("apg_closed_form", closed_task),
                 ("apg_lean", lean_task))
                if with_apg and name in only]  # apg_dots / apg_closed_form / apg_lean: the
    # same trainer on the same rewritten physics as ild_*_dots / ild_closed_form / ild_lean
    if apg_rows and reward_gradient_norm(task) == 0.0:
        print(f"apg: left out on {task_name}: the reward has no gradient (APG's backward "
              "pass is empty and its env-steps/s would time a forward rollout)", flush=True)
        apg_rows = []
    for name, physics in apg_rows:
        t0 = time.perf_counter()
        sps = _apg_sps(physics, batch, base.hidden, repeats)
        row(name, None, per_call=repeats, sec=steps / sps, compile_s=time.perf_counter() - t0)
    by = {r["what"]: r for r in rows}
    ratios = {}

    def ratio(name, num, den, field="seconds"):
        if num in by and den in by:
            ratios[name] = by[num][field] / by[den][field]
    ratio("update_over_forward", "ild", "forward")
    ratio("task_update_over_forward", "ild_task", "forward")
    ratio("substep_update_over_forward", "ild_substep", "forward")
    ratio("chamfer_share_of_update", "chamfer", "ild")
    ratio("chamfer_share_of_update_memory", "chamfer", "ild", "temp_mib")
    ratio("step_vjp_over_forward", "step_vjp", "step_forward")
    ratio("policy_vjp_over_forward", "policy_vjp", "policy_forward")
    ratio("substep_speedup", "ild_plain", "ild_substep")
    ratio("chunk_speedup", "ild", f"ild_chunk{chunk}")
    ratio("remat_chunk_speedup", "ild_remat", f"ild_remat_chunk{chunk}")
    ratio("substep_chunk_speedup", "ild_substep", f"ild_substep_chunk{chunk}")
    ratio("transposed_speedup", "ild_untransposed",
          "ild_plain" if "ild_plain" in by else "ild")  # pointmass: no plain row, the same
    ratio("transposed_substep_speedup", "ild_substep_untransposed", "ild_substep")
    ratio("dots_forward_speedup", "forward", "forward_dots")
    ratio("dots_substep_speedup", "ild_substep", "ild_substep_dots")
    ratio("dots_substep_update_over_forward", "ild_substep_dots", "forward_dots")
    ratio("closed_form_update_over_forward", "ild_closed_form", "forward")
    ratio("closed_form_speedup", "ild", "ild_closed_form")
    ratio("lean_forward_speedup", "forward", "forward_lean")
    ratio("lean_speedup", "ild", "ild_lean")
    ratio("lean_update_over_forward", "ild_lean", "forward")
    ratio("lean_update_over_forward_lean", "ild_lean", "forward_lean")
    ratio("hand_speedup", "ild_xla", "ild_hand")
    ratio("hand_update_over_forward", "ild_hand", "forward")
    ratio("hand_update_over_forward_lean", "ild_hand", "forward_lean")
    def over(name, apg):  # env-steps/s of an ILD row over an APG row's, as {name}_over_{apg}
        if name in by and apg in by:
            ratios[f"{name}_over_{apg}"] = (by[name]["env_steps_per_s"]
                                            / by[apg]["env_steps_per_s"])
    for name in ("ild", "ild_task", "ild_plain", "ild_remat", "ild_substep", "ild_both",
                 f"ild_chunk{chunk}", f"ild_remat_chunk{chunk}", f"ild_substep_chunk{chunk}",
                 "ild_untransposed", "ild_substep_untransposed", "ild_closed_form", "ild_lean",
                 "ild_xla", "ild_hand"):
        over(name, "apg")
    # like with like: ILD and APG on the same rewritten physics
    for name, apg in (("ild_dots", "apg_dots"), ("ild_substep_dots", "apg_dots"),
                      ("ild_lean", "apg_lean"), ("ild_closed_form", "apg_closed_form")):
        over(name, apg)
    if "ild_task" in by:  # like with like where the task trains on rewritten physics
        if trained.small_dots:  # its forward rollout is forward_dots (the closed form's: brax's)
            ratio("task_update_over_forward_dots", "ild_task", "forward_dots")
        if trained.lean_substeps:
            ratio("task_update_over_forward_lean", "ild_task", "forward_lean")
        over("ild_task", "apg_closed_form" if trained.closed_form_adjoint else
             "apg_dots" if trained.small_dots else
             "apg_lean" if trained.lean_substeps else None)
    print({k: round(v, 3) for k, v in ratios.items()}, flush=True)
    for r in rows:
        r.update({k: round(v, 3) for k, v in ratios.items()})
    return rows


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", default="hopper")
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--chunk", type=int, default=4,
                   help="updates per call of the ild_chunkK rows (1: leave them out)")
    p.add_argument("--no-apg", action="store_true")
    p.add_argument("--rows", default=",".join(ROWS),
                   help=f"comma-separated row groups to run (default all: {','.join(ROWS)}; "
                        f"'dots' is {','.join(DOTS_ROWS)}, 'closed_form' is "
                        f"{','.join(CLOSED_FORM_ROWS)}, 'lean' is {','.join(LEAN_ROWS)}, each "
                        "also alone)")
    p.add_argument("--out", default=None, help="append rows to this CSV")
    p.add_argument("--set", action="append", default=[], metavar="FIELD=VALUE",
                   help="an ILDConfig field on top of the task's config, for the ild_task "
                        "row (then named ild_task:FIELD=VALUE) and ild_hand's; repeatable")
    p.add_argument("--time-lock", default=None, metavar="PATH",
                   help="hold an exclusive lock on PATH around each timed section: several "
                        "processes on one accelerator then compile side by side and are "
                        "timed one at a time")
    a = p.parse_args(argv)
    TIME_LOCK.path = a.time_lock
    if a.chunk < 1 or a.repeats < 1 or a.batch < 1:
        p.error(f"--chunk, --repeats and --batch must be >= 1, got {a.chunk}, {a.repeats}, "
                f"{a.batch}")
    only = tuple(r for r in a.rows.split(",") if r)
    try:
        check_rows(only)
    except ValueError as e:
        p.error(f"--rows: {e}")
    from bench.cli import _overrides  # ildbench's own --set parser
    try:
        overrides = _overrides(a.set)
        task_config(a.task, a.batch, overrides)
    except (ConfigError, ValueError) as e:
        p.error(f"--set: {e}")
    rows = run(a.task, a.batch, a.repeats, not a.no_apg, a.chunk, only, overrides)
    if a.out:
        from bench.report import append_csv
        from bench.machine import speed_settings
        settings = speed_settings()  # XLA's code generator, glibc's huge pages: speed
        append_csv([{**r, **settings} for r in rows], a.out)


if __name__ == "__main__":
    from bench.malloc import reexec_with_hugepages
    reexec_with_hugepages("benchmarks.ild_speed")  # as `ildbench` runs (bench.malloc)
    main()
