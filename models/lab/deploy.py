"""``hil config runtime``: a runtime config made from a policy bundle and a drive table, so nobody
hand-writes a joint table (docs/any_arm.md).

The drive table (``--bus FILE``, YAML) holds what the bundle cannot know: the bus and each joint's
drive. Every field of the runtime's ``bus`` section (drivers/config.py) may be given except
``joints`` and ``period_s``, which come from the bundle::

    transport: {interface: socketcan, channel: can0, fd: true, data_bitrate: 5000000}
    heartbeat_timeout_s: 0.2
    drives:                      # optional: node ids 1..N in the bundle's joint order
      panda_joint1: 1            # a node id
      panda_joint2: {node_id: 2, max_torque_nm: 60.0}   # or a drive: any field of a bus joint

Each joint's ``max_torque_nm`` defaults to the bundle's torque limit. The config written is then
loaded exactly as ``hil run`` loads it (the bundle matched against the drives, the soft limits, the
condition checked inside them), so a bad table fails here, one line naming the file and field.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml

from hil_runtime.bundle import DEFAULT_ENCODER_NOISE_RAD
from models.errors import ModelInputError

#: The bus section's fields the bundle decides.
FROM_BUNDLE = ("joints", "period_s")


def _manifest(bundle: Path) -> Any:
    from hil_runtime.bundle import BundleError, PolicyBundle

    try:
        return PolicyBundle.load(bundle).manifest
    except (BundleError, ValueError, OSError) as exc:
        raise ModelInputError(f"--bundle: {exc}") from None


def _joints(table: dict[str, Any], manifest: Any, source: str) -> list[dict[str, Any]]:
    """The bus joints in the bundle's order: node id and drive fields from ``drives``, torque from the bundle."""
    names = list(manifest.robot.joint_names)
    torque = list(manifest.limits.torque_nm)
    drives = table.get("drives")
    if drives is None:
        drives = {name: i + 1 for i, name in enumerate(names)}
    if not isinstance(drives, dict):
        raise ModelInputError(f"{source}: drives: expected a mapping joint name -> node id or drive")
    unknown = [str(k) for k in drives if k not in names]
    if unknown:
        raise ModelInputError(f"{source}: drives.{unknown[0]}: not a joint of the bundle (joints: {', '.join(names)})")
    joints = []
    for name, limit in zip(names, torque, strict=True):
        if name not in drives:
            raise ModelInputError(f"{source}: drives: joint '{name}' of the bundle has no drive")
        drive = drives[name]
        entry = {"node_id": drive} if not isinstance(drive, dict) else dict(drive)
        if "name" in entry:
            raise ModelInputError(f"{source}: drives.{name}.name: the name is the key")
        joints.append({"name": name, **entry, "max_torque_nm": entry.get("max_torque_nm", float(limit))})
    return joints


def _conditions(manifest: Any, robot: str | None, out: Path, given: Path | None) -> Path | None:
    """The conditions file: the one given, None for ur5_paper (the paper's five, the runtime's
    default), else the robot's default conditions written beside the config."""
    from models.conditions import load_conditions
    from models.default_conditions import PAPER_ROBOT
    from models.hil_experiment.config import conditions_yaml
    from models.robots import load_robot, robot_names

    if given is not None:
        return given.resolve()
    name = manifest.robot.name
    if robot is None and name == PAPER_ROBOT:
        return None
    if robot is None and name not in robot_names():
        raise ModelInputError(
            f"--robot: bundle robot '{name}' is not built in: pass its URDF (--robot FILE) or --conditions FILE"
        )
    arm = load_robot(robot or name)
    if arm.n_joints != manifest.robot.n_joints:
        raise ModelInputError(
            f"--robot: '{robot}' has {arm.n_joints} joints, the bundle's robot {manifest.robot.n_joints}"
        )
    path = out.with_name(f"{out.stem}.conditions.yaml")
    path.write_text(conditions_yaml(load_conditions(None, robot=arm)))
    return path.resolve()


def runtime_config_from_bundle(
    bundle: Path,
    bus_file: Path,
    out: Path,
    mode: str = "lmpc",
    condition: str | None = "C1",
    conditions: Path | None = None,
    robot: str | None = None,
    measurement_noise: tuple[float, float | None] = (DEFAULT_ENCODER_NOISE_RAD, None),
) -> dict[str, Any]:
    """Write ``out`` (and its conditions file when needed); return the config, checked as ``hil run`` checks it.
    ``measurement_noise``: the bundle section's (encoder_noise_rad, velocity_noise_rad_s), the arm's sensing
    (an lmpc bundle that would chatter on it is refused, hil_runtime.bundle_probes.check_sensing)."""
    from drivers.config import read_yaml_config
    from hil_runtime.config import RuntimeConfigError, parse_runtime_config
    from hil_runtime.loading import condition_for, load_bundle_for, safety_limits_for

    manifest = _manifest(bundle)
    table = read_yaml_config(bus_file, ModelInputError, "a drive table")
    source = str(bus_file)
    if not isinstance(table, dict):
        raise ModelInputError(f"{source}: expected a mapping (transport, drives, bus fields)")
    for name in FROM_BUNDLE:
        if name in table:
            raise ModelInputError(f"{source}: {name}: comes from the bundle, remove it")
    bus = {k: v for k, v in table.items() if k != "drives"}
    bus.update(period_s=manifest.period_s, joints=_joints(table, manifest, source))
    reference: dict[str, Any] = {"kind": "hold"}
    if condition is not None:
        reference = {"kind": "condition", "condition": condition, "start": "ramp"}
        conditions_file = _conditions(manifest, robot, out, conditions)
        if conditions_file is not None:
            reference["conditions_file"] = str(conditions_file)
    data = {
        "robot": manifest.robot.name,
        "bundle": {
            "path": str(bundle.resolve()),
            "mode": mode,
            "encoder_noise_rad": measurement_noise[0],
            "velocity_noise_rad_s": measurement_noise[1],
        },
        "bus": bus,
        "reference": reference,
    }
    try:  # exactly what hil run loads: the drive table's errors name its file
        config = parse_runtime_config(data, source, bus_file.resolve().parent)
        limits = safety_limits_for(config, load_bundle_for(config))
        condition_for(config, limits)
    except RuntimeConfigError as exc:
        raise ModelInputError(str(exc)) from None
    header = f"# hil config runtime --bundle {bundle} --bus {bus_file}: the bundle's joints, the table's drives\n"
    out.write_text(header + yaml.safe_dump(data, sort_keys=False))
    return data


__all__ = ["runtime_config_from_bundle"]
