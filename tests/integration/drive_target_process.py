"""A stand-alone target process for the cross-process drive-bus test and benchmark: emulated drives
and the fake plant on an in-process virtual bus, served to other processes by the python-can-remote
bridge on loopback (or, with ``--ipc-dir``, on the ipc bus in that directory). Prints {"port": N}
(or {"ipc_dir": DIR}) once ready; exits when its stdin closes."""

from __future__ import annotations

import argparse
import json
import sys

import can

from drivers.transport import start_bridge_server
from sim_target.drives import EmulatedDrives, EmulatedDrivesConfig
from sim_target.testing.fake_plant import FakePlant, lockstep


def main() -> None:
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
