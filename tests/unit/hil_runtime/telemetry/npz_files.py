"""Bad telemetry records as bytes (issue 20), shared by the plot tests and the CLI bad-input table."""

from __future__ import annotations

import functools
import io
import struct
import zlib
from typing import Any

import numpy as np


def npz(**arrays: Any) -> bytes:
    """Any: numpy's stub types savez's **kwds as also reaching its bool allow_pickle."""
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    return buffer.getvalue()


def record(samples: int = 50, n_joints: int = 3, **extra: object) -> bytes:
    q = np.sin(np.arange(samples)[:, None] * 1e-2 + np.arange(n_joints))
    columns: dict[str, object] = {"t_s": np.arange(samples) * 1e-3, "q": q, "q_ref": q + 0.01, "tau": 2 * q}
    return npz(**{**columns, **extra})


def truncated() -> bytes:
    whole = record()
    return whole[: len(whole) // 2]


def mismatched() -> bytes:
    return record(q_ref=np.zeros((60, 3)))


def period_string() -> bytes:
    return record(period_s=np.asarray("fast"), seq=np.arange(50, dtype=np.uint64))


def many_joints(n_joints: int = 600) -> bytes:
    return record(samples=2, n_joints=n_joints)


@functools.cache
def inflating(uncompressed_bytes: int = (1 << 30) + (1 << 24)) -> bytes:
    """A valid npz of about 1 MB whose ``q`` array inflates to ``uncompressed_bytes`` of zeros (the
    issue's 6 MB file inflated to 6 GiB). Built from one deflated 16 MiB block repeated: a full
    flush makes each copy independent; the CRC over 1 GiB takes most of its ~3 s (cached)."""
    chunk_bytes = 1 << 24
    rows = uncompressed_bytes // 48
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(header, {"descr": "<f8", "fortran_order": False, "shape": (rows, 6)})
    head = header.getvalue()
    body_bytes = rows * 48
    zeros = bytes(chunk_bytes)
    compressor = zlib.compressobj(9, zlib.DEFLATED, -15)
    parts = [compressor.compress(head) + compressor.flush(zlib.Z_FULL_FLUSH)]
    block = zlib.compressobj(9, zlib.DEFLATED, -15)
    repeated = block.compress(zeros) + block.flush(zlib.Z_FULL_FLUSH)
    crc = zlib.crc32(head)
    full, rest = divmod(body_bytes, chunk_bytes)
    for _ in range(full):
        parts.append(repeated)
        crc = zlib.crc32(zeros, crc)
    tail = zlib.compressobj(9, zlib.DEFLATED, -15)
    parts.append(tail.compress(bytes(rest)) + tail.flush(zlib.Z_FINISH))
    crc = zlib.crc32(bytes(rest), crc)
    data = b"".join(parts)
    size = len(head) + body_bytes
    name = b"q.npy"
    local = struct.pack("<4sHHHHHIIIHH", b"PK\x03\x04", 20, 0, 8, 0, 0, crc, len(data), size, len(name), 0)
    central = struct.pack(
        "<4sHHHHHHIIIHHHHHII", b"PK\x01\x02", 20, 20, 0, 8, 0, 0, crc, len(data), size, len(name), 0, 0, 0, 0, 0, 0
    )
    end = struct.pack(
        "<4sHHHHIIH", b"PK\x05\x06", 0, 0, 1, 1, len(central) + len(name), len(local) + len(name) + len(data), 0
    )
    return local + name + data + central + name + end
