"""Animations of one episode that explain themselves: what `socnav animate` and `socnav demo` write.

Every frame carries a title (scenario, policy, seed, perturbation, safety), a legend (robot, humans who see or
ignore the robot, personal space, goal, trail), a metre scale and a caption in words (who drives, how close the
nearest human is); the last frame shows the outcome in large type. With an uncertainty estimator, bars beside the
scene show the windowed epistemic / aleatoric / feature uncertainty with tick values and, with a safety layer,
its thresholds marked; the robot is recoloured while the cautious controller drives.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from socnav.config import ConfigLike, EnvConfig, describe_world, load_config, perturbation_text
from socnav.envs.env import SocialNavEnv, scene_extent
from socnav.uncertainty import WindowedUncertainty
from socnav.viz import save_animation
from socnav.viz.render import SceneRenderer

__all__ = ["BARS", "FALLBACK_COLOR", "OUTCOME_WORDS", "animate_episode", "episode_title"]

FALLBACK_COLOR = "#f4a261"  # the robot while the cautious ORCA controller drives
#: bar label -> (uncertainty key, scale, threshold field): a bar shows u / (u + scale), so it is half full at the
#: scale; the scales are the paper's MC-dropout thresholds (lambda_ep, lambda_f) and sigma^2 = 0.3 for the
#: aleatoric part. The threshold field names the `Thresholds` value marked on the bar (None: the rule ignores it).
BARS = {
    "epistemic heading": ("u_ep_heading", 0.03, "lambda_ep"),
    "epistemic speed": ("u_ep_speed", 0.03, None),
    "aleatoric heading": ("u_al_heading", 0.3, None),
    "aleatoric speed": ("u_al_speed", 0.3, None),
    "feature": ("u_feat", 0.3, "lambda_feat"),
}
OUTCOME_WORDS = {"goal": "GOAL REACHED", "collision": "COLLISION", "timeout": "TIME-OUT"}
HOLD_LAST_FRAME_S = 2.0  # the outcome frame stays this long, so a viewer can read it


def _bar_position(value: float, scale: float) -> float:
    return value / (value + scale)


def _ticks() -> dict[str, tuple[tuple[float, str], ...]]:
    """Tick labels in uncertainty units under each bar (the bar is non-linear: u / (u + scale))."""
    return {label: tuple((_bar_position(u, scale), f"{u:.2g}") for u in (scale / 3, scale, 3 * scale))
            for label, (_, scale, _) in BARS.items()}


def _marks(thresholds: Any) -> dict[str, float]:
    """Where the paper's rule's thresholds sit on the uncertainty bars (a trigger has none there)."""
    from socnav.safety import Thresholds

    if not isinstance(thresholds, Thresholds):
        return {}
    values = thresholds.model_dump()
    return {label: _bar_position(values[field], scale) for label, (_, scale, field) in BARS.items()
            if field is not None and math.isfinite(values[field])}


def episode_title(config: EnvConfig, policy_label: str, seed: int, safety: str | None = None) -> str:
    """What a frame shows, in two lines: 'position_swap, 1 human | pretrained | seed 0' and
    'heading_noise=0.8 | safety layer: mc'."""
    first = [describe_world(config, with_perturbation=False), policy_label, f"seed {seed}"]
    second = [perturbation_text(config) or "no perturbation",
              f"safety layer: {safety}" if safety else "no safety layer"]
    return " | ".join(first) + "\n" + " | ".join(second)


def _caption(step: int, dt: float, gap: float | None, fallback: bool, safety: bool) -> str:
    words = [f"step {step} ({step * dt:.2f} s)"]
    if gap is not None and math.isfinite(gap):
        words.append(f"nearest human {gap:.1f} m away" if gap >= 0 else "touching a human")
    if safety:
        words.append("SAFETY FALLBACK DRIVES (uncertain and close)" if fallback else "policy drives")
    return "; ".join(words)


def _nearest_gap(env: SocialNavEnv) -> float | None:
    """True gap (m, body to body) between the robot and its nearest human; None without humans. From the world,
    not the observation, which may be perturbed."""
    world = env.world
    humans = np.flatnonzero(world.active[0, 1:]) + 1
    if not len(humans):
        return None
    distance = np.linalg.norm(world.positions[0, humans] - world.positions[0, 0], axis=1)
    return float((distance - world.radii[0, humans] - world.radii[0, 0]).min())


def animate_episode(
    policy: Any,
    estimator: Any,
    config: ConfigLike,
    out: str | Path,
    seed: int = 0,
    thresholds: Any = None,
    window: int = 4,
    max_steps: int = 1000,
    policy_label: str = "policy",
    safety_label: str | None = None,
) -> tuple[Path, dict[str, Any]]:
    """Play episode `seed` with `policy` and write a self-explaining GIF/MP4; returns (path, summary).

    `estimator` (None: no uncertainty bars) draws the windowed uncertainty live. With `thresholds` (a
    `socnav.safety.Thresholds`, a trigger's `TriggerSpec`, a preset name or a file) the policy is wrapped in
    `SafePolicy`, the rule's thresholds are marked on the bars and the robot is drawn in `FALLBACK_COLOR` on the
    steps where the cautious controller acts; a trigger that reads no uncertainty leaves the bars to `estimator`.
    `policy_label` and `safety_label` (default: "calibrated" for thresholds) name them in the title. The summary
    holds the episode metrics plus ``fallback_steps`` (None without a safety layer).
    """
    config = load_config(config)
    env = SocialNavEnv(config)
    extent = scene_extent(config)
    safe = None
    if thresholds is not None:
        from socnav.safety import SafePolicy
        from socnav.safety.triggers import load_safety

        thresholds = load_safety(thresholds)  # the paper's rule's thresholds, or a trigger (time to collision, ...)
        safe = SafePolicy(policy, estimator if thresholds.uses_uncertainty else None, thresholds, config,
                          window=window, n_envs=1)
        safety_label = safety_label or "on"
    renderer = SceneRenderer(width=720, height=480, extent=extent, annotate=True,
                             fallback_color=FALLBACK_COLOR if safe is not None else None)
    title = episode_title(config, policy_label, seed, safety_label if safe is not None else None)
    panel: dict[str, Any] = {}
    if estimator is not None:
        panel = {"panel_ticks": _ticks(), "panel_marks": _marks(thresholds),
                 "panel_title": f"uncertainty, mean of the last {window} steps"}
    windowed = WindowedUncertainty(1, window)
    observation, _ = env.reset(seed=seed)
    frames: list[np.ndarray] = []
    summary: dict[str, Any] = {}
    fallback_steps = 0
    bars: dict[str, float] | None = None
    for step in range(max_steps):
        batch = {key: value[None] for key, value in observation.items()}
        fallback = False
        if safe is not None:
            # with sensing 'true' the safety layer reads the world's noise-free state; the policy gets `batch`
            truth = env.world.observe(noisy=False) if safe.needs_true_observation else None
            actions, _ = safe.predict(batch, deterministic=True, true_observation=truth)
            values = {} if safe.estimator is None else {key: float(value[0])  # zeros there without one
                                                         for key, value in safe.last_uncertainty.items()}
            fallback = bool(safe.last_fallback[0])
        else:
            actions, _ = policy.predict(batch, deterministic=True)
            values = {}
        if not values and estimator is not None:  # no layer, or a trigger that reads no uncertainty
            smooth = windowed.update(estimator(batch)).as_dict()
            values = {key: float(np.asarray(smooth[key])[0]) for key, _, _ in BARS.values()}
        if values:
            bars = {label: _bar_position(values[key], scale) for label, (key, scale, _) in BARS.items()}
        fallback_steps += fallback
        caption = _caption(step, config.time_step, _nearest_gap(env), fallback, safe is not None)
        frame = env.scene_frame(caption=caption, robot_color=FALLBACK_COLOR if fallback else None,
                                side_panel=bars, title=title, **panel)
        frames.append(renderer.render(frame))
        observation, _, terminated, truncated, info = env.step(np.asarray(actions)[0])
        if terminated or truncated:
            summary = dict(info["episode"])
            outcome = OUTCOME_WORDS.get(summary["outcome"], str(summary["outcome"]).upper())
            last = renderer.render(env.scene_frame(
                caption=f"{outcome.lower()} after {summary['length']} steps ({summary['duration']:.1f} s)"
                + (f"; safety fallback drove {fallback_steps} steps" if safe is not None else ""),
                side_panel=bars, title=title, outcome=outcome, **panel))
            frames += [last] * max(1, round(HOLD_LAST_FRAME_S / config.time_step))
            break
    renderer.close()
    env.close()
    summary["fallback_steps"] = fallback_steps if safe is not None else None
    path = save_animation(frames, out, fps=round(1 / config.time_step))
    return path, summary
