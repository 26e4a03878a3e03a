"""The single social-navigation environment with the Gymnasium API (SPEC section 2).

`SocialNavEnv` is one `CrowdWorld` environment; `make_env` builds it from a config object, a partial dict or a YAML path.
"""

from __future__ import annotations

import os
from typing import Any

import gymnasium as gym
import numpy as np

from socnav.config import ConfigError, ConfigLike, EnvConfig, load_config
from socnav.envs.spaces import action_space, observation_space
from socnav.sim.world import OUTCOME_NAMES, CrowdWorld, StepResult


class ActionError(ValueError):
    """An action cannot be applied (NaN, wrong shape); the message names the environment."""


def check_actions(actions: Any, n_envs: int, label: str = "environment") -> np.ndarray:
    """`actions` as a float64 (n_envs, 2) array, or `ActionError` naming the first environment whose action is NaN.

    A NaN action would make the robot's position and reward NaN for the rest of the episode (no end, no error),
    so it is refused. +-inf is accepted: like every out-of-range action it is clipped to the action bounds [-1, 1]
    (SB3 clips a Box policy's actions the same way before they reach the environment).
    """
    array = np.asarray(actions, dtype=np.float64)
    if array.size != 2 * n_envs:
        raise ActionError(f"expected {n_envs} action(s) of 2 values (speed, heading change), got shape {array.shape}")
    array = array.reshape(n_envs, 2)
    bad = np.flatnonzero(np.isnan(array).any(axis=1))
    if bad.size:
        env = int(bad[0])
        others = f" (and {bad.size - 1} other(s))" if bad.size > 1 else ""
        raise ActionError(f"the action of {label} {env}{others} is NaN: {array[env].tolist()}; actions must be "
                          "numbers in [-1, 1] (larger values and +-inf are clipped)")
    return array


#: Memory of one environment in bytes ~ a + b * slots + c * slots**2 + d * max_humans (slots = 1 + most humans):
#: the world's per-agent and per-pair arrays, the observation and the per-step info dict, fitted (and rounded up
#: by ~25 %) to tracemalloc peaks of 1,500-environment VecEnvs over reset + 3 steps with 1 to 64 humans.
_ENV_BYTES = (2048, 128, 24, 128)


def env_memory_estimate(config: EnvConfig, n_envs: int) -> int:
    """Estimated bytes that `n_envs` batched environments of `config` take while stepping."""
    from socnav.sim.scenarios import n_slots

    a, b, c, d = _ENV_BYTES
    slots = n_slots(config)
    return n_envs * (a + b * slots + c * slots * slots + d * config.max_humans)


def _physical_memory() -> int | None:
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):  # not POSIX: no bound known
        return None


def check_env_count(n_envs: Any, config: EnvConfig, what: str = "n_envs") -> int:
    """`n_envs` if it is a positive integer whose environments fit in this machine's memory, else `ConfigError`
    naming `what`, the estimate and the most environments that fit (see `env_memory_estimate`)."""
    if isinstance(n_envs, bool) or not isinstance(n_envs, (int, np.integer)) or n_envs < 1:
        raise ConfigError(f"{what} must be a positive integer, got {n_envs!r}")
    need, total = env_memory_estimate(config, int(n_envs)), _physical_memory()
    if total is not None and need > total:
        most = total // env_memory_estimate(config, 1)
        raise ConfigError(
            f"{what}={int(n_envs):,} environments need about {need / 2**30:,.1f} GiB (~{need // n_envs:,} bytes each "
            f"with at most {config.humans_range()[1]} human(s)), more than this machine's {total / 2**30:,.1f} GiB of "
            f"memory; use at most {most:,}"
        )
    return int(n_envs)


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
        attentive=None if getattr(world, "attentive", None) is None else world.attentive[env].copy(),
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
        result = self.world.step(check_actions(action, 1))
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
