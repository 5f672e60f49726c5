"""The command line: errors before work, no partial records, run -> leaderboard."""
import os

import pytest

from bench.cli import main


def _run(capsys, *argv):
    code = main(list(argv))
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.mark.parametrize("argv,match", [
    (["run", "--method", "bc", "--task", "hoper", "--budget", "10s"],
     "unknown task 'hoper'; valid tasks: acrobot, ant"),
    (["run", "--method", "ild2", "--task", "pointmass", "--budget", "10s"],
     "unknown method 'ild2'; valid methods: bc"),
    (["run", "--method", "bc", "--task", "pointmass", "--budget", "0s"],
     "budget seconds must be > 0"),
    (["run", "--method", "bc", "--task", "pointmass", "--budget", "soon"],
     "cannot read budget 'soon'"),
    (["run", "--method", "bc", "--task", "pointmass", "--budget-steps", "-1"],
     "budget env steps must be > 0"),
    (["run", "--method", "bc", "--task", "pointmass"], "give a budget"),
    (["run", "--method", "bc", "--task", "pointmass", "--budget", "5s", "--set", "updates=0"],
     "updates must be >= 1"),
    (["run", "--method", "bc", "--task", "pointmass", "--budget", "5s", "--set", "lr"],
     "--set expects key=value"),
    (["sweep", "--methods", "bc", "--tasks", "pointmass", "nope", "--budget", "5s"],
     "unknown task 'nope'"),
    (["expert", "train", "--task", "acrobot", "--set", "discounting=0.9"],
     "--set: PPO settings, but 'acrobot' trains by trajectory optimization"),
    (["expert", "train", "--task", "walker2d", "--env-set", "healthy=3"],
     "--env-set: brax:walker2d takes no argument 'healthy'"),
    (["expert", "train", "--task", "walker2d", "--env-set", "healthy_reward"],
     "--env-set expects key=value"),
])
def test_bad_input_is_a_clear_error_and_writes_nothing(argv, match, capsys, tmp_path):
    store = str(tmp_path / "runs")
    code, out, err = _run(capsys, *argv, "--store", store)
    assert code == 2
    assert match in err
    assert not os.path.exists(store)


def test_a_task_without_a_demo_is_a_clear_error(capsys, tmp_path, monkeypatch):
    """Every registered task has a demo now: strip pointmass's to see the message."""
    import dataclasses

    from bench import runner
    from tasks.core import make_task
    task = make_task("pointmass")
    bare = dataclasses.replace(task, spec=dataclasses.replace(task.spec, demo=None))
    monkeypatch.setattr(runner, "make_task", lambda name: bare)
    store = str(tmp_path / "runs")
    code, out, err = _run(capsys, "run", "--method", "bc", "--task", "pointmass", "--budget",
                          "5s", "--store", store)
    assert code == 2 and "task 'pointmass' has no demo yet" in err
    assert "ildbench expert demo --task pointmass" in err and not os.path.exists(store)


def test_run_then_leaderboard(capsys, tmp_path):
    store, out_dir = str(tmp_path / "runs"), str(tmp_path / "results")
    args = ["--method", "bc", "--task", "pointmass", "--budget", "60s", "--set", "updates=200",
            "--eval-episodes", "8", "--store", store]
    code, out, _ = _run(capsys, "run", *args)
    assert code == 0 and "ok, final return" in out
    code, out, _ = _run(capsys, "run", *args)
    assert "skipped (finished before), ok" in out
    code, out, _ = _run(capsys, "leaderboard", "--store", store, "--out", out_dir)
    assert code == 0 and "| pointmass | bc" in out.replace("  ", " ").replace("  ", " ")
    assert os.path.exists(os.path.join(out_dir, "leaderboard.csv"))
    code, out, _ = _run(capsys, "sweep", "--methods", "bc", "--tasks", "pointmass", "--seeds",
                        "2", "--dry-run", "--budget", "60s", "--set", "updates=200",
                        "--eval-episodes", "8", "--store", store)
    assert "plan: 2 cells, 1 finished, 1 to run" in out
    lines = [l for l in out.splitlines() if "pointmass" in l]
    assert len(lines) == 2 and lines[0].endswith("done") and lines[1].endswith("to run")
    # without --out, a store 'X/runs' reports into X (here tmp_path), never into results/
    code, out, _ = _run(capsys, "leaderboard", "--store", store)
    assert code == 0 and f"written: {tmp_path / 'leaderboard.md'}" in out


def test_default_report_folder_follows_the_store():
    from bench.cli import default_out
    assert default_out("results/grid/runs") == "results/grid"
    assert default_out("results/grid/runs/") == "results/grid"
    assert default_out("runs") == "results"
    assert default_out("/tmp/mystore") == "/tmp/mystore_report"
    assert default_out("results/tradeoff/budget_runs/") == "results/tradeoff/budget_runs_report"
    assert default_out("mystore") == "mystore_report"


def test_listing_commands(capsys):
    code, out, _ = _run(capsys, "methods")
    assert code == 0 and "bc" in out and "demo states, demo actions" in out
    code, out, _ = _run(capsys, "tasks")
    assert code == 0 and "pointmass" in out and "acrobot" in out


def test_quick_uses_the_cpu_preset_where_a_method_has_one(monkeypatch):
    from bench import plugins
    from bench.cli import build_parser, cmd_quick
    seen = {}
    monkeypatch.setattr("bench.cli.cmd_sweep", lambda args: seen.update(
        workers=args.workers, reqs=__import__("bench.cli", fromlist=["_requests"])._requests(
            args, args.methods, args.tasks, [0])) or 0)
    monkeypatch.setattr("bench.cli.starved_note", lambda *a: "")
    cmd_quick(build_parser().parse_args(["quick", "--store", "unused"]))
    presets = {r.method: r.preset for r in seen["reqs"]}
    assert presets["ild"] == "cpu" and presets["bc"] == "cpu"
    assert {r.task for r in seen["reqs"]} == {"pointmass", "inverted_pendulum"}
    assert {r.budget.seconds for r in seen["reqs"]} == {40.0}
    assert seen["workers"] == len(os.sched_getaffinity(0))  # one cell per usable CPU
    assert plugins.get_method("ild").presets["cpu"]["num_envs"] == 32


def test_quick_note_names_the_methods_starved_at_its_budget(tmp_path):
    """Under quick's table: a method whose cells here simulated fewer env steps than its
    declared minimum is named with the median it got; one without a minimum, or above it,
    is not."""
    from bench.cli import starved_note
    from bench.plugins import get_method
    from bench.store import Store
    store = Store(str(tmp_path))
    for i, (m, steps) in enumerate([("dac", 5000), ("dac", 7000), ("bc", 0), ("ild", 10**6)]):
        store.write({"run_id": f"r{i}", "method": m, "task": "pointmass", "status": "ok",
                     "env_steps": steps})
    note = starved_note(str(tmp_path), [get_method(m) for m in ("dac", "bc", "ild")],
                        ["pointmass"])
    assert "dac: about 6,000 env steps per cell here; its paper trains for 1,000,000" in note
    assert "bc:" not in note and "ild:" not in note
    assert starved_note(str(tmp_path), [get_method("bc")], ["pointmass"]) == ""


@pytest.mark.parametrize("module", ["bench.sweep", "bench.cli", "benchmarks.ild_speed",
                                    "methods.common.policy"])
def test_importing_the_harness_prints_no_third_party_noise(module):
    """Neither mujoco's "Failed to import warp" (printed at import when the optional warp
    package is absent) nor brax's maintenance warning reaches a run's output, whichever of
    the harness's entry modules a process imports first (`bench.sweep` is a spawned cell's)."""
    import subprocess
    import sys
    out = subprocess.run([sys.executable, "-c", f"import {module}, tasks; "
                          "tasks.make_task('hopper')"], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0, out.stderr
    assert "warp" not in out.stdout + out.stderr
    assert "Brax System" not in out.stdout + out.stderr


def test_the_command_line_starts_without_the_simulation_stack():
    """`ildbench` re-executes itself once before it parses anything (bench.malloc), so what
    importing `bench.cli` loads is paid twice by every command, `--help` included: neither
    JAX nor brax is among it."""
    import subprocess
    import sys
    out = subprocess.run([sys.executable, "-c", "import sys, bench.cli; "
                          "print(sorted({m.split('.')[0] for m in sys.modules} & "
                          "{'jax', 'brax', 'mujoco', 'torch'}))"],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_a_tuning_sweep_refuses_reporting_seeds_and_runs_on_tuning_seeds(capsys, tmp_path):
    """Fault it catches: a sweep marked --tune that runs on seeds 0..N-1, the seeds the tables
    report, so a setting chosen by score is scored on the seeds it was chosen on."""
    base = ("sweep", "--methods", "bc", "--tasks", "pointmass", "--budget", "60s", "--tune",
            "--dry-run", "--store", str(tmp_path / "runs"))
    code, _, err = _run(capsys, *base, "--seeds", "2", "--seed-start", "99")
    assert code == 2 and "seeds [99] are reporting seeds" in err and "--seed-start 100" in err
    code, out, _ = _run(capsys, *base, "--seeds", "2", "--seed-start", "100")
    assert code == 0 and "plan: 2 cells" in out and "seed 100" in out and "seed 101" in out
