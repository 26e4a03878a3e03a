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
from socnav.envs.perturbations import perturbation_override, perturbed_config
from socnav.io import write_table_atomic, write_text_atomic
from socnav.safety.calibration.trigger_search import (
    ANALYTIC_TRIGGERS,
    calibrate_score_triggers,
    prepare_triggers,
)
from socnav.safety.calibration.workflow import calibrate_budgets
from socnav.safety.rule import RULE_CONDITIONS, Thresholds
from socnav.safety.triggers import SafetyDecision, decision_fields, never_fires

__all__ = [
    "ANALYTIC_TRIGGERS",
    "BENCHMARK_ROWS",
    "HELD_OUT_SHIFTS",
    "PAPER_TYPES",
    "BenchmarkSetup",
    "Layer",
    "evaluate_layers",
    "paired_against",
    "replay_shift",
    "run_safety_benchmark",
    "summarize_layers",
]

#: The paper's perturbation types at strengths the calibration (socnav.envs.perturbations.CALIBRATION_SET) never
#: plays.
PAPER_TYPES: dict[str, list[float]] = {"observation_noise": [1.0, 2.0], "heading_noise": [1.0, 2.0],
                                       "speed_noise": [1.0], "faster_humans": [4.0, 8.0], "more_humans": [7.0]}
#: Worlds no calibration step resembles: humans of another model, and a map scenario (its humans on the scenario's
#: straight legs, as the benchmark was first measured: the global planner, on by default among walls, came later).
HELD_OUT_SHIFTS: dict[str, dict[str, Any]] = {
    "behaviour_shift": {"perturbation": perturbation_override("behaviour_shift", 1)},
    "corridor": {"scenario": "corridor", "planner": {"enabled": False}}}


def replay_shift(files: Sequence[str | Path]) -> dict[str, dict[str, Any]]:
    """The held-out shift ``replay``: recorded pedestrians (ETH/UCY trajectory files, docs/humans.md) walk through
    the robot's world instead of simulated humans; ``{}`` without files (no recording ships with socnav)."""
    if not files:
        return {}
    return {"replay": {"scenario": "replay", "n_humans": None,
                       "humans": {"model": "replay", "replay": {"files": [str(path) for path in files]}}}}
#: The benchmark's rows: the rule and its proximity-only ablation, the analytic triggers, the risk model without and
#: with the uncertainty inputs (its ablation).
BENCHMARK_ROWS = ("paper", "proximity-only", *ANALYTIC_TRIGGERS, "risk-model", "risk-model+uncertainty")
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
    #: what the calibration measured of it on the calibration episodes (prevented_worst, prevented_fraction,
    #: false_activation_upper): the only scores a choice between layers may read
    calibration: dict[str, float] = field(default_factory=dict, hash=False, compare=False)


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
        layers += [Layer(conditions, thresholds, budget, calibration={
            key: float(report.get(key, math.nan)) for key in CALIBRATION_SCORES})
            for budget, (thresholds, report) in per_budget.items()]
    scored = [row for row in setup.rows if row not in RULE_CONDITIONS]
    if scored:
        specs = prepare_triggers(scored, policy, estimator, setup.env, setup.calibration_episodes,
                                 setup.risk_training_episodes, setup.sensing, setup.window, setup.n_envs, out, log)
        scores: dict[str, dict[float, dict[str, float]]] = {}
        chosen = calibrate_score_triggers(specs, policy, estimator, setup.env, setup.calibration_episodes,
                                          setup.budgets, setup.sensing, setup.window, setup.n_envs, log=log,
                                          scores=scores)
        layers += [Layer(name, spec, budget, calibration=scores[name][budget]) for name, per_budget in chosen.items()
                   for budget, spec in per_budget.items()]
    return layers


def evaluate_layers(policy: Any, estimator: Any, layers: Sequence[Layer], setup: BenchmarkSetup,
                    log: Callable[[str], None] = print) -> pd.DataFrame:
    """One row per (world, layer, episode), the plain policy as layer ``plain``: ``collided``, ``goal``,
    ``length``, ``fallback_steps``."""
    from socnav.envs.rollout import rollout_episodes
    from socnav.safety.safe_policy import FallbackCounter, SafePolicy, no_uncertainty

    parts = []
    for world, (group, config) in setup.worlds().items():
        log(f"evaluating in {world}")
        for layer in [None, STAND_STILL, *layers]:
            at_end = None
            if layer is None or layer is STAND_STILL:
                actor = policy if layer is None else _StandStill()
                records = rollout_episodes(actor, config, setup.eval_episodes, seed=setup.eval_seed,
                                           n_envs=setup.n_envs, metrics=False)
                fallbacks = np.zeros(len(records), dtype=np.int64)
            else:
                restart = getattr(estimator, "restart", None)
                if callable(restart):
                    restart()
                # a layer the calibration switched off (no collision to learn from) never fires: no estimate needed
                reads = layer.decision.uses_uncertainty and not never_fires(layer.decision)
                # The benchmark compares what decides the hand-over for people; the wall stop (the same for every
                # trigger) would turn the plain policy's wall collisions in the corridor shift into episodes that go
                # on, and the people collisions it then meets into every trigger's column alike.
                safe = SafePolicy(policy, estimator if reads else no_uncertainty, layer.decision, config,
                                  window=setup.window, fallback=layer.fallback, wall_stop=False)
                counter = FallbackCounter(safe)
                records = rollout_episodes(safe, config, setup.eval_episodes, seed=setup.eval_seed,
                                           n_envs=setup.n_envs, observer=counter, metrics=False)
                fallbacks = np.asarray(counter.per_episode(records["episode"]))
                at_end = [counter.drove_at(e, n - 1) for e, n in zip(records["episode"], records["length"],
                                                                      strict=True)]
            parts.append(pd.DataFrame({
                "world": world, "group": group, "layer": "plain" if layer is None else layer.name,
                "budget": 0.0 if layer is None else layer.budget,
                "fallback": "" if layer is None or layer is STAND_STILL else layer.fallback,
                "episode": records["episode"].to_numpy(), "collided": (records["outcome"] == "collision").to_numpy(),
                "goal": (records["outcome"] == "goal").to_numpy(), "length": records["length"].to_numpy(),
                "fallback_steps": fallbacks,
                # the fallback drove the step that ended the episode: with the brake, a collision the robot could
                # not avoid by stopping when the trigger fired
                "fallback_at_end": np.zeros(len(records), bool) if at_end is None else np.asarray(at_end)}))
    return pd.concat(parts, ignore_index=True)


class _StandStill:
    """A robot that never moves (the brake action at every step): the collisions no robot can avoid by stopping."""

    def predict(self, observation: Any, state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[np.ndarray, Any]:
        from socnav.safety.safe_policy import BRAKE_ACTION

        return np.tile(BRAKE_ACTION, (np.asarray(observation["robot"]).shape[0], 1)), None


#: The reference row of a robot that stands still the whole episode (its collisions: the benchmark's floor).
STAND_STILL = Layer("stand-still", Thresholds.never(), 0.0, "")
#: Rows that are references, not safety layers: no comparison with proximity-only.
REFERENCE_ROWS = ("plain", "stand-still")


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
    world group and pooled over the paper's types, the collisions over the paper's types in episodes where the
    robot that never moves is hit too (``collisions_unavoidable``: no fallback that stops avoids them), goal rate,
    and the paired difference against proximity-only at the same budget (cautious fallback)."""
    episodes = episodes.assign(fallback=episodes["fallback"].fillna(""))  # a CSV reads the references' '' as NaN
    plain = episodes[episodes["layer"] == "plain"]
    paper_worlds = sorted(plain.loc[~plain["group"].isin(["unperturbed", "shift"]), "world"].unique())
    # an episode in which the robot that never moves is walked into: no fallback that stops can avoid that collision
    same_episode = [column for column in ("train_seed", "world", "episode") if column in episodes]
    still = episodes[(episodes["layer"] == "stand-still") & episodes["collided"]]
    unavoidable = pd.MultiIndex.from_frame(still[same_episode]) if len(still) else None
    shift_worlds = sorted(plain.loc[plain["group"] == "shift", "world"].unique())
    rows = []
    keys = episodes[["layer", "budget", "fallback"]].drop_duplicates().itertuples(index=False)
    for name, budget, fallback in keys:
        mine = episodes[(episodes["layer"] == name) & np.isclose(episodes["budget"], budget)
                        & (episodes["fallback"] == fallback)]
        unperturbed = mine[mine["group"] == "unperturbed"]
        typed = mine[mine["world"].isin(paper_worlds)]
        row: dict[str, Any] = {"layer": name, "budget": budget, "fallback": fallback,
                               # over the paper's types, as the collisions column beside it
                               "collisions_fallback_driving": int((typed["collided"] & typed["fallback_at_end"]).sum())
                               if "fallback_at_end" in typed else 0,
                               "collisions_unavoidable": 0 if unavoidable is None else int(
                                   (typed["collided"] & pd.MultiIndex.from_frame(typed[same_episode])
                                    .isin(unavoidable)).sum()),
                               "false_activation_pct": 100.0 * unperturbed["fallback_steps"].sum()
                               / max(unperturbed["length"].sum(), 1),
                               "goal_pct": 100.0 * mine["goal"].mean()}
        for label, worlds in [("paper_types", paper_worlds), ("unperturbed", ["unperturbed"])] + [
                (world, [world]) for world in shift_worlds]:
            ours = int(mine.loc[mine["world"].isin(worlds), "collided"].sum())
            theirs = int(plain.loc[plain["world"].isin(worlds), "collided"].sum())
            row[f"collisions_{label}"] = ours
            row[f"prevented_{label}_pct"] = 100.0 * (theirs - ours) / theirs if theirs else math.nan
        if name not in REFERENCE_ROWS:
            versus = paired_against(episodes, (name, budget, fallback), ("proximity-only", budget, "cautious"),
                                    paper_worlds)
            row.update({f"vs_proximity_{key}": value for key, value in versus.items()})
        rows.append(row)
    table = pd.DataFrame(rows)
    table.attrs["plain_collisions_paper_types"] = int(plain.loc[plain["world"].isin(paper_worlds), "collided"].sum())
    return table


LAYERS_FILE = "layers.yaml"
#: The calibration's measurements of a layer kept with it (`Layer.calibration`).
CALIBRATION_SCORES = ("prevented_worst", "prevented_fraction", "false_activation_upper")


def layer_record(layer: Layer) -> dict[str, Any]:
    """A layer as a file record (:func:`load_layers` reads it back): name, budget, fallback, the decision's kind
    (``rule`` or ``trigger``) and its fields, and the flat fields of a table row."""
    kind = "rule" if isinstance(layer.decision, Thresholds) else "trigger"
    return {"name": layer.name, "budget": layer.budget, "fallback": layer.fallback, "kind": kind,
            "decision": layer.decision.model_dump(), "row": decision_fields(layer.decision),  # inf stays .inf
            "calibration": dict(layer.calibration)}


def load_layers(path: Path) -> list[Layer]:
    """The layers :func:`run_safety_benchmark` calibrated and wrote (a risk model's file must still be there)."""
    import yaml

    from socnav.safety.triggers import TriggerSpec

    records = yaml.safe_load(path.read_text())
    return [Layer(record["name"], Thresholds.create(record["decision"]) if record["kind"] == "rule"
                  else TriggerSpec.create(record["decision"]), float(record["budget"]), record["fallback"],
                  {key: float(value) for key, value in (record.get("calibration") or {}).items()})
            for record in records]


def run_safety_benchmark(policy: Any, estimator: Any, setup: BenchmarkSetup, out: str | Path,
                         log: Callable[[str], None] = print) -> pd.DataFrame:
    """Calibrate every layer (or read them from ``out/layers.yaml``, written when the calibration finished: an
    interrupted run keeps it), add the rows of `setup.brake_rows` with the brake fallback, evaluate on the held-out
    worlds, and write ``episodes.csv`` and ``summary.csv`` in ``out``. Returns the summary."""
    import yaml

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    saved = out / LAYERS_FILE
    if saved.is_file():  # an interrupted run: the calibration is kept, only the evaluation is played again
        layers = load_layers(saved)
        log(f"calibrated layers read from {saved}")
    else:
        layers = calibrate_layers(policy, estimator, setup, out, log)
        write_text_atomic(saved, yaml.safe_dump([layer_record(layer) for layer in layers], sort_keys=False))
    brakes = [Layer(layer.name, layer.decision, layer.budget, "brake") for layer in layers  # calibrated with the
              if layer.name in setup.brake_rows]                                               # cautious fallback
    episodes = evaluate_layers(policy, estimator, [*layers, *brakes], setup, log)
    write_table_atomic(episodes, out / "episodes.csv")
    summary = summarize_layers(episodes)
    write_table_atomic(summary, out / "summary.csv")
    return summary

