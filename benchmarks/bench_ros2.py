"""Benchmark: latency of the ROS 2 navigator node, from a humans message in to the cmd_vel out, beside
`SafeNavigator.act` alone, in the same run.

    python benchmarks/bench_ros2.py                      # the shipped policy exported, 1,000 decisions
    python benchmarks/bench_ros2.py --model navigator.onnx --decisions 300

What is measured (wall clock, `time.perf_counter`; the machine's other load counts):

* node: ``socnav ros2 navigator --lockstep`` runs in its own process (onnxruntime with one thread, markers and
  diagnostics on, Fast DDS on loopback, a random domain). For each of the states this process publishes the goal
  and the odometry (stamped t), waits 5 ms so that they have arrived, then times from publishing the humans cloud
  (stamped t: it completes the set, the node decides on it) to receiving the node's Twist; the next decision
  starts once the node has published its reports (markers last), as at 4 Hz it would have. That is one MC-dropout
  decision (K = 20, the paper's thresholds, the fallback where the rule fires) plus both serialisations, two DDS
  deliveries, the two executors' wake-ups, and the node's checks and reports;
* inside the node: its own ``~/latency`` (from the callback that completed the inputs to the Twist's publication);
* act: `SafeNavigator.act` on the same states, in this process (same file, K and thresholds).

The states: circle crossing with 5 humans, the robot driven by ORCA, one state per step over several episodes.
Median and p99 over ``--decisions`` decisions (after 20 of warm-up).
"""

from __future__ import annotations

import _bench  # benchmarks/_bench.py: first, so that the thread pools are capped before numpy / torch load

_bench.single_thread()

import argparse  # noqa: E402
import json  # noqa: E402
import os  # noqa: E402
import random  # noqa: E402
import signal  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

import socnav  # noqa: E402
from socnav.controllers import OrcaController  # noqa: E402
from socnav.runtime import SafeNavigator  # noqa: E402
from socnav.sim.world import CrowdWorld  # noqa: E402

WARM_UP = 20
#: Seconds between the odometry and goal and the humans cloud that completes a decision's inputs.
SETTLE_S = 0.005


def states(count: int, n_humans: int) -> list[tuple[dict[str, Any], dict[str, np.ndarray]]]:
    """``count`` (robot, humans) states of circle-crossing episodes with an ORCA robot, episode k seeded k."""
    config = socnav.load_config({"scenario": "circle_crossing", "n_humans": n_humans})
    world, controller = CrowdWorld(config, 1), OrcaController(config)
    found: list[tuple[dict[str, Any], dict[str, np.ndarray]]] = []
    episode = 0
    while len(found) < count:
        world.seed(0, episode)
        world.reset()
        episode += 1
        for _ in range(200):
            humans = np.flatnonzero(world.active[0, 1:]) + 1
            found.append(({"position": world.positions[0, 0].copy(), "velocity": world.velocities[0, 0].copy(),
                           "heading": float(world.heading[0]), "goal": world.goals[0, 0].copy(),
                           "v_pref": float(world.preferred_speeds[0, 0]), "radius": float(world.radii[0, 0])},
                          {"positions": world.positions[0, humans].copy(),
                           "velocities": world.velocities[0, humans].copy(), "radii": world.radii[0, humans].copy()}))
            result = world.step(controller.predict(world.observe())[0])
            if result.terminated[0] or result.truncated[0] or len(found) == count:
                break
    return found


def percentiles(seconds: list[float]) -> dict[str, float]:
    values = np.asarray(seconds) * 1e6
    return {"median_us": float(np.median(values)), "p99_us": float(np.percentile(values, 99)),
            "mean_us": float(values.mean())}


def time_act(model: Path, scenes: list[tuple[dict[str, Any], dict[str, np.ndarray]]]) -> list[float]:
    navigator = SafeNavigator.load(model, seed=0)
    navigator.reset()
    samples = []
    for index, (robot, humans) in enumerate(scenes):
        start = time.perf_counter()
        navigator.act(robot, humans)
        if index >= WARM_UP:
            samples.append(time.perf_counter() - start)
    return samples


def time_node(model: Path, scenes: list[tuple[dict[str, Any], dict[str, np.ndarray]]],
              environment: dict[str, str]) -> tuple[list[float], list[float]]:
    """Round trips humans -> cmd_vel through a navigator node in its own process, and the node's own latencies."""
    import rclpy
    from geometry_msgs.msg import PoseStamped, Twist
    from nav_msgs.msg import Odometry
    from rclpy.node import Node
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import Float64
    from visualization_msgs.msg import MarkerArray

    from socnav.ros2.messages import humans_to_cloud, position_to_goal, robot_to_odometry

    node_process = subprocess.Popen(
        [sys.executable, "-m", "socnav", "ros2", "navigator", "--model", str(model), "--lockstep", "--seed", "0",
         "--ros-args", "-p", f"preferred_speed:={max(robot['v_pref'] for robot, _ in scenes)}"],
        env=environment, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    rclpy.init(domain_id=int(environment["ROS_DOMAIN_ID"]))
    try:
        node = Node("bench_ros2")
        odometry = node.create_publisher(Odometry, "odom", 10)
        humans_topic = node.create_publisher(PointCloud2, "humans", 10)
        goal = node.create_publisher(PoseStamped, "goal_pose", 10)
        twists: list[float] = []
        inside: list[float] = []
        node.create_subscription(Twist, "cmd_vel", lambda _: twists.append(time.perf_counter()), 10)
        node.create_subscription(Float64, "/socnav_navigator/latency", lambda m: inside.append(m.data), 10)
        reports: list[bytes] = []  # the node's markers, the last thing it publishes per decision: then it is idle
        node.create_subscription(MarkerArray, "/socnav_navigator/markers", reports.append, 10, raw=True)
        deadline = time.monotonic() + 60
        while not (all(p.get_subscription_count() for p in (odometry, humans_topic, goal))
                   and node.count_publishers("/cmd_vel") and node.count_publishers("/socnav_navigator/markers")):
            if time.monotonic() > deadline or node_process.poll() is not None:
                raise RuntimeError("the navigator node did not start (run `socnav ros2 navigator` to see why)")
            rclpy.spin_once(node, timeout_sec=0.05)
        round_trips = []
        for index, (robot, crowd) in enumerate(scenes):
            stamp = node.get_clock().now().nanoseconds
            # preferred_speed is the node's parameter: the states' v_pref is set there once (the largest)
            goal.publish(position_to_goal(robot["goal"], stamp, "odom"))
            odometry.publish(robot_to_odometry(robot["position"], robot["velocity"], robot["heading"], 0.0, stamp,
                                               "odom", "base_link"))
            cloud = humans_to_cloud(crowd["positions"], crowd["velocities"], crowd["radii"], stamp, "odom")
            time.sleep(SETTLE_S)
            received, reported = len(twists), len(reports)
            start = time.perf_counter()
            humans_topic.publish(cloud)
            while len(twists) == received or len(reports) == reported:  # the command, then the node's reports
                rclpy.spin_once(node, timeout_sec=5.0)
                if time.perf_counter() - start > 5.0:
                    raise RuntimeError(f"no cmd_vel or markers for decision {index}")
            if index >= WARM_UP:
                round_trips.append(twists[received] - start)
        end = time.monotonic() + 1.0
        while len(inside) < len(scenes) and time.monotonic() < end:
            rclpy.spin_once(node, timeout_sec=0.05)
        return round_trips, inside[WARM_UP:]
    finally:
        node_process.send_signal(signal.SIGINT)
        try:
            node_process.wait(timeout=20)
        except subprocess.TimeoutExpired:
            node_process.kill()
        rclpy.shutdown()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, default=None, help="navigator file (default: export the shipped "
                                                                "policy to a temporary file)")
    parser.add_argument("--decisions", type=int, default=1000)
    parser.add_argument("--humans", type=int, default=5)
    parser.add_argument("--json", type=Path, default=None, help="also write the numbers here")
    args = parser.parse_args()
    from socnav.ros2.environment import Ros2Unavailable, require_rclpy

    try:
        require_rclpy()
    except Ros2Unavailable as exc:
        sys.exit(f"bench_ros2: {exc}")
    environment = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
                   "ROS_DOMAIN_ID": os.environ.get("ROS_DOMAIN_ID", str(random.randint(1, 101)))}
    os.environ.update(environment)
    with tempfile.TemporaryDirectory() as folder:
        model = args.model
        if model is None:
            import torch

            torch.set_num_threads(1)
            model = socnav.export_onnx(socnav.load_policy("pretrained"), Path(folder) / "navigator.onnx")
        scenes = states(args.decisions + WARM_UP, args.humans)
        act = percentiles(time_act(model, scenes))
        round_trips, inside = time_node(model, scenes, environment)
    results = {"decisions": args.decisions, "humans": args.humans, "act": act,
               "node_round_trip": percentiles(round_trips), "node_inside": percentiles(inside)}
    table = Table(title=f"navigator latency, circle crossing with {args.humans} humans, MC-dropout K = 20, "
                        f"{args.decisions} decisions (µs)")
    for column in ("", "median", "p99", "mean"):
        table.add_column(column, justify="right" if column else "left")
    for label, key in (("SafeNavigator.act alone", "act"), ("node: humans in -> cmd_vel out", "node_round_trip"),
                       ("node: its own ~/latency (callback -> publish)", "node_inside")):
        numbers = results[key]
        table.add_row(label, f"{numbers['median_us']:.0f}", f"{numbers['p99_us']:.0f}", f"{numbers['mean_us']:.0f}")
    Console().print(table)
    if args.json is not None:
        args.json.write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
