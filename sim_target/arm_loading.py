"""Loading a URDF arm into pybullet with exactly the URDF's dynamics (sim_target/plant.py's set-up).

pybullet defaults that would make the arm differ from the project's own dynamics, all undone by
:func:`load_arm`: velocity motors (a hidden brake) disabled, link and joint damping zeroed, inertia
taken from the file, links with no ``<inertial>`` made massless (pybullet would give them 1 kg).
"""

from __future__ import annotations

import contextlib
import os
import sys
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path

import pybullet

from sim_target.robots import RobotLookupError, builtin_urdf_path

MOVABLE_JOINT_TYPES = (pybullet.JOINT_REVOLUTE, pybullet.JOINT_PRISMATIC)


class PlantError(ValueError):
    """Bad plant parameters or inputs (wrong shape, unknown joint). Printed as one line."""

    exit_code = 2


@contextlib.contextmanager
def _quiet_native_output() -> Iterator[None]:
    """Silence pybullet's C-level warnings (printed to fd 1/2, not through Python)."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        os.dup2(devnull, 2)
        yield
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in (*saved, devnull):
            os.close(fd)


def _links_without_inertial(urdf: Path) -> set[str]:
    root = ET.parse(urdf).getroot()
    return {link.get("name", "") for link in root.iter("link") if link.find("inertial") is None}


def load_arm(client_id: int, urdf: Path | str) -> int:
    """Load a fixed-base arm into ``client_id`` with its dynamics exactly as the URDF states.

    Returns the pybullet body id. Velocity motors are disabled, damping zeroed, inertia taken from
    the file, and links the URDF gives no inertial are made massless (pybullet would give them 1 kg).
    Must run before any ``calculateInverseDynamics`` call: pybullet caches that model on first use.
    """
    urdf = Path(urdf)
    if not urdf.is_file():
        raise PlantError(f"{urdf}: URDF not found")
    with _quiet_native_output():
        body = pybullet.loadURDF(
            str(urdf),
            useFixedBase=True,
            flags=pybullet.URDF_USE_INERTIA_FROM_FILE,
            physicsClientId=client_id,
        )
    massless = _links_without_inertial(urdf)
    n_joints = pybullet.getNumJoints(body, physicsClientId=client_id)
    for link in range(-1, n_joints):
        pybullet.changeDynamics(
            body, link, linearDamping=0.0, angularDamping=0.0, jointDamping=0.0, physicsClientId=client_id
        )
    for link in range(n_joints):
        info = pybullet.getJointInfo(body, link, physicsClientId=client_id)
        if info[12].decode() in massless:
            pybullet.changeDynamics(
                body, link, mass=0.0, localInertiaDiagonal=[0.0, 0.0, 0.0], physicsClientId=client_id
            )
        if info[2] in MOVABLE_JOINT_TYPES:
            pybullet.setJointMotorControl2(
                body, link, pybullet.VELOCITY_CONTROL, targetVelocity=0.0, force=0.0, physicsClientId=client_id
            )
    return body


def default_urdf_path(robot: str = "ur5_paper") -> Path:
    """The URDF of a built-in robot (the shared table, sim_target/robots.py; no models import)."""
    try:
        return builtin_urdf_path(robot)
    except RobotLookupError as exc:
        raise PlantError(str(exc)) from None


__all__ = ["MOVABLE_JOINT_TYPES", "PlantError", "default_urdf_path", "load_arm"]
