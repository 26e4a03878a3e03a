"""The `socnav` command line: evaluate controllers, run the demo (and, as the project grows, train and report).

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


def _evaluate(policy: Any, config: EnvConfig, episodes: int, seed: int, n_envs: int, label: str) -> pd.DataFrame:
    from socnav.envs.rollout import rollout_episodes

    with _progress() as progress:
        task = progress.add_task(label, total=episodes)
        return rollout_episodes(
            policy, config, episodes, seed=seed, n_envs=n_envs, progress=lambda n: progress.advance(task, n)
        )


@app.command()
def evaluate(
    policy: str = typer.Option("orca", help="baseline controller: orca | straight"),
    scenario: Optional[str] = typer.Option(None, help=f"one of: {', '.join(scenario_names())}"),
    episodes: int = typer.Option(200, min=1, help="number of evaluation episodes"),
    seed: int = typer.Option(0, help="episode k uses seed + k"),
    n_humans: Optional[int] = typer.Option(None, min=0, help="humans per episode (default: the scenario's)"),
    config: Optional[Path] = typer.Option(None, "--config", help="YAML env config; options above override it"),
    n_envs: int = typer.Option(32, min=1, help="environments stepped together"),
    out: Optional[Path] = typer.Option(None, help="per-episode records (.csv or .parquet)"),
) -> None:
    """Evaluate a controller: Goal %, Collision %, Time-out %, PV, Return; per-episode records to a file."""
    from socnav.envs.controllers import CONTROLLERS, make_controller
    from socnav.envs.rollout import summarize
    from socnav.io import TABLE_FORMATS, write_table_atomic

    if policy not in CONTROLLERS:
        _fail(f"--policy {policy!r} is not known; allowed: {', '.join(CONTROLLERS)}")
    env_config = _env_config(scenario, config, n_humans)
    out = out or Path("runs") / "evaluate" / f"{policy}_{env_config.scenario}_seed{seed}.csv"
    if out.suffix not in TABLE_FORMATS:
        _fail(f"--out must end in one of {', '.join(TABLE_FORMATS)}, got {out.name!r}")
    records = _evaluate(make_controller(policy, env_config), env_config, episodes, seed, n_envs, f"{policy} / {env_config.scenario}")
    write_table_atomic(records, out)
    world = env_config.scenario + ("" if env_config.robot_visible else " (humans ignore the robot)")
    console.print(metrics_table([(policy, summarize(records))], f"{world}, seeds {seed}..{seed + episodes - 1}"))
    console.print(f"per-episode records: {out}")


@app.command()
def demo(
    out: Path = typer.Option(Path("runs") / "demo", help="output directory"),
    episodes: int = typer.Option(100, min=1, help="episodes per scenario and controller"),
    seed: int = typer.Option(0, help="first episode seed"),
) -> None:
    """Simulate every scenario with the baseline controllers, print the metrics and write an animation (GIF)."""
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
    console.print(f"animation of one episode ({summary.get('outcome')}, {len(frames)} frames): {gif}")


def main() -> None:
    app()


if __name__ == "__main__":
    main()
