"""hil_runtime.machine: the one machine description every results file and benchmark carries."""

from __future__ import annotations

import json
import os
from importlib import metadata

import pytest

from hil_runtime.machine import machine


def test_machine_names_cpu_load_and_versions(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(os, "getloadavg", lambda: (1.234, 0.5, 0.25))
    info = machine("numpy", "no-such-distribution-h10")
    assert set(info) == {"platform", "python", "cpu", "cpu_count", "load_average", "versions"}
    assert info["load_average"] == [1.23, 0.5, 0.25]
    assert info["cpu"] and info["cpu_count"] == os.cpu_count()
    assert info["versions"] == {"numpy": metadata.version("numpy"), "no-such-distribution-h10": None}
    assert json.loads(json.dumps(info)) == info  # plain JSON as it is
