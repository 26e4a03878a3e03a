"""The paper's published numbers: Table I (training and generalization, 15 seeds x 200 episodes), Table II
(normalised sensitivity of the uncertainties) and Table III (prevented collisions), and the budget of Table I.

Reports set them next to ours, each value once. The paper's safety thresholds are
`socnav.safety.rule.THRESHOLD_PRESETS`.
"""

from __future__ import annotations

import math

import pandas as pd

from socnav.paper.labels import PAPER_COLUMN

__all__ = [
    "PAPER_BUDGET", "PAPER_TABLE1_ROWS", "PAPER_TABLE2", "PAPER_TABLE3", "paper_table1", "paper_table2", "paper_table3",
]

#: The paper's Table I, one line per (training scenario, algorithm): per evaluation scenario (circle interaction |
#: circle crossing | random) goal %, collision %, time-out %, PV, return mean and std.
PAPER_TABLE1_ROWS = """
circle_interaction ppo            99.80 0.20 0.00 7 4.50 0.46 | 93.30 4.37 2.33 169 3.66 2.09 | 76.80 4.70 18.50 43 2.63 3.63
circle_interaction ppo-drop       99.90 0.10 0.00 8 4.66 0.42 | 94.40 3.83 1.77 200 3.92 2.01 | 78.70 5.40 15.90 57 2.93 3.65
circle_interaction odv-ppo-noloss 99.47 0.53 0.00 18 4.25 0.65 | 88.57 8.73 2.70 195 2.94 2.64 | 79.27 7.37 13.37 69 2.22 3.59
circle_interaction odv-ppo        99.23 0.77 0.00 17 4.29 0.78 | 89.93 7.80 2.57 225 3.12 2.55 | 77.77 7.50 14.73 80 2.15 3.79
circle_interaction odv-ppo-drop   99.90 0.10 0.00 1 4.52 0.36 | 96.87 2.47 0.67 101 4.04 1.45 | 82.00 4.50 13.50 40 3.02 3.39
circle_crossing ppo               49.57 12.20 38.23 101 -1.25 5.16 | 86.10 7.07 6.83 52 2.17 3.49 | 58.90 7.83 33.27 90 -0.57 5.39
circle_crossing ppo-drop          87.80 1.13 11.07 53 3.15 2.78 | 98.13 1.57 0.30 64 3.91 1.24 | 82.33 4.07 13.60 53 2.71 3.61
circle_crossing odv-ppo-noloss    41.57 9.43 49.00 147 -2.28 4.98 | 71.47 2.03 26.50 63 0.83 4.45 | 40.80 8.63 50.57 95 -2.74 5.30
circle_crossing odv-ppo           38.37 6.67 54.97 76 -2.24 5.42 | 58.90 8.70 32.40 87 0.18 4.84 | 39.60 7.17 53.23 66 -2.51 5.87
circle_crossing odv-ppo-drop      92.90 0.67 6.43 21 3.78 2.35 | 99.10 0.83 0.07 35 4.22 0.88 | 88.07 2.10 9.83 49 3.46 3.14
random ppo                        68.03 5.60 26.37 159 1.36 4.39 | 68.40 8.60 23.00 179 1.15 4.12 | 80.40 2.37 17.23 66 2.44 3.80
random ppo-drop                   91.67 2.43 5.90 67 3.40 2.59 | 86.70 8.13 5.17 219 2.76 3.12 | 90.20 3.30 6.50 64 3.28 2.86
random odv-ppo-noloss             0.00 0.37 99.63 11 -6.53 0.37 | 0.00 0.10 99.90 11 -6.54 0.71 | 0.00 0.10 99.90 6 -6.39 0.80
random odv-ppo                    58.50 2.20 39.30 73 0.19 4.81 | 53.53 3.30 43.17 112 -0.26 4.62 | 59.53 1.17 39.30 47 0.36 4.80
random odv-ppo-drop               99.53 0.30 0.17 8 4.33 0.74 | 97.53 2.43 0.03 77 4.04 1.33 | 99.43 0.47 0.10 14 4.39 0.83
"""  # noqa: E501

#: The budget of the paper's Table I (configs/experiments/table1.yaml, budget `paper`).
PAPER_BUDGET = {"timesteps": 1_000_000, "seeds": 15, "episodes": 200}

#: The paper's Table II: uncertainty -> paper column -> (MC-dropout, ensemble).
PAPER_TABLE2 = {
    "u_feat": {"obs": (1.84, 0.11), "action": (0.87, 0.03), "velocity": (0.20, 0.0), "humans": (0.65, 0.38)},
    "u_al_heading": {"obs": (0.57, 0.28), "action": (0.22, 0.26), "velocity": (0.04, 0.0), "humans": (0.90, 0.47)},
    "u_ep_heading": {"obs": (2.00, 0.18), "action": (0.67, 0.16), "velocity": (0.25, 0.0), "humans": (1.99, 0.82)},
    "u_al_speed": {"obs": (0.71, 0.19), "action": (0.31, 0.18), "velocity": (0.03, 0.0), "humans": (0.49, 0.17)},
    "u_ep_speed": {"obs": (4.08, 0.49), "action": (1.46, 0.64), "velocity": (0.39, 0.02), "humans": (3.01, 0.30)},
}
#: The paper's Table III: paper column -> estimator -> (mean, std) of prevented collisions (%).
PAPER_TABLE3 = {"obs": {"mc": (100.0, 0.0), "ensemble": (79.0, 11.0)},
          "action": {"mc": (6.0, 5.0), "ensemble": (0.0, 0.0)},
          "velocity": {"mc": (56.0, 2.0), "ensemble": (16.0, 1.0)},
          "humans": {"mc": (81.0, 8.0), "ensemble": (59.0, 13.0)}}


def paper_table1() -> pd.DataFrame:
    """The paper's Table I (15 seeds x 200 episodes), in the long form of `socnav.paper.table1.tables.table1_frame`
    (returns are the paper's reward instantiation: compare orderings, not absolute values)."""
    rows = []
    evals = ["circle_interaction", "circle_crossing", "random"]
    for line in PAPER_TABLE1_ROWS.strip().splitlines():
        head, *groups = line.split("|")
        train_scenario, algo, *first = head.split()
        for eval_scenario, values in zip(evals, [first] + [g.split() for g in groups], strict=True):
            goal, collision, timeout, pv, ret, std = map(float, values)
            rows.append({"train_scenario": train_scenario, "algo": algo, "eval_scenario": eval_scenario,
                         "goal_pct": goal, "collision_pct": collision, "timeout_pct": timeout, "pv": pv,
                         "return_mean": ret, "return_std": std})
    return pd.DataFrame(rows)


def paper_table2(uncertainty: str, perturbation: str, estimator: str) -> float:
    """The paper's Table II value for our (uncertainty, perturbation type, estimator), NaN where it has none."""
    column = PAPER_COLUMN.get(perturbation)
    index = {"mc": 0, "ensemble": 1}.get(estimator)
    if column is None or index is None or uncertainty not in PAPER_TABLE2:
        return math.nan
    return PAPER_TABLE2[uncertainty][column][index]


def paper_table3(column: str, estimator: str) -> tuple[float, float]:
    """The paper's Table III (mean, std) for our column (perturbation type or action_noise), NaN where none."""
    entry = PAPER_TABLE3.get(PAPER_COLUMN.get(column) or "", {}).get(estimator)
    return entry if entry is not None else (math.nan, math.nan)
