"""DriveBus adds each set-point's rounding error to the set-point two cycles later
(drivers/drive_bus.py): the torque the drives apply averages to the torque asked for, as a CiA
402 drive's 1 ‰ steps allow, and the rounding noise has no component at the Nyquist frequency.
Plain rounding biases a constant request by up to half a step for ever (docs/hil.md: a law with
little static stiffness, H∞, drifted 5° RMS from it in the HIL experiment)."""

from __future__ import annotations

import numpy as np

from sim_target.testing.drive_rig import make_rig


def test_rounding_error_is_carried_so_the_average_torque_is_exact() -> None:
    rig = make_rig(n=2, feedback_timeout_s=0.2)
    try:
        rig.driver.enable()
        step_nm = 1.0 / rig.driver.nodes[0].permille_per_nm  # 1 ‰ of the rated torque (5 mN m here)
        asked = np.array([0.3 * step_nm, -2.6 * step_nm])
        sent = np.array([rig.driver.exchange(asked).commanded_torque_nm for _ in range(50)])
        np.testing.assert_allclose(sent / step_nm, np.rint(sent / step_nm), atol=1e-9)  # whole steps only
        assert set(np.round(sent[:, 0] / step_nm).astype(int)) == {0, 1}  # 0.3 steps: mostly 0, sometimes 1
        np.testing.assert_allclose(sent.sum(axis=0), 50 * asked, atol=step_nm + 1e-12)  # never biased
        # No noise at the Nyquist frequency: the alternating sum of the errors stays within a step too.
        signs = (-1.0) ** np.arange(50)
        assert np.all(np.abs(signs @ (sent - asked)) <= step_nm + 1e-12)
        np.testing.assert_allclose(rig.drives.commanded_torque_nm()[:2], sent[-1])  # what the drives got
        rig.driver.quick_stop()
        rig.driver.enable()  # a new enable starts without a carried error
        np.testing.assert_allclose(rig.driver.exchange(asked).commanded_torque_nm, [0.0, -3 * step_nm])
    finally:
        rig.close()
