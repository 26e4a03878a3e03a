"""`socnav ros2`: the navigator and the simulator as ROS 2 nodes (the ``ros2`` extra; see docs/ros2.md).
Importing this module imports no rclpy: each command loads it, or says how to install it.

Arguments the command does not know (``--ros-args -p name:=value -r from:=to ...``) go to ROS 2, so every parameter,
remapping and node name works as with ``ros2 run``; the command's own options take precedence over ``-p``.
"""

from __future__ import annotations

import faulthandler
import io
import signal
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from pathlib import Path
from types import FrameType
from typing import Any

import typer
from rich.markup import escape

from socnav._console import console, fail
from socnav.sim.scenarios import scenario_names

__all__ = ["app"]

app = typer.Typer(add_completion=False, no_args_is_help=True, rich_markup_mode=None,
                  help="ROS 2 nodes: the safe navigator and the simulator (needs the ros2 extra)")

#: Unknown options and extra arguments are ROS 2's (`--ros-args ...`), passed on to rclpy.init.
_ROS_ARGUMENTS = {"allow_extra_args": True, "ignore_unknown_options": True}


def _rclpy() -> Any:
    from socnav.ros2.environment import Ros2Unavailable, require_rclpy

    try:
        return require_rclpy()
    except Ros2Unavailable as exc:
        fail(str(exc))


class _Signals:
    """The signals received (``received``), and whether ROS 2 is up to stop the process on them (``ros_up``)."""

    def __init__(self) -> None:
        self.received: list[int] = []
        self.ros_up = False
        #: shuts ROS 2 down (``rclpy.try_shutdown``), set with ``ros_up``
        self.shutdown: Callable[[], None] | None = None
        #: the node is being destroyed and ROS 2 shut down: a signal now is only recorded
        self.closing = False

    def handle(self, number: int, _frame: FrameType | None) -> None:
        self.received.append(number)
        if self.closing:  # a shutdown from here would run between the steps of destroying the node
            return
        if not self.ros_up or len(self.received) > 1:
            raise KeyboardInterrupt
        if self.shutdown is not None:  # rclpy's handler has done it already, unless its wake-up was lost
            with suppress(Exception):  # shutting down already, from rclpy's own handler thread
                self.shutdown()


@contextmanager
def _first_signal_shuts_ros_down() -> Iterator[_Signals]:
    """While ROS 2 is up (``ros_up``, set by the caller once ``rclpy.init`` returned), the first Ctrl-C or SIGTERM
    only shuts it down; a second one, or one while ROS 2 is not up, raises KeyboardInterrupt.

    rclpy's own handler (installed by ``rclpy.init``, for SIGINT and SIGTERM) shuts the context down from another
    thread, which ends the spin, and then calls the handler that was there before it. Python's default SIGINT
    handler would then raise KeyboardInterrupt at an arbitrary point of the main thread (inside a callback, between
    two publishes, in the clean-up): a race that could end in a traceback. Installed before ``rclpy.init``, this one
    is the handler rclpy calls, so nothing is raised while the spin ends by itself."""
    signals = _Signals()
    previous = {number: signal.signal(number, signals.handle) for number in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield signals
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)


def _spin(rclpy: Any, arguments: list[str], build: Callable[[], Any], run: Callable[[Any], None]) -> None:
    """Start ROS 2 with ``arguments``, build the node (its setup errors: one line, exit 2), run it until it is done
    or interrupted (the first Ctrl-C or SIGTERM: a clean exit 0), and shut ROS 2 down."""
    # A crash in ROS 2's or onnxruntime's C code (a segmentation fault at shutdown was seen, rarely, in CI) prints
    # the Python stack of every thread instead of dying silently (where stderr is a file: not under a test's capture).
    with suppress(io.UnsupportedOperation, AttributeError, ValueError):
        faulthandler.enable()
    with _first_signal_shuts_ros_down() as signals:
        _spin_ros(rclpy, arguments, build, run, signals)


def _spin_ros(rclpy: Any, arguments: list[str], build: Callable[[], Any], run: Callable[[Any], None],
              signals: _Signals) -> None:
    from rclpy.exceptions import ParameterException, ROSInterruptException
    from rclpy.executors import ExternalShutdownException

    from socnav.ros2.navigator import NavigatorSetupError
    from socnav.ros2.recording import RecordingError
    from socnav.ros2.simulator import SimulatorError
    from socnav.runtime import NavigatorLoadError
    from socnav.safety import ThresholdsError

    rclpy.init(args=["socnav", *arguments])
    signals.ros_up, signals.shutdown = True, rclpy.try_shutdown
    node = None
    try:
        try:
            node = build()
        except (NavigatorSetupError, NavigatorLoadError, ThresholdsError, RecordingError, ParameterException,
                ValueError) as exc:
            fail(" ".join(str(exc).split()))
        except RuntimeError:  # RCLError: a signal shut the context down while the node was being built
            if rclpy.ok():
                raise
        try:
            if node is not None:
                run(node)
        except SimulatorError as exc:
            if rclpy.ok():
                fail(str(exc), code=1)
        except (KeyboardInterrupt, ExternalShutdownException, ROSInterruptException):
            pass
        except RuntimeError:
            # rclpy's own SIGINT/SIGTERM handler shuts the context down; an executor then building its wait set
            # raises RCLError (a RuntimeError) "the given context is not valid": that too is the interruption.
            if rclpy.ok():
                raise
        if signals.received or not rclpy.ok():  # a spin ends by itself when a signal shut the context down
            console.print("interrupted: shutting down", highlight=False)
    finally:
        signals.closing = True
        if node is not None:
            node.destroy_node()
        if rclpy.ok():
            rclpy.shutdown()
        signals.ros_up, signals.shutdown, signals.closing = False, None, False


@app.command(context_settings=_ROS_ARGUMENTS)
def navigator(
    ctx: typer.Context,
    model: Path = typer.Option(..., help="navigator file written by `socnav export`"),
    thresholds: str | None = typer.Option(None, help="safety thresholds: mc | ensemble | a `socnav calibrate` "
                                                        "FILE (default: the navigator file's)"),
    k: int | None = typer.Option(None, min=2, help="MC-dropout samples per decision (default: the file's)"),
    seed: int | None = typer.Option(None, min=0, help="seed of the MC-dropout masks (default: fresh entropy)"),
    lockstep: bool = typer.Option(False, "--lockstep", help="decide once per set of odometry, humans, goal (and "
                                                            "scan) with one stamp (for `socnav ros2 sim --lockstep`)"),
    use_sim_time: bool = typer.Option(False, "--use-sim-time", help="read the time from /clock"),
) -> None:
    """Run the safe navigator node: odometry, goal and humans (and a scan, map, pose, path) in; cmd_vel,
    diagnostics and markers out.

    Other parameters: --ros-args -p rate:=4.0 -p odom_topic:=/robot/odom -p pose_topic:=amcl_pose ... (docs/ros2.md
    lists them)."""
    rclpy = _rclpy()
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from socnav.ros2.navigator import NavigatorNode

    given = {"model": str(model), "thresholds": thresholds, "k": k, "seed": seed,
             "lockstep": lockstep or None, "use_sim_time": use_sim_time or None}
    overrides = [Parameter(name, value=value) for name, value in given.items() if value is not None]

    def run(node: NavigatorNode) -> None:
        console.print(f"navigator node {escape(node.get_fully_qualified_name())}: {escape(repr(node.navigator))}",
                      highlight=False)
        executor = SingleThreadedExecutor()
        executor.add_node(node)
        try:
            # Polled, not `executor.spin()`: on simulated time with no /clock coming (the simulator gone) nothing
            # wakes a blocked wait, and a signal's shutdown was seen to leave `spin()` waiting for ever (1 run in
            # ~50 in CI).
            while node.context.ok():
                executor.spin_once(timeout_sec=0.1)
        finally:
            # The node leaves its executor, and the executor's own guard conditions are destroyed, before the node
            # is: left to garbage collection after the context's shutdown, the process was seen to end in a
            # segmentation fault (1 run in many in CI).
            with suppress(Exception):
                executor.remove_node(node)
            with suppress(Exception):
                executor.shutdown(timeout_sec=1.0)

    _spin(rclpy, ctx.args, lambda: NavigatorNode(parameter_overrides=overrides), run)


def _world(scenario: str | None, model: Path | None, config: Path | None, n_humans: int | None) -> Any:
    """The simulated world: a navigator file's training world (``--model``), a config file, or the defaults; then
    ``--scenario`` (another scenario than the base's starts from its own number of humans) and ``--n-humans``."""
    from socnav.config import ConfigError, load_config

    base: Any = config
    if model is not None:
        from socnav.runtime import ExportedPolicy, NavigatorLoadError

        try:
            base = ExportedPolicy.load(model).record.env_config.model_dump(mode="json")
        except NavigatorLoadError as exc:
            fail(str(exc))
        if scenario is not None and scenario != base["scenario"]:
            base["n_humans"] = None
    overrides: dict[str, Any] = {"scenario": scenario, "n_humans": n_humans}
    try:
        return load_config(base, **{key: value for key, value in overrides.items() if value is not None})
    except ConfigError as exc:
        fail(str(exc))


@app.command(context_settings=_ROS_ARGUMENTS)
def sim(
    ctx: typer.Context,
    scenario: str | None = typer.Option(None, help=f"one of: {', '.join(scenario_names())} (default: the "
                                                     "--model's or --config's, else circle_crossing)"),
    model: Path | None = typer.Option(None, help="navigator file: simulate the world it was trained in"),
    config: Path | None = typer.Option(None, "--config", help="YAML env config (instead of --model's world)"),
    n_humans: int | None = typer.Option(None, min=0, help="humans per episode (default: the scenario's)"),
    episodes: int = typer.Option(10, min=1, max=100_000, help="episodes to play, then exit"),
    seed: int = typer.Option(0, min=0, help="episode k uses seed + k"),
    out: Path | None = typer.Option(None, help="per-episode records, .csv or .parquet (default: "
                                                  "runs/ros2/<scenario>_seed<seed>_<episodes>ep.csv)"),
    record: Path | None = typer.Option(None, help="also record every message to this .mcap file (a new file in an "
                                                     "existing directory, or an existing one with --force)"),
    lockstep: bool = typer.Option(False, "--lockstep", help="wait for the navigator's command at every step "
                                                            "(run the navigator with --lockstep)"),
    real_time_factor: float = typer.Option(1.0, min=1e-3, max=1e3, help="simulated seconds per wall second"),
    force: bool = typer.Option(False, "--force", help="replace an existing --record file"),
) -> None:
    """Run the crowd simulator node: odometry, humans, goal, /clock (and scan, map) out; cmd_vel in; episode records
    written."""
    from socnav.io import TABLE_FORMATS, OutputPathError, check_output_file

    if model is not None and config is not None:
        fail("--model and --config both name the world: give one of them")
    if out is not None and out.suffix not in TABLE_FORMATS:
        fail(f"--out must end in one of {', '.join(TABLE_FORMATS)}, got {out.name!r}")
    if record is not None and record.suffix != ".mcap":
        fail(f"--record must end in .mcap, got {record.name!r}")
    if record is not None:
        # Before anything starts: opening a FIFO blocks until a reader comes (and rclpy's signal handling retries the
        # open after each signal), a link into /proc is no recording.
        try:
            check_output_file(record, what="--record", force=force, create_parent=False)
        except OutputPathError as exc:
            fail(str(exc))
    env_config = _world(scenario, model, config, n_humans)
    out = out or Path("runs") / "ros2" / f"{env_config.scenario}_seed{seed}_{episodes}ep.csv"
    if out.is_dir():
        fail(f"--out {out} is a directory; name a file")
    rclpy = _rclpy()
    out.parent.mkdir(parents=True, exist_ok=True)
    from socnav.envs.rollout import summarize
    from socnav.ros2.simulator import SimulatorNode

    def build() -> SimulatorNode:
        return SimulatorNode(env_config, episodes=episodes, seed=seed, out=out, record=record, lockstep=lockstep,
                             real_time_factor=real_time_factor)

    def run(node: SimulatorNode) -> None:
        from socnav.config import describe_world

        console.print(f"simulator node {escape(node.get_fully_qualified_name())}: {escape(describe_world(env_config))}"
                      f", {'lock-step' if lockstep else f'real time x{real_time_factor:g}'}", highlight=False)
        records = node.run()
        metrics = summarize(records)
        console.print(f"{len(records)} episodes: goal {metrics['goal_pct']:.1f} %, collision "
                      f"{metrics['collision_pct']:.1f} %, time-out {metrics['timeout_pct']:.1f} %", highlight=False)
        console.print(f"per-episode records: {escape(str(out))}", highlight=False)
        if node.recorder is not None:  # the node records exactly when given `record`
            console.print(f"recording: {escape(str(record))} ({node.recorder.messages} messages)", highlight=False)

    _spin(rclpy, ctx.args, build, run)
