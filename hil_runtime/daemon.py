"""``hil run``: the runtime as a long-running process a systemd unit can run (Type=notify).

Start-up, in this order (helper threads first, so the loop thread alone gets SCHED_FIFO):

1. config (one-line errors, exit 2), bundle and condition checked against the drives, DriveBus built;
2. telemetry sink made, memory locked (``loop.lock_memory``), control socket opened;
3. bus connected, drives configured (never enabled on any start-up error: exit 2), policy warm;
4. the loop thread: affinity / SCHED_FIFO on itself, activate (READY=1), run;
5. SIGTERM / SIGINT: stop requested; the loop quick-stops and disables the drives at the next cycle
   boundary, STOPPING=1, exit 0.

A FAULT does not end the process: drives stay stopped, the reason is in STATUS=, the control
socket and telemetry, until ``hil reset`` (or the Zenoh reset queryable) clears it.
"""

from __future__ import annotations

import logging
import signal
import sys
import threading
from pathlib import Path
from typing import Any

from hil_runtime.config import RuntimeConfigError, load_runtime_config
from hil_runtime.control import ControlServer
from hil_runtime.factory import build_runtime
from hil_runtime.lifecycle import LifecycleState
from hil_runtime.realtime import lock_memory
from hil_runtime.record import check_record_path
from hil_runtime.runtime import Runtime
from hil_runtime.sdnotify import Notifier

log = logging.getLogger("hil_runtime.daemon")


def check(config_path: Path | str) -> str:
    """Everything ``hil run`` checks before it touches the bus (config, bus-load budget, bundle vs
    drives, condition vs limits), and nothing more: a summary, or the same one-line errors."""
    config = load_runtime_config(config_path)
    runtime = build_runtime(config, telemetry=False)
    bundle, limits = runtime.bundle, runtime.limits
    reference = config.reference.condition if config.reference.kind == "condition" else "hold"
    transport = config.bus.transport
    if transport.interface == "ipc":  # a squatted or unusable bus directory, before `hil run` finds it
        from drivers.ipc.directory import channel_problem

        problem = channel_problem(transport.channel, transport.group)
        if problem is not None:
            raise RuntimeConfigError(f"{config.source}: bus.transport.channel: {problem}")
    position = ", ".join(
        f"{a:.3g}..{b:.3g}" for a, b in zip(limits.position_lower_rad, limits.position_upper_rad, strict=True)
    )
    return "\n".join(
        [
            f"{config.source}: ok",
            f"  robot {config.robot}, {len(config.joint_names)} joints: {', '.join(config.joint_names)}",
            f"  bundle {bundle.path} ({bundle.law_name}, mode {config.bundle.mode}), "
            f"period {config.period_s * 1e3:g} ms",
            f"  bus {transport.interface}:{transport.channel}{' CAN FD' if transport.fd else ''}, node ids "
            f"{list(config.bus.node_ids)}, load {config.bus.bus_load().load:.0%} of the bus",
            f"  reference {reference}, pacing {config.loop.pacing}",
            f"  limits: position [{position}] rad, velocity {limits.velocity_limit_rad_s.round(3).tolist()} rad/s, "
            f"torque {limits.torque_limit_nm.round(1).tolist()} N·m",
            f"  telemetry {'on' if config.telemetry.enabled else 'off'}, "
            f"control socket {config.control_socket or 'none'}",
        ]
    )


def _say(text: str) -> None:
    print(f"hil run: {text}", file=sys.stderr, flush=True)


def serve(
    config_path: Path | str,
    record_path: Path | None = None,
    record_cycles: int = 0,
    urdf: Path | None = None,
    can_log: Path | None = None,
) -> int:
    """Run the daemon until SIGTERM/SIGINT (or loop.duration_s); the process exit code."""
    config = load_runtime_config(config_path)
    if record_path is not None:  # before the run: a record that cannot be written is refused now
        check_record_path(record_path)
    notifier = Notifier.from_environment()
    mcap = record_path is not None and record_path.suffix.lower() == ".mcap"
    capture: Any = None
    if can_log is not None:  # the drive bus on a bus that copies every frame to python-can's writer
        from drivers.capture import CanCapture, CaptureBus
        from drivers.transport import open_bus

        capture = CaptureBus(open_bus(config.bus.transport), CanCapture(can_log))
    recordings: list[Any] = []  # the MCAP sink, made by the factory for the runtime (it needs its bundle)

    def record_to_mcap(runtime: Runtime) -> Any:
        # a second sink beside telemetry, fed the same per-cycle state (docs/formats.md)
        from hil_runtime.formats.mcap_record import mcap_sink_for_run

        assert record_path is not None
        recordings.append(
            mcap_sink_for_run(record_path, config.robot, config.joint_names, runtime.bundle, config.period_s, urdf)
        )
        return recordings[-1]

    try:
        runtime = build_runtime(
            config,
            can_bus=capture,
            notifier=notifier,
            record_cycles=0 if mcap else record_cycles,
            recording=record_to_mcap if mcap else None,
        )
    except BaseException:
        if capture is not None:  # a refused start-up (bad bundle...) leaves no capture file
            capture.bus.shutdown()
            capture.capture.abandon()
        raise
    configured = threading.Event()

    def say_state(state: LifecycleState, fault: str | None) -> None:
        # A refused start-up is one line (the error, printed by the CLI): no "state FINALIZED" before it.
        if configured.is_set() or state is not LifecycleState.FINALIZED:
            _say(f"state {state.value}" + (f": {fault}" if fault else ""))

    runtime.lifecycle.subscribe(say_state)
    if config.loop.lock_memory:
        lock_memory(runtime.realtime)
    control = (
        ControlServer(config.control_socket, runtime, avoid_cpus=config.loop.cpu_affinity or ())
        if config.control_socket
        else None
    )
    stop_seen = threading.Event()

    def on_signal(signum: int, _frame: object) -> None:
        if not stop_seen.is_set():
            stop_seen.set()
            notifier.send(stopping=1, status=f"stopping on {signal.Signals(signum).name}")
        runtime.request_stop()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGTERM, signal.SIGINT)}
    outcome: dict[str, Any] = {}
    try:
        runtime.configure()  # StartupError (exit 2): drives never enabled
        configured.set()
        _say(
            f"configured {len(config.joint_names)} joints, bundle {runtime.bundle.law_name} "
            f"({config.bundle.mode}), period {config.period_s * 1e3:g} ms, pacing {config.loop.pacing}"
            + (f", control socket {config.control_socket}" if control else "")
        )

        def loop() -> None:
            try:
                outcome["result"] = runtime.run(shutdown_at_end=True)
            except BaseException as exc:  # reported below, exit code 1
                outcome["error"] = exc
                log.exception("the loop thread failed")
                runtime.shutdown()

        runtime.request_activate()
        thread = threading.Thread(target=loop, name="hil-loop")
        thread.start()
        while thread.is_alive():
            thread.join(0.05)  # wakes for signals: the handlers run on this (main) thread
    finally:
        if runtime.state is not LifecycleState.FINALIZED and "result" not in outcome and "error" not in outcome:
            runtime.shutdown()
        if control is not None:
            control.close()
        if capture is not None:  # the drive bus does not own a bus it was given
            capture.shutdown()
        notifier.close()
        for sig, handler in previous.items():
            signal.signal(sig, handler)
    if record_path is not None and not mcap and runtime.record.n:
        runtime.record.save_npz(record_path)
    if capture is not None:
        _say(f"captured {capture.capture.written} CAN frames to {can_log}, {capture.capture.dropped} dropped")
    for recording in recordings:
        _say(f"recorded {recording.recorder.states_written} cycles to {record_path}, {recording.dropped} dropped")
    if "error" in outcome:
        _say(f"loop failed: {outcome['error']!r}")
        return 1
    result = outcome["result"]
    stats = result.stats
    _say(
        f"stopped ({result.reason}) after {result.cycles} cycles, {stats.get('rate_hz', float('nan')):.1f} Hz, "
        f"overruns {stats.get('overruns', 0)}, "
        f"compute median {stats.get('compute_median_s', float('nan')) * 1e6:.1f} µs"
        + (f", last fault: {runtime.last_fault}" if runtime.last_fault else "")
    )
    return 0
