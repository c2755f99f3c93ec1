"""HMPC configuration: one frozen dataclass, validated once, with a one-line error per bad field."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np

from models.errors import ModelInputError

PAPER_CANDIDATE_SCALES = tuple(round(0.5 + 0.1 * i, 1) for i in range(11))  # w_sel = [0.5:0.1:1.5]
BUDGET_POLICIES = ("fallback", "best_iterate")
#: W2's argument: "absolute" (the paper's tau' W2 tau), "anchored" ((tau - w* tau_fb)' W2a (tau - w* tau_fb)) or
#: "feedforward" ((tau - tau_ff)' W2a (tau - tau_ff), tau_ff = ID(q, qd, qdd_d): the feedback effort)
TORQUE_COSTS = ("absolute", "anchored", "feedforward")
KERNELS = ("auto", "numba", "numpy")
#: the applied torque's rate bound: "none", or "franka": the robot's torque-rate bound, libfranka's rule
#: (RobotModel.torque_rate_nm_s, hil_runtime.rate_limit.max_torque_step_nm, docs/scoring.md)
RATE_LIMITS = ("none", "franka")
#: Named HMPC formulations (``hil experiment --hmpc-formulation``, ``hil pipeline --hmpc-formulation``):
#: HMPCConfig options. "deployable" is the one a real arm can run (docs/hmpc.md, "Effort and smoothness"):
#: W2a = 10 dt^2 / M_ii(0)^2 on the torque beyond the model's feed-forward, a smoothness weight on the
#: acceleration change tau_j - tau_{j-1} makes and libfranka's rate bound.
FORMULATIONS: dict[str, dict[str, Any]] = {
    "absolute": {},
    "anchored": {"torque_cost": "anchored"},
    "deployable": {
        "torque_cost": "feedforward",
        "anchor_weight_scale": 10.0,
        "rate_weight_scale": 10.0,
        "torque_rate_limit": "franka",
    },
}

#: The deployable formulation's prediction step on every arm but ur5_paper (s): 5 steps of 10 ms, a 50 ms
#: preview. Under the robot's torque-rate bound (hil_runtime.rate_limit: 1 N·m per 1 ms cycle on the real
#: UR5 and the Panda) a 5 ms preview cannot see that a torque ramped at the bound takes tens of ms to
#: reverse: the optimum slews from bound to bound and the arm limit-cycles out of its velocity limits
#: after the disturbance; with a 50 ms preview it stays inside (docs/any_arm.md, "Torque-rate bound",
#: benchmarks/hmpc_rate_bound_limits.py). ur5_paper keeps the control period, the step its shipped
#: bundles and published tables were measured with.
DEPLOYABLE_PREDICTION_STEP_S = 0.01
PAPER_ROBOT = "ur5_paper"


def formulation_options(name: str, robot_name: str) -> dict[str, Any]:
    """The HMPCConfig options of formulation ``name`` (``FORMULATIONS``) on robot ``robot_name``."""
    options = dict(FORMULATIONS[name])
    if name == "deployable" and robot_name != PAPER_ROBOT:
        options["prediction_step_s"] = DEPLOYABLE_PREDICTION_STEP_S
    return options


Weight = float | tuple[float, ...]


@dataclass(frozen=True)
class HMPCConfig:
    """The MPC layer of Eq. 17. Weights are per joint (a scalar applies to every joint).

    Cost over the preview j = 1..T_N, with temporal weight w_j = 1 - temporal_decay (j - 1):
        J = sum_j w_j [ E_j' W1 E_j + tau_j' W2 tau_j ] + state_bound_weight * |state bound violation|^2
    W1 = diag(position_error_weight (per joint), velocity_error_weight (per joint),
              extra_feature_weight for any further entries of the law's E).

    torque_cost = "anchored" (docs/hmpc.md, "Formulations"): the torque term becomes
        (tau_j - w* tau_fb)' W2a (tau_j - w* tau_fb),  W2a_i = anchor_weight_scale * dt^2 / M_ii(0)^2,
    w* the cheapest candidate scale under the absolute cost (W2 = torque_weight), dt the prediction
    step: a deviation of the acceleration from the law's (scaled) one costs about as much on every
    joint, so the law keeps mattering (with W2 on tau the optimum is the same for every law).
    """

    horizon_steps: int = 5  # T_N
    candidate_scales: tuple[float, ...] = PAPER_CANDIDATE_SCALES  # w in tau_c = w * tau_fb
    temporal_decay: float = 0.05  # w_j = 1 - decay (j - 1)
    # W1 on e (rad) and e_dot (rad/s). Their ratio sets how fast the predicted error is pulled in:
    # over a 5 ms preview the optimum has e_dot ~ -(W1_e / W1_v) * ~3 dt * e, i.e. ~90 rad/s here.
    position_error_weight: Weight = 3.0e4  # 1/rad^2
    velocity_error_weight: Weight = 1.0  # 1/(rad/s)^2
    extra_feature_weight: float = 0.0  # entries of E beyond [e, e_dot] (law-specific features)
    # W2 on tau (N m). Small: the paper penalizes the absolute torque, which includes the gravity
    # load; a large W2 would pull the arm off the reference to save holding torque.
    torque_weight: Weight = 1.0e-6  # 1/(N m)^2
    torque_cost: str = "absolute"  # TORQUE_COSTS
    anchor_weight_scale: float = 10.0  # c in W2a_i = c dt^2 / M_ii(0)^2 (anchored and feedforward)
    # Smoothness (docs/hmpc.md, "Effort and smoothness"): sum_j w_j (tau_j - tau_{j-1})' Wd (tau_j - tau_{j-1}),
    # tau_0 = the torque applied last cycle, Wd_i = rate_weight_scale * dt^2 / M_ii(0)^2 (a torque change
    # that changes joint i's acceleration by da costs rate_weight_scale * (dt da)^2 on every joint alike).
    rate_weight_scale: float = 0.0
    # Effort: W2 on tau per joint = torque_weight + effort_weight_scale / limit_i^2 (a torque at the limit
    # costs effort_weight_scale on every joint alike).
    effort_weight_scale: float = 0.0
    torque_rate_limit: str = "none"  # RATE_LIMITS: a hard bound on |tau_1 - tau_0| (and j x it on tau_j)
    state_bound_weight: float = 1.0e6  # quadratic penalty on |q| > limit, |qd| > limit (soft bounds)
    use_state_bounds: bool = True
    position_limit_rad: tuple[float, ...] | None = None  # None: the robot's (Sec. IV-C) limits
    velocity_limit_rad_s: tuple[float, ...] | None = None
    torque_limit_nm: tuple[float, ...] | None = None
    prediction_step_s: float | None = None  # prediction step; None: the law's control period
    backend: str = "pinocchio"  # "pinocchio" (C++ ABA + analytic derivatives) or "rne" (own RNEFDA)
    max_iterations: int = 4  # Gauss-Newton iterations (derivative evaluations) per solve
    max_qp_iterations: int = 20  # projected-Newton iterations per box QP
    max_line_search_steps: int = 6  # halvings of the Gauss-Newton step
    # Converged when the QP predicts a decrease <= cost_rtol * J + cost_atol, or a full step's true
    # decrease matched the prediction that closely (the model is then exact to that tolerance).
    cost_rtol: float = 1e-4
    cost_atol: float = 1e-12
    qp_tolerance: float = 1e-9  # projected-gradient tolerance of the box QP (relative)
    damping: float = 1e-10  # Levenberg term, relative to the mean Hessian diagonal
    on_budget_exhausted: str = "fallback"  # "fallback" to tau_fb (counted) or "best_iterate"
    warm_start: bool = True  # add last cycle's shifted solution as a candidate
    # The solver's inner loops (models.hmpc.inner_loops: cost, condensation, box QP, penalty rounds):
    # "numba" (compiled, row by row), "numpy" (vectorized over the batch), or "auto" (numba when
    # installed). Same algorithms, same results to round-off; chosen once when the solver is built.
    kernels: str = "auto"

    def __post_init__(self) -> None:
        def fail(name: str, why: str, value: Any) -> None:
            raise ModelInputError(f"hmpc config {name}: {why}, got {value!r}")

        for name in ("horizon_steps", "max_iterations", "max_qp_iterations"):
            value = getattr(self, name)
            if not isinstance(value, int | np.integer) or isinstance(value, bool) or value < 1:
                fail(name, "must be an integer >= 1", value)
        if not isinstance(self.max_line_search_steps, int | np.integer) or self.max_line_search_steps < 0:
            fail("max_line_search_steps", "must be an integer >= 0", self.max_line_search_steps)
        scales = np.asarray(self.candidate_scales, float)
        if scales.ndim != 1 or scales.size == 0 or not np.all(np.isfinite(scales)):
            fail("candidate_scales", "must be a non-empty list of finite numbers", self.candidate_scales)
        for name in (
            "temporal_decay",
            "extra_feature_weight",
            "state_bound_weight",
            "cost_atol",
            "damping",
            "rate_weight_scale",
            "effort_weight_scale",
        ):
            value = getattr(self, name)
            if not (isinstance(value, int | float) and math.isfinite(value) and value >= 0):
                fail(name, "must be a finite number >= 0", value)
        positive = {name: getattr(self, name) for name in ("cost_rtol", "qp_tolerance", "anchor_weight_scale")}
        if self.prediction_step_s is not None:  # None: the law's control period
            positive["prediction_step_s"] = self.prediction_step_s
        for name, value in positive.items():
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                fail(name, "must be a finite number > 0", value)
        if 1.0 - self.temporal_decay * (self.horizon_steps - 1) <= 0.0:
            fail("temporal_decay", f"makes the last of {self.horizon_steps} temporal weights <= 0", self.temporal_decay)
        for name in ("position_error_weight", "velocity_error_weight", "torque_weight"):
            value = np.asarray(getattr(self, name), float)
            if value.ndim > 1 or value.size == 0 or not np.all(np.isfinite(value)) or np.any(value < 0):
                fail(name, "must be finite numbers >= 0 (a scalar or one per joint)", getattr(self, name))
        for name in ("position_limit_rad", "velocity_limit_rad_s", "torque_limit_nm"):
            value = getattr(self, name)
            if value is not None:
                array = np.asarray(value, float)
                if array.ndim != 1 or np.any(np.isnan(array)) or np.any(array <= 0):
                    fail(name, "infeasible bounds: every limit must be > 0 (|x| <= limit)", value)
        if self.on_budget_exhausted not in BUDGET_POLICIES:
            fail("on_budget_exhausted", f"must be one of {', '.join(BUDGET_POLICIES)}", self.on_budget_exhausted)
        if self.torque_cost not in TORQUE_COSTS:
            fail("torque_cost", f"must be one of {', '.join(TORQUE_COSTS)}", self.torque_cost)
        if self.torque_rate_limit not in RATE_LIMITS:
            fail("torque_rate_limit", f"must be one of {', '.join(RATE_LIMITS)}", self.torque_rate_limit)
        if self.kernels not in KERNELS:
            fail("kernels", f"must be one of {', '.join(KERNELS)}", self.kernels)
        if not isinstance(self.backend, str):
            fail("backend", "must be a string", self.backend)

    @property
    def temporal_weights(self) -> np.ndarray:
        """w_j = 1 - decay (j - 1), j = 1..T_N."""
        return 1.0 - self.temporal_decay * np.arange(self.horizon_steps)

    @classmethod
    def from_options(cls, **options: Any) -> HMPCConfig:
        """A config from keyword options (unknown names are a ModelInputError, not a TypeError)."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(options) - known)
        if unknown:
            raise ModelInputError(f"hmpc options: unknown {', '.join(unknown)} (known: {', '.join(sorted(known))})")
        cleaned: dict[str, Any] = {k: tuple(v) if isinstance(v, list | np.ndarray) else v for k, v in options.items()}
        return cls(**cleaned)


def per_joint(name: str, value: Weight | np.ndarray, n_joints: int) -> np.ndarray:
    """A scalar or per-joint value as an (N,) array, checked against the robot's joint count."""
    array = np.asarray(value, float)
    if array.ndim == 0:
        return np.full(n_joints, float(array))
    if array.shape != (n_joints,):
        raise ModelInputError(f"hmpc config {name}: expected 1 or {n_joints} values, got {array.size}")
    return array
