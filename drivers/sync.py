"""SYNC producer: one SYNC per control cycle, carrying the CiA 301 counter (1..240, 0x1019).

The frame is built once and its counter byte rewritten each cycle. The drives echo the counter
in their CAN FD TPDO (0x2100), so feedback answering an older SYNC is never taken for this one.
"""

from __future__ import annotations

import can

from drivers.cia402 import frames as fr
from drivers.cia402 import od as odx


class SyncProducer:
    def __init__(self) -> None:
        self.counter = 0  # of the last SYNC sent (0: none yet)
        self.msg = can.Message(arbitration_id=fr.SYNC_COB_ID, data=bytearray(1), is_extended_id=False)

    def advance(self) -> int:
        """The next SYNC's counter, written into :attr:`msg` (when it carries one)."""
        self.counter = counter = fr.next_sync_counter(self.counter)
        if self.msg.dlc:
            self.msg.data[0] = counter
        return counter

    def carry_counter(self, enabled: bool) -> None:
        """SYNC with the counter byte, or empty (a drive without 0x1019 expects no data, CiA 301)."""
        self.msg.data = bytearray(1 if enabled else 0)
        self.msg.dlc = len(self.msg.data)


#: Written to every drive at start-up: the SYNC counter overflow (the SYNCs carry a counter).
SYNC_OVERFLOW_OBJECT = (odx.SYNC_OVERFLOW, 0, odx.SYNC_COUNTER_MAX)
