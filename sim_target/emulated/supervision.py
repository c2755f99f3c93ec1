"""Loss of the master, on the drive's side (CiA 301 error control + CiA 402 0x6007).

Three watches, each armed by the master at start-up and each started by the first frame it
watches (CiA 301: heartbeat consumption starts at the first heartbeat received):

- heartbeat consumer (0x1016:01 = master node id << 16 | time in ms): EMCY 0x8130;
- RPDO deadline (0x1400:05, the event timer of RPDO1, in ms): EMCY 0x8250;
- SYNC deadline (0x2101, manufacturer, in ms): EMCY 0x8100.

A watch that expires while the drive is Operation Enabled makes it react per 0x6007 (3: quick
stop: torque off, brake on) and send the EMCY, once: from then on the arm is held without the
master. An expiry in any other state changes nothing (a master idle between runs, its drives
disabled, must not be told on its return that it was gone). The bank's receive thread checks the
watches only with its queue empty (after a receive timed out, or every 5 ms after draining what is
queued), never with frames of the master still waiting, so a stall of the drives' own thread is
not taken for a silent master. A drive reacts within its timeout plus 10 ms.
"""

from __future__ import annotations

from collections.abc import Sequence

from drivers.cia402 import frames as fr
from drivers.cia402.state_machine import State
from sim_target.emulated.link import FrameLink
from sim_target.emulated.node import EmulatedDrive, MasterLoss
from sim_target.emulated.p402 import abort_connection

_CAUSES = (  # (cause, last-seen field, timeout field, EMCY code)
    ("heartbeat", "last_master_heartbeat_s", "master_heartbeat_timeout_ms", fr.EMCY_HEARTBEAT),
    ("rpdo", "last_rpdo_s", "rpdo_timeout_ms", fr.EMCY_RPDO_TIMEOUT),
    ("sync", "last_sync_s", "sync_timeout_ms", fr.EMCY_COMMUNICATION),
)


class MasterWatch:
    def __init__(self, link: FrameLink, drives: Sequence[EmulatedDrive]) -> None:
        self.link = link
        self.drives = drives
        self.events: list[MasterLoss] = []
        self.consumers: dict[int, list[EmulatedDrive]] = {}  # master heartbeat COB-ID -> its consumers

    @property
    def active(self) -> bool:
        return any(d.master_heartbeat_timeout_ms or d.rpdo_timeout_ms or d.sync_timeout_ms for d in self.drives)

    def configure(self, now: float) -> None:
        """After a write to a watch object (or a reset): who consumes which heartbeat, and
        whether to check at all."""
        consumers: dict[int, list[EmulatedDrive]] = {}
        for drive in self.drives:
            if drive.master_node_id and drive.master_heartbeat_timeout_ms:
                consumers.setdefault(fr.HEARTBEAT_BASE + drive.master_node_id, []).append(drive)
        self.consumers = consumers

    def on_master_heartbeat(self, cob_id: int, now: float) -> bool:
        """A heartbeat some drive consumes; False when none does (an unknown frame)."""
        drives = self.consumers.get(cob_id)
        if drives is None:
            return False
        for drive in drives:
            drive.last_master_heartbeat_s = now
        return True

    def check(self, now: float) -> None:
        enabled = State.OPERATION_ENABLED
        for drive in self.drives:
            if drive.state is not enabled:
                continue
            # The common case, every watch fed in time, in plain comparisons (runs every few ms).
            heartbeat_ms, heartbeat_s = drive.master_heartbeat_timeout_ms, drive.last_master_heartbeat_s
            rpdo_ms, rpdo_s = drive.rpdo_timeout_ms, drive.last_rpdo_s
            sync_ms, sync_s = drive.sync_timeout_ms, drive.last_sync_s
            if not (
                (heartbeat_ms and heartbeat_s and (now - heartbeat_s) * 1000 > heartbeat_ms)
                or (rpdo_ms and rpdo_s and (now - rpdo_s) * 1000 > rpdo_ms)
                or (sync_ms and sync_s and (now - sync_s) * 1000 > sync_ms)
            ):
                continue
            for cause, last_field, timeout_field, code in _CAUSES:
                timeout_ms = getattr(drive, timeout_field)
                last = getattr(drive, last_field)
                if timeout_ms and last and (now - last) * 1000 > timeout_ms:
                    reaction = abort_connection(self.link, drive, code)
                    setattr(drive, last_field, 0.0)  # once: re-armed by the next frame watched
                    self.events.append(MasterLoss(drive.node_id, cause, now - last, reaction, now))
                    break
