"""The report page of the perturbation study and the safety layer (experiment kind ``uncertainty``): its sections in
page order -- Table 2 and its claims, Figs. 5-6, Table 3, its cost, ablation and trade-off, thresholds, information.

Each section writes nothing and returns an empty string when its records are absent (a Table 2 run has no safety
records, a Table 3 run may have no study records). Where each part lives:

- `socnav.paper.uncertainty.records`: reading the study, safety and calibration records;
- `socnav.paper.uncertainty.table2`, `socnav.paper.uncertainty.table2_claims`: Table 2 and its claims;
- `socnav.paper.uncertainty.figures`: Figs. 5 and 6;
- `socnav.paper.uncertainty.table3`, `socnav.paper.uncertainty.ablation`,
  `socnav.paper.uncertainty.tradeoff`: Table 3, its cost, its ablation and its trade-off curve;
- `socnav.paper.uncertainty.thresholds`: the calibrated thresholds next to the paper's;
- `socnav.paper.uncertainty.information`: what the uncertainty knows about a collision in the next second;
- `socnav.paper.labels`, `socnav.paper.published`: names and orders, the paper's published numbers.

The functions callers use most are importable from here as well.
"""

from __future__ import annotations

from socnav.experiments.registry import Section, register_section
from socnav.paper.uncertainty.ablation import (
    ablation_markdown,
    ablation_records,
    decisions_frame,
    mcnemar_exact,
    paired_frame,
    table3_ablation_section,
)
from socnav.paper.uncertainty.figures import (
    feature_uncertainty_collisions_section,
    plot_feature_collisions,
    plot_uncertainty_vs_strength,
    strength_curves,
    uncertainty_vs_strength_section,
)
from socnav.paper.uncertainty.information import uncertainty_information_section
from socnav.paper.uncertainty.records import safety_records, study_summaries, summarise_steps
from socnav.paper.uncertainty.table2 import study_metrics_frame, table2_frame, table2_markdown, table2_section
from socnav.paper.uncertainty.table2_claims import table2_claims_section
from socnav.paper.uncertainty.table3 import (
    cost_frame,
    cost_markdown,
    main_records,
    prevented_frame,
    prevented_markdown,
    safety_metrics_frame,
    table3_cost_section,
    table3_section,
)
from socnav.paper.uncertainty.thresholds import calibration_section
from socnav.paper.uncertainty.tradeoff import plot_tradeoff, table3_tradeoff_section, tradeoff_frame

__all__ = [
    "KIND", "PAGE", "ablation_markdown", "ablation_records", "cost_frame", "cost_markdown", "decisions_frame",
    "main_records", "mcnemar_exact", "paired_frame", "plot_feature_collisions", "plot_tradeoff",
    "plot_uncertainty_vs_strength", "prevented_frame", "prevented_markdown", "safety_metrics_frame",
    "safety_records", "strength_curves", "study_metrics_frame", "study_summaries", "summarise_steps", "table2_frame",
    "table2_markdown", "tradeoff_frame",
]

KIND = "uncertainty"

#: The report page of the kind: (section name, section), in page order.
PAGE: list[tuple[str, Section]] = [
    ("table2", table2_section),
    ("table2_claims", table2_claims_section),
    ("uncertainty_vs_strength", uncertainty_vs_strength_section),
    ("feature_uncertainty_collisions", feature_uncertainty_collisions_section),
    ("table3", table3_section),
    ("table3_cost", table3_cost_section),
    ("table3_ablation", table3_ablation_section),
    ("table3_tradeoff", table3_tradeoff_section),
    ("calibration", calibration_section),
    ("uncertainty_information", uncertainty_information_section),
]

for _name, _section in PAGE:
    register_section(KIND, _name)(_section)
