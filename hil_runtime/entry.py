"""The ``hil`` console script.

It imports the CLI (typer, numpy, onnxruntime, zenoh: a few hundred milliseconds) under a SIGINT
handler of its own, so a Ctrl-C while Python is still importing exits 130 with one line instead of a
traceback; once the CLI is loaded, ``hil_runtime.cli.main`` handles Ctrl-C itself.
"""

from __future__ import annotations

import signal
import sys
from types import FrameType

INTERRUPTED_WHILE_STARTING = "interrupted (Ctrl-C) while starting: nothing was started"


def _interrupted_while_starting(signum: int, frame: FrameType | None) -> None:
    print(INTERRUPTED_WHILE_STARTING, file=sys.stderr, flush=True)
    raise SystemExit(130)


def main() -> int:
    """Load the CLI with Ctrl-C mapped to exit 130, then run it; the process's exit code."""
    previous = signal.signal(signal.SIGINT, _interrupted_while_starting)
    try:
        from hil_runtime.cli import main as cli_main
    finally:
        signal.signal(signal.SIGINT, previous)
    return cli_main()
