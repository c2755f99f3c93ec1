"""LMPC as a closed-loop controller: the shipped policy bundle run through the runtime's loader.

Experiments score exactly what the runtime runs: the same files, the same ``hil_runtime.bundle``
code, the same onnxruntime session settings. One arm (B = 1) takes the runtime's preallocated
single-row path, whose wall time (Python around it included) is the t_L column.

    controller = make_lmpc_controller(law, robot)                      # models/bundles/<robot>/<law>
    controller = make_lmpc_controller(law, robot, bundle_dir="path/to/bundles")
    controller = make_lmpc_controller(law, robot, torque_rate_limit="libfranka")

``torque_rate_limit="libfranka"``: the runtime's output limit (``hil_runtime.rate_limit``, the same
object the runtime's policy stage uses), against the torque the simulator actually commanded last
period (:meth:`LMPCController.commit`, called after its saturation).

A bundle whose graph reads tau_prev (docs/lmpc.md §11) gets the same torque as the runtime gives it: the
one the simulator commanded last period (:meth:`LMPCController.commit`; without a commit, this
controller's own last output).

Both start a run from the held torque, as the runtime's ``Controller.reset(q0, held_torque_nm)`` starts
from the set-point the drives hold when it activates: here the nominal model's gravity torque at q0, what
holds an arm at rest there (the simulator's runs start at rest). Until 2026-11-27 they started from
zero: on the real UR5 (shoulder gravity ~60 N·m, 1 N·m per cycle) the arm then fell for tens of
milliseconds before the torque caught up, and every rate-aware run left the limits.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from hil_runtime.bundle import BundleError, PolicyBundle, sha256_file
from hil_runtime.rate_limit import TORQUE_RATE_LIMITS, TorqueRateLimiter
from hil_runtime.velocity_filter import VelocityFilter
from models.errors import ModelInputError
from models.feedback.base import FeedbackLaw
from models.robots import RobotModel

# Law parameters from a synthesis (H-infinity's gamma) differ at ~1e-8 between numerical stacks
# (slycot/scipy/numpy versions): far below what changes the law, far above a JSON string match.
# A bundle for another gain set differs by 1e-2 or more, so this tolerance still catches it.
PARAMS_RTOL = 1e-6
PARAMS_ATOL = 1e-9


def _canonical(params: Any) -> Any:
    return json.loads(json.dumps(params, sort_keys=True, default=lambda v: np.asarray(v).tolist()))


def params_difference(bundle: Any, law: Any, where: str = "params") -> str | None:
    """The first field where two law-parameter trees differ beyond PARAMS_RTOL/ATOL, or None.

    Structure, strings and booleans must match exactly; numbers within the tolerance."""
    a, b = _canonical(bundle), _canonical(law)
    if isinstance(a, dict) and isinstance(b, dict):
        if set(a) != set(b):
            return f"{where}: fields {sorted(set(a) ^ set(b))}"
        return next((d for k in sorted(a) if (d := params_difference(a[k], b[k], f"{where}.{k}"))), None)
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return f"{where}: {len(a)} values vs {len(b)}"
        return next(
            (d for i, (x, y) in enumerate(zip(a, b, strict=True)) if (d := params_difference(x, y, f"{where}[{i}]"))),
            None,
        )
    numbers = (int, float)
    if isinstance(a, numbers) and isinstance(b, numbers) and not isinstance(a, bool) and not isinstance(b, bool):
        return None if abs(a - b) <= PARAMS_ATOL + PARAMS_RTOL * max(abs(a), abs(b)) else f"{where}: {a!r} vs {b!r}"
    return None if a == b and type(a) is type(b) else f"{where}: {a!r} vs {b!r}"


SHIPPED_BUNDLES = Path(__file__).resolve().parents[1] / "bundles"


def bundle_path(robot_name: str, law_name: str, bundle_dir: str | Path | None = None) -> Path:
    """<bundle_dir>/<robot>/<law>, or <bundle_dir>/<law> when that holds a manifest directly."""
    root = Path(bundle_dir) if bundle_dir is not None else SHIPPED_BUNDLES
    if (root / law_name / "manifest.json").is_file():
        return root / law_name
    return root / robot_name / law_name


class LMPCController:
    """The bundle's fused law + emulator for a batch of B independent arms."""

    def __init__(
        self,
        bundle: PolicyBundle,
        law_name: str,
        torque_rate_limit: str = "none",
        held_torque: Callable[[np.ndarray], np.ndarray] | None = None,
        velocity_filter_hz: float | None = None,
    ) -> None:
        """``held_torque(q0)`` (B, N): the torque holding each arm at the start of a run (None: zero);
        ``velocity_filter_hz``: the runtime's LMPC velocity input filter (hil_runtime.velocity_filter; None: off)."""
        self.bundle = bundle
        self.held_torque = held_torque
        self.name = f"{law_name}/lmpc"
        applied = bundle.manifest.law.applied_torque_slice  # the law keeps the applied torque (ADRC)
        self._applied = slice(int(applied[0]), int(applied[1])) if applied else None
        self.rate_limiter = (
            TorqueRateLimiter(bundle.torque_rate_nm_s, bundle.period_s) if torque_rate_limit == "libfranka" else None
        )
        self.velocity_filter = (
            None if velocity_filter_hz is None else VelocityFilter(velocity_filter_hz, bundle.period_s, bundle.n_joints)
        )
        self.cycle_times_s: list[float] = []
        self.last_tau_fb: np.ndarray | None = None
        self.state = np.zeros((1, bundle.state_size))
        self.fallbacks = np.zeros(1, np.int64)  # per arm: cycles of full fallback (alpha = 0: tau = sat(tau_fb))
        self.blended = np.zeros(1, np.int64)  # per arm: cycles with 0 < alpha < 1 (near the box edge)
        self.clamped = np.zeros(1, np.int64)  # per arm: cycles with >= 1 joint's residual clamped to the bound
        self.cycles = 0
        # tau_prev per arm (a graph that reads it): what was commanded last period
        self.previous = np.zeros((1, bundle.n_joints))

    def reset(self, q0: np.ndarray) -> None:
        self.state = np.atleast_2d(self.bundle.initial_state(np.atleast_2d(np.asarray(q0, float))))
        self.cycle_times_s = []
        self.fallbacks = np.zeros(self.state.shape[0], np.int64)
        self.blended = np.zeros(self.state.shape[0], np.int64)
        self.clamped = np.zeros(self.state.shape[0], np.int64)
        self.cycles = 0
        arms = self.state.shape[0]
        self.previous = np.zeros((arms, self.bundle.n_joints))
        if self.held_torque is not None:
            self.previous[:] = self.held_torque(np.atleast_2d(np.asarray(q0, float)))
        if self.rate_limiter is not None:
            self.rate_limiter.reset(self.previous, arms=arms)
        if self.velocity_filter is not None:
            self.velocity_filter.reset(arms=None if arms == 1 else arms)

    def trust_counters(self) -> dict[str, object]:
        """Trust-region counters since the last reset (per arm): what the runtime's supervisor counts."""
        return {
            "cycles": self.cycles,
            "fallback_cycles": self.fallbacks.tolist(),
            "blended_cycles": self.blended.tolist(),
            "clamped_cycles": self.clamped.tolist(),
        }

    def __call__(
        self, t_s: float, q: np.ndarray, qd: np.ndarray, q_d: np.ndarray, qd_d: np.ndarray, qdd_d: np.ndarray
    ) -> np.ndarray:
        start = time.perf_counter()
        if self.velocity_filter is not None:  # the runtime's input filter, as its policy stage applies it
            qd = self.velocity_filter.filter(qd[0] if q.shape[0] == 1 else qd).reshape(qd.shape)
        if q.shape[0] == 1:
            row = self.state[0]
            if self.bundle.previous_torque_nm is not None:
                self.bundle.previous_torque_nm[:] = self.previous[0]
            _, _, state = self.bundle.step(q[0], qd[0], q_d[0], qd_d[0], qdd_d[0], row)
            row[:] = state
            pair = self.bundle.last_torques.copy()  # tau and tau_fb in one copy: (2, 1, N)
            tau, tau_fb = pair[0], pair[1]
            fallback, clamped = self.bundle.last_trust.tolist()  # Python floats: cheaper comparisons
            if fallback > 0.0:
                if fallback >= 1.0:
                    self.fallbacks[0] += 1
                else:
                    self.blended[0] += 1
            if clamped > 0.5:
                self.clamped[0] += 1
        else:
            tau, tau_fb, self.state = self.bundle.step_batch(q, qd, q_d, qd_d, qdd_d, self.state, self.previous)
            trust = self.bundle.last_trust_batch
            self.fallbacks += trust[:, 0] >= 1.0
            self.blended += (trust[:, 0] > 0.0) & (trust[:, 0] < 1.0)
            self.clamped += trust[:, 1] > 0.5
        if self.rate_limiter is not None:
            tau = self.rate_limiter.limit(tau).copy()
        if self.bundle.takes_previous_torque:  # commit() replaces it with what was actually commanded
            np.copyto(self.previous, tau, where=np.isfinite(tau))
        self.cycles += 1
        self.cycle_times_s.append(time.perf_counter() - start)
        self.last_tau_fb = tau_fb
        return tau

    def commit(self, applied_torque_nm: np.ndarray) -> None:
        """The torque the simulator commanded (B, N), after its saturation: the law's state records
        it where the law keeps it (as the runtime's ``Controller.commit``), the rate limit starts from it."""
        if self._applied is not None:
            self.state[:, self._applied] = applied_torque_nm
        if self.rate_limiter is not None:
            self.rate_limiter.commit(applied_torque_nm)
        if self.bundle.takes_previous_torque:
            self.previous[:] = applied_torque_nm


def make_lmpc_controller(
    law: FeedbackLaw, robot: RobotModel, bundle_dir: str | Path | None = None, **options: Any
) -> LMPCController:
    """The LMPC controller for ``law`` on ``robot`` from its bundle (default: the shipped ones)."""
    torque_rate_limit = str(options.pop("torque_rate_limit", "none"))
    velocity_filter_hz = options.pop("velocity_filter_hz", None)
    if options:
        raise ModelInputError(
            f"lmpc options: unknown {', '.join(sorted(options))} (known: bundle_dir, torque_rate_limit, "
            "velocity_filter_hz)"
        )
    if velocity_filter_hz is not None:
        from hil_runtime.velocity_filter import filter_pole

        try:
            filter_pole(float(velocity_filter_hz), law.period_s)
        except ValueError as exc:
            raise ModelInputError(f"--lmpc-velocity-filter-hz: {exc}") from None
    if torque_rate_limit not in TORQUE_RATE_LIMITS:
        raise ModelInputError(
            f"--torque-rate-limit: unknown '{torque_rate_limit}' (known: {', '.join(TORQUE_RATE_LIMITS)})"
        )
    path = bundle_path(robot.name, law.name, bundle_dir)
    if bundle_dir is not None and not (path / "manifest.json").is_file():  # name what the user typed
        root = Path(bundle_dir)
        raise BundleError(
            f"bundle directory {bundle_dir}: no bundle for law '{law.name}' (looked for "
            f"{root / law.name / 'manifest.json'} and {root / robot.name / law.name / 'manifest.json'})"
        )
    bundle = PolicyBundle.load(
        path,
        expected_joints=robot.n_joints,
        expected_period_s=law.period_s,
        expected_joint_names=list(robot.joint_names),
        expected_urdf_sha256=sha256_file(robot.urdf_path),
    )
    if bundle.law_name != law.name:
        raise BundleError(f"bundle {path / 'manifest.json'}: law '{bundle.law_name}', asked for '{law.name}'")
    difference = params_difference(bundle.manifest.law.params, law.params)
    if difference is not None:
        raise BundleError(
            f"bundle {path / 'manifest.json'}: law '{law.name}' parameters differ from the bundle's "
            f"(gain set {bundle.manifest.law.gain_set!r}; bundle vs law {difference}); "
            "re-export with `hil pipeline`"
        )
    from models.dynamics import make_dynamics

    dynamics = make_dynamics(robot)
    return LMPCController(
        bundle,
        law.name,
        torque_rate_limit,
        held_torque=dynamics.gravity,
        velocity_filter_hz=None if velocity_filter_hz is None else float(velocity_filter_hz),
    )
