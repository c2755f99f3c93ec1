"""HMPC torque-cost formulations: absolute (W2 on tau) and anchored (W2 on tau - w* tau_fb)."""

from __future__ import annotations

import numpy as np
import pytest

from models.errors import ModelInputError
from models.feedback import make_law
from models.hmpc import HMPCConfig, HMPCSolver
from models.robots import load_robot


@pytest.fixture(scope="module")
def robot():  # type: ignore[no-untyped-def]
    return load_robot("ur5_paper")


def states(batch: int, seed: int = 0) -> tuple[np.ndarray, ...]:
    rng = np.random.default_rng(seed)
    q_d = rng.uniform(-1.0, 1.0, (batch, 6))
    qd_d = rng.uniform(-0.3, 0.3, (batch, 6))
    qdd_d = rng.uniform(-0.2, 0.2, (batch, 6))
    return q_d + rng.normal(0.0, 0.01, (batch, 6)), qd_d + rng.normal(0.0, 0.05, (batch, 6)), q_d, qd_d, qdd_d


def test_anchored_weights_scale_with_inverse_inertia_squared(robot) -> None:  # type: ignore[no-untyped-def]
    law = make_law("pd", robot, 1e-3, "stabilized")
    solver = HMPCSolver(law, robot, HMPCConfig(torque_cost="anchored", anchor_weight_scale=10.0))
    inertia = np.array([0.048, 0.383, 0.124, 0.0168, 0.0024, 0.000125])  # M_ii(0), docs/hmpc.md
    np.testing.assert_allclose(solver.anchor_weight * inertia**2 / (10.0 * 1e-6), 1.0, rtol=0.05)
    coarse = HMPCSolver(law, robot, HMPCConfig(torque_cost="anchored", prediction_step_s=0.01))  # prediction step 10 ms
    np.testing.assert_allclose(coarse.anchor_weight / solver.anchor_weight, 100.0)


def test_anchored_compiled_equals_numpy_and_reports_w_star(robot) -> None:  # type: ignore[no-untyped-def]
    law = make_law("pd", robot, 1e-3, "stabilized")
    results = [
        HMPCSolver(law, robot, HMPCConfig(torque_cost="anchored", kernels=k)).solve(*states(8))
        for k in ("numba", "numpy")
    ]
    np.testing.assert_allclose(results[0].tau_nm, results[1].tau_nm, atol=1e-6)
    assert np.all(np.isin(results[0].anchor_scale, HMPCConfig().candidate_scales))
    assert HMPCSolver(law, robot).solve(*states(2)).anchor_scale is None


def test_a_stiff_anchor_returns_the_anchor(robot) -> None:  # type: ignore[no-untyped-def]
    law = make_law("pd", robot, 1e-3, "stabilized")
    result = HMPCSolver(law, robot, HMPCConfig(torque_cost="anchored", anchor_weight_scale=1e9)).solve(*states(6))
    anchor = np.clip(result.anchor_scale[:, None] * result.tau_fb_nm, -robot.torque_limit_nm, robot.torque_limit_nm)
    np.testing.assert_allclose(result.tau_nm, anchor, atol=1e-3 * np.abs(anchor).max())


def test_the_law_matters_only_with_the_anchored_cost(robot) -> None:  # type: ignore[no-untyped-def]
    x = states(6, seed=3)
    taus = {}
    for cost in ("absolute", "anchored"):
        for name in ("pd", "smc"):
            taus[cost, name] = (
                HMPCSolver(make_law(name, robot, 1e-3, "stabilized"), robot, HMPCConfig(torque_cost=cost))
                .solve(*x)
                .tau_nm
            )
    spread = {cost: np.abs(taus[cost, "pd"] - taus[cost, "smc"]).max() for cost in ("absolute", "anchored")}
    assert spread["anchored"] > 100 * spread["absolute"]


@pytest.mark.parametrize(
    "options", [{"torque_cost": "relative"}, {"anchor_weight_scale": 0.0}, {"anchor_weight_scale": float("nan")}]
)
def test_bad_formulation_options_are_model_input_errors(options) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ModelInputError, match="hmpc config"):
        HMPCConfig(**options)
