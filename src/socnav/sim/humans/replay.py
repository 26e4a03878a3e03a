"""Replayed humans (``humans.model: replay`` with ``scenario: replay``): pedestrians follow recorded trajectories and
do not react to anyone, the robot included (as in SocNavBench).

The recordings are read by `socnav.sim.humans.trajectories` (ETH/UCY text files, within bounds); `load_replay`
builds the flat arrays the world's kernels read, once per process and set of files (`ReplayScenes`).

A replayed episode (`ReplayScenes.plan`, drawn by the ``replay`` scenario from the episode's generator) picks a file,
a start step within it and the robot's path: a straight line through the centre of the file's bounding box (the
world's origin: every file is centred on it) at ``humans.replay.robot_distance``, in a direction drawn per
episode. `ReplayHumans` then moves each slot's pedestrian from recorded position to recorded position; pedestrians
that enter the scene take a free slot, those that leave free theirs (the slot becomes inactive padding).
"""

from __future__ import annotations

import functools
import math
import weakref
from dataclasses import dataclass
from typing import Any

import numba
import numpy as np

from socnav.sim.humans.base import Crowd

#: Files larger than this are refused from their size, before they are read (the ETH/UCY files are below 1 MB). A
#: file is parsed in blocks of ~1 MB: reading one costs about its size plus its rows (32 bytes each), docs/limits.md.
from socnav.sim.humans.trajectories import (
    MAX_FILE_BYTES,
    MAX_LINE_BYTES,
    MAX_LINES,
    MAX_PEDESTRIANS,
    MAX_SAMPLES,
    MAX_TOTAL_BYTES,
    Recording,
    TrajectoryFileError,
    check_positions,
    check_total_size,
    check_trajectory_file,
    count_positions,
    interpolate_track,
    interpolate_tracks,
    read_trajectories,
    short_list,
    track_steps,
)

#: the recordings' API is `socnav.sim.humans.trajectories`; re-exported here, where it was
__all__ = [
    "MAX_FILE_BYTES",
    "MAX_LINES",
    "MAX_LINE_BYTES",
    "MAX_PEDESTRIANS",
    "MAX_SAMPLES",
    "MAX_TOTAL_BYTES",
    "MAX_TRIES",
    "START_CLEARANCE",
    "Recording",
    "ReplayHumans",
    "ReplayScenes",
    "ReplayStart",
    "TrajectoryFileError",
    "build_scenes",
    "check_positions",
    "check_total_size",
    "check_trajectory_file",
    "count_positions",
    "interpolate_tracks",
    "load_replay",
    "read_scenes",
    "read_trajectories",
]


#: Attempts at drawing an episode whose robot start is clear of the pedestrians present then.
MAX_TRIES = 200


#: Metres between the robot's start and any pedestrian present at the episode's first step.
START_CLEARANCE = 1.0


@numba.njit(cache=True)
def _segment_distance(px, py, ax, ay, bx, by):
    """Distance from point p to the segment a-b."""
    dx, dy = bx - ax, by - ay
    length_sq = dx * dx + dy * dy
    s = 0.0
    if length_sq > 0.0:
        s = min(max(((px - ax) * dx + (py - ay) * dy) / length_sq, 0.0), 1.0)
    return math.hypot(px - ax - s * dx, py - ay - s * dy)


@dataclass(frozen=True)
class ReplayStart:
    """The scenario's plan of one replayed episode: where it starts in which file, the robot's path and the
    pedestrian in each agent slot at the start (-1: none; slot 0 is the robot)."""

    scenes: ReplayScenes
    scene: int
    step: int  # the scene's step at the episode's start
    start: np.ndarray  # (2,) robot start
    goal: np.ndarray  # (2,) robot goal
    pedestrians: np.ndarray  # (n_slots,) int64 global pedestrian index per slot
    positions: np.ndarray  # (n_slots, 2)
    goals: np.ndarray  # (n_slots, 2): each pedestrian's last recorded position


@dataclass(frozen=True)
class ReplayScenes:
    """The recorded pedestrians of one or more files on the env's time grid, as flat arrays for the kernels.

    Scene s (file s) holds pedestrians ``scene_lo[s] .. scene_hi[s] - 1``, sorted by first step (then by first
    appearance in the file); pedestrian p exists at scene steps ``first[p] .. first[p] + count[p] - 1`` at
    positions ``samples[offset[p] + k - first[p]]``. Positions are centred: each file's bounding-box centre
    (`centres`) is subtracted, so the world's origin is the centre of every scene.
    """

    files: tuple[str, ...]
    time_step: float
    centres: np.ndarray  # (S, 2) metres, in the file's coordinates
    half_sizes: np.ndarray  # (S, 2) half the bounding box
    scene_steps: np.ndarray  # (S,) steps from the file's first frame to its last, + 1
    scene_lo: np.ndarray  # (S,)
    scene_hi: np.ndarray  # (S,)
    ids: np.ndarray  # (P,) pedestrian ids as in the files
    first: np.ndarray  # (P,) int64
    count: np.ndarray  # (P,) int64
    offset: np.ndarray  # (P,) int64
    samples: np.ndarray  # (M, 2)

    @property
    def n_pedestrians(self) -> int:
        return len(self.first)

    def track(self, scene: int, pedestrian_id: float) -> tuple[int, np.ndarray]:
        """(first step, centred positions (n, 2)) of the pedestrian `pedestrian_id` of file `scene`."""
        lo, hi = int(self.scene_lo[scene]), int(self.scene_hi[scene])
        matches = np.flatnonzero(self.ids[lo:hi] == pedestrian_id)
        if matches.size == 0:
            raise KeyError(f"no pedestrian {pedestrian_id:g} in {self.files[scene]} (or it never meets a time step)")
        p = lo + int(matches[0])
        return int(self.first[p]), self.samples[self.offset[p]:self.offset[p] + self.count[p]]

    def present(self, scene: int, step: int) -> np.ndarray:
        """Global indices of the pedestrians of `scene` that exist at `step`, in the scene's order."""
        lo, hi = int(self.scene_lo[scene]), int(self.scene_hi[scene])
        first, count = self.first[lo:hi], self.count[lo:hi]
        return lo + np.flatnonzero((first <= step) & (step < first + count))

    def position(self, pedestrian: int, step: int) -> np.ndarray:
        return self.samples[self.offset[pedestrian] + step - self.first[pedestrian]]

    def last_position(self, pedestrian: int) -> np.ndarray:
        return self.samples[self.offset[pedestrian] + self.count[pedestrian] - 1]

    def plan(self, rng: np.random.Generator, n_humans: int, distance: float, horizon: int) -> ReplayStart:
        """Draw one episode from `rng`: a file (weighted by its length, so every recorded moment is equally likely),
        a start step leaving `horizon` steps of recording where the file is long enough, and the robot's direction
        through the scene's centre (start and goal `distance` apart), redrawn (at most `MAX_TRIES` times) until no
        pedestrian present at the start step is within `START_CLEARANCE` of the robot's start.

        With more than `n_humans` pedestrians present at the start, those closest to the robot's path (the segment
        from start to goal) take the slots.
        """
        weights = self.scene_steps / self.scene_steps.sum()
        for _ in range(MAX_TRIES):
            scene = int(rng.choice(len(weights), p=weights)) if len(weights) > 1 else 0
            latest = max(int(self.scene_steps[scene]) - 1 - horizon, 0)
            step = int(rng.integers(0, latest + 1))
            angle = rng.uniform(0.0, 2.0 * math.pi)
            direction = np.array((math.cos(angle), math.sin(angle)))
            start, goal = -0.5 * distance * direction, 0.5 * distance * direction
            present = self.present(scene, step)
            where = np.array([self.position(p, step) for p in present]).reshape(-1, 2)
            if not len(present) or np.hypot(*(where - start).T).min() >= START_CLEARANCE:
                break
        path_distance = np.array([_segment_distance(x, y, start[0], start[1], goal[0], goal[1]) for x, y in where])
        chosen = np.argsort(path_distance, kind="stable")[:n_humans]
        pedestrians = np.full(1 + n_humans, -1, dtype=np.int64)
        positions, goals = np.zeros((1 + n_humans, 2)), np.zeros((1 + n_humans, 2))
        for slot, k in enumerate(np.sort(chosen), start=1):  # slots in the scene's order
            pedestrians[slot] = present[k]
            positions[slot] = where[k]
            goals[slot] = self.last_position(present[k])
        return ReplayStart(scenes=self, scene=scene, step=step, start=start, goal=goal, pedestrians=pedestrians,
                           positions=positions, goals=goals)


def build_scenes(recordings: list[Recording], time_step: float, sample_rate: float) -> ReplayScenes:
    """`ReplayScenes` of `recordings` (one scene each) on the grid of `time_step` (`interpolate_tracks`).

    The positions are counted first (`MAX_SAMPLES`, from each pedestrian's first and last frame), then written
    straight into the one array the kernels read: the peak is that array (16 bytes a position) plus one track.
    """
    if not recordings:
        raise TrajectoryFileError("no trajectory files: set humans.replay.files")
    ratio = time_step * sample_rate  # recorded samples per env step
    per_scene = [track_steps(recording, ratio) for recording in recordings]
    total = sum(count for spans in per_scene for _, count in spans)
    if total > MAX_SAMPLES:
        raise TrajectoryFileError(
            f"trajectory files {short_list([r.path for r in recordings])} give {total:,} positions at time_step "
            f"{time_step:g} s; socnav keeps at most {MAX_SAMPLES:,} (fewer or shorter files, or a longer time_step)")
    centres: list[np.ndarray] = []
    half_sizes: list[np.ndarray] = []
    scene_steps: list[int] = []
    scene_lo: list[int] = []
    scene_hi: list[int] = []
    ids: list[float] = []
    first: list[int] = []
    count: list[int] = []
    samples = np.empty((total, 2))
    filled = 0
    for recording, spans in zip(recordings, per_scene, strict=True):
        everything = np.concatenate(recording.positions)
        low, high = everything.min(axis=0), everything.max(axis=0)
        del everything
        centre = (low + high) / 2.0
        centres.append(centre)
        half_sizes.append((high - low) / 2.0)
        kept = [(k0, n, index) for index, (k0, n) in enumerate(spans) if n]
        kept.sort(key=lambda item: item[0])  # stable: ties keep the order of first appearance
        scene_lo.append(len(first))
        for k0, n, index in kept:
            ids.append(recording.ids[index])
            first.append(k0)
            count.append(n)
            xy = interpolate_track(recording.samples[index], recording.positions[index], k0, n, ratio)
            np.subtract(xy, centre, out=samples[filled:filled + n])
            filled += n
        scene_hi.append(len(first))
        scene_steps.append(max((k0 + n for k0, n, _ in kept), default=1))
    count_array = np.asarray(count, dtype=np.int64)
    return ReplayScenes(
        files=tuple(r.path for r in recordings), time_step=float(time_step),
        centres=np.asarray(centres), half_sizes=np.asarray(half_sizes),
        scene_steps=np.asarray(scene_steps, dtype=np.int64), scene_lo=np.asarray(scene_lo, dtype=np.int64),
        scene_hi=np.asarray(scene_hi, dtype=np.int64), ids=np.asarray(ids, dtype=np.float64),
        first=np.asarray(first, dtype=np.int64), count=count_array,
        offset=np.r_[0, np.cumsum(count_array)[:-1]].astype(np.int64) if len(count) else np.zeros(0, np.int64),
        samples=samples,
    )


@functools.lru_cache(maxsize=8)
def read_scenes(files: tuple[str, ...], sample_rate: float, frame_step: int | None, time_step: float) -> ReplayScenes:
    """The `ReplayScenes` of trajectory files (`read_trajectories`, `build_scenes`), cached for the last 8 sets of
    arguments; `load_replay`, which keeps the scenes some world still uses, is the entry point.

    The files' sizes together are checked first (`MAX_TOTAL_BYTES`), then each file as it is read.
    """
    check_total_size(files)
    return build_scenes([read_trajectories(path, frame_step) for path in files], time_step, sample_rate)


#: The scenes some model still uses, by key: `load_replay` hands out the same object while one does, whatever
#: `read_scenes`'s cache has dropped meanwhile (the model's arrays and the scenario's plans must index the same scenes).
_LIVE: weakref.WeakValueDictionary[tuple, ReplayScenes] = weakref.WeakValueDictionary()


def load_replay(settings: Any, time_step: float) -> ReplayScenes:
    """The scenes of ``settings`` (a `socnav.config.ReplayConfig`: files, sample_rate, frame_step) at `time_step`,
    read once per process: the scenario and the model of every world of this config share one `ReplayScenes`."""
    if not settings.files:
        raise TrajectoryFileError("replayed humans need trajectory files: set humans.replay.files")
    key = (tuple(str(path) for path in settings.files), float(settings.sample_rate),
           None if settings.frame_step is None else int(settings.frame_step), float(time_step))
    scenes = _LIVE.get(key)
    if scenes is None:
        scenes = _LIVE[key] = read_scenes(*key)
    return scenes


@numba.njit(cache=True)
def _replay_velocities(positions, velocities, compute, slot_pedestrian, step, first, count, offset, samples,
                       time_step):
    """Each computed slot's velocity to its pedestrian's next recorded position (0 if it has none)."""
    out = velocities.copy()
    n_envs, n_agents = compute.shape
    for env in range(n_envs):
        k = step[env] + 1
        for agent in range(1, n_agents):
            p = slot_pedestrian[env, agent]
            if not compute[env, agent] or p < 0:
                continue
            i = k - first[p]
            if 0 <= i < count[p]:
                out[env, agent, 0] = (samples[offset[p] + i, 0] - positions[env, agent, 0]) / time_step
                out[env, agent, 1] = (samples[offset[p] + i, 1] - positions[env, agent, 1]) / time_step
            else:
                out[env, agent, 0] = 0.0
                out[env, agent, 1] = 0.0
    return out


@numba.njit(cache=True)
def _leave(active, velocities, slot_pedestrian, step, first, count):
    """Free the slots whose pedestrian has no recorded position at the next step; returns the freed slots."""
    n_envs, n_agents = active.shape
    left = np.zeros((n_envs, n_agents), dtype=np.bool_)
    for env in range(n_envs):
        k = step[env] + 1
        for agent in range(1, n_agents):
            p = slot_pedestrian[env, agent]
            if p >= 0 and not (first[p] <= k < first[p] + count[p]):
                slot_pedestrian[env, agent] = -1
                active[env, agent] = False
                velocities[env, agent, 0] = 0.0
                velocities[env, agent, 1] = 0.0
                left[env, agent] = True
    return left


@numba.njit(cache=True)
def _arrive(positions, velocities, goals, active, slot_pedestrian, step, next_arrival, scene, path,
            scene_hi, first, count, offset, samples, time_step):
    """After the move: advance every env's scene step, put its pedestrians exactly on their recorded positions, and
    give the pedestrians that appear at this step a free slot, closest to the robot's path first (those that find
    none are left out). Returns the slots that got a new pedestrian."""
    n_envs, n_agents = active.shape
    arrived = np.zeros((n_envs, n_agents), dtype=np.bool_)
    for env in range(n_envs):
        k = step[env] + 1
        step[env] = k
        for agent in range(1, n_agents):
            p = slot_pedestrian[env, agent]
            if p >= 0:
                j = offset[p] + k - first[p]
                positions[env, agent, 0] = samples[j, 0]
                positions[env, agent, 1] = samples[j, 1]
        lo = next_arrival[env]
        hi = lo
        end = scene_hi[scene[env]]
        while hi < end and first[hi] <= k:
            hi += 1
        next_arrival[env] = hi
        n_new = hi - lo
        if n_new == 0:
            continue
        distance = np.empty(n_new)
        for c in range(n_new):
            p = lo + c
            j = offset[p] + k - first[p]
            if k - first[p] >= count[p]:
                distance[c] = np.inf  # gone already (cannot happen for a pointer kept up to date)
            else:
                distance[c] = _segment_distance(samples[j, 0], samples[j, 1], path[env, 0], path[env, 1],
                                                path[env, 2], path[env, 3])
        order = np.argsort(distance, kind="mergesort")
        agent = 1
        for c in order:
            if not distance[c] < np.inf:
                break
            while agent < n_agents and slot_pedestrian[env, agent] >= 0:
                agent += 1
            if agent == n_agents:
                break  # every slot is taken: this pedestrian (and the farther ones) stay out of the episode
            p = lo + c
            j = offset[p] + k - first[p]
            slot_pedestrian[env, agent] = p
            active[env, agent] = True
            positions[env, agent, 0] = samples[j, 0]
            positions[env, agent, 1] = samples[j, 1]
            if k + 1 - first[p] < count[p]:  # its velocity over the coming step
                velocities[env, agent, 0] = (samples[j + 1, 0] - samples[j, 0]) / time_step
                velocities[env, agent, 1] = (samples[j + 1, 1] - samples[j, 1]) / time_step
            else:
                velocities[env, agent, 0] = 0.0
                velocities[env, agent, 1] = 0.0
            last = offset[p] + count[p] - 1
            goals[env, agent, 0] = samples[last, 0]
            goals[env, agent, 1] = samples[last, 1]
            arrived[env, agent] = True
    return arrived


class ReplayHumans:
    """`HumanModel` "replay": every human follows its recorded track, whatever the robot or the others do.

    None of the `Crowd`'s social inputs (attention, personal space, cooperation) changes a replayed human's path;
    personal space still scores the robot's intrusions in the reward, and the disturbance term is zero (a replayed
    human walks the same with and without the robot). Besides `velocities` (the velocity to the next recorded
    position), the world calls the `socnav.sim.humans.base.ScriptedHumans` hooks: `start_episode` at every reset,
    `before_move` (pedestrians whose track ends leave: their slot becomes inactive) and `after_move` (positions set
    exactly to the recorded ones, pedestrians whose track starts enter a free slot).
    """

    name = "replay"
    interaction_range = 0.0  # a replayed human never notices the robot
    arrival_distance = 0.0

    def __init__(self, scenes: ReplayScenes, time_step: float):
        self.scenes = scenes
        self.time_step = float(time_step)
        self.attach(0, 1)

    @classmethod
    def from_config(cls, config: Any) -> ReplayHumans:
        return cls(load_replay(config.humans.replay, config.time_step), config.time_step)

    def attach(self, n_envs: int, n_slots: int) -> None:
        """Allocate the per-environment state of a world of `n_envs` environments with `n_slots` agent slots."""
        self.scene = np.zeros(n_envs, dtype=np.int64)
        self.step = np.zeros(n_envs, dtype=np.int64)  # the scene's step now
        self.next_arrival = np.zeros(n_envs, dtype=np.int64)  # first pedestrian (global index) yet to appear
        self.path = np.zeros((n_envs, 4))  # the robot's start and goal
        self.slot_pedestrian = np.full((n_envs, n_slots), -1, dtype=np.int64)

    def start_episode(self, env: int, plan: ReplayStart, positions: np.ndarray, velocities: np.ndarray,
                      goals: np.ndarray, active: np.ndarray) -> None:
        """Begin environment `env`'s episode as `plan` says; writes its humans' state into the world's arrays."""
        scenes = self.scenes
        if not isinstance(plan, ReplayStart) or plan.scenes is not scenes:
            raise ValueError("replayed humans start from the replay scenario's plan of the same trajectory files")
        k = plan.step
        self.scene[env], self.step[env] = plan.scene, k
        self.path[env] = (*plan.start, *plan.goal)
        lo, hi = int(scenes.scene_lo[plan.scene]), int(scenes.scene_hi[plan.scene])
        self.next_arrival[env] = lo + int(np.searchsorted(scenes.first[lo:hi], k, side="right"))
        self.slot_pedestrian[env] = plan.pedestrians
        for slot, p in enumerate(plan.pedestrians):
            if p < 0:
                continue
            active[env, slot] = True
            positions[env, slot] = plan.positions[slot]
            goals[env, slot] = plan.goals[slot]
            # "the velocity of the last step": backwards where the track goes back that far, else forwards
            i = k - scenes.first[p]
            if i > 0:
                velocities[env, slot] = (scenes.position(p, k) - scenes.position(p, k - 1)) / self.time_step
            elif i + 1 < scenes.count[p]:
                velocities[env, slot] = (scenes.position(p, k + 1) - scenes.position(p, k)) / self.time_step
            else:
                velocities[env, slot] = 0.0

    def velocities(self, crowd: Crowd, compute: np.ndarray) -> np.ndarray:
        s = self.scenes
        return _replay_velocities(crowd.positions, crowd.velocities, compute, self.slot_pedestrian, self.step,
                                  s.first, s.count, s.offset, s.samples, self.time_step)

    def before_move(self, active: np.ndarray, velocities: np.ndarray) -> np.ndarray:
        """Pedestrians whose track ends before the next step leave now; returns the (E, N) slots they freed."""
        return _leave(active, velocities, self.slot_pedestrian, self.step, self.scenes.first, self.scenes.count)

    def after_move(self, positions: np.ndarray, velocities: np.ndarray, goals: np.ndarray,
                   active: np.ndarray) -> np.ndarray:
        """Advance to the next step: recorded positions, arrivals; returns the (E, N) slots that got a pedestrian."""
        s = self.scenes
        return _arrive(positions, velocities, goals, active, self.slot_pedestrian, self.step, self.next_arrival,
                       self.scene, self.path, s.scene_hi, s.first, s.count, s.offset, s.samples, self.time_step)

