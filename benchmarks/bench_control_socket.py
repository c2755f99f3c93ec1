"""The control socket under idle clients (issue 20, docs/security.md): a ControlServer (the
runtime's, drivers.json_socket underneath) with N idle connections open, against the same server
with none, in the same run.

Measures the threads the process has (the old server made one per connection: 3,000 idle clients
made 3,013 threads and starved the master heartbeat), how many idle clients were closed (at most
MAX_CLIENTS are served at once; a newcomer closes the longest idle), and the round trip of
``status`` requests from a fresh client, with and without the idlers: median / p99 / max in ms
and the ratio of the medians.

    python benchmarks/bench_control_socket.py                  # 3000 idle clients, 200 requests
    python benchmarks/bench_control_socket.py --idle 500 --requests 1000
"""

from __future__ import annotations

import argparse
import json
import socket
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import benchinfo

from hil_runtime.control import ControlServer, send_command


class _Target:
    def status(self) -> dict[str, Any]:
        return {"state": "ACTIVE", "fault": None}

    def request_stop(self) -> None:
        pass

    def request_reset(self) -> None:
        pass

    def request_activate(self) -> None:
        pass


def _round_trips_ms(path: Path, requests: int) -> list[float]:
    out = []
    for _ in range(requests):
        t0 = time.perf_counter()
        send_command(path, "status")
        out.append((time.perf_counter() - t0) * 1e3)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--idle", type=int, default=3000, help="idle connections opened")
    parser.add_argument("--requests", type=int, default=200, help="status requests timed per phase")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "control.sock"
        server = ControlServer(path, _Target())
        try:
            threads_idle_free = threading.active_count()
            quiet = _round_trips_ms(path, args.requests)
            idle = []
            for _ in range(args.idle):
                sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
                sock.connect(str(path))
                idle.append(sock)
            time.sleep(0.5)  # the server has accepted (or refused) them all
            threads_with_idle = threading.active_count()
            loaded = _round_trips_ms(path, args.requests)
            served = server._server.client_count
            evicted = server._server.evicted
            for sock in idle:
                sock.close()
        finally:
            server.close()
    quiet_spread, loaded_spread = benchinfo.spread(quiet, 3), benchinfo.spread(loaded, 3)
    print(
        json.dumps(
            {
                "benchmark": "control_socket",
                "idle_clients": args.idle,
                "threads": {"without_idle_clients": threads_idle_free, "with_idle_clients": threads_with_idle},
                "idle_clients_served": served,
                "idle_clients_evicted": evicted,
                "status_round_trip_ms": {"without_idle_clients": quiet_spread, "with_idle_clients": loaded_spread},
                "median_ratio_with_to_without": round(loaded_spread["median"] / quiet_spread["median"], 2),
                "machine": benchinfo.machine(),
            },
            indent=2,
        )
    )


if __name__ == "__main__":
    main()
