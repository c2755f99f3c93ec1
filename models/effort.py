"""Effort, smoothness and the deployable verdict: what a real arm pays for (docs/scoring.md).

Beside the paper's six tracking metrics (``models.scoring``, unchanged), per run and per joint, on
the commanded torque tau (T, N) after saturation, sampled every control period:

- ``torque_rms_nm``: sqrt(mean tau^2);
- ``peak_torque_ratio``: max |tau| / the joint's torque limit (1.0: the command hit the limit);
- ``chatter_nm``: RMS of the cycle-to-cycle change tau_k - tau_{k-1};
- ``max_torque_step_nm``: the largest cycle-to-cycle change (the commanded torque rate x period);
- ``torque_hf_rms_nm``: RMS of the part of tau above ``HIGH_FREQUENCY_HZ`` (by FFT, Parseval);
- ``energy_j``: integral of |tau qd| dt, the mechanical work the motor does or absorbs.

Deployable (per run): no limit trip (the run stayed finite, inside the position and velocity limits,
did not fault, and never commanded the full torque limit); on every joint chatter <= max(2 % of the
joint's torque limit, 2x the feedback law's chatter on the same condition); and every commanded
torque step <= the robot's torque-rate bound times the period (``hil_runtime.rate_limit``: libfranka's
``franka::kMaxTorqueRate`` = 1000 N·m/s for the Panda and the real UR5; ur5_paper keeps 1000 N·m/s per
87 N·m of the joint's torque limit).

Effort-aware composite: the paper's normalization (each metric divided by its largest value among
the configurations compared on a condition), the six tracking metrics at half their paper weights
and four effort metrics (torque RMS, chatter, high-frequency torque, all relative to the joint's
limit and pooled over joints; energy summed over joints) with ``EFFORT_WEIGHTS``.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from hil_runtime.rate_limit import FRANKA_MAX_TORQUE_RATE_NM_S, max_torque_step_nm
from models.scoring import METRICS, WEIGHTS

HIGH_FREQUENCY_HZ = 50.0  # above every reference's content (< 5 Hz) and a cobot's first structural modes
CHATTER_RATIO_OF_LIMIT = 0.02  # chatter allowed whatever the law does: 2 % of the torque limit
CHATTER_RATIO_OF_FEEDBACK = 2.0  # or twice the feedback law's chatter on the same run

#: The six tracking metrics at half their paper weights, then the effort metrics; the sum is 1.
EFFORT_METRICS = ("torque_rms_ratio", "chatter_ratio", "torque_hf_ratio", "energy_j")
EFFORT_WEIGHTS = (0.1, 0.2, 0.1, 0.1)
TRACKING_SHARE = 0.5


def effort_metrics(
    tau_nm: np.ndarray, qd_rad_s: np.ndarray, torque_limit_nm: np.ndarray, period_s: float, rows: int | None = None
) -> dict[str, Any]:
    """Per joint lists and pooled scalars of one run; ``rows``: the rows actually run (a run cut
    short by a fault is padded after them)."""
    tau = np.asarray(tau_nm, float)[:rows]
    qd = np.asarray(qd_rad_s, float)[:rows]
    limit = np.asarray(torque_limit_nm, float)
    tau = np.nan_to_num(tau)
    qd = np.nan_to_num(qd)
    n = tau.shape[1]
    if tau.shape[0] < 2:
        zeros = [0.0] * n
        return {
            "torque_rms_nm": zeros,
            "peak_torque_ratio": zeros,
            "chatter_nm": zeros,
            "max_torque_step_nm": zeros,
            "torque_hf_rms_nm": zeros,
            "energy_j": zeros,
            "torque_rms_ratio": 0.0,
            "chatter_ratio": 0.0,
            "torque_hf_ratio": 0.0,
            "energy_total_j": 0.0,
        }
    step = np.diff(tau, axis=0)
    spectrum = np.fft.rfft(tau - tau.mean(axis=0), axis=0)
    freq_hz = np.fft.rfftfreq(tau.shape[0], period_s)
    high = freq_hz > HIGH_FREQUENCY_HZ
    # Parseval: mean of x^2 = sum |X_k|^2 / T^2 over the full spectrum; rfft keeps half (x2, DC and
    # Nyquist once).
    weight = np.where((freq_hz == 0) | (np.isclose(freq_hz, 0.5 / period_s)), 1.0, 2.0)
    hf_ms = (weight[high, None] * np.abs(spectrum[high]) ** 2).sum(axis=0) / tau.shape[0] ** 2
    rms = np.sqrt(np.mean(tau**2, axis=0))
    chatter = np.sqrt(np.mean(step**2, axis=0))
    hf = np.sqrt(hf_ms)
    energy = np.sum(np.abs(tau * qd), axis=0) * period_s
    return {
        "torque_rms_nm": rms.tolist(),
        "peak_torque_ratio": (np.abs(tau).max(axis=0) / limit).tolist(),
        "chatter_nm": chatter.tolist(),
        "max_torque_step_nm": np.abs(step).max(axis=0).tolist(),
        "torque_hf_rms_nm": hf.tolist(),
        "energy_j": energy.tolist(),
        "torque_rms_ratio": float(np.sqrt(np.mean((rms / limit) ** 2))),
        "chatter_ratio": float(np.sqrt(np.mean((chatter / limit) ** 2))),
        "torque_hf_ratio": float(np.sqrt(np.mean((hf / limit) ** 2))),
        "energy_total_j": float(energy.sum()),
    }


def deployable(
    run: dict[str, Any],
    fb_run: dict[str, Any] | None,
    torque_limit_nm: np.ndarray,
    period_s: float,
    torque_rate_nm_s: np.ndarray,
) -> dict[str, Any]:
    """The verdict of one run record (with ``effort``), and every reason it fails; ``torque_rate_nm_s``:
    the robot's torque-rate bound per joint (``RobotModel.torque_rate_nm_s``)."""
    limit = np.asarray(torque_limit_nm, float)
    effort = run["effort"]
    reasons: list[str] = []
    fault = (run.get("hil") or {}).get("fault")
    if not (run["finite"] and run["within_limits"]) or fault:
        reasons.append("limit trip" + (f" ({fault})" if fault else ""))
    peak = np.asarray(effort["peak_torque_ratio"])
    if np.any(peak >= 1.0 - 1e-9):
        reasons.append(f"torque at the limit on joint(s) {(np.flatnonzero(peak >= 1.0 - 1e-9) + 1).tolist()}")
    allowed = CHATTER_RATIO_OF_LIMIT * limit
    if fb_run is not None:
        allowed = np.maximum(allowed, CHATTER_RATIO_OF_FEEDBACK * np.asarray(fb_run["effort"]["chatter_nm"]))
    chatter = np.asarray(effort["chatter_nm"])
    if np.any(chatter > allowed):
        worst = int(np.argmax(chatter / allowed))
        reasons.append(f"chatter {chatter[worst]:.3g} N·m > {allowed[worst]:.3g} on joint {worst + 1}")
    step_limit = max_torque_step_nm(torque_rate_nm_s, period_s)
    steps = np.asarray(effort["max_torque_step_nm"])
    # A command clamped at the bound (hil_runtime.rate_limit) reads back within rounding of it
    if np.any(steps > step_limit * (1.0 + 1e-9)):
        worst = int(np.argmax(steps / step_limit))
        reasons.append(
            f"torque rate {steps[worst] / period_s:.3g} N·m/s > {step_limit[worst] / period_s:.3g} on joint {worst + 1}"
        )
    return {"deployable": not reasons, "reasons": reasons}


def effort_composite(
    metrics: dict[tuple[str, str], dict[str, float]],
    effort: dict[tuple[str, str], dict[str, float]],
    failed: set[tuple[str, str]] | None = None,
) -> dict[str, float]:
    """The effort-aware composite per configuration (same normalization as the paper's)."""
    failed = failed or set()
    names = [*METRICS, *EFFORT_METRICS]
    weights = [TRACKING_SHARE * w for w in WEIGHTS] + list(EFFORT_WEIGHTS)
    configs = sorted({c for c, _ in metrics})
    conditions = sorted({k for _, k in metrics})
    totals = dict.fromkeys(configs, 0.0)

    def value(c: str, k: str, name: str) -> float:
        source = metrics[(c, k)] if name in METRICS else effort[(c, k)]
        key = "energy_total_j" if name == "energy_j" else name
        v = float(source[key])
        return v if math.isfinite(v) else 0.0

    for condition in conditions:
        present = [c for c in configs if (c, condition) in metrics]
        reference = [c for c in present if (c, condition) not in failed] or present
        for name, weight in zip(names, weights, strict=True):
            largest = max(value(c, condition, name) for c in reference)
            for c in present:
                v = value(c, condition, name)
                totals[c] += weight * (v / largest if largest > 0 else 0.0) / len(conditions)
    return totals


__all__ = [
    "CHATTER_RATIO_OF_FEEDBACK",
    "CHATTER_RATIO_OF_LIMIT",
    "EFFORT_METRICS",
    "EFFORT_WEIGHTS",
    "FRANKA_MAX_TORQUE_RATE_NM_S",
    "HIGH_FREQUENCY_HZ",
    "deployable",
    "effort_composite",
    "effort_metrics",
    "format_effort_table",
    "max_torque_step_nm",
]


def format_effort_table(results: dict[str, Any]) -> list[str]:
    """Markdown lines: per law and mode, eta on the paper's composite, eta on the effort-aware one and
    the deployable verdict side by side (docs/scoring.md). A mode with a non-deployable run is
    flagged ✗ and left out of the averages below the table, never averaged in silently."""
    modes = results["config"]["modes"]
    n_conditions = len(results["conditions"])
    head = ["Controller"]
    for mode in modes:
        m = mode.upper()
        head += [f"{m} deployable"] if mode == "fb" else [f"η_{m} (%)", f"η_{m} effort (%)", f"{m} deployable"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    averages: dict[str, list[tuple[float, float]]] = {m: [] for m in modes if m != "fb"}
    excluded: dict[str, list[str]] = {m: [] for m in modes if m != "fb"}
    for law, row in results["table"].items():
        cells = [law]
        fb_ok = not row.get("fb", {}).get("not_deployable_conditions")
        for mode in modes:
            bad = row[mode].get("not_deployable_conditions", [])
            verdict = f"{n_conditions - len(bad)}/{n_conditions}" + (" ✗" if bad else "")
            if mode == "fb":
                cells.append(verdict)
                continue
            eta, eta_effort = row[mode].get("eta"), row[mode].get("eta_effort")
            failed = row[mode].get("failed_conditions") or row.get("fb", {}).get("failed_conditions")
            cells.append("—" if eta is None or failed else f"{100 * eta:.1f}")
            cells.append("—" if eta_effort is None or failed else f"{100 * eta_effort:.1f}")
            cells.append(verdict)
            if eta is not None and eta_effort is not None:
                if bad or not fb_ok or failed:
                    excluded[mode].append(law)
                else:
                    averages[mode].append((eta, eta_effort))
        lines.append("| " + " | ".join(cells) + " |")
    realism = results["config"].get("realism", "ideal")
    lines += [
        "",
        f"Realism profile: {realism} (docs/realism.md). η: 1 − score / score_FB on the paper's composite; η effort: "
        "the same on the effort-aware composite (docs/scoring.md). Deployable: conditions on which the run "
        "tripped no limit, kept chatter within max(2 % of the torque limit, 2× FB's) and its torque rate within "
        "the robot's bound (libfranka's rule; docs/any_arm.md, Torque-rate bound); ✗: at least one run is not "
        "deployable (results.json runs[].verdict.reasons says why).",
    ]
    for mode, values in averages.items():
        m = mode.upper()
        if values:
            eta = 100 * float(np.mean([v[0] for v in values]))
            eff = 100 * float(np.mean([v[1] for v in values]))
            lines.append(
                f"Average over laws whose {m} and FB runs are all deployable: η_{m} {eta:.1f} %, "
                f"η_{m} effort {eff:.1f} % ({len(values)} laws)."
            )
        if excluded[mode]:
            lines.append(f"Left out of the {m} average (not deployable): {', '.join(excluded[mode])}.")
    return [*lines, ""]
