"""The ``hil`` console script: a Ctrl-C while the CLI is still being imported exits 130 in one line."""

from __future__ import annotations

import subprocess
import sys

# A finder that raises SIGINT in the middle of importing hil_runtime.cli (a Ctrl-C during start-up).
SCRIPT = """
import os, signal, sys, time
class CtrlCDuringImport:
    def find_spec(self, name, path=None, target=None):
        if name == "hil_runtime.cli":
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1.0)  # the handler runs here
        return None
sys.meta_path.insert(0, CtrlCDuringImport())
from hil_runtime.entry import main
sys.exit(main())
"""


def test_ctrl_c_while_importing_the_cli_exits_130_in_one_line() -> None:
    done = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=60)
    assert done.returncode == 130
    assert done.stderr.strip().splitlines() == ["interrupted (Ctrl-C) while starting: nothing was started"]
    assert "Traceback" not in done.stderr


def test_without_ctrl_c_the_entry_point_runs_the_cli() -> None:
    done = subprocess.run(
        [
            sys.executable,
            "-c",
            "import sys; from hil_runtime.entry import main; sys.argv = ['hil', '--help']; sys.exit(main())",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert "run" in done.stdout and "experiment" in done.stdout
