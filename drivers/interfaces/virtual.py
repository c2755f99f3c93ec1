"""``virtual``: python-can's in-process bus, with a cheaper per-frame copy.

:class:`FastVirtualBus` is python-can's ``VirtualBus`` whose ``send`` copies a frame with one
``can.Message`` call instead of ``copy.deepcopy`` (8 µs -> ~1 µs a frame). It shares python-can's
channels, so plain ``virtual`` buses on the same channel (the emulated drives, the bridge server)
see its frames and vice versa. That needs ``VirtualBus``'s internals (``channel``: the list of
receive queues, ``queue``, ``_check_if_open``), so python-can is pinned to the minor version they
were read from (pyproject.toml) and tests/unit/drivers/test_transport.py fails when they change.
"""

from __future__ import annotations

import queue
import time

import can
from can.interfaces.virtual import VirtualBus

from drivers.config import TransportConfig

# The python-can minor version whose VirtualBus internals FastVirtualBus.send relies on.
PYTHON_CAN_VERSION = "4.6"


class FastVirtualBus(VirtualBus):
    """python-can's ``virtual`` bus whose send copies each frame with one ``can.Message`` call."""

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        # Same contract as VirtualBus.send (4.6): every other queue of the channel gets a copy
        # stamped with the send time, the channel id and is_rx.
        self._check_if_open()
        timestamp = msg.timestamp if self.preserve_timestamps else time.time()
        data = msg.data
        all_sent = True
        for bus_queue in self.channel:
            if bus_queue is self.queue and not self.receive_own_messages:
                continue
            copy = can.Message(
                timestamp=timestamp,
                arbitration_id=msg.arbitration_id,
                is_extended_id=msg.is_extended_id,
                is_remote_frame=msg.is_remote_frame,
                is_error_frame=msg.is_error_frame,
                channel=self.channel_id,
                dlc=msg.dlc,
                data=bytearray(data),
                is_fd=msg.is_fd,
                is_rx=bus_queue is not self.queue,
                bitrate_switch=msg.bitrate_switch,
                error_state_indicator=msg.error_state_indicator,
            )
            try:
                bus_queue.put(copy, block=True, timeout=timeout)
            except queue.Full:
                all_sent = False
        if not all_sent:
            raise can.CanOperationError("Could not send message to one or more recipients")


def open_bus(config: TransportConfig) -> can.BusABC:
    protocol = can.CanProtocol.CAN_FD if config.fd else can.CanProtocol.CAN_20
    return FastVirtualBus(channel=config.channel, protocol=protocol)
