"""Speed-accuracy tables and the ablation table, on hand-made records; open-loop
trajectory error between backends."""
import numpy as np
import pytest

from bench import ablation, tradeoff
from tasks.core import task_with_backend


def _ild(store, rid, seed, norm, config, num_demos=1, secs=180.0, curve=None, version=None,
         finished="2026-11-01T00:00:00"):
    from bench.plugins import get_method
    base = {"loss": "chamfer", "truncation": 10, "alpha": 1.0, "num_envs": 32}
    store.write({"run_id": rid, "task": "hopper", "method": "ild", "seed": seed,
                 "finished": finished,
                 "method_version": version or get_method("ild").version,
                 "status": "ok", "final_normalized": norm, "final_return": 100 * norm,
                 "config": {**base, **config}, "num_demos": num_demos,
                 "budget": {"seconds": secs}, "curve": curve or [],
                 "train_metrics": {"train/updates": 50}, "env_steps": 1000, "train_s": secs})


def test_ablation_table_directions_against_the_paper(store):
    _ild(store, "b0", 0, 0.80, {})
    _ild(store, "b1", 1, 0.90, {})
    _ild(store, "l2", 0, 0.50, {"loss": "l2"})          # paper: l2 < chamfer on hopper
    _ild(store, "t1", 0, 0.95, {"truncation": 1})       # paper: trunc1 < trunc10
    _ild(store, "d16", 0, 0.85, {}, num_demos=16)
    _ild(store, "old", 2, 0.10, {}, version="0")        # an older ILD: not pooled
    df = ablation.table(store, "hopper").set_index("setting")
    assert df.loc["base", "normalized"] == pytest.approx(0.85) and df.loc["base", "seeds"] == 2
    assert df.loc["l2", "ours_vs_base"] == "down" and df.loc["l2", "paper_vs_base"] == "down"
    assert df.loc["l2", "agrees"] == "yes" and df.loc["l2", "paper_return"] == 173.39
    assert df.loc["trunc1", "ours_vs_base"] == "up" and df.loc["trunc1", "agrees"] == "no"
    assert df.loc["16demos", "ours_vs_base"] == "same" and df.loc["16demos", "agrees"] == "-"
    # base seed 1 re-run with a speed default on (another config, another run id): the
    # latest record stands for the seed, which counts once
    _ild(store, "b1lean", 1, 0.70, {"lean_substeps": True}, finished="2026-11-26T22:00:00")
    base = ablation.table(store, "hopper").set_index("setting").loc["base"]
    assert base["seeds"] == 2 and base["normalized"] == pytest.approx(0.75)
    with pytest.raises(ValueError, match="ildbench ablate --task reacher"):
        ablation.table(store, "reacher")
    reqs = ablation.requests("hopper", 180, seeds=(0,))
    assert len(reqs) == len(ablation.SETTINGS)
    assert {r.num_demos for r in reqs} == {1, 16}
    assert {r.overrides.get("truncation") for r in reqs} == {None, 1, 30, 100}


def test_budget_table_reads_anytime_curves(store):
    curve = [{"train_s": 50, "normalized": 0.2}, {"train_s": 200, "normalized": 0.6},
             {"train_s": 500, "normalized": 0.9}]
    _ild(store, "a", 0, 0.9, {}, secs=600, curve=curve)
    _ild(store, "b", 1, 0.5, {}, secs=120, curve=[{"train_s": 100, "normalized": 0.5}])
    df = tradeoff.budget_table(store, "hopper").set_index("minutes")
    assert df.loc[1, "mean"] == pytest.approx((0.2 + 0.0) / 2)   # b had no eval before 60 s
    assert df.loc[2, "mean"] == pytest.approx((0.2 + 0.5) / 2)
    assert df.loc[5, "mean"] == pytest.approx(0.6) and df.loc[5, "count"] == 1
    assert df.loc[10, "mean"] == pytest.approx(0.9)


def test_ild_grid_table(store):
    _ild(store, "a", 0, 0.7, {"truncation": 1, "num_envs": 8})
    _ild(store, "old", 0, 0.1, {"truncation": 1, "num_envs": 8}, version="0")
    _ild(store, "c", 0, 0.5, {"truncation": 30, "num_envs": 8})
    _ild(store, "d", 0, 0.6, {"truncation": 1, "num_envs": 128})
    df = tradeoff.ild_table(store, "hopper")
    assert list(zip(df.truncation, df.batch)) == [(1, 8), (1, 128), (30, 8)]  # a grid, read
    assert df.iloc[0].truncation == 1 and df.iloc[0].batch == 8
    assert df.iloc[0].normalized == 0.7  # the older ILD's record is left out
    assert tradeoff.ild_table(store, "hopper", version="0").iloc[0].normalized == 0.1
    assert df.iloc[0].env_steps_per_s == pytest.approx(1000 / 180)
    # (1, 8) seed 0 re-run with a speed default on (another config, so another run id):
    # the latest record stands for the cell's seed, which counts once
    _ild(store, "a_lean", 0, 0.9, {"truncation": 1, "num_envs": 8, "lean_substeps": True},
         finished="2026-11-27T04:00:00")
    _ild(store, "a_s1", 1, 0.3, {"truncation": 1, "num_envs": 8})   # another seed: kept
    df = tradeoff.ild_table(store, "hopper")
    assert len(df) == 4 and "finished" not in df.columns
    cell = df[(df.truncation == 1) & (df.batch == 8)]
    assert list(cell.seed) == [0, 1] and list(cell.normalized) == [0.9, 0.3]
    reqs = tradeoff.ild_requests("hopper", 60)
    assert len(reqs) == 9 and {r.overrides["num_envs"] for r in reqs} == {8, 32, 128}


def test_open_loop_error_zero_for_the_same_backend_and_finite_across():
    acts, keys = tradeoff.probe_actions("inverted_pendulum", batch=2, horizon=20)
    assert acts.shape == (2, 20, 1)
    ref = tradeoff.open_loop_positions(task_with_backend("inverted_pendulum", "generalized"),
                                       acts, keys)
    again = tradeoff.open_loop_positions(task_with_backend("inverted_pendulum", "generalized"),
                                         acts, keys)
    np.testing.assert_array_equal(ref, again)
    pos = tradeoff.open_loop_positions(task_with_backend("inverted_pendulum", "positional"),
                                       acts, keys)
    err = np.linalg.norm(pos - ref, axis=-1)
    assert np.isfinite(err).all() and err[:, 0].max() < 1e-5 and err.max() > 0


def test_cloth_substeps_trade_flags_the_unstable_setting_and_measures_error():
    from bench.tradeoff import cloth_substeps
    df = cloth_substeps(substeps=(34, 50, 60), batch=2, repeats=1, gradient=False,
                        log=lambda *_: None).set_index("substeps")
    assert df.loc[60, "err_mean_mm"] == 0.0                      # the reference itself
    assert not df.loc[34, "stable"] and df.loc[50, "stable"] and df.loc[60, "stable"]
    assert df.loc[50, "expert_success"] == 1.0 and df.loc[50, "max_strain"] < 1.2
    assert 0 < df.loc[50, "err_mean_mm"] < 20
    # past the stability limit the cloth blows up: strained links, a failed expert
    assert df.loc[34, "max_strain"] > 1.5 and df.loc[34, "expert_success"] == 0.0
    assert (df.fwd_steps_per_s > 0).all()


def test_budget_table_keeps_variants_apart(store):
    """Runs of one method under two configs (variants) never pool: each gets its own row."""
    curve = [{"train_s": 10, "normalized": 0.4}]
    _ild(store, "a", 0, 0.45, {"truncation": 10}, secs=120, curve=curve)
    _ild(store, "b", 0, 0.8, {"truncation": 1}, secs=120,
         curve=[{"train_s": 10, "normalized": 0.8}])
    df = tradeoff.budget_table(store, "hopper", minutes=(0.5, 2))
    assert len(df) == 4 and df.method.str.startswith("ild (").all()
    assert sorted(df[df.minutes == 0.5]["mean"]) == pytest.approx([0.4, 0.8])
    # at a run's own budget its final score (0.45), not the curve's last evaluation (0.4)
    assert sorted(df[df.minutes == 2]["mean"]) == pytest.approx([0.45, 0.8])
    assert (df["count"] == 1).all()


def test_budget_table_reads_budget_scheduled_runs_at_their_own_budget_only(store):
    """A learning rate that decays over the budget makes a different run per budget: its
    curve at 0.5 minutes is not what a 0.5-minute budget would have made."""
    curve = [{"train_s": 10, "normalized": 0.4}, {"train_s": 100, "normalized": 0.7}]
    _ild(store, "a", 0, 0.75, {"lr_schedule": "budget"}, secs=120, curve=curve)
    df = tradeoff.budget_table(store, "hopper", minutes=(0.5, 1, 2))
    assert df.minutes.tolist() == [2] and df["mean"].tolist() == pytest.approx([0.75])


def test_budget_table_adds_the_runs_of_more_stores(store, tmp_path):
    """Shorter-budget runs kept in their own store join the table at their own budget."""
    from bench.store import Store
    _ild(store, "a", 0, 0.75, {"lr_schedule": "budget"}, secs=120, curve=[])
    short = Store(str(tmp_path / "short"))
    _ild(short, "b", 0, 0.4, {"lr_schedule": "budget"}, secs=30, curve=[])
    _ild(short, "c", 1, 0.6, {"lr_schedule": "budget"}, secs=30, curve=[])
    df = tradeoff.budget_table(store, "hopper", minutes=(0.5, 1, 2), more_stores=(short,))
    assert df.minutes.tolist() == [0.5, 2]
    assert df["mean"].tolist() == pytest.approx([0.5, 0.75])
    assert df["count"].tolist() == [2, 1]
    with pytest.raises(ValueError, match="no finished runs on 'ant'.*short"):
        tradeoff.budget_table(store, "ant", more_stores=(short,))


def test_append_csv_keeps_earlier_rows_when_columns_are_added(tmp_path):
    """The benchmarks' CSVs: a later run's new column is empty in the earlier rows."""
    import pandas as pd
    from bench.report import append_csv
    path = str(tmp_path / "speed.csv")
    append_csv([{"what": "ild", "seconds": 0.5}], path)
    append_csv([{"what": "ild", "seconds": 0.6, "ratio": 7.0}], path)
    df = pd.read_csv(path)
    assert list(df.columns) == ["what", "seconds", "ratio"]
    assert df.seconds.tolist() == [0.5, 0.6] and pd.isna(df.ratio[0]) and df.ratio[1] == 7.0


def _sb3(store, rid, method, utd, seed, norm, env_steps, updates, secs=180.0, train_s=180.0,
         version=None, finished="2026-12-01T00:00:00"):
    from bench.plugins import get_method
    store.write({"run_id": rid, "task": "hopper", "method": method, "seed": seed,
                 "finished": finished,
                 "method_version": version or get_method(method).version,
                 "status": "ok", "final_normalized": norm, "final_return": 100 * norm,
                 "config": {"updates_per_step": utd}, "budget": {"seconds": secs},
                 "curve": [], "train_metrics": {"train/updates": updates},
                 "env_steps": env_steps, "train_s": train_s})


def test_utd_table_sets_each_ratio_beside_its_methods_ratio_one_row(store):
    _sb3(store, "d1a", "dac", 1.0, 0, 0.5, 18_000, 17_000)
    _sb3(store, "d1b", "dac", 1.0, 1, 0.7, 22_000, 21_000)
    _sb3(store, "d4a", "dac", 0.25, 0, 0.2, 70_000, 17_000)
    _sb3(store, "d4b", "dac", 0.25, 1, 0.4, 90_000, 22_000)
    _sb3(store, "p4", "pwil", 0.25, 0, 0.9, 60_000, 15_000, train_s=150.0)
    _sb3(store, "old", "dac", 1.0, 2, -1.0, 1, 1, version="0")      # an older DAC: left out
    _sb3(store, "10m", "dac", 1.0, 2, -1.0, 1, 1, secs=600.0)       # another budget: left out
    # seed 0 at ratio 0.25 re-run later: the latest record stands for it, counted once
    _sb3(store, "d4a2", "dac", 0.25, 0, 0.3, 80_000, 20_000, finished="2026-12-02T00:00:00")
    df = tradeoff.utd_table(store, "hopper", 180.0)
    assert list(zip(df.method, df.utd)) == [("dac", 1.0), ("dac", 0.25), ("pwil", 0.25)]
    d1, d4, p4 = (df.iloc[i] for i in range(3))
    assert d1.seeds == 2 and d1["mean"] == pytest.approx(0.6) and d1.env_steps == 20_000
    assert d1["std"] == pytest.approx(np.std([0.5, 0.7], ddof=1))
    assert d4.seeds == 2 and d4["mean"] == pytest.approx(0.35) and d4.env_steps == 85_000
    assert d4.updates == 21_000 and d4.env_steps_per_s == pytest.approx(85_000 / 180)
    assert d4.score_vs_utd1 == pytest.approx(0.35 - 0.6)
    assert d4.env_steps_vs_utd1 == pytest.approx(85_000 / 20_000)
    assert d1.score_vs_utd1 == 0.0 and d1.env_steps_vs_utd1 == 1.0
    # PWIL has no ratio-1 row in this store: nothing to compare with, so no number
    assert np.isnan(p4.score_vs_utd1) and np.isnan(p4.env_steps_vs_utd1)
    assert p4.updates_per_s == pytest.approx(100.0)
    with pytest.raises(ValueError, match="ildbench tradeoff utd --task hopper --budget 60s"):
        tradeoff.utd_table(store, "hopper", 60.0)


def test_utd_requests_at_ratio_one_are_the_plain_sweeps_cells():
    """Ratio 1 is the methods' default: its cells are the plain sweep's, run id and all; the
    other ratios are other cells."""
    from bench.budget import Budget
    from bench.runner import RunRequest, prepare
    reqs = tradeoff.utd_requests("hopper", 180.0, ratios=(1.0, 0.25), seeds=(0,))
    assert [(r.method, r.overrides["updates_per_step"]) for r in reqs] == [
        ("dac", 1.0), ("dac", 0.25), ("pwil", 1.0), ("pwil", 0.25)]
    plain = prepare(RunRequest(method="dac", task="hopper", seed=0,
                               budget=Budget(seconds=180.0), preset="cpu")).run_id
    ids = [prepare(r).run_id for r in reqs]
    assert ids[0] == plain and ids[1] != plain and len(set(ids)) == 4


def test_tradeoff_utd_refuses_a_ratio_that_is_not_positive(capsys):
    from bench.cli import EXIT_BAD_INPUT, main
    assert main(["tradeoff", "utd", "--task", "hopper", "--ratios", "1", "0"]) == EXIT_BAD_INPUT
    assert capsys.readouterr().err == (
        "error: tradeoff utd: every update-to-data ratio must be > 0, got 0 in --ratios\n")


def test_tradeoff_utd_table_only_writes_the_table_of_the_stores_runs(store, tmp_path, capsys):
    import pandas as pd
    from bench.cli import EXIT_BAD_INPUT, main
    out = str(tmp_path / "out")
    args = ["tradeoff", "utd", "--task", "hopper", "--budget", "3m", "--table-only",
            "--store", store.root, "--out", out]
    assert main(args) == EXIT_BAD_INPUT  # nothing to tabulate: the error names the command
    assert "run `ildbench tradeoff utd --task hopper --budget 180s` first" in \
        capsys.readouterr().err
    _sb3(store, "d1", "dac", 1.0, 0, 0.5, 18_000, 17_000)
    _sb3(store, "d4", "dac", 0.25, 0, 0.3, 72_000, 18_000)
    assert main(args) == 0
    df = pd.read_csv(f"{out}/hopper_utd.csv")
    assert df.utd.tolist() == [1.0, 0.25] and df.env_steps_vs_utd1.tolist() == [1.0, 4.0]
    assert (tmp_path / "out" / "hopper_utd.png").exists()
    assert "| dac" in capsys.readouterr().out
