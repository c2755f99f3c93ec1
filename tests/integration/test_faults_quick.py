"""``hil faults --quick`` (issue 15): the campaign's subset against the live runtime and the
pybullet target, through the installed command; every row must pass (docs/faults.md)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from models.lab.faults.campaign import QUICK


@pytest.mark.timeout(660)  # the campaign's own subprocess bound (600 s) governs, not the suite's 300 s
def test_hil_faults_quick_passes_every_row(tmp_path: Path) -> None:
    out = tmp_path / "faults"
    done = subprocess.run(
        [sys.executable, "-m", "hil_runtime.cli", "faults", "--quick", "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    document = json.loads((out / "results.json").read_text())
    failed = {row["fault"]: row["failures"] for row in document["rows"] if not row["pass"]}
    assert done.returncode == 0 and not failed, f"{failed}\n{done.stderr[-3000:]}"
    assert [row["fault"] for row in document["rows"]] == list(QUICK)
    assert len(document["cases"]) == len(QUICK)  # one repeat each
    table = (out / "table.md").read_text()
    assert table.count("**pass**") == len(QUICK) and "FAIL" not in table
    assert not [p for p in out.iterdir() if p.name.startswith(".")]  # no temporary left
    # the guarantees the table checks, case by case
    for case in document["cases"]:
        assert case["max_torque_ratio"] is not None and case["max_torque_ratio"] <= 1.0 + 1e-9, case
        assert not case["nonfinite_commanded"] and case["daemon_alive"], case


def test_unknown_fault_names_are_one_line_exit_2(tmp_path: Path) -> None:
    command = [sys.executable, "-m", "hil_runtime.cli", "faults", "--only", "nope", "--out", str(tmp_path / "x")]
    done = subprocess.run(command, capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and "nope" in done.stderr, done.stderr
    assert not (tmp_path / "x").exists()
