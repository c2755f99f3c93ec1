"""Byte vectors for the CiA 301/402 frame codec (little-endian, CiA 301 predefined set)."""

import pytest

from drivers.cia402 import frames as f


def test_nmt_start_node_5() -> None:
    assert f.encode_nmt(f.NmtCommand.START, 5) == bytes.fromhex("0105")
    assert f.decode_nmt(bytes.fromhex("8200")) == (f.NmtCommand.RESET_COMMUNICATION, 0)


@pytest.mark.parametrize("data", [b"\x01", b"\x01\x05\x00", b"\x03\x05", b"\x01\x80"])
def test_nmt_malformed(data: bytes) -> None:
    with pytest.raises(f.MalformedFrameError):
        f.decode_nmt(data)


def test_sync_with_and_without_counter() -> None:
    assert f.encode_sync() == b""
    assert f.encode_sync(240) == b"\xf0"
    assert f.decode_sync(b"") is None
    assert f.decode_sync(b"\x07") == 7
    with pytest.raises(f.MalformedFrameError):
        f.decode_sync(b"\x00")
    with pytest.raises(ValueError):
        f.encode_sync(241)


def test_heartbeat_masks_toggle_bit_and_rejects_unknown_state() -> None:
    assert f.encode_heartbeat(f.NmtState.PRE_OPERATIONAL) == b"\x7f"
    assert f.decode_heartbeat(b"\x85") is f.NmtState.OPERATIONAL
    assert f.decode_heartbeat(b"\x00") is f.NmtState.BOOT_UP
    with pytest.raises(f.MalformedFrameError):
        f.decode_heartbeat(b"\x06")
    with pytest.raises(f.MalformedFrameError):
        f.decode_heartbeat(b"\x05\x00")


def test_emcy_overcurrent() -> None:
    data = f.encode_emcy(f.EMCY_OVERCURRENT, 0x03, b"\x01")
    assert data == bytes.fromhex("1023030100000000")
    assert f.decode_emcy(data) == f.Emcy(0x2310, 0x03, b"\x01\x00\x00\x00\x00")
    with pytest.raises(f.MalformedFrameError):
        f.decode_emcy(data[:7])


def test_rpdo_controlword_and_negative_torque() -> None:
    data = f.encode_rpdo(0x000F, -1000)
    assert data == bytes.fromhex("0f0018fc")
    assert f.decode_rpdo(data) == f.RpdoData(0x000F, -1000)
    with pytest.raises(ValueError):
        f.encode_rpdo(0x000F, 40000)
    with pytest.raises(f.MalformedFrameError):
        f.decode_rpdo(data + b"\x00")


def test_tpdo1_tpdo2_classical() -> None:
    data = f.encode_tpdo1(0x1237, 500, -2)
    assert data == bytes.fromhex("3712f401feffffff")
    assert f.decode_tpdo1(data) == f.TpdoData(0x1237, 500, -2, None)
    assert f.encode_tpdo2(100000) == bytes.fromhex("a0860100")
    assert f.decode_tpdo2(bytes.fromhex("ffffffff")) == -1
    with pytest.raises(f.MalformedFrameError):
        f.decode_tpdo1(data[:6])
    with pytest.raises(f.MalformedFrameError):
        f.decode_tpdo2(b"\x00" * 8)


def test_tpdo_fd_twelve_bytes() -> None:
    data = f.encode_tpdo_fd(0x0027, -1, 2**31 - 1, -(2**31))
    assert data == bytes.fromhex("2700ffffffffff7f00000080")
    assert f.decode_tpdo_fd(data) == f.TpdoData(0x27, -1, 2**31 - 1, -(2**31))
    with pytest.raises(f.MalformedFrameError):
        f.decode_tpdo_fd(data + b"\x00" * 4)  # a 16-byte FD frame is not this PDO
    with pytest.raises(ValueError):
        f.encode_tpdo_fd(0x27, 0, 2**31, 0)


def test_split_cob_id() -> None:
    assert f.split_cob_id(0x185) == (f.TPDO1_BASE, 5)
    assert f.split_cob_id(0x080) == (f.SYNC_COB_ID, 0)
    assert f.split_cob_id(0x081) == (f.EMCY_BASE, 1)


def test_rpdo_into_a_reused_buffer() -> None:
    buffer = bytearray(f.RPDO_LENGTH)
    f.encode_rpdo_into(buffer, 0x000F, -1000)
    assert bytes(buffer) == bytes.fromhex("0f0018fc") == f.encode_rpdo(0x000F, -1000)
    with pytest.raises(ValueError):
        f.encode_rpdo_into(buffer, 0x000F, 40000)
    with pytest.raises(ValueError):
        f.encode_rpdo_into(bytearray(3), 0x000F, 0)


def test_tagged_fd_tpdo_into_a_reused_buffer() -> None:
    buffer = bytearray(b"\xaa" * f.TPDO_FD_SYNC_LENGTH)
    f.encode_tpdo_fd_sync_into(buffer, 0x1237, -2, 5, -6, 240)
    assert bytes(buffer) == bytes.fromhex("3712feff05000000fafffffff0000000")  # pad bytes zeroed
    assert f.decode_tpdo_fd_sync(buffer) == (f.TpdoData(0x1237, -2, 5, -6), 240)
    with pytest.raises(ValueError):
        f.encode_tpdo_fd_sync_into(buffer, 0x1237, 0, 0, 0, 256)


def test_communication_loss_emcy_codes() -> None:
    # CiA 301 table 21: heartbeat consumer timeout, RPDO timeout; generic communication (SYNC loss).
    assert (f.EMCY_HEARTBEAT, f.EMCY_RPDO_TIMEOUT, f.EMCY_COMMUNICATION) == (0x8130, 0x8250, 0x8100)
    assert f.decode_emcy(f.encode_emcy(f.EMCY_HEARTBEAT, f.ERROR_REGISTER_COMMUNICATION)).error_code == 0x8130
