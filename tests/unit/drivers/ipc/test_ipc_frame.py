"""The ipc bus's frames are SocketCAN's ``struct can_frame`` / ``struct canfd_frame``: byte vectors,
and agreement with python-can's own SocketCAN packing in both directions."""

from __future__ import annotations

import sys

import can
import pytest
from can.interfaces.socketcan.socketcan import build_can_frame, dissect_can_frame

from drivers.ipc.frame import (
    CAN_ERR_CRTL,
    CAN_ERR_CRTL_RX_OVERFLOW,
    FrameBatch,
    FrameError,
    decode,
    encode,
    raw_frames,
    rx_overflow_frame,
    split_batch,
)

little_endian = pytest.mark.skipif(sys.byteorder != "little", reason="the byte vectors are in little-endian host order")


@little_endian
def test_classical_standard_frame_bytes() -> None:
    msg = can.Message(arbitration_id=0x123, data=b"abc", is_extended_id=False)
    assert encode(msg) == bytes.fromhex("23010000030000006162630000000000")


@little_endian
def test_extended_remote_frame_bytes() -> None:
    msg = can.Message(arbitration_id=0x1234567, is_extended_id=True, is_remote_frame=True, dlc=4)
    # can_id = 0x01234567 | CAN_EFF_FLAG | CAN_RTR_FLAG
    assert encode(msg) == bytes.fromhex("674523c104000000") + bytes(8)


@little_endian
def test_fd_frame_bytes_with_flags() -> None:
    msg = can.Message(
        arbitration_id=0x181,
        data=bytes(range(12)),
        is_extended_id=False,
        is_fd=True,
        bitrate_switch=True,
        error_state_indicator=True,
    )
    frame = encode(msg)
    assert len(frame) == 72
    # len 12; flags FDF | ESI | BRS = 0x07
    assert frame[:8] == bytes.fromhex("810100000c070000")
    assert frame[8:20] == bytes(range(12)) and frame[20:] == bytes(52)


@little_endian
def test_rx_overflow_error_frame_is_linux_error_class() -> None:
    frame = rx_overflow_frame()
    assert frame[:8] == bytes.fromhex("0400002008000000")  # CAN_ERR_FLAG | CAN_ERR_CRTL, len 8
    msg = decode(frame)
    assert msg.is_error_frame and msg.arbitration_id == CAN_ERR_CRTL
    assert msg.data[1] == CAN_ERR_CRTL_RX_OVERFLOW


MESSAGES = [
    can.Message(arbitration_id=0x7FF, data=bytes(8), is_extended_id=False),
    can.Message(arbitration_id=0x000, data=b"", is_extended_id=False),
    can.Message(arbitration_id=0x1FFFFFFF, data=b"\x01\x02", is_extended_id=True),
    can.Message(arbitration_id=0x601, is_extended_id=False, is_remote_frame=True, dlc=8),
    can.Message(arbitration_id=0x201, data=bytes(range(64)), is_extended_id=False, is_fd=True, bitrate_switch=True),
    can.Message(arbitration_id=0x12345, data=bytes(range(20)), is_extended_id=True, is_fd=True),
    can.Message(arbitration_id=0x004, data=bytes(8), is_error_frame=True, is_extended_id=False),
]


def _same(a: can.Message, b: can.Message) -> None:
    assert (a.arbitration_id, a.is_extended_id, a.is_remote_frame, a.is_error_frame, a.is_fd, a.dlc) == (
        b.arbitration_id,
        b.is_extended_id,
        b.is_remote_frame,
        b.is_error_frame,
        b.is_fd,
        b.dlc,
    )
    assert bytes(a.data) == bytes(b.data)
    if a.is_fd:
        assert (a.bitrate_switch, a.error_state_indicator) == (b.bitrate_switch, b.error_state_indicator)


@pytest.mark.parametrize("msg", MESSAGES, ids=lambda m: f"{m.arbitration_id:x}{'-fd' if m.is_fd else ''}")
def test_round_trip(msg: can.Message) -> None:
    _same(decode(encode(msg), channel="bus", timestamp=1.5), msg)


@pytest.mark.parametrize("msg", MESSAGES, ids=lambda m: f"{m.arbitration_id:x}{'-fd' if m.is_fd else ''}")
def test_agrees_with_python_cans_socketcan_packing(msg: can.Message) -> None:
    # python-can writes its dlc into len8_dlc (ignored by Linux below 8 bytes); everything else agrees.
    theirs = build_can_frame(msg)
    assert len(theirs) == len(encode(msg))
    _same(decode(theirs), msg)
    their_id, their_dlc, _flags, their_data = dissect_can_frame(encode(msg))
    ours = encode(msg)
    assert their_id == int.from_bytes(ours[:4], sys.byteorder) and their_dlc == msg.dlc
    if not msg.is_remote_frame:
        assert their_data == bytes(msg.data)


def test_fd_payload_padded_to_a_fd_length() -> None:
    msg = can.Message(arbitration_id=0x1, data=bytes(10), is_fd=True, is_extended_id=False)
    assert decode(encode(msg)).dlc == 12


@pytest.mark.parametrize(
    "msg",
    [
        can.Message(arbitration_id=0x800, data=b"", is_extended_id=False),
        can.Message(arbitration_id=0x20000000, data=b"", is_extended_id=True),
        can.Message(arbitration_id=0x1, data=bytes(9), is_extended_id=False, check=False),
        can.Message(arbitration_id=0x1, data=bytes(65), is_extended_id=False, is_fd=True, check=False),
    ],
)
def test_refuses_what_is_not_a_frame(msg: can.Message) -> None:
    with pytest.raises(FrameError):
        encode(msg)


@pytest.mark.parametrize(
    "datagram",
    [
        b"",
        bytes(15),
        bytes(17),
        bytes(71),
        bytes(73),
        bytes.fromhex("0000000009000000") + bytes(8),
        bytes.fromhex("000000000d000000") + bytes(64),
    ],
)
def test_refuses_datagrams_that_are_not_frames(datagram: bytes) -> None:
    with pytest.raises(FrameError):
        decode(datagram)


def test_a_batch_splits_into_its_frames_by_each_frames_fd_flag() -> None:
    frames = [
        encode(can.Message(arbitration_id=0x181, data=bytes(12), is_extended_id=False, is_fd=True)),
        encode(can.Message(arbitration_id=0x80, data=b"\x05", is_extended_id=False)),
        encode(can.Message(arbitration_id=0x182, data=bytes(range(64)), is_extended_id=False, is_fd=True)),
    ]
    assert split_batch(b"".join(frames)) == frames
    assert [decode(f).arbitration_id for f in split_batch(b"".join(frames))] == [0x181, 0x80, 0x182]
    with pytest.raises(FrameError, match="cut short"):
        split_batch(b"".join(frames)[:-1])
    with pytest.raises(FrameError, match="trailing bytes"):
        split_batch(frames[1] + bytes(5))


def test_raw_frames_agree_with_decode_and_refuse_what_it_refuses() -> None:
    msgs = [
        can.Message(arbitration_id=0x181, data=bytes(range(12)), is_fd=True),
        can.Message(arbitration_id=0x80, data=b"\x05", is_extended_id=False),
        can.Message(arbitration_id=0x1234567, data=b"\x01\x02", is_extended_id=True),
    ]
    frames = [encode(m) for m in msgs]
    for frame in frames:  # one frame: its size tells the layout
        ((can_id, data, is_fd),) = raw_frames(frame)
        msg = decode(frame)
        assert (can_id & 0x1FFFFFFF, data, is_fd) == (msg.arbitration_id, bytes(msg.data), msg.is_fd)
    assert [(c & 0x1FFFFFFF, d, f) for c, d, f in raw_frames(b"".join(frames))] == [
        (m.arbitration_id, bytes(m.data), m.is_fd) for m in msgs
    ]
    assert raw_frames(frames[2])[0][0] & 0x80000000  # CAN_EFF_FLAG kept
    with pytest.raises(FrameError):
        raw_frames(b"".join(frames)[:-1])
    with pytest.raises(FrameError):
        raw_frames(frames[1][:4] + bytes([9]) + frames[1][5:])  # a classical frame of 9 bytes


def test_a_frame_batch_rewrites_payloads_in_place() -> None:
    msgs = [
        can.Message(arbitration_id=0x201, data=bytes(8), is_fd=True, is_extended_id=False),
        can.Message(arbitration_id=0x80, data=b"\x00", is_extended_id=False),
    ]
    batch = FrameBatch(msgs)
    datagram = batch.datagram
    batch.payloads[0][:] = b"ABCDEFGH"
    batch.payloads[1][0] = 7
    assert batch.datagram is datagram and batch.count == 2 and batch.fd
    assert [(c, d) for c, d, _ in raw_frames(bytes(datagram))] == [(0x201, b"ABCDEFGH"), (0x80, b"\x07")]
    with pytest.raises(FrameError):
        FrameBatch([])
