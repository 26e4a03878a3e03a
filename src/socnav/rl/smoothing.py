"""Training-time costs that make a learned policy drive smoothly: an SB3 ``VecEnvWrapper`` that subtracts a turning
cost and an action-change cost from the reward the agent learns from (docs/training.md, "Smooth driving").

Why: PPO with a Gaussian policy on a bounded action space learns bang-bang turning here. The shipped open-plane
policy puts its heading action at a bound (+-1, i.e. +-0.524 rad) on 98 % of the steps and flips its sign almost every
step: the world's reward does not care, a real base and the people beside it do. Both costs are per step, on the
actions as the environment receives them (SB3 clips them to the Box first), in the action space's units ([-1, 1]):

    r'_t = r_t - turn_penalty * |a_t[heading]| - action_change_penalty * sum_i |a_t[i] - a_{t-1}[i]| / 2

The change cost is not charged on the first step of an episode (there is no previous action). The world's own reward
(what the evaluations and the paper's return report) is unchanged.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from stable_baselines3.common.vec_env import VecEnv, VecEnvWrapper
from stable_baselines3.common.vec_env.base_vec_env import VecEnvStepReturn

from socnav.envs.spaces import ACTION_NAMES

__all__ = ["SmoothnessPenalty", "smoothness_costs"]

HEADING = ACTION_NAMES.index("heading")


def smoothness_costs(actions: np.ndarray, previous: np.ndarray, has_previous: np.ndarray, turn_penalty: float,
                     action_change_penalty: float) -> np.ndarray:
    """Per environment: ``turn_penalty * |heading action| + action_change_penalty * sum |a_t - a_{t-1}| / 2`` (the
    change term only where ``has_previous``); actions in [-1, 1], shape (n_envs, 2)."""
    turning = np.abs(actions[:, HEADING])
    change = 0.5 * np.abs(actions - previous).sum(axis=1)  # / 2: the range of one action dimension
    return turn_penalty * turning + action_change_penalty * np.where(has_previous, change, 0.0)


class SmoothnessPenalty(VecEnvWrapper):
    """Subtracts :func:`smoothness_costs` from the rewards of the wrapped vectorised environment."""

    def __init__(self, venv: VecEnv, turn_penalty: float = 0.0, action_change_penalty: float = 0.0) -> None:
        if turn_penalty < 0 or action_change_penalty < 0:
            raise ValueError(f"penalties must be >= 0, got turn_penalty={turn_penalty}, "
                             f"action_change_penalty={action_change_penalty}")
        super().__init__(venv)
        self.turn_penalty = float(turn_penalty)
        self.action_change_penalty = float(action_change_penalty)
        low, high = self.action_space.low, self.action_space.high  # type: ignore[attr-defined]
        self._low, self._high = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
        self._previous = np.zeros((self.num_envs, len(ACTION_NAMES)))
        self._has_previous = np.zeros(self.num_envs, dtype=bool)
        self._actions = self._previous.copy()

    def reset(self) -> Any:
        self._has_previous[:] = False
        return self.venv.reset()

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.clip(np.asarray(actions, dtype=np.float64), self._low, self._high)
        self.venv.step_async(actions)

    def step_wait(self) -> VecEnvStepReturn:
        observations, rewards, dones, infos = self.venv.step_wait()
        costs = smoothness_costs(self._actions, self._previous, self._has_previous, self.turn_penalty,
                                 self.action_change_penalty)
        self._previous = self._actions
        self._has_previous = ~np.asarray(dones, dtype=bool)  # an episode that ended restarted: no previous action
        return observations, (rewards - costs).astype(rewards.dtype), dones, infos
