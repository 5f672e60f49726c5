"""Our scores beside the paper's Table 2: ratios, orderings and their agreement."""
import pytest

from bench import paper


def test_orderings_group_ties_within_the_tolerance():
    assert paper.ordering({"a": 0.9, "b": 0.5, "c": 0.7}, 0.01) == [["a"], ["c"], ["b"]]
    assert paper.ordering({"a": 0.5, "b": 0.505, "c": 0.2}, 0.01) == [["b", "a"], ["c"]]
    # a chain of neighbours within the tolerance is one group
    assert paper.ordering({"a": 0.50, "b": 0.509, "c": 0.518}, 0.01) == [["c", "b", "a"]]


def test_paper_ratios_are_returns_over_the_expert_return():
    assert paper.paper_ratio("hopper", "ild") == pytest.approx(243.93 / 292.83)
    assert paper.paper_ratio("reacher", "dac") == pytest.approx(-21.52 / -22.49)
    assert paper.paper_ratio("pointmass", "ild") is None


def test_the_comparison_orders_by_return_and_counts_agreeing_pairs():
    rows = {r["task"]: r for r in paper.comparison({
        "hopper": {"ild": 0.9, "dac": 0.6, "pwil": 0.3, "bc": 1.0},   # paper: ild>dac>pwil
        # the paper's returns are negative here: dac (-21.52) > ild (-22.86) > pwil
        "reacher": {"ild": 0.95, "dac": 0.90, "pwil": 0.2},
        "inverted_pendulum": {"ild": 1.0, "dac": 0.8},                  # paper: all 128
        "swimmer": {"ild": 0.7},                                        # one method: no row
        "pointmass": {"ild": 1.0, "dac": 0.5}})}                        # not in Table 2
    assert set(rows) == {"hopper", "reacher", "inverted_pendulum"}
    h = rows["hopper"]
    assert (h["ours_order"], h["paper_order"]) == ("ild > dac > pwil", "ild > dac > pwil")
    assert (h["pairs_agreeing"], h["agrees"]) == ("3/3", "yes")
    assert h["paper_dac"] == pytest.approx(220.54 / 292.83) and h["ours_pwil"] == 0.3
    r = rows["reacher"]
    assert r["paper_order"] == "dac > ild > pwil"
    assert (r["pairs_agreeing"], r["agrees"]) == ("2/3", "no")        # ild vs dac flips
    ip = rows["inverted_pendulum"]
    assert (ip["paper_order"], ip["ours_order"]) == ("dac = ild", "ild > dac")
    assert (ip["pairs_agreeing"], ip["agrees"]) == ("0/1", "no")
    assert ip["ours_pwil"] is None and ip["paper_pwil"] is None


def test_the_markdown_has_one_table_per_budget_and_counts_the_agreeing_tasks():
    rows = paper.comparison({"hopper": {"ild": 0.9, "dac": 0.6},
                             "ant": {"ild": 0.2, "dac": 0.6}})
    md = paper.comparison_markdown({"180s of training (wall-clock)": rows, "empty": []})
    assert "## 180s of training (wall-clock)" in md and "## empty" not in md
    assert "Orderings agreeing on 1 of 2 tasks." in md
