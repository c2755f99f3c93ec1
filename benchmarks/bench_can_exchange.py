"""Benchmark: one DriveBus.exchange per control cycle with N emulated CiA 402 drives.

Prints JSON: per-exchange latency (median, p99, max), the master thread's own CPU time per exchange
(``master_cpu_us``: the driver's work, the waits for the drives left out), achieved rate, overruns, frames lost/late,
the bus-load budget of the configuration, the codec cost per frame against the canopen library's
PDO objects (why the cyclic path has its own codec), and machine info.

    python benchmarks/bench_can_exchange.py                       # 6 drives, 1 kHz, CAN FD, in-process
    python benchmarks/bench_can_exchange.py --mode bridge --rate-hz 500   # across processes (loopback)
    python benchmarks/bench_can_exchange.py --mode ipc            # across processes on the ipc bus
    python benchmarks/bench_can_exchange.py --unpaced             # back-to-back: the ceiling

The plant is the fake double integrator of sim_target/testing/fake_plant.py (lock-stepped: each SYNC
steps it one period); the pybullet plant's version lives with the target server.
"""

from __future__ import annotations

import argparse
import gc
import json
import time
import timeit
import uuid
from pathlib import Path
from typing import Any

import benchinfo
import can
import canopen
import numpy as np

from drivers.cia402 import frames as fr
from drivers.cia402.od import EDS_PATH
from drivers.config import parse_drive_bus_config
from drivers.drive_bus import DriveBus
from sim_target.testing.drive_process import drive_process


def _config(args: argparse.Namespace, transport: dict[str, Any]) -> Any:
    if args.fd:
        transport = {**transport, "fd": True, "data_bitrate": args.data_bitrate}
    return parse_drive_bus_config(
        {
            "transport": {**transport, "bitrate": args.bitrate},
            "period_s": 1.0 / args.rate_hz,
            "feedback_timeout_s": args.feedback_timeout_s,
            "max_missed_cycles": 10_000,  # count, don't stop (the config's maximum): the benchmark reports losses
            "comm_loss_timeout_s": 5.0,  # nor may the drives stop on a stall of this loaded machine
            "joints": [{"name": f"j{i}", "node_id": i + 1, "max_torque_nm": 150.0} for i in range(args.drives)],
        },
        "benchmark",
    )


def _run_loop(driver: DriveBus, args: argparse.Namespace) -> dict[str, Any]:
    period_s = 1.0 / args.rate_hz
    cycles = int(args.seconds * args.rate_hz)
    latencies = np.empty(cycles)
    cpu_s = np.empty(cycles)
    thread_time = time.thread_time
    torque = np.linspace(-1.0, 1.0, driver.n_joints)
    driver.enable()
    for _ in range(100):  # warm-up
        driver.exchange(torque)
    before = driver.counters
    gc.collect()
    gc.freeze()  # as the runtime loop does: no collector pauses inside the measured cycles
    gc.disable()
    overruns = 0
    start = time.perf_counter()
    next_s = start
    for k in range(cycles):
        c0 = thread_time()
        t0 = time.perf_counter()
        driver.exchange(torque)
        t1 = time.perf_counter()
        cpu_s[k] = thread_time() - c0
        latencies[k] = t1 - t0
        if args.unpaced:
            continue
        next_s += period_s
        if t1 > next_s:  # overran: skip the periods already past, never burst
            overruns += 1
            next_s += ((t1 - next_s) // period_s + 1) * period_s
        else:
            time.sleep(max(0.0, next_s - time.perf_counter()))
    elapsed = time.perf_counter() - start
    gc.enable()
    gc.unfreeze()
    after = driver.counters
    driver.quick_stop()
    us = latencies * 1e6
    return {
        "cycles": cycles,
        "elapsed_s": round(elapsed, 3),
        "achieved_rate_hz": round(cycles / elapsed, 1),
        "latency_us": benchinfo.spread(us),
        "master_cpu_us": benchinfo.spread(cpu_s * 1e6),
        "p99_fraction_of_period": round(float(np.percentile(latencies, 99)) / period_s, 3),
        "overruns": overruns,
        "frames_lost": after.dropped - before.dropped - (after.late - before.late),
        "tpdos_missed_deadline": after.dropped - before.dropped,
        "frames_late": after.late - before.late,
        "frames_malformed": after.malformed - before.malformed,
        "frames_sent": after.frames_sent - before.frames_sent,
        "frames_received": after.frames_received - before.frames_received,
    }


def _measure(config: Any, args: argparse.Namespace) -> dict[str, Any]:
    """A driver on ``config`` against drives that are already up: the loop's figures and the bus load."""
    driver = DriveBus(config)
    try:
        driver.connect()
        result = _run_loop(driver, args)
    finally:
        driver.close()
    result["bus_load"] = config.bus_load().describe()
    return result


def run_in_process(args: argparse.Namespace) -> dict[str, Any]:
    from sim_target.drives import EmulatedDrives, EmulatedDrivesConfig
    from sim_target.testing.fake_plant import FakePlant, lockstep

    channel = f"bench-{uuid.uuid4().hex[:8]}"
    config = _config(args, {"interface": "virtual", "channel": channel})
    side = can.Bus(interface="virtual", channel=channel, ignore_config=True)
    drives = EmulatedDrives(side, EmulatedDrivesConfig(node_ids=config.node_ids))
    lockstep(drives, FakePlant(args.drives, config.period_s))
    drives.start()
    try:
        return _measure(config, args)
    finally:
        drives.close()
        side.shutdown()


def run_bridge(args: argparse.Namespace, ipc_dir: str | None = None) -> dict[str, Any]:
    """The drives in another process: behind the python-can-remote bridge, or on the ipc bus."""
    extra = ["--ipc-dir", ipc_dir] + ([] if args.fd else ["--classical"]) if ipc_dir else []
    with drive_process("--drives", str(args.drives), "--period-s", str(1.0 / args.rate_hz), *extra) as target:
        ready = target.ready
        if ipc_dir:
            config = _config(args, {"interface": "ipc", "channel": ready["ipc_dir"]})
        else:
            config = _config(
                args, {"interface": "remote", "bridge_host": "127.0.0.1", "bridge_port": ready["port"], "channel": ""}
            )
        return _measure(config, args)


def run_ipc(args: argparse.Namespace) -> dict[str, Any]:
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        return run_bridge(args, str(Path(tmp) / "bus"))


def codec_cost() -> dict[str, float]:
    """µs per frame: our struct codec against canopen's PDO map objects, both directions."""
    node = canopen.RemoteNode(1, str(EDS_PATH))
    tpdo = node.tpdo[1]
    tpdo.clear()
    for index in (0x6041, 0x6077, 0x6064):
        tpdo.add_variable(index)
    tpdo.cob_id = 0x181
    rpdo = node.rpdo[1]
    rpdo.clear()
    rpdo.add_variable(0x6040)
    rpdo.add_variable(0x6071)
    data = fr.encode_tpdo1(0x1237, 500, -123456)
    n = 20000

    def canopen_decode() -> tuple[int, int, int]:
        tpdo.on_message(0x181, data, 0.0)
        return tpdo[0].raw, tpdo[1].raw, tpdo[2].raw

    def canopen_encode() -> bytes:
        rpdo[0].raw = 0x000F
        rpdo[1].raw = -1000
        return bytes(rpdo.data)

    def ours_decode() -> tuple[int, int, int]:
        statusword, torque_permille, position_counts, _ = fr.decode_tpdo1(data)
        return statusword, torque_permille, position_counts

    def ours_encode() -> bytes:
        return fr.encode_rpdo(0x000F, -1000)

    assert canopen_decode() == ours_decode() and canopen_encode() == ours_encode()
    return {
        name: round(timeit.timeit(fn, number=n) / n * 1e6, 3)
        for name, fn in (
            ("canopen_tpdo_decode_us", canopen_decode),
            ("canopen_rpdo_encode_us", canopen_encode),
            ("struct_tpdo_decode_us", ours_decode),
            ("struct_rpdo_encode_us", ours_encode),
        )
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--mode", choices=("inprocess", "bridge", "ipc"), default="inprocess")
    parser.add_argument("--drives", type=int, default=6)
    parser.add_argument("--rate-hz", type=float, default=1000.0)
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--classical", dest="fd", action="store_false", help="classical CAN (default CAN FD)")
    parser.add_argument("--bitrate", type=int, default=1_000_000)
    parser.add_argument("--data-bitrate", type=int, default=5_000_000)
    parser.add_argument("--feedback-timeout-s", type=float, default=0.005)
    parser.add_argument("--unpaced", action="store_true", help="back-to-back exchanges, no pacing")
    args = parser.parse_args()
    runner = {"inprocess": run_in_process, "bridge": run_bridge, "ipc": run_ipc}[args.mode]
    result = {
        "benchmark": "can_exchange",
        "mode": args.mode,
        "plant": "fake double integrator (lock-step)",
        "drives": args.drives,
        "rate_hz": args.rate_hz,
        "paced": not args.unpaced,
        "can": "fd" if args.fd else "classical",
        **runner(args),
        "codec": codec_cost(),
        "machine": benchinfo.machine("python-can", "canopen", "numpy"),
    }
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
