"""Robot descriptions: load a serial revolute arm by name or from a URDF path.

One URDF feeds the project's own Newton-Euler code, pinocchio and pybullet. Built-in names:

- ``ur5_paper``: the paper's UR5-like arm (Sec. IV-A), generated from ``data/ur5_paper.yaml``.
- ``ur5``: the real UR5 (example-robot-data).
- ``panda``: the 7-joint Franka Emika Panda (example-robot-data; finger joints locked at 0).

Example::

    from models.robots import load_robot
    robot = load_robot("ur5_paper")          # or load_robot("path/to/arm.urdf")
    robot.n_joints, robot.joint_names, robot.torque_limit_nm

This module needs only numpy and the standard library, so the sim target can import it.
"""

from __future__ import annotations

from models.robots.description import RobotModel, load_robot, robot_names, urdf_path

__all__ = ["RobotModel", "load_robot", "robot_names", "urdf_path"]
