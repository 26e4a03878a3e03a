"""Loading rclpy from ROS 2 Jazzy's pip wheels (the ``ros2`` extra), with one clear error when it cannot load.
Nothing outside `socnav.ros2`'s nodes imports rclpy; this module itself imports it only when asked.

How the wheels start (read from their packages, ros-wheels-bootstrapper 0.1.2): the C libraries of rclpy, rcl and
Fast DDS live in ``<prefix>/lib`` and ``site-packages/ros_*.libs``, which the dynamic loader finds only through
``LD_LIBRARY_PATH``, read once when a process starts. The wheel ``ros-wheels-bootstrapper`` therefore installs a
``.pth`` file that, at every interpreter start, sets ``LD_LIBRARY_PATH`` and re-executes the interpreter (once: it
marks the environment with ``_ROS_WHEELS_BOOTSTRAP_COMPLETE=1``). No other variable is needed: without
``AMENT_PREFIX_PATH`` and ``RMW_IMPLEMENTATION``, rclpy uses the only middleware installed, Fast DDS
(``rmw_fastrtps_cpp``). A process started with that marker but without the library path (a child given a rebuilt
environment) cannot load rclpy, and nothing done inside it can fix that: `require_rclpy` says so.
"""

from __future__ import annotations

import importlib
import importlib.util
import os
import sys
from types import ModuleType

from socnav.extras import install_hint

__all__ = ["BOOTSTRAP_MARKER", "MESSAGE_PACKAGES", "ROS2_EXTRA", "Ros2Unavailable", "require_rclpy"]

#: The optional extra that installs ROS 2 (pyproject.toml).
ROS2_EXTRA = "ros2"
#: The environment variable ros-wheels-bootstrapper sets once it has put the ROS libraries on the library path.
BOOTSTRAP_MARKER = "_ROS_WHEELS_BOOTSTRAP_COMPLETE"
#: The ROS 2 message packages the nodes use (all standard: common_interfaces and rosgraph_msgs).
MESSAGE_PACKAGES = ("builtin_interfaces", "std_msgs", "geometry_msgs", "nav_msgs", "sensor_msgs", "visualization_msgs",
                    "diagnostic_msgs", "rosgraph_msgs", "rcl_interfaces")


class Ros2Unavailable(RuntimeError):
    """rclpy or a message package cannot be imported; the message says how to install or start it."""


def require_rclpy() -> ModuleType:
    """The imported ``rclpy`` (with every package of :data:`MESSAGE_PACKAGES` importable).

    :raises Ros2Unavailable: the ``ros2`` extra is not installed (the pip command that installs it), or rclpy is
        installed but its libraries are not on the library path (why, and how to start the process instead).
    """
    missing = [name for name in ("rclpy", *MESSAGE_PACKAGES) if importlib.util.find_spec(name) is None]
    if missing:
        raise Ros2Unavailable(f"socnav ros2 needs ROS 2 Jazzy (rclpy and the standard message packages; missing: "
                              f"{', '.join(missing)}): {install_hint(ROS2_EXTRA)}")
    try:
        rclpy = importlib.import_module("rclpy")
        for name in MESSAGE_PACKAGES:
            importlib.import_module(f"{name}.msg")
    except ImportError as exc:
        raise Ros2Unavailable(_library_path_problem(exc)) from None
    return rclpy


def _library_path_problem(error: ImportError) -> str:
    """Why an installed rclpy does not load: almost always its C libraries missing from the library path."""
    reason = " ".join(str(error).split())[:300]
    if os.environ.get(BOOTSTRAP_MARKER) and "shared object" in reason:
        libraries = os.path.join(sys.prefix, "lib")
        return (f"rclpy is installed but cannot load its C libraries ({reason}): this process was started with "
                f"{BOOTSTRAP_MARKER}=1 but without the ROS libraries on LD_LIBRARY_PATH (e.g. {libraries} and "
                f"site-packages/ros_*.libs). Start it without {BOOTSTRAP_MARKER} in its environment, so that the "
                "ROS wheels set the path at start-up, or keep the parent's LD_LIBRARY_PATH")
    return (f"rclpy is installed but does not import ({reason}); reinstall the ros2 extra: "
            f"{install_hint(ROS2_EXTRA)}")
