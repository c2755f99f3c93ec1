"""CAN captures written through CaptureBus and read back with python-can's own readers, for every
suffix; captures python-can would misread are refused in one line; CANopen decoding of a capture."""

from __future__ import annotations

import uuid
from pathlib import Path

import can
import pytest

from drivers.capture import CAPTURE_SUFFIXES, CanCapture, CaptureBus, CaptureError, read_capture
from drivers.cia402 import frames as fr
from drivers.decode import Decoder

SUFFIXES = sorted(CAPTURE_SUFFIXES)


def _frames() -> list[can.Message]:
    """What the drive bus carries: NMT, SYNC with counter, an RPDO, a tagged FD TPDO, EMCY, heartbeat."""
    return [
        can.Message(arbitration_id=fr.NMT_COB_ID, data=fr.encode_nmt(fr.NmtCommand.START, 0), is_extended_id=False),
        can.Message(arbitration_id=fr.SYNC_COB_ID, data=fr.encode_sync(17), is_extended_id=False),
        can.Message(arbitration_id=0x203, data=fr.encode_rpdo(0x000F, -250), is_extended_id=False),
        can.Message(
            arbitration_id=0x183,
            data=fr.encode_tpdo_fd_sync(0x0237, 12, -83443, 4096, 17),
            is_extended_id=False,
            is_fd=True,
            bitrate_switch=True,
        ),
        can.Message(arbitration_id=0x083, data=fr.encode_emcy(fr.EMCY_FOLLOWING_ERROR, 0x01), is_extended_id=False),
        can.Message(arbitration_id=0x703, data=fr.encode_heartbeat(fr.NmtState.OPERATIONAL), is_extended_id=False),
    ]


def _capture(path: Path) -> list[can.Message]:
    """Half the frames sent through the capturing bus, half received through it; returns them in order."""
    channel = f"cap-{uuid.uuid4().hex[:8]}"
    master = can.Bus(interface="virtual", channel=channel, protocol=can.CanProtocol.CAN_FD)
    drives = can.Bus(interface="virtual", channel=channel, protocol=can.CanProtocol.CAN_FD)
    bus = CaptureBus(master, CanCapture(path))
    order = []
    try:
        for i, msg in enumerate(_frames()):
            if i % 2 == 0:
                bus.send(msg)
            else:
                drives.send(msg)
                received = bus.recv(1.0)
                assert received is not None and received.arbitration_id == msg.arbitration_id
            order.append(msg)
    finally:
        bus.shutdown()
        drives.shutdown()
    return order


@pytest.mark.parametrize("suffix", SUFFIXES)
def test_every_frame_reads_back_with_python_can_s_reader(tmp_path: Path, suffix: str) -> None:
    path = tmp_path / f"run{suffix}"
    sent = _capture(path)
    back = list(can.LogReader(str(path)))  # python-can's reader, not ours
    assert [m.arbitration_id for m in back] == [m.arbitration_id for m in sent]
    assert [bytes(m.data) for m in back] == [bytes(m.data) for m in sent]
    assert not any(m.is_extended_id for m in back)
    if suffix != ".csv":  # python-can's CSV has no direction or FD columns
        assert [m.is_rx for m in back] == [i % 2 == 1 for i in range(len(sent))]
        assert [m.is_fd for m in back] == [m.is_fd for m in sent]
    assert len(list(read_capture(path))) == len(sent)
    assert not list(tmp_path.glob(".*partial*"))


def test_a_full_queue_drops_frames_and_counts_them(tmp_path: Path) -> None:
    capture = CanCapture(tmp_path / "run.log", queue_size=4, drain_period_s=30.0)
    for msg in _frames():
        capture.tap(msg, False)
    assert (capture.captured, capture.dropped) == (4, 2)
    capture.close()
    assert len(list(can.LogReader(str(tmp_path / "run.log")))) == 4


@pytest.mark.parametrize("suffix", SUFFIXES)
def test_truncated_or_foreign_captures_are_one_line(tmp_path: Path, suffix: str) -> None:
    full = tmp_path / f"full{suffix}"
    _capture(full)
    data = full.read_bytes()
    cut = tmp_path / f"cut{suffix}"
    cut.write_bytes(data[: len(data) - 5])
    foreign = tmp_path / f"foreign{suffix}"
    foreign.write_bytes(b"robot: ur5_paper\nperiod_s: 0.001\n")
    empty = tmp_path / f"empty{suffix}"
    empty.write_bytes(b"")
    for bad, reason in ((cut, "truncated|not a"), (foreign, "not a|no CAN frames|truncated"), (empty, "empty|not a")):
        with pytest.raises(CaptureError, match=reason) as info:
            list(read_capture(bad))
        assert str(bad) in str(info.value) and "\n" not in str(info.value)
    with pytest.raises(CaptureError, match="unknown capture format '.pcap'"):
        list(read_capture(tmp_path / "x.pcap"))


def test_a_capture_decodes_as_canopen_with_eds_names_and_units(tmp_path: Path) -> None:
    path = tmp_path / "run.blf"
    _capture(path)
    decoder = Decoder()
    t = [decoder.decode(msg).line(0.0) for msg in read_capture(path)]
    assert "tx 0x000 NMT: START all nodes" in t[0]
    assert "rx 0x080 SYNC: counter 17" in t[1]
    assert "0x203 RPDO1 node 3: Controlword=0x000F, Target torque=-250 ‰ rated" in t[2]
    assert "0x183 TPDO1 FD node 3: Statusword=0x0237 (OPERATION_ENABLED), Torque actual value=12 ‰ rated" in t[3]
    assert "Position actual value=-83443 counts, Velocity actual value=4096 counts/s" in t[3]
    assert "0x083 EMCY node 3: 0x8611 following error, error register 0x01" in t[4]
    assert "0x703 heartbeat node 3: OPERATIONAL" in t[5]
    malformed = decoder.decode(can.Message(arbitration_id=0x080, data=b"\x00\x01", is_extended_id=False))
    assert malformed.kind == "malformed"
