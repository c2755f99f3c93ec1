"""What a bundle's graph must do, checked when it is loaded, and the probe rows the writer records.

The loader (:meth:`hil_runtime.bundle.PolicyBundle.load`) calls :func:`check_graph`: the graph
reproduces the manifest's recorded probe outputs (a graph of another law under a fixed-up sha256
fails here), saturates at ``limits.torque_nm`` and keeps its residual within
``trust_region.residual_bound_nm`` wherever the probes exercise them. The writer
(``models.lmpc.bundle_export``) records the probes with :func:`record_probes`: seeded states
(:func:`make_probe_inputs`) and rows that clamp each joint's residual (:func:`clamp_probe_inputs`);
the saturation rows (:func:`saturation_probe_inputs`) are generated at load.

A graph that reads tau_prev (the input layout's optional last slot, docs/lmpc.md §11) steps from it by
at most the rate bound (``limits.torque_rate_nm_s`` x the period): every row with a commanded tau_prev
(within the torque limits) must, and that is checked on every row run here. Its probe rows carry a
settled tau_prev (:func:`settle_previous`: the graph's own torque fed back until it rests, the state a
running arm is in), its saturation rows ramp to the plateau the same way, and its residual check allows
what lies between tau_prev and the trust region's target (the step's share beta is the graph's).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np

from hil_runtime.bundle_schema import TRUST_MIN_SPAN, Manifest
from hil_runtime.rate_limit import SCALED_RULE, max_torque_step_nm, torque_rate_limit_nm_s
from hil_runtime.velocity_filter import filter_pole, step_noise_gain

PROBE_RTOL = 1e-6
PROBE_SEED = 20261123
SATURATION_TOLERANCE_NM = 1e-9

RunRows = Callable[[np.ndarray], np.ndarray]  # graph input rows (B, 5N + S) -> output rows (B, 2N + S + 2)


class GraphCheckError(ValueError):
    """The graph does not do what its manifest says (the loader reports it as a BundleError)."""


def _torque_limit(manifest: Manifest) -> np.ndarray:
    return np.asarray(manifest.limits.torque_nm, float)


def _residual_bound(manifest: Manifest) -> np.ndarray | None:
    trust = manifest.trust_region
    return None if trust is None or trust.residual_bound_nm is None else np.asarray(trust.residual_bound_nm, float)


def initial_state(manifest: Manifest, q0: np.ndarray) -> np.ndarray:
    """The law's state from positions q0: constant + q0 gain^T ((N,) -> (S,), (B, N) -> (B, S))."""
    init, s, n = manifest.law.initial_state, manifest.law.state_size, manifest.robot.n_joints
    state: np.ndarray = (
        np.asarray(init.constant, float).reshape(s)
        + np.asarray(q0, float) @ np.asarray(init.position_gain, float).reshape(s, n).T
    )
    return state


#: feed-back passes beyond a full ramp (2 x limit / step) when settling tau_prev: the geometric tail of a
#: step share beta < 1 ((1 - beta)^k of the distance is left after k passes)
SETTLE_EXTRA_PASSES = 200
RATE_TOLERANCE = 1e-9  # relative, on a step of the rate bound


def torque_rate_nm_s(manifest: Manifest) -> np.ndarray:
    """The robot's torque-rate bound per joint (N m/s): the manifest's; a manifest from before the field
    keeps the rule it was made under (hil_runtime.rate_limit's scaled rule)."""
    rate = manifest.limits.torque_rate_nm_s
    return torque_rate_limit_nm_s(SCALED_RULE if rate is None else rate, _torque_limit(manifest))


def rate_step_nm(manifest: Manifest) -> np.ndarray:
    """The largest torque change per period a real arm accepts, the bound a graph reading tau_prev steps
    within (N m, per joint)."""
    return max_torque_step_nm(torque_rate_nm_s(manifest), manifest.period_s)


def settle_previous(manifest: Manifest, run_rows: RunRows, x: np.ndarray, passes: int | None = None) -> np.ndarray:
    """Rows x with tau_prev set to where the graph's own torque rests: tau fed back as tau_prev ``passes``
    times (default: a full ramp across the torque range and SETTLE_EXTRA_PASSES more), the law's state
    kept. A graph that does not read tau_prev: x unchanged."""
    if not manifest.takes_previous_torque:
        return x
    x = np.array(x, float)
    n, columns = manifest.robot.n_joints, manifest.layout.previous_torque_columns
    if passes is None:
        passes = int(np.ceil(2.0 * np.max(_torque_limit(manifest) / rate_step_nm(manifest)))) + SETTLE_EXTRA_PASSES
    moving = np.arange(len(x))
    for _ in range(passes):  # the rows still moving only; a row rests when its torque equals its tau_prev
        tau = run_rows(x[moving])[:, :n]
        before = x[moving][:, columns]
        tau = np.where(np.isfinite(tau), tau, before)
        x[moving, columns] = tau
        moving = moving[np.abs(tau - before).max(axis=1) > 1e-12 * (1.0 + np.abs(tau).max(axis=1))]
        if moving.size == 0:
            break
    return x


def _check_rate(manifest: Manifest, manifest_path: Path, x: np.ndarray, y: np.ndarray) -> None:
    """Every row whose tau_prev is a commandable torque: |tau - tau_prev| <= the rate step."""
    if not manifest.takes_previous_torque:
        return
    n, limit, step = manifest.robot.n_joints, _torque_limit(manifest), rate_step_nm(manifest)
    previous, tau = x[:, manifest.layout.previous_torque_columns], y[:, :n]
    commandable = (np.abs(previous) <= limit).all(axis=1) & np.isfinite(tau).all(axis=1)
    over = commandable[:, None] & (np.abs(tau - previous) > step * (1.0 + RATE_TOLERANCE) + 1e-12)
    if over.any():
        j = int(np.argwhere(over)[0][1])
        raise GraphCheckError(
            f"bundle {manifest_path}: limits.torque_rate_nm_s[{j}] allows {step[j]:g} N m per period but the graph "
            f"steps {np.abs(tau - previous)[over[:, j], j].max():g} N m from tau_prev"
        )


def check_graph(manifest: Manifest, run_rows: RunRows, manifest_path: Path) -> np.ndarray:
    """The graph does what the manifest says: recorded probes, saturation, residual bound. Returns
    the joints whose saturation the probes observed (a plateau at ``limits.torque_nm``);
    :class:`GraphCheckError` (one line) otherwise."""
    probes = manifest.probes
    if probes is None:
        raise GraphCheckError(f"bundle {manifest_path}: probes: missing")
    x, expected = np.asarray(probes.inputs, float), np.asarray(probes.outputs, float)
    y = run_rows(x)
    error = np.abs(y - expected) - (probes.atol + PROBE_RTOL * np.abs(expected))
    if not np.all(np.isfinite(y)) or np.any(error > 0):
        column = int(np.unravel_index(np.nanargmax(np.where(np.isfinite(error), error, np.inf)), error.shape)[1])
        name, index = manifest.layout.output_slot(column)
        raise GraphCheckError(
            f"bundle {manifest_path}: the graph does not reproduce the recorded probe outputs "
            f"({name}[{index}]): it is not the graph of this manifest's law "
            f"'{manifest.law.name}', or was changed"
        )
    sat_x = saturation_probe_inputs(manifest)
    if manifest.takes_previous_torque:  # ramp to the plateau at the rate bound, each pass checked
        passes = int(np.ceil(2.0 * np.max(_torque_limit(manifest) / rate_step_nm(manifest)))) + 2
        for _ in range(passes):
            sat_y = run_rows(sat_x)
            _check_rate(manifest, manifest_path, sat_x, sat_y)
            sat_x[:, manifest.layout.previous_torque_columns] = np.nan_to_num(sat_y[:, : manifest.robot.n_joints])
    sat_y = run_rows(sat_x)
    _check_rate(manifest, manifest_path, np.concatenate([x, sat_x]), np.concatenate([y, sat_y]))
    joints = _check_saturation(manifest, manifest_path, np.concatenate([y, sat_y]), sat_y, np.concatenate([x, sat_x]))
    bound = probes.position_sensitivity_nm_per_mrad
    if bound is not None:
        if len(bound) != manifest.robot.n_joints or not all(np.isfinite(bound)) or min(bound) < 0:
            raise GraphCheckError(
                f"bundle {manifest_path}: probes.position_sensitivity_nm_per_mrad: needs "
                f"{manifest.robot.n_joints} finite values >= 0"
            )
        measured = position_sensitivity(manifest, run_rows, x)
        worst = int(np.argmax(measured - np.asarray(bound)))
        if measured[worst] > bound[worst] * (1 + PROBE_RTOL) + probes.atol:
            raise GraphCheckError(
                f"bundle {manifest_path}: probes.position_sensitivity_nm_per_mrad: the graph turns 1 mrad of "
                f"position error into {measured[worst]:.3g} N m on joint {worst + 1} (bound {bound[worst]:.3g})"
            )
    return joints


SENSITIVITY_STEP_RAD = 1e-3  # the measurement error the sensitivity is stated for (1 mrad)


def _largest_torque_change(manifest: Manifest, run_rows: RunRows, x: np.ndarray, first: int, step: float) -> np.ndarray:
    """Per joint i: max over the rows x and the joints j of |tau_i(x + step e_(first + j)) - tau_i(x)| (either
    sign; a non-finite change counts as infinite), the law's state kept."""
    n = manifest.robot.n_joints
    base = run_rows(x)[:, :n]
    worst = np.zeros(n)
    for j in range(n):
        for sign in (1.0, -1.0):
            moved = x.copy()
            moved[:, first + j] += sign * step
            change = np.abs(run_rows(moved)[:, :n] - base)
            worst = np.maximum(worst, np.nanmax(np.where(np.isfinite(change), change, np.inf), 0))
    return worst


def position_sensitivity(manifest: Manifest, run_rows: RunRows, x: np.ndarray) -> np.ndarray:
    """Per joint i: max over the rows x and the joints j of |tau_i(q + 1 mrad e_j) - tau_i(q)|, N m per
    mrad: what one encoder's error of 1 mrad does to the commanded torque (the law's state kept)."""
    return _largest_torque_change(manifest, run_rows, x, 0, SENSITIVITY_STEP_RAD)


#: the runtime's default encoder noise (bundle.encoder_noise_rad): about one increment of a 19-bit encoder
DEFAULT_ENCODER_NOISE_RAD = 1e-5
VELOCITY_STEP_RAD_S = 1e-2  # the velocity error the velocity sensitivity is measured with (linear part)
GATE_ROWS, GATE_SEED = 24, PROBE_SEED + 1  # the sensing gate's own seeded rows (make_probe_inputs), beside the probes


def velocity_sensitivity(manifest: Manifest, run_rows: RunRows, x: np.ndarray) -> np.ndarray:
    """Per joint i: max over the rows x and the joints j of |tau_i(qd + dv e_j) - tau_i(qd)| / dv, N m per
    rad/s (dv = VELOCITY_STEP_RAD_S): what a velocity error does to the commanded torque."""
    n = manifest.robot.n_joints
    return _largest_torque_change(manifest, run_rows, x, n, VELOCITY_STEP_RAD_S) / VELOCITY_STEP_RAD_S


def differenced_velocity_noise_rad_s(encoder_noise_rad: float, period_s: float) -> float:
    """The velocity noise of a position noise differenced over one period, unfiltered (RMS): sqrt(2) sigma / T."""
    return float(np.sqrt(2.0) * encoder_noise_rad / period_s)


def noise_step_nm(
    position_nm_per_mrad: np.ndarray,
    velocity_nm_s_per_rad: np.ndarray,
    encoder_noise_rad: float,
    velocity_noise_rad_s: float,
    velocity_step_gain: float = float(np.sqrt(2.0)),
) -> np.ndarray:
    """Per joint: the RMS cycle-to-cycle torque change that measurement noise alone makes through a graph of
    these sensitivities, sqrt(2) S_q sigma_q + k S_v sigma_v (two independent samples differenced: k = sqrt(2);
    behind the runtime's velocity filter k = hil_runtime.velocity_filter.step_noise_gain; the two channels
    added). An open-loop estimate: in closed loop the noise-driven torque also moves the arm. On
    ur5_paper's shipped PD bundle at the issue's 3e-4 rad and 0.2 rad/s it gives 8.3 N m on the shoulder; the
    simulator measures 10.1 on C1 (tests/unit/models/lmpc/test_bundle_probes.py) and 8.5 over C1-C5."""
    steps: np.ndarray = (
        np.sqrt(2.0) * np.asarray(position_nm_per_mrad, float) * encoder_noise_rad / SENSITIVITY_STEP_RAD
        + velocity_step_gain * np.asarray(velocity_nm_s_per_rad, float) * velocity_noise_rad_s
    )
    return steps


def predicted_noise_steps(
    manifest: Manifest,
    run_rows: RunRows,
    encoder_noise_rad: float,
    velocity_noise_rad_s: float | None = None,
    velocity_filter_hz: float | None = None,
) -> np.ndarray:
    """Per joint: :func:`noise_step_nm` of the graph (its sensitivities measured on the manifest's probe rows
    and the gate's own) at this noise; velocity noise None: the position's differenced over one period;
    ``velocity_filter_hz``: the runtime's velocity input filter (None: off)."""
    if velocity_noise_rad_s is None:
        velocity_noise_rad_s = differenced_velocity_noise_rad_s(encoder_noise_rad, manifest.period_s)
    if manifest.probes is None:
        raise GraphCheckError("probes: missing")
    x = np.asarray(manifest.probes.inputs, float)  # a tau_prev graph's probe rows carry a settled tau_prev
    if not manifest.takes_previous_torque:  # and the loader's own rows: the writer does not pick where it is measured
        x = np.concatenate([x, make_probe_inputs(manifest, GATE_ROWS, GATE_SEED)])
    return noise_step_nm(
        position_sensitivity(manifest, run_rows, x),
        velocity_sensitivity(manifest, run_rows, x),
        encoder_noise_rad,
        velocity_noise_rad_s,
        float(np.sqrt(2.0))
        if velocity_filter_hz is None
        else step_noise_gain(filter_pole(velocity_filter_hz, manifest.period_s)),
    )


def tolerated_encoder_noise_rad(manifest: Manifest, run_rows: RunRows) -> float:
    """The largest encoder noise (RMS, velocity differenced from it) the sensing gate accepts for this graph:
    the steps are linear in the noise; inf for a graph that reads tau_prev (bounded by construction)."""
    if manifest.takes_previous_torque:
        return float("inf")
    per_rad = predicted_noise_steps(manifest, run_rows, 1.0)
    return float(np.min(rate_step_nm(manifest) / np.maximum(per_rad, 1e-300)))


def check_sensing(
    manifest: Manifest,
    run_rows: RunRows,
    manifest_path: Path,
    encoder_noise_rad: float,
    velocity_noise_rad_s: float | None = None,
    velocity_filter_hz: float | None = None,
) -> np.ndarray:
    """Refuse a graph that turns the arm's measurement noise into torque steps a real arm does not accept:
    per joint, :func:`noise_step_nm` at the stated noise (velocity noise None: the position's, differenced)
    must stay within the robot's torque-rate bound per period (``limits.torque_rate_nm_s`` x the period,
    hil_runtime.rate_limit). Returns the predicted steps (N m). A graph that reads tau_prev steps by at most
    that bound by construction (checked on every probe row): passes. :class:`GraphCheckError` (one line)."""
    differenced = velocity_noise_rad_s is None
    if velocity_noise_rad_s is None:
        velocity_noise_rad_s = differenced_velocity_noise_rad_s(encoder_noise_rad, manifest.period_s)
    try:
        steps = predicted_noise_steps(manifest, run_rows, encoder_noise_rad, velocity_noise_rad_s, velocity_filter_hz)
    except GraphCheckError as exc:
        raise GraphCheckError(f"bundle {manifest_path}: {exc}") from None
    bound = rate_step_nm(manifest)
    if manifest.takes_previous_torque:
        capped: np.ndarray = np.minimum(steps, bound)
        return capped
    worst = int(np.argmax(steps / bound))
    if steps[worst] > bound[worst] * (1.0 + RATE_TOLERANCE):
        share = bound[worst] / steps[worst]  # the steps are linear in the noise
        filtered = "" if velocity_filter_hz is None else f", filtered at {velocity_filter_hz:g} Hz"
        tolerated = f"{encoder_noise_rad * share:.2g} rad" if differenced else f"{100 * share:.2g} % of this noise"
        raise GraphCheckError(
            f"bundle {manifest_path}: turns an encoder noise of {encoder_noise_rad:.3g} rad (velocity "
            f"{velocity_noise_rad_s:.3g} rad/s{filtered}) into torque steps of {steps[worst]:.3g} N m per period "
            f"on joint {worst + 1}, above the {bound[worst]:.3g} N m a real arm accepts (limits.torque_rate_nm_s): "
            f"it would chatter there; it tolerates about {tolerated}"
        )
    return steps


def _check_saturation(
    manifest: Manifest, manifest_path: Path, y: np.ndarray, sat_y: np.ndarray, x: np.ndarray
) -> np.ndarray:
    n = manifest.robot.n_joints
    limit = _torque_limit(manifest)
    tau, tau_fb, _, trust = manifest.layout.split(y)
    over = np.abs(tau) > limit + SATURATION_TOLERANCE_NM
    if over.any():
        j = int(np.argwhere(over)[0][1])
        raise GraphCheckError(
            f"bundle {manifest_path}: limits.torque_nm[{j}] is {limit[j]:g} but the graph gives "
            f"{np.abs(tau[:, j]).max():g} N m: its saturation differs"
        )
    magnitude = np.abs(sat_y[:, :n])
    peak = magnitude.max(axis=0)
    plateau: np.ndarray = (
        np.sum(np.abs(magnitude - peak) <= SATURATION_TOLERANCE_NM * np.maximum(1.0, peak), axis=0) >= 2
    ) & (peak > 0)
    short = plateau & (np.abs(peak - limit) > SATURATION_TOLERANCE_NM * np.maximum(1.0, limit))
    if short.any():
        j = int(np.flatnonzero(short)[0])
        raise GraphCheckError(
            f"bundle {manifest_path}: limits.torque_nm[{j}] is {limit[j]:g} but the graph saturates at {peak[j]:g} N m"
        )
    bound = _residual_bound(manifest)
    if bound is None:
        return plateau
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
    allowed = np.broadcast_to(bound, residual.shape)
    if manifest.takes_previous_torque:
        # tau lies between tau_prev and the target tau_fb + alpha clip(r): within the bound or tau_prev's distance
        allowed = np.maximum(allowed, np.abs(x[:, manifest.layout.previous_torque_columns] - tau_fb) * scale)
    beyond = inside & (residual > allowed + tol)
    if beyond.any():
        j = int(np.argwhere(beyond)[0][1])
        raise GraphCheckError(
            f"bundle {manifest_path}: trust_region.residual_bound_nm[{j}] is {bound[j]:g} but the graph "
            f"passes a residual of {residual[beyond[:, j], j].max():g} N m"
        )
    if manifest.takes_previous_torque:  # the step's share hides the clamp's level (module docstring)
        return plateau
    at_bound = np.abs(residual - bound) <= 1e-7 * np.maximum(1.0, bound)
    clamped_rows = inside.all(axis=1) & (trust[:, 1] > 0.5)
    unexplained = clamped_rows & (at_bound.sum(axis=1) < np.rint(trust[:, 1]))
    if unexplained.any():
        raise GraphCheckError(
            f"bundle {manifest_path}: trust_region.residual_bound_nm does not match the graph's clamp "
            "(the graph clamps residuals below the manifest's bound)"
        )
    return plateau


def _probe_state(manifest: Manifest, q: np.ndarray) -> np.ndarray:
    return np.atleast_2d(initial_state(manifest, q))


def saturation_probe_inputs(manifest: Manifest) -> np.ndarray:
    """Rows far beyond any tracking error the arm can have (q_d and qd_d at 1e4 and 1e5, both
    signs), generated at load: the torque runs into the graph's saturation, which then shows as a
    plateau of |tau| that must equal limits.torque_nm."""
    n = manifest.robot.n_joints
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
                            _probe_state(manifest, q),
                            _zero_previous(manifest, 1),
                        ],
                        1,
                    )
                )
    return np.concatenate(rows)


def _zero_previous(manifest: Manifest, rows: int) -> np.ndarray:
    """A zero tau_prev block for ``rows`` input rows (width 0 when the graph does not read it)."""
    columns = manifest.layout.previous_torque_columns
    return np.zeros((rows, columns.stop - columns.start))


def make_probe_inputs(manifest: Manifest, count: int = 12, seed: int = PROBE_SEED) -> np.ndarray:
    """Seeded probe rows for the writer to record: states inside the joint limits with moderate
    errors, and (with a trust region) rows sampled inside its box, where the emulator acts."""
    rng = np.random.default_rng(seed)
    n = manifest.robot.n_joints
    position = np.minimum(np.abs(np.asarray(manifest.limits.position_rad, float)), np.pi)
    velocity = np.minimum(np.abs(np.asarray(manifest.limits.velocity_rad_s, float)), 10.0)
    rows = []
    trust = manifest.trust_region
    for k in range(count):
        if trust is not None and k % 2:
            low, high = np.asarray(trust.feature_low, float), np.asarray(trust.feature_high, float)
            g = low + rng.uniform(0.1, 0.9, size=low.shape) * np.clip(high - low, 0.0, 1e6)
            q, e, qd, e_dot, qdd_d = (g[i * n : (i + 1) * n] for i in range(5))
            q_d, qd_d = q + e, qd + e_dot
        else:
            q = rng.uniform(-0.5, 0.5, n) * position
            q_d = q + rng.normal(0.0, 0.05, n)
            qd = rng.uniform(-0.3, 0.3, n) * velocity
            qd_d = qd + rng.normal(0.0, 0.1, n)
            qdd_d = rng.normal(0.0, 0.5, n)
        state = _probe_state(manifest, q[None])[0] + rng.normal(0.0, 0.01, manifest.law.state_size)
        rows.append(np.concatenate([q, qd, q_d, qd_d, qdd_d, state, _zero_previous(manifest, 1)[0]]))
    return np.asarray(rows)


#: trust weights alpha at which clamp_probe_inputs tries each direction beyond the box (1: its edge)
CLAMP_PROBE_ALPHAS = (1.0, 0.9, 0.75, 0.5, 0.3, 0.2, 0.1, 0.05, 0.02, 0.01, 0.005, 0.002, 1e-3, 3e-4, 1e-4)
CLAMP_PROBE_INSIDE = (0.0, 0.25, 0.5)  # fractions of the half box, inside it (alpha = 1)


def _guard_rows(manifest: Manifest, g: np.ndarray) -> np.ndarray:
    """Graph input rows from guard features g (B, 5N) = (q, e, qd, e_dot, qdd_d), the law at its
    initial state for q."""
    n = manifest.robot.n_joints
    q, e, qd, e_dot, qdd_d = (g[:, i * n : (i + 1) * n] for i in range(5))
    return np.concatenate(
        [q, qd, q + e, qd + e_dot, qdd_d, _probe_state(manifest, q), _zero_previous(manifest, len(q))], 1
    )


def clamp_probe_inputs(manifest: Manifest, run_rows: RunRows) -> np.ndarray:
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
    trust, bound = manifest.trust_region, _residual_bound(manifest)
    n = manifest.robot.n_joints
    if trust is None or bound is None:
        return np.zeros((0, manifest.layout.input_width))
    width = 5 * n  # the guard features the graph's inputs set (tau_fb is the law's output)
    low, high = np.asarray(trust.feature_low, float)[:width], np.asarray(trust.feature_high, float)[:width]
    span = np.clip(high - low, TRUST_MIN_SPAN, 1e6)
    centre, margin = 0.5 * (low + high), float(trust.box_margin)
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
    x = settle_previous(manifest, run_rows, _guard_rows(manifest, np.asarray(g)))
    y = run_rows(x)
    tau, tau_fb, _, trust_out = manifest.layout.split(y)
    fallback, clamped = trust_out[:, 0], trust_out[:, 1]
    alpha = 1.0 - fallback
    ok = np.isfinite(y).all(axis=1) & (alpha > 0) & (np.abs(tau) < _torque_limit(manifest) - 1e-6).all(axis=1)
    residual = np.abs(tau - tau_fb) / np.where(ok, alpha, 1.0)[:, None]
    # settled rows (a graph reading tau_prev) rest at the target up to the step share's geometric tail
    tolerance = 1e-6 if manifest.takes_previous_torque else 1e-9
    at_bound = ok[:, None] & (clamped > 0.5)[:, None] & (np.abs(residual - bound) <= tolerance * np.maximum(1.0, bound))
    chosen = []
    for j in range(n):
        rows = np.flatnonzero(at_bound[:, j])
        if rows.size:
            chosen.append(int(rows[np.argmax(alpha[rows])]))
    free = np.flatnonzero(ok & (alpha == 1.0) & (clamped == 0.0))
    if free.size:
        chosen.append(int(free[0]))
    return x[sorted(set(chosen))]


def probe_section(manifest: Manifest, run_rows: RunRows, where: str, count: int = 12) -> dict[str, object]:
    """The ``probes`` section for a bundle whose graph and files are final (the writer's step)."""
    seeded = settle_previous(manifest, run_rows, make_probe_inputs(manifest, count))
    x = np.concatenate([seeded, clamp_probe_inputs(manifest, run_rows)])
    y = run_rows(x)
    if not np.isfinite(y).all():
        raise GraphCheckError(f"bundle {where}: the graph gives non-finite outputs on probe inputs")
    return {
        "inputs": x.tolist(),
        "outputs": y.tolist(),
        "position_sensitivity_nm_per_mrad": position_sensitivity(manifest, run_rows, x).tolist(),
        "atol": 1e-6,
        "note": "graph inputs (hil_runtime.bundle_probes.make_probe_inputs, clamp_probe_inputs) and the "
        "exporter's onnxruntime outputs; the loader reruns them (atol + 1e-6 relative)",
    }
