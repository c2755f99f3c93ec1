"""Fixtures shared by the whole suite."""

from __future__ import annotations

import shutil
import signal
import sys
from pathlib import Path

import pytest

# A suite started in the background by a non-interactive shell inherits SIGINT ignored, and an
# ignored signal stays ignored across exec: every child the Ctrl-C tests start would then shrug
# off their SIGINT. A handler (unlike SIG_IGN) is reset to the default on exec, so installing
# Python's own one here gives every child the disposition a terminal would.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


@pytest.fixture(scope="session")
def hil_command() -> list[str]:
    """The ``hil`` console script as a user runs it: the one ``pip install`` put beside this
    interpreter, else the one on PATH. Missing means the install is broken: a failure, not a skip."""
    beside = Path(sys.executable).with_name("hil")
    found = str(beside) if beside.is_file() else shutil.which("hil")
    if found is None:
        pytest.fail("the hil entry point is not installed (pip install -e .)")
    return [found]
