"""Commissioning reads: which nodes answer on a bus (``hil drives scan``) and, on a configured
drive bus, what each drive holds after the runtime's start-up (``hil drives check``).

:func:`scan_nodes` uses canopen's own network and node scanner on any python-can bus of
:func:`drivers.transport.open_bus`: an SDO upload of 0x1000 to every node id, then per answering
node its identity (0x1018), supported modes (0x6502) and, from the heartbeats heard meanwhile,
its NMT state. It writes nothing and starts nothing.

:func:`read_back` reads a connected :class:`~drivers.drive_bus.DriveBus`'s drives (never enabled)
and compares with the configuration: the mode, the PDO mappings, the reactions, the interpolation
period, the SDO initialisation entries.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import can
import canopen
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from drivers.cia402 import frames as fr
from drivers.cia402 import od as odx
from drivers.eds_check import CST_BIT, FAULT_REACTION, INTERPOLATION_PERIOD, PROFILE_402, Finding, Level, obj_name
from drivers.errors import DriveError
from drivers.supervision import ABORT_CONNECTION_QUICK_STOP

if TYPE_CHECKING:
    from drivers.drive_bus import DriveBus

IDENTITY = 0x1018
DEVICE_NAME = 0x1008
POLARITY = 0x607E  # CiA 402 polarity: bit 7 position, bit 6 velocity
NMT_NAMES = {0x00: "boot-up", 0x04: "stopped", 0x05: "operational", 0x7F: "pre-operational"}


@dataclass
class NodeInfo:
    node_id: int
    device_type: int | None = None
    vendor_id: int | None = None
    product_code: int | None = None
    revision: int | None = None
    serial: int | None = None
    supported_modes: int | None = None
    nmt_state: str = "unknown (no heartbeat heard)"
    notes: list[str] = field(default_factory=list)

    @property
    def profile(self) -> int | None:
        return None if self.device_type is None else self.device_type & 0xFFFF

    @property
    def is_402(self) -> bool:
        return self.profile == PROFILE_402

    @property
    def cst(self) -> bool | None:
        return None if self.supported_modes is None else bool(self.supported_modes & CST_BIT)


class _Heartbeats(can.Listener):
    def __init__(self) -> None:
        self.states: dict[int, int] = {}

    def on_message_received(self, msg: can.Message) -> None:
        if 0x701 <= msg.arbitration_id <= 0x77F and len(msg.data) == 1 and not msg.is_remote_frame:
            self.states[msg.arbitration_id - 0x700] = msg.data[0] & 0x7F


def _upload_u32(node: canopen.RemoteNode, index: int, subindex: int) -> int | None:
    try:
        data = node.sdo.upload(index, subindex)
    except (SdoAbortedError, SdoCommunicationError):
        return None
    return int.from_bytes(bytes(data)[:4].ljust(4, b"\0"), "little")


def scan_nodes(bus: can.BusABC, node_ids: range = range(1, 128), wait_s: float = 0.5) -> list[NodeInfo]:
    """Every node in ``node_ids`` that answers an SDO upload of 0x1000, with what it reports."""
    network = canopen.Network(bus)
    heartbeats = _Heartbeats()
    notifier = can.Notifier(bus, [*network.listeners, heartbeats], 0.05)
    network.notifier = notifier
    try:
        request = bytes([0x40, 0x00, 0x10, 0x00, 0, 0, 0, 0])  # SDO upload 0x1000:00
        for node_id in node_ids:
            network.send_message(fr.SDO_RX_BASE + node_id, request)
        time.sleep(wait_s)
        found = sorted(n for n in network.scanner.nodes if n in node_ids)
        infos = []
        for node_id in found:
            node = canopen.RemoteNode(node_id, canopen.ObjectDictionary())  # type: ignore[no-untyped-call]  # canopen leaves its __init__ untyped
            node.sdo.RESPONSE_TIMEOUT = 0.5
            network.add_node(node)
            info = NodeInfo(node_id, _upload_u32(node, odx.DEVICE_TYPE, 0))
            info.vendor_id = _upload_u32(node, IDENTITY, 1)
            info.product_code = _upload_u32(node, IDENTITY, 2)
            info.revision = _upload_u32(node, IDENTITY, 3)
            info.serial = _upload_u32(node, IDENTITY, 4)
            if info.is_402:
                info.supported_modes = _upload_u32(node, odx.SUPPORTED_MODES, 0)
            infos.append(info)
        for info in infos:
            state = heartbeats.states.get(info.node_id)
            if state is not None:
                info.nmt_state = NMT_NAMES.get(state, f"0x{state:02X}")
        return infos
    finally:
        notifier.stop()


class _Reader:
    """Reads of one configured drive, each result a finding."""

    def __init__(self, bus: DriveBus, node: Any, source: str, findings: list[Finding]) -> None:
        self.bus, self.node, self.source, self.findings = bus, node, source, findings

    def add(self, level: Level, index: int | None, sub: int, message: str) -> None:
        obj = "-" if index is None else obj_name(index, sub)
        self.findings.append(Finding(level, self.source, self.node.node_id, obj, message))

    def read(self, index: int, sub: int = 0) -> int | None:
        node_id = self.node.node_id
        if self.bus.sdo_variable(node_id, index, sub) is None:
            return None
        try:
            return self.bus.sdo_read_int(node_id, index, sub)
        except DriveError as exc:
            self.add("error", index, sub, f"read failed: {exc}")
            return None

    def expect(self, index: int, sub: int, want: int | None, label: str = "") -> None:
        got = self.read(index, sub)
        if got is None:
            return
        if want is None:
            self.add("ok", index, sub, f"{label}{got} (the drive's own)")
        elif got == want:
            self.add("ok", index, sub, f"{label}{got}")
        else:
            self.add("error", index, sub, f"{label}{got}, expected {want}")


def read_back(bus: DriveBus) -> list[Finding]:
    """After ``bus.connect()`` (drives configured, none enabled): what each drive holds, against
    what the runtime wrote and the config asked for."""
    findings: list[Finding] = []
    for node in bus.nodes:
        spec = node.joint.drive
        r = _Reader(bus, node, str(spec.eds if spec is not None else (bus.config.eds_path or odx.EDS_PATH)), findings)
        device_type = r.read(odx.DEVICE_TYPE) or 0
        r.add("ok" if device_type & 0xFFFF == PROFILE_402 else "error", odx.DEVICE_TYPE, 0, f"0x{device_type:08X}")
        modes = r.read(odx.SUPPORTED_MODES) or 0
        r.add("ok" if modes & CST_BIT else "error", odx.SUPPORTED_MODES, 0, f"0x{modes:08X} (bit 9: CST)")
        r.expect(odx.MODES_DISPLAY, 0, odx.MODE_CYCLIC_SYNC_TORQUE, "mode ")
        layout = bus.layout_for(node)
        for name, mapping, entries in (
            ("RPDO1", odx.RPDO1_MAP, layout.rpdo1),
            ("TPDO1", odx.TPDO1_MAP, layout.tpdo1),
            ("TPDO2", odx.TPDO2_MAP, layout.tpdo2),
        ):
            got = [r.read(mapping, k) for k in range(1, len(entries) + 1)]
            shown = ", ".join(f"0x{e:08X}" for e in entries) or "disabled"
            ok = got == list(entries)
            r.add("ok" if ok else "error", mapping, 0, f"{name}: {shown}" + ("" if ok else f" (drive: {got})"))
        polarity = ", polarity -1" if node.counts_per_rad < 0 else ""
        r.add(
            "ok",
            odx.RATED_TORQUE,
            0,
            f"1 per mille = {1.0 / abs(node.permille_per_nm):.5g} N·m at the joint; "
            f"{abs(node.counts_per_rad):.6g} counts/rad{polarity}",
        )
        max_permille = node.joint.max_torque_nm * abs(node.permille_per_nm)
        r.add("ok", odx.TARGET_TORQUE, 0, f"torque limit {node.joint.max_torque_nm} N·m = {max_permille:.0f} per mille")
        polarity_flags = r.read(POLARITY)
        if polarity_flags is not None:
            # 0x607E bit 7 flips positions, bit 6 velocities: one without the other breaks any loop.
            position_flip, velocity_flip = bool(polarity_flags & 0x80), bool(polarity_flags & 0x40)
            level: Level = "ok" if position_flip == velocity_flip else "error"
            r.add(
                level,
                POLARITY,
                0,
                f"0x{polarity_flags:02X}: the drive's own polarity (position "
                f"{'reversed' if position_flip else 'normal'}, velocity {'reversed' if velocity_flip else 'normal'})",
            )
        reactions = spec.reactions if spec is not None else None
        quick_stop = reactions.quick_stop if reactions is not None else None
        r.expect(odx.QUICK_STOP_OPTION, 0, quick_stop if quick_stop is not None else bus.config.quick_stop_option)
        r.expect(FAULT_REACTION, 0, reactions.fault if reactions is not None else None)
        abort = reactions.abort_connection if reactions is not None else None
        if abort is None and bus.config.comm_loss_timeout_s is not None:
            abort = ABORT_CONNECTION_QUICK_STOP  # what the master-loss set-up writes (drivers/supervision.py)
        r.expect(odx.ABORT_CONNECTION_OPTION, 0, abort)
        if spec is not None and spec.interpolation_period:
            value, exponent = r.read(INTERPOLATION_PERIOD, 1), r.read(INTERPOLATION_PERIOD, 2)
            if value is not None and exponent is not None:
                period_s = value * 10.0**exponent
                ok = abs(period_s - bus.config.period_s) < 1e-9
                r.add("ok" if ok else "error", INTERPOLATION_PERIOD, 1, f"{period_s * 1e3:g} ms")
        for entry in spec.sdo if spec is not None else ():
            r.expect(entry.index, entry.sub_index, entry.value, "SDO init: ")
    return findings
