"""Experiment files: a YAML grid (algorithms x training scenarios x seeds, evaluated in several scenarios), named
budgets that override parts of the grid, and the expansion of a resolved experiment into units of work.

An experiment file (see ``configs/experiments/table1.yaml``)::

    name: table1                     # names the default run directory (runs/<name>-<budget>)
    kind: table1                     # which planner expands it and which report sections describe it
    env: {}                          # env overrides for every environment (training and evaluation)
    scenario_env:                    # env overrides per scenario, applied wherever that scenario is used
      circle_crossing: {n_humans: 5}
    grid:
      algorithms: [ppo, odv-ppo-drop]
      train_scenarios: [circle_crossing, random]
      seeds: 15                      # an int n means seeds 0..n-1; or a list [0, 3, 7]
      timesteps: 1000000
      n_envs: 16                     # training environments per run
      eval_every: null               # periodic validation (null: a tenth of the run)
      validation_episodes: 50        # episodes per periodic validation
      overrides: {}                  # AlgoConfig fields for every algorithm
      algo_overrides:                # AlgoConfig fields per algorithm: a mapping or a preset YAML path
        ppo: presets/ppo_tuned.yaml  #   (relative to this file; `socnav tune --write-preset` writes one)
    evaluation:
      scenarios: [circle_interaction, circle_crossing, random]
      episodes: 200                  # test episodes per policy and scenario
      seed: 0                        # episode k uses seed + k: every policy sees the same episodes
    budgets:
      quick: {seeds: 2, timesteps: 200000, episodes: 100}
      paper: {seeds: 15, episodes: 200}

Every field is validated before any work starts; errors name the field and the allowed values.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any, Literal, cast

from pydantic import Field, StrictInt, ValidationError, field_validator, model_serializer, model_validator

from socnav.config import (
    REPLAY_MAX_FILES,
    ConfigError,
    StrictModel,
    deep_merge,
    format_validation_error,
    load_config,
    read_mapping_file,
    short_repr,
)
from socnav.experiments.moved import moved_attribute
from socnav.experiments.registry import PLANNERS, UNIT_COUNTS, experiment_kinds, load_kind, register_planner
from socnav.experiments.units import Unit

__all__ = [
    "PLANNERS",
    "Budget",
    "Evaluation",
    "Experiment",
    "ExperimentError",
    "Grid",
    "Unit",
    "load_experiment",
    "plan_units",
    "register_planner",
    "resolve_budget",
]

class ExperimentError(ConfigError):
    """An experiment file is wrong; the message names the file, the field and what is allowed."""


#: Training seeds stay below socnav.rl.training.MAX_SEED (2**28: their environments' seeds stay in [2**40, 2**41));
#: evaluation episode seeds (seed + k) stay far below the training environments' 2**40.
TRAIN_SEED_LIMIT = 2**28 - 1
EPISODE_SEED_LIMIT = 2**31 - 1
#: Upper bounds of counts: far beyond the paper's budgets (1e6 steps, 200 episodes), below what cannot finish.
MAX_TIMESTEPS = 10**10
MAX_EPISODES = 10**7
MAX_SAMPLES = 10_000  # MC-dropout samples, window steps, repeats
MAX_SEEDS = 10_000  # training seeds per grid: a seed count is checked before it is expanded into a list
MAX_STRENGTHS = 1_000  # strengths of one perturbation
#: Units one experiment may plan: counted from the grid's sizes before any unit is built (a 2-core laptop runs
#: ~100 units an hour, a cluster a few thousand; the bound is far above both, far below what exhausts memory).
MAX_UNITS = 1_000_000
#: Experiment and budget names become directory names under runs/: one safe pattern for both.
SAFE_NAME = r"[A-Za-z0-9_.-]+"
Seeds = StrictInt | list[StrictInt]


def _algorithms() -> tuple[str, ...]:
    from socnav.rl.presets import ALGOS  # imports torch: only when an experiment is validated

    return ALGOS


def _scenarios() -> list[str]:
    from socnav.sim.scenarios import scenario_names

    return scenario_names()


def _check_names(values: list[str], allowed: Any, what: str) -> list[str]:
    allowed = list(allowed)
    if not values:
        raise ValueError(f"needs at least one {what}; allowed: {', '.join(allowed)}")
    for value in values:
        if value not in allowed:
            raise ValueError(f"unknown {what} {short_repr(value)}; allowed: {', '.join(allowed)}")
    duplicates = sorted({value for value in values if values.count(value) > 1})
    if duplicates:
        raise ValueError(f"{what} listed twice: {', '.join(duplicates)}")
    return values


def _seed_list(value: Seeds) -> list[int]:
    if isinstance(value, int) and not 1 <= value <= MAX_SEEDS:  # before range() is expanded
        raise ValueError(f"an integer seed count must be in [1, {MAX_SEEDS}] (n means seeds 0..n-1)")
    seeds = list(range(value)) if isinstance(value, int) else list(value)
    if len(seeds) > MAX_SEEDS:
        raise ValueError(f"at most {MAX_SEEDS} seeds; got {len(seeds)}")
    if not seeds:
        raise ValueError("needs at least one seed")
    if any(seed < 0 or seed > TRAIN_SEED_LIMIT for seed in seeds):
        raise ValueError(f"seeds must lie in [0, {TRAIN_SEED_LIMIT}]")
    if len(set(seeds)) != len(seeds):
        raise ValueError("a seed is listed twice")
    return seeds


class Grid(StrictModel):
    """What is trained: every algorithm on every training scenario with every seed."""

    algorithms: list[str] = Field(description="preset names (socnav.rl.ALGOS)")
    train_scenarios: list[str] = Field(description="registered scenario names")
    seeds: Seeds = Field(description="an int n (seeds 0..n-1) or a list of seeds")
    timesteps: StrictInt = Field(gt=0, le=MAX_TIMESTEPS, description="environment steps per training run")
    n_envs: StrictInt = Field(16, gt=0, description="training environments per run (must fit in memory)")
    eval_every: StrictInt | None = Field(None, gt=0, le=MAX_TIMESTEPS,
                                            description="timesteps between validations (null: a tenth)")
    validation_episodes: StrictInt = Field(50, gt=0, le=MAX_EPISODES,
                                           description="episodes per periodic validation during training")
    overrides: dict[str, Any] = Field(default_factory=dict, description="AlgoConfig fields for every algorithm")
    algo_overrides: dict[str, dict[str, Any] | str] = Field(
        default_factory=dict, description="per algorithm: AlgoConfig fields, or a preset YAML path"
    )

    @field_validator("algorithms")
    @classmethod
    def _known_algorithms(cls, value: list[str]) -> list[str]:
        return _check_names(value, _algorithms(), "algorithm")

    @field_validator("train_scenarios")
    @classmethod
    def _known_scenarios(cls, value: list[str]) -> list[str]:
        return _check_names(value, _scenarios(), "scenario")

    @field_validator("seeds")
    @classmethod
    def _seeds(cls, value: Seeds) -> list[int]:
        return _seed_list(value)

    @field_validator("algo_overrides")
    @classmethod
    def _override_keys(cls, value: dict[str, Any]) -> dict[str, Any]:
        for name in value:
            if name not in _algorithms():
                raise ValueError(f"unknown algorithm {short_repr(name)}; allowed: {', '.join(_algorithms())}")
        return value


class Evaluation(StrictModel):
    """How every trained policy is tested: `episodes` episodes (seeds `seed`, `seed`+1, ...) in each scenario."""

    scenarios: list[str] = Field(description="registered scenario names")
    episodes: StrictInt = Field(200, gt=0, le=MAX_EPISODES, description="test episodes per policy and scenario")
    seed: StrictInt = Field(0, ge=0, le=EPISODE_SEED_LIMIT,
                            description="episode k uses seed + k (disjoint from training seeds >= 2**40)")
    n_envs: StrictInt = Field(32, gt=0, description="environments stepped together during evaluation (must fit)")
    deterministic: bool = Field(True, description="mean action (True) or sampled actions")

    @field_validator("scenarios")
    @classmethod
    def _known_scenarios(cls, value: list[str]) -> list[str]:
        return _check_names(value, _scenarios(), "scenario")


def _perturbation_grid(value: dict[str, list[float]]) -> dict[str, list[float]]:
    from socnav.envs.perturbations import PERTURBATIONS

    for name, strengths in value.items():
        if name not in PERTURBATIONS:
            raise ValueError(f"unknown perturbation {short_repr(name)}; allowed: {', '.join(PERTURBATIONS)}")
        if len(strengths) > MAX_STRENGTHS:
            raise ValueError(f"{name}: at most {MAX_STRENGTHS} strengths; got {len(strengths)}")
        if len(strengths) < 2 or sorted(strengths) != list(strengths):
            raise ValueError(f"{name}: strengths must be increasing, the first being the unperturbed one (sigma(0))")
        PERTURBATIONS[name].check_strengths(strengths)
    return value


def _paper_grids() -> dict[str, list[float]]:
    """The default grids: every registered perturbation type marked ``default`` (not the behaviour shift)."""
    from socnav.envs.perturbations import DEFAULT_GRIDS

    return {name: list(values) for name, values in DEFAULT_GRIDS.items()}


PERTURBATIONS_DESCRIPTION = ("perturbation -> strengths, sigma(0) first; behaviour_shift (humans of another model "
                             "than trained with, not in the default grids) numbers its models: 0 = as trained, "
                             "1 = social_force, 2 = orca")

Estimator = Literal["mc", "ensemble"]
Sensing = Literal["perceived", "true"]
#: The defaults of the study and the safety layer: both estimators, the layer reading the observation.
BOTH_ESTIMATORS: tuple[Estimator, ...] = ("mc", "ensemble")
PERCEIVED_ONLY: tuple[Sensing, ...] = ("perceived",)


class Study(StrictModel):
    """The perturbation study (paper Table 2): per estimator and perturbation, episodes at every strength with the
    uncertainty estimated at every step. All policies of `grid` form the ensemble; seed `mc_seed` acts (for both
    estimators, so they see identical episodes) and is the MC-dropout policy."""

    estimators: list[Estimator] = Field(default_factory=lambda: list(BOTH_ESTIMATORS),
                                        description="uncertainty estimators studied")
    perturbations: dict[str, list[float]] = Field(default_factory=_paper_grids,
                                                  description=PERTURBATIONS_DESCRIPTION)
    k: StrictInt = Field(20, ge=2, le=MAX_SAMPLES, description="MC-dropout samples")
    p_test: float | None = Field(None, ge=0, lt=1, description="MC-dropout probability (null: the policy's)")
    window: StrictInt = Field(4, ge=1, le=MAX_SAMPLES, description="steps of the windowed uncertainty")
    mc_seed: StrictInt = Field(0, ge=0, le=TRAIN_SEED_LIMIT,
                               description="training seed of the acting / MC-dropout policy")

    @field_validator("perturbations")
    @classmethod
    def _grid(cls, value: dict[str, list[float]]) -> dict[str, list[float]]:
        return _perturbation_grid(value)


Ablated = Literal["proximity-only", "uncertainty-only"]


class Safety(StrictModel):
    """The safety evaluation (paper Table 3): per estimator and perturbation, the same episodes without the safety
    layer, with the paper's thresholds and (if `calibrate`) with thresholds calibrated on disjoint perturbations
    and seeds, each with every `sensing` (one calibration per estimator and sensing); `repeats` independent blocks
    of `evaluation.episodes` episodes give mean +- std.

    The ablation (Table 3's question whether the uncertainty condition changes the safety decision): each rule of
    `ablation` (`socnav.safety.Thresholds.conditions`) is calibrated under the same false-activation budget on the
    same calibration episodes and played on the same evaluation episodes, for the one sensing `ablation_sensing`;
    ``proximity-only`` reads no uncertainty, so it is calibrated and played once, not per estimator. With
    `tradeoff_budgets`, the paper's rule of every estimator and the proximity-only rule are also calibrated and
    played at each of those false-activation budgets (the trade-off curve) -- with `tradeoff_search` and
    `tradeoff_repeats` more cheaply than at `false_activation_budget`, for every rule alike."""

    estimators: list[Estimator] = Field(default_factory=lambda: list(BOTH_ESTIMATORS),
                                        description="uncertainty estimators driving the safety layer")
    perturbations: dict[str, list[float]] = Field(default_factory=_paper_grids,
                                                  description=PERTURBATIONS_DESCRIPTION)
    repeats: StrictInt = Field(3, ge=1, le=MAX_SAMPLES,
                               description="independent blocks of evaluation.episodes episodes (mean +- std)")
    thresholds: dict[str, str] = Field(default_factory=lambda: {"mc": "mc", "ensemble": "ensemble"},
                                       description="estimator -> paper preset name or threshold file")
    calibrate: bool = Field(True, description="also evaluate thresholds calibrated on disjoint episodes")
    calibration_episodes: StrictInt = Field(40, ge=1, le=MAX_EPISODES,
                                            description="episodes per calibration configuration")
    false_activation_budget: float = Field(0.05, ge=0, le=1, description="share of unperturbed steps on which the "
                                           "calibrated fallback may act (`socnav calibrate --false-activation-budget`)")
    proximity: Literal["abs-relative-speed", "closing-speed"] = Field(
        "abs-relative-speed", description="c_prox reading for the paper's threshold sets")
    calibration_proximity: Literal["both", "abs-relative-speed", "closing-speed"] = Field(
        "both", description="c_prox readings the calibration searches")
    sensing: list[Sensing] = Field(
        default_factory=lambda: list(PERCEIVED_ONLY),
        description="what c_prox, c_ap and the fallback read: perceived (the noisy observation) and/or true (the "
                    "simulator's state); each one is calibrated and evaluated (a single value is a list of one)")
    k: StrictInt = Field(20, ge=2, le=MAX_SAMPLES, description="MC-dropout samples")
    window: StrictInt = Field(4, ge=1, le=MAX_SAMPLES, description="steps of the windowed uncertainty")
    mc_seed: StrictInt = Field(0, ge=0, le=TRAIN_SEED_LIMIT,
                               description="training seed of the acting / MC-dropout policy")
    ablation: list[Ablated] = Field(default_factory=list,
                                    description="rule variants calibrated and evaluated next to the paper's rule "
                                                "(eq. (10)): proximity-only and/or uncertainty-only")
    ablation_sensing: Sensing | None = Field(
        None, description="the sensing the ablation and the trade-off curve are run with (one of `sensing`; null: "
                          "true if listed, else the first)")
    tradeoff_budgets: list[float] = Field(default_factory=list,
                                          description="false-activation budgets (each in (0, 1], increasing) of "
                                                      "the trade-off curve; [] for none")
    tradeoff_search: Literal["full", "light"] = Field(
        "full", description="calibration at the trade-off budgets other than false_activation_budget: full (as at "
                            "that budget) or light (one proxy budget, the c_prox reading chosen at that budget, no "
                            "refinement stage; every rule alike)")
    tradeoff_repeats: StrictInt | None = Field(
        None, ge=1, le=MAX_SAMPLES, description="the first repeats the rules of those budgets are evaluated on "
                                                "(null: every repeat); the curve uses the repeats all its points share")
    triggers: list[str] = Field(default_factory=list,
                                description="kind safety_benchmark: the rows (registered triggers, and "
                                            "risk-model+uncertainty); [] for every built-in row")
    replay_files: list[str] = Field(default_factory=list, max_length=REPLAY_MAX_FILES,
                                    description="kind safety_benchmark: recorded pedestrian trajectories (ETH/UCY "
                                                "text, as humans.replay.files) played as the held-out shift "
                                                "`replay`; [] for none (no recording ships with socnav)")

    @field_validator("triggers")
    @classmethod
    def check_triggers(cls, value: list[str]) -> list[str]:
        """Registered trigger names (or ``risk-model+uncertainty``), each once."""
        from socnav.safety.triggers import TriggerError, trigger_class, trigger_names

        for name in value:
            if name not in (*trigger_names(), "risk-model+uncertainty"):
                try:
                    trigger_class(name)
                except TriggerError as exc:
                    raise ValueError(str(exc)) from None
        if len(set(value)) != len(value):
            raise ValueError(f"lists a trigger twice: {value}")
        return value

    @model_serializer(mode="wrap")
    def _dump(self, handler: Any) -> dict[str, Any]:
        data = handler(self)
        for key in ("triggers", "replay_files"):  # only the benchmark reads them: Table 3's run files stay as they were
            if not data.get(key):
                data.pop(key, None)
        return data

    @field_validator("perturbations")
    @classmethod
    def _grid(cls, value: dict[str, list[float]]) -> dict[str, list[float]]:
        return _perturbation_grid(value)

    @field_validator("ablation")
    @classmethod
    def _ablation(cls, value: list[str]) -> list[str]:
        if len(set(value)) != len(value):
            raise ValueError(f"lists a rule twice: {value}; allowed: proximity-only, uncertainty-only (each once)")
        return value

    @field_validator("ablation_sensing", mode="before")
    @classmethod
    def _ablation_sensing(cls, value: Any) -> Any:
        return "true" if value is True else value  # YAML reads an unquoted `true` as a boolean

    @field_validator("tradeoff_budgets")
    @classmethod
    def check_budgets(cls, value: list[float]) -> list[float]:
        """Budgets in (0, 1], increasing, each once."""
        if any(not 0.0 < budget <= 1.0 for budget in value):
            raise ValueError(f"each budget must lie in (0, 1] (a share of unperturbed steps), got {value}")
        if sorted(set(value)) != list(value):
            raise ValueError(f"budgets must be increasing, each listed once, got {value}")
        return value

    @model_validator(mode="after")
    def _ablation_needs_calibration(self) -> Safety:
        if (self.ablation or self.tradeoff_budgets) and not self.calibrate:
            raise ValueError("ablation / tradeoff_budgets: the rules are calibrated, so calibrate must be true")
        if self.ablation_sensing is not None and self.ablation_sensing not in self.sensing:
            raise ValueError(f"ablation_sensing {self.ablation_sensing!r} must be one of sensing {self.sensing}")
        return self

    @property
    def ablation_sensing_resolved(self) -> str:
        """The sensing of the ablation: `ablation_sensing`, or ``true`` if `sensing` lists it, else its first."""
        if self.ablation_sensing is not None:
            return self.ablation_sensing
        return "true" if "true" in self.sensing else self.sensing[0]

    @field_validator("sensing", mode="before")
    @classmethod
    def _sensing_list(cls, value: Any) -> Any:
        values = [value] if isinstance(value, (str, bool)) else value
        if isinstance(values, list):
            # YAML reads an unquoted `true` as a boolean: it can only mean the `true` sensing here.
            values = ["true" if v is True else v for v in values]
            if not values:
                raise ValueError("must name at least one of: perceived, true")
            if len(set(map(str, values))) != len(values):
                raise ValueError(f"lists a sensing twice: {values}; allowed: perceived, true (each at most once)")
        return values


class Budget(StrictModel):
    """A named budget (`socnav run --budget NAME`): any field given replaces the value named in its description;
    `overrides` merges."""

    description: str = ""
    seeds: Seeds | None = Field(None, description="grid.seeds: an int n (seeds 0..n-1) or a list of seeds")
    timesteps: StrictInt | None = Field(None, gt=0, le=MAX_TIMESTEPS, description="grid.timesteps")
    n_envs: StrictInt | None = Field(None, gt=0, description="grid.n_envs")
    eval_every: StrictInt | None = Field(None, gt=0, le=MAX_TIMESTEPS, description="grid.eval_every")
    validation_episodes: StrictInt | None = Field(None, gt=0, le=MAX_EPISODES,
                                                     description="grid.validation_episodes")
    episodes: StrictInt | None = Field(None, gt=0, le=MAX_EPISODES,
                                          description="evaluation.episodes: episodes per policy and scenario")
    eval_n_envs: StrictInt | None = Field(None, gt=0, description="evaluation.n_envs")
    algorithms: list[str] | None = Field(None, description="grid.algorithms")
    train_scenarios: list[str] | None = Field(None, description="grid.train_scenarios")
    eval_scenarios: list[str] | None = Field(None, description="evaluation.scenarios")
    overrides: dict[str, Any] | None = Field(None, description="merged into grid.overrides")
    study_perturbations: dict[str, list[float]] | None = Field(None, description="study.perturbations")
    safety_perturbations: dict[str, list[float]] | None = Field(None, description="safety.perturbations")
    repeats: StrictInt | None = Field(None, ge=1, le=MAX_SAMPLES, description="safety.repeats")
    calibration_episodes: StrictInt | None = Field(None, ge=1, le=MAX_EPISODES,
                                                      description="safety.calibration_episodes")
    eval_seed: StrictInt | None = Field(None, ge=0, le=EPISODE_SEED_LIMIT,
                                           description="evaluation.seed: episode k uses seed + k")
    mc_seed: StrictInt | None = Field(None, ge=0, le=TRAIN_SEED_LIMIT,
                                         description="study.mc_seed and safety.mc_seed (one of the seeds trained)")
    tradeoff_budgets: list[float] | None = Field(None, description="safety.tradeoff_budgets")
    triggers: list[str] | None = Field(None, description="safety.triggers")

    @field_validator("tradeoff_budgets")
    @classmethod
    def _budget_list(cls, value: list[float] | None) -> list[float] | None:
        return None if value is None else Safety.check_budgets(value)

    @field_validator("triggers")
    @classmethod
    def _trigger_list(cls, value: list[str] | None) -> list[str] | None:
        return None if value is None else Safety.check_triggers(value)

    @field_validator("study_perturbations", "safety_perturbations")
    @classmethod
    def _grids(cls, value: dict[str, list[float]] | None) -> dict[str, list[float]] | None:
        return None if value is None else _perturbation_grid(value)

    @field_validator("seeds")
    @classmethod
    def _seeds(cls, value: Seeds | None) -> list[int] | None:
        return None if value is None else _seed_list(value)

    @field_validator("algorithms")
    @classmethod
    def _known_algorithms(cls, value: list[str] | None) -> list[str] | None:
        return None if value is None else _check_names(value, _algorithms(), "algorithm")

    @field_validator("train_scenarios", "eval_scenarios")
    @classmethod
    def _known_scenarios(cls, value: list[str] | None) -> list[str] | None:
        return None if value is None else _check_names(value, _scenarios(), "scenario")


class Experiment(StrictModel):
    """A validated experiment file. After `resolve_budget`, `budget` names the budget that was applied."""

    name: str = Field(description="letters, digits, '.', '_' or '-'")
    kind: str = Field("table1", description="planner and report sections (socnav.experiments.registry)")
    description: str = ""
    env: dict[str, Any] = Field(default_factory=dict, description="env overrides for every environment")
    scenario_env: dict[str, dict[str, Any]] = Field(default_factory=dict, description="env overrides per scenario")
    grid: Grid
    evaluation: Evaluation
    study: Study | None = Field(None, description="kind uncertainty: the perturbation study (Table 2)")
    safety: Safety | None = Field(None, description="kind uncertainty: the safety evaluation (Table 3)")
    budgets: dict[str, Budget] = Field(default_factory=dict)
    budget: str | None = Field(None, description="set by resolve_budget: the budget applied (null: none)")

    @field_validator("name")
    @classmethod
    def _safe_name(cls, value: str) -> str:
        if not re.fullmatch(SAFE_NAME, value):
            raise ValueError("must consist of letters, digits, '.', '_' or '-' (it names a directory)")
        return value

    @field_validator("budgets")
    @classmethod
    def _safe_budget_names(cls, value: dict[str, Budget]) -> dict[str, Budget]:
        for name in value:  # runs/<name>-<budget> is the default run directory
            if not re.fullmatch(SAFE_NAME, name):
                raise ValueError(f"budget name {short_repr(name)} must consist of letters, digits, '.', '_' or "
                                 "'-' (it names a directory)")
        return value

    @field_validator("kind")
    @classmethod
    def _known_kind(cls, value: str) -> str:
        if value not in experiment_kinds():
            raise ValueError(f"unknown experiment kind {short_repr(value)}; allowed: {', '.join(experiment_kinds())}")
        return value

    @field_validator("scenario_env")
    @classmethod
    def _scenario_keys(cls, value: dict[str, Any]) -> dict[str, Any]:
        for name in value:
            if name not in _scenarios():
                raise ValueError(f"unknown scenario {short_repr(name)}; allowed: {', '.join(_scenarios())}")
        return value

    # ---- derived values ----
    def env_config(self, scenario: str) -> dict[str, Any]:
        """The (partial) env config of `scenario` in this experiment: env, then scenario_env[scenario]."""
        return deep_merge({**self.env, "scenario": scenario}, self.scenario_env.get(scenario, {}))

    def algo_overrides(self, algo: str) -> dict[str, Any]:
        """Hyperparameter overrides of `algo`: grid.overrides, then grid.algo_overrides[algo] (inlined)."""
        extra = self.grid.algo_overrides.get(algo, {})
        if not isinstance(extra, dict):
            raise ExperimentError(f"grid.algo_overrides.{algo}: preset path {extra!r} was not loaded")
        return {**self.grid.overrides, **extra}

    def to_json(self) -> dict[str, Any]:
        return self.model_dump(mode="json")


# --------------------------------------------------------------------------------------------------------------
# Loading and validation
# --------------------------------------------------------------------------------------------------------------

def parse_experiment(data: dict[str, Any], source: str = "dict", base_dir: Path | None = None) -> Experiment:
    """Validate an experiment mapping (no budget applied): schema, env configs, hyperparameter overrides."""
    try:
        experiment = Experiment.model_validate(data)
    except ValidationError as exc:
        raise ExperimentError(format_validation_error(exc, f"invalid experiment ({source}):", Experiment)) from None
    if experiment.budget is not None:
        raise ExperimentError(f"invalid experiment ({source}):\n  - budget: set by --budget, not in the file")
    experiment = _inline_presets(experiment, source, base_dir)
    _check_consistency(experiment, source)
    for name in experiment.budgets:
        _check_consistency(resolve_budget(experiment, name), f"{source}, budget {name!r}")
    return experiment


def load_experiment(path: str | Path, budget: str | None = None) -> Experiment:
    """Read and validate an experiment file and apply `budget` (None: the grid as written).

    :raises ExperimentError: the message names the file, the field and the allowed values.
    """
    path = Path(path)
    experiment = parse_experiment(read_mapping_file(path, "experiment", ExperimentError), str(path), path.parent)
    return resolve_budget(experiment, budget)


def _inline_presets(experiment: Experiment, source: str, base_dir: Path | None) -> Experiment:
    """Replace preset paths in grid.algo_overrides by their contents (the resolved experiment is self-contained)."""
    inlined: dict[str, dict[str, Any]] = {}
    for algo, value in experiment.grid.algo_overrides.items():
        if isinstance(value, str):
            preset = Path(value)
            if not preset.is_absolute() and base_dir is not None:
                preset = base_dir / preset
            try:
                value = read_mapping_file(preset, "preset", ExperimentError)
            except ExperimentError as exc:
                raise ExperimentError(f"invalid experiment ({source}):\n  - grid.algo_overrides.{algo}: "
                                      f"{exc}") from None
        inlined[algo] = dict(value)
    grid = experiment.grid.model_copy(update={"algo_overrides": inlined})
    return experiment.model_copy(update={"grid": grid})


def _check_consistency(experiment: Experiment, source: str) -> None:
    """Env configs, environment counts and hyperparameters of every unit are valid, and every policy fits every
    evaluation env."""
    from socnav.envs.env import check_env_count
    from socnav.envs.perturbations import perturbed_config
    from socnav.rl.presets import describe_override_error, resolve_config

    max_humans: dict[str, int] = {}
    for scenario in dict.fromkeys(experiment.grid.train_scenarios + experiment.evaluation.scenarios):
        try:
            config = load_config(experiment.env_config(scenario))
        except ConfigError as exc:
            detail = str(exc).split("\n", 1)[-1]
            raise ExperimentError(f"invalid experiment ({source}): env of scenario {scenario!r} "
                                  f"(env + scenario_env.{scenario}):\n{detail}") from None
        max_humans[scenario] = config.max_humans
        try:  # before any unit starts: a count that cannot fit would otherwise fail in every unit
            check_env_count(experiment.grid.n_envs, config, "grid.n_envs")
            check_env_count(min(experiment.evaluation.n_envs, experiment.evaluation.episodes), config,
                            "evaluation.n_envs")
        except ConfigError as exc:
            raise ExperimentError(f"invalid experiment ({source}): scenario {scenario!r}: {exc}") from None
    for name, block in (("study", experiment.study), ("safety", experiment.safety)):
        for kind, strengths in (block.perturbations if block is not None else {}).items():
            for strength in strengths:
                try:
                    perturbed_config(experiment.env_config(experiment.grid.train_scenarios[0]), kind, strength)
                except ConfigError as exc:
                    detail = str(exc).split("\n", 1)[-1]
                    raise ExperimentError(f"invalid experiment ({source}): {name}.perturbations.{kind}: strength "
                                          f"{strength} gives an invalid env:\n{detail}") from None
    for name, block in (("study", experiment.study), ("safety", experiment.safety)):
        seeds = cast(list[int], experiment.grid.seeds)  # validated into a list
        if block is not None and experiment.kind == "uncertainty" and block.mc_seed not in seeds:
            raise ExperimentError(f"invalid experiment ({source}): {name}.mc_seed {block.mc_seed} is not among "
                                  f"grid.seeds {experiment.grid.seeds}: the acting policy must be one of those trained")
    if len(set(max_humans.values())) > 1:
        raise ExperimentError(
            f"invalid experiment ({source}): env.max_humans differs between scenarios ({max_humans}); every policy "
            "is evaluated in every scenario, so the observation size (max_humans) must be the same everywhere"
        )
    for algo in experiment.grid.algorithms:
        try:
            resolve_config(algo, experiment.algo_overrides(algo))
        except ValueError as exc:
            message = " ".join(describe_override_error(algo, exc).split())
            raise ExperimentError(
                f"invalid experiment ({source}): grid.overrides / grid.algo_overrides.{algo}: {message}"
            ) from None


def resolve_budget(experiment: Experiment, budget: str | None) -> Experiment:
    """The experiment with budget `budget` applied to its grid and evaluation (None: unchanged)."""
    if budget is None:
        return experiment.model_copy(update={"budget": None})
    if budget not in experiment.budgets:
        allowed = ", ".join(experiment.budgets) or "none (this experiment defines no budgets)"
        raise ExperimentError(f"unknown budget {budget!r} for experiment {experiment.name!r}; allowed: {allowed}")
    chosen = experiment.budgets[budget]
    grid_update: dict[str, Any] = {}
    for key in ("seeds", "timesteps", "n_envs", "eval_every", "validation_episodes", "algorithms", "train_scenarios"):
        if getattr(chosen, key) is not None:
            grid_update[key] = getattr(chosen, key)
    if chosen.overrides is not None:
        grid_update["overrides"] = {**experiment.grid.overrides, **chosen.overrides}
    evaluation_update: dict[str, Any] = {}
    for key, target in (("episodes", "episodes"), ("eval_n_envs", "n_envs"), ("eval_scenarios", "scenarios"),
                        ("eval_seed", "seed")):
        if getattr(chosen, key) is not None:
            evaluation_update[target] = getattr(chosen, key)
    update: dict[str, Any] = {
        "grid": experiment.grid.model_copy(update=grid_update),
        "evaluation": experiment.evaluation.model_copy(update=evaluation_update),
        "budget": budget,
    }
    if experiment.study is not None:
        study_update = {key: value for key, value in (("perturbations", chosen.study_perturbations),
                                                      ("mc_seed", chosen.mc_seed)) if value is not None}
        update["study"] = experiment.study.model_copy(update=study_update)
    if experiment.safety is not None:
        safety_update = {key: value for key, value in (("perturbations", chosen.safety_perturbations),
                                                       ("repeats", chosen.repeats),
                                                       ("calibration_episodes", chosen.calibration_episodes),
                                                       ("mc_seed", chosen.mc_seed),
                                                       ("tradeoff_budgets", chosen.tradeoff_budgets),
                                                       ("triggers", chosen.triggers))
                         if value is not None}
        update["safety"] = experiment.safety.model_copy(update=safety_update)
    return experiment.model_copy(update=update)


# --------------------------------------------------------------------------------------------------------------
# Units of work
# --------------------------------------------------------------------------------------------------------------

def planned_unit_count(experiment: Experiment) -> int | None:
    """An upper bound of the units `plan_units` builds, from the grid's sizes alone (nothing expanded); None when the
    kind registered no counter."""
    try:
        load_kind(experiment.kind)
    except ValueError as error:
        raise ExperimentError(f"experiment {experiment.name!r}: {error}") from None
    counter = UNIT_COUNTS.get(experiment.kind)
    return None if counter is None else counter(experiment)


def plan_units(experiment: Experiment) -> list[Unit]:
    """The units of a resolved experiment, every unit after the units it depends on; refused (with the count)
    above `MAX_UNITS`, counted before any unit is built when the kind counts its units."""
    count = planned_unit_count(experiment)
    if count is not None and count > MAX_UNITS:
        raise ExperimentError(f"experiment {experiment.name!r}: the grid makes {count:,} units, above the bound of "
                              f"{MAX_UNITS:,}; reduce grid.seeds, grid.algorithms or the scenarios")
    units = PLANNERS[experiment.kind](experiment)
    if len(units) > MAX_UNITS:
        raise ExperimentError(f"experiment {experiment.name!r}: the plan has {len(units):,} units, above the bound of "
                              f"{MAX_UNITS:,}; reduce grid.seeds, grid.algorithms or the scenarios")
    seen: set[str] = set()
    for unit in units:
        if unit.id in seen:
            raise ExperimentError(f"experiment {experiment.name!r}: unit {unit.id} planned twice")
        missing = [dep for dep in unit.deps if dep not in seen]
        if missing:
            raise ExperimentError(f"experiment {experiment.name!r}: unit {unit.id} is planned before {missing}")
        seen.add(unit.id)
    return units


def __getattr__(name: str) -> Any:
    # names that moved to socnav.paper: still importable from here, with a DeprecationWarning
    return moved_attribute('socnav.experiments.spec', name)
