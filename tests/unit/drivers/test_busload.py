"""Bus-load budget: frame lengths against published worst cases, and the refusal message."""

import pytest

from drivers.busload import (
    check_bus_load,
    classical_frame_bits,
    compute_bus_load,
    fd_frame_bits,
    fd_padded_length,
)
from drivers.errors import BusLoadError


def test_classical_worst_case_frame_lengths() -> None:
    # Davis et al. 2007: 8n + 47 + floor((34 + 8n - 1) / 4); 135 bits for 8 bytes.
    assert classical_frame_bits(0) == 55
    assert classical_frame_bits(4) == 95
    assert classical_frame_bits(8) == 135


def test_fd_frame() -> None:
    nominal, data = fd_frame_bits(12)
    assert nominal == 34  # 17 arbitration + 4 stuff + 13 frame end
    assert data == 5 + 96 + 25 + 21 + 6
    assert fd_padded_length(9) == 12
    assert fd_frame_bits(17)[1] > fd_frame_bits(16)[1] + 8 * 4  # 20 bytes and CRC-21


def test_six_drives_classical_1mbit() -> None:
    load = compute_bus_load(6, 1000.0, 1_000_000)
    assert load.nominal_bits_per_cycle == 55 + 6 * (95 + 135 + 95)
    assert load.load == pytest.approx(2.005)
    assert 420 < load.max_rate_hz < 425


def test_refusal_says_what_fits() -> None:
    with pytest.raises(BusLoadError) as info:
        check_bus_load(6, 1000.0, 1_000_000, None, 0.05, source="arm.yaml")
    message = str(info.value)
    assert message.startswith("arm.yaml: 6 drives on classical CAN at 1 Mbit/s")
    assert "fits about 420 Hz" in message
    assert "CAN FD with a 4 Mbit/s data phase" in message
    assert "\n" not in message
    assert info.value.exit_code == 2


def test_fd_fits_1khz() -> None:
    load = check_bus_load(6, 1000.0, 1_000_000, 5_000_000, 0.05)
    assert 0.70 < load.load < 0.80
    assert load.frames_per_cycle == 13


def test_heartbeats_add_load() -> None:
    base = compute_bus_load(6, 100.0, 125_000).load
    with_hb = compute_bus_load(6, 100.0, 125_000, heartbeat_period_s=0.01).load
    assert with_hb - base == pytest.approx(6 * 65 / 125_000 / 0.01)
