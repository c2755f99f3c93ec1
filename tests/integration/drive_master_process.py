"""A stand-alone master for the loss-of-master tests: a DriveBus over the loopback bridge (or the
ipc bus) that connects, enables and exchanges until it is killed. Prints {"running": cycle} once
it has run ``--announce-cycles`` cycles, then keeps exchanging (the test kills it with SIGKILL:
no close(), no NMT, no last frame)."""

from __future__ import annotations

import argparse
import json
import time
from typing import Any

import numpy as np

from drivers.config import parse_drive_bus_config
from drivers.drive_bus import DriveBus


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--bridge-url", default="")
    parser.add_argument("--ipc-dir", default="")
    parser.add_argument("--drives", type=int, default=6)
    parser.add_argument("--period-s", type=float, default=0.002)
    parser.add_argument("--comm-loss-timeout-s", type=float, default=0.1)
    parser.add_argument("--announce-cycles", type=int, default=100)
    parser.add_argument("--torque-nm", type=float, default=0.0, help="every joint, every cycle")
    args = parser.parse_args()
    transport: dict[str, Any] = {"fd": True, "data_bitrate": 5_000_000}
    if args.ipc_dir:
        transport.update(interface="ipc", channel=args.ipc_dir)
    else:
        transport.update(interface="remote", channel=args.bridge_url)
    config = parse_drive_bus_config(
        {
            "transport": transport,
            "period_s": args.period_s,
            "joints": [{"name": f"j{n}", "node_id": n, "max_torque_nm": 100.0} for n in range(1, args.drives + 1)],
            "feedback_timeout_s": 0.05,
            "max_missed_cycles": 10_000,  # the config bound (drivers/config.py); the test kills it sooner
            "heartbeat_timeout_s": 2.0,
            "sdo_timeout_s": 2.0,
            "state_change_timeout_s": 5.0,
            "comm_loss_timeout_s": args.comm_loss_timeout_s,
        },
        "drive_master_process",
    )
    bus = DriveBus(config)
    bus.connect()
    bus.enable()
    torque = np.full(args.drives, args.torque_nm)
    next_s = time.monotonic()
    cycle = 0
    while True:
        bus.exchange(torque)
        cycle += 1
        if cycle == args.announce_cycles:
            print(json.dumps({"running": cycle}), flush=True)
        next_s += args.period_s
        time.sleep(max(0.0, next_s - time.monotonic()))


if __name__ == "__main__":
    main()
