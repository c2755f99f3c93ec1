"""The closed-loop simulator: fixed control period, zero-order hold, RK4 plant with substeps.

Many runs advance together (one vectorized plant). Per period k: measure (q, qd) at t_k, compute
the reference, ask the controller for torques, saturate them to the robot's torque limits, hold
them over [t_k, t_k+1) while the plant integrates with RK4 substeps; the disturbance pulse is
integrated exactly (the period containing it is split at the pulse edges). Plant-model mismatch
(payload, scaled masses/inertias, viscous and Coulomb friction) changes the plant only.

A realism profile (``sim_target.realism``, the same model the HIL target applies) sits between the
plant and the controller: the controller sees what the drives would report, the plant receives what
the torque loop would apply, minus the profile's friction; the logged ``tau`` is the command.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from models.conditions import Condition, Disturbance, Mismatch
from models.dynamics import make_dynamics
from models.errors import ModelInputError
from models.robots import RobotModel
from models.sim.controllers import Controller
from sim_target.realism import RealismError, RealismModel, RealismSpec

COULOMB_SMOOTHING_RAD_S = 0.01  # tanh(qd / v) stands in for sign(qd), keeping RK4 well-behaved


@dataclass(frozen=True)
class SimConfig:
    period_s: float = 1e-3  # control period (the paper: 1 kHz)
    substeps: int = 2  # RK4 steps per control period
    plant_backend: str = "pinocchio"  # "pinocchio" (C++ ABA, fast) or "rne" (the paper's RNEFDA)

    def __post_init__(self) -> None:
        if not (self.period_s > 0 and math.isfinite(self.period_s)):
            raise ModelInputError(f"simulation period_s: must be a positive number, got {self.period_s}")
        if self.substeps < 1:
            raise ModelInputError(f"simulation substeps: must be >= 1, got {self.substeps}")


@dataclass
class Trajectory:
    """A batch of runs. Arrays are (B, T, N) sampled at t_s (T,), every control period."""

    t_s: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    q_ref: np.ndarray
    qd_ref: np.ndarray
    tau: np.ndarray  # applied (saturated) torque held over each period
    tau_fb: np.ndarray | None  # the feedback law's torque, when the controller exposes it
    condition_names: list[str]
    disturbance: Disturbance | None
    position_ratio: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (B,) max |q| / limit
    velocity_ratio: np.ndarray = field(default_factory=lambda: np.zeros(0))  # (B,) max |qd| / limit
    finite: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))  # (B,)

    @property
    def within_limits(self) -> np.ndarray:
        return self.finite & (self.position_ratio <= 1.0) & (self.velocity_ratio <= 1.0)

    def run(self, b: int) -> dict[str, np.ndarray]:
        """One run's arrays, for saving as .npz."""
        out = {
            "t": self.t_s,
            "q": self.q[b],
            "qd": self.qd[b],
            "q_ref": self.q_ref[b],
            "qd_ref": self.qd_ref[b],
            "tau": self.tau[b],
        }
        if self.tau_fb is not None:
            out["tau_fb"] = self.tau_fb[b]
        return out


class ModelPlant:
    """The models' simulated arm: the (possibly mismatched) robot, friction, RK4 with substeps.

    Not the HIL target's physics (``sim_target.plant_protocol.TargetPlant``, pybullet behind emulated drives).
    """

    def __init__(self, robot: RobotModel, mismatch: Mismatch, config: SimConfig) -> None:
        self.robot = robot
        self.dynamics = make_dynamics(mismatch.apply(robot), config.plant_backend)
        n = robot.n_joints
        self.viscous = np.broadcast_to(np.asarray(mismatch.viscous_friction_nm_s, float), (n,))
        self.coulomb = np.broadcast_to(np.asarray(mismatch.coulomb_friction_nm, float), (n,))
        self.config = config

    def acceleration(self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray) -> np.ndarray:
        friction = self.viscous * qd + self.coulomb * np.tanh(qd / COULOMB_SMOOTHING_RAD_S)
        return self.dynamics.forward_dynamics(q, qd, tau - friction)

    def integrate(
        self, q: np.ndarray, qd: np.ndarray, tau: np.ndarray, duration_s: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """RK4 over ``duration_s`` with torque held, in steps no longer than period_s / substeps."""
        steps = max(1, math.ceil(duration_s / (self.config.period_s / self.config.substeps) - 1e-9))
        h = duration_s / steps
        for _ in range(steps):
            k1v, k1a = qd, self.acceleration(q, qd, tau)
            k2v = qd + 0.5 * h * k1a
            k2a = self.acceleration(q + 0.5 * h * k1v, k2v, tau)
            k3v = qd + 0.5 * h * k2a
            k3a = self.acceleration(q + 0.5 * h * k2v, k3v, tau)
            k4v = qd + h * k3a
            k4a = self.acceleration(q + h * k3v, k4v, tau)
            q = q + h / 6.0 * (k1v + 2 * k2v + 2 * k3v + k4v)
            qd = qd + h / 6.0 * (k1a + 2 * k2a + 2 * k3a + k4a)
        return q, qd


def batch_key(condition: Condition) -> tuple:
    """What conditions must share to run in one simulator batch (one vectorized plant)."""
    return (condition.duration_s, condition.disturbance, condition.mismatch)


def plant_mismatch(condition_mismatch: Mismatch, realism: RealismSpec | None) -> Mismatch:
    """The plant's inertial errors: the condition's mismatch, or the realism profile's (not both:
    two sources of one error would be ambiguous)."""
    if realism is None or not realism.plant.has_inertial_errors:
        return condition_mismatch
    if not condition_mismatch.is_nominal:
        raise RealismError(
            f"realism {realism.name}: plant: the conditions carry a mismatch too; give the plant errors in one place"
        )
    p = realism.plant
    return Mismatch(
        payload_kg=p.payload_kg,
        payload_com_m=p.payload_com_m,
        mass_scale=tuple(float(x) for x in p.mass_scale),
        inertia_scale=tuple(float(x) for x in p.inertia_scale),
    )


def simulate(
    robot: RobotModel,
    controller: Controller,
    conditions: list[Condition],
    config: SimConfig = SimConfig(),
    progress: object | None = None,
    realism: RealismSpec | None = None,
) -> Trajectory:
    """Run ``controller`` on every condition at once (they must share duration, disturbance, mismatch).

    ``robot`` is the nominal robot; each condition's mismatch turns it into the plant.
    ``progress``: an optional callable(advance_in_periods) for a progress bar.
    ``realism``: the sensing/actuation/plant profile (docs/realism.md); None or ideal: today's world.
    """
    if not conditions:
        raise ModelInputError("simulate: no conditions given")
    if len({batch_key(c) for c in conditions}) != 1:
        raise ModelInputError("simulate: conditions in one batch must share duration, disturbance and mismatch")
    first = conditions[0]
    plant = ModelPlant(robot, plant_mismatch(first.mismatch, realism), config)
    world = RealismModel(realism) if realism is not None and not realism.is_ideal else None
    n, batch, dt = robot.n_joints, len(conditions), config.period_s
    steps = int(round(first.duration_s / dt))
    t = np.arange(steps) * dt

    refs = [c.reference(t) for c in conditions]
    q_ref = np.stack([r[0] for r in refs])
    qd_ref = np.stack([r[1] for r in refs])
    qdd_ref = np.stack([r[2] for r in refs])
    q = np.stack([c.initial_position() for c in conditions])
    qd = np.zeros_like(q)
    if first.initial_state == "reference":
        qd = qd_ref[:, 0].copy()

    log_q, log_qd, log_tau = (np.empty((batch, steps, n)) for _ in range(3))
    log_fb = np.full((batch, steps, n), np.nan)
    finite = np.ones(batch, bool)
    limit = robot.torque_limit_nm
    dist = first.disturbance
    dist_torque = None if dist is None else np.broadcast_to(np.asarray(dist.torque_nm, float), (n,))

    if world is not None:
        world.reset(q, qd)
    q_seen, qd_seen = world.sense(q, qd) if world is not None else (q, qd)
    controller.reset(q_seen.copy())
    commit = getattr(controller, "commit", None)
    with np.errstate(all="ignore"):
        for k in range(steps):
            log_q[:, k], log_qd[:, k] = q, qd
            if k > 0 and world is not None:
                q_seen, qd_seen = world.sense(q, qd)
            elif world is None:
                q_seen, qd_seen = q, qd
            tau = np.asarray(controller(t[k], q_seen, qd_seen, q_ref[:, k], qd_ref[:, k], qdd_ref[:, k]), float)
            tau = np.clip(np.nan_to_num(tau, nan=0.0), -limit, limit)
            if commit is not None:  # the controller learns what was commanded (the runtime's commit)
                commit(tau)
            log_tau[:, k] = tau
            fb = getattr(controller, "last_tau_fb", None)
            if fb is not None:
                log_fb[:, k] = fb
            applied = tau if world is None else _realism_torque(world, plant, tau, q, qd)
            q, qd = _advance(plant, q, qd, applied, t[k], dt, dist, dist_torque)
            bad = ~(np.isfinite(q).all(1) & np.isfinite(qd).all(1))
            if bad.any():  # a diverged run is frozen where it failed and reported, never propagated
                finite &= ~bad
                q[bad], qd[bad] = log_q[bad, k], 0.0
            if progress is not None:
                progress(1)

    traj = Trajectory(
        t_s=t,
        q=log_q,
        qd=log_qd,
        q_ref=q_ref,
        qd_ref=qd_ref,
        tau=log_tau,
        tau_fb=None if np.isnan(log_fb).all() else log_fb,
        condition_names=[c.name for c in conditions],
        disturbance=dist,
    )
    traj.position_ratio = np.max(robot.position_limit_ratio(log_q), axis=(1, 2))
    traj.velocity_ratio = np.max(np.abs(log_qd) / robot.velocity_limit_rad_s, axis=(1, 2))
    traj.finite = finite
    return traj


def _realism_torque(
    world: RealismModel, plant: ModelPlant, tau: np.ndarray, q: np.ndarray, qd: np.ndarray
) -> np.ndarray:
    """The torque the plant feels this period: the drive's output minus the profile's friction."""
    applied = world.actuate(tau, q)
    if world.spec.plant.has_friction:
        inertia = np.diagonal(plant.dynamics.mass_matrix(q), axis1=-2, axis2=-1)
        applied = applied - world.friction_nm(qd, inertia)
    return applied


def _advance(
    plant: ModelPlant,
    q: np.ndarray,
    qd: np.ndarray,
    tau: np.ndarray,
    t0: float,
    dt: float,
    dist: Disturbance | None,
    dist_torque: np.ndarray | None,
) -> tuple[np.ndarray, np.ndarray]:
    """One control period; split at the disturbance pulse's edges so it is integrated exactly."""
    t1 = t0 + dt
    if dist is None or dist.duration_s <= 0 or dist.time_s >= t1 or dist.time_s + dist.duration_s <= t0:
        return plant.integrate(q, qd, tau, dt)
    edges = sorted({t0, t1, min(max(dist.time_s, t0), t1), min(max(dist.time_s + dist.duration_s, t0), t1)})
    for a, b in zip(edges[:-1], edges[1:], strict=False):
        if b - a <= 0:
            continue
        inside = dist.time_s <= a and b <= dist.time_s + dist.duration_s + 1e-15
        q, qd = plant.integrate(q, qd, tau + dist_torque if inside else tau, b - a)
    return q, qd
