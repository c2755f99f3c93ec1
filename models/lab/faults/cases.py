"""The faults of the campaign (issue 15), each a function of (scratch directory, seed) -> CaseResult.

Every case runs on a fresh rig (models/lab/rigs.py) so no case inherits another's state. A
case that FAULTs before its fault is injected (the rig, not the runtime: a loaded machine) raises
:class:`RigFault` and is run again (counted in results.json as ``rig_retries``).
"""

from __future__ import annotations

import contextlib
import io
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from sim_target.launch import Transport

from hil_runtime.outputs import json_safe
from models.lab import rigs
from models.lab.rigs import InProcessRig, in_process_rig
from sim_target.testing.ur5 import Q0_RAD

QUICK_STOPPED = ("quick stop active", "switch on disabled", "fault", "fault reaction active", "not enabled")
LIMIT_FAULTS = ("position_limit", "velocity_limit")
# The counters a tolerated fault may raise (status), as the action column names them.
ANOMALIES = frozenset(
    {
        "stale_cycles",
        "dropped",
        "late",
        "malformed",
        "unknown_cob_id",
        "emcy",
        "overruns",
        "law_substitutions",
        "saturated_cycles",
    }
)


class RigFault(RuntimeError):
    """The rig failed before the fault was injected: the case is run again."""


@dataclass
class CaseResult:
    fault: str
    repeat: int
    seed: int
    detected_cycles: int | None = None  # cycles from injection to the runtime's reaction
    detected_s: float | None = None  # wall time of the same, where cycles are not the measure
    action: str = ""
    max_torque_ratio: float | None = None  # max |tau| / limit commanded after the fault (bus and record)
    nonfinite_commanded: bool = False
    drives_final: list[str] | str = ""
    daemon_alive: bool = False
    daemon_note: str = ""
    telemetry_event: bool | None = None  # None: not applicable (stated in the note)
    status_shows: bool | None = None
    arm_in_limits: bool | None = None
    passed: bool = False
    failures: list[str] = field(default_factory=list)
    rig_retries: int = 0
    plant_invalid: str | None = None  # why the free-running plant's lateness voids the case (lateness.py)
    wall_s: float = 0.0
    detail: dict[str, Any] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return json_safe(asdict(self))


@dataclass(frozen=True)
class Expect:
    """What the runtime must do about one fault."""

    faults: tuple[str, ...] = ()  # FAULT kinds accepted; () = no FAULT allowed (tolerated)
    may_fault: tuple[str, ...] = ()  # tolerated, but these FAULT kinds are acceptable too (plant faults)
    max_cycles: int | None = 2  # detection bound in cycles; None: not measured in cycles
    event: bool = True  # a telemetry event must be seen
    counters: tuple[str, ...] = ()  # for tolerated faults: one of these status counters must rise


# --- the in-process driver ----------------------------------------------------------------------------


def _counters(runtime: Any) -> dict[str, int]:
    status = runtime.status()
    out = {f"supervisor.{k}": int(v) for k, v in status.get("supervisor", {}).items()}
    out.update({f"bus.{k}": int(v) for k, v in (status.get("bus") or {}).items()})
    out["overruns"] = int(status.get("overruns") or 0)
    return out


def run_in_process(
    name: str,
    repeat: int,
    seed: int,
    inject: Callable[[InProcessRig, np.random.Generator], Any],
    expect: Expect,
    *,
    transport: Transport = "virtual",
    q0_rad: tuple[float, ...] = Q0_RAD,
    bundle_path: Path | None = None,
    config_extra: dict[str, Any] | None = None,
    observe_cycles: int = 400,
    fault_at_activation: bool = False,
    settle_s: float = 0.3,
    watch_telemetry: bool = True,
    post_check: Callable[[InProcessRig, CaseResult], None] | None = None,
    prepare: Callable[[InProcessRig, np.random.Generator], Any] | None = None,
    target_extra: dict[str, Any] | None = None,
) -> CaseResult:
    """Run the loop, inject at a cycle boundary, watch the runtime react; the row's figures."""
    from hil_runtime.lifecycle import LifecycleState

    rng = np.random.default_rng(seed)
    result = CaseResult(name, repeat, seed)
    kwargs: dict[str, Any] = {"q0_rad": q0_rad, "config_extra": config_extra, "target_extra": target_extra}
    if bundle_path is not None:
        kwargs["bundle_path"] = bundle_path
    with in_process_rig(transport, **kwargs) as rig:
        runtime = rig.runtime
        rig.start(watch=watch_telemetry)
        watch = rig.watch
        if prepare is not None:  # slow set-up (a subscriber process) before the drives are enabled
            result.detail["prepared"] = prepare(rig, rng)
        t_inject = time.monotonic()
        injected_cycle = 0
        if fault_at_activation:
            if rig.tap is not None:
                rig.tap.mark_s = t_inject
            activated = runtime.activate()
            result.detail["activated"] = activated
        else:
            if not runtime.activate():
                raise RigFault(f"activation failed: {runtime.lifecycle.fault}")
            warm = int(rng.integers(150, 300))
            first = runtime.run(max_cycles=warm)
            if first.fault is not None:
                raise RigFault(f"FAULT before the injection: {first.fault}")
            before = _counters(runtime)
            injected_cycle = runtime.total_cycles
            t_inject = time.monotonic()
            if rig.tap is not None:
                rig.tap.mark_s = t_inject
            info = inject(rig, rng)
            if info:
                result.detail["injection"] = info
        if fault_at_activation:
            before = {}
        # The loop runs on as the daemon's does (until the stop below) while the case is judged:
        # a paused loop would itself be a fault (the drives stop when the master goes silent).
        if runtime.state is LifecycleState.ACTIVE or runtime.state is LifecycleState.FAULT:
            rig.loop.start(None)
        deadline = time.monotonic() + 60.0
        fault_seen_s: float | None = None
        while rig.loop.alive and time.monotonic() < deadline:
            if runtime.state is LifecycleState.FAULT:
                fault_seen_s = fault_seen_s or time.monotonic()
                if time.monotonic() - fault_seen_s > settle_s:  # the daemon stays up in FAULT
                    break
            elif runtime.total_cycles - injected_cycle >= observe_cycles:
                break
            time.sleep(0.005)
        state = runtime.state
        result.daemon_alive = (
            rig.loop.error is None
            and state is not LifecycleState.FINALIZED
            and (rig.loop.alive or rig.loop.thread is None)
        )
        result.daemon_note = (
            "loop thread up"
            if rig.loop.alive
            else (
                f"loop returned ({rig.loop.result.reason})"
                if rig.loop.result is not None
                else (f"loop raised {rig.loop.error!r}" if rig.loop.error else "not started (FAULT at activation)")
            )
        )
        result.drives_final = rig.drive_states()
        arm = rig.arm_position()
        lower, upper = rig.position_limits()
        status = runtime.status()
        fault_kind = (
            runtime.last_fault.kind.value if runtime.last_fault is not None and state is LifecycleState.FAULT else None
        )
        # the telemetry event (the publisher thread sends within a millisecond or so)
        event = None
        if watch is not None:
            kinds = ("fault",) if fault_kind else ("warning", "stale_feedback")
            event = watch.wait_event(kinds, t_inject - 0.001, 2.0)
            result.detail["events"] = [{k: v for k, v in e.items() if k != "t"} for e in watch.events[-6:]]
        after = _counters(runtime)
        rose = {k: after[k] - before.get(k, 0) for k in after if after[k] > before.get(k, 0)}
        result.detail["counters_rose"] = rose
        result.detail["status"] = {k: status.get(k) for k in ("state", "fault", "fault_cycle", "cycles", "overruns")}
        if post_check is not None:
            post_check(rig, result)
        if fault_seen_s is not None:
            result.detail["fault_after_s"] = round(fault_seen_s - t_inject, 4)
        rig.loop.stop()
        record = {k: v.copy() for k, v in runtime.record.arrays().items()}
        runtime.shutdown()

    # figures ------------------------------------------------------------------------------------
    limit = runtime.limits.torque_limit_nm
    tau = record["tau"][injected_cycle:]
    q = record["q"][injected_cycle:]
    result.nonfinite_commanded = bool(tau.size and not np.isfinite(tau).all())
    ratio = float(np.max(np.abs(tau) / limit)) if tau.size else 0.0
    if rig.tap is not None:
        ratio = max(ratio, rig.tap.max_ratio_after)
        result.detail["rpdo_frames_after"] = rig.tap.frames_after
    result.max_torque_ratio = ratio
    inside = True if arm is None else bool(np.all((arm >= lower) & (arm <= upper)))
    if q.size:
        inside = inside and bool(np.all((q >= lower) & (q <= upper)))
    result.arm_in_limits = inside
    result.detail["arm_final_rad"] = None if arm is None else arm.round(4).tolist()
    if fault_kind is not None:
        cycles = (runtime.fault_cycle or 0) - injected_cycle
        result.detected_cycles = cycles
        result.detected_s = result.detail.get("fault_after_s")
        result.action = f"FAULT {fault_kind}, quick stop"
        result.status_shows = bool(status.get("fault")) and status.get("state") == "FAULT"
        result.detail["fault"] = status.get("fault")
    else:
        shown = [f"{k.split('.')[-1]} +{v}" for k, v in sorted(rose.items()) if k.split(".")[-1] in ANOMALIES]
        result.action = "tolerated: " + (", ".join(shown) or "nothing counted")
        result.status_shows = any(k in rose for k in expect.counters) if expect.counters else None
        if event is not None and event.get("cycle") is not None:
            result.detected_cycles = int(event["cycle"]) - injected_cycle
    result.telemetry_event = (event is not None) if watch is not None else None
    if not expect.event and fault_kind is None and not result.telemetry_event:
        result.telemetry_event = None  # nothing to report (plant faults ridden through, subscriber faults)

    # judgement ------------------------------------------------------------------------------------
    fails = result.failures
    if fault_kind is None and expect.faults:
        fails.append(f"no FAULT (expected {'/'.join(expect.faults)})")
    if fault_kind is not None and fault_kind not in expect.faults + expect.may_fault:
        fails.append(f"FAULT {fault_kind} (expected {'/'.join(expect.faults + expect.may_fault) or 'none'})")
    if fault_kind is not None:
        if isinstance(result.drives_final, list) and any(s == "operation enabled" for s in result.drives_final):
            fails.append("a drive is still enabled after the FAULT")
        if (
            expect.faults
            and expect.max_cycles is not None
            and fault_kind in expect.faults
            and (result.detected_cycles is None or result.detected_cycles > expect.max_cycles)
        ):
            fails.append(f"detected after {result.detected_cycles} cycles (bound {expect.max_cycles})")
        if not result.status_shows:
            fails.append("the status does not show the FAULT")
    elif expect.counters and not result.status_shows:
        fails.append(f"no counter rose ({', '.join(expect.counters)})")
    if ratio > 1.0 + 1e-9:
        fails.append(f"|tau| reached {ratio:.3f} x the limit")
    if result.nonfinite_commanded:
        fails.append("a non-finite torque was commanded")
    if not result.daemon_alive:
        fails.append(f"daemon not alive: {result.daemon_note}")
    if (expect.event or fault_kind is not None) and watch is not None and not result.telemetry_event:
        fails.append("no telemetry event")
    if not result.arm_in_limits:
        fails.append("the arm left the position limits")
    result.passed = not fails
    return result


# --- start-up refusals (the daemon exits 2 with one line, drives never enabled) ----------------------


def run_cli_in_process(argv: list[str]) -> tuple[int, str]:
    """``hil`` in this process (signal handlers need the main thread); exit code and stderr."""
    from hil_runtime.cli import main

    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = main(argv)
    return code, err.getvalue()


Prepare = Callable[[Path, dict[str, Any], Any], dict[str, Any]]


def startup_case(name: str, repeat: int, seed: int, work: Path, prepare: Prepare, expect_text: str) -> CaseResult:
    """Write a runtime config (changed by ``prepare``), run ``hil run`` on it against a live target."""
    import yaml

    from sim_target.launch import launch_target

    result = CaseResult(name, repeat, seed)
    work.mkdir(parents=True, exist_ok=True)
    with launch_target(rigs.target_config(), "virtual") as target:
        data = rigs.runtime_config_dict(dict(target.transport), telemetry_port=None)
        data = prepare(work, data, target)
        path = work / "runtime.yaml"
        path.write_text(yaml.safe_dump(data))
        t0 = time.monotonic()
        code, err = run_cli_in_process(["run", "--config", str(path)])
        result.detected_s = round(time.monotonic() - t0, 3)
        enabled = [s.value for s in target.server.drives.states()]
        steps = target.server.stats.steps
        arm = np.asarray(target.server.plant.state().position_rad)
    lines = [line for line in err.splitlines() if line.strip()]
    result.detail.update({"exit_code": code, "stderr": lines[-3:], "target_steps": steps})
    result.action = f"refused at start-up: exit {code}, one line"
    result.drives_final = enabled
    result.daemon_alive = code == 2
    result.daemon_note = "exit 2: unrecoverable start-up error (allowed)"
    result.telemetry_event = None  # no session before start-up succeeds: the line and exit code say it
    result.status_shows = None
    result.max_torque_ratio = 0.0
    result.arm_in_limits = bool(np.all(np.abs(arm) <= np.pi))
    fails = result.failures
    if code != 2:
        fails.append(f"exit {code}, expected 2")
    if len(lines) != 1 or "Traceback" in err:
        fails.append(f"{len(lines)} lines on stderr, expected one")
    if expect_text not in err:
        fails.append(f"'{expect_text}' not in the message")
    if any(s == "operation enabled" for s in enabled):
        fails.append("a drive was enabled")
    result.passed = not fails
    return result


def prepare_sdo_abort(work: Path, data: dict[str, Any], target: Any) -> dict[str, Any]:
    # Drive 2 refuses its torque limit (0x6072) as a real drive refuses a value out of its range.
    target.server.drives.abort_sdo_writes(2, 0x6072, 0x06090030)
    return data


def prepare_tampered(work: Path, data: dict[str, Any], target: Any) -> dict[str, Any]:
    from models.lab.faults.crafted import tamper_bundle

    tamper_bundle(rigs.PD_BUNDLE, work / "tampered")
    data["bundle"]["path"] = str(work / "tampered")
    return data


def prepare_reference_out(work: Path, data: dict[str, Any], target: Any) -> dict[str, Any]:
    # C1's shape with joint 2 asked to swing 4 rad: past its ±2.513 rad limit.
    (work / "conditions.yaml").write_text(
        "defaults: {duration_s: 5.0, shape: raised_sine, frequency_hz: 0.1, phase_s: 2.5, initial_state: reference}\n"
        "conditions:\n  - name: WIDE\n    amplitude_rad: [-pi/4, 4.0, -pi/6, -pi/4, pi/2, pi/2]\n"
    )
    data["reference"] = {"kind": "condition", "condition": "WIDE", "conditions_file": str(work / "conditions.yaml")}
    return data
