"""socnav on a robot: the torch-free safe navigator (`socnav.runtime`) and the crowd simulator as ROS 2 nodes.
Importing this package imports no rclpy; the nodes need the ``ros2`` extra (ROS 2 Jazzy's pip wheels).

* `socnav.ros2.navigator.NavigatorNode` (``socnav ros2 navigator``): odometry, goal and tracked humans in,
  ``cmd_vel`` out, with diagnostics, the decision's state and RViz markers;
* `socnav.ros2.simulator.SimulatorNode` (``socnav ros2 sim``): the crowd world publishing what a robot's drivers
  and tracker would, stepping on ``cmd_vel`` in real time or in lock-step with the navigator;
* `socnav.ros2.messages`: the conversions between ROS messages and the navigator's plain arrays;
* `socnav.ros2.environment.require_rclpy`: imports rclpy, or says how to install it.

See docs/ros2.md for the topics, parameters and a launch example.
"""

from socnav.ros2.environment import ROS2_EXTRA, Ros2Unavailable, require_rclpy

__all__ = ["ROS2_EXTRA", "Ros2Unavailable", "require_rclpy"]
