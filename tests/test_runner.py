"""Budgeted runs, records, resume, determinism, divergence and failure accounting."""
import dataclasses
import json
import os
import time

import jax.numpy as jnp
import pytest

from bench import plugins
from bench.api import MethodSpec, Policy, TrainResult, Uses
from bench.budget import Budget, BudgetError, parse_seconds
from bench.evaluator import EvalConfig, Evaluator
from bench.runner import RunContext, RunRequest, execute, prepare
from tasks import make_task

FAST_EVAL = EvalConfig(num_episodes=8)


@dataclasses.dataclass(frozen=True)
class ToyConfig:
    gain: float = 2.0
    nan_after: int = -1
    crash: bool = False


def _pd(params, obs, key, deterministic):
    return jnp.clip(-params * obs[..., :1] - obs[..., 1:], -1, 1)


def toy_train(task, demo, config, ctx, seed):
    """Steps 100 env steps per iteration until the budget is spent; reports each time."""
    steps, it = 0, 0
    gain = jnp.asarray(config.gain)
    while not ctx.should_stop(steps):
        it += 1
        steps += 100
        if config.crash and it == 3:
            raise RuntimeError("boom")
        if config.nan_after >= 0 and it > config.nan_after:
            gain = jnp.asarray(jnp.nan)
        ctx.report(Policy(_pd, gain), steps, {"train/loss": 1.0 / it})
    return TrainResult(Policy(_pd, gain), env_steps=steps)


@pytest.fixture
def toy(temp_method):
    return temp_method(MethodSpec(name="toy", train=toy_train, config_cls=ToyConfig,
                                  uses=Uses()))


def _req(method="toy", steps=1000, seed=0, **over):
    return RunRequest(method=method, task="pointmass", seed=seed,
                      budget=Budget(env_steps=steps, evals=5), overrides=over, eval=FAST_EVAL)


def test_step_budget_is_enforced_and_curve_recorded(toy, store):
    rec, skipped = execute(prepare(_req()), store, log=lambda s: None)
    assert not skipped and rec["status"] == "ok"
    assert rec["env_steps"] == 1000
    assert [p["env_steps"] for p in rec["curve"]] == [200, 400, 600, 800, 1000, 1000]
    # each point carries the training metrics last reported (toy: loss 1 / iteration)
    assert [p["train"]["train/loss"] for p in rec["curve"]] == pytest.approx(
        [1 / 2, 1 / 4, 1 / 6, 1 / 8, 1 / 10, 1 / 10])
    assert rec["final_normalized"] == rec["curve"][-1]["normalized"]
    assert rec["final_from"] == "final policy"
    assert rec["reports"] == 10           # one per iteration (planted fault: counting two)


def test_record_round_trip_and_fields(toy, store, monkeypatch, tmp_path):
    p = prepare(_req())
    monkeypatch.chdir(tmp_path)  # the demo's path is recorded relative to the repository
    lines = []
    rec, _ = execute(p, store, log=lines.append)
    assert rec["demo"] == {"path": "tasks/data/pointmass.npz", "sha256": p.demo.sha256}
    first = rec["curve"][0]       # each evaluation's log line, hand-formatted from the curve
    assert (f"  eval @ {first['train_s']:.1f}s, 200 env steps: return {first['return']:.2f}, "
            f"normalized {first['normalized']:.3f}") in lines
    with open(store.path(rec["run_id"])) as f:
        assert json.load(f) == json.loads(json.dumps(rec))
    for key in ("method", "task", "seed", "config", "versions", "git_revision", "machine",
                "budget", "curve", "final_return", "final_normalized", "compile_s", "status",
                "uses", "train_s", "env_steps", "demo", "references", "wall_s", "compiles",
                "retraced", "reports"):
        assert key in rec, key
    assert isinstance(rec["wall_s"], float) and rec["wall_s"] == round(rec["wall_s"], 3)
    assert rec["references"] == {"expert_return": p.demo.expert_return,
                                 "random_return": p.demo.random_return}
    assert rec["started"] <= rec["finished"]
    assert lines[-1] == (f"run {rec['run_id']}: ok, final return {rec['final_return']:.2f}, "
                         f"normalized {rec['final_normalized']:.3f}, 1000 env steps")
    assert rec["config"] == {"gain": 2.0, "nan_after": -1, "crash": False}


def test_record_names_the_xla_flags_it_ran_under(toy, store, monkeypatch):
    # XLA's CPU code generator and glibc's huge-page tunable (bench.malloc) change speed,
    # so updates per budget: the record says which.
    monkeypatch.delenv("XLA_FLAGS", raising=False)
    monkeypatch.delenv("GLIBC_TUNABLES", raising=False)
    rec, _ = execute(prepare(_req(seed=1)), store, log=lambda s: None)
    assert rec["machine"]["xla_flags"] is None and rec["machine"]["malloc_hugetlb"] is None
    monkeypatch.setenv("XLA_FLAGS", "--xla_cpu_use_fusion_emitters=false")
    monkeypatch.setenv("GLIBC_TUNABLES", "glibc.malloc.arena_max=2:glibc.malloc.hugetlb=1")
    p = prepare(_req(seed=2))
    rec, _ = execute(p, store, log=lambda s: None)
    assert rec["machine"]["xla_flags"] == "--xla_cpu_use_fusion_emitters=false"
    assert rec["machine"]["malloc_hugetlb"] == "1"
    monkeypatch.delenv("XLA_FLAGS")  # recorded, not hashed: the same cell either way
    monkeypatch.delenv("GLIBC_TUNABLES")
    assert prepare(_req(seed=2)).run_id == p.run_id


def test_resume_skips_finished_cells(toy, store):
    p = prepare(_req())
    rec, skipped = execute(p, store, log=lambda s: None)
    mtime = os.path.getmtime(store.path(p.run_id))
    again, skipped = execute(prepare(_req()), store, log=lambda s: None)
    assert skipped and again == rec and os.path.getmtime(store.path(p.run_id)) == mtime


def test_run_id_is_a_content_hash(toy):
    base = prepare(_req()).run_id
    assert prepare(_req()).run_id == base
    assert prepare(_req(seed=1)).run_id != base
    assert prepare(_req(steps=2000)).run_id != base
    assert prepare(_req(gain="3")).run_id != base


@dataclasses.dataclass(frozen=True)
class ToyConfigWithKnob(ToyConfig):
    knob: tuple = (1, 2)  # a field added after records were made; its default = old behaviour


def test_a_knob_added_later_keeps_run_ids_and_variants(toy, store, monkeypatch):
    """The run id hashes the config's non-default fields: a record made before a field
    existed is the same cell as one at that field's default (same id, same leaderboard
    variant); a non-default value is a new cell."""
    from bench.leaderboard import variant
    from bench.runner import config_identity
    assert config_identity(ToyConfigWithKnob, {"gain": 2.0, "knob": [1, 2]}) == {}
    assert config_identity(ToyConfigWithKnob, {"gain": 3, "knob": [1]}) == {"gain": 3,
                                                                            "knob": [1]}
    assert config_identity(None, {"gain": 2.0}) == {"gain": 2.0}  # unknown method: all
    old, _ = execute(prepare(_req()), store, log=lambda s: None)
    monkeypatch.setitem(plugins._REGISTRY, "toy",
                        dataclasses.replace(toy, config_cls=ToyConfigWithKnob))
    p = prepare(_req())
    assert p.run_id == old["run_id"] and store.finished(p.run_id) is not None
    assert prepare(_req(knob="3")).run_id != old["run_id"]
    new = {**old, "config": {**old["config"], "knob": [1, 2]}}
    assert variant(new) == variant(old)
    assert variant({**old, "config": {**old["config"], "knob": [3]}}) != variant(old)


def test_reindex_renames_old_scheme_records_and_sets_duplicates_aside(toy, store):
    """Records whose id came from an earlier id scheme are renamed to today's id (record,
    trajectory), keep the old id, and are then found by a sweep; the older of two records of
    the same cell moves to duplicates/."""
    from bench.runner import reindex
    rec, _ = execute(prepare(_req()), store, log=lambda s: None)
    rid = rec["run_id"]
    for i, started in ((1, "2000-01-01"), (2, "2001-01-01")):   # the same cell, old ids
        old = {**rec, "run_id": f"oldscheme{i:07d}", "started": started}
        with open(store.path(old["run_id"]), "w") as f:
            json.dump(old, f)
    os.replace(store.path(rid), os.path.join(str(tmp_dir := store.root), "..", "moved.json"))
    os.replace(store.trajectory_path(rid), store.trajectory_path("oldscheme0000002"))
    assert reindex(store, dry_run=True, log=lambda s: None) == [
        ("oldscheme0000001", rid), ("oldscheme0000002", rid)]
    assert store.get(rid) is None                                  # a dry run moves nothing
    moves = reindex(store, log=lambda s: None)
    assert len(moves) == 2
    now = store.finished(prepare(_req()).run_id)
    assert now["previous_run_ids"] == ["oldscheme0000002"] and now["started"] == "2001-01-01"
    assert os.path.exists(store.trajectory_path(rid))
    dup = [n for n in os.listdir(os.path.join(tmp_dir, "duplicates")) if n.endswith(".json")]
    assert len(dup) == 1
    with open(os.path.join(tmp_dir, "duplicates", dup[0])) as f:
        assert json.load(f)["started"] == "2000-01-01"            # the older one
    assert [r["run_id"] for r in store.records()] == [rid]
    assert reindex(store, log=lambda s: None) == []                # idempotent
    # an old-scheme record older than the one already under today's id moves aside itself
    # (planted fault: the older one left in place, the store then holding the cell twice)
    with open(store.path("oldscheme0000003"), "w") as f:
        json.dump({**rec, "run_id": "oldscheme0000003", "started": "1999-01-01"}, f)
    lines = []
    assert reindex(store, log=lines.append) == [("oldscheme0000003", rid)]
    assert lines[0] == f"reindex: oldscheme0000003 duplicates the newer {rid}; moved to duplicates/"
    assert [r["run_id"] for r in store.records()] == [rid]
    assert store.get(rid)["started"] == "2001-01-01"
    assert sorted(os.listdir(os.path.join(tmp_dir, "duplicates"))) == sorted(
        dup + ["oldscheme0000003.json"])
    # a JSON file that is no run record is named in the log and left alone
    with open(store.path("notes"), "w") as f:
        json.dump({"about": "my notes"}, f)
    lines = []
    assert reindex(store, log=lines.append) == []
    assert lines[0] == "reindex: ? is not a run record; left as is"
    assert json.load(open(store.path("notes"))) == {"about": "my notes"}


def test_the_record_of_a_cell_whose_worker_died_is_failed_complete_and_re_run(toy, store):
    """A sweep writes this record when a Ray worker dies mid-cell: the cell's head fields,
    status 'failed', the demo's references and the provenance of every record; a sweep
    re-runs it. Planted fault: a provenance field under another name."""
    from bench.machine import git_revision, machine
    from bench.runner import failed_record
    p = prepare(_req())
    rec = failed_record(p, "the Ray worker died: killed")
    assert (rec["run_id"], rec["method"], rec["task"], rec["seed"]) == (
        p.run_id, "toy", "pointmass", 0)
    assert rec["status"] == "failed" and rec["message"] == "the Ray worker died: killed"
    assert rec["git_revision"] == git_revision() and rec["machine"] == machine()
    assert rec["references"] == {"expert_return": p.demo.expert_return,
                                 "random_return": p.demo.random_return}
    assert rec["started"] == rec["finished"] and rec["env_steps"] == 0 and rec["curve"] == []
    store.write(rec)
    assert store.get(p.run_id)["status"] == "failed" and store.finished(p.run_id) is None


def test_divergence_is_recorded_with_the_last_valid_evaluation(toy, store):
    rec, _ = execute(prepare(_req(nan_after=4)), store, log=lambda s: None)
    assert rec["status"] == "diverged" and "non-finite parameters" in rec["message"]
    assert rec["final_from"] == "last valid evaluation"
    assert rec["final_return"] == rec["curve"][-1]["return"]
    assert rec["curve"][-1]["env_steps"] == 400


def test_a_failed_run_is_recorded_and_leaves_finished_records_alone(toy, store):
    good, _ = execute(prepare(_req()), store, log=lambda s: None)
    before = open(store.path(good["run_id"])).read()
    rec, _ = execute(prepare(_req(crash=True)), store, log=lambda s: None)
    assert rec["status"] == "failed" and "RuntimeError: boom" in rec["message"]
    assert open(store.path(good["run_id"])).read() == before
    assert store.finished(rec["run_id"]) is None  # a failed cell is re-run on resume


def test_evaluation_does_not_count_against_the_budget():
    class SlowEvaluator(Evaluator):
        def evaluate(self, policy, seed):
            time.sleep(0.5)
            return super().evaluate(policy, seed)

    ctx = RunContext(Budget(seconds=100), SlowEvaluator(make_task("pointmass"), FAST_EVAL), 0)
    ctx.evaluate(Policy(_pd, jnp.asarray(2.0)), 0)  # compiles + sleeps, all paused
    assert ctx.elapsed() < 0.25


def test_remaining_budget():
    """(seconds, env steps) left; None where the budget has no such limit."""
    ev = Evaluator(make_task("pointmass"), FAST_EVAL)
    assert RunContext(Budget(env_steps=100), ev, 0).remaining(30) == (None, 70)
    left_s, left_steps = RunContext(Budget(seconds=50, env_steps=10), ev, 0).remaining(12)
    assert 49.0 < left_s <= 50.0 and left_steps == -2  # overspent steps read negative
    assert RunContext(Budget(seconds=50), ev, 0).remaining(10 ** 9)[1] is None


@pytest.mark.parametrize("kw, message", [
    (dict(), "a budget needs seconds (e.g. --budget 300s) or env steps (--budget-steps N)"),
    (dict(seconds=0), "budget seconds must be > 0, got 0"),
    (dict(env_steps=-5), "budget env steps must be > 0, got -5"),
    (dict(env_steps=0), "budget env steps must be > 0, got 0"),
    (dict(env_steps=2.5), "budget env steps must be a whole number, got 2.5"),
    (dict(seconds=5, evals=0), "budget evals must be >= 1, got 0")])
def test_invalid_budgets(kw, message):
    with pytest.raises(BudgetError) as e:
        Budget(**kw)
    assert str(e.value) == message


def test_a_budget_is_one_value_however_it_is_written():
    """600 and 600.0 seconds, 1e5 and 100000 env steps: one budget, one run id (the run id
    hashes them as JSON). Planted fault: the whole-number steps stored under another name."""
    b = Budget(seconds=600, env_steps=1e5)
    assert type(b.env_steps) is int and type(b.seconds) is float
    assert b == Budget(seconds=600.0, env_steps=100000)
    assert b.describe() == "600s / 100000 env steps"
    assert Budget(env_steps=5).describe() == "5 env steps"


def test_parse_seconds():
    assert parse_seconds("300") == 300 and parse_seconds("10m") == 600
    assert parse_seconds("1.5h") == 5400 and parse_seconds("45s") == 45
    with pytest.raises(BudgetError, match="cannot read budget"):
        parse_seconds("ten minutes")


def _bc(seed, store):
    req = RunRequest(method="bc", task="pointmass", seed=seed, budget=Budget(seconds=120),
                     eval=EvalConfig(num_episodes=16))
    return execute(prepare(req), store, force=True, log=lambda s: None)[0]


def test_bc_learns_pointmass_and_is_deterministic(store, tmp_path):
    from bench.store import Store
    a = _bc(0, store)
    assert a["status"] == "ok" and a["final_normalized"] >= 0.9
    b = _bc(0, Store(str(tmp_path / "other")))
    assert b["final_return"] == a["final_return"]  # same seed -> identical on CPU
    c = _bc(1, store)
    assert c["final_normalized"] >= 0.9
    assert c["compile_s"]["train"] >= 0.0 and a["compile_s"]["train"] > 0.0


_CACHE_PROBE = """
import sys, jax, jax.numpy as jnp
from bench.runner import enable_compilation_cache
hits = []
jax.monitoring.register_event_listener(
    lambda e, **k: hits.append(e) if e == "/jax/compilation_cache/cache_hits" else None)
enable_compilation_cache(sys.argv[1], min_compile_s=0)
jax.jit(lambda x: jnp.sin(x) * 3.0 + jnp.arange(7.0))(jnp.ones(7)).block_until_ready()
print(len(hits))
"""


def test_persistent_compilation_cache_is_reused_across_processes(tmp_path):
    import subprocess
    import sys
    cache = str(tmp_path / "cache")
    run = lambda: subprocess.run([sys.executable, "-c", _CACHE_PROBE, cache], check=True,
                                 capture_output=True, text=True).stdout.split()[-1]
    assert run() == "0" and os.listdir(cache)  # first process compiles and writes
    assert int(run()) >= 1                      # second process loads from the cache


def test_final_policy_trajectory_is_stored_beside_the_record(toy, store):
    rec, _ = execute(prepare(_req()), store, log=lambda s: None)
    traj = store.trajectory(rec["run_id"])
    assert rec["trajectory"] == f"{rec['run_id']}.traj.npz"
    # the record names it relative to the store: the file sits in the store's folder
    assert os.path.isfile(os.path.join(store.root, rec["trajectory"]))
    task = make_task("pointmass")
    assert traj.shape == (task.episode_length + 1, task.state_size)
    assert not [n for n in os.listdir(store.root) if n.startswith(".tmp-")]
    assert [r["run_id"] for r in store.records()] == [rec["run_id"]]  # not read as a record


def test_a_trajectory_is_stored_as_float32_whatever_it_is_given(store):
    """Renders read float32 states (half the file of float64). Planted fault: the states
    saved in the dtype they came in."""
    import numpy as np
    os.makedirs(store.root, exist_ok=True)
    states = np.arange(6, dtype=np.float64).reshape(3, 2) / 3
    store.write_trajectory("abc", states)
    back = store.trajectory("abc")
    assert back.dtype == np.float32 and np.array_equal(back, states.astype(np.float32))


def test_cpu_model_names_the_first_processor_and_records_carry_it(toy, store):
    """Speed ratios move with the CPU model (update / forward 2.91-2.95x on one, 3.15-3.21x
    on another for the same code), so records and speed CSVs name it;
    `platform.processor()` is empty on Linux."""
    from bench.machine import cpu_model
    text = ("processor\t: 0\nvendor_id\t: AuthenticAMD\ncpu family\t: 26\nmodel\t\t: 2\n"
            "model name\t: AMD EPYC\n\nprocessor\t: 1\ncpu family\t: 6\nmodel\t\t: 167\n"
            "model name\t: Other\n")
    assert cpu_model(text) == "AMD EPYC (family 26, model 2)"
    assert cpu_model("model name\t: Neoverse\n") == "Neoverse"
    rec, _ = execute(prepare(_req(seed=3)), store, log=lambda s: None)
    assert rec["machine"]["cpu_model"] == cpu_model()


def test_env_steps_print_with_the_unit_of_their_size():
    """Hand values at each boundary (and a value that rounds up only with the right
    divisor): below 10k exact, then whole thousands, then millions with two decimals."""
    from bench.budget import format_steps
    assert [format_steps(n) for n in (0, 950, 9999, 10_000, 10_505, 51_234, 999_499)] == \
        ["0", "950", "9999", "10k", "11k", "51k", "999k"]
    assert [format_steps(n) for n in (1_000_000, 20_485_010)] == ["1.00M", "20.49M"]


def test_the_store_reads_records_only(store):
    """Only `<id>.json` files are records: a temp file of an atomic write in progress (a
    leading '.') and other files are skipped, whatever their order in the folder, and an
    unreadable record is skipped with a warning that names it."""
    store.write({"run_id": "b", "status": "ok"})
    with open(os.path.join(store.root, ".tmp-x.json"), "w") as f:
        json.dump({"run_id": "tmp"}, f)
    with open(os.path.join(store.root, "a_notes.txt"), "w") as f:
        f.write("not a record")
    with open(os.path.join(store.root, "c.json"), "w") as f:
        f.write("{\"run_id\": ")
    with pytest.warns(UserWarning, match="c.json"):
        assert [r["run_id"] for r in store.records()] == ["b"]


def test_a_transfer_run_records_each_default_perturbation_as_evaluated_alone(toy, store,
                                                                            tmp_path,
                                                                            monkeypatch):
    """With --transfer the record holds one entry per perturbation of the task's default
    set, each what `evaluate_transfer` gives for the final policy and the run's seed, and
    their summary. Planted faults: the transfer left out, evaluated with another seed, or
    with the perturbations dropped."""
    from bench import perturb
    from bench.transfer import default_summary, evaluate_transfer
    _references_in(tmp_path, monkeypatch)
    req = dataclasses.replace(_req(seed=3), eval=dataclasses.replace(FAST_EVAL, transfer=True))
    p = prepare(req)
    rec, _ = execute(p, store, log=lambda s: None)
    assert rec["status"] == "ok", rec["message"]
    task = make_task("pointmass")
    todo = perturb.default_set(task)
    alone = evaluate_transfer(task, p.demo, Policy(_pd, jnp.asarray(2.0)), 3, req.eval, todo,
                              False)
    assert sorted(rec["transfer"]) == sorted(alone) and len(alone) == len(todo) > 0
    scored = [k for k, e in alone.items() if "skipped" not in e]   # pointmass has no friction
    assert scored
    for key, entry in alone.items():
        if key in scored:
            assert rec["transfer"][key]["normalized"] == pytest.approx(entry["normalized"],
                                                                       rel=1e-6), key
        else:
            assert rec["transfer"][key] == entry
    assert rec["transfer_normalized"] == pytest.approx(default_summary(alone, task))


def test_a_run_in_changed_dynamics_logs_its_nominal_score(toy, store, monkeypatch, tmp_path):
    """The log line of the nominal score beside the headline one, hand-formatted from the
    record. Planted faults: the dynamics not passed to the scored task, a field misread or
    misformatted in the line."""
    from bench import transfer as tr
    monkeypatch.setattr(tr, "REF_DIR", str(tmp_path / "refs"))
    lines = []
    rec, _ = execute(prepare(dataclasses.replace(_req(), train_dynamics="action_bias:0.5:fixed")),
                     store, log=lines.append)
    assert rec["status"] == "ok", rec["message"]
    n = rec["nominal"]
    assert (f"  nominal dynamics: return {n['return']:.2f}, normalized "
            f"{n['normalized']:.3f}") in lines
    assert rec["references"] != rec["nominal_references"]   # scored under the changed physics
    p = prepare(_req())
    assert rec["nominal_references"] == {"expert_return": p.demo.expert_return,
                                         "random_return": p.demo.random_return}
    assert rec["run_id"] != prepare(_req()).run_id             # another cell than the nominal


def _not_a_result(task, demo, config, ctx, seed):
    return {"policy": None}


def test_a_method_that_returns_no_train_result_fails_naming_what_it_returned(temp_method,
                                                                            store):
    temp_method(MethodSpec(name="dicty", train=_not_a_result, config_cls=ToyConfig,
                           uses=Uses()))
    rec, _ = execute(prepare(_req(method="dicty")), store, log=lambda s: None)
    assert rec["status"] == "failed"
    assert rec["message"].startswith("TypeError: method 'dicty' returned dict, expected "
                                     "bench.api.TrainResult\n")


def test_a_method_with_simulator_gradients_records_its_physics_plan(temp_method, store):
    """The record names the physics plan the method's views ran (planted fault: the plan
    under another key)."""
    temp_method(MethodSpec(name="toy_grad", train=toy_train, config_cls=ToyConfig,
                           uses=Uses(sim_gradients=True)))
    p = prepare(_req(method="toy_grad"))
    rec, _ = execute(p, store, log=lambda s: None)
    assert rec["physics"] == {"choice": "task", "platform": p.platform,
                              "plan": dataclasses.asdict(p.plan)}


def test_a_config_field_at_its_default_factory_value_leaves_the_identity():
    """A list-valued knob (a default_factory field) at its default is left out of the run
    identity like any other default. Planted fault: the factory's value not computed."""
    from bench.runner import config_identity

    @dataclasses.dataclass(frozen=True)
    class WithList:
        xs: list = dataclasses.field(default_factory=lambda: [1, 2])
        lr: float = 0.1

    assert config_identity(WithList, {"xs": (1, 2), "lr": 0.1}) == {}
    assert config_identity(WithList, {"xs": [3], "lr": 0.1}) == {"xs": [3]}


def _state_policy_train(task, demo, config, ctx, seed):
    pol = Policy(lambda p, s, k, d: jnp.clip(-2.0 * s.obs[..., :1] - s.obs[..., 1:], -1, 1), (),
                 kind="jax_state")
    return TrainResult(pol, env_steps=0)


def _references_in(tmp_path, monkeypatch):
    """The transfer references read from a copy of the committed ones: what a test computes
    lands in tmp_path, never in the package data."""
    import shutil

    from bench import transfer as tr
    shutil.copytree(tr.REF_DIR, tmp_path / "refs")
    monkeypatch.setattr(tr, "REF_DIR", str(tmp_path / "refs"))


def test_a_robustness_run_scores_a_simulator_policy_on_the_whole_grid(temp_method, store,
                                                                      tmp_path, monkeypatch):
    """--robustness evaluates every perturbation of the task's grid, and a method that
    declared sim_at_test keeps that right under the perturbations too. Planted faults: the
    default set used instead of the grid; the declaration not passed to the transfer
    evaluation (its simulator policy then refused)."""
    from bench import perturb
    _references_in(tmp_path, monkeypatch)
    temp_method(MethodSpec(name="planner", train=_state_policy_train, config_cls=ToyConfig,
                           uses=Uses(sim_at_test=True)))
    req = dataclasses.replace(_req(method="planner"),
                              eval=EvalConfig(num_episodes=2, robustness=True))
    rec, _ = execute(prepare(req), store, log=lambda s: None)
    assert rec["status"] == "ok", rec["message"]
    grid = perturb.grid_set(make_task("pointmass"))
    assert sorted(rec["transfer"]) == sorted(p.key for p in grid) and len(grid) == 28


def _nan_at_the_end(task, demo, config, ctx, seed):
    ctx.report(Policy(_pd, jnp.asarray(2.0)), 100, force_eval=True)
    return TrainResult(Policy(_pd, jnp.asarray(jnp.nan)), env_steps=300)


def test_a_final_policy_that_diverged_keeps_the_env_steps_the_method_simulated(temp_method,
                                                                              store):
    """The record's env steps are what the method simulated (300), not those of its last
    valid evaluation (100), which the score falls back to. Planted fault: the env steps
    read from the fallback point."""
    temp_method(MethodSpec(name="late_nan", train=_nan_at_the_end, config_cls=ToyConfig,
                           uses=Uses()))
    rec, _ = execute(prepare(_req(method="late_nan")), store, log=lambda s: None)
    assert rec["status"] == "diverged" and "non-finite parameters" in rec["message"]
    assert rec["final_from"] == "last valid evaluation" and rec["curve"][-1]["env_steps"] == 100
    assert rec["env_steps"] == 300
