"""Any arm (issue 25 item 2): each robot's default conditions inside its limits, paper-range draws
around its home pose, the HMPC's and the runtime's limits on an asymmetric range, how a URDF robot
is named to the target, and ``hil config runtime`` (a runtime config from a bundle and a drive table)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
import yaml

from hil_runtime.cli import main
from hil_runtime.conditions import load_conditions as paper_conditions
from models.conditions import load_conditions
from models.default_conditions import MAX_EFFORT_FACTOR, default_conditions, home_pose_rad
from models.robots import RobotModel, load_robot

ROOT = Path(__file__).resolve().parents[3]
PD_BUNDLE = ROOT / "models" / "bundles" / "ur5_paper" / "pd"


@pytest.fixture(scope="module")
def panda() -> RobotModel:
    return load_robot("panda")


def test_ur5_paper_keeps_the_papers_five() -> None:
    assert default_conditions(load_robot("ur5_paper")) == paper_conditions(None)


@pytest.mark.parametrize("name", ["ur5", "panda"])
def test_other_arms_get_five_conditions_inside_their_limits(name: str) -> None:
    robot = load_robot(name)
    conditions = load_conditions(robot=robot)  # no file: the robot's defaults
    assert [c.name for c in conditions] == ["C1", "C2", "C3", "C4", "C5"]
    for c in conditions:
        assert c.n_joints == robot.n_joints
        c.check_limits(robot)  # raises if a reference leaves the limits
        lowest, highest, _ = c.extrema()
        assert np.all(lowest >= robot.position_lower_rad) and np.all(highest <= robot.position_upper_rad)
        assert c.disturbance is not None and len(c.disturbance.torque_nm) == robot.n_joints
        assert np.all(np.abs(c.disturbance.torque_nm) <= MAX_EFFORT_FACTOR * robot.torque_limit_nm + 1e-9)


def test_the_pandas_home_pose_lies_inside_its_range(panda: RobotModel) -> None:
    home = home_pose_rad(panda)
    # the elbow's range [-3.07, -0.07] excludes 0: its midpoint; joint 6 [-0.02, 3.75]: 0 is at its edge
    assert home[3] == pytest.approx(0.5 * (panda.position_lower_rad[3] + panda.position_upper_rad[3]))
    assert home[5] == pytest.approx(0.5 * (panda.position_lower_rad[5] + panda.position_upper_rad[5]))
    assert home[0] == 0.0
    assert np.all(home > panda.position_lower_rad) and np.all(home < panda.position_upper_rad)


def test_paper_range_draws_stay_inside_an_asymmetric_range(panda: RobotModel) -> None:
    from models.lmpc.paper_range import paper_range_conditions

    for c in paper_range_conditions(panda, 40, 7101):
        c.check_limits(panda)


def test_paper_range_draws_on_ur5_paper_are_unchanged() -> None:
    """The earlier formula (symmetric, around 0), written out: the shipped bundles' training draws."""
    from models.lmpc.paper_range import paper_range_conditions

    robot = load_robot("ur5_paper")
    rng = np.random.default_rng(11)
    pos_limit = np.minimum(robot.position_limit_rad, math.pi) * 0.8
    for c in paper_range_conditions(robot, 3, 11):
        freq = float(rng.uniform(0.05, 0.1))
        cap = np.minimum(np.minimum(pos_limit, math.pi / 2), 0.8 * robot.velocity_limit_rad_s / (math.pi * freq))
        assert np.array_equal(c.amplitude_rad, rng.uniform(-1.0, 1.0, size=6) * cap)
        rng.uniform(0.0, c.duration_s)


def test_hmpc_bounds_an_asymmetric_range_about_its_centre(panda: RobotModel) -> None:
    from models.feedback import make_law
    from models.hmpc import HMPCConfig, HMPCSolver

    law = make_law("pd", panda, 1e-3, kp=[100.0] * 7, kd=[10.0] * 7)
    solver = HMPCSolver(law, panda, HMPCConfig(kernels="numpy"))  # |q| <= 0 on the elbow was refused
    centre = 0.5 * (panda.position_lower_rad + panda.position_upper_rad)
    assert np.allclose(solver.position_centre_rad, centre)
    assert np.allclose(solver.position_limit_rad, 0.5 * (panda.position_upper_rad - panda.position_lower_rad))
    home = home_pose_rad(panda)[None]
    zeros = np.zeros_like(home)
    result = solver.solve(home, zeros, home, zeros, zeros)
    assert np.all(np.isfinite(result.tau_nm))
    # at rest on the reference, mid-range, no bound acts: the same torque as with the bounds off
    # (a bound about 0, |q - 0| <= half range, would push the elbow at -1.57 rad towards 0)
    free = HMPCSolver(law, panda, HMPCConfig(kernels="numpy", use_state_bounds=False))
    assert np.allclose(result.tau_nm, free.solve(home, zeros, home, zeros, zeros).tau_nm, atol=1e-9)


def test_runtime_soft_limits_follow_an_asymmetric_bundle_range() -> None:
    from hil_runtime.config import parse_runtime_config
    from hil_runtime.loading import safety_limits_for

    lower, upper = [-2.9, -1.7, -2.9, -3.0, -2.9, -0.01], [2.9, 1.7, 2.9, -0.07, 2.9, 3.7]
    limits = SimpleNamespace(
        position_rad=[2.9, 1.7, 2.9, 0.0, 2.9, 0.0],
        velocity_rad_s=[2.0] * 6,
        position_lower_rad=lower,
        position_upper_rad=upper,
    )
    # A stand-in with the two attributes safety_limits_for reads (Any: not a PolicyBundle).
    bundle: Any = SimpleNamespace(manifest=SimpleNamespace(limits=limits), torque_limit_nm=np.full(6, 50.0))
    joints = [{"name": f"j{i}", "node_id": i + 1, "max_torque_nm": 50.0} for i in range(6)]
    config = parse_runtime_config({"robot": "x", "bundle": {"path": "b"}, "bus": {"period_s": 5e-3, "joints": joints}})
    safety = safety_limits_for(config, bundle)
    assert np.array_equal(safety.position_lower_rad, lower) and np.array_equal(safety.position_upper_rad, upper)


def test_the_manifest_refuses_half_an_asymmetric_range() -> None:
    import json

    from hil_runtime.bundle_schema import Manifest

    raw = json.loads((PD_BUNDLE / "manifest.json").read_text())
    raw["limits"]["position_lower_rad"] = [-1.0] * 6
    with pytest.raises(ValueError, match="go together"):
        Manifest.model_validate(raw)
    raw["limits"]["position_upper_rad"] = [1.0] * 5
    with pytest.raises(ValueError, match="needs 6 values"):
        Manifest.model_validate(raw)


def test_a_urdf_robot_is_named_to_the_target_by_its_file(tmp_path: Path) -> None:
    from models.robot_target import robot_spec, target_robot_config
    from models.robots import urdf_path

    builtin = load_robot("ur5")
    assert robot_spec(builtin) == "ur5"
    assert target_robot_config(builtin, {"plant": {"substeps": 4}}) == {"plant": {"substeps": 4}, "robot": "ur5"}
    copy = tmp_path / "my_panda.urdf"
    copy.write_text(urdf_path("panda").read_text())
    arm = load_robot(copy)
    assert robot_spec(arm) == str(copy.resolve())
    config = target_robot_config(arm, {"plant": {"substeps": 4}})
    assert config["urdf"] == str(copy.resolve()) and config["robot"] is None
    assert config["plant"] == {"substeps": 4, "joint_names": list(arm.joint_names)}  # the fingers stay locked


def _config_runtime(tmp_path: Path, table: str, *extra: str) -> int:
    (tmp_path / "bus.yaml").write_text(table)
    args = ["config", "runtime", "--bundle", str(PD_BUNDLE), "--bus", str(tmp_path / "bus.yaml")]
    return main([*args, "--out", str(tmp_path / "runtime.yaml"), *extra])


def test_config_runtime_writes_what_hil_run_loads(tmp_path: Path) -> None:
    from hil_runtime.config import load_runtime_config
    from hil_runtime.loading import condition_for, load_bundle_for, safety_limits_for

    others = ", ".join(f"{j}: {i + 10}" for i, j in enumerate(_joints()[:5]))
    table = (
        "transport: {interface: virtual, channel: t, fd: true, data_bitrate: 5000000}\n"
        f"drives: {{wrist_3_joint: {{node_id: 16, max_torque_nm: 20}}, {others}}}\n"
    )
    assert _config_runtime(tmp_path, table) == 0
    config = load_runtime_config(tmp_path / "runtime.yaml")
    assert [j.node_id for j in config.bus.joints] == [10, 11, 12, 13, 14, 16]
    assert [j.max_torque_nm for j in config.bus.joints] == [102.0, 102.0, 66.0, 34.0, 34.0, 20.0]
    assert config.period_s == 1e-3 and config.robot == "ur5_paper"
    assert condition_for(config, safety_limits_for(config, load_bundle_for(config))) is not None


def _joints() -> list[str]:
    return yaml.safe_load((PD_BUNDLE / "manifest.json").read_text())["robot"]["joint_names"]


@pytest.mark.parametrize(
    ("table", "message"),
    [
        ("transport: {interface: virtual}\ndrives: {elbow: 3}\n", "bus.yaml: drives.elbow: not a joint of the bundle"),
        ("transport: {interface: virtual}\ndrives: {elbow_joint: 3}\n", "joint 'shoulder_pan_joint' of the bundle"),
        ("transport: {interface: virtual}\nperiod_s: 0.002\n", "bus.yaml: period_s: comes from the bundle"),
        ("transport: {interface: carrier_pigeon}\n", "bus.yaml: bus.transport.interface"),
        ("- 1\n", "bus.yaml: expected a mapping"),
    ],
)
def test_config_runtime_refuses_a_bad_table(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], table: str, message: str
) -> None:
    assert _config_runtime(tmp_path, table) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "runtime.yaml").exists()


def test_config_runtime_writes_another_arms_conditions(tmp_path: Path, panda: RobotModel) -> None:
    """A 7-joint bundle is not at hand without a pipeline run: the conditions file is written from the robot."""
    from models.lab.deploy import _conditions

    manifest = SimpleNamespace(robot=SimpleNamespace(name="panda", n_joints=7))
    path = _conditions(manifest, None, tmp_path / "runtime.yaml", None)
    assert path is not None and path.name == "runtime.conditions.yaml"
    written = load_conditions(path, robot=panda)
    assert written == default_conditions(panda)


def test_a_seven_joint_arm_gets_a_bus_that_carries_it(panda: RobotModel) -> None:
    """7 drives at 1 kHz on a 5 Mbit/s CAN FD data phase are 92 % of the bus: refused; 8 Mbit/s: both ends."""
    from models.lab.configs import target_config
    from models.robot_target import target_robot_config
    from sim_target.launch import launch_target

    config = target_robot_config(panda, target_config("panda", 1e-3, 4))
    assert config["bus"]["data_bitrate"] == 8_000_000
    with launch_target(config, "virtual") as target:  # the target's config passes its bus-load check
        assert target.transport["data_bitrate"] == 8_000_000  # the runtime's end of the same bus
    six = target_robot_config(load_robot("ur5"), target_config("ur5", 1e-3, 4))
    assert six["bus"]["data_bitrate"] == 5_000_000  # six drives: unchanged


def test_random_conditions_stay_inside_an_asymmetric_range(panda: RobotModel) -> None:
    """The dataset's draws (``hil pipeline --design paper``): around the home pose, inside the range."""
    from models.conditions import random_conditions

    for c in random_conditions(panda, 40, 3):
        c.check_limits(panda)
    paper = load_robot("ur5_paper")
    assert all(c.offset_rad is None for c in random_conditions(paper, 3, 3))  # ur5_paper: around 0 as before


def test_config_runtime_refuses_a_bundle_that_would_chatter_on_the_stated_encoders(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The real UR5's shipped static bundles turn a 19-bit encoder's noise (1e-5 rad, differenced) into ~6 N m
    steps on the base joint, above the 1 N m per period its rate bound allows: refused with one line naming the
    field; stated as perfect sensors (an emulated arm, 0), or run as the law alone (--mode fb), accepted."""
    from models.lmpc.controller import bundle_path

    ur5 = bundle_path("ur5", "pd")
    joints = json.loads((ur5 / "manifest.json").read_text())["robot"]["joint_names"]
    drives = ", ".join(f"{j}: {i + 1}" for i, j in enumerate(joints))
    transport = "{interface: virtual, channel: t, fd: true, data_bitrate: 5000000}"
    (tmp_path / "bus.yaml").write_text(f"transport: {transport}\ndrives: {{{drives}}}\n")
    args = ["config", "runtime", "--bundle", str(ur5), "--bus", str(tmp_path / "bus.yaml")]
    out = tmp_path / "runtime.yaml"
    assert main([*args, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "bus.yaml: bundle.encoder_noise_rad: bundle " in err, err
    assert "on joint 1" in err and "tolerates about" in err and not out.exists(), err
    assert main([*args, "--out", str(out), "--encoder-noise-rad", "0"]) == 0
    assert yaml.safe_load(out.read_text())["bundle"]["encoder_noise_rad"] == 0.0
    assert main([*args, "--out", str(out), "--mode", "fb", "--force"]) == 0
