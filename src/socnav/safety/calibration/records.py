"""Calibration records: one row per step of rollouts of the plain policy (no fallback), the data every stage of
the calibration reads; their columns, their recorder and their collection.

==================  ==========================================================================================
``episode``         episode id, unique over the whole frame (e.g. an int offset per perturbation)
``step``            step index in the episode (0-based); the row is the observation at that step and the
                    action chosen from it
``perturbed``       bool: the episode ran in a perturbed world (the collisions to prevent) or not (the
                    false activations to avoid)
``u_ep_heading``    WINDOWED epistemic heading uncertainty at that step
``u_feat``          WINDOWED predictive feature uncertainty
``gap``             nearest-human gap ``d(t)`` from the sensed observation (``inf`` without humans)
``relative_speed``  ``|dv|`` to the nearest human
``previous_gap``    ``d(t-1)`` of the same episode, NaN at its first step
``collided``        per episode (repeated on its rows): the episode ended in a collision
``collision_step``  per episode: the ``step`` whose action led to the collision (its last step); NaN if none
``closing_speed``   optional: needed for ``proximity="closing-speed"``
``group``           optional: the perturbation type of a perturbed episode (its collisions are scored per type)
==================  ==========================================================================================

:func:`collect_records` produces this frame from rollouts.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pandas as pd

from socnav.config import ConfigLike, load_config
from socnav.envs.perturbations import is_perturbed
from socnav.safety.rule import Thresholds

__all__ = ["RECORD_COLUMNS", "STEP_COLUMNS", "CalibrationRecorder", "collect_records", "validate_records"]

RECORD_COLUMNS = ("episode", "step", "perturbed", "u_ep_heading", "u_feat", "gap", "relative_speed",
                  "previous_gap", "collided", "collision_step")
#: Per-step columns a :class:`CalibrationRecorder` keeps (the per-episode ones are added by :func:`collect_records`).
STEP_COLUMNS = ("episode", "step", "u_ep_heading", "u_feat", "gap", "relative_speed", "closing_speed", "previous_gap")


def validate_records(records: pd.DataFrame) -> pd.DataFrame:
    """``records`` with a fresh 0-based index, after checking that it holds the :data:`RECORD_COLUMNS` and one
    ``perturbed`` and one ``collided`` value per episode id (``ValueError`` naming what is wrong otherwise)."""
    missing = [c for c in RECORD_COLUMNS if c not in records]
    if missing:
        raise ValueError(f"calibration records lack columns {missing}; required: {', '.join(RECORD_COLUMNS)}")
    per_episode = records.groupby("episode", sort=False)[["perturbed", "collided"]].nunique()
    if (per_episode > 1).any().any():
        raise ValueError("each episode id must have one 'perturbed' and one 'collided' value; are episode ids "
                         "unique across the perturbed and unperturbed rollouts?")
    return records.reset_index(drop=True)


class CalibrationRecorder:
    """Rollout observer (``socnav.envs.rollout.rollout_episodes(..., observer=...)``) keeping one calibration row
    per step: what ``probe`` -- the :class:`~socnav.safety.SafePolicy` the rollout plays -- computed for that step's
    action (windowed uncertainty, nearest human, previous gap), episode ids shifted by ``episode_offset``.

    :meth:`frame` returns the per-step columns of the records (module docstring); the per-episode ones come from
    the rollout's episode records (see :func:`collect_records`).
    """

    def __init__(self, probe: Any, episode_offset: int = 0) -> None:
        self.probe = probe
        self.episode_offset = episode_offset
        self.steps: np.ndarray | None = None  # step index of each environment's current episode
        self._columns: dict[str, list[np.ndarray]] = {key: [] for key in STEP_COLUMNS}

    def on_episode_start(self, envs: np.ndarray) -> None:
        if self.steps is None:  # the first call names every environment of the rollout
            self.steps = np.zeros(len(envs), dtype=np.int64)
        self.steps[envs] = 0

    def on_step(self, observation: Any, actions: Any, result: Any, episodes: np.ndarray) -> None:
        # Called after the world stepped but before any reset: `probe.last_*` still describe this step's action.
        if self.steps is None:
            raise RuntimeError("CalibrationRecorder.on_step before on_episode_start: the rollout names its "
                               "environments with on_episode_start first")
        live = episodes >= 0
        probe, nearest = self.probe, self.probe.last_nearest
        for key, values in (("episode", episodes + self.episode_offset), ("step", self.steps),
                            ("u_ep_heading", probe.last_uncertainty["u_ep_heading"]),
                            ("u_feat", probe.last_uncertainty["u_feat"]), ("gap", nearest.gap),
                            ("relative_speed", nearest.relative_speed), ("closing_speed", nearest.closing_speed),
                            ("previous_gap", probe.last_previous_gap)):
            self._columns[key].append(np.asarray(values)[live])
        self.steps += 1

    def frame(self) -> pd.DataFrame:
        """The recorded steps, in the order they were played (columns :data:`STEP_COLUMNS`)."""
        return pd.DataFrame({key: np.concatenate(values) for key, values in self._columns.items()})


def collect_records(
    policy: Any,
    estimator: Any,
    config: ConfigLike,
    n_episodes: int,
    seed: int = 0,
    perturbed: bool | None = None,
    window: int = 4,
    n_envs: int = 8,
    episode_offset: int = 0,
    deterministic: bool = True,
    progress: Callable[[int], None] | None = None,
    sensing: str = "perceived",
) -> pd.DataFrame:
    """Per-step calibration records (module docstring) of ``n_episodes`` plain-policy episodes (episode k from
    seed ``seed + k``, id ``episode_offset + k``), with the windowed uncertainty of ``estimator``.

    ``perturbed``: the flag to store; None: True iff the config has any registered perturbation type switched on
    (`socnav.envs.perturbations.is_perturbed`: every type of the registry compared with its unperturbed value).
    ``sensing``: what the proximity columns (``gap``, speeds, ``previous_gap``) are read from, as
    ``Thresholds.sensing``: the observation (``perceived``) or the noise-free state (``true``).
    ``progress(n)`` is called with the number of episodes finished at each step that finishes some.
    ``estimator`` None: no uncertainty is estimated (the columns hold 0), for a rule that reads none
    (``Thresholds.conditions == "proximity-only"``).
    Concatenate the frames of an unperturbed and some perturbed configs (distinct ``episode_offset``).
    """
    from socnav.envs.rollout import rollout_episodes
    from socnav.safety.safe_policy import SafePolicy, no_uncertainty

    config = load_config(config)
    if perturbed is None:
        perturbed = is_perturbed(config)
    # A SafePolicy whose rule never fires plays exactly `policy` and computes the rule's inputs on the way.
    probe = SafePolicy(policy, no_uncertainty if estimator is None else estimator,
                       Thresholds.create(Thresholds.never().model_dump(), sensing=sensing), config, window=window)
    recorder = CalibrationRecorder(probe, episode_offset)
    episodes = rollout_episodes(probe, config, n_episodes, seed=seed, n_envs=n_envs, deterministic=deterministic,
                                progress=progress, observer=recorder)
    episodes = episodes.set_index(episodes["episode"] + episode_offset)
    collided = episodes["outcome"] == "collision"
    frame = recorder.frame()
    frame["perturbed"] = bool(perturbed)
    frame["collided"] = frame["episode"].map(collided).astype(bool)
    # The action of an episode's last step is the one that led to its end.
    frame["collision_step"] = frame["episode"].map((episodes["length"] - 1).where(collided)).astype(np.float64)
    ordered = [*RECORD_COLUMNS, "closing_speed"]
    return frame[ordered].sort_values(["episode", "step"], ignore_index=True)
