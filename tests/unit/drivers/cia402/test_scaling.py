import math

import pytest

from drivers.cia402.scaling import (
    JointScaling,
    check_torque_range,
    counts_per_rad_from_resolution,
    rated_torque_for_resolution,
)


def test_torque_permille_round_trip_and_saturation() -> None:
    s = JointScaling(counts_per_rad=1000.0, rated_torque_mnm=5000)  # 5 mN·m per ‰
    assert s.torque_resolution_nm == pytest.approx(0.005)
    assert s.torque_to_permille(150.0) == 30000
    assert s.torque_to_permille(-0.0124) == -2
    assert s.permille_to_torque(30000) == pytest.approx(150.0)
    assert s.torque_to_permille(1e9) == 32767


def test_counts() -> None:
    cpr = counts_per_rad_from_resolution(1 << 20)
    assert cpr == pytest.approx((1 << 20) / (2 * math.pi))
    s = JointScaling(cpr, 1000)
    assert s.rad_to_counts(math.pi) == 1 << 19
    assert s.counts_to_rad(1 << 19) == pytest.approx(math.pi)


def test_rated_torque_for_resolution() -> None:
    assert rated_torque_for_resolution(150.0, 0.005) == 5000
    with pytest.raises(ValueError, match="at best"):
        rated_torque_for_resolution(150.0, 0.001)  # 150 N·m / 1 mN·m > 32767 steps


def test_check_torque_range_names_the_fix() -> None:
    check_torque_range(32.0, 1000)
    with pytest.raises(ValueError, match="at least 4578 mN·m"):
        check_torque_range(150.0, 1000)
