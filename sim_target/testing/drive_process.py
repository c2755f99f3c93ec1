"""Emulated drives in a process of their own, for the cross-process drive-bus test and benchmark:
emulated drives and the fake plant on an in-process virtual bus, served to other processes by the
python-can-remote bridge on loopback (or, with ``--ipc-dir``, on the ipc bus in that directory).

    python -m sim_target.testing.drive_process [--drives 6] [--period-s 0.001] [--ipc-dir DIR]

prints ``{"port": N}`` (or ``{"ipc_dir": DIR}``) once ready, and when its stdin closes
``{"plant_steps": N, "syncs": M}`` before it exits. :func:`drive_process` starts it and reads both.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import selectors
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any


def read_json_line(proc: subprocess.Popen[str], timeout_s: float) -> dict[str, Any]:
    """The next line of ``proc``'s stdout as JSON; TimeoutError when none comes in ``timeout_s``."""
    assert proc.stdout is not None and proc.stderr is not None
    selector = selectors.DefaultSelector()
    selector.register(proc.stdout, selectors.EVENT_READ)
    if not selector.select(timeout_s):
        raise TimeoutError(f"drive process printed nothing in {timeout_s} s")
    line = proc.stdout.readline()
    if not line:
        raise RuntimeError(f"drive process exited: {proc.stderr.read()}")
    document: dict[str, Any] = json.loads(line)
    return document


@dataclass
class DriveProcess:
    proc: subprocess.Popen[str]
    ready: dict[str, Any]  # {"port": N} (bridge) or {"ipc_dir": DIR}

    def finish(self, timeout_s: float = 10.0) -> dict[str, Any]:
        """Close its stdin; its summary (plant steps, SYNCs seen) once it has exited."""
        assert self.proc.stdin is not None
        self.proc.stdin.close()
        summary = read_json_line(self.proc, timeout_s)
        self.proc.wait(timeout=timeout_s)
        return summary


@contextlib.contextmanager
def drive_process(*args: str, start_timeout_s: float = 30.0) -> Iterator[DriveProcess]:
    """This module as a child process with ``args``, up to its ready line; stopped afterwards."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "sim_target.testing.drive_process", *args],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        yield DriveProcess(proc, read_json_line(proc, start_timeout_s))
    finally:
        if proc.poll() is None:
            assert proc.stdin is not None
            proc.stdin.close()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()


def main() -> None:
    import can

    from drivers.transport import start_bridge_server
    from sim_target.drives import EmulatedDrives, EmulatedDrivesConfig
    from sim_target.testing.fake_plant import FakePlant, lockstep

    parser = argparse.ArgumentParser()
    parser.add_argument("--channel", default="hil-target")
    parser.add_argument("--drives", type=int, default=6)
    parser.add_argument("--period-s", type=float, default=0.001)
    parser.add_argument("--ipc-dir", help="join the ipc bus in this directory instead of serving a bridge")
    parser.add_argument("--classical", action="store_true", help="ipc bus without CAN FD")
    args = parser.parse_args()
    if args.ipc_dir:
        bridge = None
        bus = can.Bus(interface="ipc", channel=args.ipc_dir, fd=not args.classical)
    else:
        bridge = start_bridge_server("127.0.0.1", 0, args.channel)
        bus = can.Bus(interface="virtual", channel=args.channel, ignore_config=True)
    drives = EmulatedDrives(bus, EmulatedDrivesConfig(node_ids=tuple(range(1, args.drives + 1))))
    plant = FakePlant(args.drives, args.period_s)
    lockstep(drives, plant)
    drives.start()
    print(json.dumps({"port": bridge.port} if bridge is not None else {"ipc_dir": args.ipc_dir}), flush=True)
    sys.stdin.read()  # until the parent closes our stdin (or dies)
    drives.close()
    bus.shutdown()
    if bridge is not None:
        bridge.close()
    print(json.dumps({"plant_steps": plant.steps, "syncs": drives.counters.syncs}), flush=True)


if __name__ == "__main__":
    main()
