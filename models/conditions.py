"""Operating conditions: the runtime's light definitions plus what needs a robot model.

The condition format, the reference evaluation and the loader live in ``hil_runtime.conditions``
(the runtime evaluates references every cycle and must not import ``models``); this module
re-exports them, turns their errors into ``ModelInputError`` and adds the seeded random generator,
which draws inside a robot's limits (docs/conditions.md).

    conditions = load_conditions()                 # the paper's five
    conditions = load_conditions(robot=load_robot("panda"))   # the Panda's defaults (default_conditions.py)
    conditions = load_conditions("my_conditions.yaml", robot=load_robot("ur5_paper"))
    q_d, qd_d, qdd_d = conditions[0].reference(t_s)  # t_s scalar or (T,) -> (..., N)
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np

from hil_runtime import conditions as _runtime
from hil_runtime.conditions import (
    INITIAL_STATES,
    PAPER_CONDITIONS,
    SHAPES,
    Condition,
    ConditionError,
    Disturbance,
    Mismatch,
    parse_conditions,
)
from models.errors import ModelInputError
from models.robots import RobotModel

__all__ = [
    "INITIAL_STATES",
    "PAPER_CONDITIONS",
    "SHAPES",
    "Condition",
    "ConditionError",
    "Disturbance",
    "Mismatch",
    "load_conditions",
    "parse_conditions",
    "random_conditions",
]


def load_conditions(path: str | Path | None = None, robot: RobotModel | None = None) -> list[Condition]:
    """Conditions from a YAML file, checked against ``robot``; with no file, the robot's default
    conditions (the paper's five for ur5_paper or no robot; models/default_conditions.py)."""
    from models.default_conditions import default_conditions

    try:
        if path is None and robot is not None:
            return default_conditions(robot)
        return _runtime.load_conditions(path, limits=robot)
    except ConditionError as exc:
        raise ModelInputError(str(exc)) from None


def random_conditions(
    robot: RobotModel,
    count: int,
    seed: int,
    frequency_range_hz: tuple[float, float] = (0.05, 0.2),
    limit_fraction: float = 0.8,
    template: Condition | None = None,
) -> list[Condition]:
    """Seeded raised-sine conditions whose references stay inside ``limit_fraction`` of the limits."""
    from models.default_conditions import home_pose_rad

    rng = np.random.default_rng(seed)
    # Around the robot's home pose (0 for ur5_paper, the Panda's elbow at its range's midpoint).
    home = home_pose_rad(robot)
    template = template or Condition(
        name="template", amplitude_rad=(0.0,) * robot.n_joints, frequency_hz=(0.1,) * robot.n_joints
    )
    offset = template.offset_rad if not home.any() else tuple(float(h) for h in home)
    room_up = np.minimum(robot.position_upper_rad - home, math.pi) * limit_fraction
    room_down = np.minimum(home - robot.position_lower_rad, math.pi) * limit_fraction
    vel_limit = np.minimum(robot.velocity_limit_rad_s, 10.0) * limit_fraction
    out = []
    for k in range(count):
        freq = rng.uniform(*frequency_range_hz, size=robot.n_joints)
        draw = rng.uniform(-1.0, 1.0, size=robot.n_joints)
        # |A| bounded by the room towards the limit it moves to (the reference spans [h, h + A]) and
        # by the peak velocity pi f |A|.
        max_amp = np.minimum(np.where(draw > 0, room_up, room_down), vel_limit / (math.pi * freq))
        amp = draw * max_amp
        out.append(
            replace(
                template,
                name=f"R{seed}-{k:03d}",
                amplitude_rad=tuple(amp),
                frequency_hz=tuple(freq),
                phase_s=float(rng.uniform(0.0, template.duration_s)),
                offset_rad=offset,
            )
        )
    return out
