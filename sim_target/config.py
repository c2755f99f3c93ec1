"""Frozen configuration of the HIL target (``hil target serve --config FILE``), YAML or TOML.

Example (deploy/target.virtual.yaml)::

    robot: ur5_paper            # a built-in robot name, or urdf: path/to/arm.urdf
    period_s: 0.001
    clock: lockstep             # lockstep: each SYNC steps physics once; realtime: a monotonic timer
    bus: {interface: virtual, channel: hil}
    bridge: {host: 127.0.0.1, port: 54701}   # optional: serve the bus to other processes
    drives: {node_ids: [1, 2, 3, 4, 5, 6]}
    plant: {substeps: 32, initial_position_rad: [0, -0.5, 0.8, 0, 0, 0]}
    faults:
      - {kind: impulse, at_s: 2.0, duration_s: 2.0e-5, torque_nm: [1, 1, 5, 5, 10, 10]}
    control_socket: /tmp/hil-target.sock      # optional: run-time fault injection

Faults share one schema between the file (scheduled at ``at_s``, simulated seconds in lock-step,
seconds since start in real time) and the control socket (applied at once). Bad input raises
:class:`TargetConfigError` (exit code 2) with one line naming the file and field.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Annotated, Any, Literal, Union

import yaml
from pydantic import BaseModel, ConfigDict, Field, TypeAdapter, ValidationError, model_validator

from drivers.config import TransportConfig, format_validation_error, is_loopback_host


class TargetConfigError(ValueError):
    """Bad target configuration or fault command; printed as one line."""

    exit_code = 2


class _Frozen(BaseModel):
    model_config = ConfigDict(frozen=True, extra="forbid")


def _finite(values: tuple[float, ...], field: str) -> tuple[float, ...]:
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"{field} must be finite")
    return values


# --- faults ----------------------------------------------------------------------------------------


class _Fault(_Frozen):
    at_s: float = Field(0.0, ge=0)  # when it applies (ignored for run-time injection: at once)


class FrameFault(_Fault):
    """Frames the drives send (TPDO, heartbeat, EMCY, SDO answers): handed to the drive layer."""

    kind: Literal["frames"]
    drop_probability: float = Field(0.0, ge=0, le=1)
    delay_s: float = Field(0.0, ge=0, le=1)  # every sent frame held this long
    corrupt_probability: float = Field(0.0, ge=0, le=1)  # payload bytes flipped / length changed
    node_ids: tuple[int, ...] | None = None  # None: every drive
    seed: int = 0


class DriveFault(_Fault):
    """A drive goes to Fault (CiA 402) and sends EMCY with ``error_code``."""

    kind: Literal["drive_fault"]
    node_id: int = Field(ge=1, le=127)
    error_code: int = Field(0x5530, ge=0, le=0xFFFF)  # default: 0x5530 "data storage" (hardware)


class HeartbeatFault(_Fault):
    """A drive stops (``silent: true``) or resumes sending its heartbeat; PDOs and SDOs go on."""

    kind: Literal["heartbeat"]
    node_id: int = Field(ge=1, le=127)
    silent: bool = True


class EncoderNoiseFault(_Fault):
    kind: Literal["encoder_noise"]
    position_rad: float = Field(ge=0)  # standard deviation
    velocity_rad_s: float = Field(0.0, ge=0)


class PayloadFault(_Fault):
    """A payload on the flange (0 removes it)."""

    kind: Literal["payload"]
    mass_kg: float = Field(ge=0, le=1000)
    inertia_kg_m2: tuple[float, float, float] = (0.0, 0.0, 0.0)


class ImpulseFault(_Fault):
    """An external joint torque over [at_s, at_s + duration_s); the paper's disturbance by default."""

    kind: Literal["impulse"]
    torque_nm: tuple[float, ...] = (1.0, 1.0, 5.0, 5.0, 10.0, 10.0)
    duration_s: float = Field(2e-5, gt=0)  # 20 µs, as in the models simulator (docs/conditions.md)

    @model_validator(mode="after")
    def _check(self) -> ImpulseFault:
        _finite(self.torque_nm, "torque_nm")
        return self


Fault = Annotated[
    Union[FrameFault, DriveFault, HeartbeatFault, EncoderNoiseFault, PayloadFault, ImpulseFault], Field(discriminator="kind")
]
_FAULT_ADAPTER: TypeAdapter[Fault] = TypeAdapter(Fault)
PLANT_FAULTS = (EncoderNoiseFault, PayloadFault, ImpulseFault)
DRIVE_FAULTS = (FrameFault, DriveFault, HeartbeatFault)


# --- sections --------------------------------------------------------------------------------------


class BridgeConfig(_Frozen):
    """Serve the target's virtual bus to other processes through python-can-remote (loopback only)."""

    host: str = "127.0.0.1"
    port: int = Field(54701, ge=0, lt=65536)  # 0: any free port (printed by ``hil target serve``)

    @model_validator(mode="after")
    def _check(self) -> BridgeConfig:
        if not is_loopback_host(self.host):
            raise ValueError(f"bridge host {self.host!r} is not loopback (127.0.0.1/::1)")
        return self


class DrivesConfig(_Frozen):
    node_ids: tuple[int, ...] | None = None  # one per joint, in joint order; None: 1..N
    encoder_counts_per_rev: int = Field(1 << 20, gt=0)  # the drives' 0x608F
    heartbeat_producer_ms: int = Field(0, ge=0, le=65535)  # until the master sets 0x1017

    @model_validator(mode="after")
    def _check(self) -> DrivesConfig:
        if self.node_ids is not None:
            if len(set(self.node_ids)) != len(self.node_ids) or not all(1 <= n <= 127 for n in self.node_ids):
                raise ValueError(f"node_ids must be distinct and in 1..127, got {list(self.node_ids)}")
        return self


class PlantConfig(_Frozen):
    substeps: int = Field(32, ge=1, le=10_000)  # pybullet steps per control period
    joint_names: tuple[str, ...] | None = None  # None: every revolute joint, URDF order
    initial_position_rad: tuple[float, ...] | None = None
    brake_holding_torque_nm: tuple[float, ...] | None = None  # None: twice the effort limit
    encoder_noise_rad: float = Field(0.0, ge=0)
    velocity_noise_rad_s: float = Field(0.0, ge=0)
    seed: int = 0


class TargetConfig(_Frozen):
    robot: str | None = "ur5_paper"  # built-in robot name (models.robots)
    urdf: Path | None = None  # or a URDF file; wins over robot
    period_s: float = Field(1e-3, gt=0, le=1.0)
    clock: Literal["lockstep", "realtime"] = "lockstep"
    bus: TransportConfig = TransportConfig()
    bridge: BridgeConfig | None = None
    drives: DrivesConfig = DrivesConfig()
    plant: PlantConfig = PlantConfig()
    faults: tuple[Fault, ...] = ()
    control_socket: Path | None = None  # Unix socket for run-time faults; no network traffic

    @model_validator(mode="after")
    def _check(self) -> TargetConfig:
        if self.bridge is not None and self.bus.interface != "virtual":
            raise ValueError("bridge: only a virtual bus can be served to other processes")
        return self


# --- loading ---------------------------------------------------------------------------------------


def parse_target_config(data: Any, source: str = "config") -> TargetConfig:
    try:
        return TargetConfig.model_validate(data if data is not None else {})
    except ValidationError as exc:
        raise TargetConfigError(format_validation_error(source, exc)) from None


def load_target_config(path: Path | str) -> TargetConfig:
    """Read a YAML (.yaml/.yml) or TOML (.toml) target configuration."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise TargetConfigError(f"{path}: cannot read ({exc.strerror})") from None
    try:
        data = tomllib.loads(text) if path.suffix == ".toml" else yaml.safe_load(text)
    except (yaml.YAMLError, tomllib.TOMLDecodeError) as exc:
        raise TargetConfigError(f"{path}: not valid {'TOML' if path.suffix == '.toml' else 'YAML'} "
                                f"({str(exc).splitlines()[0]})") from None
    config = parse_target_config(data, str(path))
    if config.urdf is not None and not config.urdf.is_absolute():
        # Relative URDF paths are relative to the config file, not the working directory.
        config = config.model_copy(update={"urdf": (path.parent / config.urdf).resolve()})
    return config


def parse_fault(data: Any, source: str = "fault") -> Fault:
    """Validate one fault command (from the control socket)."""
    try:
        return _FAULT_ADAPTER.validate_python(data)
    except ValidationError as exc:
        raise TargetConfigError(format_validation_error(source, exc)) from None
