"""The equations of the uncertainty estimates in NumPy alone (paper IV-B, eqs. (5)-(9)).
Shared by the torch estimators (`socnav.uncertainty.estimators`) and the torch-free runtime (`socnav.runtime`).

See `socnav.uncertainty.estimators` for the estimators that draw the K samples these functions summarise.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numba
import numpy as np

from socnav.envs.spaces import ACTION_NAMES

__all__ = [
    "HEADING",
    "SPEED",
    "Uncertainty",
    "apply_feature_map",
    "ensemble_feature_uncertainty",
    "feature_map",
    "feature_uncertainty",
    "summarise_samples",
]

#: Index of each action dimension in the env action (and in every (B, 2) array of :class:`Uncertainty`).
SPEED = ACTION_NAMES.index("speed")
HEADING = ACTION_NAMES.index("heading")


# ----------------------------------------------------------------------------------------------------------
# The result
# ----------------------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Uncertainty:
    """Uncertainty of a batch of ``B`` observations (all arrays float64).

    :param mean_action: (B, 2) average of the K sampled action means ``mu_bar`` (unclipped; index 0 speed,
        1 heading change).
    :param u_ep: (B, 2) epistemic uncertainty ``(1/K) sum_k (mu_k - mu_bar)^2``.
    :param u_al: (B, 2) aleatoric uncertainty ``(1/K) sum_k sigma_k^2``.
    :param u_feat: (B,) predictive feature uncertainty (MC-dropout eq. (8) or ensemble eq. (9)).
    """

    mean_action: np.ndarray
    u_ep: np.ndarray
    u_al: np.ndarray
    u_feat: np.ndarray

    def __post_init__(self) -> None:
        for name in ("mean_action", "u_ep", "u_al", "u_feat"):
            value = getattr(self, name)
            if type(value) is not np.ndarray or value.dtype != np.float64:  # (one cheap test per field at B = 1)
                object.__setattr__(self, name, np.asarray(value, dtype=np.float64))
        shape, batch = self.mean_action.shape, self.u_feat.shape
        if (len(batch) != 1 or len(shape) != 2 or shape[0] != batch[0]
                or not shape == self.u_ep.shape == self.u_al.shape):
            raise ValueError(
                "Uncertainty needs mean_action, u_ep, u_al of one shape (B, A) and u_feat (B,), got "
                f"{self.mean_action.shape}, {self.u_ep.shape}, {self.u_al.shape}, {self.u_feat.shape}"
            )

    @property
    def batch_size(self) -> int:
        """Number of observations ``B``."""
        return int(self.u_feat.shape[0])

    @property
    def u_ep_speed(self) -> np.ndarray:
        """(B,) epistemic uncertainty of the speed action."""
        return self.u_ep[:, SPEED]

    @property
    def u_ep_heading(self) -> np.ndarray:
        """(B,) epistemic uncertainty of the heading-change action (the safety rule's ``c_ep``)."""
        return self.u_ep[:, HEADING]

    @property
    def u_al_speed(self) -> np.ndarray:
        """(B,) aleatoric uncertainty of the speed action."""
        return self.u_al[:, SPEED]

    @property
    def u_al_heading(self) -> np.ndarray:
        """(B,) aleatoric uncertainty of the heading-change action."""
        return self.u_al[:, HEADING]

    def as_dict(self) -> dict[str, np.ndarray]:
        """Flat (B,) columns for a DataFrame: ``mean_action_speed``, ``mean_action_heading``, ``u_ep_speed``,
        ``u_ep_heading``, ``u_al_speed``, ``u_al_heading``, ``u_feat``."""
        out: dict[str, np.ndarray] = {}
        for field in ("mean_action", "u_ep", "u_al"):
            values = getattr(self, field)
            for index, action in enumerate(ACTION_NAMES):
                out[f"{field}_{action}"] = values[:, index]
        out["u_feat"] = self.u_feat
        return out


# ----------------------------------------------------------------------------------------------------------
# Pure functions (the equations)
# ----------------------------------------------------------------------------------------------------------
def feature_uncertainty(variances: Any, h_min: Any, h_max: Any) -> np.ndarray:
    """MC-dropout feature uncertainty, paper eq. (8), of per-element variances ``V`` (..., D).

        V_max,d = (h_max,d - h_min,d)^2 / 12
        u_feat  = sum_d w_d * r_d,   w_d = V_d / sum_d' V_d',   r_d = V_d / V_max,d

    ``u_feat`` is the ``w``-weighted average of the normalised variances ``r_d``, so it lies in
    ``[min_d r_d, max_d r_d]``, i.e. in [0, 1] whenever every ``V_d <= V_max,d``. It is *not* clipped: ``V_max``
    is the variance of a uniform distribution on the tracked range, not a hard bound (a distribution on
    that range can reach 3 ``V_max``, and dropout samples can leave the range seen in training), so values
    above 1 are possible and mean "more spread than uniform over the training range".

    Degenerate cases (explicit, not NaN):

    * an element whose range is untracked (``h_min = +inf`` / ``h_max = -inf``, nothing observed yet),
      non-finite, or of zero width (``h_max <= h_min``: the element never varied in training) has no usable
      ``V_max`` and is **excluded** from both sums (weights are renormalised over the remaining elements);
    * if the variances of all remaining elements are zero (or no element remains), ``u_feat = 0``, the limit
      of eq. (8) as ``V -> 0`` (``0 <= u_feat <= max_d r_d``).

    :param variances: (..., D) non-negative element-wise variances.
    :param h_min: (D,) tracked element-wise minimum.
    :param h_max: (D,) tracked element-wise maximum.
    :return: (...) float64 array.
    """
    return apply_feature_map(_to_numpy(variances), *feature_map(h_min, h_max))


def feature_map(h_min: Any, h_max: Any) -> tuple[np.ndarray, np.ndarray]:
    """The per-element part of eq. (8) that depends on the tracked range only, computed once per range:
    ``(valid, 1 / V_max)``, (D,) each, with ``V_max,d = (h_max,d - h_min,d)^2 / 12``; ``1 / V_max = 0`` on the
    excluded (invalid) elements (see :func:`feature_uncertainty`). :func:`apply_feature_map` uses it."""
    lo, hi = _to_numpy(h_min), _to_numpy(h_max)
    width = hi - lo
    valid = np.isfinite(lo) & np.isfinite(hi) & (width > 0.0)
    inv_v_max = np.where(valid, 12.0 / np.where(valid, width, 1.0) ** 2, 0.0)
    return valid, inv_v_max


def apply_feature_map(v: np.ndarray, valid: np.ndarray, inv_v_max: np.ndarray) -> np.ndarray:
    """Eq. (8) over the valid elements: ``sum_d V_d^2 / V_max,d / sum_d V_d`` (0 where ``sum_d V_d = 0``), with
    ``(valid, inv_v_max)`` from :func:`feature_map`. ``v`` (..., D) float; returns (...) float64. One compiled pass
    (cheap at batch 1, where NumPy's per-call overhead would dominate)."""
    v = _float_array(v)
    flat = v.reshape(-1, v.shape[-1]) if v.ndim != 2 else v
    out = _feature_kernel(flat, np.asarray(valid, dtype=np.bool_), np.asarray(inv_v_max, dtype=np.float64))
    return out.reshape(v.shape[:-1]) if v.ndim != 2 else out


@numba.njit(cache=True)
def _feature_kernel(v: np.ndarray, valid: np.ndarray, inv_v_max: np.ndarray) -> np.ndarray:  # pragma: no cover
    rows, width = v.shape
    out = np.empty(rows)
    for row in range(rows):
        total, weighted = 0.0, 0.0
        for d in range(width):
            # multiplied, not skipped: a NaN / inf variance of an excluded element still makes the result NaN
            x = np.float64(v[row, d]) * (1.0 if valid[d] else 0.0)
            total += x
            weighted += x * x * inv_v_max[d]
        out[row] = weighted / total if total > 0.0 else 0.0
    return out


def ensemble_feature_uncertainty(variances: Any) -> np.ndarray:
    """Ensemble feature uncertainty, paper eq. (9): ``u_feat = (1/D) sum_d V_d`` of ``V`` (..., D)."""
    return _to_numpy(variances).mean(axis=-1)


def summarise_samples(mu: Any, log_std: Any, h: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Moments of K samples: ``(mu_bar, u_ep, u_al, V)`` from ``mu``, ``log_std`` (K, B, A) and ``h`` (K, B, D).

        mu_bar = (1/K) sum_k mu_k,   u_ep = (1/K) sum_k (mu_k - mu_bar)^2,   u_al = (1/K) sum_k exp(2 log sigma_k)
        V_d    = (1/K) sum_k (h_{d,k} - h_bar_d)^2

    Shapes of the results: (B, A), (B, A), (B, A), (B, D); float64 (accumulated in float64 whatever the input's
    float type). One compiled pass over the samples (two for the variances: mean first, then the deviations).
    """
    mu, log_std, h = _float_array(mu), _float_array(log_std), _float_array(h)
    if mu.ndim != 3 or h.ndim != 3 or log_std.shape != mu.shape or h.shape[:2] != mu.shape[:2]:
        raise ValueError(f"summarise_samples needs mu, log_std (K, B, A) and h (K, B, D), got {mu.shape}, "
                         f"{log_std.shape}, {h.shape}")
    return _moments_kernel(mu, log_std, h)


@numba.njit(cache=True)
def _moments_kernel(mu: np.ndarray, log_std: np.ndarray,
                    h: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    # paper eq. (5): u_ep, eq. (6): u_al, eq. (7): V (the feature variance per element), from the K samples
    k, batch, actions = mu.shape
    width = h.shape[2]
    mean, u_ep, u_al = np.zeros((batch, actions)), np.zeros((batch, actions)), np.zeros((batch, actions))
    h_mean, variance = np.zeros((batch, width)), np.zeros((batch, width))
    for s in range(k):  # sums in sample order (streams through the (K, B, .) arrays)
        for b in range(batch):
            for a in range(actions):
                mean[b, a] += np.float64(mu[s, b, a])
                u_al[b, a] += np.exp(2.0 * np.float64(log_std[s, b, a]))
            for d in range(width):
                h_mean[b, d] += np.float64(h[s, b, d])
    mean /= k
    u_al /= k
    h_mean /= k
    for s in range(k):
        for b in range(batch):
            for a in range(actions):
                deviation = np.float64(mu[s, b, a]) - mean[b, a]
                u_ep[b, a] += deviation * deviation
            for d in range(width):
                deviation = np.float64(h[s, b, d]) - h_mean[b, d]
                variance[b, d] += deviation * deviation
    u_ep /= k
    variance /= k
    return mean, u_ep, u_al, variance


def _float_array(x: Any) -> np.ndarray:
    """A float32 / float64 NumPy array of an array-like or a torch tensor, without a copy where it already is one
    (the compiled kernels accumulate in float64 either way)."""
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    if type(x) is np.ndarray and (x.dtype == np.float64 or x.dtype == np.float32):
        return x
    return np.asarray(x, dtype=np.float64)


def _to_numpy(x: Any) -> np.ndarray:
    """float64 NumPy array of an array-like or a torch tensor (duck-typed: this module never imports torch)."""
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)
