"""``remote``: the python-can-remote websocket bridge, a virtual bus shared between processes.

Loopback only. :func:`start_bridge_server` hosts the bridge inside a process (the sim target), so
the emulated drives sit on the bridge's own virtual channel and only the runtime crosses the
socket. The client bus opened here differs from python-can-remote's ``RemoteBus`` in three ways:

- ``send_batch`` sends a cycle's RPDOs and SYNC as one TCP segment (TCP_CORK) instead of seven,
  and Nagle is off (a SYNC right after six RPDOs would otherwise wait for a delayed ACK);
- when the peer process dies, ``recv``/``send`` raise ``TransportError("peer closed: ...")``
  (python-can-remote raises a bare ``WebsocketClosed``/``BrokenPipeError``, or after a close
  frame silently drops what is sent);
- ``shutdown`` never raises and never waits more than ``_CLOSE_WAIT_S`` for the close handshake
  (python-can-remote's raises ``OSError`` on a dead socket, masking the error that stopped the
  run, and loops until the server answers).

python-can-remote is the ``sim`` extra: it is imported when a remote bus or bridge is opened.
"""

from __future__ import annotations

import functools
import logging
import socket
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlparse

import can

from drivers.config import TransportConfig, is_loopback_host
from drivers.errors import DriveConfigError, TransportError

log = logging.getLogger(__name__)

_CLOSE_WAIT_S = 1.0  # shutdown: longest wait for the server to answer the websocket close


@functools.cache
def _remote_bus_class() -> type[can.BusABC]:
    from can_remote.client import RemoteBus
    from can_remote.protocol import RemoteError
    from can_remote.websocket import WebsocketClosed

    class BatchingRemoteBus(RemoteBus):
        """python-can-remote's client with ``send_batch``, a typed peer-closed error and a
        shutdown that cannot raise."""

        _peer_closed: str | None = None

        def _closed(self, exc: BaseException) -> TransportError:
            if self._peer_closed is None:
                self._peer_closed = (
                    f"peer closed: the bridge at {self.channel} closed the connection ({type(exc).__name__}: {exc})"
                )
            return TransportError(self._peer_closed)

        def _check_peer(self) -> None:
            if self._peer_closed is not None:
                raise TransportError(self._peer_closed)
            if self.remote_protocol._ws.closed:  # a close frame was read: sends would be dropped
                raise self._closed(ConnectionError("websocket closed by the peer"))

        def recv(self, timeout: float | None = None) -> can.Message | None:
            self._check_peer()
            try:
                msg: can.Message | None = super().recv(timeout)
                return msg
            except (WebsocketClosed, OSError, ValueError) as exc:  # ValueError: select on a closed fd
                raise self._closed(exc) from exc

        def send(self, msg: can.Message, timeout: float | None = None) -> None:
            self._check_peer()
            try:
                self.remote_protocol.send_msg(msg)
            except OSError as exc:
                raise self._closed(exc) from exc

        def send_batch(self, msgs: Sequence[can.Message]) -> None:
            self._check_peer()
            sock = self.socket
            cork = getattr(socket, "TCP_CORK", None)  # Linux only; elsewhere one segment a frame
            try:
                if cork is not None:
                    sock.setsockopt(socket.IPPROTO_TCP, cork, 1)
                try:
                    for msg in msgs:
                        self.remote_protocol.send_msg(msg)
                finally:
                    if cork is not None:
                        sock.setsockopt(socket.IPPROTO_TCP, cork, 0)  # uncorking sends it now
            except OSError as exc:
                raise self._closed(exc) from exc

        def shutdown(self) -> None:
            if self._is_shutdown:
                return
            try:
                if self._peer_closed is None and not self.remote_protocol._ws.closed:
                    self.remote_protocol.close()  # close frame + half-close
                    deadline = time.monotonic() + _CLOSE_WAIT_S
                    while (remaining := deadline - time.monotonic()) > 0:
                        try:
                            self.remote_protocol.recv(remaining)
                        except WebsocketClosed:
                            break
                        except RemoteError:
                            pass
            except (OSError, ValueError, WebsocketClosed) as exc:
                log.debug("bridge close handshake failed (peer gone): %s", exc)
            finally:
                try:
                    self.socket.close()
                except OSError:
                    pass
                can.BusABC.shutdown(self)

    return BatchingRemoteBus


def open_bus(config: TransportConfig) -> can.BusABC:
    url = config.remote_url
    if not is_loopback_host(urlparse(url).hostname or ""):
        raise DriveConfigError(f"transport.channel: {url} is not a loopback address")
    kwargs: dict[str, Any] = {"bitrate": config.bitrate, "fd": config.fd}
    if config.fd and config.data_bitrate:
        kwargs["data_bitrate"] = config.data_bitrate
    bus = _remote_bus_class()(url, **kwargs)
    # The bridge client leaves Nagle on: a SYNC right after six RPDOs would wait for the ACK of
    # the first segment (tens of ms with delayed ACKs). The server side already disables it.
    sock = getattr(bus, "socket", None)
    if isinstance(sock, socket.socket):
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
    return bus


@dataclass
class BridgeServer:
    """A python-can-remote server on loopback serving one virtual channel, in a daemon thread."""

    host: str
    port: int
    channel: str
    _server: Any
    _thread: threading.Thread

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.port}/"

    def close(self) -> None:
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(timeout=2.0)


@functools.cache
def _client_handler_class() -> type:
    """python-can-remote's per-client handler whose sending thread survives a dead client.

    Upstream, the thread that forwards the bus to a client dies with ``BrokenPipeError`` when the
    client process is killed and never shuts its bus down: the client's queue stays on the virtual
    channel for the life of the target, copying every frame. Here a dead client ends the thread
    quietly and the bus is shut down either way.
    """
    from can_remote.server import ClientRequestHandler, RemoteServerProtocol
    from can_remote.websocket import WebSocket, WebsocketClosed, get_accept_key

    class _Protocol(RemoteServerProtocol):
        running: bool  # set by RemoteServerProtocol.__init__

        def _send_to_client(self) -> None:
            try:
                while self.running:
                    msg = self.bus.recv(0.5)
                    if msg is not None:
                        self.send_msg(msg)
            except (OSError, WebsocketClosed, can.CanError) as exc:
                log.debug("bridge client gone: %s", exc)
                self.running = False
            finally:
                self.bus.shutdown()

    class _Handler(ClientRequestHandler):
        def start_websocket(self) -> None:
            # python-can-remote 0.3's start_websocket, building the protocol above.
            self.send_response(101)
            self.send_header("Upgrade", "WebSocket")
            self.send_header("Connection", "Upgrade")
            self.send_header("Sec-WebSocket-Accept", get_accept_key(self.headers["Sec-WebSocket-Key"]))
            offered = [p.strip() for p in self.headers.get("Sec-WebSocket-Protocol", "can.json.v1").split(",")]
            protocol_name = "can.binary+json.v1" if "can.binary+json.v1" in offered else "can.json.v1"
            self.send_header("Sec-WebSocket-Protocol", protocol_name)
            self.end_headers()
            protocol = _Protocol(self.server.config, WebSocket(None, protocol_name, sock=self.request))
            self.server.clients.append(protocol)
            try:
                protocol.run()
            finally:
                self.server.clients.remove(protocol)

    return _Handler


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

    class _Server(RemoteServer):
        address_family = socket.AF_INET6 if ":" in host else socket.AF_INET

    try:
        server = _Server(host, port, interface="virtual", channel=channel, ignore_config=True)
    except OSError as exc:
        raise TransportError(f"cannot listen on {host}:{port}: {exc.strerror}") from exc
    server.RequestHandlerClass = _client_handler_class()
    thread = threading.Thread(target=server.serve_forever, name="can-bridge", daemon=True)
    thread.start()
    return BridgeServer(host, server.server_port, channel, server, thread)
