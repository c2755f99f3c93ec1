"""The LMPC's output torque-rate limit (hil_runtime/rate_limit.py, docs/lmpc.md section 10): the one
bound, the clamp, and the runtime's policy stage applying it against the torque actually commanded."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.testing import FakeJointBus
from hil_runtime.config import RuntimeConfigError, parse_runtime_config
from hil_runtime.rate_limit import TorqueRateLimiter, max_torque_step_nm, torque_rate_limit_nm_s
from hil_runtime.runtime import Runtime
from sim_target.testing.ur5 import MAX_TORQUE_NM, Q0_RAD
from tests.unit.hil_runtime.support import c1_on_model, config_dict


def test_the_step_is_the_rate_times_the_period() -> None:
    np.testing.assert_allclose(max_torque_step_nm(np.array([1000.0, 500.0]), 1e-3), [1.0, 0.5])
    np.testing.assert_allclose(max_torque_step_nm(np.array([1000.0]), 2e-3), [2.0])


def test_the_rate_rules() -> None:
    limit = np.array([87.0, 102.0, 34.0])
    # "scaled" (ur5_paper's): libfranka's 1000 N·m/s per 87 N·m of the joint's limit
    np.testing.assert_allclose(torque_rate_limit_nm_s("scaled", limit), [1000.0, 1000 * 102 / 87, 1000 * 34 / 87])
    # a number: every joint, unscaled (libfranka's kMaxTorqueRate); None: the documented default, the same
    np.testing.assert_allclose(torque_rate_limit_nm_s(1000.0, limit), [1000.0] * 3)
    np.testing.assert_allclose(torque_rate_limit_nm_s(None, limit), [1000.0] * 3)
    np.testing.assert_allclose(torque_rate_limit_nm_s([500.0, 600.0, 700.0], limit), [500.0, 600.0, 700.0])
    for bad in ("fast", 0.0, -1.0, float("nan"), [1.0, 2.0], [1.0, 2.0, -3.0], {"a": 1}):
        with pytest.raises(ValueError, match="torque rate"):
            torque_rate_limit_nm_s(bad, limit)  # type: ignore[arg-type]  # the bad values are the test


def test_one_definition_serves_the_verdict_and_the_hmpc() -> None:
    import hil_runtime.rate_limit as rate_limit
    import models.effort as effort

    assert effort.max_torque_step_nm is rate_limit.max_torque_step_nm
    assert effort.FRANKA_MAX_TORQUE_RATE_NM_S is rate_limit.FRANKA_MAX_TORQUE_RATE_NM_S


def test_the_clamp_per_joint_from_the_held_torque() -> None:
    limiter = TorqueRateLimiter(np.array([1000.0, 1000.0, 2000.0]), 1e-3)
    limiter.reset(np.array([10.0, 0.0, 0.0]))
    out = limiter.limit(np.array([15.0, 0.5, -5.0]))
    np.testing.assert_allclose(out, [11.0, 0.5, -2.0])  # +1 clamped, 0.5 passes, -2 (2000 N·m/s joint) clamped
    assert limiter.limited_cycles == 1
    limiter.commit(np.array([11.0, 0.5, -2.0]))
    np.testing.assert_allclose(limiter.limit(np.array([11.5, 0.0, -2.0])), [11.5, 0.0, -2.0])
    assert limiter.limited_cycles == 1  # nothing clamped this time
    # what the supervisor commanded, not what the limiter proposed, is the next reference
    limiter.commit(np.array([0.0, 0.0, 0.0]))
    np.testing.assert_allclose(limiter.limit(np.array([11.5, 0.0, 0.0])), [1.0, 0.0, 0.0])
    limiter.reset(None)
    np.testing.assert_allclose(limiter.limit(np.array([-5.0, 5.0, 0.0])), [-1.0, 1.0, 0.0])


def test_a_batch_and_a_non_finite_torque() -> None:
    limiter = TorqueRateLimiter(np.array([1000.0, 1000.0]), 1e-3)
    limiter.reset(np.array([[0.0, 0.0], [5.0, 5.0]]), arms=2)
    out = limiter.limit(np.array([[3.0, 0.2], [5.0, np.nan]]))
    np.testing.assert_allclose(out[0], [1.0, 0.2])
    assert out[1, 0] == 5.0 and np.isnan(out[1, 1])  # NaN passes on: the supervisor substitutes the law's
    limiter.reset(np.array([np.nan, 1.0]))  # a held torque is finite: a NaN reading counts as zero
    np.testing.assert_allclose(limiter.limit(np.array([0.5, 1.5])), [0.5, 1.5])


def test_the_config_field_defaults_to_none_and_refuses_unknown_names() -> None:
    assert parse_runtime_config(config_dict(), "rt.yaml").bundle.torque_rate_limit == "none"
    data = config_dict()
    data["bundle"] = {**data["bundle"], "torque_rate_limit": "franka"}
    with pytest.raises(RuntimeConfigError) as info:
        parse_runtime_config(data, "rt.yaml")
    assert "rt.yaml" in str(info.value) and "torque_rate_limit" in str(info.value)
    assert "\n" not in str(info.value)


def _run(limit: str, cycles: int = 600) -> tuple[np.ndarray, Runtime]:
    config, bus = c1_on_model(limit, ramp_s=0.2)
    rt = Runtime(config, bus, record_cycles=cycles + 1)
    rt.configure()
    assert rt.activate()
    result = rt.run(max_cycles=cycles)
    rt.shutdown()
    assert result.reason == "cycles", result
    return np.asarray(rt.record.arrays()["tau"]), rt


def test_the_runtime_limits_every_commanded_step_from_the_held_zero() -> None:
    # the test bundle's manifest predates limits.torque_rate_nm_s: the "scaled" rule it was made under
    bound = max_torque_step_nm(torque_rate_limit_nm_s("scaled", np.asarray(MAX_TORQUE_NM, float)), 0.001) * (1 + 1e-9)
    tau_free, _ = _run("none")
    steps_free = np.abs(np.diff(np.vstack([np.zeros(6), tau_free]), axis=0))
    assert (steps_free > bound).any()  # the PD bundle's first command holds gravity at once
    tau, rt = _run("libfranka")
    steps = np.abs(np.diff(np.vstack([np.zeros(6), tau]), axis=0))  # row 0 against enable's zero set-point
    assert (steps <= bound).all(), steps.max(axis=0)
    assert rt.controller.rate_limiter is not None and rt.controller.rate_limiter.limited_cycles > 0


def test_fb_mode_is_never_limited() -> None:
    config = parse_runtime_config(config_dict(bundle={"mode": "fb", "torque_rate_limit": "libfranka"}), "rt.yaml")
    bus = FakeJointBus(6, period_s=0.001, max_torque_nm=MAX_TORQUE_NM, initial_position_rad=Q0_RAD)
    assert Runtime(config, bus).controller.rate_limiter is None
