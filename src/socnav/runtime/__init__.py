"""socnav's torch-free runtime: run an exported navigator (`socnav export`) on a robot with onnxruntime.
Imports NumPy, onnxruntime and socnav's simulator kernels and safety layer — never torch or Stable-Baselines3.

Example (one control step; a ROS 2 node would call `act` from its timer callback)::

    from socnav.runtime import SafeNavigator

    navigator = SafeNavigator.load("navigator.onnx", seed=0)
    navigator.reset()                                            # at the start of every navigation task
    decision = navigator.act(
        {"position": [0, -4], "velocity": [0, 0], "heading": 1.57, "goal": [0, 4], "v_pref": 1.0, "radius": 0.3},
        {"positions": [[0.2, 1.0]], "velocities": [[0, -1]], "radii": [0.3]},
    )
    v, dtheta = decision.command                                 # decision.fallback, decision.uncertainty
    # decision.fault is None unless the network's output was not finite (then: fallback, or a stop)

A navigator exported from a world with walls keeps its fallback off them (``SafeNavigator.load(..., walls=polygons)``
gives it another map), planning from the robot's pose in the map frame (``act(..., pose=(x, y, yaw))``; default: the
robot's position and heading); one whose policy reads a range scan needs it: ``act(..., scan=ranges)``.

`SafeNavigator.load` refuses (`NavigatorLoadError`, at load) a file that is corrupted (its sha256 checksum), of
another format version, or whose metadata or graph is invalid; `act` refuses invalid states (`InputError`).
"""

from socnav.runtime.format import NavigatorMetadata
from socnav.runtime.navigator import (
    NON_FINITE_OBSERVATION,
    NON_FINITE_OUTPUT,
    STOPPED,
    Decision,
    HumansState,
    InputError,
    RobotState,
    SafeNavigator,
)
from socnav.runtime.network import DropoutStream, ExportedPolicy, NavigatorLoadError, NetworkOutput
from socnav.uncertainty.stats import Uncertainty

__all__ = [
    "NON_FINITE_OBSERVATION",
    "NON_FINITE_OUTPUT",
    "STOPPED",
    "Decision",
    "DropoutStream",
    "ExportedPolicy",
    "HumansState",
    "InputError",
    "NavigatorLoadError",
    "NavigatorMetadata",
    "NetworkOutput",
    "RobotState",
    "SafeNavigator",
    "Uncertainty",
]
