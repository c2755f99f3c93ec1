"""The shipped configs and units keep the bus and the sockets out of shared directories (issue 20):
no fixed name in /tmp, where any local user could create it first; both units share /run/hil."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"


@pytest.mark.parametrize("config", sorted(DEPLOY.glob("*.yaml")), ids=lambda p: p.name)
def test_no_deploy_config_puts_a_bus_or_socket_in_tmp(config: Path) -> None:
    data = yaml.safe_load(config.read_text())
    bus = data["bus"]
    transport = bus.get("transport", bus)
    paths = [str(data.get("control_socket") or ""), str(transport.get("channel") or "")]
    assert not [p for p in paths if p.startswith(("/tmp", "/var/tmp", "/dev/shm"))], paths


@pytest.mark.parametrize("unit", ["hil-runtime.service", "hil-target.service"])
def test_both_units_own_the_runtime_directory(unit: str) -> None:
    lines = (DEPLOY / "systemd" / unit).read_text().splitlines()
    assert "RuntimeDirectory=hil" in lines and "RuntimeDirectoryPreserve=yes" in lines
