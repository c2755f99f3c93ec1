"""The configs ``hil demo`` writes for its two processes: ``hil target serve`` and ``hil run`` on
one ipc bus, lock-step (the runtime paces on the bus) or free-running (both on their own clocks)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from models.demo.options import DemoOptions, target_substeps


def target_config(options: DemoOptions, period_s: float, bus_dir: Path, control_socket: Path) -> dict[str, Any]:
    """``hil target serve``'s config: the pybullet arm on the ipc bus in ``bus_dir``, a control socket."""
    from sim_target.launch import CAN_FD
    from sim_target.rt_settings import split_cpus

    data: dict[str, Any] = {
        "robot": options.robot,
        "period_s": period_s,
        "clock": "realtime" if options.realtime else "lockstep",
        "bus": {"interface": "ipc", "channel": str(bus_dir), **CAN_FD},
        "plant": {"substeps": target_substeps(options)},
        "control_socket": str(control_socket),
        "realism": options.realism
        if options.realism in ("ideal", "realistic", "harsh")
        else str(Path(options.realism).resolve()),
    }
    if options.realtime:  # SCHED_FIFO and mlockall by default; its own CPU, apart from the runtime's
        data["realtime"] = {"cpus": split_cpus(options.cpus)[1]}
    from models.robot_target import target_robot_config
    from models.robots import load_robot

    return target_robot_config(load_robot(options.robot), data)  # a URDF robot: its file and joints


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
    if options.realtime:  # the loop thread on its own CPU, apart from the target's physics
        from sim_target.rt_settings import split_cpus

        data["loop"].update(cpu_affinity=split_cpus(options.cpus)[0], fifo_priority=80, lock_memory=True)
    data["telemetry"] = {"enabled": True, "listen": [], "connect": [endpoint], "stats_period_s": 1.0}
    data["control_socket"] = str(control_socket)
    return data


__all__ = ["runtime_config", "target_config"]
