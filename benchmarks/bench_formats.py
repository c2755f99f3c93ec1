"""What recording costs the control loop at 1 kHz: the MCAP recorder (``hil run --record x.mcap``)
and the CAN capture (``hil run --can-log x.blf``), each off and on interleaved, then 10 s on
without a break to count what was lost.

A 1 kHz loop (absolute deadlines on the monotonic clock) does a fixed piece of numpy work per
cycle (about the runtime's own compute, as bench_telemetry), then hands the cycle on:

- ``mcap``: ``McapSink.offer_state`` (the copy into the bounded queue; the writer thread encodes
  CDR and writes the file meanwhile) in "on" blocks, ``NullTelemetry`` in "off" blocks;
- ``can``: the 13 frames of a 6-drive CAN FD cycle (SYNC, 6 RPDOs sent, 6 tagged TPDOs received)
  through ``CanCapture.tap`` in "on" blocks (the writer thread hands them to python-can's
  ``can.Logger``), nothing in "off" blocks.

Blocks alternate every ``--block`` cycles so load changes on the machine hit both alike.
``cycle_us`` is work + hand-off (what the loop's budget sees, GIL time taken by the writer thread
included); ``added_cycle_us`` on - off; the budget is 5 % of the period (median). The continuous
phase records ``--continuous-s`` seconds with every cycle on and reports written and dropped.

    python benchmarks/bench_formats.py                     # both, 20 s interleaved + 10 s continuous each
    python benchmarks/bench_formats.py --what can --suffix .asc
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import benchinfo
import can
import numpy as np

JOINTS = ("shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3")
BUDGET_FRACTION = 0.05


def _work(state: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    for _ in range(8):
        state = np.tanh(matrix @ state) + 0.01 * state
    return state


def _cycle_frames() -> list[tuple[can.Message, bool]]:
    from drivers.cia402 import frames as fr

    frames = [(can.Message(arbitration_id=fr.SYNC_COB_ID, data=fr.encode_sync(7), is_extended_id=False), False)]
    for node in range(1, 7):
        rpdo = can.Message(arbitration_id=fr.RPDO1_BASE + node, data=fr.encode_rpdo(0x0F, 120), is_extended_id=False)
        frames.append((rpdo, False))
    for node in range(1, 7):
        data = fr.encode_tpdo_fd_sync(0x0237, 12, 1000 * node, 50, 7)
        tpdo = can.Message(arbitration_id=fr.TPDO1_BASE + node, data=data, is_extended_id=False, is_fd=True)
        frames.append((tpdo, True))
    return frames


def run(what: str, seconds: float, continuous_s: float, block: int, rate_hz: float, suffix: str) -> dict[str, Any]:
    from drivers.capture import CanCapture
    from hil_runtime.formats.mcap_record import McapRecorder, McapSink
    from hil_runtime.telemetry import CycleState

    n = len(JOINTS)
    rng = np.random.default_rng(0)
    matrix = rng.normal(size=(6 * n, 6 * n)) / (6 * n)
    state = rng.normal(size=6 * n)
    period_s = 1.0 / rate_hz
    frames = _cycle_frames()
    directory = Path(tempfile.mkdtemp(prefix="bench-formats-"))
    path = directory / ("run.mcap" if what == "mcap" else f"run{suffix}")
    if what == "mcap":
        sink = McapSink(McapRecorder(path, JOINTS, "bench_arm"))
        sink.start()
    else:
        capture = CanCapture(path)
    load_before = benchinfo.machine()["load_average"]

    def loop(cycles: int, interleaved: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        nonlocal state
        hand_ns = np.zeros(cycles, dtype=np.int64)
        cycle_ns = np.zeros(cycles, dtype=np.int64)
        on = np.zeros(cycles, dtype=bool)
        deadline = time.monotonic()
        for k in range(cycles):
            recording = (k // block) % 2 == 1 if interleaved else True
            deadline += period_s
            delay = deadline - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            late_s = time.monotonic() - deadline
            if late_s > period_s:  # overrun: skip, never catch up in a burst
                deadline += period_s * int(late_s / period_s)
            begin = time.perf_counter_ns()
            state = _work(state, matrix)
            middle = time.perf_counter_ns()
            if recording:
                if what == "mcap":
                    q = state[:n]
                    sink.offer_state(CycleState(k, time.monotonic_ns(), q, q, q, q, q, q, 0.0, 2e-5))
                else:
                    for msg, is_rx in frames:
                        capture.tap(msg, is_rx)
            end = time.perf_counter_ns()
            hand_ns[k], cycle_ns[k], on[k] = end - middle, end - begin, recording
        return hand_ns, cycle_ns, on

    cycles = int(seconds * rate_hz)
    hand_ns, cycle_ns, on = loop(cycles, True)
    mask_on, mask_off = on.copy(), ~on
    mask_on[:block] = mask_off[:block] = False  # the first block warms caches
    result: dict[str, Any] = {"benchmark": f"formats_{what}", "rate_hz": rate_hz, "seconds": seconds, "block": block}
    if what == "can":
        result["capture_format"] = suffix
        result["frames_per_cycle"] = len(frames)
    for name, mask in (("off", mask_off), ("on", mask_on)):
        result[name] = {
            "handoff_us": benchinfo.spread(hand_ns[mask] / 1e3, 2),
            "cycle_us": benchinfo.spread(cycle_ns[mask] / 1e3, 2),
        }
    added = result["on"]["cycle_us"]["median"] - result["off"]["cycle_us"]["median"]
    result["added_cycle_us_median"] = round(added, 2)
    result["added_fraction_of_period_median"] = round(added * 1e-6 / period_s, 4)
    result["budget_fraction_of_period"] = BUDGET_FRACTION
    result["within_budget"] = bool(added * 1e-6 <= BUDGET_FRACTION * period_s)

    before = (sink.offered, sink.dropped) if what == "mcap" else (capture.captured + capture.dropped, capture.dropped)
    continuous = int(continuous_s * rate_hz)
    hand_ns, cycle_ns, _ = loop(continuous, False)
    if what == "mcap":
        sink.close()
        offered, dropped = sink.offered - before[0], sink.dropped - before[1]
        written_total, dropped_total = sink.recorder.states_written, sink.dropped
        unit = "cycles"
    else:
        capture.close()
        offered = capture.captured + capture.dropped - before[0]
        dropped = capture.dropped - before[1]
        written_total, dropped_total = capture.written, capture.dropped
        unit = "frames"
    result["continuous"] = {
        "seconds": continuous_s,
        "cycles": continuous,
        f"offered_{unit}": offered,
        f"dropped_{unit}": dropped,
        f"written_{unit}_whole_file": written_total,
        f"dropped_{unit}_whole_file": dropped_total,
        "handoff_us": benchinfo.spread(hand_ns / 1e3, 2),
        "file_bytes": path.stat().st_size,
    }
    path.unlink()
    directory.rmdir()
    result["machine"] = benchinfo.machine("mcap", "python-can", "numpy")
    result["machine"]["load_average_before"] = load_before
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--what", choices=["mcap", "can", "both"], default="both")
    parser.add_argument("--seconds", type=float, default=20.0, help="interleaved off/on phase")
    parser.add_argument("--continuous-s", type=float, default=10.0, help="all-on phase (losses counted)")
    parser.add_argument("--block", type=int, default=250, help="cycles per off/on block")
    parser.add_argument("--rate-hz", type=float, default=1000.0)
    parser.add_argument("--suffix", choices=[".blf", ".asc", ".log", ".csv"], default=".blf")
    args = parser.parse_args(argv)
    whats = ["mcap", "can"] if args.what == "both" else [args.what]
    results = [run(w, args.seconds, args.continuous_s, args.block, args.rate_hz, args.suffix) for w in whats]
    print(json.dumps(results if len(results) > 1 else results[0], indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
