"""A Stable-Baselines3 `VecEnv` that advances all environments in one batched `CrowdWorld` call.

Auto-reset, `terminal_observation` and `TimeLimit.truncated` follow SB3's conventions; env i seeded with s+i equals
`SocialNavEnv` reset with seed s+i, step for step.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvStepReturn

from socnav.config import ConfigLike, EnvConfig, load_config
from socnav.envs.env import ActionError, check_actions, check_env_count, scene_frame, step_infos
from socnav.envs.spaces import action_space, world_observation_space
from socnav.sim.world import CrowdWorld


class SocialNavVecEnv(VecEnv):
    """`n_envs` social-navigation environments stepped together (no Python loop over environments when stepping)."""

    def __init__(self, config: ConfigLike = None, n_envs: int = 1, render_mode: str | None = None, **overrides: Any):
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode={render_mode!r} is not supported by the VecEnv; allowed: rgb_array, None")
        self.config: EnvConfig = load_config(config, **overrides)
        n_envs = check_env_count(n_envs, self.config)
        self.render_mode = render_mode
        self.world = CrowdWorld(self.config, n_envs)
        self._actions: np.ndarray | None = None
        self._renderers: dict[int, Any] = {}
        actions = action_space()
        self._action_shape = actions.shape
        super().__init__(n_envs, world_observation_space(self.world), actions)
        for env in range(n_envs):
            self.world.seed(env, None)

    # ---------------------------------------------------------------------------------------------------- core

    def reset(self):
        for env, seed in enumerate(self._seeds):
            if seed is not None:
                self.world.seed(env, seed)
        self._reset_seeds()
        self._reset_options()
        self.world.reset()
        self.reset_infos = [{"time": 0.0} for _ in range(self.num_envs)]
        return self.world.observe()

    def step_async(self, actions: np.ndarray) -> None:
        """Take one action per environment, an array of shape (num_envs, 2) (SB3's layout: one row per environment);
        any other shape -- (8,) or (2, 4) for 4 environments, (4, 2, 1) -- raises `socnav.envs.env.ActionError`
        rather than being reshaped into rows it was not meant as. A NaN action raises it naming its index."""
        shape = np.shape(actions)
        expected = (self.num_envs, *self._action_shape)
        if shape != expected:
            raise ActionError(f"actions must have shape {expected} (one row of speed, heading change per "
                              f"environment), got shape {shape}")
        self._actions = check_actions(actions, self.num_envs)

    def step_wait(self) -> VecEnvStepReturn:
        if self._actions is None:
            raise RuntimeError("step_async() must be called before step_wait()")
        result = self.world.step(self._actions)
        self._actions = None
        infos = step_infos(self.world, result)
        dones = result.terminated | result.truncated
        if dones.any():
            finished = np.flatnonzero(dones)
            terminal = self.world.observe(finished)
            for row, env in enumerate(finished):
                infos[env]["terminal_observation"] = {key: value[row] for key, value in terminal.items()}
                infos[env]["TimeLimit.truncated"] = bool(result.truncated[env] and not result.terminated[env])
            self.world.reset(finished)
        return self.world.observe(), result.reward.astype(np.float32), dones, infos

    def close(self) -> None:
        for renderer in self._renderers.values():
            renderer.close()
        self._renderers.clear()

    # ---------------------------------------------------------------------------------------------------- SB3 API

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        return [getattr(self, attr_name) for _ in self._get_indices(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        setattr(self, attr_name, value)

    def env_method(self, method_name: str, *method_args, indices: VecEnvIndices = None, **method_kwargs) -> list[Any]:
        method = getattr(self, method_name)
        return [method(*method_args, **method_kwargs) for _ in self._get_indices(indices)]

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

    def get_images(self) -> Sequence[np.ndarray | None]:
        return [self.render_env(env) for env in range(self.num_envs)]

    def render_env(self, env: int) -> np.ndarray:
        """An rgb_array frame of environment `env`."""
        from socnav.viz.render import SceneRenderer

        if env not in self._renderers:
            self._renderers[env] = SceneRenderer()
        return self._renderers[env].render(scene_frame(self.world, env))


def make_vec_env(config: ConfigLike = None, n_envs: int = 1, render_mode: str | None = None,
                 **overrides: Any) -> SocialNavVecEnv:
    """Build `n_envs` batched environments as an SB3 VecEnv; `config` as for `make_env`."""
    return SocialNavVecEnv(config, n_envs=n_envs, render_mode=render_mode, **overrides)
