"""What a bundle's graph must do, checked when it is loaded, and the probe rows the writer records.

The loader (:meth:`hil_runtime.bundle.PolicyBundle.load`) calls :func:`check_graph`: the graph
reproduces the manifest's recorded probe outputs (a graph of another law under a fixed-up sha256
fails here), saturates at ``limits.torque_nm`` and keeps its residual within
``trust_region.residual_bound_nm`` wherever the probes exercise them. The writer
(``models.lmpc.bundle_export``) records the probes with :func:`record_probes`: seeded states
(:func:`make_probe_inputs`) and rows that clamp each joint's residual (:func:`clamp_probe_inputs`);
the saturation rows (:func:`saturation_probe_inputs`) are generated at load.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from hil_runtime.bundle_schema import TRUST_MIN_SPAN

if TYPE_CHECKING:
    from hil_runtime.bundle import PolicyBundle

PROBE_RTOL = 1e-6
PROBE_SEED = 20261123
SATURATION_TOLERANCE_NM = 1e-9


def _bundle_error(message: str) -> Exception:
    from hil_runtime.bundle import BundleError  # bundle imports this module when it loads one

    return BundleError(message)


def check_graph(bundle: PolicyBundle, manifest_path: Path) -> None:
    """The graph does what the manifest says: recorded probes, saturation, residual bound."""
    probes = bundle.manifest["probes"]
    x, expected = np.asarray(probes["inputs"], float), np.asarray(probes["outputs"], float)
    y = bundle._run_rows(x)
    error = np.abs(y - expected) - (float(probes.get("atol", 1e-6)) + PROBE_RTOL * np.abs(expected))
    if not np.all(np.isfinite(y)) or np.any(error > 0):
        column = int(np.unravel_index(np.nanargmax(np.where(np.isfinite(error), error, np.inf)), error.shape)[1])
        slot = next(x for x in bundle.outputs.values() if x.start <= column < x.start + x.size)
        raise _bundle_error(
            f"bundle {manifest_path}: the graph does not reproduce the recorded probe outputs "
            f"({slot.name}[{column - slot.start}]): it is not the graph of this manifest's law "
            f"'{bundle.law_name}', or was changed"
        )
    sat_x = saturation_probe_inputs(bundle)
    sat_y = bundle._run_rows(sat_x)
    _check_saturation(bundle, manifest_path, np.concatenate([y, sat_y]), sat_y)


def _check_saturation(bundle: PolicyBundle, manifest_path: Path, y: np.ndarray, sat_y: np.ndarray) -> None:
    n, s = bundle.n_joints, bundle.state_size
    limit = bundle.torque_limit_nm
    tau, tau_fb, trust = y[:, :n], y[:, n : 2 * n], y[:, 2 * n + s :]
    over = np.abs(tau) > limit + SATURATION_TOLERANCE_NM
    if over.any():
        j = int(np.argwhere(over)[0][1])
        raise _bundle_error(
            f"bundle {manifest_path}: limits.torque_nm[{j}] is {limit[j]:g} but the graph gives "
            f"{np.abs(tau[:, j]).max():g} N m: its saturation differs"
        )
    magnitude = np.abs(sat_y[:, :n])
    peak = magnitude.max(axis=0)
    plateau = (np.sum(np.abs(magnitude - peak) <= SATURATION_TOLERANCE_NM * np.maximum(1.0, peak), axis=0) >= 2) & (
        peak > 0
    )
    short = plateau & (np.abs(peak - limit) > SATURATION_TOLERANCE_NM * np.maximum(1.0, limit))
    if short.any():
        j = int(np.flatnonzero(short)[0])
        raise _bundle_error(
            f"bundle {manifest_path}: limits.torque_nm[{j}] is {limit[j]:g} but the graph saturates at {peak[j]:g} N m"
        )
    bound = bundle.residual_bound_nm
    bundle.saturation_checked = plateau
    if bound is None:
        return
    # Where the emulator acts (alpha > 0) and the joint is not saturated, tau - tau_fb = alpha clip(r):
    # divided by alpha (1 - trust[:, 0]) it is the clipped residual, which must stay within the bound,
    # and every joint the graph reports clamped (trust[:, 1]) must sit exactly at it. The writer records
    # probes that clamp each joint (clamp_probe_inputs), so a changed bound shows whatever its size.
    alpha = 1.0 - trust[:, 0]
    acting = alpha > 0.0
    inside = acting[:, None] & (np.abs(tau) < limit - SATURATION_TOLERANCE_NM)
    scale = 1.0 / np.where(acting, alpha, 1.0)[:, None]
    residual = np.abs(tau - tau_fb) * scale
    tol = (1e-9 + 1e-9 * np.abs(tau_fb)) * scale
    beyond = inside & (residual > bound + tol)
    if beyond.any():
        j = int(np.argwhere(beyond)[0][1])
        raise _bundle_error(
            f"bundle {manifest_path}: trust_region.residual_bound_nm[{j}] is {bound[j]:g} but the graph "
            f"passes a residual of {residual[beyond[:, j], j].max():g} N m"
        )
    at_bound = np.abs(residual - bound) <= 1e-7 * np.maximum(1.0, bound)
    clamped_rows = inside.all(axis=1) & (trust[:, 1] > 0.5)
    unexplained = clamped_rows & (at_bound.sum(axis=1) < np.rint(trust[:, 1]))
    if unexplained.any():
        raise _bundle_error(
            f"bundle {manifest_path}: trust_region.residual_bound_nm does not match the graph's clamp "
            "(the graph clamps residuals below the manifest's bound)"
        )


def _probe_state(bundle: PolicyBundle, q: np.ndarray) -> np.ndarray:
    return np.atleast_2d(bundle.initial_state(q))


def saturation_probe_inputs(bundle: PolicyBundle) -> np.ndarray:
    """Rows far beyond any tracking error the arm can have (q_d and qd_d at 1e4 and 1e5, both
    signs), generated at load: the torque runs into the graph's saturation, which then shows as a
    plateau of |tau| that must equal limits.torque_nm."""
    n = bundle.n_joints
    rows = []
    for reach in (1e4, 1e5):
        for velocity in (0.0, reach):
            for sign in (1.0, -1.0):
                q = np.zeros((1, n))
                rows.append(
                    np.concatenate(
                        [
                            q,
                            np.zeros((1, n)),
                            np.full((1, n), sign * reach),
                            np.full((1, n), sign * velocity),
                            np.zeros((1, n)),
                            _probe_state(bundle, q),
                        ],
                        1,
                    )
                )
    return np.concatenate(rows)


def make_probe_inputs(bundle: PolicyBundle, count: int = 12, seed: int = PROBE_SEED) -> np.ndarray:
    """Seeded probe rows for the writer to record: states inside the joint limits with moderate
    errors, and (with a trust region) rows sampled inside its box, where the emulator acts."""
    rng = np.random.default_rng(seed)
    n = bundle.n_joints
    position = np.minimum(np.abs(np.asarray(bundle.manifest["limits"]["position_rad"], float)), np.pi)
    velocity = np.minimum(np.abs(np.asarray(bundle.manifest["limits"]["velocity_rad_s"], float)), 10.0)
    rows = []
    trust = bundle.manifest.get("trust_region")
    for k in range(count):
        if trust is not None and k % 2:
            low, high = np.asarray(trust["feature_low"], float), np.asarray(trust["feature_high"], float)
            g = low + rng.uniform(0.1, 0.9, size=low.shape) * np.clip(high - low, 0.0, 1e6)
            q, e, qd, e_dot, qdd_d = (g[i * n : (i + 1) * n] for i in range(5))
            q_d, qd_d = q + e, qd + e_dot
        else:
            q = rng.uniform(-0.5, 0.5, n) * position
            q_d = q + rng.normal(0.0, 0.05, n)
            qd = rng.uniform(-0.3, 0.3, n) * velocity
            qd_d = qd + rng.normal(0.0, 0.1, n)
            qdd_d = rng.normal(0.0, 0.5, n)
        state = _probe_state(bundle, q[None])[0] + rng.normal(0.0, 0.01, bundle.state_size)
        rows.append(np.concatenate([q, qd, q_d, qd_d, qdd_d, state]))
    return np.asarray(rows)


#: trust weights alpha at which clamp_probe_inputs tries each direction beyond the box (1: its edge)
CLAMP_PROBE_ALPHAS = (1.0, 0.9, 0.75, 0.5, 0.3, 0.2, 0.1, 0.05, 0.02, 0.01, 0.005, 0.002, 1e-3, 3e-4, 1e-4)
CLAMP_PROBE_INSIDE = (0.0, 0.25, 0.5)  # fractions of the half box, inside it (alpha = 1)


def _guard_rows(bundle: PolicyBundle, g: np.ndarray) -> np.ndarray:
    """Graph input rows from guard features g (B, 5N) = (q, e, qd, e_dot, qdd_d), the law at its
    initial state for q."""
    n = bundle.n_joints
    q, e, qd, e_dot, qdd_d = (g[:, i * n : (i + 1) * n] for i in range(5))
    return np.concatenate([q, qd, q + e, qd + e_dot, qdd_d, _probe_state(bundle, q)], 1)


def clamp_probe_inputs(bundle: PolicyBundle) -> np.ndarray:
    """Rows that exercise the residual clamp, for the writer to record (the loader then sees a changed
    ``residual_bound_nm`` whatever its size): per joint, a row where that joint's residual is clamped
    and no joint saturates, and one row at the box centre where none is clamped. Found by running the
    graph: from the trust box's centre, one guard feature (q, e, qd, e_dot, qdd_d) of one joint moved at a
    time, or the tracking features (e, e_dot, qdd_d) of one or every joint together, both signs, inside
    the box and beyond it at the trust weights CLAMP_PROBE_ALPHAS (a small alpha keeps
    tau_fb + alpha * bound below the torque limit when the bound is larger than it). Per joint the row
    with the largest alpha is kept. A joint whose residual no row clamps gets none: its bound is then
    beyond anything the graph gives where the emulator acts (it never clamps there), and the loader
    cannot check it. Empty without a trust region or a bound."""
    trust, bound = bundle.manifest.get("trust_region"), bundle.residual_bound_nm
    n = bundle.n_joints
    if trust is None or bound is None:
        return np.zeros((0, bundle.input_width))
    width = 5 * n  # the guard features the graph's inputs set (tau_fb is the law's output)
    low, high = np.asarray(trust["feature_low"], float)[:width], np.asarray(trust["feature_high"], float)[:width]
    span = np.clip(high - low, TRUST_MIN_SPAN, 1e6)
    centre, margin = 0.5 * (low + high), float(trust["box_margin"])
    offsets = [f * 0.5 * span for f in CLAMP_PROBE_INSIDE] + [
        0.5 * span + (1.0 - a) * margin * span for a in CLAMP_PROBE_ALPHAS
    ]
    # directions: one feature of one joint; a joint's (e, e_dot, qdd_d) together (their accelerations add);
    # every joint's (e, e_dot, qdd_d) together. alpha is set by the largest excess, so moving several
    # features by the same share of their span costs no more trust than moving one.
    tracking = (1, 3, 4)  # e, e_dot, qdd_d blocks of the guard features
    directions = [[k] for k in range(width)]
    directions += [[b * n + j for b in tracking] for j in range(n)]
    directions += [[b * n + j for j in range(n) for b in tracking]]
    g = [centre]
    for index in directions:
        for offset in offsets[1:]:
            for sign in (1.0, -1.0):
                row = centre.copy()
                row[index] += sign * offset[index]
                g.append(row)
    x = _guard_rows(bundle, np.asarray(g))
    y = bundle._run_rows(x)
    s = bundle.state_size
    tau, tau_fb, fallback, clamped = y[:, :n], y[:, n : 2 * n], y[:, 2 * n + s], y[:, 2 * n + s + 1]
    alpha = 1.0 - fallback
    ok = np.isfinite(y).all(axis=1) & (alpha > 0) & (np.abs(tau) < bundle.torque_limit_nm - 1e-6).all(axis=1)
    residual = np.abs(tau - tau_fb) / np.where(ok, alpha, 1.0)[:, None]
    at_bound = ok[:, None] & (clamped > 0.5)[:, None] & (np.abs(residual - bound) <= 1e-9 * np.maximum(1.0, bound))
    chosen = []
    for j in range(n):
        rows = np.flatnonzero(at_bound[:, j])
        if rows.size:
            chosen.append(int(rows[np.argmax(alpha[rows])]))
    free = np.flatnonzero(ok & (alpha == 1.0) & (clamped == 0.0))
    if free.size:
        chosen.append(int(free[0]))
    return x[sorted(set(chosen))]


def record_probes(path: str | Path, count: int = 12) -> dict[str, Any]:
    """The ``probes`` section for the bundle at ``path`` (the writer's step; graph and files final)."""
    from hil_runtime.bundle import PolicyBundle

    bundle = PolicyBundle.load(path, check_behaviour=False)
    x = np.concatenate([make_probe_inputs(bundle, count), clamp_probe_inputs(bundle)])
    y = bundle._run_rows(x)
    if not np.isfinite(y).all():
        raise _bundle_error(f"bundle {path}: the graph gives non-finite outputs on probe inputs")
    return {
        "inputs": x.tolist(),
        "outputs": y.tolist(),
        "atol": 1e-6,
        "note": "graph inputs (hil_runtime.bundle.make_probe_inputs, clamp_probe_inputs) and the exporter's "
        "onnxruntime outputs; "
        "the loader reruns them (atol + 1e-6 relative)",
    }
