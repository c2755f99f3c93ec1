"""Where a free-running target's period goes under a 1 kHz master: ``hil target serve`` (clock
realtime, deploy/target.ipc.yaml, as ``bench_hil_realtime.py --target-only --master``) with
thread-CPU timers around the parts of its cycle, and a DriveBus exchanging zero torque at 1 kHz
(that benchmark's master, its own CPU, SCHED_FIFO). Prints JSON: the loop thread's CPU per SYNC,
in µs, for each part, from the 200th SYNC on (the master's window), with the machine and the load.

    python benchmarks/bench_target_parts.py [--seconds 10]

Each timer costs ~1 µs of thread CPU (a ``thread_time_ns`` system call on each side), counted in
the part around it: the total is that much above the untimed target's (``timers_per_sync``). A
part missing from the code under test (an older tree, for a before/after) is left out.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from typing import Any

import benchinfo

_FIRST_SYNC = 200  # SYNCs before the window: enabling, the settling exchanges, the phase lock


def _serve_timed(config: str, out: str) -> None:
    """The target with timers, in this process (the child); the per-SYNC means to ``out`` at exit."""
    import atexit

    import pybullet

    import drivers.ipc.bus as ipc
    import sim_target.drives as emulated
    import sim_target.emulated.answer as answer
    import sim_target.emulated.p402 as p402
    import sim_target.plant as plant
    import sim_target.server as server
    from hil_runtime.cli import main

    totals: defaultdict[str, list[int]] = defaultdict(lambda: [0, 0])
    clock = time.thread_time_ns
    window = {"syncs": 0, "cpu_ns": 0}

    def timed(owner: Any, name: str) -> None:
        function = getattr(owner, name, None)
        if function is None:
            return
        label = f"{owner.__name__.rsplit('.', 1)[-1]}.{name}"

        def wrapper(*args: Any, **kwargs: Any) -> Any:
            started = clock()
            try:
                return function(*args, **kwargs)
            finally:
                entry = totals[label]
                entry[0] += 1
                entry[1] += clock() - started

        setattr(owner, name, wrapper)

    for owner, name in [
        (ipc.IpcBus, "_next_datagram"),
        (ipc.IpcBus, "recv_frames"),
        (ipc.IpcBus, "recv_datagram"),
        (ipc.IpcBus, "send_frames"),
        (emulated.EmulatedDrives, "_handle_frames"),
        (emulated.EmulatedDrives, "_handle_cycle"),
        (emulated.EmulatedDrives, "_on_sync"),
        (p402, "step"),
        (p402, "step_all"),
        (answer.SyncAnswer, "send"),
        (answer.SyncAnswer, "_pack"),
        (server.TargetServer, "_on_sync"),
        (server.TargetServer, "_step"),
        (plant.PybulletPlant, "advance"),
        (pybullet, "stepSimulation"),
        (pybullet, "setJointMotorControlArray"),
        (pybullet, "getJointStates"),
    ]:
        timed(owner, name)
    if not hasattr(plant.PybulletPlant, "advance"):  # an older tree: step was the hot path
        timed(plant.PybulletPlant, "step")
    on_sync = emulated.EmulatedDrives._on_sync

    def counting(self: Any, counter: int) -> None:
        window["syncs"] += 1
        if window["syncs"] == _FIRST_SYNC:
            totals.clear()
            window["cpu_ns"] = clock()
        on_sync(self, counter)

    emulated.EmulatedDrives._on_sync = counting  # type: ignore[method-assign]  # the window's start

    def dump() -> None:
        syncs = window["syncs"] - _FIRST_SYNC
        if syncs <= 0:
            return
        means = {label: {"calls": calls / syncs, "us": ns / 1e3 / syncs} for label, (calls, ns) in totals.items()}
        means["total"] = {"calls": 1.0, "us": (clock() - window["cpu_ns"]) / 1e3 / syncs}
        Path(out).write_text(json.dumps({"syncs": syncs, "means": means}))

    atexit.register(dump)  # the target stops cleanly on SIGTERM: atexit runs on the loop thread
    sys.exit(main(["target", "serve", "--config", config]))


def _parts(means: dict[str, dict[str, float]]) -> dict[str, float]:
    """The cycle's parts (µs per SYNC) from the timed functions (nested timers subtracted)."""

    def us(*labels: str) -> float:
        return sum(means.get(label, {}).get("us", 0.0) for label in labels)

    plant_step = us("PybulletPlant.advance", "PybulletPlant.step")
    pybullet_io = us("pybullet.setJointMotorControlArray", "pybullet.getJointStates")
    cia402 = us("p402.step", "p402.step_all")
    parts = {
        "wait_and_receive_datagram": us("IpcBus._next_datagram"),
        "parse_and_latch_rpdos": us("IpcBus.recv_frames", "IpcBus.recv_datagram", "EmulatedDrives._handle_frames")
        + us("EmulatedDrives._handle_cycle")
        - us("IpcBus._next_datagram", "EmulatedDrives._on_sync"),
        "cia402_six_drives": cia402,
        "sync_handler": us("TargetServer._on_sync"),
        "tpdo_pack": us("SyncAnswer._pack"),
        "send_answer": us("IpcBus.send_frames"),
        "answer_rest": us("EmulatedDrives._on_sync")
        - us("SyncAnswer._pack", "IpcBus.send_frames")
        - cia402
        - us("TargetServer._on_sync"),
        "pybullet_step_simulation": us("pybullet.stepSimulation"),
        "pybullet_torque_and_state_calls": pybullet_io,
        "plant_python": plant_step - us("pybullet.stepSimulation") - pybullet_io,
        "server_step_rest": us("TargetServer._step") - plant_step,
    }
    parts["loop_bookkeeping"] = us("total") - sum(parts.values())  # serve_until's loop, the ticks, the watch
    parts["total"] = us("total")
    return {name: round(value, 1) for name, value in parts.items()}


def run(seconds: float) -> dict[str, Any]:
    import yaml
    from bench_hil_realtime import _master

    from sim_target.control import send_control
    from sim_target.launch import wait_ready
    from sim_target.rt_settings import split_cpus

    runtime_cpus, target_cpus = split_cpus("auto")
    root = Path(__file__).resolve().parents[1]
    with tempfile.TemporaryDirectory(prefix="bench-parts-") as tmp:
        sock, out = f"{tmp}/target.sock", f"{tmp}/parts.json"
        config = yaml.safe_load((root / "deploy" / "target.ipc.yaml").read_text())
        config.update(clock="realtime", control_socket=sock, realtime={"cpus": target_cpus})
        config["bus"]["channel"] = f"{tmp}/bus"
        config["plant"].pop("substeps", None)  # the real-time default
        (Path(tmp) / "target.yaml").write_text(yaml.safe_dump(config))

        process = subprocess.Popen(
            [sys.executable, __file__, "--serve", f"{tmp}/target.yaml", out],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, "PYTHONUNBUFFERED": "1"},
        )
        try:
            wait_ready(process)
            time.sleep(1.0)
            cpu_s, wall_s, _exchange_us = _master(f"{tmp}/bus", seconds, runtime_cpus, process.pid)
            status = send_control(sock, {"kind": "status"})
        finally:
            process.terminate()
            process.wait(timeout=30)
        timed = json.loads(Path(out).read_text())
    means = timed["means"]
    return {
        "seconds": seconds,
        "syncs": timed["syncs"],
        "us_per_sync": _parts(means),
        "timers_per_sync": round(sum(m["calls"] for label, m in means.items() if label != "total"), 1),
        "functions_us_per_sync": {label: round(m["us"], 1) for label, m in sorted(means.items())},
        "target_process_cpu_fraction": round(cpu_s / wall_s, 4),
        "lateness": status.get("lateness"),
        "substeps": status.get("substeps"),
    }


def main() -> None:
    if len(sys.argv) == 4 and sys.argv[1] == "--serve":
        _serve_timed(sys.argv[2], sys.argv[3])
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=10.0, help="the master's window")
    args = parser.parse_args()
    load_before = benchinfo.load_average()
    print(benchinfo.report("target_parts", load_before, run(args.seconds)))


if __name__ == "__main__":
    main()
