"""A late SYNC at the free-running target (issue 21, item 3, the drive side): as a CiA 402 drive in
cyclic synchronous torque does, each emulated drive applies the target torque latched at the last
SYNC, holds it while the SYNC is late (an RPDO alone changes nothing), and only when the SYNC
timeout (0x2101) runs out reacts as 0x6007 says (quick stop: torque off, brake on)."""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Callable, Iterator

import can
import numpy as np
import pytest
from canopen.sdo import SdoVariable

from drivers.cia402 import frames as fr
from drivers.cia402 import od as odx
from drivers.cia402.state_machine import State
from sim_target.config import parse_target_config
from sim_target.drives import EmulatedDrives
from sim_target.server import TargetServer, build_server

NODE_IDS = (1, 2, 3, 4, 5, 6)
SYNC_TIMEOUT_MS = 40
PERIOD_S = 0.002


def _wait_until(predicate: Callable[[], object], timeout_s: float = 5.0) -> bool:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        if predicate():
            return True
        time.sleep(0.001)
    return False


def emulated(server: TargetServer) -> EmulatedDrives:
    """The target's drives as the emulated ones they are here (the server types them by protocol)."""
    drives = server.drives
    assert isinstance(drives, EmulatedDrives)
    return drives


@pytest.fixture
def target() -> Iterator[tuple[TargetServer, can.BusABC]]:
    channel = f"late-sync-{uuid.uuid4().hex[:8]}"
    config = parse_target_config(
        {
            "period_s": PERIOD_S,
            "clock": "realtime",
            "bus": {"interface": "virtual", "channel": channel, "fd": True, "data_bitrate": 5_000_000},
            "plant": {"substeps": 4, "initial_position_rad": [0.0, -0.5, 0.8, -0.3, 0.0, 0.0]},
            "realtime": {"fifo_priority": 0, "lock_memory": False},  # not for the pytest process
        }
    )
    server, close = build_server(config)
    for node_id in NODE_IDS:  # what the master's SDO configuration would write
        node = emulated(server)._drive(node_id).node
        for index, value in ((odx.SYNC_TIMEOUT, SYNC_TIMEOUT_MS), (odx.ABORT_CONNECTION_OPTION, 3)):
            entry = node.sdo[index]
            assert isinstance(entry, SdoVariable)
            entry.raw = value
    runner = threading.Thread(target=server.run, name="target", daemon=True)
    runner.start()
    master = can.Bus(interface="virtual", channel=channel, fd=True)
    try:
        yield server, master
    finally:
        master.shutdown()
        server.stop()
        runner.join(timeout=10)
        close()


def _cycle(master: can.BusABC, controlword: int, permille: int, sync: bool = True) -> None:
    for node_id in NODE_IDS:
        master.send(
            can.Message(
                arbitration_id=fr.RPDO1_BASE + node_id, data=fr.encode_rpdo(controlword, permille), is_extended_id=False
            )
        )
    if sync:
        master.send(can.Message(arbitration_id=fr.SYNC_COB_ID, data=b"", is_extended_id=False))
    time.sleep(PERIOD_S)


def test_a_late_sync_holds_the_last_torque_until_the_sync_timeout_then_quick_stops(
    target: tuple[TargetServer, can.BusABC],
) -> None:
    server, master = target
    drives = emulated(server)
    master.send(
        can.Message(arbitration_id=fr.NMT_COB_ID, data=fr.encode_nmt(fr.NmtCommand.START, 0), is_extended_id=False)
    )
    for controlword in (0x06, 0x07, 0x0F):
        _cycle(master, controlword, 0)
    assert _wait_until(lambda: all(s is State.OPERATION_ENABLED for s in drives.states()))
    rated_nm = np.array([d.rated_torque_mnm for d in drives._drives]) * 1e-3
    for _ in range(5):
        _cycle(master, 0x0F, 20)  # 2 % of rated torque, SYNC on time
    held_nm = 0.020 * rated_nm
    assert _wait_until(lambda: np.allclose(server.plant.state().torque_nm, held_nm))

    # The SYNC goes late: a new set-point arrives, but no SYNC latches it.
    last_sync_s = time.monotonic()
    _cycle(master, 0x0F, -50, sync=False)
    torques = []
    while time.monotonic() - last_sync_s < 0.5 * SYNC_TIMEOUT_MS * 1e-3:
        torques.append(server.plant.state().torque_nm.copy())
        time.sleep(PERIOD_S)
    assert torques and all(np.allclose(t, held_nm) for t in torques)  # the last latched torque, held
    assert all(s is State.OPERATION_ENABLED for s in drives.states())
    steps_before = server.stats.steps

    # Past the SYNC timeout: the configured reaction (0x6007 = 3, quick stop), torque off, brakes on.
    assert _wait_until(lambda: all(s is State.QUICK_STOP_ACTIVE for s in drives.states()), 2.0)
    losses = drives.master_losses
    assert {loss.cause for loss in losses} == {"sync"} and len(losses) == len(NODE_IDS)
    assert all(SYNC_TIMEOUT_MS <= loss.silent_s * 1e3 <= SYNC_TIMEOUT_MS + 30 for loss in losses)
    assert _wait_until(lambda: not server.plant.state().torque_nm.any())
    assert server.stats.steps > steps_before  # the physics ran on its own clock all along
