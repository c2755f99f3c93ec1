"""``socketcan``: Linux SocketCAN (``vcan0`` or a real ``can0``) through python-can."""

from __future__ import annotations

import os
import socket

import can

from drivers.config import TransportConfig


def socketcan_unavailable(channel: str = "vcan0") -> str | None:
    """None when a SocketCAN ``channel`` can be opened here, else the reason it cannot."""
    if not hasattr(socket, "AF_CAN"):
        return "this Python/OS has no AF_CAN sockets (SocketCAN is Linux only)"
    if not os.path.exists(f"/sys/class/net/{channel}"):
        return f"network interface {channel!r} does not exist (no SocketCAN / vcan in this kernel?)"
    try:
        probe = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    except OSError as exc:
        return f"cannot create a CAN_RAW socket: {exc.strerror}"
    probe.close()
    return None


def open_bus(config: TransportConfig) -> can.BusABC:
    # ignore_config: the bus is exactly what the config says, never python-can's config files.
    return can.Bus(interface="socketcan", channel=config.channel, fd=config.fd, ignore_config=True)
