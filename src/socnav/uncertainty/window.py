"""Windowed uncertainty: the mean of the last ``w`` per-step estimates of every environment (paper IV-C, V-B.2).
A per-environment ring buffer that the safety rule reads instead of the raw, noisier per-step values.

For environment ``i`` at step ``t`` with ``n_i = min(w, steps since its episode started)``::

    u_bar_i(t) = (1/n_i) sum_{j=0}^{n_i - 1} u_i(t - j)        for u in (u_ep, u_al, u_feat)

so the first steps of an episode average over fewer (1, 2, ..., w) values; nothing is carried over from the
previous episode once :meth:`WindowedUncertainty.reset` was called for that environment. ``mean_action`` is
*not* windowed: the returned value is the current step's (an action from earlier steps is never meant).
"""

from __future__ import annotations

from typing import Any

import numba
import numpy as np

from socnav.uncertainty.stats import Uncertainty

__all__ = ["WindowedUncertainty"]


class WindowedUncertainty:
    """Per-environment ring buffer of the last ``window`` uncertainty estimates.

    Use with a vectorised env (SB3 auto-reset)::

        window = WindowedUncertainty(n_envs, window=4)
        obs = venv.reset()
        while ...:
            u = window.update(estimator(obs))        # windowed values for the current observations
            obs, rewards, dones, infos = venv.step(actions)
            window.reset(np.flatnonzero(dones))      # obs[i] of a done env is already the next episode's

    :param n_envs: number of environments (the batch size of every update).
    :param window: window length ``w`` (paper: 4).
    """

    def __init__(self, n_envs: int, window: int = 4) -> None:
        if n_envs < 1 or window < 1:
            raise ValueError(f"need n_envs >= 1 and window >= 1, got n_envs={n_envs}, window={window}")
        self.n_envs = int(n_envs)
        self.window = int(window)
        self._action_dim: int | None = None
        self._buffer = np.zeros((0,))  # (n_envs, window, 2 A + 1): [u_ep, u_al, u_feat], allocated on first use
        self._count = np.zeros(self.n_envs, dtype=np.int64)  # valid entries per env (<= window)
        self._pos = np.zeros(self.n_envs, dtype=np.int64)  # next slot to write per env

    @property
    def counts(self) -> np.ndarray:
        """(n_envs,) number of steps the current window of each environment averages over."""
        return self._count.copy()

    def _envs_index(self, envs: Any) -> np.ndarray:
        if envs is None:
            return np.arange(self.n_envs)
        index = np.asarray(envs)
        if index.dtype == bool:
            if index.shape != (self.n_envs,):
                raise ValueError(f"a boolean env mask needs shape ({self.n_envs},), got {index.shape}")
            return np.flatnonzero(index)
        index = np.atleast_1d(index).astype(np.int64)
        if index.size and (index.min() < -self.n_envs or index.max() >= self.n_envs):
            raise IndexError(f"env index out of range for {self.n_envs} environments: {index.tolist()}")
        return index % self.n_envs

    def reset(self, envs: Any = None) -> None:
        """Empty the windows of ``envs`` (indices, a boolean mask, or None for all): call at episode start."""
        index = self._envs_index(envs)
        self._count[index] = 0
        self._pos[index] = 0
        if self._buffer.ndim == 3:
            self._buffer[index] = 0.0

    def update(self, u: Uncertainty) -> Uncertainty:
        """Push this step's estimate of every environment; return the windowed means (``mean_action``: current)."""
        if u.batch_size != self.n_envs:
            raise ValueError(f"expected an Uncertainty of batch {self.n_envs}, got {u.batch_size}")
        action_dim = u.u_ep.shape[1]
        if self._action_dim is None:
            self._action_dim = action_dim
            self._buffer = np.zeros((self.n_envs, self.window, 2 * action_dim + 1))
        elif action_dim != self._action_dim:
            raise ValueError(f"action dimension changed from {self._action_dim} to {action_dim}")
        u_ep, u_al, u_feat = _push(self._buffer, self._pos, self._count, u.u_ep, u.u_al, u.u_feat)
        return Uncertainty(u.mean_action, u_ep, u_al, u_feat)


@numba.njit(cache=True)
def _push(buffer: np.ndarray, pos: np.ndarray, count: np.ndarray, u_ep: np.ndarray, u_al: np.ndarray,
          u_feat: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
    """Write ``[u_ep, u_al, u_feat]`` of every env into its slot ``pos``, advance ``pos`` and ``count`` (in place)
    and return the means over each env's window. Slots not yet written since the last reset hold zeros, so the
    sum over the whole window divided by ``count`` is exact."""
    n_envs, window, _ = buffer.shape
    a = u_ep.shape[1]
    mean_ep, mean_al, mean_feat = np.empty((n_envs, a)), np.empty((n_envs, a)), np.empty(n_envs)
    for env in range(n_envs):
        slot = buffer[env, pos[env]]
        slot[:a] = u_ep[env]
        slot[a:2 * a] = u_al[env]
        slot[2 * a] = u_feat[env]
        pos[env] = (pos[env] + 1) % window
        count[env] = min(count[env] + 1, window)
        for column in range(2 * a + 1):
            total = 0.0
            for index in range(window):
                total += buffer[env, index, column]
            value = total / count[env]
            if column < a:
                mean_ep[env, column] = value
            elif column < 2 * a:
                mean_al[env, column - a] = value
            else:
                mean_feat[env] = value
    return mean_ep, mean_al, mean_feat
