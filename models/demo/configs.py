"""The configs ``hil demo`` writes for its two processes: ``hil target serve`` and ``hil run`` on
one ipc bus, lock-step (the runtime paces on the bus) or free-running (both on their own clocks).
Built by the lab's builders (models/lab/configs.py) with the demo's options."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from models.demo.options import DemoOptions, realism_specs, target_substeps
from models.lab import configs as lab


def target_config(options: DemoOptions, period_s: float, bus_dir: Path, control_socket: Path) -> dict[str, Any]:
    """``hil target serve``'s config: the pybullet arm on the ipc bus in ``bus_dir``, a control socket;
    real time: SCHED_FIFO and mlockall by default, its own CPU, apart from the runtime's. A URDF
    robot: its file and its joints (models/robot_target.py)."""
    from models.robot_target import target_robot_config
    from models.robots import load_robot

    robot = load_robot(options.robot)
    return target_robot_config(
        robot,
        lab.target_config(
            robot.name,
            period_s,
            target_substeps(options),
            realism=options.realism,
            realtime_cpus=options.cpus if options.realtime else None,
            lockstep_fifo=not options.realtime,
            bus={"interface": "ipc", "channel": str(bus_dir)},
            control_socket=control_socket,
        ),
    )


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
    from models.lab.runs import DRIVER_TIMEOUTS
    from models.lmpc.controller import bundle_path
    from sim_target.launch import can_fd

    steps = round(condition.duration_s / period_s)
    # The stats cover the whole run (not the default last 4096 cycles). duration_s: a backstop only,
    # the demo stops the daemon with SIGTERM when the run has covered the condition.
    stats = {"stats_window": min(steps + 20_000, 1 << 20), "stats_interval_s": 1.0}
    duration_s = condition.duration_s + 10.0
    loop = (
        lab.realtime_loop(duration_s, options.cpus, stats["stats_window"], stats_interval_s=1.0, lock_memory=True)
        if options.realtime
        else lab.lockstep_loop(**stats, duration_s=duration_s, fifo_priority=lab.FIFO_PRIORITY)
    )
    return lab.runtime_config(
        robot.name,
        lab.robot_joints(robot.joint_names, robot.torque_limit_nm),
        bundle_path(robot.name, options.law, None),
        options.mode,
        {"interface": "ipc", "channel": str(bus_dir), **can_fd(robot.n_joints)},  # the target's rates
        period_s,
        driver=DRIVER_TIMEOUTS,
        reference=lab.condition_reference(conditions_file, condition.name),
        loop=loop,
        telemetry=lab.telemetry_section(1.0, connect=[endpoint]),
        control_socket=control_socket,
        measurement_noise=realism_specs(options)[0].measurement_noise(),  # the runtime gates as on an arm
    )


__all__ = ["runtime_config", "target_config"]
