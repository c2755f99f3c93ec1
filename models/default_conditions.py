"""Each robot's default operating conditions: the paper's five for ``ur5_paper``, and for any other
arm five conditions of the same form placed inside that arm's limits (docs/conditions.md, "Other
arms").

The paper's five (Sec. IV-A) are written for its UR5: joint amplitudes up to pi/2 around q = 0, a
torque pulse sized for its 0.4 kg wrist. Another arm's joints may not even contain q = 0 (the
Panda's elbow lives in [-3.07, -0.07] rad), and the same torque pulse means nothing on a 8 kg upper
arm. So for another arm, condition Ck keeps the paper's Ck shape, frequency, phase, duration and
start state, and takes from the arm:

- the home pose ``h``: per joint 0 when it lies in the middle half of the joint's range, else the
  range's midpoint (the reference is ``h + A/2 (1 + sin(...))``);
- the amplitudes: the paper's Ck amplitudes (joint j takes the paper's joint ``j mod 6``), each cut
  to 80 % of the room between ``h`` and the limit it moves towards, and to 80 % of the velocity
  limit at the condition's frequency;
- the disturbance: a rectangular pulse one control period (1 ms) long at the paper's t = 2 s, whose
  impulse changes each joint's velocity by 20 % of its velocity limit at the home pose
  (torque = 0.2 v_max / (M(h)^-1)_jj / 1 ms), at most 5x the joint's effort limit (the HIL target
  refuses blows beyond 10x: sim_target/config.py IMPULSE_EFFORT_FACTOR).

    conditions = default_conditions(load_robot("panda"))     # C1..C5, inside the Panda's limits
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from hil_runtime.conditions import Condition, Disturbance
from models.robots import RobotModel

#: The robot whose default conditions are the paper's five.
PAPER_ROBOT = "ur5_paper"
ROOM_FRACTION = 0.8  # of the way from the home pose to the limit the amplitude moves towards
VELOCITY_FRACTION = 0.8  # of the velocity limit, the reference's peak speed at most
KICK_FRACTION = 0.2  # the disturbance's velocity change, of the velocity limit
PULSE_S = 1.0e-3  # one control period (the paper's 20 us reading needs 50x the torque for the same blow)
MAX_EFFORT_FACTOR = 5.0  # the pulse's torque, of the joint's effort limit at most


def home_pose_rad(robot: RobotModel) -> np.ndarray:
    """Per joint: 0 inside the middle half of the range, else the midpoint (0 for unbounded joints)."""
    lower, upper = np.asarray(robot.position_lower_rad, float), np.asarray(robot.position_upper_rad, float)
    span = upper - lower
    inner = (lower + 0.25 * span <= 0.0) & (0.0 <= upper - 0.25 * span)
    middle = np.where(np.isfinite(span), 0.5 * (lower + upper), 0.0)
    return np.where(inner | ~np.isfinite(span), 0.0, middle)


def disturbance_torque_nm(robot: RobotModel, home_rad: np.ndarray) -> np.ndarray:
    """The pulse torque whose impulse changes each joint's velocity by KICK_FRACTION of its limit."""
    from models.dynamics import make_dynamics

    mass = np.asarray(make_dynamics(robot, "rne").mass_matrix(home_rad), float).reshape(robot.n_joints, -1)
    effective_inertia = 1.0 / np.diag(np.linalg.inv(mass))  # kg m^2 seen by a pulse on one joint
    torque = KICK_FRACTION * np.asarray(robot.velocity_limit_rad_s, float) * effective_inertia / PULSE_S
    torque = np.minimum(torque, MAX_EFFORT_FACTOR * np.asarray(robot.torque_limit_nm, float))
    return np.array([float(f"{t:.3g}") for t in torque])  # three digits: a readable conditions file


def default_conditions(robot: RobotModel) -> list[Condition]:
    """The robot's five default conditions C1..C5 (module docstring); the paper's for ur5_paper."""
    from hil_runtime.conditions import load_conditions

    paper = load_conditions(None)
    if robot.name == PAPER_ROBOT:
        return load_conditions(None, limits=robot)
    n = robot.n_joints
    home = home_pose_rad(robot)
    lower, upper = np.asarray(robot.position_lower_rad, float), np.asarray(robot.position_upper_rad, float)
    velocity = np.asarray(robot.velocity_limit_rad_s, float)
    torque = tuple(float(t) for t in disturbance_torque_nm(robot, home))
    out = []
    for c in paper:
        pattern = np.array([c.amplitude_rad[j % len(c.amplitude_rad)] for j in range(n)])
        frequency = np.array([c.frequency_hz[j % len(c.frequency_hz)] for j in range(n)])
        room = np.where(pattern > 0, upper - home, home - lower)
        peak_speed_per_rad = 0.5 * 2.0 * math.pi * frequency  # raised sine: |qd| <= A/2 * omega
        cap = np.minimum(ROOM_FRACTION * room, VELOCITY_FRACTION * velocity / peak_speed_per_rad)
        amplitude = np.sign(pattern) * np.minimum(np.abs(pattern), cap)
        disturbance = None if c.disturbance is None else Disturbance(c.disturbance.time_s, torque, PULSE_S)
        condition = replace(
            c,
            amplitude_rad=tuple(float(a) for a in amplitude),
            frequency_hz=tuple(float(f) for f in frequency),
            offset_rad=tuple(float(h) for h in home),
            disturbance=disturbance,
        )
        condition.check_limits(robot, source=f"{robot.name} default conditions")
        out.append(condition)
    return out


__all__ = ["PAPER_ROBOT", "default_conditions", "disturbance_torque_nm", "home_pose_rad"]
