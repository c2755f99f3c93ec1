"""The RNEIDA (paper Alg. 2) in torch, written for a small ONNX graph: the one torch-traceable RNE.

Same equations as ``models.dynamics.rne.rneida`` in spatial-vector form (Featherstone's notation,
frame origins, motion m = [w; v], force f = [n; f]):

    v_i = X_i v_p + S_i qd_i
    a_i = X_i a_p + S_i qdd_i + crm(v_i) S_i qd_i          a_base = [0; -g] (gravity as a base acceleration)
    f_i = I_i a_i + crf(v_i) I_i v_i                       I_i: spatial inertia at the frame origin
    F_i = f_i + X_{i+1}^T F_{i+1},   tau_i = S_i^T F_i

written so that onnxruntime runs few, larger nodes (its per-node cost dominates small graphs):

- X_i(q_i) is affine in (sin q_i, 1 - cos q_i) (Rodrigues): all joints' transforms are three
  constant tensors combined once for the whole chain.
- The forward pass carries the row W = [v, a, 1] (13 entries): one link is one 13 x 13 product
  W_i = W_p N_i, where N_i holds X_i, the S_i qd_i, S_i qdd_i terms and crm(v_i) S_i qd_i (all
  built for every link at once before the recursion). The backward pass likewise carries
  [F, 1] through 7 x 7 products.
- f_i is a fixed quadratic form of W_i (its last entry is 1, so the linear part I_i a_i is
  quadratic too): one outer product and one matmul for every link at once.

About 65 ONNX nodes for a 6-joint arm (the component-wise version: ~1,700; the compact one it
replaces, models.lmpc.compact_rne before this change: 408 for gravity, 860 for full ID).
Checked against ``rneida`` (tests/unit/lmpc/test_structured.py) to 1e-12.
"""

from __future__ import annotations

import numpy as np
import torch

from models.robots import RobotModel


def _skew(v: np.ndarray) -> np.ndarray:
    """skew(v) @ w = v x w."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _crm(m: np.ndarray) -> np.ndarray:
    out = np.zeros((6, 6))
    out[:3, :3] = out[3:, 3:] = _skew(m[:3])
    out[3:, :3] = _skew(m[3:])
    return out


def _crf(m: np.ndarray) -> np.ndarray:
    return -_crm(m).T


def _t(a: np.ndarray) -> torch.Tensor:
    return torch.as_tensor(np.ascontiguousarray(a, dtype=np.float64))


class SpatialRne:
    """tau = ID(q, qd, qdd) for batches (B, N) of torch tensors (float64), gravity optional."""

    def __init__(self, robot: RobotModel) -> None:
        n = robot.n_joints
        self.n = n
        axis = np.asarray(robot.joint_axis, float)
        r0 = np.asarray(robot.joint_rotation, float)
        p = np.asarray(robot.joint_translation, float)

        # R_i(q) = R0 + sin(q) R0 K + (1 - cos q) R0 K^2 (K = skew(axis)); the motion transform parent -> i
        # is X = [[R^T, 0], [-R^T skew(p), R^T]], affine in R, so X^T (what a row multiplies) is
        # XT0 + sin(q) XT1 + (1 - cos q) XT2.
        def xt(rot: np.ndarray, p_i: np.ndarray) -> np.ndarray:
            x = np.zeros((6, 6))
            x[:3, :3] = x[3:, 3:] = rot.T
            x[3:, :3] = -rot.T @ _skew(p_i)
            return x.T

        parts = np.zeros((3, n, 6, 6))
        for i in range(n):
            k = _skew(axis[i])
            for j, rot in enumerate((r0[i], r0[i] @ k, r0[i] @ k @ k)):
                parts[j, i] = xt(rot, p[i])

        # the forward map on W = [v (6), a (6), 1]: blockdiag(XT, XT, 1) (the constant 1 is added below)
        def forward_block(m6: np.ndarray) -> np.ndarray:
            out = np.zeros(m6.shape[:-2] + (13, 13))
            out[..., :6, :6] = m6
            out[..., 6:12, 6:12] = m6
            return out

        self.d0, self.d1, self.d2 = (_t(forward_block(parts[j])) for j in range(3))
        self.d0 = self.d0.clone()
        self.d0[:, 12, 12] = 1.0
        self.x0, self.x1, self.x2 = (_t(np.swapaxes(parts[j], -1, -2)) for j in range(3))  # X (rows: f @ X = (X^T f)^T)
        s = np.zeros((n, 6))
        s[:, :3] = axis
        # G_i(qd_i): after the transform, v += S qd, a += S qdd + qd (v @ crf(S)) (row form of crm(v) S qd).
        # G = I + qd * Gv + [qd S | qdd S] in the last row: W_i = W_p XT-block G.
        gv = np.zeros((n, 13, 13))
        gq = np.zeros((n, 13, 13))
        gqq = np.zeros((n, 13, 13))
        for i in range(n):
            gv[i, :6, 6:12] = _crf(s[i])  # row v @ crf(S) = (crm(v) S)^T ... = (-crm(S) v)^T
            gq[i, 12, :6] = s[i]
            gqq[i, 12, 6:12] = s[i]
        self.g_qd = _t(gv + gq)
        self.g_qdd = _t(gqq)
        self.eye13 = _t(np.eye(13))
        # f_i = I_i a_i + crf(v_i) I_i v_i as sum_jk W_j W_k T_i[j, k] (W_12 = 1)
        m = np.asarray(robot.mass_kg, float)
        c = np.asarray(robot.com_m, float)
        ic = np.asarray(robot.inertia_kg_m2, float)
        quad = np.zeros((n, 13, 13, 6))
        for i in range(n):
            cs = _skew(c[i])
            inertia = np.zeros((6, 6))
            inertia[:3, :3] = ic[i] + m[i] * cs @ cs.T
            inertia[:3, 3:] = m[i] * cs
            inertia[3:, :3] = m[i] * cs.T
            inertia[3:, 3:] = m[i] * np.eye(3)
            quad[i, 6:12, 12, :] = inertia.T  # row a @ I^T
            for a in range(6):
                for b in range(6):
                    e_a, e_b = np.eye(6)[a], np.eye(6)[b]
                    quad[i, a, b, :] = _crf(e_a) @ inertia @ e_b
        self.quad = _t(quad.reshape(n, 169, 6))
        self.gravity = _t(np.asarray(robot.gravity_m_s2, float))
        base = np.zeros((1, 13))
        base[0, 9:12] = -np.asarray(robot.gravity_m_s2, float)
        base[0, 12] = 1.0
        self.base_gravity = _t(base)
        base0 = np.zeros((1, 13))
        base0[0, 12] = 1.0
        self.base_free = _t(base0)
        # tau_i = S_i . F_i on the row [F (6), 1]
        s7 = np.zeros((n, 7))
        s7[:, :6] = s
        self.s7 = _t(s7)
        top = np.zeros((7, 6))
        top[:6] = np.eye(6)
        self.place_top = _t(top)  # (7, 6): X into rows 0..5
        self.place_right = _t(top.T)  # (6, 7): into columns 0..5
        last = np.zeros((7, 1))
        last[6, 0] = 1.0
        self.last_col = _t(last)  # (7, 1) @ (1, 7): a row into the last row
        corner = np.zeros((7, 7))
        corner[6, 6] = 1.0
        self.corner = _t(corner)
        self.corner_row = _t(corner[6:7])

    def inverse_dynamics(
        self, q: torch.Tensor, qd: torch.Tensor, qdd: torch.Tensor, gravity: bool = True
    ) -> torch.Tensor:
        """M(q) qdd + C(q, qd) qd (+ G(q)), (B, N). Reshapes use constant shapes (no Shape nodes)."""
        n = self.n
        sin = torch.sin(q).reshape(-1, n, 1, 1)
        vers = (1.0 - torch.cos(q)).reshape(-1, n, 1, 1)
        d = self.d0 + sin * self.d1 + vers * self.d2  # (B, N, 13, 13)
        g = self.eye13 + qd.reshape(-1, n, 1, 1) * self.g_qd + qdd.reshape(-1, n, 1, 1) * self.g_qdd
        step = d @ g  # W_i = W_p @ step_i
        w = (self.base_gravity if gravity else self.base_free).reshape(1, 1, 13)
        rows = []
        for i in range(n):
            w = w @ step[:, i]
            rows.append(w)
        w_all = torch.cat(rows, 1)  # (B, N, 13)
        outer = (w_all.reshape(-1, n, 13, 1) * w_all.reshape(-1, n, 1, 13)).reshape(-1, n, 1, 169)
        f = outer @ self.quad  # (B, N, 1, 6)
        # backward: [F_i, 1] = [F_{i+1}, 1] @ [[X_{i+1}, 0], [f_i, 1]], the blocks placed by constant products
        x = self.x0[1:] + sin[:, 1:] * self.x1[1:] + vers[:, 1:] * self.x2[1:]  # (B, N-1, 6, 6)
        back = (
            self.place_top @ x @ self.place_right + self.last_col @ (f[:, :-1] @ self.place_right) + self.corner
        )  # (B, N-1, 7, 7)
        r = f[:, n - 1] @ self.place_right + self.corner_row  # (B, 1, 7)
        out = [r]
        for i in range(n - 2, -1, -1):
            r = r @ back[:, i]
            out.append(r)
        forces = torch.cat(out[::-1], 1)  # (B, N, 7)
        return torch.sum(forces * self.s7, -1)

    def gravity_torque(self, q: torch.Tensor) -> torch.Tensor:
        zero = torch.zeros_like(q)
        return self.inverse_dynamics(q, zero, zero, gravity=True)
