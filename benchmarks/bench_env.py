"""Benchmark: env-steps per second of the batched `SocialNavVecEnv` vs a CrowdNav-style REFERENCE loop, same run.

    python benchmarks/bench_env.py            # full run (about a minute)
    python benchmarks/bench_env.py --quick    # shorter samples, fewer repeats (< 30 s)

What is measured (everything on ONE core: thread pools are capped to 1 and the process is pinned to CPU 0):

* ours: `socnav.make_vec_env({"scenario": "circle_crossing", "n_humans": 5}, n_envs=N)` stepped with `vec.step(actions)`
  in a loop (random actions drawn up front with numpy, auto-reset, SB3 infos, batched observations), N = 1, 16, 256.
* REFERENCE: the same world simulated the way CrowdNav (vita-epfl/CrowdNav, `CrowdSim.step` + `ORCA.predict`) does it:
  a Python object per agent, every human's ORCA policy owning its own RVO2 simulator (pyrvo) into which it writes all
  agents' states every step and calls doStep to read back its own velocity; observation, reward and collision / goal
  checks in Python, human by human; environments stepped one after another, DummyVecEnv style, with auto-reset.
* ORCA cost per agent-step of our numba kernel vs pyrvo's doStep (`bench_orca.measure_orca_cost`).
* the cost of the default reward's disturbance term (a second, robot-free ORCA solve for humans near the robot).

The ratio column is ours / reference on the same actions-per-step workload; the reference computes no disturbance term
(see `ReferenceCrowdSim.step`), so the ratio against the default VecEnv is conservative.
"""

from __future__ import annotations

import _bench  # benchmarks/_bench.py: first, so that the thread pools are capped before numpy / numba load

_bench.single_thread()
PINNED = _bench.pin_to_one_core()

import argparse  # noqa: E402
import math  # noqa: E402
import os  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402

try:  # the reference loop and the ORCA comparison run RVO2 itself: without it there is nothing to compare against
    import pyrvo
except ImportError:
    sys.exit('error: benchmarks/bench_env.py needs the RVO2 reference pyrvo: pip install "pyrvo>=0.4.3" '
             '(or the test extras: pip install -e ".[test]")')
from rich.console import Console  # noqa: E402
from rich.table import Table  # noqa: E402

try:
    import socnav
except ImportError:  # a checkout without `pip install -e .`
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "src"))
    import socnav
from bench_orca import measure_orca_cost  # noqa: E402  (benchmarks/ is on sys.path: the script's directory)

from socnav.config import EnvConfig  # noqa: E402

ENV_CONFIG: dict[str, Any] = {"scenario": "circle_crossing", "n_humans": 5}
N_ENVS = (1, 16, 256)
TARGET_N_ENVS = 256
TARGET_STEPS_PER_S = 100_000
TARGET_RATIO = 30.0


# =====================================================================================================================
# REFERENCE: a CrowdNav-style simulator, one environment at a time (modelled on vita-epfl/CrowdNav
# crowd_sim/envs/crowd_sim.py CrowdSim.step and crowd_sim/envs/policy/orca.py ORCA.predict; written from scratch).
# It simulates the same world as socnav's circle_crossing: 1 unicycle robot + 5 ORCA humans on a 7 m circle crossing to
# their antipodes (+-0.5 m jitter, starts and goals >= 1 m apart), robot on one of four diameters, radii 0.3 m, v_pref
# ~ U(0.5, 1), personal spaces ~ U(0.3, 0.7) m, dt = 0.25 s, ORCA time horizon 5 s, neighbour dist 10 m, 10 neighbours.
# Differences kept on purpose, because RVO2 cannot express them or because they are no extra work:
#   * RVO2 splits avoidance 50/50 between every pair; socnav humans take a `cooperation` share w.r.t. the robot.
#     (Same solver work either way.) The personal-space pad IS modelled: a human's simulator gives the robot a radius
#     grown by that human's personal space, as socnav's radius_pad does.
#   * no disturbance reward term (it would need a second RVO2 solve per nearby human; see the third table for what it
#     costs us), no CrowdNav render-history recording, no human-human collision logging.
# =====================================================================================================================


class ObservableState:
    """What an agent shows the others (CrowdNav `ObservableState`)."""

    def __init__(self, px: float, py: float, vx: float, vy: float, radius: float):
        self.px, self.py, self.vx, self.vy, self.radius = px, py, vx, vy, radius
        self.position = (px, py)
        self.velocity = (vx, vy)


class FullState(ObservableState):
    """An agent's own full state (CrowdNav `FullState`)."""

    def __init__(self, px, py, vx, vy, radius, gx, gy, v_pref, theta):
        super().__init__(px, py, vx, vy, radius)
        self.gx, self.gy, self.v_pref, self.theta = gx, gy, v_pref, theta
        self.goal_position = (gx, gy)


class JointState:
    def __init__(self, self_state: FullState, human_states: list[ObservableState]):
        self.self_state = self_state
        self.human_states = human_states


class ReferenceORCA:
    """CrowdNav `ORCA` policy: owns one RVO2 simulator, rewrites every agent's state into it each step, runs
    doStep for the whole simulator and returns its own (agent 0's) new velocity. Other agents' goals are unknown:
    pref velocity 0."""

    def __init__(self, world: EnvConfig):
        self.time_step = world.time_step
        self.neighbor_dist = world.orca.neighbor_dist
        self.max_neighbors = world.orca.max_neighbors
        self.time_horizon = world.orca.time_horizon
        self.time_horizon_obst = world.orca.time_horizon
        self.radius = world.human_radius
        self.max_speed = 1.0
        self.sim = None

    def predict(self, state: JointState) -> tuple[float, float]:
        me = state.self_state
        params = (self.neighbor_dist, self.max_neighbors, self.time_horizon, self.time_horizon_obst)
        if self.sim is not None and self.sim.get_num_agents() != len(state.human_states) + 1:
            self.sim = None
        if self.sim is None:
            self.sim = pyrvo.RVOSimulator(self.time_step, *params, self.radius, self.max_speed)
            self.sim.add_agent(me.position, *params, me.radius, me.v_pref, me.velocity)
            for other in state.human_states:
                self.sim.add_agent(other.position, *params, other.radius, self.max_speed, other.velocity)
        else:
            self.sim.set_agent_position(0, me.position)
            self.sim.set_agent_velocity(0, me.velocity)
            for i, other in enumerate(state.human_states):
                self.sim.set_agent_position(i + 1, other.position)
                self.sim.set_agent_velocity(i + 1, other.velocity)

        # Preferred velocity: v_pref towards the goal, slowing down to stop on it (socnav's human rule).
        dx, dy = me.gx - me.px, me.gy - me.py
        distance = math.hypot(dx, dy)
        if distance < 1e-9:
            pref = (0.0, 0.0)
        else:
            speed = min(me.v_pref, distance / self.time_step)
            pref = (speed * dx / distance, speed * dy / distance)
        self.sim.set_agent_pref_velocity(0, pref)
        for i in range(len(state.human_states)):
            self.sim.set_agent_pref_velocity(i + 1, (0.0, 0.0))

        self.sim.do_step()
        velocity = self.sim.get_agent_velocity(0)
        return velocity.x, velocity.y


class Agent:
    """CrowdNav-style agent: physical attributes + a policy."""

    def __init__(self, radius: float, v_pref: float):
        self.radius, self.v_pref = radius, v_pref
        self.px = self.py = self.gx = self.gy = self.vx = self.vy = self.theta = 0.0

    def set(self, px, py, gx, gy, vx, vy, theta) -> None:
        self.px, self.py, self.gx, self.gy, self.vx, self.vy, self.theta = px, py, gx, gy, vx, vy, theta

    def get_observable_state(self) -> ObservableState:
        return ObservableState(self.px, self.py, self.vx, self.vy, self.radius)

    def get_full_state(self) -> FullState:
        return FullState(self.px, self.py, self.vx, self.vy, self.radius, self.gx, self.gy, self.v_pref, self.theta)


class Human(Agent):
    """A human with its own ORCA policy (and its own RVO2 simulator) and a personal space that pads the robot."""

    def __init__(self, world: EnvConfig, v_pref: float, personal_space: float, cooperation: float):
        super().__init__(world.human_radius, v_pref)
        self.personal_space, self.cooperation = personal_space, cooperation
        self.policy = ReferenceORCA(world)

    def act(self, ob: list[ObservableState]) -> tuple[float, float]:
        return self.policy.predict(JointState(self.get_full_state(), ob))

    def step(self, velocity: tuple[float, float], time_step: float) -> None:
        self.vx, self.vy = velocity
        self.px += self.vx * time_step
        self.py += self.vy * time_step


class Robot(Agent):
    """Unicycle robot; action [-1, 1]^2 -> v = v_pref (a0 + 1) / 2, dtheta = max_heading_change a1
    (socnav's mapping)."""

    def __init__(self, world: EnvConfig, v_pref: float):
        super().__init__(world.robot_radius, v_pref)
        self.max_heading_change = world.max_heading_change

    def command(self, action) -> tuple[float, float]:
        a_speed = min(max(float(action[0]), -1.0), 1.0)
        a_turn = min(max(float(action[1]), -1.0), 1.0)
        return self.v_pref * (a_speed + 1.0) / 2.0, self.max_heading_change * a_turn

    def step(self, speed: float, theta: float, time_step: float) -> None:
        self.theta = theta
        self.vx, self.vy = speed * math.cos(theta), speed * math.sin(theta)
        self.px += self.vx * time_step
        self.py += self.vy * time_step


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def _point_to_segment_dist(x1, y1, x2, y2, x3, y3) -> float:
    """Distance from (x3, y3) to the segment (x1, y1)-(x2, y2) (CrowdNav utils)."""
    px, py = x2 - x1, y2 - y1
    if px == 0 and py == 0:
        return math.hypot(x3 - x1, y3 - y1)
    u = ((x3 - x1) * px + (y3 - y1) * py) / (px * px + py * py)
    u = min(max(u, 0.0), 1.0)
    return math.hypot(x1 + u * px - x3, y1 + u * py - y3)


class ReferenceCrowdSim:
    """REFERENCE single environment, CrowdNav `CrowdSim` style: reset() -> obs;
    step(action) -> obs, reward, done, info."""

    ROBOT_ANGLES = (0.0, 0.5 * math.pi, math.pi, 1.5 * math.pi)

    def __init__(self, world: EnvConfig, seed: int):
        self.world = world
        self.rng = np.random.default_rng(seed)
        self.n_humans = world.humans_range()[1]
        self.max_humans = world.max_humans
        reward = world.reward
        self.w_goal, self.w_collision, self.w_time = reward.goal, reward.collision, reward.time
        self.w_progress, self.w_personal_space = reward.progress, reward.personal_space
        self.time_step = world.time_step
        self.robot: Robot | None = None
        self.humans: list[Human] = []
        self.global_time = 0.0
        self.time_limit = 0.0

    # ---- episode generation (circle crossing, rejection sampling as in CrowdNav's generate_circle_crossing_human) --
    def reset(self) -> dict[str, np.ndarray]:
        w, rng = self.world, self.rng
        self.robot = Robot(w, rng.uniform(*w.preferred_speed))
        angle = self.ROBOT_ANGLES[int(rng.integers(4))]
        radius = w.circle_radius
        rx, ry = radius * math.cos(angle), radius * math.sin(angle)
        self.robot.set(rx, ry, -rx, -ry, 0.0, 0.0, math.atan2(-2 * ry, -2 * rx))
        self.humans = []
        for _ in range(self.n_humans):
            self.humans.append(self._circle_crossing_human())
        self.global_time = 0.0
        self.time_limit = w.timeout_factor * math.hypot(2 * rx, 2 * ry) / self.robot.v_pref + w.timeout_margin
        return self._observation()

    def _circle_crossing_human(self) -> Human:
        w, rng = self.world, self.rng
        human = Human(w, rng.uniform(*w.preferred_speed), rng.uniform(*w.personal_space), rng.uniform(*w.cooperation))
        jitter, radius = w.circle_jitter, w.circle_radius
        for _ in range(200):
            angle = rng.uniform(0.0, 2 * math.pi)
            px = radius * math.cos(angle) + rng.uniform(-jitter, jitter)
            py = radius * math.sin(angle) + rng.uniform(-jitter, jitter)
            gx = -radius * math.cos(angle) + rng.uniform(-jitter, jitter)
            gy = -radius * math.sin(angle) + rng.uniform(-jitter, jitter)
            collide = False
            for agent in [self.robot, *self.humans]:
                if math.hypot(px - agent.px, py - agent.py) < 1.0 or math.hypot(gx - agent.gx, gy - agent.gy) < 1.0:
                    collide = True
                    break
            if not collide:
                break
        human.set(px, py, gx, gy, 0.0, 0.0, 0.0)
        return human

    # ---- one step (CrowdSim.step) ---------------------------------------------------------------------------------
    def step(self, action) -> tuple[dict[str, np.ndarray], float, bool, dict[str, Any]]:
        robot, dt = self.robot, self.time_step
        # every human acts on the others' observable states; it sees the robot grown by its own personal space
        human_actions = []
        for human in self.humans:
            ob = [other.get_observable_state() for other in self.humans if other is not human]
            ob.append(ObservableState(robot.px, robot.py, robot.vx, robot.vy, robot.radius + human.personal_space))
            human_actions.append(human.act(ob))

        speed, turn = robot.command(action)
        theta = _wrap(robot.theta + turn)
        rvx, rvy = speed * math.cos(theta), speed * math.sin(theta)

        # collision detection: closest approach during the step, human by human (CrowdNav point_to_segment_dist)
        closest_gap = math.inf
        for human, (hvx, hvy) in zip(self.humans, human_actions, strict=True):
            px, py = human.px - robot.px, human.py - robot.py
            ex, ey = px + (hvx - rvx) * dt, py + (hvy - rvy) * dt
            gap = _point_to_segment_dist(px, py, ex, ey, 0.0, 0.0) - human.radius - robot.radius
            closest_gap = min(closest_gap, gap)

        # update all agents
        old_goal_distance = math.hypot(robot.gx - robot.px, robot.gy - robot.py)
        robot.step(speed, theta, dt)
        for human, velocity in zip(self.humans, human_actions, strict=True):
            human.step(velocity, dt)
        self.global_time += dt
        goal_distance = math.hypot(robot.gx - robot.px, robot.gy - robot.py)

        # reward: time, progress, personal-space intrusion per human; then collision / goal / time-out
        reward = -self.w_time * dt + self.w_progress * (old_goal_distance - goal_distance)
        nearest_gap, intrusions = math.inf, 0
        for human in self.humans:
            gap = math.hypot(human.px - robot.px, human.py - robot.py) - human.radius - robot.radius
            nearest_gap = min(nearest_gap, gap)
            if gap < human.personal_space:
                intrusions += 1
                reward -= self.w_personal_space * (1.0 - max(gap, 0.0) / human.personal_space)
        if closest_gap < 0.0:
            reward -= self.w_collision
            done, outcome = True, "collision"
        elif goal_distance < self.world.goal_tolerance:
            reward += self.w_goal
            done, outcome = True, "goal"
        elif self.global_time > self.time_limit:
            done, outcome = True, "timeout"
        else:
            done, outcome = False, None
        info: dict[str, Any] = {"time": self.global_time, "nearest_gap": nearest_gap, "intrusions": intrusions}
        if outcome is not None:
            info["outcome"] = outcome
            info["TimeLimit.truncated"] = outcome == "timeout"
        return self._observation(), reward, done, info

    # ---- robot-centric observation: rotate into the goal frame, humans sorted by gap (closest last) ---------------
    def _observation(self) -> dict[str, np.ndarray]:
        robot = self.robot
        gx, gy = robot.gx - robot.px, robot.gy - robot.py
        goal_angle = math.atan2(gy, gx)
        cos_a, sin_a = math.cos(goal_angle), math.sin(goal_angle)
        rows = []
        for human in self.humans:
            dx, dy = human.px - robot.px, human.py - robot.py
            dvx, dvy = human.vx - robot.vx, human.vy - robot.vy
            combined = human.radius + robot.radius
            gap = math.hypot(dx, dy) - combined
            rows.append((
                gap,
                (cos_a * dx + sin_a * dy, -sin_a * dx + cos_a * dy, cos_a * dvx + sin_a * dvy,
                 -sin_a * dvx + cos_a * dvy, human.radius, combined, gap),
            ))
        rows.sort(key=lambda row: -row[0])  # farthest first, closest last
        rows = rows[max(len(rows) - self.max_humans, 0):]
        humans = np.zeros((self.max_humans, 7), dtype=np.float32)
        mask = np.zeros(self.max_humans, dtype=np.float32)
        if rows:
            humans[: len(rows)] = [row[1] for row in rows]
            mask[: len(rows)] = 1.0
        robot_obs = np.array(
            [math.hypot(gx, gy), _wrap(robot.theta - goal_angle), math.hypot(robot.vx, robot.vy), robot.v_pref,
             robot.radius],
            dtype=np.float32,
        )
        return {"robot": robot_obs, "humans": humans, "humans_mask": mask}


class ReferenceVecLoop:
    """REFERENCE batch: `n_envs` ReferenceCrowdSim stepped one after another (SB3 DummyVecEnv style), auto-reset,
    observations copied into batched buffers."""

    def __init__(self, world: EnvConfig, n_envs: int, seed: int = 0):
        self.envs = [ReferenceCrowdSim(world, seed + i) for i in range(n_envs)]
        self.buffers = {
            "robot": np.zeros((n_envs, 5), dtype=np.float32),
            "humans": np.zeros((n_envs, world.max_humans, 7), dtype=np.float32),
            "humans_mask": np.zeros((n_envs, world.max_humans), dtype=np.float32),
        }
        self.rewards = np.zeros(n_envs, dtype=np.float32)
        self.dones = np.zeros(n_envs, dtype=bool)

    def _save(self, i: int, obs: dict[str, np.ndarray]) -> None:
        for key, buffer in self.buffers.items():
            buffer[i] = obs[key]

    def reset(self) -> dict[str, np.ndarray]:
        for i, env in enumerate(self.envs):
            self._save(i, env.reset())
        return {key: value.copy() for key, value in self.buffers.items()}

    def step(self, actions: np.ndarray):
        infos = []
        for i, env in enumerate(self.envs):
            obs, reward, done, info = env.step(actions[i])
            if done:
                info["terminal_observation"] = obs
                obs = env.reset()
            self._save(i, obs)
            self.rewards[i], self.dones[i] = reward, done
            infos.append(info)
        return {key: value.copy() for key, value in self.buffers.items()}, self.rewards.copy(), self.dones.copy(), infos


def check_reference(steps: int = 100, seed: int = 3) -> tuple[float, float, int]:
    """Faithfulness check of the REFERENCE: with cooperation fixed at 0.5 (RVO2's 50/50 split) and no disturbance term,
    start it from a VecEnv episode's initial state and step both with the same actions.

    Returns (max |observation difference|, max |reward difference|, steps compared); RVO2 works in float32, so
    differences of ~1e-6 are expected.
    """
    vec = socnav.make_vec_env(dict(ENV_CONFIG), n_envs=1, cooperation=(0.5, 0.5), reward={"disturbance": 0.0})
    vec.seed(seed)
    first = vec.reset()
    w = vec.world
    env = ReferenceCrowdSim(vec.config, seed)
    env.reset()
    env.robot.v_pref = float(w.preferred_speeds[0, 0])
    env.robot.set(*w.positions[0, 0], *w.goals[0, 0], 0.0, 0.0, float(w.heading[0]))
    env.time_limit = float(w.time_limit[0])
    for k, human in enumerate(env.humans, start=1):
        human.v_pref, human.personal_space = float(w.max_speeds[0, k]), float(w.personal_space[0, k])
        human.set(*w.positions[0, k], *w.goals[0, k], 0.0, 0.0, 0.0)
    obs = env._observation()
    obs_diff = max(float(np.abs(obs[key] - first[key][0]).max()) for key in obs)
    reward_diff, compared = 0.0, 0
    for action in np.random.default_rng(seed).uniform(-1.0, 1.0, (steps, 1, 2)):
        ours, reward, done, _ = vec.step(action)
        obs, ref_reward, ref_done, _ = env.step(action[0])
        compared += 1
        if done[0] or ref_done:  # compare up to the end of the first episode (the VecEnv auto-resets)
            reward_diff = max(reward_diff, abs(float(reward[0]) - ref_reward))
            if done[0] != ref_done:
                return math.inf, math.inf, compared
            break
        obs_diff = max(obs_diff, max(float(np.abs(obs[key] - ours[key][0]).max()) for key in obs))
        reward_diff = max(reward_diff, abs(float(reward[0]) - ref_reward))
    vec.close()
    return obs_diff, reward_diff, compared


# =====================================================================================================================
# Measurement
# =====================================================================================================================


def _calibrate(step: Callable[[np.ndarray], Any], n_envs: int, seconds: float, rng: np.random.Generator) -> int:
    """Batched steps that take about `seconds` (doubling until a trial takes >= 50 ms; also extra warm-up)."""
    calls, elapsed = 1, 0.0
    while elapsed < 0.05:
        actions = rng.uniform(-1.0, 1.0, (calls, n_envs, 2)).astype(np.float32)
        start = time.perf_counter()
        for action in actions:
            step(action)
        elapsed = time.perf_counter() - start
        calls *= 2
    return max(1, math.ceil(seconds * (calls // 2) / elapsed))


def _measure_interleaved(steppers: dict[str, tuple[Callable[[np.ndarray], Any], float]], n_envs: int, repeats: int,
                         seed: int = 2) -> dict[str, dict]:
    """Env-steps/s of each warmed-up `step(actions)` in `steppers` ({label: (step, seconds per sample)}).

    Samples of the steppers alternate (A B A B ...), so drift of the machine hits all of them alike; each sample's
    actions are drawn up front; each stepper gets `repeats` samples. Returns {label: {median, min, max, calls}}.
    """
    rng = np.random.default_rng(seed)
    calls = {label: _calibrate(step, n_envs, seconds, rng) for label, (step, seconds) in steppers.items()}
    rates: dict[str, list[float]] = {label: [] for label in steppers}
    for _ in range(repeats):
        for label, (step, _seconds) in steppers.items():
            actions = rng.uniform(-1.0, 1.0, (calls[label], n_envs, 2)).astype(np.float32)
            start = time.perf_counter()
            for action in actions:
                step(action)
            rates[label].append(calls[label] * n_envs / (time.perf_counter() - start))
    return {
        label: {"median": statistics.median(r), "min": min(r), "max": max(r), "calls": calls[label]}
        for label, r in rates.items()
    }


def warmed_vec_env(n_envs: int, warmup_steps: int, **overrides: Any):
    """Our VecEnv, reset and stepped `warmup_steps` times (numba cache load; spreads envs over episode phases)."""
    vec = socnav.make_vec_env(dict(ENV_CONFIG), n_envs=n_envs, **overrides)
    vec.seed(0)
    vec.reset()
    for action in np.random.default_rng(1).uniform(-1.0, 1.0, (warmup_steps, n_envs, 2)).astype(np.float32):
        vec.step(action)
    return vec


def warmed_reference(world: EnvConfig, n_envs: int, warmup_steps: int) -> ReferenceVecLoop:
    """The REFERENCE loop, reset, each env stepped a random 0..warmup_steps times (spread over episode phases)."""
    loop = ReferenceVecLoop(world, n_envs, seed=0)
    loop.reset()
    rng = np.random.default_rng(1)
    for env in loop.envs:
        for action in rng.uniform(-1.0, 1.0, (int(rng.integers(0, warmup_steps + 1)), 2)):
            _, _, done, _ = env.step(action)
            if done:
                env.reset()
    return loop


def _rate(value: float) -> str:
    return f"{value:,.0f}"


def _spread(result: dict) -> str:
    return f"{_rate(result['median'])} [dim]\\[{_rate(result['min'])}-{_rate(result['max'])}][/]"


def _version(package: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(package)
    except PackageNotFoundError:
        return "?"


def _verdict(ok: bool) -> str:
    return "[bold green]PASS[/]" if ok else "[bold red]FAIL[/]"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="shorter samples and fewer repeats (< 60 s)")
    args = parser.parse_args(argv)
    console = Console(width=max(Console().width, 132))
    t_start = time.perf_counter()

    if args.quick:
        seconds, ref_seconds, repeats, orca_repeats = 0.5, 0.5, 3, 5
        vec_warmup, ref_warmup = 200, 20
    else:
        seconds, ref_seconds, repeats, orca_repeats = 1.0, 1.0, 7, 20
        vec_warmup, ref_warmup = 400, 100

    import numba

    console.print(f"[bold]socnav VecEnv benchmark[/] ({'quick' if args.quick else 'full'} run)")
    console.print("single thread: " + ", ".join(f"{v}={os.environ[v]}" for v in _bench.THREAD_VARIABLES)
                  + f" (numba.config.NUMBA_NUM_THREADS={numba.config.NUMBA_NUM_THREADS})")
    console.print(f"single core:   {PINNED}")
    console.print(f"world: {ENV_CONFIG} (1 robot + 5 humans); python {sys.version.split()[0]}, numpy {np.__version__}, "
                  f"numba {numba.__version__}, pyrvo {_version('pyrvo')}")
    console.print(f"timing: time.perf_counter; after warm-up, {repeats} samples of ~{seconds:g} s per stepper, "
                  f"samples of the compared steppers interleaved; median \\[min-max] env-steps/s reported")

    t_warm = time.perf_counter()
    warmed_vec_env(2, 5).close()  # loads (or compiles) every numba kernel the step uses
    warmed_reference(socnav.load_config(dict(ENV_CONFIG)), 2, 5)
    console.print(f"warm-up (numba compile / cache load, pyrvo): {time.perf_counter() - t_warm:.1f} s\n")

    obs_diff, reward_diff, compared = check_reference()
    console.print(f"REFERENCE faithfulness check (cooperation=0.5, no disturbance term; same initial state and actions "
                  f"as the VecEnv): max |obs diff| {obs_diff:.1e}, max |reward diff| {reward_diff:.1e} over {compared} "
                  f"steps {_verdict(obs_diff < 1e-4 and reward_diff < 1e-4)}\n")
    world = socnav.load_config(dict(ENV_CONFIG))

    # ---- table 1: ours vs reference --------------------------------------------------------------------------------
    table = Table(title="Env-steps/s, one core: socnav VecEnv vs REFERENCE (CrowdNav-style loop, one env at a time)")
    for column in ("n_envs", "socnav VecEnv", "REFERENCE loop", "ratio", f"target >= {TARGET_STEPS_PER_S:,}/s",
                   f"target >= {TARGET_RATIO:g}x"):
        table.add_column(column, justify="right")
    ratios = {}
    ours_256 = None
    ref_256 = None
    for n_envs in N_ENVS:
        vec = warmed_vec_env(n_envs, vec_warmup)
        loop = warmed_reference(world, n_envs, ref_warmup)
        measured = _measure_interleaved({"ours": (vec.step, seconds), "ref": (loop.step, ref_seconds)}, n_envs, repeats)
        ours, ref = measured["ours"], measured["ref"]
        vec.close()
        ratio = ours["median"] / ref["median"]
        ratios[n_envs] = ratio
        if n_envs == TARGET_N_ENVS:
            ours_256, ref_256 = ours, ref
            speed_target = _verdict(ours["median"] >= TARGET_STEPS_PER_S)
            ratio_target = _verdict(ratio >= TARGET_RATIO)
        else:
            speed_target = ratio_target = "[dim]at 256[/]"
        table.add_row(
            str(n_envs),
            _spread(ours),
            _spread(ref),
            f"{ratio:.1f}x",
            speed_target,
            ratio_target,
        )
        console.print(f"  measured n_envs={n_envs} ({time.perf_counter() - t_start:.0f} s elapsed)", style="dim")
    console.print(table)
    console.print("[dim]VecEnv: vec.step(actions) with auto-reset, SB3 infos, default reward (incl. disturbance). "
                  "REFERENCE: per-agent Python objects, one pyrvo RVOSimulator per human (doStep of all 6 agents to "
                  "get one velocity), Python observation / reward / collision checks, DummyVecEnv-style loop, "
                  "no disturbance term.[/]\n")

    # ---- table 2: ORCA cost per agent-step -------------------------------------------------------------------------
    orca = Table(title="ORCA cost per agent-step (us), single thread; speedup = pyrvo doStep / ours (wrapper)")
    for column in ("envs x agents", "numba kernel", "numba wrapper", "pyrvo doStep", "speedup"):
        orca.add_column(column, justify="right")
    for row in measure_orca_cost(repeats=orca_repeats):
        orca.add_row(
            f"{row['n_envs']} x {row['n_agents']}",
            f"{row['kernel_us']:.3f}",
            f"{row['wrapper_us']:.3f}",
            f"{row['pyrvo_us']:.3f}",
            f"{row['speedup']:.1f}x",
        )
    console.print(orca)
    console.print()

    # ---- table 3: what the disturbance reward term costs -----------------------------------------------------------
    with_term = warmed_vec_env(TARGET_N_ENVS, vec_warmup)
    without_term = warmed_vec_env(TARGET_N_ENVS, vec_warmup, reward={"disturbance": 0.0})
    measured = _measure_interleaved(
        {"default": (with_term.step, seconds), "off": (without_term.step, seconds)}, TARGET_N_ENVS, repeats
    )
    default, no_disturbance = measured["default"], measured["off"]
    cost = Table(title=f"Disturbance reward term at n_envs={TARGET_N_ENVS} (counterfactual robot-free ORCA for humans "
                       f"within reward.social_radius of the robot)")
    for column in ("reward", "env-steps/s", "time per env-step", "vs REFERENCE"):
        cost.add_column(column, justify="right")
    for label, result in (("default (disturbance=0.25)", default), ("reward.disturbance = 0", no_disturbance)):
        cost.add_row(
            label,
            _spread(result),
            f"{1e6 / result['median']:.2f} us",
            f"{result['median'] / ref_256['median']:.1f}x",
        )
    console.print(cost)
    extra = 1e6 / default["median"] - 1e6 / no_disturbance["median"]
    console.print(f"disturbance term: {extra:+.2f} us per env-step "
                  f"({100 * extra / (1e6 / default['median']):+.0f}% of the default step time)\n")

    total = time.perf_counter() - t_start
    passed = ours_256["median"] >= TARGET_STEPS_PER_S and ratios[TARGET_N_ENVS] >= TARGET_RATIO
    console.print(f"targets at n_envs={TARGET_N_ENVS}: {_verdict(passed)}; total benchmark time {total:.1f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
