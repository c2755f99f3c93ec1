"""What the source info on every telemetry put costs the publisher thread (docs/telemetry.md, "Who
publishes"): ``Publisher.put(payload)`` against ``put(payload, source_info=SourceInfo(id, sn))``,
a 328-byte state payload (6 joints), interleaved in blocks so load changes hit both alike. The
loop thread never calls put (the publisher thread does), so this is GIL time the publisher takes.

    python benchmarks/bench_telemetry_source_info.py              # 20 blocks of 2000 puts each
"""

from __future__ import annotations

import argparse
import json
import time

import benchinfo
import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--blocks", type=int, default=20)
    parser.add_argument("--block", type=int, default=2000)
    args = parser.parse_args()

    import zenoh

    from hil_runtime.telemetry.config import zenoh_config

    session = zenoh.open(zenoh_config("peer", ["tcp/127.0.0.1:0"], []))
    publisher = session.declare_publisher("hil/bench_arm/state", congestion_control=zenoh.CongestionControl.DROP)
    source_id = publisher.id
    payload = bytes(328)
    plain_us: list[float] = []
    with_info_us: list[float] = []
    sn = 0
    for _ in range(args.blocks):
        for _ in range(args.block):
            start = time.perf_counter_ns()
            publisher.put(payload)
            plain_us.append((time.perf_counter_ns() - start) / 1e3)
        for _ in range(args.block):
            sn += 1
            start = time.perf_counter_ns()
            publisher.put(payload, source_info=zenoh.SourceInfo(source_id, sn))
            with_info_us.append((time.perf_counter_ns() - start) / 1e3)
    publisher.undeclare()
    session.close()
    plain, with_info = benchinfo.spread(plain_us, 2), benchinfo.spread(with_info_us, 2)
    print(
        json.dumps(
            {
                "benchmark": "telemetry_source_info",
                "puts_each": args.blocks * args.block,
                "put_us": plain,
                "put_with_source_info_us": with_info,
                "added_median_us": round(float(np.median(with_info_us) - np.median(plain_us)), 2),
                "machine": benchinfo.machine("eclipse-zenoh"),
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
