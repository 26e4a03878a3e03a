"""A 4 Hz control loop driving a simulated robot with `socnav.runtime.SafeNavigator` alone (no torch).
What a ROS 2 node would wrap: read the robot's and the tracked humans' state, `act`, send (v, dtheta), repeat.

    socnav export pretrained --out navigator.onnx
    python examples/control_loop.py navigator.onnx            # real time, 4 Hz
    python examples/control_loop.py navigator.onnx --fast     # as fast as it computes
    python examples/control_loop.py navigator.onnx --thresholds examples/thresholds_closing_speed.yaml

The person walking head-on at 1 m/s does not yield. With the paper's rule as printed (the default thresholds) a
2 m/s approach never meets c_prox before contact, so the policy drives alone: both shipped open-plane policies
(`pretrained`, `pretrained-ppo`) step aside by themselves and reach the goal after 8.5 s. With the closing-speed
reading of c_prox the cautious fallback drives 6 steps as the person passes, and the robot reaches its goal too.

In a ROS 2 node, `on_timer` would read odometry and the people tracker instead of `Scene`, and publish the command
as a Twist (linear.x = v, angular.z = dtheta / period); `navigator.reset()` goes where a new goal is accepted.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from socnav.runtime import SafeNavigator

PERIOD = 0.25  # s: 4 Hz, the time step the policy was trained with


class Scene:
    """A toy world standing in for the robot's sensors: a unicycle robot and humans walking at constant velocity."""

    def __init__(self, seed: int, crossing: int) -> None:
        rng = np.random.default_rng(seed)
        self.position, self.heading, self.speed = np.array([0.0, -4.0]), math.pi / 2, 0.0
        self.goal, self.v_pref, self.radius = np.array([0.0, 4.0]), 1.0, 0.3
        # One person walking head-on towards the robot (the shipped policy's position-swap task), then `crossing`
        # people crossing the robot's path from alternating sides.
        starts = [[rng.uniform(-0.2, 0.2), 4.0]] + [[-5.0 if i % 2 == 0 else 5.0, 2.0 * i - 2.0]
                                                  for i in range(crossing)]
        velocities = [[0.0, -1.0]] + [[0.7 if i % 2 == 0 else -0.7, 0.0] for i in range(crossing)]
        self.humans, self.human_velocities = np.array(starts), np.array(velocities)
        self.human_radii = np.full(len(starts), 0.3)

    def robot_state(self) -> dict:
        velocity = self.speed * np.array([math.cos(self.heading), math.sin(self.heading)])
        return {"position": self.position, "velocity": velocity, "heading": self.heading, "goal": self.goal,
                "v_pref": self.v_pref, "radius": self.radius}

    def tracked_humans(self) -> dict:
        return {"positions": self.humans, "velocities": self.human_velocities, "radii": self.human_radii}

    def apply(self, speed: float, turn: float, dt: float) -> None:
        """The unicycle as the simulator moves it: turn first, then drive at `speed` along the new heading."""
        self.heading = (self.heading + turn + math.pi) % (2 * math.pi) - math.pi
        self.speed = speed
        self.position = self.position + speed * dt * np.array([math.cos(self.heading), math.sin(self.heading)])
        self.humans = self.humans + self.human_velocities * dt

    def nearest_gap(self) -> float:
        return float((np.linalg.norm(self.humans - self.position, axis=1) - self.human_radii - self.radius).min())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("navigator", help="ONNX file written by `socnav export`")
    parser.add_argument("--steps", type=int, default=80, help="control steps at most (20 s at 4 Hz)")
    parser.add_argument("--fast", action="store_true", help="do not wait for the 4 Hz clock")
    parser.add_argument("--crossing", type=int, default=0, help="people crossing the robot's path, besides the "
                                                                  "one walking towards it")
    parser.add_argument("--thresholds", default=None, help="safety thresholds: mc | ensemble | a `socnav calibrate` "
                                                           "file (default: those exported with the navigator)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the scene and of the dropout masks")
    args = parser.parse_args()

    navigator = SafeNavigator.load(args.navigator, thresholds=args.thresholds, seed=args.seed)
    scene = Scene(args.seed, args.crossing)
    navigator.reset()  # a new navigation task
    latencies = []
    next_tick = time.monotonic()
    print("step  time    v     dtheta  fallback  u_ep(heading)  u_feat  nearest gap")
    for step in range(args.steps):
        start = time.perf_counter()
        decision = navigator.act(scene.robot_state(), scene.tracked_humans())
        latencies.append(time.perf_counter() - start)
        speed, turn = decision.command
        print(f"{step:4d}  {step * PERIOD:5.2f}  {speed:4.2f}  {turn:+6.3f}  {decision.fallback!s:8s}  "
              f"{decision.windowed['u_ep_heading']:13.4f}  {decision.windowed['u_feat']:6.3f}  "
              f"{scene.nearest_gap():6.2f}")
        scene.apply(speed, turn, PERIOD)
        if scene.nearest_gap() < 0:
            print("collision")
            break
        if np.linalg.norm(scene.goal - scene.position) < 0.3:
            print(f"goal reached after {(step + 1) * PERIOD:.2f} s")
            break
        if not args.fast:
            next_tick += PERIOD
            time.sleep(max(0.0, next_tick - time.monotonic()))
    print(f"decision latency: median {np.median(latencies) * 1e3:.2f} ms, max {max(latencies) * 1e3:.2f} ms "
          f"(budget {PERIOD * 1e3:.0f} ms)")


if __name__ == "__main__":
    main()
