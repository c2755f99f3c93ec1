"""The ``ipc`` python-can interface: a virtual CAN bus shared between processes on one machine
over Unix SOCK_SEQPACKET sockets, frames in SocketCAN's layout (docs/ipc_bus.md).

- :mod:`drivers.ipc.frame`: ``struct can_frame`` / ``struct canfd_frame`` encode and decode.
- :mod:`drivers.ipc.bus`: :class:`~drivers.ipc.bus.IpcBus`, registered as ``can.Bus(interface="ipc")``.
"""

from drivers.ipc.bus import IpcBus, IpcBusStats, IpcMessage, Sender, bus_directory

__all__ = ["IpcBus", "IpcBusStats", "IpcMessage", "Sender", "bus_directory"]
