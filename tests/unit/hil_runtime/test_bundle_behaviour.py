"""The bundle's behavioural check (probes, saturation, residual bound), the shared schema, and a
shipped bundle's non-finite output under the supervisor's one rule (issue 9, item 5; issue 22,
item 5). Runs on the shipped bundles with the runtime's own dependencies only (no torch)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hil_runtime.bundle import (
    BundleError,
    PolicyBundle,
    sha256_file,
)
from hil_runtime.supervisor import FaultKind, SafetyLimits, Supervisor

SHIPPED = Path(__file__).resolve().parents[3] / "models" / "bundles" / "ur5_paper"
LAWS = ("pd", "pid", "adrc", "hinf", "smc", "mrac")


def _copy(tmp_path: Path, law: str) -> Path:
    path = tmp_path / law
    shutil.copytree(SHIPPED / law, path)
    return path


def _edit(path: Path, change: Callable[[dict[str, Any]], object]) -> None:
    manifest = json.loads((path / "manifest.json").read_text())
    change(manifest)
    (path / "manifest.json").write_text(json.dumps(manifest))


@pytest.mark.parametrize("law", LAWS)
def test_every_shipped_bundle_passes_its_behavioural_check(law: str) -> None:
    bundle = PolicyBundle.load(SHIPPED / law, expected_joints=6, expected_period_s=1e-3)
    assert bundle.saturation_checked.all()  # every joint's saturation was observed and matched
    # and every joint's residual clamp: some recorded probe puts that joint at its bound (the loader's
    # check of residual_bound_nm), whatever the bound's size (issue 13: 10x the labels' largest residual)
    assert bundle.manifest.probes is not None
    tau, tau_fb, _, trust = bundle.layout.split(np.asarray(bundle.manifest.probes.outputs))
    alpha, clamped = 1.0 - trust[:, 0], trust[:, 1]
    acting = (alpha > 0) & (clamped >= 1) & (np.abs(tau) < bundle.torque_limit_nm).all(axis=1)
    residual = np.abs(tau - tau_fb)[acting] / alpha[acting, None]
    bound = bundle.residual_bound_nm
    assert bound is not None
    assert np.isclose(residual, bound, rtol=1e-7).any(axis=0).all()


def test_a_graph_of_another_law_under_a_fixed_up_hash_is_refused(tmp_path: Path) -> None:
    path = _copy(tmp_path, "pd")
    shutil.copy(SHIPPED / "smc" / "policy.onnx", path / "policy.onnx")
    _edit(path, lambda m: m["files"].__setitem__("policy.onnx", sha256_file(path / "policy.onnx")))
    with pytest.raises(BundleError, match="does not reproduce the recorded probe outputs .*law 'pd'") as info:
        PolicyBundle.load(path)
    assert info.value.exit_code == 2 and "\n" not in str(info.value)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        (
            lambda m: m["limits"].__setitem__("torque_nm", [2 * t for t in m["limits"]["torque_nm"]]),
            r"limits.torque_nm\[0\] is 204 but the graph saturates at 102",
        ),
        (
            lambda m: m["limits"].__setitem__("torque_nm", [t / 2 for t in m["limits"]["torque_nm"]]),
            r"limits.torque_nm\[\d\] is \d+ but the graph gives",
        ),
        (
            lambda m: m["trust_region"].__setitem__(
                "residual_bound_nm", [b / 10 for b in m["trust_region"]["residual_bound_nm"]]
            ),
            r"trust_region.residual_bound_nm\[\d\] is .* but the graph passes a residual",
        ),
        (
            lambda m: m["trust_region"].__setitem__(
                "residual_bound_nm", [b * 10 for b in m["trust_region"]["residual_bound_nm"]]
            ),
            "residual_bound_nm does not match the graph's clamp",
        ),
        (lambda m: m.pop("probes"), "probes: missing"),
        (lambda m: m["probes"].__setitem__("atol", 1.0), r"probes.atol: Input should be less than or equal to 0.001"),
        (
            lambda m: m["probes"]["outputs"][0].__setitem__(0, m["probes"]["outputs"][0][0] + 1.0),
            "recorded probe outputs",
        ),
        (lambda m: m["law"].__setitem__("state_size", 3), "law.initial_state needs"),
        (
            lambda m: m["limits"].__setitem__("torque_nm", [float("nan")] * 6),
            r"limits.torque_nm.0: Input should be a finite number|unreadable JSON \(NaN is not JSON\)",
        ),
        (lambda m: m["robot"].__setitem__("urdf_sha256", "xyz"), "robot.urdf_sha256: String should match pattern"),
        (lambda m: m.__setitem__("colour", "red"), "colour: Extra inputs are not permitted"),
    ],
)
def test_a_manifest_that_does_not_describe_its_graph_is_refused(
    tmp_path: Path, change: Callable[[dict[str, Any]], object], message: str
) -> None:
    path = _copy(tmp_path, "pd")
    _edit(path, change)
    with pytest.raises(BundleError, match=message) as info:
        PolicyBundle.load(path)
    assert str(info.value).startswith(f"bundle {path}") and "\n" not in str(info.value)


def test_a_wrong_urdf_sha256_is_refused_when_the_caller_passes_it(tmp_path: Path) -> None:
    with pytest.raises(BundleError, match="urdf_sha256 .* differs from the robot's URDF"):
        PolicyBundle.load(SHIPPED / "pd", expected_urdf_sha256="0" * 64)


def test_a_directory_without_a_manifest_names_the_typed_path(tmp_path: Path) -> None:
    (tmp_path / "empty").mkdir()
    with pytest.raises(BundleError, match=r"^bundle .*empty: no manifest.json in this directory"):
        PolicyBundle.load(tmp_path / "empty")
    with pytest.raises(BundleError, match=r"^bundle .*nowhere: no such directory"):
        PolicyBundle.load(tmp_path / "nowhere")


def test_a_non_finite_output_is_never_commanded() -> None:
    bundle = PolicyBundle.load(SHIPPED / "pd")
    limits = np.asarray(bundle.manifest.limits.position_rad, float)
    velocity = np.asarray(bundle.manifest.limits.velocity_rad_s, float)
    supervisor = Supervisor(SafetyLimits(-limits, limits, velocity, bundle.torque_limit_nm))
    command = np.zeros(6)
    zeros = np.zeros(6)
    q_d = np.full(6, 0.1)

    def select(tau: np.ndarray, tau_fb: np.ndarray, state: np.ndarray) -> FaultKind | None:
        fault = supervisor.select_torque(tau, tau_fb, 0.0, command, state)
        return None if fault is None else fault.kind

    # qdd_d feeds only the emulator and the trust guard: the law's torque stays finite -> used instead
    tau, tau_fb, state = bundle.step(zeros, zeros, q_d, zeros, np.full(6, np.nan), np.zeros(0))
    assert not np.isfinite(tau).all() and select(tau, tau_fb, state) is None
    assert np.isfinite(command).all() and np.array_equal(
        command, np.clip(tau_fb, -bundle.torque_limit_nm, bundle.torque_limit_nm)
    )
    assert supervisor.law_substitutions == 1
    # a NaN position leaves nothing finite: FAULT policy_nonfinite, the caller stops the arm
    assert select(*bundle.step(np.full(6, np.nan), zeros, q_d, zeros, zeros, np.zeros(0))) is FaultKind.POLICY_NONFINITE
    tau, tau_fb, state = bundle.step(zeros, zeros, q_d, zeros, zeros, np.zeros(0))  # and it goes on
    assert select(tau, tau_fb, state) is None
    assert np.isfinite(command).all() and supervisor.law_substitutions == 1


def test_writer_and_loader_share_one_schema() -> None:
    code = (
        "import hil_runtime.bundle as b, hil_runtime.bundle_schema as s; import models.lmpc.bundle_export as w;"
        "assert b.Manifest is s.Manifest and w.Manifest is s.Manifest and w.SCHEMA == s.SCHEMA;"
        "assert b.SUPPORTED_SCHEMAS == s.SUPPORTED_SCHEMAS"
    )
    pytest.importorskip("torch")
    done = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-1000:]


def test_step_batch_falls_back_per_arm_and_keeps_a_diverged_arm_visible() -> None:
    bundle = PolicyBundle.load(SHIPPED / "pd")
    q = np.zeros((3, 6))
    q_d = np.full((3, 6), 0.1)
    qdd_d = np.zeros((3, 6))
    qdd_d[1] = np.nan  # arm 1: emulator input broken, law fine -> law torque
    q[2, 0] = np.nan  # arm 2: diverged -> stays non-finite for the offline record, no exception
    tau, tau_fb, _ = bundle.step_batch(q, np.zeros((3, 6)), q_d, np.zeros((3, 6)), qdd_d, np.zeros((3, 0)))
    assert np.isfinite(tau[:2]).all() and not np.isfinite(tau[2]).all()
    assert np.array_equal(tau[1], np.clip(tau_fb[1], -bundle.torque_limit_nm, bundle.torque_limit_nm))
    assert (bundle.nonfinite_fallbacks, bundle.nonfinite_refusals) == (1, 1)
    assert bundle.last_trust_batch[1].tolist() == [1.0, 0.0]  # reported as a full fallback to the law
