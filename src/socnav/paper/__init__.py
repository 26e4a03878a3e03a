"""The paper's experiments, as kinds of the experiment engine (`socnav.experiments`): what each plans, what its units
do and the report page it writes -- the tables, figures and claims of Tables 1-3 and the safety-layer benchmark.

One package per experiment kind, each registered by name in `socnav.experiments.registry.KIND_MODULES`:

- `socnav.paper.table1`: Table 1 (algorithms x training scenarios x seeds, tested in every scenario);
- `socnav.paper.uncertainty`: Table 2 (the perturbation study) and Table 3 (the safety layer), their figures;
- `socnav.paper.safety_benchmark`: every collision trigger calibrated and played on held-out worlds.

What they share: `socnav.paper.train_eval` (the training and evaluation units), `socnav.paper.labels` (names and
orders in tables and figures), `socnav.paper.published` (the paper's published numbers). A new table of a kind is one
module in its package, added to that kind's page (its ``report.PAGE``).
"""
