"""The ILD paper's reported numbers (returns, not normalized), shown beside ours.

Table 2 (one demonstration; Brax tasks; MuJoCo-free): DAC, PWIL, ILD and the expert.
Table 3 (ablations, ILD): loss, truncation length, deviation factor, on four tasks.
Source: ../shared/reference/ild_paper.md (section 4.1 and 4.3).
"""
from __future__ import annotations

TABLE2: dict[str, dict[str, float]] = {
    "ant": {"dac": 393.57, "pwil": -1.98, "ild": 594.88, "expert": 624.34},
    "hopper": {"dac": 220.54, "pwil": 205.72, "ild": 243.93, "expert": 292.83},
    "humanoid": {"dac": 256.63, "pwil": 722.41, "ild": 736.87, "expert": 933.24},
    "reacher": {"dac": -21.52, "pwil": -47.19, "ild": -22.86, "expert": -22.49},
    "walker2d": {"dac": 93.19, "pwil": 205.78, "ild": 214.17, "expert": 289.14},
    "swimmer": {"dac": 4.52, "pwil": 1.98, "ild": 4.54, "expert": 4.29},
    "inverted_pendulum": {"dac": 128.00, "pwil": 128.00, "ild": 128.00, "expert": 128.00},
    "acrobot": {"dac": 185.26, "pwil": 157.03, "ild": 202.74, "expert": 200.80},
}

# Table 3: columns are the ablated setting; the paper's default is Chamfer-alpha, truncation
# 10, deviation factor 0.2 for the ablation rows (its Table 2 used factor 1).
TABLE3: dict[str, dict[str, float]] = {
    "ant": {"chamfer": 583.77, "l2": 514.07, "trunc1": 110.07, "trunc10": 583.77,
            "trunc30": -15.50, "trunc100": -16.29, "dev0": 560.95, "dev0.2": 583.77,
            "dev1": 594.88, "dev5": 552.25},
    "hopper": {"chamfer": 242.27, "l2": 173.39, "trunc1": 53.45, "trunc10": 242.27,
               "trunc30": 217.87, "trunc100": 144.95, "dev0": 239.96, "dev0.2": 242.27,
               "dev1": 243.93, "dev5": 248.76},
    "humanoid": {"chamfer": 715.14, "l2": 542.94, "trunc1": 331.27, "trunc10": 715.14,
                 "trunc30": 788.84, "trunc100": 355.09, "dev0": 704.96, "dev0.2": 715.14,
                 "dev1": 736.87, "dev5": 710.12},
    "reacher": {"chamfer": -23.18, "l2": -22.02, "trunc1": -31.72, "trunc10": -23.18,
                "trunc30": -23.24, "trunc100": -21.99, "dev0": -75.36, "dev0.2": -23.18,
                "dev1": -22.86, "dev5": -22.95},
}


def paper_return(task: str, method: str) -> float | None:
    return TABLE2.get(task, {}).get(method)


COMPARED = ("ild", "dac", "pwil")
SAME_WITHIN = 0.01
"""Two methods tie on a task when their scores differ by at most this fraction of the
expert's: 1% of the paper's expert return in Table 2, 0.01 normalized in ours."""


def paper_ratio(task: str, method: str) -> float | None:
    """The paper's Table 2 return of `method` over its expert's return on `task`."""
    ret, expert = paper_return(task, method), paper_return(task, "expert")
    return None if ret is None or not expert else ret / expert


def ordering(scores: dict[str, float], tie: float) -> list[list[str]]:
    """Methods from best to worst, as groups of methods that tie (a chain of neighbours each
    within `tie` of the next forms one group)."""
    ranked = sorted(scores, key=lambda m: (-scores[m], m))
    groups: list[list[str]] = []
    for m in ranked:
        if groups and scores[groups[-1][-1]] - scores[m] <= tie:
            groups[-1].append(m)
        else:
            groups.append([m])
    return groups


def _relations(groups: list[list[str]]) -> dict[tuple[str, str], str]:
    rank = {m: i for i, g in enumerate(groups) for m in g}
    return {(a, b): ">" if rank[a] < rank[b] else ("=" if rank[a] == rank[b] else "<")
            for a in rank for b in rank if a < b}


def _describe(groups: list[list[str]]) -> str:
    return " > ".join(" = ".join(g) for g in groups)


def comparison(scores: dict[str, dict[str, float]]) -> list[dict]:
    """Rows of the paper comparison from our mean normalized scores {task: {method: score}}:
    per task of Table 2, our score and the paper's return ratio for each compared method we
    have, both orderings (higher return is better; ties within SAME_WITHIN of the expert),
    and how many method pairs the two orderings agree on. The paper's returns are ordered,
    not its ratios, so reacher's negative returns order the right way round."""
    rows = []
    for task in sorted(scores):
        if task not in TABLE2:
            continue
        ours = {m: v for m, v in scores[task].items() if m in COMPARED and v == v}
        if len(ours) < 2:
            continue
        expert = abs(TABLE2[task]["expert"])
        paper = {m: TABLE2[task][m] / expert for m in ours}  # same order as the returns
        mine, theirs = ordering(ours, SAME_WITHIN), ordering(paper, SAME_WITHIN)
        rel_ours, rel_paper = _relations(mine), _relations(theirs)
        agree = sum(rel_ours[k] == rel_paper[k] for k in rel_ours)
        row = {"task": task}
        for m in COMPARED:
            row[f"ours_{m}"] = ours.get(m)
            row[f"paper_{m}"] = paper_ratio(task, m) if m in ours else None
        row.update({"ours_order": _describe(mine), "paper_order": _describe(theirs),
                    "pairs_agreeing": f"{agree}/{len(rel_ours)}",
                    "agrees": "yes" if agree == len(rel_ours) else "no"})
        rows.append(row)
    return rows


def comparison_markdown(tables: dict[str, list[dict]]) -> str:
    """One table per budget ({budget label: comparison rows})."""
    import pandas as pd
    out = ["# Beside the paper (Table 2, one demonstration)", "",
           "`ours_M`: our mean normalized score (1 = expert, 0 = random policy). `paper_M`: "
           "the paper's return over its expert's return. The orderings rank by score (ours) "
           "and by return (the paper's); two methods tie within 1% of the expert. "
           "`pairs_agreeing`: method pairs ordered the same way in both. On reacher the "
           "returns are negative, so a ratio below 1 there is better than the expert.", ""]
    if not any(tables.values()):
        out.append("_no task with two or more of ILD, DAC and PWIL scored_")
    for label, rows in tables.items():
        if not rows:
            continue
        df = pd.DataFrame(rows)
        agree = int((df.agrees == "yes").sum())
        out += [f"## {label}", "", df.to_markdown(index=False, floatfmt=".3f"), "",
                f"Orderings agreeing on {agree} of {len(df)} tasks.", ""]
    return "\n".join(out) + "\n"
