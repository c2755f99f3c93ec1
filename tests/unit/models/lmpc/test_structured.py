"""The torch RNE (models.dynamics.torch_rne), the structured emulator, the paper-range conditions."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pytest
import torch

from models.dynamics import make_dynamics
from models.dynamics.torch_rne import SpatialRne
from models.errors import ModelInputError
from models.robots import load_robot

if TYPE_CHECKING:
    from models.lmpc.structured import StructuredConfig


def _export(module: torch.nn.Module, width: int, path: Path) -> None:
    """The bundle exporter's ONNX settings (opset 17, float64 rows, dynamic batch)."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        torch.onnx.export(
            module,
            (torch.zeros(2, width, dtype=torch.float64),),
            str(path),
            input_names=["x"],
            output_names=["y"],
            dynamic_axes={"x": {0: "batch"}, "y": {0: "batch"}},
            opset_version=17,
            dynamo=False,
        )


@pytest.mark.parametrize("name", ["ur5_paper", "ur5", "panda"])
def test_spatial_rne_equals_rneida(name: str) -> None:
    robot = load_robot(name)
    rng = np.random.default_rng(1)
    q, qd, qdd = (rng.normal(size=(7, robot.n_joints)) for _ in range(3))
    dyn = make_dynamics(robot, "rne")
    rne = SpatialRne(robot)
    got = rne.inverse_dynamics(*(torch.as_tensor(a) for a in (q, qd, qdd))).numpy()
    np.testing.assert_allclose(got, dyn.inverse_dynamics(q, qd, qdd), atol=1e-12 * max(1.0, np.abs(got).max()))
    np.testing.assert_allclose(rne.gravity_torque(torch.as_tensor(q)).numpy(), dyn.gravity(q), atol=1e-12 * 60)
    free = rne.inverse_dynamics(*(torch.as_tensor(a) for a in (q, qd, qdd)), gravity=False).numpy()
    np.testing.assert_allclose(got - free, dyn.gravity(q), atol=1e-11)


def test_spatial_rne_is_a_small_onnx_graph(tmp_path: Path) -> None:
    onnx = pytest.importorskip("onnx")
    ort = pytest.importorskip("onnxruntime")
    robot = load_robot("ur5_paper")
    rne = SpatialRne(robot)

    class Wrap(torch.nn.Module):
        def forward(self, x: torch.Tensor) -> torch.Tensor:
            return rne.inverse_dynamics(x[:, :6], x[:, 6:12], x[:, 12:])

    path = tmp_path / "rne.onnx"
    _export(Wrap(), 18, path)
    compute = [n for n in onnx.load(str(path)).graph.node if n.op_type != "Constant"]
    assert len(compute) <= 32  # 29 for the RNE, 3 slices of x
    x = np.random.default_rng(0).normal(size=(5, 18))
    got = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"]).run(None, {"x": x})[0]
    np.testing.assert_allclose(
        got, make_dynamics(robot, "rne").inverse_dynamics(x[:, :6], x[:, 6:12], x[:, 12:]), atol=1e-10
    )


def test_paper_range_conditions_are_seeded_in_range_and_parsed() -> None:
    from models.lmpc.paper_range import paper_range_conditions, parse_random_spec

    robot = load_robot("ur5_paper")
    a, b = paper_range_conditions(robot, 20, 5), paper_range_conditions(robot, 20, 5)
    assert a == b and a != paper_range_conditions(robot, 20, 6)
    assert all(
        max(abs(x) for x in c.amplitude_rad) <= np.pi / 2 + 1e-12 and 0.05 <= c.frequency_hz[0] <= 0.1 for c in a
    )
    assert len({c.name for c in a}) == 20
    assert parse_random_spec("random:20:7") == (20, 7) and parse_random_spec("my.yaml") is None
    for bad in ("random:0:1", "random:x:1", "random:3", "random:3:1:2"):
        with pytest.raises(ModelInputError, match="--conditions"):
            parse_random_spec(bad)


def _tiny(target: str, **extra: Any) -> StructuredConfig:
    from models.lmpc.structured import StructuredConfig

    extra.setdefault("laws", ("pd",))
    extra.setdefault("perturb_error_rad", 1e-4)
    extra.setdefault("perturb_rate_rad_s", 1e-2)
    return StructuredConfig(
        target=target,
        train_conditions=2,
        duration_s=0.3,
        stride=10,
        residual_epochs=2,
        physics_steps=200,
        **extra,
    )


def test_structured_pipeline_exports_a_loadable_bundle_equal_to_its_torch_model(tmp_path: Path) -> None:
    from hil_runtime.bundle import PolicyBundle
    from models.lmpc.structured import run_structured

    summary = run_structured(
        _tiny("hmpc", laws=("pd", "smc")), tmp_path / "bundles", tmp_path / "work", log=lambda _: None
    )
    fit = summary["rounds"][0]["pd"]
    assert fit["onnx_vs_torch_max_abs_nm"] <= 1e-5
    assert (
        summary["rounds"][0]["smc"]["onnx_vs_torch_max_abs_nm"] <= 1e-5
    )  # the law's RNE batched with the feed-forward's
    bundle = PolicyBundle.load(tmp_path / "bundles" / "ur5_paper" / "pd", expected_joints=6, expected_period_s=1e-3)
    assert bundle.manifest.emulator.feature_set == "eq22+qdd_d"
    assert bundle.manifest.training["design"].startswith("structured")
    physics = fit["fit"]["physics"]
    assert all(0.0 <= g <= 1.2 for g in physics["g"]) and all(-1.05 <= c <= 0.0 for c in physics["c"])
    assert (tmp_path / "work" / "structured.json").exists()


def test_a_dagger_round_runs_the_exported_lmpc_and_refits_on_its_states(tmp_path: Path) -> None:
    from hil_runtime.bundle import PolicyBundle
    from models.lmpc.structured import run_structured

    summary = run_structured(
        _tiny("hmpc", dagger_rounds=1), tmp_path / "bundles", tmp_path / "work", log=lambda _: None
    )
    first, second = (r["pd"]["fit"]["samples"] for r in summary["rounds"])
    assert len(summary["rounds"]) == 2 and second > first  # the LMPC's own states were added
    PolicyBundle.load(tmp_path / "bundles" / "ur5_paper" / "pd")  # the round-1 bundle, every check


def test_control_row_the_law_imitated_is_the_law(tmp_path: Path) -> None:
    from hil_runtime.bundle import PolicyBundle
    from models.feedback import make_law
    from models.lmpc.structured import run_structured

    run_structured(_tiny("law"), tmp_path / "bundles", tmp_path / "work", log=lambda _: None)
    bundle = PolicyBundle.load(tmp_path / "bundles" / "ur5_paper" / "pd")
    robot = load_robot("ur5_paper")
    law = make_law("pd", robot, 1e-3, "stabilized")
    rng = np.random.default_rng(0)
    q_d = rng.uniform(-0.3, 0.3, (16, 6))
    q, qd, qd_d, qdd_d = (
        q_d + rng.normal(0, 0.01, (16, 6)),
        rng.normal(0, 0.05, (16, 6)),
        rng.normal(0, 0.05, (16, 6)),
        np.zeros((16, 6)),
    )
    state = bundle.initial_state(q)
    tau, tau_fb, _ = bundle.step_batch(q, qd, q_d, qd_d, qdd_d, state)
    expected = np.asarray(law.step(np, state, q, qd, q_d, qd_d, qdd_d)[0])
    np.testing.assert_allclose(tau_fb, expected, atol=1e-9)
    assert np.abs(tau - tau_fb).max() <= 1e-2 * np.abs(tau_fb).max()


def test_structured_config_refuses_unknown_options() -> None:
    from models.lmpc.structured import StructuredConfig

    bad_options: list[dict[str, Any]] = [{"target": "mpc"}, {"ff_point": "desired"}, {"train_conditions": 0}]
    for bad in bad_options:
        with pytest.raises(ModelInputError, match="structured lmpc"):
            StructuredConfig(**bad)


def test_batched_nominal_gives_the_law_and_the_caller_their_own_rows() -> None:
    from models.feedback._common import NominalModel
    from models.feedback.base import SharedId

    robot = load_robot("ur5_paper")
    nominal = NominalModel(robot)
    rng = np.random.default_rng(2)
    q, qd, qdd, pq, pqd, pa = (torch.as_tensor(rng.normal(size=(4, 6))) for _ in range(6))
    eye, zero = np.eye(6), np.zeros((6, 6))
    rate_map = (np.vstack([eye, zero]), np.vstack([zero, eye]), None)
    alone_law, alone_caller = (
        nominal.inverse_dynamics(torch, q, qd, qdd),
        nominal.torch_rne.inverse_dynamics(pq, pqd, pa),
    )
    for position, expected in ((pq, alone_caller), (q, nominal.torch_rne.inverse_dynamics(q, pqd, pa))):
        # another position: a second pass; the law's own q: one shared pass
        request = SharedId(position, torch.cat([pqd, pa], 1), rate_map)
        both, caller = nominal.inverse_dynamics_sharing(q, qd, qdd, request)
        torch.testing.assert_close(both, alone_law, rtol=0, atol=1e-12)
        torch.testing.assert_close(caller, expected, rtol=0, atol=1e-12)
        request = SharedId(position, torch.cat([pqd, pa], 1), rate_map, np.full(6, 2.0))
        gravity, caller = nominal.gravity_sharing(q, request)
        torch.testing.assert_close(
            gravity, torch.as_tensor(NominalModel(robot).gravity(np, q.numpy())), rtol=0, atol=1e-11
        )
        torch.testing.assert_close(caller, 2.0 * expected, rtol=0, atol=1e-12)
    assert nominal.gravity_sharing(q, None)[1] is None  # no request, no caller's torque


def test_experiment_cli_refuses_a_bad_formulation_and_a_bad_random_spec(tmp_path: Path) -> None:
    from models.cli import experiment

    with pytest.raises(ModelInputError, match="--hmpc-formulation"):
        experiment(modes="fb", laws="pd", out=tmp_path, hmpc_formulation="relative", conditions=None)
    with pytest.raises(ModelInputError, match="--conditions"):
        experiment(modes="fb", laws="pd", out=tmp_path, conditions="random:zero:1")


@pytest.mark.parametrize("law_name", ["pd", "pid", "adrc", "hinf", "smc", "mrac"])
def test_compact_structured_graph_equals_the_reference_policy(law_name: str, tmp_path: Path) -> None:
    """The folded graph (models.lmpc.structured) computes FusedPolicy.forward with the emulator's own forward
    to round-off: inside the trust box, in the fade-out, outside it, clamped or not; and it is small."""
    onnx = pytest.importorskip("onnx")
    ort = pytest.importorskip("onnxruntime")
    from models.feedback import make_law
    from models.lmpc.bundle_export import FusedPolicy
    from models.lmpc.structured import StructuredEmulator, structured_policy_class

    robot = load_robot("ur5_paper")
    n = robot.n_joints
    limit = np.asarray(robot.torque_limit_nm, float)
    rng = np.random.default_rng(11)
    torch.manual_seed(11)
    for ff_point in ("measured", "reference"):
        law = make_law(law_name, robot, 1e-3, "stabilized")
        model = StructuredEmulator(robot, (16, 16), 0.02 * limit, ff_point)
        with torch.no_grad():
            model.c.copy_(torch.as_tensor(rng.uniform(-1.0, 0.0, n)))
            model.g.copy_(torch.as_tensor(rng.uniform(0.8, 1.2, n)))
            model.theta_kp.copy_(torch.eye(n) * 5.0 + torch.as_tensor(rng.normal(size=(n, n))) * 0.1)
            model.theta_kd.copy_(torch.eye(n) * 5.0)
            for layer in model.net:
                if isinstance(layer, torch.nn.Linear):
                    layer.weight.normal_(0.0, 0.3)
                    layer.bias.normal_(0.0, 0.1)
            model.in_mean.copy_(torch.as_tensor(rng.normal(size=6 * n) * 0.1))
            model.in_std.copy_(torch.as_tensor(rng.uniform(0.5, 2.0, 6 * n)))
        model.freeze()
        low, high = -np.full(6 * n, 0.4), np.full(6 * n, 0.4)
        low[5 * n :], high[5 * n :] = -limit, limit
        low[n], high[n] = -0.3, 0.3 + 1e-12  # a span near the minimum is handled as the reference does
        trust = {"feature_low": low, "feature_high": high, "box_margin": 0.5, "residual_bound_nm": 0.05 * limit}
        reference = FusedPolicy(law, model, True, trust, "eq22+qdd_d").eval()
        compact = structured_policy_class()(law, model, True, trust, "eq22+qdd_d").eval()
        width = 5 * n + law.state_size
        x = rng.normal(size=(96, width)) * np.repeat([0.02, 0.2, 0.6], 32)[:, None]  # inside, fade-out, outside
        x[:, 5 * n :] = rng.normal(size=(96, law.state_size)) * 0.01
        with torch.no_grad():
            expected = reference(torch.as_tensor(x)).numpy()
            got = compact(torch.as_tensor(x)).numpy()
        trust_col = expected[:, 2 * n + law.state_size]  # 1 - alpha
        assert (trust_col == 0).any() and (trust_col == 1).any() and ((trust_col > 0) & (trust_col < 1)).any()
        assert expected[:, -1].sum() > 0  # some rows clamp
        np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-9)
        path = tmp_path / f"{law_name}_{ff_point}.onnx"
        _export(compact, width, path)
        session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
        np.testing.assert_allclose(session.run(None, {"x": x})[0], expected, rtol=1e-9, atol=1e-9)
        compute = [node for node in onnx.load(str(path)).graph.node if node.op_type != "Constant"]
        if ff_point == "measured":  # shipped; at the reference point H-inf and SMC run a second RNE pass
            assert len(compute) <= {"pd": 62, "pid": 68, "hinf": 66, "smc": 69}.get(law_name, 81)


@pytest.mark.parametrize("law_name", ["adrc", "smc"])  # SMC: its RNE shared with the feed-forward's
def test_compact_rate_aware_graph_equals_the_reference_policy(law_name: str) -> None:
    """With tau_prev read (docs/lmpc.md section 11) the folded graph still computes FusedPolicy.forward:
    the trust region's target, then the step from tau_prev within the rate bound."""
    from models.feedback import make_law
    from models.lmpc.bundle_export import FusedPolicy
    from models.lmpc.structured import StructuredEmulator, structured_policy_class

    robot = load_robot("ur5_paper")
    n = robot.n_joints
    limit = np.asarray(robot.torque_limit_nm, float)
    rng = np.random.default_rng(12)
    law = make_law(law_name, robot, 1e-3, "stabilized")
    model = StructuredEmulator(robot, (16,), 0.02 * limit, "measured", 0.0, True, 1e-3)
    with torch.no_grad():
        model.c.fill_(-1.0)
        model.beta.copy_(torch.as_tensor(rng.uniform(0.1, 1.0, n)))
        model.theta_kp.copy_(torch.eye(n) * 0.5)
        model.theta_kd.copy_(torch.eye(n) * 0.5)
    model.freeze()
    low, high = -np.full(6 * n, 0.4), np.full(6 * n, 0.4)
    low[5 * n :], high[5 * n :] = -limit, limit
    trust = {"feature_low": low, "feature_high": high, "box_margin": 0.5, "residual_bound_nm": 0.05 * limit}
    reference = FusedPolicy(law, model, True, trust, "eq22+qdd_d").eval()
    compact = structured_policy_class()(law, model, True, trust, "eq22+qdd_d").eval()
    width = 6 * n + law.state_size
    x = rng.normal(size=(96, width)) * np.repeat([0.02, 0.2, 0.6], 32)[:, None]
    x[:, 5 * n : 5 * n + law.state_size] = rng.normal(size=(96, law.state_size)) * 0.01
    x[:, -n:] = rng.uniform(-0.1, 0.1, (96, n)) * limit
    with torch.no_grad():
        expected = reference(torch.as_tensor(x)).numpy()
        got = compact(torch.as_tensor(x)).numpy()
    np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-9)
    step = model.rate_step.numpy()
    assert (np.abs(expected[:, :n] - x[:, -n:]) <= step * (1 + 1e-12)).all()


@pytest.mark.heavy  # ~25 s: rollouts and HMPC relabels
def test_the_rate_aware_pipeline_logs_tau_prev_relabels_given_it_and_fits_beta(tmp_path: Path) -> None:
    import pickle

    from hil_runtime.bundle import PolicyBundle
    from hil_runtime.rate_limit import max_torque_step_nm
    from models.hmpc.config import formulation_options
    from models.lmpc.structured import run_structured
    from models.lmpc.structured.data import ROW_KINDS
    from models.lmpc.structured.model import BETA_MIN

    options = formulation_options("deployable", "ur5_paper")
    config = _tiny("hmpc", previous_torque=True, hmpc_options=options, c_fixed=-1.0, perturb_error_rad=1e-3)
    summary = run_structured(config, tmp_path / "bundles", tmp_path / "work", log=lambda _: None)
    _, data = pickle.loads((tmp_path / "work" / "rollouts_pd.pkl").read_bytes())
    kind = data["row_kind"][:, 0]
    assert set(np.unique(kind)) == set(ROW_KINDS.values())  # on-policy, cold static copies, rate copies
    step = max_torque_step_nm(load_robot("ur5_paper").torque_rate_nm_s, 1e-3)
    change = np.abs(data["tau_star"] - data["tau_prev"])
    given = kind != ROW_KINDS["static"]
    assert (change[given] <= step * (1 + 1e-6)).all()  # every label given its tau_0: the HMPC's rate box
    assert (change[~given] > step).any()  # a cold solve has no tau_0: no rate box
    rate = kind == ROW_KINDS["rate"]
    assert (change[rate] >= step * (1 - 1e-6)).any() and (change[rate] < 0.5 * step).any()  # both regimes
    fit = summary["rounds"][0]["pd"]["fit"]["rate"]
    assert all(max(BETA_MIN, config.beta_floor) <= b <= 1.0 for b in fit["beta"])
    bundle = PolicyBundle.load(tmp_path / "bundles" / "ur5_paper" / "pd", expected_joints=6)
    assert bundle.takes_previous_torque
