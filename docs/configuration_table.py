"""Writes docs/configuration.md: every CLI flag <-> YAML field <-> Python name of train, evaluate, calibrate, run,
tune and export, and every field of the config models with its allowed values, read off the typer app and pydantic.

    python docs/configuration_table.py > docs/configuration.md

The YAML and Python columns of the flags are the `FLAGS` table below (a name mapping only a person can write);
everything else comes from the code. tests/test_config_docs.py fails when a flag or a field is missing from the doc.
"""

from __future__ import annotations

import typing
from typing import Any

from pydantic import BaseModel

#: The commands whose flags are documented, in the order of the doc.
COMMANDS = ("train", "evaluate", "calibrate", "run", "tune", "export")

#: --humans, in every command that has it: one model for every human.
HUMANS = ("env file `humans.model` (a single model: `humans.mix` is dropped)", "`EnvConfig.humans.model`")

#: (command, CLI parameter name) -> (YAML field, Python name). "—": no counterpart.
FLAGS: dict[tuple[str, str], tuple[str, str]] = {
    # socnav train -> socnav.rl.training.train(config, algo, seed, timesteps, out_dir, ...)
    ("train", "scenario"): ("env file `scenario`; experiment `grid.train_scenarios`", "`EnvConfig.scenario`"),
    ("train", "algo"): ("experiment `grid.algorithms`", "`train(algo=)`, `make_model(algo)`"),
    ("train", "seed"): ("experiment `grid.seeds` (`N`: seeds 0..N-1; a list: those seeds)", "`train(seed=)`"),
    ("train", "timesteps"): ("experiment `grid.timesteps`", "`train(timesteps=)`"),
    ("train", "n_envs"): ("experiment `grid.n_envs`", "`train(n_envs=)`"),
    ("train", "n_humans"): ("env file `n_humans`", "`EnvConfig.n_humans`"),
    ("train", "max_humans"): ("env file `max_humans`", "`EnvConfig.max_humans`"),
    ("train", "config"): ("an env file (EnvConfig fields, or under `env:`); experiment `env`", "`train(config=)`"),
    ("train", "algo_config"): ("a preset file (AlgoConfig fields); experiment `grid.algo_overrides.<algo>`",
                               "`train(overrides=)`"),
    ("train", "settings"): ("experiment `grid.overrides` (AlgoConfig fields)", "`train(overrides={key: value})`"),
    ("train", "eval_every"): ("experiment `grid.eval_every`", "`train(eval_every=)`"),
    ("train", "eval_episodes"): ("experiment `grid.validation_episodes`", "`train(eval_episodes=)`"),
    ("train", "out"): ("— (`socnav run`: `<run dir>/train/...`)", "`train(out_dir=)`"),
    ("train", "resume"): ("— (`socnav run` resumes by itself)", "`train(resume=True)`"),
    ("train", "force"): ("—", "`train(force=True)` (moves the run aside to `<out_dir>.old-<timestamp>`)"),
    ("train", "humans"): HUMANS,
    # socnav evaluate -> socnav.envs.rollout.rollout_episodes(policy, config, n_episodes, seed, n_envs, ...)
    ("evaluate", "controller"): ("—", "`socnav.controllers.make_controller(name, config)`"),
    ("evaluate", "policy"): ("—", "hidden, deprecated: `--controller`"),
    ("evaluate", "model"): ("— (experiments evaluate the policies they train)", "`socnav.load_policy(path)`"),
    ("evaluate", "stochastic"): ("experiment `evaluation.deterministic` (negated)",
                                 "`rollout_episodes(deterministic=False)`"),
    ("evaluate", "scenario"): ("env file `scenario`; experiment `evaluation.scenarios`", "`EnvConfig.scenario`"),
    ("evaluate", "episodes"): ("experiment `evaluation.episodes`", "`rollout_episodes(n_episodes=)`"),
    ("evaluate", "metrics"): ("— (experiment records hold every metric)",
                              "`socnav.sim.metrics.select_metrics(spec)`, `summarize(records, metrics=)`"),
    ("evaluate", "seed"): ("experiment `evaluation.seed` (one seed: episode k uses seed + k)",
                           "`rollout_episodes(seed=)`"),
    ("evaluate", "n_humans"): ("env file `n_humans`", "`EnvConfig.n_humans`"),
    ("evaluate", "max_humans"): ("env file `max_humans`", "`EnvConfig.max_humans`"),
    ("evaluate", "config"): ("an env file; experiment `env`, `scenario_env.<scenario>`", "`load_config(path)`"),
    ("evaluate", "perturb"): ("env file `perturbation.<key>`", "`EnvConfig.perturbation.<key>`"),
    ("evaluate", "safety"): ("experiment `safety.thresholds.<estimator>`",
                             "`SafePolicy(policy, estimator, thresholds)`, `load_thresholds()`"),
    ("evaluate", "estimator"): ("experiment `safety.estimators`", "`socnav.uncertainty.make_estimator(kind)`"),
    ("evaluate", "sensing"): ("experiment `safety.sensing`; threshold file `sensing`", "`Thresholds.sensing`"),
    ("evaluate", "members"): ("— (experiment: the policies of `grid.seeds`)", "`EnsembleEstimator(policies)`"),
    ("evaluate", "k"): ("experiment `safety.k`", "`MCDropoutEstimator(k=)`"),
    ("evaluate", "n_envs"): ("experiment `evaluation.n_envs`", "`rollout_episodes(n_envs=)`"),
    ("evaluate", "out"): ("—", "`socnav.io.write_table_atomic(records, path)`"),
    ("evaluate", "force"): ("—", "— (`write_table_atomic` replaces the file; the CLI checks with "
                                 "`socnav.io.check_output_file(path, force=)`)"),
    ("evaluate", "humans"): HUMANS,
    # socnav calibrate -> socnav.safety.calibrate_thresholds(policy, estimator, env, episodes, budget, ...)
    ("calibrate", "model"): ("—", "`socnav.load_policy(path)`"),
    ("calibrate", "estimator"): ("experiment `safety.estimators`", "`socnav.uncertainty.make_estimator(kind)`"),
    ("calibrate", "members"): ("— (experiment: the policies of `grid.seeds`)", "`EnsembleEstimator(policies)`"),
    ("calibrate", "k"): ("experiment `safety.k`", "`MCDropoutEstimator(k=)`"),
    ("calibrate", "scenario"): ("env file `scenario`", "`EnvConfig.scenario`"),
    ("calibrate", "n_humans"): ("env file `n_humans`", "`EnvConfig.n_humans`"),
    ("calibrate", "max_humans"): ("env file `max_humans`", "`EnvConfig.max_humans`"),
    ("calibrate", "config"): ("an env file", "`calibrate_thresholds(env=)`"),
    ("calibrate", "episodes"): ("experiment `safety.calibration_episodes`", "`calibrate_thresholds(episodes=)`"),
    ("calibrate", "false_activation_budget"): ("experiment `safety.false_activation_budget`",
                                               "`calibrate_thresholds(budget=)`, "
                                               "`select_by_proxy(false_activation_budget=)`"),
    ("calibrate", "budget"): ("—", "hidden, deprecated: `--false-activation-budget`"),
    ("calibrate", "proximity"): ("experiment `safety.calibration_proximity`", "`calibrate_thresholds(proximity=)`"),
    ("calibrate", "sensing"): ("experiment `safety.sensing`", "`calibrate_thresholds(sensing=)`"),
    ("calibrate", "confidence"): ("— (experiments use the default)", "`calibrate_thresholds(confidence=)`"),
    ("calibrate", "out"): ("— (a threshold file: Thresholds fields)", "`save_thresholds(thresholds, path)`"),
    ("calibrate", "force"): ("—", "— (`save_thresholds` replaces the file)"),
    ("calibrate", "humans"): HUMANS,
    ("calibrate", "trigger"): ("experiment `safety.triggers` (the rows a `safety_benchmark` calibrates)",
                               "`calibrate_thresholds(conditions=)` (the rule's variants); "
                               "`socnav.safety.calibration.trigger_search.calibrate_score_triggers` (score triggers)"),
    # socnav run -> socnav.experiments.load_experiment(path, budget) + run_experiment(experiment, root, ...)
    ("run", "experiment"): ("the experiment file (below)", "`load_experiment(path)`"),
    ("run", "budget"): ("experiment `budgets.<name>` (a compute budget)", "`load_experiment(path, budget=)`"),
    ("run", "backend"): ("—", "`run_experiment(backend=)`"),
    ("run", "address"): ("—", "`run_experiment(address=)`"),
    ("run", "workers"): ("—", "`run_experiment(workers=)`"),
    ("run", "retries"): ("—", "`run_experiment(retries=)`"),
    ("run", "out"): ("— (default `runs/<name>-<budget>`)", "`run_experiment(root=)`"),
    ("run", "dry_run"): ("—", "`plan_units(experiment)`, `unit_states(root, units)`"),
    # socnav tune -> socnav.cli.workflows.tune.tune(config, algo, trials, ...) and write_preset(path, ...)
    ("tune", "algo"): ("experiment `grid.algorithms`", "`tune(algo=)`"),
    ("tune", "scenario"): ("env file `scenario`", "`EnvConfig.scenario`"),
    ("tune", "trials"): ("—", "`tune(trials=)`"),
    ("tune", "storage"): ("—", "`tune(storage=)`"),
    ("tune", "timesteps"): ("experiment `grid.timesteps`", "`tune(timesteps=)`"),
    ("tune", "study_name"): ("—", "`tune(study_name=)`"),
    ("tune", "n_envs"): ("experiment `grid.n_envs`", "`tune(n_envs=)`"),
    ("tune", "eval_every"): ("experiment `grid.eval_every`", "`tune(eval_every=)`"),
    ("tune", "eval_episodes"): ("experiment `grid.validation_episodes`", "`tune(eval_episodes=)`"),
    ("tune", "metric"): ("—", "`tune(metric=)`"),
    ("tune", "seed"): ("one seed of `grid.seeds`", "`tune(seed=)`"),
    ("tune", "n_humans"): ("env file `n_humans`", "`EnvConfig.n_humans`"),
    ("tune", "config"): ("an env file", "`tune(config=)`"),
    ("tune", "out"): ("—", "`tune(out_dir=)`"),
    ("tune", "timeout"): ("—", "`tune(timeout=)`"),
    ("tune", "write_preset"): ("writes a preset file for `--algo-config` / `grid.algo_overrides.<algo>`",
                               "`write_preset(path, result, ...)`"),
    ("tune", "force"): ("—", "— (`write_preset` replaces the file)"),
    ("tune", "humans"): HUMANS,
    # socnav export -> socnav.export.export_onnx(model, out, thresholds, k, p_test, window, with_value)
    ("export", "model"): ("—", "`export_onnx(model=)`"),
    ("export", "out"): ("—", "`export_onnx(out=)`"),
    ("export", "thresholds"): ("a threshold file; experiment `safety.thresholds.<estimator>`",
                               "`export_onnx(thresholds=)`"),
    ("export", "k"): ("experiment `safety.k`", "`export_onnx(k=)`"),
    ("export", "p_test"): ("experiment `study.p_test`; hyperparameter `p_test`", "`export_onnx(p_test=)`"),
    ("export", "window"): ("experiment `safety.window`", "`export_onnx(window=)`"),
    ("export", "value"): ("—", "`export_onnx(with_value=)`"),
    ("export", "force"): ("—", "— (`export_onnx` replaces the file)"),
}


def command_params(command: str) -> list[Any]:
    """The click parameters of `socnav <command>` (hidden ones included, `--help` excluded)."""
    import typer.main

    from socnav.cli import app

    return [param for param in typer.main.get_command(app).commands[command].params if param.name != "help"]


def flag_name(param: Any) -> str:
    """`--n-envs`, `--stochastic / --no-stochastic`, or an argument's metavar (`EXPERIMENT`)."""
    if param.param_type_name == "argument":
        return param.name.upper()
    return " / ".join(param.opts + list(param.secondary_opts))


def choices() -> dict[str, tuple[str, ...]]:
    """CLI parameter name -> its allowed values, from the code that checks them (the same name means the same
    values in every command)."""
    from socnav.cli.workflows.tune import METRICS
    from socnav.controllers import CONTROLLERS
    from socnav.experiments.runner import run_experiment
    from socnav.rl.persistence import PRETRAINED_FILES
    from socnav.rl.presets import ALGOS
    from socnav.safety import PROXIMITY_VARIANTS, SENSING_CHOICES, THRESHOLD_PRESETS
    from socnav.sim.humans import human_model_names
    from socnav.sim.scenarios import scenario_names
    from socnav.uncertainty import ESTIMATOR_KINDS

    return {
        "scenario": tuple(scenario_names()), "algo": ALGOS, "controller": tuple(CONTROLLERS),
        "estimator": tuple(ESTIMATOR_KINDS), "sensing": SENSING_CHOICES, "proximity": ("both", *PROXIMITY_VARIANTS),
        "safety": (*THRESHOLD_PRESETS, "FILE"), "thresholds": (*THRESHOLD_PRESETS, "FILE"),
        "backend": typing.get_args(typing.get_type_hints(run_experiment)["backend"]), "metric": tuple(METRICS),
        "model": ("FILE", *PRETRAINED_FILES), "humans": tuple(human_model_names()),
    }


def flag_values(param: Any, allowed: dict[str, tuple[str, ...]]) -> str:
    """Allowed values of a CLI parameter: its choices, range and default."""
    parts = [" | ".join(allowed[param.name])] if param.name in allowed else []
    limits = ((">=", getattr(param, "min", None)), ("<=", getattr(param, "max", None)))
    bounds = [f"{op} {value}" for op, value in limits if value is not None]
    if bounds:
        parts.append(", ".join(bounds))
    if getattr(param, "multiple", False):
        parts.append("repeatable")
    if param.required:
        parts.append("required")
    elif param.default not in (None, [], ()) and not getattr(param, "is_flag", False):
        parts.append(f"default {param.default}")
    return "; ".join(parts) or "—"


def named_values() -> dict[str, tuple[str, ...]]:
    """Fields (dotted, as in the doc) whose strings name something registered in the code, and those names."""
    from socnav.envs.perturbations import PERTURBATION_FIELDS
    from socnav.experiments.registry import experiment_kinds
    from socnav.rl.presets import ALGOS
    from socnav.sim.humans import human_model_names
    from socnav.sim.scenarios import scenario_names

    scenarios = tuple(scenario_names())
    return {
        "scenario": scenarios, "humans.model": tuple(human_model_names()), "kind": tuple(experiment_kinds()), "scenario_env": scenarios, "grid.algorithms": ALGOS,
        "grid.train_scenarios": scenarios, "grid.algo_overrides": ALGOS, "evaluation.scenarios": scenarios,
        "study.perturbations": tuple(PERTURBATION_FIELDS), "safety.perturbations": tuple(PERTURBATION_FIELDS),
        "safety.thresholds": ("mc", "ensemble"), "budgets.<name>.algorithms": ALGOS,
        "budgets.<name>.train_scenarios": scenarios, "budgets.<name>.eval_scenarios": scenarios,
        "budgets.<name>.study_perturbations": tuple(PERTURBATION_FIELDS),
        "budgets.<name>.safety_perturbations": tuple(PERTURBATION_FIELDS),
    }


def model_rows(model: type[BaseModel], prefix: str = "") -> list[tuple[str, str, str, str]]:
    """(dotted field, allowed values, default, description) of every field of `model`, nested models expanded."""
    named = named_values()
    rows = []
    for name, info in model.model_fields.items():
        annotation = info.annotation
        if isinstance(annotation, type) and issubclass(annotation, BaseModel):
            rows += model_rows(annotation, f"{prefix}{name}.")
            continue
        default = "required" if info.is_required() else yaml_value(info.get_default(call_default_factory=True))
        values = type_name(annotation)
        bounds = bounds_text(info.metadata)
        values = f"{values} ({bounds})" if bounds else values
        if prefix + name in named:  # names checked by a validator: list them
            values += f"; names (keys) from: {', '.join(named[prefix + name])}"
        rows.append((prefix + name, values, default, info.description or ""))
    return rows


def bounds_text(metadata: Any) -> str:
    """'> 0, <= 2' from pydantic's constraint objects (annotated_types Gt, Ge, Lt, Le, MaxLen)."""
    # Annotated[int, Field(gt=0)] carries a FieldInfo whose own metadata holds the constraints
    items = [part for item in metadata for part in getattr(item, "metadata", [item])]
    symbols = (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<="), ("max_length", "at most"))
    return ", ".join(f"{symbol} {getattr(item, attr)}" for item in items for attr, symbol in symbols
                     if getattr(item, attr, None) is not None)


def type_name(annotation: Any) -> str:
    """A type as a YAML writer reads it: 'int or [int, int] or null', 'list of (int > 0)', 'random | goal'."""
    import types

    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is typing.Annotated:
        bounds = bounds_text(args[1:])
        return f"({type_name(args[0])} {bounds})" if bounds else type_name(args[0])
    if origin is typing.Literal:
        return " | ".join(map(str, args))
    if origin in (typing.Union, types.UnionType):
        names = [type_name(arg) for arg in args if arg is not type(None)]
        return " or ".join(names) + (" or null" if type(None) in args else "")
    if origin is tuple:
        return f"list of {type_name(args[0])}" if args[1:] == (Ellipsis,) else f"[{', '.join(map(type_name, args))}]"
    if origin is list:
        return f"list of {type_name(args[0])}"
    if origin is dict:
        value = type_name(args[1])
        return f"mapping {type_name(args[0])} -> {f'({value})' if ' or ' in value else value}"
    return "any" if annotation is Any else getattr(annotation, "__name__", str(annotation))


def yaml_value(value: Any) -> str:
    """A default as YAML writes it (null, true, [0.5, 1.0])."""
    import yaml

    text = yaml.safe_dump(value, default_flow_style=True, width=10_000, sort_keys=False)
    return text.strip().removesuffix("...").strip()


def cell(text: str) -> str:
    """Text for a Markdown table cell."""
    return text.replace("|", "\\|").replace("\n", " ")


def flag_table(command: str, allowed: dict[str, tuple[str, ...]]) -> list[str]:
    lines = [f"### `socnav {command}`", "", "| CLI flag | YAML field | Python name | allowed values |",
             "|---|---|---|---|"]
    for param in command_params(command):
        yaml_field, python = FLAGS.get((command, param.name), ("?", "?"))
        lines.append(f"| `{flag_name(param)}` | {yaml_field} | {python} | {cell(flag_values(param, allowed))} |")
    return lines + [""]


def field_table(title: str, model: type[BaseModel], prefix: str = "") -> list[str]:
    lines = [title, "", "| YAML field = Python attribute | allowed values | default | meaning |", "|---|---|---|---|"]
    for name, values, default, description in model_rows(model, prefix):
        lines.append(f"| `{name}` | {cell(values)} | {cell(default)} | {cell(description)} |")
    return lines + [""]


INTRO = """# Configuration: CLI flags, YAML fields and Python names

Generated by `python docs/configuration_table.py > docs/configuration.md` from the typer app and the pydantic
models; `tests/test_config_docs.py` fails when a flag or a field is missing here.

Every config (env, hyperparameters, safety thresholds, experiment files) is one strict pydantic model
(`socnav.config.StrictModel`: unknown fields refused, floats finite, counts strict integers), read from YAML by one
bounded loader (`socnav.config.read_mapping_file`: 1 MiB, 100,000 values with aliases expanded), merged by one
`deep_merge` and reported by one formatter (`socnav.config.format_validation_error`): each bad field on its own
line with its path, what is allowed and the value given, e.g.
`  - reward.gaol: unknown field; allowed fields: goal, collision, ...; did you mean goal? (got 1)`.

**Seeds.** In an experiment file `grid.seeds: N` means the training seeds 0..N-1 and a list (`[0, 3, 7]`) means
those seeds; `--seed` on the command line is always one seed (`socnav train --seed 3` is one unit of
`grid.seeds: [3]`); `evaluation.seed` and `evaluate --seed` are the first episode seed (episode k uses seed + k).
**Budgets.** `socnav run --budget NAME` picks a named compute budget of the experiment (`budgets.<name>`); the
false-activation rate of the safety calibration is `--false-activation-budget` / `safety.false_activation_budget`.

Deprecated names (still accepted with a warning, or refused with a pointer to the new name):

| deprecated name | use instead | what happens |
|---|---|---|
| `socnav evaluate --policy orca` | `--controller orca` (non-learned baselines; `--model` takes trained policies) | hidden alias, prints a deprecation warning |
| `socnav calibrate --budget 0.05` | `--false-activation-budget 0.05` | hidden alias, prints a deprecation warning |
| hyperparameter `dropout_p` (YAML, `--set`, `overrides`) | `p_train` (the paper's name) | refused: "renamed: write p_train" |

## Commands
"""


def main() -> None:
    from socnav.config import EnvConfig
    from socnav.experiments.spec import Budget, Evaluation, Experiment, Grid, Safety, Study
    from socnav.rl.presets import AlgoConfig
    from socnav.safety.rule import Thresholds

    lines = [INTRO]
    allowed = choices()
    for command in COMMANDS:
        lines += flag_table(command, allowed)
    lines += ["## Config files", ""]
    lines += field_table("### Env config: `--config FILE`, experiment `env` and `scenario_env.<scenario>` "
                         "(`socnav.EnvConfig`)", EnvConfig)
    lines += field_table("### Hyperparameters: `--set`, `--algo-config FILE`, experiment `grid.overrides` and "
                         "`grid.algo_overrides.<algo>` (`socnav.rl.AlgoConfig`)", AlgoConfig)
    lines += field_table("### Safety thresholds: `--safety FILE`, `export --thresholds FILE`, experiment "
                         "`safety.thresholds.<estimator>` (`socnav.safety.Thresholds`)", Thresholds)
    lines += ["### Experiment files: `socnav run FILE` (`socnav.experiments.spec.Experiment`)", "",
              "| YAML field = Python attribute | allowed values | default | meaning |", "|---|---|---|---|"]
    for name, values, default, description in model_rows(Experiment):
        if name.split(".")[0] not in ("grid", "evaluation", "study", "safety", "budgets"):
            lines.append(f"| `{name}` | {cell(values)} | {cell(default)} | {cell(description)} |")
    lines.append("")
    for block, model in (("grid", Grid), ("evaluation", Evaluation), ("study", Study), ("safety", Safety),
                         ("budgets.<name>", Budget)):
        lines += field_table(f"#### `{block}`", model, f"{block}.")
    print("\n".join(lines).rstrip())


if __name__ == "__main__":
    main()
