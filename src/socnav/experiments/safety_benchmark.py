"""The safety-layer benchmark: every trigger calibrated by the same pipeline to the same false-activation budget on
calibration episodes, then played on held-out episodes against the plain policy and the proximity-only rule.

Rows are layers (a trigger, calibrated at a budget, with a fallback); worlds are the unperturbed one, the paper's
perturbation types at strengths the calibration never played, and held-out shifts (``behaviour_shift``: social
force humans; a map scenario). Every layer plays the SAME episodes (seeds) as the plain policy, so collisions are
compared episode by episode:

- ``prevented`` = (plain collisions - layer collisions) / plain collisions, per world and pooled over the paper's
  perturbation types;
- ``false activation`` = fallback steps / steps on the held-out UNPERTURBED episodes;
- the paired difference in collisions against proximity-only (the row to beat) with an exact McNemar test on the
  discordant episodes and a 95 % interval of the difference in collision rate.

`socnav.safety.calibration.trigger_search` chooses the score triggers' thresholds; the rule's rows go through the
rule's own three stages (`socnav.safety.calibration.workflow.calibrate_budgets`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from socnav.config import load_config
from socnav.envs.perturbations import CALIBRATION_SEED, perturbed_config
from socnav.io import write_table_atomic, write_text_atomic
from socnav.safety.calibration.rollout_selection import CalibrationRun, rollout_scores
from socnav.safety.calibration.trigger_search import (
    RISK_TRAINING_SEED,
    calibrate_trigger,
    collect_trigger_records,
    collision_labels,
)
from socnav.safety.calibration.workflow import calibrate_budgets, calibration_runs
from socnav.safety.rule import RULE_CONDITIONS, Thresholds
from socnav.safety.triggers import SafetyDecision, TriggerSpec, decision_fields

__all__ = [
    "ANALYTIC_TRIGGERS",
    "BENCHMARK_ROWS",
    "HELD_OUT_SHIFTS",
    "PAPER_TYPES",
    "BenchmarkSetup",
    "Layer",
    "evaluate_layers",
    "paired_against",
    "run_safety_benchmark",
    "summarize_layers",
]

ANALYTIC_TRIGGERS = ("time-to-collision", "closing-gap", "predicted-clearance", "conformal")
#: The paper's perturbation types at strengths the calibration (socnav.envs.perturbations.CALIBRATION_SET) never
#: plays.
PAPER_TYPES: dict[str, list[float]] = {"observation_noise": [1.0, 2.0], "heading_noise": [1.0, 2.0],
                                       "speed_noise": [1.0], "faster_humans": [4.0, 8.0], "more_humans": [7.0]}
#: Worlds no calibration step resembles: humans of another model, and a map scenario.
HELD_OUT_SHIFTS: dict[str, dict[str, Any]] = {"behaviour_shift": {"perturbation": {"behaviour_shift": 1}},
                                              "corridor": {"scenario": "corridor"}}
#: The benchmark's rows: the rule and its proximity-only ablation, the analytic triggers, the risk model without and
#: with the uncertainty inputs (its ablation).
BENCHMARK_ROWS = ("paper", "proximity-only", *ANALYTIC_TRIGGERS, "risk-model", "risk-model+uncertainty")
RISK_HORIZON_STEPS = 4
FULL_SEARCH_BUDGET = 0.05  # 1 s at the default 0.25 s step: "a collision within the next second"


@dataclass
class BenchmarkSetup:
    """What the benchmark plays: the world ``env`` (a config mapping), the budgets, the episode counts and seeds."""

    env: dict[str, Any]
    budgets: Sequence[float] = (0.05,)
    calibration_episodes: int = 40
    risk_training_episodes: int = 120
    eval_episodes: int = 100
    eval_seed: int = 3_000_000
    sensing: str = "perceived"
    window: int = 4
    n_envs: int = 40
    paper_types: Mapping[str, Sequence[float]] = field(default_factory=lambda: dict(PAPER_TYPES))
    shifts: Mapping[str, Mapping[str, Any]] = field(default_factory=lambda: dict(HELD_OUT_SHIFTS))
    rows: Sequence[str] = BENCHMARK_ROWS
    brake_rows: Sequence[str] = ("proximity-only", "time-to-collision", "conformal")

    def worlds(self) -> dict[str, tuple[str, Any]]:
        """Evaluation worlds: name -> (group, config); group ``unperturbed``, a paper type, or ``shift``."""
        worlds: dict[str, tuple[str, Any]] = {"unperturbed": ("unperturbed", load_config(self.env))}
        for kind, strengths in self.paper_types.items():
            for strength in strengths:
                worlds[f"{kind}={strength:g}"] = (kind, perturbed_config(self.env, kind, strength))
        for name, override in self.shifts.items():
            worlds[name] = ("shift", load_config({**self.env, **override}))
        return worlds


@dataclass(frozen=True)
class Layer:
    """One row of the benchmark: a name, what decides (rule thresholds or a trigger spec), the fallback, and the
    budget it was calibrated at."""

    name: str
    decision: SafetyDecision
    budget: float
    fallback: str = "cautious"


def _training_runs(setup: BenchmarkSetup) -> list[CalibrationRun]:
    """The calibration configurations on their own seed range, for the risk model to learn from."""
    runs = calibration_runs(setup.env, setup.risk_training_episodes)
    return [CalibrationRun(run.config, run.perturbed, run.n_episodes,
                           RISK_TRAINING_SEED + index * setup.risk_training_episodes, run.group)
            for index, run in enumerate(runs)]


def fit_conformal_start(policy: Any, setup: BenchmarkSetup, spec: TriggerSpec) -> TriggerSpec:
    """``spec`` with ``initial_quantile`` the ``1 - alpha`` quantile of the forecast errors on the unperturbed
    calibration episodes (the bound the shield starts each episode with)."""
    from socnav.envs.rollout import rollout_episodes
    from socnav.safety.conformal import ConformalShieldTrigger
    from socnav.safety.safe_policy import SafePolicy, no_uncertainty

    run = calibration_runs(setup.env, setup.calibration_episodes)[0]
    errors: list[np.ndarray] = []
    probe = SafePolicy(policy, no_uncertainty, Thresholds.create(Thresholds.never().model_dump(), sensing=setup.sensing),
                       run.config, window=setup.window)
    shield = ConformalShieldTrigger(spec)

    class _Errors:
        def on_episode_start(self, envs: np.ndarray) -> None:
            if not hasattr(shield, "_quantile"):
                shield.allocate(len(envs))
            shield.reset(np.asarray(envs))

        def on_step(self, observation: Any, actions: Any, result: Any, episodes: np.ndarray) -> None:
            assert probe.last_inputs is not None
            shield.score(probe.last_inputs)
            errors.append(shield.last_errors[episodes >= 0])

    rollout_episodes(probe, run.config, run.n_episodes, seed=run.seed, n_envs=setup.n_envs, observer=_Errors(),
                     metrics=False)
    values = np.concatenate(errors)
    values = values[np.isfinite(values)]
    start = float(np.quantile(values, 1.0 - shield.params.alpha)) if len(values) else 0.0
    return TriggerSpec.create(spec.model_dump(), params={**spec.params, "initial_quantile": round(start, 4)})


def train_risk_models(policy: Any, estimator: Any, setup: BenchmarkSetup, out: Path) -> dict[str, TriggerSpec]:
    """The risk model without and with the uncertainty inputs (the ablation), trained on the risk-training
    seeds; returns name -> spec (threshold inf: calibrated later)."""
    from socnav.safety.risk_model import save_risk_model, train_risk_model

    records, features = collect_trigger_records(policy, estimator, _training_runs(setup), [], setup.window,
                                                setup.n_envs, setup.sensing, features=True, uncertainty=True)
    assert features is not None
    labels = collision_labels(records, RISK_HORIZON_STEPS)
    episodes = records["episode"].to_numpy()
    specs = {}
    geometry = features.shape[1] - 5
    for name, columns, with_uncertainty in (("risk-model", slice(0, geometry), False),
                                            ("risk-model+uncertainty", slice(None), True)):
        model = train_risk_model(features[:, columns], labels, episodes, with_uncertainty, RISK_HORIZON_STEPS)
        path = save_risk_model(model, out / f"{name}.npz")
        specs[name] = TriggerSpec.create(trigger="risk-model", threshold=math.inf, model=str(path),
                                         sensing=setup.sensing)
    return specs


def calibrate_layers(policy: Any, estimator: Any, setup: BenchmarkSetup, out: Path,
                     log: Callable[[str], None] = print) -> list[Layer]:
    """Every trigger calibrated at every budget of ``setup`` on the calibration episodes (the rule's two rows by
    the rule's stages)."""
    layers: list[Layer] = []
    # as Table 3's trade-off curve: the full search at the 5 % budget, the light one at the others (every rule alike)
    light = [budget for budget in setup.budgets if budget != FULL_SEARCH_BUDGET] if (
        FULL_SEARCH_BUDGET in setup.budgets) else []
    for conditions in [row for row in ("paper", "proximity-only", "uncertainty-only") if row in setup.rows]:
        log(f"calibrating the rule ({conditions})")
        per_budget = calibrate_budgets(policy, None if conditions == "proximity-only" else estimator, setup.env,
                                       setup.calibration_episodes, setup.budgets, sensing=setup.sensing,
                                       conditions=conditions, window=setup.window, light=light)
        layers += [Layer(conditions, thresholds, budget) for budget, (thresholds, _report) in per_budget.items()]
    specs = {name: TriggerSpec.create(trigger=name, threshold=math.inf, sensing=setup.sensing)
             for name in setup.rows if name not in RULE_CONDITIONS and not name.startswith("risk-model")}
    if "conformal" in specs:
        specs["conformal"] = fit_conformal_start(policy, setup, specs["conformal"])
    if any(name.startswith("risk-model") for name in setup.rows):
        log("training the risk models")
        risk = train_risk_models(policy, estimator, setup, out)
        specs.update({name: spec for name, spec in risk.items() if name in setup.rows})
    runs = calibration_runs(setup.env, setup.calibration_episodes)
    plain = rollout_scores(None, policy, None, runs, setup.window, setup.n_envs)["collisions"]
    analytic = [spec for name, spec in specs.items() if name in ANALYTIC_TRIGGERS]
    records, _ = collect_trigger_records(policy, None, runs, analytic, setup.window, setup.n_envs, setup.sensing)
    for name, spec in specs.items():
        if name not in ANALYTIC_TRIGGERS:  # the risk model's two rows share a trigger name: one column at a time
            one, _ = collect_trigger_records(policy, estimator if spec.uses_uncertainty else None, runs, [spec],
                                             setup.window, setup.n_envs, setup.sensing)
            records[f"score_{spec.trigger}"] = one[f"score_{spec.trigger}"].to_numpy()
        replayed: dict[Any, dict[str, Any]] = {}  # a threshold proposed at two budgets is replayed once
        for budget in setup.budgets:
            log(f"calibrating {name} at {budget:.0%}")
            chosen, _table = calibrate_trigger(spec, records, policy, estimator if spec.uses_uncertainty else None,
                                               runs, budget, setup.window, setup.n_envs, plain_collisions=plain,
                                               cache=replayed)
            layers.append(Layer(name, chosen, budget))
    return layers


def evaluate_layers(policy: Any, estimator: Any, layers: Sequence[Layer], setup: BenchmarkSetup,
                    log: Callable[[str], None] = print) -> pd.DataFrame:
    """One row per (world, layer, episode), the plain policy as layer ``plain``: ``collided``, ``goal``,
    ``length``, ``fallback_steps``."""
    from socnav.envs.rollout import rollout_episodes
    from socnav.safety.safe_policy import FallbackCounter, SafePolicy

    parts = []
    for world, (group, config) in setup.worlds().items():
        log(f"evaluating in {world}")
        for layer in [None, *layers]:
            if layer is None:
                records = rollout_episodes(policy, config, setup.eval_episodes, seed=setup.eval_seed,
                                           n_envs=setup.n_envs, metrics=False)
                fallbacks = np.zeros(len(records), dtype=np.int64)
            else:
                restart = getattr(estimator, "restart", None)
                if callable(restart):
                    restart()
                reads = layer.decision.uses_uncertainty
                safe = SafePolicy(policy, estimator if reads else None, layer.decision, config, window=setup.window,
                                  fallback=layer.fallback)
                counter = FallbackCounter(safe)
                records = rollout_episodes(safe, config, setup.eval_episodes, seed=setup.eval_seed,
                                           n_envs=setup.n_envs, observer=counter, metrics=False)
                fallbacks = np.asarray(counter.per_episode(records["episode"]))
            parts.append(pd.DataFrame({
                "world": world, "group": group, "layer": "plain" if layer is None else layer.name,
                "budget": 0.0 if layer is None else layer.budget,
                "fallback": "" if layer is None else layer.fallback,
                "episode": records["episode"].to_numpy(), "collided": (records["outcome"] == "collision").to_numpy(),
                "goal": (records["outcome"] == "goal").to_numpy(), "length": records["length"].to_numpy(),
                "fallback_steps": fallbacks}))
    return pd.concat(parts, ignore_index=True)


def paired_against(episodes: pd.DataFrame, layer: tuple[str, float, str], baseline: tuple[str, float, str],
                   worlds: Sequence[str]) -> dict[str, float]:
    """Collisions of ``layer`` minus ``baseline`` over the same episodes of ``worlds``: the difference in collision
    rate, its 95 % interval (Wald on the paired differences), and the exact McNemar p-value (two-sided binomial test
    on the discordant episodes)."""
    from scipy.stats import binomtest

    def pick(key: tuple[str, float, str]) -> pd.Series:
        name, budget, fallback = key
        rows = episodes[(episodes["layer"] == name) & np.isclose(episodes["budget"], budget)
                        & (episodes["fallback"] == fallback) & episodes["world"].isin(worlds)]
        return rows.set_index(["world", "episode"])["collided"].astype(int)

    x, y = pick(layer).align(pick(baseline), join="inner")
    difference = (x - y).to_numpy()
    n = len(difference)
    if n == 0:
        return {"difference": math.nan, "low": math.nan, "high": math.nan, "p": math.nan, "episodes": 0}
    mean = float(difference.mean())
    half = 1.96 * float(difference.std(ddof=1)) / math.sqrt(n) if n > 1 else math.inf
    worse, better = int((difference > 0).sum()), int((difference < 0).sum())
    p = float(binomtest(better, worse + better).pvalue) if worse + better else 1.0
    return {"difference": mean, "low": mean - half, "high": mean + half, "p": p, "episodes": n,
            "fewer": better, "more": worse}


def summarize_layers(episodes: pd.DataFrame) -> pd.DataFrame:
    """Per layer (name, budget, fallback): false activation on the unperturbed episodes, collisions prevented per
    world group and pooled over the paper's types, goal rate, and the paired difference against proximity-only
    at the same budget and fallback."""
    plain = episodes[episodes["layer"] == "plain"]
    paper_worlds = sorted(plain.loc[~plain["group"].isin(["unperturbed", "shift"]), "world"].unique())
    shift_worlds = sorted(plain.loc[plain["group"] == "shift", "world"].unique())
    rows = []
    keys = episodes[["layer", "budget", "fallback"]].drop_duplicates().itertuples(index=False)
    for name, budget, fallback in keys:
        mine = episodes[(episodes["layer"] == name) & np.isclose(episodes["budget"], budget)
                        & (episodes["fallback"] == fallback)]
        unperturbed = mine[mine["group"] == "unperturbed"]
        row: dict[str, Any] = {"layer": name, "budget": budget, "fallback": fallback,
                               "false_activation_pct": 100.0 * unperturbed["fallback_steps"].sum()
                               / max(unperturbed["length"].sum(), 1),
                               "goal_pct": 100.0 * mine["goal"].mean()}
        for label, worlds in [("paper_types", paper_worlds), ("unperturbed", ["unperturbed"])] + [
                (world, [world]) for world in shift_worlds]:
            ours = int(mine.loc[mine["world"].isin(worlds), "collided"].sum())
            theirs = int(plain.loc[plain["world"].isin(worlds), "collided"].sum())
            row[f"collisions_{label}"] = ours
            row[f"prevented_{label}_pct"] = 100.0 * (theirs - ours) / theirs if theirs else math.nan
        if name != "plain":
            versus = paired_against(episodes, (name, budget, fallback), ("proximity-only", budget, "cautious"),
                                    paper_worlds)
            row.update({f"vs_proximity_{key}": value for key, value in versus.items()})
        rows.append(row)
    table = pd.DataFrame(rows)
    table.attrs["plain_collisions_paper_types"] = int(plain.loc[plain["world"].isin(paper_worlds), "collided"].sum())
    return table


def run_safety_benchmark(policy: Any, estimator: Any, setup: BenchmarkSetup, out: str | Path,
                         log: Callable[[str], None] = print) -> pd.DataFrame:
    """Calibrate every layer, add the best score trigger with the brake fallback, evaluate on the held-out worlds,
    and write ``layers.yaml``, ``episodes.csv`` and ``summary.csv`` in ``out``. Returns the summary."""
    import yaml

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    layers = calibrate_layers(policy, estimator, setup, out, log)
    write_text_atomic(out / "layers.yaml", yaml.safe_dump(
        [{"name": layer.name, "budget": layer.budget, **decision_fields(layer.decision)} for layer in layers],
        sort_keys=False))
    brakes = [Layer(layer.name, layer.decision, layer.budget, "brake") for layer in layers
              if layer.name in setup.brake_rows]
    episodes = evaluate_layers(policy, estimator, [*layers, *brakes], setup, log)
    write_table_atomic(episodes, out / "episodes.csv")
    summary = summarize_layers(episodes)
    write_table_atomic(summary, out / "summary.csv")
    return summary


#: The episodes the benchmark never shares with the calibration: evaluation seeds start far above these.
assert CALIBRATION_SEED < RISK_TRAINING_SEED < 3_000_000
