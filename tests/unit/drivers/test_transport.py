"""Transports from config: what opens, and the typed one-line errors when it cannot."""

import socket

import can
import pytest
from can_remote import RemoteBus

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
        assert isinstance(remote, RemoteBus)  # python-can-remote's client (untyped), Nagle off on its socket
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


def test_every_config_interface_has_a_backend_and_each_resolves() -> None:
    import importlib
    from typing import get_args

    from drivers.config import Interface
    from drivers.transport import BACKENDS

    assert set(BACKENDS) == set(get_args(Interface))
    for module, function in BACKENDS.values():
        assert callable(getattr(importlib.import_module(module), function))


def test_python_can_version_is_the_one_fast_virtual_bus_was_written_against() -> None:
    # FastVirtualBus.send reimplements VirtualBus.send with its internals; pyproject pins the
    # minor version. A python-can upgrade must come with a re-read of virtual.py (then bump both).
    from drivers.interfaces.virtual import PYTHON_CAN_VERSION

    assert can.__version__.rsplit(".", 1)[0] == PYTHON_CAN_VERSION


def test_virtual_bus_internals_fast_virtual_bus_relies_on() -> None:
    from can.interfaces import virtual

    from drivers.interfaces.virtual import FastVirtualBus

    bus = virtual.VirtualBus(channel="t-internals")
    try:
        assert bus.channel is virtual.channels["t-internals"]  # the channel's list of receive queues
        assert bus.queue in bus.channel
        assert callable(bus._check_if_open)
        assert {"receive_own_messages", "preserve_timestamps", "channel_id"} <= set(vars(bus))
    finally:
        bus.shutdown()
    # Every Message field the copy must carry (a new slot would be lost by the fast copy).
    assert set(can.Message.__slots__) == {
        "__weakref__",
        "arbitration_id",
        "bitrate_switch",
        "channel",
        "data",
        "dlc",
        "error_state_indicator",
        "is_error_frame",
        "is_extended_id",
        "is_fd",
        "is_remote_frame",
        "is_rx",
        "timestamp",
    }
    assert FastVirtualBus.__mro__[1] is virtual.VirtualBus


@pytest.mark.parametrize(
    "msg",
    [
        can.Message(arbitration_id=0x201, data=bytes(range(6)), is_extended_id=False),
        can.Message(
            arbitration_id=0x181,
            data=bytes(range(12)),
            is_fd=True,
            bitrate_switch=True,
            error_state_indicator=True,
            is_extended_id=False,
        ),
        can.Message(arbitration_id=0x1ABCDEF, is_remote_frame=True, dlc=4, is_extended_id=True),
        can.Message(is_error_frame=True, data=b"\x01", is_extended_id=False),
    ],
    ids=["classical", "fd", "remote", "error"],
)
def test_fast_virtual_bus_delivers_what_virtual_bus_delivers(msg: can.Message) -> None:
    from can.interfaces.virtual import VirtualBus

    from drivers.interfaces.virtual import FastVirtualBus

    received = []
    for cls in (VirtualBus, FastVirtualBus):
        sender, receiver = cls(channel="t-parity", preserve_timestamps=True), VirtualBus(channel="t-parity")
        try:
            sender.send(msg)
            got = receiver.recv(1.0)
        finally:
            sender.shutdown()
            receiver.shutdown()
        assert got is not None
        received.append({slot: getattr(got, slot) for slot in can.Message.__slots__ if slot != "__weakref__"})
        assert got.data is not msg.data
    assert received[0] == received[1]
