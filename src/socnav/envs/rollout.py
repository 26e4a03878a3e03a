"""Batched evaluation rollouts: N episodes of any policy with `predict`, episode k seeded with `seed + k`.

Each episode's seed is fixed by its index, so the world of every episode does not depend on how many environments
run at once, nor do the records of a policy that decides each environment alone. A policy whose decision reads the
batch (the safety layer with MC dropout: its masks come from one stream drawn across the batch, and torch's batched
float32 forward pass changes in the last digits with the batch shape) can play an episode differently with another
``n_envs``: compare such policies at the same ``n_envs``. The records hold the world's episode columns
(`EPISODE_COLUMNS`) and, by default, every metric's per-episode column (`socnav.sim.metrics.METRIC_RECORD_COLUMNS`);
`summarize` aggregates them with the metrics registry.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from typing import Any, Protocol, cast

import numpy as np
import pandas as pd

from socnav.config import ConfigLike, load_config
from socnav.envs.env import check_actions, check_env_count
from socnav.sim.metrics import DEFAULT_METRICS, METRIC_RECORD_COLUMNS, PV_PER, summarize_episodes
from socnav.sim.world import CrowdWorld

EPISODE_COLUMNS = (
    "episode", "seed", "outcome", "return", "length", "duration", "path_length", "time_to_goal", "min_gap",
    "intrusion_steps", "intrusion_events", "disturbance",
)


class RolloutInterrupted(KeyboardInterrupt):
    """Ctrl-C during `rollout_episodes`: a KeyboardInterrupt (code catching that still does) that also carries the
    records of the episodes finished before it, in the layout `rollout_episodes` returns (`records`), and how many
    episodes were asked (`asked`)."""

    def __init__(self, records: pd.DataFrame, asked: int) -> None:
        super().__init__(f"interrupted after {len(records):,} of {asked:,} episodes")
        self.records = records
        self.asked = asked


#: `rollout_episodes(progress=...)`: a callable ``progress(n)``, True (a progress bar), False (none) or None (a bar
#: when called from your own code in a terminal or a notebook; none inside socnav, whose callers show their own).
Progress = Callable[[int], None] | bool | None


class Policy(Protocol):
    def predict(self, observation: dict[str, np.ndarray], state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[np.ndarray, Any]: ...


class SensingPolicy(Policy, Protocol):
    """A policy that also reads each step's true (noise-free) observation, as a separate safety sensor does: a
    `socnav.safety.SafePolicy` with ``sensing: true``, whose `needs_true_observation` is then True."""

    @property
    def needs_true_observation(self) -> bool: ...

    def sense(self, true_observation: Mapping[str, np.ndarray]) -> None: ...


class StepObserver(Protocol):
    """Sees every step of a rollout, e.g. to record per-step uncertainties (`socnav.uncertainty.recording`)."""

    def on_step(self, observation: dict[str, np.ndarray], actions: np.ndarray, result: Any,
                episodes: np.ndarray) -> None:
        """`episodes[e]` is the episode environment e played this step (-1: none, its result is to be ignored).

        Called after the world stepped and before ended episodes are reset and announced, so the policy's record
        of this step (e.g. `SafePolicy.last_uncertainty`) is still the one of the action in `actions`."""

    def on_episode_start(self, envs: np.ndarray) -> None:
        """Environments `envs` start a new episode (called before their first observation is used)."""


def rollout_episodes(
    policy: Policy,
    config: ConfigLike,
    n_episodes: int,
    seed: int = 0,
    n_envs: int = 16,
    deterministic: bool = True,
    progress: Progress = None,
    observer: StepObserver | None = None,
    metrics: bool = True,
) -> pd.DataFrame:
    """Run `n_episodes` episodes (episode k from seed `seed + k`) and return one record per episode.

    The records' columns: `EPISODE_COLUMNS`, then with `metrics` (the world accumulating every metric of
    `socnav.sim.metrics` per step; it changes no other column) `METRIC_RECORD_COLUMNS`.

    `progress(n)` is called with the number of episodes finished at each step that finishes some; ``progress=True``
    shows a progress bar (tqdm, on stderr), False none, and None (the default) shows one when called from your own
    code with a terminal or in a notebook: a long rollout is never silent there, and socnav's own callers (the
    CLI, training, experiments) are left to show their own. Policies and
    observers with an `on_episode_start(envs)` method are told when environments start new episodes (stateful
    policies such as `socnav.safety.SafePolicy` keep per-environment windows). A policy whose
    `needs_true_observation` is True (a `SafePolicy` with `sensing: true`) is also given each step's noise-free
    observation through its `sense` method before `predict`; `predict` itself gets the (noisy) observation.

    :raises RolloutInterrupted: Ctrl-C (a KeyboardInterrupt); it carries the records of the episodes finished by
        then.
    """
    if n_episodes < 1:
        raise ValueError(f"n_episodes must be >= 1, got {n_episodes}")
    show = _show_progress(progress, sys._getframe(1).f_globals.get("__name__", ""))
    records: list[dict[str, Any]] = []
    with _progress_bar(n_episodes, show) as bar:
        try:
            _rollout(policy, config, n_episodes, seed, n_envs, deterministic, progress if callable(progress) else bar,
                     observer, metrics, records)
        except (KeyboardInterrupt, SystemError) as exc:
            if not is_interrupt(exc):
                raise
            raise RolloutInterrupted(_records_frame(records, metrics), n_episodes) from None
    return _records_frame(records, metrics)


def is_interrupt(exc: BaseException) -> bool:
    """Whether `exc` is a Ctrl-C: a KeyboardInterrupt, or what numba raises when one arrives while it loads a compiled
    function from its cache (a SystemError, "returned a result with an exception set", caused by the
    KeyboardInterrupt)."""
    seen: BaseException | None = exc
    while seen is not None:
        if isinstance(seen, KeyboardInterrupt):
            return True
        seen = seen.__cause__ or seen.__context__
    return False


def _records_frame(records: list[dict[str, Any]], metrics: bool) -> pd.DataFrame:
    """The records as `rollout_episodes` returns them: its columns, sorted by episode."""
    columns = [*EPISODE_COLUMNS, *(METRIC_RECORD_COLUMNS if metrics else ())]
    return pd.DataFrame.from_records(records, columns=columns).sort_values("episode", ignore_index=True)


def _show_progress(progress: Progress, caller: str) -> bool:
    """Whether `rollout_episodes` draws its own bar: when asked (True), and by default (None) for a caller outside
    socnav (whose own callers report progress their way, or run in worker processes) with a terminal or a
    notebook."""
    if progress is None:
        if caller == "socnav" or caller.startswith("socnav."):
            return False
        return _in_notebook() or sys.stderr.isatty()
    return progress is True


def _in_notebook() -> bool:
    """Whether this runs in a Jupyter kernel (no terminal, yet someone watches)."""
    shell = getattr(sys.modules.get("IPython"), "get_ipython", lambda: None)()
    return type(shell).__name__ == "ZMQInteractiveShell"


@contextmanager
def _progress_bar(total: int, show: bool) -> Iterator[Callable[[int], None] | None]:
    """A tqdm bar of `total` episodes while the block runs (yields its ``advance(n)``), or nothing (yields None)."""
    if not show:
        yield None
        return
    from tqdm.auto import tqdm  # a widget in a notebook, text on a terminal

    with tqdm(total=total, unit="episode", desc="episodes", dynamic_ncols=True) as bar:
        yield bar.update


def _rollout(policy: Policy, config: ConfigLike, n_episodes: int, seed: int, n_envs: int, deterministic: bool,
             progress: Callable[[int], None] | None, observer: StepObserver | None, metrics: bool,
             records: list[dict[str, Any]]) -> None:
    """The episodes of `rollout_episodes`, appended to `records` as each finishes (an interruption keeps the
    finished ones)."""
    env_config = load_config(config)
    n_envs = check_env_count(max(1, min(n_envs, n_episodes)), env_config)
    world = CrowdWorld(env_config, n_envs, metrics=metrics)
    running = np.arange(n_envs)  # episode index each environment is playing; -1 once there is none left
    for env in range(n_envs):
        world.seed(env, seed + env)
    world.reset()
    listeners = [x.on_episode_start for x in (policy, observer) if x is not None and hasattr(x, "on_episode_start")]
    sensor = cast(SensingPolicy, policy) if getattr(policy, "needs_true_observation", False) else None
    for listener in listeners:
        listener(np.arange(n_envs))
    next_episode = n_envs
    while len(records) < n_episodes:
        observation = world.observe()
        if sensor is not None:  # a separate safety sensor: only the safety layer reads the true state
            sensor.sense(world.observe(noisy=False))
        actions, _ = policy.predict(observation, deterministic=deterministic)
        actions = np.asarray(actions)
        result = world.step(check_actions(actions, n_envs))  # a NaN action: ActionError naming the environment
        if observer is not None:
            observer.on_step(observation, actions, result, running.copy())
        done = np.flatnonzero(result.terminated | result.truncated)
        finished = done[running[done] >= 0]
        for env in finished:
            summary = world.episode_summary(env, int(result.outcome[env]))
            records.append({"episode": int(running[env]), "seed": seed + int(running[env]), **summary})
            if next_episode < n_episodes:
                running[env] = next_episode
                world.seed(env, seed + next_episode)
                next_episode += 1
            else:
                running[env] = -1
        if len(done):
            world.reset(done)
            for listener in listeners:
                listener(done)
        if len(finished) and progress is not None:
            progress(len(finished))


def summarize(records: pd.DataFrame, pv_per: int = PV_PER,
              metrics: Sequence[str] = DEFAULT_METRICS) -> dict[str, float]:
    """Table metrics over the episodes of `records`: ``episodes`` and the registry's `metrics` (default: Goal %,
    Collision %, Time-out %, PV per `pv_per` episodes, return mean / std, mean time to goal; see
    `socnav.sim.metrics.summarize_episodes`)."""
    return summarize_episodes(records, metrics, pv_per)


def record_episode(
    policy: Policy, config: ConfigLike, seed: int = 0, deterministic: bool = True, max_frames: int = 2000
) -> tuple[list[np.ndarray], dict[str, Any]]:
    """Play one episode (seed `seed`, as episode 0 of `rollout_episodes`) and return its rgb frames and summary."""
    from socnav.envs.env import SocialNavEnv

    env = SocialNavEnv(config)
    observation, _ = env.reset(seed=seed)
    frames = [env.render_frame()]
    summary: dict[str, Any] = {}
    for _ in range(max_frames):
        action, _ = policy.predict(observation, deterministic=deterministic)
        observation, _, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            summary = info["episode"]
            frames.append(env.render_frame(caption=str(summary["outcome"])))
            break
        frames.append(env.render_frame())
    env.close()
    return frames, summary
