"""The plant's per-period inputs checked and turned into plain floats and bools (sim_target/plant.py):
six joints in plain floats, numpy's per-call overhead on 6-element arrays costing more than
pybullet's step itself at a few substeps."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import numpy as np

from sim_target.arm_loading import PlantError


def finite_floats(
    values: np.ndarray | Sequence[float],
    n_joints: int,
    vector: Callable[[np.ndarray | Sequence[float], str], np.ndarray],
    name: str,
) -> list[float]:
    """``values`` as ``n_joints`` finite floats; anything else goes through ``vector`` (the plant's
    full check, which raises its errors)."""
    floats: list[float] | None = None
    if type(values) is np.ndarray and values.shape == (n_joints,) and values.dtype == np.float64:
        floats = values.tolist()
    elif type(values) is list and len(values) == n_joints and all(type(x) is float for x in values):
        floats = list(values)
    if floats is not None and math.isfinite(sum(floats)):  # NaN or an infinity makes the sum non-finite
        return floats
    return vector(values, name).tolist()


def bool_flags(brake_engaged: np.ndarray | Sequence[bool], n_joints: int) -> list[bool]:
    """``brake_engaged`` as ``n_joints`` bools; PlantError for another shape."""
    if type(brake_engaged) is np.ndarray and brake_engaged.shape == (n_joints,) and brake_engaged.dtype == bool:
        return brake_engaged.tolist()
    if type(brake_engaged) is list and len(brake_engaged) == n_joints and all(type(b) is bool for b in brake_engaged):
        return list(brake_engaged)
    braked = np.asarray(brake_engaged, dtype=bool)
    if braked.shape != (n_joints,):
        raise PlantError(f"brake_engaged: expected {n_joints} values, got shape {braked.shape}")
    return braked.tolist()
