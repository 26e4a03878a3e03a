"""What the benchmarks share: one thread per pool, one core, and the timing loops several of them use.
A script imports it first and calls `single_thread()` (and `pin_to_one_core()`) before numpy / numba / torch load.
"""

from __future__ import annotations

import math
import os
import statistics
import time
from collections.abc import Callable
from typing import Any

#: The thread-pool sizes read when numba, OpenMP, MKL, OpenBLAS, Accelerate and numexpr load: set to 1 beforehand.
THREAD_VARIABLES = (
    "NUMBA_NUM_THREADS",
    "OMP_NUM_THREADS",
    "MKL_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "NUMEXPR_NUM_THREADS",
)


def single_thread() -> None:
    """Caps every thread pool to one thread (`THREAD_VARIABLES` = "1"); only takes effect before the libraries load."""
    for variable in THREAD_VARIABLES:
        os.environ[variable] = "1"


def pin_to_one_core() -> str:
    """Pins this process to CPU 0 (`os.sched_setaffinity(0, {0})`), before any thread pool starts; returns what
    happened, to print beside the results."""
    if not hasattr(os, "sched_setaffinity"):
        return "os.sched_setaffinity unavailable on this platform; NOT pinned to a core"
    try:
        os.sched_setaffinity(0, {0})
    except OSError as error:  # e.g. CPU 0 not in this container's cpuset
        return f"os.sched_setaffinity(0, {{0}}) failed ({error}); NOT pinned"
    return f"os.sched_setaffinity(0, {{0}}) -> running on CPU(s) {sorted(os.sched_getaffinity(0))}"


def best_of(call: Callable[[], Any], repeats: int, agent_steps: int) -> float:
    """Best (smallest) seconds per call of `call` over `repeats` samples (wall clock, `time.perf_counter`); a sample
    makes max(1, 20,000 // `agent_steps`) calls, so that it lasts far longer than the timer's resolution."""
    inner = max(1, 20_000 // agent_steps)
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        for _ in range(inner):
            call()
        best = min(best, (time.perf_counter() - start) / inner)
    return best


def time_call(fn: Callable[[], Any], repeats: int, min_time: float,
              clock: Callable[[], float] = time.perf_counter) -> float:
    """Median seconds per call over ``repeats`` timed blocks of >= ``min_time`` seconds each (after warm-up), as
    measured by ``clock`` (wall clock by default; `time.process_time` for the process's CPU time)."""
    for _ in range(3):
        fn()
    start, calls = clock(), 0
    while clock() - start < min_time:
        fn()
        calls += 1
    number = max(1, calls)
    samples = []
    for _ in range(repeats):
        start = clock()
        for _ in range(number):
            fn()
        samples.append((clock() - start) / number)
    return statistics.median(samples)
