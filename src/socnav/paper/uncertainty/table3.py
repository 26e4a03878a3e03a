"""Table 3 of the paper from the safety records -- collisions the safety layer prevented against the plain policy
on the same episode seeds -- and the layer's cost; their report sections.

- **Table 3** (prevented collisions): per repeat, ``100 (C_none - C_variant) / C_none`` with ``C`` the collisions
  over every PERTURBED strength (``strength != sigma_0``, the unperturbed strength of the perturbation type) of
  that type; mean +- std (ddof=0) over the repeats where ``C_none > 0``. The paper's columns, each compared once
  with the paper's value: observation noise, action noise (heading and speed noise pooled), velocity (faster
  humans), new humans (more humans); heading and speed noise alone in a separate table, as ours. Only the paper's
  rule at the run's budget (:func:`main_records`).
- **Cost**: fallback activation rate (fallback steps / steps) in perturbed episodes, false-activation rate (the
  same in unperturbed episodes), success and collision rates, mean time to goal of successful episodes.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np
import pandas as pd

from socnav.envs.perturbations import CALIBRATION_SEED, CALIBRATION_SET, PERTURBATIONS
from socnav.experiments.registry import ReportContext
from socnav.io import write_table_atomic, write_text_atomic
from socnav.paper.labels import (
    ESTIMATOR_ORDER,
    MISSING,
    OWN_TABLE3_COLUMNS,
    PAPER_TABLE3_COLUMNS,
    PERTURBATION_ORDER,
    POOLED,
    SENSING_ORDER,
    TABLE3_COLUMN_LABELS,
    ZERO,
    estimator_label,
    perturbation_label,
    present_in_order,
    variant_label,
)
from socnav.paper.published import paper_table3
from socnav.paper.uncertainty.plan import NO_ESTIMATOR
from socnav.paper.uncertainty.records import perturbed_rows, safety_records, with_rule, with_sensing
from socnav.sim.metrics import ALL_METRICS, summarize_episodes, summarize_groups

__all__ = [
    "COST_COLUMNS", "DEFAULT_BUDGET", "DEVELOPMENT_SEEDS", "SAFETY_METRIC_KEYS", "TABLE3_COLUMNS", "cost_frame",
    "cost_markdown", "decimal_text", "episode_rates", "main_records", "prevented_cell", "prevented_frame",
    "prevented_markdown", "run_budget", "safe_variants", "safety_metrics_frame", "sensing_shown", "table3_cost_section",
    "table3_groups", "table3_section", "unpaired_groups",
]

# --------------------------------------------------------------------------------------------------------------
# Table 3: prevented collisions
# --------------------------------------------------------------------------------------------------------------

TABLE3_COLUMNS = ["estimator", "variant", "sensing", "column", "repeats", "repeats_defined", "collisions_none",
                  "collisions_variant", "prevented_mean", "prevented_std", "paper_mean", "paper_std"]
#: Episode seeds the development of Table 3 looked at: its evaluations at seeds 0-999 (the paper budget's 5 x 200)
#: and the fresh-episodes check at 100,000-100,449; an evaluation overlapping them is not held out. The calibration's
#: seeds (CALIBRATION_SEED...) are added per run.
DEVELOPMENT_SEEDS = ((0, 999), (100_000, 100_449))
#: The false-activation budget of the main rows when the run does not name one (`Safety.false_activation_budget`).
DEFAULT_BUDGET = 0.05


def table3_groups(perturbations: Iterable[str]) -> dict[str, list[str]]:
    """Table 3 columns: each perturbation type, plus each pooled column (:data:`POOLED`; the paper's action noise =
    heading and speed noise) after the last of its types when all of them are there."""
    present = present_in_order(perturbations, PERTURBATION_ORDER)
    groups: dict[str, list[str]] = {}
    for perturbation in present:
        groups[perturbation] = [perturbation]
        pool = PERTURBATIONS[perturbation].pooled if perturbation in PERTURBATIONS else None
        if pool is not None and all(kind in present for kind in POOLED[pool]) and \
                perturbation == [kind for kind in present if kind in POOLED[pool]][-1]:
            groups[pool] = list(POOLED[pool])
    return groups


def main_records(safety: pd.DataFrame, budget: float = DEFAULT_BUDGET) -> pd.DataFrame:
    """The records of Table 3 and its cost: the plain policy, the paper's thresholds and the paper's rule calibrated
    at `budget` -- not the ablation's rules, the trade-off budgets, nor the units of the rule without estimator."""
    safety = with_rule(safety)
    budgets = safety["budget"].to_numpy(np.float64)
    keep = ((safety["estimator"] != NO_ESTIMATOR) & safety["rule"].isin(["", "paper"])
            & (np.isnan(budgets) | np.isclose(budgets, budget)))
    return safety[keep]


def run_budget(context: ReportContext) -> float:
    """The false-activation budget of the run's main calibrated rows (:data:`DEFAULT_BUDGET` if it names none)."""
    safety = context.experiment.get("safety") or {}
    return float(safety.get("false_activation_budget", DEFAULT_BUDGET))


def safe_variants(safety: pd.DataFrame) -> list[tuple[str, str]]:
    """The (variant, sensing) pairs of the safety layer in the records, paper before calibrated, perceived first."""
    pairs = safety.loc[safety["variant"] != "none", ["variant", "sensing"]].drop_duplicates()
    variants = present_in_order(pairs["variant"], ["paper", "calibrated"])
    sensings = present_in_order(pairs["sensing"], SENSING_ORDER)
    present = set(pairs.itertuples(index=False, name=None))
    return [(v, s) for v in variants for s in sensings if (v, s) in present]


def sensing_shown(pairs: Iterable[tuple[str, str]]) -> bool:
    """Name the sensing in labels unless every safe variant read the observation (the only sensing of records
    without a ``sensing`` column)."""
    return any(sensing != "perceived" for variant, sensing in pairs if variant != "none")


def prevented_frame(safety: pd.DataFrame) -> pd.DataFrame:
    """Prevented collisions per (estimator, safe variant, sensing, Table 3 column): per repeat ``100 (C_none -
    C_variant) / C_none`` over the perturbed strengths, then mean and population std over the repeats with
    ``C_none > 0`` (NaN if there is none). ``collisions_*`` are the totals over the repeats used. One rule and
    budget per (estimator, variant, sensing): pass :func:`main_records` (or the ablation's view)."""
    if safety.empty:
        return pd.DataFrame(columns=TABLE3_COLUMNS)
    safety = with_sensing(safety)
    perturbed = safety[perturbed_rows(safety)]
    keys = ["estimator", "perturbation", "repeat", "variant", "sensing"]
    collisions = (perturbed["outcome"] == "collision").groupby([perturbed[k] for k in keys]).sum()
    plain = ("none", "")  # the plain policy has no safety layer, so no sensing
    rows = []
    groups = table3_groups(safety["perturbation"])
    for estimator in present_in_order(safety["estimator"], ESTIMATOR_ORDER):
        mine = safety[safety["estimator"] == estimator]
        for variant, sensing in safe_variants(mine):
            for column, kinds in groups.items():
                kinds = [k for k in kinds if (mine["perturbation"] == k).any()]
                if not kinds:
                    continue
                repeats = sorted(set(mine["repeat"]))
                used = [r for r in repeats if all((estimator, k, r, *v) in collisions.index
                                                  for k in kinds for v in (plain, (variant, sensing)))]
                if not used:
                    continue
                c_none = np.array([sum(collisions[(estimator, k, r, *plain)] for k in kinds) for r in used])
                c_var = np.array([sum(collisions[(estimator, k, r, variant, sensing)] for k in kinds) for r in used])
                defined = c_none > 0
                prevented = 100.0 * (c_none[defined] - c_var[defined]) / c_none[defined]
                paper_mean, paper_std = paper_table3(column, estimator)
                rows.append({"estimator": estimator, "variant": variant, "sensing": sensing, "column": column,
                             "repeats": len(used), "repeats_defined": int(defined.sum()),
                             "collisions_none": int(c_none.sum()), "collisions_variant": int(c_var.sum()),
                             "prevented_mean": float(prevented.mean()) if len(prevented) else math.nan,
                             "prevented_std": float(prevented.std(ddof=0)) if len(prevented) else math.nan,
                             "paper_mean": paper_mean, "paper_std": paper_std})
    return pd.DataFrame(rows, columns=TABLE3_COLUMNS)


def prevented_cell(indexed: pd.DataFrame, key: tuple[Any, ...]) -> str:
    """``mean ± std`` of one Table 3 cell (``(k of n)`` when only k repeats had a collision to prevent)."""
    if key not in indexed.index:
        return MISSING
    cell = indexed.loc[key]
    if cell["repeats_defined"] == 0:
        return ZERO
    text = f"{cell['prevented_mean']:.1f} ± {cell['prevented_std']:.1f}"
    if cell["repeats_defined"] < cell["repeats"]:
        text += f" ({int(cell['repeats_defined'])} of {int(cell['repeats'])})"
    return text


def prevented_markdown(table: pd.DataFrame, columns: Sequence[str] | None = None, paper_rows: bool = True) -> str:
    """Rows: estimator x thresholds (x sensing, named when not only ``perceived``), then (`paper_rows`) the paper's
    row of that estimator, each of its values once; `columns` (default: the paper's Table III columns present,
    :data:`PAPER_TABLE3_COLUMNS`). ``—``: no collision without the safety layer; ``(k of n)``: only k repeats had
    one."""
    table = table if "sensing" in table else table.assign(sensing="perceived")
    wanted = PAPER_TABLE3_COLUMNS if columns is None else list(columns)
    columns = [c for c in wanted if c in set(table["column"])]
    header = ["Approach", "Thresholds"] + [TABLE3_COLUMN_LABELS.get(c, perturbation_label(c)) for c in columns]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join([":--", ":--"] + ["--:"] * len(columns)) + "|"]
    indexed = table.set_index(["estimator", "variant", "sensing", "column"])
    show_sensing = sensing_shown(table[["variant", "sensing"]].itertuples(index=False, name=None))
    for estimator in present_in_order(table["estimator"], ESTIMATOR_ORDER):
        for variant, sensing in safe_variants(table[table["estimator"] == estimator]):
            row = [estimator_label(estimator), variant_label(variant, sensing, show_sensing)]
            row += [prevented_cell(indexed, (estimator, variant, sensing, column)) for column in columns]
            lines.append("| " + " | ".join(row) + " |")
        paper = [paper_table3(column, estimator) for column in columns]
        if paper_rows and any(math.isfinite(mean) for mean, _ in paper):
            cells = [f"*{mean:.0f} ± {std:.0f}*" if math.isfinite(mean) else MISSING for mean, std in paper]
            lines.append(f"| {estimator_label(estimator)} | *paper's Table III* | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def unpaired_groups(safety: pd.DataFrame) -> int:
    """(estimator, perturbation, strength, repeat, variant) groups whose episode seeds differ from 'none''s."""
    if "seed" not in safety or safety.empty:
        return 0
    keys = ["estimator", "perturbation", "strength", "repeat"]
    mismatches = 0
    # each sensing, rule and budget of a variant is its own run of the episodes: compare each with the plain
    # policy's seeds
    variant_keys = [key for key in ("variant", "sensing", "rule", "budget") if key in safety]
    for _, group in safety.groupby(keys, sort=False):
        plain = group[group["variant"] == "none"]
        if plain.empty:
            continue
        reference = sorted(plain["seed"].tolist())
        for _, runs in group[group["variant"] != "none"].groupby(variant_keys, dropna=False):
            mismatches += sorted(runs["seed"].tolist()) != reference
    return mismatches


def _seed_ranges_text(context: ReportContext) -> str:
    """Which episode seeds the evaluation played, and whether any development step looked at them."""
    evaluation, safety = context.experiment.get("evaluation") or {}, context.experiment.get("safety") or {}
    seed, episodes, repeats = evaluation.get("seed"), evaluation.get("episodes"), safety.get("repeats")
    if not (isinstance(seed, int) and isinstance(episodes, int) and isinstance(repeats, int)):
        return ""
    last = seed + repeats * episodes - 1
    configurations = 1 + sum(len(strengths) for strengths in CALIBRATION_SET.values())  # unperturbed + perturbed
    calibration = (CALIBRATION_SEED, CALIBRATION_SEED + configurations * int(safety.get("calibration_episodes", 0)) - 1)
    looked = [*DEVELOPMENT_SEEDS, calibration]
    seen = [f"{a:,}–{b:,}" for a, b in looked if a <= last and seed <= b]
    ranges = ", ".join(f"{a:,}–{b:,}" for a, b in looked)
    verdict = (f"held out: no development step looked at them (the earlier Table 3 evaluations and checks played "
               f"seeds {', '.join(f'{a:,}–{b:,}' for a, b in DEVELOPMENT_SEEDS)}, the calibration "
               f"{calibration[0]:,}–{calibration[1]:,})" if not seen else
               f"**not held out**: they overlap seeds development looked at ({', '.join(seen)} of {ranges})")
    return (f"Evaluation episodes: seeds {seed:,}–{last:,} (repeat r, episode k: seed + r · {episodes} + k), "
            f"{verdict}.")


def table3_section(context: ReportContext) -> str:
    """Table 3's section: table3.md/csv of the main rows (:func:`main_records`; empty without safety records)."""
    safety = safety_records(context)
    if safety.empty:
        return ""
    safety = main_records(safety, run_budget(context))
    table = prevented_frame(safety)
    write_table_atomic(table, context.out_dir / "table3.csv")
    if table.empty:
        markdown = own = "No safe variant with its plain-policy runs yet."
    else:
        markdown = prevented_markdown(table)
        own = prevented_markdown(table, OWN_TABLE3_COLUMNS, paper_rows=False)
    has_own = not table.empty and bool(set(table["column"]) & set(OWN_TABLE3_COLUMNS))
    write_text_atomic(context.out_dir / "table3.md", markdown + ("\n\n" + own if has_own else "") + "\n")
    repeats = safety["repeat"].nunique()
    lines = [
        "## Table 3: prevented collisions with safe action selection",
        "",
        "Prevented collisions (%) = 100 · (C_none − C_safe) / C_none per column, C the collisions over all "
        "perturbed strengths of its perturbation type(s) (the unperturbed strength left out), the plain policy and "
        f"the safety layer on identical episode seeds; mean ± standard deviation over {repeats} repeat(s) "
        f"(independent seed blocks). {ZERO}: the plain policy did not collide, nothing to prevent; (k of n): only k "
        "repeats had a collision to prevent. The paper's four columns, each compared once with the paper's value "
        "(italic): observation noise; action noise = our heading and speed noise pooled (the paper perturbs the "
        "action); velocity = our faster humans; new humans = our more humans.",
        "",
    ]
    seeds = _seed_ranges_text(context)
    if seeds:
        lines += [seeds, ""]
    if sensing_shown(table[["variant", "sensing"]].itertuples(index=False, name=None)):
        lines += ["*Perceived* / *true state*: what the layer's proximity terms (c_prox, c_ap) and cautious fallback "
                  "read — the robot's observation, observation noise included, or the simulator's noise-free state "
                  "(a separate safety sensor); the policy and the uncertainty estimates always see the observation. "
                  "Without observation noise both read the same.", ""]
    lines += [markdown, ""]
    if has_own:
        lines += ["Our own columns (the paper has none for them: it reports heading and speed noise only pooled, "
                  "as action noise above, and has no behaviour shift — humans of another model than the policy "
                  "was trained with, never seen by the calibration):", "", own, ""]
    unpaired = unpaired_groups(safety_records(context))
    if unpaired:
        lines += [f"**Warning**: in {unpaired} (estimator, perturbation, strength, repeat) group(s) a safe variant "
                  "played other episode seeds than the plain policy; those comparisons are not paired.", ""]
    lines.append("Data: [table3.csv](table3.csv) (also the collision totals and repeat counts per cell).")
    return "\n".join(lines)


# --------------------------------------------------------------------------------------------------------------
# The cost of the safety layer
# --------------------------------------------------------------------------------------------------------------

#: The groups of table3_metrics.csv.
SAFETY_METRIC_KEYS = ["estimator", "variant", "sensing", "perturbed"]
COST_COLUMNS = ["estimator", "variant", "sensing", "episodes_perturbed", "episodes_unperturbed", "activation_pct",
                "false_activation_pct", "success_pct_perturbed", "success_pct_unperturbed",
                "collision_pct_perturbed", "collision_pct_unperturbed", "time_to_goal_perturbed",
                "time_to_goal_unperturbed"]


def episode_rates(frame: pd.DataFrame, layer: bool) -> dict[str, float]:
    """Fallback activation (% of steps), and the registry's success and collision rates and mean time to goal of
    the successful episodes (`socnav.sim.metrics`)."""
    n = len(frame)
    goal = frame["outcome"] == "goal"
    if "time_to_goal" not in frame and "duration" in frame:  # a successful episode's duration is its time to goal
        frame = frame.assign(time_to_goal=frame["duration"])
    activation = math.nan
    if layer and n and "fallback_steps" in frame and frame["length"].sum() > 0:
        activation = 100.0 * float(frame["fallback_steps"].sum()) / float(frame["length"].sum())
    rates = summarize_episodes(frame, ["goal_pct", "collision_pct"]) if n else {}
    timed = "time_to_goal" in frame and goal.any()
    return {
        "episodes": n,
        "activation": activation,
        "success": rates.get("goal_pct", math.nan),
        "collision": rates.get("collision_pct", math.nan),
        "time": summarize_episodes(frame[goal], ["time_to_goal_mean"])["time_to_goal_mean"] if timed else math.nan,
    }


def safety_metrics_frame(safety: pd.DataFrame) -> pd.DataFrame:
    """Every registry metric the safety records hold (`socnav.sim.metrics`), per (estimator, variant, sensing,
    perturbed): the plain policy and each safety layer in perturbed and unperturbed (strength σ(0)) episodes."""
    if safety.empty:
        return pd.DataFrame(columns=[*SAFETY_METRIC_KEYS, "episodes"])
    safety = with_sensing(safety).assign(perturbed=perturbed_rows(safety))
    return summarize_groups(safety, SAFETY_METRIC_KEYS, ALL_METRICS)


def cost_frame(safety: pd.DataFrame) -> pd.DataFrame:
    """Per (estimator, variant incl. none, sensing): fallback activation rate (% of steps) in perturbed episodes,
    false activation rate (% of steps) in unperturbed ones (NaN for the plain policy), success and collision rates
    (%) and mean time to goal of successful episodes, in perturbed and unperturbed episodes."""
    if safety.empty:
        return pd.DataFrame(columns=COST_COLUMNS)
    safety = with_sensing(safety)
    perturbed = perturbed_rows(safety)
    rows = []
    for estimator in present_in_order(safety["estimator"], ESTIMATOR_ORDER):
        mine = safety["estimator"] == estimator
        pairs = ([("none", "")] if (safety.loc[mine, "variant"] == "none").any() else []) \
            + safe_variants(safety[mine])
        for variant, sensing in pairs:
            chosen = mine & (safety["variant"] == variant) & (safety["sensing"] == sensing)
            layer = variant != "none"
            hot = episode_rates(safety[chosen & perturbed], layer)
            cold = episode_rates(safety[chosen & ~perturbed], layer)
            rows.append({"estimator": estimator, "variant": variant, "sensing": sensing,
                         "episodes_perturbed": hot["episodes"],
                         "episodes_unperturbed": cold["episodes"], "activation_pct": hot["activation"],
                         "false_activation_pct": cold["activation"], "success_pct_perturbed": hot["success"],
                         "success_pct_unperturbed": cold["success"], "collision_pct_perturbed": hot["collision"],
                         "collision_pct_unperturbed": cold["collision"], "time_to_goal_perturbed": hot["time"],
                         "time_to_goal_unperturbed": cold["time"]})
    return pd.DataFrame(rows, columns=COST_COLUMNS)


def decimal_text(value: float, decimals: int) -> str:
    """`value` with `decimals` decimals, ``–`` when it is not finite."""
    return "–" if not math.isfinite(value) else f"{value:.{decimals}f}"


def cost_markdown(table: pd.DataFrame) -> str:
    """The cost table: a row per approach and safety layer, perturbed / unperturbed episodes side by side."""
    header = ["Approach", "Safety layer", "Episodes (pert. / unpert.)", "Fallback activation (% steps, pert.)",
              "False activation (% steps, unpert.)", "Success % (pert. / unpert.)", "Collision % (pert. / unpert.)",
              "Time to goal s (pert. / unpert.)"]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join([":--", ":--"] + ["--:"] * 6) + "|"]
    table = table if "sensing" in table else table.assign(sensing=np.where(table["variant"] == "none", "", "perceived"))
    show_sensing = sensing_shown(table[["variant", "sensing"]].itertuples(index=False, name=None))
    for row in table.to_dict("records"):
        lines.append("| " + " | ".join([
            estimator_label(row["estimator"]), variant_label(row["variant"], row["sensing"], show_sensing),
            f"{row['episodes_perturbed']} / {row['episodes_unperturbed']}",
            decimal_text(row["activation_pct"], 2), decimal_text(row["false_activation_pct"], 2),
            f"{decimal_text(row['success_pct_perturbed'], 1)} / {decimal_text(row['success_pct_unperturbed'], 1)}",
            f"{decimal_text(row['collision_pct_perturbed'], 1)} / {decimal_text(row['collision_pct_unperturbed'], 1)}",
            f"{decimal_text(row['time_to_goal_perturbed'], 2)} / {decimal_text(row['time_to_goal_unperturbed'], 2)}",
        ]) + " |")
    return "\n".join(lines)


def table3_cost_section(context: ReportContext) -> str:
    """The cost's section: table3_cost.md/csv and table3_metrics.csv of the main rows (empty without safety records)."""
    safety = safety_records(context)
    if safety.empty:
        return ""
    main = main_records(safety, run_budget(context))  # the ablation's rows: its own section
    table = cost_frame(main)
    write_table_atomic(table, context.out_dir / "table3_cost.csv")
    write_table_atomic(safety_metrics_frame(main), context.out_dir / "table3_metrics.csv")
    markdown = cost_markdown(table)
    write_text_atomic(context.out_dir / "table3_cost.md", markdown + "\n")
    lines = [
        "## The cost of the safety layer",
        "",
        "Over all perturbation types of the safety runs: fallback activation = steps where the cautious controller "
        "acted / all steps, in perturbed episodes; false activation = the same in unperturbed episodes (strength "
        "σ(0)), where there is little to prevent. Success and collision rates over episodes; time to goal: mean over "
        "successful episodes (seconds). '–': no such episodes (or no safety layer).",
        "",
        markdown,
        "",
    ]
    if (table["episodes_unperturbed"] == 0).all():
        lines += ["No unperturbed (σ(0)) episodes in the safety runs: the false-activation rate is not measured.", ""]
    lines.append("Data: [table3_cost.csv](table3_cost.csv); every metric of docs/metrics.md per approach, safety "
                 "layer and perturbed / unperturbed episodes: [table3_metrics.csv](table3_metrics.csv).")
    return "\n".join(lines)
