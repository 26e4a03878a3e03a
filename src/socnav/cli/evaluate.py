"""`socnav evaluate` (a controller, a trained policy, or an exported navigator, with or without the safety layer)
and `socnav animate` (one episode with its uncertainty drawn live).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

import typer
from rich.markup import escape
from rich.table import Table

from socnav._console import console, fail
from socnav.cli.options import (
    ACTING_MODEL_HELP,
    SCENARIOS,
    SINGLE_AGENT_MAX_HUMANS_HELP,
    SINGLE_AGENT_N_HUMANS_HELP,
    SINGLE_AGENT_SCENARIO_HELP,
    config_option,
    episodes_option,
    estimator_option,
    force_option,
    humans_option,
    max_humans_option,
    mc_samples_option,
    members_option,
    model_option,
    n_envs_option,
    n_humans_option,
    perturb_option,
    safety_option,
    scenario_option,
    seed_option,
    sensing_option,
)
from socnav.config import EnvConfig, describe_world
from socnav.sim.metrics import PV_PER

if TYPE_CHECKING:  # pandas, torch and SB3 load inside the commands: `socnav --help` stays fast
    import pandas as pd

    from socnav.envs.rollout import RolloutInterrupted
    from socnav.safety import SafePolicy

from socnav.cli.common import (
    check_estimator_options,
    check_human_model,
    check_mc_dropout,
    check_n_envs,
    check_observation_size,
    check_out_file,
    check_perturbations,
    command_env_config,
    deprecated_alias,
    estimator_policies,
    is_navigator_file,
    load_learned_policy,
    load_thresholds_option,
    metrics_table,
    model_label,
    model_world,
    note_other_world,
    perturbed_config,
    play_episodes,
    policy_and_estimator,
    single_agent_env_config,
)


def _default_records_path(label: str, config: EnvConfig, seed: int, episodes: int, extra: dict[str, Any]) -> Path:
    """runs/evaluate/<label>_<scenario>_<hash>_seed<k>_<n>ep.csv: unique per (policy or model file, env config,
    seed, episodes, and the other options that change the records), so two evaluations never share a file."""
    import hashlib
    import json
    import re

    identity = json.dumps({"label": label, "env": config.model_dump(mode="json"), **extra}, sort_keys=True)
    digest = hashlib.sha1(identity.encode()).hexdigest()[:8]
    slug = re.sub(r"[^A-Za-z0-9._-]+", "-", label.removesuffix(".zip")).strip("-")
    return Path("runs") / "evaluate" / f"{slug}_{config.scenario}_{digest}_seed{seed}_{episodes}ep.csv"


def evaluate(
    controller: str = typer.Option("orca", help="non-learned baseline controller: orca | straight (ignored with "
                                                "--model, which evaluates a trained policy)"),
    policy: str | None = typer.Option(None, "--policy", hidden=True,
                                         callback=deprecated_alias("--policy", "--controller"),
                                         help="deprecated name of --controller"),
    model: str | None = model_option("trained policy file, or 'pretrained' / 'pretrained-maps' / "
                                                  "'pretrained-ppo' for a shipped one"),
    stochastic: bool = typer.Option(False, help="sample actions instead of the mean action"),
    scenario: str | None = scenario_option(None, help=f"one of: {SCENARIOS} (default: the model's training world "
                                                       "with --model, else circle_crossing)"),
    episodes: int = episodes_option(200, help="number of evaluation episodes"),
    seed: int = seed_option("episode k uses seed + k"),
    n_humans: int | None = n_humans_option(),
    max_humans: int | None = max_humans_option("observation rows (default 10; a model needs the value it was "
                                                "trained with)"),
    config: Path | None = config_option(),
    perturb: list[str] = perturb_option(),
    safety: str | None = safety_option("wrap the model in the safety layer with these thresholds: mc | ensemble | "
                                       "FILE (from socnav calibrate)"),
    estimator: str | None = estimator_option(None, help="uncertainty estimator of --safety: mc | ensemble (default: "
                                                        "ensemble for --safety ensemble, else mc)"),
    sensing: str | None = sensing_option(),
    members: str | None = members_option(),
    k: int = mc_samples_option("MC-dropout samples, for --estimator mc"),
    n_envs: int = n_envs_option(32),
    out: Path | None = typer.Option(None, help="per-episode records (.csv or .parquet; default a name unique "
                                                  "to the policy, world, seed and episodes under runs/evaluate)"),
    metrics: str = typer.Option("default", "--metrics", help="default (Goal %, Col. %, TO %, PV, nav time, "
                                                             "Return) | all | NAME,... (docs/metrics.md); other than "
                                                             "default, the records also hold every metric's "
                                                             "per-episode column"),
    humans: str | None = humans_option(),
    force: bool = force_option("the --out records file"),
) -> None:
    """Evaluate a controller: Goal %, Collision %, Time-out %, PV, nav time, Return (--metrics: more); records to
    a file."""
    from socnav.controllers import CONTROLLERS, make_controller
    from socnav.envs.rollout import RolloutInterrupted
    from socnav.io import TABLE_FORMATS, write_table_atomic

    # Every option is checked before a model loads (18-24 s for the shipped one on a loaded machine).
    chosen = _chosen_metrics(metrics)
    controller = policy if policy is not None else controller
    if model is None and controller not in CONTROLLERS:
        fail(f"--controller {controller!r} is not known; allowed: {', '.join(CONTROLLERS)}")
    if out is not None and out.suffix not in TABLE_FORMATS:
        fail(f"--out must end in one of {', '.join(TABLE_FORMATS)}, got {out.name!r}")
    if safety is not None and model is None and members is None:
        fail("--safety needs a learned policy: --model PATH (or --model pretrained), or --estimator ensemble "
             "--members GLOB")
    exported = model is not None and is_navigator_file(model)
    if exported and (safety is not None or stochastic):
        fail(f"--model {model} is an exported navigator: evaluate scores its policy's deterministic action alone; "
             f"for {'--safety' if safety is not None else '--stochastic'} evaluate the policy file it was exported "
             "from (model.zip or pretrained)")
    if safety is not None:
        _check_safety_options(safety, sensing, estimator, model, members)
    check_perturbations(perturb)
    check_human_model(humans)
    if out is not None:
        check_out_file("--out", out, force=force)
    actor: Any = None if model is None else _load_navigator(model) if exported else load_learned_policy(model)
    env_config = _evaluation_world(actor, scenario, config, n_humans, max_humans, perturb, humans)
    name = model_label(model) if model is not None else controller
    if model is not None and config is None:
        note_other_world(actor.socnav_metadata["env_config"], env_config, name)
    observer = None
    if safety is not None:
        from socnav.safety import FallbackCounter

        actor = _safe_policy_option(safety, sensing, estimator, model, members, k, env_config)
        observer = FallbackCounter(actor)
        name = (name if model is not None else "ensemble") + f" + safety ({safety})"
    elif actor is not None:
        check_observation_size([actor], env_config)
    else:
        actor = make_controller(controller, env_config)
    if out is None:  # the command's own directory (runs/evaluate) is created, a --out directory never is
        out = _default_records_path(name, env_config, seed, episodes,
                                    {"stochastic": stochastic, "k": k, "estimator": estimator,
                                     "members": members, "sensing": sensing,
                                     **({"metrics": chosen} if chosen is not None else {})})
        check_out_file("--out", out, force=force, create_parent=True)
    if stochastic:
        import torch

        # Sampled actions come from torch's generator: seeded, a run repeats; they still depend on --n-envs (the
        # order in which the batch draws them), unlike the deterministic mean action.
        torch.manual_seed(seed)
    check_n_envs(min(n_envs, episodes), env_config)  # a rollout never steps more environments than episodes
    try:
        records = play_episodes(actor, env_config, episodes, seed, n_envs, f"{name} / {env_config.scenario}",
                            deterministic=not stochastic, observer=observer)
    except RolloutInterrupted as stopped:
        _save_interrupted_records(stopped, env_config, chosen, observer, out)
    records, summary = _evaluation_summary(records, env_config, chosen, observer)
    try:
        write_table_atomic(records, out)
    except OSError as exc:  # e.g. the disk filled up while the episodes ran
        fail(f"--out {out}: cannot write the records ({exc.strerror or exc})")
    title = f"{describe_world(env_config)}, seeds {seed}..{seed + episodes - 1}"
    if chosen is not None:
        console.print(_all_metrics_table(summary, chosen, f"{escape(name)}: {title}"))
    else:
        console.print(metrics_table([(name, summary)], title))
    console.print(f"per-episode records: {escape(str(out))}", highlight=False)


def _save_interrupted_records(stopped: RolloutInterrupted, env_config: EnvConfig, chosen: list[str] | None,
                              observer: Any, out: Path) -> NoReturn:
    """Ctrl-C during `evaluate`: the episodes finished by then are written to `out` (atomically: a second Ctrl-C
    leaves the file whole or absent), said in one line; exit code 130."""
    from socnav.io import write_table_atomic

    finished = len(stopped.records)
    if not finished:
        console.print("[yellow]interrupted[/] before any episode finished: nothing written", highlight=False)
        raise typer.Exit(code=130)
    records, _ = _evaluation_summary(stopped.records, env_config, chosen, observer)
    try:
        write_table_atomic(records, out)
    except OSError as exc:
        fail(f"interrupted; --out {out}: cannot write the {finished:,} finished episodes ({exc.strerror or exc})",
             code=130)
    console.print(f"[yellow]interrupted[/]: wrote the {finished:,} finished episodes (of {stopped.asked:,}) to "
                  f"{escape(str(out))}", highlight=False)
    raise typer.Exit(code=130)


class _ExportedActor:
    """An exported navigator's policy as `evaluate` plays it: the deterministic action of its ONNX graph for the
    whole batch (`socnav.runtime.ExportedPolicy.predict`, what the torch policy it came from gives), with what
    `evaluate` reads of a loaded policy file: the world it was trained in and the rows it observes."""

    def __init__(self, network: Any) -> None:
        from types import SimpleNamespace

        from socnav.envs.spaces import HUMAN_FEATURE_NAMES

        record = network.record
        self.network = network
        self.socnav_metadata = {"algo": record.policy.algo, "env_config": record.env_config.model_dump(mode="json")}
        self.observation_space = {"humans": SimpleNamespace(shape=(network.max_humans, len(HUMAN_FEATURE_NAMES)))}

    def predict(self, observation: dict[str, Any], state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[Any, Any]:
        return self.network.predict(observation, state, episode_start, deterministic)


def _load_navigator(model: str) -> _ExportedActor:
    """The policy of the navigator file `model` (torch-free, onnxruntime), or a one-line error."""
    import importlib.util

    from socnav.extras import install_hint

    if importlib.util.find_spec("onnxruntime") is None:
        fail(f"--model {model} is an exported navigator; running it needs onnxruntime: {install_hint('runtime')}")
    from socnav.runtime import ExportedPolicy, NavigatorLoadError

    try:
        return _ExportedActor(ExportedPolicy.load(model))
    except NavigatorLoadError as exc:
        fail(str(exc))


def _check_safety_options(safety: str, sensing: str | None, estimator: str | None, model: str | None,
                          members: str | None) -> None:
    """--safety and the options that go with it, checked before any model loads: the thresholds file or preset,
    --sensing, --estimator (by default the one the thresholds were made for) and what it needs."""
    from socnav.safety.assembly import default_estimator_kind

    load_thresholds_option(safety, sensing)
    check_estimator_options(estimator or default_estimator_kind(safety), model, members)


def _chosen_metrics(metrics: str) -> list[str] | None:
    """The metrics `evaluate --metrics` names, None for the default table's (then the records keep only the world's
    episode columns)."""
    from socnav.sim.metrics import DEFAULT_METRICS, select_metrics

    try:
        chosen = select_metrics(metrics)
    except ValueError as exc:
        fail(f"--metrics: {exc}")
    return None if tuple(chosen) == DEFAULT_METRICS else chosen


def _evaluation_world(actor: Any, scenario: str | None, config: Path | None, n_humans: int | None,
                      max_humans: int | None, perturb: list[str], humans: str | None = None) -> EnvConfig:
    """The world `evaluate` plays, printed: a learned `actor` without --config plays the world it was trained in
    (the world options change it), anything else --config's or the defaults; then the --perturb settings."""
    base: Path | dict[str, Any] | None = config
    origin = f"--config {config}" if config is not None else "defaults"
    if actor is not None and config is None:
        from socnav.rl.persistence import training_world

        base, origin = training_world(actor, scenario, n_humans, max_humans)
        origin += ", changed by the options" if humans is not None and "changed" not in origin else ""
    observes = None if actor is None else actor.observation_space["humans"].shape[0]
    env_config = perturbed_config(command_env_config(scenario, config, n_humans, max_humans, base=base,
                                               observes=observes, humans=humans), perturb)
    console.print(f"world: {escape(describe_world(env_config))} ({escape(origin)})", highlight=False)
    return env_config


def _evaluation_summary(records: pd.DataFrame, env_config: EnvConfig, chosen: list[str] | None,
                        observer: Any) -> tuple[pd.DataFrame, dict[str, Any]]:
    """The records `evaluate` writes and their summary: the `chosen` metrics (None: the default table's, and
    only the world's episode columns kept), the wall collisions in a world with walls, and the share of steps the
    safety fallback drove when an `observer` (`FallbackCounter`) counted them."""
    from socnav.envs.rollout import EPISODE_COLUMNS, summarize
    from socnav.sim.metrics import DEFAULT_METRICS
    from socnav.sim.walls import has_walls

    walls = has_walls(env_config)  # a world with walls also counts the episodes that ended against a wall
    if chosen is None:
        records = records[list(EPISODE_COLUMNS) + (["collision_obstacle"] if walls else [])].copy()
    defaults = DEFAULT_METRICS + (("collision_obstacle_pct",) if walls else ())
    summary = summarize(records, pv_per=PV_PER, metrics=chosen if chosen is not None else defaults)
    if observer is not None:
        from socnav.safety import fallback_percent

        records["fallback_steps"] = observer.per_episode(records["episode"])
        summary["fallback_pct"] = fallback_percent(records)
    return records, summary


def _all_metrics_table(summary: dict[str, Any], chosen: list[str], title: str) -> Table:
    """`evaluate --metrics` other than default: one row per chosen metric, with its unit and which way is better."""
    from socnav.sim.metrics import metric_table_rows

    table = Table(title=title, caption=f"{summary['episodes']} episodes; definitions, units and sources: "
                                       "docs/metrics.md")
    for column in ("metric", "", "value", "unit", "better"):
        table.add_column(column, justify="right" if column == "value" else "left", no_wrap=True)
    for row in metric_table_rows(summary, chosen):
        table.add_row(*row)
    if "fallback_pct" in summary:
        table.add_row("fallback_pct", "fallback % steps", f"{summary['fallback_pct']:.1f}", "%", "–")
    return table


def _safe_policy_option(safety: str, sensing: str | None, estimator: str | None, model: str | None,
                        members: str | None, k: int, env_config: EnvConfig) -> SafePolicy:
    """`evaluate --safety`: the model (or, without one, the ensemble's first member) in the safety layer with the
    --safety thresholds, reading --estimator's uncertainty (by default the one the thresholds were made for)."""
    from socnav.safety.assembly import assemble_safe_policy, default_estimator_kind

    thresholds = load_thresholds_option(safety, sensing)
    kind = estimator or default_estimator_kind(safety)
    policy, ensemble = estimator_policies(kind, model, members, env_config)
    if kind == "mc":
        check_mc_dropout(str(model), policy, required=True)
    return assemble_safe_policy(policy, thresholds, env_config, estimator=kind, members=ensemble, k=k)


#: The default files of `animate` and `calibrate`: their directories are the commands' own, created when missing
#: (a --out directory that does not exist is refused: a typo).
ANIMATION_OUT = Path("runs") / "animate" / "episode.gif"


def animate(
    model: str | None = model_option(ACTING_MODEL_HELP),
    estimator: str = estimator_option("mc"),
    members: str | None = members_option(),
    k: int = mc_samples_option(),
    scenario: str | None = scenario_option(None, help=SINGLE_AGENT_SCENARIO_HELP),
    n_humans: int | None = n_humans_option(SINGLE_AGENT_N_HUMANS_HELP),
    max_humans: int | None = max_humans_option(SINGLE_AGENT_MAX_HUMANS_HELP),
    config: Path | None = config_option(),
    perturb: list[str] = perturb_option(),
    safety: str | None = safety_option("thresholds (mc | ensemble | FILE): wrap the policy in SafePolicy"),
    sensing: str | None = sensing_option(),
    seed: int = seed_option("episode seed"),
    out: Path = typer.Option(ANIMATION_OUT, help="output .gif or .mp4"),
    humans: str | None = humans_option(),
    force: bool = force_option("the --out animation"),
) -> None:
    """Animate one episode with the windowed uncertainties drawn live (and the safety fallback coloured)."""
    from socnav.cli.workflows.animation import animate_episode
    from socnav.viz import check_animation_path

    if out.suffix not in (".gif", ".mp4"):
        fail(f"--out must end in .gif or .mp4, got {out.name!r}")
    try:
        check_animation_path(out)  # before the episode is played: .mp4 without the [video] extra
    except ImportError as exc:
        fail(f"--out {out}: {exc}")
    check_out_file("--out", out, force=force, create_parent=out == ANIMATION_OUT)
    # Every option is checked before a model loads.
    check_estimator_options(estimator, model, members)
    if safety is not None:
        load_thresholds_option(safety, sensing)
    check_perturbations(perturb)
    check_human_model(humans)
    env_config = perturbed_config(model_world(
        model, scenario, config, n_humans, max_humans,
        default=lambda: single_agent_env_config(scenario, config, n_humans, max_humans, humans),
        humans=humans), perturb)
    # Without a safety layer the bars are only drawn when there is an uncertainty to draw: a model without dropout
    # has no MC-dropout samples (all zero bars would say "certain").
    policy, uncertainty = policy_and_estimator(estimator, model, members, k, env_config, required=safety is not None)
    thresholds = None if safety is None else load_thresholds_option(safety, sensing)
    label = model_label(model) if model is not None else f"ensemble of {members}"
    path, summary = animate_episode(policy, uncertainty, env_config, out, seed=seed, thresholds=thresholds,
                                    policy_label=label, safety_label=safety)
    fallback = "" if safety is None else f", safety fallback on {summary['fallback_steps']} steps"
    console.print(f"{summary.get('outcome', 'running')} after {summary.get('length', '?')} steps{fallback}: "
                  f"{escape(str(path))}", highlight=False)

