"""The one-shot fault injections of the emulated drives (tests, ``hil target inject``): a drive fault
at the next SYNC, dropped, corrupted or delayed TPDOs, a silent heartbeat, refused SDO writes."""

from __future__ import annotations

import canopen

from drivers.cia402 import frames as fr
from sim_target.emulated.node import EmulatedDrive


class OneShotFaults:
    """Mixed into :class:`sim_target.drives.EmulatedDrives` (which provides :meth:`_drive`)."""

    def _drive(self, node_id: int) -> EmulatedDrive:
        raise NotImplementedError

    def inject_drive_fault(self, node_id: int, error_code: int = fr.EMCY_OVERCURRENT) -> None:
        """The drive goes to Fault at its next SYNC and sends EMCY ``error_code``."""
        self._drive(node_id).pending_fault = error_code

    def drop_tpdos(self, node_id: int, cycles: int = 1) -> None:
        self._drive(node_id).policy.drop_next += cycles

    def corrupt_tpdos(self, node_id: int, cycles: int = 1) -> None:
        self._drive(node_id).policy.corrupt_next += cycles

    def delay_tpdos(self, node_id: int, delay_s: float, cycles: int = 1) -> None:
        policy = self._drive(node_id).policy
        policy.delay_next += cycles
        policy.delay_next_s = delay_s

    def silence_heartbeat(self, node_id: int, silent: bool = True) -> None:
        self._drive(node_id).policy.silent_heartbeat = silent

    def abort_sdo_writes(self, node_id: int, index: int, abort_code: int = 0x06090030) -> None:
        """The drive answers every SDO write to ``index`` with an abort (CiA 301 ``abort_code``;
        default 0x06090030, value range exceeded), as a real drive refuses a value it cannot take."""

        def refuse(index: int, subindex: int, od: object, data: bytes, _target: int = index) -> None:
            if index == _target:
                raise canopen.sdo.SdoAbortedError(abort_code)

        self._drive(node_id).node.add_write_callback(refuse)
