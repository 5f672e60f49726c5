"""The CI regression gate: tolerance arithmetic, and a planted regression that must fail."""
import json

import pytest

from bench import check


def _ref(mean, std=0.0, n=2):
    return {"mean": mean, "std": std, "n": n, "scores": []}


def test_compare_tolerances_hand_values():
    ref = {"a/x": _ref(0.9), "b/x": _ref(0.8, std=0.1, n=4), "c/x": _ref(0.5)}
    now = {"a/x": _ref(0.86), "b/x": _ref(0.66), "c/x": {"mean": None, "scores": [None, 0.5]}}
    v = {x.key: x for x in check.compare(ref, now, abs_tol=0.05, z=3)}
    assert v["a/x"].passed and v["a/x"].tolerance == 0.05          # -0.04 within 0.05
    assert v["b/x"].tolerance == pytest.approx(0.15)               # 3 * 0.1 / sqrt(4)
    assert v["b/x"].passed                                         # -0.14 within 0.15
    assert not v["c/x"].passed and "failed or diverged" in v["c/x"].why
    v = {x.key: x for x in check.compare(ref, {**now, "a/x": _ref(0.84)}, 0.05, 3)}
    assert not v["a/x"].passed and "dropped 0.060 > tolerance 0.050" in v["a/x"].why
    v = {x.key: x for x in check.compare({"a/x": _ref(0.9)}, {"a/x": _ref(1.0),
                                                               "n/x": _ref(0.1)})}
    assert v["a/x"].passed and v["n/x"].passed and "no reference yet" in v["n/x"].why
    v = check.compare({"a/x": {**_ref(0.9), "canary": {"env_steps": 8}}},
                      {"a/x": {**_ref(0.95), "canary": {"env_steps": 4}}})
    assert not v[0].passed and "canary changed since its reference" in v[0].why
    v = check.compare({"a/x": _ref(0.9)}, {})
    assert not v[0].passed and "missing" in v[0].why
    table = check.render(check.compare(ref, now))
    a_line = next(l for l in table.splitlines() if l.startswith("a/x"))
    assert "0.900" in a_line and "0.860" in a_line and "-0.040" in a_line and "PASS" in a_line
    assert "FAIL" in next(l for l in table.splitlines() if l.startswith("c/x"))


def test_summarize_mean_std_and_failed_runs():
    s = check.summarize({"a/x": [0.5, 0.7], "b/x": [0.5, None]})
    assert s["a/x"]["mean"] == pytest.approx(0.6) and s["a/x"]["std"] == pytest.approx(0.1414213562)
    assert s["b/x"]["mean"] is None and s["b/x"]["scores"] == [0.5, None]


def test_summarize_gives_one_seed_and_a_failed_seed_std_zero_and_counts_the_seeds():
    """Hand values. Planted faults: a std taken over one seed (NaN, ddof=1) or over a run
    that diverged (NaN); the seed count stored under another key (compare reads `n`)."""
    s = check.summarize({"one": [0.7], "two": [0.5, None], "three": [0.1, 0.2, 0.6]})
    assert s["one"] == {"scores": [0.7], "mean": 0.7, "std": 0.0, "n": 1}
    assert s["two"] == {"scores": [0.5, None], "mean": None, "std": 0.0, "n": 2}
    assert s["three"]["n"] == 3 and s["three"]["mean"] == pytest.approx(0.3)
    assert s["three"]["std"] == pytest.approx(0.2645751311)       # sqrt(0.14 / 2)


def test_compare_reads_a_reference_without_a_seed_count_as_one_seed():
    """A reference written without `n` widens its band by the full std (n = 1): 3 * 0.1.
    Planted fault: the default count dropped (max(None, 1) raises)."""
    ref = {"a/x": {"mean": 0.9, "std": 0.1, "scores": [0.8, 1.0]}}
    v = check.compare(ref, {"a/x": _ref(0.65)}, abs_tol=0.05, z=3)[0]
    assert v.tolerance == pytest.approx(0.3) and v.passed


def test_a_failed_canary_names_its_seeds_scores_and_the_table_reads_as_written():
    """The verdict of a canary with a failed seed lists the seeds' scores; the rendered
    table, hand-written here, is what CI prints. Planted faults: the scores left out of the
    reason; a header or PASS/FAIL word changed."""
    ref = {"a/x": _ref(0.9), "c/x": _ref(0.5)}
    now = {"a/x": _ref(0.86), "c/x": {"mean": None, "scores": [None, 0.5]}}
    verdicts = check.compare(ref, now, abs_tol=0.05, z=3)
    assert verdicts[1].why == "a run failed or diverged: [None, 0.5]"
    assert check.render(verdicts).splitlines() == [
        "canary                       reference     now   delta    tol  result",
        "a/x                              0.900   0.860  -0.040  0.050  PASS: ok",
        "c/x                              0.500       -       -  0.050  FAIL: a run failed or "
        "diverged: [None, 0.5]"]


def test_gate_passes_unchanged_and_fails_a_planted_regression(tmp_path):
    bc = [c for c in check.default_suite().canaries if c.key == "bc/pointmass"]
    ref = tmp_path / "reference.json"
    ok, report = check.check(str(ref), update=True, suite=bc, log=lambda s: None)
    written = json.loads(ref.read_text())
    head, body = report.split("\n", 1)
    assert ok and head == f"reference written: {ref}" and json.loads(body) == written["canaries"]
    assert body == json.dumps(json.loads(body), indent=1)      # printed one space per level
    with open(check.REFERENCE) as f:   # the committed reference is what --update writes
        assert written["about"] == json.load(f)["about"]
    ok, report = check.check(str(ref), suite=bc, log=lambda s: None)
    assert ok and "PASS" in report and "bc/pointmass" in report
    assert report.endswith("\n\ncanary gate: PASS")
    # the suite's z widens the band: tol = max(tolerance, z * std / sqrt(n)), hand-computed
    # from the reference (planted fault: the suite's z not passed on, the default 3 used)
    r = written["canaries"]["bc/pointmass"]
    assert r["std"] > 0 and r["n"] == 2
    ok, report = check.check(str(ref), suite=check.Suite(tuple(bc), z=1000.0),
                             log=lambda s: None)
    line = next(l for l in report.splitlines() if l.startswith("bc/pointmass"))
    assert f"{max(bc[0].tolerance, 1000.0 * r['std'] / 2 ** 0.5):6.3f}  PASS" in line
    # planted regression: BC trained for 1 update instead of 300 (near-random policy)
    ok, report = check.check(str(ref), suite=bc, extra={"bc/pointmass": {"updates": 1}},
                             log=lambda s: None)
    assert not ok
    line = next(l for l in report.splitlines() if l.startswith("bc/pointmass"))
    assert "FAIL: dropped" in line and "canary gate: FAIL" in report
    # a canary whose budget changed since the reference was written is not compared with it
    changed = [check.Canary("bc", "pointmass", 1, (("updates", 299),))]
    ok, report = check.check(str(ref), suite=changed, log=lambda s: None)
    line = next(l for l in report.splitlines() if l.startswith("bc/pointmass"))
    assert not ok and "canary changed since its reference" in line
    assert "'updates': 300" in line and "'updates': 299" in line and "--update" in line


def test_committed_reference_covers_the_suite():
    data = json.load(open(check.REFERENCE))
    suite = check.default_suite().canaries
    assert set(data["canaries"]) == {c.key for c in suite}
    assert all(v["mean"] is not None and v["n"] == len(check.SEEDS)
               for v in data["canaries"].values())
    # the reference was measured with the suite's budgets and overrides as they are now
    assert {c.key: c.definition for c in suite} == {
        k: v["canary"] for k, v in data["canaries"].items()}


def test_bad_reference_file_is_a_clear_error(tmp_path, capsys):
    bad = tmp_path / "ref.json"
    bad.write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        check.load_reference(str(bad))
    with pytest.raises(FileNotFoundError, match="ildbench check --update"):
        check.load_reference(str(tmp_path / "none.json"))


def test_canary_definition_reads_as_its_stored_json():
    """The definition stored beside a reference compares equal after a JSON round trip, so
    a tuple-valued override does not fail the gate as 'changed' forever."""
    c = check.Canary("ild", "pointmass", 10, (("hidden", (64, 64)), ("num_envs", 8)))
    assert c.definition == {"env_steps": 10, "overrides": {"hidden": [64, 64], "num_envs": 8},
                            "seeds": [0, 1], "eval_episodes": 16}
    assert json.loads(json.dumps(c.definition)) == c.definition


SUITE = '''seeds = [0, 1]
tolerance = 0.1

[[canary]]
method = "bc"
task = "pointmass"
env_steps = 1
overrides = { updates = 300 }

[[canary]]
name = "bc-short"
method = "bc"
task = "pointmass"
env_steps = 1
overrides = { updates = 1 }
seeds = [3]
tolerance = 0.2
'''


def _suite(tmp_path, text, name="suite.toml"):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


def test_a_suite_file_sets_each_canarys_budget_overrides_seeds_and_tolerance(tmp_path):
    s = check.load_suite(_suite(tmp_path, SUITE))
    a, b = s.canaries
    assert (a.key, a.env_steps, a.overrides, a.seeds, a.tolerance, a.eval_episodes) == (
        "bc/pointmass", 1, (("updates", 300),), (0, 1), 0.1, 16)
    assert (b.key, b.overrides, b.seeds, b.tolerance) == ("bc-short", (("updates", 1),),
                                                          (3,), 0.2)
    reqs = check.requests(s.canaries)
    assert [(k, r.seed, r.overrides["updates"]) for k, r in reqs] == [
        ("bc/pointmass", 0, 300), ("bc/pointmass", 1, 300), ("bc-short", 3, 1)]
    assert all(r.budget.env_steps == 1 and r.eval.num_episodes == 16 for _, r in reqs)
    # per-canary tolerance: a drop of 0.15 fails at 0.1, passes at 0.2
    v = {x.key: x for x in check.compare(
        {"bc/pointmass": _ref(0.9), "bc-short": _ref(0.9)},
        {"bc/pointmass": _ref(0.75), "bc-short": _ref(0.75)},
        tolerances={c.key: c.tolerance for c in s.canaries})}
    assert not v["bc/pointmass"].passed and v["bc-short"].passed


_ONE = "[[canary]]\nmethod = 'bc'\ntask = 'pointmass'\nenv_steps = 1\n"


@pytest.mark.parametrize("text, message", [
    ("[[canary]]\nmethod = 'nope'\ntask = 'pointmass'\nenv_steps = 5\n",
     "line 1 ([[canary]] 1): unknown method 'nope'"),
    ("seeds = [0]\n\n[[canary]]\nmethod = 'bc'\ntask = 'mars'\nenv_steps = 5\n",
     "line 3 ([[canary]] 1): unknown task 'mars'; valid tasks: acrobot"),
    ("[[canary]]\nmethod = 'bc'\ntask = 'pointmass'\nenv_steps = 0\n",
     "env_steps must be a whole number >= 1, got 0"),
    ("[[canary]]\nmethod = 'bc'\ntask = 'pointmass'\nenv_steps = 1.5\n",
     "env_steps must be a whole number >= 1, got 1.5"),
    ("[[canary]]\nmethod = 'bc'\ntask = 'pointmass'\n", "missing env_steps"),
    ("[[canary]]\nmethod = 'bc'\ntask = 'pointmass'\nenv_steps = 1\n"
     "overrides = { lr = 1 }\n", "has no config field 'lr'"),
    ("[[canary]]\nmethod = 'bc'\ntask = 'pointmass'\nenv_steps = 1\nbudget = 3\n",
     "unknown key(s) ['budget']"),
    ("[[canary]]\nmethod = 'bc'\ntask = 'pointmass'\nenv_steps = 1\nseeds = []\n",
     "seeds must be a non-empty list"),
    ("[[canary]]\nmethod = 'bc'\ntask = 'pointmass'\nenv_steps = 1\n\n"
     "[[canary]]\nmethod = 'bc'\ntask = 'pointmass'\nenv_steps = 2\n",
     "line 6 ([[canary]] 2): canary 'bc/pointmass' is already defined at"),
    ("seeds = [0\n", "not valid TOML"),
    ("seeds = [0]\n", "no canaries"),
    ("canary = 3\n", "no canaries"),
    ("eval_episodes = 2.5\n" + _ONE, "suite.toml: eval_episodes must be a whole number >= 1, "
     "got 2.5"),
    ("tolerance = -1\n" + _ONE, "suite.toml: tolerance must be a number >= 0, got -1"),
    ("z = -0.5\n" + _ONE, "suite.toml: z must be a number >= 0, got -0.5"),
    (_ONE + "eval_episodes = 0\n", "suite.toml line 1 ([[canary]] 1): eval_episodes must be a "
     "whole number >= 1, got 0"),
])
def test_a_malformed_suite_names_the_line_and_the_fix(tmp_path, text, message):
    with pytest.raises(check.SuiteError) as e:
        check.load_suite(_suite(tmp_path, text))
    assert message in str(e.value) and "suite.toml" in str(e.value)


def test_the_cli_refuses_a_bad_suite_or_a_missing_reference_before_any_run(tmp_path, capsys):
    from bench.cli import main
    bad = _suite(tmp_path, "[[canary]]\nmethod = 'bc'\ntask = 'mars'\nenv_steps = 1\n")
    assert main(["check", "--suite", bad]) == 2
    assert "unknown task 'mars'" in capsys.readouterr().err
    assert main(["check", "--suite", str(tmp_path / "absent.toml")]) == 2
    assert "no canary suite at" in capsys.readouterr().err
    good = _suite(tmp_path, SUITE)
    assert main(["check", "--suite", good]) == 2          # no suite_reference.json yet
    err = capsys.readouterr().err
    assert "no canary reference at" in err and "suite_reference.json" in err
    assert f"ildbench check --suite {good} --reference" in err and "--update" in err
