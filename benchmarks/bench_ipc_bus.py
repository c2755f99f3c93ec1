"""The ipc bus between two processes, and the topology choice behind it (docs/ipc_bus.md).

One control cycle's traffic: 7 frames out (6 RPDOs + SYNC, 72-byte CAN FD datagrams), 6 back
(TPDOs) from a peer process that answers the 7th; paced at 1 kHz; the round trip measured.

- ``direct``: raw SOCK_SEQPACKET sockets, peer to peer (what the ipc bus does underneath).
- ``hub``: the same frames through a hub process in Python (epoll, forward each datagram to every
  other peer): the design the ipc bus does not use.
- ``bus``: ``can.Bus(interface="ipc")`` at both ends (python-can objects, encode/decode).

Prints one JSON document (median / p99 / max round trip in µs, machine, load average).

    python benchmarks/bench_ipc_bus.py                       # all three, 5000 cycles each
    python benchmarks/bench_ipc_bus.py --mode bus --cycles 20000 --rt
"""

from __future__ import annotations

import argparse
import json
import os
import select
import socket
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import benchinfo
import numpy as np

FRAME = struct.pack("=IBBBB64s", 0x201, 12, 4, 0, 0, bytes(12))
OUT, BACK = 7, 6

PEER = r"""
import os, socket, struct, sys
mode, path = sys.argv[1], sys.argv[2]
if mode == "bus":
    import can
    bus = can.Bus(interface="ipc", channel=path, fd=True)
    reply = [can.Message(arbitration_id=0x181 + i, data=bytes(16), is_fd=True, is_extended_id=False) for i in range(6)]
    print("ready", flush=True)
    n = 0
    while True:
        msg = bus.recv(5.0)
        if msg is None or msg.arbitration_id == 0x7FF:
            break
        n += 1
        if n % 7 == 0:
            for r in reply:
                bus.send(r)
    bus.shutdown()
else:
    frame = struct.pack("=IBBBB64s", 0x181, 16, 4, 0, 0, bytes(16))
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    sock.connect(path)
    print("ready", flush=True)
    while True:
        for _ in range(7):
            if not sock.recv(72):
                sys.exit(0)
        for _ in range(6):
            sock.send(frame)
"""


def _hub(listen: socket.socket) -> None:
    """Forward every datagram to every other peer (the rejected design, as lean as Python allows)."""
    poller = select.epoll()
    poller.register(listen.fileno(), select.EPOLLIN)
    peers: dict[int, socket.socket] = {}
    others: dict[int, list[socket.socket]] = {}
    while True:
        for fd, _ in poller.poll():
            if fd == listen.fileno():
                conn, _ = listen.accept()
                conn.setblocking(False)
                peers[conn.fileno()] = conn
                poller.register(conn.fileno(), select.EPOLLIN)
                others = {f: [p for g, p in peers.items() if g != f] for f in peers}
                continue
            sock = peers[fd]
            while True:
                try:
                    data = sock.recv(72)
                except BlockingIOError:
                    break
                if not data:
                    return
                for other in others[fd]:
                    other.send(data)


def _realtime(pid: int | None = None) -> bool:
    tids = [0] if pid is None else [int(t) for t in os.listdir(f"/proc/{pid}/task")]
    try:
        for tid in tids:
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(50))
    except OSError:
        return False
    return True


def _start_peer(mode: str, path: str) -> subprocess.Popen[str]:
    peer = subprocess.Popen([sys.executable, "-c", PEER, mode, path], stdout=subprocess.PIPE, text=True)
    assert peer.stdout is not None
    if peer.stdout.readline().strip() != "ready":
        peer.kill()
        raise RuntimeError(f"{mode} peer did not start")
    return peer


def _paced(round_trip: Any, cycles: int, period_s: float) -> np.ndarray:
    samples = np.empty(cycles)
    next_s = time.perf_counter()
    for k in range(cycles):
        start = time.perf_counter()
        round_trip()
        samples[k] = time.perf_counter() - start
        next_s += period_s
        while time.perf_counter() < next_s:
            time.sleep(max(0.0, next_s - time.perf_counter() - 2e-4))
    return samples * 1e6


def run(mode: str, cycles: int, period_s: float, rt: bool) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as tmp:
        hub_pid = None
        if mode == "bus":
            import can

            from drivers.ipc.bus import IpcBus

            path = str(Path(tmp) / "bus")
            peer = _start_peer("bus", path)
            bus = can.Bus(interface="ipc", channel=path, fd=True)
            assert isinstance(bus, IpcBus)  # can.Bus is typed as BusABC; send_batch is the ipc bus's own
            out = [
                can.Message(arbitration_id=0x201 + i, data=bytes(12), is_fd=True, is_extended_id=False)
                for i in range(OUT)
            ]
            send_batch, recv = bus.send_batch, bus.recv

            def round_trip() -> None:
                send_batch(out)
                for _ in range(BACK):
                    recv(1.0)
        else:
            path = str(Path(tmp) / "hub.sock")
            if mode == "direct":
                listen = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
                listen.bind(path)
                listen.listen()
                peer = _start_peer("raw", path)
                sock, _ = listen.accept()
                listen.close()
            else:
                listen = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
                listen.bind(path)
                listen.listen()
                hub_pid = os.fork()
                if hub_pid == 0:  # the hub process
                    try:
                        _hub(listen)
                    finally:
                        os._exit(0)
                listen.close()
                peer = _start_peer("raw", path)
                sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
                sock.connect(path)
                time.sleep(0.2)  # the hub accepts both
            send, recv_raw = sock.send, sock.recv

            def round_trip() -> None:
                for _ in range(OUT):
                    send(FRAME)
                for _ in range(BACK):
                    recv_raw(72)

        granted = False
        if rt:
            granted = _realtime() and _realtime(peer.pid) and (hub_pid is None or _realtime(hub_pid))
        try:
            for _ in range(200):  # warm-up
                round_trip()
            load = os.getloadavg()
            us = _paced(round_trip, cycles, period_s)
        finally:
            if rt:
                os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
            if mode == "bus":
                import can

                bus.send(can.Message(arbitration_id=0x7FF, is_extended_id=False))
                bus.shutdown()
            else:
                sock.close()
            peer.wait(10)
            if hub_pid is not None:
                os.kill(hub_pid, 9)
                os.waitpid(hub_pid, 0)
    return {
        "mode": mode,
        "cycles": cycles,
        "sched_fifo": granted,
        "round_trip_us": benchinfo.spread(us),
        "load_average_at_start": [round(x, 2) for x in load],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--mode", choices=["all", "direct", "hub", "bus"], default="all")
    parser.add_argument("--cycles", type=int, default=5000)
    parser.add_argument("--period-s", type=float, default=0.001)
    parser.add_argument("--rt", action="store_true", help="SCHED_FIFO 50 for every process involved")
    args = parser.parse_args()
    modes = ["direct", "hub", "bus"] if args.mode == "all" else [args.mode]
    out = {
        "benchmark": "ipc_bus",
        "traffic": f"{OUT} x 72-byte datagrams out, {BACK} back, per cycle",
        "machine": benchinfo.machine(),
        "results": [run(mode, args.cycles, args.period_s, args.rt) for mode in modes],
        "load_average_after": [round(x, 2) for x in os.getloadavg()],
    }
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
