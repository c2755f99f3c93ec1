"""How late the pacer starts a cycle after its deadline, sleeping the whole slack or with the hybrid
wait (``loop.spin_s``: sleep, then spin the last stretch), rounds interleaved. The loop does 0.5 ms
of busy work per 1 ms period, on one CPU under SCHED_FIFO as ``hil demo --realtime`` runs it.

    python benchmarks/bench_pacer_wake.py [--cpu 1] [--fifo 50] [--spins-us 0,100,200] [--rounds 3]

Prints JSON: per spin, the cycle start after its deadline (µs median / p99 / max), machine, load.
"""

from __future__ import annotations

import argparse
import os
import time

import benchinfo
import numpy as np

from hil_runtime.pacer import Pacer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cpu", type=int, default=1)
    parser.add_argument("--fifo", type=int, default=50)
    parser.add_argument("--spins-us", default="0,100,200")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--cycles", type=int, default=1500)
    args = parser.parse_args()
    load_before = benchinfo.load_average()
    os.sched_setaffinity(0, {args.cpu})
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.fifo))
    spins = [float(x) * 1e-6 for x in args.spins_us.split(",")]
    late: dict[float, list[float]] = {spin: [] for spin in spins}
    for _ in range(args.rounds):
        for spin in spins:
            pacer = Pacer(1e-3, "clock", spin_s=spin)
            pacer.start()
            for k in range(args.cycles):
                start = pacer.wait()
                if k >= 100:
                    late[spin].append(start - (pacer.started_s + pacer.tick * 1e-3))
                busy_until = time.perf_counter() + 0.5e-3
                while time.perf_counter() < busy_until:
                    pass
    os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    print(
        benchinfo.report(
            "pacer_wake",
            load_before,
            {
                "cycle_start_after_deadline_us": {
                    f"spin_{spin * 1e6:g}us": benchinfo.spread(np.array(v) * 1e6) for spin, v in late.items()
                },
            },
        )
    )


if __name__ == "__main__":
    main()
