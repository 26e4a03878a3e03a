"""Animations of one episode with the policy's uncertainty drawn live beside the scene (and the safety fallback).
What `socnav animate` writes: bars for windowed epistemic / aleatoric / feature uncertainty, the robot recoloured
while the cautious controller acts.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from socnav.config import ConfigLike, load_config
from socnav.envs.env import SocialNavEnv
from socnav.uncertainty import WindowedUncertainty
from socnav.viz import save_animation
from socnav.viz.render import SceneRenderer

FALLBACK_COLOR = "#f4a261"  # the robot while the cautious ORCA controller drives
#: bar label -> (uncertainty key, scale): a bar shows u / (u + scale), so it is half full at the scale; the scales
#: are the paper's MC-dropout thresholds (lambda_ep, lambda_f) and sigma^2 = 0.3 for the aleatoric part.
BARS = {
    "epistemic heading": ("u_ep_heading", 0.03),
    "epistemic speed": ("u_ep_speed", 0.03),
    "aleatoric heading": ("u_al_heading", 0.3),
    "aleatoric speed": ("u_al_speed", 0.3),
    "feature": ("u_feat", 0.3),
}


def _bars(values: dict[str, float]) -> dict[str, float]:
    return {label: values[key] / (values[key] + scale) for label, (key, scale) in BARS.items()}


def animate_episode(
    policy: Any,
    estimator: Any,
    config: ConfigLike,
    out: str | Path,
    seed: int = 0,
    thresholds: Any = None,
    window: int = 4,
    max_steps: int = 1000,
) -> tuple[Path, dict[str, Any]]:
    """Play episode `seed` with `policy` and write a GIF/MP4 with live uncertainty bars; returns (path, summary).

    With `thresholds` (a `socnav.safety.Thresholds`, preset name or file), the policy is wrapped in `SafePolicy`
    and the robot is drawn in `FALLBACK_COLOR` on the steps where the cautious controller acts. The summary holds
    the episode metrics plus ``fallback_steps``.
    """
    config = load_config(config)
    env = SocialNavEnv(config)
    extent = config.circle_radius + 1.5 if config.scenario != "random" else config.square_size / 2 + 1.5
    renderer = SceneRenderer(width=720, height=480, extent=extent)
    safe = None
    if thresholds is not None:
        from socnav.safety import SafePolicy

        safe = SafePolicy(policy, estimator, thresholds, config, window=window, n_envs=1)
    windowed = WindowedUncertainty(1, window)
    observation, _ = env.reset(seed=seed)
    frames: list[np.ndarray] = []
    summary: dict[str, Any] = {}
    fallback_steps = 0
    for _ in range(max_steps):
        batch = {key: value[None] for key, value in observation.items()}
        if safe is not None:
            actions, _ = safe.predict(batch, deterministic=True)
            values = {key: float(value[0]) for key, value in safe.last_uncertainty.items()}
            fallback = bool(safe.last_fallback[0])
        else:
            actions, _ = policy.predict(batch, deterministic=True)
            smooth = windowed.update(estimator(batch)).as_dict()
            values = {key: float(np.asarray(smooth[key])[0]) for key, _ in BARS.values()}
            fallback = False
        fallback_steps += fallback
        caption = (f"ep h {values['u_ep_heading']:.3f}  al h {values['u_al_heading']:.2f}  "
                   f"feat {values['u_feat']:.2f}" + ("  FALLBACK" if fallback else ""))
        frame = env.scene_frame(caption=caption, robot_color=FALLBACK_COLOR if fallback else None,
                                side_panel=_bars(values))
        frames.append(renderer.render(frame))
        observation, _, terminated, truncated, info = env.step(np.asarray(actions)[0])
        if terminated or truncated:
            summary = dict(info["episode"])
            frames.append(renderer.render(env.scene_frame(caption=summary["outcome"], side_panel=_bars(values))))
            break
    renderer.close()
    env.close()
    summary["fallback_steps"] = fallback_steps
    path = save_animation(frames, out, fps=round(1 / config.time_step))
    return path, summary
