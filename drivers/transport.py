"""Open a python-can bus from a frozen :class:`~drivers.config.TransportConfig`.

- ``virtual``: python-can's in-process bus (tests, lock-step HIL in one process).
- ``socketcan``: Linux SocketCAN (``vcan0`` or a real ``can0``); :func:`socketcan_unavailable`
  tells why it cannot be used on this machine.
- ``remote``: the python-can-remote websocket bridge, a virtual bus shared between processes;
  loopback only. :func:`start_bridge_server` hosts the bridge inside a process (the sim target),
  so the emulated drives sit on the bridge's own virtual channel and only the runtime crosses
  the socket.
- ``slcan``: serial-line CAN adapters (classical CAN only).

Configuration files of python-can are ignored on purpose: the bus is exactly what the config says.

Two thin subclasses trim the per-frame cost of the cyclic path without changing what goes on the
(virtual) wire: :class:`FastVirtualBus` copies a frame with one constructor call instead of
``copy.deepcopy`` (8 µs -> ~1 µs a frame; it shares python-can's channels, so plain ``virtual``
buses on the same channel see its frames and vice versa), and :class:`BatchingRemoteBus` sends a
cycle's RPDOs and SYNC as one TCP segment (``send_batch``, TCP_CORK) instead of seven.
"""

from __future__ import annotations

import logging
import os
import queue
import socket
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlparse

import can
from can.interfaces.virtual import VirtualBus

from drivers.config import TransportConfig, is_loopback_host
from drivers.errors import DriveConfigError, TransportError

log = logging.getLogger(__name__)


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


class FastVirtualBus(VirtualBus):  # type: ignore[misc]
    """python-can's ``virtual`` bus whose send copies each frame with one ``can.Message`` call."""

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
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


def _batching_remote_bus(**kwargs: Any) -> can.BusABC:
    from can_remote.client import RemoteBus

    class BatchingRemoteBus(RemoteBus):  # type: ignore[misc, valid-type]
        """The python-can-remote client with ``send_batch``: frames corked into one segment."""

        def send_batch(self, msgs: Sequence[can.Message]) -> None:
            sock = self.socket
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_CORK, 1)
            try:
                for msg in msgs:
                    self.remote_protocol.send_msg(msg)
            finally:
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_CORK, 0)  # uncorking sends it now

    channel = kwargs.pop("channel")
    kwargs.pop("interface")
    kwargs.pop("ignore_config", None)
    return BatchingRemoteBus(channel, **kwargs)


def open_bus(config: TransportConfig) -> can.BusABC:
    """A python-can bus for ``config``; :class:`TransportError` naming the bus if it fails."""
    kwargs: dict[str, object] = {"ignore_config": True}
    if config.interface == "virtual":
        kwargs.update(
            interface="virtual",
            channel=config.channel,
            protocol=can.CanProtocol.CAN_FD if config.fd else can.CanProtocol.CAN_20,
        )
    elif config.interface == "socketcan":
        kwargs.update(interface="socketcan", channel=config.channel, fd=config.fd)
    elif config.interface == "slcan":
        if config.fd:
            raise DriveConfigError("transport.fd: slcan adapters carry classical CAN only")
        kwargs.update(interface="slcan", channel=config.channel, bitrate=config.bitrate)
    elif config.interface == "remote":
        url = config.remote_url
        if not is_loopback_host(urlparse(url).hostname or ""):
            raise DriveConfigError(f"transport.channel: {url} is not a loopback address")
        kwargs.update(interface="remote", channel=url, bitrate=config.bitrate, fd=config.fd)
        if config.fd and config.data_bitrate:
            kwargs["data_bitrate"] = config.data_bitrate
    else:  # pragma: no cover - the config Literal rules this out
        raise DriveConfigError(f"transport.interface: unknown {config.interface!r}")
    try:
        if config.interface == "virtual":
            kwargs.pop("interface")
            kwargs.pop("ignore_config")
            bus = FastVirtualBus(**kwargs)
        elif config.interface == "remote" and hasattr(socket, "TCP_CORK"):
            bus = _batching_remote_bus(**kwargs)
        else:
            bus = can.Bus(**kwargs)
    except (can.CanError, OSError, ValueError, ImportError, AssertionError) as exc:
        # python-can-remote asserts on a bad websocket handshake; all are "could not open".
        raise TransportError(
            f"cannot open {config.interface} bus {kwargs.get('channel')!r}: {exc or type(exc).__name__}"
        ) from exc
    if config.interface == "remote":
        _disable_nagle(bus)
    return bus


def _disable_nagle(bus: can.BusABC) -> None:
    # The bridge client leaves Nagle on: a SYNC right after six RPDOs would wait for the ACK of
    # the first segment (tens of ms with delayed ACKs). The server side already disables it.
    sock = getattr(bus, "socket", None)
    if isinstance(sock, socket.socket):
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)


@dataclass
class BridgeServer:
    """A python-can-remote server on loopback serving one virtual channel, in a daemon thread."""

    host: str
    port: int
    channel: str
    _server: object
    _thread: threading.Thread

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.port}/"

    def close(self) -> None:
        self._server.shutdown()  # type: ignore[attr-defined]
        self._server.server_close()  # type: ignore[attr-defined]
        self._thread.join(timeout=2.0)


def start_bridge_server(host: str = "127.0.0.1", port: int = 0, channel: str = "hil") -> BridgeServer:
    """Serve the in-process virtual ``channel`` to bridge clients on ``host:port`` (0: any free).

    Every client gets its own virtual bus on ``channel`` inside this process, so buses opened
    here with ``interface="virtual", channel=channel`` see the clients' frames and vice versa.
    """
    if not is_loopback_host(host):
        raise DriveConfigError(f"bridge host {host!r} is not loopback (127.0.0.1/::1)")
    try:
        from can_remote import RemoteServer
    except ImportError as exc:
        raise TransportError("python-can-remote is not installed (pip install python-can-remote)") from exc

    class _Server(RemoteServer):  # type: ignore[misc, valid-type]
        address_family = socket.AF_INET6 if ":" in host else socket.AF_INET

    try:
        server = _Server(host, port, interface="virtual", channel=channel, ignore_config=True)
    except OSError as exc:
        raise TransportError(f"cannot listen on {host}:{port}: {exc.strerror}") from exc
    thread = threading.Thread(target=server.serve_forever, name="can-bridge", daemon=True)
    thread.start()
    return BridgeServer(host, server.server_port, channel, server, thread)
