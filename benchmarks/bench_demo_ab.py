"""The lock-step ``hil demo --headless`` of two source trees, interleaved, at the same moment: is a
change of rate the code's or the machine's? (docs/runtime.md, "The lock-step demo's rate")

For each round and each tree (a git worktree of the commit to compare, ``git worktree add --detach
DIR COMMIT``): one ``hil demo --headless --duration D`` of that tree (``PYTHONPATH=TREE``), the whole
demo under SCHED_FIFO (``--fifo``, default 30: the children inherit it) so that other jobs on the
machine do not decide the rate; while the runtime is ACTIVE, its cycles (control socket) and the CPU
time of the target and runtime processes (/proc) are sampled, so the JSON also has each process's
CPU per cycle, which the machine's load changes far less than the wall rate. Before each run, a bare
one-node onnxruntime call is timed back to back on this process (the machine's speed at that moment:
the period is also given in those units, ``period_over_onnx_1node``).

    python benchmarks/bench_demo_ab.py --tree /work/old --tree . --rounds 2 --duration 3

Prints one JSON document (per run and per tree: median of the rounds; machine, load average).
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import benchinfo
import numpy as np

TICKS_S = os.sysconf("SC_CLK_TCK")


def onnx_1node_us(calls: int = 3000) -> float:
    """Median of a bare one-node onnxruntime call, back to back (warm), in µs."""
    from lmpc_graphs import bound_runner, make_session, one_node_graph

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "one.onnx"
        one_node_graph(path, width=6, nodes=1)
        run = bound_runner(make_session(str(path)), width=6)
        times = []
        for _ in range(calls):
            t0 = time.perf_counter()
            run()
            times.append(time.perf_counter() - t0)
    return float(np.median(times[calls // 10 :]) * 1e6)


def _parents() -> dict[int, int]:
    parents = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                stat = Path(f"/proc/{entry}/stat").read_text()
            except OSError:
                continue
            parents[int(entry)] = int(stat[stat.rindex(")") + 2 :].split()[1])
    return parents


def _children(root: int) -> dict[str, int]:
    """The demo's ``target`` and ``runtime`` processes among ``root``'s descendants."""
    parents = _parents()
    found: dict[str, int] = {}
    todo = [root]
    while todo:
        pid = todo.pop()
        for child, parent in parents.items():
            if parent != pid:
                continue
            todo.append(child)
            try:
                args = Path(f"/proc/{child}/cmdline").read_bytes().split(b"\0")
            except OSError:
                continue
            if b"serve" in args and b"target" in args:
                found["target"] = child
            elif b"run" in args and b"--config" in args:
                found["runtime"] = child
    return found


def _cpu_s(pid: int) -> float:
    stat = Path(f"/proc/{pid}/stat").read_text()
    fields = stat[stat.rindex(")") + 2 :].split()
    return (int(fields[11]) + int(fields[12])) / TICKS_S


def _status(path: str) -> dict[str, Any]:
    with socket.socket(socket.AF_UNIX) as sock:
        sock.settimeout(2.0)
        sock.connect(path)
        sock.sendall(b'{"command": "status"}\n')
        data = b""
        while not data.endswith(b"\n"):
            chunk = sock.recv(65536)
            if not chunk:
                break
            data += chunk
    reply: dict[str, Any] = json.loads(data)
    return reply


def _runtime_socket(pid: int) -> str | None:
    import yaml

    args = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    config = args[args.index(b"--config") + 1].decode()
    socket_path = yaml.safe_load(Path(config).read_text()).get("control_socket")
    return str(socket_path) if socket_path else None


def run_demo(tree: Path, duration_s: float, fifo: int) -> dict[str, Any]:
    """One lock-step demo of ``tree``: its timing, and CPU per cycle of target and runtime."""
    env = dict(os.environ, PYTHONPATH=str(tree))
    with tempfile.TemporaryDirectory(prefix="bench-demo-ab-") as tmp:
        command = [sys.executable, "-m", "hil_runtime.cli", "demo", "--headless", "--duration", str(duration_s)]
        command += ["--out", str(Path(tmp) / "out")]
        if fifo:
            command = ["chrt", "-f", str(fifo), *command]
        proc = subprocess.Popen(command, cwd=tree, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        samples: list[tuple[int, float, float]] = []  # (cycles, target cpu s, runtime cpu s) while ACTIVE
        while proc.poll() is None:
            children = _children(proc.pid)
            try:
                if "target" in children and "runtime" in children:
                    path = _runtime_socket(children["runtime"])
                    status = _status(path) if path else {}
                    if status.get("state") == "ACTIVE":
                        samples.append((int(status["cycles"]), _cpu_s(children["target"]), _cpu_s(children["runtime"])))
            except (OSError, ValueError, KeyError):
                pass  # a process starting or leaving meanwhile
            time.sleep(0.25)
        output = proc.stdout.read().decode(errors="replace") if proc.stdout else ""
        results_file = Path(tmp) / "out" / "results.json"
        if not results_file.is_file():
            return {"error": output[-400:]}
        timing = json.loads(results_file.read_text())["timing"]
    out: dict[str, Any] = {
        "rate_hz": timing["rate_hz"],
        "period_median_us": timing["period_us"]["median"],
        "compute_median_us": timing["compute_us"]["median"],
        "exchange_median_us": timing["exchange_us"]["median"],
    }
    if len(samples) >= 3:  # the first sample may straddle activation
        (c0, t0, r0), (c1, t1, r1) = samples[1], samples[-1]
        if c1 > c0:
            out["target_cpu_us_per_cycle"] = round((t1 - t0) / (c1 - c0) * 1e6, 1)
            out["runtime_cpu_us_per_cycle"] = round((r1 - r0) / (c1 - c0) * 1e6, 1)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tree", type=Path, action="append", required=True, help="a source tree (repeat)")
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--duration", type=float, default=3.0, help="the demo's --duration (s)")
    parser.add_argument("--fifo", type=int, default=30, help="SCHED_FIFO priority of the demo (0: none)")
    args = parser.parse_args()
    load_before = benchinfo.load_average()
    runs = []
    for round_index in range(args.rounds):
        for tree in args.tree:
            floor_us = onnx_1node_us()
            load = [round(x, 2) for x in os.getloadavg()]
            result = run_demo(tree.resolve(), args.duration, args.fifo)
            if "period_median_us" in result:
                result["period_over_onnx_1node"] = round(result["period_median_us"] / floor_us, 1)
            runs.append(
                {"tree": str(tree), "round": round_index, "onnx_1node_us": round(floor_us, 2), "load": load, **result}
            )
    summary = {}
    for tree in args.tree:
        mine = [r for r in runs if r["tree"] == str(tree) and "error" not in r]
        keys = [k for k in (mine[0] if mine else {}) if k not in ("tree", "round", "load")]
        summary[str(tree)] = {k: round(float(np.median([r[k] for r in mine if k in r])), 1) for k in keys}
    print(
        benchinfo.report(
            "demo_ab",
            load_before,
            {
                "runs": runs,
                "median_by_tree": summary,
            },
        )
    )


if __name__ == "__main__":
    main()
