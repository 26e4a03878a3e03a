"""Per-step uncertainty records of evaluation rollouts: what the perturbation study (paper Table 2, Figs. 5-6) reads.
`UncertaintyRecorder` is a `rollout_episodes` observer; `record_uncertainty` runs episodes and returns both tables.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pandas as pd

from socnav.config import ConfigLike
from socnav.envs.rollout import rollout_episodes
from socnav.uncertainty.window import WindowedUncertainty

#: Uncertainty columns, raw and windowed ("w_" prefix).
UNCERTAINTY_COLUMNS = ("u_ep_heading", "u_ep_speed", "u_al_heading", "u_al_speed", "u_feat")


class UncertaintyRecorder:
    """Estimates the uncertainty of every observation the policy acts on and keeps one row per environment step.

    Row columns: ``episode, step, u_* (raw), w_u_* (windowed mean of the last `window` steps), nearest_gap,
    nearest_relative_speed, outcome`` (``outcome`` is set on an episode's last step: goal / collision / timeout).
    The uncertainty of a row is the one of the observation the action was chosen from, so the row of a collision
    step holds the uncertainty one step before the collision.
    """

    def __init__(self, estimator: Any, window: int = 4) -> None:
        self.estimator = estimator
        self.window_size = window
        self.window: WindowedUncertainty | None = None
        self.steps: np.ndarray | None = None
        self._columns: dict[str, list[np.ndarray]] = {}

    def on_episode_start(self, envs: np.ndarray) -> None:
        """Restart the windows and step counts of the environments `envs` (a rollout's first call names them all)."""
        if self.window is None or self.steps is None:  # the first call names every environment of the rollout
            self.window = WindowedUncertainty(len(envs), self.window_size)
            self.steps = np.zeros(len(envs), dtype=np.int64)
        self.window.reset(envs)
        self.steps[envs] = 0

    def on_step(self, observation: dict[str, np.ndarray], actions: np.ndarray, result: Any,
                episodes: np.ndarray) -> None:
        """Estimate the uncertainty of `observation` and record a row per environment playing an episode."""
        from socnav.sim.world import OUTCOME_NAMES

        window, steps = self._started()
        uncertainty = self.estimator(observation)
        windowed = window.update(uncertainty)
        playing = episodes >= 0
        raw, smooth = uncertainty.as_dict(), windowed.as_dict()
        self._add("episode", episodes[playing])
        self._add("step", steps[playing])
        for name in UNCERTAINTY_COLUMNS:
            self._add(name, np.asarray(raw[name])[playing])
            self._add(f"w_{name}", np.asarray(smooth[name])[playing])
        self._add("nearest_gap", result.nearest_gap[playing])
        self._add("nearest_relative_speed", result.nearest_relative_speed[playing])
        outcome = np.array([OUTCOME_NAMES.get(int(o), "") for o in result.outcome[playing]], dtype=object)
        self._add("outcome", outcome)
        steps += 1  # in place: self.steps

    def _started(self) -> tuple[WindowedUncertainty, np.ndarray]:
        """The window and the step counts, which the rollout's first `on_episode_start` creates."""
        if self.window is None or self.steps is None:
            raise RuntimeError("UncertaintyRecorder.on_step before on_episode_start (rollout_episodes calls it first)")
        return self.window, self.steps

    def _add(self, name: str, values: np.ndarray) -> None:
        self._columns.setdefault(name, []).append(np.asarray(values))

    def frame(self) -> pd.DataFrame:
        """All recorded steps, sorted by episode and step."""
        if not self._columns:
            return pd.DataFrame(columns=["episode", "step", *UNCERTAINTY_COLUMNS])
        frame = pd.DataFrame({name: np.concatenate(parts) for name, parts in self._columns.items()})
        return frame.sort_values(["episode", "step"], ignore_index=True)


def record_uncertainty(
    policy: Any,
    estimator: Any,
    config: ConfigLike,
    n_episodes: int,
    seed: int = 0,
    n_envs: int = 50,
    window: int = 4,
    deterministic: bool = True,
    progress: Callable[[int], None] | None = None,
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Play `n_episodes` (episode k from seed `seed + k`) with `policy`, estimating uncertainty at every step;
    `progress(n)` is told the episodes finished, as in `rollout_episodes`.

    :return: ``(steps, episodes)``: one row per step (see `UncertaintyRecorder`) and one per episode
        (`rollout_episodes` records).
    """
    recorder = UncertaintyRecorder(estimator, window)
    episodes = rollout_episodes(policy, config, n_episodes, seed=seed, n_envs=n_envs, deterministic=deterministic,
                                observer=recorder, progress=progress)
    return recorder.frame(), episodes


def critical_steps(steps: pd.DataFrame, column: str = "w_u_feat") -> pd.DataFrame:
    """Per episode, `column` at the step before a collision (collision episodes) or at the closest approach (others).

    Returns columns ``episode, collided, value``: the quantities of the paper's Fig. 6.
    """
    rows = []
    for episode, group in steps.groupby("episode", sort=True):
        collided = bool((group["outcome"] == "collision").any())
        row = group.iloc[-1] if collided else group.loc[group["nearest_gap"].idxmin()]
        rows.append({"episode": int(episode), "collided": collided, "value": float(row[column])})
    return pd.DataFrame(rows, columns=["episode", "collided", "value"])
