"""Figures of the perturbation study -- Fig. 5 (uncertainty vs perturbation strength) and Fig. 6 (feature uncertainty
before a collision vs at the closest approach) -- with their data, report sections and the plot style they share.

- **Fig. 5** (``uncertainty_vs_strength``): ``u(sigma) / u(sigma_0)`` of the epistemic and aleatoric heading and
  speed uncertainty vs strength, with the collision rate per strength.
- **Fig. 6** (``feature_uncertainty_collisions``): windowed feature uncertainty ``w_u_feat`` on the row of a
  collision episode's last step (the observation one step before the collision) vs on the row of the closest
  approach (minimum ``nearest_gap``) of the other episodes, all strengths pooled.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Literal

import numpy as np
import pandas as pd

from socnav.experiments.registry import ReportContext
from socnav.io import save_figure, write_table_atomic
from socnav.paper.labels import (
    CURVE_UNCERTAINTIES,
    ESTIMATOR_ORDER,
    ESTIMATOR_SHORT,
    MISSING,
    PERTURBATION_ORDER,
    STRENGTH_LABELS,
    estimator_label,
    order_rank,
    perturbation_label,
    present_in_order,
)
from socnav.paper.uncertainty.records import study_summaries

__all__ = [
    "CRITICAL_SUMMARY_COLUMNS", "CURVE_COLUMNS", "LINESTYLES", "MARKERS", "critical_summary",
    "feature_uncertainty_collisions_section", "panel_grid", "plot_feature_collisions", "plot_uncertainty_vs_strength",
    "pyplot", "strength_curves", "uncertainty_vs_strength_section",
]


# --------------------------------------------------------------------------------------------------------------
# The plot style the uncertainty kind's figures share
# --------------------------------------------------------------------------------------------------------------

def pyplot() -> Any:
    """matplotlib.pyplot on the Agg backend (files only, no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def panel_grid(n_panels: int, columns: int = 3, width: float = 4.4, height: float = 3.4) -> tuple[Any, list[Any]]:
    """A figure of `n_panels` axes, `columns` per row, the unused ones of the last row hidden."""
    plt = pyplot()
    ncols = max(1, min(n_panels, columns))
    nrows = max(1, math.ceil(n_panels / ncols))
    figure, axes = plt.subplots(nrows, ncols, figsize=(width * ncols, height * nrows), squeeze=False)
    flat = list(axes.ravel())
    for axis in flat[n_panels:]:
        axis.set_visible(False)
    return figure, flat[:n_panels]


LineStyle = Literal["-", "--", "-.", ":"]
#: Line style and marker per estimator (MC-dropout solid / circles, ensemble dashed / crosses).
LINESTYLES: dict[str, LineStyle] = {"mc": "-", "ensemble": "--"}
MARKERS = {"mc": "o", "ensemble": "x"}


# --------------------------------------------------------------------------------------------------------------
# Fig. 5: uncertainty vs perturbation strength
# --------------------------------------------------------------------------------------------------------------

CURVE_COLUMNS = ["estimator", "perturbation", "strength", "uncertainty", "u_mean", "u_normalised", "episodes",
                 "collision_rate"]


def strength_curves(episode_means: pd.DataFrame, critical: pd.DataFrame) -> pd.DataFrame:
    """Per (estimator, perturbation, strength, uncertainty): u(sigma) (mean over episodes of the episode means),
    u(sigma) / u(sigma_0) (NaN where u(sigma_0) = 0) and the share of episodes ending in a collision."""
    if episode_means.empty:
        return pd.DataFrame(columns=CURVE_COLUMNS)
    keys = ["estimator", "perturbation", "strength"]
    uncertainties = [c for c in CURVE_UNCERTAINTIES if c in episode_means]
    means = episode_means.groupby(keys, sort=True)[uncertainties].mean()
    counts = episode_means.groupby(keys, sort=True).size().rename("episodes")
    if not critical.empty:
        rates = critical.groupby(keys, sort=True)["collided"].mean().rename("collision_rate")
    else:
        rates = pd.Series(np.nan, index=means.index, name="collision_rate")
    long = means.reset_index().melt(id_vars=keys, value_vars=uncertainties, var_name="uncertainty",
                                    value_name="u_mean")
    long = long.merge(counts.reset_index(), on=keys).merge(rates.reset_index(), on=keys, how="left")
    baseline = long.loc[long.groupby(["estimator", "perturbation", "uncertainty"])["strength"].idxmin()]
    baseline = baseline.set_index(["estimator", "perturbation", "uncertainty"])["u_mean"].rename("u0")
    long = long.join(baseline, on=["estimator", "perturbation", "uncertainty"])
    long["u_normalised"] = np.where(long["u0"] != 0, long["u_mean"] / long["u0"].where(long["u0"] != 0), np.nan)
    return long.sort_values(["estimator", "perturbation", "uncertainty", "strength"], ignore_index=True)[CURVE_COLUMNS]


def plot_uncertainty_vs_strength(curves: pd.DataFrame, out_base: Path) -> list[Path]:
    """One panel per perturbation type: u(sigma)/u(sigma_0) of each uncertainty (colour) and estimator (MC solid,
    ensemble dashed); grey markers on a right axis: collision rate (%) per strength and estimator."""
    from matplotlib.lines import Line2D

    plt = pyplot()
    perturbations = present_in_order(curves["perturbation"], PERTURBATION_ORDER)
    estimators = present_in_order(curves["estimator"], ESTIMATOR_ORDER)
    colours = {u: plt.get_cmap("tab10")(i) for i, u in enumerate(CURVE_UNCERTAINTIES)}
    figure, axes = panel_grid(len(perturbations))
    for axis, perturbation in zip(axes, perturbations, strict=True):
        data = curves[curves["perturbation"] == perturbation]
        twin = axis.twinx()
        for estimator in estimators:
            rows = data[data["estimator"] == estimator]
            for uncertainty in CURVE_UNCERTAINTIES:
                line = rows[rows["uncertainty"] == uncertainty]
                if line.empty or line["u_normalised"].isna().all():
                    continue
                axis.plot(line["strength"], line["u_normalised"], color=colours[uncertainty],
                          linestyle=LINESTYLES.get(estimator, ":"), linewidth=1.5, marker=".", markersize=4)
            rates = rows.drop_duplicates("strength")
            if rates["collision_rate"].notna().any():
                twin.plot(rates["strength"], 100 * rates["collision_rate"], linestyle="none", color="0.55",
                          marker=MARKERS.get(estimator, "s"), markersize=4, alpha=0.8, clip_on=False)
        axis.axhline(1.0, color="0.8", linewidth=0.8, zorder=0)
        axis.set_title(perturbation_label(perturbation))
        axis.set_xlabel(STRENGTH_LABELS.get(perturbation, "strength"))
        axis.set_ylabel("u_σ / u_σ(0)")
        twin.set_ylabel("collisions (%)", color="0.45")
        twin.tick_params(axis="y", colors="0.45")
        twin.set_ylim(bottom=0)
        axis.grid(alpha=0.3)
    handles = [Line2D([], [], color=colours[u], label=label) for u, label in CURVE_UNCERTAINTIES.items()]
    handles += [Line2D([], [], color="black", linestyle=LINESTYLES.get(e, ":"), label=estimator_label(e))
                for e in estimators]
    handles += [Line2D([], [], color="0.55", linestyle="none", marker=MARKERS.get(e, "s"),
                       label=f"collisions, {estimator_label(e)}") for e in estimators]
    figure.legend(handles=handles, loc="lower center", ncol=min(len(handles), 4), frameon=False)
    legend_inches = 0.25 * math.ceil(len(handles) / 4) + 0.15
    figure.tight_layout(rect=(0, min(0.5, legend_inches / figure.get_figheight()), 1, 1))
    return save_figure(figure, out_base)


def uncertainty_vs_strength_section(context: ReportContext) -> str:
    """Fig. 5's section: uncertainty_vs_strength.png/svg/csv (empty without study records)."""
    episode_means, critical = study_summaries(context)
    if episode_means.empty:
        return ""
    curves = strength_curves(episode_means, critical)
    write_table_atomic(curves, context.out_dir / "uncertainty_vs_strength.csv")
    plot_uncertainty_vs_strength(curves, context.out_dir / "uncertainty_vs_strength")
    return "\n".join([
        "## Uncertainty vs perturbation strength (Fig. 5)",
        "",
        "Normalised episodic mean u_σ / u_σ(0) of the epistemic and aleatoric heading and speed uncertainty vs the "
        "perturbation strength; MC-dropout solid, ensemble dashed. Grey markers (right axis): share of episodes "
        "ending in a collision at that strength (circles MC-dropout, crosses ensemble). A curve is left out where "
        "u_σ(0) = 0.",
        "",
        "![uncertainty vs strength](uncertainty_vs_strength.png)",
        "",
        "Vector version: [uncertainty_vs_strength.svg](uncertainty_vs_strength.svg); data: "
        "[uncertainty_vs_strength.csv](uncertainty_vs_strength.csv) (also the unnormalised means).",
    ])


# --------------------------------------------------------------------------------------------------------------
# Fig. 6: feature uncertainty before a collision vs at the closest approach
# --------------------------------------------------------------------------------------------------------------

def plot_feature_collisions(critical: pd.DataFrame, out_base: Path) -> list[Path]:
    """Rows: estimators; columns: perturbation types. Each panel: box + jittered points of ``w_u_feat`` one step
    before a collision and at the closest approach of the episodes without one (all strengths pooled)."""
    plt = pyplot()
    perturbations = present_in_order(critical["perturbation"], PERTURBATION_ORDER)
    estimators = present_in_order(critical["estimator"], ESTIMATOR_ORDER)
    ncols, nrows = len(perturbations), len(estimators)
    figure, axes = plt.subplots(nrows, ncols, figsize=(3.2 * ncols, 3.3 * nrows), squeeze=False)
    rng = np.random.default_rng(0)
    colours = {True: "tab:red", False: "tab:blue"}
    for r, estimator in enumerate(estimators):
        for c, perturbation in enumerate(perturbations):
            axis = axes[r][c]
            data = critical[(critical["estimator"] == estimator) & (critical["perturbation"] == perturbation)]
            labels = []
            if data.empty:
                axis.text(0.5, 0.5, "no records", transform=axis.transAxes, ha="center", va="center",
                          color="0.5")
            for position, collided in ((1, True), (2, False)):
                values = data.loc[data["collided"].astype(bool) == collided, "value"].to_numpy(float)
                values = values[np.isfinite(values)]
                name = "before collision" if collided else "closest approach"
                labels.append(f"{name}\n(n={len(values)})")
                if not len(values):
                    continue
                axis.boxplot([values], positions=[position], widths=0.5, showfliers=False,
                             medianprops={"color": colours[collided]})
                jitter = rng.uniform(-0.15, 0.15, len(values))
                axis.scatter(position + jitter, values, s=8, color=colours[collided], alpha=0.5, linewidths=0)
            axis.set_xticks([1, 2])
            axis.set_xticklabels(labels, fontsize=8)
            axis.set_xlim(0.4, 2.6)
            axis.set_title(f"{perturbation_label(perturbation)} — {ESTIMATOR_SHORT.get(estimator, estimator)}",
                           fontsize=9)
            axis.grid(alpha=0.3, axis="y")
            if c == 0:
                axis.set_ylabel(f"{estimator_label(estimator)}\nwindowed feature uncertainty")
    figure.tight_layout()
    return save_figure(figure, out_base)


CRITICAL_SUMMARY_COLUMNS = ["estimator", "perturbation", "collisions", "episodes", "median_before_collision",
                            "median_closest_approach", "mean_before_collision", "mean_closest_approach"]


def critical_summary(critical: pd.DataFrame) -> pd.DataFrame:
    """Per (estimator, perturbation): collisions, episodes and the median / mean ``w_u_feat`` before a collision and at
    the closest approach."""
    rows = []
    for (estimator, perturbation), group in critical.groupby(["estimator", "perturbation"], sort=False):
        hit = group["collided"].astype(bool)
        before, closest = group.loc[hit, "value"].astype(float), group.loc[~hit, "value"].astype(float)
        rows.append({"estimator": estimator, "perturbation": perturbation, "collisions": int(hit.sum()),
                     "episodes": len(group),
                     "median_before_collision": before.median() if len(before) else math.nan,
                     "median_closest_approach": closest.median() if len(closest) else math.nan,
                     "mean_before_collision": before.mean() if len(before) else math.nan,
                     "mean_closest_approach": closest.mean() if len(closest) else math.nan})
    return pd.DataFrame(rows, columns=CRITICAL_SUMMARY_COLUMNS)


def _g(value: float) -> str:
    return MISSING if not math.isfinite(value) else f"{value:.3g}"


def feature_uncertainty_collisions_section(context: ReportContext) -> str:
    """Fig. 6's section: feature_uncertainty_collisions.png/svg/csv and its medians (empty without study records)."""
    _, critical = study_summaries(context)
    if critical.empty:
        return ""
    write_table_atomic(critical, context.out_dir / "feature_uncertainty_collisions.csv")
    plot_feature_collisions(critical, context.out_dir / "feature_uncertainty_collisions")
    summary = critical_summary(critical)
    lines = [
        "## Feature uncertainty before a collision vs at the closest approach (Fig. 6)",
        "",
        "Windowed (w = 4) predictive feature uncertainty on the step before a collision (collision episodes: the "
        "uncertainty of the observation the colliding action was chosen from) and at the closest approach to a "
        "human (minimum gap; episodes without a collision), every strength of each perturbation pooled.",
        "",
        "![feature uncertainty before collisions](feature_uncertainty_collisions.png)",
        "",
        "| Estimator | Perturbation | Collisions / episodes | Median before collision | Median at closest approach |",
        "|:--|:--|--:|--:|--:|",
    ]
    ordered = summary.assign(_e=order_rank(summary["estimator"], ESTIMATOR_ORDER),
                             _p=order_rank(summary["perturbation"], PERTURBATION_ORDER)).sort_values(["_e", "_p"])
    for row in ordered.to_dict("records"):
        lines.append(f"| {estimator_label(row['estimator'])} | {perturbation_label(row['perturbation'])} | "
                     f"{row['collisions']} / {row['episodes']} | {_g(row['median_before_collision'])} | "
                     f"{_g(row['median_closest_approach'])} |")
    lines += ["", "Vector version: [feature_uncertainty_collisions.svg](feature_uncertainty_collisions.svg); data: "
                  "[feature_uncertainty_collisions.csv](feature_uncertainty_collisions.csv) (one row per episode)."]
    return "\n".join(lines)
