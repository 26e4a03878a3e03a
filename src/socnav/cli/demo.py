"""`socnav demo`: the tour of socnav in one command (its steps: `socnav.cli.workflows.demo`).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer
from rich.markup import escape

from socnav._console import console, fail
from socnav.cli.options import (
    episodes_option,
    seed_option,
)
from socnav.config import describe_world

if TYPE_CHECKING:  # pandas, torch and SB3 load inside the commands: `socnav --help` stays fast

    pass

from socnav.cli.common import (
    check_out_writable,
    load_learned_policy,
    metrics_table,
    progress_bar,
    progress_display,
)


def demo(
    out: Path = typer.Option(Path("runs") / "demo", help="output directory"),
    episodes: int = episodes_option(100, help="episodes per scenario and controller"),
    seed: int = seed_option("first episode seed"),
    train_steps: int = typer.Option(0, min=0, help="train a fresh ODV-PPO-Drop policy for this many steps "
                                                    "(0: use the pretrained one shipped with socnav)"),
) -> None:
    """Baselines in every scenario, an ODV-PPO-Drop policy, then that policy under heading noise with and without
    the safety layer: metrics and animations (GIF)."""
    from socnav.cli.workflows import demo as steps

    if out.exists() and not out.is_dir():
        fail(f"--out {out} is an existing file; name a directory for the demo's tables and animations")
    check_out_writable("--out", out)
    rows = steps.baseline_rows(out, episodes, seed, progress=progress_bar)
    console.print(metrics_table(rows, f"Baseline controllers, {episodes} episodes each (seeds {seed}..)"))
    gif, summary = steps.animate_baseline(out, seed)
    console.print(f"animation of one ORCA episode ({summary.get('outcome')}): {escape(str(gif))}", highlight=False)
    gif, summary = steps.animate_map_baseline(out, seed)
    console.print(f"animation of one ORCA episode among walls, its planned path and subgoal drawn "
                  f"({summary.get('outcome')}): {escape(str(gif))}", highlight=False)

    world, rows = steps.map_policy_rows(out, episodes, seed, progress=progress_bar)
    console.print(metrics_table(rows, f"{describe_world(world)}, the shipped map policy alone and inside its safety "
                                      f"layer, {episodes} episodes (seeds {seed}..)"))
    gif, summary = steps.animate_map_policy(world, out, seed)
    console.print(f"animation of one {steps.MAP_POLICY} episode inside its safety layer, its planned path and "
                  f"subgoal drawn ({summary.get('outcome')}, fallback on {summary.get('fallback_steps')} steps): "
                  f"{escape(str(gif))}", highlight=False)

    if train_steps:
        from socnav.rl.training import TrainingInterrupted

        console.print(f"training ODV-PPO-Drop on position swap with one human for {train_steps:,} steps")
        try:
            trained = steps.train_policy(out, seed, train_steps)
        except TrainingInterrupted as exc:
            fail(str(exc), code=1)
        model_path, label = str(trained.model_path), "odv-ppo-drop (trained now)"
    else:
        model_path, label = "pretrained", "odv-ppo-drop (pretrained)"
    policy = load_learned_policy(model_path)
    world, row = steps.learned_policy_row(policy, label, out, episodes, seed, progress=progress_bar)
    console.print(metrics_table([row], f"{describe_world(world)}, {episodes} episodes"))
    gif, summary = steps.animate_learned_policy(policy, world, out, seed, label)
    console.print(f"animation of one learned-policy episode ({summary.get('outcome')}): {escape(str(gif))}",
                  highlight=False)

    # The point of the project: under a perturbation, the safety layer hands over to a cautious controller when
    # the policy is uncertain and a human is close.
    console.print(f"[bold]safety layer[/]: {label} under {steps.PERTURBATION}, the same episodes without and with "
                  "the layer (MC-dropout, the paper's thresholds), and with " + " and ".join(steps.COMPARISONS)
                  + " (calibrated for the shipped policy at the 5 % budget)")
    with progress_display() as progress:
        def tick(what: str, total: int) -> Any:
            task = progress.add_task(f"{what} / {world.scenario}", total=total)
            return lambda n: progress.advance(task, n)

        result = steps.safety_demo(policy, world, episodes, seed, progress=tick)
    steps.write_safety_records(result, out)
    console.print(metrics_table(steps.summary_rows(result, label), f"{describe_world(result.config)}, "
                                                                   f"{episodes} episodes"))
    for line in steps.describe(result):
        console.print(line, highlight=False)
    saved_seed = steps.find_saved_episode(policy, result.config, result.saved) if result.saved else None
    if saved_seed is not None:
        without, with_layer = steps.animate_saved_episode(policy, result.config, saved_seed, out, label)
        console.print(f"an episode the safety layer saves (seed {saved_seed}): without it {escape(str(without))}, "
                      f"with it {escape(str(with_layer))}", highlight=False)
    elif result.saved:
        console.print("no animation: the saved episodes are not saved when replayed alone (the MC-dropout masks "
                      "differ for a batch of one)", highlight=False)

