"""The harness's guarantees, each held by a test that fails when it breaks.

Every test names, in its docstring, the fault it was written to catch: the fault was planted
in a copy of the code and the test failed on it.
"""
import dataclasses
import os
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bench.access import DemoView, TaskView
from bench.api import InformationError, MethodSpec, Policy, TrainResult, Uses
from bench.budget import Budget
from bench.evaluator import EvalConfig
from bench.plugins import get_method
from bench.runner import RunRequest, execute, prepare
from tasks import make_task

FAST_EVAL = EvalConfig(num_episodes=4)
RESULTS = pathlib.Path(__file__).resolve().parents[1] / "results"


# ----------------------------------------------------------------------------- truncation


@pytest.mark.parametrize("task_name", ["pointmass", "inverted_pendulum"])
def test_truncation_zeroes_the_cotangent_of_every_state_leaf_at_a_window_boundary(task_name):
    """ILD's physics step at the last step of a truncation window hands back an exactly zero
    cotangent to the state and the action it came from, for every floating leaf of the state
    (the brax pipeline state included), and a non-zero one inside a window.
    Planted fault: only the observation cut at window boundaries, the physics state not."""
    from methods.ild.config import ILDConfig
    from methods.ild.train import make_physics_step
    from tasks.core import task_with_backend
    # A brax task runs on the spring pipeline: the cut is the same on every backend, and
    # spring's step is the cheapest of them to differentiate and compile.
    task = (make_task(task_name) if task_name == "pointmass"
            else task_with_backend(task_name, "spring"))
    cfg = ILDConfig(truncation=4, grad_normalization=False)
    step = make_physics_step(task, cfg)
    s = jax.vmap(task.env.reset)(jax.random.split(jax.random.PRNGKey(0), 2))
    a = 0.3 * jnp.ones((2, task.action_size))

    @jax.jit  # one compilation serves both calls: the step index is traced
    def cotangents(t):
        out, vjp = jax.vjp(lambda s_, a_: step(s_, a_, t)[0], s, a)
        ones = jax.tree.map(lambda x: jnp.ones_like(x) if jnp.issubdtype(x.dtype, jnp.floating)
                            else np.zeros(x.shape, jax.dtypes.float0), out)
        ds, da = vjp(ones)
        return [x for x in jax.tree_util.tree_leaves((ds, da)) if x.dtype != jax.dtypes.float0]

    boundary = cotangents(jnp.int32(3))   # (3 + 1) % 4 == 0: the window ends here
    inside = cotangents(jnp.int32(1))
    assert boundary and all(np.all(np.asarray(x) == 0) for x in boundary)
    assert any(np.any(np.asarray(x) != 0) for x in inside)


# ----------------------------------------------------------------------------- gating

DECLARED = {
    "bc": Uses(demo_states=True, demo_actions=True),
    "ild": Uses(demo_states=True, demo_actions=True, sim_gradients=True),
    "dac": Uses(demo_states=True, demo_actions=True),
    "pwil": Uses(demo_states=True, demo_actions=True),
    "shac": Uses(true_reward=True, sim_gradients=True),
    "cem_mpc": Uses(true_reward=True, sim_at_test=True),
    "cem_mpc_track": Uses(demo_states=True, sim_at_test=True),
}


@pytest.mark.parametrize("name", sorted(DECLARED))
def test_each_in_repo_methods_declaration_is_pinned(name):
    """What each method reads is part of the comparison: a change to a declaration must be
    a deliberate edit here too. Planted fault: DAC declaring true_reward."""
    assert get_method(name).uses == DECLARED[name]


@dataclasses.dataclass(frozen=True)
class _ProbeConfig:
    pass


def test_the_runner_hands_a_method_the_gated_views_of_its_declaration(temp_method):
    """execute() gives train() the TaskView and DemoView of the method's Uses: the reward
    reads NaN, undeclared demo fields raise, and no gradient flows through the physics.
    Planted fault: execute() passing the plain task and demo."""
    seen = {}

    def train(task, demo, config, ctx, seed):
        seen["task"], seen["demo"] = task, demo
        env = task.env
        s0 = env.reset(jax.random.PRNGKey(0))
        seen["reward"] = float(env.step(s0, jnp.zeros(env.action_size)).reward)
        seen["grad"] = float(jnp.abs(jax.grad(
            lambda a: env.step(s0, a).obs.sum())(0.5 * jnp.ones(env.action_size))).sum())
        seen["states"] = np.asarray(demo.states).shape
        try:
            demo.actions
        except InformationError as e:
            seen["actions"] = str(e)
        return TrainResult(Policy(lambda p, o, k, d: jnp.zeros(o.shape[:-1] + (1,)), 0.0),
                           env_steps=1)

    temp_method(MethodSpec(name="probe", train=train, config_cls=_ProbeConfig,
                           uses=Uses(demo_states=True)))
    from bench.store import Store
    import tempfile
    with tempfile.TemporaryDirectory() as d:
        rec, _ = execute(prepare(RunRequest(method="probe", task="pointmass", seed=0,
                                            budget=Budget(env_steps=1, evals=1),
                                            eval=FAST_EVAL)), Store(d), log=lambda s: None)
    assert rec["status"] == "ok", rec["message"]
    assert isinstance(seen["task"], TaskView) and isinstance(seen["demo"], DemoView)
    assert np.isnan(seen["reward"]) and seen["grad"] == 0.0
    assert seen["states"] == (1, 129, 2)  # one demo, as declared
    assert "demo.actions" in seen["actions"] and "demo_actions" in seen["actions"]


# ----------------------------------------------------------------------------- budgets


def _seconds_run(store, method, seconds, charge_compile=True, **over):
    req = RunRequest(method=method, task="pointmass", seed=0, preset="cpu",
                     budget=Budget(seconds=seconds, evals=1, charge_compile=charge_compile),
                     overrides=over, eval=FAST_EVAL)
    rec, _ = execute(prepare(req), store, log=lambda s: None)
    assert rec["status"] == "ok", rec["message"]
    return rec


def test_a_seconds_budget_stops_bc_within_one_chunk_of_updates(store):
    """BC asked for far more updates than 3 s allow stops once the clock reads 3 s: its
    training time is at least the budget and past it by at most one jitted chunk of updates.
    Planted fault: Clock.elapsed() returning 0 (BC then runs all its updates, and the
    record's training time reads 0). Compile time is not charged, so a slow compile on a
    loaded machine cannot spend the budget before the first chunk."""
    rec = _seconds_run(store, "bc", 3.0, charge_compile=False, updates=300_000, chunk=50)
    done = rec["train_metrics"]["train/updates"]
    assert 0 < done < 300_000
    per_chunk = rec["train_s"] / done * 50
    assert 3.0 <= rec["train_s"] <= 3.0 + per_chunk + 0.25, (rec["train_s"], per_chunk)


def test_a_seconds_budget_stops_ild_within_one_update(store):
    """ILD stops once the clock reads the budget: at least the budget, past it by at most
    one update (the budget check sits between calls of a chunk of updates, each sized from
    the time per update measured so far). Compile time is not charged here, so the first
    update's compiling cannot overrun the budget by itself; the update count is capped so
    that a broken clock ends the run instead of hanging it. Planted fault: Clock.elapsed()
    returning 0."""
    rec = _seconds_run(store, "ild", 3.0, charge_compile=False, updates=2000, num_envs=8,
                       hidden="(32, 32)", bc_updates=0, chunk=50)
    done = rec["train_metrics"]["train/updates"]
    assert 1 < done < 2000
    per_update = rec["train_s"] / done
    # the slack covers a last update slower than the mean on a loaded machine; a clock that
    # never advances runs all 2000 updates, far past it
    assert 3.0 <= rec["train_s"] <= 3.0 + per_update + 0.75, (rec["train_s"], per_update)


@dataclasses.dataclass(frozen=True)
class _CompileConfig:
    width: int = 400


def _compiling_train(task, demo, config, ctx, seed):
    """Compiles one fresh, long program, then idles in 10 ms steps until the budget is
    spent (or 15 s of its own wall time have passed: a broken clock ends the run)."""
    t0 = time.perf_counter()

    def long(x):
        for i in range(config.width):
            x = jnp.sin(x * (1.0 + i * 1e-3)) + x
        return x
    jax.jit(long)(jnp.ones(3)).block_until_ready()
    steps = 0
    while not ctx.should_stop(steps) and time.perf_counter() - t0 < 15:
        time.sleep(0.01)
        steps += 1
    return TrainResult(Policy(lambda p, o, k, d: jnp.zeros(o.shape[:-1] + (1,)), 0.0),
                       env_steps=steps, metrics={"own_wall_s": time.perf_counter() - t0})


@pytest.mark.parametrize("charge", [True, False])
def test_compile_time_is_charged_to_the_budget_only_when_configured(temp_method, store, charge):
    """With charge_compile the method's own wall time is the budget (compiling included);
    without, it is the budget plus the compile time the record reports.
    Planted faults: Clock.elapsed() ignoring charge_compile; the compile meter not counting."""
    temp_method(MethodSpec(name="compiler", train=_compiling_train,
                           config_cls=_CompileConfig, uses=Uses()))
    req = RunRequest(method="compiler", task="pointmass", seed=int(charge),
                     budget=Budget(seconds=1.5, evals=1, charge_compile=charge),
                     eval=FAST_EVAL)
    rec, _ = execute(prepare(req), store, log=lambda s: None)
    compile_s = rec["compile_s"]["train"]
    own = rec["train_metrics"]["own_wall_s"]
    assert compile_s > 0.2, compile_s
    assert own < 15
    expect = 1.5 if charge else 1.5 + compile_s
    assert abs(own - expect) < 0.25, (own, expect, compile_s)
    assert 1.5 <= rec["train_s"] < 1.5 + 0.25


# ----------------------------------------------------------------------------- run ids


def test_a_fresh_compile_meter_explains_retraces_only_while_a_clock_runs():
    """Faults it catches: a compile meter that starts with a stale state (an active clock
    that is not one, a saved flag) or filters the wrong logger. Then a compilation before any
    clock crashes the listener, a clock never asks JAX to explain its cache misses (so a
    training function traced again after a report goes unseen), or closing it does not give
    the user's flag back. The process keeps one meter (its JAX listeners register once), so
    the tests that run methods meet only the first; this builds a fresh one."""
    import logging

    from bench import budget as B

    saved_meter, flag = B._METER, jax.config.jax_explain_cache_misses
    meter = B._CompileMeter()
    B._METER = meter
    try:
        for name in meter._LOGGERS:
            assert meter._on_log in logging.getLogger(name).filters, name
        jax.jit(lambda x: x * 3.0)(jnp.ones(2)).block_until_ready()  # no clock: ignored
        clock = B.Clock()
        assert meter.active is clock and jax.config.jax_explain_cache_misses is True
        f = jax.jit(lambda x: x + 1.0)
        f(jnp.ones(3)).block_until_ready()
        assert clock.retraced == {}                  # a first trace is not a retrace
        clock.interval = 1                           # a report was made
        f(jnp.ones(4)).block_until_ready()           # traced again (a new shape)
        assert [v["count"] for v in clock.retraced.values()] == [1]
        clock.close()
        assert meter.active is None and jax.config.jax_explain_cache_misses == flag
    finally:
        B._METER = saved_meter
        jax.config.update("jax_explain_cache_misses", flag)
        for name in meter._LOGGERS:
            logging.getLogger(name).removeFilter(meter._on_log)


def test_a_retrace_names_its_function_and_the_last_two_parts_of_its_file():
    """Hand-written explanations in JAX's two forms (a function never seen, one seen with
    other arguments), with and without a place. Planted faults: the no-match case inverted,
    the name read from the place's group."""
    from bench.budget import _traced_function
    assert _traced_function("TRACING CACHE MISS at x.py:1 because:\n  never seen function:\n"
                            "    update id=140 defined at /a/b/methods/ild/train.py:42\n"
                            ) == "update (ild/train.py:42)"
    assert _traced_function("TRACING CACHE MISS because:\n  for epoch defined at "
                            "/r/methods/shac/loop.py:7\n    tracing context doesn't match"
                            ) == "epoch (shac/loop.py:7)"
    assert _traced_function("TRACING CACHE MISS because:\n  for step\n") == "step"
    assert _traced_function("TRACING CACHE MISS for reasons of its own") == "?"


def test_a_retrace_explanation_drops_its_call_site_line_and_is_bounded():
    """Hand-computed: the first line (call site and cost) goes, blank lines go, at most 8
    lines joined by ' / ', at most 600 characters."""
    from bench.budget import _why
    assert _why("TRACING CACHE MISS at f.py:3 costing 1 ms\n  because:\n\n   x changed  \n"
                ) == "because: / x changed"
    assert _why("head\n" + "\n".join(f"l{i}" for i in range(20))) == \
        " / ".join(f"l{i}" for i in range(8))
    assert _why("head\n" + "x" * 1000) == "x" * 600


@pytest.mark.parametrize("method,task,budget,preset,transfer,expect", [
    # The committed 10-minute ILD cell on hopper, seed 0 (results/tenmin/runs).
    ("ild", "hopper", Budget(seconds=600), "cpu", True, "e66ac33f50886650"),
    ("ild", "hopper", Budget(seconds=600.0), "cpu", True, "e66ac33f50886650"),
    ("bc", "pointmass", Budget(env_steps=1000), None, False, "33f16f0c6b98bbfd"),
    ("bc", "pointmass", Budget(env_steps=1000.0), None, False, "33f16f0c6b98bbfd"),
])
def test_golden_run_ids(method, task, budget, preset, transfer, expect):
    """A run id is the cell's name in every store: these values must not move. A new field
    of Budget, EvalConfig or RunRequest that enters the hash, a changed config default, or
    a budget of 600 naming another cell than 600.0 re-keys every committed record.
    Planted faults: a new Budget field with a default; Budget keeping 600 as an int."""
    req = RunRequest(method=method, task=task, seed=0, budget=budget, preset=preset,
                     eval=EvalConfig(transfer=transfer))
    assert prepare(req).run_id == expect
    if method == "ild":
        assert (RESULTS / "tenmin" / "runs" / f"{expect}.json").exists()


# ----------------------------------------------------------------------------- store


def test_a_truncated_record_is_named_set_aside_and_its_cell_re_run(temp_method, store):
    """A record file cut short (a full disk, an interrupted copy) is an error naming the file
    when read directly; a sweep moves it to corrupt/ (nothing deleted) and runs the cell
    again. Planted fault: Store.get letting json's bare JSONDecodeError through."""
    from bench.store import CorruptRecord
    from bench.sweep import run_local
    temp_method(MethodSpec(name="probe2", train=_constant_train, config_cls=_ProbeConfig,
                           uses=Uses()))
    p = prepare(RunRequest(method="probe2", task="pointmass", seed=0,
                           budget=Budget(env_steps=1, evals=1), eval=FAST_EVAL))
    good, _ = execute(p, store, log=lambda s: None)
    text = open(store.path(p.run_id)).read()
    with open(store.path(p.run_id), "w") as f:
        f.write(text[: len(text) // 2])
    with pytest.raises(CorruptRecord) as e:
        store.get(p.run_id)
    assert str(e.value).startswith(f"record {store.path(p.run_id)} is not valid JSON (")
    assert str(e.value).endswith("it was truncated or edited by hand; delete it (or run the "
                                 "sweep again, which sets it aside under corrupt/ and re-runs "
                                 "the cell)")
    with pytest.warns(UserWarning, match="corrupt"):
        out = run_local([p], store, log=lambda s: None, isolate=False, warm=False)
    assert out[0].status == "ok" and not out[0].skipped
    again = store.get(p.run_id)
    assert again["final_return"] == good["final_return"]
    assert open(f"{store.root}/corrupt/{p.run_id}.json").read() == text[: len(text) // 2]
    # cut short again: this copy joins the first in corrupt/, and neither is lost (planted
    # fault: creating corrupt/ anew failing once it exists)
    with open(store.path(p.run_id), "w") as f:
        f.write(text[:10])
    with pytest.warns(UserWarning, match=f"moved to .*corrupt/{p.run_id}.2.json"):
        assert store.finished(p.run_id) is None
    assert sorted(os.listdir(f"{store.root}/corrupt")) == [f"{p.run_id}.2.json",
                                                           f"{p.run_id}.json"]
    assert open(f"{store.root}/corrupt/{p.run_id}.2.json").read() == text[:10]


def test_a_record_file_that_holds_no_object_is_named_with_the_fix(store):
    """Valid JSON that is not an object (a list written by another tool) is no record.
    Planted fault: the error raised without its message."""
    from bench.store import CorruptRecord
    os.makedirs(store.root, exist_ok=True)
    with open(store.path("abc"), "w") as f:
        f.write("[1, 2]")
    with pytest.raises(CorruptRecord) as e:
        store.get("abc")
    assert str(e.value) == (f"record {store.path('abc')} holds a list, not a run record; "
                            "delete it and re-run the cell")


def _constant_train(task, demo, config, ctx, seed):
    return TrainResult(Policy(lambda p, o, k, d: jnp.zeros(o.shape[:-1] + (1,)), 0.0),
                       env_steps=1)


def test_an_atomic_write_that_fails_keeps_the_old_file_and_leaves_no_temp_file(tmp_path):
    """Planted fault: write_atomic writing in place (a failure then leaves half a file)."""
    import os

    from bench.store import write_atomic, write_json_atomic
    path = str(tmp_path / "r.json")
    write_json_atomic(path, {"v": 1, "run_id": "r", "x": float("nan")})
    before = open(path).read()
    # records are diffable text: keys sorted, one space per level, NaN kept (a diverged
    # run's score)
    assert before == '{\n "run_id": "r",\n "v": 1,\n "x": NaN\n}'

    during = []

    def fails(f):
        f.write('{"run_id": "r", "v": 2, "pad": "')
        during.extend(os.listdir(tmp_path))
        raise OSError("disk full")
    with pytest.raises(OSError, match="disk full"):
        write_atomic(path, fails)
    assert open(path).read() == before
    assert os.listdir(tmp_path) == ["r.json"]
    # the temp file sits beside the target (os.replace is atomic only within one file
    # system), named so the store skips it: planted faults, the temp file in /tmp or
    # under another prefix
    (tmp,) = [n for n in during if n != "r.json"]
    assert tmp.startswith(".tmp-") and tmp.endswith(".json")


# ----------------------------------------------------------------------------- evaluator


def _terminating_pointmass():
    """pointmass whose episode ends once x > 1.2 (pointmass itself never terminates)."""
    from brax.envs.base import Wrapper

    from tasks.core import Task

    class Terminating(Wrapper):
        def step(self, state, action):
            s = self.env.step(state, action)
            return s.replace(done=jnp.asarray(s.obs[0] > 1.2, jnp.float32))

    base = make_task("pointmass")
    return Task(spec=base.spec, env=Terminating(base.env))


def test_an_early_terminating_host_policy_keeps_its_partial_return():
    """The evaluator's host path (DAC, PWIL) on a task that terminates (pointmass ended once
    x > 1.2): each episode's return is the sum of its rewards up to and including the
    terminal step, its length the steps taken, the same as the JAX path's and as a plain
    loop's. Planted fault: the host path adding rewards after done."""
    from bench.evaluator import run_episodes
    task = _terminating_pointmass()

    def push(params, obs, key_or_rng, deterministic):
        return np.full(np.shape(obs)[:-1] + (1,), 0.8, np.float32)
    host = Policy(push, 0.0, kind="host")
    jaxp = Policy(lambda p, o, k, d: jnp.full(o.shape[:-1] + (1,), 0.8), 0.0)
    key = jax.random.PRNGKey(3)
    ret_h, len_h, _ = run_episodes(task, host, key, 4, True)
    ret_j, len_j, _ = run_episodes(task, jaxp, key, 4, True)
    assert np.all(len_h < task.episode_length) and np.all(len_h > 0)
    np.testing.assert_array_equal(len_h, len_j)
    np.testing.assert_allclose(ret_h, ret_j, rtol=1e-5)
    # A plain loop over the first episode, from the same reset state.
    s = task.env.reset(jax.random.split(jax.random.split(key, 4)[0])[0])
    total, n = 0.0, 0
    while True:
        s = task.env.step(s, jnp.array([0.8]))
        total, n = total + float(s.reward), n + 1
        if float(s.done) > 0:
            break
    assert n == len_h[0] and total == pytest.approx(ret_h[0], rel=1e-5)


def test_each_evaluation_records_the_mean_steps_before_termination():
    """A run's evaluation points carry the mean episode length, the evidence that a policy
    scoring below the random one falls earlier. On pointmass ended once x > 1.2, a constant
    push of 0.8 ends every episode early. Planted fault: the point's length read as the
    task's episode length instead of the steps taken."""
    from bench.evaluator import EvalConfig, Evaluator, eval_key, run_episodes
    from bench.runner import RunContext
    task = _terminating_pointmass()
    push = Policy(lambda p, o, k, d: jnp.full(o.shape[:-1] + (1,), 0.8), 0.0)
    ctx = RunContext(Budget(env_steps=10), Evaluator(task, EvalConfig(num_episodes=4), 1.0,
                                                     0.0), 5)
    point = ctx.evaluate(push, 0)
    _, lengths, _ = run_episodes(task, push, eval_key(5), 4, True)
    assert 0 < point["length"] < task.episode_length
    assert point["length"] == pytest.approx(float(np.mean(lengths)))


# ----------------------------------------------------------------------------- perturbations


def _perturbed_rollout(task, steps, action, **mags):
    from bench.perturb import FAMILIES, _Perturbed
    m = np.zeros(len(FAMILIES), np.float32)
    for family, value in mags.items():
        m[FAMILIES.index(family)] = value
    env = _Perturbed(task.env, m)
    s = jax.jit(env.reset)(jax.random.PRNGKey(0))
    s = jax.jit(lambda s: jax.lax.fori_loop(0, steps, lambda i, s: env.step(s, action), s))(s)
    ps = s.pipeline_state
    return np.concatenate([np.ravel(ps.q), np.ravel(ps.qd)])


@pytest.mark.parametrize("task_name", ["inverted_pendulum", "acrobot"])
def test_actuator_strength_scales_the_force_as_a_scaled_action_would(task_name):
    """Actuator strength x (1 + m) with action a is, for a motor, action (1 + m) a at
    nominal strength: the same motion to float32 round-off (m = -0.3, a = 0.5 vs 0.35).
    Planted fault: the actuator family scaling the gear of a copy the step never reads."""
    task = make_task(task_name)
    a = 0.5 * jnp.ones(task.action_size)
    weak = _perturbed_rollout(task, 3, a, actuator=-0.3)
    np.testing.assert_allclose(weak, _perturbed_rollout(task, 3, 0.7 * a), atol=1e-6)
    assert np.abs(weak - _perturbed_rollout(task, 3, a)).max() > 1e-3


def test_mass_x_k_with_actuator_x_k_leaves_acrobots_motion_unchanged():
    """Acrobot (brax's generalized pipeline, no joint damping): M(q) qdd + C(q, qd) = tau.
    Masses and inertias x k scale M and C (gravity and Coriolis terms) by k, so with the
    actuator's torque also x k the motion is the nominal one exactly, while the mass change
    alone slows the arm. Planted fault: mass scaling the masses but not the inertias."""
    task = make_task("acrobot")
    a = 0.5 * jnp.ones(task.action_size)
    base = _perturbed_rollout(task, 3, a)
    np.testing.assert_allclose(_perturbed_rollout(task, 3, a, mass=0.5, actuator=0.5), base,
                               atol=1e-6)
    assert np.abs(_perturbed_rollout(task, 3, a, mass=0.5) - base).max() > 1e-2


def test_friction_reaches_the_contact_physics_of_a_brax_task():
    """Hopper stands on its foot from reset: the physics step reads contact friction x
    (1 + m) (captured inside the step), and the fixed-action motion changes.
    Planted fault: friction scaling a field the contact model does not read."""
    from tasks.core import Task, build_env
    base = make_task("hopper")
    env = build_env(base.spec)
    inner = env.unwrapped
    seen = []
    step = inner.pipeline_step

    def recording_step(*args, **kw):  # runs while the step is traced
        jax.debug.callback(lambda f: seen.append(np.asarray(f)), inner.sys.geom_friction)
        return step(*args, **kw)
    inner.pipeline_step = recording_step
    task = Task(spec=base.spec, env=env)
    a = 0.3 * jnp.ones(task.action_size)
    nominal = _perturbed_rollout(task, 40, a)
    seen.clear()
    slippery = _perturbed_rollout(task, 40, a, friction=-0.75)
    np.testing.assert_allclose(seen[-1], 0.25 * np.asarray(base.env.unwrapped.sys.geom_friction),
                               rtol=1e-6)
    assert np.abs(slippery - nominal).max() > 1e-3
