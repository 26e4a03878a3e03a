"""How large must a difference be for Table 1's verdicts to see it? The smallest goal-rate difference the report's
rule (stratified Welch test on per-policy means, Holm / Bonferroni) calls *holds* with 80 % power, per budget.

    python docs/analysis/power_table.py                          # the documented default seed variation
    python docs/analysis/power_table.py runs/table1-quick        # the seed variation measured in a run

Prints the design's parameters, the false-verdict rate of the rule under the null at each budget (it must stay
<= 5 %), and two Markdown tables. Goal-rate claims: per budget (quick: 3 seeds x 100 episodes, paper: 15 x 200) and
claim shape (all 9 cells, the 6 generalization cells, one cell), the minimum detectable difference in goal-rate
points for one claim and for a table of 10 claims (the claims table; Bonferroni level = Holm's first step),
simulated with socnav.experiments.power (2,000 replicates per power value, bisection to 0.1 points). Training-curve
claims (5 algorithms as strata): the normal-theory difference in between-seed SDs (convergence) and ratio of
variances (spread across seeds). Below those sizes a real difference is mostly reported as *cannot tell at this
budget*. About 10 s on two cores.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from socnav.experiments.power import (
    Design,
    cellwise_bootstrap_verdicts,
    estimate_design,
    false_verdict_rate,
    min_detectable_difference,
    min_detectable_standardised_difference,
    min_detectable_variance_ratio,
)

BUDGETS = {"quick": (3, 100), "paper": (15, 200)}
#: (label, cells a policy contributes, training scenarios): the shapes of Table 1's goal-rate claims.
SHAPES = [("all 9 cells", 3, 3), ("6 generalization cells", 2, 3), ("one cell", 1, 1)]
CLAIMS_IN_TABLE = 10


def seed_variation(run_dir: Path | None) -> Design:
    """The default design, or the one measured from a run's per-seed goal rates."""
    if run_dir is None:
        return Design()
    from socnav.experiments.registry import ReportContext
    from socnav.experiments.runner import read_plan, unit_states
    from socnav.paper.table1.tables import table1_seed_frame

    experiment, units = read_plan(run_dir)
    context = ReportContext(run_dir, run_dir, experiment, units, unit_states(run_dir, units))
    return estimate_design(table1_seed_frame(context.episode_records()))


def points(value: float) -> str:
    return "> base rate" if value != value else f"{value:.1f}"  # NaN: even Y at 0 % is not enough


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run_dir", nargs="?", default=None, help="a Table 1 run to measure the seed variation from")
    parser.add_argument("--replicates", type=int, default=2000)
    args = parser.parse_args()
    measured = seed_variation(Path(args.run_dir) if args.run_dir else None)
    source = f"measured in {args.run_dir}" if args.run_dir else "default (socnav.experiments.power.Design)"
    print(f"Seed variation ({source}): between-seed SD {measured.seed_sd_pct:.2f} points beyond binomial noise, "
          f"correlation between a policy's cells {measured.cell_correlation:.2f}, mean goal rate "
          f"{measured.base_goal_pct:.1f} %, SD of the cells' goal rates {measured.cell_sd_pct:.1f} points.")
    print()
    for name, (seeds, episodes) in BUDGETS.items():
        design = replace(measured, seeds=seeds, episodes=episodes)
        rate = false_verdict_rate(design, replicates=20_000)
        print(f"Null false-verdict rate, {name} ({seeds} seeds, all 9 cells): {rate.rate:.4f} "
              f"[99 % {rate.low:.4f}, {rate.high:.4f}] over {rate.replicates} replicates")
        earlier = false_verdict_rate(design, replicates=1000, decide=cellwise_bootstrap_verdicts)
        print(f"  the earlier rule (percentile bootstrap of seeds within each cell, no adjustment): "
              f"{earlier.rate:.4f} [99 % {earlier.low:.4f}, {earlier.high:.4f}] over {earlier.replicates} replicates")
    print()
    print("| Budget | Seeds × episodes | Claim over | Min. difference, 1 claim (points) | "
          f"Min. difference, {CLAIMS_IN_TABLE} claims (points) |")
    print("|:--|:--|:--|--:|--:|")
    for name, (seeds, episodes) in BUDGETS.items():
        for label, cells, strata in SHAPES:
            design = replace(measured, seeds=seeds, episodes=episodes, cells_per_policy=cells, train_scenarios=strata)
            single = min_detectable_difference(design, replicates=args.replicates, tolerance=0.1)
            family = min_detectable_difference(design, n_claims=CLAIMS_IN_TABLE, replicates=args.replicates,
                                               tolerance=0.1)
            print(f"| {name} | {seeds} × {episodes} | {label} | {points(single)} | {points(family)} |")
    print()
    print("| Budget | Training runs per scenario | Convergence difference, 1 / "
          f"{CLAIMS_IN_TABLE} claims (between-seed SDs) | Variance ratio, 1 / {CLAIMS_IN_TABLE} claims |")
    print("|:--|:--|--:|--:|")
    for name, (seeds, _) in BUDGETS.items():
        curve = [min_detectable_standardised_difference(seeds, n_claims=k) for k in (1, CLAIMS_IN_TABLE)]
        ratio = [min_detectable_variance_ratio(seeds, n_claims=k) for k in (1, CLAIMS_IN_TABLE)]
        print(f"| {name} | 5 algorithms × {seeds} seeds | {curve[0]:.2f} / {curve[1]:.2f} | "
              f"{ratio[0]:.1f} / {ratio[1]:.1f} |")


if __name__ == "__main__":
    main()
