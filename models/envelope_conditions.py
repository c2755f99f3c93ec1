"""Seeded conditions across the arm's whole operating envelope (``hil experiment --conditions envelope:N:SEED``).

The paper's conditions and the LMPC's training draws (models.lmpc.paper_range) are raised sines from the
home pose. These are not: each condition is, with equal odds, a raised sine from a random offset pose, a
sine about a random offset pose, or a hold at a random pose; positions up to 80 % of each joint's position
limit (at most pi), peak velocities up to 80 % of its velocity limit, one frequency per condition in
[0.05, 0.5] Hz, the run starting on the reference, and the disturbance pulse at a random time (one of
four seeded times per set, so conditions share simulator batches) with a random sign and scale (0.5-2x
the paper's pulse). Never used in training: the structured LMPC trains on paper-range seeds
(docs/lmpc.md).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from models.conditions import Condition, Disturbance, load_conditions
from models.errors import ModelInputError
from models.robots import RobotModel

ENVELOPE_FRACTION = 0.8  # of the position and velocity limits
FREQUENCY_RANGE_HZ = (0.05, 0.5)
DISTURBANCE_TIMES = 4  # distinct seeded disturbance times per set (conditions sharing one share a batch)
ENVELOPE_SHAPES = ("raised_sine", "sine", "constant")


def envelope_conditions(robot: RobotModel, count: int, seed: int, prefix: str = "E") -> list[Condition]:
    """``count`` seeded conditions across the envelope (module docstring); names ``{prefix}{seed}-{k}``."""
    if count < 1:
        raise ModelInputError(f"envelope conditions: count must be >= 1, got {count}")
    template = load_conditions(None, robot=robot)[0]
    rng = np.random.default_rng(seed)
    n = robot.n_joints
    pos = np.minimum(np.abs(np.asarray(robot.position_limit_rad, float)), math.pi) * ENVELOPE_FRACTION
    vel = np.asarray(robot.velocity_limit_rad_s, float) * ENVELOPE_FRACTION
    pulse = np.asarray((template.disturbance or Disturbance()).torque_nm, float)
    times = rng.uniform(0.5, template.duration_s - 0.5, DISTURBANCE_TIMES)
    out = []
    for k in range(count):
        shape = ENVELOPE_SHAPES[int(rng.integers(len(ENVELOPE_SHAPES)))]
        freq = float(rng.uniform(*FREQUENCY_RANGE_HZ))
        omega = 2.0 * math.pi * freq
        if shape == "raised_sine":  # q in [offset, offset + A], peak speed |A| omega / 2
            amp = rng.uniform(-1.0, 1.0, n) * np.minimum(pos, 2.0 * vel / omega)
            offset = rng.uniform(-pos - np.minimum(amp, 0.0), pos - np.maximum(amp, 0.0))
        elif shape == "sine":  # q in offset +- |A|, peak speed |A| omega
            amp = rng.uniform(-1.0, 1.0, n) * np.minimum(pos, vel / omega)
            offset = rng.uniform(-pos + np.abs(amp), pos - np.abs(amp))
        else:  # a hold at offset + A
            amp, offset = rng.uniform(-1.0, 1.0, n) * pos, np.zeros(n)
        scale = rng.uniform(0.5, 2.0) * rng.choice((-1.0, 1.0))
        out.append(
            replace(
                template,
                name=f"{prefix}{seed}-{k:02d}",
                shape=shape,
                amplitude_rad=tuple(float(a) for a in amp),
                offset_rad=tuple(float(o) for o in offset),
                frequency_hz=(freq,) * n,
                phase_s=float(rng.uniform(0.0, 1.0 / freq)),
                initial_state="reference",
                disturbance=replace(
                    template.disturbance or Disturbance(),
                    time_s=float(times[int(rng.integers(DISTURBANCE_TIMES))]),
                    torque_nm=tuple(float(t) for t in scale * pulse),
                ),
            )
        )
    for condition in out:
        condition.check_limits(robot, "envelope conditions")
    return out


def parse_envelope_spec(text: str) -> tuple[int, int] | None:
    """(count, seed) from 'envelope:COUNT:SEED', None for anything else."""
    from models.lmpc.paper_range import parse_generator_spec

    return parse_generator_spec(text, "envelope")
