"""Delay margin: is a feedback law's loop stable with the cyclic protocol's measurement delay?

A free-running CiA 402 cycle samples the drives at SYNC k and applies the torque computed from that
sample from SYNC k+1 on: one period of delay that lock-step simulation does not have
(docs/feedback_laws.md, "Delay margin"). For the laws whose step is linear near the equilibrium
(PD, PID, ADRC, H-infinity) the check is linear and exact for small motions:

    plant at pose q0, at rest, linearized and discretized exactly for a torque held one period (ZOH):
        x = [dq, dqd],  x[k+1] = Ad x[k] + Bd u[k],   qdd = M(q0)^-1 (u - dG/dq(q0) dq)
    law linearized at e = 0 (numerical Jacobians of law.step, state s):
        u[k] = Ly y[k-d] + Ls s[k],   s[k+1] = Fy y[k-d] + Fs s[k],   y = [q, qd] as measured
    closed loop on [x[k], y[k-1] .. y[k-d], s[k]]: stable at q0 iff its spectral radius < 1
    (up to modes growing slower than GROWTH_TOLERANCE_PER_S, counted as marginal).

The radius is evaluated over poses drawn uniformly inside the joint ranges (capped at +/- pi: the
operating envelope), seeded. SMC (a boundary-layer relay whose linearization is meaningless at
1 kHz, docs/feedback_laws.md) and MRAC (adaptive: its gains move with theta) are checked by
simulation instead: ``simulated_delay_check`` runs the law in the models simulator with the delay on
operating conditions and reports whether every run stays inside the limits.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from models.errors import ModelInputError
from models.feedback.base import FeedbackLaw
from models.robots import RobotModel

#: The laws whose delay margin is checked by the linear analysis; the others by simulation.
LINEAR_LAWS = ("pd", "pid", "adrc", "hinf")
DEFAULT_POSES = 400
DEFAULT_SEED = 0
#: Finite-difference step of the law's Jacobians (rad, rad/s, state units): the laws are linear near
#: e = 0 (H-infinity's gravity feed-forward is smooth), so central differences are exact to ~1e-9.
_JACOBIAN_STEP = 1e-6
#: A mode growing slower than this (1/s: e-folding over 20 s, 4x a condition) counts as marginal: laws
#: with near-cancelled poles (H-infinity's controller zeros on the plant's shifted double pole) put
#: modes at |z| = 1 - 1e-8 that rounding in the eigenvalues moves either side of 1.
GROWTH_TOLERANCE_PER_S = 0.05


@dataclass(frozen=True)
class DelayMarginReport:
    """Spectral radius of the discrete loop per sampled pose, with the delay and without it (< 1: stable).

    The check holds when the delay makes no pose unstable that is stable without it. A pose unstable
    already without the delay (a slow mode of the law itself, e.g. H-infinity's near-zero static
    stiffness against the arm's coupling) is reported apart, with its growth rate ln(radius) / period."""

    law: str
    delay_periods: int
    period_s: float
    poses: np.ndarray  # (P, N) rad
    spectral_radius: np.ndarray  # (P,) with the delay
    spectral_radius_no_delay: np.ndarray  # (P,)

    @property
    def worst_radius(self) -> float:
        return float(self.spectral_radius.max())

    @property
    def radius_limit(self) -> float:
        """The spectral radius above which a pose counts as unstable (GROWTH_TOLERANCE_PER_S)."""
        return float(np.exp(GROWTH_TOLERANCE_PER_S * self.period_s))

    @property
    def unstable_poses(self) -> int:
        return int(np.sum(self.spectral_radius > self.radius_limit))

    @property
    def delay_induced_poses(self) -> int:
        """Poses stable without the delay and unstable with it."""
        limit = self.radius_limit
        return int(np.sum((self.spectral_radius > limit) & (self.spectral_radius_no_delay <= limit)))

    @property
    def holds(self) -> bool:
        return self.delay_induced_poses == 0

    def growth_rate_per_s(self, radius: float) -> float:
        """ln(radius) / period: the worst mode's exponential rate (> 0 grows), 1/s."""
        return float(np.log(radius) / self.period_s)

    def as_dict(self) -> dict[str, Any]:
        worst = int(np.argmax(self.spectral_radius))
        no_delay = float(self.spectral_radius_no_delay.max())
        return {
            "law": self.law,
            "method": "linear",
            "delay_periods": self.delay_periods,
            "period_s": self.period_s,
            "poses": len(self.poses),
            "unstable_poses": self.unstable_poses,
            "delay_induced_unstable_poses": self.delay_induced_poses,
            "unstable_poses_without_delay": int(np.sum(self.spectral_radius_no_delay > self.radius_limit)),
            "growth_tolerance_per_s": GROWTH_TOLERANCE_PER_S,
            "worst_spectral_radius": self.worst_radius,
            "worst_growth_rate_per_s": self.growth_rate_per_s(self.worst_radius),
            "worst_spectral_radius_without_delay": no_delay,
            "worst_growth_rate_without_delay_per_s": self.growth_rate_per_s(no_delay),
            "worst_pose_rad": self.poses[worst].tolist(),
            "holds": self.holds,
        }


def envelope_poses(robot: RobotModel, count: int = DEFAULT_POSES, seed: int = DEFAULT_SEED) -> np.ndarray:
    """``count`` poses (count, N) drawn uniformly inside each joint's range, capped at +/- pi."""
    if count < 1:
        raise ModelInputError(f"delay margin: need at least one pose, got {count}")
    lower = np.maximum(np.asarray(robot.position_lower_rad, float), -np.pi)
    upper = np.minimum(np.asarray(robot.position_upper_rad, float), np.pi)
    return np.random.default_rng(seed).uniform(lower, upper, size=(count, robot.n_joints))


def _gravity_jacobian(robot: RobotModel, poses: np.ndarray) -> np.ndarray:
    """dG/dq (P, N, N) by central differences of the batched gravity."""
    from models.dynamics import make_dynamics

    dynamics = make_dynamics(robot, "pinocchio")
    n, h = robot.n_joints, 1e-6
    out = np.zeros((len(poses), n, n))
    for j in range(n):
        step = np.zeros(n)
        step[j] = h
        out[:, :, j] = (dynamics.gravity(poses + step) - dynamics.gravity(poses - step)) / (2 * h)
    return out


def linearize_law(law: FeedbackLaw, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(Ly (P, N, 2N), Ls (P, N, S), Fy (P, S, 2N), Fs (P, S, S)) of ``law.step`` at rest at each pose.

    y = [q, qd] as measured; the reference holds the pose (q_d = q0, qd_d = qdd_d = 0)."""
    n, s = law.n_joints, law.state_size
    p = len(poses)
    zeros = np.zeros_like(poses)
    state0 = law.initial_state(poses)
    columns = 2 * n + s
    d_tau, d_state = np.zeros((p, n, columns)), np.zeros((p, s, columns))
    for c in range(columns):
        outputs = []
        for sign in (1.0, -1.0):
            q, qd, state = poses.copy(), zeros.copy(), state0.copy()
            target = q if c < n else qd if c < 2 * n else state
            target[:, c % n if c < 2 * n else c - 2 * n] += sign * _JACOBIAN_STEP
            outputs.append(law.step(np, state, q, qd, poses, zeros, zeros))
        d_tau[:, :, c] = (outputs[0][0] - outputs[1][0]) / (2 * _JACOBIAN_STEP)
        d_state[:, :, c] = (outputs[0][1] - outputs[1][1]) / (2 * _JACOBIAN_STEP)
    return d_tau[:, :, : 2 * n], d_tau[:, :, 2 * n :], d_state[:, :, : 2 * n], d_state[:, :, 2 * n :]


def plant_matrices(robot: RobotModel, poses: np.ndarray, period_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(Ad (P, 2N, 2N), Bd (P, 2N, N)): the arm at rest at each pose, torque held one period (exact ZOH)."""
    from models.dynamics import make_dynamics

    n = robot.n_joints
    inverse_mass = np.linalg.inv(make_dynamics(robot, "pinocchio").mass_matrix(poses))
    d_gravity = _gravity_jacobian(robot, poses)
    block = np.zeros((len(poses), 3 * n, 3 * n))
    block[:, :n, n : 2 * n] = np.eye(n)
    block[:, n : 2 * n, :n] = -inverse_mass @ d_gravity
    block[:, n : 2 * n, 2 * n :] = inverse_mass
    discrete = _expm_nilpotent_input(block * period_s)
    return discrete[:, : 2 * n, : 2 * n], discrete[:, : 2 * n, 2 * n :]


def _expm_nilpotent_input(blocks: np.ndarray, terms: int = 20) -> np.ndarray:
    """exp of (P, X, X) ZOH blocks [[A T, B T], [0, 0]] by their Taylor series, batched.

    The input rows are zero, so the series converges at the rate of ||A T|| (here ~1e-2: T = 1 ms
    against the arm's gravity stiffness), whatever the size of B T: 20 terms are exact to machine
    precision, and batched matrix products beat one scipy expm per pose by ~100x."""
    result = np.broadcast_to(np.eye(blocks.shape[1]), blocks.shape).copy()
    term = result.copy()
    for k in range(1, terms + 1):
        term = term @ blocks / k
        result += term
    return result


def closed_loop_matrices(
    ad: np.ndarray, bd: np.ndarray, ly: np.ndarray, ls: np.ndarray, fy: np.ndarray, fs: np.ndarray, delay_periods: int
) -> np.ndarray:
    """The closed loop's transition matrices (P, X, X) on [x[k], y[k-1] .. y[k-d], s[k]]."""
    p, nx, _ = ad.shape
    s, d = fs.shape[1], delay_periods
    size = nx * (1 + d) + s
    loop = np.zeros((p, size, size))
    measured = slice(nx * d, nx * (d + 1))  # where y[k-d] sits (x[k] itself when d = 0)
    law_state = slice(nx * (1 + d), size)
    loop[:, :nx, :nx] = ad
    loop[:, :nx, measured] += bd @ ly
    loop[:, :nx, law_state] = bd @ ls
    for j in range(d):  # the delay line: y[k] = x[k] enters slot 1, each slot moves one on
        loop[:, nx * (j + 1) : nx * (j + 2), nx * j : nx * (j + 1)] = np.eye(nx)
    loop[:, law_state, measured] += fy
    loop[:, law_state, law_state] = fs
    return loop


def delay_margin(
    law: FeedbackLaw,
    robot: RobotModel,
    delay_periods: int = 1,
    poses: np.ndarray | None = None,
    count: int = DEFAULT_POSES,
    seed: int = DEFAULT_SEED,
) -> DelayMarginReport:
    """The linear delay check of ``law`` over ``poses`` (default: ``count`` seeded envelope poses)."""
    if law.name not in LINEAR_LAWS:
        raise ModelInputError(
            f"delay margin: law '{law.name}' is not linear near its equilibrium; check it by simulation "
            f"(simulated_delay_check); linear: {', '.join(LINEAR_LAWS)}"
        )
    if delay_periods < 0:
        raise ModelInputError(f"delay margin: delay_periods must be >= 0, got {delay_periods}")
    poses = envelope_poses(robot, count, seed) if poses is None else np.atleast_2d(np.asarray(poses, float))
    ad, bd = plant_matrices(robot, poses, law.period_s)
    jacobians = linearize_law(law, poses)
    radius = [
        np.abs(np.linalg.eigvals(closed_loop_matrices(ad, bd, *jacobians, d))).max(axis=1) for d in (delay_periods, 0)
    ]
    return DelayMarginReport(law.name, delay_periods, law.period_s, poses, *radius)


def simulated_delay_check(
    law_name: str,
    robot: RobotModel,
    conditions: list[Any],
    gain_set: str,
    delay_periods: int = 1,
    period_s: float = 1e-3,
    law_gains: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Run ``law_name`` (FB) with a ``delay_periods`` measurement delay on ``conditions``: inside the limits?"""
    from models.feedback import make_law
    from models.modes import make_controller
    from models.sim import SimConfig, simulate
    from sim_target.realism_profiles import bind_profile, parse_profile

    sim = SimConfig(period_s=period_s)
    profile = parse_profile({"sensing": {"delay_periods": delay_periods}}, "delay check")
    world = bind_profile(
        profile, "delay check", robot.n_joints, period_s, period_s / sim.substeps, robot.torque_limit_nm
    )
    law = make_law(law_name, robot, period_s, gain_set, **(law_gains or {}))
    trajectory = simulate(robot, make_controller("fb", law, robot), list(conditions), sim, realism=world)
    inside = trajectory.within_limits
    return {
        "law": law_name,
        "method": "simulation",
        "delay_periods": delay_periods,
        "conditions": [c.name for c in conditions],
        "inside_limits": [bool(v) for v in inside],
        "velocity_limit_ratio": [float(v) for v in trajectory.velocity_ratio],
        "holds": bool(np.all(inside)),
    }
