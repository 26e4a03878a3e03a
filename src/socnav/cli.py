"""The `socnav` command line: train, evaluate, animate, calibrate, run experiments, report, tune, demo.

Every command validates its options up front and reports bad input as one clear line, never a traceback.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Optional

import pandas as pd
import typer
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from socnav.config import ConfigError, EnvConfig, load_config
from socnav.sim.scenarios import scenario_names

app = typer.Typer(add_completion=False, no_args_is_help=True, help=__doc__.splitlines()[0])
console = Console()


def _fail(message: str) -> None:
    console.print(f"[bold red]error:[/] {message}")
    raise typer.Exit(code=2)


def _env_config(scenario: Optional[str], config_file: Optional[Path], n_humans: Optional[int]) -> EnvConfig:
    overrides: dict[str, Any] = {}
    if scenario is not None:
        overrides["scenario"] = scenario
    if n_humans is not None:
        overrides["n_humans"] = n_humans
    try:
        return load_config(config_file, **overrides)
    except ConfigError as exc:
        _fail(str(exc))
        raise  # unreachable, keeps type checkers happy


def _progress() -> Progress:
    return Progress(
        TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), console=console
    )


def metrics_table(rows: list[tuple[str, dict[str, float]]], title: str) -> Table:
    """The paper's metrics as a rich table: Goal %, Collision %, Time-out %, PV (per 200 episodes), Return mean ± std."""
    table = Table(title=title)
    for column in ("run", "episodes", "Goal %", "Col. %", "TO %", "PV", "Return"):
        table.add_column(column, justify="right" if column != "run" else "left")
    for name, m in rows:
        table.add_row(
            name, str(m["episodes"]), f"{m['goal_pct']:.1f}", f"{m['collision_pct']:.1f}", f"{m['timeout_pct']:.1f}",
            f"{m['pv']:.0f}", f"{m['return_mean']:.2f} ± {m['return_std']:.2f}",
        )
    return table


def _evaluate(policy: Any, config: EnvConfig, episodes: int, seed: int, n_envs: int, label: str,
              deterministic: bool = True) -> pd.DataFrame:
    from socnav.envs.rollout import rollout_episodes

    with _progress() as progress:
        task = progress.add_task(label, total=episodes)
        return rollout_episodes(
            policy, config, episodes, seed=seed, n_envs=n_envs, deterministic=deterministic,
            progress=lambda n: progress.advance(task, n),
        )


def _algo_overrides(algo: str, algo_config: Optional[Path], settings: list[str]) -> dict[str, Any]:
    """Hyperparameter overrides from a YAML file, then `--set key=value` pairs (values parsed as YAML)."""
    import yaml

    from socnav.rl.presets import ALGOS, resolve_config

    if algo not in ALGOS:
        _fail(f"--algo {algo!r} is not known; allowed: {', '.join(ALGOS)}")
    overrides: dict[str, Any] = {}
    if algo_config is not None:
        if not algo_config.is_file():
            _fail(f"--algo-config: no such file {algo_config}")
        loaded = yaml.safe_load(algo_config.read_text()) or {}
        if not isinstance(loaded, dict):
            _fail(f"--algo-config {algo_config} must hold a mapping of hyperparameters")
        overrides.update(loaded)
    for setting in settings:
        key, sep, value = setting.partition("=")
        if not sep or not key:
            _fail(f"--set expects key=value, got {setting!r}")
        overrides[key.strip()] = yaml.safe_load(value)
    try:
        resolve_config(algo, overrides)
    except ValueError as exc:
        _fail(" ".join(str(exc).split()))
    return overrides


@app.command()
def train(
    scenario: Optional[str] = typer.Option(None, help=f"training scenario, one of: {', '.join(scenario_names())}"),
    algo: str = typer.Option("odv-ppo-drop", help="ppo | ppo-drop | odv-ppo-noloss | odv-ppo | odv-ppo-drop"),
    seed: int = typer.Option(0, min=0, max=2**28 - 1,
                             help="seed of the run (network init, dropout, training episodes)"),
    timesteps: int = typer.Option(200_000, min=1, help="total environment steps"),
    n_envs: int = typer.Option(16, min=1, help="environments stepped together"),
    n_humans: Optional[int] = typer.Option(None, min=0, help="humans per episode (default: the scenario's)"),
    config: Optional[Path] = typer.Option(None, "--config", help="YAML env config; options above override it"),
    algo_config: Optional[Path] = typer.Option(None, help="YAML of hyperparameter overrides for the preset"),
    settings: list[str] = typer.Option([], "--set", help="hyperparameter override key=value (repeatable)"),
    eval_every: Optional[int] = typer.Option(None, min=1, help="timesteps between evaluations/checkpoints"),
    eval_episodes: int = typer.Option(50, min=1, help="validation episodes per evaluation"),
    out: Optional[Path] = typer.Option(None, help="run directory (default runs/train/<scenario>_<algo>_seed<k>)"),
    resume: Optional[Path] = typer.Option(None, help="continue the run in this directory from its last checkpoint"),
) -> None:
    """Train a policy: progress with live success rate, TensorBoard in OUT/tb, checkpoints, final OUT/model.zip."""
    import json

    from socnav.rl.training import CheckpointError, TrainingInterrupted
    from socnav.rl.training import train as train_run

    if resume is not None:
        run_file = resume / "run.json"
        if not run_file.is_file():
            _fail(f"--resume {resume}: no run.json there (not a socnav training run directory)")
        try:
            asked = json.loads(run_file.read_text())
            env_config = load_config(asked["env_config"])
            algo, seed, timesteps = asked["algo"], asked["seed"], asked["timesteps"]
            n_envs, overrides, out = asked["n_envs"], asked["overrides"], resume
            eval_every, eval_episodes = asked["eval_every"], asked["eval_episodes"]
        except (ValueError, KeyError, TypeError, ConfigError) as exc:
            _fail(f"--resume {resume}: run.json is unreadable ({type(exc).__name__}: {exc})")
    else:
        env_config = _env_config(scenario, config, n_humans)
        overrides = _algo_overrides(algo, algo_config, settings)
        out = out or Path("runs") / "train" / f"{env_config.scenario}_{algo}_seed{seed}"
    console.print(f"training {algo} on {env_config.scenario} (seed {seed}, {timesteps:,} steps) -> {out}")
    try:
        result = train_run(env_config, algo, seed, timesteps, out, n_envs=n_envs, overrides=overrides,
                           eval_every=eval_every, eval_episodes=eval_episodes, resume=resume is not None,
                           progress=True)
    except TrainingInterrupted as exc:
        console.print(f"[bold red]error:[/] {exc}")
        raise typer.Exit(code=1)
    except CheckpointError as exc:
        _fail(f"--resume {out}: {exc}")
    console.print(metrics_table([(f"{algo} (validation)", result.final_eval)],
                                f"{result.timesteps:,} steps in {result.wall_time_s:.0f} s"))
    console.print(f"model: {result.model_path}   TensorBoard: tensorboard --logdir {out / 'tb'}")


def _single_agent_env_config(scenario: Optional[str], config_file: Optional[Path], n_humans: Optional[int]) -> EnvConfig:
    """`_env_config` for animate / calibrate: without --config, position swap with one human unless given."""
    if config_file is None:
        scenario = "position_swap" if scenario is None else scenario
        n_humans = 1 if n_humans is None else n_humans
    return _env_config(scenario, config_file, n_humans)


def _check_observation_size(policies: list[Any], env_config: EnvConfig) -> None:
    """A clear error (not a reshape traceback) when a policy observes a different max_humans than the env."""
    for policy in policies:
        observed = policy.observation_space["humans"].shape[0]
        if observed != env_config.max_humans:
            _fail(f"the model observes max_humans={observed} but the env config has "
                  f"max_humans={env_config.max_humans}; set max_humans in --config to match")


def _load_learned_policy(model: str) -> Any:
    import torch

    from socnav.rl.persistence import PolicyLoadError, load_policy

    # Batched inference on small matrices: one thread is faster than torch's intra-op pool, which also collapses
    # when the cores are shared.
    torch.set_num_threads(1)
    try:
        return load_policy(model)
    except PolicyLoadError as exc:
        _fail(str(exc))


@app.command()
def evaluate(
    policy: str = typer.Option("orca", help="baseline controller: orca | straight (ignored with --model)"),
    model: Optional[str] = typer.Option(None, help="trained policy file, or 'pretrained' for the shipped one"),
    stochastic: bool = typer.Option(False, help="sample actions instead of the mean action"),
    scenario: Optional[str] = typer.Option(None, help=f"one of: {', '.join(scenario_names())}"),
    episodes: int = typer.Option(200, min=1, help="number of evaluation episodes"),
    seed: int = typer.Option(0, min=0, help="episode k uses seed + k"),
    n_humans: Optional[int] = typer.Option(None, min=0, help="humans per episode (default: the scenario's)"),
    config: Optional[Path] = typer.Option(None, "--config", help="YAML env config; options above override it"),
    n_envs: int = typer.Option(32, min=1, help="environments stepped together"),
    out: Optional[Path] = typer.Option(None, help="per-episode records (.csv or .parquet)"),
) -> None:
    """Evaluate a controller: Goal %, Collision %, Time-out %, PV, Return; per-episode records to a file."""
    from socnav.envs.controllers import CONTROLLERS, make_controller
    from socnav.envs.rollout import summarize
    from socnav.io import TABLE_FORMATS, write_table_atomic

    if model is None and policy not in CONTROLLERS:
        _fail(f"--policy {policy!r} is not known; allowed: {', '.join(CONTROLLERS)}")
    env_config = _env_config(scenario, config, n_humans)
    if model is not None:
        actor = _load_learned_policy(model)
        name = "pretrained" if model == "pretrained" else Path(model).stem
        _check_observation_size([actor], env_config)
    else:
        actor, name = make_controller(policy, env_config), policy
    out = out or Path("runs") / "evaluate" / f"{name}_{env_config.scenario}_seed{seed}.csv"
    if out.suffix not in TABLE_FORMATS:
        _fail(f"--out must end in one of {', '.join(TABLE_FORMATS)}, got {out.name!r}")
    if stochastic:
        import torch

        # Sampled actions come from torch's generator: seeded, a run repeats; they still depend on --n-envs (the
        # order in which the batch draws them), unlike the deterministic mean action.
        torch.manual_seed(seed)
    records = _evaluate(actor, env_config, episodes, seed, n_envs, f"{name} / {env_config.scenario}",
                        deterministic=not stochastic)
    write_table_atomic(records, out)
    world = env_config.scenario + ("" if env_config.robot_visible else " (humans ignore the robot)")
    console.print(metrics_table([(name, summarize(records))], f"{world}, seeds {seed}..{seed + episodes - 1}"))
    console.print(f"per-episode records: {out}")


def _estimator(kind: str, model: Optional[str], members: Optional[str], k: int,
               env_config: EnvConfig) -> tuple[Any, Any]:
    """(policy that acts, uncertainty estimator) for `--estimator mc|ensemble`."""
    import glob

    from socnav.uncertainty import ESTIMATOR_KINDS, make_estimator

    if kind not in ESTIMATOR_KINDS:
        _fail(f"--estimator {kind!r} is not known; allowed: {', '.join(ESTIMATOR_KINDS)}")
    if kind == "mc":
        if model is None:
            _fail("--estimator mc needs --model PATH (or --model pretrained)")
        from socnav.experiments.uncertainty_units import MC_SEED
        from socnav.uncertainty import MCDropoutEstimator

        policy = _load_learned_policy(model)
        _check_observation_size([policy], env_config)
        # A private, seeded mask stream (as the experiment units use): the same command gives the same thresholds
        # and the same animation, instead of drawing from torch's unseeded global RNG.
        return policy, MCDropoutEstimator(policy, k=k, seed=MC_SEED)
    if members is None:
        _fail("--estimator ensemble needs --members GLOB, e.g. 'runs/ensemble-quick/units/*/model.zip'")
    paths = sorted(glob.glob(members))
    if len(paths) < 2:
        _fail(f"--members {members!r} matches {len(paths)} policy file(s); an ensemble needs at least 2")
    policies = [_load_learned_policy(path) for path in paths]
    policy = _load_learned_policy(model) if model is not None else policies[0]
    _check_observation_size([policy, *policies], env_config)
    return policy, make_estimator("ensemble", policies)


def _perturbation_overrides(settings: list[str]) -> dict[str, Any]:
    import yaml

    perturbation: dict[str, Any] = {}
    for setting in settings:
        key, sep, value = setting.partition("=")
        if not sep or not key:
            _fail(f"--perturb expects key=value (e.g. observation_noise=0.6), got {setting!r}")
        perturbation[key.strip()] = yaml.safe_load(value)
    return perturbation


@app.command()
def animate(
    model: Optional[str] = typer.Option(None, help="policy file or 'pretrained' (acts; MC-dropout estimates on it)"),
    estimator: str = typer.Option("mc", help="mc | ensemble"),
    members: Optional[str] = typer.Option(None, help="ensemble policy files (glob), for --estimator ensemble"),
    k: int = typer.Option(20, min=2, help="MC-dropout samples"),
    scenario: Optional[str] = typer.Option(None, help=f"one of: {', '.join(scenario_names())} "
                                                     "(default: position_swap, or the --config file's)"),
    n_humans: Optional[int] = typer.Option(None, min=0, help="humans per episode (default: 1, or the --config file's)"),
    config: Optional[Path] = typer.Option(None, "--config", help="YAML env config; options above override it"),
    perturb: list[str] = typer.Option([], "--perturb", help="perturbation key=value (repeatable), e.g. heading_noise=0.8"),
    safety: Optional[str] = typer.Option(None, help="thresholds (mc | ensemble | FILE): wrap the policy in SafePolicy"),
    seed: int = typer.Option(0, min=0, help="episode seed"),
    out: Path = typer.Option(Path("runs") / "animate" / "episode.gif", help="output .gif or .mp4"),
) -> None:
    """Animate one episode with the windowed uncertainties drawn live (and the safety fallback coloured)."""
    from socnav.experiments.animate import animate_episode

    if out.suffix not in (".gif", ".mp4"):
        _fail(f"--out must end in .gif or .mp4, got {out.name!r}")
    env_config = _single_agent_env_config(scenario, config, n_humans)
    perturbation = _perturbation_overrides(perturb)
    try:
        env_config = load_config(env_config, perturbation={**env_config.perturbation.model_dump(), **perturbation})
    except ConfigError as exc:
        _fail(str(exc))
    policy, uncertainty = _estimator(estimator, model, members, k, env_config)
    thresholds = None
    if safety is not None:
        from socnav.safety import ThresholdsError, load_thresholds

        try:
            thresholds = load_thresholds(safety)
        except (ThresholdsError, OSError) as exc:
            _fail(f"--safety: {exc}")
    path, summary = animate_episode(policy, uncertainty, env_config, out, seed=seed, thresholds=thresholds)
    console.print(f"{summary.get('outcome', 'running')} after {summary.get('length', '?')} steps, "
                  f"fallback on {summary['fallback_steps']} steps: {path}")


@app.command()
def calibrate(
    model: Optional[str] = typer.Option(None, help="policy file or 'pretrained' (acts; MC-dropout estimates on it)"),
    estimator: str = typer.Option("mc", help="mc | ensemble"),
    members: Optional[str] = typer.Option(None, help="ensemble policy files (glob), for --estimator ensemble"),
    k: int = typer.Option(20, min=2, help="MC-dropout samples"),
    scenario: Optional[str] = typer.Option(None, help=f"one of: {', '.join(scenario_names())} "
                                                     "(default: position_swap, or the --config file's)"),
    n_humans: Optional[int] = typer.Option(None, min=0, help="humans per episode (default: 1, or the --config file's)"),
    config: Optional[Path] = typer.Option(None, "--config", help="YAML env config; options above override it"),
    episodes: int = typer.Option(40, min=1, help="episodes per calibration configuration"),
    budget: float = typer.Option(0.05, min=0.0, max=1.0, help="allowed false-activation rate (unperturbed steps)"),
    proximity: str = typer.Option("both", help="c_prox readings to search: both | abs-relative-speed | closing-speed"),
    confidence: float = typer.Option(0.95, min=0.5, max=0.999, help="the budget must hold at this one-sided "
                                                                     "confidence (0.5: the point estimate)"),
    out: Path = typer.Option(Path("runs") / "calibration" / "thresholds.yaml", help="threshold file (.yaml/.json)"),
) -> None:
    """Choose the safety thresholds on calibration episodes (perturbations and seeds disjoint from evaluation)."""
    import json
    import math

    from socnav.experiments.uncertainty_units import calibrate_thresholds
    from socnav.io import write_text_atomic
    from socnav.safety import PROXIMITY_VARIANTS, save_thresholds

    if proximity != "both" and proximity not in PROXIMITY_VARIANTS:
        _fail(f"--proximity {proximity!r} is not known; allowed: both, {', '.join(PROXIMITY_VARIANTS)}")
    if out.is_dir() or out.suffix not in (".yaml", ".yml", ".json"):
        _fail(f"--out must be a .yaml or .json file path, got {str(out)!r}")
    env_config = _single_agent_env_config(scenario, config, n_humans)
    policy, uncertainty = _estimator(estimator, model, members, k, env_config)
    with console.status("collecting calibration episodes, searching thresholds, replaying the candidates"):
        thresholds, report = calibrate_thresholds(policy, uncertainty, env_config.model_dump(mode="json"), episodes,
                                                  budget, proximity, confidence=confidence)
    save_thresholds(thresholds, out)
    write_text_atomic(out.with_suffix(".report.json"), json.dumps(report, indent=2, default=str))
    table = Table(title=f"calibrated thresholds ({estimator}, false-activation budget {budget:.0%})")
    for column in ("λ_ep", "λ_f", "λ_prox", "β1", "c_prox", "prevented", "collisions", "false act."):
        table.add_column(column, justify="right", overflow="fold")
    values = thresholds.model_dump()
    table.add_row(*(f"{values[key]:.4g}" for key in ("lambda_ep", "lambda_feat", "lambda_prox", "beta1")),
                  values["proximity"],
                  "–" if math.isnan(report["prevented_fraction"]) else f"{report['prevented_fraction']:.0%}",
                  str(report["n_collisions"]),
                  f"{report['false_activation_rate']:.1%}"
                  + (f" (≤ {report['false_activation_upper']:.1%})" if "false_activation_upper" in report else ""))
    console.print(table)
    console.print("prevented: share of the plain policy's calibration collisions prevented in the replayed episodes "
                  "(mean over perturbation types); false act.: share of unperturbed steps where the fallback acted "
                  f"(≤ its {confidence:.0%} upper bound); every candidate in {out.with_suffix('.report.json')}")
    if "note" in report:
        console.print(report["note"])
    console.print(f"thresholds: {out}  (use with --safety {out})")


@app.command()
def demo(
    out: Path = typer.Option(Path("runs") / "demo", help="output directory"),
    episodes: int = typer.Option(100, min=1, help="episodes per scenario and controller"),
    seed: int = typer.Option(0, min=0, help="first episode seed"),
    train_steps: int = typer.Option(0, min=0, help="train a fresh ODV-PPO-Drop policy for this many steps "
                                                    "(0: use the pretrained one shipped with socnav)"),
) -> None:
    """Baselines in every scenario, then an ODV-PPO-Drop policy on position swap: metrics and animations (GIF)."""
    from socnav.envs.controllers import make_controller
    from socnav.envs.rollout import record_episode, summarize
    from socnav.io import write_table_atomic
    from socnav.viz import save_animation

    rows = []
    for scenario in scenario_names():
        env_config = load_config({"scenario": scenario})
        for name in ("orca", "straight"):
            records = _evaluate(make_controller(name, env_config), env_config, episodes, seed, 32, f"{name} / {scenario}")
            write_table_atomic(records, out / f"{name}_{scenario}.csv")
            rows.append((f"{name} / {scenario}", summarize(records)))
    console.print(metrics_table(rows, f"Baseline controllers, {episodes} episodes each (seeds {seed}..)"))
    env_config = load_config({"scenario": "circle_crossing"})
    frames, summary = record_episode(make_controller("orca", env_config), env_config, seed=seed)
    gif = save_animation(frames, out / "orca_circle_crossing.gif", fps=round(1 / env_config.time_step))
    console.print(f"animation of one ORCA episode ({summary.get('outcome')}, {len(frames)} frames): {gif}")

    swap = load_config({"scenario": "position_swap", "n_humans": 1})
    if train_steps:
        from socnav.rl.training import TrainingInterrupted
        from socnav.rl.training import train as train_run

        console.print(f"training ODV-PPO-Drop on position swap with one human for {train_steps:,} steps")
        try:
            result = train_run(swap, "odv-ppo-drop", seed, train_steps, out / "odv_ppo_drop", progress=True)
        except TrainingInterrupted as exc:
            console.print(f"[bold red]error:[/] {exc}")
            raise typer.Exit(code=1)
        model_path, label = str(result.model_path), "odv-ppo-drop (trained now)"
    else:
        model_path, label = "pretrained", "odv-ppo-drop (pretrained)"
    policy = _load_learned_policy(model_path)
    records = _evaluate(policy, swap, episodes, seed, 32, f"{label} / position_swap")
    write_table_atomic(records, out / "odv_ppo_drop_position_swap.csv")
    console.print(metrics_table([(label, summarize(records))], f"position swap, one human, {episodes} episodes"))
    frames, summary = record_episode(policy, swap, seed=seed)
    gif = save_animation(frames, out / "odv_ppo_drop_position_swap.gif", fps=round(1 / swap.time_step))
    console.print(f"animation of one learned-policy episode ({summary.get('outcome')}, {len(frames)} frames): {gif}")


from socnav.experiments.cli import register as _register_experiments  # noqa: E402
_register_experiments(app)  # socnav run / report / tune


def main() -> None:
    app()


if __name__ == "__main__":
    main()
