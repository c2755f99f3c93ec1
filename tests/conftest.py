"""Fixtures shared by the whole suite."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def hil_command() -> list[str]:
    """The ``hil`` console script as a user runs it: the one ``pip install`` put beside this
    interpreter, else the one on PATH. Missing means the install is broken: a failure, not a skip."""
    beside = Path(sys.executable).with_name("hil")
    found = str(beside) if beside.is_file() else shutil.which("hil")
    if found is None:
        pytest.fail("the hil entry point is not installed (pip install -e .)")
    return [found]
