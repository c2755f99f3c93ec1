"""Seeded random conditions over the paper's amplitude and frequency range (training and held-out).

The paper's five conditions (Sec. IV-A) have per-joint amplitudes |Q_j| <= pi/2 and f in
{0.05, 0.1} Hz, start on the reference, and carry the 2 s impulse. ``paper_range_conditions`` draws
Q_j uniform in [-pi/2, pi/2] (clipped to 80 % of the joint's position and velocity limits), one f
uniform in [0.05, 0.1] Hz per condition, and a phase uniform over the 5 s run, with the paper's
disturbance and initial state. ``hil experiment --conditions random:20:SEED`` uses it; the LMPC's
training draws from other seeds (docs/lmpc.md lists the seeds of both).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from models.conditions import Condition, load_conditions
from models.errors import ModelInputError
from models.robots import RobotModel

PAPER_AMPLITUDE_RAD = math.pi / 2
PAPER_FREQUENCY_RANGE_HZ = (0.05, 0.1)


def paper_range_conditions(robot: RobotModel, count: int, seed: int, prefix: str = "P") -> list[Condition]:
    """``count`` seeded conditions in the paper's range (module docstring); names ``{prefix}{seed}-{k}``."""
    if count < 1:
        raise ModelInputError(f"random conditions: count must be >= 1, got {count}")
    template = load_conditions(None, robot=robot)[0]
    rng = np.random.default_rng(seed)
    n = robot.n_joints
    # Around the robot's home pose (0 for ur5_paper; models/default_conditions.py): the room towards
    # each limit, so an arm whose range excludes q = 0 (the Panda's elbow) is drawn inside it.
    home = np.zeros(n) if template.offset_rad is None else np.asarray(template.offset_rad, float)
    room_up = np.minimum(np.asarray(robot.position_upper_rad, float) - home, math.pi) * 0.8
    room_down = np.minimum(home - np.asarray(robot.position_lower_rad, float), math.pi) * 0.8
    vel_limit = np.asarray(robot.velocity_limit_rad_s, float) * 0.8
    out = []
    for k in range(count):
        freq = float(rng.uniform(*PAPER_FREQUENCY_RANGE_HZ))
        draw = rng.uniform(-1.0, 1.0, size=n)
        pos_limit = np.where(draw > 0, room_up, room_down)
        cap = np.minimum(np.minimum(pos_limit, PAPER_AMPLITUDE_RAD), vel_limit / (math.pi * freq))
        amp = draw * cap
        phase = float(rng.uniform(0.0, template.duration_s))
        out.append(
            replace(
                template,
                name=f"{prefix}{seed}-{k:02d}",
                amplitude_rad=tuple(float(a) for a in amp),
                frequency_hz=(freq,) * n,
                phase_s=phase,
            )
        )
    return out


def parse_generator_spec(text: str, kind: str) -> tuple[int, int] | None:
    """(count, seed) from 'KIND:COUNT:SEED', None for anything else (a file path)."""
    if not text.startswith(f"{kind}:"):
        return None
    parts = text.split(":")
    try:
        count, seed = int(parts[1]), int(parts[2])
        if len(parts) != 3 or count < 1:
            raise ValueError
    except (ValueError, IndexError):
        raise ModelInputError(f"--conditions: expected {kind}:COUNT:SEED (COUNT >= 1), got {text!r}") from None
    return count, seed


def parse_random_spec(text: str) -> tuple[int, int] | None:
    """(count, seed) from 'random:COUNT:SEED', None for anything else (a file path)."""
    return parse_generator_spec(text, "random")
