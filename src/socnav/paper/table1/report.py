"""The report page of Table 1's experiments (kind ``table1``): its sections in page order.

Table 1 metrics, per (training scenario, algorithm, evaluation scenario), each the mean over seeds of the per-seed
value computed from that seed's test episodes:
Goal %, Col. %, TO %  -- share of episodes ending at the goal / in a collision / in a time-out;
PV                    -- personal-space violations (intrusion events: entering a human's personal space) per 200
                         episodes;
Return                -- mean over seeds of the per-seed mean episode return, +- the standard deviation over all
                         test episodes of all seeds (population std, ddof=0: the spread a user sees per episode).
The CSV adds ``return_seed_std`` (std over seeds of the per-seed mean return) and the seed / episode counts.

Statistics (:mod:`socnav.experiments.statistics`): a trained policy (training scenario, algorithm, seed) is one unit
in every evaluation cell it appears in, and every verdict comes from a test that keeps its error rate at 3 seeds.
``table1_ci.md/csv``: per cell and metric the mean over seeds with a 95 % Student t-interval over seeds (descriptive,
not adjusted for the number of cells). ``aggregate.png/svg/csv``: per algorithm the IQM of the goal rate over
policies x cells with a cluster-bootstrap interval (policies resampled within training scenarios; descriptive).
``comparisons.csv``: ODV-PPO-Drop against each other algorithm on the goal rate over all cells, one family: stratified
Welch t-test on per-policy means (strata: training scenarios), intervals at the Bonferroni level, verdicts by Holm
(holds / does not hold / cannot tell at this budget), and the probability of improvement (descriptive).
``claims.md/csv``: the paper's Table 1 claims (dropout improves PPO; ODV without the variance loss fails to converge
in random; ODV-PPO-Drop generalizes best; circle-interaction training converges fastest with the lowest variance
across seeds), one family, with the statistic, test, estimate, adjusted interval, Holm p-value and verdict of each
part (`socnav.paper.table1.claims.claims_frame`); ``training_runs.csv``: the per-run training-curve statistics they read
(`socnav.paper.table1.claims.training_run_frame`).
"""

from __future__ import annotations

from socnav.experiments.registry import Section, register_section
from socnav.paper.table1.claims import claims_section
from socnav.paper.table1.comparison import paper_comparison_section
from socnav.paper.table1.curves import training_curves_section
from socnav.paper.table1.intervals import table1_ci_section
from socnav.paper.table1.tables import table1_section

__all__ = ["KIND", "PAGE"]

KIND = "table1"

#: The report page of the kind: (section name, section), in page order.
PAGE: list[tuple[str, Section]] = [
    ("table1", table1_section),
    ("table1_ci", table1_ci_section),
    ("training_curves", training_curves_section),
    ("claims", claims_section),
    ("paper_comparison", paper_comparison_section),
]

for _name, _section in PAGE:
    register_section(KIND, _name)(_section)
