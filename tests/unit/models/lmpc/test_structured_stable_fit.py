"""The structured emulator's "stable" physics fit (docs/any_arm.md "The stable physics fit"): on labels made
by a feed-forward with g_1 = 0.7 and cross-coupled gains whose symmetric part is indefinite (the Panda's
free fit, docs/any_arm.md "SMC on the real arms"), the free fit reproduces an unstable loop and the stable
fit returns g = 1 and, since g = 1 alone leaves a loop that does not decay, symmetric K_p, K_d above
their floors: a stable linearized loop."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from models.dynamics import make_dynamics
from models.errors import ModelInputError
from models.lmpc.structured import StructuredConfig, train_structured
from models.lmpc.structured.training import STABLE_KD_MIN_1_S, STABLE_KP_MIN_1_S2
from models.robots import load_robot


def _synthetic(samples: int = 128) -> tuple[object, np.ndarray, np.ndarray]:
    """States (q, e, qd, e_dot, qdd_d, tau_fb = 0) and labels y = g ⊙ ID(q, qd, qdd_d + Kp e + Kd e_dot)."""
    robot = load_robot("ur5_paper")
    n = robot.n_joints
    rng = np.random.default_rng(3)
    q, qd = rng.uniform(-1, 1, (samples, n)), rng.uniform(-1, 1, (samples, n))
    e, e_dot = rng.normal(0, 0.02, (samples, n)), rng.normal(0, 0.2, (samples, n))
    qdd_d = rng.normal(0, 1, (samples, n))
    kp = np.diag(np.full(n, 100.0))
    kp[0, 2], kp[2, 0] = -150.0, 150.0  # skew part: fine alone
    kp[1, 3] = kp[3, 1] = -180.0  # symmetric part with an eigenvalue of -80
    kd = np.diag(np.full(n, 20.0))
    g = np.ones(n)
    g[0] = 0.7
    dyn = make_dynamics(robot, "pinocchio")
    mass = np.asarray(dyn.mass_matrix(q)).reshape(-1, n, n)
    bias = np.asarray(dyn.nonlinear_effects(q, qd)).reshape(-1, n)
    accel = qdd_d + e @ kp.T + e_dot @ kd.T
    y = g * (np.einsum("bij,bj->bi", mass, accel) + bias)
    s = np.concatenate([q, e, qd, e_dot, qdd_d, np.zeros((samples, n))], axis=1)
    return robot, s, y


def _largest_real_part(kp: np.ndarray, kd: np.ndarray, g: np.ndarray) -> float:
    """e'' = -M^-1 G M (Kp e + Kd e_dot) at q = 0 (the benchmarks' `loop`, one pose)."""
    robot = load_robot("ur5_paper")
    n = robot.n_joints
    mass = np.asarray(make_dynamics(robot, "pinocchio").mass_matrix(np.zeros(n))).reshape(n, n)
    b = np.linalg.solve(mass, np.diag(g) @ mass)
    a = np.block([[np.zeros((n, n)), np.eye(n)], [-b @ kp, -b @ kd]])
    return float(np.linalg.eigvals(a).real.max())


def test_stable_fit_gives_a_stable_loop_where_the_free_fit_does_not() -> None:
    robot, s, y = _synthetic()
    config = StructuredConfig(
        hidden=(8,), c_fixed=-1.0, physics_steps=150, residual_epochs=1, physics_learning_rate=0.05
    )
    fits = {}
    for mode in ("free", "stable"):
        _, summary = train_structured(robot, s, y, replace(config, physics_fit=mode), log=lambda _: None)
        physics = summary["physics"]
        fits[mode] = tuple(np.asarray(physics[k], float) for k in ("g", "kp_1_s2", "kd_1_s"))
        assert physics["fit"] == mode
        assert physics["gains_projected"] is (mode == "stable")  # g = 1 alone leaves the indefinite K_p
    g, kp, kd = fits["free"]
    assert np.linalg.eigvalsh((kp + kp.T) / 2).min() < -20.0  # the free fit finds the indefinite gains
    assert _largest_real_part(kp, kd, g) > 0.0
    g, kp, kd = fits["stable"]
    np.testing.assert_array_equal(g, 1.0)
    np.testing.assert_allclose(kp, kp.T, atol=1e-9)
    np.testing.assert_allclose(kd, kd.T, atol=1e-9)
    assert np.linalg.eigvalsh(kp).min() >= STABLE_KP_MIN_1_S2 * (1 - 1e-9)
    assert np.linalg.eigvalsh(kd).min() >= STABLE_KD_MIN_1_S * (1 - 1e-9)
    assert _largest_real_part(kp, kd, g) < 0.0


def test_bounded_fit_keeps_the_feed_forward_and_symmetric_gains_above_their_floors() -> None:
    """The "bounded" fit: g >= G_BOUNDED_MIN per joint (the labels' g_1 = 0.3 sits below it), K_p, K_d
    symmetric above the stable floors, and g left free above its floor (joints 2-6 keep g ~ 1)."""
    from models.lmpc.structured.model import StructuredEmulator

    robot, s, y = _synthetic()
    n = s.shape[1] // 6  # s = (q, e, qd, e_dot, qdd_d, tau_fb)
    g_true = np.ones(n)
    g_true[0] = 0.3
    y = y / np.where(np.arange(n) == 0, 0.7, 1.0) * g_true  # the labels' g_1: 0.7 -> 0.3
    config = StructuredConfig(
        hidden=(8,), c_fixed=-1.0, physics_steps=150, residual_epochs=1, physics_learning_rate=0.05
    )
    _, summary = train_structured(robot, s, y, replace(config, physics_fit="bounded"), log=lambda _: None)
    physics = summary["physics"]
    g, kp, kd = (np.asarray(physics[k], float) for k in ("g", "kp_1_s2", "kd_1_s"))
    assert physics["fit"] == "bounded" and physics["gains_projected"] is True
    assert g.min() >= StructuredEmulator.G_BOUNDED_MIN - 1e-12
    assert g[0] == pytest.approx(StructuredEmulator.G_BOUNDED_MIN)  # held at its floor, not at the label's 0.3
    assert np.all(np.abs(g[1:] - 1.0) < 0.2)  # free above the floor: not the stable fit's g = 1 by fiat
    np.testing.assert_allclose(kp, kp.T, atol=1e-9)
    np.testing.assert_allclose(kd, kd.T, atol=1e-9)
    assert np.linalg.eigvalsh(kp).min() >= STABLE_KP_MIN_1_S2 * (1 - 1e-9)
    assert np.linalg.eigvalsh(kd).min() >= STABLE_KD_MIN_1_S * (1 - 1e-9)
    assert physics["loop_decay_rate_1_s"] is not None
    # the reported decay is the loop with this g (M0^-1 G M0), the same as the benchmarks' one-pose loop
    assert physics["loop_decay_rate_1_s"] == pytest.approx(-_largest_real_part(kp, kd, g), rel=1e-6, abs=1e-9)


def test_unknown_physics_fit_is_refused() -> None:
    with pytest.raises(ModelInputError, match="physics_fit"):
        StructuredConfig(physics_fit="psd")


def test_the_pipeline_refuses_an_unknown_physics_fit_in_one_line(tmp_path: Path) -> None:
    import subprocess
    import sys

    result = subprocess.run(
        [sys.executable, "-m", "hil_runtime.cli", "pipeline", "--physics-fit", "stiff", "--work", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2 and "--physics-fit" in result.stderr and "stiff" in result.stderr
    assert "Traceback" not in result.stderr and not any(tmp_path.iterdir())
