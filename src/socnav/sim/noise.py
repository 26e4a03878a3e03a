"""Counter-based random numbers for perturbations, compiled with numba.

A draw is a pure function of (episode key, stream, step, element), so every environment's noise is the same whatever the
batch it runs in, and recomputing an observation never consumes randomness.
"""

from __future__ import annotations

import math

import numba
import numpy as np

OBSERVATION_STREAM = 1
HEADING_STREAM = 2
SPEED_STREAM = 3
ATTENTION_STREAM = 4
MODEL_STREAM = 5  # which model moves each human of a mixed crowd (humans.mix)

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
_MIX1 = np.uint64(0xBF58476D1CE4E5B9)
_MIX2 = np.uint64(0x94D049BB133111EB)


@numba.njit(cache=True, inline="always")
def _splitmix64(value: np.uint64) -> np.uint64:
    z = value + _GOLDEN
    z = (z ^ (z >> np.uint64(30))) * _MIX1
    z = (z ^ (z >> np.uint64(27))) * _MIX2
    return z ^ (z >> np.uint64(31))


@numba.njit(cache=True)
def uniform01(key: np.uint64, stream: int, step: int, element: int) -> float:
    """Uniform in (0, 1): splitmix64 hash of the counter tuple, top 53 bits."""
    h = _splitmix64(key ^ _splitmix64(np.uint64(stream)))
    h = _splitmix64(h ^ np.uint64(step))
    h = _splitmix64(h ^ np.uint64(element))
    return ((h >> np.uint64(11)) + 0.5) * (1.0 / 9007199254740992.0)


@numba.njit(cache=True)
def standard_normal(key: np.uint64, stream: int, step: int, element: int) -> float:
    """N(0, 1) by Box-Muller from two counter-based uniforms."""
    u1 = uniform01(key, stream, step, 2 * element)
    u2 = uniform01(key, stream, step, 2 * element + 1)
    return math.sqrt(-2.0 * math.log(u1)) * math.cos(2.0 * math.pi * u2)
