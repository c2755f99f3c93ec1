"""H-infinity law (Sec. IV-B): a mixed-sensitivity synthesis per joint, run as a discrete state-space filter.

Synthesis (python-control ``mixsyn``, i.e. hinfsyn on the augmented plant), per joint i:

    nominal plant  P_i(s) = 1 / (m_i (s + delta)^2),  m_i = M^_ii(q = 0) (kg*m^2), delta = 1e-3 rad/s
    minimize gamma such that || [W_s S;  W_u K S;  W_T T] ||_inf < gamma,  S = 1/(1 + P K), T = 1 - S
    W_s = makeweight(10, 1, 0.01),  W_u = makeweight(0.1, 1, 10),  W_T = alpha = 0.2

Readings (docs/feedback_laws.md): alpha = 0.2 "uniform weighting coefficient" is the constant third
weight W_T on the complementary sensitivity (robustness to multiplicative model error). The pure
double integrator has its poles on the imaginary axis, which hinfsyn's rank conditions reject, so
they are moved to -delta (no visible effect above 0.01 rad/s). The controller's very fast pole
(|p| > 0.2 * 2/dt, an artefact of the near-improper optimum, ~1e7 rad/s) is residualized (DC kept)
before the Tustin discretization at period_s, since Tustin would put it at z = -1.

Gravity: the linear design cannot hold gravity (the loop's bandwidth is ~1-10 rad/s; its
low-frequency gain is far below the ~1 N*m gravity torque per rad), so the nominal gravity G^(q)
(one RNEIDA call) is added as feedforward:

    x[k+1] = Ad x[k] + Bd e[k],    tau[k] = sat(G^(q[k]) + Cd x[k] + Dd e[k])

State: x (B, sum of controller orders), the block-diagonal controller state.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.linalg import schur, solve_sylvester
from scipy.signal import cont2discrete

from models.errors import ModelInputError
from models.feedback._common import NominalModel, const
from models.feedback.base import FeedbackLaw, SharedId
from models.robots import RobotModel

PAPER_ALPHA = 0.2
PAPER_WS = (10.0, 1.0, 0.01)  # makeweight(dc gain, crossover rad/s, high-frequency gain)
PAPER_WU = (0.1, 1.0, 10.0)
PLANT_POLE_SHIFT_RAD_S = 1e-3
#: The designed set's unit-plant pole shift (in units of the bandwidth): 0.1 w makes the synthesis give
#: the loop a real static stiffness; 1e-3 leaves slow unstable modes on a coupled arm (docs/feedback_laws.md)
SCALED_POLE_SHIFT = 0.1


def makeweight_coefficients(dc_gain: float, crossover_rad_s: float, hf_gain: float) -> tuple[list[float], list[float]]:
    """MATLAB's first-order makeweight: W(s) = (hf s + a dc) / (s + a) with |W(j crossover)| = 1.

    Needs the crossover magnitude 1 to lie strictly between dc_gain and hf_gain.
    """
    if not (min(dc_gain, hf_gain) < 1.0 < max(dc_gain, hf_gain)) or crossover_rad_s <= 0:
        raise ModelInputError(f"makeweight({dc_gain}, {crossover_rad_s}, {hf_gain}): 1 must lie between the gains")
    pole = crossover_rad_s * np.sqrt((1.0 - hf_gain**2) / (dc_gain**2 - 1.0))
    return [hf_gain, pole * dc_gain], [1.0, pole]


@dataclass(frozen=True)
class JointDesign:
    """One joint's synthesis result: gamma and the discrete controller (Ad, Bd, Cd, Dd)."""

    gamma: float
    inertia_kg_m2: float
    continuous_order: int
    a: np.ndarray
    b: np.ndarray
    c: np.ndarray
    d: np.ndarray


def residualize_fast_modes(
    a: np.ndarray, b: np.ndarray, c: np.ndarray, d: np.ndarray, max_rad_s: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Drop modes faster than max_rad_s, keeping the DC gain (singular perturbation)."""
    t, z, n_slow = schur(a, output="real", sort=lambda re, im: abs(complex(re, im)) <= max_rad_s)
    if n_slow == a.shape[0]:
        return a, b, c, d
    t11, t12, t22 = t[:n_slow, :n_slow], t[:n_slow, n_slow:], t[n_slow:, n_slow:]
    x = solve_sylvester(t11, -t22, -t12)  # block-diagonalize: T11 X - X T22 = -T12
    s = np.eye(a.shape[0])
    s[:n_slow, n_slow:] = x
    s_inv = np.eye(a.shape[0])
    s_inv[:n_slow, n_slow:] = -x
    b_m, c_m = s_inv @ z.T @ b, c @ z @ s
    d_r = d - c_m[:, n_slow:] @ np.linalg.solve(t22, b_m[n_slow:])
    return t11, b_m[:n_slow], c_m[:, :n_slow], d_r


def design_joint(
    inertia_kg_m2: float,
    period_s: float,
    alpha: float = PAPER_ALPHA,
    ws: tuple[float, float, float] = PAPER_WS,
    wu: tuple[float, float, float] = PAPER_WU,
    bandwidth_rad_s: float | None = None,
) -> JointDesign:
    """One joint's synthesis on 1 / (m (s + delta)^2), discretized at period_s.

    With ``bandwidth_rad_s`` = w the synthesis runs on the unit plant (m = 1) with the same weights and
    is scaled to K(s) = m w^2 K~(s / w): the unit design's loop (S, T) moved to crossover w, the effort
    weight W_u read per unit of m w^2, the plant's poles at -SCALED_POLE_SHIFT w (the designed gain set,
    models/feedback/design.py)."""
    if bandwidth_rad_s is None:
        gamma, order, (a, b, c, d) = _synthesize(inertia_kg_m2, alpha, ws, wu)
    else:
        gamma, order, (a, b, c, d) = _synthesize(1.0, alpha, ws, wu, SCALED_POLE_SHIFT)
        w, gain = float(bandwidth_rad_s), float(inertia_kg_m2) * float(bandwidth_rad_s) ** 2
        a, b, c, d = w * a, w * b, gain * c, gain * d
    a, b, c, d = residualize_fast_modes(a, b, c, d, max_rad_s=0.2 * 2.0 / period_s)
    ad, bd, cd, dd, _ = cont2discrete((a, b, c, d), period_s, method="bilinear")
    return JointDesign(gamma, float(inertia_kg_m2), order, ad, bd, cd, dd)


def _synthesize(
    inertia_kg_m2: float,
    alpha: float,
    ws: tuple[float, float, float],
    wu: tuple[float, float, float],
    delta: float = PLANT_POLE_SHIFT_RAD_S,
) -> tuple[float, int, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]:
    """mixsyn on the joint's plant 1 / (m (s + delta)^2): (gamma, controller order, continuous (A, B, C, D))."""
    import control as ct

    plant = ct.tf([1.0], [inertia_kg_m2, 2 * inertia_kg_m2 * delta, inertia_kg_m2 * delta**2])
    weights = [ct.tf(*makeweight_coefficients(*ws)), ct.tf(*makeweight_coefficients(*wu)), ct.tf([alpha], [1.0])]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)  # python-control's internal connect() deprecation
        try:
            controller, _, info = ct.mixsyn(plant, *weights)
        except Exception as exc:  # slycot raises its own arithmetic errors
            raise ModelInputError(
                f"law 'hinf': mixsyn failed for inertia {inertia_kg_m2:.3g}: {exc}".splitlines()[0]
            ) from exc
        closed_loop = ct.feedback(
            ct.ss(plant) * ct.ss(controller), 1
        )  # state space: tf products lose the cancellations
    if np.any(np.real(closed_loop.poles()) >= 0):
        raise ModelInputError(f"law 'hinf': synthesized loop unstable for inertia {inertia_kg_m2:.3g}")
    k = ct.ss(controller)
    return float(info[0]), int(k.nstates), (np.asarray(k.A), np.asarray(k.B), np.asarray(k.C), np.asarray(k.D))


class HinfLaw(FeedbackLaw):
    name = "hinf"

    def __init__(
        self,
        robot: RobotModel,
        period_s: float,
        alpha: np.ndarray | float = PAPER_ALPHA,
        gravity_compensation: bool = True,
        nominal_inertia_kg_m2: np.ndarray | None = None,
        bandwidth_rad_s: np.ndarray | None = None,
    ) -> None:
        """``nominal_inertia_kg_m2`` (default diag M^(q = 0)) and ``bandwidth_rad_s`` (default: the paper's
        weights as they are, on the physical plant) per joint: see ``design_joint``."""
        super().__init__(robot.n_joints, period_s, robot.torque_limit_nm)
        n = robot.n_joints
        self.alpha = np.broadcast_to(np.asarray(alpha, float), (n,)).copy()
        self.gravity_compensation = gravity_compensation
        self.nominal = NominalModel(robot)
        inertia = (
            self.nominal.mass_matrix_diagonal(np.zeros(n))
            if nominal_inertia_kg_m2 is None
            else np.broadcast_to(np.asarray(nominal_inertia_kg_m2, float), (n,))
        )
        bandwidth = [None] * n if bandwidth_rad_s is None else np.broadcast_to(np.asarray(bandwidth_rad_s, float), (n,))
        if np.any(inertia <= 0) or (bandwidth_rad_s is not None and not np.all(np.asarray(bandwidth, float) > 0)):
            raise ModelInputError("law 'hinf': nominal inertias and bandwidths must be positive")
        self.bandwidth_rad_s = None if bandwidth_rad_s is None else np.asarray(bandwidth, float)
        self.designs = [
            design_joint(m, self.period_s, a, bandwidth_rad_s=None if w is None else float(w))
            for m, a, w in zip(inertia, self.alpha, bandwidth, strict=True)
        ]
        orders = [j.a.shape[0] for j in self.designs]
        nx, n = sum(orders), robot.n_joints
        self.ad, self.bd, self.cd, self.dd = np.zeros((nx, nx)), np.zeros((nx, n)), np.zeros((n, nx)), np.zeros((n, n))
        start = 0
        for i, (design, order) in enumerate(zip(self.designs, orders, strict=True)):
            block = slice(start, start + order)
            self.ad[block, block], self.bd[block, i], self.cd[i, block] = design.a, design.b[:, 0], design.c[0]
            self.dd[i, i] = design.d[0, 0]
            start += order
        # torch path: [q, q_d, x] @ it = [C x + D e, A x + B e] (one ONNX MatMul for six nodes:
        # onnxruntime spends ~0.3 us per node, docs/lmpc.md t_L); numpy keeps the equations as written
        out = np.concatenate([np.concatenate([self.dd.T, self.bd.T], 1), np.concatenate([self.cd.T, self.ad.T], 1)])
        self.step_matrix = np.concatenate([-out[:n], out])

    @property
    def gammas(self) -> list[float]:
        """The achieved H-infinity norm of the weighted mixed-sensitivity problem, per joint."""
        return [j.gamma for j in self.designs]

    @property
    def state_size(self) -> int:
        return self.ad.shape[0]

    @property
    def params(self) -> dict[str, Any]:
        return {
            "alpha_wt": self.alpha.tolist(),
            "ws": list(PAPER_WS),
            "wu": list(PAPER_WU),
            "gamma": self.gammas,
            "nominal_inertia_kg_m2": [j.inertia_kg_m2 for j in self.designs],
            **({} if self.bandwidth_rad_s is None else {"bandwidth_rad_s": self.bandwidth_rad_s.tolist()}),
            "plant_pole_shift_rad_s": PLANT_POLE_SHIFT_RAD_S,
            "discretization": "tustin",
            "gravity_compensation": self.gravity_compensation,
        }

    def step(self, xp: Any, state: Any, q: Any, qd: Any, q_d: Any, qd_d: Any, qdd_d: Any) -> tuple[Any, Any]:
        tau, nxt, _ = self.step_sharing_id(xp, state, q, qd, q_d, qd_d, qdd_d, None)
        return tau, nxt

    def step_sharing_id(
        self, xp: Any, state: Any, q: Any, qd: Any, q_d: Any, qd_d: Any, qdd_d: Any, shared: SharedId | None
    ) -> tuple[Any, Any, Any]:
        if xp is not np:  # traced for the ONNX graph
            mapped = xp.concatenate([q, q_d, state], -1) @ const(xp, self.step_matrix)
            tau, nxt = xp.split(mapped, [self.n_joints, self.state_size], 1)
            shared_tau = None
            if self.gravity_compensation:
                gravity, shared_tau = self.nominal.gravity_sharing(q, shared)
                tau = tau + gravity
            return self.saturate(xp, tau), nxt, shared_tau
        ad_t, bd_t, cd_t, dd_t = (const(xp, m.T.copy()) for m in (self.ad, self.bd, self.cd, self.dd))
        e = q_d - q
        tau = state @ cd_t + e @ dd_t
        if self.gravity_compensation:
            tau = tau + self.nominal.gravity(xp, q)
        return self.saturate(xp, tau), state @ ad_t + e @ bd_t, None
