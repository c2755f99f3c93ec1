"""NMT on the drive's side: boot-up, the commands, the heartbeat producer (0x1017).

Leaving NMT operational while enabled (NMT stop, pre-operational, reset) takes the torque off:
PDOs stop with it, so the drive would otherwise hold its last set-point.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence

from drivers.cia402 import frames as fr
from drivers.cia402.state_machine import State
from sim_target.emulated.link import FrameLink
from sim_target.emulated.node import EmulatedDrive

_NMT_STATE_CODE = {
    fr.NmtState.BOOT_UP: 0,
    fr.NmtState.PRE_OPERATIONAL: 0x7F,
    fr.NmtState.OPERATIONAL: 0x05,
    fr.NmtState.STOPPED: 0x04,
}

ResetObjects = Callable[[EmulatedDrive, bool], None]  # (drive, communication_only)


class NmtSlave:
    def __init__(self, link: FrameLink, drives: Sequence[EmulatedDrive], reset_objects: ResetObjects) -> None:
        self.link = link
        self.drives = drives
        self.reset_objects = reset_objects
        self._due = math.inf  # earliest next heartbeat: the receive loop asks for it at every frame

    def boot(self, drive: EmulatedDrive, now: float) -> None:
        drive.nmt = fr.NmtState.BOOT_UP
        self.link.emit(drive, fr.HEARTBEAT_BASE + drive.node_id, fr.encode_heartbeat(fr.NmtState.BOOT_UP))
        drive.nmt = fr.NmtState.PRE_OPERATIONAL
        self.schedule(drive, now)

    def on_command(self, drive: EmulatedDrive, command: fr.NmtCommand, now: float) -> None:
        was_operational = drive.nmt is fr.NmtState.OPERATIONAL
        if command is fr.NmtCommand.START:
            drive.nmt = fr.NmtState.OPERATIONAL
        elif command is fr.NmtCommand.STOP:
            drive.nmt = fr.NmtState.STOPPED
        elif command is fr.NmtCommand.ENTER_PRE_OPERATIONAL:
            drive.nmt = fr.NmtState.PRE_OPERATIONAL
        elif command is fr.NmtCommand.RESET_NODE:
            self.reset_objects(drive, False)
            drive.state = State.SWITCH_ON_DISABLED
            drive.error_code = drive.error_register = 0
            self.boot(drive, now)
        elif command is fr.NmtCommand.RESET_COMMUNICATION:
            self.reset_objects(drive, True)
            self.boot(drive, now)
        if was_operational and drive.nmt is not fr.NmtState.OPERATIONAL:
            # Losing the master's PDOs while enabled: torque off, brake on.
            if drive.state in (State.OPERATION_ENABLED, State.QUICK_STOP_ACTIVE):
                drive.state = State.SWITCH_ON_DISABLED
            drive.applied_permille = 0
            drive.controlword = drive.previous_controlword = 0
            drive.target_permille = 0

    def schedule(self, drive: EmulatedDrive, now: float) -> None:
        """(Re)start a drive's heartbeat schedule from ``now`` (boot, reset, a write of 0x1017)."""
        drive.next_heartbeat_s = now + drive.heartbeat_ms / 1000 if drive.heartbeat_ms > 0 else math.inf
        self._due = min(self._due, drive.next_heartbeat_s)  # too early at worst: recomputed below

    def next_due(self) -> float:
        return self._due

    def produce_heartbeats(self, now: float) -> None:
        for drive in self.drives:
            if now >= drive.next_heartbeat_s:
                if not drive.policy.silent_heartbeat:
                    self.link.emit(drive, fr.HEARTBEAT_BASE + drive.node_id, bytes((_NMT_STATE_CODE[drive.nmt],)))
                # Keep the schedule absolute (no drift), but never burst after a stall.
                drive.next_heartbeat_s = max(drive.next_heartbeat_s + drive.heartbeat_ms / 1000, now)
        self._due = min(drive.next_heartbeat_s for drive in self.drives)
