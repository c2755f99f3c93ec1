"""How a robot model is named to the other processes: a built-in name, or its URDF file.

A robot loaded from a URDF path carries the URDF's ``<robot name>``, which no other process can
load by name: the simulation twin and the HIL target get the file instead, and the target drives
exactly the model's joints (``plant.joint_names``), so a gripper's fingers stay locked.
"""

from __future__ import annotations

from typing import Any

from models.robots import RobotModel, robot_names, urdf_path


def is_builtin(robot: RobotModel) -> bool:
    """True for a built-in robot loaded by its name (its URDF is the table's)."""
    return robot.name in robot_names() and robot.urdf_path == urdf_path(robot.name).resolve()


def robot_spec(robot: RobotModel) -> str:
    """What ``load_robot`` takes to load ``robot`` again in another process: a name or a URDF path."""
    return robot.name if is_builtin(robot) else str(robot.urdf_path)


def target_robot_config(robot: RobotModel, config: dict[str, Any]) -> dict[str, Any]:
    """``config`` (a target config mapping) for ``robot``: its built-in name, or its URDF and joints;
    a bus fast enough for its drives (more than six at 1 kHz need an 8 Mbit/s CAN FD data phase)."""
    from sim_target.launch import can_fd

    if robot.n_joints > 6:
        config = {**config, "bus": {**config.get("bus", {}), **can_fd(robot.n_joints)}}
    if is_builtin(robot):
        return {**config, "robot": robot.name}
    plant = {**config.get("plant", {}), "joint_names": list(robot.joint_names)}
    return {**config, "robot": None, "urdf": str(robot.urdf_path), "plant": plant}


__all__ = ["is_builtin", "robot_spec", "target_robot_config"]
