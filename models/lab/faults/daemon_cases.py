"""The campaign's cases that run ``hil run`` as its own process against ``hil target serve`` (the
daemon rig, models/lab/rigs.py): SIGTERM during enable, the loop stalled past the watchdog."""

from __future__ import annotations

import math
import signal
import time
from pathlib import Path

import numpy as np

from models.lab import rigs
from models.lab.faults.cases import CaseResult, RigFault
from sim_target.testing.ur5 import MAX_TORQUE_NM

# --- the daemon as its own process ------------------------------------------------------------------------


# Two niced processes on a loaded machine: the heartbeat and feedback waits are loosened (the
# protocol bounds are measured in process); these cases are about the watchdog and signals.
DAEMON_BUS = {"heartbeat_timeout_s": 2.0, "feedback_timeout_s": 0.2}


def _stderr_ok(lines: list[str]) -> bool:
    return not any("Traceback" in line for line in lines)


def sigterm_during_enable(name: str, repeat: int, seed: int, work: Path) -> CaseResult:
    """SIGTERM as the daemon activates (drives being enabled): quick stop, disable, exit 0."""
    rng = np.random.default_rng(seed)
    result = CaseResult(name, repeat, seed)
    delay_s = float(rng.uniform(0.0, 0.01))
    with rigs.daemon_rig(work, telemetry=False, bus=DAEMON_BUS) as rig:
        deadline = time.monotonic() + 90
        while rig.configured_at is None and rig.process.poll() is None and time.monotonic() < deadline:
            time.sleep(0.0005)
        if rig.configured_at is None:
            raise RigFault(f"the daemon did not configure: {rig.stderr_lines[-3:]}")
        time.sleep(delay_s)
        sent = time.monotonic()
        rig.process.send_signal(signal.SIGTERM)
        code = rig.wait_exit(30)
        result.detected_s = round(time.monotonic() - sent, 3)
        enabled = rigs.target_drives_enabled(rig.target)
        notify_stopping = rig.notify.saw("STOPPING=1")
        before_active = rig.active_at is None or sent < rig.active_at
        lines = list(rig.stderr_lines)
        record_ok = (not rig.record.exists()) or _npz_ok(rig.record)
        leftovers = [p.name for p in work.iterdir() if ".partial" in p.name]
    states = [line.split("state ", 1)[1] for line in lines if "hil run: state " in line]
    result.detail.update(
        {
            "exit_code": code,
            "signal_after_configured_s": round(delay_s, 4),
            "states": states,
            "stderr_tail": lines[-2:],
            "record_complete": record_ok,
            "partial_files": leftovers,
        }
    )
    result.detail["signal_before_active"] = before_active
    when = "during start-up/enable" if before_active else "just after ACTIVE"
    result.action = f"SIGTERM {when}: quick stop, disable, exit {code}"
    result.drives_final = ["operation enabled" if x else "not enabled" for x in enabled]
    result.daemon_alive = code == 0
    result.daemon_note = f"exit {code} on SIGTERM (allowed)"
    result.telemetry_event = None  # a requested stop, not a fault: STOPPING=1 reaches systemd
    result.status_shows = notify_stopping
    result.max_torque_ratio = _record_ratio(rig.record) if record_ok and rig.record.exists() else 0.0
    result.nonfinite_commanded = False
    result.arm_in_limits = True
    fails = result.failures
    if code != 0:
        fails.append(f"exit {code}")
    if not _stderr_ok(lines):
        fails.append("a traceback on stderr")
    if any(enabled):
        fails.append("a drive is still enabled")
    if not notify_stopping:
        fails.append("no STOPPING=1")
    if not record_ok or leftovers:
        fails.append("a half-written file")
    if (result.max_torque_ratio or 0) > 1 + 1e-9:
        fails.append("torque over the limit")
    result.passed = not fails
    return result


def _npz_ok(path: Path) -> bool:
    try:
        with np.load(path) as data:
            return "tau" in data.files
    except Exception:  # noqa: BLE001 - a half-written file is exactly what this detects
        return False


def _record_ratio(path: Path) -> float:
    with np.load(path) as data:
        tau = data["tau"]
    return float(np.max(np.abs(tau) / np.asarray(MAX_TORQUE_NM))) if tau.size else 0.0


def loop_stall(name: str, repeat: int, seed: int, work: Path) -> CaseResult:
    """The daemon's whole process stopped (SIGSTOP) for longer than the watchdog and the drives'
    master-loss timeout: the watchdog pings stop (systemd would restart it), the drives quick-stop
    on their own, and on SIGCONT the daemon finds them stopped: FAULT, alive."""
    rng = np.random.default_rng(seed)
    result = CaseResult(name, repeat, seed)
    watchdog_usec = 200_000
    comm_loss_s = 0.3
    stall_s = comm_loss_s + 0.7 + float(rng.uniform(0.0, 0.3))
    bus = {**DAEMON_BUS, "comm_loss_timeout_s": comm_loss_s}
    # The telemetry link must outlive the stop (Zenoh's lease, 1 s by default, is shorter than the
    # 1.0-1.3 s stall): the case checks the runtime's fault event, not Zenoh's reconnection (a CI
    # run lost the event once, 2026-11-26).
    with rigs.daemon_rig(work, watchdog_usec=watchdog_usec, bus=bus, telemetry_lease_s=stall_s + 2.0) as rig:
        status = rig.wait_status(
            lambda s: s.get("state") == "FAULT" or (s.get("state") == "ACTIVE" and s.get("cycles", 0) > 300), 120
        )
        if status.get("state") != "ACTIVE":
            raise RigFault(f"the daemon did not reach ACTIVE: {status} {rig.stderr_lines[-3:]}")
        watch = rigs.TelemetryWatch(rig.telemetry_port)
        try:
            time.sleep(0.3)
            stopped_at = time.monotonic()
            rig.process.send_signal(signal.SIGSTOP)
            time.sleep(stall_s)
            during = rigs.target_drives_enabled(rig.target)
            rig.process.send_signal(signal.SIGCONT)
            resumed = time.monotonic()
            after = rig.wait_status(lambda s: s.get("state") == "FAULT", 30)
            time.sleep(0.5)
            alive = rig.process.poll() is None
            final = rigs.target_drives_enabled(rig.target)
            event = watch.wait_event(("fault",), stopped_at, 3.0)
        finally:
            watch.close()
        pings = rig.notify.watchdog_times()
        gaps = np.diff([t for t in pings if stopped_at - 1.0 <= t <= resumed + 1.0])
        max_gap = float(gaps.max()) if gaps.size else math.inf
        rig.process.send_signal(signal.SIGTERM)
        code = rig.wait_exit(30)
        lines = list(rig.stderr_lines)
        ratio = _record_ratio(rig.record) if _npz_ok(rig.record) else None
    result.detected_s = round(max_gap, 3)
    result.detail.update(
        {
            "stall_s": round(stall_s, 3),
            "watchdog_usec": watchdog_usec,
            "max_ping_gap_s": round(max_gap, 3),
            "drives_enabled_during_stall": during,
            "status_after": {k: after.get(k) for k in ("state", "fault")},
            "exit_code": code,
            "stderr_tail": lines[-2:],
        }
    )
    kind = str(after.get("fault") or "").split(":")[0]
    result.detail["fault_on_resume"] = kind
    result.action = (
        f"watchdog silent (> WatchdogSec: systemd restarts); drives quick-stopped on their own; on resume FAULT {kind}"
    )
    result.drives_final = ["operation enabled" if x else "not enabled" for x in final]
    result.daemon_alive = alive
    result.daemon_note = "up in FAULT after SIGCONT; exit 0 on SIGTERM" if alive and code == 0 else f"exit {code}"
    result.telemetry_event = event is not None
    result.status_shows = after.get("state") == "FAULT"
    result.max_torque_ratio = ratio
    result.arm_in_limits = True
    fails = result.failures
    if not max_gap > watchdog_usec / 1e6:
        fails.append(f"watchdog pings went on during the stall (max gap {max_gap:.3f} s)")
    if any(during):
        fails.append("drives stayed enabled during the stall")
    if any(final):
        fails.append("drives enabled after the stall")
    if not result.status_shows:
        fails.append(f"no FAULT after resume: {after}")
    if not alive or code != 0 or not _stderr_ok(lines):
        fails.append(f"daemon: alive {alive}, exit {code}")
    if not result.telemetry_event:
        fails.append("no telemetry event")
    if ratio is None or ratio > 1 + 1e-9:
        fails.append(f"record: {ratio}")
    result.passed = not fails
    return result
