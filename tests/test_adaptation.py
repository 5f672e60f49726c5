"""The adaptation table: changed-dynamics runs beside nominal-trained runs scored in the same
dynamics, on hand-made records."""
import numpy as np
import pytest

from bench import adaptation
from bench.cli import main
from bench.leaderboard import records_frame
from bench.store import Store

BUDGET = {"seconds": 180.0, "env_steps": None, "charge_compile": True, "evals": 1}


def _adapted(method, seed, norm, nominal, key="actuator=-0.3", task="hopper", status="ok"):
    return {"run_id": f"a-{method}-{task}-{seed}", "task": task, "method": method,
            "method_version": "2", "seed": seed, "status": status, "final_normalized": norm,
            "nominal": {"normalized": nominal}, "train_dynamics": {"key": key},
            "budget": BUDGET, "eval": {}, "config": {}, "started": f"2026-01-0{seed + 1}"}


def _zero_shot(method, seed, norm, transfer, task="hopper", budget=BUDGET, key="actuator=-0.3"):
    return {"run_id": f"z-{method}-{task}-{seed}", "task": task, "method": method,
            "method_version": "2", "seed": seed, "status": "ok", "final_normalized": norm,
            "transfer": {key: {"normalized": transfer}, "mass=0.3": {"normalized": -5.0}},
            "budget": budget, "eval": {"transfer": True}, "config": {},
            "started": f"2026-01-0{seed + 1}"}


def _frame(tmp_path, name, records):
    """records_frame of a store holding `records` (the fields a store's reader needs added)."""
    store = Store(str(tmp_path / name))
    for r in records:
        store.write({"uses": {"demo_states": True}, "reference_method": False, **r})
    return records_frame(store)


def _table(tmp_path, adapted, zero_shot):
    return adaptation.table(_frame(tmp_path, "a", adapted), _frame(tmp_path, "z", zero_shot))


def test_adapted_and_zero_shot_scores_pool_over_seeds_on_the_same_dynamics(tmp_path):
    adapted = [_adapted("bc", 0, 0.5, 0.9), _adapted("bc", 1, 0.7, 0.8),
               _adapted("bc", 2, None, None, status="failed"),  # not scored
               _adapted("dac", 0, 0.2, 0.1)]
    zero_shot = [_zero_shot("bc", 0, 1.0, 0.2), _zero_shot("bc", 1, 0.8, 0.4),
                 _zero_shot("bc", 2, 0.9, 0.3),
                 _zero_shot("bc", 3, 0.9, 0.3, task="ant")]  # another task: not read
    df = _table(tmp_path, adapted, zero_shot).set_index("method")
    bc = df.loc["bc"]
    assert bc.seeds == 2 and bc.zero_shot_seeds == 3 and bc.dynamics == "actuator=-0.3"
    assert bc.adapted_mean == pytest.approx(0.6)
    assert bc.adapted_std == pytest.approx(np.sqrt(0.02))  # sample std of (0.5, 0.7)
    assert bc.adapted_nominal == pytest.approx(0.85)
    assert bc.zero_shot_mean == pytest.approx(0.3)  # the actuator entry, not mass's -5
    assert bc.zero_shot_std == pytest.approx(0.1)
    assert bc.zero_shot_nominal == pytest.approx(0.9)
    assert bc.gain == pytest.approx(0.3)
    dac = df.loc["dac"]  # no zero-shot runs of DAC: its zero-shot side is empty, not zero
    assert dac.zero_shot_seeds == 0 and np.isnan(dac.zero_shot_mean) and np.isnan(dac.gain)
    md = adaptation.to_markdown(_table(tmp_path, adapted, zero_shot))
    assert "0.60 ± 0.14" in md and "+0.30" in md and "No zero-shot runs for: dac on hopper" in md
    assert "Both sides trained for 180s" in md


def test_a_zero_shot_run_without_that_dynamics_entry_is_not_read_and_budgets_are_compared(
        tmp_path):
    adapted = [_adapted("bc", 0, 0.5, 0.9)]
    other = _zero_shot("bc", 0, 1.0, 0.2, key="action_bias=0.1")  # the wrong family
    short = _zero_shot("bc", 1, 1.0, 0.4, budget={**BUDGET, "seconds": 60.0})
    df = _table(tmp_path, adapted, [other, short])
    assert df.zero_shot_seeds.iloc[0] == 1 and df.zero_shot_mean.iloc[0] == pytest.approx(0.4)
    md = adaptation.to_markdown(df)
    assert "budgets differ: adapted 180s, zero-shot 60s" in md


def test_leaderboard_writes_the_adaptation_table_and_refuses_a_missing_zero_shot_store(
        tmp_path, capsys):
    from bench.budget import Budget
    assert Budget(**BUDGET).describe() == "180s"
    a, z = Store(str(tmp_path / "a")), Store(str(tmp_path / "z"))
    for r in [_adapted("bc", 0, 0.5, 0.9), _adapted("bc", 1, 0.7, 0.8)]:
        a.write({**r, "uses": {"demo_states": True, "demo_actions": True},
                 "reference_method": False, "final_return": 1.0, "train_s": 1.0})
    z.write({**_zero_shot("bc", 0, 1.0, 0.2), "uses": {"demo_states": True},
             "reference_method": False})
    out = tmp_path / "out"
    assert main(["leaderboard", "--store", a.root, "--out", str(out), "--zero-shot",
                 str(tmp_path / "nowhere")]) == 2
    assert "--zero-shot store" in capsys.readouterr().err
    assert main(["leaderboard", "--store", a.root, "--out", str(out),
                 "--zero-shot", z.root]) == 0
    text = (out / "adaptation.md").read_text()
    assert "0.60 ± 0.14" in text and "+0.40" in text  # 0.6 adapted vs 0.2 zero-shot


def test_tuning_runs_are_left_out_where_reporting_runs_exist(tmp_path):
    tuning = {**_adapted("bc", 0, 1.0, 1.0), "seed": 100, "run_id": "t"}
    df = _table(tmp_path, [_adapted("bc", 0, 0.5, 0.9), tuning], [])
    assert df.seeds.iloc[0] == 1 and df.adapted_mean.iloc[0] == pytest.approx(0.5)
