"""What the `socnav` commands share: the world a command plays (options, config file or a model's training world),
its checks of paths and choices before any work, loading policies, estimators and thresholds, and progress bars and
metric tables. Each check ends the command with one clear line (`socnav._console.fail`), never a traceback.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any

from rich.markup import escape
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn
from rich.table import Table

from socnav._console import console, fail
from socnav.config import ConfigError, EnvConfig, describe_world, load_config
from socnav.sim.metrics import PV_PER

if TYPE_CHECKING:  # pandas, torch and SB3 load inside the commands: `socnav --help` stays fast
    import pandas as pd


def deprecated_alias(old: str, new: str) -> Callable[[Any], Any]:
    """Callback of a hidden option kept under its old name: warns when it is used and passes its value on (the
    command takes it as the value of `new`)."""

    def warn(value: Any) -> Any:
        if value is not None:
            console.print(f"[yellow]warning:[/] {old} is deprecated: use {new}", highlight=False)
        return value

    return warn


def check_n_envs(n_envs: int, env_config: EnvConfig) -> None:
    """Refuse --n-envs whose environments cannot fit in memory, before anything is built or written."""
    from socnav.envs.env import check_env_count

    try:
        check_env_count(n_envs, env_config, "--n-envs")
    except ConfigError as exc:
        fail(str(exc))


def command_env_config(scenario: str | None, config_file: Path | None, n_humans: int | None,
                max_humans: int | None = None, base: Any = None, observes: int | None = None,
                humans: str | None = None) -> EnvConfig:
    """The env config of a command: `base` (a config file, or e.g. a model's stored config), then the options.

    :param observes: the max_humans of the model the command runs, if any: raising max_humans is then no way out
        (a model runs only with the observation size it was trained with), fewer humans are.
    :param humans: --humans, the human model (checked by `check_human_model`).
    """
    import re

    overrides: dict[str, Any] = {}
    if scenario is not None:
        overrides["scenario"] = scenario
    if humans is not None:  # one model for every human: a mixed crowd of the base world is replaced, not kept
        overrides["humans"] = {"model": humans, "mix": None}
    if n_humans is not None:
        overrides["n_humans"] = n_humans
    if max_humans is not None:
        overrides["max_humans"] = max_humans
    try:
        return load_config(config_file if base is None else base, **overrides)
    except ConfigError as exc:
        message = str(exc)
        needed = re.search(r"raise max_humans to at least (\d+)", message)
        limit = EnvConfig.model_fields["max_humans"].metadata  # the field's bounds, e.g. Le(le=64)
        most = min((bound.le for bound in limit if getattr(bound, "le", None) is not None), default=None)
        if needed and observes is not None:
            message += (f"\n  the model observes at most {observes} humans (it was trained with max_humans="
                        f"{observes}): use --n-humans {observes} or fewer")
        elif needed and most is not None and int(needed.group(1)) > most:
            message += f"\n  at most {most} humans are supported (max_humans <= {most})"
        elif needed and max_humans is None:
            message += f"\n  from the command line: --max-humans {needed.group(1)}"
        fail(message)
        raise  # unreachable, keeps type checkers happy


def progress_display() -> Progress:
    return Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
        TextColumn("ETA"), TimeRemainingColumn(), console=console,
    )


@contextmanager
def progress_bar(label: str, total: int) -> Iterator[Callable[[int], None]]:
    """One progress bar of `total` episodes, shown while the block runs; yields its `advance(n)` (a library step's
    ``progress``, e.g. `socnav.cli.workflows.demo.ProgressBar`)."""
    with progress_display() as progress:
        task = progress.add_task(escape(label), total=total)
        yield lambda n: progress.advance(task, n)


def metrics_table(rows: list[tuple[str, dict[str, float]]], title: str) -> Table:
    """The paper's metrics as a rich table: Goal %, Collision %, Time-out %, PV per 200 episodes, navigation time
    (mean time to the goal of the successful episodes, CrowdNav's "nav time"), Return mean ± std, and the share of
    steps where the safety fallback acted when the rows have ``fallback_pct``."""
    import math

    table = Table(title=title, caption=f"PV: personal-space violations (intrusion events) per {PV_PER} episodes; "
                  "nav time of the episodes reaching the goal")
    fallback = any("fallback_pct" in m for _, m in rows)
    walls = any("collision_obstacle_pct" in m for _, m in rows)  # worlds with walls: wall collisions, apart
    columns = ["run", "episodes", "Goal %", "Col. %", "TO %", f"PV/{PV_PER} ep.", "nav time (s)", "Return"]
    if walls:
        columns.insert(4, "Wall %")
    for column in columns + (["fallback % steps"] if fallback else []):
        table.add_column(column, justify="right" if column != "run" else "left", no_wrap=column != "run")
    for name, m in rows:
        nav_time = m.get("time_to_goal_mean", float("nan"))
        cells = [escape(name), str(m["episodes"]), f"{m['goal_pct']:.1f}", f"{m['collision_pct']:.1f}",
                 f"{m['timeout_pct']:.1f}", f"{m['pv']:.0f}", "–" if math.isnan(nav_time) else f"{nav_time:.1f}",
                 f"{m['return_mean']:.2f} ± {m['return_std']:.2f}"]
        if walls:
            cells.insert(4, f"{m['collision_obstacle_pct']:.1f}" if "collision_obstacle_pct" in m else "–")
        if fallback:
            cells.append(f"{m['fallback_pct']:.1f}" if "fallback_pct" in m else "–")
        table.add_row(*cells)
    return table


def play_episodes(policy: Any, config: EnvConfig, episodes: int, seed: int, n_envs: int, label: str,
              deterministic: bool = True, observer: Any = None) -> pd.DataFrame:
    from socnav.envs.rollout import rollout_episodes

    with progress_bar(label, episodes) as advance:
        return rollout_episodes(policy, config, episodes, seed=seed, n_envs=n_envs, deterministic=deterministic,
                                progress=advance, observer=observer)


def yaml_value(option: str, text: str) -> Any:
    """A YAML value given on the command line, read with socnav's bounded loader; bad or oversized YAML (or an
    integer of thousands of digits) is a one-line error naming the option."""
    import yaml

    from socnav.config import safe_load_yaml, yaml_problem

    shown = repr(text if len(text) <= 60 else text[:57] + "...")
    try:
        return safe_load_yaml(text)
    except yaml.YAMLError as exc:
        fail(f"{option} {shown} {' '.join(yaml_problem(exc).split())}")
    except ValueError as exc:  # YAML parses it, Python will not build it, e.g. an integer of 5,000 digits
        import sys

        digits = sys.get_int_max_str_digits()
        reason = (f"an integer of more than {digits:,} digits" if "integer string conversion" in str(exc)
                  else " ".join(str(exc).split())[:200])
        fail(f"{option} {shown} is refused: {reason}")


def check_out_file(option: str, path: Path, force: bool = False, create_parent: bool = False) -> None:
    """A clear error, before any work, when the output file `path` cannot or may not be written
    (`socnav.io.check_output_file`): an existing file without --force, a directory, FIFO or device, a path in
    /proc, /sys or /dev, a directory that does not exist (a typo is never created silently; `create_parent` only
    for a command's own default directory, e.g. runs/evaluate) or that cannot be written."""
    from socnav.io import OutputPathError, check_output_file

    try:
        check_output_file(path, what=option, force=force, create_parent=create_parent)
    except OutputPathError as exc:
        fail(str(exc))
    # Probed as well: root passes the permission check above where no file can be created (a read-only mount).
    check_out_writable(option, path, directory=False)


def check_human_model(humans: str | None) -> None:
    """--humans names a registered human model (`socnav.sim.humans`), or a one-line error with did-you-mean."""
    if humans is None:
        return
    from socnav.config import unknown_name_message
    from socnav.sim.humans import human_model_names

    if humans not in human_model_names():
        fail(f"--humans: {unknown_name_message('human model', humans, human_model_names())}")


def check_choice(option: str, value: str | None, allowed: Any) -> None:
    """A one-line error naming `option` and the `allowed` values when `value` (None: not given) is not one."""
    if value is not None and value not in allowed:
        fail(f"{option} {value!r} is not known; allowed: {', '.join(allowed)}")


def check_members(members: str | None) -> None:
    """--members matches at least two policy files (checked before any of them loads)."""
    import glob

    if members is None:
        return
    paths = sorted(glob.glob(members))
    if len(paths) < 2:
        fail(f"--members {members!r} matches {len(paths)} policy file(s); an ensemble needs at least 2")


def check_perturbations(settings: list[str]) -> None:
    """The --perturb settings parse and name known perturbation fields with valid values, before a model loads
    (the world they apply to is known only after)."""
    if not settings:
        return
    try:
        load_config(None, perturbation=perturbation_overrides(settings))
    except ConfigError as exc:
        fail(str(exc))


def note_other_world(trained: Any, env_config: EnvConfig, label: str) -> None:
    """One line when a policy plays outside the world it was trained in (`trained`: the env config its file
    records): another scenario, walls it never saw (or none of those it learned with), another human model. The
    numbers then measure how the policy generalises, which a user may not have meant to measure."""
    from socnav.sim.walls import has_walls

    try:
        world = load_config(trained)
    except ConfigError:  # validated when the policy loaded; a note is not worth an error
        return

    def walls(config: EnvConfig) -> str:
        return "walls" if has_walls(config) else "no walls"

    changes = []
    if world.scenario != env_config.scenario:
        changes.append(f"scenario {world.scenario} -> {env_config.scenario}")
    if has_walls(world) != has_walls(env_config):
        changes.append(f"{walls(world)} -> {walls(env_config)}")
    elif has_walls(world) and (world.obstacles, world.map) != (env_config.obstacles, env_config.map):
        changes.append("other walls")
    if (world.humans.model, world.humans.mix) != (env_config.humans.model, env_config.humans.mix):
        changes.append(f"humans {world.humans.model} -> {env_config.humans.model}")
    if changes:
        console.print(f"note: {escape(label)} runs outside the world it was trained in ({escape('; '.join(changes))}"
                      "): the results measure how it generalises", highlight=False)


def check_out_writable(option: str, path: Path, directory: bool = True) -> None:
    """A clear error, before any work, when `path` (a directory to create, or a file whose directory it is) cannot
    be written: a parent that is a file, a dangling link, or a place where no file can be created (no permission,
    a read-only or virtual filesystem such as /proc). Probed by creating and removing a temporary file in the
    nearest existing directory, which also holds for root, whom permission bits do not stop."""
    import os
    import tempfile

    existing = path if directory else path.parent
    while not existing.exists():
        if existing.is_symlink():
            fail(f"{option} {path}: {existing} is a dangling symbolic link")
        if existing == existing.parent:
            break
        existing = existing.parent
    if not existing.is_dir():
        fail(f"{option} {path}: {existing} is a file, not a directory")
    try:
        handle, probe = tempfile.mkstemp(prefix=".socnav-write-probe.", dir=existing)
    except OSError as exc:
        fail(f"{option} {path}: cannot write in {existing} ({exc.strerror or exc})")
    os.close(handle)
    os.unlink(probe)


def single_agent_env_config(scenario: str | None, config_file: Path | None, n_humans: int | None,
                             max_humans: int | None = None, humans: str | None = None) -> EnvConfig:
    """`command_env_config` for animate / calibrate: without --config, position swap with one human unless given."""
    if config_file is None:
        scenario = "position_swap" if scenario is None else scenario
        n_humans = 1 if n_humans is None else n_humans
    return command_env_config(scenario, config_file, n_humans, max_humans, humans=humans)


def check_observation_size(policies: list[Any], env_config: EnvConfig) -> None:
    """A clear error (not a reshape traceback) when a policy observes a different max_humans than the env, with
    the option that fixes it."""
    for policy in policies:
        observed = policy.observation_space["humans"].shape[0]
        if observed != env_config.max_humans:
            _, most = env_config.humans_range()
            fix = (f"--max-humans {observed}" if most <= observed else
                   f"--max-humans {observed} with at most {observed} humans (--n-humans {observed} or fewer)")
            fail(f"the model observes max_humans={observed} but the env config has "
                 f"max_humans={env_config.max_humans}; a model runs only with the value it was trained with: "
                 f"use {fix}")


def model_world(model: str | None, scenario: str | None, config: Path | None, n_humans: int | None,
                 max_humans: int | None, default: Callable[[], EnvConfig], humans: str | None = None) -> EnvConfig:
    """The world a command plays: with --model and without --config, the world the model was trained in (as
    `evaluate` does; --scenario, --n-humans, --max-humans, --humans change it), else `default()`. Prints which
    world, and a note when the model plays outside its training world."""
    if model is None or config is not None:  # (with --config the user chose the world: no note)
        env_config = default()
        origin = f"--config {config}" if config is not None else "defaults"
    else:
        from socnav.rl.persistence import training_world

        policy = load_learned_policy(model)
        base, origin = training_world(policy, scenario, n_humans, max_humans)
        origin += ", changed by the options" if humans is not None and "changed" not in origin else ""
        env_config = command_env_config(scenario, None, n_humans, max_humans, base=base,
                                 observes=policy.observation_space["humans"].shape[0], humans=humans)
    console.print(f"world: {escape(describe_world(env_config))} ({escape(origin)})", highlight=False)
    if model is not None and config is None:
        note_other_world(policy.socnav_metadata["env_config"], env_config, model_label(model))
    return env_config


def load_learned_policy(model: str) -> Any:
    if is_navigator_file(model):  # else "corrupted or not a zip archive" for a valid export
        fail(f"--model {model} is an exported navigator (ONNX): socnav evaluate scores it; this command needs the "
             "policy file it was exported from (socnav train's model.zip, or pretrained)")
    import torch

    from socnav.rl.persistence import PolicyLoadError, load_policy

    # Batched inference on small matrices: one thread is faster than torch's intra-op pool, which also collapses
    # when the cores are shared.
    torch.set_num_threads(1)
    try:
        return load_policy(model)
    except PolicyLoadError as exc:
        fail(str(exc))


def model_label(model: str) -> str:
    """How a model file is named in tables and default output names: its path as given (`runs/swap/model.zip`),
    so that two runs' `model.zip` files stay apart; the name of a shipped policy ('pretrained', 'pretrained-maps',
    'pretrained-ppo')."""
    from socnav.rl.persistence import PRETRAINED_FILES

    return model if model in PRETRAINED_FILES else str(Path(model))


def is_navigator_file(model: str) -> bool:
    """Whether --model names an exported navigator (`socnav export`'s ONNX file) rather than a policy file."""
    return Path(model).suffix.lower() == ".onnx"


def check_estimator_options(kind: str, model: str | None, members: str | None) -> None:
    """--estimator `kind` is known and has what it estimates with (--model for mc, --members for ensemble), checked
    before any model loads (`estimator_policies` loads them)."""
    from socnav.uncertainty import ESTIMATOR_KINDS

    check_choice("--estimator", kind, ESTIMATOR_KINDS)
    if kind == "mc" and model is None:
        fail("--estimator mc needs --model PATH (or --model pretrained)")
    if kind == "ensemble" and members is None:
        fail("--estimator ensemble needs --members GLOB, e.g. 'runs/ensemble-quick/units/*/model.zip'")
    check_members(members)


def load_thresholds_option(safety: str, sensing: str | None = None) -> Any:
    """`--safety mc | ensemble | FILE` (with `--sensing perceived | true` if given) as `Thresholds` or, for a
    trigger file (socnav.safety.triggers), a `TriggerSpec`; or a clear error."""
    from socnav.safety import SENSING_CHOICES, Thresholds, ThresholdsError
    from socnav.safety.triggers import TriggerError, TriggerSpec, load_safety

    if Path(safety).is_dir():
        fail(f"--safety {safety} is a directory; name a thresholds or trigger file (.yaml or .json, from socnav "
             "calibrate) or a preset: mc, ensemble")
    try:
        decision = load_safety(safety)
    except (ThresholdsError, TriggerError, OSError) as exc:
        fail(f"--safety: {exc}")
    if sensing is None:
        return decision
    if sensing not in SENSING_CHOICES:
        fail(f"--sensing {sensing!r} is not known; allowed: {', '.join(SENSING_CHOICES)}")
    if isinstance(decision, TriggerSpec):
        return TriggerSpec.create(decision.model_dump(), sensing=sensing)
    return Thresholds.create(decision.model_dump(), sensing=sensing)


def perturbed_config(env_config: EnvConfig, settings: list[str]) -> EnvConfig:
    """`env_config` with the `--perturb key=value` settings on top of its own perturbation."""
    if not settings:
        return env_config
    perturbation = perturbation_overrides(settings)
    try:
        return load_config(env_config, perturbation={**env_config.perturbation.model_dump(), **perturbation})
    except ConfigError as exc:
        fail(str(exc))
        raise


def policy_and_estimator(kind: str, model: str | None, members: str | None, k: int,
               env_config: EnvConfig, required: bool = True) -> tuple[Any, Any]:
    """(policy that acts, uncertainty estimator) for `--estimator mc|ensemble`.

    :param required: whether the command needs the estimate (a safety layer, a calibration): then a model without
        dropout layers under ``mc`` is an error; else its estimator is None (nothing to estimate), with a note.
    """
    from socnav.safety.assembly import make_safety_estimator

    policy, ensemble = estimator_policies(kind, model, members, env_config)
    if kind == "mc" and not check_mc_dropout(str(model), policy, required):
        return policy, None
    # MC dropout draws from a private, seeded mask stream (as the experiment units do): the same command gives the
    # same thresholds and the same animation, instead of drawing from torch's unseeded global RNG.
    return policy, make_safety_estimator(kind, policy, ensemble, k)


def estimator_policies(kind: str, model: str | None, members: str | None,
                        env_config: EnvConfig) -> tuple[Any, list[Any]]:
    """(policy that acts, the ensemble's members: none under mc) of `--estimator kind`, loaded and checked against
    the world's observation size."""
    import glob

    from socnav.uncertainty import ESTIMATOR_KINDS

    if kind not in ESTIMATOR_KINDS:
        fail(f"--estimator {kind!r} is not known; allowed: {', '.join(ESTIMATOR_KINDS)}")
    if kind == "mc":
        if model is None:
            fail("--estimator mc needs --model PATH (or --model pretrained)")
        policy = load_learned_policy(model)
        check_observation_size([policy], env_config)
        return policy, []
    if members is None:
        fail("--estimator ensemble needs --members GLOB, e.g. 'runs/ensemble-quick/units/*/model.zip'")
    paths = sorted(glob.glob(members))
    if len(paths) < 2:
        fail(f"--members {members!r} matches {len(paths)} policy file(s); an ensemble needs at least 2")
    policies = [load_learned_policy(path) for path in paths]
    policy = load_learned_policy(model) if model is not None else policies[0]
    check_observation_size([policy, *policies], env_config)
    return policy, policies


def check_mc_dropout(model: str, policy: Any, required: bool) -> bool:
    """Whether MC dropout can sample `policy` (of --model `model`); if not, an error when the command needs the
    estimate (`required`), else a note that there is no uncertainty to draw."""
    from socnav.safety.assembly import has_mc_dropout

    if has_mc_dropout(policy):
        return True
    algo = policy.socnav_metadata.get("algo", "?")
    if required:
        fail(f"--estimator mc needs a model trained with dropout (odv-ppo-drop, ppo-drop); {model} is "
             f"{algo}, trained without: use --estimator ensemble --members GLOB")
    console.print(f"note: no uncertainty bars: {escape(model)} ({escape(algo)}) was trained without dropout, "
                  "so MC-dropout has nothing to sample (--estimator ensemble --members GLOB estimates with "
                  "an ensemble)", highlight=False)
    return False


def perturbation_overrides(settings: list[str]) -> dict[str, Any]:
    perturbation: dict[str, Any] = {}
    for setting in settings:
        key, sep, value = setting.partition("=")
        if not sep or not key:
            fail(f"--perturb expects key=value (e.g. observation_noise=0.6), got {setting!r}")
        perturbation[key.strip()] = yaml_value("--perturb", value)
    return perturbation

