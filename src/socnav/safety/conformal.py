"""A conformal shield in the manner of SoNIC (Yao et al. 2024): the clearance the robot's intended motion leaves to
the crowd, predicted at constant velocities, inflated by an online conformal bound on that prediction's error.

Per environment and step ``t`` (``T = horizon_steps * time_step``):

- prediction: ``g_hat(t + T)``, the nearest gap at ``t + T`` if the robot drove at the velocity its action asks for
  and every human kept its observed velocity (a constant-velocity forecast of every human at once);
- its error, once ``t + T`` has come: ``e = g_hat(t + T) - g(t + T)`` with ``g`` the observed nearest gap (a
  positive error is an optimistic forecast). The minimum over humans needs no association of people across steps;
- adaptive conformal inference (Gibbs & Candes 2021) in its quantile-tracking form (Angelopoulos et al. 2023):
  ``q <- q + eta * (1[e > q] - alpha)``: ``q`` tracks the ``1 - alpha`` quantile of the errors online, growing after
  every miss and shrinking slowly otherwise, whatever the error distribution does -- a crowd that moves unlike the
  forecast inflates the bound within a few steps;
- score: ``q - c`` with ``c`` the smallest gap to any human over the next ``T`` seconds
  (`socnav.safety.triggers.predicted_clearance`): the predicted clearance after inflating every human by ``q``,
  negated. It fires where the inflated clearance falls below ``-threshold`` metres.

``q`` starts each episode at ``initial_quantile`` (the calibration sets it to the ``1 - alpha`` quantile of the
errors on unperturbed calibration episodes).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pydantic import Field

from socnav.config import StrictModel
from socnav.safety.triggers import (
    ScoreTrigger,
    TriggerInputs,
    TriggerSpec,
    intended_relative_motion,
    predicted_clearance,
    register_trigger,
)

__all__ = ["ConformalShieldTrigger", "forecast_gap"]


class _ConformalParams(StrictModel):
    horizon_steps: float = Field(4, ge=1, le=40, description="steps ahead the forecast is checked (an integer)")
    alpha: float = Field(0.1, gt=0, lt=1, description="target miscoverage of the conformal bound")
    learning_rate: float = Field(0.05, gt=0, le=10, description="metres the bound moves per miss")
    initial_quantile: float = Field(0.0, ge=-10, le=10, description="metres: the bound at an episode's start")


def forecast_gap(inputs: TriggerInputs, seconds: float) -> np.ndarray:
    """(B,) the nearest gap ``seconds`` from now under constant velocities (robot at its intended one; ``inf``
    without humans)."""
    positions, velocities, radii, mask = intended_relative_motion(inputs)
    future = positions + velocities * seconds
    gaps = np.where(mask, np.sqrt((future ** 2).sum(-1)) - radii, np.inf)
    return gaps.min(axis=1) if gaps.shape[1] else np.full(len(gaps), np.inf)


@register_trigger
class ConformalShieldTrigger(ScoreTrigger):
    """Adaptive-conformal shield (module docstring). ``last_quantile`` (B,) holds each environment's bound ``q``."""

    name = "conformal"
    Params = _ConformalParams
    description = "predicted clearance inflated by an adaptive conformal bound on its error (SoNIC-like)"

    def __init__(self, spec: TriggerSpec, base: Path | None = None) -> None:
        super().__init__(spec, base)
        self.steps = round(self.params.horizon_steps)
        self.last_quantile = np.zeros(0)
        self.last_errors = np.zeros(0)

    def allocate(self, n_envs: int) -> None:
        self._forecasts = np.full((n_envs, self.steps), np.nan)  # ring buffer: forecasts made `steps` ago first
        self._position = np.zeros(n_envs, dtype=np.int64)
        self._quantile = np.full(n_envs, self.params.initial_quantile)

    def reset(self, envs: np.ndarray) -> None:
        self._forecasts[envs] = np.nan
        self._quantile[envs] = self.params.initial_quantile

    def score(self, inputs: TriggerInputs) -> np.ndarray:
        rows = np.arange(len(self._quantile))
        due = self._forecasts[rows, self._position]  # the forecast made `steps` steps ago for now
        with np.errstate(invalid="ignore"):  # no human in view: inf - inf, an unknown error (masked next)
            errors = due - inputs.nearest.gap
        known = np.isfinite(errors)
        missed = (errors > self._quantile) & known
        # quantile tracking: up by eta (1 - alpha) after a miss, down by eta alpha after a hit
        self._quantile = np.where(known, self._quantile + self.params.learning_rate
                                  * (missed.astype(np.float64) - self.params.alpha), self._quantile)
        self.last_errors = np.where(known, errors, np.nan)
        horizon = self.steps * inputs.time_step
        self._forecasts[rows, self._position] = forecast_gap(inputs, horizon)
        self._position = (self._position + 1) % self.steps
        self.last_quantile = self._quantile.copy()
        return self._quantile - predicted_clearance(inputs, horizon)
