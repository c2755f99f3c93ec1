"""The lab's one runtime-config builder and one target-config builder, and the writing of both.

The demo, the HIL experiment and the fault campaign differ only in the sections they pass: the
reference (hold, or a condition from t = 0 on the placed arm), the loop (lock-step on the bus, or
free-running on the wall clock with the loop on its own CPU), the driver's timeouts, telemetry
(listening, or connecting to a session of the caller's) and a control socket.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from sim_target.launch import CAN_FD

REALISM_PROFILES = ("ideal", "realistic", "harsh")
HOLD: Mapping[str, Any] = {"kind": "hold"}
FIFO_PRIORITY = 80  # the free-running loop thread's SCHED_FIFO priority (docs/runtime.md)


def robot_joints(names: Sequence[str], max_torque_nm: Sequence[float]) -> list[dict[str, Any]]:
    """The runtime config's ``bus.joints``: node ids 1..n in the robot's joint order."""
    return [
        {"name": name, "node_id": i + 1, "max_torque_nm": float(t)}
        for i, (name, t) in enumerate(zip(names, max_torque_nm, strict=True))
    ]


def condition_reference(conditions_file: Path, condition: str) -> dict[str, Any]:
    """The reference of a placed run: ``condition`` from t = 0 (no ramp: the target placed the arm)."""
    return {"kind": "condition", "conditions_file": str(conditions_file), "condition": condition, "start": "condition"}


def lockstep_loop(**overrides: Any) -> dict[str, Any]:
    """The loop paced by the bus (the target lock-stepped), one reference row per exchange."""
    return {"pacing": "bus", "time_base": "cycles", "stats_interval_s": 3600.0, **overrides}


def realtime_loop(duration_s: float, cpus: str, stats_window: int, **overrides: Any) -> dict[str, Any]:
    """The loop free-running on wall-clock deadlines for ``duration_s``, on its own CPU of
    :func:`sim_target.rt_settings.split_cpus` (the target's physics on the other), SCHED_FIFO."""
    from sim_target.rt_settings import split_cpus

    return {
        "pacing": "clock",
        "time_base": "wall",
        "duration_s": duration_s,
        "stats_interval_s": 3600.0,
        "stats_window": min(stats_window, 1 << 20),
        "cpu_affinity": split_cpus(cpus)[0],
        "fifo_priority": FIFO_PRIORITY,
        **overrides,
    }


def telemetry_section(
    stats_period_s: float, *, listen_port: int | None = None, connect: Sequence[str] = (), **extra: Any
) -> dict[str, Any]:
    """Telemetry on 127.0.0.1: listening on ``listen_port``, or connecting to ``connect``'s endpoints."""
    data: dict[str, Any] = {
        "enabled": True,
        "listen": [f"tcp/127.0.0.1:{listen_port}"] if listen_port is not None else [],
    }
    if connect:
        data["connect"] = list(connect)
    return {**data, "stats_period_s": stats_period_s, **extra}


def runtime_config(
    robot: str,
    joints: list[dict[str, Any]],
    bundle: Path,
    mode: str,
    transport: Mapping[str, Any],
    period_s: float,
    *,
    driver: Mapping[str, Any],
    reference: Mapping[str, Any] = HOLD,
    loop: Mapping[str, Any] | None = None,
    telemetry: Mapping[str, Any] | None = None,
    control_socket: Path | None = None,
    torque_rate_limit: str = "none",
    measurement_noise: tuple[float, float | None] = (0.0, None),
    velocity_filter_hz: float | None = None,
    **sections: Any,
) -> dict[str, Any]:
    """``hil run``'s config (hil_runtime/config.py) for a lab rig: ``bundle`` in ``mode`` on the
    drives of ``joints`` over ``transport`` (CAN FD unless it says otherwise); ``driver``: the
    driver's timeouts (bus section); ``loop``: :func:`lockstep_loop` by default; ``torque_rate_limit``:
    the bundle section's (none | libfranka, hil_runtime.rate_limit); ``measurement_noise``: the bundle
    section's (encoder_noise_rad, velocity_noise_rad_s), the sensing the runtime gates an lmpc bundle by
    (hil_runtime.bundle_probes.check_sensing). (0, None) by default: a measurement rig records what a
    bundle does under its target's noise, it does not refuse it; the demo states its target's noise.
    ``velocity_filter_hz``: the bundle section's LMPC velocity input filter (None: off)."""
    encoder_noise_rad, velocity_noise_rad_s = measurement_noise
    data: dict[str, Any] = {
        "robot": robot,
        "bundle": {
            "path": str(bundle),
            "mode": mode,
            "torque_rate_limit": torque_rate_limit,
            "encoder_noise_rad": encoder_noise_rad,
            "velocity_noise_rad_s": velocity_noise_rad_s,
            **({"velocity_filter_hz": velocity_filter_hz} if velocity_filter_hz is not None else {}),
        },
        "bus": {"transport": {**CAN_FD, **transport}, "period_s": period_s, "joints": joints, **driver},
        "reference": dict(reference),
        "loop": dict(loop) if loop is not None else lockstep_loop(),
        **sections,
    }
    if telemetry is not None:
        data["telemetry"] = dict(telemetry)
    if control_socket is not None:
        data["control_socket"] = str(control_socket)
    return data


def target_config(
    robot: str,
    period_s: float,
    substeps: int,
    *,
    realism: str | None = None,
    realtime_cpus: str | None = None,
    lockstep_fifo: bool = False,
    initial_position_rad: Sequence[float] | None = None,
    bus: Mapping[str, Any] | None = None,
    control_socket: Path | None = None,
    **extra: Any,
) -> dict[str, Any]:
    """``hil target serve``'s config (sim_target/config.py): lock-stepped unless ``realtime_cpus``
    (then free-running, its physics on the target's CPU of ``split_cpus``; ``lockstep_fifo``: lock-step
    with SCHED_FIFO on the thread serving the SYNCs, docs/target.md); ``realism`` a profile
    name or a file (resolved: the target may run in another directory); ``bus`` over the default
    (virtual, CAN FD; :func:`sim_target.launch.launch_target` sets the channel)."""
    from sim_target.launch import target_config_dict

    data = target_config_dict(robot, period_s, substeps, **extra)
    if bus is not None:
        data["bus"] = {**data["bus"], **bus}
    if initial_position_rad is not None:
        data["plant"] = {**data["plant"], "initial_position_rad": [float(x) for x in initial_position_rad]}
    if control_socket is not None:
        data["control_socket"] = str(control_socket)
    if realism is not None:
        data["realism"] = realism if realism in REALISM_PROFILES else str(Path(realism).resolve())
    if realtime_cpus is not None:
        from sim_target.rt_settings import split_cpus

        data["clock"] = "realtime"
        data["realtime"] = {"cpus": split_cpus(realtime_cpus)[1]}
    elif lockstep_fifo:
        data["realtime"] = {"in_lockstep": True, "fifo_priority": FIFO_PRIORITY}
    return data


def write_checked_configs(work: Path, target: Mapping[str, Any], runtime: Mapping[str, Any]) -> tuple[Path, Path]:
    """``target.yaml`` and ``runtime.yaml`` in ``work``, each checked as its process will check it
    (one line naming the file and field, exit 2), before any process starts."""
    from hil_runtime.daemon import check as check_runtime_config
    from sim_target.config import load_target_config

    target_path, runtime_path = work / "target.yaml", work / "runtime.yaml"
    target_path.write_text(yaml.safe_dump(dict(target)))
    runtime_path.write_text(yaml.safe_dump(dict(runtime)))
    load_target_config(target_path)
    check_runtime_config(runtime_path)
    return target_path, runtime_path


__all__ = [
    "CAN_FD",
    "HOLD",
    "condition_reference",
    "lockstep_loop",
    "realtime_loop",
    "robot_joints",
    "runtime_config",
    "target_config",
    "telemetry_section",
    "write_checked_configs",
]
