"""Leaderboard aggregation on hand-made records."""
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
