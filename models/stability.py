"""Theorem 1 (Sec. III-B, Eqs. 19-21) as a tool: do a law's sufficient stability conditions hold?

Along a trajectory (q, qd, q_d, qd_d, qdd_d over time, and the law's state) the conditions are

    (19)  l_de  >  beta lmax(M) + |C| + eps
    (20)  l_e   >  |dG/dq| + (|P| + beta |C|) / beta + eps
    (21)  |beta dphi/de - P|  <  (2/beta) [l_de - beta lmax(M) - |C|] [beta l_de - beta^2 |dG/dq|]

with l_e = lmin(dphi/de), l_de = lmin(dphi/de_dot). Readings (docs/feedback_laws.md):
- dphi/de and dphi/de_dot are the Jacobians of the law's torque output (one step, state held) with
  respect to e = q_d - q and e_dot = qd_d - qd at fixed reference, by torch autograd of ``law.step``;
  lmin is taken of their symmetric part (the quadratic form that enters V_dot).
- |.| is the induced 2-norm; "max" is the worst case over the trajectory: every lmin is the minimum
  over time, every norm and lmax(M) the maximum over time (conservative, one margin per condition).
- M is the mass matrix (crba), C the Coriolis matrix (pinocchio computeCoriolisMatrix, the
  Christoffel one with M_dot - 2C skew), dG/dq from computeGeneralizedGravityDerivatives.
Margins are lhs - rhs for (19), (20) and rhs - lhs for (21): positive means the condition holds.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from models.dynamics.backends import build_pinocchio_model
from models.errors import ModelInputError
from models.feedback.base import FeedbackLaw
from models.robots import RobotModel

PAPER_P = np.diag([25.0, 150.0, 65.0, 25.0, 2.0, 1.0])
PAPER_BETA = 1e-6
DEFAULT_EPSILON = 1e-3


@dataclass
class Theorem1Report:
    """Per-condition margins (positive: holds) and the worst-case terms they were built from."""

    law: str
    margins: dict[str, float]
    holds: dict[str, bool]
    terms: dict[str, float]
    samples: int
    notes: list[str] = field(default_factory=list)

    @property
    def all_hold(self) -> bool:
        return all(self.holds.values())

    def as_dict(self) -> dict[str, Any]:
        return {
            "law": self.law,
            "margins": self.margins,
            "holds": self.holds,
            "terms": self.terms,
            "samples": self.samples,
            "all_hold": self.all_hold,
        }


def law_jacobians(
    law: FeedbackLaw,
    states: np.ndarray,
    q: np.ndarray,
    qd: np.ndarray,
    q_d: np.ndarray,
    qd_d: np.ndarray,
    qdd_d: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """d tau / d e and d tau / d e_dot (T, N, N) of one law step, by torch autograd (batched over T)."""
    import torch

    as_t = lambda a: torch.as_tensor(np.asarray(a, float), dtype=torch.float64)  # noqa: E731
    q_d_t, qd_d_t, qdd_d_t, state_t = as_t(q_d), as_t(qd_d), as_t(qdd_d), as_t(states)
    e = (q_d_t - as_t(q)).requires_grad_(True)
    e_dot = (qd_d_t - as_t(qd)).requires_grad_(True)
    tau, _ = law.step(torch, state_t, q_d_t - e, qd_d_t - e_dot, q_d_t, qd_d_t, qdd_d_t)
    n = law.n_joints
    d_e, d_edot = np.zeros((len(q), n, n)), np.zeros((len(q), n, n))
    for i in range(n):  # rows are independent across the batch, so d(sum_b tau[b, i]) gives row i for all b
        g_e, g_edot = torch.autograd.grad(tau[:, i].sum(), (e, e_dot), retain_graph=True, allow_unused=True)
        d_e[:, i] = 0.0 if g_e is None else g_e.numpy()
        d_edot[:, i] = 0.0 if g_edot is None else g_edot.numpy()
    return d_e, d_edot


def roll_states(
    law: FeedbackLaw, q: np.ndarray, qd: np.ndarray, q_d: np.ndarray, qd_d: np.ndarray, qdd_d: np.ndarray
) -> np.ndarray:
    """The law's state before each sample (T, S), stepping the law along the given signals."""
    state = law.initial_state(q[:1])
    states = np.zeros((len(q), law.state_size))
    for k in range(len(q)):
        states[k] = state[0]
        _, state = law.step(np, state, q[k : k + 1], qd[k : k + 1], q_d[k : k + 1], qd_d[k : k + 1], qdd_d[k : k + 1])
    return states


def model_terms(robot: RobotModel, q: np.ndarray, qd: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """M (T, N, N), C (T, N, N) and dG/dq (T, N, N) along the trajectory (pinocchio)."""
    import pinocchio as pin

    model = build_pinocchio_model(robot)
    data = model.createData()
    t, n = q.shape
    mass, coriolis, d_gravity = (np.zeros((t, n, n)) for _ in range(3))
    for k in range(t):
        m = pin.crba(model, data, q[k])
        mass[k] = np.triu(m) + np.triu(m, 1).T
        coriolis[k] = pin.computeCoriolisMatrix(model, data, q[k], qd[k])
        d_gravity[k] = pin.computeGeneralizedGravityDerivatives(model, data, q[k])
    return mass, coriolis, d_gravity


def _sym_min_eig(matrices: np.ndarray) -> np.ndarray:
    return np.linalg.eigvalsh(0.5 * (matrices + np.swapaxes(matrices, -1, -2)))[..., 0]


def evaluate_theorem1(
    law: FeedbackLaw,
    robot: RobotModel,
    q: np.ndarray,
    qd: np.ndarray,
    q_d: np.ndarray,
    qd_d: np.ndarray,
    qdd_d: np.ndarray,
    states: np.ndarray | None = None,
    p_matrix: np.ndarray = PAPER_P,
    beta: float = PAPER_BETA,
    epsilon: float = DEFAULT_EPSILON,
) -> Theorem1Report:
    """Evaluate Eqs. 19-21 for ``law`` along a trajectory of T samples (arrays (T, N)).

    ``states`` (T, S): the law's state at each sample; None rolls the law along the signals from
    its initial state.
    """
    arrays = [np.atleast_2d(np.asarray(a, float)) for a in (q, qd, q_d, qd_d, qdd_d)]
    n = law.n_joints
    if any(a.shape != arrays[0].shape or a.shape[1] != n for a in arrays):
        raise ModelInputError(f"stability: q, qd, q_d, qd_d, qdd_d must all be (T, {n}) arrays")
    if not all(np.all(np.isfinite(a)) for a in arrays):
        raise ModelInputError("stability: trajectory arrays contain NaN or inf")
    p_matrix = np.asarray(p_matrix, float)
    if p_matrix.shape != (n, n):
        raise ModelInputError(f"stability: P must be {n}x{n}, got {p_matrix.shape}")
    if not (beta > 0 and epsilon >= 0):
        raise ModelInputError(f"stability: need beta > 0 and epsilon >= 0, got beta={beta}, epsilon={epsilon}")
    q, qd, q_d, qd_d, qdd_d = arrays
    if states is None:
        states = roll_states(law, q, qd, q_d, qd_d, qdd_d)
    d_e, d_edot = law_jacobians(law, np.atleast_2d(states), q, qd, q_d, qd_d, qdd_d)
    mass, coriolis, d_gravity = model_terms(robot, q, qd)

    l_e = float(_sym_min_eig(d_e).min())
    l_edot = float(_sym_min_eig(d_edot).min())
    m_max = float(np.linalg.eigvalsh(mass)[:, -1].max())
    c_max = float(np.linalg.norm(coriolis, 2, axis=(1, 2)).max())
    g_max = float(np.linalg.norm(d_gravity, 2, axis=(1, 2)).max())
    p_norm = float(np.linalg.norm(p_matrix, 2))
    lhs3 = float(np.linalg.norm(beta * d_e - p_matrix, 2, axis=(1, 2)).max())
    damping_bracket = l_edot - beta * m_max - c_max
    rhs3 = (2.0 / beta) * damping_bracket * (beta * l_edot - beta**2 * g_max)
    margins = {
        "eq19": damping_bracket - epsilon,
        "eq20": l_e - g_max - (p_norm + beta * c_max) / beta - epsilon,
        "eq21": rhs3 - lhs3,
    }
    notes = []
    if damping_bracket < 0 and rhs3 > lhs3:
        notes.append("eq21 holds only because both of its brackets are negative (eq19 fails)")
    terms = {
        "lmin_dphi_de": l_e,
        "lmin_dphi_dedot": l_edot,
        "lmax_M": m_max,
        "C_max": c_max,
        "dGdq_max": g_max,
        "P_norm": p_norm,
        "eq21_lhs": lhs3,
        "eq21_rhs": rhs3,
        "beta": beta,
        "epsilon": epsilon,
    }
    return Theorem1Report(law.name, margins, {k: bool(v > 0) for k, v in margins.items()}, terms, len(q), notes)
