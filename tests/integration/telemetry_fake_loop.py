"""A fake control loop publishing telemetry at 1 kHz: the runtime's calls, none of its work.

    python tests/integration/telemetry_fake_loop.py --port 17447 --seconds 5 --timing out.npz

Prints ``ready`` once the sink is started (publishers warm, token declared), then runs an absolute
1 kHz schedule calling ``offer_state`` with values that are a known function of the sample number
(``expected_state``), so a subscriber can check what it decoded. On exit (time up or SIGTERM) it
writes per-cycle timing (monotonic start, lateness, offer cost) and prints the sink's counters.
"""

from __future__ import annotations

import argparse
import json
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import TypedDict

import numpy as np

JOINTS = ("shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3")


class StateValues(TypedDict):
    """CycleState's values after (seq, t_ns), by name."""

    q: np.ndarray
    qd: np.ndarray
    q_ref: np.ndarray
    qd_ref: np.ndarray
    tau: np.ndarray
    tau_fb: np.ndarray
    fallback: float
    compute_s: float


class FakeLoop:
    """The fake loop as a child process, started and ready (publishers warm, token declared)."""

    def __init__(
        self, port: int, seconds: float = 60.0, timing: Path | None = None, controls: Path | None = None
    ) -> None:
        command = [sys.executable, str(Path(__file__)), "--port", str(port), "--seconds", str(seconds)]
        if timing is not None:
            command += ["--timing", str(timing)]
        if controls is not None:
            command += ["--controls", str(controls)]
        self.process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        assert self.process.stdout is not None and self.process.stderr is not None
        line = self.process.stdout.readline().strip()
        if line != "ready":
            self.process.kill()
            raise AssertionError(f"fake loop did not start: {line!r} {self.process.stderr.read()}")
        self.endpoint = f"tcp/127.0.0.1:{port}"

    def finish(self, timeout_s: float = 20.0) -> dict:
        """SIGTERM, wait, and the counters it printed."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
        out, err = self.process.communicate(timeout=timeout_s)
        assert self.process.returncode == 0, err
        return json.loads(out.strip().splitlines()[-1])

    def kill(self) -> None:
        if self.process.poll() is None:
            self.process.kill()
            self.process.wait(10)


def expected_state(seq: int, n: int = len(JOINTS)) -> StateValues:
    """The values sample ``seq`` carries: smooth, distinct per field and joint."""
    t = seq * 1e-3
    j = np.arange(n, dtype=float)
    q = np.sin(t + j)
    q_ref = np.sin(t + j + 0.01)
    return {
        "q": q,
        "qd": np.cos(t + j),
        "q_ref": q_ref,
        "qd_ref": np.cos(t + j + 0.01),
        "tau": 10.0 * (q_ref - q) + j,
        "tau_fb": 9.0 * (q_ref - q) + j,
        "fallback": 1.0 if seq % 100 == 0 else 0.0,
        "compute_s": 1e-5 + 1e-9 * (seq % 1000),
    }


class _Controls:
    def __init__(self) -> None:
        self.stop = False
        self.resets = 0

    def request_stop(self) -> None:
        self.stop = True

    def request_reset(self, activate: bool | None = None) -> None:
        self.resets += 1


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--robot", default="fake_arm")
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--rate-hz", type=float, default=1000.0)
    parser.add_argument("--timing", type=Path, default=None)
    parser.add_argument("--controls", type=Path, default=None, metavar="USERS_FILE", help="controls, usrpwd users")
    parser.add_argument("--off", action="store_true", help="telemetry disabled (NullTelemetry)")
    args = parser.parse_args(argv)

    from hil_runtime.telemetry import CycleState, TelemetryConfig, make_sink
    from hil_runtime.telemetry.auth import TelemetryAuth

    config = TelemetryConfig(
        enabled=not args.off,
        listen=(f"tcp/127.0.0.1:{args.port}",),
        controls_enabled=args.controls is not None,
        auth=None if args.controls is None else TelemetryAuth(users_file=args.controls),
    )
    controls = _Controls()
    info = {
        "joints": list(JOINTS),
        "config": {"robot": args.robot, "period_s": 1.0 / args.rate_hz},
        "bundle": {"bundle_id": "fake:000000000000", "law": "pd", "files": {"policy.onnx": "0" * 64}},
    }
    sink = make_sink(config, args.robot, info, controls if args.controls is not None else None)
    stopping = {"flag": False}
    signal.signal(signal.SIGTERM, lambda *_: stopping.__setitem__("flag", True))
    sink.start()
    sink.set_status("INACTIVE", None)
    sink.set_status("ACTIVE", None)
    print("ready", flush=True)

    period_s = 1.0 / args.rate_hz
    n_max = int(args.seconds * args.rate_hz) + 1
    starts = np.zeros(n_max)
    lateness = np.zeros(n_max)
    offer_ns = np.zeros(n_max, dtype=np.int64)
    t0 = time.monotonic()
    deadline = t0
    seq = 0
    while seq < n_max and not stopping["flag"] and not controls.stop:
        deadline += period_s
        delay = deadline - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        now = time.monotonic()
        if now - deadline > period_s:  # overrun: skip the missed periods, never catch up in a burst
            deadline += period_s * int((now - deadline) / period_s)
        s = expected_state(seq)
        begin = time.perf_counter_ns()
        sink.offer_state(CycleState(seq, time.monotonic_ns(), **s))
        offer_ns[seq] = time.perf_counter_ns() - begin
        starts[seq] = now
        lateness[seq] = now - deadline
        if seq % 1000 == 999:
            sink.offer_stats({"rate_hz": 1000.0 / max(now - starts[seq - 999], 1e-9) * 999 / 1000, "cycles": seq + 1})
        seq += 1
    sink.set_status("FINALIZED", None)
    sink.close()
    counters = getattr(sink, "counters", {})
    if args.timing is not None:
        np.savez(args.timing, start_s=starts[:seq], lateness_s=lateness[:seq], offer_ns=offer_ns[:seq])
    print(
        json.dumps({"cycles": seq, "resets": controls.resets, "stopped_by_control": controls.stop, **counters}),
        flush=True,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
