"""Fixtures for the socnav.rl tests: a tiny Gymnasium env with the socnav observation/action spaces.
The real environment lives in socnav.envs; this stand-in only reproduces its spaces and padding conventions.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from typing import Any, ClassVar

import gymnasium as gym
import numpy as np
import pytest
import torch as th
from gymnasium import spaces
from stable_baselines3.common.logger import KVWriter, Logger
from stable_baselines3.common.vec_env import DummyVecEnv

MAX_HUMANS = 10


def socnav_spaces(max_humans: int = MAX_HUMANS) -> tuple[spaces.Dict, spaces.Box]:
    """The socnav observation and action spaces (docs/world.md, Observation and action)."""
    obs_space = spaces.Dict(
        {
            "robot": spaces.Box(-np.inf, np.inf, (5,), np.float32),
            "humans": spaces.Box(-np.inf, np.inf, (max_humans, 7), np.float32),
            "humans_mask": spaces.Box(0.0, 1.0, (max_humans,), np.float32),
        }
    )
    return obs_space, spaces.Box(-1.0, 1.0, (2,), np.float32)


class DummySocNavEnv(gym.Env):
    """Random observations with the socnav layout: n real rows (a prefix), zero padding.

    ``n`` is drawn per episode from ``U{n_min..n_max}`` (default ``0..max_humans``, the worst case for the LSTM).
    Reward ``-|a - target(o)|``, a learnable but meaningless signal; episodes truncate after ``episode_len``.
    """

    metadata: ClassVar[dict[str, Any]] = {"render_modes": []}

    def __init__(
        self, max_humans: int = MAX_HUMANS, episode_len: int = 100, n_humans: tuple[int, int] | None = None
    ) -> None:
        self.observation_space, self.action_space = socnav_spaces(max_humans)
        self.max_humans = max_humans
        self.n_range = n_humans if n_humans is not None else (0, max_humans)
        self.episode_len = episode_len
        self._t = 0
        self._n = 0

    def _obs(self) -> dict[str, np.ndarray]:
        rng = self.np_random
        humans = np.zeros((self.max_humans, 7), np.float32)
        humans[: self._n] = rng.normal(size=(self._n, 7))
        mask = np.zeros(self.max_humans, np.float32)
        mask[: self._n] = 1.0
        robot = rng.normal(size=5).astype(np.float32)
        self._target = np.tanh(robot[:2])
        return {"robot": robot, "humans": humans, "humans_mask": mask}

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):  # type: ignore[override]
        super().reset(seed=seed)
        self._t = 0
        self._n = int(self.np_random.integers(self.n_range[0], self.n_range[1] + 1))
        return self._obs(), {}

    def step(self, action: np.ndarray):  # type: ignore[override]
        reward = -float(np.abs(np.asarray(action) - self._target).sum())
        self._t += 1
        return self._obs(), reward, False, self._t >= self.episode_len, {}


def make_dummy_vec_env(n_envs: int = 4, seed: int = 0, **kwargs: Any) -> DummyVecEnv:
    """``n_envs`` DummySocNavEnv in an SB3 DummyVecEnv, seeded."""
    venv = DummyVecEnv([lambda: DummySocNavEnv(**kwargs) for _ in range(n_envs)])
    venv.seed(seed)
    return venv


def random_obs(batch: int, max_humans: int = MAX_HUMANS, seed: int = 0,
               n: list[int] | None = None) -> dict[str, th.Tensor]:
    """A batch of observation tensors with a random (or given) number of humans per sample."""
    gen = np.random.default_rng(seed)
    counts = np.asarray(n if n is not None else gen.integers(0, max_humans + 1, size=batch))
    humans = np.zeros((batch, max_humans, 7), np.float32)
    mask = np.zeros((batch, max_humans), np.float32)
    for b, k in enumerate(counts):
        humans[b, :k] = gen.normal(size=(k, 7))
        mask[b, :k] = 1.0
    robot = gen.normal(size=(batch, 5)).astype(np.float32)
    return {"robot": th.as_tensor(robot), "humans": th.as_tensor(humans), "humans_mask": th.as_tensor(mask)}


class RecordingWriter(KVWriter):
    """SB3 logger output that keeps every dumped ``{key: value}`` dict (to check what training logs)."""

    def __init__(self) -> None:
        self.dumps: list[dict[str, Any]] = []

    def write(self, key_values: dict[str, Any], key_excluded: dict[str, Any], step: int = 0) -> None:
        self.dumps.append(dict(key_values))

    def close(self) -> None:
        pass

    @property
    def keys(self) -> set[str]:
        """All keys ever dumped."""
        return set().union(*self.dumps) if self.dumps else set()


def attach_recorder(model: Any) -> RecordingWriter:
    """Give ``model`` a logger that records its dumps (kept across ``learn`` calls)."""
    writer = RecordingWriter()
    model.set_logger(Logger(folder=None, output_formats=[writer]))
    return writer


# Small but complete PPO settings for fast tests: 4 envs x 32 steps = 128 samples per rollout.
SMALL = {"n_steps": 32, "batch_size": 64, "n_epochs": 2}


@pytest.fixture
def make_vec_env() -> Iterator[Callable[..., DummyVecEnv]]:
    """Factory ``make_vec_env(n_envs=4, seed=0, **env_kwargs)``; the envs are closed after the test."""
    envs: list[DummyVecEnv] = []

    def factory(n_envs: int = 4, seed: int = 0, **kwargs: Any) -> DummyVecEnv:
        envs.append(make_dummy_vec_env(n_envs, seed, **kwargs))
        return envs[-1]

    yield factory
    for env in envs:
        env.close()


@pytest.fixture
def small_model(make_vec_env: Callable[..., DummyVecEnv]) -> Callable[..., Any]:
    """Factory ``small_model(algo, **overrides)``: ``make_model`` on 4 dummy envs with the SMALL settings."""
    from socnav.rl import make_model

    def factory(algo: str, seed: int = 0, **overrides: Any) -> Any:
        return make_model(algo, make_vec_env(4, seed), seed=seed, overrides={**SMALL, **overrides})

    return factory


@pytest.fixture
def recorder() -> Callable[[Any], RecordingWriter]:
    """``recorder(model)`` attaches a :class:`RecordingWriter` logger to the model and returns it."""
    return attach_recorder


@pytest.fixture
def obs_batch() -> Callable[..., dict[str, th.Tensor]]:
    """Factory ``obs_batch(batch, max_humans=10, seed=0, n=None)`` of observation tensors."""
    return random_obs
