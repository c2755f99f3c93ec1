"""The emulated drives' two paths behave alike: python-can's ``recv``/``send_batch`` (the virtual bus,
and any bus but the ipc bus itself) and the ipc bus's raw datagrams (``recv_frames``: a datagram's
frames undecoded; the SYNC's TPDOs packed in place into one preallocated ``FrameBatch``).

Every check of the python-can path holds on the raw one: malformed, remote, extended and error
frames counted, NMT, SDO, the injected frame faults (drop, corrupt, delay).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import can
import numpy as np
import pytest

from drivers.cia402 import frames as fr
from sim_target.testing.drive_rig import Rig, make_rig, wait_until

PATHS = ["virtual", "ipc"]


@pytest.fixture(params=PATHS)
def rig(request: pytest.FixtureRequest) -> Iterator[Rig]:
    rig = make_rig(n=2, fd=True, interface=request.param, feedback_timeout_s=0.2)
    yield rig
    rig.close()


def _intruder(rig: Rig) -> can.BusABC:
    transport = rig.config.transport
    if transport.interface == "ipc":
        return can.Bus(interface="ipc", channel=transport.channel, fd=True)
    return can.Bus(interface="virtual", channel=transport.channel, ignore_config=True)


def _msg(cob_id: int, data: bytes = b"", **kwargs: Any) -> can.Message:
    return can.Message(arbitration_id=cob_id, data=data, is_extended_id=kwargs.pop("is_extended_id", False), **kwargs)


def test_the_ipc_bus_takes_the_raw_path(rig: Rig) -> None:
    """On the ipc bus the drives never build a can.Message to receive, and answer each SYNC with
    the preallocated batch; elsewhere python-can's path, unchanged."""
    recv_calls = []
    original_recv = rig.drive_side_bus.recv

    def counting_recv(timeout: float | None = None) -> can.Message | None:
        recv_calls.append(timeout)
        return original_recv(timeout)

    rig.drive_side_bus.recv = counting_recv  # type: ignore[method-assign]  # an instance stand-in
    rig.driver.enable()
    for _ in range(20):
        feedback = rig.driver.exchange(np.array([1.0, -1.0]))
    assert feedback.fresh.all()
    np.testing.assert_allclose(feedback.position_rad, rig.plant.state().position_rad, atol=1e-5)
    answered_fast = rig.drives._answer.fast
    if rig.config.transport.interface == "ipc":
        assert not recv_calls
        assert answered_fast >= 20
        assert rig.drives.cycles_read >= 19  # the master's RPDOs and SYNC read in one unpack
    else:
        assert recv_calls
        assert answered_fast == 0
        assert rig.drives.cycles_read == 0


def test_junk_frames_are_counted_alike(rig: Rig) -> None:
    rig.driver.enable()
    intruder = _intruder(rig)
    try:
        before = rig.drives.counters
        junk = [
            _msg(0x201, bytes(8), is_extended_id=True),  # extended id
            _msg(0x201, is_remote_frame=True, dlc=6),  # remote request
            _msg(0x201, bytes(8), is_error_frame=True),  # error frame
            _msg(0x201, b"\x0f\x00\x10"),  # short RPDO
            _msg(0x080, b"\x01\x02"),  # 2-byte SYNC
            _msg(0x080, b"\x00"),  # SYNC counter 0
            _msg(0x000, b"\x01"),  # short NMT
            _msg(0x601, bytes(7)),  # short SDO request
            _msg(0x3FF, b"\x00"),  # nobody's COB-ID: unknown, not malformed
        ]
        if rig.config.transport.interface == "ipc":
            intruder.send_batch(junk)  # type: ignore[attr-defined]  # one datagram: the raw path's case
        else:
            for msg in junk:
                intruder.send(msg)
        assert wait_until(lambda: rig.drives.counters.frames_received - before.frames_received >= len(junk))
        after = rig.drives.counters
        assert after.malformed - before.malformed == 8
        assert after.unknown_cob_id - before.unknown_cob_id >= 1
        assert rig.drives.counters.syncs == before.syncs  # no junk SYNC was answered
    finally:
        intruder.shutdown()


def test_nmt_and_sdo_alike(rig: Rig) -> None:
    intruder = _intruder(rig)
    try:
        # SDO upload of the statusword (0x6041:00) from drive 2, answered on 0x582.
        request = bytes([0x40, 0x41, 0x60, 0x00, 0, 0, 0, 0])
        intruder.send(_msg(fr.SDO_RX_BASE + 2, request))
        answer = _recv_from(intruder, fr.SDO_TX_BASE + 2)
        assert answer is not None and answer.data[0] == 0x4B and bytes(answer.data[1:4]) == request[1:4]
        intruder.send(_msg(fr.NMT_COB_ID, bytes([0x02, 2])))  # stop drive 2
        assert wait_until(lambda: rig.drives.nmt_states()[1] is fr.NmtState.STOPPED)
        assert rig.drives.nmt_states()[0] is not fr.NmtState.STOPPED
        intruder.send(_msg(fr.SDO_RX_BASE + 2, request))  # a stopped drive answers no SDO
        assert _recv_from(intruder, fr.SDO_TX_BASE + 2, timeout_s=0.2) is None
        intruder.send(_msg(fr.NMT_COB_ID, bytes([0x01, 0])))  # start all
        assert wait_until(lambda: all(s is fr.NmtState.OPERATIONAL for s in rig.drives.nmt_states()))
    finally:
        intruder.shutdown()


def _recv_from(bus: can.BusABC, cob_id: int, timeout_s: float = 2.0) -> can.Message | None:
    import time

    deadline = time.monotonic() + timeout_s
    while (remaining := deadline - time.monotonic()) > 0:
        msg = bus.recv(remaining)
        if msg is not None and msg.arbitration_id == cob_id:
            return msg
    return None


def test_frame_faults_alike(rig: Rig) -> None:
    """Injected drops, corruption and delays reach the master on both paths (the raw path steps
    aside for a drive with a fault pending, and takes over again after it)."""
    bus = rig.driver
    bus.enable()
    bus.exchange(np.zeros(2))
    rig.drives.drop_tpdos(2, cycles=1)
    assert bus.exchange(np.zeros(2)).fresh.tolist() == [True, False]
    assert bus.counters.dropped == 1
    rig.drives.corrupt_tpdos(1, cycles=1)
    fresh = bus.exchange(np.zeros(2)).fresh.tolist()
    assert rig.drives.counters.corrupted_injected == 1
    if rig.config.transport.interface == "virtual":
        assert fresh == [False, True]
        assert bus.counters.malformed == 1
    # (On the ipc bus, as on SocketCAN, a CAN FD frame one byte short is padded up to the next FD
    # length, 16 bytes: the master cannot tell it from a good one.)
    rig.drives.delay_tpdos(2, 0.5, cycles=1)  # past the 0.2 s feedback timeout: counted late
    assert bus.exchange(np.zeros(2)).fresh.tolist() == [True, False]
    assert wait_until(lambda: rig.drives.counters.delayed_injected == 1)
    fast_before = rig.drives._answer.fast
    bus.exchange(np.zeros(2))  # under load the delayed frame's release can fall into this cycle (slow path)
    for _ in range(5):
        assert bus.exchange(np.zeros(2)).fresh.all()
    if rig.config.transport.interface == "ipc":  # back on the hot path: the five cycles after it at least
        # (the drive thread counts its answer after the master has it: wait for the count to catch up)
        assert wait_until(lambda: rig.drives._answer.fast - fast_before >= 5)
        assert rig.drives._answer.fast - fast_before <= 6
