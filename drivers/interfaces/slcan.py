"""``slcan``: serial-line CAN adapters through python-can (classical CAN only)."""

from __future__ import annotations

import can

from drivers.config import TransportConfig
from drivers.errors import DriveConfigError


def open_bus(config: TransportConfig) -> can.BusABC:
    if config.fd:
        raise DriveConfigError("transport.fd: slcan adapters carry classical CAN only")
    return can.Bus(interface="slcan", channel=config.channel, bitrate=config.bitrate, ignore_config=True)
