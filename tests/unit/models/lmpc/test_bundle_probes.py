"""The writer's probes exercise the residual clamp whatever its size (issue 13): a bundle exported with
the old (3x) or the shipped (10x) residual-bound scale, or a far larger one, still has its manifest's
bound checked against the graph by the loader; and a bundle re-exported from the trained file
(models.lmpc.reexport) is the same graph."""

from __future__ import annotations

import dataclasses
import json
import shutil
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from hil_runtime.bundle import BundleError, PolicyBundle  # noqa: E402
from hil_runtime.bundle_schema import Probes, TrustRegion  # noqa: E402
from models.errors import ModelInputError  # noqa: E402
from models.lmpc.structured import (  # noqa: E402
    StructuredConfig,
    StructuredEmulator,
    export_trained,
    reexport,
    save_trained,
    trust_box,
)
from models.robots import load_robot  # noqa: E402

ROBOT = load_robot("ur5_paper")
#: max |tau* - tau_fb| per joint of the shipped PD bundle's labels (N m)
LABEL_MAX_NM = np.array([14.52, 24.14, 13.35, 4.352, 0.8674, 0.01152])
FIT = {"physics": {"relative_loss": 0.0}, "residual": {"val_relative_loss": 0.0}}  # what the manifest quotes


def _probes(bundle: PolicyBundle) -> Probes:
    assert bundle.manifest.probes is not None
    return bundle.manifest.probes


def _trust(bundle: PolicyBundle) -> TrustRegion:
    assert bundle.manifest.trust_region is not None
    return bundle.manifest.trust_region


def _emulator() -> StructuredEmulator:
    """The structure with the absolute-cost HMPC's coefficients (c = -1, g = 1, deadbeat-like gains)."""
    n = ROBOT.n_joints
    model = StructuredEmulator(ROBOT, (8,), 0.02 * np.asarray(ROBOT.torque_limit_nm, float))
    with torch.no_grad():
        model.c.fill_(-1.0)
        model.g.fill_(1.0)
        model.theta_kp.copy_(torch.eye(n, dtype=torch.float64) * 9e4 / model.KP_SCALE)
        model.theta_kd.copy_(torch.eye(n, dtype=torch.float64) * 900.0 / model.KD_SCALE)
        model.net[-1].weight.normal_(0.0, 1.0)  # a residual MLP that is not zero
    model.freeze()
    return model.eval()


def _export(path: Path, scale: float) -> tuple[StructuredEmulator, StructuredConfig, tuple[np.ndarray, np.ndarray]]:
    config = StructuredConfig(laws=("pd",), hidden=(8,), bound_scale=scale)
    model = _emulator()
    box = trust_box(np.zeros((1, 6 * ROBOT.n_joints)), ROBOT, config)
    export_trained(path, "pd", ROBOT, model, box, LABEL_MAX_NM, config, FIT)
    return model, config, box


def _tampered(src: Path, dst: Path, factor: np.ndarray) -> Path:
    shutil.copytree(src, dst)
    manifest = json.loads((dst / "manifest.json").read_text())
    bound = np.asarray(manifest["trust_region"]["residual_bound_nm"], float)
    manifest["trust_region"]["residual_bound_nm"] = (bound * factor).tolist()
    (dst / "manifest.json").write_text(json.dumps(manifest))
    return dst


@pytest.mark.parametrize("scale", [3.0, 10.0, 100.0])
def test_a_changed_residual_bound_is_refused_whatever_the_bound(tmp_path: Path, scale: float) -> None:
    _export(tmp_path / "pd", scale)
    bundle = PolicyBundle.load(tmp_path / "pd")  # the honest bundle passes every check
    n = bundle.n_joints
    outputs = np.asarray(_probes(bundle).outputs)
    alpha, clamped = 1.0 - outputs[:, -2], outputs[:, -1]
    assert (clamped[alpha > 0] >= 1).any() and ((alpha == 1.0) & (clamped == 0)).any()  # clamp and inside
    if scale >= 10:  # the bound exceeds the first joints' torque limits: their clamp shows only at alpha < 1
        assert np.any(np.asarray(_trust(bundle).residual_bound_nm) > bundle.torque_limit_nm)
    for k, factor in enumerate((10.0, 1.1, 0.1, 0.9)):
        with pytest.raises(BundleError, match="residual_bound_nm") as info:
            PolicyBundle.load(_tampered(tmp_path / "pd", tmp_path / f"all{k}", np.full(n, factor)))
        assert info.value.exit_code == 2 and "\n" not in str(info.value)
    for j in range(n):  # one joint's bound changed, up or down: its own clamp row shows it
        for sign, factor in enumerate((1.01, 0.99)):
            one = np.ones(n)
            one[j] = factor
            with pytest.raises(BundleError, match="residual_bound_nm"):
                PolicyBundle.load(_tampered(tmp_path / "pd", tmp_path / f"j{j}{sign}", one))


def test_reexport_from_the_trained_file_gives_the_same_graph(tmp_path: Path) -> None:
    model, config, box = _export(tmp_path / "first" / "ur5_paper" / "pd", 10.0)
    save_trained(tmp_path / "work" / "trained_pd.pt", model, config, FIT, box, LABEL_MAX_NM)
    reexport(tmp_path / "work", tmp_path / "again", log=lambda _: None)
    first = PolicyBundle.load(tmp_path / "first" / "ur5_paper" / "pd")
    again = PolicyBundle.load(tmp_path / "again" / "ur5_paper" / "pd")
    x = np.asarray(_probes(first).inputs)
    np.testing.assert_array_equal(again.run_rows(x), first.run_rows(x))
    assert again.manifest.trust_region == first.manifest.trust_region
    reexport(tmp_path / "work", tmp_path / "wider", bound_scale=20.0, log=lambda _: None)
    wider = PolicyBundle.load(tmp_path / "wider" / "ur5_paper" / "pd")
    np.testing.assert_allclose(
        np.asarray(_trust(wider).residual_bound_nm, float) - 1e-3, 20.0 * LABEL_MAX_NM, rtol=1e-12
    )


def test_reexport_refuses_a_work_directory_without_trained_files(tmp_path: Path) -> None:
    from models.lmpc.reexport import main

    assert main(["--work", str(tmp_path), "--bundles", str(tmp_path / "b")]) == 2
    (tmp_path / "trained_pd.pt").write_bytes(b"not a torch file")
    with pytest.raises(ModelInputError, match=r"trained_pd.pt: unreadable"):
        reexport(tmp_path, tmp_path / "b", log=lambda _: None)
    assert main(["--work", str(tmp_path), "--residual-bound-scale", "0"]) == 2


def test_a_graph_more_sensitive_to_position_error_than_its_manifest_is_refused(tmp_path: Path) -> None:
    """Issue 24: the writer records what 1 mrad of position error does to the torque (N m per mrad, per
    joint); the loader measures it again on the probe rows and refuses a graph above the recorded bound."""
    _export(tmp_path / "pd", 10.0)
    bundle = PolicyBundle.load(tmp_path / "pd")
    recorded = np.asarray(_probes(bundle).position_sensitivity_nm_per_mrad, float)
    # the deadbeat-like gains (K_p = 9e4 1/s^2) turn 1 mrad into ~M_ii K_p 1e-3: tens of N m on the shoulder
    assert recorded.shape == (ROBOT.n_joints,) and recorded[1] > 10.0
    shutil.copytree(tmp_path / "pd", tmp_path / "tight")
    manifest = json.loads((tmp_path / "tight" / "manifest.json").read_text())
    manifest["probes"]["position_sensitivity_nm_per_mrad"] = (recorded * 0.5).tolist()
    (tmp_path / "tight" / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(BundleError, match=r"position_sensitivity_nm_per_mrad: the graph turns 1 mrad .* on joint"):
        PolicyBundle.load(tmp_path / "tight")
    manifest["probes"]["position_sensitivity_nm_per_mrad"] = [1.0, 2.0]
    (tmp_path / "tight" / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(BundleError, match=r"position_sensitivity_nm_per_mrad: needs 6 finite values"):
        PolicyBundle.load(tmp_path / "tight")


def test_the_sensing_gate_predicts_the_chatter_the_simulator_measures() -> None:
    """hil_runtime.bundle_probes.noise_step_nm is what the runtime refuses a bundle by: on the shipped PD
    bundle under the issue's noise target (3e-4 rad, 0.2 rad/s measured velocity) its prediction for the
    shoulder must match the RMS cycle-to-cycle torque change of a simulated run to within -25 % / +50 %, and the
    bundle must be refused there while it is accepted at a 19-bit encoder's noise. (The estimate is open-loop:
    the closed loop adds ~20 % here, 8.3 N m estimated, 10.1 measured.)"""
    from hil_runtime.bundle_probes import noise_step_nm, position_sensitivity, velocity_sensitivity
    from models.conditions import load_conditions
    from models.feedback import make_law
    from models.lmpc import make_lmpc_controller
    from models.sim import SimConfig, simulate
    from sim_target.realism_profiles import bind_profile, parse_profile

    robot, sim = load_robot("ur5_paper"), SimConfig()
    bundle = PolicyBundle.load(Path("models/bundles/ur5_paper/pd"))
    sensing = {"encoder_noise_rad": 3e-4, "velocity": "true", "velocity_noise_rad_s": 0.2}
    profile = parse_profile({"seed": 3, "sensing": sensing}, "noise")
    realism = bind_profile(profile, "noise", 6, sim.period_s, sim.period_s / 2, robot.torque_limit_nm)
    assert realism.measurement_noise() == (3e-4, 0.2)
    condition = load_conditions()[0]
    short = dataclasses.replace(condition, duration_s=0.4)
    controller = make_lmpc_controller(make_law("pd", robot, sim.period_s), robot)
    traj = simulate(robot, controller, [short], sim, realism=realism)
    assert traj.within_limits.all()
    measured = float(np.sqrt(np.mean(np.diff(traj.tau[0, 50:, 1]) ** 2)))
    x = np.asarray(bundle.manifest.probes.inputs, float)  # type: ignore[union-attr]  # shipped: has probes
    predicted = noise_step_nm(
        position_sensitivity(bundle.manifest, bundle.run_rows, x),
        velocity_sensitivity(bundle.manifest, bundle.run_rows, x),
        3e-4,
        0.2,
    )[1]
    print(f"shoulder: predicted {predicted:.2f} N m, measured {measured:.2f} N m")
    assert 0.75 * predicted <= measured <= 1.5 * predicted, (measured, predicted)
    with pytest.raises(BundleError, match="on joint 2"):
        bundle.check_sensing(3e-4, 0.2)
    assert bundle.check_sensing(1e-5).max() < 1.17
    # behind the runtime's 50 Hz velocity filter (hil_runtime.velocity_filter), the simulator's LMPC alike
    filtered = make_lmpc_controller(make_law("pd", robot, sim.period_s), robot, velocity_filter_hz=50.0)
    traj = simulate(robot, filtered, [short], sim, realism=realism)
    measured_50 = float(np.sqrt(np.mean(np.diff(traj.tau[0, 50:, 1]) ** 2)))
    with pytest.raises(BundleError, match="filtered at 50 Hz") as info:
        bundle.check_sensing(3e-4, 0.2, 50.0)
    predicted_50 = float(str(info.value).split("torque steps of ")[1].split(" ")[0])
    print(f"shoulder behind 50 Hz: predicted {predicted_50:.2f} N m, measured {measured_50:.2f} N m")
    assert 0.6 * predicted_50 <= measured_50 <= 1.5 * predicted_50 and measured_50 < 0.4 * measured


def test_the_sensing_gate_measures_on_rows_of_its_own() -> None:
    """A manifest whose probe rows sit where the graph is insensitive (every torque saturated) does not hide
    the emulator's gain from the gate: it measures on its own seeded rows too."""
    from hil_runtime.bundle_probes import GraphCheckError, check_sensing, saturation_probe_inputs

    bundle = PolicyBundle.load(Path("models/bundles/ur5_paper/pd"))
    saturated = saturation_probe_inputs(bundle.manifest)
    assert np.allclose(np.abs(bundle.run_rows(saturated)[:, :6]), bundle.torque_limit_nm)  # insensitive rows
    probes = bundle.manifest.probes.model_copy(update={"inputs": saturated.tolist()})  # type: ignore[union-attr]
    hiding = bundle.manifest.model_copy(update={"probes": probes})
    with pytest.raises(GraphCheckError, match="on joint 2"):
        check_sensing(hiding, bundle.run_rows, Path("m.json"), 3e-4, 0.2)
