"""deploy/systemd units pass ``systemd-analyze verify`` with no output at all."""

from __future__ import annotations

import configparser
import shutil
import subprocess
from pathlib import Path

import pytest

UNITS = sorted((Path(__file__).resolve().parents[3] / "deploy" / "systemd").glob("*.service"))


def test_units_exist() -> None:
    assert {u.name for u in UNITS} >= {"hil-runtime.service", "hil-target.service"}


@pytest.mark.parametrize("unit", UNITS, ids=lambda u: u.name)
def test_systemd_analyze_verify_is_silent(unit: Path, tmp_path: Path) -> None:
    if shutil.which("systemd-analyze") is None:
        pytest.skip("systemd-analyze is not installed on this machine")
    result = subprocess.run(
        ["systemd-analyze", "verify", str(unit)], capture_output=True, text=True, cwd=tmp_path, timeout=60, check=False
    )
    output = (result.stdout + result.stderr).strip()
    assert result.returncode == 0 and output == "", output


class _CaseSensitiveParser(configparser.ConfigParser):
    """systemd keys are case-sensitive (WatchdogSec); ConfigParser lower-cases them by default."""

    def optionxform(self, optionstr: str) -> str:
        return optionstr


def test_the_runtime_unit_has_the_settings_the_daemon_relies_on() -> None:
    parser = _CaseSensitiveParser(strict=False, interpolation=None)
    parser.read(UNITS[[u.name for u in UNITS].index("hil-runtime.service")])
    service = parser["Service"]
    assert service["Type"] == "notify"
    assert service["WatchdogSec"] and service["Restart"] == "on-failure"
    assert service["LimitMEMLOCK"] == "infinity" and int(service["LimitRTPRIO"]) >= 80
    assert "hil run --config" in service["ExecStart"]
    assert service["RuntimeDirectory"] == "hil"  # the control socket's directory
