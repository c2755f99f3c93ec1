"""The machine's real-time floor: what a bare 1 kHz loop gets, with no bus, no policy and no target.

One SCHED_FIFO process per CPU, each pinned, paced like the runtime's loop (absolute deadlines, sleep
then spin the last 100 µs) and busy for a fixed share of each period: ``--work-us`` on the runtime's
CPU (the cycle's cost), ``--target-work-us`` on the other (the target's physics). What it prints (JSON):
how late each cycle started, how many periods ran over 1.2 and 2 ms, the longest stall. A free-running
HIL run cannot do better than this floor; the runs' own stalls compare with it (docs/runtime.md).

    python benchmarks/bench_machine_floor.py                  # 20 s, 450 µs + 150 µs of work
    python benchmarks/bench_machine_floor.py --seconds 60 --work-us 300

Needs SCHED_FIFO (root or LimitRTPRIO); without it the loop runs SCHED_OTHER and says so.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import time
from typing import Any

import benchinfo
import numpy as np

PERIOD_S = 1e-3
SPIN_S = 100e-6  # the runtime's default hybrid wait (hil_runtime.config.DEFAULT_SPIN_S)


def paced_loop(cpu: int, work_us: float, seconds: float) -> dict[str, Any]:
    """The loop on ``cpu``: start lateness (µs) and periods over 1.2 / 2 ms."""
    os.sched_setaffinity(0, {cpu})
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(80))
        policy = "SCHED_FIFO 80"
    except OSError as exc:
        policy = f"SCHED_OTHER (SCHED_FIFO refused: {exc.strerror})"
    import gc

    gc.disable()
    n = int(seconds / PERIOD_S)
    starts = np.zeros(n)
    monotonic = time.monotonic
    t0 = deadline = monotonic()
    for i in range(n):
        deadline += PERIOD_S
        slack = deadline - monotonic()
        if slack > SPIN_S:
            time.sleep(slack - SPIN_S)
        while monotonic() < deadline:
            pass
        starts[i] = start = monotonic()
        end = start + work_us * 1e-6
        while monotonic() < end:
            pass
    late_us = (starts - (t0 + PERIOD_S * np.arange(1, n + 1))) * 1e6
    period_us = np.diff(starts) * 1e6
    return {
        "cpu": cpu,
        "policy": policy,
        "work_us": work_us,
        "periods": n,
        "start_late_us": benchinfo.spread(late_us),
        "periods_over_1200_us": int((period_us > 1200).sum()),
        "periods_over_2000_us": int((period_us > 2000).sum()),
        "longest_period_us": round(float(period_us.max()), 1),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0)
    parser.add_argument("--work-us", type=float, default=450.0, help="busy work per period on the last CPU")
    parser.add_argument("--target-work-us", type=float, default=150.0, help="on the CPU before it (0: none)")
    args = parser.parse_args()
    if not 0 <= args.work_us < 900 or not 0 <= args.target_work_us < 900:
        parser.error("--work-us and --target-work-us must be in [0, 900) µs of the 1000 µs period")
    load_before = benchinfo.load_average()
    cpus = sorted(os.sched_getaffinity(0))
    jobs = [(cpus[-1], args.work_us)]
    if args.target_work_us > 0 and len(cpus) > 1:
        jobs.append((cpus[-2], args.target_work_us))
    with multiprocessing.get_context("fork").Pool(len(jobs)) as pool:
        loops = pool.starmap(paced_loop, [(cpu, work, args.seconds) for cpu, work in jobs])
    print(
        benchinfo.report("machine_floor", load_before, {"period_s": PERIOD_S, "seconds": args.seconds, "loops": loops})
    )


if __name__ == "__main__":
    main()
