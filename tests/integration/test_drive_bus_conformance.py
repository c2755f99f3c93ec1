"""DriveBus on the emulated drives passes the public JointBus checker (drivers.checks)."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.checks import check_joint_bus
from sim_target.testing.drive_rig import make_rig


@pytest.mark.parametrize("fd", [False, True], ids=["classical", "fd"])
def test_drive_bus_passes_check_joint_bus(fd: bool) -> None:
    rig = make_rig(n=3, fd=fd, connect=False, feedback_timeout_s=0.2)
    try:
        check_joint_bus(rig.driver, hold_torque_nm=np.array([1.0, -2.0, 0.5]))
        assert rig.driver.counters.cycles > 5
    finally:
        rig.close()
