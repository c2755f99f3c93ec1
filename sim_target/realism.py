"""One model of the real world an arm lives in, applied by both plants (docs/realism.md).

``models.sim`` (the pinocchio/RNE simulator) and ``sim_target`` (the pybullet target behind emulated
drives) call the same three steps once per control period, in this order, so the simulation twin and
the HIL see the same world:

1. :meth:`RealismModel.sense` (true q, qd) -> what the drives report: encoder noise, quantization to
   ``encoder_counts_per_rev``, velocity by finite difference of the quantized position (optionally a
   first-order filter), the whole delayed by ``delay_periods``.
2. :meth:`RealismModel.actuate` (commanded torque, true q) -> the torque the motor puts on the joint,
   held over the period: dead band, per-mille quantization of the rated torque (0x6071 is INTEGER16
   per mille of 0x6076), the torque loop's first-order lag (its exact mean over the period), ripple.
3. :meth:`RealismModel.friction_nm` (true qd, inertia) -> viscous + Coulomb + Stribeck friction,
   held over the period like the motor torque, never larger than what stops the joint in one period.

numpy only (ARCHITECTURE.md: ``models`` may import ``sim_target``, never the reverse); the profile
files and their validation are in ``sim_target/realism_profiles.py``. Noise is drawn once per period
for all rows of a batch (common random numbers: every law of a batch sees the same noise), from one
seeded generator reset by :meth:`RealismModel.reset`, so the same seed gives the same world in both
plants. Arrays are (..., N): one row per run of a batch, one column per joint.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


class RealismError(ValueError):
    """A realism profile that cannot be applied; printed as one line (exit code 2)."""

    exit_code = 2


@dataclass(frozen=True)
class Sensing:
    """What the drives report. Per-joint values are (N,) arrays; 0 turns an effect off."""

    encoder_counts_per_rev: np.ndarray  # (N,) joint-side increments per revolution (0x608F); 0: exact
    encoder_noise_rad: np.ndarray  # (N,) standard deviation, added before quantization
    velocity_from_difference: bool  # True: (q_k - q_{k-1}) / period of the quantized q; False: true qd
    velocity_filter_cutoff_hz: float  # first-order low-pass on the reported velocity; 0: none
    velocity_noise_rad_s: np.ndarray  # (N,) standard deviation added to the reported velocity
    delay_periods: int  # measurement delay in whole control periods


@dataclass(frozen=True)
class Actuation:
    """What the drive's torque loop makes of the command."""

    torque_bandwidth_hz: float  # first-order lag cut-off; 0: ideal (no lag)
    torque_quantum_nm: np.ndarray  # (N,) 1 per mille of the rated torque; 0: exact
    torque_ripple_ratio: np.ndarray  # (N,) amplitude as a fraction of the torque
    torque_ripple_cycles_per_rev: np.ndarray  # (N,) ripple periods per joint revolution
    torque_dead_band_nm: np.ndarray  # (N,) |command| below this gives no torque


@dataclass(frozen=True)
class PlantErrors:
    """How the plant differs from the controllers' model (the conditions' ``mismatch`` fields, plus
    friction with a Stribeck term)."""

    viscous_friction_nm_s_per_rad: np.ndarray  # (N,)
    coulomb_friction_nm: np.ndarray  # (N,)
    stribeck_friction_nm: np.ndarray  # (N,) static minus Coulomb friction, decays with velocity
    stribeck_velocity_rad_s: np.ndarray  # (N,)
    friction_smoothing_velocity_rad_s: float  # tanh(qd / v) for sign(qd), so friction is continuous
    payload_kg: float = 0.0
    payload_com_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # in the flange frame
    payload_inertia_kg_m2: tuple[float, float, float] = (0.0, 0.0, 0.0)  # principal moments at its CoM
    mass_scale: np.ndarray = field(default_factory=lambda: np.ones(1))  # per link (or one for all)
    inertia_scale: np.ndarray = field(default_factory=lambda: np.ones(1))  # per link (or one for all)

    @property
    def has_friction(self) -> bool:
        return bool(
            np.any(self.viscous_friction_nm_s_per_rad)
            or np.any(self.coulomb_friction_nm)
            or np.any(self.stribeck_friction_nm)
        )

    @property
    def has_inertial_errors(self) -> bool:
        return bool(self.payload_kg or np.any(self.mass_scale != 1.0) or np.any(self.inertia_scale != 1.0))


@dataclass(frozen=True)
class RealismSpec:
    """A validated profile bound to one arm (joint count) and control period."""

    name: str
    period_s: float
    sensing: Sensing
    actuation: Actuation
    plant: PlantErrors
    seed: int = 0

    @property
    def n_joints(self) -> int:
        return int(self.sensing.encoder_noise_rad.shape[0])

    def measurement_noise(self) -> tuple[float, float | None]:
        """(encoder noise, velocity noise) RMS, the worst joint's, as the runtime config states them
        (``bundle.encoder_noise_rad`` / ``velocity_noise_rad_s``): the encoder's jitter and its quantization
        (step / sqrt(12)) together; the velocity's noise when the drive reports a measured one, None when it
        differences the position (the runtime's own rule then applies)."""
        s = self.sensing
        counts = np.asarray(s.encoder_counts_per_rev, float)
        quantum = np.where(counts > 0, 2.0 * np.pi / np.where(counts > 0, counts, 1.0), 0.0)
        encoder = float(np.max(np.sqrt(np.asarray(s.encoder_noise_rad, float) ** 2 + quantum**2 / 12.0)))
        velocity = None if s.velocity_from_difference else float(np.max(s.velocity_noise_rad_s))
        return encoder, velocity

    @property
    def is_ideal(self) -> bool:
        """Today's world: the plant reports its true state and applies the command exactly."""
        s, a = self.sensing, self.actuation
        return bool(
            not np.any(s.encoder_counts_per_rev)
            and not np.any(s.encoder_noise_rad)
            and not s.velocity_from_difference
            and not s.velocity_filter_cutoff_hz
            and not np.any(s.velocity_noise_rad_s)
            and s.delay_periods == 0
            and not a.torque_bandwidth_hz
            and not np.any(a.torque_quantum_nm)
            and not np.any(a.torque_ripple_ratio)
            and not np.any(a.torque_dead_band_nm)
            and not self.plant.has_friction
            and not self.plant.has_inertial_errors
        )


# --- the pure pieces (closed forms in tests/unit/sim_target/test_realism.py) ------------------------


def quantize(value: np.ndarray, step: np.ndarray) -> np.ndarray:
    """``value`` rounded to the nearest multiple of ``step``; a zero step leaves it exact."""
    step = np.asarray(step, dtype=float)
    safe = np.where(step > 0.0, step, 1.0)
    return np.where(step > 0.0, np.rint(value / safe) * safe, value)


def encoder_step_rad(counts_per_rev: np.ndarray) -> np.ndarray:
    """One encoder increment in radians (0 where the encoder is exact)."""
    counts = np.asarray(counts_per_rev, dtype=float)
    return np.where(counts > 0.0, 2.0 * math.pi / np.where(counts > 0.0, counts, 1.0), 0.0)


def lag_factor(bandwidth_hz: float, period_s: float) -> float:
    """a = exp(-2 pi f T): the part of the previous torque left after one period of a first-order lag."""
    return math.exp(-2.0 * math.pi * bandwidth_hz * period_s) if bandwidth_hz > 0.0 else 0.0


def lag_period(
    previous_end_nm: np.ndarray, command_nm: np.ndarray, bandwidth_hz: float, period_s: float
) -> tuple[np.ndarray, np.ndarray]:
    """One period of a first-order lag driven by a held command: (mean over the period, end value).

    The mean is what a plant holding one torque over the period must apply for the same impulse as
    the continuous lag: u + (x0 - u)(1 - a)/(w T), the end value u + (x0 - u) a, with w = 2 pi f.
    """
    if bandwidth_hz <= 0.0:
        return command_nm, command_nm
    w_t = 2.0 * math.pi * bandwidth_hz * period_s
    a = math.exp(-w_t)
    gap = previous_end_nm - command_nm
    return command_nm + gap * ((1.0 - a) / w_t), command_nm + gap * a


def friction_nm(qd_rad_s: np.ndarray, plant: PlantErrors) -> np.ndarray:
    """Viscous + (Coulomb + Stribeck exp(-(qd/v_s)^2)) tanh(qd / v_smooth): the torque opposing motion."""
    v_s = np.where(plant.stribeck_velocity_rad_s > 0.0, plant.stribeck_velocity_rad_s, 1.0)
    level = plant.coulomb_friction_nm + plant.stribeck_friction_nm * np.exp(-((qd_rad_s / v_s) ** 2))
    sign = np.tanh(qd_rad_s / plant.friction_smoothing_velocity_rad_s)
    return plant.viscous_friction_nm_s_per_rad * qd_rad_s + level * sign


class RealismModel:
    """The stateful per-period model of one batch of runs (``rows`` runs of N joints).

    Call :meth:`reset` at the start of every run, then per period :meth:`sense` once (at the start
    of the period) and :meth:`actuate` / :meth:`friction_nm` once (the torque held over it).
    """

    def __init__(self, spec: RealismSpec) -> None:
        self.spec = spec
        self._step_rad = encoder_step_rad(spec.sensing.encoder_counts_per_rev)
        cutoff = spec.sensing.velocity_filter_cutoff_hz
        self._filter_alpha = 1.0 - math.exp(-2.0 * math.pi * cutoff * spec.period_s) if cutoff > 0.0 else 1.0
        self._rng = np.random.default_rng(spec.seed)
        self._q_prev: np.ndarray | None = None
        self._qd_filtered: np.ndarray | None = None
        self._torque_end_nm: np.ndarray | None = None
        self._delay: list[tuple[np.ndarray, np.ndarray]] = []

    @property
    def is_ideal(self) -> bool:
        return self.spec.is_ideal

    def reset(self, q_rad: np.ndarray, qd_rad_s: np.ndarray, torque_nm: np.ndarray | None = None) -> None:
        """Start a run at the true state (q, qd): the generator reseeded, the filter and the delay
        line filled as if the arm had been there for ever (the delay line holds its first reading)."""
        self._rng = np.random.default_rng(self.spec.seed)
        q = np.asarray(q_rad, dtype=float)
        qd = np.asarray(qd_rad_s, dtype=float)
        # The position one period ago, as the drive's differencing would have seen it.
        self._q_prev = quantize(q - qd * self.spec.period_s, self._step_rad)
        self._qd_filtered = None
        self._torque_end_nm = np.zeros_like(q) if torque_nm is None else np.asarray(torque_nm, dtype=float).copy()
        self._delay = []

    def sense(self, q_rad: np.ndarray, qd_rad_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The (q, qd) the drives report this period, from the true state at its start."""
        spec = self.spec.sensing
        q = np.asarray(q_rad, dtype=float)
        qd = np.asarray(qd_rad_s, dtype=float)
        if self._q_prev is None:
            self.reset(q, qd)
        n = q.shape[-1]
        noise_q = self._rng.standard_normal(n) * spec.encoder_noise_rad  # one draw per period, all rows
        q_meas = quantize(q + noise_q, self._step_rad)
        if spec.velocity_from_difference:
            qd_meas = (q_meas - self._q_prev) / self.spec.period_s
        else:
            qd_meas = qd.copy()
        noise_v = self._rng.standard_normal(n) * spec.velocity_noise_rad_s
        qd_meas = qd_meas + noise_v
        self._q_prev = q_meas
        if self._qd_filtered is None or self._filter_alpha >= 1.0:
            self._qd_filtered = qd_meas
        else:
            self._qd_filtered = self._qd_filtered + self._filter_alpha * (qd_meas - self._qd_filtered)
        reading = (q_meas, self._qd_filtered)
        if spec.delay_periods == 0:
            return reading
        if not self._delay:
            self._delay = [reading] * spec.delay_periods
        self._delay.append(reading)
        return self._delay.pop(0)

    def actuate(self, command_nm: np.ndarray, q_rad: np.ndarray) -> np.ndarray:
        """The torque the drive applies over this period for ``command_nm`` (already clipped to the
        limits): dead band, per-mille quantization, torque-loop lag (period mean), ripple."""
        spec = self.spec.actuation
        tau = np.asarray(command_nm, dtype=float)
        tau = np.where(np.abs(tau) < spec.torque_dead_band_nm, 0.0, tau)
        tau = quantize(tau, spec.torque_quantum_nm)
        if self._torque_end_nm is None or self._torque_end_nm.shape != tau.shape:
            self._torque_end_nm = np.zeros_like(tau)
        mean, self._torque_end_nm = lag_period(self._torque_end_nm, tau, spec.torque_bandwidth_hz, self.spec.period_s)
        if np.any(spec.torque_ripple_ratio):
            mean = mean * (1.0 + spec.torque_ripple_ratio * np.sin(spec.torque_ripple_cycles_per_rev * q_rad))
        return mean

    def friction_nm(self, qd_rad_s: np.ndarray, inertia_kg_m2: np.ndarray) -> np.ndarray:
        """Friction held over this period, from the velocity at its start. ``inertia_kg_m2``: the
        joint-space mass matrix's diagonal; friction never exceeds the torque that would stop the
        joint within the period (held friction larger than that would reverse it: a limit cycle of
        the integration, not of the arm)."""
        plant = self.spec.plant
        if not plant.has_friction:
            return np.zeros_like(np.asarray(qd_rad_s, dtype=float))
        tau = friction_nm(qd_rad_s, plant)
        stop_nm = np.abs(inertia_kg_m2 * qd_rad_s) / self.spec.period_s
        return np.clip(tau, -stop_nm, stop_nm)


__all__ = [
    "Actuation",
    "PlantErrors",
    "RealismError",
    "RealismModel",
    "RealismSpec",
    "Sensing",
    "encoder_step_rad",
    "friction_nm",
    "lag_factor",
    "lag_period",
    "quantize",
]
