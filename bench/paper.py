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
