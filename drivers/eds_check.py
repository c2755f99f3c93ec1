"""Offline checks of a drive bus against each drive's own EDS/DCF, before anything is written to a
drive: the objects the runtime needs (present, readable/writable, PDO-mappable with the right
length), the PDO lengths against the frame, cyclic synchronous torque in 0x6502, the CiA 402
profile in 0x1000, the scaling against the INTEGER16 per-mille range at the torque limit, the
configured reactions and SDO initialisation entries (present, writable, in range), and the
COB-IDs of the whole bus (no two senders on one identifier).

Every problem is a :class:`Finding` whose :meth:`~Finding.line` names the file, the node and the
object; :func:`raise_first_error` turns the first error into a one-line
:class:`~drivers.errors.DriveConfigError` (exit 2). Dictionaries are imported with canopen's
``import_od`` (EDS and DCF), never parsed by hand.
"""

from __future__ import annotations

import configparser
import functools
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Final, Literal

import canopen
from canopen.objectdictionary import ObjectDictionary, ODVariable, datatypes

from drivers.cia402 import frames as fr
from drivers.cia402 import od as odx
from drivers.cia402.scaling import INT16_MAX
from drivers.drive_spec import DriveSpec
from drivers.errors import DriveConfigError

if TYPE_CHECKING:
    from drivers.config import DriveBusConfig, JointDriveConfig

Level = Literal["error", "warning", "ok"]

WRITABLE: Final = frozenset({"wo", "rw", "rwr", "rww"})
BITS: Final = {
    datatypes.BOOLEAN: 1,
    datatypes.INTEGER8: 8,
    datatypes.UNSIGNED8: 8,
    datatypes.INTEGER16: 16,
    datatypes.UNSIGNED16: 16,
    datatypes.INTEGER32: 32,
    datatypes.UNSIGNED32: 32,
}
PROFILE_402: Final = 402
CST_BIT: Final = 1 << 9  # 0x6502 bit 9: cyclic synchronous torque
INTERPOLATION_PERIOD: Final = 0x60C2
FAULT_REACTION: Final = 0x605E
GEAR_RATIO: Final = 0x6091
EMCY_COB_ID: Final = 0x1014
CLASSICAL_PDO_BITS: Final = 64
FD_PDO_BITS: Final = 512

# What the runtime writes itself at start-up: an SDO init entry must not fight it.
RUNTIME_OWNED: Final = frozenset(
    {
        odx.CONTROLWORD,
        odx.TARGET_TORQUE,
        odx.MODES_OF_OPERATION,
        odx.HEARTBEAT_PRODUCER,
        odx.CONSUMER_HEARTBEAT,
        odx.SYNC_OVERFLOW,
        odx.RPDO1_COMM,
        odx.RPDO1_MAP,
        odx.TPDO1_COMM,
        odx.TPDO1_MAP,
        odx.TPDO2_COMM,
        odx.TPDO2_MAP,
        odx.QUICK_STOP_OPTION,
        FAULT_REACTION,
        odx.ABORT_CONNECTION_OPTION,
        INTERPOLATION_PERIOD,
    }
)


@dataclass(frozen=True)
class Finding:
    level: Level
    source: str  # the EDS/DCF (or the config for bus-wide findings)
    node_id: int
    obj: str  # "0x6071:00", or "-" for the drive as a whole
    message: str

    def line(self) -> str:
        return f"{self.source}: node {self.node_id}: {self.obj}: {self.message}"


def obj_name(index: int, subindex: int = 0) -> str:
    return f"0x{index:04X}:{subindex:02X}"


def load_dictionary(path: Path | str, node_id: int) -> ObjectDictionary:
    """canopen's import of an EDS or DCF; :class:`DriveConfigError` naming the file otherwise.

    Imports are cached per (file version, node id): a vendor's EDS takes canopen up to a second
    to import, and the checks, the master's SDO client and the emulated drives of one process
    each need it. The dictionaries are only read (values live in the nodes' own stores)."""
    path = Path(path)
    try:
        stat = path.stat()
    except OSError:
        raise DriveConfigError(f"{path}: node {node_id}: EDS file not found") from None
    if not path.is_file():
        raise DriveConfigError(f"{path}: node {node_id}: EDS file not found")
    return _import(str(path.resolve()), stat.st_mtime_ns, stat.st_size, node_id, str(path))


@functools.lru_cache(maxsize=128)
def _import(resolved: str, _mtime_ns: int, _size: int, node_id: int, shown: str) -> ObjectDictionary:
    try:
        return canopen.import_od(resolved, node_id)
    except (configparser.Error, KeyError, ValueError, UnicodeDecodeError, IndexError) as exc:
        raise DriveConfigError(f"{shown}: node {node_id}: unreadable EDS ({type(exc).__name__}: {exc})") from None


def variable(od: ObjectDictionary, index: int, subindex: int = 0) -> ODVariable | None:
    return odx.lookup_variable(od, index, subindex)


def known_value(var: ODVariable | None) -> int | None:
    """The DCF's configured value, else the EDS default, as an int (None when neither)."""
    if var is None:
        return None
    for raw in (var.value, var.default):
        if isinstance(raw, int):
            return raw
    return None


def _fits(var: ODVariable, value: int) -> str | None:
    """Why ``value`` cannot be written to ``var`` (type range, EDS limits), or None."""
    try:
        var.encode_raw(value)
    except Exception as exc:  # noqa: BLE001 - canopen raises struct.error/ValueError/TypeError
        return f"value {value} does not fit its data type 0x{var.data_type:04X} ({exc})"
    if var.min is not None and value < var.min:
        return f"value {value} below the EDS LowLimit {var.min}"
    if var.max is not None and value > var.max:
        return f"value {value} above the EDS HighLimit {var.max}"
    return None


class _Drive:
    """Findings for one drive, against its dictionary."""

    def __init__(self, source: str, node_id: int, od: ObjectDictionary) -> None:
        self.source, self.node_id, self.od = source, node_id, od
        self.findings: list[Finding] = []

    def add(self, level: Level, index: int | None, subindex: int, message: str) -> None:
        obj = "-" if index is None else obj_name(index, subindex)
        self.findings.append(Finding(level, self.source, self.node_id, obj, message))

    def need(self, index: int, subindex: int, write: bool, why: str) -> ODVariable | None:
        var = variable(self.od, index, subindex)
        if var is None:
            self.add("error", index, subindex, f"missing from the EDS ({why})")
            return None
        if write and var.access_type not in WRITABLE:
            self.add("error", index, subindex, f"access {var.access_type}: not writable ({why})")
            return None
        if not write and var.access_type == "wo":
            self.add("error", index, subindex, f"access wo: not readable ({why})")
            return None
        return var

    def mapped(self, index: int, bits: int, rpdo: bool, why: str) -> None:
        var = self.need(index, 0, rpdo, why)
        if var is None:
            return
        if not var.pdo_mappable:
            self.add("error", index, 0, f"not PDO-mappable (PDOMapping=0) but the runtime maps it ({why})")
        elif var.data_type is None or BITS.get(var.data_type) != bits:
            self.add("error", index, 0, f"DataType 0x{var.data_type:04X} is not {bits} bits ({why})")

    def pdo(self, comm: int, mapping: int, entries: Sequence[int], max_bits: int, name: str) -> None:
        if not entries:
            return
        self.need(comm, 1, True, f"{name} COB-ID")
        self.need(comm, 2, True, f"{name} transmission type")
        count = self.need(mapping, 0, True, f"{name} number of mapped objects")
        for k in range(1, len(entries) + 1):
            self.need(mapping, k, True, f"{name} mapping entry {k}")
        if count is not None and count.max is not None and count.max < len(entries):
            self.add("error", mapping, 0, f"{name} takes at most {count.max} objects, the runtime maps {len(entries)}")
        bits = sum(entry & 0xFF for entry in entries)
        if bits > max_bits:
            self.add("error", mapping, 0, f"{name} maps {bits} bits, above the frame's {max_bits}")


def check_drive(joint: JointDriveConfig, index: int, config: DriveBusConfig) -> list[Finding]:
    """Every finding for one joint's drive (its ``drive`` spec, or the emulated drive's EDS)."""
    spec = joint.drive
    path = spec.eds if spec is not None else (config.eds_path or odx.EDS_PATH)
    od = load_dictionary(path, joint.node_id)
    d = _Drive(str(path), joint.node_id, od)
    fd = config.transport.fd
    device_type = known_value(d.need(odx.DEVICE_TYPE, 0, False, "device type"))
    if device_type is not None and device_type & 0xFFFF != PROFILE_402:
        d.add("error", odx.DEVICE_TYPE, 0, f"device profile {device_type & 0xFFFF}, not CiA 402")
    modes = known_value(d.need(odx.SUPPORTED_MODES, 0, False, "supported drive modes"))
    if modes is not None and not modes & CST_BIT:
        d.add("error", odx.SUPPORTED_MODES, 0, f"0x{modes:08X}: the drive does not support cyclic synchronous torque")
    d.need(odx.MODES_OF_OPERATION, 0, True, "mode 10 is written")
    d.need(odx.MODES_DISPLAY, 0, False, "the mode is checked")
    d.need(odx.HEARTBEAT_PRODUCER, 0, True, "the drive's heartbeat")
    d.mapped(odx.CONTROLWORD, 16, True, "RPDO1")
    d.mapped(odx.TARGET_TORQUE, 16, True, "RPDO1")
    d.mapped(odx.STATUSWORD, 16, False, "TPDO1")
    d.mapped(odx.TORQUE_ACTUAL, 16, False, "TPDO1")
    d.mapped(odx.POSITION_ACTUAL, 32, False, "TPDO1")
    d.mapped(odx.VELOCITY_ACTUAL, 32, False, "TPDO1" if fd else "TPDO2")
    layout = (odx.FD_SYNC_LAYOUT if spec is None else odx.FD_LAYOUT) if fd else odx.CLASSICAL_LAYOUT
    frame_bits = FD_PDO_BITS if fd else CLASSICAL_PDO_BITS
    d.pdo(odx.RPDO1_COMM, odx.RPDO1_MAP, layout.rpdo1, frame_bits, "RPDO1")
    d.pdo(odx.TPDO1_COMM, odx.TPDO1_MAP, layout.tpdo1, frame_bits, "TPDO1")
    d.pdo(odx.TPDO2_COMM, odx.TPDO2_MAP, layout.tpdo2, frame_bits, "TPDO2")
    if config.comm_loss_timeout_s is not None:
        d.need(odx.ABORT_CONNECTION_OPTION, 0, True, "the reaction to a lost master")
        if variable(od, odx.CONSUMER_HEARTBEAT, 1) is None and variable(od, odx.RPDO1_COMM, 5) is None:
            d.add("error", odx.CONSUMER_HEARTBEAT, 1, "no heartbeat consumer nor RPDO timer: no watch on the master")
    if spec is None:
        d.need(odx.RATED_TORQUE, 0, True, "the torque scale is written")
        d.need(odx.MAX_TORQUE, 0, True, "the torque limit is written")
    else:
        _check_spec(d, joint, index, spec, config)
    return d.findings


def _check_spec(d: _Drive, joint: JointDriveConfig, index: int, spec: DriveSpec, config: DriveBusConfig) -> None:
    od = d.od
    for name, obj, subs in (
        ("rated_torque", odx.RATED_TORQUE, (0,)),
        ("encoder_increments", odx.ENCODER_RESOLUTION, (1, 2)),
        ("gear_ratio", GEAR_RATIO, (1, 2)),
    ):
        if getattr(spec, name) == "drive":
            for sub in subs:
                if variable(od, obj, sub) is None:
                    d.add("error", obj, sub, f"missing from the EDS: give joints.{index}.drive.{name} in the config")
    # The rated torque as configured, or as the DCF says the drive holds it (checked again at start-up).
    rated = spec.rated_torque if spec.rated_torque != "drive" else known_value(variable(od, odx.RATED_TORQUE))
    if rated and spec.gear_ratio != "drive":
        nm_per_permille = rated * spec.rated_torque_unit_nm * spec.gear_ratio / 1000.0
        permille = joint.max_torque_nm / nm_per_permille
        if permille > INT16_MAX:
            d.add(
                "error",
                odx.TARGET_TORQUE,
                0,
                f"max_torque_nm {joint.max_torque_nm} is {permille:.0f} per mille of the rated torque "
                f"({nm_per_permille * 1000:.4g} N·m at the joint), above the INTEGER16 limit {INT16_MAX}",
            )
        elif nm_per_permille > joint.max_torque_nm / 100:
            d.add("warning", odx.TARGET_TORQUE, 0, f"one per mille is {nm_per_permille:.4g} N·m: coarse torque steps")
    for value, obj in (
        (spec.reactions.quick_stop, odx.QUICK_STOP_OPTION),
        (spec.reactions.fault, FAULT_REACTION),
        (spec.reactions.abort_connection, odx.ABORT_CONNECTION_OPTION),
    ):
        if value is None:
            continue
        var = d.need(obj, 0, True, "a configured reaction")
        if var is not None and (why := _fits(var, value)) is not None:
            d.add("error", obj, 0, why)
    if spec.interpolation_period:
        for sub in (1, 2):
            if variable(od, INTERPOLATION_PERIOD, sub) is None:
                d.add("warning", INTERPOLATION_PERIOD, sub, "missing: the interpolation period is not written")
                break
    if config.transport.fd:
        d.add("warning", None, 0, "CAN FD: untagged 12-byte TPDO (no SYNC counter echo on a vendor drive)")
    for entry in spec.sdo:
        if entry.index in RUNTIME_OWNED:
            d.add("error", entry.index, entry.sub_index, "written by the runtime itself (see drive.reactions)")
            continue
        var = variable(od, entry.index, entry.sub_index)
        if var is None:
            d.add("error", entry.index, entry.sub_index, "SDO init entry: object missing from the EDS")
        elif var.access_type not in WRITABLE:
            d.add("error", entry.index, entry.sub_index, f"SDO init entry: the EDS marks it {var.access_type}")
        elif (why := _fits(var, entry.value)) is not None:
            d.add("error", entry.index, entry.sub_index, f"SDO init entry: {why}")
    commissioned = _commissioned_node_id(spec.eds)
    if commissioned is not None and commissioned != joint.node_id:
        d.add("warning", None, 0, f"DCF commissioned for node {commissioned}: its COB-ID values are that node's")


def _commissioned_node_id(path: Path) -> int | None:
    """A DCF's ``[DeviceComissioning] NodeID`` (CiA 306 spells it so), None for an EDS."""
    try:
        stat = path.stat()
    except OSError:
        return None
    return _read_commissioned(str(path), stat.st_mtime_ns)


@functools.lru_cache(maxsize=64)
def _read_commissioned(path: str, _mtime_ns: int) -> int | None:
    try:
        text = Path(path).read_text(encoding="utf-8", errors="replace")
    except OSError:
        return None
    section = text.find("[DeviceComissioning]")
    if section < 0:
        return None
    for line in text[section:].splitlines()[1:]:
        if line.startswith("["):
            return None
        key, _, value = line.partition("=")
        if key.strip().lower() == "nodeid":
            try:
                return int(value.strip(), 0)
            except ValueError:
                return None
    return None


def _cob_ids(joint: JointDriveConfig, fd: bool) -> list[tuple[int, str]]:
    """(COB-ID, what) a drive sends or receives on once configured by the runtime."""
    n = joint.node_id
    used = [
        (fr.RPDO1_BASE + n, "RPDO1"),
        (fr.TPDO1_BASE + n, "TPDO1"),
        (0x80 + n, "EMCY"),
        (fr.SDO_TX_BASE + n, "SDO response"),
        (fr.SDO_RX_BASE + n, "SDO request"),
        (0x700 + n, "heartbeat"),
    ]
    if not fd:
        used.append((fr.TPDO2_BASE + n, "TPDO2"))
    spec = joint.drive
    if spec is not None:
        for entry in spec.sdo:
            is_pdo_comm = 0x1400 <= entry.index <= 0x15FF or 0x1800 <= entry.index <= 0x19FF
            if (is_pdo_comm and entry.sub_index == 1) or entry.index == EMCY_COB_ID:
                if not entry.value & odx.PDO_COB_ID_INVALID:
                    used.append((entry.value & 0x7FF, f"{obj_name(entry.index, entry.sub_index)} (SDO init)"))
    return used


def check_cob_ids(config: DriveBusConfig, source: str) -> list[Finding]:
    """Two senders on one identifier: between drives, or a drive against the master's SYNC/NMT/
    heartbeat. The identifiers the runtime sets come first, so an SDO init entry that moves a PDO
    or the EMCY onto a taken one is the finding, named by its own drive's file."""
    owners: dict[int, tuple[int, str]] = {
        0x000: (0, "NMT (master)"),
        fr.SYNC_COB_ID: (0, "SYNC (master)"),
        0x700 + config.master_node_id: (0, "heartbeat (master)"),
    }
    findings = []
    passes = [(joint, cob_id, what) for joint in config.joints for cob_id, what in _cob_ids(joint, config.transport.fd)]
    passes.sort(key=lambda item: "(SDO init)" in item[2])
    for joint, cob_id, what in passes:
        owner = owners.get(cob_id)
        if owner is None:
            owners[cob_id] = (joint.node_id, what)
        elif owner != (joint.node_id, what):
            other = f"node {owner[0]}'s {owner[1]}" if owner[0] else owner[1]
            where = str(joint.drive.eds) if joint.drive is not None else source
            findings.append(Finding("error", where, joint.node_id, what, f"COB-ID 0x{cob_id:03X} is also {other}"))
    return findings


def check_bus(config: DriveBusConfig, source: str = "config") -> list[Finding]:
    """Every finding for every drive of ``config`` and the bus-wide COB-ID check."""
    findings: list[Finding] = []
    for i, joint in enumerate(config.joints):
        findings.extend(check_drive(joint, i, config))
    findings.extend(check_cob_ids(config, source))
    return findings


def errors(findings: Iterable[Finding]) -> list[Finding]:
    return [f for f in findings if f.level == "error"]


def raise_first_error(findings: Iterable[Finding]) -> None:
    bad = errors(findings)
    if bad:
        more = f" (+{len(bad) - 1} more)" if len(bad) > 1 else ""
        raise DriveConfigError(bad[0].line() + more)
