"""The emulated drives read a master's cycle datagram (its RPDOs, then a SYNC) in one unpack once
they have seen its layout (sim_target/emulated/reception.py), with the checks of the frame-by-frame
path: a SYNC counter out of range is malformed and not answered, RPDOs outside NMT operational are
ignored, and a datagram of another layout goes the long way."""

from __future__ import annotations

import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from drivers.cia402 import frames as fr
from drivers.ipc import IpcBus
from drivers.ipc.frame import FrameBatch
from sim_target.drives import EmulatedDrives, EmulatedDrivesConfig

NODES = (1, 2, 3)


@pytest.fixture
def pair(tmp_path: Path) -> Iterator[tuple[EmulatedDrives, IpcBus]]:
    side = IpcBus(tmp_path / "bus", fd=True)
    master = IpcBus(tmp_path / "bus", fd=True)
    drives = EmulatedDrives(side, EmulatedDrivesConfig(node_ids=NODES))
    drives.start()
    try:
        yield drives, master
    finally:
        drives.close()
        master.shutdown()
        side.shutdown()


def _cycle(targets: tuple[int, ...], counter: int, rpdo_length: int = fr.RPDO_LENGTH) -> FrameBatch:
    rpdos = [
        can.Message(
            arbitration_id=fr.RPDO1_BASE + node,
            data=fr.encode_rpdo(0x000F, target)[:rpdo_length],
            is_extended_id=False,
            is_fd=True,
            bitrate_switch=True,
        )
        for node, target in zip(NODES, targets, strict=True)
    ]
    sync = can.Message(arbitration_id=fr.SYNC_COB_ID, data=bytes([counter]), is_extended_id=False)
    return FrameBatch([*rpdos, sync])


def _wait(condition: object, timeout_s: float = 2.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():  # type: ignore[operator]  # a callable
            return True
        time.sleep(0.005)
    return False


def test_a_cycle_is_read_in_one_unpack_with_the_same_checks(pair: tuple[EmulatedDrives, IpcBus]) -> None:
    drives, master = pair
    master.send(can.Message(arbitration_id=fr.NMT_COB_ID, data=bytes([0x01, 0]), is_extended_id=False))
    assert _wait(lambda: all(s is fr.NmtState.OPERATIONAL for s in drives.nmt_states()))
    master.send_frames(_cycle((10, 20, 30), 1))  # learnt from this one (frame by frame)
    assert _wait(lambda: drives.counters.syncs == 1)
    assert drives.cycles_read == 0
    for k in range(2, 6):
        master.send_frames(_cycle((10 * k, -20 * k, 30 * k), k))
    assert _wait(lambda: drives.counters.syncs == 5)
    assert drives.cycles_read == 4
    assert [d.target_permille for d in drives._drives] == [50, -100, 150]
    assert [d.controlword for d in drives._drives] == [0x000F] * 3
    before = drives.counters

    master.send_frames(_cycle((1, 2, 3), 0))  # the same layout, SYNC counter 0: not a SYNC
    assert _wait(lambda: drives.counters.malformed == before.malformed + 1)
    assert drives.counters.syncs == before.syncs
    assert drives.cycles_read == 5
    assert drives.counters.frames_received == before.frames_received + 4

    master.send_frames(_cycle((7, 8, 9), 6, rpdo_length=3))  # short RPDOs: another layout, the long way
    assert _wait(lambda: drives.counters.syncs == before.syncs + 1)
    assert drives.counters.malformed == before.malformed + 4
    assert drives.cycles_read == 5

    master.send(can.Message(arbitration_id=fr.NMT_COB_ID, data=bytes([0x02, 2]), is_extended_id=False))  # stop 2
    assert _wait(lambda: drives.nmt_states()[1] is fr.NmtState.STOPPED)
    stopped = drives._drives[1].target_permille
    master.send_frames(_cycle((11, 22, 33), 7))
    assert _wait(lambda: drives.cycles_read == 6)
    assert [d.target_permille for d in drives._drives] == [11, stopped, 33]  # a stopped drive ignores its RPDO
    assert stopped != 22
