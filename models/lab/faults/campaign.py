"""``hil faults``: every fault the rig can inject, against the live runtime, with a table of figures.

    run_campaign(out_dir, quick=False, repeats=3, seed=0) -> results (also results.json + table.md)

Each fault (:data:`FAULTS`) runs ``repeats`` times on a fresh rig, seeded (the warm-up length, the
drive hit, the delay, the moment of the signal vary with the seed). A case that the rig spoils
before its fault is injected is run again, at most :data:`RIG_RETRIES` times, and counted. The
table has the issue's columns; docs/faults.md explains each fault and bound.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hil_runtime.machine import machine
from models.lab.faults import cases as c
from models.lab.faults import daemon_cases, realism_cases, zenoh_cases
from models.lab.faults import injections as inj
from models.lab.faults import security as sec
from models.lab.faults.cases import Expect
from models.lab.faults.report import summarize, write_outputs

if TYPE_CHECKING:
    from models.lab.faults.crafted import CraftKind

RIG_RETRIES = 2
TOLERATED_DROP = ("supervisor.stale_cycles", "bus.dropped", "bus.late", "bus.malformed")


@dataclass(frozen=True)
class FaultSpec:
    name: str
    label: str  # the table's fault column
    bound: str  # the detection bound the row is held to
    quick: bool  # part of ``hil faults --quick`` (the test suite)
    run: Callable[[str, int, int, Path], c.CaseResult]


def _ip(inject: Callable[..., Any], expect: Expect, **kwargs: Any) -> Callable[[str, int, int, Path], c.CaseResult]:
    return lambda name, repeat, seed, work: c.run_in_process(name, repeat, seed, inject, expect, **kwargs)


def _crafted(kind: CraftKind, expect: Expect, **kwargs: Any) -> Callable[[str, int, int, Path], c.CaseResult]:
    def run(name: str, repeat: int, seed: int, work: Path) -> c.CaseResult:
        from models.lab.faults.crafted import craft_bundle
        from sim_target.testing.ur5 import Q0_RAD

        trigger = craft_bundle(c.rigs.PD_BUNDLE, work / f"bundle-{kind}", kind)
        q0 = (trigger, *Q0_RAD[1:])  # the arm starts where the crafted graph misbehaves
        result = c.run_in_process(
            name,
            repeat,
            seed,
            lambda rig, rng: None,
            expect,
            q0_rad=q0,
            bundle_path=work / f"bundle-{kind}",
            fault_at_activation=True,
            **kwargs,
        )
        result.detail["trigger_q0_rad"] = trigger
        return result

    return run


def _startup(prepare: Callable[..., dict[str, Any]], text: str) -> Callable[[str, int, int, Path], c.CaseResult]:
    return lambda name, repeat, seed, work: c.startup_case(name, repeat, seed, work, prepare, text)


def _states_flow(rig: Any, result: c.CaseResult) -> None:
    """After the subscriber process is killed, the runtime's stream still reaches ours."""
    before = rig.watch.states
    time.sleep(0.3)
    flowing = rig.watch.states > before
    result.detail["state_samples_after_kill"] = rig.watch.states - before
    result.telemetry_event = None
    if not flowing:
        result.failures.append("no state sample reached the remaining subscriber after the kill")


def _telemetry_sent(rig: Any, result: c.CaseResult) -> None:
    counters = getattr(rig.runtime.telemetry, "counters", None)
    sent = counters().get("sent", 0) if callable(counters) else getattr(rig.runtime.telemetry, "sent", 0)
    result.detail["telemetry_sent_without_peer"] = sent


TWO = "2 cycles"
F = ("feedback_timeout", "stale_feedback")
SECURITY_FAULTS: tuple[FaultSpec, ...] = (  # issue 20, models/lab/faults/security.py
    FaultSpec(
        "forged_tpdo",
        "forged TPDO: another station answers each SYNC first with drive 3's TPDO (+0.03 rad)",
        TWO,
        True,
        _ip(sec.forge_tpdo, Expect(("bus_intruder",))),
    ),
    FaultSpec(
        "second_sender",
        "a second sender of a drive's heartbeat (another ipc peer, SO_PEERCRED)",
        TWO,
        False,
        _ip(sec.second_sender, Expect(("bus_intruder",)), transport="ipc"),
    ),
    FaultSpec(
        "second_master_nmt",
        "a second master's NMT command on the bus while running",
        TWO,
        False,
        _ip(sec.foreign_nmt, Expect(("bus_intruder",))),
    ),
    FaultSpec(
        "second_master_startup",
        "hil run on a bus that already has a master",
        "at start-up, before sending: exit 2",
        True,
        sec.second_master_at_start_up,
    ),
    FaultSpec(
        "squatted_bus_directory",
        "the ipc bus directory made first by another user",
        "at start-up: exit 2",
        False,
        sec.squatted_bus_directory,
    ),
    FaultSpec(
        "squatted_control_socket",
        "a fake runtime of another user at the control socket's path",
        "the client refuses: exit 2",
        True,
        sec.squatted_control_socket,
    ),
)
FAULTS: tuple[FaultSpec, ...] = (
    FaultSpec(
        "tpdo_drop_1_one",
        "TPDO dropped, 1 cycle, one drive",
        "tolerated (max_stale_cycles 1), counted",
        True,
        _ip(inj.drop_tpdos(1, False), Expect(counters=TOLERATED_DROP, max_cycles=None)),
    ),
    FaultSpec(
        "tpdo_drop_1_all",
        "TPDOs dropped, 1 cycle, all drives",
        "tolerated, counted",
        False,
        _ip(inj.drop_tpdos(1, True), Expect(counters=TOLERATED_DROP, max_cycles=None)),
    ),
    FaultSpec(
        "tpdo_drop_3_one", "TPDO dropped, 3 cycles, one drive", TWO, False, _ip(inj.drop_tpdos(3, False), Expect(F))
    ),
    FaultSpec(
        "tpdo_drop_3_all", "TPDOs dropped, 3 cycles, all drives", TWO, True, _ip(inj.drop_tpdos(3, True), Expect(F))
    ),
    FaultSpec(
        "tpdo_drop_50_one", "TPDO dropped, 50 cycles, one drive", TWO, False, _ip(inj.drop_tpdos(50, False), Expect(F))
    ),
    FaultSpec(
        "tpdo_drop_50_all", "TPDOs dropped, 50 cycles, all drives", TWO, False, _ip(inj.drop_tpdos(50, True), Expect(F))
    ),
    FaultSpec(
        "tpdo_delay_1_one",
        "TPDO delayed past the cycle, once, one drive",
        "tolerated, counted late",
        False,
        _ip(inj.delay_tpdos(1, False), Expect(counters=TOLERATED_DROP, max_cycles=None)),
    ),
    FaultSpec(
        "tpdo_delay_3_all",
        "TPDOs delayed past the cycle, 3 cycles, all drives",
        TWO,
        True,
        _ip(inj.delay_tpdos(3, True), Expect(F)),
    ),
    FaultSpec(
        "tpdo_corrupt_1_one",
        "TPDO corrupted (wrong length), once, one drive",
        "tolerated, counted malformed",
        True,
        _ip(inj.corrupt_tpdos(1, False), Expect(counters=TOLERATED_DROP, max_cycles=None)),
    ),
    FaultSpec(
        "tpdo_corrupt_3_all",
        "TPDOs corrupted (wrong length), 3 cycles, all drives",
        TWO,
        False,
        _ip(inj.corrupt_tpdos(3, True), Expect(F)),
    ),
    FaultSpec(
        "wrong_length_flood",
        "wrong-length TPDO/heartbeat/EMCY frames on our drives' COB-IDs, 0.3 s",
        f"a second sender: {TWO}",
        False,
        _ip(inj.flood("wrong_length"), Expect(("bus_intruder",))),
    ),
    FaultSpec(
        "unknown_cob_flood",
        "unknown COB-IDs flooding the bus, 0.3 s",
        "tolerated, counted",
        True,
        _ip(inj.flood("unknown"), Expect(counters=("bus.unknown_cob_id",), max_cycles=None)),
    ),
    FaultSpec(
        "heartbeat_lost",
        "a drive's heartbeat lost",
        "heartbeat_timeout_s (0.5 s)",
        True,
        _ip(
            inj.target_fault({"kind": "heartbeat", "node_id": "random", "silent": True}),
            Expect(("heartbeat_lost",), max_cycles=None),
            observe_cycles=5000,
        ),
    ),
    FaultSpec(
        "drive_fault_emcy",
        "a drive enters FAULT (EMCY 0x2310)",
        TWO,
        True,
        _ip(
            inj.target_fault({"kind": "drive_fault", "node_id": "random", "error_code": 0x2310}),
            Expect(("drive_fault",)),
        ),
    ),
    FaultSpec(
        "sdo_abort_startup",
        "SDO abort at start-up (drive 2 refuses 0x6072)",
        "at start-up, before any enable",
        False,
        _startup(c.prepare_sdo_abort, "0x06090030"),
    ),
    FaultSpec(
        "bus_closed",
        "the bus closed under the driver",
        TWO,
        True,
        _ip(inj.close_bus_under_driver, Expect(("transport",)), settle_s=1.6),
    ),
    FaultSpec(
        "target_killed",
        "the target process killed (SIGKILL), ipc bus",
        TWO,
        True,
        _ip(inj.kill_target_process, Expect(("feedback_timeout", "transport", "stale_feedback")), transport="ipc"),
    ),
    FaultSpec(
        "emulator_nan",
        "emulator output NaN (crafted bundle)",
        "substituted in the cycle; reported at the next stats",
        True,
        _crafted("nan", Expect(counters=("supervisor.law_substitutions",), max_cycles=None)),
    ),
    FaultSpec(
        "emulator_inf",
        "emulator output +inf (crafted bundle)",
        "substituted in the cycle; reported at the next stats",
        False,
        _crafted("inf", Expect(counters=("supervisor.law_substitutions",), max_cycles=None)),
    ),
    FaultSpec(
        "policy_nan_both",
        "law and emulator output NaN (crafted bundle)",
        TWO,
        True,
        _crafted("nan_both", Expect(("policy_nonfinite",))),
    ),
    FaultSpec(
        "saturating_bundle",
        "a bundle that saturates every joint (crafted, +1e6 N·m)",
        "clipped in the cycle",
        True,
        _crafted(
            "saturate",
            Expect(may_fault=c.LIMIT_FAULTS, counters=("supervisor.saturated_cycles",), max_cycles=None),
            observe_cycles=3000,
        ),
    ),
    FaultSpec(
        "tampered_bundle",
        "bundle tampered on disk before start",
        "at start-up, before the bus",
        True,
        _startup(c.prepare_tampered, "sha256 mismatch"),
    ),
    FaultSpec(
        "subscriber_killed",
        "the telemetry subscriber killed (SIGKILL)",
        "not a runtime fault",
        False,
        _ip(
            inj.kill_subscriber,
            Expect(event=False, max_cycles=None),
            post_check=_states_flow,
            prepare=inj.start_subscriber,
        ),
    ),
    FaultSpec(
        "no_zenoh_peer",
        "no Zenoh peer at all (telemetry on)",
        "not a runtime fault",
        False,
        _ip(
            lambda rig, rng: None,
            Expect(event=False, max_cycles=None),
            watch_telemetry=False,
            post_check=_telemetry_sent,
        ),
    ),
    FaultSpec(
        "cpu_starvation",
        "CPU starvation: busy processes on every CPU, clock pacing",
        "overruns counted",
        False,
        _ip(
            inj.starve_cpu,
            Expect(
                may_fault=("feedback_timeout", "stale_feedback", "overrun_budget"),
                counters=("overruns",),
                max_cycles=None,
            ),
            observe_cycles=2500,
            config_extra={"loop": {"pacing": "clock", "time_base": "cycles"}},
        ),
    ),
    FaultSpec(
        "loop_stall",
        "the loop stalled (daemon SIGSTOPped past the watchdog)",
        "WatchdogSec (0.2 s here)",
        True,
        daemon_cases.loop_stall,
    ),
    FaultSpec(
        "sigterm_during_enable",
        "SIGTERM during enable (daemon)",
        "a request: exit 0",
        True,
        daemon_cases.sigterm_during_enable,
    ),
    FaultSpec(
        "payload_jump",
        "payload jump, +5 kg at the flange",
        "not a fault: rejected, or a limit FAULT",
        False,
        _ip(
            inj.target_fault({"kind": "payload", "mass_kg": 5.0}),
            Expect(may_fault=c.LIMIT_FAULTS, event=False, max_cycles=None),
            observe_cycles=1500,
        ),
    ),
    FaultSpec(
        "disturbance_10x",
        "10x the paper's disturbance on the plant",
        "not a fault: rejected, or a limit FAULT",
        True,
        _ip(
            inj.target_fault({"kind": "impulse", "torque_nm": [10, 10, 50, 50, 100, 100]}),
            Expect(may_fault=c.LIMIT_FAULTS, event=False, max_cycles=None),
            observe_cycles=1500,
        ),
    ),
    *realism_cases.faults(FaultSpec),
    *SECURITY_FAULTS,
    FaultSpec(
        "reference_out_of_limits",
        "a reference that would leave the limits",
        "at start-up, before the bus",
        False,
        _startup(c.prepare_reference_out, "WIDE"),
    ),
)
# Zenoh controls (issue 20): hostile sessions against stop/reset while the arm runs.
FAULTS += (
    FaultSpec(
        "zenoh_control_unauthenticated",
        "stop/reset (exact and wildcard) from Zenoh sessions without credentials or with a wrong password",
        "refused at the handshake: no reply, ACTIVE",
        True,
        zenoh_cases.unauthenticated_control,
    ),
    FaultSpec(
        "zenoh_control_wildcard",
        "wildcard queries (hil/<robot>/**, hil/*/stop, hil/<robot>/re$*...) from an authenticated session",
        "only exact keys reach stop/reset: ACTIVE",
        True,
        zenoh_cases.wildcard_control,
    ),
)
QUICK = tuple(spec.name for spec in FAULTS if spec.quick)


def run_case(spec: FaultSpec, repeat: int, seed: int, scratch: Path) -> c.CaseResult:
    """One case, run again when the rig spoils it before the injection (counted)."""
    retries = 0
    while True:
        work = scratch / f"{spec.name}-{repeat}-{retries}"
        work.mkdir(parents=True, exist_ok=True)
        started = time.monotonic()
        c.rigs.PLANT_LATENESS.clear()
        try:
            result = spec.run(spec.name, repeat, seed, work)
        except c.RigFault as exc:
            if retries < RIG_RETRIES:
                retries += 1
                continue
            result = c.CaseResult(spec.name, repeat, seed, action=f"rig failed: {exc}", failures=[f"rig: {exc}"])
        except Exception as exc:  # noqa: BLE001 - a campaign bug or a crash: the row fails, the campaign goes on
            result = c.CaseResult(
                spec.name,
                repeat,
                seed,
                action=f"case raised {type(exc).__name__}",
                failures=[f"{type(exc).__name__}: {exc}"],
            )
        result.rig_retries = retries
        result.wall_s = round(time.monotonic() - started, 2)
        _mark_plant_validity(result)
        shutil.rmtree(work, ignore_errors=True)
        return result


def _mark_plant_validity(result: c.CaseResult) -> None:
    """A case whose free-running plant fell behind the wall clock tested nothing: INVALID, not passed."""
    from sim_target.lateness import invalid_reason

    for lateness, period_s in c.rigs.PLANT_LATENESS:
        reason = invalid_reason(lateness, period_s)
        if reason is not None:
            result.plant_invalid = reason
            result.passed = False
            result.failures.append(f"INVALID: {reason}")
            return


def select(quick: bool, only: tuple[str, ...] | None = None) -> tuple[FaultSpec, ...]:
    specs = tuple(spec for spec in FAULTS if (not quick or spec.quick))
    if only:
        known = {spec.name for spec in FAULTS}
        unknown = [name for name in only if name not in known]
        if unknown:
            raise CampaignError(f"--only: unknown fault(s) {', '.join(unknown)} (known: {', '.join(sorted(known))})")
        specs = tuple(spec for spec in FAULTS if spec.name in only)
    return specs


class CampaignError(ValueError):
    exit_code = 2


def run_campaign(
    out_dir: Path | None,
    *,
    quick: bool = False,
    repeats: int = 3,
    seed: int = 0,
    only: tuple[str, ...] | None = None,
    progress: Callable[[c.CaseResult], None] | None = None,
) -> dict[str, Any]:
    """Run the faults; write ``results.json`` and ``table.md`` to ``out_dir`` (atomically)."""
    specs = select(quick, only)
    if repeats < 1:
        raise CampaignError(f"--repeats: must be at least 1, got {repeats}")
    load_before = machine()["load_average"]
    started = time.monotonic()
    rows: list[dict[str, Any]] = []
    cases: list[c.CaseResult] = []
    scratch = Path(tempfile.mkdtemp(prefix="hil-faults-"))
    try:
        for index, spec in enumerate(specs):
            results = []
            for repeat in range(repeats):
                case_seed = seed * 1000 + index * 10 + repeat
                result = run_case(spec, repeat, case_seed, scratch)
                results.append(result)
                if progress is not None:
                    progress(result)
            cases.extend(results)
            rows.append(summarize(spec, results))
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    document = {
        "command": "hil faults"
        + (" --quick" if quick else "")
        + (f" --repeats {repeats}" if repeats != 3 else "")
        + (f" --seed {seed}" if seed else "")
        + (f" --only {','.join(only)}" if only else ""),
        "machine": {**machine("python-can", "canopen", "pybullet", "numpy"), "load_average_before": load_before},
        "wall_s": round(time.monotonic() - started, 1),
        "repeats": repeats,
        "passed": all(row["pass"] for row in rows),
        "rows": rows,
        "cases": [case.to_json() for case in cases],
    }
    if out_dir is not None:
        write_outputs(out_dir, document)
    return document
