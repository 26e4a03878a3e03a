"""`SafeNavigator`: the deployable safe navigator — observation, policy, MC-dropout, safety rule and fallback.
Plain arrays in (the robot's state and its tracked humans), a command ``(v, dtheta)`` out; no torch anywhere.

One decision:

1. the observation, built by the environment's own kernel (`socnav.sim.observation.observe_robot`);
2. ONE onnxruntime call on ``1 + K`` rows: row 0 with all-ones keep masks (the deterministic action the policy
   executes), rows 1..K with MC-dropout masks drawn from a `DropoutStream` (the uncertainty samples);
3. the safety layer's own parts: the uncertainty window (`WindowedUncertainty`), the nearest human and the
   collision-probability rule (`socnav.safety.rule`: eq. (10), or the ablation the thresholds' ``conditions``
   name, exactly as `socnav.safety.SafePolicy` applies it) and, where it fires (or fired within the last
   ``hold_steps`` steps), the cautious ORCA controller (`CautiousController`) in place of the policy — what
   `socnav.safety.SafePolicy` does for one robot (tested step for step against it), without its batch bookkeeping;
4. the action turned into ``(v, dtheta)`` by the simulator's own command kernel.

No NaN reaches a command: the inputs are checked (:class:`InputError`), and should the network's outputs still not
be finite, the policy's action is not used: the cautious controller acts, or the robot stops
(:attr:`Decision.fault`).

The humans handed to :meth:`SafeNavigator.act` are the robot's tracked state: the policy, the rule's proximity
terms and the fallback all read them (the runtime counterpart of the safety layer's ``perceived`` sensing; a
thresholds file's ``sensing`` field therefore changes nothing here).

Walls (a navigator exported from a world with walls, or given a map at load): the cautious fallback keeps off the
map's walls, planning in the map frame from the robot's ``pose`` (x, y, yaw), which :meth:`SafeNavigator.act` takes
(default: the robot's own position and heading, its world frame then being the map frame), and no command steps onto
a wall: it stands still instead (`Decision.wall_stop`, `socnav.safety.wall_stop`). A policy trained with a
range scan reads the robot's ``scan`` (its ranges, as a sensor_msgs/LaserScan gives them), which ``act`` then needs.

A route (a policy trained with ``planner.observe``, file format 5): the navigator plans the robot's shortest path on
the map from its pose to its goal, as the simulator does (`socnav.sim.planning`), and the policy observes the goal
along that path (`socnav.sim.route.observed_goals`); or it follows a path it is given (``act(..., path=...)``, e.g.
a nav_msgs/Path from nav2's planner): its pure-pursuit subgoal instead of its own. The cautious fallback acts on
the same observation, as the simulator's safety layer does (`socnav.safety.SafePolicy`): it heads for the subgoal,
and a fallback at rest faces it rather than a goal behind a wall. `Decision.subgoal` says where the policy was
pointed.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from socnav.config import short_repr
from socnav.runtime.format import MAX_K
from socnav.runtime.network import DropoutStream, ExportedPolicy, MCBatch, Uniforms, keep_from_uniforms
from socnav.safety.cautious import CautiousController
from socnav.safety.rule import (
    RuleConditions,
    Thresholds,
    held_fallback,
    nearest_human,
    rule_conditions,
)
from socnav.safety.triggers import RuleTrigger, TriggerInputs, TriggerSpec, load_safety, make_trigger
from socnav.safety.wall_stop import WallStop
from socnav.sim.maps import validate_polygons
from socnav.sim.observation import observe_robot, robot_command
from socnav.sim.planning import PathFollower, planner_for
from socnav.sim.route import observed_goals, subgoal_on_path, validate_path
from socnav.sim.walls import POSE_KEY, SCAN_KEY
from socnav.uncertainty.stats import Uncertainty
from socnav.uncertainty.window import WindowedUncertainty

__all__ = ["NON_FINITE_OBSERVATION", "NON_FINITE_OUTPUT", "STOPPED", "Decision", "HumansState", "InputError",
           "RobotState", "SafeNavigator"]

#: `Decision.fault` when the network's outputs (or the uncertainty computed from them) are not finite.
NON_FINITE_OUTPUT = "non-finite network output"
#: `Decision.fault` when the observation handed to `SafeNavigator.act_observation` is not finite (the robot stops).
NON_FINITE_OBSERVATION = "non-finite observation"
#: Appended to `Decision.fault` when no trustworthy finite command exists: the robot is told to stop, (0, 0).
STOPPED = "stopped: no finite command"
#: The environment's action for the command (0, 0): speed v_pref (a0 + 1) / 2 = 0, no turn.
_STOP_ACTION = np.array([-1.0, 0.0], dtype=np.float32)


class InputError(ValueError):
    """A robot or human state that the navigator cannot act on (wrong shape, NaN / inf, impossible value)."""


def _shown(value: Any, limit: int = 80) -> str:
    """A value for a one-line message: its repr, shortened, on one line (NumPy prints arrays over several)."""
    return " ".join(short_repr(value, limit).split())


def _real_array(owner: str, name: str, value: Any) -> np.ndarray:
    """``value`` as a float64 array, refused unless it holds real numbers (int or float): NumPy would turn text
    (``"1.5"``) into a number, and a complex array into its real part, without a word."""
    try:
        array = value if isinstance(value, np.ndarray) else np.asarray(value)
    except (TypeError, ValueError) as exc:  # e.g. ragged nested lists
        raise InputError(f"{owner}.{name} must be numeric (int or float numbers), got {_shown(value)} "
                         f"({exc})") from None
    if array.dtype.kind not in "iuf":
        what = {"b": "booleans", "c": "complex numbers", "U": "text", "S": "bytes"}.get(array.dtype.kind,
                                                                                      f"{array.dtype} values")
        raise InputError(f"{owner}.{name} must be numeric (int or float numbers), got {what}: "
                         f"{_shown(value)}")
    return array.astype(np.float64, copy=False)


def _vector(owner: str, name: str, value: Any, size: int) -> np.ndarray:
    array = _real_array(owner, name, value)
    if array.shape != (size,):
        raise InputError(f"{owner}.{name} must have shape ({size},), got {array.shape}")
    if not _finite(array):
        raise InputError(f"{owner}.{name} must be finite, got {array.tolist()}")
    return array


def _finite(array: np.ndarray) -> bool:
    """Every element finite. One cheap test first (a NaN / inf anywhere makes the sum of squares NaN / inf); the
    exact element-wise test only where that sum is not finite (a bad value, or an overflow of huge values)."""
    return math.isfinite(np.vdot(array, array)) or bool(np.isfinite(array).all())


def _scalar(owner: str, name: str, value: Any, minimum: float = -math.inf, strict: bool = False,
            maximum: float = math.inf) -> float:
    """A finite real number in [minimum, maximum] (``strict``: above ``minimum``). An int, a float, or a NumPy
    integer / float scalar (0-d array); a bool, text, a complex number or a sequence is refused."""
    if type(value) is float or type(value) is int:  # the common case, without NumPy's per-call overhead
        try:
            number = float(value)
        except OverflowError:  # an int beyond float's range
            number = math.nan
    elif isinstance(value, (bool, np.bool_, str, bytes, complex, np.complexfloating)):
        raise InputError(f"{owner}.{name} must be a finite number (a real int or float), got "
                         f"{type(value).__name__} {_shown(value, 60)}")
    else:
        array = np.asarray(value) if isinstance(value, (np.generic, np.ndarray)) else None
        if array is None or array.ndim != 0 or array.dtype.kind not in "iuf":
            raise InputError(f"{owner}.{name} must be a finite number (a real int or float), got "
                             f"{type(value).__name__} {_shown(value, 60)}")
        number = float(array)
    if not math.isfinite(number):
        raise InputError(f"{owner}.{name} must be a finite number, got {value!r}")
    below = number < minimum or (strict and number == minimum)
    if below or number > maximum:
        low = f"{'>' if strict else '>='} {minimum}"
        allowed = low if maximum == math.inf else f"{low} and <= {maximum}"
        raise InputError(f"{owner}.{name} must be {allowed}, got {number}")
    return number


def _ranges(scan: Any, beams: int, max_range: float) -> np.ndarray:
    """A range scan of ``beams`` ranges as the simulator reads them, in [0, max_range]: REP 117's readings mapped,
    +inf (no return) and anything beyond the range to ``max_range``, -inf (too close to measure) to 0. NaN (an
    erroneous reading) and negative finite values are refused: what stands in for them is the caller's call."""
    array = _real_array("scan", "ranges", scan)
    if array.shape != (beams,):
        raise InputError(f"scan must have shape ({beams},) (the beams the policy was trained with), got {array.shape}")
    if np.isnan(array).any():
        raise InputError(f"scan is NaN at beams {np.flatnonzero(np.isnan(array)).tolist()[:10]} (erroneous readings)")
    negative = np.flatnonzero((array < 0.0) & ~np.isneginf(array))
    if negative.size:
        raise InputError(f"scan ranges must be >= 0 (metres), got {array[negative[0]]} at beams "
                         f"{negative.tolist()[:10]}")
    return np.clip(np.where(np.isneginf(array), 0.0, array), 0.0, max_range)


@dataclass(frozen=True)
class RobotState:
    """The robot's state in any fixed world frame (metres, seconds, radians).

    :param position: (2,) position. :param velocity: (2,) current velocity. :param heading: yaw (rad).
    :param goal: (2,) goal position. :param v_pref: preferred (maximum) speed, > 0 (and at most the navigator's
        env config allows: its ``preferred_speed`` range, what the policy was trained with).
    :param radius: body radius, >= 0.
    """

    position: Any
    velocity: Any
    heading: float
    goal: Any
    v_pref: float
    radius: float

    @classmethod
    def parse(cls, robot: RobotState | Mapping[str, Any], max_speed: float = math.inf) -> RobotState:
        """A validated copy with float64 arrays; :class:`InputError` names the bad field and the allowed values.
        ``max_speed``: the largest ``v_pref`` accepted."""
        if not isinstance(robot, (Mapping, RobotState)):
            raise InputError(f"robot must be a RobotState or a mapping of its fields, got {type(robot).__name__}")
        fields = robot if isinstance(robot, Mapping) else robot.__dict__
        missing = {"position", "velocity", "heading", "goal", "v_pref", "radius"} - fields.keys()
        if missing:
            raise InputError(f"robot state lacks {sorted(missing)}")
        return cls(
            position=_vector("robot", "position", fields["position"], 2),
            velocity=_vector("robot", "velocity", fields["velocity"], 2),
            heading=_scalar("robot", "heading", fields["heading"]),
            goal=_vector("robot", "goal", fields["goal"], 2),
            v_pref=_scalar("robot", "v_pref", fields["v_pref"], minimum=0.0, strict=True, maximum=max_speed),
            radius=_scalar("robot", "radius", fields["radius"], minimum=0.0),
        )


@dataclass(frozen=True)
class HumansState:
    """The tracked humans, same world frame: ``positions`` (n, 2), ``velocities`` (n, 2), ``radii`` (n,); n >= 0."""

    positions: Any = field(default_factory=lambda: np.zeros((0, 2)))
    velocities: Any = field(default_factory=lambda: np.zeros((0, 2)))
    radii: Any = field(default_factory=lambda: np.zeros(0))

    @classmethod
    def parse(cls, humans: HumansState | Mapping[str, Any] | None) -> HumansState:
        """A validated copy with float64 arrays; :class:`InputError` says which array and row is wrong."""
        if humans is None:
            return cls()
        if not isinstance(humans, (Mapping, HumansState)):
            raise InputError(f"humans must be a HumansState, a mapping of its fields or None, got "
                             f"{type(humans).__name__}")
        fields = humans if isinstance(humans, Mapping) else humans.__dict__
        unknown = fields.keys() - {"positions", "velocities", "radii"}
        if unknown:
            raise InputError(f"unknown human fields {sorted(unknown)}; allowed: positions, velocities, radii")
        arrays = {}
        for name, width in (("positions", 2), ("velocities", 2), ("radii", 0)):
            array = _real_array("humans", name, fields.get(name, ()))
            if array.size == 0:
                array = array.reshape((0, width) if width else (0,))
            expected = f"(n, {width})" if width else "(n,)"
            if array.ndim != (2 if width else 1) or (width and array.shape[1] != width):
                raise InputError(f"humans.{name} must have shape {expected}, got {array.shape}")
            if not _finite(array):
                bad = ~np.isfinite(array).all(axis=tuple(range(1, array.ndim)))
                raise InputError(f"humans.{name} is not finite in rows {np.flatnonzero(bad).tolist()}")
            arrays[name] = array
        positions, velocities, radii = arrays["positions"], arrays["velocities"], arrays["radii"]
        if not len(positions) == len(velocities) == len(radii):
            counts = {name: len(array) for name, array in arrays.items()}
            raise InputError(f"humans.positions, velocities and radii must have one row per human, got {counts}")
        if len(radii) and radii.min() < 0.0:
            raise InputError(f"humans.radii must be >= 0, got {radii.tolist()}")
        return cls(positions, velocities, radii)


@dataclass(frozen=True)
class Decision:
    """What the navigator decided for one control step.

    :param speed: commanded speed ``v`` (m/s, in [0, v_pref]). :param turn: heading change ``dtheta`` (rad) over
        the next control step. :param action: the normalised action in [-1, 1]^2 (the environment's action).
    :param fallback: the cautious ORCA controller acted (the collision rule fired, or fired within the last
        ``thresholds.hold_steps`` steps).
    :param uncertainty: this step's MC-dropout estimate (batch of one; ``mean_action`` is the sample mean).
    :param windowed: the windowed values the rule read: ``u_ep_speed``, ``u_ep_heading``, ``u_al_speed``,
        ``u_al_heading``, ``u_feat``. :param conditions: the rule's conditions (``c_ep``, ... as (1,) arrays).
    :param observation: the observation the network saw (batch of one).
    :param subgoal: for a policy that observes its route, the subgoal its observed goal points at (map frame, (2,));
        None otherwise.
    :param wall_stop: the step would have brought the robot onto a wall of the navigator's map, so it stands still
        (speed 0, the turn kept; `socnav.safety.wall_stop`), as the simulator's `socnav.safety.SafePolicy` does.
    :param fault: None when the network's output was usable. Otherwise why it was not (:data:`NON_FINITE_OUTPUT`:
        the network gave NaN / inf): the policy's action is then never used; the cautious controller acts
        (``fallback`` True) if its command is finite, else the robot stops (command ``(0, 0)``, ``fallback`` False,
        :data:`STOPPED` appended to the fault). The uncertainty window is not fed that step (``windowed`` holds
        NaN) and the fallback is held as if the rule had fired. A non-finite observation (only
        :meth:`SafeNavigator.act_observation` takes one) stops the robot: :data:`NON_FINITE_OBSERVATION`.
    """

    speed: float
    turn: float
    action: np.ndarray
    fallback: bool
    uncertainty: Uncertainty
    windowed: dict[str, float]
    conditions: RuleConditions
    observation: dict[str, np.ndarray]
    fault: str | None = None
    subgoal: np.ndarray | None = None
    wall_stop: bool = False

    @property
    def command(self) -> tuple[float, float]:
        """``(v, dtheta)``."""
        return self.speed, self.turn


class SafeNavigator:
    """Decide ``(v, dtheta)`` from the robot's state and the tracked humans with the exported policy, MC-dropout
    uncertainty, the collision-probability rule and the cautious ORCA fallback.

    Keeps the episode's state (uncertainty window, previous nearest gap): call :meth:`reset` at the start of every
    new navigation task. Build it with :meth:`load`.

    :param network: the exported policy network (`ExportedPolicy.load`).
    :param thresholds: safety thresholds (None: the file's; else a preset name, a `socnav calibrate` file, a
        mapping or a `Thresholds`).
    :param k: MC-dropout samples per decision (None: the file's K).
    :param uniforms: the dropout-uniform stream (None: ``DropoutStream(seed)``).
    :param seed: seed of the default stream (None: fresh entropy).
    :param walls: the map the cautious fallback keeps off: polygons of (x, y) vertices in the map frame, RVO2's
        convention (counter-clockwise: solid; clockwise: encloses free space; two vertices: a wall segment), as
        the ``obstacles`` of an env config; None: the file's (the walls of the world it was exported from, or
        none); an empty list: no walls.
    :raises ValueError: invalid ``walls`` (naming the polygon) or ``k``.
    """

    def __init__(self, network: ExportedPolicy, thresholds: Thresholds | str | Path | Mapping[str, Any] | None = None,
                 k: int | None = None, uniforms: Uniforms | None = None, seed: int | None = None, *,
                 walls: Sequence[Any] | None = None) -> None:
        record = network.record  # validated at load: env config, thresholds, window, radius scale
        self.network = network
        self.config = record.env_config
        decision = self.file_decision(record) if thresholds is None else load_safety(thresholds)
        #: the rule's thresholds, or a score trigger's spec (`socnav.safety.triggers`): what decides the hand-over
        self.thresholds: Thresholds | TriggerSpec = decision
        self.trigger = make_trigger(decision)
        self.trigger.allocate(1)
        # the rule's conditions are reported with every decision; a score trigger is shown beside the paper's rule
        self._rule = decision if isinstance(decision, Thresholds) else Thresholds.create(
            record.safety.thresholds.model_dump(), sensing=decision.sensing)
        if k is None:
            self.k = network.k
        elif isinstance(k, (bool, np.bool_)) or not isinstance(k, (int, np.integer)) or not 2 <= k <= MAX_K:
            raise ValueError(f"k (MC-dropout samples per decision) must be an integer in [2, {MAX_K}], got {k!r}")
        else:
            self.k = int(k)
        self.uniforms = DropoutStream(seed) if uniforms is None else uniforms
        self._window = WindowedUncertainty(1, window=record.safety.window)
        #: whether the policy observes its route (``planner.observe``): `act` plans it, or follows a given path
        self.observes_route = bool(self.config.planner.observe)
        self.walls: list[np.ndarray] | None = None
        self.route: PathFollower | None = None
        self._use_walls(network.walls if walls is None else validate_polygons(walls, name="walls"))
        # v_pref above the trained range would give the policy an observation it never saw (and faster commands)
        self.max_speed = float(self.config.preferred_speed[1])
        self._previous_gap = np.full(1, np.nan)  # d(t-1) of this episode; NaN: none yet (c_ap holds)
        self._hold_left = np.zeros(1, dtype=np.int64)  # held fallback steps still owed (thresholds.hold_steps)
        self._batches: dict[tuple[int, int, bool], MCBatch] = {}  # per (K, human rows, any human)
        self._warm_up()

    def _use_walls(self, polygons: list[np.ndarray] | None) -> None:
        """Walls (validated; None or empty: none) for the fallback and for a route-observing policy's path."""
        #: the walls the fallback keeps off (polygons (k, 2), map frame), None without walls
        self.walls = polygons or None
        self.cautious = CautiousController(self.config, radius_scale=self.network.record.safety.radius_scale,
                                           walls=polygons or [])
        #: stands the robot still rather than step onto a wall (`socnav.safety.wall_stop`), None without walls
        self.wall_stop = (WallStop(polygons, self.config.time_step, self.config.max_heading_change) if polygons
                          else None)
        planner = self.config.planner
        #: the robot's own path on the map (a route-observing policy among walls), else None
        self.route = None
        if self.observes_route and polygons:
            self.route = PathFollower(planner_for(polygons, self.config.robot_radius + planner.margin), 1,
                                      planner.lookahead, planner.replan_distance,
                                      direct_clearance=self.config.robot_radius)

    def set_walls(self, walls: Sequence[Any]) -> None:
        """Replace the map (e.g. a nav_msgs/OccupancyGrid that arrived, as polygons in the map frame; an empty
        list: no walls): the fallback keeps off these walls and a route-observing policy's path is planned on them
        from the next decision; the episode's state (uncertainty window, held fallback) is kept.

        :raises ValueError: invalid ``walls`` (naming the polygon); the navigator's map is then unchanged."""
        polygons = validate_polygons(walls, name="walls")
        self._use_walls(polygons)
        if self.walls is not None:
            self.cautious.predict(observe_robot(np.zeros(2), np.zeros(2), 0.0, np.ones(2), 1.0, 0.3,
                                                np.full((1, 2), 2.0), np.zeros((1, 2)), np.full(1, 0.3),
                                                self.network.max_humans, pose=np.zeros(3)))

    @staticmethod
    def file_decision(record: Any) -> Thresholds | TriggerSpec:
        """What the navigator file says decides the hand-over: its score trigger (a risk model's embedded weights
        made loadable) or the rule's thresholds."""
        trigger = record.safety.trigger
        if trigger is None:
            return record.safety.thresholds
        model = None
        if trigger.risk_model is not None:
            import base64

            from socnav.safety.risk_model import embed_risk_model

            model = embed_risk_model(base64.b64decode(trigger.risk_model, validate=True))
        return TriggerSpec.create(trigger=trigger.trigger, params=trigger.params, threshold=trigger.threshold,
                                  sensing=trigger.sensing, hold_steps=trigger.hold_steps, model=model)

    def _warm_up(self) -> None:
        """Compile (or load) the numba kernels and prepare the onnxruntime session now, not at the first decision:
        the first fallback would otherwise stall the control loop. Touches neither the episode state nor the
        dropout stream."""
        scan = self.network.scan
        observation = observe_robot(np.zeros(2), np.zeros(2), 0.0, np.ones(2), 1.0, 0.3, np.full((1, 2), 2.0),
                                    np.zeros((1, 2)), np.full(1, 0.3), self.network.max_humans,
                                    pose=None if self.walls is None else np.zeros(3),
                                    scan=None if scan is None else np.full(scan.beams, scan.range))
        output = self.network.run(*self.network.trim(observation)[:3], scan=self.network.scan_of(observation))
        self.cautious.predict(observation)
        robot_command(np.zeros(2), 1.0, self.config.max_heading_change)
        h, mean = np.zeros((1 + self.k, output.h.shape[1]), np.float32), np.zeros((1 + self.k, 2), np.float32)
        estimate = self.network.summarise(h[1:, None], mean[1:, None], mean[1:, None])  # a decision's layouts
        WindowedUncertainty(1, window=1).update(estimate)
        nearest_human(observation)
        keep_from_uniforms(np.ones(1, np.float32), self.network.p_test, np.ones(1, np.float32))

    @classmethod
    def load(cls, path: str | Path, thresholds: Thresholds | str | Path | Mapping[str, Any] | None = None,
             k: int | None = None, seed: int | None = None, uniforms: Uniforms | None = None,
             threads: int = 1, *, walls: Sequence[Any] | None = None) -> SafeNavigator:
        """Open a navigator file written by ``socnav export`` (onnxruntime with ``threads`` intra-op threads);
        ``walls``: the fallback's map, as for the constructor (None: the file's).

        :raises socnav.runtime.NavigatorLoadError: a missing, unreadable, non-ONNX, foreign, corrupted (checksum) or
            incompatible file, invalid metadata, or a graph that fails or gives non-finite outputs on a test call:
            every problem of the file shows here, none at the first :meth:`act`.
        :raises socnav.safety.ThresholdsError: invalid ``thresholds``.
        :raises ValueError: ``k`` outside [2, :data:`~socnav.runtime.format.MAX_K`], invalid ``walls``.
        """
        return cls(ExportedPolicy.load(path, threads=threads), thresholds=thresholds, k=k, uniforms=uniforms,
                   seed=seed, walls=walls)

    @property
    def max_humans(self) -> int:
        """Human rows of the observation; with more tracked humans the closest ones are kept."""
        return self.network.max_humans

    def reset(self) -> None:
        """Start a new episode: empty the uncertainty window, forget the previous nearest-human gap, end a hold."""
        self._window.reset()
        self._previous_gap[:] = np.nan
        self._hold_left[:] = 0
        self.trigger.reset(np.zeros(1, dtype=np.int64))
        if self.route is not None:
            self.route.forget(slice(None))

    @property
    def scan_beams(self) -> int | None:
        """The beams of the range scan the policy reads (``act``'s ``scan``), None if it reads none."""
        return None if self.network.scan is None else self.network.scan.beams

    def act(self, robot: RobotState | Mapping[str, Any],
            humans: HumansState | Mapping[str, Any] | None = None, *, scan: Any = None,
            pose: Any = None, path: Any = None) -> Decision:
        """One control decision.

        :param robot: a :class:`RobotState` or a mapping with its fields (position, velocity, heading, goal,
            v_pref, radius), world frame.
        :param humans: a :class:`HumansState` or a mapping (positions (n, 2), velocities (n, 2), radii (n,)), or
            None for nobody around. With more than :attr:`max_humans` humans, the ``max_humans`` closest (by gap
            to the robot) are kept — the simulator's own rule; the others are ignored by the policy, the rule
            and the fallback alike. In a world with walls, the humans the robot sees (as the simulator's
            occlusion leaves out those behind walls).
        :param scan: the range scan, :attr:`scan_beams` ranges in metres from -fov/2 counter-clockwise about the
            heading (a sensor_msgs/LaserScan's ``ranges``), as the env config's ``scan`` describes it: needed by a
            policy trained with one, ignored otherwise. +inf and ranges beyond the scan's range read as that
            range, -inf as 0 (REP 117); NaN is refused.
        :param pose: the robot's pose in the map frame, (x, y, yaw), for the fallback's walls; None: the robot's
            ``position`` and ``heading`` (its world frame is the map frame). Ignored without walls.
        :param path: for a policy that observes its route: the path to follow, (x, y) waypoints in the map frame
            (a nav_msgs/Path's poses), instead of the one the navigator plans itself; None: its own (or, without
            walls, the goal itself). Refused for a policy that does not observe a route.
        :return: the decision; its command is always finite (see :attr:`Decision.fault` for what happens when
            the network's output is not).
        :raises InputError: a wrong shape or type (text, bool, complex), a NaN / inf, ``v_pref <= 0`` or above
            the env config's largest preferred speed, a negative radius, a missing or invalid scan, or states so
            large that the observation overflows float32 (nothing reaches onnxruntime).
        """
        robot = RobotState.parse(robot, max_speed=self.max_speed)
        humans = HumansState.parse(humans)
        ranges = None
        if self.network.scan is not None:
            if scan is None:
                raise InputError(f"scan: this navigator's policy reads a range scan of {self.network.scan.beams} "
                                 f"beams (range {self.network.scan.range:g} m, fov {self.network.scan.fov:g} "
                                 "degrees); pass act(..., scan=ranges)")
            ranges = _ranges(scan, self.network.scan.beams, self.network.scan.range)
        map_pose = None
        if self.walls is not None or path is not None:
            map_pose = (np.array([*robot.position, robot.heading]) if pose is None
                        else _vector("act", "pose (x, y, yaw)", pose, 3))
        given_path = None
        if path is not None:
            if not self.observes_route:
                raise InputError("path: this navigator's policy does not observe a route (its env config's "
                                 "planner.observe is false); allowed: None")
            try:
                given_path = validate_path(path, name="path")
            except ValueError as exc:
                raise InputError(str(exc)) from None

        def observe(goal: np.ndarray) -> dict[str, np.ndarray]:
            observed = observe_robot(robot.position, robot.velocity, robot.heading, goal, robot.v_pref,
                                     robot.radius, humans.positions, humans.velocities, humans.radii,
                                     self.network.max_humans, pose=map_pose if self.walls is not None else None,
                                     scan=ranges)
            for key, value in observed.items():  # finite float64 states can still overflow float32
                if not _finite(value):
                    raise InputError(f"the robot's and humans' states give a non-finite observation ({key}): "
                                     "positions or velocities beyond float32's range (about 3.4e38)")
            return observed

        observation = observe(robot.goal)
        if self.route is None and given_path is None:
            return self.act_observation(observation, v_pref=robot.v_pref)
        assert map_pose is not None
        route_goal, subgoal = self._route_goal(robot, map_pose, pose is None, given_path)
        decision = self.act_observation(observe(route_goal), v_pref=robot.v_pref)
        return dataclasses.replace(decision, subgoal=subgoal)

    def _route_goal(self, robot: RobotState, pose: np.ndarray, same_frame: bool,
                    path: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """The goal the route-observing policy sees (world frame) and its subgoal (map frame): the subgoal of the
        given `path`, or of the navigator's own path from `pose` to the goal."""
        # The robot's world frame and the map frame differ by the rotation yaw - heading about the robot.
        angle = float(pose[2]) - robot.heading
        rotation = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
        position = pose[:2].copy()
        goal = robot.goal if same_frame else rotation @ (robot.goal - robot.position) + position
        if path is not None:
            subgoal = subgoal_on_path(path, position, self.config.planner.lookahead)
        else:
            assert self.route is not None
            subgoal = self.route.update(position[None], goal[None])[0][0].copy()
        seen = observed_goals(position[None], subgoal[None], goal[None])[0]
        return (seen if same_frame else rotation.T @ (seen - position) + robot.position), subgoal

    def act_observation(self, observation: Mapping[str, np.ndarray], v_pref: float | None = None) -> Decision:
        """One decision from an observation already in the environment's layout (batch of one, float32), e.g.
        one from :func:`socnav.sim.observation.observe_robot`; unlike :meth:`act` its input is not checked, but
        its command is finite all the same (:attr:`Decision.fault`: a non-finite observation stops the robot).

        `v_pref`: the robot's preferred speed at full precision, to turn the action into a speed as the simulator
        does (None: the observation's float32 copy; :meth:`act` passes the robot state's).

        :raises InputError: the observation lacks the ``scan`` the policy reads or the ``pose`` the fallback needs
            with walls."""
        needed = ([SCAN_KEY] if self.network.scan is not None else []) + ([POSE_KEY] if self.walls else [])
        missing = [key for key in needed if key not in observation]
        if missing:
            raise InputError(f"the observation lacks {missing}: this navigator reads "
                             + " and ".join({SCAN_KEY: "a range scan", POSE_KEY: "the robot's map pose (walls)"}[key]
                                            for key in missing))
        # onnxruntime's LSTM can turn a NaN input into finite outputs: a broken observation is caught here, not
        # by the output check. Neither the policy nor the fallback (which would ignore a NaN human) acts on it.
        observed = all(_finite(np.asarray(value)) for value in observation.values())
        if observed:
            action, estimate, usable = self._policy_and_uncertainty(observation)
        else:  # not run at all (an inf humans_mask has no row count): the uncertainty is unknown
            nan = np.full((1, 2), np.nan)
            action, estimate, usable = _STOP_ACTION.copy(), Uncertainty(nan, nan, nan, np.full(1, np.nan)), False
        fault = None if usable else (NON_FINITE_OUTPUT if observed else NON_FINITE_OBSERVATION)
        nearest = nearest_human(observation)
        speed_term = nearest.speed(self._rule.proximity)
        if fault is None:
            windowed = self._window.update(estimate)
            (u_ep_speed, u_ep_heading), (u_al_speed, u_al_heading) = (windowed.u_ep[0].tolist(),
                                                                      windowed.u_al[0].tolist())
            values = {"u_ep_speed": u_ep_speed, "u_ep_heading": u_ep_heading, "u_al_speed": u_al_speed,
                      "u_al_heading": u_al_heading, "u_feat": float(windowed.u_feat[0])}
            inputs = TriggerInputs(observation=observation, actions=np.asarray(action, np.float32).reshape(1, 2),
                                   uncertainty={key: np.array([value]) for key, value in values.items()},
                                   nearest=nearest, previous_gap=self._previous_gap.copy(),
                                   time_step=self.config.time_step, max_heading_change=self.config.max_heading_change)
            fire = self.trigger.fires(inputs)
            conditions = (self.trigger.last_conditions if isinstance(self.trigger, RuleTrigger)
                          else rule_conditions(windowed.u_ep_heading, windowed.u_feat, nearest.gap, speed_term,
                                               self._previous_gap, self._rule))
        else:
            # A NaN would stay in the window for `window` steps and make every uncertainty comparison False (the
            # rule blind): the window is not fed. The uncertainty is unknown, read as high in the conditions, and
            # the fallback takes over now, held as if the rule had fired.
            conditions = rule_conditions(math.inf, math.inf, nearest.gap, speed_term, self._previous_gap,
                                         self._rule)
            values = dict.fromkeys(("u_ep_speed", "u_ep_heading", "u_al_speed", "u_al_heading", "u_feat"), math.nan)
            fire = np.ones(1, dtype=bool)
        self._previous_gap = np.where(nearest.present, nearest.gap, np.nan)  # no human: nothing to compare next
        held, self._hold_left = held_fallback(fire, self._hold_left, self.thresholds.hold_steps)
        fallback = bool(held[0])
        speed = turn = math.nan
        wall_stop = False
        if observed:
            if fallback:
                action = self.cautious.predict(dict(observation))[0][0]
            preferred = float(observation["robot"][0, 3]) if v_pref is None else float(v_pref)
            if self.wall_stop is not None:
                action = np.array(action, dtype=np.float32).reshape(1, 2)
                wall_stop = bool(self.wall_stop.apply(action, observation, preferred)[0])
                action = action[0]
            speed, turn = robot_command(action, preferred, self.config.max_heading_change)
        if not (math.isfinite(speed) and math.isfinite(turn)):  # the last guard: never a NaN command
            speed, turn, action, fallback = 0.0, 0.0, _STOP_ACTION.copy(), False
            fault = f"{fault}; {STOPPED}" if fault else STOPPED
        return Decision(speed=speed, turn=turn, action=action, fallback=fallback, uncertainty=estimate,
                        windowed=values, conditions=conditions, observation=dict(observation), fault=fault,
                        wall_stop=wall_stop)

    def _policy_and_uncertainty(self, observation: Mapping[str, np.ndarray]) -> tuple[np.ndarray, Uncertainty, bool]:
        """ONE graph call on ``1 + K`` rows: row 0 without dropout (the action, clipped to [-1, 1]), rows 1..K with
        MC-dropout masks from the stream (this step's uncertainty); and whether all of it is finite."""
        network = self.network
        robot, humans, mask, any_human = network.trim(observation)
        key = (self.k, humans.shape[1], any_human)
        batch = self._batches.get(key)
        if batch is None:  # first decision with this many humans: buffers + IO binding, kept for the next ones
            batch = self._batches[key] = network.mc_batch(self.k, humans.shape[1], any_human, deterministic_rows=1)
        batch.run(robot, humans, mask, self.uniforms, network.p_test, scan=network.scan_of(observation))
        estimate = network.summarise(batch.h[1:, None], batch.mean[1:, None], batch.log_std[1:, None])
        # All rows' raw outputs: a NaN in an MC row poisons the uncertainty as surely as one in row 0 the action
        usable = (_finite(batch.mean) and _finite(batch.log_std) and _finite(batch.h) and _finite(estimate.u_ep)
                  and _finite(estimate.u_al) and _finite(estimate.u_feat))
        return np.minimum(np.maximum(batch.mean[0], -1.0), 1.0), estimate, usable  # np.clip costs more here

    def __repr__(self) -> str:
        walls = "" if self.walls is None else f", walls={len(self.walls)} polygons"
        return f"SafeNavigator({self.network!r}, K={self.k}, thresholds={self.thresholds!r}{walls})"
