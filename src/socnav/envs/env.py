"""The single social-navigation environment with the Gymnasium API (SPEC section 2).

`SocialNavEnv` is one `CrowdWorld` environment; `make_env` builds it from a config object, a partial dict or a YAML path.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from socnav.config import ConfigLike, EnvConfig, load_config
from socnav.envs.spaces import action_space, observation_space
from socnav.sim.world import OUTCOME_NAMES, CrowdWorld, StepResult


def step_infos(world: CrowdWorld, result: StepResult) -> list[dict[str, Any]]:
    """Per-step `info` of every environment; at the end of an episode it carries the `episode` summary."""
    # .tolist() converts whole columns at once: building these dicts element by element cost more than the physics.
    columns = zip(world.time.tolist(), result.nearest_gap.tolist(), result.nearest_relative_speed.tolist(),
                  result.intrusions.tolist())
    infos = [
        {"time": time, "nearest_gap": gap, "nearest_relative_speed": speed, "intrusions": intrusions}
        for time, gap, speed, intrusions in columns
    ]
    for env in np.flatnonzero(result.outcome):
        outcome = int(result.outcome[env])
        summary = world.episode_summary(env, outcome)
        info = infos[env]
        info["outcome"] = OUTCOME_NAMES[outcome]
        info["is_success"] = outcome == 1
        # "r" and "l" make SB3 log rollout/ep_rew_mean and ep_len_mean as with its Monitor wrapper.
        info["episode"] = {"r": summary["return"], "l": summary["length"], "t": summary["duration"], **summary}
    return infos


def scene_frame(world: CrowdWorld, env: int, trail: list[np.ndarray] | None = None, caption: str = "", **extra: Any):
    """Environment `env` of `world` as a `socnav.viz.SceneFrame`, with the robot's recent `trail` of positions."""
    from socnav.viz.render import SceneFrame

    return SceneFrame(
        positions=world.positions[env].copy(),
        velocities=world.velocities[env].copy(),
        radii=world.radii[env].copy(),
        goals=world.goals[env].copy(),
        personal_space_radii=world.personal_space[env].copy(),
        active=world.active[env].copy(),
        robot_heading=float(world.heading[env]),
        time=float(world.time[env]),
        trails=np.stack(trail) if trail else None,
        caption=caption,
        **extra,
    )


class SocialNavEnv(gym.Env):
    """A robot among socially individual ORCA humans. Observation: Dict; action: Box [-1, 1]^2 (speed, heading change)."""

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": 4}

    def __init__(self, config: ConfigLike = None, render_mode: str | None = None, **overrides: Any):
        self.config: EnvConfig = load_config(config, **overrides)
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode={render_mode!r} is not supported; allowed: rgb_array, human, None")
        self.render_mode = render_mode
        self.world = CrowdWorld(self.config, n_envs=1)
        self.observation_space = observation_space(self.config.max_humans)
        self.action_space = action_space()
        self.metadata = {**self.metadata, "render_fps": round(1.0 / self.config.time_step)}
        self._trail: list[np.ndarray] = []
        self._renderer = None
        self._viewer = None
        self._started = False

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        if seed is not None or not self._started:
            # The world owns the randomness so that env i of a VecEnv seeded with s equals this env seeded with s+i.
            self.world.seed(0, seed if seed is not None else int(self.np_random.integers(2**63)))
        self._started = True
        self.world.reset([0])
        self._trail = [self.world.positions[0].copy()]
        info = {"time": 0.0}
        if self.render_mode == "human":
            self.render()
        return self._observation(), info

    def step(self, action: np.ndarray):
        if not self._started:
            raise RuntimeError("call reset() before step()")
        result = self.world.step(np.asarray(action, dtype=np.float64).reshape(1, 2))
        self._trail.append(self.world.positions[0].copy())
        info = step_infos(self.world, result)[0]
        if self.render_mode == "human":
            self.render()
        return (
            self._observation(),
            float(result.reward[0]),
            bool(result.terminated[0]),
            bool(result.truncated[0]),
            info,
        )

    def _observation(self) -> dict[str, np.ndarray]:
        return {key: value[0] for key, value in self.world.observe().items()}

    # ------------------------------------------------------------------------------------------------ rendering

    def scene_frame(self, caption: str = "", **extra: Any):
        """The current scene as a `socnav.viz.SceneFrame` (positions, goals, personal spaces, trail)."""
        return scene_frame(self.world, 0, self._trail[-40:], caption=caption, **extra)

    def render(self):
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode='rgb_array' or 'human'.")
            return None
        from socnav.viz.render import SceneRenderer

        if self._renderer is None:
            self._renderer = SceneRenderer(extent=self.config.circle_radius + 1.5
                                           if self.config.scenario != "random" else self.config.square_size / 2 + 1.5)
        image = self._renderer.render(self.scene_frame())
        if self.render_mode == "rgb_array":
            return image
        from socnav.viz import HumanViewer

        if self._viewer is None:
            self._viewer = HumanViewer()
        self._viewer.show(image)
        return None

    def close(self):
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        if self._viewer is not None:
            self._viewer.close()
            self._viewer = None


def make_env(config: ConfigLike = None, render_mode: str | None = None, **overrides: Any) -> SocialNavEnv:
    """Build one environment; `config` may be an `EnvConfig`, a partial dict, a YAML path or None."""
    return SocialNavEnv(config, render_mode=render_mode, **overrides)
