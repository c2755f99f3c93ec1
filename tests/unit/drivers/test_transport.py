"""Transports from config: what opens, and the typed one-line errors when it cannot."""

import socket

import can
import pytest

from drivers.config import TransportConfig
from drivers.errors import DriveConfigError, TransportError
from drivers.transport import open_bus, socketcan_unavailable, start_bridge_server


def _closed_loopback_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def test_virtual_bus_carries_fd_frames() -> None:
    config = TransportConfig(interface="virtual", channel="t-transport", fd=True, data_bitrate=5_000_000)
    a, b = open_bus(config), open_bus(config)
    try:
        a.send(can.Message(arbitration_id=0x181, data=bytes(range(12)), is_fd=True, is_extended_id=False))
        msg = b.recv(1.0)
        assert msg is not None and msg.is_fd and bytes(msg.data) == bytes(range(12))
    finally:
        a.shutdown()
        b.shutdown()


def test_remote_bridge_round_trip_on_loopback() -> None:
    bridge = start_bridge_server("127.0.0.1", 0, "t-bridge-unit")
    local = can.Bus(interface="virtual", channel="t-bridge-unit", ignore_config=True)
    remote = open_bus(TransportConfig(interface="remote", bridge_port=bridge.port))
    try:
        assert remote.socket.getsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY)
        remote.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))
        msg = local.recv(5.0)
        assert msg is not None and msg.arbitration_id == 0x080
    finally:
        remote.shutdown()
        local.shutdown()
        bridge.close()


def test_remote_bridge_not_listening_is_a_transport_error() -> None:
    port = _closed_loopback_port()
    with pytest.raises(TransportError, match=f"cannot open remote bus 'ws://127.0.0.1:{port}/'"):
        open_bus(TransportConfig(interface="remote", bridge_port=port))


def test_bridge_server_refuses_non_loopback() -> None:
    with pytest.raises(DriveConfigError, match="not loopback"):
        start_bridge_server("::", 0)  # all interfaces (IPv6 wildcard)


def test_slcan_has_no_fd() -> None:
    with pytest.raises(DriveConfigError, match="transport.fd"):
        open_bus(TransportConfig(interface="slcan", channel="/dev/null", fd=True, data_bitrate=2_000_000))


def test_socketcan_missing_interface_is_explained() -> None:
    reason = socketcan_unavailable("hilnosuch0")
    assert reason is not None
    if hasattr(socket, "AF_CAN"):
        assert "'hilnosuch0' does not exist" in reason
    with pytest.raises(TransportError, match="cannot open socketcan bus 'hilnosuch0'"):
        open_bus(TransportConfig(interface="socketcan", channel="hilnosuch0"))
