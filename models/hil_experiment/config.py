"""What ``hil experiment --plant hil`` is asked (checked with one line each), and what it hands the
target for one run: the conditions file, the target's run start (the runtime's config: the lab's
builder, models/lab/runs.py). ``hil demo`` hands its processes the same (models/demo/configs.py)."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import yaml

from models.conditions import Condition
from models.errors import ModelInputError
from models.experiment import ExperimentConfig
from models.robots import RobotModel

if TYPE_CHECKING:
    from sim_target.launch import Transport

HIL_MODES = ("fb", "lmpc")


@dataclass(frozen=True)
class HilOptions:
    transport: Transport = "virtual"  # virtual (one process) | ipc | bridge (the target in its own process)
    target_substeps: int = 32  # pybullet steps per control period (docs/hil.md: integration)
    parity: bool = True  # also simulate, compare run by run
    bundle_dir: Path | None = None  # LMPC/FB bundles; None: models/bundles (the shipped ones)
    # lockstep: each SYNC steps the arm (deterministic); realtime: both free-running on the wall
    # clock, the target in its own process, each on its own CPU (docs/hil.md, docs/runtime.md)
    clock: str = "lockstep"
    cpus: str = "auto"  # realtime: the runtime loop's and the target's CPUs (sim_target.rt_settings.split_cpus)
    # the LMPC torque's output rate limit in the runtime (bundle.torque_rate_limit) and its simulation
    # twin alike: none | libfranka (hil_runtime.rate_limit)
    torque_rate_limit: str = "none"
    # the LMPC's velocity input filter in the runtime (bundle.velocity_filter_hz) and its twin alike; None: off
    velocity_filter_hz: float | None = None


def conditions_yaml(conditions: list[Condition]) -> str:
    """The conditions in the runtime's YAML format (hil_runtime/conditions.py), exactly (repr floats)."""

    def plain(value: Any) -> Any:
        if isinstance(value, dict):
            return {k: plain(v) for k, v in value.items() if v is not None}
        if isinstance(value, (list, tuple)):
            return [plain(v) for v in value]
        return float(value) if isinstance(value, (float, np.floating)) else value

    items = []
    for c in conditions:
        item = plain(asdict(c))  # a None field (no disturbance, no offset) is left out: None when read
        if c.mismatch.is_nominal:
            item.pop("mismatch", None)
        items.append(item)
    return yaml.safe_dump({"conditions": items}, sort_keys=False)


def initial_state(condition: Condition) -> tuple[np.ndarray, np.ndarray]:
    """(q0, qd0) as the simulator starts (models.sim.closed_loop.simulate)."""
    q0 = np.asarray(condition.initial_position(), float)
    if condition.initial_state == "reference":
        return q0, np.asarray(condition.reference(0.0)[1], float)
    return q0, np.zeros_like(q0)


def run_start(condition: Condition) -> dict[str, Any]:
    """The target's RunStart for ``condition``: its initial state, its disturbance (if any)."""
    q0, qd0 = initial_state(condition)
    faults = []
    d = condition.disturbance
    if d is not None and d.duration_s > 0 and any(t != 0 for t in d.torque_nm):
        faults.append({"kind": "impulse", "at_s": d.time_s, "duration_s": d.duration_s, "torque_nm": list(d.torque_nm)})
    return {"kind": "start", "position_rad": q0.tolist(), "velocity_rad_s": qd0.tolist(), "faults": faults}


def check_hil_inputs(
    robot: RobotModel, conditions: list[Condition], config: ExperimentConfig, options: HilOptions
) -> None:
    """Refuse what the HIL plant cannot do, with one line each (exit 2)."""
    from models.lmpc.controller import bundle_path
    from sim_target.launch import TRANSPORTS

    bad_modes = [m for m in config.modes if m not in HIL_MODES]
    if bad_modes:
        raise ModelInputError(
            f"--modes: '{bad_modes[0]}' cannot run on --plant hil (the runtime runs bundles: {', '.join(HIL_MODES)})"
        )
    if options.transport not in TRANSPORTS:
        raise ModelInputError(f"--transport: unknown '{options.transport}' (known: {', '.join(TRANSPORTS)})")
    if options.target_substeps < 1:
        raise ModelInputError(f"--target-substeps: must be >= 1, got {options.target_substeps}")
    from hil_runtime.rate_limit import TORQUE_RATE_LIMITS

    if options.torque_rate_limit not in TORQUE_RATE_LIMITS:
        raise ModelInputError(
            f"--torque-rate-limit: unknown '{options.torque_rate_limit}' (known: {', '.join(TORQUE_RATE_LIMITS)})"
        )
    if options.clock not in ("lockstep", "realtime"):
        raise ModelInputError(f"--clock: unknown '{options.clock}' (known: lockstep, realtime)")
    if options.clock == "realtime" and options.transport == "virtual":
        raise ModelInputError(
            "--clock realtime: the target must run in its own process (the GIL would pace both): --transport ipc"
        )
    from sim_target.rt_settings import split_cpus

    try:
        split_cpus(options.cpus)
    except ValueError as exc:
        raise ModelInputError(str(exc)) from None
    for c in conditions:
        if not c.mismatch.is_nominal:
            raise ModelInputError(
                f"condition {c.name}: plant-model mismatch is not emulated by the HIL target "
                "(it runs the nominal URDF): use --mismatch none"
            )
    from sim_target.realism_profiles import load_realism

    period_s = config.sim.period_s
    world = load_realism(
        config.realism, robot.n_joints, period_s, period_s / options.target_substeps, robot.torque_limit_nm
    )
    if any(world.plant.payload_com_m):
        raise ModelInputError(
            f"--realism {config.realism}: plant.payload_com_m: the HIL target cannot move the flange's centre of mass"
        )
    for law in config.laws:
        path = bundle_path(robot.name, law, options.bundle_dir)
        manifest = path / "manifest.json"
        if not manifest.is_file():
            raise ModelInputError(f"{manifest}: no bundle for law '{law}' (export one with `hil pipeline`)")
        gain_set = json.loads(manifest.read_text())["law"].get("gain_set")
        if gain_set != config.gain_set:
            raise ModelInputError(
                f"{manifest}: bundle exported with gain set '{gain_set}', --gains is "
                f"'{config.gain_set}' (the runtime runs the bundle's law)"
            )


__all__ = [
    "HIL_MODES",
    "HilOptions",
    "check_hil_inputs",
    "conditions_yaml",
    "initial_state",
    "run_start",
]
