"""D_input: what is logged is enough to replay the law, and bad files are refused in one line."""

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from models.errors import ModelInputError
from models.lmpc.dataset import RawDatasetSpec, generate_raw_dataset, load_raw_dataset

SPEC = RawDatasetSpec(laws=("pd", "adrc"), conditions=3, duration_s=0.2, stride=5, chunks=2)


@pytest.fixture(scope="module")
def raw_path(tmp_path_factory):
    return generate_raw_dataset(SPEC, tmp_path_factory.mktemp("raw") / "raw.h5")


def test_layout_counts_and_manifest(raw_path):
    raw = load_raw_dataset(raw_path)
    assert raw.manifest["spec"]["conditions"] == 3 and raw.manifest["git_commit"]
    assert {c["name"] for c in raw.manifest["conditions"]} == {f"R{SPEC.seed}-{k:03d}" for k in range(3)}
    for law in SPEC.laws:
        rows = raw.laws[law]
        assert len(rows) == 3 * 40  # 200 periods / stride 5, per condition
        np.testing.assert_allclose(rows.t_s[:3], [0.0, 0.005, 0.010])
        assert rows.features().shape == (120, 30)
    assert raw.laws["adrc"].law_state.shape == (120, 24)
    assert (Path(str(raw_path) + ".manifest.json")).is_file()


def test_logged_state_replays_the_logged_feedback_torque(raw_path):
    from models.feedback import make_law
    from models.robots import load_robot

    raw = load_raw_dataset(raw_path)
    robot = load_robot("ur5_paper")
    for law_name in SPEC.laws:
        rows = raw.laws[law_name]
        law = make_law(law_name, robot, 1e-3, SPEC.gain_set)
        tau, _ = law.step(np, rows.law_state, rows.q, rows.qd, rows.q_d, rows.qd_d, rows.qdd_d)
        np.testing.assert_allclose(tau, rows.tau_fb, atol=1e-9)


def test_a_truncated_file_is_one_line_naming_it(raw_path, tmp_path):
    bad = tmp_path / "raw.h5"
    data = raw_path.read_bytes()
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(ModelInputError, match=str(bad)) as info:
        load_raw_dataset(bad)
    assert "\n" not in str(info.value) and info.value.exit_code == 2


def test_a_missing_file_is_refused(tmp_path):
    with pytest.raises(ModelInputError, match="no such file"):
        load_raw_dataset(tmp_path / "nope.h5")


def test_cli_refuses_a_corrupt_dataset_with_exit_2_and_leaves_it_alone(tmp_path):
    bad = tmp_path / "raw.h5"
    bad.write_bytes(b"\x89HDF\r\n\x1a\n" + b"\x00" * 100)
    before = bad.read_bytes()
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "hil_runtime.cli",
            "pipeline",
            "--design",
            "paper",
            "--stages",
            "dataset",
            "--work",
            str(tmp_path),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 2, done.stderr
    lines = [line for line in done.stderr.splitlines() if line.startswith("error:")]
    assert len(lines) == 1 and str(bad) in lines[0]
    assert bad.read_bytes() == before
