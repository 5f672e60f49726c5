"""results/substep/scripts/swish_policy.py (session 60) times the rollout's policy alone
with swish_remat off and on. Checked: its rows hold both variants' programs with XLA's
working memory, which swish_remat cuts, and its summary's medians and ratios on hand-made
rows."""
import pytest


@pytest.fixture(scope="module")
def swish_policy(substep_script):
    with substep_script("swish_policy") as mod:
        yield mod


def test_rows_time_both_variants_and_remat_keeps_less(swish_policy):
    rows = swish_policy.run("pointmass", batch=4, rounds=1, repeats=1)
    assert {(r["swish_remat"], r["program"]) for r in rows} == {
        (False, "fwd"), (False, "grad"), (True, "fwd"), (True, "grad")}
    mib = {r["swish_remat"]: r["grad_temp_mib"] for r in rows}
    assert 0 < mib[True] < 0.7 * mib[False], mib  # the 512-256 policy's stacked residuals


def test_summary_of_hand_made_rows(swish_policy):
    rows = [{"swish_remat": remat, "program": prog, "seconds": s, "grad_temp_mib": m}
            for remat, m, secs in ((False, 40.0, {"fwd": [1.0, 1.0, 2.0], "grad": [6.0, 5.0, 8.0]}),
                                   (True, 10.0, {"fwd": [1.0, 1.0, 2.0], "grad": [3.0, 4.0, 5.0]}))
            for prog, ss in secs.items() for s in ss]
    lines = swish_policy.summary_lines(rows)
    assert lines[0] == ("swish_remat=False: forward 1.0000 s, gradient 6.0000 s (5.00x its "
                        "forward), working memory 40.0 MiB")
    assert lines[1].startswith("swish_remat=True: forward 1.0000 s, gradient 4.0000 s (3.00x")
    assert lines[2] == "gradient speed-up 1.600x (1.250-2.000) over 3 rounds"
