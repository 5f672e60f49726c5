"""The sample-matched table: scores at equal env-step budgets, read from anytime curves."""
import pandas as pd
import pytest

from bench import leaderboard as lb
from bench import sample_matched as sm


def _pt(steps, norm, updates=None):
    p = {"train_s": steps / 1000, "env_steps": steps, "normalized": norm, "return": 0.0}
    if updates is not None:
        p["train"] = {"train/updates": updates}
    return p


CURVE = [_pt(0, 0.1), _pt(10_256, 0.3, 9_000), _pt(40_960, 0.5, 39_000),
         _pt(51_200, 0.7, 50_000), _pt(200_016, 0.9, 199_000)]


def test_a_run_counts_at_the_evaluation_nearest_the_budget_within_the_tolerance():
    assert sm.point_at(CURVE, 200_016, 50_000)["normalized"] == 0.7      # 2.4% over
    assert sm.point_at(CURVE, 200_016, 200_000)["normalized"] == 0.9     # 0.008% over
    assert sm.point_at(CURVE, 200_016, 10_000)["normalized"] == 0.3      # 2.6% over
    assert sm.point_at(CURVE, 200_016, 100_000) is None                  # nearest 51k: 49% off
    assert sm.point_at(CURVE, 200_016, 30_000) is None                   # 40,960: 37% off
    assert sm.point_at(CURVE, 200_016, 45_000)["normalized"] == 0.5      # 40,960: 9% off
    assert sm.point_at(CURVE, 200_016, 45_000, tolerance=0.05) is None


def test_a_run_that_used_no_more_than_the_budget_counts_with_its_final_evaluation():
    bc = [_pt(0, 0.6), {**_pt(0, 0.8), "train_s": 9.0}]    # BC: every point at 0 env steps
    assert sm.point_at(bc, 0, 50_000)["normalized"] == 0.8
    assert sm.point_at(bc, 0, 200_000)["normalized"] == 0.8
    short = [_pt(20_000, 0.2), _pt(40_000, 0.4)]            # a 40k-step run, read at 50k
    assert sm.point_at(short, 40_000, 50_000)["normalized"] == 0.4
    assert sm.point_at([{"env_steps": 0, "normalized": None}], 0, 50_000) is None


def _write(store, rid, method, seed, curve, total, steps_budget=200_000, seconds=None):
    store.write({"run_id": rid, "task": "hopper", "method": method, "seed": seed,
                 "status": "ok", "final_normalized": curve[-1]["normalized"],
                 "final_return": 1.0, "curve": curve, "uses": {}, "config": {},
                 "method_version": "1", "preset": None, "reference_method": False,
                 "budget": {"seconds": seconds, "env_steps": steps_budget,
                            "charge_compile": True, "evals": 20}, "env_steps": total})


def test_the_table_averages_runs_per_budget_and_leaves_wall_clock_runs_out(store):
    for seed, (a, b) in enumerate(((0.6, 0.8), (0.8, 1.0))):
        _write(store, f"d{seed}", "dac", seed,
               [_pt(10_256, 0.1, 10_000), _pt(51_200, a, 50_000), _pt(200_016, b, 199_000)],
               200_016)
        _write(store, f"b{seed}", "bc", seed, [_pt(0, 0.5 + seed / 10)], 0)
    # a wall-clock DAC run with an evaluation at 50k: not read
    _write(store, "w", "dac", 9, [_pt(50_000, 0.0)], 60_000, steps_budget=None,
           seconds=600.0)
    df = sm.table(lb.records_frame(store)).set_index(["env_steps_budget", "method"])
    assert df.loc[(50_000, "dac")].normalized_mean == pytest.approx(0.7)
    assert df.loc[(50_000, "dac")].normalized_std == pytest.approx(0.141421356)
    assert df.loc[(50_000, "dac")].seeds == 2
    assert df.loc[(50_000, "dac")].env_steps_read == 51_200
    assert df.loc[(50_000, "dac")].updates_median == 50_000
    assert df.loc[(200_000, "dac")].normalized_mean == pytest.approx(0.9)
    assert df.loc[(50_000, "bc")].normalized_mean == pytest.approx(0.55)
    assert df.loc[(200_000, "bc")].normalized_mean == pytest.approx(0.55)
    assert len(df) == 4
    md = sm.to_markdown(sm.table(lb.records_frame(store)),
                        {"hopper": {"zero_action": {"normalized": 0.084, "return": 1.0}}})
    assert "## 50k env steps" in md and "## 200k env steps" in md
    assert "0.700 ± 0.141" in md and "0.084" in md and "51k" in md


def test_the_report_writes_the_sample_matched_table_beside_the_wall_clock_one(store, tmp_path):
    from bench.report import write_report
    for seed in range(2):
        _write(store, f"d{seed}", "dac", seed, [_pt(51_200, 0.4), _pt(200_016, 0.6)],
               200_016)
        _write(store, f"i{seed}", "ild", seed, [_pt(49_152, 0.9), _pt(200_704, 0.95)],
               200_704)
    paths = write_report(store, str(tmp_path / "out"), reps=50)
    names = {p.rsplit("/", 1)[-1] for p in paths}
    assert {"leaderboard.md", "sample_matched.md", "sample_matched.csv",
            "paper_comparison.md", "paper_comparison.csv"} <= names
    csv = pd.read_csv(tmp_path / "out" / "sample_matched.csv")
    assert sorted(zip(csv.env_steps_budget, csv.method, csv.normalized_mean)) == [
        (50_000, "dac", 0.4), (50_000, "ild", 0.9), (200_000, "dac", 0.6),
        (200_000, "ild", 0.95)]
    text = (tmp_path / "out" / "paper_comparison.md").read_text()
    assert "## 50k env steps (sample-matched)" in text and "(wall-clock)" not in text


def test_the_table_names_the_cells_that_hold_fewer_runs_than_the_fullest():
    df = pd.DataFrame([
        {"env_steps_budget": 50_000, "task": t, "method": m, "variant": "v", "seeds": n,
         "normalized_mean": 0.5, "normalized_std": 0.1, "env_steps_read": 51_200.0,
         "updates_median": 50_000.0}
        for t, m, n in (("ant", "ild", 3), ("ant", "dac", 1), ("hopper", "ild", 3),
                        ("hopper", "dac", 3), ("hopper", "pwil", 2))])
    assert sm.gaps(df) == {50_000: [("ant", "dac", 1), ("ant", "pwil", 0),
                                    ("hopper", "pwil", 2)]}
    md = sm.to_markdown(df)
    assert "Incomplete (runs out of 3): ant dac 1, pwil 0; hopper pwil 2." in md
    full = df.assign(seeds=3)
    full = pd.concat([full, full.iloc[[0]].assign(method="pwil")])
    assert sm.gaps(full) == {50_000: []} and "Incomplete" not in sm.to_markdown(full)
