"""The master's cycle on the ipc bus's raw path (drivers/pdo.py, drivers/network.py): the RPDOs and
the SYNC go out as one preallocated datagram, the TPDOs are handled on their bytes, and 1,000
cycles keep nothing (tracemalloc), with the drives in a process of their own so that only the
master's allocations are traced."""

from __future__ import annotations

import contextlib
import gc
import time
import tracemalloc
from collections.abc import Iterator
from pathlib import Path

import can
import numpy as np
import pytest

from drivers.cia402 import frames as fr
from drivers.drive_bus import DriveBus
from sim_target.testing.drive_process import drive_process
from sim_target.testing.drive_rig import drive_bus_config

ROOT = Path(__file__).resolve().parents[2]
CYCLES = 1000
N = 6


@contextlib.contextmanager
def _driver(bus_dir: Path, fd: bool) -> Iterator[DriveBus]:
    """A DriveBus on the ipc bus, enabled, against N emulated drives in a process of their own."""
    with drive_process("--drives", str(N), "--ipc-dir", str(bus_dir), *([] if fd else ["--classical"])):
        # Heartbeats every 100 ms (the guard judges their rate over 20 periods: 2 s): tracemalloc's
        # snapshots stall this process for hundreds of ms on a loaded machine, and the heartbeats
        # queued meanwhile are dated by their arrival here (the ipc bus stamps the receive), so a
        # 0.4 s window saw a burst, a second sender (CI, 2026-11-26 23:50).
        config = drive_bus_config(
            "unused",
            N,
            fd,
            transport={"interface": "ipc", "channel": str(bus_dir)},
            heartbeat_producer_ms=100,
            heartbeat_timeout_s=1.0,
        )
        bus = DriveBus(config)
        bus.connect()
        try:
            bus.enable()
            yield bus
        finally:
            bus.close()


@pytest.fixture
def driver(tmp_path: Path) -> Iterator[DriveBus]:
    with _driver(tmp_path / "bus", fd=True) as bus:
        yield bus


class _MessageCount:
    """Counts every can.Message made (an IpcMessage too) while installed."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.made = 0
        original = can.Message.__init__

        def counting(msg: can.Message, *args: object, **kwargs: object) -> None:
            self.made += 1
            original(msg, *args, **kwargs)  # type: ignore[arg-type]  # python-can's keyword signature

        monkeypatch.setattr(can.Message, "__init__", counting)


def test_a_cycle_makes_no_message_per_frame_and_sends_what_it_packed(
    driver: DriveBus, monkeypatch: pytest.MonkeyPatch
) -> None:
    torque = np.linspace(-2.0, 2.0, N)
    driver.exchange(torque)
    heartbeats = driver.counters.heartbeats
    count = _MessageCount(monkeypatch)
    for _ in range(200):
        feedback = driver.exchange(torque)
    # The drives' heartbeats (every 20 ms here) still take the message path; the 1,400 frames of
    # the cycles do not (the message path made 6.5 a cycle).
    assert count.made <= driver.counters.heartbeats - heartbeats + 10, count.made
    assert feedback.fresh.all() and driver.counters.dropped == 0 and driver.counters.malformed == 0
    # What went out is what was packed: the datagram's RPDO payloads and the SYNC counter.
    exchange = driver._services.exchange  # type: ignore[union-attr]  # connected above
    batch = exchange._batch
    assert batch is not None and batch.count == N + 1
    permille = [fr.decode_rpdo(bytes(payload)).target_torque_permille for payload in batch.payloads[:N]]
    assert permille == np.rint(feedback.commanded_torque_nm * driver._permille_per_nm).astype(int).tolist()
    assert bytes(batch.payloads[N]) == bytes((driver.sync_counter,))


def test_classical_can_takes_the_raw_path_too(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """TPDO1 + TPDO2 per drive (no SYNC echo): both on their bytes, every cycle fresh."""
    with _driver(tmp_path / "bus", fd=False) as driver:
        torque = np.linspace(-2.0, 2.0, N)
        driver.exchange(torque)
        heartbeats = driver.counters.heartbeats
        count = _MessageCount(monkeypatch)
        for _ in range(100):
            feedback = driver.exchange(torque)
            assert feedback.fresh.all()
        monkeypatch.undo()
        counters = driver.counters
    assert count.made <= counters.heartbeats - heartbeats + 10, count.made  # 12 TPDOs a cycle, no message
    assert counters.dropped == 0 and counters.late == 0 and counters.malformed == 0


def test_a_thousand_cycles_keep_nothing_on_the_raw_path(driver: DriveBus, monkeypatch: pytest.MonkeyPatch) -> None:
    torque = np.linspace(-2.0, 2.0, N)
    tracemalloc.start(1)
    try:
        for _ in range(CYCLES):  # warm: every buffer made, every code path taken
            driver.exchange(torque)
        gc.collect()
        before = tracemalloc.take_snapshot()
        heartbeats = driver.counters.heartbeats
        count = _MessageCount(monkeypatch)
        for _ in range(CYCLES):
            driver.exchange(torque)
        monkeypatch.undo()
        gc.collect()
        after = tracemalloc.take_snapshot()
        peaks = []
        for _ in range(200):
            tracemalloc.reset_peak()
            start, _ = tracemalloc.get_traced_memory()
            feedback = driver.exchange(torque)
            peaks.append(tracemalloc.get_traced_memory()[1] - start)
            del feedback
    finally:
        tracemalloc.stop()
    own = [tracemalloc.Filter(True, str(ROOT / "drivers" / "*"))]
    grown = {
        f"{stat.traceback[0].filename}:{stat.traceback[0].lineno}": stat.size_diff
        for stat in after.filter_traces(own).compare_to(before.filter_traces(own), "lineno")
        if stat.size_diff > 0
    }
    # The driver keeps nothing per cycle (4 B a cycle would be 4 KiB): what shows is the receive
    # thread caught mid-frame by a snapshot (a heartbeat's message, the master heartbeat's datagram).
    assert sum(grown.values()) <= 4096, grown
    # What one exchange has alive at once, freed at once: ~12 KiB of it is the event buffer
    # Python's epoll.poll allocates per call (FD_SETSIZE - 1 events, drivers/ipc/bus.py), the
    # rest the received datagram, its frames and the feedback's arrays.
    assert float(np.median(peaks)) <= 16384, np.median(peaks)
    assert driver.counters.dropped == 0
    assert count.made <= driver.counters.heartbeats - heartbeats + 10, count.made  # none per cycle frame


def test_an_overlapped_cycle_returns_the_feedback_of_the_sync_sent_before(driver: DriveBus) -> None:
    """send() returns once the SYNC is out; collect() (the next cycle) returns that SYNC's feedback:
    fresh, the set-point it carried, nothing late or dropped over 300 cycles; the blocking exchange
    is refused while a SYNC waits for its collect, and collect without a send is refused."""
    from drivers.errors import DriveStateError

    torque = np.linspace(-2.0, 2.0, N)
    driver.send(torque)
    with pytest.raises(DriveStateError, match="collect"):
        driver.exchange(torque)
    with pytest.raises(DriveStateError, match="twice"):
        driver.send(torque)
    stale = 0
    for i in range(300):
        time.sleep(0.002)  # the caller's cycle: the drives answer meanwhile
        sent_counter = driver.sync_counter
        feedback = driver.collect()
        stale += not feedback.fresh.all()  # an answer later than the grace: stale, then late
        assert feedback.cycle == driver._services.exchange.cycle  # type: ignore[union-attr]  # connected
        assert sent_counter == driver.sync_counter  # collect sent nothing
        driver.send(torque * (i % 3))
    time.sleep(0.002)
    feedback = driver.collect()
    assert np.allclose(feedback.commanded_torque_nm, torque * (299 % 3), atol=0.2)
    with pytest.raises(DriveStateError, match="without a send"):
        driver.collect()
    assert stale <= 6, stale  # 2 % (a loaded machine's drive process may answer past the grace)
    assert driver.counters.late <= stale * N
    driver.exchange(torque)  # the blocking cycle again, once the overlapped one is closed
