"""What a runtime config names, loaded and cross-checked before any I/O: the bundle (robot, URDF
hash, joint count and order, period), the soft safety limits, the reference condition. Each
refusal is one line naming the config file and the field (:class:`RuntimeConfigError`, exit 2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hil_runtime.bundle import BundleError, PolicyBundle
from hil_runtime.bundle_security import BundleSecurityError, load_public_key
from hil_runtime.conditions import Condition, load_conditions
from hil_runtime.config import RuntimeConfig, RuntimeConfigError
from hil_runtime.supervisor import SafetyLimits


def load_bundle_for(config: RuntimeConfig) -> PolicyBundle:
    """The config's bundle, refused unless it matches the drives (joint count/order, period), the
    robot's name and, when the config pins it (``bundle.urdf_sha256``), the robot's URDF."""
    keys = []
    for i, key_path in enumerate(config.bundle.trusted_keys):
        try:
            keys.append(load_public_key(key_path))
        except BundleSecurityError as exc:
            raise RuntimeConfigError(f"{config.source}: bundle.trusted_keys[{i}]: {exc}") from None
    bundle = PolicyBundle.load(
        config.bundle.path,
        expected_joints=len(config.bus.joints),
        expected_period_s=config.period_s,
        expected_joint_names=config.joint_names,
        trusted_keys=keys,
    )
    noisy = config.bundle.encoder_noise_rad > 0.0 or (config.bundle.velocity_noise_rad_s or 0.0) > 0.0
    if config.bundle.mode == "lmpc" and noisy:
        try:
            bundle.check_sensing(
                config.bundle.encoder_noise_rad, config.bundle.velocity_noise_rad_s, config.bundle.velocity_filter_hz
            )
        except BundleError as exc:
            raise RuntimeConfigError(f"{config.source}: bundle.encoder_noise_rad: {exc}") from None
    robot = bundle.manifest.robot
    if robot.name != config.robot:
        raise RuntimeConfigError(
            f"{config.source}: robot: '{config.robot}' but bundle {config.bundle.path} is for '{robot.name}'"
        )
    expected = config.bundle.urdf_sha256
    if expected is not None and robot.urdf_sha256 != expected:
        raise RuntimeConfigError(
            f"{config.source}: bundle.urdf_sha256: {expected[:12]}… but bundle {config.bundle.path} was exported "
            f"for URDF {robot.urdf_sha256[:12]}… ({robot.urdf_file}): another description of the arm"
        )
    return bundle


def safety_limits_for(config: RuntimeConfig, bundle: PolicyBundle) -> SafetyLimits:
    """Soft limits: the config's, else the bundle manifest's; torque: the tighter of bundle and drives."""
    limits = bundle.manifest.limits
    position = np.asarray(limits.position_rad, float)
    bundle_lower = -position if limits.position_lower_rad is None else np.asarray(limits.position_lower_rad, float)
    bundle_upper = position if limits.position_upper_rad is None else np.asarray(limits.position_upper_rad, float)
    velocity = np.asarray(limits.velocity_rad_s, float)
    safety = config.safety
    lower = np.asarray(safety.position_lower_rad, float) if safety.position_lower_rad is not None else bundle_lower
    upper = np.asarray(safety.position_upper_rad, float) if safety.position_upper_rad is not None else bundle_upper
    vmax = np.asarray(safety.velocity_limit_rad_s, float) if safety.velocity_limit_rad_s is not None else velocity
    # The config may tighten the bundle's limits (the URDF's, which the exporter copied), never widen
    # them: the law was trained and checked inside them, and the arm's own description ends there.
    for name, values, bound, beyond in (
        ("position_lower_rad", lower, bundle_lower, lower < bundle_lower - 1e-9),
        ("position_upper_rad", upper, bundle_upper, upper > bundle_upper + 1e-9),
        ("velocity_limit_rad_s", vmax, velocity, vmax > velocity + 1e-9),
    ):
        if beyond.any():
            j = int(np.flatnonzero(beyond)[0])
            raise RuntimeConfigError(
                f"{config.source}: safety.{name}[{j}]: {values[j]:g} is beyond the bundle's limit {bound[j]:g} "
                f"(limits of {config.bundle.path}, from the robot's URDF): the config may only tighten it"
            )
    drives = np.array([j.max_torque_nm for j in config.bus.joints])
    torque = np.minimum(np.asarray(bundle.torque_limit_nm, float), drives)
    try:
        return SafetyLimits(lower, upper, vmax, torque, safety.max_stale_cycles, safety.overrun_budget)
    except ValueError as exc:
        raise RuntimeConfigError(f"{config.source}: safety: {exc}") from None


@dataclass
class _Limits:
    """The JointLimits view of the safety limits that a condition is checked against."""

    name: str
    n_joints: int
    position_lower_rad: np.ndarray
    position_upper_rad: np.ndarray
    velocity_limit_rad_s: np.ndarray


def condition_for(config: RuntimeConfig, limits: SafetyLimits) -> Condition | None:
    """The configured condition (None for hold), checked against the soft limits."""
    ref = config.reference
    if ref.kind == "hold":
        return None
    view = _Limits(
        config.robot, limits.n_joints, limits.position_lower_rad, limits.position_upper_rad, limits.velocity_limit_rad_s
    )
    conditions = load_conditions(ref.conditions_file, view)
    for condition in conditions:
        if condition.name == ref.condition:
            return condition
    names = ", ".join(c.name for c in conditions)
    where = ref.conditions_file or "the paper's conditions"
    raise RuntimeConfigError(
        f"{config.source}: reference.condition: no condition '{ref.condition}' in {where} (known: {names})"
    )
