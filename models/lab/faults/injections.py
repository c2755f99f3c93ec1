"""What the in-process fault cases inject, each ``inject(rig, rng) -> detail`` (models/lab/faults/
cases.run_in_process calls it once the rig is ACTIVE): frame faults at the emulated drives (drop,
delay, corrupt TPDOs), floods of foreign frames, plant and drive faults at the target, the bus or
the target process taken away, a starved CPU, telemetry subscribers started and killed."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from models.lab import rigs
from models.lab.rigs import InProcessRig


def _server(rig: InProcessRig) -> Any:
    return rig.target.server


def _nodes(rng: np.random.Generator, all_drives: bool) -> list[int]:
    return list(range(1, 7)) if all_drives else [int(rng.integers(1, 7))]


def drop_tpdos(cycles: int, all_drives: bool) -> Callable[[InProcessRig, np.random.Generator], Any]:
    def inject(rig: InProcessRig, rng: np.random.Generator) -> Any:
        nodes = _nodes(rng, all_drives)
        for node in nodes:
            _server(rig).drives.drop_tpdos(node, cycles)
        return {"nodes": nodes, "cycles": cycles}

    return inject


def delay_tpdos(cycles: int, all_drives: bool) -> Callable[[InProcessRig, np.random.Generator], Any]:
    def inject(rig: InProcessRig, rng: np.random.Generator) -> Any:
        nodes = _nodes(rng, all_drives)
        delay_s = rigs.FEEDBACK_TIMEOUT_S * float(rng.uniform(1.5, 2.5))  # past the cycle's wait
        for node in nodes:
            _server(rig).drives.delay_tpdos(node, delay_s, cycles)
        return {"nodes": nodes, "cycles": cycles, "delay_s": round(delay_s, 4)}

    return inject


def corrupt_tpdos(cycles: int, all_drives: bool) -> Callable[[InProcessRig, np.random.Generator], Any]:
    def inject(rig: InProcessRig, rng: np.random.Generator) -> Any:
        nodes = _nodes(rng, all_drives)
        for node in nodes:
            _server(rig).drives.corrupt_tpdos(node, cycles)  # one byte short: wrong length
        return {"nodes": nodes, "cycles": cycles}

    return inject


class _Flood:
    """A rogue node on the channel: frames from a thread until stopped."""

    def __init__(self, channel: str, frames: list[tuple[int, bytes]], duration_s: float) -> None:
        import can

        self.bus = can.Bus(interface="virtual", channel=channel)
        self.frames = frames
        self.sent = 0
        self.until = time.monotonic() + duration_s
        self.thread = threading.Thread(target=self._run, name="rogue", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        import can

        messages = [
            can.Message(arbitration_id=cob, data=data, is_extended_id=False, is_fd=True, bitrate_switch=True)
            for cob, data in self.frames
        ]
        while time.monotonic() < self.until:
            for msg in messages:
                self.bus.send(msg)
                self.sent += 1
            time.sleep(0.0002)

    def close(self) -> None:
        self.thread.join(timeout=10)
        self.bus.shutdown()


def flood(kind: str) -> Callable[[InProcessRig, np.random.Generator], Any]:
    def inject(rig: InProcessRig, rng: np.random.Generator) -> Any:
        from drivers.cia402 import frames as fr

        if kind == "unknown":  # a node that is not ours (100), every service of it
            node = 100
            frames = [
                (fr.TPDO1_BASE + node, bytes(8)),
                (0x700 + node, b"\x05"),
                (0x080 + node, bytes(8)),
                (0x580 + node, bytes(8)),
                (0x7E4, bytes(rng.integers(0, 256, 8).tolist())),
            ]
        else:  # wrong lengths on the COB-IDs of our own drives: TPDO, heartbeat, EMCY
            node = int(rng.integers(1, 7))
            frames = [
                (fr.TPDO1_BASE + node, b"\x01\x02\x03"),
                (0x700 + node, b""),
                (0x700 + node, b"\x05\x00\x00"),
                (0x080 + node, b"\x00\x10"),
            ]
        rogue = _Flood(rig.config.bus.transport.channel, frames, 0.3)
        rig.cleanups.append(rogue.close)
        return {"kind": kind, "node": node, "cob_ids": sorted({hex(c) for c, _ in frames})}

    return inject


def target_fault(fault: dict[str, Any]) -> Callable[[InProcessRig, np.random.Generator], Any]:
    def inject(rig: InProcessRig, rng: np.random.Generator) -> Any:
        from sim_target.config import parse_fault

        data = dict(fault)
        if data.get("node_id") == "random":
            data["node_id"] = int(rng.integers(1, 7))
        _server(rig).inject(parse_fault(data, "campaign"))
        return data

    return inject


def close_bus_under_driver(rig: InProcessRig, rng: np.random.Generator) -> Any:
    """The python-can bus the driver runs on is shut down between two cycles (a USB adapter pulled)."""
    rig.can_bus.shutdown()
    return {"closed": "python-can bus.shutdown() between two cycles"}


def kill_target_process(rig: InProcessRig, rng: np.random.Generator) -> Any:
    process = rig.target.process
    process.send_signal(signal.SIGKILL)
    return {"pid": process.pid, "signal": "SIGKILL"}


def starve_cpu(rig: InProcessRig, rng: np.random.Generator) -> Any:
    """Busy processes, one more than the CPUs: the loop (clock pacing) must count its overruns."""
    count = (os.cpu_count() or 2) + 1
    spin = "import time\nend = time.monotonic() + 3.0\nwhile time.monotonic() < end: pass"
    busy = [subprocess.Popen([sys.executable, "-c", spin]) for _ in range(count)]

    def reap() -> None:
        for process in busy:
            with contextlib.suppress(Exception):
                process.kill()
                process.wait(5)

    rig.cleanups.append(reap)
    return {"busy_processes": count, "for_s": 3.0}


def start_subscriber(rig: InProcessRig, rng: np.random.Generator) -> Any:
    """A second subscriber process on state (started before the drives are enabled)."""
    code = (
        "import sys, time\nfrom hil_runtime.telemetry.subscriber import TelemetryClient\n"
        f"c = TelemetryClient.open(connect=['tcp/127.0.0.1:{rig.telemetry_port}'], robot='ur5_paper',"
        " timeout_s=20)\n"
        "n = [0]\nc.subscribe('state', lambda p: n.__setitem__(0, n[0] + 1))\n"
        "print('subscribed', flush=True)\ntime.sleep(60)\n"
    )
    process = subprocess.Popen(
        [sys.executable, "-c", code], stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
    )
    assert process.stdout is not None
    ready = process.stdout.readline().strip() == "subscribed"
    rig.subscriber = process

    def reap() -> None:
        process.kill()
        process.wait(10)

    rig.cleanups.append(reap)
    return {"subscriber_ready": ready}


def kill_subscriber(rig: InProcessRig, rng: np.random.Generator) -> Any:
    """SIGKILL the subscriber process while the loop publishes to it."""
    process = rig.subscriber
    assert process is not None
    process.kill()
    return {"killed": "SIGKILL", "pid": process.pid}
