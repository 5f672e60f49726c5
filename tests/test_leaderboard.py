"""Leaderboard aggregation on hand-made records."""
import pandas as pd
import pytest

from bench import leaderboard as lb


def _rec(store, rid, method, seed, status, norm, ret=None):
    store.write({"run_id": rid, "task": "pointmass", "method": method, "seed": seed,
                 "status": status, "final_normalized": norm, "final_return": ret,
                 "uses": {"demo_states": True}, "reference_method": False,
                 "budget": {"seconds": 60.0, "env_steps": None, "charge_compile": True,
                            "evals": 10}, "train_s": 1.0})


def test_mean_std_and_seed_counts(store):
    _rec(store, "a", "m", 0, "ok", 0.5, 1.0)
    _rec(store, "b", "m", 1, "ok", 0.7, 3.0)
    _rec(store, "c", "m", 2, "diverged", None)   # never evaluated: counts as 0.0
    _rec(store, "d", "m", 3, "failed", None)     # not averaged, only counted
    board = lb.leaderboard(store)
    row = board.iloc[0]
    assert row.seeds == 3 and row.failed == 1 and row.diverged == 1
    assert row.normalized_mean == pytest.approx(0.4)
    assert row.normalized_std == pytest.approx(0.36055512754, rel=1e-9)  # std(0.5, 0.7, 0)
    assert row.return_mean == pytest.approx(2.0)
    md = lb.to_markdown(board)
    assert "0.400 ± 0.361" in md and "demo states" in md


def test_empty_store(store):
    assert lb.leaderboard(store).empty
    assert "no finished runs" in lb.to_markdown(lb.leaderboard(store))


def test_robustness_plot_from_transfer_entries(store, tmp_path):
    from bench.plots import robustness_frame, robustness_plot
    for seed, (nom, noisy) in enumerate([(1.0, 0.5), (0.8, 0.3)]):
        store.write({"run_id": f"r{seed}", "task": "pointmass", "method": "m", "seed": seed,
                     "status": "ok", "final_normalized": nom, "transfer": {
                         "action_noise=0.3": {"family": "action_noise", "magnitude": 0.3,
                                              "normalized": noisy}}})
    df = robustness_frame(store, "pointmass")
    g = df[df.family == "action_noise"]
    assert g.normalized.mean() == pytest.approx(0.4) and len(df) == 4
    path = robustness_plot(store, "pointmass", str(tmp_path))
    assert path.endswith("robustness_pointmass.png") and (tmp_path / "robustness_pointmass.png").stat().st_size > 1000
    with pytest.raises(ValueError, match="no finished runs for task 'hopper'"):
        robustness_plot(store, "hopper", str(tmp_path))


def test_different_configs_are_not_pooled(store):
    for rid, seed, lr in (("a", 0, 1e-3), ("b", 1, 1e-3), ("c", 0, 1e-4)):
        store.write({"run_id": rid, "task": "pointmass", "method": "m", "seed": seed,
                     "status": "ok", "final_normalized": 0.5, "final_return": 1.0,
                     "config": {"lr": lr}, "method_version": "1", "preset": None,
                     "uses": {}, "reference_method": False,
                     "budget": {"seconds": 60.0, "env_steps": None, "charge_compile": True,
                                "evals": 10}})
    board = lb.leaderboard(store)
    assert sorted(board.seeds.tolist()) == [1, 2] and board.variant.nunique() == 2


def test_aggregates_take_the_variant_with_most_seeds_then_the_newest(store):
    from bench.report import main_variants
    runs = (("a", 0, 1e-3, "2026-01-01"), ("b", 1, 1e-3, "2026-01-02"),
            ("c", 0, 1e-4, "2026-03-01"), ("d", 1, 1e-4, "2026-02-01"))
    for rid, seed, lr, started in runs:
        store.write({"run_id": rid, "task": "pointmass", "method": "m", "seed": seed,
                     "status": "ok", "final_normalized": lr * 1000, "final_return": 1.0,
                     "config": {"lr": lr}, "method_version": "1", "preset": None,
                     "uses": {}, "reference_method": False, "started": started,
                     "budget": {"seconds": 60.0, "env_steps": None, "charge_compile": True,
                                "evals": 10}})
    frame = lb.records_frame(store)
    assert main_variants(frame).normalized.tolist() == [0.1, 0.1]  # tie: 2 seeds each, newest
    store.write({"run_id": "e", "task": "pointmass", "method": "m", "seed": 2, "status": "ok",
                 "final_normalized": 1.0, "final_return": 1.0, "config": {"lr": 1e-3},
                 "method_version": "1", "preset": None, "uses": {}, "reference_method": False,
                 "started": "2025-01-01", "budget": {"seconds": 60.0, "env_steps": None,
                                                     "charge_compile": True, "evals": 10}})
    assert sorted(main_variants(lb.records_frame(store)).normalized) == [1.0, 1.0, 1.0]


def _full(store, rid, method, task, seed, norm, curve, transfer=None, ref=False, secs=60.0):
    store.write({"run_id": rid, "task": task, "method": method, "seed": seed, "status": "ok",
                 "final_normalized": norm, "final_return": norm * 100, "curve": curve,
                 "uses": {"demo_states": True}, "reference_method": ref, "config": {},
                 "method_version": "1", "preset": None,
                 "transfer": transfer or {},
                 "budget": {"seconds": secs, "env_steps": None, "charge_compile": True,
                            "evals": 10}, "train_s": secs})


def _pt(t, s):
    return {"train_s": t, "normalized": s, "env_steps": 0, "return": 0.0}


def test_leaderboard_anytime_columns_ci_and_paper(store):
    _full(store, "a", "ild", "hopper", 0, 1.0, [_pt(10, 0.2), _pt(30, 0.6), _pt(50, 1.0)])
    _full(store, "b", "ild", "hopper", 1, 0.6, [_pt(20, 0.6)])
    row = lb.leaderboard(store).iloc[0]
    # AUC: run a (0.2*20 + 0.6*20 + 1.0*10)/60, run b 0.6*40/60
    assert row.auc_mean == pytest.approx(((4 + 12 + 10) / 60 + 24 / 60) / 2)
    assert row.t50_mean == pytest.approx(25.0) and row.t50_reached == 2   # 30 s and 20 s
    assert row.t90_mean == pytest.approx(50.0) and row.t90_reached == 1
    assert (row.ci_lo, row.ci_hi) == (pytest.approx(0.6), pytest.approx(1.0))
    assert row.paper_return == 243.93 and row.paper_expert == 292.83
    md = lb.to_markdown(lb.leaderboard(store))
    assert "243.93 (expert 292.83)" in md and "25s (2/2)" in md and "50s (1/2)" in md


def test_report_aggregates_curves_and_refusal(store, tmp_path):
    from bench.report import write_report
    # ild > bc on both tasks in every seed; shac is a reference (excluded from aggregates)
    for seed in range(2):
        for task, (i, b) in {"hopper": (0.9, 0.5), "reacher": (0.8, 0.4)}.items():
            i, b = i - 0.1 * seed, b - 0.1 * seed
            _full(store, f"i{task}{seed}", "ild", task, seed, i, [_pt(5, i)])
            _full(store, f"b{task}{seed}", "bc", task, seed, b, [_pt(5, b)])
        _full(store, f"s{seed}", "shac", "hopper", seed, 1.0, [_pt(5, 1.0)], ref=True)
    paths = write_report(store, str(tmp_path / "out"), reps=200)
    names = {p.rsplit("/", 1)[-1] for p in paths}
    assert {"leaderboard.md", "aggregates.md", "aggregates.csv", "curves_hopper.png",
            "curves_reacher.png", "curves_aggregate.png"} <= names
    agg = pd.read_csv(tmp_path / "out" / "aggregates.csv")
    nominal = agg[(agg.score == "normalized") & agg.method.notna()].set_index("method")
    assert set(nominal.index) == {"ild", "bc"}                     # the reference left out
    assert nominal.loc["ild", "mean"] == pytest.approx((0.9 + 0.8 + 0.8 + 0.7) / 4)
    assert nominal.loc["ild", "iqm"] == pytest.approx(0.8)         # middle of .7 .8 .8 .9
    poi = agg[agg.comparison == "P(ild > bc)"]
    assert poi.p.iloc[0] == 1.0
    # a third seed for one cell only: aggregates refuse and say which cell is short
    _full(store, "extra", "ild", "hopper", 2, 0.5, [_pt(5, 0.5)])
    write_report(store, str(tmp_path / "out2"), reps=50)
    text = (tmp_path / "out2" / "aggregates.md").read_text()
    assert "not aggregated: unequal seed counts" in text


def test_a_task_with_a_weak_reference_stays_in_the_table_but_not_the_aggregates(
        store, tmp_path, monkeypatch):
    import dataclasses

    from bench.report import aggregates, write_report
    from tasks import TASKS
    # No registered task has a weak reference since swimmer's open-loop expert (session 13);
    # swimmer plays one here, as it did with its old PPO expert.
    assert not any(spec.weak_reference for spec in TASKS.values())
    monkeypatch.setitem(TASKS, "swimmer", dataclasses.replace(
        TASKS["swimmer"], weak_reference="a constant action beats the expert"))
    for seed in range(2):
        _full(store, f"ih{seed}", "ild", "hopper", seed, 0.9 - 0.1 * seed, [_pt(5, 0.9)])
        _full(store, f"bh{seed}", "bc", "hopper", seed, 0.5 - 0.1 * seed, [_pt(5, 0.5)])
        _full(store, f"is{seed}", "ild", "swimmer", seed, 3.0, [_pt(5, 3.0)])
        _full(store, f"bs{seed}", "bc", "swimmer", seed, 3.2, [_pt(5, 3.2)])
    agg, imp, notes = aggregates(lb.records_frame(store), reps=200)
    nominal = agg[agg.score == "normalized"].set_index("method")
    assert nominal.loc["ild", "mean"] == pytest.approx(0.85)          # hopper only
    assert set(nominal.task_set) == {"hopper"}
    assert any(n.startswith("swimmer: left out of the aggregates") for n in notes)
    write_report(store, str(tmp_path / "out"), reps=200)
    assert "swimmer" in open(tmp_path / "out" / "leaderboard.md").read()
