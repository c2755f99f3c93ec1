"""Open a python-can bus from a frozen :class:`~drivers.config.TransportConfig`.

:data:`BACKENDS` names, for each ``transport.interface``, the module and the function that opens
it (python-can's ``BACKENDS`` idea); the module is imported only when that interface is opened,
so the runtime never imports an interface it does not use (python-can-remote is an extra).

- ``virtual``: python-can's in-process bus (tests, lock-step HIL in one process).
- ``socketcan``: Linux SocketCAN (``vcan0`` or a real ``can0``); :func:`socketcan_unavailable`
  tells why it cannot be used on this machine.
- ``remote``: the python-can-remote websocket bridge, a virtual bus shared between processes;
  loopback only; :func:`start_bridge_server` hosts one (the sim target).
- ``slcan``: serial-line CAN adapters (classical CAN only).
- ``ipc``: the project's bus between processes (:mod:`drivers.ipc`, docs/ipc_bus.md).

Configuration files of python-can are ignored on purpose: the bus is exactly what the config says.
Adding an interface: one row here, its name in ``drivers.config.Interface``, and a module with
``open_bus(config) -> can.BusABC``.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable

import can

from drivers.config import TransportConfig
from drivers.errors import DriveError, TransportError
from drivers.interfaces.remote import BridgeServer, start_bridge_server  # python-can-remote: lazily
from drivers.interfaces.socketcan import socketcan_unavailable

__all__ = ["BACKENDS", "BridgeServer", "open_bus", "socketcan_unavailable", "start_bridge_server"]

# interface name -> (module, function taking the TransportConfig and returning an open bus)
BACKENDS: dict[str, tuple[str, str]] = {
    "virtual": ("drivers.interfaces.virtual", "open_bus"),
    "socketcan": ("drivers.interfaces.socketcan", "open_bus"),
    "remote": ("drivers.interfaces.remote", "open_bus"),
    "slcan": ("drivers.interfaces.slcan", "open_bus"),
    "ipc": ("drivers.ipc.bus", "open_bus"),
}


def _factory(interface: str) -> Callable[[TransportConfig], can.BusABC]:
    try:
        module_name, function = BACKENDS[interface]
    except KeyError:  # the config's Literal rules this out unless the two tables disagree
        raise TransportError(
            f"transport.interface: no backend for {interface!r} (known: {', '.join(BACKENDS)})"
        ) from None
    factory: Callable[[TransportConfig], can.BusABC] = getattr(importlib.import_module(module_name), function)
    return factory


def open_bus(config: TransportConfig) -> can.BusABC:
    """A python-can bus for ``config``; :class:`TransportError` naming the bus if it fails,
    :class:`~drivers.errors.DriveConfigError` if the config asks for what the interface lacks."""
    channel = config.remote_url if config.interface == "remote" else config.channel
    try:
        return _factory(config.interface)(config)
    except DriveError:
        raise
    except (can.CanError, OSError, ValueError, ImportError, AssertionError) as exc:
        # python-can-remote asserts on a bad websocket handshake; all are "could not open".
        raise TransportError(f"cannot open {config.interface} bus {channel!r}: {exc or type(exc).__name__}") from exc
