"""Free-running HIL at 1 kHz: ``hil run`` against ``hil target serve`` (clock realtime), both on
their own clocks, each on its own CPU with SCHED_FIFO (``hil demo --realtime``'s set-up), for one
law and mode. Prints JSON: the loop's period (median, p99, max), overruns, compute and exchange
times, the target's lateness (late ticks, skipped periods, worst lag, its physics thread's CPU
share), the run's validity, its scores, the machine and its load average; with
``--compare-lockstep`` also the lock-step run of the same law and mode and the relative change of
the composite score.

    python benchmarks/bench_hil_realtime.py --law pd --mode fb [--duration 5] [--condition C1]
    python benchmarks/bench_hil_realtime.py --law mrac --mode lmpc --duration 60   # a soak
    python benchmarks/bench_hil_realtime.py --all [--compare-lockstep]             # 6 laws x fb, lmpc
    python benchmarks/bench_hil_realtime.py --target-only 10            # the target alone, brakes holding
    python benchmarks/bench_hil_realtime.py --target-only 10 --master   # + a master at 1 kHz, drives enabled

``--target-only``: ``hil target serve`` (deploy/target.ipc.yaml with ``clock: realtime``) for that
many seconds, alone or with a DriveBus master exchanging zero torque at 1 kHz from this process
(its own CPU, SCHED_FIFO): the target process's CPU share (/proc), its physics thread's, its
lateness, and (with a master) the exchange times the master saw.

Run it on a quiet machine: the figures are the machine's (docs/runtime.md); the load average
before and after is in the JSON.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
from pathlib import Path
from typing import Any

import benchinfo

LAWS = ("pd", "pid", "adrc", "hinf", "smc", "mrac")
MODES = ("fb", "lmpc")


def run_one(law: str, mode: str, duration_s: float | None, condition: str, realtime: bool, cpus: str) -> dict[str, Any]:
    """One ``hil demo`` run (headless), its figures."""
    from models.demo.options import DemoOptions
    from models.demo.run import run_demo

    options = DemoOptions(law=law, mode=mode, condition=condition, duration_s=duration_s, realtime=realtime, cpus=cpus)
    with tempfile.TemporaryDirectory(prefix="bench-hil-rt-") as tmp:
        results = run_demo(options, Path(tmp) / "out", headless=True)
        effort = run_effort(Path(tmp) / "out" / "runtime_record.npz")
    timing = results["timing"]
    scores = results["scores"]
    target = results.get("target") or {}
    return {
        "law": law,
        "mode": mode,
        "clock": "realtime" if realtime else "lockstep",
        "condition": condition,
        "duration_s": results["demo"]["duration_s"],
        "fault": results["fault"],
        "valid": results.get("valid", True),
        "invalid_reason": results.get("invalid_reason"),
        "cycles": timing["cycles"],
        "rate_hz": timing["rate_hz"],
        "overruns": timing["overruns"],
        "overrun_fraction": round(timing["overruns"] / timing["cycles"], 5) if timing["cycles"] else None,
        "skipped_periods": timing.get("skipped_periods"),
        "period_us": timing["period_us"],
        "compute_us": timing["compute_us"],
        "exchange_us": timing.get("exchange_us"),
        "target_lateness": target.get("lateness"),
        "target_realtime": target.get("realtime"),
        "composite_hil": scores["composite"]["hil"],
        "metrics_hil": scores["metrics"]["hil"],
        "effort_hil": effort,
    }


def run_effort(record: Path) -> dict[str, Any] | None:
    """The effort the HIL run took, from the runtime's record (models.effort's measures, per joint: RMS
    torque, the RMS and largest cycle-to-cycle change; pooled ratios to the torque limits)."""
    import numpy as np

    from models.effort import effort_metrics
    from models.robots import load_robot

    if not record.exists():
        return None
    with np.load(record) as data:
        tau, qd = data["tau"], data["qd"]
    robot = load_robot("ur5_paper")  # the demo's default robot, the one this benchmark runs
    figures = effort_metrics(tau, qd, np.asarray(robot.torque_limit_nm, float), 1e-3)
    keep = ("torque_rms_nm", "chatter_nm", "max_torque_step_nm", "torque_rms_ratio", "chatter_ratio")
    return {key: figures[key] for key in keep}


def target_only(seconds: float, master: bool, substeps: int | None) -> dict[str, Any]:
    """The realtime target in its own process, alone or under a 1 kHz master; its cost and lateness."""
    import time

    import numpy as np
    import yaml

    from sim_target.control import send_control
    from sim_target.launch import start_hil, wait_ready
    from sim_target.rt_settings import split_cpus

    runtime_cpus, target_cpus = split_cpus("auto")
    root = Path(__file__).resolve().parents[1]
    with tempfile.TemporaryDirectory(prefix="bench-target-") as tmp:
        sock = f"{tmp}/target.sock"
        config = yaml.safe_load((root / "deploy" / "target.ipc.yaml").read_text())
        config.update(clock="realtime", control_socket=sock, realtime={"cpus": target_cpus})
        config["bus"]["channel"] = f"{tmp}/bus"
        config["plant"].pop("substeps", None)  # the realtime default, unless asked
        if substeps is not None:
            config["plant"]["substeps"] = substeps
        (Path(tmp) / "target.yaml").write_text(yaml.safe_dump(config))
        process = start_hil("target", "serve", "--config", f"{tmp}/target.yaml")
        try:
            wait_ready(process)
            time.sleep(1.0)  # start-up (cost probe, real-time settings) out of the window
            exchange_us: list[float] = []
            if master:
                cpu_s, wall_s, exchange_us = _master(f"{tmp}/bus", seconds, runtime_cpus, process.pid)
            else:
                cpu0_s, wall0_s = _process_cpu_s(process.pid), time.monotonic()
                time.sleep(seconds)
                cpu_s, wall_s = _process_cpu_s(process.pid) - cpu0_s, time.monotonic() - wall0_s
            status = send_control(sock, {"kind": "status"})
        finally:
            process.terminate()
            process.wait(timeout=30)
    out: dict[str, Any] = {
        "mode": "target + master at 1 kHz, drives enabled" if master else "target alone, brakes holding",
        "seconds": seconds,
        "target_process_cpu_fraction": round(cpu_s / wall_s, 4),
        "lateness_since_start": status.get("lateness"),
        "realtime": status.get("realtime"),
        "substeps": status.get("substeps"),
    }
    if exchange_us:
        out["master_exchange_us"] = benchinfo.spread(np.array(exchange_us))
    return out


def _process_cpu_s(pid: int) -> float:
    """utime + stime of the process, every thread (/proc/PID/stat)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _master(channel: str, seconds: float, cpus: tuple[int, ...] | None, pid: int) -> tuple[float, float, list[float]]:
    """A DriveBus at 1 kHz, zero torque, drives enabled, on its own CPU with SCHED_FIFO; returns
    the target's CPU seconds and the wall seconds of the window, and the exchange times (µs)."""
    import time

    import numpy as np

    from drivers.drive_bus import DriveBus
    from sim_target.testing.hil_target import drive_bus_config

    config = drive_bus_config({"interface": "ipc", "channel": channel}, 1e-3)
    exchange_us = []
    with DriveBus(config) as bus:
        bus.enable()
        if cpus:
            os.sched_setaffinity(0, set(cpus))
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(80))
        except OSError as exc:
            print(f"bench: SCHED_FIFO refused ({exc.strerror}); the master runs without it", file=sys.stderr)
        zero = np.zeros(6)
        try:
            for _ in range(500):  # settle: the target's phase lock, the caches
                bus.exchange(zero)
            started = deadline = time.monotonic()
            cpu0_s = _process_cpu_s(pid)
            while time.monotonic() - started < seconds:
                deadline += 1e-3
                delay = deadline - time.monotonic()
                if delay > 0:
                    time.sleep(delay)
                t0 = time.perf_counter()
                bus.exchange(zero)
                exchange_us.append((time.perf_counter() - t0) * 1e6)
            cpu_s, wall_s = _process_cpu_s(pid) - cpu0_s, time.monotonic() - started
        finally:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    return cpu_s, wall_s, exchange_us


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--law", choices=LAWS, default="pd")
    parser.add_argument("--mode", choices=MODES, default="fb")
    parser.add_argument("--all", action="store_true", help="every law in fb and lmpc")
    parser.add_argument("--duration", type=float, default=None, help="seconds (default: the condition's, 5 s)")
    parser.add_argument("--condition", default="C1")
    parser.add_argument("--cpus", default="auto", help="runtime,target CPUs: auto, none or R,T")
    parser.add_argument("--compare-lockstep", action="store_true", help="also run lock-step; compare the scores")
    parser.add_argument("--target-only", type=float, default=None, metavar="SECONDS", help="the target's own cost")
    parser.add_argument("--master", action="store_true", help="--target-only: under a 1 kHz master")
    parser.add_argument("--substeps", type=int, default=None, help="--target-only: pybullet substeps")
    args = parser.parse_args()
    load_before = benchinfo.load_average()
    if args.target_only is not None:
        result = target_only(args.target_only, args.master, args.substeps)
        result.update(
            benchmark="hil_realtime_target",
            command="python " + " ".join(sys.argv),
            machine=benchinfo.machine(),
            load_average_before=load_before,
            load_average_after=[round(x, 2) for x in os.getloadavg()],
        )
        print(json.dumps(result, indent=1))
        return
    pairs = [(law, mode) for mode in MODES for law in LAWS] if args.all else [(args.law, args.mode)]
    runs = []
    for law, mode in pairs:
        row: dict[str, Any]
        try:
            row = run_one(law, mode, args.duration, args.condition, True, args.cpus)
        except Exception as exc:  # noqa: BLE001 - one failing run is a row, the benchmark goes on
            row = {"law": law, "mode": mode, "clock": "realtime", "error": f"{type(exc).__name__}: {exc}"}
        if args.compare_lockstep and "error" not in row:
            lock = run_one(law, mode, args.duration, args.condition, False, args.cpus)
            row["lockstep_composite"] = lock["composite_hil"]
            row["lockstep_fault"] = lock["fault"]
            ref = lock["composite_hil"]
            row["composite_change_vs_lockstep"] = (
                round((row["composite_hil"] - ref) / ref, 4) if ref and math.isfinite(ref) else None
            )
        print(json.dumps(row), file=sys.stderr, flush=True)  # progress: one line per run
        runs.append(row)
    print(
        benchinfo.report(
            "hil_realtime",
            load_before,
            {
                "period_s": 1e-3,
                "runs": runs,
                "all_valid_without_fault": all(r.get("valid") and not r.get("fault") for r in runs),
            },
        )
    )


if __name__ == "__main__":
    main()
