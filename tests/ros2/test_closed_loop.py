"""Closed loop in a real ROS 2 graph: `socnav ros2 navigator` and `socnav ros2 sim` as two processes (loopback, a
random domain), in lock-step, play 20 circle-crossing episodes whose records match the in-process evaluation of the
same exported navigator on the same seeds; a navigator fed the odometry's twist in the wrong frame is caught by the
same comparison; the recording opens with an MCAP reader that knows nothing of rclpy; real time runs too.

The in-process evaluation is `SafeNavigator.act` on the world's state arrays with its command ``(v, dtheta)``
executed by the world (the environment's action for that command), episode ``k`` seeded ``seed + k``: what a robot
does with the navigator, without ROS. "Match": the same outcome, length, intrusions and duration in every episode,
and the float columns within :data:`FLOAT_TOLERANCE`. Not bit for bit, because the heading travels as a quaternion:
``2 atan2(...)`` of ``(sin(h / 2), cos(h / 2))`` is ``h`` within 1e-16 rad, which moves the float32 observation of a
heading that points almost exactly at the goal by one step, and the fallback's turn by ~1e-15 rad (seen once in 20
episodes). (Stepping the world with `Decision.action` instead of the command would differ by ~1e-8 in speed:
`SafeNavigator` computes ``v = v_pref (a0 + 1) / 2`` with the float32 ``v_pref`` of its observation, the world with
its float64 one; over 20 episodes that moved one goal arrival by a step.)
"""

from __future__ import annotations

import math
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from socnav.config import load_config
from socnav.envs.rollout import EPISODE_COLUMNS
from socnav.runtime import SafeNavigator
from socnav.sim.world import CrowdWorld

pytestmark = [pytest.mark.ros2, pytest.mark.heavy]  # heavy: a ROS 2 graph of separate processes

EPISODES = 20
SEED = 100
NAVIGATOR_SEED = 7
#: Records' float columns (return, metres, seconds) agree to this (see the module's docstring: ~1e-15 seen).
FLOAT_TOLERANCE = 1e-9


def circle_crossing(navigator_file: Path):
    """The navigator's training world with the circle-crossing scenario and that scenario's own crowd, as
    `socnav ros2 sim --model FILE --scenario circle_crossing` builds it."""
    world = SafeNavigator.load(navigator_file).config.model_dump(mode="json")
    return load_config({**world, "n_humans": None}, scenario="circle_crossing")


def in_process_records(navigator_file: Path, episodes: int) -> pd.DataFrame:
    """The navigator driving the world directly, one SafeNavigator across episodes, reset at each (as the node
    resets on a new goal); records as `socnav.envs.rollout.rollout_episodes` writes them."""
    navigator = SafeNavigator.load(navigator_file, seed=NAVIGATOR_SEED)
    config = circle_crossing(navigator_file)
    world = CrowdWorld(config, 1)
    records = []
    for episode in range(episodes):
        world.seed(0, SEED + episode)
        world.reset()
        navigator.reset()
        while True:
            humans = np.flatnonzero(world.active[0, 1:]) + 1
            v_pref = world.preferred_speeds[0, 0]
            speed, turn = navigator.act(
                {"position": world.positions[0, 0], "velocity": world.velocities[0, 0], "heading": world.heading[0],
                 "goal": world.goals[0, 0], "v_pref": v_pref, "radius": world.radii[0, 0]},
                {"positions": world.positions[0, humans], "velocities": world.velocities[0, humans],
                 "radii": world.radii[0, humans]}).command
            # the command executed: v = v_pref (a0 + 1) / 2, dtheta = max_heading_change a1, solved for a
            result = world.step(np.array([[2.0 * speed / v_pref - 1.0, turn / config.max_heading_change]]))
            if result.terminated[0] or result.truncated[0]:
                summary = world.episode_summary(0, int(result.outcome[0]))
                records.append({"episode": episode, "seed": SEED + episode, **summary})
                break
    return pd.DataFrame.from_records(records)


def mismatches(records: pd.DataFrame, reference: pd.DataFrame) -> list[str]:
    """Every difference between two runs' per-episode records (`EPISODE_COLUMNS`), one line each; empty: they match
    (integers and outcomes equal, floats within :data:`FLOAT_TOLERANCE`, NaN where the other is NaN)."""
    if len(records) != len(reference):
        return [f"{len(records)} episodes != {len(reference)}"]
    found = []
    for (_, ros), (_, ours) in zip(records.iterrows(), reference.iterrows(), strict=True):
        for column in EPISODE_COLUMNS:
            a, b = ros[column], ours[column]
            same = ((math.isnan(a) and math.isnan(b)) or abs(a - b) <= FLOAT_TOLERANCE) if isinstance(b, float) \
                else a == b
            if not same:
                found.append(f"seed {ours['seed']}: {column} {a!r} != {b!r}")
    return found


def closed_loop(tmp_path: Path, environment: dict[str, str], navigator_file: Path, episodes: int,
                navigator_arguments: tuple[str, ...] = (), record: bool = False,
                alongside=None) -> tuple[pd.DataFrame, str]:
    """Run the navigator and the simulator as two `socnav ros2` processes in lock-step; the simulator's records and
    both processes' output. ``alongside``: a context manager around the simulator's run (e.g. a relay node)."""
    socnav = [sys.executable, "-m", "socnav", "ros2"]
    out = tmp_path / "records.csv"
    navigator = subprocess.Popen(
        [*socnav, "navigator", "--model", str(navigator_file), "--lockstep", "--use-sim-time", "--seed",
         str(NAVIGATOR_SEED), *navigator_arguments],
        env=environment, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # stopped by SIGINT below, as in a terminal
    try:
        simulator_command = [*socnav, "sim", "--model", str(navigator_file), "--scenario", "circle_crossing",
                             "--episodes", str(episodes), "--seed", str(SEED), "--lockstep", "--out", str(out),
                             *(["--record", str(tmp_path / "episodes.mcap")] if record else []),
                             "--ros-args", "-p", "wait_timeout:=30.0"]
        with alongside if alongside is not None else _nothing():
            simulator = subprocess.run(simulator_command, env=environment, capture_output=True, text=True,
                                       timeout=240)
    finally:
        navigator.send_signal(signal.SIGINT)
        try:
            navigator_output = navigator.communicate(timeout=30)[0]
        except subprocess.TimeoutExpired:
            navigator.kill()
            navigator_output = navigator.communicate()[0]
    output = f"--- simulator (exit {simulator.returncode}):\n{simulator.stdout}{simulator.stderr}\n" \
             f"--- navigator (exit {navigator.returncode}):\n{navigator_output}"
    assert simulator.returncode == 0, output
    assert navigator.returncode == 0, output  # Ctrl-C is a clean exit
    return pd.read_csv(out), output


class _nothing:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def test_closed_loop_matches_the_in_process_evaluation(tmp_path, ros_environment, navigator_file):
    records, output = closed_loop(tmp_path, ros_environment, navigator_file, EPISODES, record=True)
    reference = in_process_records(navigator_file, EPISODES)
    assert len(records) == EPISODES and set(records["outcome"]) <= {"goal", "collision", "timeout"}, output
    assert mismatches(records, reference) == [], output
    assert records["duration"].tolist() == (records["length"] * 0.25).tolist()
    _check_recording(tmp_path / "episodes.mcap", records, circle_crossing(navigator_file))


def _check_recording(path: Path, records: pd.DataFrame, config) -> None:
    """Read back with mcap + mcap-ros2-support (their own CDR decoder, driven by the schemas in the file): one
    state per step, one command per step, every topic a viewer needs, and the decoded first odometry."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    with path.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        summary = reader.get_summary()
        topics = {channel.topic: summary.schemas[channel.schema_id].name for channel in summary.channels.values()}
        counts = {summary.channels[channel].topic: count
                  for channel, count in summary.statistics.channel_message_counts.items()}
        first = next(reader.iter_decoded_messages(topics=["/odom"]))
    assert topics["/odom"] == "nav_msgs/msg/Odometry" and topics["/humans"] == "sensor_msgs/msg/PointCloud2"
    assert {"/clock", "/goal_pose", "/cmd_vel", "/socnav_sim/markers", "/socnav_navigator/markers",
            "/socnav_navigator/fallback", "/socnav_navigator/uncertainty", "/diagnostics"} <= set(topics)
    steps = int(records["length"].sum())
    assert counts["/odom"] == counts["/humans"] == counts["/clock"] == steps  # the state before each step
    assert counts["/cmd_vel"] == steps
    odometry = first[3]  # (schema, channel, message, decoded)
    assert odometry.header.frame_id == "odom" and odometry.child_frame_id == "base_link"
    start = robot_start(config, records["seed"].iloc[0])
    assert (odometry.pose.pose.position.x, odometry.pose.pose.position.y) == tuple(start)


def robot_start(config, seed: int) -> np.ndarray:
    """The robot's start in the episode of ``seed``, drawn by a world of our own."""
    world = CrowdWorld(config, 1)
    world.seed(0, int(seed))
    world.reset()
    return world.positions[0, 0]


RELAY = """
import rclpy
from nav_msgs.msg import Odometry
from socnav.ros2.messages import odometry_to_robot

rclpy.init()
node = rclpy.create_node("wrong_frame_relay")
publisher = node.create_publisher(Odometry, "odom_wrong_frame", 10)


def relay(message):
    velocity = odometry_to_robot(message, "odom", "base_link").velocity  # over the ground, odom axes
    message.twist.twist.linear.x, message.twist.twist.linear.y = float(velocity[0]), float(velocity[1])
    publisher.publish(message)


node.create_subscription(Odometry, "odom", relay, 10)
rclpy.spin(node)
"""


class TwistInTheOdomFrame:
    """A relay that hands the navigator odometry whose twist is expressed in the odometry frame while still
    labelled ``base_link`` -- a common driver mistake -- on topic ``odom_wrong_frame``. A process of its own, like
    the nodes: DDS reads its discovery settings once per process, so a relay inside the test process could be cut off
    from the graph by an earlier test of the same worker."""

    def __init__(self, environment: dict[str, str]) -> None:
        self.environment = environment

    def __enter__(self):
        self.process = subprocess.Popen([sys.executable, "-c", RELAY], env=self.environment,
                                        stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        return self

    def __exit__(self, *exc):
        self.process.terminate()
        try:
            self.process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.process.kill()
        return False


def test_a_navigator_fed_the_wrong_frame_is_caught(tmp_path, ros_environment, navigator_file):
    episodes = 3
    records, output = closed_loop(tmp_path, ros_environment, navigator_file, episodes,
                                  ("--ros-args", "-p", "odom_topic:=odom_wrong_frame"),
                                  alongside=TwistInTheOdomFrame(ros_environment))
    found = mismatches(records, in_process_records(navigator_file, episodes))
    assert found, f"the wrong frame went unnoticed:\n{records}\n{output}"


def test_real_time(ros_context, navigator_file, tmp_path):
    """The simulator in real time (8x) with the navigator on its timer and /clock: the episode plays to its end
    and its record is written."""
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from socnav.ros2.navigator import NavigatorNode
    from socnav.ros2.simulator import SimulatorNode

    navigator = NavigatorNode(parameter_overrides=[Parameter("model", value=str(navigator_file)),
                                                   Parameter("use_sim_time", value=True)], context=ros_context)
    simulator = SimulatorNode(circle_crossing(navigator_file), episodes=1, seed=SEED, out=tmp_path / "r.csv",
                              real_time_factor=8.0, context=ros_context)
    executor = SingleThreadedExecutor(context=ros_context)
    for node in (navigator, simulator):
        executor.add_node(node)
    try:
        records = simulator.run(executor)
    finally:
        executor.shutdown()
    written = pd.read_csv(tmp_path / "r.csv")
    assert len(records) == len(written) == 1 and written["seed"][0] == SEED
    assert written["outcome"][0] in ("goal", "collision", "timeout") and written["path_length"][0] > 1.0
    assert navigator.decisions >= written["length"][0] - 1  # one decision per simulated step
    assert simulator.commands_received >= written["length"][0] - 1
    assert navigator.settings["preferred_speed"] == simulator.world.preferred_speeds[0, 0]  # set per episode
