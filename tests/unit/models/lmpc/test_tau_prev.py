"""The rate-aware structured LMPC (docs/lmpc.md section 11): a bundle whose graph reads tau_prev, the torque
commanded last period, and steps from it within the rate bound. The graph, its contract (the optional
input slot, the loader's checks), the simulator's and the runtime's policy stage feeding it the same torque."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from hil_runtime.bundle import BundleError, PolicyBundle
from hil_runtime.controller import Controller
from hil_runtime.rate_limit import max_torque_step_nm
from models.conditions import load_conditions
from models.feedback import make_law
from models.lmpc.controller import bundle_path, make_lmpc_controller
from models.robots import load_robot
from models.sim import SimConfig, simulate

ROBOT = load_robot("ur5_paper")
N = ROBOT.n_joints
LIMIT = np.asarray(ROBOT.torque_limit_nm, float)
STEP = max_torque_step_nm(ROBOT.torque_rate_nm_s, 1e-3)
BETA = np.linspace(0.2, 0.9, N)


def _export(root: Path, law_name: str) -> Path:
    """A small rate-aware structured bundle (fixed coefficients, no fit): Kp = 3e3, Kd = 30 on the diagonal,
    the law's torque removed (c = -1), a residual MLP, the trust box +-1 on every feature."""
    from models.lmpc.structured import StructuredConfig, StructuredEmulator, export_trained

    config = StructuredConfig(laws=(law_name,), previous_torque=True, c_fixed=-1.0)
    torch.manual_seed(3)
    model = StructuredEmulator(ROBOT, (8,), 0.02 * LIMIT, "measured", 0.0, True, 1e-3)
    with torch.no_grad():
        model.c.fill_(-1.0)
        model.g.fill_(1.0)
        model.beta.copy_(torch.as_tensor(BETA))
        model.theta_kp.copy_(torch.eye(N) * 0.3)
        model.theta_kd.copy_(torch.eye(N) * 0.3)
        model.net[-1].weight.normal_(0.0, 0.1)
    model.freeze()
    low, high = -np.full(6 * N, 1.0), np.full(6 * N, 1.0)
    low[5 * N :], high[5 * N :] = -LIMIT, LIMIT
    summary = {"physics": {"relative_loss": 0.0}, "residual": {"val_relative_loss": 0.0}}
    out = root / ROBOT.name / law_name
    export_trained(out, law_name, ROBOT, model.eval(), (low, high), 0.05 * LIMIT, config, summary)
    return out


@pytest.fixture(scope="module")
def bundles(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("tau_prev")
    for law_name in ("pd", "adrc"):  # ADRC: its state keeps the applied torque too
        _export(root, law_name)
    return root


def test_the_manifest_declares_tau_prev_and_old_bundles_read_as_before(bundles: Path) -> None:
    bundle = PolicyBundle.load(bundles / "ur5_paper" / "pd", expected_joints=N, expected_period_s=1e-3)
    layout = bundle.manifest.graph.input.layout
    assert (layout[-1].name, layout[-1].size) == ("tau_prev", N)
    assert bundle.takes_previous_torque and bundle.input_width == 6 * N + bundle.state_size
    assert bundle.saturation_checked.all()  # the ramp to the plateau, at the rate bound
    shipped = PolicyBundle.load(bundle_path("ur5_paper", "pd"))
    assert not shipped.takes_previous_torque and shipped.previous_torque_nm is None
    assert shipped.input_width == 5 * N + shipped.state_size


def test_the_graph_steps_from_tau_prev_within_the_bound_and_hands_over_at_it(bundles: Path) -> None:
    bundle = PolicyBundle.load(bundles / "ur5_paper" / "pd")
    rng = np.random.default_rng(5)
    rows = 300
    q = rng.uniform(-0.5, 0.5, (rows, N))
    scale = np.repeat([0.01, 0.3, 3.0], rows // 3)[:, None]  # inside the box, in the fade-out, outside
    q_d = q + rng.normal(0, 1, (rows, N)) * scale
    qd, qd_d, qdd_d = (rng.normal(0, 0.3, (rows, N)) for _ in range(3))
    previous = rng.uniform(-0.2, 0.2, (rows, N)) * LIMIT
    state = np.zeros((rows, 0))
    tau, tau_fb, _ = bundle.step_batch(q, qd, q_d, qd_d, qdd_d, state, previous)
    fallback = bundle.last_trust_batch[:, 0]
    assert (np.abs(tau - previous) <= STEP * (1 + 1e-9)).all()
    assert (np.abs(tau - previous) >= STEP * (1 - 1e-9)).any()  # the bound acts in the graph
    law = fallback == 1.0  # handed over: the law's torque, reached at the rate bound
    assert law.any() and (fallback == 0.0).any()
    expected = np.clip(previous + np.clip(tau_fb - previous, -STEP, STEP), -LIMIT, LIMIT)
    np.testing.assert_allclose(tau[law], expected[law], rtol=0, atol=1e-9)
    # inside the box, a small gap: beta of it (the target from a row whose tau_prev is the target itself)
    inside = np.flatnonzero(fallback == 0.0)[:20]
    rows_in = (q[inside], qd[inside], q_d[inside], qd_d[inside], qdd_d[inside], state[inside])
    rest = tau[inside].copy()
    for _ in range(400):  # tau fed back: it settles at the target
        rest = bundle.step_batch(*rows_in, rest)[0]
    moved = rest + 0.1 * STEP  # 0.1 step away from the target: the graph steps back by beta of it
    back = bundle.step_batch(*rows_in, moved)[0]
    np.testing.assert_allclose(back - moved, np.broadcast_to(-BETA * 0.1 * STEP, moved.shape), rtol=1e-6, atol=1e-9)
    with pytest.raises(ValueError, match="previous_torque_nm"):
        bundle.step_batch(q, qd, q_d, qd_d, qdd_d, state)


def test_step_reads_the_previous_torque_the_caller_keeps(bundles: Path) -> None:
    bundle = PolicyBundle.load(bundles / "ur5_paper" / "pd")
    assert bundle.previous_torque_nm is not None
    q, zero = np.full(N, 0.2), np.zeros(N)
    first = bundle.step(q, zero, q, zero, zero, np.zeros(0))[0].copy()
    np.testing.assert_allclose(np.abs(first), np.minimum(np.abs(first), STEP))  # from zero: one step at most
    bundle.previous_torque_nm[:] = first
    second = bundle.step(q, zero, q, zero, zero, np.zeros(0))[0]
    assert np.abs(second - first).max() <= STEP.max() * (1 + 1e-9) and not np.allclose(second, first)


def test_the_loader_refuses_a_graph_that_steps_beyond_the_declared_rate(bundles: Path, tmp_path: Path) -> None:
    copy = tmp_path / "pd"
    shutil.copytree(bundles / "ur5_paper" / "pd", copy)
    manifest = json.loads((copy / "manifest.json").read_text())
    manifest["limits"]["torque_rate_nm_s"] = [r / 2 for r in manifest["limits"]["torque_rate_nm_s"]]
    (copy / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(BundleError) as info:
        PolicyBundle.load(copy)
    assert "limits.torque_rate_nm_s" in str(info.value) and "\n" not in str(info.value)
    manifest["limits"].pop("torque_rate_nm_s")
    (copy / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(BundleError, match="torque_rate_nm_s: required by a graph that reads tau_prev"):
        PolicyBundle.load(copy)


def test_the_simulated_lmpc_and_the_runtime_feed_the_same_tau_prev(bundles: Path) -> None:
    """The simulator's LMPC (commit: the saturated command) and the runtime's Controller (commit: what the
    supervisor sent; reset: the held set-point) give the same torque every cycle, through C1's impulse."""
    law = make_law("adrc", ROBOT, 1e-3)
    condition = replace(load_conditions()[0], duration_s=2.06)
    lmpc = make_lmpc_controller(law, ROBOT, bundle_dir=bundles)
    assert lmpc.bundle.takes_previous_torque
    traj = simulate(ROBOT, lmpc, [condition], SimConfig())
    tau = traj.tau[0]
    steps = np.abs(np.diff(np.vstack([np.zeros(N), tau]), axis=0))  # from the zero held at the start
    assert (steps <= STEP * (1 + 1e-9)).all() and traj.within_limits.all()
    runtime = Controller(PolicyBundle.load(bundles / "ur5_paper" / "adrc"), "lmpc")
    runtime.reset(traj.q[0, 0], np.zeros(N))
    for k in range(tau.shape[0]):
        candidate, _, _ = runtime.step(
            traj.q[0, k], traj.qd[0, k], traj.q_ref[0, k], traj.qd_ref[0, k], condition.reference(k * 1e-3)[2]
        )
        np.testing.assert_allclose(candidate, tau[k], rtol=0, atol=1e-9, err_msg=f"cycle {k}")
        runtime.commit(tau[k])
    # activation from a held set-point: the first command is within one step of it, not of zero
    held = np.full(N, 3.0)
    runtime.reset(traj.q[0, 0], held)
    first, _, _ = runtime.step(traj.q[0, 0], traj.qd[0, 0], traj.q_ref[0, 0], traj.qd_ref[0, 0], np.zeros(N))
    assert (np.abs(first - held) <= STEP * (1 + 1e-9)).all()


def test_the_runtime_commands_every_step_within_the_bound_without_a_limiter(bundles: Path) -> None:
    from hil_runtime.runtime import Runtime
    from tests.unit.hil_runtime.support import c1_on_model

    config, bus = c1_on_model("none", ramp_s=0.2, bundle={"path": str(bundles / "ur5_paper" / "pd"), "mode": "lmpc"})
    rt = Runtime(config, bus, record_cycles=401)
    rt.configure()
    assert rt.activate()
    result = rt.run(max_cycles=400)
    rt.shutdown()
    assert result.reason == "cycles", result
    assert rt.controller.rate_limiter is None  # the bound is the graph's own
    tau = np.asarray(rt.record.arrays()["tau"])
    steps = np.abs(np.diff(np.vstack([np.zeros(N), tau]), axis=0))  # row 0 against enable's zero set-point
    assert (steps <= STEP * (1 + 1e-9)).all(), steps.max(axis=0)


def test_the_pipeline_refuses_a_beta_floor_outside_0_1_in_one_line(tmp_path: Path) -> None:
    import subprocess
    import sys

    result = subprocess.run(
        [sys.executable, "-m", "hil_runtime.cli", "pipeline", "--tau-prev", "--beta-floor", "0"]
        + ["--work", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2 and "--beta-floor: must be in (0, 1], got 0.0" in result.stderr
    assert "Traceback" not in result.stderr and not any(tmp_path.iterdir())


def test_the_rate_check_slows_the_static_gains_until_the_bounded_loop_holds(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """models.lmpc.structured.run.rate_feasible_bandwidth: the scale whose closed loop holds the most check
    conditions, the largest among equals, stopping at the first that holds them all (here full bandwidth
    holds none, 0.7x one, 0.5x both), the frozen gains scaled as K_p s^2, K_d s, every try recorded; the
    check runs the exported bundle, not the torch model. When no scale holds more, the fitted gains stay."""
    from types import SimpleNamespace

    import models.sim
    from models.lmpc.structured import StructuredConfig, StructuredEmulator
    from models.lmpc.structured.run import rate_feasible_bandwidth

    config = StructuredConfig(laws=("pd",), previous_torque=True, c_fixed=-1.0)
    model = StructuredEmulator(ROBOT, (8,), 0.02 * LIMIT, "measured", 0.0, True, 1e-3)
    with torch.no_grad():
        model.c.fill_(-1.0)
        model.g.fill_(1.0)
        model.theta_kp.copy_(torch.eye(N) * 0.3)
        model.theta_kd.copy_(torch.eye(N) * 0.3)
    model.freeze()
    kp0, kd0 = (t.clone() for t in model.frozen[2:])
    low, high = -np.full(6 * N, 1.0), np.full(6 * N, 1.0)
    low[5 * N :], high[5 * N :] = -LIMIT, LIMIT
    summary = {"physics": {"relative_loss": 0.0}, "residual": {"val_relative_loss": 0.0}}
    seen: list[int] = []

    def fake_simulate(robot: object, controller: Any, conditions: object, config: object = None, **_: object) -> Any:
        assert controller.bundle.takes_previous_torque  # the exported rate-aware bundle is what runs
        seen.append(1)
        holds = len(seen) in (4, 5, 6)  # 1.0 leaves on both conditions, 0.7 holds on its second, 0.5 on both
        return SimpleNamespace(tau=np.zeros((1, 10, N)), within_limits=np.array([holds]))

    monkeypatch.setattr(models.sim, "simulate", fake_simulate)
    conditions = load_conditions()[:2]
    result = rate_feasible_bandwidth(model, "pd", ROBOT, config, conditions, (low, high), 0.05 * LIMIT, summary)
    assert result["bandwidth_scale"] == 0.5 and result["bandwidth_feasible"] is True
    assert result["bandwidth_checked"] == [
        {"scale": 1.0, "inside": 0},
        {"scale": 0.7, "inside": 1},
        {"scale": 0.5, "inside": 2},
    ]
    np.testing.assert_allclose(model.frozen[2].numpy(), kp0.numpy() * 0.25)
    np.testing.assert_allclose(model.frozen[3].numpy(), kd0.numpy() * 0.5)
    # no scale holds more than the fitted gains: they stay (the Panda: one training condition left at every scale)
    calls: list[int] = []

    def one_of_two(*_: object, **__: object) -> Any:  # every scale holds the first condition, leaves the second
        calls.append(1)
        return SimpleNamespace(tau=np.zeros((1, 10, N)), within_limits=np.array([len(calls) % 2 == 1]))

    monkeypatch.setattr(models.sim, "simulate", one_of_two)
    model.freeze()
    model.frozen = (model.frozen[0], model.frozen[1], kp0, kd0)
    result = rate_feasible_bandwidth(model, "pd", ROBOT, config, conditions, (low, high), 0.05 * LIMIT, summary)
    assert result["bandwidth_scale"] == 1.0 and result["bandwidth_feasible"] is False
    assert len(result["bandwidth_checked"]) == 5
    np.testing.assert_allclose(model.frozen[2].numpy(), kp0.numpy())
