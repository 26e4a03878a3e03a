"""The steps of `socnav demo` (the command prints what they return): the baseline controllers in every scenario
(`baseline_rows`), a learned policy in the world it was trained in (`train_policy`, `learned_policy_row`), the
shipped map policy in the doorway inside its safety layer (`map_policy_rows`), each with an animation, and the
safety part: the learned policy under a perturbation, with and without the safety layer, on the same episodes; the
collisions it prevents, how often its fallback drives, and an episode it saves.

Where a step takes ``progress``, it is a `ProgressBar`: ``progress(label, total)`` returns a context manager that
shows one bar while its evaluation runs and yields the callback advanced by finished episodes.

The perturbation is heading noise (the robot's turns go astray). Its strength is chosen by a quick measurement on
screening episodes disjoint from the demo's: the strength among `STRENGTHS` at which the plain policy collides most
(the layer has the most to prevent there). The safety layer is MC-dropout with the paper's thresholds
(``Thresholds.preset("mc")``); beside it, on the same episodes, the layers of `COMPARISONS`: proximity-only (the
row the safety-layer benchmark asks every trigger to beat) and the trigger the benchmark recommends, both calibrated
for the shipped policy at the 5 % false-activation budget (files in ``socnav/data``, made by the commands in its
README).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from contextlib import AbstractContextManager, nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pandas as pd

from socnav.config import EnvConfig, load_config

if TYPE_CHECKING:
    from socnav.rl.training import TrainResult

__all__ = ["BASELINES", "COMPARISONS", "MAP_POLICY", "MAP_POLICY_LAYER", "MAP_SCENARIO", "PERTURBATION", "STRENGTHS",
           "TRAINING_WORLD", "ProgressBar",
           "SafetyDemo", "animate_baseline", "animate_learned_policy", "animate_map_baseline", "animate_map_policy",
           "animate_saved_episode", "baseline_rows", "choose_strength", "comparison_file", "describe",
           "find_saved_episode", "learned_policy_row", "map_policy_rows", "safety_demo", "summary_rows",
           "train_policy", "write_safety_records"]

#: ``progress(label, total)``: a context manager showing one progress bar, yielding its ``advance(n)`` callback.
ProgressBar = Callable[[str, int], AbstractContextManager[Callable[[int], None]]]
#: A metrics-table row: (run name, `socnav.envs.rollout.summarize` of its records).
Row = tuple[str, dict[str, Any]]

BASELINES = ("orca", "straight")  # the non-learned controllers run in every scenario
N_ENVS = 32  # environments stepped together in the demo's evaluations
TRAINING_WORLD = {"scenario": "position_swap", "n_humans": 1}  # where `socnav demo --train-steps` trains a policy
MAP_SCENARIO = "doorway"  # the map scenario the demo animates, the planned path drawn
MAP_POLICY = "pretrained-maps"  # the shipped map policy, played in MAP_SCENARIO inside MAP_POLICY_LAYER
MAP_POLICY_LAYER = "pretrained-maps_time-to-collision.yaml"  # its safety layer (socnav/data; the wall stop is on)

PERTURBATION = "heading_noise"
STRENGTHS = (0.2, 0.4, 0.8)  # rad; above ~1 the robot rarely reaches its goal at all, with or without the layer
SCREEN_EPISODES = 50
SCREEN_SEED = 900_000  # screening episodes: disjoint from the demo's (seed .. seed + episodes - 1)
MC_SAMPLES = 20
THRESHOLDS = "mc"
#: label -> the shipped trigger file (socnav/data) the demo plays beside the paper's rule
COMPARISONS = {"proximity-only": "pretrained_proximity-only.yaml",
               "time to collision": "pretrained_time-to-collision.yaml"}


@dataclass
class SafetyDemo:
    """What the safety demo measured (records: one row per episode, `fallback_steps` on the safe ones)."""

    config: EnvConfig
    strength: float
    screening: dict[float, int]  # strength -> plain-policy collisions in the screening episodes
    plain: pd.DataFrame
    safe: pd.DataFrame
    saved: list[int] = field(default_factory=list)  # seeds where the plain policy collides and the safe one not
    caused: list[int] = field(default_factory=list)  # seeds where only the safe policy collides
    #: label -> the records of a `COMPARISONS` layer on the same episodes (`fallback_steps` included)
    comparisons: dict[str, pd.DataFrame] = field(default_factory=dict)

    @property
    def prevented(self) -> int:
        """Collisions prevented, net: plain-policy collisions minus safe-policy collisions."""
        return int((self.plain["outcome"] == "collision").sum() - (self.safe["outcome"] == "collision").sum())

    @property
    def fallback_share(self) -> float:
        """Share of the safe episodes' steps on which the cautious controller drove."""
        from socnav.safety import fallback_percent

        return fallback_percent(self.safe) / 100.0


def _rollout(policy: Any, config: EnvConfig, episodes: int, seed: int, n_envs: int, label: str,
             progress: ProgressBar | None) -> pd.DataFrame:
    """`rollout_episodes` of `policy`, shown as the progress bar `label` when `progress` is given."""
    from socnav.envs.rollout import rollout_episodes

    with (progress(label, episodes) if progress is not None else nullcontext(None)) as advance:
        return rollout_episodes(policy, config, episodes, seed=seed, n_envs=n_envs, progress=advance)


def baseline_rows(out: Path, episodes: int, seed: int, n_envs: int = N_ENVS,
                  progress: ProgressBar | None = None) -> list[Row]:
    """Every `BASELINES` controller in every scenario (its default world), `episodes` episodes each from seed
    `seed`; writes each run's records to OUT/<controller>_<scenario>.csv and returns the metrics-table rows,
    named "<controller> / <scenario>"."""
    from socnav.controllers import make_controller
    from socnav.envs.rollout import summarize
    from socnav.io import write_table_atomic
    from socnav.sim.metrics import DEFAULT_METRICS
    from socnav.sim.scenarios import scenario_names
    from socnav.sim.walls import has_walls

    rows = []
    for scenario in scenario_names(self_contained=True):
        config = load_config({"scenario": scenario})
        for name in BASELINES:
            label = f"{name} / {scenario}"
            records = _rollout(make_controller(name, config), config, episodes, seed, n_envs, label, progress)
            write_table_atomic(records, Path(out) / f"{name}_{scenario}.csv")
            walls = ("collision_obstacle_pct",) if has_walls(config) else ()  # a map scenario: wall hits apart
            rows.append((label, summarize(records, metrics=DEFAULT_METRICS + walls)))
    return rows


def animate_baseline(out: Path, seed: int) -> tuple[Path, dict[str, Any]]:
    """One ORCA episode (seed `seed`) of circle crossing as OUT/orca_circle_crossing.gif; returns
    `animate_episode`'s (path, summary)."""
    from socnav.cli.workflows.animation import animate_episode
    from socnav.controllers import make_controller

    config = load_config({"scenario": "circle_crossing"})
    return animate_episode(make_controller("orca", config), None, config, Path(out) / "orca_circle_crossing.gif",
                           seed=seed, policy_label="ORCA robot")


def animate_map_baseline(out: Path, seed: int) -> tuple[Path, dict[str, Any]]:
    """One ORCA episode (seed `seed`) of `MAP_SCENARIO` as OUT/orca_<scenario>.gif, the robot's planned path and its
    subgoal drawn (the global planner, docs/maps.md); returns `animate_episode`'s (path, summary)."""
    from socnav.cli.workflows.animation import animate_episode
    from socnav.controllers import make_controller

    config = load_config({"scenario": MAP_SCENARIO})
    return animate_episode(make_controller("orca", config), None, config, Path(out) / f"orca_{MAP_SCENARIO}.gif",
                           seed=seed, policy_label="ORCA robot, global planner")


def train_policy(out: Path, seed: int, timesteps: int) -> TrainResult:
    """Train a fresh ODV-PPO-Drop policy in `TRAINING_WORLD` for `timesteps` steps, the run in OUT/odv_ppo_drop
    (with its own progress display); the run of an earlier demo there is moved aside to
    ``odv_ppo_drop.old-<timestamp>``, never overwritten. Raises `socnav.rl.training.TrainingInterrupted` when
    stopped."""
    from socnav.rl.training import train

    return train(load_config(TRAINING_WORLD), "odv-ppo-drop", seed, timesteps, Path(out) / "odv_ppo_drop",
                 progress=True, force=True)


def learned_policy_row(policy: Any, label: str, out: Path, episodes: int, seed: int, n_envs: int = N_ENVS,
                       progress: ProgressBar | None = None) -> tuple[EnvConfig, Row]:
    """`policy` in the world it was trained in (`socnav.rl.persistence.training_world`), `episodes` episodes from
    seed `seed`; writes the records to OUT/odv_ppo_drop_<scenario>.csv and returns (that world, its metrics-table
    row named `label`)."""
    from socnav.envs.rollout import summarize
    from socnav.io import write_table_atomic
    from socnav.rl.persistence import training_world

    world = load_config(training_world(policy)[0])
    records = _rollout(policy, world, episodes, seed, n_envs, f"{label} / {world.scenario}", progress)
    write_table_atomic(records, Path(out) / f"odv_ppo_drop_{world.scenario}.csv")
    return world, (label, summarize(records))


def animate_learned_policy(policy: Any, world: EnvConfig, out: Path, seed: int, label: str
                           ) -> tuple[Path, dict[str, Any]]:
    """One episode (seed `seed`) of `policy` in `world` as OUT/odv_ppo_drop_<scenario>.gif; returns
    `animate_episode`'s (path, summary)."""
    from socnav.cli.workflows.animation import animate_episode

    return animate_episode(policy, None, world, Path(out) / f"odv_ppo_drop_{world.scenario}.gif", seed=seed,
                           policy_label=label)


def map_policy_rows(out: Path, episodes: int, seed: int, n_envs: int = N_ENVS,
                    progress: ProgressBar | None = None) -> tuple[EnvConfig, list[Row]]:
    """The shipped map policy (`MAP_POLICY`) in `MAP_SCENARIO`, alone and inside its safety layer
    (`MAP_POLICY_LAYER`: time to collision at 2 s, the wall stop) on the same `episodes` episodes from seed `seed`;
    writes OUT/pretrained-maps_<scenario>.csv and OUT/pretrained-maps_<scenario>_safety.csv (`fallback_steps`
    included) and returns (the world, the two metrics-table rows)."""
    from socnav.envs.rollout import summarize
    from socnav.io import write_table_atomic
    from socnav.rl.persistence import load_policy
    from socnav.safety import SafePolicy, fallback_percent
    from socnav.sim.metrics import DEFAULT_METRICS

    policy = load_policy(MAP_POLICY)
    world = load_config(policy.socnav_metadata["env_config"], scenario=MAP_SCENARIO)
    label = f"{MAP_POLICY} / {world.scenario}"
    alone = _rollout(policy, world, episodes, seed, n_envs, label, progress)
    layer = SafePolicy(policy, None, str(comparison_file(MAP_POLICY_LAYER)), world)  # reads no uncertainty
    with (progress(f"{label} + layer", episodes) if progress is not None else nullcontext(None)) as advance:
        safe = _with_layer(layer, world, episodes, seed, n_envs, advance)
    base = Path(out) / f"{MAP_POLICY}_{world.scenario}"
    write_table_atomic(alone, base.with_name(base.name + ".csv"))
    write_table_atomic(safe, base.with_name(base.name + "_safety.csv"))
    metrics = (*DEFAULT_METRICS, "collision_obstacle_pct")
    return world, [(label, summarize(alone, metrics=metrics)),
                   (f"{label} + safety layer", {**summarize(safe, metrics=metrics),
                                                "fallback_pct": fallback_percent(safe)})]


def animate_map_policy(world: EnvConfig, out: Path, seed: int) -> tuple[Path, dict[str, Any]]:
    """One episode (seed `seed`) of the shipped map policy inside its safety layer in `world` (`map_policy_rows`'s)
    as OUT/pretrained-maps_<scenario>.gif, its planned path and subgoal drawn; returns `animate_episode`'s (path,
    summary)."""
    from socnav.cli.workflows.animation import animate_episode
    from socnav.rl.persistence import load_policy
    from socnav.uncertainty import MC_SEED, MCDropoutEstimator

    policy = load_policy(MAP_POLICY)
    # the layer reads no uncertainty; the bars show the policy's own (MC dropout), as the other animations do
    estimator = MCDropoutEstimator(policy, k=MC_SAMPLES, seed=MC_SEED)
    return animate_episode(policy, estimator, world, Path(out) / f"{MAP_POLICY}_{world.scenario}.gif",
                           seed=seed, thresholds=comparison_file(MAP_POLICY_LAYER), policy_label=MAP_POLICY,
                           safety_label="time to collision 2 s, wall stop")


def comparison_file(name: str) -> Path:
    """The shipped trigger file ``name`` (socnav/data): a layer shipped beside a pretrained policy."""
    from importlib.resources import files

    return Path(str(files("socnav") / "data" / name))


def _with_layer(safe_policy: Any, config: EnvConfig, episodes: int, seed: int, n_envs: int,
                advance: Callable[[int], None] | None) -> pd.DataFrame:
    """Episodes of `safe_policy`, with the steps its fallback drove (`fallback_steps`) per episode."""
    from socnav.envs.rollout import rollout_episodes
    from socnav.safety import FallbackCounter

    counter = FallbackCounter(safe_policy)
    records = rollout_episodes(safe_policy, config, episodes, seed=seed, n_envs=n_envs, observer=counter,
                               progress=advance)
    records["fallback_steps"] = counter.per_episode(records["episode"])
    return records


def _safe_policy(policy: Any, config: EnvConfig) -> Any:
    from socnav.safety import SafePolicy
    from socnav.uncertainty import MC_SEED, MCDropoutEstimator

    # A private, seeded mask stream: the same command gives the same result.
    return SafePolicy(policy, MCDropoutEstimator(policy, k=MC_SAMPLES, seed=MC_SEED), THRESHOLDS, config)


def choose_strength(policy: Any, base: EnvConfig, n_envs: int = 50) -> tuple[float, dict[float, int]]:
    """The `PERTURBATION` strength of `STRENGTHS` at which the plain policy collides most on the screening
    episodes (the smallest on ties); returns (strength, collisions per strength)."""
    from socnav.envs.rollout import rollout_episodes

    collisions = {}
    for strength in STRENGTHS:
        config = load_config(base, perturbation={PERTURBATION: strength})
        records = rollout_episodes(policy, config, SCREEN_EPISODES, seed=SCREEN_SEED, n_envs=n_envs)
        collisions[strength] = int((records["outcome"] == "collision").sum())
    return max(STRENGTHS, key=lambda s: (collisions[s], -s)), collisions


def safety_demo(policy: Any, base: EnvConfig, episodes: int, seed: int, n_envs: int = 32,
                progress: Callable[[str, int], Callable[[int], None]] | None = None,
                comparisons: Mapping[str, str | Path] | None = None) -> SafetyDemo:
    """Play `episodes` episodes (seeds `seed`...) of the perturbed world with `policy`, with the same policy inside
    the safety layer, and inside each layer of `comparisons` (label -> trigger or threshold file; default: the
    shipped `COMPARISONS`). `progress(label, total)` returns a callback advanced by finished episodes."""
    from socnav.envs.rollout import rollout_episodes
    from socnav.safety import SafePolicy

    strength, screening = choose_strength(policy, base)
    config = load_config(base, perturbation={PERTURBATION: strength})
    tick = (lambda label: progress(label, episodes)) if progress is not None else (lambda label: None)
    plain = rollout_episodes(policy, config, episodes, seed=seed, n_envs=n_envs, progress=tick("plain policy"))
    safe = _with_layer(_safe_policy(policy, config), config, episodes, seed, n_envs, tick("with the safety layer"))
    files = comparisons if comparisons is not None else {label: comparison_file(name)
                                                         for label, name in COMPARISONS.items()}
    others = {}
    for label, path in files.items():
        layer = SafePolicy(policy, None, str(path), config)  # these triggers read no uncertainty: no estimator
        others[label] = _with_layer(layer, config, episodes, seed, n_envs, tick(f"with {label}"))
    plain_hit, safe_hit = plain["outcome"].eq("collision"), safe["outcome"].eq("collision")
    return SafetyDemo(config, strength, screening, plain, safe,
                      saved=[int(s) for s in plain.loc[plain_hit & ~safe_hit, "seed"]],
                      caused=[int(s) for s in plain.loc[~plain_hit & safe_hit, "seed"]], comparisons=others)


def write_safety_records(result: SafetyDemo, out: Path) -> tuple[Path, ...]:
    """The safety demo's records: OUT/perturbed_<scenario>.csv (plain policy), OUT/perturbed_<scenario>_safety.csv
    (with the layer, `fallback_steps` included) and OUT/perturbed_<scenario>_<comparison>.csv per comparison layer;
    returns the paths."""
    from socnav.io import write_table_atomic

    base = Path(out) / f"perturbed_{result.config.scenario}"
    paths = [write_table_atomic(result.plain, base.with_name(base.name + ".csv")),
             write_table_atomic(result.safe, base.with_name(base.name + "_safety.csv"))]
    for label, records in result.comparisons.items():
        slug = "_".join(label.replace("-", " ").split())
        paths.append(write_table_atomic(records, base.with_name(f"{base.name}_{slug}.csv")))
    return tuple(paths)


def find_saved_episode(policy: Any, config: EnvConfig, saved: list[int], tries: int = 3) -> int | None:
    """The first of the `saved` seeds that the safety layer also saves when the episode is played alone (as an
    animation plays it: MC-dropout draws other masks for a batch of one, so a batched save need not repeat);
    None if none of the first `tries` does."""
    from socnav.envs.rollout import rollout_episodes

    for episode_seed in saved[:tries]:
        alone = rollout_episodes(_safe_policy(policy, config), config, 1, seed=episode_seed, n_envs=1)
        if alone["outcome"].iloc[0] != "collision":
            return episode_seed
    return None


def animate_saved_episode(policy: Any, config: EnvConfig, episode_seed: int, out_dir: Path,
                          policy_label: str) -> tuple[Path, Path]:
    """The episode `episode_seed` without the safety layer (a collision) and with it (saved), as two GIFs."""
    from socnav.cli.workflows.animation import animate_episode
    from socnav.uncertainty import MC_SEED, MCDropoutEstimator

    without, _ = animate_episode(policy, None, config, out_dir / f"safety_off_seed{episode_seed}.gif",
                                 seed=episode_seed, policy_label=policy_label)
    with_layer, _ = animate_episode(policy, MCDropoutEstimator(policy, k=MC_SAMPLES, seed=MC_SEED), config,
                                    out_dir / f"safety_on_seed{episode_seed}.gif", seed=episode_seed,
                                    thresholds=THRESHOLDS, policy_label=policy_label,
                                    safety_label=f"MC-dropout, paper thresholds ({THRESHOLDS})")
    return without, with_layer


def describe(result: SafetyDemo) -> list[str]:
    """The demo's findings in words (honest when the layer saved nothing or caused collisions)."""
    plain_hits = int(result.plain["outcome"].eq("collision").sum())
    safe_hits = int(result.safe["outcome"].eq("collision").sum())
    n = len(result.plain)
    screening = ", ".join(f"{s:g}: {c}" for s, c in result.screening.items())
    lines = [f"{PERTURBATION} = {result.strength:g} rad, where the plain policy collided most in {SCREEN_EPISODES} "
             f"screening episodes (collisions per strength: {screening})",
             f"collisions in {n} episodes: {plain_hits} without the safety layer, {safe_hits} with it -> "
             f"{result.prevented} prevented net ({len(result.saved)} episode(s) saved, {len(result.caused)} "
             f"collision(s) the layer caused); the fallback drove {result.fallback_share:.1%} of the steps"]
    if not plain_hits:
        lines.append("the plain policy did not collide here, so the safety layer had nothing to prevent")
    elif not result.saved:
        lines.append("the safety layer saved none of these episodes")
    from socnav.safety import fallback_percent

    for label, records in result.comparisons.items():
        hits = int(records["outcome"].eq("collision").sum())
        lines.append(f"{label} (calibrated for the shipped policy, 5 % budget) on the same episodes: {hits} "
                     f"collision(s), {plain_hits - hits} prevented net; its fallback drove "
                     f"{fallback_percent(records) / 100.0:.1%} of the steps")
    return lines


def summary_rows(result: SafetyDemo, label: str) -> list[tuple[str, dict[str, Any]]]:
    """Metrics-table rows (`socnav.envs.rollout.summarize`) of the plain run, the safe run and the comparisons."""
    from socnav.envs.rollout import summarize
    from socnav.safety import fallback_percent

    rows = [(f"{label}, no safety layer", summarize(result.plain))]
    for name, records in {"safety layer (mc)": result.safe, **result.comparisons}.items():
        row = summarize(records)
        row["fallback_pct"] = fallback_percent(records)
        rows.append((f"{label} + {name}", row))
    return rows

