"""The campaign's report: one table row per fault from its repeats (:func:`summarize`), the
markdown table (:func:`format_table`) and ``results.json`` + ``table.md`` (:func:`write_outputs`)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from models.lab.faults import cases as c

if TYPE_CHECKING:
    from models.lab.faults.campaign import FaultSpec

SECONDS_ROWS = ("heartbeat_lost", "loop_stall")  # bounds in seconds: the wall time is shown too


def _fmt_cycles(values: list[int]) -> str:
    if not values:
        return "—"
    return f"{int(np.median(values))}, {max(values)}"


def summarize(spec: FaultSpec, results: list[c.CaseResult]) -> dict[str, Any]:
    """One table row from the repeats of one fault."""
    cycles = [r.detected_cycles for r in results if r.detected_cycles is not None]
    seconds = [r.detected_s for r in results if r.detected_s is not None]
    ratios = [r.max_torque_ratio for r in results if r.max_torque_ratio is not None]
    actions = _actions(results)
    finals = sorted(
        {
            ", ".join(sorted(set(r.drives_final))) if isinstance(r.drives_final, list) else r.drives_final
            for r in results
        }
    )

    def tri(values: list[bool | None]) -> str:
        known = [v for v in values if v is not None]
        if not known:
            return "n/a"
        return "yes" if all(known) else f"no ({known.count(False)}/{len(known)})"

    return {
        "fault": spec.name,
        "label": spec.label,
        "bound": spec.bound,
        "repeats": len(results),
        "detected_cycles": cycles,
        "detected_cycles_median": float(np.median(cycles)) if cycles else None,
        "detected_cycles_max": max(cycles) if cycles else None,
        "detected_s_max": max(seconds) if seconds else None,
        "action": actions,
        "max_torque_ratio": max(ratios) if ratios else None,
        "nonfinite": any(r.nonfinite_commanded for r in results),
        "drives_final": "; ".join(finals),
        "daemon_alive": tri([r.daemon_alive for r in results]),
        "daemon_note": "; ".join(sorted({r.daemon_note for r in results})),
        "telemetry_event": tri([r.telemetry_event for r in results]),
        "arm_in_limits": tri([r.arm_in_limits for r in results]),
        "rig_retries": sum(r.rig_retries for r in results),
        "pass": all(r.passed for r in results),
        "plant_invalid": sorted({r.plant_invalid for r in results if r.plant_invalid}),
        "failures": sorted({f for r in results for f in r.failures}),
    }


def _actions(results: list[c.CaseResult]) -> str:
    """The repeats' actions in one phrase: FAULT kinds merged, counters with their range."""
    tolerated = [r for r in results if r.action.startswith("tolerated")]
    others = sorted({r.action for r in results if not r.action.startswith("tolerated")})
    faults = sorted({r.action.split(",")[0].removeprefix("FAULT ") for r in results if r.action.startswith("FAULT ")})
    if faults and len(faults) > 1 and all(a.startswith("FAULT ") for a in others):
        others = [f"FAULT {' / '.join(faults)}, quick stop"]
    if "watchdog" in " ".join(others):  # one phrase, the kinds seen on resume merged
        kinds = sorted({str(r.detail.get("fault_on_resume")) for r in results})
        others = [
            f"watchdog silent (> WatchdogSec: systemd restarts); drives quick-stopped on their own; on resume "
            f"FAULT {' / '.join(kinds)}"
        ]
    if tolerated:
        ranges: dict[str, list[int]] = {}
        for r in tolerated:
            for name, rise in r.detail.get("counters_rose", {}).items():
                if name.split(".")[-1] in c.ANOMALIES:
                    ranges.setdefault(name.split(".")[-1], []).append(int(rise))
        counted = ", ".join(
            f"{k} +{min(v)}"
            + (f"..{max(v)}" if max(v) != min(v) else "")
            + ("" if len(v) == len(tolerated) else f" ({len(v)}/{len(tolerated)})")
            for k, v in sorted(ranges.items())
        )
        others.append("tolerated" + (f"; counted: {counted}" if counted else ", nothing to count"))
    return "; ".join(others)


def format_table(document: dict[str, Any]) -> str:
    head = (
        "| fault | detected after (cycles: median, max) | bound | action taken | max \\|τ\\| after the fault "
        "/ limit | non-finite commanded | drives' final state | daemon alive | telemetry event | arm inside "
        "the position limits | pass |"
    )
    lines = [head, "|" + "---|" * 11]
    for row in document["rows"]:
        cycles = _fmt_cycles(row["detected_cycles"]) if row["detected_cycles"] else "—"
        if row["detected_s_max"] is not None and row["fault"] in SECONDS_ROWS:
            cycles = (
                f"{cycles} (≤ {row['detected_s_max']:.3f} s)"
                if row["detected_cycles"]
                else f"— (watchdog silent ≤ {row['detected_s_max']:.2f} s)"
            )
        ratio = "—" if row["max_torque_ratio"] is None else f"{row['max_torque_ratio']:.3f} (≤ 1)"
        lines.append(
            " | ".join(
                [
                    f"| {row['label']}",
                    cycles,
                    row["bound"],
                    row["action"].replace("|", "\\|"),
                    ratio,
                    "yes" if row["nonfinite"] else "no",
                    row["drives_final"],
                    row["daemon_alive"],
                    row["telemetry_event"],
                    row["arm_in_limits"],
                    (
                        "**INVALID** (the plant fell behind real time): " + "; ".join(row["plant_invalid"])
                        if row.get("plant_invalid")
                        else "**pass**"
                        if row["pass"]
                        else "**FAIL**: " + "; ".join(row["failures"])
                    )
                    + " |",
                ]
            )
        )
    machine = document["machine"]
    lines += [
        "",
        f"`{document['command']}`: {len(document['rows'])} faults × {document['repeats']} repeats, "
        f"{document['wall_s']} s, {machine['cpu_count']} CPUs ({machine['cpu']}), load average "
        f"{machine['load_average_before']} before, {machine['load_average']} after; "
        f"{'every row passes' if document['passed'] else 'SOME ROWS FAIL'}.",
    ]
    return "\n".join(lines) + "\n"


def write_outputs(out_dir: Path, document: dict[str, Any]) -> None:
    from hil_runtime.outputs import write_text_atomic

    out_dir.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out_dir / "table.md", format_table(document))
    write_text_atomic(out_dir / "results.json", json.dumps(document, indent=1) + "\n")  # last: the run's seal
