"""Does the uncertainty tell the safety rule anything its proximity terms do not? Diagnostics from a Table 2 run's
study records, and (optionally) the same measured again with MC-dropout at other dropout rates and windows.

    python docs/analysis/uncertainty_information.py runs/table2-quick
    python docs/analysis/uncertainty_information.py runs/table2-quick --try-p-test 0.05 0.1 0.2 0.5 --try-window 1 4 8

Prints, per estimator and perturbation type (all strengths pooled; definitions in
`socnav.paper.uncertainty.information`):

1. the gate: where the proximity terms fire (c_prox and c_ap, the paper's lambda_prox = 0.9, beta1 = 0.5), the share
   of steps where the windowed uncertainty already passes the paper's thresholds (c_ep or c_feat; 100 %: removing
   the uncertainty condition changes nothing), the same at all steps, the windowed values' quantiles there against
   the thresholds, their rank correlation with the gap, and in how many collisions the rule fired at all in the last
   second;
2. how well the rule's two windowed uncertainties and the best of all ten rank the steps followed by a collision
   within 1 s: AUROC alone, among the proximity-firing steps, and the AUROC gain over a proximity-only model, with
   95 % intervals from a bootstrap over episodes.

With ``--try-p-test`` / ``--try-window`` it replays the run's acting policy (the study's MC-dropout policy) on
``--episodes`` fresh episodes (seeds from ``--seed``) at the largest strength of each ``--perturbations`` type, for
every p_test (MC-dropout with K = 20, the study's mask seed), and prints the same for every (p_test, window): the
paper allows both choices (p_test "is crucial", w = 4 steps). One torch thread; about 3 s per 50 episodes.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import pandas as pd

from socnav.paper.labels import MEASURE_LABELS
from socnav.paper.uncertainty.information import (
    MEASURES,
    PROXIMITY_MODEL,
    PROXIMITY_SCORE,
    RULE_MEASURES,
    gate_diagnostics,
    information_table,
    read_study_steps,
)
from socnav.safety.rule import THRESHOLD_PRESETS

pd.set_option("display.width", 200)
pd.set_option("display.max_columns", 30)
RAW = [m for m in MEASURES if not m.startswith("w_")]


def interval(row: pd.Series, name: str) -> str:
    if not np.isfinite(row[name]):
        return "–"
    if not (np.isfinite(row[f"{name}_low"]) and np.isfinite(row[f"{name}_high"])):
        return f"{row[name]:.3f} [n/a]"
    return f"{row[name]:.3f} [{row[f'{name}_low']:.3f}, {row[f'{name}_high']:.3f}]"


def print_gate(steps: pd.DataFrame, thresholds: dict | None = None) -> None:
    diagnostics = gate_diagnostics(steps, thresholds)
    print("\n== The gate where the proximity terms fire (paper thresholds, windowed values, all strengths) ==")
    for row in diagnostics.itertuples():
        print(f"{row.estimator:8s} {row.perturbation:18s} proximity firing {row.proximity_steps:5d} of {row.steps:6d} "
              f"steps; gate open there {row.gate_open_pct:5.1f} % (c_ep {row.c_ep_pct:5.1f}, c_feat "
              f"{row.c_feat_pct:5.1f}); at all steps {row.gate_open_pct_all_steps:5.1f} % (c_ep "
              f"{row.c_ep_pct_all_steps:5.1f}, c_feat {row.c_feat_pct_all_steps:5.1f})")
        print(f"{'':27s} there: w_u_ep_heading p5 {row.w_u_ep_heading_p05_proximity:.3g}, median "
              f"{row.w_u_ep_heading_median_proximity:.3g} (lambda_ep {row.lambda_ep:g}); w_u_feat p5 "
              f"{row.w_u_feat_p05_proximity:.3g}, median {row.w_u_feat_median_proximity:.3g} (lambda_f "
              f"{row.lambda_feat:g}), max anywhere {row.w_u_feat_max:.3g}")
        print(f"{'':27s} Spearman with the gap: w_u_ep_heading {row.spearman_w_u_ep_heading_gap:+.2f}, w_u_feat "
              f"{row.spearman_w_u_feat_gap:+.2f}; collisions {row.collisions}: proximity fired in the last 1 s in "
              f"{row.collisions_proximity_fired_pct:.0f} %, the rule in {row.collisions_rule_fired_pct:.0f} %")
    for estimator, group in steps.groupby("estimator", sort=False):
        quantiles = group[["w_u_ep_heading", "w_u_feat"]].quantile([0.0, 0.01, 0.5, 0.99, 1.0])
        print(f"\n{estimator}: windowed values at every step (quantiles 0, 1, 50, 99, 100 %)")
        print(quantiles.T.to_string(float_format=lambda v: f"{v:.4g}"))


def print_information(table: pd.DataFrame, title: str) -> None:
    print(f"\n== {title} ==")
    pooled = table[table["scope"] == "all"]
    for (estimator, perturbation), cell in pooled.groupby(["estimator", "perturbation"], sort=False):
        first = cell.iloc[0]
        print(f"\n{estimator} / {perturbation}: {first['steps']} steps of {first['episodes']} episodes, "
              f"{first['positives']} positive steps ({first['collision_episodes']} collisions); proximity firing "
              f"{first['proximity_steps']} steps, {first['proximity_positives']} positive")
        measures = [m for m in RULE_MEASURES if m in set(cell["measure"])]
        uncertainties = cell[cell["measure"].isin(MEASURES)]
        if not uncertainties.empty and uncertainties["proximity_auroc"].notna().any():
            best = uncertainties.loc[uncertainties["proximity_auroc"].idxmax(), "measure"]
            measures += [best] if best not in measures else []
        for measure in measures + [PROXIMITY_SCORE, PROXIMITY_MODEL]:
            row = cell[cell["measure"] == measure]
            if row.empty:
                continue
            row = row.iloc[0]
            print(f"  {MEASURE_LABELS.get(measure, measure):28s} AUROC {interval(row, 'auroc'):26s} "
                  f"AUPRC {interval(row, 'auprc'):26s} given proximity: AUROC {interval(row, 'proximity_auroc'):26s} "
                  f"AUPRC {interval(row, 'proximity_auprc'):26s} gain over proximity model "
                  f"{interval(row, 'delta_auroc')}")


def acting_policy(run: Path) -> tuple[Path, dict]:
    """The model file of the study's acting (MC-dropout) policy -- the first training dependency of a study unit --
    and that unit's parameters."""
    units = json.loads((run / "units.json").read_text())
    study = next(u for u in units if u["id"].startswith("study/mc/"))
    return run / study["deps"][0] / "model.zip", study["params"]


def windowed(steps: pd.DataFrame, window: int) -> pd.DataFrame:
    """``w_*`` recomputed from the raw values: the mean of the last min(window, steps so far) values per episode,
    as `socnav.uncertainty.WindowedUncertainty`."""
    steps = steps.sort_values(["strength", "episode", "step"], ignore_index=True)
    grouped = steps.groupby(["strength", "episode"], sort=False)
    for name in RAW:
        steps[f"w_{name}"] = grouped[name].transform(lambda u: u.rolling(window, min_periods=1).mean())
    return steps


def try_changes(run: Path, p_tests: list[float], windows: list[int], perturbations: list[str], episodes: int,
                seed: int, resamples: int) -> None:
    import torch

    import socnav
    from socnav.envs.perturbations import perturbed_config
    from socnav.uncertainty import MC_SEED, MCDropoutEstimator
    from socnav.uncertainty.recording import record_uncertainty

    torch.set_num_threads(1)
    model, params = acting_policy(run)
    policy = socnav.load_policy(str(model))
    units = {u["id"]: u for u in json.loads((run / "units.json").read_text())}
    for p_test in p_tests:
        frames = []
        for perturbation in perturbations:
            strength = max(units[f"study/mc/{perturbation}"]["params"]["strengths"])
            config = perturbed_config(params["env"], perturbation, strength)
            start = time.time()
            estimator = MCDropoutEstimator(policy, k=params["k"], p_test=p_test, seed=MC_SEED)
            steps, records = record_uncertainty(policy, estimator, config, episodes, seed=seed, n_envs=50,
                                                window=max(windows))
            print(f"p_test {p_test:g}, {perturbation} at {strength:g}: {episodes} episodes, "
                  f"{int((records['outcome'] == 'collision').sum())} collisions ({time.time() - start:.0f} s)",
                  flush=True)
            frames.append(steps.assign(estimator=f"mc p={p_test:g}", perturbation=perturbation, strength=strength))
        recorded = pd.concat(frames, ignore_index=True)
        for window in windows:
            steps = windowed(recorded, window)
            print_gate(steps, {f"mc p={p_test:g}": THRESHOLD_PRESETS["mc"][:2]})  # the paper's MC-dropout thresholds
            table = information_table(steps, n_resamples=resamples)
            print_information(table, f"p_test = {p_test:g}, window = {window}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="run directory of a Table 2 experiment (study/*/*/steps.parquet)")
    parser.add_argument("--resamples", type=int, default=1000, help="bootstrap resamples (episodes)")
    parser.add_argument("--try-p-test", type=float, nargs="*", default=[], help="MC-dropout rates to try")
    parser.add_argument("--try-window", type=int, nargs="*", default=[4], help="windows (steps) to try")
    parser.add_argument("--perturbations", nargs="*", default=["observation_noise", "heading_noise", "more_humans"])
    parser.add_argument("--episodes", type=int, default=200, help="episodes per perturbation for the tries")
    parser.add_argument("--seed", type=int, default=100_000, help="first episode seed of the tries (fresh episodes)")
    args = parser.parse_args()
    steps = read_study_steps(sorted(args.run.glob("study/*/*/steps.parquet")))
    if steps.empty:
        raise SystemExit(f"no study records under {args.run}/study")
    print_gate(steps)
    print_information(information_table(steps, n_resamples=args.resamples),
                      f"What the uncertainty knows: {args.run} (all strengths pooled)")
    if args.try_p_test:
        try_changes(args.run, args.try_p_test, args.try_window, args.perturbations, args.episodes, args.seed,
                    args.resamples)


if __name__ == "__main__":
    main()
