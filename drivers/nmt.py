"""NMT: commands, boot-up, and heartbeats in both directions (CiA 301 network management).

- :func:`send_command`: an NMT command to one drive (or all, node id 0).
- :class:`HeartbeatConsumer`: the drives' heartbeats (0x1017 on each drive); a drive silent for
  ``heartbeat_timeout_s`` raises :class:`HeartbeatLostError`, a reboot or a drive leaving NMT
  operational a :class:`DriveStateError` (both through the network's error queue).
- :class:`HeartbeatProducer`: the master's own heartbeat, which each drive consumes (0x1016,
  written at start-up): a drive whose master falls silent quick-stops (see :mod:`drivers.supervision`).
- :func:`wait_for`: poll a per-drive condition during start-up, with a deadline.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import can

from drivers.cia402 import frames as fr
from drivers.errors import DriveStateError, HeartbeatLostError, TransportError
from drivers.network import DriveNetwork
from drivers.node import DriveNode


def send_command(network: DriveNetwork, command: fr.NmtCommand, node_id: int = 0) -> None:
    network.send(can.Message(arbitration_id=fr.NMT_COB_ID, data=fr.encode_nmt(command, node_id), is_extended_id=False))


def wait_for(
    network: DriveNetwork, nodes: Sequence[DriveNode], done: Callable[[DriveNode], bool], timeout_s: float, what: str
) -> None:
    """Until ``done(node)`` for every drive; :class:`DriveStateError` naming the others after
    ``timeout_s``; a transport failure seen meanwhile is raised at once."""
    deadline = time.monotonic() + timeout_s
    while True:
        missing = [node.node_id for node in nodes if not done(node)]
        if not missing:
            return
        if network.errors and isinstance(network.errors[0], TransportError):
            raise network.errors.popleft()
        if time.monotonic() > deadline:
            raise DriveStateError(f"drive(s) {', '.join(map(str, missing))}: {what} within {timeout_s:g} s")
        time.sleep(0.0005)


class HeartbeatConsumer:
    """The drives' heartbeats: boot-up, NMT state, and their absence."""

    def __init__(self, network: DriveNetwork, nodes: Sequence[DriveNode], timeout_s: float) -> None:
        self.network = network
        self.nodes = nodes
        self.timeout_s = timeout_s
        self.armed = False  # checked only once every drive is operational
        self.received = 0
        for node in nodes:
            network.subscribe(fr.HEARTBEAT_BASE + node.node_id, self.on_heartbeat, node)

    def arm(self) -> None:
        now = time.monotonic()
        for node in self.nodes:
            node.last_heartbeat_s = now
            node.heartbeat_lost = False
        self.armed = True

    def on_heartbeat(self, node: DriveNode, msg: can.Message, now: float) -> None:
        state = fr.decode_heartbeat(bytes(msg.data))
        self.received += 1
        # When it was on the bus, not when a cycle got round to it: the transport's time stamp
        # (wall clock in every python-can backend) mapped onto the monotonic clock.
        seen = msg.timestamp + (now - time.time()) if msg.timestamp > 0 else now
        node.last_heartbeat_s = min(now, seen)
        node.heartbeat_lost = False
        previous = node.nmt_state
        node.nmt_state = fr.NmtState.PRE_OPERATIONAL if state is fr.NmtState.BOOT_UP else state
        if state is fr.NmtState.BOOT_UP:
            node.booted = True
        if self.armed and state is not fr.NmtState.OPERATIONAL and previous is not state:
            what = "rebooted (boot-up message)" if state is fr.NmtState.BOOT_UP else f"NMT state {state.name}"
            self.network.errors.append(DriveStateError(f"drive {node.node_id}: {what}"))

    def check(self, now: float) -> None:
        """Under the receive lock, the queue drained: report each drive silent for too long, once."""
        if not self.armed:
            return
        timeout = self.timeout_s
        for node in self.nodes:
            if not node.heartbeat_lost and now - node.last_heartbeat_s > timeout:
                node.heartbeat_lost = True
                self.network.errors.append(
                    HeartbeatLostError(node.node_id, f"no heartbeat for {now - node.last_heartbeat_s:.3f} s")
                )


class HeartbeatProducer:
    """The master's heartbeat (NMT state operational) every ``period_s``, on an absolute schedule
    that never bursts after a stall. Sent by whichever thread calls :meth:`send_if_due`."""

    def __init__(self, network: DriveNetwork, node_id: int, period_s: float) -> None:
        self.network = network
        self.period_s = period_s
        self.msg = can.Message(
            arbitration_id=fr.HEARTBEAT_BASE + node_id,
            data=fr.encode_heartbeat(fr.NmtState.OPERATIONAL),
            is_extended_id=False,
        )
        self.next_s = float("inf")  # stopped
        self.sent = 0

    def start(self) -> None:
        self.next_s = time.monotonic()

    def stop(self) -> None:
        self.next_s = float("inf")

    def send_if_due(self, now: float) -> None:
        if now < self.next_s:
            return
        self.next_s += self.period_s
        if self.next_s <= now:  # stalled: resume the period from now, no catch-up burst
            self.next_s = now + self.period_s
        self.network.send(self.msg)
        self.sent += 1
