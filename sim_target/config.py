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
    control_socket: /run/hil/target.sock      # optional: run-time fault injection

Faults share one schema between the file (scheduled at ``at_s``, simulated seconds in lock-step,
seconds since start in real time) and the control socket (applied at once). Bad input raises
:class:`TargetConfigError` (exit code 2) with one line naming the file and field.
"""

from __future__ import annotations

import math
import os
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import (
    Field,
    TypeAdapter,
    ValidationError,
    model_validator,
)

from drivers.busload import DEFAULT_LIMIT, TPDO_FD_SYNC_BYTES, check_bus_load
from drivers.config import (
    DriveBusConfig,
    TransportConfig,
    format_validation_error,
    is_loopback_host,
    read_config_text,
    read_yaml_config,
)
from drivers.errors import BusLoadError
from drivers.strict_input import StrictModel
from sim_target.emulated.profile import DriveProfile
from sim_target.robots import DEFAULT_ROBOT, RobotLookupError, builtin_urdf_path

# An impulse (a blow on the arm) may exceed what the joint's motor can give, not by orders of
# magnitude: 1e30 N·m would only produce NaN states. The paper's is at most 0.6× the UR5 limits.
IMPULSE_EFFORT_FACTOR = 10.0


class TargetConfigError(ValueError):
    """Bad target configuration or fault command; printed as one line."""

    exit_code = 2


class _Frozen(StrictModel):
    """Frozen, no unknown fields, no .inf/.nan ("not a finite number", not a range error), no
    ``true`` or ``"1"`` read as a number."""


def _finite(values: tuple[float, ...], field: str) -> tuple[float, ...]:
    if not all(math.isfinite(v) for v in values):
        raise ValueError(f"{field} must be finite")
    return values


_NonNegative = Annotated[float, Field(ge=0)]


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
    position_rad: float = Field(ge=0, le=10)  # standard deviation
    velocity_rad_s: float = Field(0.0, ge=0, le=100)


class PayloadFault(_Fault):
    """A payload on the flange (0 removes it)."""

    kind: Literal["payload"]
    mass_kg: float = Field(ge=0, le=1000)
    inertia_kg_m2: tuple[_NonNegative, _NonNegative, _NonNegative] = (0.0, 0.0, 0.0)  # principal moments


class ImpulseFault(_Fault):
    """An external joint torque over [at_s, at_s + duration_s); the paper's disturbance by default."""

    kind: Literal["impulse"]
    torque_nm: tuple[float, ...] = Field((1.0, 1.0, 5.0, 5.0, 10.0, 10.0), min_length=1)
    duration_s: float = Field(2e-5, gt=0, le=3600)  # 20 µs, as in the models simulator (docs/conditions.md)

    @model_validator(mode="after")
    def _check(self) -> ImpulseFault:
        _finite(self.torque_nm, "torque_nm")
        return self


Fault = Annotated[
    FrameFault | DriveFault | HeartbeatFault | EncoderNoiseFault | PayloadFault | ImpulseFault,
    Field(discriminator="kind"),
]
_FAULT_ADAPTER: TypeAdapter[Fault] = TypeAdapter(Fault)
PLANT_FAULTS = (EncoderNoiseFault, PayloadFault, ImpulseFault)
DRIVE_FAULTS = (FrameFault, DriveFault, HeartbeatFault)


class RunStart(_Frozen):
    """Start a new run (control socket ``{"kind": "start", ...}``; ``hil experiment --plant hil``).

    At the first period in which every drive is in Operation Enabled, after that period's step,
    the arm is placed at ``position_rad`` moving at ``velocity_rad_s``, simulated time restarts at
    0 and ``faults`` are scheduled from there (their ``at_s`` in the new time; the config's faults
    are dropped). The TPDOs of that SYNC report the placed state (free-running: the arm is placed at
    that SYNC, before its answer, without a step). A test rig's privilege (a real
    arm cannot be placed): it lets a HIL run start exactly where a simulation starts.
    """

    kind: Literal["start"]
    position_rad: tuple[float, ...] = Field(min_length=1)
    velocity_rad_s: tuple[float, ...] | None = None  # None: at rest
    faults: tuple[Fault, ...] = ()


_RUN_START_ADAPTER: TypeAdapter[RunStart] = TypeAdapter(RunStart)


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
    # One per joint: the drive presents a vendor's EDS/DCF and its motor (sim_target/emulated/profile.py).
    profiles: tuple[DriveProfile, ...] | None = None

    @model_validator(mode="after")
    def _check(self) -> DrivesConfig:
        if self.node_ids is not None:
            if len(set(self.node_ids)) != len(self.node_ids) or not all(1 <= n <= 127 for n in self.node_ids):
                raise ValueError(f"node_ids must be distinct and in 1..127, got {list(self.node_ids)}")
        return self


# pybullet steps per control period when the config gives none: lock-step keeps parity with the
# models simulator (4.3e-4 rad over 2 s); real time must fit a period on a small machine, at a
# parity cost stated in docs/target.md (benchmarks/bench_plant_parity.py): 4 substeps, 3.4e-3 /
# 7.0e-3 rad over 2 s, half the physics of 8 (1.7e-3 / 3.5e-3 rad).
LOCKSTEP_SUBSTEPS = 32
REALTIME_SUBSTEPS = 4


class PlantConfig(_Frozen):
    substeps: int | None = Field(None, ge=1, le=10_000)  # pybullet steps per period; None: per clock
    joint_names: tuple[str, ...] | None = None  # None: every revolute joint, URDF order
    initial_position_rad: tuple[float, ...] | None = None
    brake_holding_torque_nm: tuple[float, ...] | None = None  # None: twice the effort limit
    encoder_noise_rad: float = Field(0.0, ge=0, le=1.0)  # std dev; a real encoder's is ~1e-5 rad
    velocity_noise_rad_s: float = Field(0.0, ge=0, le=100.0)
    seed: int = 0


class RealtimeConfig(_Frozen):
    """The physics thread's OS settings, applied with ``clock: realtime`` (sim_target/rt_settings.py),
    and in lock-step with ``in_lockstep`` (a lock-stepped run's rate is the two processes' hand-offs:
    on a shared machine each waits behind other jobs without SCHED_FIFO, docs/target.md)."""

    fifo_priority: int = Field(80, ge=0, le=99)  # SCHED_FIFO priority; 0: leave the default policy
    cpus: tuple[int, ...] | None = None  # CPUs the physics thread may run on; None: any
    lock_memory: bool = True  # mlockall: no page fault in the loop
    in_lockstep: bool = False  # also with clock: lockstep (the thread serving the SYNCs)

    @model_validator(mode="after")
    def _check(self) -> RealtimeConfig:
        if self.cpus is not None:  # the machine's CPUs (a CPU outside this process's mask: a warning later)
            count = os.cpu_count() or 1
            if not self.cpus or any(not 0 <= cpu < count for cpu in self.cpus):
                raise ValueError(f"cpus {list(self.cpus)}: this machine has CPUs 0..{count - 1}")
        return self


class TargetConfig(_Frozen):
    robot: str | None = "ur5_paper"  # built-in robot name (models/robots/data/robots.yaml)
    urdf: Path | None = None  # or a URDF file; wins over robot
    period_s: float = Field(1e-3, gt=0, le=1.0)
    clock: Literal["lockstep", "realtime"] = "lockstep"
    bus: TransportConfig = TransportConfig()
    bridge: BridgeConfig | None = None
    drives: DrivesConfig = DrivesConfig()
    plant: PlantConfig = PlantConfig()
    faults: tuple[Fault, ...] = ()
    control_socket: Path | None = None  # Unix socket for run-time faults; no network traffic
    realism: str = "ideal"  # a realism profile (ideal, realistic, harsh) or a profile YAML (docs/realism.md)
    realtime: RealtimeConfig = RealtimeConfig()

    @property
    def substeps(self) -> int:
        """The plant's pybullet steps per period: the config's, else the clock's default."""
        if self.plant.substeps is not None:
            return self.plant.substeps
        return REALTIME_SUBSTEPS if self.clock == "realtime" else LOCKSTEP_SUBSTEPS

    @model_validator(mode="after")
    def _check(self) -> TargetConfig:
        if self.bridge is not None and self.bus.interface != "virtual":
            raise ValueError("bridge: only a virtual bus can be served to other processes")
        return self


# --- loading ---------------------------------------------------------------------------------------


def parse_target_config(data: Any, source: str = "config", base_dir: Path | None = None) -> TargetConfig:
    """Validate a mapping, then check it against its URDF and the drive bus (``check_target_config``)."""
    if data is None:
        raise TargetConfigError(f"{source}: empty (expected a mapping of target settings)")
    if not isinstance(data, dict):
        raise TargetConfigError(f"{source}: expected a mapping of target settings, got {type(data).__name__}")
    try:
        config = TargetConfig.model_validate(data, context={"base_dir": base_dir})
    except ValidationError as exc:
        raise TargetConfigError(format_validation_error(source, exc)) from None
    check_target_config(config, source)
    return config


def load_target_config(path: Path | str) -> TargetConfig:
    """Read a YAML (.yaml/.yml) or TOML (.toml) target configuration."""
    path = Path(path)
    if path.suffix == ".toml":
        try:
            data: Any = tomllib.loads(read_config_text(path, TargetConfigError, "a target config"))
        except tomllib.TOMLDecodeError as exc:
            raise TargetConfigError(f"{path}: not valid TOML ({str(exc).splitlines()[0]})") from None
    else:
        data = read_yaml_config(path, TargetConfigError, "a target config")
    if data is None or data == {}:
        raise TargetConfigError(f"{path}: empty file (expected target settings; see deploy/target.virtual.yaml)")
    if isinstance(data, dict) and isinstance(data.get("urdf"), str) and not Path(data["urdf"]).is_absolute():
        # Relative URDF paths are relative to the config file, not the working directory.
        data = {**data, "urdf": str((path.parent / data["urdf"]).resolve())}
    realism = data.get("realism") if isinstance(data, dict) else None
    if isinstance(realism, str) and realism not in ("ideal", "realistic", "harsh") and not Path(realism).is_absolute():
        data = {**data, "realism": str((path.parent / realism).resolve())}  # a profile file, like urdf
    return parse_target_config(data, str(path), path.resolve().parent)  # drives.profiles' eds: same rule


def parse_fault(data: Any, source: str = "fault") -> Fault:
    """Validate one fault command's schema (from the control socket); see also ``check_fault``."""
    try:
        return _FAULT_ADAPTER.validate_python(data)
    except ValidationError as exc:
        raise TargetConfigError(format_validation_error(source, exc)) from None


def parse_run_start(data: Any, source: str = "start") -> RunStart:
    """Validate a ``{"kind": "start", ...}`` command's schema; see also ``check_run_start``."""
    try:
        return _RUN_START_ADAPTER.validate_python(data)
    except ValidationError as exc:
        raise TargetConfigError(format_validation_error(source, exc)) from None


# --- checks against the robot and the bus ----------------------------------------------------------


def target_urdf_path(config: TargetConfig) -> Path:
    """The URDF the plant will load: ``urdf``, or the built-in robot's (sim_target/robots.py)."""
    if config.urdf is not None:
        return config.urdf
    try:
        return builtin_urdf_path(config.robot or DEFAULT_ROBOT)
    except RobotLookupError as exc:
        raise TargetConfigError(str(exc)) from None


@dataclass(frozen=True)
class TargetLayout:
    """The drives the target will run: joint names, limits and node ids, in drive order."""

    joint_names: tuple[str, ...]
    lower_rad: tuple[float, ...]
    upper_rad: tuple[float, ...]
    node_ids: tuple[int, ...]
    effort_nm: tuple[float, ...] | None = None  # URDF effort limits (None: not known)
    velocity_limit_rad_s: tuple[float, ...] | None = None  # URDF velocity limits

    @property
    def n_joints(self) -> int:
        return len(self.joint_names)


def target_layout(config: TargetConfig, source: str = "config") -> TargetLayout:
    """Joints (as the plant picks them: ``plant.joint_names`` or every revolute joint) and node ids."""
    from sim_target.urdf import UrdfError, read_urdf_joints

    urdf = target_urdf_path(config)
    try:
        joints = read_urdf_joints(urdf)
    except UrdfError as exc:
        raise TargetConfigError(f"{source}: urdf: {exc}") from None
    movable = {j.name: j for j in joints if j.type in ("revolute", "continuous", "prismatic")}
    if config.plant.joint_names is not None:
        unknown = [n for n in config.plant.joint_names if n not in movable]
        if unknown:
            raise TargetConfigError(f"{source}: plant.joint_names: {unknown} are not movable joints of {urdf.name}")
        chosen = [movable[n] for n in config.plant.joint_names]
    else:
        chosen = [j for j in joints if j.type == "revolute"]
    if not chosen:
        raise TargetConfigError(f"{source}: {urdf.name}: no revolute joint to drive")
    node_ids = config.drives.node_ids or tuple(range(1, len(chosen) + 1))
    if len(node_ids) != len(chosen):
        raise TargetConfigError(
            f"{source}: drives.node_ids: {len(node_ids)} ids for {len(chosen)} joints of {urdf.name}"
        )
    profiles = config.drives.profiles
    if profiles is not None and len(profiles) != len(chosen):
        raise TargetConfigError(f"{source}: drives.profiles: {len(profiles)} for {len(chosen)} joints of {urdf.name}")
    for i, profile in enumerate(profiles or ()):
        if not profile.eds.is_file():
            raise TargetConfigError(f"{source}: drives.profiles.{i}.eds: {profile.eds}: file not found")
    return TargetLayout(
        tuple(j.name for j in chosen),
        tuple(j.lower_rad for j in chosen),
        tuple(j.upper_rad for j in chosen),
        tuple(node_ids),
        tuple(j.effort_nm for j in chosen),
        tuple(j.velocity_rad_s for j in chosen),
    )


def check_fault(fault: Fault, layout: TargetLayout, source: str = "fault") -> None:
    """Refuse a fault the target could not apply (wrong joint count, a node that is not a drive)."""
    nodes = set(layout.node_ids)

    def known(node_id: int, field: str) -> None:
        if node_id not in nodes:
            raise TargetConfigError(
                f"{source}: {field}: node {node_id} is not a drive of this target "
                f"(drives: {', '.join(map(str, layout.node_ids))})"
            )

    if isinstance(fault, ImpulseFault) and len(fault.torque_nm) != layout.n_joints:
        raise TargetConfigError(f"{source}: torque_nm: {len(fault.torque_nm)} values for {layout.n_joints} joints")
    if isinstance(fault, ImpulseFault) and layout.effort_nm is not None:
        limits = zip(fault.torque_nm, layout.effort_nm, layout.joint_names, strict=True)
        for i, (torque, effort, name) in enumerate(limits):
            if abs(torque) > IMPULSE_EFFORT_FACTOR * effort:
                raise TargetConfigError(
                    f"{source}: torque_nm[{i}]: {torque:g} N·m is beyond {IMPULSE_EFFORT_FACTOR:g}× joint '{name}' "
                    f"effort limit ({effort:g} N·m)"
                )
    if isinstance(fault, (DriveFault, HeartbeatFault)):
        known(fault.node_id, "node_id")
    if isinstance(fault, FrameFault) and fault.node_ids is not None:
        for i, node_id in enumerate(fault.node_ids):
            known(node_id, f"node_ids[{i}]")


def check_run_start(start: RunStart, layout: TargetLayout, source: str = "start") -> None:
    """Refuse a start state the plant could not take (joint count, outside the joint limits)."""
    n = layout.n_joints
    for field in ("position_rad", "velocity_rad_s"):
        values = getattr(start, field)
        if values is not None and len(values) != n:
            raise TargetConfigError(f"{source}: {field}: {len(values)} values for {n} joints")
    for i, (q, lo, hi, name) in enumerate(
        zip(start.position_rad, layout.lower_rad, layout.upper_rad, layout.joint_names, strict=True)
    ):
        if not lo <= q <= hi:
            raise TargetConfigError(
                f"{source}: position_rad[{i}]: {q:g} rad is outside joint '{name}' limits [{lo:g}, {hi:g}]"
            )
    if start.velocity_rad_s is not None and layout.velocity_limit_rad_s is not None:
        for i, (v, limit, name) in enumerate(
            zip(start.velocity_rad_s, layout.velocity_limit_rad_s, layout.joint_names, strict=True)
        ):
            if not abs(v) <= limit:
                raise TargetConfigError(
                    f"{source}: velocity_rad_s[{i}]: {v:g} rad/s is beyond joint '{name}' velocity limit {limit:g}"
                )
    for i, fault in enumerate(start.faults):
        check_fault(fault, layout, f"{source}: faults[{i}]")


def check_target_config(config: TargetConfig, source: str = "config") -> TargetLayout:
    """What the schema alone cannot see: the URDF (limits, inertials), the initial position inside
    the joint limits, the faults against the drives, and the bus load the runtime's DriveBus would
    refuse (the same budget: drivers.busload with DriveBusConfig's heartbeat defaults)."""
    layout = target_layout(config, source)
    q0 = config.plant.initial_position_rad
    if q0 is not None:
        if len(q0) != layout.n_joints:
            raise TargetConfigError(
                f"{source}: plant.initial_position_rad: {len(q0)} values for {layout.n_joints} joints"
            )
        for i, (q, lo, hi, name) in enumerate(
            zip(q0, layout.lower_rad, layout.upper_rad, layout.joint_names, strict=True)
        ):
            if not lo <= q <= hi:
                raise TargetConfigError(
                    f"{source}: plant.initial_position_rad[{i}]: {q:g} rad is outside joint "
                    f"'{name}' limits [{lo:g}, {hi:g}]"
                )
    for field in ("brake_holding_torque_nm",):
        values = getattr(config.plant, field)
        if values is not None:
            if len(values) != layout.n_joints:
                raise TargetConfigError(f"{source}: plant.{field}: {len(values)} values for {layout.n_joints} joints")
            if any(v < 0 for v in values):
                raise TargetConfigError(f"{source}: plant.{field}: negative value")
    for i, fault in enumerate(config.faults):
        check_fault(fault, layout, f"{source}: faults[{i}]")
    if config.bus.interface == "ipc":
        from drivers.ipc.directory import channel_problem

        problem = channel_problem(config.bus.channel, config.bus.group)
        if problem is not None:
            raise TargetConfigError(f"{source}: bus.channel: {problem}")
    if config.realism != "ideal":  # before pybullet starts: the profile's one line is the only output
        from sim_target.realism import RealismError
        from sim_target.realism_profiles import load_realism

        try:
            physics_step_s = config.period_s / config.substeps
            load_realism(config.realism, layout.n_joints, config.period_s, physics_step_s, [1.0] * layout.n_joints)
        except RealismError as exc:
            raise TargetConfigError(str(exc)) from None
    defaults = DriveBusConfig.model_fields
    try:
        check_bus_load(
            layout.n_joints,
            1.0 / config.period_s,
            config.bus.bitrate,
            config.bus.fd_data_bitrate,
            defaults["heartbeat_producer_ms"].default / 1000.0,
            DEFAULT_LIMIT,
            f"{source}: bus",
            TPDO_FD_SYNC_BYTES,
            defaults["master_heartbeat_ms"].default / 1000.0,
        )
    except BusLoadError as exc:
        raise TargetConfigError(str(exc)) from None
    return layout
