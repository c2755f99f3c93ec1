"""The runtime's configuration: one YAML file, validated once, frozen (``hil run --config FILE``).

::

    robot: ur5_paper                     # must be the bundle's robot
    bundle:
      path: ../models/bundles/ur5_paper/pd   # relative paths are relative to this file
      mode: lmpc                         # lmpc: the fused law + emulator; fb: the law alone
      urdf_sha256: null                  # the arm's URDF hash: the bundle's must match; null: unchecked
      trusted_keys: []                   # Ed25519 public keys (PEM): the bundle must be signed by one
      torque_rate_limit: none            # none | libfranka: the LMPC torque's change per cycle clamped
      encoder_noise_rad: 1.0e-5          # encoder noise, RMS: an lmpc bundle that turns it into torque
      velocity_noise_rad_s: null         # steps beyond the rate bound is refused (null: differenced)
      velocity_filter_hz: null           # lmpc: low-pass on the measured velocity before the policy
    bus:                                 # drivers.config.DriveBusConfig: transport, joints, period
      transport: {interface: remote, bridge_host: 127.0.0.1, bridge_port: 54701,
                  fd: true, data_bitrate: 5000000}
      period_s: 0.002                    # the control period: one SYNC, one policy step
      joints:                            # order = the bundle's joint order
        - {name: shoulder_pan_joint, node_id: 1, max_torque_nm: 102.0}
        - ...
    reference:
      kind: condition                    # condition | hold (the measured start pose)
      conditions_file: null              # null: the paper's five (hil_runtime/data)
      condition: C1
      ramp_s: 2.0                        # from the measured pose onto the reference start
      start: ramp                        # ramp | condition (no ramp: a plant placed on the condition)
    loop:
      pacing: clock                      # clock: absolute deadlines; bus: as fast as the bus answers
      time_base: auto                    # reference index: wall (clock) or cycles (lock-step, bus)
      exchange: auto                     # overlap (clock pacing) or wait (bus pacing); docs/runtime.md
      cpu_affinity: null                 # e.g. [1]: the loop thread only
      fifo_priority: null                # e.g. 50: SCHED_FIFO on the loop thread only
      lock_memory: false                 # mlockall(MCL_CURRENT | MCL_FUTURE)
      spin_s: null                       # hybrid wait: spin this long before each deadline (null:
                                         # 100 µs with cpu_affinity, else 0; docs/runtime.md)
      duration_s: null                   # stop (exit 0) after this long in ACTIVE; null: run on
    safety:                              # null: the bundle manifest's limits
      position_lower_rad: null
      position_upper_rad: null
      velocity_limit_rad_s: null
      max_stale_cycles: 1
      overrun_budget: 20                 # late periods in a row before FAULT overrun_budget
    telemetry: {enabled: false}          # hil_runtime.telemetry
    control_socket: /run/hil/runtime.sock   # hil status / hil reset / hil stop; null: none

Bad input raises :class:`RuntimeConfigError` (exit code 2) with one line naming the file and the
field. Whether the bundle matches the drives (joint count, order, period) is checked when the
bundle is loaded (:func:`hil_runtime.loading.load_bundle_for`), before the bus is touched.
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, ValidationError, model_validator

from drivers.config import DriveBusConfig, format_validation_error, read_yaml_config
from drivers.errors import DriveConfigError
from drivers.strict_input import StrictModel
from hil_runtime.bundle_probes import DEFAULT_ENCODER_NOISE_RAD
from hil_runtime.telemetry.config import TelemetryConfig
from hil_runtime.velocity_filter import filter_pole

MAX_RAMP_S = 60.0  # the reference's ramp from the measured pose (precomputed, like the condition)
MAX_RUN_S = 7 * 86400.0  # loop.duration_s: a week; null runs until stopped


class RuntimeConfigError(ValueError):
    """A runtime config the daemon refuses: one line naming the file and the field."""

    exit_code = 2


class _Frozen(StrictModel):
    """Frozen, no unknown fields, no .inf/.nan, no ``true`` or ``"1"`` read as a number."""


class BundleSection(_Frozen):
    path: Path  # the bundle directory (manifest.json + policy.onnx)
    mode: Literal["lmpc", "fb"] = "lmpc"  # lmpc: fused law + emulator; fb: the law's torque alone
    # The sha256 of the arm's URDF, when the operator pins it: the bundle's robot.urdf_sha256 must
    # be the same (a bundle exported for another description of the arm is refused). None: the
    # robot's name is checked only (the runtime reads no URDF; real drives report none).
    urdf_sha256: str | None = Field(None, pattern=r"^[0-9a-f]{64}$")
    # Ed25519 public keys (PEM files, `hil bundle keygen`): when any is listed, the bundle must be
    # signed by one of them (`hil bundle sign`); an unsigned or re-signed bundle is refused.
    trusted_keys: tuple[Path, ...] = ()
    # libfranka: the lmpc torque's change per cycle clamped per joint to libfranka's rate bound
    # (hil_runtime.rate_limit, docs/lmpc.md section 10), against the torque last commanded; none: off.
    torque_rate_limit: Literal["none", "libfranka"] = "none"
    # The arm's measurement noise, RMS: the joint encoders' position (jitter and quantization; 1e-5 rad is
    # about one increment of a 19-bit encoder) and the velocity the drives report (null: the position
    # differenced over one period, unfiltered: sqrt(2) x encoder_noise_rad / period_s). In lmpc mode a
    # bundle that turns this noise into torque steps beyond the robot's rate bound per period is refused
    # at load (hil_runtime.bundle_probes.check_sensing); 0: perfect sensors (an emulated arm without noise).
    encoder_noise_rad: float = Field(DEFAULT_ENCODER_NOISE_RAD, ge=0.0, le=0.1)
    velocity_noise_rad_s: float | None = Field(None, ge=0.0, le=100.0)
    # lmpc mode: a first-order low-pass at this cutoff on the measured velocity before the policy
    # (hil_runtime.velocity_filter; for drives whose velocity is noisy; it costs tracking on a clean one,
    # docs/lmpc.md section 13); null: off. Must be below the Nyquist rate of bus.period_s.
    velocity_filter_hz: float | None = Field(None, gt=0.0)


class ReferenceSection(_Frozen):
    kind: Literal["condition", "hold"] = "condition"
    conditions_file: Path | None = None  # None: the paper's five (hil_runtime/data)
    condition: str | None = None  # required for kind: condition
    ramp_s: float = Field(2.0, ge=0.0, le=MAX_RAMP_S)  # shortest ramp from the measured pose onto the reference start
    # The ramp is lengthened so its peak speed stays below this fraction of each joint's limit.
    ramp_speed_fraction: float = Field(0.25, gt=0.0, le=1.0)
    # ramp: from the measured pose onto the condition (above). condition: the condition from its
    # t = 0 at once, no ramp, for a plant placed on the condition's initial state (a HIL target's
    # RunStart, hil experiment --plant hil); on a real arm the first error would be a step.
    start: Literal["ramp", "condition"] = "ramp"

    @model_validator(mode="after")
    def _check(self) -> ReferenceSection:
        if self.kind == "condition" and not self.condition:
            raise ValueError("condition: required when kind is 'condition' (e.g. C1)")
        if self.kind == "hold" and (self.condition or self.conditions_file):
            raise ValueError("kind 'hold' takes no condition or conditions_file")
        return self


DEFAULT_SPIN_S = 100e-6  # the hybrid wait's spin with a CPU of its own (docs/runtime.md, measured)


class LoopSection(_Frozen):
    # clock: absolute deadlines on the monotonic clock at bus.period_s (overruns counted, skipped).
    # bus: no sleeping; a lock-stepped target's answer paces the loop (simulated time still
    # advances one period per cycle).
    pacing: Literal["clock", "bus"] = "clock"
    # What indexes the reference: wall (period slots, skipped ones included: a real arm moves on
    # while the loop overruns) or cycles (one row per exchange: a lock-stepped target advances one
    # period per SYNC whatever the wall clock does). auto: wall with clock pacing, cycles with bus.
    time_base: Literal["auto", "wall", "cycles"] = "auto"
    # How a cycle meets the drives: wait (set-points and SYNC out, then wait for this SYNC's
    # feedback: a lock-stepped target answers after its simulated period) or overlap (the feedback
    # of the SYNC sent last cycle, compute, set-points and SYNC out: a real master's sequence, the
    # drives' answer time outside the cycle; the same one period from sample to torque). auto:
    # overlap with clock pacing, wait with bus pacing (docs/runtime.md, "The cycle").
    exchange: Literal["auto", "wait", "overlap"] = "auto"
    cpu_affinity: tuple[int, ...] | None = None  # CPUs for the loop thread only
    fifo_priority: int | None = Field(None, ge=1, le=99)  # SCHED_FIFO priority of the loop thread
    lock_memory: bool = False  # mlockall; needs LimitMEMLOCK (systemd) or CAP_IPC_LOCK
    # Clock pacing's hybrid wait: sleep until spin_s before each deadline, then spin on the clock
    # (no late wake-up at the cycle's start). None: DEFAULT_SPIN_S when the loop has
    # CPUs of its own (cpu_affinity), else 0 (spinning on a shared CPU takes it from others).
    spin_s: float | None = Field(None, ge=0.0, le=0.5e-3)
    warmup_cycles: int = Field(200, ge=0, le=100_000)  # policy/supervisor calls before ACTIVE
    stats_window: int = Field(4096, ge=16, le=1 << 20)  # cycles kept for median/p99/max
    stats_interval_s: float = Field(1.0, gt=0.0, le=3600.0)  # stats to telemetry / STATUS= this often
    duration_s: float | None = Field(None, gt=0.0, le=MAX_RUN_S)  # leave ACTIVE (stop, exit 0) after this long
    idle_poll_s: float = Field(0.01, gt=0.0, le=1.0)  # INACTIVE/FAULT: how often requests are read
    activate_on_reset: bool = True  # a reset goes on to ACTIVE (ramp from the measured pose)


class SafetySection(_Frozen):
    """Soft limits; None takes the bundle manifest's limits (position ±, velocity ±)."""

    position_lower_rad: tuple[float, ...] | None = None
    position_upper_rad: tuple[float, ...] | None = None
    velocity_limit_rad_s: tuple[float, ...] | None = None
    max_stale_cycles: int = Field(1, ge=0, le=1000)  # consecutive cycles with stale feedback before FAULT
    # Late periods in a row (an overrun and the periods it skipped) before FAULT overrun_budget.
    overrun_budget: int = Field(20, ge=1, le=100_000)

    @model_validator(mode="after")
    def _check(self) -> SafetySection:
        for name in ("position_lower_rad", "position_upper_rad", "velocity_limit_rad_s"):
            value = getattr(self, name)
            if value is not None and not all(math.isfinite(v) for v in value):
                raise ValueError(f"{name}: values must be finite")
        if self.velocity_limit_rad_s is not None and any(v <= 0 for v in self.velocity_limit_rad_s):
            raise ValueError("velocity_limit_rad_s: values must be positive")
        lo, hi = self.position_lower_rad, self.position_upper_rad
        if (
            lo is not None
            and hi is not None
            and (len(lo) != len(hi) or any(a >= b for a, b in zip(lo, hi, strict=True)))
        ):
            raise ValueError("position_lower_rad must be below position_upper_rad, joint by joint")
        return self


class RuntimeConfig(_Frozen):
    robot: str
    bundle: BundleSection
    bus: DriveBusConfig
    reference: ReferenceSection = ReferenceSection(kind="hold")
    loop: LoopSection = LoopSection()
    safety: SafetySection = SafetySection()
    telemetry: TelemetryConfig = TelemetryConfig()
    control_socket: Path | None = None  # Unix stream socket: hil status / reset / stop
    source: str = Field("config", exclude=True)  # the file it came from, for messages

    @model_validator(mode="after")
    def _check(self) -> RuntimeConfig:
        n = len(self.bus.joints)
        for name in ("position_lower_rad", "position_upper_rad", "velocity_limit_rad_s"):
            value = getattr(self.safety, name)
            if value is not None and len(value) != n:
                raise ValueError(f"safety.{name}: {len(value)} values for {n} joints")
        if self.bundle.velocity_filter_hz is not None:
            try:
                filter_pole(self.bundle.velocity_filter_hz, self.bus.period_s)
            except ValueError as exc:
                raise ValueError(f"bundle.velocity_filter_hz: {exc}") from None
        spin_s = self.loop.spin_s
        if spin_s is not None and spin_s >= self.bus.period_s / 2:
            raise ValueError(f"loop.spin_s: {spin_s:g} s is not under half the period ({self.bus.period_s:g} s)")
        # One stale-feedback budget: the supervisor's (FAULT stale_feedback); the runtime's drive bus
        # does not count its own (hil_runtime.factory). A config naming both must agree.
        missed, stale = self.bus.max_missed_cycles, self.safety.max_stale_cycles
        if "max_missed_cycles" in self.bus.model_fields_set and missed != stale:
            raise ValueError(
                f"bus.max_missed_cycles {missed} differs from safety.max_stale_cycles {stale}: the runtime has "
                "one stale-feedback budget, safety.max_stale_cycles (remove bus.max_missed_cycles)"
            )
        return self

    @property
    def period_s(self) -> float:
        return self.bus.period_s

    @property
    def loop_overlaps(self) -> bool:
        """Whether cycles overlap (``loop.exchange``; auto: with clock pacing)."""
        exchange = self.loop.exchange
        return self.loop.pacing == "clock" if exchange == "auto" else exchange == "overlap"

    @property
    def loop_spin_s(self) -> float:
        """The hybrid wait's spin the pacer uses: ``loop.spin_s``, or DEFAULT_SPIN_S (at most a
        quarter period) when the clock-paced loop has CPUs of its own, else 0."""
        loop = self.loop
        if loop.spin_s is not None:
            return loop.spin_s
        if not (loop.cpu_affinity and loop.pacing == "clock"):
            return 0.0
        return min(DEFAULT_SPIN_S, self.period_s / 4)

    @property
    def joint_names(self) -> tuple[str, ...]:
        return tuple(j.name for j in self.bus.joints)


def _resolve(path: Path | None, base: Path) -> Path | None:
    if path is None:
        return None
    path = path.expanduser()
    return Path(os.path.normpath(path if path.is_absolute() else base / path))


def parse_runtime_config(data: Any, source: str = "config", base_dir: Path | None = None) -> RuntimeConfig:
    """Validate a mapping; relative paths are taken relative to ``base_dir`` (the file's folder)."""
    if not isinstance(data, dict):
        raise RuntimeConfigError(f"{source}: expected a mapping at the top level")
    try:
        config = RuntimeConfig.model_validate({**data, "source": source}, context={"base_dir": base_dir})
    except ValidationError as exc:
        raise RuntimeConfigError(format_validation_error(source, exc)) from None
    try:
        config.bus.bus_load(f"{source}: bus")  # the bus-load budget, before anything is opened
    except DriveConfigError as exc:
        raise RuntimeConfigError(str(exc)) from None
    base = base_dir or Path.cwd()
    keys = tuple(_resolve(key, base) or key for key in config.bundle.trusted_keys)
    bundle = config.bundle.model_copy(update={"path": _resolve(config.bundle.path, base), "trusted_keys": keys})
    reference = config.reference.model_copy(
        update={"conditions_file": _resolve(config.reference.conditions_file, base)}
    )
    control = _resolve(config.control_socket, base)
    return config.model_copy(update={"bundle": bundle, "reference": reference, "control_socket": control})


def load_runtime_config(path: Path | str) -> RuntimeConfig:
    path = Path(path)
    data = read_yaml_config(path, RuntimeConfigError, "a runtime config")
    return parse_runtime_config(data, str(path), path.resolve().parent)
