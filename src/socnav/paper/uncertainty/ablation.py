"""Table 3's ablation -- does the uncertainty condition change the safety decision? -- the paper's rule with the
paper's thresholds, proximity-only, uncertainty-only and the paper's rule calibrated, each against proximity-only.

Each row is compared with proximity-only paired by episode seed: the discordant episodes give the difference in
prevented collisions with an exact conditional interval (:func:`mcnemar_exact`, Bonferroni over the rows compared);
the hand-overs the uncertainty condition vetoed and the episodes whose hand-overs differ from proximity-only's.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np
import pandas as pd

from socnav.envs.perturbations import PERTURBATIONS
from socnav.experiments.registry import ReportContext
from socnav.experiments.statistics import Interval, verdict
from socnav.io import write_table_atomic, write_text_atomic
from socnav.paper.labels import (
    ESTIMATOR_ORDER,
    MISSING,
    PAPER_TABLE3_COLUMNS,
    PERTURBATION_ORDER,
    SENSING_LABELS,
    TABLE3_COLUMN_LABELS,
    estimator_label,
    present_in_order,
)
from socnav.paper.uncertainty.plan import NO_ESTIMATOR
from socnav.paper.uncertainty.records import perturbed_rows, safety_records, with_rule
from socnav.paper.uncertainty.table3 import (
    DEFAULT_BUDGET,
    decimal_text,
    episode_rates,
    prevented_cell,
    prevented_frame,
    run_budget,
    table3_groups,
)

__all__ = [
    "ABLATION_CONFIDENCE", "ABLATION_ROWS", "DECISION_COLUMNS", "EPISODE_KEYS", "PAIRED_COLUMNS", "REFERENCE",
    "UNPERTURBED_COLUMN", "ablation_markdown", "ablation_records", "ablation_sensing", "decisions_frame",
    "mcnemar_exact", "paired_frame", "paired_markdown", "paper_column_kinds", "table3_ablation_section",
    "vetoes_frame", "vetoes_markdown",
]


#: Rows of the ablation (variant of its view -> label): the paper's rule with the paper's thresholds as printed,
#: the two ablated rules and the paper's rule calibrated (gated by that estimator's uncertainty).
ABLATION_ROWS = {"paper": "Paper's rule, paper's thresholds (as printed)",
                 "proximity-only": "Proximity only: c_prox ∧ c_ap (calibrated)",
                 "uncertainty-only": "Uncertainty only: (c_ep ∨ c_feat) ∧ c_ap (calibrated)",
                 "calibrated": "Paper's rule (c_ep ∨ c_feat) ∧ c_prox ∧ c_ap, calibrated: uncertainty-gated"}
#: The reference every other row is compared with, episode by episode.
REFERENCE = "proximity-only"
ABLATION_CONFIDENCE = 0.95  # family-wise, Bonferroni over the rows compared (or rows x columns)
EPISODE_KEYS = ["perturbation", "strength", "repeat", "seed"]
#: The paired comparison's column of the unperturbed episodes (ours: the paper's columns are all perturbed).
UNPERTURBED_COLUMN = "unperturbed"
PAIRED_COLUMNS = ["estimator", "row", "column", "episodes", "collisions_none", "collisions_reference",
                  "collisions_row", "row_only_prevented", "reference_only_prevented", "difference",
                  "difference_pct", "low_pct", "high_pct", "p_value", "p_adjusted", "comparisons", "confidence",
                  "verdict"]
DECISION_COLUMNS = ["estimator", "row", "episodes", "activation_pct", "false_activation_pct", "proximity_steps",
                    "vetoed_steps", "vetoed_pct", "paired_episodes", "episodes_other_decisions"]


def ablation_sensing(safety: pd.DataFrame, context: ReportContext | None = None) -> str | None:
    """The sensing of the ablation: that of the proximity-only rows (or the run's `ablation_sensing`)."""
    rows = safety.loc[safety["rule"] == REFERENCE, "sensing"]
    if len(rows):
        return str(rows.iloc[0])
    chosen = ((context.experiment.get("safety") or {}).get("ablation_sensing") if context is not None else None)
    ablated = safety.loc[safety["rule"] == "uncertainty-only", "sensing"]
    return chosen if chosen is not None else (str(ablated.iloc[0]) if len(ablated) else None)


def ablation_records(safety: pd.DataFrame, sensing: str, budget: float = DEFAULT_BUDGET) -> pd.DataFrame:
    """The ablation's view of the records: the plain policy and, for `sensing` and the main `budget`, every row of
    :data:`ABLATION_ROWS` -- ``variant`` renamed to the row (``paper``: the paper's thresholds; ``calibrated``: the
    paper's rule calibrated; ``proximity-only``, ``uncertainty-only``: the ablated rules, calibrated)."""
    safety = with_rule(safety)
    budgets = safety["budget"].to_numpy(np.float64)
    plain = safety["variant"] == "none"
    mine = (safety["sensing"] == sensing) & ~plain
    as_printed = mine & (safety["variant"] == "paper")
    calibrated = mine & (safety["variant"] == "calibrated") & np.isclose(budgets, budget)
    view = safety[plain | as_printed | calibrated].copy()
    ablated = view["rule"].isin(["proximity-only", "uncertainty-only"])
    view.loc[ablated, "variant"] = view.loc[ablated, "rule"]
    return view


def mcnemar_exact(row_only: int, reference_only: int, confidence: float) -> tuple[float, float, float]:
    """Exact paired comparison of two rules on the same episodes from their discordant episodes: ``row_only``
    episodes where only the reference collided (the row prevented a collision the reference did not),
    ``reference_only`` where only the row collided. Returns ``(low, high, p)``: the conditional interval of the
    difference in prevented collisions ``D = row_only - reference_only`` given the ``n`` discordant episodes --
    ``n (2 pi - 1)`` at the ends of the central Clopper-Pearson interval of ``pi``, the share of discordant episodes
    the row wins -- and the exact two-sided McNemar p-value (binomial test of ``pi = 1/2``). ``n = 0``: the rules
    decided alike in every episode, ``(0, 0, 1)``."""
    from scipy.stats import beta, binomtest

    b, n = int(row_only), int(row_only) + int(reference_only)
    if n == 0:
        return 0.0, 0.0, 1.0
    alpha = 1.0 - confidence
    low = 0.0 if b == 0 else float(beta.ppf(alpha / 2, b, n - b + 1))
    high = 1.0 if b == n else float(beta.ppf(1 - alpha / 2, b + 1, n - b))
    return n * (2 * low - 1), n * (2 * high - 1), float(binomtest(b, n, 0.5).pvalue)


def paper_column_kinds(perturbations: Iterable[str]) -> dict[str, list[str]]:
    """The paper's Table III columns present (column -> our perturbation types), after ``all`` (every type of the
    paper's columns: the pre-specified pooled comparison, which a column of ours must not change), then each
    perturbation beyond the paper as its own column (e.g. the behaviour shift)."""
    present = present_in_order(perturbations, PERTURBATION_ORDER)
    paper = [kind for kind in present if kind not in PERTURBATIONS or not PERTURBATIONS[kind].ours]
    groups = {"all": paper} if paper else {}
    groups.update({c: kinds for c, kinds in table3_groups(present).items() if c in PAPER_TABLE3_COLUMNS})
    groups.update({kind: [kind] for kind in present if kind in PERTURBATIONS and PERTURBATIONS[kind].ours})
    return groups


def _outcomes(view: pd.DataFrame, estimator: str, variant: str) -> pd.DataFrame:
    rows = view[(view["estimator"] == estimator) & (view["variant"] == variant)]
    return rows.drop_duplicates(EPISODE_KEYS).set_index(EPISODE_KEYS)


def _compared_rows(view: pd.DataFrame) -> list[tuple[str, str]]:
    """(estimator, row) of every row compared with the reference, in the ablation table's order."""
    rows = []
    for variant in ("paper", "uncertainty-only", "calibrated"):
        for estimator in present_in_order(view.loc[view["variant"] == variant, "estimator"], ESTIMATOR_ORDER):
            rows.append((estimator, variant))
    return rows


def paired_frame(view: pd.DataFrame, confidence: float = ABLATION_CONFIDENCE) -> pd.DataFrame:
    """Every row of the ablation's `view` (:func:`ablation_records`) against the proximity-only rule, paired by
    episode (perturbation, strength, repeat, seed), over the perturbed episodes of each of the paper's columns, of
    ``all`` of them and over the unperturbed episodes (:data:`UNPERTURBED_COLUMN`): discordant episodes, the
    difference in prevented collisions ``D`` (row minus reference; in
    points of the plain policy's collisions on those episodes: ``difference_pct``) with its exact conditional
    interval and McNemar p (:func:`mcnemar_exact`). Bonferroni: the ``all`` comparisons at ``1 - (1 - confidence) /
    m`` with m the rows compared, the per-column ones with m = rows x columns; ``p_adjusted = min(1, m p)``.
    Verdict of "the row prevents more collisions than proximity-only": holds / does not hold when the interval
    lies above / below 0, cannot tell when it contains 0."""
    if view.empty or not (view["variant"] == REFERENCE).any():
        return pd.DataFrame(columns=PAIRED_COLUMNS)
    reference = _outcomes(view, NO_ESTIMATOR, REFERENCE)
    groups = paper_column_kinds(view.loc[perturbed_rows(view), "perturbation"])
    compared = _compared_rows(view)
    results = []
    for estimator, variant in compared:
        row = _outcomes(view, estimator, variant)
        plain = _outcomes(view, estimator, "none")
        if plain.empty:
            plain = _outcomes(view, NO_ESTIMATOR, "none")
        paired = row[["outcome"]].join(reference["outcome"].rename("outcome_reference"), how="inner").join(
            plain["outcome"].rename("outcome_none"), how="left")
        shifted = perturbed_rows(paired.index.to_frame(index=False))
        # the paper's columns (perturbed episodes) and, as ours, the unperturbed episodes: where the false
        # activation is measured, so where a gate that keeps within budget by vetoing costs protection
        cells = [(column, shifted & paired.index.get_level_values("perturbation").isin(kinds))
                 for column, kinds in groups.items()] + [(UNPERTURBED_COLUMN, ~shifted)]
        for column, chosen in cells:
            cell = paired[chosen]
            if cell.empty:
                continue
            hit_row = (cell["outcome"] == "collision").to_numpy()
            hit_reference = (cell["outcome_reference"] == "collision").to_numpy()
            hit_none = int((cell["outcome_none"] == "collision").sum())
            results.append({"estimator": estimator, "row": variant, "column": column, "episodes": len(cell),
                            "collisions_none": hit_none, "collisions_reference": int(hit_reference.sum()),
                            "collisions_row": int(hit_row.sum()),
                            "row_only_prevented": int((hit_reference & ~hit_row).sum()),
                            "reference_only_prevented": int((hit_row & ~hit_reference).sum())})
    frame = pd.DataFrame(results, columns=PAIRED_COLUMNS[:9])
    if frame.empty:
        return pd.DataFrame(columns=PAIRED_COLUMNS)
    pooled = frame["column"] == "all"
    frame["comparisons"] = np.where(pooled, int(pooled.sum()), int((~pooled).sum()))
    frame["confidence"] = 1.0 - (1.0 - confidence) / frame["comparisons"]
    stats = [mcnemar_exact(b, c, level) for b, c, level in
             zip(frame["row_only_prevented"], frame["reference_only_prevented"], frame["confidence"],
                 strict=True)]
    frame["difference"] = frame["row_only_prevented"] - frame["reference_only_prevented"]
    scale = np.where(frame["collisions_none"] > 0, 100.0 / frame["collisions_none"].clip(lower=1), np.nan)
    frame["difference_pct"] = frame["difference"] * scale
    frame["low_pct"] = np.array([low for low, _, _ in stats]) * scale
    frame["high_pct"] = np.array([high for _, high, _ in stats]) * scale
    frame["p_value"] = [p for _, _, p in stats]
    frame["p_adjusted"] = np.minimum(1.0, frame["p_value"] * frame["comparisons"])
    frame["verdict"] = [verdict(Interval(d, low, high)) for d, low, high in
                        zip(frame["difference"], [s[0] for s in stats], [s[1] for s in stats], strict=True)]
    return frame[PAIRED_COLUMNS]


def decisions_frame(view: pd.DataFrame) -> pd.DataFrame:
    """What the uncertainty condition changed, per row of the ablation's `view` over all its episodes (perturbed and
    unperturbed): fallback activation (% of perturbed steps) and false activation (% of unperturbed steps); the
    steps where the rule's proximity terms fired (``c_prox and c_ap``) and those of them the uncertainty condition
    vetoed (eq. (10)'s rows only; with a hold the fallback may still drive there); and in how many episodes the
    fallback drove on other steps than the proximity-only rule's on the same episode (the rules' hand-over
    decisions differ: ``fallback_digest``)."""
    if view.empty:
        return pd.DataFrame(columns=DECISION_COLUMNS)
    perturbed = perturbed_rows(view)
    reference = _outcomes(view, NO_ESTIMATOR, REFERENCE) if (view["variant"] == REFERENCE).any() else None
    rows = []
    for variant in ("paper", REFERENCE, "uncertainty-only", "calibrated"):
        for estimator in present_in_order(view.loc[view["variant"] == variant, "estimator"], ESTIMATOR_ORDER):
            chosen = (view["estimator"] == estimator) & (view["variant"] == variant)
            hot, cold = episode_rates(view[chosen & perturbed], True), episode_rates(view[chosen & ~perturbed], True)
            mine = view[chosen]
            proximity = int(mine["proximity_steps"].sum()) if "proximity_steps" in mine else 0
            vetoed = int(mine["vetoed_steps"].sum()) if "vetoed_steps" in mine else 0
            paired, other = 0, 0
            if reference is not None and variant != REFERENCE and "fallback_digest" in mine:
                joined = mine.drop_duplicates(EPISODE_KEYS).set_index(EPISODE_KEYS)[["fallback_digest"]].join(
                    reference["fallback_digest"].rename("fallback_digest_reference"), how="inner")
                paired = len(joined)
                other = int((joined["fallback_digest"] != joined["fallback_digest_reference"]).sum())
            rows.append({"estimator": estimator, "row": variant, "episodes": int(chosen.sum()),
                         "activation_pct": hot["activation"], "false_activation_pct": cold["activation"],
                         "proximity_steps": proximity, "vetoed_steps": vetoed,
                         "vetoed_pct": 100.0 * vetoed / proximity if variant in ("paper", "calibrated") and proximity
                         else math.nan,
                         "paired_episodes": paired, "episodes_other_decisions": other})
    return pd.DataFrame(rows, columns=DECISION_COLUMNS)


def _paired_text(row: Mapping[str, Any]) -> str:
    if not math.isfinite(row["difference_pct"]):
        return f"{int(row['difference']):+d} collisions (no plain-policy collision)"
    return (f"{row['difference_pct']:+.1f} [{row['low_pct']:+.1f}, {row['high_pct']:+.1f}] "
            f"({int(row['row_only_prevented'])} vs {int(row['reference_only_prevented'])})")


def ablation_markdown(prevented: pd.DataFrame, paired: pd.DataFrame, decisions: pd.DataFrame) -> str:
    """The ablation table: a row per rule (and estimator), the paper's columns (prevented %, mean ± std over the
    repeats), false activation, the uncertainty condition's vetoes, the episodes whose hand-overs differ from the
    proximity-only rule's, and the paired difference with proximity-only over all perturbed episodes."""
    columns = [c for c in PAPER_TABLE3_COLUMNS if c in set(prevented["column"])]
    header = (["Rule", "Estimator"] + [TABLE3_COLUMN_LABELS[c] for c in columns]
              + ["False activation (% steps)", "Vetoed by uncertainty (% of proximity firings)",
                 "Episodes with other hand-overs than proximity-only",
                 "Δ prevented vs proximity-only, all perturbed (points [CI]; episodes won vs lost)", "Verdict"])
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join([":--", ":--"] + ["--:"] * (len(header) - 3) + [":--"])
             + "|"]
    indexed = prevented.set_index(["estimator", "variant", "column"])
    decided = decisions.set_index(["estimator", "row"])
    compared = paired[paired["column"] == "all"].set_index(["estimator", "row"])
    for variant in ("paper", REFERENCE, "uncertainty-only", "calibrated"):
        for estimator in present_in_order(decisions.loc[decisions["row"] == variant, "estimator"], ESTIMATOR_ORDER):
            cells = [ABLATION_ROWS[variant], "–" if estimator == NO_ESTIMATOR else estimator_label(estimator)]
            for column in columns:
                key = (estimator, variant, column)
                cells.append(prevented_cell(indexed, key) if key in indexed.index else MISSING)
            decision = decided.loc[(estimator, variant)]
            cells.append(decimal_text(decision["false_activation_pct"], 2))
            cells.append("–" if not math.isfinite(decision["vetoed_pct"]) else
                         f"{decision['vetoed_pct']:.1f} ({int(decision['vetoed_steps'])} of "
                         f"{int(decision['proximity_steps'])})")
            cells.append("reference" if variant == REFERENCE else
                         f"{int(decision['episodes_other_decisions'])} of {int(decision['paired_episodes'])}")
            if (estimator, variant) in compared.index:
                row = compared.loc[(estimator, variant)]
                cells += [_paired_text(row), row["verdict"]]
            else:
                cells += ["–", "–"]
            lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def paired_markdown(paired: pd.DataFrame) -> str:
    """Per paper column and the unperturbed episodes: the paired difference with proximity-only of every compared
    row (points [CI])."""
    ours = [name for name, p in PERTURBATIONS.items() if p.ours]
    columns = [c for c in [*PAPER_TABLE3_COLUMNS, *ours, UNPERTURBED_COLUMN] if c in set(paired["column"])]
    labels = {**TABLE3_COLUMN_LABELS, UNPERTURBED_COLUMN: "Unperturbed (ours)"}
    header = ["Rule", "Estimator"] + [labels[c] for c in columns]
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join([":--", ":--"] + ["--:"] * len(columns)) + "|"]
    indexed = paired.set_index(["estimator", "row", "column"])
    for estimator, variant in dict.fromkeys(zip(paired["estimator"], paired["row"], strict=True)):
        cells = [ABLATION_ROWS[variant], estimator_label(estimator)]
        for column in columns:
            key = (estimator, variant, column)
            cells.append(_paired_text(indexed.loc[key]) + f", {indexed.loc[key, 'verdict']}"
                         if key in indexed.index else MISSING)
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def vetoes_frame(view: pd.DataFrame) -> pd.DataFrame:
    """Where the uncertainty condition vetoes, per uncertainty-gated row of the ablation's `view` (the paper's rule,
    calibrated and as printed) and per setting: the steps its proximity terms fired, those the uncertainty
    condition vetoed, and their share. ``setting`` is ``unperturbed`` for every unperturbed episode (the ones the
    false activation is measured on), else ``<perturbation> <strength>``. A gate that vetoes mostly where nothing
    is perturbed spends the false-activation budget on the perturbed settings: what it knows is the shift, not the
    collision (docs/reproduction.md)."""
    columns = ["estimator", "row", "setting", "perturbation", "strength", "proximity_steps", "vetoed_steps",
               "vetoed_pct"]
    gated = view[view["variant"].isin(["paper", "calibrated"])]
    if gated.empty or "vetoed_steps" not in gated:
        return pd.DataFrame(columns=columns)
    gated = gated.assign(setting=np.where(perturbed_rows(gated), gated["perturbation"] + " " + gated["strength"].map(
        "{:g}".format), "unperturbed"))
    gated.loc[gated["setting"] == "unperturbed", ["perturbation", "strength"]] = ["", math.nan]
    totals = gated.groupby(["estimator", "variant", "setting", "perturbation", "strength"], dropna=False, sort=False)[
        ["proximity_steps", "vetoed_steps"]].sum().reset_index().rename(columns={"variant": "row"})
    totals["vetoed_pct"] = 100.0 * totals["vetoed_steps"] / totals["proximity_steps"].where(
        totals["proximity_steps"] > 0)
    order = {"row": {"paper": 0, "calibrated": 1}, "estimator": {name: i for i, name in enumerate(ESTIMATOR_ORDER)}}
    return totals.sort_values(["row", "estimator", "perturbation", "strength"], ignore_index=True, key=lambda c: (
        c.map(order[c.name]).fillna(len(order[c.name])) if c.name in order else c))[columns]


def vetoes_markdown(vetoes: pd.DataFrame) -> str:
    """One row per gated rule, one column per setting: the vetoed share of its proximity firings (%)."""
    if vetoes.empty:
        return ""
    settings = list(dict.fromkeys(["unperturbed", *vetoes["setting"]]))
    names = {"calibrated": "calibrated", "paper": "paper's thresholds"}
    lines = ["| Rule | " + " | ".join(settings) + " |", "|:--|" + "--:|" * len(settings)]
    for (row, estimator), rows in vetoes.groupby(["row", "estimator"], sort=False):
        share = dict(zip(rows["setting"], rows["vetoed_pct"], strict=True))
        cells = ["–" if not math.isfinite(share.get(name, math.nan)) else f"{share[name]:.1f}" for name in settings]
        lines.append(f"| {estimator_label(estimator)}, {names.get(row, row)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def table3_ablation_section(context: ReportContext) -> str:
    """The ablation's section: table3_ablation.md/csv, the paired comparisons, decisions and vetoes (empty without
    ablation records)."""
    safety = safety_records(context)
    if safety.empty:
        return ""
    safety = with_rule(safety)
    if not safety["rule"].isin(["proximity-only", "uncertainty-only"]).any():
        return ""
    sensing = ablation_sensing(safety, context)
    assert sensing is not None  # the ablation's rows are there, and so is their sensing
    view = ablation_records(safety, sensing, run_budget(context))
    prevented = prevented_frame(view)
    paired = paired_frame(view)
    decisions = decisions_frame(view)
    write_table_atomic(prevented, context.out_dir / "table3_ablation.csv")
    write_table_atomic(paired, context.out_dir / "table3_ablation_paired.csv")
    write_table_atomic(decisions, context.out_dir / "table3_ablation_decisions.csv")
    vetoes = vetoes_frame(view)
    write_table_atomic(vetoes, context.out_dir / "table3_ablation_vetoes.csv")
    markdown = ablation_markdown(prevented, paired, decisions)
    write_text_atomic(context.out_dir / "table3_ablation.md", markdown + "\n")
    pooled = paired[paired["column"] == "all"]
    lines = [
        "## Table 3 ablation: does the uncertainty condition change the safety decision?",
        "",
        "The paper's rule (eq. (10)) hands control to the cautious controller when the policy is uncertain AND "
        "close to a person AND approaching. Each rule below is calibrated under the same false-activation budget "
        f"({100 * run_budget(context):g} % of unperturbed steps) on the same calibration episodes, and all play "
        f"the same evaluation episodes as Table 3, with the {SENSING_LABELS.get(sensing, sensing)} sensing (Table "
        "3's primary row). Proximity only drops the uncertainty condition, uncertainty only drops c_prox (c_ap stays: "
        "it is no distance test but the paper's 'moving away averts the risk'); the paper's thresholds as printed "
        "are shown uncalibrated.",
        "",
        "Prevented collisions: as in Table 3 (mean ± std over the repeats). *Vetoed by uncertainty*: steps where "
        "the rule's own proximity terms fired (c_prox ∧ c_ap) but its uncertainty condition did not, so eq. (10) "
        "left the policy in control. *Episodes with other hand-overs*: episodes where the fallback drove on other "
        "steps than proximity-only's on the same episode seed. *Δ prevented*: paired by episode over all perturbed "
        "episodes, (collisions only proximity-only had − collisions only this rule had) in points of the plain "
        "policy's collisions, with the exact conditional (McNemar / Clopper-Pearson) interval, Bonferroni-adjusted "
        f"over the {len(pooled)} rows compared ({ABLATION_CONFIDENCE:.0%} family-wise). Verdict of 'this rule "
        "prevents more collisions than proximity-only': holds / does not hold when the interval lies above / below "
        "0, cannot tell at this budget when it contains 0.",
        "",
        markdown,
        "",
    ]
    if not paired.empty and (paired["column"] != "all").any():
        lines += ["Per column, and over the unperturbed episodes, where the false activation is measured (ours; "
                  "Bonferroni over rows × columns; cells: Δ points [CI] (won vs lost), verdict):", "",
                  paired_markdown(paired[paired["column"] != "all"]), ""]
    if not vetoes.empty:
        lines += ["Where the uncertainty condition vetoes (% of the rule's proximity firings it vetoed, per setting; "
                  "the false activation is measured on the unperturbed episodes):", "", vetoes_markdown(vetoes), ""]
    lines.append("Data: [table3_ablation.csv](table3_ablation.csv) (prevented per column), "
                 "[table3_ablation_paired.csv](table3_ablation_paired.csv) (paired comparisons, p-values), "
                 "[table3_ablation_decisions.csv](table3_ablation_decisions.csv) (hand-over decisions), "
                 "[table3_ablation_vetoes.csv](table3_ablation_vetoes.csv) (vetoes per setting).")
    return "\n".join(lines)
