"""The LMPC's torque-rate limit in the simulator (models.lmpc.controller + models.sim's commit) is the
runtime's (hil_runtime.controller): same clamp, same previous torque, same law state (docs/lmpc.md
section 10)."""

from __future__ import annotations

import subprocess
import sys
from dataclasses import replace

import numpy as np
import pytest

from hil_runtime.bundle import PolicyBundle
from hil_runtime.controller import Controller
from hil_runtime.rate_limit import max_torque_step_nm
from models.conditions import Condition, load_conditions
from models.effort import deployable, effort_metrics
from models.errors import ModelInputError
from models.feedback import make_law
from models.lmpc.controller import bundle_path, make_lmpc_controller
from models.robots import load_robot
from models.sim import SimConfig, simulate


def _c1_through_the_impulse() -> Condition:
    return replace(load_conditions()[0], duration_s=2.06)  # the impulse at 2 s, and 60 ms after it


def test_the_simulated_lmpc_is_limited_and_the_runtime_commands_the_same_torques() -> None:
    robot = load_robot("ur5_paper")
    law = make_law("adrc", robot, 1e-3)  # ADRC: its state keeps the applied torque, a second check
    condition = _c1_through_the_impulse()
    bound = max_torque_step_nm(robot.torque_rate_nm_s, 1e-3)
    free = simulate(robot, make_lmpc_controller(law, robot), [condition], SimConfig())
    assert np.abs(np.diff(free.tau[0], axis=0)).max() > 2 * bound.max()  # the step after the impulse
    lmpc = make_lmpc_controller(law, robot, torque_rate_limit="libfranka")
    traj = simulate(robot, lmpc, [condition], SimConfig())
    tau = traj.tau[0]
    steps = np.abs(np.diff(np.vstack([np.zeros(robot.n_joints), tau]), axis=0))  # from the held zero
    assert (steps <= bound * (1 + 1e-9)).all()
    assert traj.within_limits.all()
    effort = effort_metrics(tau, traj.qd[0], robot.torque_limit_nm, 1e-3)
    verdict = deployable(
        {"effort": effort, "finite": True, "within_limits": True},
        None,
        robot.torque_limit_nm,
        1e-3,
        robot.torque_rate_nm_s,
    )
    assert not any("torque rate" in r for r in verdict["reasons"]), verdict

    # The runtime's policy stage on the simulator's measurements, committing what the simulator commanded
    bundle = PolicyBundle.load(bundle_path(robot.name, "adrc"))
    runtime = Controller(bundle, "lmpc", "libfranka")
    runtime.reset(traj.q[0, 0], np.zeros(robot.n_joints))
    for k in range(tau.shape[0]):
        candidate, _, _ = runtime.step(
            traj.q[0, k], traj.qd[0, k], traj.q_ref[0, k], traj.qd_ref[0, k], condition.reference(k * 1e-3)[2]
        )
        np.testing.assert_allclose(candidate, tau[k], rtol=0, atol=1e-9, err_msg=f"cycle {k}")
        runtime.commit(tau[k])


def test_no_limit_by_default_and_unknown_names_refused() -> None:
    robot = load_robot("ur5_paper")
    law = make_law("pd", robot, 1e-3)
    assert make_lmpc_controller(law, robot).rate_limiter is None
    with pytest.raises(ModelInputError, match="--torque-rate-limit: unknown 'franka'"):
        make_lmpc_controller(law, robot, torque_rate_limit="franka")


def test_the_experiment_refuses_an_unknown_limit_in_one_line() -> None:
    result = subprocess.run(
        [sys.executable, "-m", "hil_runtime.cli", "experiment", "--torque-rate-limit", "franka"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2 and "--torque-rate-limit: unknown 'franka'" in result.stderr
    assert "Traceback" not in result.stderr and len(result.stderr.strip().splitlines()) == 1
