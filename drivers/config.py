"""Frozen configuration of the drive bus, validated once at load.

A YAML (or dict) like::

    transport: {interface: remote, bridge_port: 54701, bitrate: 1000000,
                fd: true, data_bitrate: 5000000}
    period_s: 0.001
    joints:
      - {name: shoulder_pan, node_id: 1, max_torque_nm: 150.0}
      - ...

Bad input raises :class:`drivers.errors.DriveConfigError` with one line naming the file and field.
"""

from __future__ import annotations

import ipaddress
import math
import re
from pathlib import Path
from typing import Any, Literal
from urllib.parse import urlparse

import yaml
from pydantic import Field, ValidationError, model_validator

from drivers.busload import DEFAULT_LIMIT, TPDO_FD_SYNC_BYTES, BusLoad, check_bus_load
from drivers.cia402.scaling import INT16_MAX, JointScaling, check_torque_range
from drivers.drive_spec import DriveSpec
from drivers.errors import DriveConfigError
from drivers.strict_input import StrictModel, error_location, load_yaml_unique

Interface = Literal["virtual", "socketcan", "remote", "slcan", "ipc"]
LOOPBACK_NAMES = frozenset({"localhost", "ip6-localhost"})


def is_loopback_host(host: str) -> bool:
    if host.lower() in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


class _Frozen(StrictModel):
    """Frozen, no unknown fields, no .inf/.nan, no ``true`` or ``"1"`` read as a number."""


class TransportConfig(_Frozen):
    """Which python-can bus to open."""

    interface: Interface = "virtual"
    # virtual: any name shared in-process; socketcan: vcan0/can0; slcan: serial port;
    # remote: a ws:// URL (left empty, it is built from bridge_host/bridge_port).
    # ipc: the bus directory shared by the processes, or a name (docs/ipc_bus.md).
    channel: str = "hil"
    bitrate: int = Field(1_000_000, gt=0)  # nominal (arbitration) bit rate, bit/s
    fd: bool = False  # CAN FD frames (one 12-byte TPDO per drive)
    data_bitrate: int | None = Field(None, gt=0)  # CAN FD data-phase bit rate, bit/s
    bridge_host: str = "127.0.0.1"  # python-can-remote server; loopback only
    bridge_port: int = Field(54701, gt=0, lt=65536)
    # ipc: a group whose members may share the bus (directory 0770, sockets 0660); None: this user only.
    group: str | None = None

    @model_validator(mode="after")
    def _check(self) -> TransportConfig:
        if self.fd and self.data_bitrate is None:
            raise ValueError("data_bitrate is required when fd is on")
        if self.fd and self.data_bitrate is not None and self.data_bitrate < self.bitrate:
            raise ValueError("data_bitrate must not be below bitrate")
        if self.interface == "remote":
            host = urlparse(self.remote_url).hostname or ""
            if not is_loopback_host(host):
                raise ValueError(f"remote bridge host {host!r} is not loopback (127.0.0.1/::1)")
        return self

    @property
    def remote_url(self) -> str:
        if self.channel.startswith(("ws://", "wss://")):
            return self.channel
        host = self.bridge_host
        if ":" in host and not host.startswith("["):
            host = f"[{host}]"
        return f"ws://{host}:{self.bridge_port}/"

    @property
    def fd_data_bitrate(self) -> int | None:
        """Data bit rate when CAN FD is on, else None (what the bus-load budget takes)."""
        return self.data_bitrate if self.fd else None


class JointDriveConfig(_Frozen):
    """One joint's drive."""

    name: str
    node_id: int = Field(ge=1, le=127)  # CANopen node id
    max_torque_nm: float = Field(gt=0)  # written to 0x6072; set-points are clipped to it
    # 0x6076, mN·m; 1 ‰ of it is the torque resolution. Default: the max torque at ~30000 ‰.
    rated_torque_mnm: int | None = Field(None, gt=0)
    # Encoder counts per joint revolution; None adopts the drive's 0x608F, else it must match.
    encoder_counts_per_rev: int | None = Field(None, gt=0)
    # A real drive described by its own EDS/DCF: scaling, reactions, SDO init list (drivers/drive_spec.py).
    # None: the emulated drive of drivers/cia402/data, scaled by the two fields above.
    drive: DriveSpec | None = None

    @model_validator(mode="after")
    def _check(self) -> JointDriveConfig:
        if not math.isfinite(self.max_torque_nm):
            raise ValueError("max_torque_nm must be finite")
        if self.drive is not None:
            if self.rated_torque_mnm is not None or self.encoder_counts_per_rev is not None:
                raise ValueError("with a drive section, give the scaling there (drive.rated_torque, ...)")
            return self  # its scaling is checked against the EDS and the drive (drivers/eds_check.py)
        check_torque_range(self.max_torque_nm, self.effective_rated_torque_mnm)
        return self

    @property
    def effective_rated_torque_mnm(self) -> int:
        if self.rated_torque_mnm is not None:
            return self.rated_torque_mnm
        return max(1, math.ceil(self.max_torque_nm * 1e6 / 30000))

    @property
    def max_torque_permille(self) -> int:
        return min(INT16_MAX, math.floor(self.max_torque_nm * 1e6 / self.effective_rated_torque_mnm))

    def scaling(self, counts_per_rad: float) -> JointScaling:
        return JointScaling(counts_per_rad, self.effective_rated_torque_mnm)


class DriveBusConfig(_Frozen):
    transport: TransportConfig = TransportConfig()
    joints: tuple[JointDriveConfig, ...] = Field(min_length=1)
    period_s: float = Field(gt=0, le=1.0)  # control period: one SYNC per period
    heartbeat_producer_ms: int = Field(50, ge=1, le=65535)  # written to every drive's 0x1017
    # Defaults that hold on a loaded 2-core machine with the drives in another Python process
    # (docs/drivers.md, "Timeouts and what they trade"); a real bus can be much tighter
    # (deploy/runtime.can0.yaml).
    # Upper bounds: a start-up or a stop that waits longer than these is hung, and the daemon must
    # still answer SIGTERM (docs/security.md, "Configs").
    heartbeat_timeout_s: float = Field(1.0, gt=0, le=60.0)  # no heartbeat for this long: HeartbeatLostError
    feedback_timeout_s: float = Field(0.02, gt=0, le=1.0)  # wait for TPDOs after SYNC, per cycle
    # Consecutive cycles a drive may miss before the driver raises FeedbackTimeoutError; None: not
    # enforced here, the caller supervises staleness (the runtime: safety.max_stale_cycles, one budget).
    max_missed_cycles: int | None = Field(25, ge=0, le=10_000)
    sdo_timeout_s: float = Field(0.3, gt=0, le=10.0)
    state_change_timeout_s: float = Field(2.0, gt=0, le=60.0)  # NMT / CiA 402 transitions at start-up
    quick_stop_option: int = Field(2, ge=0, le=8)  # written to 0x605A
    # The master's own heartbeat (NMT node id, period): the drives consume it (0x1016).
    master_node_id: int = Field(127, ge=1, le=127)
    master_heartbeat_ms: int = Field(20, ge=1, le=65535)
    # Loss of the master: a drive that misses its heartbeat, its RPDOs or the SYNC for this long
    # quick-stops on its own (0x1016, 0x1400:05, 0x2101; 0x6007 = quick stop). None: not set up.
    comm_loss_timeout_s: float | None = Field(0.5, gt=0, le=65.535)
    bus_load_limit: float = Field(DEFAULT_LIMIT, gt=0, le=1)
    eds_path: Path | None = None  # None: the EDS shipped in drivers/cia402/data

    @model_validator(mode="after")
    def _check(self) -> DriveBusConfig:
        ids = [j.node_id for j in self.joints]
        if len(set(ids)) != len(ids):
            raise ValueError(f"duplicate node_id in joints: {ids}")
        if self.heartbeat_timeout_s * 1000 <= self.heartbeat_producer_ms:
            raise ValueError("heartbeat_timeout_s must exceed the heartbeat producer time")
        if self.master_node_id in ids:
            raise ValueError(f"master_node_id {self.master_node_id} is also a drive's node_id")
        if self.comm_loss_timeout_s is not None:
            if round(self.comm_loss_timeout_s * 1000) <= self.master_heartbeat_ms:
                raise ValueError("comm_loss_timeout_s must exceed the master heartbeat period (master_heartbeat_ms)")
            if self.comm_loss_timeout_s <= self.feedback_timeout_s + self.period_s:
                # A cycle waiting for late feedback sends nothing meanwhile: not a lost master.
                raise ValueError("comm_loss_timeout_s must exceed feedback_timeout_s + period_s")
        return self

    @property
    def node_ids(self) -> tuple[int, ...]:
        return tuple(j.node_id for j in self.joints)

    def bus_load(self, source: str = "config") -> BusLoad:
        """The configured bus load; :class:`BusLoadError` if above ``bus_load_limit``."""
        return check_bus_load(
            len(self.joints),
            1.0 / self.period_s,
            self.transport.bitrate,
            self.transport.fd_data_bitrate,
            self.heartbeat_producer_ms / 1000.0,
            self.bus_load_limit,
            source,
            TPDO_FD_SYNC_BYTES,  # the driver maps the FD TPDO with the SYNC counter echo
            self.master_heartbeat_ms / 1000.0,
        )


MAX_CONFIG_FILE_BYTES = 1 << 20  # config and conditions files are a few kB: refuse what plainly is not one


def read_config_text(path: Path, error: type[Exception], what: str, max_bytes: int = MAX_CONFIG_FILE_BYTES) -> str:
    """The text of a config-like file; ``error`` with one line naming ``path`` for a missing, unreadable,
    oversized or binary file (shared by the drive, runtime, target and conditions loaders)."""
    if not path.exists():
        raise error(f"{path}: file not found")
    if not path.is_file():
        raise error(f"{path}: not a regular file")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise error(f"{path}: cannot read ({exc.strerror or exc})") from None
    if len(data) > max_bytes:
        raise error(f"{path}: {len(data)} bytes, not {what} (limit {max_bytes})")
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise error(f"{path}: not a UTF-8 text file (byte {exc.start})") from None
    if "\x00" in text:
        raise error(f"{path}: not a text file (contains NUL bytes)")
    return text


def read_yaml_config(path: Path, error: type[Exception], what: str) -> Any:
    """The YAML document in a config-like file, after :func:`read_config_text`'s checks; ``error``
    with one line naming ``path`` (and the line, when YAML says it) for malformed or too deeply
    nested YAML. Shared by the drive-bus, runtime, target and conditions loaders."""
    text = read_config_text(path, error, what)
    try:
        return load_yaml_unique(text)  # a key given twice is refused, not silently the last one
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None)
        raise error(f"{path}: not valid YAML{where}" + (f" ({problem})" if problem else "")) from None
    except RecursionError:
        raise error(f"{path}: not valid YAML (nested too deeply)") from None


def format_validation_error(source: str, exc: ValidationError) -> str:
    """One line naming the file and the first failing field (pydantic's own message is multi-line)."""
    errors = exc.errors()
    first = errors[0]
    loc = ".".join(str(part) for part in error_location(first))
    more = f" (+{len(errors) - 1} more)" if len(errors) > 1 else ""
    message = str(first["msg"])
    if first.get("type") == "value_error":  # a validator's own ValueError: its text, without pydantic's prefix
        message = message.removeprefix("Value error, ")
        if not loc and re.match(r"[A-Za-z_][\w.\[\]]*: ", message):  # a cross-field check names its field
            return f"{source}: {message}{more}"
    return f"{source}: {loc or '(top level)'}: {message}{more}"


def parse_drive_bus_config(data: Any, source: str = "config", base_dir: Path | None = None) -> DriveBusConfig:
    """Validate a mapping (e.g. one section of a larger config) and check the bus-load budget;
    relative ``drive.eds`` paths are taken relative to ``base_dir``."""
    try:
        config = DriveBusConfig.model_validate(data, context={"base_dir": base_dir})
    except ValidationError as exc:
        raise DriveConfigError(format_validation_error(source, exc)) from None
    config.bus_load(source)
    return config


def load_drive_bus_config(path: Path | str) -> DriveBusConfig:
    path = Path(path)
    data = read_yaml_config(path, DriveConfigError, "a drive-bus config")
    return parse_drive_bus_config(data, str(path), path.resolve().parent)
