"""ur5_paper's six emulated drives as the HIL tests, benchmarks and the fault rig configure them:
one table (joint names, node ids, max torques, the start pose) instead of a copy in each. Light: no
pybullet, no runtime imports."""

from __future__ import annotations

from pathlib import Path
from typing import Any

JOINT_NAMES = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)
NODE_IDS = (1, 2, 3, 4, 5, 6)
# ur5_paper's URDF effort limits: the drives' max torque (0x6072).
MAX_TORQUE_NM = (102.0, 102.0, 66.0, 34.0, 34.0, 34.0)
Q0_RAD = (0.0, -0.5, 0.8, -0.3, 0.0, 0.0)  # the pose the target starts in (away from singularities)
# The shipped PD bundle (a source checkout's models/bundles; sim_target does not import models).
PD_BUNDLE = Path(__file__).resolve().parents[2] / "models" / "bundles" / "ur5_paper" / "pd"


def bus_joints() -> list[dict[str, Any]]:
    """The runtime config's ``bus.joints`` for the six drives (a new list each call: callers edit it)."""
    return [
        {"name": name, "node_id": node_id, "max_torque_nm": torque_nm}
        for name, node_id, torque_nm in zip(JOINT_NAMES, NODE_IDS, MAX_TORQUE_NM, strict=True)
    ]


__all__ = ["JOINT_NAMES", "MAX_TORQUE_NM", "NODE_IDS", "PD_BUNDLE", "Q0_RAD", "bus_joints"]
