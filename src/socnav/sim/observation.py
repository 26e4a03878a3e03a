"""One robot's observation and command from plain state arrays, through the environment's own compiled kernels.
The deployed navigator (`socnav.runtime`) and the simulator therefore build identical observations and commands.

`observe_batch` IS the kernel `CrowdWorld.observe` calls (`socnav.sim.world.observe_batch`), and `robot_command`
wraps the one `CrowdWorld.step` calls (`socnav.sim.world.robot_command_batch`): one function each, shared, never a
copy.
"""

from __future__ import annotations

import numpy as np

from socnav.sim.walls import POSE_KEY, SCAN_KEY
from socnav.sim.world import observe_batch, robot_command_batch

__all__ = ["observe_batch", "observe_robot", "robot_command"]

_NO_NOISE_KEY = np.zeros(1, dtype=np.uint64)
_NO_NOISE_STEP = np.zeros(1, dtype=np.int64)


def observe_robot(
    position: np.ndarray,
    velocity: np.ndarray,
    heading: float,
    goal: np.ndarray,
    v_pref: float,
    radius: float,
    human_positions: np.ndarray,
    human_velocities: np.ndarray,
    human_radii: np.ndarray,
    max_humans: int,
    *,
    pose: np.ndarray | None = None,
    scan: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """The observation (batch of one, as `CrowdWorld.observe`) of a robot among ``n`` humans (world frame).

    Inputs are float64 arrays already checked by the caller: ``position``, ``velocity``, ``goal`` (2,);
    ``human_positions``, ``human_velocities`` (n, 2); ``human_radii`` (n,). With more than ``max_humans`` humans
    the closest ``max_humans`` (by gap) are kept, exactly as in the simulator. No observation noise is added.
    The humans are those the robot sees: in a world with occlusion the caller leaves out those behind walls.

    In a world with walls the observation also holds ``pose`` (x, y, yaw in the map frame: ``pose`` (3,)), and
    with a range scan ``scan`` (its ranges (beams,), as `socnav.sim.walls.Walls.scan` reads them); both are
    passed through as float32, as the simulator rounds them.

    :return: ``{"robot": (1, 5), "humans": (1, max_humans, 7), "humans_mask": (1, max_humans)}``, float32, and
        ``"pose"`` (1, 3) / ``"scan"`` (1, beams) when given.
    """
    n_humans = len(human_radii)
    positions = np.empty((1, 1 + n_humans, 2))
    velocities = np.empty((1, 1 + n_humans, 2))
    radii = np.empty((1, 1 + n_humans))
    positions[0, 0], positions[0, 1:] = position, human_positions
    velocities[0, 0], velocities[0, 1:] = velocity, human_velocities
    radii[0, 0], radii[0, 1:] = radius, human_radii
    goals = np.zeros_like(positions)  # the kernel reads the robot's goal (slot 0) only
    goals[0, 0] = goal
    active = np.ones((1, 1 + n_humans), dtype=np.bool_)
    robot, humans, mask = observe_batch(positions, velocities, radii, goals, np.array([float(v_pref)]), active,
                                        np.array([float(heading)]), int(max_humans))
    observation = {"robot": robot, "humans": humans, "humans_mask": mask}
    if pose is not None:
        observation[POSE_KEY] = np.asarray(pose, dtype=np.float64).reshape(1, 3).astype(np.float32)
    if scan is not None:
        observation[SCAN_KEY] = np.array(scan, dtype=np.float32).reshape(1, -1)
    return observation


def robot_command(action: np.ndarray, v_pref: float, max_heading_change: float) -> tuple[float, float]:
    """``(v, dtheta)`` of an action in [-1, 1]^2 (clipped), as the simulator applies it without action noise:
    ``v = v_pref (a0 + 1) / 2``, ``dtheta = max_heading_change * a1``."""
    speed, turn = robot_command_batch(np.asarray(action, dtype=np.float64).reshape(1, 2), np.array([float(v_pref)]),
                                      float(max_heading_change), _NO_NOISE_KEY, _NO_NOISE_STEP, 0.0, 0.0)
    return float(speed[0]), float(turn[0])
