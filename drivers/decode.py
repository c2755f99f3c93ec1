"""A CAN capture as CANopen: ``hil bus decode FILE`` (docs/formats.md).

Each frame is named by its COB-ID (CiA 301 predefined connection set) and decoded with the
project's codec (:mod:`drivers.cia402.frames`): NMT, SYNC, EMCY, heartbeat, SDO (command, index,
subindex), and each PDO field by the name and data type its object has in the drive's EDS
(``--eds``, default the shipped one), with its unit. The PDO layout comes from the frame length,
as the driver maps it (:mod:`drivers.cia402.od`: classical, CAN FD, CAN FD with the SYNC echo).
"""

from __future__ import annotations

import collections
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can

from drivers.cia402 import frames as fr
from drivers.cia402 import od as odx
from drivers.cia402.state_machine import decode_statusword

# Units of the mapped objects (the codec's: torques in per mille of rated torque, encoder counts).
UNITS = {
    odx.TARGET_TORQUE: "‰ rated",
    odx.TORQUE_ACTUAL: "‰ rated",
    odx.POSITION_ACTUAL: "counts",
    odx.VELOCITY_ACTUAL: "counts/s",
}

# (function code, data length) -> (frame name, mapping entries)
_PDO_LAYOUTS: dict[tuple[int, int], tuple[str, tuple[int, ...]]] = {
    (fr.RPDO1_BASE, fr.RPDO_LENGTH): ("RPDO1", odx.CLASSICAL_LAYOUT.rpdo1),
    (fr.TPDO1_BASE, fr.TPDO1_LENGTH): ("TPDO1", odx.CLASSICAL_LAYOUT.tpdo1),
    (fr.TPDO1_BASE, fr.TPDO_FD_LENGTH): ("TPDO1 FD", odx.FD_LAYOUT.tpdo1),
    (fr.TPDO1_BASE, fr.TPDO_FD_SYNC_LENGTH): ("TPDO1 FD", odx.FD_SYNC_LAYOUT.tpdo1),
    (fr.TPDO2_BASE, fr.TPDO2_LENGTH): ("TPDO2", odx.CLASSICAL_LAYOUT.tpdo2),
}

_SDO_COMMANDS = {
    fr.SDO_RX_BASE: {0: "download segment", 1: "download", 2: "upload", 3: "upload segment", 4: "abort"},
    fr.SDO_TX_BASE: {0: "upload segment", 1: "download segment ack", 2: "upload", 3: "download ack", 4: "abort"},
}


@dataclass(frozen=True)
class DecodedFrame:
    t_s: float  # the capture's timestamp
    direction: str  # "rx" / "tx" as captured
    cob_id: int
    kind: str  # NMT, SYNC, EMCY, heartbeat, SDO, RPDO1, TPDO1, ..., unknown, malformed
    node: int  # 0: broadcast
    text: str  # the decoded fields

    def line(self, t0_s: float) -> str:
        node = f" node {self.node}" if self.node else ""
        return f"{self.t_s - t0_s:12.6f} {self.direction} 0x{self.cob_id:03X} {self.kind}{node}: {self.text}"


class Decoder:
    """Decodes frames against one object dictionary (names and data types of the mapped objects)."""

    def __init__(self, eds_path: Path | None = None) -> None:
        self.od = odx.load_object_dictionary(1, eds_path or odx.EDS_PATH)

    def _field(self, entry: int, raw: bytes) -> str:
        index, subindex = entry >> 16, (entry >> 8) & 0xFF
        var = odx.lookup_variable(self.od, index, subindex)
        name = var.name if var is not None else f"0x{index:04X}:{subindex:02X}"
        value: Any = var.decode_raw(raw) if var is not None else int.from_bytes(raw, "little")
        if index == odx.STATUSWORD:
            return f"{name}=0x{value:04X} ({decode_statusword(value).name})"
        if index == odx.CONTROLWORD:
            return f"{name}=0x{value:04X}"
        unit = UNITS.get(index)
        return f"{name}={value}" + (f" {unit}" if unit else "")

    def _pdo(self, name: str, entries: tuple[int, ...], data: bytes) -> str:
        fields, offset = [], 0
        for entry in entries:
            size = (entry & 0xFF) // 8
            fields.append(self._field(entry, data[offset : offset + size]))
            offset += size
        return ", ".join(fields)

    def decode(self, msg: can.Message) -> DecodedFrame:
        data = bytes(msg.data)
        cob_id = msg.arbitration_id
        direction = "rx" if msg.is_rx else "tx"

        def frame(kind: str, node: int, text: str) -> DecodedFrame:
            return DecodedFrame(msg.timestamp, direction, cob_id, kind, node, text)

        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            flags = "error" if msg.is_error_frame else "remote" if msg.is_remote_frame else "extended id"
            return frame("unknown", 0, f"{flags} frame {data.hex(' ')}")
        function, node = fr.split_cob_id(cob_id)
        try:
            if cob_id == fr.NMT_COB_ID:
                command, target = fr.decode_nmt(data)
                return frame("NMT", 0, f"{command.name} {'all nodes' if target == 0 else f'node {target}'}")
            if cob_id == fr.SYNC_COB_ID:
                counter = fr.decode_sync(data)
                return frame("SYNC", 0, "no counter" if counter is None else f"counter {counter}")
            if function == fr.EMCY_BASE:
                emcy = fr.decode_emcy(data)
                what = "error reset" if emcy.error_code == 0 else fr.EMCY_TEXT.get(emcy.error_code, "error")
                return frame(
                    "EMCY", node, f"0x{emcy.error_code:04X} {what}, error register 0x{emcy.error_register:02X}"
                )
            if function == fr.HEARTBEAT_BASE:
                state = fr.decode_heartbeat(data)
                return frame("heartbeat", node, "boot-up" if state is fr.NmtState.BOOT_UP else state.name)
            if function in _SDO_COMMANDS:
                return frame("SDO", node, self._sdo(function, data))
            layout = _PDO_LAYOUTS.get((function, len(data)))
            if layout is not None:
                return frame(layout[0], node, self._pdo(layout[0], layout[1], data))
        except (fr.MalformedFrameError, ValueError) as exc:
            return frame("malformed", node, f"{exc} ({data.hex(' ')})")
        return frame("unknown", node, f"{len(data)} bytes {data.hex(' ')}")

    def _sdo(self, function: int, data: bytes) -> str:
        if len(data) != 8:
            raise fr.MalformedFrameError(f"SDO frame has {len(data)} bytes, expected 8")
        side = "request" if function == fr.SDO_RX_BASE else "response"
        command = _SDO_COMMANDS[function].get(data[0] >> 5, f"command {data[0] >> 5}")
        if command.endswith("segment") or command.endswith("segment ack"):
            return f"{side}, {command}"
        index, subindex = int.from_bytes(data[1:3], "little"), data[3]
        var = odx.lookup_variable(self.od, index, subindex)
        name = f" ({var.name})" if var is not None else ""
        if command == "abort":
            return f"{side}, abort 0x{index:04X}:{subindex:02X}{name}, code 0x{int.from_bytes(data[4:], 'little'):08X}"
        return f"{side}, {command} 0x{index:04X}:{subindex:02X}{name}, data {data[4:].hex(' ')}"


def decode_frames(msgs: Iterable[can.Message], decoder: Decoder) -> Iterator[DecodedFrame]:
    for msg in msgs:
        yield decoder.decode(msg)


def summary(kinds: collections.Counter[str]) -> str:
    return ", ".join(f"{count} {kind}" for kind, count in kinds.most_common())
