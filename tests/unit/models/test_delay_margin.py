"""Delay margin: the linearized delayed loop is right, and it separates the gains that hold one period
of delay from the paper's elbow gain (docs/feedback_laws.md, "Delay margin")."""

from __future__ import annotations

import re

import numpy as np
import pytest

from models.delay_margin import closed_loop_matrices, delay_margin, envelope_poses, linearize_law, plant_matrices
from models.errors import ModelInputError
from models.feedback import GAIN_SETS, make_law
from models.robots import load_robot

ROBOT = load_robot("ur5_paper")
POSES = envelope_poses(ROBOT, 400)


def test_linearized_pd_is_its_gains_and_the_plant_is_the_exact_zoh() -> None:
    law = make_law("pd", ROBOT, 1e-3, "paper")
    ly, ls, fy, fs = linearize_law(law, POSES[:3])
    expected = np.concatenate([-np.diag(law.kp), -np.diag(law.kd)], 1)
    np.testing.assert_allclose(ly, np.broadcast_to(expected, ly.shape), atol=1e-7)
    assert ls.shape == (3, 6, 0) and fy.shape == (3, 0, 12) and fs.shape == (3, 0, 0)
    # The batched Taylor series equals scipy's expm of the ZOH block [[A, B], [0, 0]] T.
    from scipy.linalg import expm

    from models.delay_margin import _gravity_jacobian
    from models.dynamics import make_dynamics

    pose = POSES[:1]
    ad, bd = plant_matrices(ROBOT, pose, 1e-3)
    inverse_mass = np.linalg.inv(make_dynamics(ROBOT).mass_matrix(pose))[0]
    block = np.zeros((18, 18))
    block[:6, 6:12] = np.eye(6)
    block[6:12, :6] = -inverse_mass @ _gravity_jacobian(ROBOT, pose)[0]
    block[6:12, 12:] = inverse_mass
    exact = expm(block * 1e-3)
    np.testing.assert_allclose(ad[0], exact[:12, :12], rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(bd[0], exact[:12, 12:], rtol=1e-10, atol=1e-14)


def test_one_period_delay_moves_the_measurement_one_slot_back() -> None:
    # Scalar velocity loop v+ = v - a v[k-1]: stable iff a < 1 (z^2 - z + a); without delay iff a < 2.
    ad, bd = np.array([[[1.0]]]), np.array([[[1.0]]])
    for a, stable_delayed in ((0.9, True), (1.1, False)):
        ly = np.array([[[-a]]])
        empty = (np.zeros((1, 1, 0)), np.zeros((1, 0, 1)), np.zeros((1, 0, 0)))
        radius = np.abs(np.linalg.eigvals(closed_loop_matrices(ad, bd, ly, *empty, 1))).max()
        assert (radius < 1.0) == stable_delayed
        assert np.abs(np.linalg.eigvals(closed_loop_matrices(ad, bd, ly, *empty, 0))).max() < 1.0


@pytest.mark.parametrize("name", ["pd", "pid"])
def test_stabilized_pd_and_pid_hold_one_period_of_delay(name: str) -> None:
    report = delay_margin(make_law(name, ROBOT, 1e-3, "stabilized"), ROBOT, 1, poses=POSES)
    assert report.holds and report.unstable_poses == 0, report.as_dict()


@pytest.mark.parametrize("name", ["pd", "pid"])
def test_the_papers_elbow_gain_fails_with_the_delay_and_holds_without(name: str) -> None:
    kd = np.array(GAIN_SETS["stabilized"][name]["kd"])
    kd[2] = 2.0  # the paper's elbow Kd, every other gain as in the stabilized set
    law = make_law(name, ROBOT, 1e-3, "stabilized", kd=kd)
    delayed = delay_margin(law, ROBOT, 1, poses=POSES)
    assert not delayed.holds and delayed.delay_induced_poses > 0
    assert delay_margin(law, ROBOT, 0, poses=POSES).unstable_poses == 0


def test_stabilized_adrc_holds_and_the_papers_omega_c_does_not() -> None:
    poses = POSES[:200]  # ADRC's 24 state columns: half the poses keep the test fast
    assert delay_margin(make_law("adrc", ROBOT, 1e-3, "stabilized"), ROBOT, 1, poses=poses).holds
    fast = make_law("adrc", ROBOT, 1e-3, "stabilized", omega_c=20.0)
    assert delay_margin(fast, ROBOT, 1, poses=poses).delay_induced_poses > 0


def test_nonlinear_laws_are_refused_by_the_linear_check() -> None:
    with pytest.raises(ModelInputError, match="law 'smc'.*simulation"):
        delay_margin(make_law("smc", ROBOT), ROBOT, 1, poses=POSES[:2])


def test_hil_stability_prints_the_delay_margin(capsys: pytest.CaptureFixture[str]) -> None:
    from hil_runtime.cli import main

    assert main(["stability", "pd", "--gains", "paper", "--stride", "500", "--poses", "100"]) == 0
    out = capsys.readouterr().out
    assert "Theorem 1 for pd" in out
    assert re.search(r"Delay margin \(1 period\(s\), linear, 100 envelope poses\): FAILS; unstable poses \d+", out)
    assert main(["stability", "pd", "--stride", "500", "--poses", "100"]) == 0  # the stabilized set holds
    assert "envelope poses): holds" in capsys.readouterr().out
