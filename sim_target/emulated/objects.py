"""The drive's object dictionary behind canopen's ``LocalNode`` SDO server.

The EDS gives every object its type and default; the hooks here give the live ones their value
(statusword, actual values, the SYNC counter echo) and apply writes the drive must act on
(mode, torque scale and limit, quick stop option, heartbeat, PDO communication and mapping, the
watches on the master). Writes the drive cannot honour are refused with the CiA 301 abort code.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from canopen.sdo.exceptions import SdoAbortedError

from drivers.cia402 import od as odx
from drivers.cia402 import sdo as sdo_codes
from sim_target.emulated import pdo
from sim_target.emulated.node import EmulatedDrive
from sim_target.emulated.p402 import statusword

Feedback = tuple[list[float], list[float], list[float]] | None  # position, velocity, torque (published)


class ObjectServer:
    """Read/write hooks of every drive's object dictionary."""

    def __init__(
        self,
        encoder_counts_per_rev: int,
        heartbeat_producer_ms: int,
        feedback: Callable[[], Feedback],
        sync_counter: Callable[[], int],
        on_watch_change: Callable[[float], None],
        schedule_heartbeat: Callable[[EmulatedDrive, float], None],
    ) -> None:
        self.encoder_counts_per_rev = encoder_counts_per_rev
        self.heartbeat_producer_ms = heartbeat_producer_ms
        self.feedback = feedback
        self.sync_counter = sync_counter
        self.on_watch_change = on_watch_change
        self.schedule_heartbeat = schedule_heartbeat

    def attach(self, drive: EmulatedDrive) -> None:
        drive.node.add_read_callback(self._read_hook(drive))
        drive.node.add_write_callback(self._write_hook(drive))

    def reset(self, drive: EmulatedDrive, communication_only: bool) -> None:
        """Objects back to their EDS defaults (all, or the communication area 0x1000-0x1FFF)."""
        store = drive.node.data_store
        for index in list(store):
            if not communication_only or 0x1000 <= index <= 0x1FFF:
                del store[index]
        od = drive.node.object_dictionary
        profile = drive.profile
        if profile is None:
            store.setdefault(odx.ENCODER_RESOLUTION, {})[1] = self.encoder_counts_per_rev.to_bytes(4, "little")
        else:
            _present_motor(drive, od, store, profile)
        if self.heartbeat_producer_ms:
            store.setdefault(odx.HEARTBEAT_PRODUCER, {})[0] = self.heartbeat_producer_ms.to_bytes(2, "little")

        def value(index: int, subindex: int = 0, fallback: int | None = None) -> int:
            var = odx.lookup_variable(od, index, subindex)
            if var is None and fallback is not None:  # a vendor's dictionary without this object
                return fallback
            if var is None:
                raise ValueError(f"object 0x{index:04X}:{subindex}: not in the EDS")
            raw = store.get(index, {}).get(subindex)
            if raw is not None:
                return int(var.decode_raw(raw))
            for known in (var.value, var.default):  # a DCF's ParameterValue, then the EDS default
                if isinstance(known, int):
                    return known
            if fallback is not None:
                return fallback
            raise ValueError(f"object 0x{index:04X}:{subindex}: no value and no default in the EDS")

        drive.rated_torque_mnm = value(odx.RATED_TORQUE, fallback=profile.rated_torque if profile else None)
        drive.max_torque_permille = value(odx.MAX_TORQUE, fallback=0xFFFF)  # none: the drive's current limit
        drive.quick_stop_option = value(odx.QUICK_STOP_OPTION, fallback=2)
        drive.heartbeat_ms = value(odx.HEARTBEAT_PRODUCER)
        drive.rpdo_valid = not value(odx.RPDO1_COMM, 1) & odx.PDO_COB_ID_INVALID
        drive.tpdo1_valid = not value(odx.TPDO1_COMM, 1) & odx.PDO_COB_ID_INVALID
        drive.tpdo2_valid = not value(odx.TPDO2_COMM, 1) & odx.PDO_COB_ID_INVALID
        drive.mappings = {
            mapping: [value(mapping, k) for k in range(value(mapping, 0) + 1)][1:]
            for mapping in (odx.RPDO1_MAP, odx.TPDO1_MAP, odx.TPDO2_MAP)
        }
        pdo.set_tpdo1_layout(drive, len(drive.mappings[odx.TPDO1_MAP]))
        consumer = value(odx.CONSUMER_HEARTBEAT, 1, fallback=0)
        drive.master_node_id, drive.master_heartbeat_timeout_ms = (consumer >> 16) & 0x7F, consumer & 0xFFFF
        drive.rpdo_timeout_ms = value(odx.RPDO1_COMM, 5, fallback=0)
        # 0x2101 is the emulated drive's own SYNC timeout; a vendor's 0x2101 is something else.
        drive.sync_timeout_ms = value(odx.SYNC_TIMEOUT) if profile is None else 0
        drive.abort_connection_option = value(odx.ABORT_CONNECTION_OPTION, fallback=1)
        drive.last_master_heartbeat_s = drive.last_rpdo_s = drive.last_sync_s = 0.0
        now = time.monotonic()
        self.schedule_heartbeat(drive, now)
        self.on_watch_change(now)

    def _read_hook(self, drive: EmulatedDrive) -> Callable[..., int | None]:
        def read(index: int, subindex: int, od: Any) -> int | None:
            if index == odx.STATUSWORD:
                return statusword(drive)
            if index == odx.CONTROLWORD:
                return drive.controlword
            if index == odx.TARGET_TORQUE:
                return drive.target_permille
            if index == odx.ERROR_CODE:
                return drive.error_code
            if index == odx.ERROR_REGISTER:
                return drive.error_register
            if index == odx.SYNC_COUNTER_ECHO and drive.profile is None:
                return self.sync_counter()
            if index == odx.MODES_DISPLAY:
                mode = drive.node.data_store.get(odx.MODES_OF_OPERATION, {}).get(0)
                return mode[0] if mode is not None else odx.MODE_CYCLIC_SYNC_TORQUE
            if index in (odx.POSITION_ACTUAL, odx.VELOCITY_ACTUAL, odx.TORQUE_ACTUAL):
                feedback = self.feedback()
                if feedback is None:
                    return 0
                i = drive.index
                if index == odx.POSITION_ACTUAL:
                    return clamp32(round(float(feedback[0][i]) * drive.counts_per_rad))
                if index == odx.VELOCITY_ACTUAL:
                    return clamp32(round(float(feedback[1][i]) * drive.counts_per_rad))
                return clamp16(round(float(feedback[2][i]) * drive.units_per_nm / drive.rated_torque_mnm))
            return None

        return read

    def _write_hook(self, drive: EmulatedDrive) -> Callable[..., None]:
        def write(index: int, subindex: int, od: Any, data: bytes) -> None:
            value = od.decode_raw(data)
            if index == odx.MODES_OF_OPERATION and value != odx.MODE_CYCLIC_SYNC_TORQUE:
                raise SdoAbortedError(sdo_codes.ABORT_INVALID_VALUE)  # only mode 10 is emulated
            if index == odx.RATED_TORQUE:
                if value <= 0:
                    raise SdoAbortedError(sdo_codes.ABORT_VALUE_TOO_LOW)
                drive.rated_torque_mnm = value
            elif index == odx.MAX_TORQUE:
                drive.max_torque_permille = value
            elif index == odx.QUICK_STOP_OPTION:
                if not 0 <= value <= 8:
                    raise SdoAbortedError(sdo_codes.ABORT_INVALID_VALUE)
                drive.quick_stop_option = value
            elif index == odx.HEARTBEAT_PRODUCER:
                drive.heartbeat_ms = value
                self.schedule_heartbeat(drive, time.monotonic())
            elif index == odx.CONTROLWORD:
                drive.controlword = value
            elif index == odx.TARGET_TORQUE:
                drive.target_permille = value
            elif index == odx.CONSUMER_HEARTBEAT and subindex == 1:
                master = (value >> 16) & 0xFF
                if master > 127:
                    raise SdoAbortedError(sdo_codes.ABORT_INVALID_VALUE)
                drive.master_node_id, drive.master_heartbeat_timeout_ms = master, value & 0xFFFF
                drive.last_master_heartbeat_s = 0.0  # monitoring starts at the next heartbeat
                self.on_watch_change(time.monotonic())
            elif index == odx.SYNC_TIMEOUT and drive.profile is None:
                drive.sync_timeout_ms = value
                self.on_watch_change(time.monotonic())
            elif index == odx.ABORT_CONNECTION_OPTION:
                drive.abort_connection_option = value
            elif pdo.write_comm(drive, index, subindex, value):
                if index == odx.RPDO1_COMM and subindex == 5:
                    self.on_watch_change(time.monotonic())
            else:
                pdo.write_mapping(drive, index, subindex, value)

        return write


def clamp32(value: int) -> int:
    return max(-(2**31), min(2**31 - 1, value))


def clamp16(value: int) -> int:
    return max(-32768, min(32767, value))


def _present_motor(drive: EmulatedDrive, od: Any, store: dict[int, dict[int, bytes]], profile: Any) -> None:
    """A vendor's dictionary with the profile's motor behind it: 0x6076 and 0x608F hold the motor's
    values where the EDS has them (a DCF's commissioned value, or an EDS default of 0, would not be
    this motor's), 0x1000 the device type the profile answers with."""
    for index, subindex, number in (
        (odx.RATED_TORQUE, 0, profile.rated_torque),
        (odx.ENCODER_RESOLUTION, 1, profile.encoder_increments),
        (odx.ENCODER_RESOLUTION, 2, 1),
        (0x6091, 1, round(profile.gear_ratio)),  # gear ratio: motor revolutions
        (0x6091, 2, 1),  # per shaft revolution
        (odx.DEVICE_TYPE, 0, profile.device_type),
    ):
        var = odx.lookup_variable(od, index, subindex)
        if var is not None and number is not None:
            store.setdefault(index, {})[subindex] = var.encode_raw(number)
