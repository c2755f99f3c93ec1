"""drivers/bus_guard.py's rules on hand-made frames (no bus): who may send what, counted exactly."""

from __future__ import annotations

import collections
from typing import Any

import can
import pytest

from drivers.bus_guard import MAX_TPDO_CREDIT, BusGuard, BusIntruderError
from drivers.ipc import IpcMessage, Sender

DRIVE, OTHER = Sender(1, 100, 0), Sender(2, 200, 1000)


class _Network:
    def __init__(self) -> None:
        self.errors: collections.deque[Any] = collections.deque()


def _guard(syncs: list[int]) -> tuple[BusGuard, _Network]:
    network = _Network()
    guard = BusGuard(network, (1, 2), 127, (0x181, 0x182), 0.02, lambda: syncs[0])  # type: ignore[arg-type]  # the guard uses only .errors
    return guard, network


def _frame(cob_id: int, data: bytes = b"\x05", sender: Sender | None = None, t: float = 1.0) -> can.Message:
    if sender is None:
        return can.Message(arbitration_id=cob_id, data=data, is_extended_id=False, timestamp=t)
    return IpcMessage(arbitration_id=cob_id, data=data, is_extended_id=False, timestamp=t, sender=sender)


def test_tpdos_never_outnumber_the_syncs_of_one_sender() -> None:
    syncs = [0]
    guard, network = _guard(syncs)
    guard.arm()
    for _ in range(100):
        syncs[0] += 1
        guard.watch(_frame(0x181), 0.0)
    assert not network.errors
    guard.watch(_frame(0x181), 0.0)  # one more than asked for
    assert isinstance(network.errors.popleft(), BusIntruderError)


def test_lost_tpdos_leave_bounded_credit() -> None:
    syncs = [1000]  # a thousand SYNCs unanswered, then a forger answering each one twice
    guard, network = _guard(syncs)
    guard.arm()
    syncs[0] += 1000
    for _ in range(MAX_TPDO_CREDIT + 1):
        guard.watch(_frame(0x182), 0.0)
    for _ in range(3):
        syncs[0] += 1
        guard.watch(_frame(0x182), 0.0)
        guard.watch(_frame(0x182), 0.0)
    assert "second sender of TPDO 0x182" in str(network.errors[0])


def test_a_sender_other_than_the_drives_is_refused_until_the_drive_boots_again() -> None:
    guard, network = _guard([0])
    guard.watch(_frame(0x701, b"\x00", DRIVE), 0.0)  # boot-up: drive 1 is DRIVE
    guard.watch(_frame(0x701, b"\x05", DRIVE), 0.0)
    assert not network.errors
    guard.watch(_frame(0x081, bytes(8), OTHER), 0.0)  # an EMCY of drive 1 from someone else
    assert "drive 1" in str(network.errors.popleft())
    assert guard.tripped is not None and "pid 200 (uid 1000)" in guard.tripped
    guard.forget_senders()
    guard.arm()
    guard.watch(_frame(0x701, b"\x00", OTHER), 0.0)  # after a reconnect the new process boots
    guard.watch(_frame(0x701, b"\x05", OTHER), 0.0)
    assert not network.errors


@pytest.mark.parametrize("cob_id", [0x000, 0x080, 0x77F, 0x201, 0x602])
def test_frames_only_a_master_sends_are_another_master(cob_id: int) -> None:
    guard, network = _guard([0])
    guard.watch(_frame(cob_id), 0.0)
    assert "second master on the bus" in str(network.errors.popleft())
    assert guard.foreign_master is not None


def test_our_own_echoed_frames_and_other_nodes_are_not_intruders() -> None:
    guard, network = _guard([0])
    own = can.Message(arbitration_id=0x080, data=b"\x01", is_extended_id=False, is_rx=False)
    guard.watch(own, 0.0)
    guard.watch(_frame(0x703), 0.0)  # node 3 is not ours
    guard.watch(_frame(0x5FF), 0.0)
    assert not network.errors


def test_heartbeats_at_twice_the_rate_are_two_producers() -> None:
    guard, network = _guard([0])
    guard.arm()
    for k in range(30):  # 20 ms producer: 30 beats in 0.3 s is 1.5 × the window's 15
        guard.watch(_frame(0x702, t=100.0 + 0.02 * k), 0.0)
    assert not network.errors
    for k in range(40):
        guard.watch(_frame(0x702, t=200.0 + 0.01 * k), 0.0)
    assert "second sender of heartbeat 0x702" in str(network.errors.popleft())
