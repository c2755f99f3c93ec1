"""Gains for any serial revolute arm, designed from its URDF: the gain set ``designed``.

    from models.feedback import make_law
    law = make_law("pd", load_robot("panda"), 1e-3, gain_set="designed")
    design = design_gains(load_robot("panda"))        # every law's gains and the envelope figures

Per joint j, over the operating envelope (``models.delay_margin.envelope_poses``: poses drawn inside
the joint ranges, capped at +/- pi):

    m_min_j = 1 / max (M^-1)_jj     the lightest effective inertia (the arm folded, the others free)
    m_max_j = max M_jj              the heaviest (the arm stretched)

and the control period T with d periods of measurement delay (the cyclic protocol's one). A discrete
velocity loop v+ = v - (K_d T / m) v[k-d] is stable for K_d T / m < 1 with d = 1 (< 2 without delay),
so every law's damping-like gain is held to

    K_d,j <= C_V m_min_j / T                        (C_V = 0.5: half the limit, for coupling and filters)

and its bandwidth to the phase the delay and the hold cost at crossover:

    w_j <= PHASE / ((d + 1/2) T)                    (PHASE = 0.2 rad)
    K_p,j <= tau_max,j / E_SAT                      (E_SAT = 0.1 rad: the P term alone saturates beyond it)

The laws (docs/feedback_laws.md, "Designed gains", gives the equations and the figures):

- PD: K_d = min(C_V m_min / T, 2 ZETA m_max w_phase); K_p = min(K_d^2 / (4 ZETA^2 m_max), m_max w_phase^2,
  tau_max / E_SAT), so the heaviest configuration has damping ratio >= ZETA; w_j = sqrt(K_p / m_max).
- PID: PD's K_p, K_d; K_i = K_p w_j / 30 (the integral's corner 30x below the loop: at w / 10 the
  integral against the Panda's gravity stiffness leaves a slow unstable mode).
- ADRC: b0_j = m_max_j; omega_c (one for the arm) = min_j of w_j and of the damping budget
  b0_j 2 omega_c <= C_V m_min_j / T; omega_o = max(w_phase / 2, 4 omega_c): the observer as fast as
  the delay allows with a factor 2 (at 1 kHz and d = 1: 67 rad/s). (b0 = m_min, the textbook
  "b0 <= 2 m" side, leaves slow unstable modes at most poses when m_max / m_min is large: 46 on
  ur5_paper's elbow; b0 = m_max and a slow omega_c do not.)
- H-infinity: the paper's mixed-sensitivity weights on the unit plant 1 / (s + 0.1)^2, the result
  scaled to each joint's nominal inertia m_min_j and bandwidth w_j (hinf.design_joint).
- SMC: lambda_j = w_j; boundary layer epsilon = 0.02 rad/s (the paper's); k_j = C_V m_min_j epsilon / T
  (the layer's gain k / epsilon at the delay budget: no relay chatter), at most 5 % of tau_max.
- MRAC: inertia box at 1x diag M^(0) (=: m0); alpha_j = C_V m_min_j / (4 T); Lambda_j = min(w_j,
  3 C_V m_min_j / (4 T m0_j)) so theta_I Lambda + alpha stays within the damping budget; gamma_j =
  alpha_j w_j / 10 (the offset's integral action a decade below).

The linear laws (PD, PID, ADRC, H-infinity) are then checked with ``models.delay_margin.delay_margin``;
a design that fails it is retried with its bandwidths and damping budget scaled by BACKOFF, and refused
(DesignError, the reason named) after RETRIES. SMC and MRAC take the scale the PD design passed with
(the same budget against the same coupling) and are checked by simulation (``hil stability``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any

import numpy as np

from models.errors import ModelInputError
from models.robots import RobotModel

C_V = 0.5  # of the one-period-delay velocity-loop limit K_d T / m < 1
PHASE_RAD = 0.2  # phase the delay and the zero-order hold may cost at crossover
E_SAT_RAD = 0.1  # position error at which the P term alone reaches the torque limit
ZETA = 0.5  # damping ratio at the heaviest configuration, at least
SMC_EPSILON = 0.02  # the paper's boundary layer, rad/s
SMC_MAX_SWITCHING_RATIO = 0.05  # of the torque limit
PID_INTEGRAL_RATIO = 30.0  # K_i = K_p w / this (w / 10 leaves a slow mode against the Panda's gravity)
BACKOFF = 0.7  # bandwidth scale per retry when the delay check fails
RETRIES = 4
PAPER_HINF_ALPHA = 0.2  # W_T, the paper's (models/feedback/hinf.py)
LINEAR = ("pd", "pid", "adrc", "hinf")


class DesignError(ModelInputError):
    """The automatic design cannot give a law gains that pass its checks (the message says why)."""


@dataclass(frozen=True)
class Envelope:
    """Per-joint inertia range over the operating envelope (kg m^2) and what bounds the bandwidth."""

    m_min: np.ndarray
    m_max: np.ndarray
    m_zero: np.ndarray  # diag M(q = 0): the nominal inertia MRAC's box is built on
    torque_limit_nm: np.ndarray
    period_s: float
    delay_periods: int
    poses: int

    @property
    def phase_bandwidth_rad_s(self) -> float:
        return PHASE_RAD / ((self.delay_periods + 0.5) * self.period_s)

    @property
    def damping_budget_nm_s(self) -> np.ndarray:
        """C_V m_min / T: the most damping (N m s/rad) the delayed velocity loop takes."""
        return C_V * self.m_min / self.period_s


@dataclass
class Design:
    """Every law's designed gains for one robot (``gains[law]``, make_law keyword arguments)."""

    robot: str
    envelope: Envelope
    gains: dict[str, dict[str, Any]]
    bandwidth_rad_s: np.ndarray
    scale: dict[str, float] = field(default_factory=dict)  # bandwidth back-off applied per law
    delay_checks: dict[str, dict[str, Any]] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        env = self.envelope
        return {
            "robot": self.robot,
            "envelope": {
                "m_min_kg_m2": env.m_min.tolist(),
                "m_max_kg_m2": env.m_max.tolist(),
                "poses": env.poses,
                "delay_periods": env.delay_periods,
                "period_s": env.period_s,
            },
            "bandwidth_rad_s": self.bandwidth_rad_s.tolist(),
            "gains": {law: {k: _plain(v) for k, v in g.items()} for law, g in self.gains.items()},
            "bandwidth_scale": self.scale,
            "delay_checks": self.delay_checks,
        }


def _plain(value: Any) -> Any:
    return value.tolist() if isinstance(value, np.ndarray) else value


def envelope(robot: RobotModel, period_s: float = 1e-3, delay_periods: int = 1, poses: int = 400) -> Envelope:
    """The inertia range of each joint over ``poses`` seeded envelope poses."""
    from models.delay_margin import envelope_poses
    from models.dynamics import make_dynamics

    dynamics = make_dynamics(robot, "pinocchio")
    mass = dynamics.mass_matrix(envelope_poses(robot, poses))
    inverse_diagonal = np.diagonal(np.linalg.inv(mass), axis1=1, axis2=2)
    m_zero = np.diag(np.asarray(dynamics.mass_matrix(np.zeros((1, robot.n_joints))))[0]).copy()
    m_min, m_max = 1.0 / inverse_diagonal.max(0), np.diagonal(mass, axis1=1, axis2=2).max(0)
    if not (np.all(np.isfinite(m_min)) and np.all(m_min > 0)):
        raise DesignError(f"gain design for '{robot.name}': the mass matrix is singular somewhere in the envelope")
    limit = np.asarray(robot.torque_limit_nm, float)
    return Envelope(m_min, m_max, m_zero, limit, float(period_s), int(delay_periods), int(poses))


def law_gains(name: str, env: Envelope, scale: float = 1.0) -> tuple[dict[str, Any], np.ndarray]:
    """One law's gains from the envelope, bandwidths scaled by ``scale``: (make_law kwargs, w_j rad/s)."""
    w_phase = scale * env.phase_bandwidth_rad_s
    budget = scale * env.damping_budget_nm_s
    kd = np.minimum(budget, 2.0 * ZETA * env.m_max * w_phase)
    kp = np.minimum.reduce(
        [kd**2 / (4.0 * ZETA**2 * env.m_max), env.m_max * w_phase**2, env.torque_limit_nm / E_SAT_RAD]
    )
    bandwidth = np.sqrt(kp / env.m_max)
    if name == "pd":
        return {"kp": kp, "kd": kd}, bandwidth
    if name == "pid":
        return {"kp": kp, "kd": kd, "ki": kp * bandwidth / PID_INTEGRAL_RATIO}, bandwidth
    if name == "adrc":  # b0 = m_max: a smaller b0 leaves slow unstable modes (docs/feedback_laws.md)
        omega_c = float(min(bandwidth.min(), (budget / (2.0 * env.m_max)).min()))
        return {"b0": env.m_max, "omega_o": float(max(0.5 * w_phase, 4.0 * omega_c)), "omega_c": omega_c}, bandwidth
    if name == "hinf":
        nominal = env.m_min  # the geometric mean leaves slow unstable modes on the Panda (docs)
        return {"alpha": PAPER_HINF_ALPHA, "nominal_inertia_kg_m2": nominal, "bandwidth_rad_s": bandwidth}, bandwidth
    if name == "smc":
        k = np.minimum(budget * SMC_EPSILON, SMC_MAX_SWITCHING_RATIO * env.torque_limit_nm)
        return {"lam": bandwidth, "k": k, "epsilon": SMC_EPSILON}, bandwidth
    if name == "mrac":
        alpha = budget / 4.0
        lam = np.minimum(bandwidth, 0.75 * budget / env.m_zero)
        gains = {"alpha": alpha, "gamma": alpha * bandwidth / 10.0, "lam": lam, "inertia_bound_scale": 1.0}
        return gains, bandwidth
    raise ModelInputError(f"gain design: unknown law '{name}'")


def design_law(robot: RobotModel, name: str, period_s: float = 1e-3, delay_periods: int = 1) -> dict[str, Any]:
    """The designed gains of one law (make_law keyword arguments), checked; DesignError if none pass."""
    return _design_cached(robot, period_s, delay_periods, name)[0]


def design_gains(robot: RobotModel, period_s: float = 1e-3, delay_periods: int = 1) -> Design:
    """Every law's designed gains for ``robot``, each checked (the linear ones by the delay margin)."""
    env = _envelope_cached(robot, period_s, delay_periods)
    design = Design(robot.name, env, {}, law_gains("pd", env)[1])
    for name in ("pd", "pid", "adrc", "hinf", "smc", "mrac"):
        gains, scale, check = _design_cached(robot, period_s, delay_periods, name)
        design.gains[name], design.scale[name] = gains, scale
        if check is not None:
            design.delay_checks[name] = check
    return design


def _key(robot: RobotModel) -> tuple[str, str]:
    return robot.name, str(robot.urdf_path)


_ROBOTS: dict[tuple[str, str], RobotModel] = {}


def _envelope_cached(robot: RobotModel, period_s: float, delay_periods: int) -> Envelope:
    _ROBOTS[_key(robot)] = robot
    return _envelope_by_key(_key(robot), period_s, delay_periods)


@lru_cache(maxsize=32)
def _envelope_by_key(key: tuple[str, str], period_s: float, delay_periods: int) -> Envelope:
    return envelope(_ROBOTS[key], period_s, delay_periods)


def _design_cached(
    robot: RobotModel, period_s: float, delay_periods: int, name: str
) -> tuple[dict[str, Any], float, dict[str, Any] | None]:
    _ROBOTS[_key(robot)] = robot
    return _design_by_key(_key(robot), period_s, delay_periods, name)


@lru_cache(maxsize=64)
def _design_by_key(
    key: tuple[str, str], period_s: float, delay_periods: int, name: str
) -> tuple[dict[str, Any], float, dict[str, Any] | None]:
    """(gains, bandwidth scale used, delay check of the accepted design or None for SMC/MRAC)."""
    from models.delay_margin import delay_margin, envelope_poses
    from models.feedback import make_law

    robot = _ROBOTS[key]
    env = _envelope_by_key(key, period_s, delay_periods)
    if name not in LINEAR:  # SMC, MRAC: the damping budget the PD design's delayed loop was proven with
        scale = _design_by_key(key, period_s, delay_periods, "pd")[1]
        return law_gains(name, env, scale)[0], scale, None
    poses = envelope_poses(robot)  # the poses `hil stability` checks
    scale = 1.0
    last: dict[str, Any] = {}
    for _ in range(RETRIES + 1):
        gains = law_gains(name, env, scale)[0]
        report = delay_margin(make_law(name, robot, period_s, "paper", **gains), robot, delay_periods, poses=poses)
        last = report.as_dict()
        last.pop("worst_pose_rad")
        if report.holds and report.unstable_poses == 0:
            return gains, scale, last
        scale *= BACKOFF
    raise DesignError(
        f"gain design for '{robot.name}', law '{name}': the delayed loop ({delay_periods} period(s)) stays unstable "
        f"at {last['unstable_poses']} of {last['poses']} envelope poses (worst spectral radius "
        f"{last['worst_spectral_radius']:.4f}) even with the bandwidths scaled by {scale / BACKOFF:.3g}"
    )
