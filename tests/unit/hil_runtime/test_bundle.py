"""The runtime's policy-bundle loader: verification, refusals (one line, exit code 2), stepping."""

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from hil_runtime.bundle import BundleError, PolicyBundle
from hil_runtime.supervisor import policy_torque

torch = pytest.importorskip("torch")


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A real bundle (ADRC: stateful, with the applied-torque slot) with an untrained emulator."""
    from models.feedback import make_law
    from models.lmpc.bundle_export import FusedPolicy, export_bundle
    from models.lmpc.emulator import Emulator
    from models.robots import load_robot

    robot = load_robot("ur5_paper")
    law = make_law("adrc", robot, 1e-3)
    torch.manual_seed(0)
    emulator = Emulator(30, 6, (16, 16))
    path = tmp_path_factory.mktemp("bundles") / "adrc"
    export_bundle(path, law, robot, emulator, {"note": "test"}, {"val_mse_normalized": 1.0})
    return path, FusedPolicy(law, emulator), law, robot


@pytest.fixture
def bundle_copy(exported, tmp_path):
    path = tmp_path / "b"
    shutil.copytree(exported[0], path)
    return path


def _refuse(path, match, **kwargs):
    before = {p: p.read_bytes() for p in path.rglob("*") if p.is_file()} if path.is_dir() else {}
    with pytest.raises(BundleError, match=match) as info:
        PolicyBundle.load(path, **kwargs)
    assert info.value.exit_code == 2
    assert "\n" not in str(info.value)
    after = {p: p.read_bytes() for p in path.rglob("*") if p.is_file()} if path.is_dir() else {}
    assert before == after  # nothing overwritten
    return str(info.value)


def test_onnxruntime_matches_torch_and_the_numpy_law(exported):
    path, model, law, robot = exported
    bundle = PolicyBundle.load(path, expected_joints=6, expected_period_s=1e-3, expected_joint_names=robot.joint_names)
    rng = np.random.default_rng(5)
    q, qd, q_d, qd_d, qdd_d = (rng.normal(size=(8, 6)) * 0.3 for _ in range(5))
    state = law.initial_state(q) + rng.normal(size=(8, law.state_size)) * 0.01
    tau, tau_fb, nxt = bundle.step_batch(q, qd, q_d, qd_d, qdd_d, state)
    with torch.no_grad():
        expected = model(torch.as_tensor(np.concatenate([q, qd, q_d, qd_d, qdd_d, state], 1))).numpy()
    np.testing.assert_allclose(
        np.concatenate([tau, tau_fb, nxt, bundle.last_trust_batch], 1), expected, atol=1e-5, rtol=0
    )
    fb_np, state_np = law.step(np, state, q, qd, q_d, qd_d, qdd_d)
    np.testing.assert_allclose(tau_fb, fb_np, atol=1e-9)
    np.testing.assert_allclose(nxt, law.with_applied_torque(state_np, tau), atol=1e-9)
    assert np.all(np.abs(tau) <= robot.torque_limit_nm + 1e-12)
    one = bundle.step(q[3], qd[3], q_d[3], qd_d[3], qdd_d[3], state[3])
    np.testing.assert_allclose(np.concatenate([*one, bundle.last_trust]), expected[3], atol=1e-5, rtol=0)
    np.testing.assert_allclose(bundle.initial_state(q[:2]), law.initial_state(q[:2]))


def test_refuses_a_missing_manifest(bundle_copy):
    (bundle_copy / "manifest.json").unlink()
    message = _refuse(bundle_copy, "missing file")
    assert message.startswith(f"bundle {bundle_copy}: no manifest.json in this directory")


def test_refuses_a_missing_graph_file(bundle_copy):
    (bundle_copy / "policy.onnx").unlink()
    assert "policy.onnx" in _refuse(bundle_copy, "missing file")


def test_refuses_a_wrong_hash(bundle_copy):
    data = bytearray((bundle_copy / "policy.onnx").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (bundle_copy / "policy.onnx").write_bytes(bytes(data))
    assert "policy.onnx" in _refuse(bundle_copy, "sha256 mismatch")


def test_refuses_an_unknown_schema(bundle_copy):
    manifest = json.loads((bundle_copy / "manifest.json").read_text())
    manifest["schema"] = "hil-policy-bundle/99"
    (bundle_copy / "manifest.json").write_text(json.dumps(manifest))
    _refuse(bundle_copy, "unknown schema 'hil-policy-bundle/99'")


def test_refuses_a_malformed_trust_region(bundle_copy):
    manifest = json.loads((bundle_copy / "manifest.json").read_text())
    manifest["trust_region"] = {
        "feature_low": [0.0],
        "feature_high": [1.0],
        "box_margin": 0.1,
        "residual_bound_nm": None,
    }
    (bundle_copy / "manifest.json").write_text(json.dumps(manifest))
    _refuse(bundle_copy, r"manifest.json: trust_region.feature_low/high need 36 values")


def test_trust_region_in_the_graph_matches_the_numpy_rule_and_falls_back(tmp_path):
    """Residual emulator + training box + residual bound: graph == hil_runtime.bundle.trust_filter;
    outside the box tau = sat(tau_fb) and the fallback flag is set; large residuals are clamped."""
    from hil_runtime.trust_region import emulator_features, trust_filter
    from models.feedback import make_law
    from models.lmpc.bundle_export import export_bundle
    from models.lmpc.emulator import Emulator
    from models.robots import load_robot

    robot = load_robot("ur5_paper")
    law = make_law("pid", robot, 1e-3)
    torch.manual_seed(1)
    emulator = Emulator(36, 6, (16,))
    emulator.out_std.fill_(30.0)  # residuals of tens of N m, some above the bound
    box = (np.r_[np.full(30, -1.0), np.full(6, -1e3)], np.r_[np.full(30, 1.0), np.full(6, 1e3)])
    bound = np.array([20.0, 20.0, 10.0, 5.0, 5.0, 5.0])
    export_bundle(
        tmp_path / "pid",
        law,
        robot,
        emulator,
        {},
        {},
        trust_region=box,
        residual=True,
        residual_bound_nm=bound,
        box_margin=0.0,
    )
    bundle = PolicyBundle.load(tmp_path / "pid", expected_joints=6)
    assert bundle.manifest.emulator.residual and bundle.manifest.emulator.feature_set == "eq22+qdd_d"
    rng = np.random.default_rng(3)
    q, qd, q_d, qd_d, qdd_d = (rng.uniform(-0.02, 0.02, size=(16, 6)) for _ in range(5))
    q[8:, 0] = 1.5  # outside the box: fallback
    state = law.initial_state(q)
    tau, tau_fb, _ = bundle.step_batch(q, qd, q_d, qd_d, qdd_d, state)
    s = emulator_features("eq22+qdd_d", q, qd, q_d, qd_d, qdd_d, tau_fb)
    with torch.no_grad():
        r = emulator(torch.as_tensor(s)).numpy()
    tau_np, trust_np = trust_filter(bundle.manifest, s, r, tau_fb)
    np.testing.assert_allclose(tau, tau_np, atol=1e-9)
    np.testing.assert_allclose(bundle.last_trust_batch, trust_np)
    assert np.all(trust_np[8:, 0] == 1) and np.all(trust_np[:8, 0] == 0)
    np.testing.assert_allclose(tau[8:], np.clip(tau_fb[8:], -robot.torque_limit_nm, robot.torque_limit_nm))
    assert trust_np[:8, 1].sum() > 0  # some residuals clamped
    assert np.all(np.abs(tau[:8] - tau_fb[:8]) <= bound + 1e-9)


def test_refuses_a_joint_count_mismatch(bundle_copy):
    assert "6 joints, the config has 7" in _refuse(bundle_copy, "joints", expected_joints=7)


def test_refuses_a_joint_order_mismatch(bundle_copy):
    names = json.loads((bundle_copy / "manifest.json").read_text())["robot"]["joint_names"]
    _refuse(bundle_copy, "joint order", expected_joint_names=list(reversed(names)))


def test_refuses_a_period_mismatch(bundle_copy):
    _refuse(bundle_copy, "control period 0.001 s, the config has 0.002 s", expected_period_s=2e-3)


def test_refuses_a_truncated_manifest(bundle_copy):
    text = (bundle_copy / "manifest.json").read_text()
    (bundle_copy / "manifest.json").write_text(text[: len(text) // 2])
    _refuse(bundle_copy, "unreadable JSON")


def test_refuses_a_graph_that_does_not_load_even_with_a_matching_hash(bundle_copy):
    from hil_runtime.bundle import sha256_file

    (bundle_copy / "policy.onnx").write_bytes(b"not an onnx file")
    manifest = json.loads((bundle_copy / "manifest.json").read_text())
    manifest["files"]["policy.onnx"] = sha256_file(bundle_copy / "policy.onnx")
    (bundle_copy / "manifest.json").write_text(json.dumps(manifest))
    _refuse(bundle_copy, "not an ONNX model|onnxruntime cannot load")


def test_loader_imports_no_torch_or_models():
    code = (
        "import sys, hil_runtime.bundle;"
        "bad = [m for m in ('torch', 'models', 'pinocchio', 'pybullet') if m in sys.modules];"
        "print(bad); sys.exit(1 if bad else 0)"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stdout + done.stderr


def test_shipped_bundles_load_with_the_robot_config():
    from models.feedback import LAW_NAMES
    from models.lmpc.controller import SHIPPED_BUNDLES
    from models.robots import load_robot

    robot = load_robot("ur5_paper")
    root = SHIPPED_BUNDLES / "ur5_paper"
    # The bundles ship with the package: moved or missing is a failure, not a skip.
    assert sorted(p.name for p in root.iterdir() if (p / "manifest.json").is_file()) == sorted(LAW_NAMES), root
    for law in LAW_NAMES:
        bundle = PolicyBundle.load(
            root / law, expected_joints=6, expected_period_s=1e-3, expected_joint_names=robot.joint_names
        )
        assert bundle.law_name == law
        assert bundle.manifest.validation["onnx_vs_torch_max_abs_nm"] <= 1e-5


@pytest.mark.parametrize("law_name", ["hinf", "smc"])
def test_laws_with_the_nominal_model_export_compactly_and_exactly(tmp_path, law_name):
    import onnx

    from models.feedback import make_law
    from models.lmpc.bundle_export import export_bundle
    from models.lmpc.emulator import Emulator
    from models.robots import load_robot

    robot = load_robot("ur5_paper")
    law = make_law(law_name, robot, 1e-3)
    export_bundle(tmp_path / law_name, law, robot, Emulator(30, 6, (8,)), {}, {})
    assert len(onnx.load(str(tmp_path / law_name / "policy.onnx")).graph.node) < 1000  # the traced rneida gives ~1,700
    bundle = PolicyBundle.load(tmp_path / law_name)
    rng = np.random.default_rng(7)
    q, qd, q_d, qd_d, qdd_d = (rng.normal(size=(6, 6)) * 0.5 for _ in range(5))
    state = law.initial_state(q) + rng.normal(size=(6, law.state_size)) * 0.01
    _, tau_fb, nxt = bundle.step_batch(q, qd, q_d, qd_d, qdd_d, state)
    fb_np, state_np = law.step(np, state, q, qd, q_d, qd_d, qdd_d)
    np.testing.assert_allclose(tau_fb, fb_np, atol=1e-9)
    np.testing.assert_allclose(nxt, state_np, atol=1e-9)


def test_step_keeps_a_large_finite_output_and_returns_the_same_views(exported):
    """step only produces; the supervisor's cheap finiteness test (a sum of floats) keeps a large
    finite row (a test on y . y would overflow for |y| > 1e154)."""
    bundle = PolicyBundle.load(exported[0])
    n, run = bundle.n_joints, bundle._run_bound

    def huge_tau_fb(binding, options):
        run(binding, options)
        bundle._y[0, n] = 1e200  # finite, but its square is not

    bundle._run_bound = huge_tau_fb
    q = np.full(n, 0.1)
    first = bundle.step(q, q, q, q, q, bundle.initial_state(q))
    assert first[1][0] == 1e200 and np.isfinite(first[0]).all()
    assert (bundle.nonfinite_fallbacks, bundle.nonfinite_refusals) == (0, 0)
    usable = policy_torque(*first)
    assert usable is not None and usable[0] is first[0]
    second = bundle.step(q, q, q, q, q, first[2].copy())
    assert all(a is b for a, b in zip(first, second, strict=True))  # views of the one output row
    assert np.array_equal(bundle.last_torques[:, 0], np.stack(second[:2]))
