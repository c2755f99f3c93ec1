"""Six CiA 402 drives lock-stepped with the pybullet target, driven by the driver master
(drivers/drive_bus.py), paced at the control rate with absolute deadlines (``next += period``;
an overrun is counted and the missed periods skipped, never run in a burst).

- ``inprocess``: target and driver in one process on python-can's ``virtual`` bus, 1 kHz, CAN FD.
- ``bridge``: the target as ``hil target serve`` in another process, its bus served by the
  python-can-remote bridge on 127.0.0.1, 500 Hz, CAN FD.
- ``ipc``: the target as ``hil target serve`` in another process on the project's ipc bus (Unix
  sockets, drivers/ipc), 1 kHz, CAN FD.

Per mode: achieved exchange rate, exchange latency (``DriveBus.exchange``: RPDOs + SYNC out, every
TPDO back) median / p99 / max, also as % of the period, the cycle period (start to start) median /
p99 / max, cycles whose latency exceeded the period,
overruns, and frames lost: SYNCs the target never saw plus TPDOs that never arrived (missing at
their cycle's deadline and not received late either). Prints one JSON document.

    python benchmarks/bench_hil_lockstep.py                 # 60 s per mode
    python benchmarks/bench_hil_lockstep.py --duration 10 --mode inprocess
    python benchmarks/bench_hil_lockstep.py --mode ipc      # budget: >= 995 Hz, p99 <= 1 ms, 0 lost
"""

from __future__ import annotations

import argparse
import json
import os
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import benchinfo
import numpy as np

from drivers.drive_bus import DriveBus
from drivers.ipc.bus import IpcBus
from drivers.transport import open_bus
from models.dynamics import make_dynamics
from models.robots import load_robot
from sim_target.drives import EmulatedDrives
from sim_target.server import send_control
from sim_target.testing.hil_target import drive_bus_config, target_in_process, target_process, unique_channel
from sim_target.testing.ur5 import Q0_RAD

# The benchmark measures losses rather than stopping at the first stale cycle.
# Likewise the drives' master-loss watchdog: a scheduler stall of 100 ms on a loaded machine must
# show up in the figures, not fault the drives.
BENCH_DRIVER = {"max_missed_cycles": 10_000, "heartbeat_timeout_s": 1.0, "comm_loss_timeout_s": 1.0}
RT_PRIORITY = 50  # --rt: SCHED_FIFO for the driver's thread and every thread of the target process


def realtime(pid: int | None = None) -> bool:
    """SCHED_FIFO for this thread (``pid`` None) or every thread of process ``pid``; False if refused."""
    tids = [0] if pid is None else [int(t) for t in os.listdir(f"/proc/{pid}/task")]
    try:
        for tid in tids:
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(RT_PRIORITY))
    except (PermissionError, OSError):
        return False
    return True


def _run(bus: DriveBus, period_s: float, duration_s: float, rt: bool = False) -> dict[str, Any]:
    rt_granted = realtime() if rt else False  # before connect(): the driver's rx thread inherits it
    dynamics = make_dynamics(load_robot("ur5_paper"), backend="pinocchio")  # ~10 µs (own RNE: ~600 µs)
    amplitude = np.array([0.05, 0.3, 0.1, 0.02, 0.005, 0.001])
    bus.connect()
    bus.enable()
    start_counters = bus.counters
    n = int(round(duration_s / period_s))
    latency = np.empty(n)
    starts = np.empty(n)
    stale = 0
    overruns = 0
    q = np.array(Q0_RAD)
    exchange = bus.exchange
    perf = time.perf_counter
    t0 = next_s = perf()
    k = 0
    while k < n:
        torque = dynamics.gravity(q) + amplitude * np.sin(2 * np.pi * 0.5 * k * period_s)
        a = perf()
        starts[k] = a
        feedback = exchange(torque)
        latency[k] = perf() - a
        if not feedback.fresh.all():
            stale += 1
        q = feedback.position_rad
        k += 1
        next_s += period_s
        now = perf()
        if now > next_s:  # overran: skip the periods already past
            missed = int((now - next_s) // period_s) + 1
            overruns += 1
            next_s += missed * period_s
        else:
            while perf() < next_s - 2e-4:  # sleep coarse, spin the last 200 µs
                time.sleep(max(0.0, next_s - perf() - 3e-4))
            while perf() < next_s:
                pass
    elapsed = perf() - t0
    time.sleep(0.1)  # let late TPDOs arrive before counting what never came
    end = bus.counters
    dropped = end.dropped - start_counters.dropped
    late = end.late - start_counters.late
    latency_us = latency * 1e6
    period_us = period_s * 1e6
    cycle_us = np.diff(starts) * 1e6
    if rt_granted:
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    return {
        "sched_fifo": rt_granted,
        "cycles": n,
        "period_s": period_s,
        "elapsed_s": round(elapsed, 3),
        "achieved_rate_hz": round(n / elapsed, 1),
        "latency_us": benchinfo.spread(latency_us),
        "latency_pct_of_period": {
            "median": round(float(np.median(latency_us)) / period_us * 100, 1),
            "p99": round(float(np.percentile(latency_us, 99)) / period_us * 100, 1),
        },
        "cycle_period_us": benchinfo.spread(cycle_us),
        "cycles_over_period": int((latency_us > period_us).sum()),
        "overruns": overruns,
        "stale_cycles": stale,  # some TPDO missing at the feedback deadline (arrived late or never)
        "tpdos_missing_at_deadline": dropped,
        "tpdos_late": late,
        "tpdos_lost": dropped - late,
        "frames_sent": end.frames_sent - start_counters.frames_sent,
        "frames_received": end.frames_received - start_counters.frames_received,
        "malformed": end.malformed - start_counters.malformed,
        "feedback_timeout_s": bus.config.feedback_timeout_s,
    }


def bench_inprocess(duration_s: float, period_s: float, substeps: int, rt: bool = False) -> dict[str, Any]:
    channel = unique_channel()
    with target_in_process(channel, period_s, substeps=substeps) as target:
        bus = DriveBus(drive_bus_config({"interface": "virtual", "channel": channel}, period_s, **BENCH_DRIVER))
        try:
            result = _run(bus, period_s, duration_s, rt)
            result["syncs_lost"] = bus.counters.cycles - target.stats.syncs
        finally:
            bus.close()
        assert isinstance(target.drives, EmulatedDrives)  # the server's DriveBank protocol has no counters
        drives = target.drives.counters
        result["target_frames_received"] = drives.frames_received
        result["target_frames_sent"] = drives.frames_sent
    result["frames_lost"] = result["syncs_lost"] + result["tpdos_lost"]
    return {"mode": "inprocess", "transport": "virtual, CAN FD", "substeps": substeps, **result}


def bench_bridge(duration_s: float, period_s: float, substeps: int, rt: bool = False) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as tmp, target_process(Path(tmp), period_s, substeps=substeps) as target:
        target_rt = realtime(target.process.pid) if rt else False
        bus = DriveBus(
            drive_bus_config({"interface": "remote", "channel": target.bridge_url}, period_s, **BENCH_DRIVER)
        )
        try:
            result = _run(bus, period_s, duration_s, rt)
            status = send_control(target.control_socket, {"kind": "status"})
            result["syncs_lost"] = bus.counters.cycles - status["syncs"]
            result["target_sched_fifo"] = target_rt
        finally:
            bus.close()
        code, _ = target.stop()
        result["target_exit_code"] = code
    result["frames_lost"] = result["syncs_lost"] + result["tpdos_lost"]
    return {"mode": "bridge", "transport": "python-can-remote on 127.0.0.1, CAN FD", "substeps": substeps, **result}


def bench_ipc(duration_s: float, period_s: float, substeps: int, rt: bool = False) -> dict[str, Any]:
    with (
        tempfile.TemporaryDirectory() as tmp,
        target_process(Path(tmp), period_s, substeps=substeps, transport="ipc") as target,
    ):
        target_rt = realtime(target.process.pid) if rt else False
        config = drive_bus_config({"interface": "ipc", "channel": str(target.ipc_dir)}, period_s, **BENCH_DRIVER)
        ipc_bus = open_bus(config.transport)  # ours, to read its counters
        assert isinstance(ipc_bus, IpcBus)
        bus = DriveBus(config, bus=ipc_bus)
        try:
            result = _run(bus, period_s, duration_s, rt)
            status = send_control(target.control_socket, {"kind": "status"})
            result["syncs_lost"] = bus.counters.cycles - status["syncs"]
            result["ipc_frames_dropped"] = ipc_bus.stats.frames_dropped  # to a full peer queue
            result["target_sched_fifo"] = target_rt
        finally:
            bus.close()
            ipc_bus.shutdown()
        code, _ = target.stop()
        result["target_exit_code"] = code
    result["frames_lost"] = result["syncs_lost"] + result["tpdos_lost"]
    return {
        "mode": "ipc",
        "transport": "ipc bus (Unix SOCK_SEQPACKET, drivers/ipc), CAN FD",
        "substeps": substeps,
        **result,
    }


def machine() -> dict[str, Any]:
    return benchinfo.machine("python-can", "python-can-remote", "canopen", "pybullet", "numpy")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=60.0, help="seconds per mode (default 60)")
    parser.add_argument("--mode", choices=["all", "inprocess", "bridge", "ipc"], default="all")
    parser.add_argument("--inprocess-period", type=float, default=0.001)
    parser.add_argument("--bridge-period", type=float, default=0.002)
    parser.add_argument("--inprocess-substeps", type=int, default=32)
    parser.add_argument("--bridge-substeps", type=int, default=64)
    parser.add_argument("--ipc-period", type=float, default=0.001)
    parser.add_argument("--ipc-substeps", type=int, default=32)
    parser.add_argument(
        "--rt",
        action="store_true",
        help=f"SCHED_FIFO {RT_PRIORITY} for the driver thread and the target process (CAP_SYS_NICE)",
    )
    args = parser.parse_args()
    out: dict[str, Any] = {
        "benchmark": "hil_lockstep",
        "drives": 6,
        "duration_s": args.duration,
        "machine_before": machine(),
        "results": [],
    }
    if args.mode in ("all", "inprocess"):
        out["results"].append(bench_inprocess(args.duration, args.inprocess_period, args.inprocess_substeps, args.rt))
    if args.mode in ("all", "bridge"):
        out["results"].append(bench_bridge(args.duration, args.bridge_period, args.bridge_substeps, args.rt))
    if args.mode in ("all", "ipc"):
        out["results"].append(bench_ipc(args.duration, args.ipc_period, args.ipc_substeps, args.rt))
    out["load_average_after"] = [round(x, 2) for x in os.getloadavg()]
    for result in out["results"]:
        if result["mode"] == "ipc":  # issue 12: across processes at 1 ms
            result["targets"] = {
                "rate>=995Hz": result["achieved_rate_hz"] >= 995.0,
                "p99_latency<=period": result["latency_us"]["p99"] <= result["period_s"] * 1e6,
                "p99_cycle<=period*1.05": result["cycle_period_us"]["p99"] <= result["period_s"] * 1e6 * 1.05,
                "zero_frames_lost": result["frames_lost"] == 0,
            }
            continue
        target_hz = 1000 if result["mode"] == "inprocess" else 500
        result["targets"] = {
            f"rate>={target_hz}Hz": result["achieved_rate_hz"] >= target_hz * 0.995,
            "p99<=30%": result["latency_pct_of_period"]["p99"] <= 30.0,
            "zero_frames_lost": result["frames_lost"] == 0,
        }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    threading.current_thread().name = "bench"
    main()
