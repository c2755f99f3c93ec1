"""EMCY consumer: a drive's emergency message becomes a :class:`DriveFaultError` with its code.

The error goes through the network's queue (raised by the caller's next check, which
quick-stops the drives); an "error reset" EMCY (code 0x0000) clears the drive's last code.
"""

from __future__ import annotations

from collections.abc import Sequence

import can

from drivers.cia402 import frames as fr
from drivers.errors import DriveFaultError
from drivers.network import DriveNetwork
from drivers.node import DriveNode


class EmcyConsumer:
    def __init__(self, network: DriveNetwork, nodes: Sequence[DriveNode]) -> None:
        self.network = network
        self.received = 0
        for node in nodes:
            network.subscribe(fr.EMCY_BASE + node.node_id, self.on_emcy, node)

    def on_emcy(self, node: DriveNode, msg: can.Message, now: float) -> None:
        emcy = fr.decode_emcy(bytes(msg.data))
        self.received += 1
        if emcy.error_code == fr.EMCY_ERROR_RESET:
            node.last_emcy_code = 0
            return
        node.last_emcy_code = emcy.error_code
        meaning = fr.EMCY_TEXT.get(emcy.error_code)
        detail = f"EMCY, error register 0x{emcy.error_register:02X}" + (f": {meaning}" if meaning else "")
        self.network.errors.append(DriveFaultError(node.node_id, emcy.error_code, detail))
