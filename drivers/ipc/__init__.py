"""The ``ipc`` python-can interface: a virtual CAN bus shared between processes on one machine
over Unix SOCK_SEQPACKET sockets, frames in SocketCAN's layout (docs/ipc_bus.md).

- :mod:`drivers.ipc.frame`: ``struct can_frame`` / ``struct canfd_frame`` encode and decode.
- :mod:`drivers.ipc.bus`: :class:`~drivers.ipc.bus.IpcBus`, registered as ``can.Bus(interface="ipc")``.
- :mod:`drivers.ipc.directory`: the bus directory (where a name points, who may join) and the
  sender each received frame carries.
"""

from drivers.ipc.bus import IpcBus
from drivers.ipc.directory import IpcMessage, Sender, bus_directory
from drivers.ipc.peer import IpcBusStats

__all__ = ["IpcBus", "IpcBusStats", "IpcMessage", "Sender", "bus_directory"]
