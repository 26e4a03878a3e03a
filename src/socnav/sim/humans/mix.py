"""Mixed crowds (``humans.mix: {orca: 0.5, social_force: 0.5}``): each human walks by one of several models, drawn
per human and episode with the configured shares.

The draw is counter-based (episode key, `MODEL_STREAM`, step 0, slot), like attention: it consumes nothing of the
episode's generator, so starts, goals, traits and every other draw of an episode are those of the unmixed world,
and an episode is the same whatever the batch it runs in. Every model computes the velocities of its own humans in
one batched call over all environments, seeing every other agent (whatever moves it) as it sees any agent.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numba
import numpy as np

from socnav.sim.humans.base import Crowd, HumanModel
from socnav.sim.noise import MODEL_STREAM, uniform01

#: The value of ``humans.model`` for a mixed crowd (set by ``humans.mix``); not a registered model.
MIX = "mix"


@numba.njit(cache=True)
def draw_models(key, n_slots, cumulative):
    """Per slot, the index of the model that moves it: the first k with u < cumulative[k], u ~ U(0, 1) drawn from
    (episode key, MODEL_STREAM, 0, slot); slot 0 (the robot) gets 0."""
    index = np.zeros(n_slots, dtype=np.int64)
    last = len(cumulative) - 1
    for agent in range(1, n_slots):
        u = uniform01(key, MODEL_STREAM, 0, agent)
        k = 0
        while k < last and u >= cumulative[k]:
            k += 1
        index[agent] = k
    return index


class MixedHumans:
    """`HumanModel` "mix": the models of ``humans.mix`` side by side, each moving the humans the episode gave it
    (``crowd.model_index``). Its `interaction_range` and `arrival_distance` are the largest of its models'; the world
    applies each model's own to that model's humans (`ranges`, `arrival_distances`)."""

    name = MIX

    def __init__(self, models: list[HumanModel], shares: list[float]):
        if not models or len(models) != len(shares):
            raise ValueError("a mixed crowd needs one share per model")
        total = float(sum(shares))
        self.models = list(models)
        self.names = [model.name for model in self.models]
        self.shares = [float(share) / total for share in shares]
        cumulative = np.cumsum(self.shares)
        cumulative[-1] = np.inf  # rounding never leaves a draw without a model
        self.cumulative = cumulative
        self.ranges = np.array([model.interaction_range for model in self.models], dtype=np.float64)
        self.arrival_distances = np.array([model.arrival_distance for model in self.models], dtype=np.float64)
        self.interaction_range = float(self.ranges.max())
        self.arrival_distance = float(self.arrival_distances.max())

    @classmethod
    def from_shares(cls, shares: Mapping[str, float], build: Callable[[str], HumanModel]) -> MixedHumans:
        """The mix of `shares` (model name -> share), each model built by `build(name)`; zero shares are dropped."""
        kept = [(name, share) for name, share in shares.items() if share > 0]
        return cls([build(name) for name, _ in kept], [share for _, share in kept])

    def draw(self, key: Any, n_slots: int) -> np.ndarray:
        """The model index of every slot of an episode with noise key `key`."""
        return draw_models(np.uint64(key), n_slots, self.cumulative)

    def velocities(self, crowd: Crowd, compute: np.ndarray) -> np.ndarray:
        index = crowd.model_index if crowd.model_index is not None else np.zeros(compute.shape, dtype=np.int64)
        out = crowd.velocities.copy()
        for k, model in enumerate(self.models):
            mine = compute & (index == k)
            if mine.any():
                velocities = model.velocities(crowd, mine)
                out[mine] = velocities[mine]
        return out
