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


def test_record_round_trip_and_fields(toy, store):
    rec, _ = execute(prepare(_req()), store, log=lambda s: None)
    with open(store.path(rec["run_id"])) as f:
        assert json.load(f) == json.loads(json.dumps(rec))
    for key in ("method", "task", "seed", "config", "versions", "git_revision", "machine",
                "budget", "curve", "final_return", "final_normalized", "compile_s", "status",
                "uses", "train_s", "env_steps", "demo", "references"):
        assert key in rec, key
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


@pytest.mark.parametrize("kw", [dict(seconds=0), dict(env_steps=-5), dict()])
def test_invalid_budgets(kw):
    with pytest.raises(BudgetError):
        Budget(**kw)


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
