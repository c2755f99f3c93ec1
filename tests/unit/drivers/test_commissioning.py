"""Pieces of a vendor drive's start-up (drivers/commissioning.py, drivers/sync.py)."""

from __future__ import annotations

import pytest

from drivers.commissioning import interpolation_period
from drivers.errors import DriveConfigError
from drivers.sync import SyncProducer


@pytest.mark.parametrize(
    ("period_s", "expected"),
    [(0.001, (1, -3)), (0.004, (4, -3)), (0.0025, (25, -4)), (0.0005, (5, -4)), (0.000125, (125, -6))],
)
def test_interpolation_period_prefers_milliseconds(period_s: float, expected: tuple[int, int]) -> None:
    assert interpolation_period(period_s) == expected


def test_interpolation_period_that_0x60c2_cannot_hold() -> None:
    with pytest.raises(DriveConfigError, match="0x60C2"):
        interpolation_period(0.5)  # 500 ms: above 255 of any unit


def test_sync_without_counter_for_drives_without_0x1019() -> None:
    sync = SyncProducer()
    sync.carry_counter(False)
    assert sync.advance() == 1 and sync.msg.dlc == 0 and bytes(sync.msg.data) == b""
    sync.carry_counter(True)
    assert sync.advance() == 2 and bytes(sync.msg.data) == b"\x02"
