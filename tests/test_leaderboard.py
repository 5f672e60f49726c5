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
    row = board[~board.floor].iloc[0]
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


def test_training_plot_reads_each_curve_points_metrics_at_the_registered_version(store,
                                                                                  tmp_path):
    from bench.plots import training_frame, training_plot

    def point(steps, norm, **train):
        return {"env_steps": steps, "normalized": norm, "train": train}
    for rid, seed, version, curve in [
            ("a", 0, "2", [point(10, 0.2, **{"train/q_recent": 4.0, "speed/x": 1.0}),
                           point(20, 0.9, **{"train/q_recent": 8.0, "speed/x": 1.0})]),
            ("b", 1, "2", [point(10, 0.1, **{"train/q_recent": 3.0}),
                           point(20, 0.3, **{"train/q_recent": 900.0})]),
            ("c", 0, "1", [point(10, -1.0, **{"train/q_recent": 1.0})])]:
        store.write({"run_id": rid, "task": "pointmass", "method": "m", "seed": seed,
                     "status": "ok", "method_version": version, "curve": curve})
    df = training_frame(store, "pointmass", "m", version="2")
    assert sorted(df.run_id.unique()) == ["a", "b"] and len(df) == 4
    b = df[df.run_id == "b"].sort_values("env_steps")
    assert list(b["train/q_recent"]) == [3.0, 900.0] and list(b.normalized) == [0.1, 0.3]
    assert len(training_frame(store, "pointmass", "m")) == 5  # every version
    path = training_plot(store, "pointmass", "m", str(tmp_path), version="2")
    assert path.endswith("train_pointmass_m.png")
    assert (tmp_path / "train_pointmass_m.png").stat().st_size > 1000
    with pytest.raises(ValueError, match="unknown metric.*train/loss.*train/q_recent"):
        training_plot(store, "pointmass", "m", str(tmp_path), metrics=["train/loss"])
    with pytest.raises(ValueError, match="no finished 'm' runs on 'hopper'"):
        training_plot(store, "hopper", "m", str(tmp_path))


def test_training_plot_draws_its_runs_in_seed_order(store, tmp_path, monkeypatch):
    """The legend reads seed 0, 1, 2 whatever the run ids' order (run ids are hashes).
    Planted fault: grouping the runs by run id first."""
    import bench.plots as plots
    for rid, seed in [("ff", 0), ("aa", 2), ("cc", 1)]:
        store.write({"run_id": rid, "task": "pointmass", "method": "m", "seed": seed,
                     "status": "ok", "method_version": "1",
                     "curve": [{"env_steps": 10, "normalized": 0.5,
                                "train": {"train/q_recent": 1.0}}]})
    drawn = {}
    monkeypatch.setattr(plots, "save_figure", lambda fig, out, name: drawn.setdefault("fig", fig))
    plots.training_plot(store, "pointmass", "m", str(tmp_path))
    axes = drawn["fig"].axes
    assert [t.get_text() for t in axes[0].get_legend().get_texts()] == [
        "seed 0", "seed 1", "seed 2"]
    assert [line.get_label() for line in axes[1].get_lines()] == ["seed 0", "seed 1", "seed 2"]


def test_different_configs_are_not_pooled(store):
    for rid, seed, lr in (("a", 0, 1e-3), ("b", 1, 1e-3), ("c", 0, 1e-4)):
        store.write({"run_id": rid, "task": "pointmass", "method": "m", "seed": seed,
                     "status": "ok", "final_normalized": 0.5, "final_return": 1.0,
                     "config": {"lr": lr}, "method_version": "1", "preset": None,
                     "uses": {}, "reference_method": False,
                     "budget": {"seconds": 60.0, "env_steps": None, "charge_compile": True,
                                "evals": 10}})
    board = lb.leaderboard(store)
    board = board[~board.floor]
    assert sorted(board.seeds.tolist()) == [1, 2] and board.variant.nunique() == 2


def test_aggregates_take_the_variant_with_most_seeds_then_the_newest(store):
    from bench.leaderboard import main_variants
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
    # a third seed for one cell only: no task has every method at 3 seeds, so the
    # aggregates refuse and say which cell is short
    _full(store, "extra", "ild", "hopper", 2, 0.5, [_pt(5, 0.5)])
    write_report(store, str(tmp_path / "out2"), reps=50)
    text = (tmp_path / "out2" / "aggregates.md").read_text()
    assert "not aggregated: unequal seed counts" in text
    # bc's third hopper seed completes hopper at 3; reacher (2 seeds) is left out, named
    _full(store, "extra_bc", "bc", "hopper", 2, 0.1, [_pt(5, 0.1)])
    write_report(store, str(tmp_path / "out3"), reps=50)
    agg = pd.read_csv(tmp_path / "out3" / "aggregates.csv")
    nominal = agg[(agg.score == "normalized") & agg.method.notna()].set_index("method")
    assert set(nominal.task_set) == {"hopper"}
    assert nominal.loc["ild", "mean"] == pytest.approx((0.9 + 0.8 + 0.5) / 3)
    assert nominal.loc["bc", "mean"] == pytest.approx((0.5 + 0.4 + 0.1) / 3)
    text = (tmp_path / "out3" / "aggregates.md").read_text()
    assert ("normalized: over the tasks where every method has 3 seeds (hopper); left out "
            "until their cells are complete: reacher (unequal seed counts: ") in text


def test_a_task_with_a_weak_reference_stays_in_the_table_but_not_the_aggregates(
        store, tmp_path, monkeypatch):
    import dataclasses

    from bench.report import aggregates, write_report
    from tasks import TASKS
    # No registered task has a weak reference since swimmer's open-loop expert;
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


def test_floors_on_pointmass_equal_their_hand_computed_returns(tmp_path):
    """pointmass: x_{t+1} = x_t + dt v_t, v_{t+1} = v_t + dt f_t / m, f = 2 a, reward
    -|x_{t+1}|. zero_action keeps v_0: x_t = x_0 + t dt v_0. demo_replay plays the demo's
    a_t from each episode's own (x_0, v_0). Both over the references' 128 episodes from
    seed 0, normalized by the demo's references."""
    import jax
    import numpy as np

    from bench.evaluator import eval_key
    from bench.floors import floors
    from tasks import make_task
    from tasks.demo import load_demo
    task = make_task("pointmass")
    demo = load_demo(task.spec.demo_path, task)
    got = floors(task, demo, ref_dir=str(tmp_path))  # computed afresh, then stored
    keys = jax.random.split(eval_key(0), 128)
    x0v0 = np.stack([np.asarray(task.env.reset(jax.random.split(k)[0]).pipeline_state)
                     for k in keys]).astype(np.float64)
    env = task.env.unwrapped
    dt, m, fs = env.dt, env.mass, env.force_scale

    def episode_return(x, v, actions):
        total = 0.0
        for a in actions:
            x, v = x + dt * v, v + dt * fs * np.clip(a, -1, 1) / m
            total -= abs(x)
        return total
    T = demo.length
    zero = np.mean([episode_return(x, v, np.zeros(T)) for x, v in x0v0])
    replay = np.mean([episode_return(x, v, np.asarray(demo.actions[0, :, 0], np.float64))
                      for x, v in x0v0])
    assert got["zero_action"]["return"] == pytest.approx(zero, rel=1e-4)
    assert got["demo_replay"]["return"] == pytest.approx(replay, rel=1e-4)
    assert got["zero_action"]["normalized"] == pytest.approx(float(demo.normalize(zero)),
                                                             rel=1e-4)
    assert floors(task, demo, ref_dir=str(tmp_path), compute=False) == got  # read back
    # the random policy on the same episodes is the demo's own random reference, exactly,
    # and pointmass never terminates: every episode lasts the task's length
    assert got["random"]["return"] == pytest.approx(demo.random_return, rel=1e-9)
    assert got["random"]["normalized"] == pytest.approx(0.0, abs=1e-9)
    assert {v["length"] for v in got.values()} == {float(task.episode_length)}


def _steps_rec(store, rid, method, seed, norm, steps, updates):
    store.write({"run_id": rid, "task": "pointmass", "method": method, "seed": seed,
                 "status": "ok", "final_normalized": norm, "final_return": 1.0,
                 "uses": {"demo_states": True}, "reference_method": False,
                 "budget": {"seconds": 60.0, "env_steps": None, "charge_compile": True,
                            "evals": 10}, "env_steps": steps,
                 "train_metrics": {"train/updates": updates}})


def test_cells_report_median_env_steps_and_updates_and_mark_starved_and_floor_cells(store):
    """Median env steps and updates per cell; a DAC cell under its 1M-step paper budget is
    starved; a cell not above the zero_action floor is marked; floors are rows."""
    for seed, steps, updates in ((0, 30_000, 29_000), (1, 50_000, 49_000), (2, 40_000, 39_000)):
        _steps_rec(store, f"d{seed}", "dac", seed, 0.9, steps, updates)
    for seed in range(2):
        _steps_rec(store, f"b{seed}", "bc", seed, 0.1, 0, 1000)
    floors = {"pointmass": {"zero_action": {"return": -50.0, "normalized": 0.2},
                            "demo_replay": {"return": -30.0, "normalized": 0.7}}}
    board = lb.board(lb.records_frame(store), floors)
    dac = board[board.method == "dac"].iloc[0]
    bc = board[board.method == "bc"].iloc[0]
    assert dac.env_steps_median == 40_000 and dac.updates_median == 39_000
    assert dac.starved and dac.min_env_steps == 1_000_000 and not dac.below_zero_action
    assert not bc.starved and bc.below_zero_action and bc.env_steps_median == 0
    assert sorted(board[board.floor].method) == ["demo_replay", "zero_action"]
    md = lb.to_markdown(board)
    assert "dac†" in md and "bc‡" in md and "40k" in md and "_zero_action (floor)_" in md
    assert "starved" in md and "dac 1.00M" in md and "not above the zero_action floor" in md
    assert "Weakly discriminative" not in md
    floors["pointmass"]["zero_action"]["normalized"] = 0.85
    assert "Weakly discriminative (zero_action above 0.8 normalized): pointmass." in \
        lb.to_markdown(lb.board(lb.records_frame(store), floors))


def test_curves_read_against_env_steps_and_plot_on_a_step_axis(store, tmp_path):
    """A run's score at n env steps is its latest evaluation at or before n (0 before the
    first): the sample-matched reading of an anytime curve."""
    from bench import curves
    from bench.report import step_curve_plots
    curve = [{"train_s": 5.0, "env_steps": 10_000, "normalized": 0.3},
             {"train_s": 9.0, "env_steps": 50_000, "normalized": 0.8},
             {"train_s": 20.0, "env_steps": 200_000, "normalized": 0.9}]
    got = curves.value_at(curve, [5_000, 10_000, 49_999, 50_000, 10 ** 6], x="env_steps")
    assert got.tolist() == [0.0, 0.3, 0.3, 0.8, 0.9]
    assert curves.value_at(curve, [10.0], x="train_s").tolist() == [0.8]
    with pytest.raises(ValueError, match="'train_s' or 'env_steps'"):
        curves.value_at(curve, [1], x="updates")
    for seed in range(2):
        store.write({"run_id": f"s{seed}", "task": "pointmass", "method": "dac", "seed": seed,
                     "status": "ok", "final_normalized": 0.9, "final_return": 1.0,
                     "curve": curve, "uses": {}, "reference_method": False,
                     "budget": {"seconds": None, "env_steps": 200_000,
                                "charge_compile": True, "evals": 3}, "env_steps": 200_000})
    paths = step_curve_plots(lb.records_frame(store), str(tmp_path))
    assert [p.split("/")[-1] for p in paths] == ["steps_pointmass.png"]
    assert (tmp_path / "steps_pointmass.png").stat().st_size > 1000


def test_a_cell_made_by_an_older_method_version_is_marked_stale(store):
    """The registered DAC is version 2: a version-1 cell carries §, a note names both
    versions, and a version-2 cell (its re-run, one seed of two so far) is not marked."""
    for seed in range(2):
        _full(store, f"old{seed}", "dac", "hopper", seed, 0.5, [_pt(5, 0.5)])
    store.write({**store.get("old0"), "run_id": "new0", "method_version": "2",
                 "final_normalized": 0.8})
    board = lb.board(lb.records_frame(store))
    assert dict(zip(board.version, board.stale)) == {"1": True, "2": False}
    assert dict(zip(board.version, board.seeds)) == {"1": 2, "2": 1}
    md = lb.to_markdown(board)
    assert md.count("dac§") == 1 and "dac version 1 (now 2)" in md
    assert "superseded" not in md


def test_a_stale_cell_below_random_says_its_re_run_is_not_complete(store):
    for seed in range(2):
        _full(store, f"old{seed}", "dac", "hopper", seed, -0.5, [_pt(5, -0.5)])
    store.write({**store.get("old0"), "run_id": "new0", "method_version": "2",
                 "final_normalized": 0.8})
    md = lb.to_markdown(lb.board(lb.records_frame(store)))
    assert ("dac on hopper at version 1 (stale: its records hold no episode lengths; the "
            "registered version's re-run is not complete)") in md


def test_a_stale_cell_is_left_out_once_its_re_run_has_as_many_seeds(store):
    """Version 2's re-run of DAC on hopper has both seeds: the version-1 row goes from the
    table (named in the notes, its records kept), and the aggregates read version 2. Planted
    fault it catches: a superseded version-1 cell below random left in the table with no
    explanation (its records hold no episode lengths)."""
    for seed in range(2):
        _full(store, f"old{seed}", "dac", "hopper", seed, -0.5, [_pt(5, -0.5)])
        store.write({**store.get(f"old{seed}"), "run_id": f"new{seed}", "method_version": "2",
                     "final_normalized": 0.8})
    board = lb.board(lb.records_frame(store))
    cells = board[~board.floor.fillna(False).astype(bool)]
    assert list(cells.version) == ["2"] and cells.normalized_mean.iloc[0] == pytest.approx(0.8)
    md = lb.to_markdown(board)
    assert "dac§" not in md and "Below the random policy" not in md
    assert "superseded by a re-run of the registered version" in md
    assert "dac version 1 on hopper" in md
    assert len(list(store.records())) == 4


def _seeded(store, rid, seed, norm):
    store.write({"run_id": rid, "task": "pointmass", "method": "m", "seed": seed,
                 "status": "ok", "final_normalized": norm, "final_return": norm,
                 "uses": {"demo_states": True}, "reference_method": False,
                 "budget": {"seconds": 60.0, "env_steps": None, "charge_compile": True,
                            "evals": 10}, "train_s": 1.0})


def test_tuning_runs_are_left_out_of_a_table_of_reporting_runs(store):
    """Fault it catches: runs on tuning seeds (100 and up) pooled with the reporting seeds, so
    the runs a setting was chosen on enter the score it is reported with."""
    _seeded(store, "a", 0, 0.2)
    _seeded(store, "b", 1, 0.4)
    _seeded(store, "t", 100, 1.0)
    board = lb.leaderboard(store)
    row = board[~board.floor].iloc[0]
    assert row.seeds == 2 and row.normalized_mean == pytest.approx(0.3)
    assert "1 tuning run(s) (seeds 100 and up) are left out" in lb.to_markdown(board)


def test_a_store_of_tuning_runs_only_is_its_own_report(store):
    _seeded(store, "t0", 100, 1.0)
    _seeded(store, "t1", 101, 0.5)
    board = lb.leaderboard(store)
    row = board[~board.floor].iloc[0]
    assert row.seeds == 2 and row.normalized_mean == pytest.approx(0.75)
    assert "left out" not in lb.to_markdown(board)


def test_a_cell_below_random_is_explained_by_its_episode_lengths(store):
    """A cell below the random policy is named in the notes with the mean steps its
    episodes last against the random policy's (the floors' `random` entry, not printed as
    a row). Planted fault: the length read from the first evaluation instead of the final
    one."""
    for seed, length in ((0, 20.0), (1, 30.0)):
        store.write({"run_id": f"f{seed}", "task": "pointmass", "method": "pwil", "seed": seed,
                     "status": "ok", "final_normalized": -0.5, "final_return": 1.0,
                     "curve": [{"train_s": 1.0, "env_steps": 10, "normalized": 0.0,
                                "length": 128.0},
                               {"train_s": 2.0, "env_steps": 20, "normalized": -0.5,
                                "length": length}],
                     "uses": {}, "reference_method": False,
                     "budget": {"seconds": 60.0, "env_steps": None, "charge_compile": True,
                                "evals": 2}, "env_steps": 20})
    floors = {"pointmass": {"zero_action": {"return": -50.0, "normalized": 0.2, "length": 90},
                            "demo_replay": {"return": -30.0, "normalized": 0.7},
                            "random": {"return": -60.0, "normalized": 0.0, "length": 88.0}}}
    board = lb.board(lb.records_frame(store), floors)
    assert sorted(board[board.floor].method) == ["demo_replay", "zero_action"]
    cell = board[board.method == "pwil"].iloc[0]
    assert cell.length_mean == pytest.approx(25.0) and cell.random_length == 88.0
    assert "pwil on pointmass: 25 steps vs 88, it ends its episodes earlier" in \
        lb.to_markdown(board)
