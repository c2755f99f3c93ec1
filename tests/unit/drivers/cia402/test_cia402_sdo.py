"""SDO codec byte vectors, cross-checked against the canopen library's own SDO client."""

import struct

import canopen
import pytest

from drivers.cia402 import sdo
from drivers.cia402.frames import MalformedFrameError
from drivers.cia402.od import EDS_PATH


@pytest.mark.parametrize(
    ("index", "sub", "payload", "expected"),
    [
        (0x6060, 0, b"\x0a", "2f6060000a000000"),
        (0x1017, 0, struct.pack("<H", 50), "2b17100032000000"),
        (0x6076, 0, struct.pack("<I", 5000), "2376600088130000"),
        (0x1A00, 3, b"\x20\x00\x64\x60", "23001a0320006460"),
    ],
)
def test_expedited_download(index: int, sub: int, payload: bytes, expected: str) -> None:
    data = sdo.encode_download_expedited(index, sub, payload)
    assert data.hex() == expected
    assert sdo.decode_request(data) == sdo.SdoFrame(sdo.SdoKind.DOWNLOAD_EXPEDITED, index, sub, payload, 0)


def test_upload_request_and_response() -> None:
    assert sdo.encode_upload_request(0x6041, 0).hex() == "4041600000000000"
    response = sdo.encode_upload_expedited_response(0x6041, 0, struct.pack("<H", 0x0237))
    assert response.hex() == "4b41600037020000"
    assert sdo.decode_response(response).data == b"\x37\x02"


def test_download_ack_and_abort() -> None:
    assert sdo.encode_download_response(0x6060, 0).hex() == "6060600000000000"
    abort = sdo.encode_abort(0x6041, 0, 0x06010002)
    assert abort.hex() == "8041600002000106"
    frame = sdo.decode_response(abort)
    assert frame.kind is sdo.SdoKind.ABORT and frame.value == sdo.ABORT_READ_ONLY
    assert sdo.abort_code_text(frame.value) == "attempt to write a read only object"
    assert sdo.abort_code_text(0x12345678) == "unknown abort code"


def test_segmented_upload_initiate_is_recognised() -> None:
    frame = sdo.decode_response(bytes.fromhex("4108100000000000")[:4] + struct.pack("<I", 13))
    assert frame.kind is sdo.SdoKind.UPLOAD_SEGMENTED and frame.value == 13


@pytest.mark.parametrize("data", [b"\x40\x41\x60", bytes.fromhex("e041600000000000")])
def test_malformed_sdo(data: bytes) -> None:
    with pytest.raises(MalformedFrameError):
        sdo.decode_response(data)


def test_encoder_matches_canopen_client() -> None:
    """The canopen library's SdoClient must put exactly our bytes on the bus."""
    sent: list[bytes] = []

    class RecordingNetwork:
        def send_message(self, can_id: int, data: bytes, remote: bool = False) -> None:
            sent.append(bytes(data))
            client.on_response(0x585, sdo.encode_download_response(0x6060, 0), 0.0)

    od = canopen.import_od(str(EDS_PATH), 5)
    client = canopen.sdo.SdoClient(0x605, 0x585, od)
    client.network = RecordingNetwork()  # type: ignore[assignment]  # a recording stand-in, not a canopen Network
    client.download(0x6060, 0, b"\x0a")
    assert sent == [sdo.encode_download_expedited(0x6060, 0, b"\x0a")]
