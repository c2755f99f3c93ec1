"""The RNEIDA (paper Alg. 2) in torch, written for a small ONNX graph: the one torch-traceable RNE.

Same equations as ``models.dynamics.rne.rneida`` in spatial-vector form (Featherstone's notation,
frame origins, motion m = [w; v], force f = [n; f]):

    v_i = X_i v_p + S_i qd_i
    a_i = X_i a_p + S_i qdd_i + crm(v_i) S_i qd_i          a_base = [0; -g] (gravity as a base acceleration)
    f_i = I_i a_i + crf(v_i) I_i v_i                       I_i: spatial inertia at the frame origin
    tau_i = S_i^T sum_{j >= i} X*_{i<-j} f_j

onnxruntime spends ~0.3-0.5 us per node on tensors this small, so the graph is written as few nodes:

- Forward: one 13 x 13 matrix per link, L_i = blockdiag(X_i^T, X_i^T, 1) (I + qd_i Gv + [qd_i S | qdd_i S]
  in the last row). X_i is affine in (1, sin q_i, cos q_i) (Rodrigues; cos q = sin(q + pi/2), so one Sin
  node), the rest affine in (1, qd_i, qdd_i): L_i = sum_ab u_a w_b K_iab, one product with constants for
  all links at once. The chain C_i = C_{i-1} L_i (7 x 13, five MatMul nodes, carried transposed; C_0 is
  folded into link 1's constants) holds the row W_i = [v_i, a_i, 1] and, in rows 1..6, X_{i<-0}^T.
- f_i is a fixed quadratic form of W_i (its last entry is 1): one outer product and one MatMul.
- Backward without a recursion: in base coordinates f_j^0 = X_{j<-0}^T f_j (one batched MatMul with the
  chain), and tau_i = (S_i^0)^T sum_{j >= i} f_j^0 with S_i^0 = X_{0<-i} S_i = P X_{i<-0}^T P S_i (P swaps
  the angular and linear halves; X^-1 = P X^T P for a motion transform): the suffix sums and that P are
  one constant MatMul, X_{i<-0}^T P S_i one batched MatMul, the dot products and any per-joint output
  scale one Mul and one constant MatMul.

29 ONNX nodes for any joint count (the spatial recursion it replaces: 66; the component-wise RNEIDA:
~1,700); its MatMuls are sized to the work (onnxruntime's small GEMMs cost ~0.3 us per 1,000
multiply-adds here, so a padded product is not free). Several rate sets (qd, qdd) at one position run
as one pass (``inverse_dynamics_shared``: a law's own nominal model and a feed-forward in one graph at
no extra node). Checked against ``rneida`` and pinocchio (tests/unit/models/dynamics/test_dynamics_parity.py).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch

from models.robots import RobotModel

#: one rate set of inverse_dynamics_shared: qd = z @ qd_map, qdd = z @ qdd_map (+ qdd_offset), z its input
RateMap = tuple[np.ndarray, np.ndarray, "np.ndarray | None"]
W = 13  # the chain row [v (6), a (6), 1]


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


def spatial_inertia(mass_kg: float, com_m: np.ndarray, inertia_kg_m2: np.ndarray) -> np.ndarray:
    """The 6 x 6 spatial inertia of a link at its frame origin (inertia_kg_m2 about the COM)."""
    cs = _skew(com_m)
    out = np.zeros((6, 6))
    out[:3, :3] = inertia_kg_m2 + mass_kg * cs @ cs.T
    out[:3, 3:] = mass_kg * cs
    out[3:, :3] = mass_kg * cs.T
    out[3:, 3:] = mass_kg * np.eye(3)
    return out


class SpatialRne:
    """tau = ID(q, qd, qdd) for batches (B, N) of torch tensors (float64), gravity optional."""

    def __init__(self, robot: RobotModel) -> None:
        n = robot.n_joints
        self.n = n
        axis = np.asarray(robot.joint_axis, float)
        r0 = np.asarray(robot.joint_rotation, float)
        p = np.asarray(robot.joint_translation, float)
        swap = np.zeros((6, 6))  # P: [w; v] <-> [v; w]
        swap[:3, 3:] = swap[3:, :3] = np.eye(3)

        # X_i^T (what a row multiplies) = A + sin(q) B + cos(q) C, from R_i(q) = R0 (I + sin q K + (1 - cos q) K^2)
        def xt(rot: np.ndarray, p_i: np.ndarray) -> np.ndarray:
            x = np.zeros((6, 6))
            x[:3, :3] = x[3:, 3:] = rot.T
            x[3:, :3] = -rot.T @ _skew(p_i)
            return x.T

        def block(m6: np.ndarray) -> np.ndarray:
            out = np.zeros((W, W))
            out[:6, :6] = out[6:12, 6:12] = m6
            return out

        s = np.zeros((n, 6))
        s[:, :3] = axis
        links = np.zeros((n, 3, 3, W, W))  # [joint, (1, sin, cos), (1, qd, qdd)]
        for i in range(n):
            k = _skew(axis[i])
            a0, a1, a2 = (xt(rot, p[i]) for rot in (r0[i], r0[i] @ k, r0[i] @ k @ k))
            trig = [block(a0 + a2), block(a1), -block(a2)]
            trig[0][12, 12] = 1.0
            rate = [np.eye(W), np.zeros((W, W)), np.zeros((W, W))]
            rate[1][:6, 6:12] = _crf(s[i])  # row v @ crf(S) qd: the crm(v) S qd term
            rate[1][12, :6] = s[i]  # + S qd on v
            rate[2][12, 6:12] = s[i]  # + S qdd on a
            for a in range(3):
                for b in range(3):
                    links[i, a, b] = trig[a] @ rate[b]
        # C_0 (7 x 13): row 0 the base row [0, a_base, 1], rows 1..6 [I | 0]; folded into link 1
        start = np.zeros((2, 7, W))
        start[:, 1:7, :6] = np.eye(6)
        start[:, 0, 12] = 1.0
        start[0, 0, 9:12] = -np.asarray(robot.gravity_m_s2, float)  # [0]: with gravity, [1]: without
        self._links = {}
        for key, c0 in ((True, start[0]), (False, start[1])):
            folded = links.copy()
            folded[0] = 0.0
            folded[0, :, :, :7] = np.einsum("rk,abkc->abrc", c0, links[0])
            # the chain is carried transposed (D_i = C_i^T = L_i^T D_{i-1}, 13 x 7), so that a row times
            # D_i is (C_i x)^T; u9 * w9 = all nine (a, b) products, a slow
            transposed = np.swapaxes(folded, -1, -2)
            self._links[key] = _t(transposed.reshape(n, 9, W * W))
        # (1, sin q_i, cos q_i) per joint, each thrice: Sin(q @ trig_map + trig_offset)
        trig_map = np.zeros((n, 9 * n))
        trig_offset = np.zeros(9 * n)
        for i in range(n):
            for a in range(3):
                for b in range(3):
                    col = 9 * i + 3 * a + b
                    trig_map[i, col] = 0.0 if a == 0 else 1.0
                    trig_offset[col] = {0: np.pi / 2, 1: 0.0, 2: np.pi / 2}[a]
        self._trig = (trig_map, trig_offset)
        # f_i^T = vec(W_i W_i^T) (row, W_12 = 1) @ forms_i (169 x 6)
        m = np.asarray(robot.mass_kg, float)
        forms = np.zeros((n, W, W, 6))  # [joint, a, b, k]
        for i in range(n):
            com, inertia_c = np.asarray(robot.com_m[i], float), np.asarray(robot.inertia_kg_m2[i], float)
            inertia = spatial_inertia(m[i], com, inertia_c)
            forms[i, 6:12, 12, :] = inertia.T  # I a (row form, W_12 = 1)
            for a in range(6):
                for b in range(6):
                    forms[i, a, b, :] = _crf(np.eye(6)[a]) @ inertia @ np.eye(6)[b]  # crf(v) I v
        self.forms = _t(forms.reshape(n, 1, W * W, 6))
        self.axis = _t((s @ swap.T).reshape(n, 1, 1, 6))  # (P S_i)^T: C_i P S_i = X_{i<-0}^T P S_i
        self.eye = np.eye(n)
        self._sums: dict[tuple[int, tuple[bytes, ...]], tuple[torch.Tensor, torch.Tensor]] = {}

    def _suffix_and_sum(self, variants: int, scales: Sequence[np.ndarray | None]) -> tuple[torch.Tensor, torch.Tensor]:
        """(suffix, total) on the flat rows (C_i f_i)^T and (C_i P S_i)^T (7 entries per variant and link):
        tau_i = (S_i^0)^T F_i^0 = (X^T P S_i) . P sum_{j >= i} X_j^T f_j (X^-1 = P X^T P), so ``suffix``
        sums over j >= i and swaps the halves, and ((forces @ suffix) * axes) @ total = tau."""
        n = self.n
        key = (variants, tuple(b"" if v is None else np.asarray(v, float).tobytes() for v in scales))
        if key not in self._sums:
            suffix = np.zeros((variants, n, 7, variants, n, 7))
            total = np.zeros((variants, n, 7, variants, n))
            swapped = [4, 5, 6, 1, 2, 3]
            for k in range(variants):
                scale = np.ones(n) if scales[k] is None else np.asarray(scales[k], float)
                for i in range(n):
                    for r in range(1, 7):
                        suffix[k, i:, r, k, i, swapped[r - 1]] = 1.0
                    total[k, i, 1:7, k, i] = scale[i]
            size = variants * n * 7
            self._sums[key] = (_t(suffix.reshape(size, size)), _t(total.reshape(size, variants * n)))
        return self._sums[key]

    def inverse_dynamics(
        self, q: torch.Tensor, qd: torch.Tensor, qdd: torch.Tensor, gravity: bool = True
    ) -> torch.Tensor:
        """M(q) qdd + C(q, qd) qd (+ G(q)), (B, N)."""
        n = self.n
        maps = (np.vstack([self.eye, np.zeros((n, n))]), np.vstack([np.zeros((n, n)), self.eye]), None)
        return self.inverse_dynamics_shared(q, torch.cat([qd, qdd], 1), [maps], gravity=gravity)[0]

    def gravity_torque(self, q: torch.Tensor) -> torch.Tensor:
        """G(q), (B, N): no rate input at all."""
        return self.inverse_dynamics_shared(q, None, [None])[0]

    def inverse_dynamics_shared(
        self,
        q: torch.Tensor,
        rates: torch.Tensor | None,
        maps: Sequence[RateMap | None],
        scales: Sequence[np.ndarray | None] | None = None,
        gravity: bool = True,
    ) -> list[torch.Tensor]:
        """ID at one position q (B, N) for K rate sets, one pass: [scale_k * ID(q, z M_k, z M'_k + o_k)].

        ``rates`` z (B, R) is one input the K maps read (None for K rate sets that are all zero, G(q));
        ``maps[k]`` = (qd_map (R, N), qdd_map (R, N), qdd_offset (N,) or None), or None for zero rates;
        ``scales[k]`` (N,) multiplies variant k's torque (folded into the last constant).
        """
        n, k = self.n, len(maps)
        scales = list(scales) if scales is not None else [None] * k
        # (1, sin q_i, cos q_i) thrice per joint, once per variant: (B, K 9N), as the rates below
        trig_map, trig_offset = (_t(np.tile(a, k)) for a in self._trig)
        u = torch.sin(torch.addmm(trig_offset, q, trig_map))
        # (1, qd_i, qdd_i) each repeated, per variant
        width = 0 if rates is None else rates.shape[1]
        rate_map = np.zeros((width, k, n, 3, 3))
        rate_offset = np.zeros((k, n, 3, 3))
        rate_offset[:, :, :, 0] = 1.0
        for v, spec in enumerate(maps):
            if spec is None:
                continue
            qd_map, qdd_map, offset = spec
            rate_map[:, v, :, :, 1] = np.asarray(qd_map, float)[:, :, None]
            rate_map[:, v, :, :, 2] = np.asarray(qdd_map, float)[:, :, None]
            if offset is not None:
                rate_offset[v, :, :, 2] = np.asarray(offset, float)[:, None]
        # u9 is (a, b)-ordered with a slow: (1,1,1, s,s,s, c,c,c); w9 = (1,qd,qdd) three times
        if rates is None:
            w = _t(rate_offset.reshape(1, -1))
        else:
            w = torch.addmm(_t(rate_offset.reshape(-1)), rates, _t(rate_map.reshape(width, -1)))
        links = (u * w).reshape(-1, k, n, 1, 9) @ self._links[gravity]  # (B, K, N, 1, 169)
        steps = torch.split(links.reshape(-1, k, n, 1, W, W), 1, 2)
        chain = [steps[0][..., :7]]  # D_1 = (C_0 L_1)^T, 13 x 7
        for i in range(1, n):
            chain.append(steps[i] @ chain[-1])  # D_i = L_i^T D_{i-1}
        d = torch.cat(chain, 2)  # (B, K, N, 1, 13, 7), D_i = C_i^T
        column = d[..., :1]  # W_i = [v_i, a_i, 1] (column 0 of D_i)
        outer = (column * column.reshape(-1, k, n, 1, 1, W)).reshape(-1, k, n, 1, 1, W * W)
        y = d[..., :6, :]  # rows 0..5 of D_i: what a 6-vector (a force, P S_i) meets
        forces = ((outer @ self.forms) @ y).reshape(-1, k * n * 7)  # (X_{i<-0}^T f_i) in entries 1..6
        axes = (self.axis @ y).reshape(-1, k * n * 7)  # (X_{i<-0}^T P S_i) in entries 1..6
        suffix, total = self._suffix_and_sum(k, scales)
        out = ((forces @ suffix) * axes) @ total  # (B, K N)
        return [out] if k == 1 else list(torch.split(out, n, 1))
