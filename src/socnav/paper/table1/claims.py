"""The paper's Table 1 claims, each tested, one family (Holm): dropout improves PPO; ODV without the variance loss
fails to converge in random; ODV-PPO-Drop generalizes best; circle-interaction training converges fastest.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

from socnav.experiments.registry import ReportContext
from socnav.io import write_table_atomic, write_text_atomic
from socnav.paper.labels import algo_label, scenario_label
from socnav.paper.table1.intervals import (
    FAMILY_CONFIDENCE,
    Cell,
    interval_text,
    p_text,
    paired_policy_strata,
    policy_cells,
)
from socnav.paper.table1.tables import table1_seed_frame

if TYPE_CHECKING:
    from socnav.experiments.statistics import VarianceRatioTest, WelchTest


CURVE_VALUE = "ep_rew_mean"
#: A run has converged when its curve first reaches this fraction of the way from its first to its final value.
CONVERGENCE_FRACTION = 0.9
#: The final value of a run: the mean of the last share of its logged points (the plateau, not one noisy point).
FINAL_SHARE = 0.1
TRAINING_RUN_COLUMNS = ["train_scenario", "algo", "seed", "points", "total_steps", "start_reward", "final_reward",
                        "steps_to_converge"]
CLAIM_COLUMNS = ["claim", "part", "statistic", "test", "n_x", "n_y", "estimate", "ci_low", "ci_high", "confidence",
                 "p_value", "p_holm", "verdict", "claim_verdict"]
FAST_SCENARIO = "circle_interaction"


def training_run_frame(curves: pd.DataFrame, value: str = CURVE_VALUE, fraction: float = CONVERGENCE_FRACTION,
                       final_share: float = FINAL_SHARE) -> pd.DataFrame:
    """Per training run (training scenario, algorithm, seed), from its curve of ``value`` vs timesteps (rows with a
    value): ``start_reward`` (the first point), ``final_reward`` (mean of the last ``final_share`` of the points,
    at least one) and ``steps_to_converge``, the first timestep at which the curve reaches
    ``start + fraction (final - start)`` -- the last timestep if the run never improved (final <= start). Scale
    free: every run is measured against its own start and plateau, so scenarios with other reward scales compare."""
    rows = []
    for (scenario, algo, seed), group in curves.groupby(["train_scenario", "algo", "seed"], sort=False):
        points = group.dropna(subset=[value]).sort_values("timesteps")
        steps, values = points["timesteps"].to_numpy(float), points[value].to_numpy(float)
        row = {"train_scenario": scenario, "algo": algo, "seed": seed, "points": len(points),
               "total_steps": steps[-1] if len(steps) else np.nan, "start_reward": np.nan, "final_reward": np.nan,
               "steps_to_converge": np.nan}
        if len(points) >= 2:
            start, final = values[0], values[-max(1, math.ceil(final_share * len(values))):].mean()
            reached = values >= start + fraction * (final - start)
            converged_at = steps[np.argmax(reached)] if final > start else steps[-1]
            row.update(start_reward=start, final_reward=final, steps_to_converge=converged_at)
        rows.append(row)
    return pd.DataFrame(rows, columns=TRAINING_RUN_COLUMNS)


@dataclass
class _Part:
    claim: str
    part: str
    statistic: str
    test: WelchTest | VarianceRatioTest
    n_x: int
    n_y: int


def _goal_part(per_seed: pd.DataFrame, claim: str, part: str, statistic: str, algo_x: str, algo_y: str,
               cells: list[Cell]) -> _Part:
    from socnav.experiments.statistics import welch_test

    evaluated = set(policy_cells(per_seed, algo_x, algo_y))
    cells = [cell for cell in cells if cell in evaluated]
    strata_x, strata_y = paired_policy_strata(per_seed, algo_x, algo_y, cells)
    if not strata_x:
        return _Part(claim, part, statistic, _untestable(), 0, 0)
    return _Part(claim, part, statistic, welch_test(strata_x, strata_y), sum(map(len, strata_x)),
                 sum(map(len, strata_y)))


def _untestable() -> WelchTest:
    from socnav.experiments.statistics import WelchTest

    return WelchTest(np.nan, np.nan, np.nan, np.nan)


def _run_groups(runs: pd.DataFrame, scenario: str, column: str, algorithms: list[str]) -> list[np.ndarray]:
    """``column`` of the runs trained on ``scenario``, one array per algorithm (in ``algorithms`` order)."""
    mine = runs[(runs["train_scenario"] == scenario)].dropna(subset=[column])
    return [mine.loc[mine["algo"] == algo, column].to_numpy(float) for algo in algorithms]


def claims_frame(per_seed: pd.DataFrame, runs: pd.DataFrame, confidence: float = FAMILY_CONFIDENCE
                 ) -> pd.DataFrame:
    """The paper's Table 1 claims, one row per tested part, as one family (Holm verdicts, Bonferroni intervals):

    - *Dropout improves PPO*: PPO-Drop - PPO, goal rate (points) over all cells;
    - *ODV without the variance loss is unstable (fails to converge in the random scenario)*: ODV-PPO - ODV-PPO
      no Loss, goal rate of the policies trained on random, in random;
    - *ODV-PPO-Drop is best in generalization*: ODV-PPO-Drop - each other algorithm, goal rate over the cells with
      training != evaluation scenario;
    - *circle-interaction training converges fastest*: steps to converge (:func:`training_run_frame`, in thousands)
      of each other training scenario - circle interaction's, strata: algorithms;
    - *... with the lowest variance across seeds*: variance over seeds (pooled within algorithms) of the final
      training reward, each other training scenario / circle interaction's (F-test).

    Goal-rate parts: stratified Welch test on per-policy means (``per_seed`` from :func:`table1_seed_frame`); curve
    parts read ``runs`` from :func:`training_run_frame`. A claim with several parts holds if every part holds, does
    not hold if one does not, and otherwise cannot be told.
    """
    from socnav.experiments.statistics import (
        CANNOT_TELL,
        DOES_NOT_HOLD,
        HOLDS,
        adjust_family,
        variance_ratio_test,
        welch_test,
    )

    all_cells = list(dict.fromkeys(map(tuple, per_seed[["train_scenario", "eval_scenario"]].drop_duplicates()
                                       .to_numpy().tolist())))
    off_diagonal = [(train, evaluation) for train, evaluation in all_cells if train != evaluation]
    goal = "goal rate (%)"
    parts = [
        _goal_part(per_seed, "Dropout improves PPO", "PPO-Drop > PPO", f"{goal}, all cells: difference (points)",
                   "ppo-drop", "ppo", all_cells),
        _goal_part(per_seed, "ODV without the variance loss is unstable (fails to converge in the random scenario)",
                   "ODV-PPO > ODV-PPO no Loss, trained and evaluated in Random",
                   f"{goal} in Random of policies trained on Random: difference (points)", "odv-ppo",
                   "odv-ppo-noloss", [("random", "random")]),
    ]
    for baseline in ["ppo", "ppo-drop", "odv-ppo-noloss", "odv-ppo"]:
        parts.append(_goal_part(per_seed, "ODV-PPO-Drop is best in generalization",
                                f"ODV-PPO-Drop > {algo_label(baseline)}",
                                f"{goal}, training ≠ evaluation scenario: difference (points)", "odv-ppo-drop",
                                baseline, off_diagonal))
    algorithms = list(dict.fromkeys(runs["algo"]))
    in_thousands = runs.assign(steps_to_converge=runs["steps_to_converge"] / 1000)
    fast = _run_groups(in_thousands, FAST_SCENARIO, "steps_to_converge", algorithms)
    for other in ["circle_crossing", "random"]:
        slow = _run_groups(in_thousands, other, "steps_to_converge", algorithms)
        # strata: the algorithms with runs in both scenarios (each algorithm is compared with itself)
        both = [(s, f) for s, f in zip(slow, fast, strict=True) if len(s) and len(f)]
        test = welch_test([s for s, _ in both], [f for _, f in both]) if both else _untestable()
        parts.append(_Part("Circle-interaction training converges fastest", f"faster than {scenario_label(other)}",
                           f"steps to {100 * CONVERGENCE_FRACTION:.0f} % of the final training reward (thousands): "
                           f"{scenario_label(other)} − Circle Interaction", test,
                           sum(len(s) for s, _ in both), sum(len(f) for _, f in both)))
    fast = _run_groups(runs, FAST_SCENARIO, "final_reward", algorithms)
    for other in ["circle_crossing", "random"]:
        slow = _run_groups(runs, other, "final_reward", algorithms)
        parts.append(_Part("Circle-interaction training has the lowest variance across seeds",
                           f"lower than {scenario_label(other)}",
                           f"variance over seeds of the final training reward: {scenario_label(other)} / "
                           "Circle Interaction", variance_ratio_test(slow, fast), sum(map(len, slow)),
                           sum(map(len, fast))))

    adjusted = adjust_family([part.test for part in parts], confidence)
    rows: list[dict[str, Any]] = [
        {"claim": part.claim, "part": part.part, "statistic": part.statistic, "test": part.test.method,
         "n_x": part.n_x, "n_y": part.n_y, "estimate": part.test.estimate, "ci_low": result.interval.low,
         "ci_high": result.interval.high, "confidence": result.confidence, "p_value": result.p_value,
         "p_holm": result.p_adjusted, "verdict": result.verdict}
        for part, result in zip(parts, adjusted, strict=True)]
    overall: dict[str, set[str]] = {}
    for row in rows:
        overall.setdefault(row["claim"], set()).add(row["verdict"])
    for row in rows:
        verdicts = overall[row["claim"]]
        row["claim_verdict"] = (DOES_NOT_HOLD if DOES_NOT_HOLD in verdicts
                                else HOLDS if verdicts == {HOLDS} else CANNOT_TELL)
    return pd.DataFrame(rows, columns=CLAIM_COLUMNS)


def _power_note(per_seed: pd.DataFrame, n_claims: int) -> list[str]:
    """What this run could have told (a paragraph and a blank line; nothing without 2+ seeds): the goal-rate
    differences its rule detects with 80 % power at its budget and measured seed variation (simulated,
    :func:`socnav.experiments.power.min_detectable_difference`, at the Bonferroni level: Holm's first step), and the
    normal-theory sizes for the two training-curve claims."""
    from socnav.experiments.power import (
        estimate_design,
        min_detectable_difference,
        min_detectable_standardised_difference,
        min_detectable_variance_ratio,
    )

    try:
        design = estimate_design(per_seed)
    except ValueError:
        return []
    sizes = {}
    for cells, strata in ((3, 3), (2, 3), (1, 1)):
        size = min_detectable_difference(replace(design, cells_per_policy=cells, train_scenarios=strata),
                                         n_claims=n_claims, replicates=1000, tolerance=0.25)
        sizes[cells] = "no difference the base rate allows" if math.isnan(size) else f"about {size:.1f} points"
    ratio = min_detectable_variance_ratio(design.seeds, n_claims=n_claims)
    standardised = min_detectable_standardised_difference(design.seeds, n_claims=n_claims)
    return [
        f"**Power at this budget** ({design.seeds} seeds, {design.episodes} episodes; measured in this run: "
        f"between-seed SD {design.seed_sd_pct:.1f} points beyond the binomial noise, correlation "
        f"{design.cell_correlation:.2f} between a policy's cells, mean goal rate {design.base_goal_pct:.0f} %): in a "
        f"family of {n_claims} claim(s), the rule says *holds* with 80 % power from {sizes[3]} over all cells, "
        f"{sizes[2]} over "
        f"the generalization cells and {sizes[1]} in one cell (simulated); smaller differences are mostly *cannot "
        f"tell*. The convergence parts need about {standardised:.1f} between-seed SDs, the variance parts a ratio "
        f"of about {ratio:.1f} (normal theory; `docs/analysis/power_table.py`).",
        "",
    ]


def claims_section(context: ReportContext) -> str:
    """Table 1's claims, each tested: claims.md/csv, training_runs.csv."""
    per_seed = table1_seed_frame(context.episode_records())
    runs = training_run_frame(context.training_curves())
    claims = claims_frame(per_seed, runs)
    write_table_atomic(runs, context.out_dir / "training_runs.csv")
    write_table_atomic(claims, context.out_dir / "claims.csv")
    n_claims = int(claims["p_value"].notna().sum())
    level = claims["confidence"].iloc[0] if len(claims) else FAMILY_CONFIDENCE
    table = ["| Claim (paper) | Part | Statistic | Test | n | Estimate [adjusted CI] | p (Holm) | Verdict |",
             "|:--|:--|:--|:--|--:|--:|--:|:--|"]
    previous = None
    for row in claims.to_dict("records"):
        decimals = 2 if "variance" in row["statistic"] else 1
        table.append(
            f"| {row['claim'] if row['claim'] != previous else ''} | {row['part']} | {row['statistic']} "
            f"| {row['test']} | {row['n_x']} vs {row['n_y']} "
            f"| {interval_text(row['estimate'], row['ci_low'], row['ci_high'], decimals)} "
            f"| {p_text(row['p_holm'])} | {row['verdict']} |")
        previous = row["claim"]
    write_text_atomic(context.out_dir / "claims.md", "\n".join(table) + "\n")
    overall = claims.drop_duplicates("claim")
    lines = [
        "## Table 1's claims",
        "",
        "The paper's claims about Table 1 and its training curves, each tested. Goal-rate claims: a policy "
        "(training scenario, algorithm, seed) is one unit, its goal rate averaged over the claim's cells; stratified "
        "Welch t-test (strata: training scenarios), estimate = difference of the mean goal rates in points. "
        f"Convergence: per training run, the first step at which its training reward ({CURVE_VALUE}) reaches "
        f"{100 * CONVERGENCE_FRACTION:.0f} % of the way from its first to its final value (mean of the last "
        f"{100 * FINAL_SHARE:.0f} % of its points), in thousands of steps; stratified Welch test with the algorithms "
        "as "
        "strata (positive: circle interaction is faster). Variance across seeds: the final training reward's "
        "variance over seeds, pooled within algorithms, as a ratio (above 1: circle interaction spreads less); "
        "F-test, which assumes normal per-seed values (one diverging seed can decide it). "
        f"All {n_claims} testable part(s) are one family: intervals at the Bonferroni level ({100 * level:.2f} %), "
        "verdicts by Holm's step-down (family-wise error ≤ 5 %): **holds** if the Holm-adjusted p ≤ 0.05 and the "
        "estimate is on the claim's side, **does not hold** if it is significantly on the other side, otherwise "
        "**cannot tell at this budget**. Holm may be decisive where the Bonferroni interval still touches the null "
        "(never the reverse). A claim with several parts holds if all hold and does not hold if one does not.",
        "",
        *_power_note(per_seed, max(n_claims, 1)),
        "\n".join(table),
        "",
        "Claim by claim:",
        *[f"- **{row['claim']}**: {row['claim_verdict']}" for row in overall.to_dict("records")],
        "",
        "Data: [claims.csv](claims.csv), [training_runs.csv](training_runs.csv) (per run: start and final training "
        "reward, steps to converge).",
    ]
    return "\n".join(lines)
