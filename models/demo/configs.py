"""The configs ``hil demo`` writes for its two processes: ``hil target serve`` and ``hil run`` on
one ipc bus, lock-step (the runtime paces on the bus) or free-running (both on their own clocks)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from models.demo.options import DemoOptions


def target_config(options: DemoOptions, period_s: float, bus_dir: Path, control_socket: Path) -> dict[str, Any]:
    """``hil target serve``'s config: the pybullet arm on the ipc bus in ``bus_dir``, a control socket."""
    from sim_target.launch import CAN_FD

    return {
        "robot": options.robot,
        "period_s": period_s,
        "clock": "realtime" if options.realtime else "lockstep",
        "bus": {"interface": "ipc", "channel": str(bus_dir), **CAN_FD},
        "plant": {"substeps": options.target_substeps},
        "control_socket": str(control_socket),
    }


def runtime_config(
    options: DemoOptions,
    robot: Any,
    condition: Any,
    period_s: float,
    bus_dir: Path,
    conditions_file: Path,
    control_socket: Path,
    endpoint: str,
) -> dict[str, Any]:
    """``hil run``'s config: the shipped bundle, the condition from t = 0 on the placed arm, telemetry
    connecting to the demo's session, a control socket; lock-step (bus pacing) or real time (clock)."""
    from models.hil_experiment.config import runtime_config_dict
    from models.lmpc.controller import bundle_path
    from sim_target.launch import CAN_FD

    transport = {"interface": "ipc", "channel": str(bus_dir), **CAN_FD}
    data = runtime_config_dict(
        robot,
        bundle_path(robot.name, options.law, None),
        options.mode,
        transport,
        period_s,
        conditions_file,
        condition.name,
    )
    steps = round(condition.duration_s / period_s)
    data["loop"] = {
        "pacing": "clock" if options.realtime else "bus",
        "time_base": "wall" if options.realtime else "cycles",
        # The stats cover the whole run (not the default last 4096 cycles).
        "stats_window": min(steps + 20_000, 1 << 20),
        "stats_interval_s": 1.0,
        # A backstop only: the demo stops the daemon with SIGTERM when the run has covered the condition.
        "duration_s": condition.duration_s + 10.0,
    }
    if options.realtime:
        # Free-running, the loop thread must hold its deadlines on a shared machine: SCHED_FIFO (the
        # target's physics thread takes the same priority), memory locked, and a CPU of its own.
        # Without these the runtime only warned "without SCHED_FIFO" (never asked for, not refused).
        data["loop"].update(fifo_priority=80, lock_memory=True, cpu_affinity=runtime_cpus())
    data["telemetry"] = {"enabled": True, "listen": [], "connect": [endpoint], "stats_period_s": 1.0}
    data["control_socket"] = str(control_socket)
    return data


def runtime_cpus() -> list[int] | None:
    """The runtime loop's CPU in a free-running demo: the last one the process may use (the target
    is pinned apart from it); None on a one-CPU machine."""
    import os

    cpus = sorted(os.sched_getaffinity(0))
    return [cpus[-1]] if len(cpus) > 1 else None


__all__ = ["runtime_config", "runtime_cpus", "target_config"]
