"""The ROS 2 nodes under hostile or mistaken use: the largest accepted crowd does not slow the navigator's decisions,
clocks that do not match are named as such (once), a malformed cloud of any size stops the robot, a record path that
is not a regular file is refused before anything starts, each node stops cleanly on the first Ctrl-C or SIGTERM, and a
simulator without a navigator says what it waits for."""

from __future__ import annotations

import math
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytestmark = pytest.mark.ros2

SOCNAV = [sys.executable, "-m", "socnav", "ros2"]
#: The crowd test: cmd_vel counted over this many wall seconds, once the navigator decides on the crowd.
RATE_WINDOW_S = 10.0
#: The accepted decision rate with the largest accepted crowd (the node's rate is 4 Hz).
MIN_RATE_HZ = 3.5


def crowd(count: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``count`` humans in a ring 3 to 60 m around the origin, walking: positions, velocities, radii."""
    rng = np.random.default_rng(seed)
    angle, distance = rng.uniform(0, 2 * math.pi, count), rng.uniform(3.0, 60.0, count)
    positions = np.column_stack([distance * np.cos(angle), distance * np.sin(angle)])
    return positions, rng.normal(0.0, 0.5, (count, 2)), np.full(count, 0.3)


def _stop(process: subprocess.Popen, how: int = signal.SIGINT, timeout: float = 30.0) -> tuple[int, str]:
    """Send ``how`` once; the exit status and output (a process still running after ``timeout`` is killed and
    reported as such)."""
    process.send_signal(how)
    try:
        output = process.communicate(timeout=timeout)[0]
    except subprocess.TimeoutExpired:
        process.kill()
        return -999, f"still running {timeout:g} s after {signal.Signals(how).name}:\n{process.communicate()[0]}"
    return process.returncode, output


@pytest.mark.heavy  # a navigator process and 10 s of wall-clock rate measurement
def test_the_largest_accepted_crowd_keeps_the_decision_rate(ros_graph_context, ros_environment, navigator_file):
    """10,000 humans (MAX_TRACKED_HUMANS) at 10 Hz, markers on (the default), the navigator on its 4 Hz wall-clock
    timer in its own process: cmd_vel keeps >= 3.5 Hz, every decision reads the whole crowd and drives."""
    from diagnostic_msgs.msg import DiagnosticArray
    from geometry_msgs.msg import PoseStamped, Twist
    from nav_msgs.msg import Odometry
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node
    from sensor_msgs.msg import PointCloud2
    from visualization_msgs.msg import MarkerArray

    from socnav.ros2 import messages

    navigator = subprocess.Popen([*SOCNAV, "navigator", "--model", str(navigator_file), "--seed", "0"],
                                 env=ros_environment, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                                 preexec_fn=_sigint_as_in_a_terminal)
    driver = Node("crowd_driver", context=ros_graph_context)
    odometry = driver.create_publisher(Odometry, "odom", 10)
    humans = driver.create_publisher(PointCloud2, "humans", 10)
    goal = driver.create_publisher(PoseStamped, "goal_pose", 10)
    commands: list[float] = []
    statuses: list[dict[str, str]] = []
    marker_counts: list[int] = []
    driver.create_subscription(Twist, "cmd_vel", lambda _message: commands.append(time.monotonic()), 10)
    driver.create_subscription(DiagnosticArray, "/diagnostics", lambda message: statuses.append(
        {"message": message.status[0].message, **{v.key: v.value for v in message.status[0].values}}), 10)
    driver.create_subscription(MarkerArray, "/socnav_navigator/markers",
                               lambda message: marker_counts.append(len(message.markers)), 10)
    executor = SingleThreadedExecutor(context=ros_graph_context)
    executor.add_node(driver)
    positions, velocities, radii = crowd(messages.MAX_TRACKED_HUMANS)
    try:
        deadline = time.monotonic() + 60.0
        while humans.get_subscription_count() == 0 or driver.count_publishers("cmd_vel") == 0:
            assert time.monotonic() < deadline and navigator.poll() is None, "the navigator did not start"
            executor.spin_once(timeout_sec=0.05)
        started, window = None, None
        next_publish = time.monotonic()
        while window is None or time.monotonic() < window + RATE_WINDOW_S:
            assert time.monotonic() < deadline + 60.0, f"the navigator never decided on the crowd: {statuses[-3:]}"
            now = time.monotonic()
            if now >= next_publish:
                next_publish = now + 0.1
                stamp = driver.get_clock().now().nanoseconds
                odometry.publish(messages.robot_to_odometry(np.zeros(2), np.zeros(2), 0.0, 0.0, stamp, "odom",
                                                            "base_link"))
                humans.publish(messages.humans_to_cloud(positions, velocities, radii, stamp, "odom"))
                goal.publish(messages.position_to_goal(np.array([0.0, 8.0]), stamp, "odom"))
            executor.spin_once(timeout_sec=max(0.0, min(0.01, next_publish - time.monotonic())))
            if started is None and statuses and statuses[-1].get("humans") == str(messages.MAX_TRACKED_HUMANS):
                started = time.monotonic()
            if window is None and started is not None and time.monotonic() > started + 2.0:  # settled
                window, first = time.monotonic(), len(statuses)
        counted = [stamp for stamp in commands if window <= stamp <= window + RATE_WINDOW_S]
        rate = len(counted) / RATE_WINDOW_S
        decided = statuses[first:]
    finally:
        code, output = _stop(navigator)
        executor.shutdown()
        driver.destroy_node()
    print(f"cmd_vel {rate:.2f} Hz with {messages.MAX_TRACKED_HUMANS} humans; markers per array: "
          f"{sorted(set(marker_counts))}")
    assert rate >= MIN_RATE_HZ, f"cmd_vel at {rate:.2f} Hz with {messages.MAX_TRACKED_HUMANS} humans\n{output}"
    assert decided and all(status["humans"] == str(messages.MAX_TRACKED_HUMANS) for status in decided)
    assert all(status["stopped"] == "False" for status in decided), decided[:3]
    assert marker_counts and max(marker_counts) <= 200, "markers are bounded"
    assert code == 0, output


# ------------------------------------------------------------------------------------------------- markers, shutdown


def _navigator(context, navigator_file, **parameters):
    from rclpy.parameter import Parameter

    from socnav.ros2.navigator import NavigatorNode

    settings = {"model": str(navigator_file), "seed": 0, **parameters}
    return NavigatorNode(parameter_overrides=[Parameter(k, value=v) for k, v in settings.items()], context=context)


class Capture:
    """Stands in for a publisher: keeps what is published."""

    def __init__(self) -> None:
        self.messages: list = []

    def publish(self, message) -> None:
        self.messages.append(message)


def _feed(node, positions, velocities, radii, stamp_ns: int) -> None:
    """The node's inputs, through its own callbacks: the robot at the origin facing +y, the goal 8 m ahead."""
    from socnav.ros2 import messages

    node._on_odometry(messages.robot_to_odometry(np.zeros(2), np.zeros(2), math.pi / 2, 0.0, stamp_ns, "odom",
                                                 "base_link"))
    node._on_humans(messages.humans_to_cloud(positions, velocities, radii, stamp_ns, "odom"))
    node._on_goal(messages.position_to_goal(np.array([0.0, 8.0]), stamp_ns, "odom"))


def test_markers_are_drawn_for_the_nearest_humans_only(ros_context, navigator_file):
    """10,000 humans: the marker array holds the 50 nearest (nearest first) and says how many it left out; the
    decision itself read them all."""
    from visualization_msgs.msg import Marker

    from socnav.ros2.messages import MAX_TRACKED_HUMANS
    from socnav.ros2.navigator import MARKER_HUMANS

    node = _navigator(ros_context, navigator_file)
    node.markers, node.diagnostics = Capture(), Capture()
    positions, velocities, radii = crowd(MAX_TRACKED_HUMANS)
    _feed(node, positions, velocities, radii, node.get_clock().now().nanoseconds)
    node._decide(time.perf_counter())
    markers = node.markers.messages[-1].markers
    humans = [marker for marker in markers if marker.ns == "humans"]
    nearest = np.argsort(np.hypot(*positions.T))[:MARKER_HUMANS]
    assert [(marker.pose.position.x, marker.pose.position.y) for marker in humans] == \
        [tuple(positions[index]) for index in nearest]
    assert len(markers) == 1 + MARKER_HUMANS + 3  # DELETEALL, humans, goal, robot, text
    text = next(marker for marker in markers if marker.type == Marker.TEXT_VIEW_FACING).text
    assert f"({MARKER_HUMANS} nearest of {MAX_TRACKED_HUMANS} humans drawn)" in text
    values = {value.key: value.value for value in node.diagnostics.messages[-1].status[0].values}
    assert values["humans"] == str(MAX_TRACKED_HUMANS) and values["stopped"] == "False"
    node.destroy_node()


def test_nothing_is_published_once_the_context_is_shut_down(ros_context, navigator_file):
    """What rclpy's signal handler does on Ctrl-C while a decision is due: the decision publishes nothing (a
    publish would raise RCLError "publisher's context is invalid")."""
    import rclpy

    node = _navigator(ros_context, navigator_file)
    node._decide(time.perf_counter())
    assert node.decisions == 1
    rclpy.shutdown(context=ros_context)
    node._decide(time.perf_counter())  # real publishers: raised RCLError before the guard
    assert node.decisions == 1


class FakeRclpy:
    """rclpy's init / ok / shutdown / try_shutdown on a flag, each shutdown noted in ``events``."""

    def __init__(self, events: list[str] | None = None):
        self.alive = False
        self.events = [] if events is None else events

    def init(self, args):
        self.alive = True

    def ok(self):
        return self.alive

    def shutdown(self):
        self.events.append("shutdown")
        self.alive = False

    def try_shutdown(self):
        self.events.append("try_shutdown")
        self.alive = False


def test_the_first_signal_ends_the_spin_without_an_exception(capsys):
    """`socnav.cli.ros2._spin`: a signal while ROS 2 is up raises nothing (rclpy's handler shuts the context down,
    which ends the spin by itself); the exit is the clean "interrupted" one, and the handlers are restored."""
    from socnav.cli.ros2 import _spin

    class FakeNode:
        def destroy_node(self):
            pass

    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    for number in (signal.SIGINT, signal.SIGTERM):
        rclpy = FakeRclpy()

        def run(_node, number=number, rclpy=rclpy):
            signal.raise_signal(number)  # delivered to the Python handler here: no KeyboardInterrupt
            # rclpy's own handler shuts the context down too, from its thread; should its wake-up be lost, the
            # navigator's polling spin still ends, because the Python handler shut ROS 2 down as well:
            assert not rclpy.ok()

        _spin(rclpy, [], FakeNode, run)
        assert capsys.readouterr().out.strip() == "interrupted: shutting down"
        assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before


def test_a_signal_while_the_node_is_destroyed_only_is_recorded(capsys):
    """A Ctrl-C that reaches the Python handler while the node is being destroyed neither shuts ROS 2 down in the
    middle of it nor raises there: it is recorded, the node is destroyed whole, and ROS 2 is shut down after."""
    from socnav.cli.ros2 import _spin

    events: list[str] = []

    class FakeNode:
        def destroy_node(self):
            events.append("destroy begins")
            signal.raise_signal(signal.SIGINT)  # delivered to the Python handler here
            events.append("destroy ends")

    _spin(FakeRclpy(events), [], FakeNode, lambda _node: None)
    assert events == ["destroy begins", "destroy ends", "shutdown"]


# ------------------------------------------------------------------------------------------------- the record path


@pytest.fixture
def bad_paths(tmp_path: Path) -> dict[str, Path]:
    fifo = tmp_path / "fifo.mcap"
    os.mkfifo(fifo)
    memory = tmp_path / "memory.mcap"
    memory.symlink_to("/proc/self/mem")
    existing = tmp_path / "old.mcap"
    existing.write_bytes(b"keep")
    (tmp_path / "folder.mcap").mkdir()
    return {"a FIFO": fifo, "a link to /proc/self/mem": memory, "an existing file": existing,
            "a directory": tmp_path / "folder.mcap", "a missing directory": tmp_path / "nowhere" / "r.mcap"}


REFUSALS = {"a FIFO": "is not a regular file", "a link to /proc/self/mem": "a system path",
            "an existing file": "exists; pass --force", "a directory": "is a directory",
            "a missing directory": "does not exist"}


@pytest.mark.parametrize("case", list(REFUSALS))
def test_a_record_path_that_is_not_a_new_or_regular_file_is_refused_before_anything_starts(
        monkeypatch, tmp_path, bad_paths, case):
    from typer.testing import CliRunner

    from socnav.cli import app

    monkeypatch.chdir(tmp_path)
    monkeypatch.setitem(sys.modules, "rclpy", None)  # refused before ROS 2 (or the world) is even loaded
    result = CliRunner().invoke(app, ["ros2", "sim", "--episodes", "1", "--record", str(bad_paths[case])])
    output = " ".join(result.output.split())
    assert result.exit_code == 2 and f"error: --record {bad_paths[case]}" in output, result.output
    assert REFUSALS[case] in output, result.output
    assert Path("runs").exists() is False  # no work started: not even the records' directory
    if case == "an existing file":
        assert bad_paths[case].read_bytes() == b"keep"


@pytest.mark.parametrize("case", ["a FIFO", "a link to /proc/self/mem"])
def test_the_recorder_refuses_them_too_without_blocking(bad_paths, case):
    """`McapRecorder` itself (a FIFO without a reader blocked its open for ever): refused at once."""
    from socnav.ros2.recording import McapRecorder, RecordingError

    def too_long(*_args):
        raise TimeoutError("the recorder blocked")

    previous = signal.signal(signal.SIGALRM, too_long)
    signal.alarm(10)
    try:
        with pytest.raises(RecordingError, match=REFUSALS[case]):
            McapRecorder(bad_paths[case])
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


# ------------------------------------------------------------------------------------------------- clean stops


def _sigint_as_in_a_terminal() -> None:
    """In the child before it runs: SIGINT's default disposition (Python then installs its handler), as for a command
    typed in a terminal. A test run started where SIGINT is ignored (a background job of a non-interactive shell)
    passes that on to its children, and a node would then never see the Ctrl-C these tests send."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start(command: list[str], environment: dict[str, str], ready: str,
           timeout: float = 90.0) -> tuple[subprocess.Popen, list[str]]:
    """Start ``command``; return once a line of its output contains ``ready`` (its output so far, and the rest as
    it comes, in the list)."""
    import threading

    process = subprocess.Popen(command, env=environment, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                               preexec_fn=_sigint_as_in_a_terminal)
    lines: list[str] = []

    def read() -> None:
        assert process.stdout is not None
        for line in process.stdout:
            lines.append(line)

    threading.Thread(target=read, daemon=True).start()
    deadline = time.monotonic() + timeout
    while not any(ready in line for line in lines):
        if process.poll() is not None or time.monotonic() > deadline:
            process.kill()
            pytest.fail(f"{command[3:5]} never printed {ready!r}:\n{''.join(lines)}")
        time.sleep(0.05)
    return process, lines


def _signal_once(process: subprocess.Popen, lines: list[str], how: int, timeout: float = 20.0) -> str:
    """Send ``how`` once; the process must exit 0 within ``timeout`` s with the clean line and no error."""
    process.send_signal(how)
    try:
        process.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        process.kill()
        process.wait()
        pytest.fail(f"still running {timeout:g} s after one {signal.Signals(how).name}:\n{''.join(lines)}")
    time.sleep(0.2)  # the reader thread's last lines
    output = "".join(lines)
    assert process.returncode == 0, output
    assert "interrupted: shutting down" in output, output
    for bad in ("Traceback", "RCLError", "ERROR", "context is invalid", "KeyboardInterrupt"):
        assert bad not in output, output
    return output


@pytest.mark.heavy  # separate processes, seconds each
@pytest.mark.parametrize("how", [signal.SIGINT, signal.SIGTERM], ids=["SIGINT", "SIGTERM"])
def test_every_node_stops_on_the_first_signal(ros_environment, navigator_file, tmp_path, how):
    """The navigator deciding at 200 Hz (so a signal lands between publishes), a simulator waiting for a navigator,
    and a simulator playing episodes with one: each stops on one Ctrl-C or SIGTERM, exit 0, no traceback."""
    navigator_command = [*SOCNAV, "navigator", "--model", str(navigator_file), "--use-sim-time", "--ros-args", "-p",
                         "rate:=200.0"]
    sim_command = [*SOCNAV, "sim", "--model", str(navigator_file), "--scenario", "circle_crossing", "--episodes",
                   "1000", "--out", str(tmp_path / "records.csv"), "--real-time-factor", "4",
                   "--record", str(tmp_path / "episodes.mcap")]
    # a simulator alone: it says what it waits for, and stops on the signal
    simulator, lines = _start(sim_command, ros_environment, "waiting for a navigator")
    assert "/odom, /humans and /goal_pose and publishes /cmd_vel" in "".join(lines)
    _signal_once(simulator, lines, how)
    (tmp_path / "episodes.mcap").unlink()
    # the navigator and a simulator playing episodes with it: the simulator stopped mid-run, then the navigator
    navigator, navigator_lines = _start(navigator_command, ros_environment, "navigator node /socnav_navigator")
    try:
        simulator, lines = _start(sim_command, ros_environment, "navigator found")
        time.sleep(2.0)  # steps published, commands coming
        _signal_once(simulator, lines, how)
        assert (tmp_path / "episodes.mcap").stat().st_size > 0  # the recording was closed, not lost
    finally:
        if navigator.poll() is None:
            _signal_once(navigator, navigator_lines, how)


def test_a_simulator_without_a_navigator_says_what_it_waits_for(ros_context, navigator_file, monkeypatch, capfd):
    """At start, and every WAIT_REPORT_PERIOD s (here 0.5 s), naming the topics and what is still missing; then the
    one-line error of wait_timeout."""
    from rclpy.parameter import Parameter

    from socnav.config import load_config
    from socnav.ros2 import simulator as simulator_module

    monkeypatch.setattr(simulator_module, "WAIT_REPORT_PERIOD", 0.5)
    node = simulator_module.SimulatorNode(load_config(None, scenario="circle_crossing"), context=ros_context,
                                          parameter_overrides=[Parameter("wait_timeout", value=1.6)])
    started = time.monotonic()
    with pytest.raises(simulator_module.SimulatorError, match="no navigator subscribed to /odom"):
        node.run()
    assert time.monotonic() - started < 10.0
    output = capfd.readouterr().err
    node.destroy_node()
    assert "waiting for a navigator (up to 1.6 s, parameter wait_timeout): one that subscribes to /odom, /humans " \
           "and /goal_pose and publishes /cmd_vel, node socnav_navigator" in output, output
    still = [line for line in output.splitlines() if "still waiting for a navigator after" in line]
    assert 2 <= len(still) <= 4, output
    assert ("missing: a subscriber on /odom, a subscriber on /humans, a subscriber on /goal_pose, a publisher on "
            "/cmd_vel, the parameter service of node socnav_navigator") in still[0]


# ------------------------------------------------------------------------------------------------- clocks


def test_simulated_stamps_on_a_wall_clock_node_are_a_clock_mismatch_logged_once(ros_context, navigator_file,
                                                                                monkeypatch):
    """A navigator without --use-sim-time fed `socnav ros2 sim`'s stamps (simulated seconds
    since 0): 52 decisions say "clock mismatch" and name --use-sim-time; one log line, not 52. A stop whose age
    changes at every decision (stale inputs) is one log line too."""
    import types

    node = _navigator(ros_context, navigator_file)
    node.diagnostics = Capture()
    warnings: list[str] = []
    logger = types.SimpleNamespace(warning=warnings.append, error=warnings.append, info=lambda *_: None)
    monkeypatch.setattr(node, "get_logger", lambda: logger)
    positions, velocities, radii = crowd(5)

    def statuses(count: int, stamp) -> list[str]:
        for step in range(count):
            _feed(node, positions, velocities, radii, stamp(step))
            node._decide(time.perf_counter())
        return [array.status[0].message for array in node.diagnostics.messages[-count:]]

    mismatch = statuses(52, lambda step: 250_000_000 * (step + 1))  # 0.25 s, 0.5 s, ... of simulated time
    behind = r"stopped: odometry stamp is \d+ s behind the node clock: a clock mismatch; "
    hint = ("is the publisher on simulated time (e.g. socnav ros2 sim, publishing /clock)? start the navigator with "
            "--use-sim-time (use_sim_time:=true)")
    assert all(re.match(behind, message) and message.endswith(hint) for message in mismatch), mismatch[0]
    assert warnings == [mismatch[0]]
    assert statuses(1, lambda _: node.get_clock().now().nanoseconds) == ["policy drives"]
    stale = statuses(8, lambda step: node.get_clock().now().nanoseconds - 2 * 10**9 - step * 10**7)
    assert len(set(stale)) == 8 and all(message.startswith("stopped: odometry is stale: 2.0") for message in stale)
    assert warnings == [mismatch[0], stale[0]]
    node.destroy_node()
