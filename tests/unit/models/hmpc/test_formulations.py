"""HMPC torque-cost formulations: absolute (W2 on tau) and anchored (W2 on tau - w* tau_fb)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
import pytest

from models.errors import ModelInputError
from models.feedback import make_law
from models.hmpc import HMPCConfig, HMPCSolver
from models.robots import RobotModel

if TYPE_CHECKING:
    from tests.unit.models.hmpc.conftest import MakeStates


def test_anchored_weights_scale_with_inverse_inertia_squared(robot: RobotModel) -> None:
    law = make_law("pd", robot, 1e-3, "stabilized")
    solver = HMPCSolver(law, robot, HMPCConfig(torque_cost="anchored", anchor_weight_scale=10.0))
    inertia = np.array([0.048, 0.383, 0.124, 0.0168, 0.0024, 0.000125])  # M_ii(0), docs/hmpc.md
    np.testing.assert_allclose(solver.anchor_weight * inertia**2 / (10.0 * 1e-6), 1.0, rtol=0.05)
    coarse = HMPCSolver(law, robot, HMPCConfig(torque_cost="anchored", prediction_step_s=0.01))  # prediction step 10 ms
    assert coarse.anchor_weight is not None and solver.anchor_weight is not None  # anchored: weights exist
    np.testing.assert_allclose(coarse.anchor_weight / solver.anchor_weight, 100.0)


def test_anchored_compiled_equals_numpy_and_reports_w_star(make_states: MakeStates, robot: RobotModel) -> None:
    law = make_law("pd", robot, 1e-3, "stabilized")
    results = [
        HMPCSolver(law, robot, HMPCConfig(torque_cost="anchored", kernels=k)).solve(*make_states(8))
        for k in ("numba", "numpy")
    ]
    np.testing.assert_allclose(results[0].tau_nm, results[1].tau_nm, atol=1e-6)
    assert results[0].anchor_scale is not None
    assert np.all(np.isin(results[0].anchor_scale, HMPCConfig().candidate_scales))
    assert HMPCSolver(law, robot).solve(*make_states(2)).anchor_scale is None


def test_a_stiff_anchor_returns_the_anchor(make_states: MakeStates, robot: RobotModel) -> None:
    law = make_law("pd", robot, 1e-3, "stabilized")
    result = HMPCSolver(law, robot, HMPCConfig(torque_cost="anchored", anchor_weight_scale=1e9)).solve(*make_states(6))
    assert result.anchor_scale is not None
    anchor = np.clip(result.anchor_scale[:, None] * result.tau_fb_nm, -robot.torque_limit_nm, robot.torque_limit_nm)
    np.testing.assert_allclose(result.tau_nm, anchor, atol=1e-3 * np.abs(anchor).max())


def test_the_law_matters_only_with_the_anchored_cost(make_states: MakeStates, robot: RobotModel) -> None:
    x = make_states(6, seed=3)
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
def test_bad_formulation_options_are_model_input_errors(options: dict[str, Any]) -> None:
    with pytest.raises(ModelInputError, match="hmpc config"):
        HMPCConfig(**options)
