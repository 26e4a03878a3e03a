"""`MixedVecEnv`: several socnav worlds (e.g. the four map scenarios) side by side as one SB3 `VecEnv`, so that one
policy trains on all of them at once; each world is a batched `SocialNavVecEnv` stepped in one call.

The worlds must give the same observation space (the same ``max_humans``, the same ``scan``, walls in all or in
none): a policy reads one layout. Environment i of the mixture is environment i - offset of its world; seeding the
mixture with s seeds environment i with s + i, as for one world.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from stable_baselines3.common.vec_env.base_vec_env import VecEnv, VecEnvIndices, VecEnvStepReturn

from socnav.config import ConfigLike
from socnav.envs.env import ActionError
from socnav.envs.vec_env import SocialNavVecEnv

__all__ = ["MixedVecEnv", "make_mixed_vec_env"]


class MixedVecEnv(VecEnv):
    """`n_envs[k]` environments of each world `configs[k]`, in that order, as one VecEnv.

    :raises ValueError: no world, counts that do not match the worlds, or worlds whose observation spaces differ
        (naming the world and the part of the observation).
    """

    def __init__(self, configs: Sequence[ConfigLike], n_envs: int | Sequence[int] = 1):
        if not configs:
            raise ValueError("configs: at least one world is needed")
        counts = [n_envs] * len(configs) if isinstance(n_envs, int) else list(n_envs)
        if len(counts) != len(configs):
            raise ValueError(f"n_envs: one count per world ({len(configs)}), got {len(counts)}")
        self.parts = [SocialNavVecEnv(config, n_envs=count) for config, count in zip(configs, counts, strict=True)]
        first = self.parts[0].observation_space
        assert isinstance(first, gym.spaces.Dict)
        for index, part in enumerate(self.parts[1:], start=1):
            other = part.observation_space
            assert isinstance(other, gym.spaces.Dict)
            if other != first:
                keys = set(first.spaces) ^ set(other.spaces) or {key for key in first.spaces
                                                                  if first[key] != other[key]}
                raise ValueError(f"configs[{index}] ({part.config.scenario}) observes another layout than configs[0] "
                                 f"({self.parts[0].config.scenario}): {sorted(keys)} differ; the worlds of a mixture "
                                 "need the same max_humans, scan, and walls in all or in none")
        bounds = np.cumsum([0, *(part.num_envs for part in self.parts)])
        self._slices = [slice(int(start), int(end)) for start, end in itertools.pairwise(bounds)]
        super().__init__(int(bounds[-1]), first, self.parts[0].action_space)

    def _owners(self, indices: VecEnvIndices) -> list[tuple[SocialNavVecEnv, int]]:
        """(world, its own index) of each environment in `indices`."""
        owners = []
        for index in self._get_indices(indices):
            for part, rows in zip(self.parts, self._slices, strict=True):
                if rows.start <= index < rows.stop:
                    owners.append((part, index - rows.start))
        return owners

    def _concatenated(self, observations: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
        return {key: np.concatenate([observation[key] for observation in observations]) for key in observations[0]}

    def reset(self):
        for part, rows in zip(self.parts, self._slices, strict=True):
            part._seeds = self._seeds[rows]
            part._options = self._options[rows]
        self._reset_seeds()
        self._reset_options()
        observations = [part.reset() for part in self.parts]
        self.reset_infos = [info for part in self.parts for info in part.reset_infos]
        return self._concatenated(observations)

    def step_async(self, actions: np.ndarray) -> None:
        expected = (self.num_envs, *(self.action_space.shape or ()))
        if np.shape(actions) != expected:
            raise ActionError(f"actions must have shape {expected} (one row of speed, heading change per "
                              f"environment), got shape {np.shape(actions)}")
        for part, rows in zip(self.parts, self._slices, strict=True):
            part.step_async(np.asarray(actions)[rows])

    def step_wait(self) -> VecEnvStepReturn:
        results = [part.step_wait() for part in self.parts]
        observations = self._concatenated([result[0] for result in results])  # type: ignore[misc]
        rewards = np.concatenate([result[1] for result in results])
        dones = np.concatenate([result[2] for result in results])
        infos = [info for result in results for info in result[3]]
        return observations, rewards, dones, infos

    def close(self) -> None:
        for part in self.parts:
            part.close()

    def get_attr(self, attr_name: str, indices: VecEnvIndices = None) -> list[Any]:
        return [part.get_attr(attr_name, own)[0] for part, own in self._owners(indices)]

    def set_attr(self, attr_name: str, value: Any, indices: VecEnvIndices = None) -> None:
        for part, own in self._owners(indices):
            part.set_attr(attr_name, value, own)

    def env_method(self, method_name: str, *method_args, indices: VecEnvIndices = None, **method_kwargs) -> list[Any]:
        return [part.env_method(method_name, *method_args, indices=own, **method_kwargs)[0]
                for part, own in self._owners(indices)]

    def env_is_wrapped(self, wrapper_class: type[gym.Wrapper], indices: VecEnvIndices = None) -> list[bool]:
        return [False for _ in self._get_indices(indices)]

    def get_images(self) -> Sequence[np.ndarray | None]:
        return [image for part in self.parts for image in part.get_images()]


def make_mixed_vec_env(configs: Sequence[ConfigLike], n_envs: int | Sequence[int] = 1) -> MixedVecEnv:
    """`MixedVecEnv` of `configs`, `n_envs` environments of each (one count, or one per world)."""
    return MixedVecEnv(configs, n_envs)
