"""The safety supervisor: pure rules over one cycle's feedback and policy output.

No I/O, no clock, no bus: the loop calls it and acts on what it returns (quick stop and FAULT), so
every rule is table-tested (tests/unit/hil_runtime/test_supervisor.py).

Feedback (:meth:`Supervisor.check_feedback`), before the policy runs:

    position or velocity non-finite                   -> FAULT feedback_nonfinite
    position outside [lower, upper]                    -> FAULT position_limit
    |velocity| above its limit                         -> FAULT velocity_limit
    stale feedback more than max_stale_cycles in a row -> FAULT stale_feedback

Timing (:meth:`Supervisor.check_overruns`), before the exchange of a cycle that started late:

    more than overrun_budget late periods in a row     -> FAULT overrun_budget
    (an overrun and the periods it skipped; the drives hold the last set-point meanwhile)

Policy output (:meth:`Supervisor.select_torque`), after it; the one owner of the non-finite rule
(:func:`policy_torque`; the bundle's ``step`` only produces):

    tau finite                       -> tau (clipped to the torque limit)
    tau non-finite, tau_fb finite    -> the law's tau_fb, clipped; counted (law_substitutions)
    both non-finite                  -> FAULT policy_nonfinite
    the law's next state non-finite  -> FAULT policy_nonfinite (the law cannot go on)
    |torque| at the limit            -> counted (saturated_cycles)
    trust fallback > 0 (alpha < 1)   -> counted (fallback_cycles; full_fallback_cycles at 1)

Bus errors (:func:`classify_bus_error`): the driver raises them after quick-stopping the drives;
each is a FAULT of its own kind (feedback_timeout, heartbeat_lost, drive_fault, ...).

The checks use preallocated buffers: a healthy cycle allocates nothing.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np

from drivers.errors import DriveError
from drivers.joint_bus import all_finite, clip_torque

_NO_STATE = np.zeros(0)  # a law without state (``next_law_state`` not given)


class FaultKind(str, enum.Enum):
    FEEDBACK_NONFINITE = "feedback_nonfinite"
    POSITION_LIMIT = "position_limit"
    VELOCITY_LIMIT = "velocity_limit"
    STALE_FEEDBACK = "stale_feedback"
    POLICY_NONFINITE = "policy_nonfinite"
    FEEDBACK_TIMEOUT = "feedback_timeout"
    HEARTBEAT_LOST = "heartbeat_lost"
    DRIVE_FAULT = "drive_fault"
    DRIVE_STATE = "drive_state"
    TRANSPORT = "transport"
    BUS_INTRUDER = "bus_intruder"  # a second sender or a second master on the bus (drivers/bus_guard.py)
    COMMAND = "command"
    OVERRUN_BUDGET = "overrun_budget"
    INTERNAL = "internal"


@dataclass(frozen=True)
class Fault:
    kind: FaultKind
    detail: str

    def __str__(self) -> str:
        return f"{self.kind.value}: {self.detail}"


@dataclass(frozen=True)
class SafetyLimits:
    position_lower_rad: np.ndarray
    position_upper_rad: np.ndarray
    velocity_limit_rad_s: np.ndarray
    torque_limit_nm: np.ndarray
    max_stale_cycles: int = 1
    overrun_budget: int = 20  # late periods in a row tolerated (docs/runtime.md, "Overruns")

    def __post_init__(self) -> None:
        n = self.torque_limit_nm.shape
        shapes = {a.shape for a in (self.position_lower_rad, self.position_upper_rad, self.velocity_limit_rad_s)}
        if shapes != {n} or len(n) != 1:
            raise ValueError("every limit needs one value per joint")
        if np.any(self.position_lower_rad >= self.position_upper_rad) or np.any(self.velocity_limit_rad_s <= 0):
            raise ValueError("position_lower < position_upper and velocity_limit > 0 are required")
        if np.any(self.torque_limit_nm <= 0):
            raise ValueError("torque limits must be positive")

    @property
    def n_joints(self) -> int:
        return int(self.torque_limit_nm.shape[0])


def classify_bus_error(exc: BaseException) -> Fault:
    """The FAULT a driver error stands for (its ``fault_kind``; INTERNAL for anything unexpected)."""
    if isinstance(exc, DriveError):
        try:
            return Fault(FaultKind(exc.fault_kind), str(exc) or type(exc).__name__)
        except ValueError:  # a kind this runtime does not know: still a FAULT, named as a bug
            pass
    return Fault(FaultKind.INTERNAL, f"{type(exc).__name__}: {exc}")


class Supervisor:
    """The rules of the module docstring, with the counters they keep."""

    def __init__(self, limits: SafetyLimits, joint_names: tuple[str, ...] | None = None) -> None:
        self.limits = limits
        n = limits.n_joints
        self.joint_names = joint_names or tuple(f"joint {i + 1}" for i in range(n))
        self._lower = np.asarray(limits.position_lower_rad, float)
        self._upper = np.asarray(limits.position_upper_rad, float)
        self._vmax = np.asarray(limits.velocity_limit_rad_s, float)
        self._tmax = np.asarray(limits.torque_limit_nm, float)
        # The per-cycle checks run on Python floats: for a handful of joints, ``tolist()`` and a
        # loop cost ~2 µs where one numpy call per rule costs ~1 µs each (docs/runtime.md).
        self._bounds = list(zip(self._lower.tolist(), self._upper.tolist(), self._vmax.tolist(), strict=True))
        self._tmax_list = self._tmax.tolist()
        self._sat_list = (self._tmax * (1.0 - 1e-9)).tolist()
        self.stale_run = 0  # consecutive cycles with some stale feedback
        self.reset_counters()

    def reset_counters(self) -> None:
        self.law_substitutions = 0
        self.saturated_cycles = 0
        self.fallback_cycles = 0
        self.full_fallback_cycles = 0
        self.stale_cycles = 0
        self.stale_run = 0

    def counters(self) -> dict[str, int]:
        return {
            "law_substitutions": self.law_substitutions,
            "saturated_cycles": self.saturated_cycles,
            "fallback_cycles": self.fallback_cycles,
            "full_fallback_cycles": self.full_fallback_cycles,
            "stale_cycles": self.stale_cycles,
        }

    # --- feedback -----------------------------------------------------------------------------
    def check_feedback(self, q: np.ndarray, qd: np.ndarray, fresh: np.ndarray) -> Fault | None:
        """None when the feedback is usable; else the FAULT to enter."""
        # NaN compares False everywhere, so the bound checks also catch non-finite values.
        for x, v, (lower, upper, vmax) in zip(q.tolist(), qd.tolist(), self._bounds, strict=True):
            if not (lower <= x <= upper and -vmax <= v <= vmax):
                return self._describe_feedback(q, qd)
        if False not in fresh.tolist():
            self.stale_run = 0
        else:
            self.stale_cycles += 1
            self.stale_run += 1
            if self.stale_run > self.limits.max_stale_cycles:
                stale = [self.joint_names[i] for i in np.flatnonzero(~np.asarray(fresh, bool))]
                return Fault(
                    FaultKind.STALE_FEEDBACK,
                    f"no fresh feedback from {', '.join(stale)} for {self.stale_run} consecutive cycles",
                )
        return None

    def _describe_feedback(self, q: np.ndarray, qd: np.ndarray) -> Fault:
        bad = ~(np.isfinite(q) & np.isfinite(qd))
        if bad.any():
            j = int(np.flatnonzero(bad)[0])
            return Fault(FaultKind.FEEDBACK_NONFINITE, f"{self.joint_names[j]}: position {q[j]}, velocity {qd[j]}")
        out = (q < self._lower) | (q > self._upper)
        if out.any():
            j = int(np.flatnonzero(out)[0])
            return Fault(
                FaultKind.POSITION_LIMIT,
                f"{self.joint_names[j]} at {q[j]:.4f} rad, limits [{self._lower[j]:.4f}, {self._upper[j]:.4f}]",
            )
        j = int(np.argmax(np.abs(qd) - self._vmax))
        return Fault(
            FaultKind.VELOCITY_LIMIT, f"{self.joint_names[j]} at {qd[j]:.4f} rad/s, limit ±{self._vmax[j]:.4f}"
        )

    # --- timing -------------------------------------------------------------------------------------
    def check_overruns(self, late_periods: int) -> Fault | None:
        """None while ``late_periods`` (in a row) is within the budget; else FAULT overrun_budget."""
        budget = self.limits.overrun_budget
        if late_periods <= budget:
            return None
        return Fault(
            FaultKind.OVERRUN_BUDGET,
            f"{late_periods} late periods in a row, budget {budget}: the drives held a stale set-point too long",
        )

    # --- policy output --------------------------------------------------------------------------
    def select_torque(
        self,
        tau: np.ndarray,
        tau_fb: np.ndarray,
        fallback: float,
        out: np.ndarray,
        next_law_state: np.ndarray = _NO_STATE,
    ) -> Fault | None:
        """Write the torque to command into ``out``; None, or the FAULT when nothing is usable.

        ``next_law_state``: the law's state after this cycle (the controller commits it next)."""
        usable = policy_torque(tau, tau_fb, next_law_state)
        if usable is None:
            if all_finite(next_law_state.tolist()):
                return Fault(FaultKind.POLICY_NONFINITE, "policy and feedback-law torques are both non-finite")
            return Fault(FaultKind.POLICY_NONFINITE, "the feedback law's next state is non-finite: it cannot go on")
        source, values = usable
        if source is not tau:
            self.law_substitutions += 1
        if clip_torque(source, values, self._tmax_list, self._sat_list, out):
            self.saturated_cycles += 1
        if fallback > 0.0:  # NaN trust is no fallback evidence either way: not counted
            self.fallback_cycles += 1
            if fallback >= 1.0:
                self.full_fallback_cycles += 1
        return None


def policy_torque(
    tau: np.ndarray, tau_fb: np.ndarray, next_law_state: np.ndarray = _NO_STATE
) -> tuple[np.ndarray, list[float]] | None:
    """The one rule for a non-finite policy output, one arm: (the torque to command, its floats).

    ``tau`` when it and the law's next state are finite; the law's own ``tau_fb`` when only ``tau``
    is not (the emulator broke, the law did not); None when the law's torque or next state is
    non-finite (nothing usable: the caller stops the arm). Unclipped: the caller clips
    (:func:`drivers.joint_bus.clip_torque`). The supervisor applies it every cycle; the bundle's
    ``step_batch`` per arm for offline runs, which have no supervisor (they score what the runtime
    commands). The bundle's ``step`` only produces.
    """
    if next_law_state.size and not all_finite(next_law_state.tolist()):
        return None
    values = tau.tolist()  # Python floats: six of them test faster than numpy calls
    if all_finite(values):
        return tau, values
    values = tau_fb.tolist()
    return (tau_fb, values) if all_finite(values) else None
