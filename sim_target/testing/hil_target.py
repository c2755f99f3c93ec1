"""Helpers shared by the HIL integration tests and benchmarks (bench_hil_lockstep, bench_runtime):
start the pybullet target (in this process, or as ``hil target serve`` in another one) and build the
driver master's config for it. Loopback only: the bridge listens on 127.0.0.1, on a port the OS picks."""

from __future__ import annotations

import contextlib
import signal
import subprocess
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from drivers.config import DriveBusConfig, parse_drive_bus_config
from sim_target.config import parse_target_config
from sim_target.launch import CAN_FD, bridge_url, serve_in_thread, start_hil, target_config_dict, wait_ready
from sim_target.server import TargetServer
from sim_target.testing.ur5 import MAX_TORQUE_NM, NODE_IDS, Q0_RAD


def unique_channel() -> str:
    return f"hil-{uuid.uuid4().hex[:8]}"


def ur5_target_config(channel: str, period_s: float, substeps: int = 32, **extra: Any) -> dict[str, Any]:
    """:func:`sim_target.launch.target_config_dict` for ur5_paper's six drives on the virtual
    ``channel``, starting at Q0_RAD; ``extra`` merged on top."""
    base = target_config_dict("ur5_paper", period_s, substeps)
    return {
        **base,
        "bus": {**base["bus"], "channel": channel},
        "drives": {"node_ids": list(NODE_IDS)},
        "plant": {"substeps": substeps, "initial_position_rad": list(Q0_RAD)},
        **extra,
    }


def drive_bus_config(transport: dict[str, Any], period_s: float, **extra: Any) -> DriveBusConfig:
    return parse_drive_bus_config(
        {
            "transport": {**CAN_FD, **transport},
            "period_s": period_s,
            "joints": [
                {"name": f"joint{n}", "node_id": n, "max_torque_nm": m}
                for n, m in zip(NODE_IDS, MAX_TORQUE_NM, strict=True)
            ],
            **extra,
        }
    )


@contextlib.contextmanager
def target_in_process(channel: str, period_s: float, **config: Any) -> Iterator[TargetServer]:
    """The target on the in-process virtual ``channel``, its lock-step clock in a thread."""
    with serve_in_thread(parse_target_config(ur5_target_config(channel, period_s, **config))) as server:
        yield server


def serve_config(data: dict[str, Any], path: Path) -> tuple[subprocess.Popen[str], str]:
    """``hil target serve`` on the target config ``data`` (written to ``path``), up to its ready
    line: the process (the rest of its stderr still in the pipe) and that line."""
    path.write_text(yaml.safe_dump(data))
    process = start_hil("target", "serve", "--config", str(path))
    return process, wait_ready(process)


def start_hil_run(config_path: Path, record: Path, env: dict[str, str] | None = None) -> subprocess.Popen[str]:
    """``hil run`` on ``config_path``, recording up to 20000 cycles into ``record`` (stderr piped)."""
    return start_hil("run", "--config", str(config_path), "--record", str(record), "--record-cycles", "20000", env=env)


@dataclass
class TargetProcess:
    process: subprocess.Popen[str]
    bridge_url: str  # "" on the ipc bus
    control_socket: Path
    ipc_dir: Path | None = None  # the ipc bus directory (transport "ipc")

    def stop(self, timeout_s: float = 10.0) -> tuple[int, str]:
        """SIGTERM; the exit code and the rest of stderr."""
        if self.process.poll() is None:
            self.process.send_signal(signal.SIGTERM)
        try:
            _, err = self.process.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.process.kill()
            _, err = self.process.communicate()
            return -9, err
        return self.process.returncode, err


@contextlib.contextmanager
def target_process(
    tmp_dir: Path, period_s: float, substeps: int = 32, transport: str = "bridge", **config: Any
) -> Iterator[TargetProcess]:
    """``hil target serve`` in a subprocess, its bus served by the bridge on 127.0.0.1:<free port>,
    or (``transport="ipc"``) on the ipc bus in ``tmp_dir/bus``."""
    sock = tmp_dir / "target.sock"
    ipc_dir = tmp_dir / "bus" if transport == "ipc" else None
    if ipc_dir is not None:
        data = ur5_target_config("hil", period_s, substeps, control_socket=str(sock), **config)
        data["bus"] = {**data["bus"], "interface": "ipc", "channel": str(ipc_dir)}
    else:
        data = ur5_target_config(
            "hil", period_s, substeps, bridge={"host": "127.0.0.1", "port": 0}, control_socket=str(sock), **config
        )
    process, ready = serve_config(data, tmp_dir / "target.yaml")
    url = "" if ipc_dir is not None else bridge_url(ready)
    if url is None:
        process.kill()
        raise RuntimeError(f"target names no bridge URL: {ready}")
    target = TargetProcess(process, url, sock, ipc_dir)
    try:
        yield target
    finally:
        target.stop()
