"""The structured LMPC's ONNX policy graph: FusedPolicy's layout and numbers, folded into few nodes."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from torch import nn


def structured_policy_class() -> type:
    """A FusedPolicy with the same layout, the same numbers (to round-off) and the trust-region rule, written
    as few ONNX nodes as the algebra allows (onnxruntime spends ~0.3-0.5 us per node on rows this small):

    - every affine function of the input row x feeds its consumer directly as one Gemm: the feed-forward's
      acceleration qdd_d + Kp e + Kd e_dot, the residual MLP's normalized input (normalization folded
      into its first layer), the trust box's scaled guard features (box centre and 1/span folded in);
    - the feed-forward's ID is one pass of models.dynamics.torch_rne (g folded into its last constant),
      shared with the law's own nominal RNE (H-infinity, SMC) when both are at the measured q;
    - d = max over [g - mid - half, mid - g - half] / span (one Gemm and one ReduceMax) replaces
      max_j max(low_j - g_j, g_j - high_j, 0) / span_j (alpha = clip(1 - d / margin, 0, 1) is the same for
      d < 0 as for d = 0); r is computed in units of the trust region's residual bound (the clamp is one
      Clip), 1/b folded into the MLP's last layer, |r| alpha > alpha counts the clamped joints where alpha > 0.

    The reference semantics is FusedPolicy.forward with the emulator's own forward (tests compare both).
    """
    from models.feedback.base import SharedId
    from models.lmpc.bundle_export import FusedPolicy

    class _StructuredPolicy(FusedPolicy):  # type: ignore[misc, valid-type]  # a torch Module: Any to mypy
        _compact: dict[str, Any] | None = None

        def compact_constants(self) -> dict[str, Any]:
            """The folded constants of the graph (built once from the frozen emulator and the trust box)."""
            if self._compact is not None:
                return self._compact
            emulator, n, size = self.emulator, self.n, self.s
            width = (6 if self.previous else 5) * n + size  # x (tau_prev last, if read); xt = [x, tau_fb]
            eye = np.eye(n)

            def block(index: int) -> np.ndarray:  # (width + n, n): x's index-th N-block (5: tau_fb)
                out = np.zeros((width + n, n))
                at = width if index == 5 else index * n
                out[at : at + n] = eye
                return out

            q, qd, q_d, qd_d, qdd_d, tau_fb = (block(i) for i in range(6))
            guard = np.concatenate([q, q_d - q, qd, qd_d - qd, qdd_d, tau_fb], 1)  # GUARD_FEATURES order
            c, g, kp, kd = (t.detach().numpy().astype(float) for t in emulator.coefficients())
            accel = qdd_d + (q_d - q) @ kp.T + (qd_d - qd) @ kd.T
            rate = qd if emulator.ff_point == "measured" else qd_d
            low, high = self.box_low.numpy(), self.box_high.numpy()
            inv_span = self.box_inv_span.numpy()
            mid, half = 0.5 * (low + high) * inv_span, 0.5 * (high - low) * inv_span
            trust_bound = self.bound.numpy()  # r is computed in units of it: clip(r', -1, 1) is one node
            out: dict[str, Any] = {
                "rate_map": (rate[:width], accel[:width], None),
                "scale": g / trust_bound,
                "law_gain": torch.as_tensor(tau_fb * (c / trust_bound)[None, :]),  # c on the tau_fb rows
                # max(|g - mid| / span - half / span) over j as one max over [g - mid - half, mid - g - half]
                "guard_map": torch.as_tensor(np.concatenate([guard * inv_span, -guard * inv_span], 1)),
                "guard_offset": torch.as_tensor(np.concatenate([-mid - half, mid - half])),
                "alpha_gain": torch.full((1, 1), -self.inv_margin, dtype=torch.float64),
                "alpha_offset": torch.ones(1, dtype=torch.float64),
                "trust_bound": torch.as_tensor(np.diag(trust_bound)),
                "residual_scale": torch.as_tensor(np.diag(emulator.bound.numpy() / trust_bound)),
                "layers": [],
            }
            if emulator.use_residual:
                linears = [m for m in emulator.net if isinstance(m, nn.Linear)]
                mean, std = emulator.in_mean.numpy(), emulator.in_std.numpy()
                bound = emulator.bound.numpy()
                for k, layer in enumerate(linears):
                    weight = layer.weight.detach().numpy().astype(float)
                    bias = layer.bias.detach().numpy().astype(float)
                    if k == 0:  # (s - mean) / std folded in; s = xt @ guard (the emulator's s is the guard)
                        weight = weight / std[None, :]
                        bias = bias - weight @ mean
                        weight = weight @ guard.T
                    if k == len(linears) - 1:  # b tanh(y / b): 1/b folded in
                        weight, bias = weight / bound[:, None], bias / bound
                    out["layers"].append((torch.as_tensor(bias), torch.as_tensor(np.ascontiguousarray(weight.T))))
            self._compact = out
            return out

        def forward(self, x: torch.Tensor) -> torch.Tensor:
            n, size = self.n, self.s
            k = self.compact_constants()
            parts = torch.split(x, [n] * 5 + ([size] if size else []) + ([n] if self.previous else []), 1)
            q, qd, q_d, qd_d, qdd_d = parts[:5]
            state = parts[5] if size else x[:, 5 * n : 5 * n]
            position = q if self.emulator.ff_point == "measured" else q_d
            request = SharedId(position, x, k["rate_map"], k["scale"])
            # a law with a nominal model (H-infinity, SMC) runs its RNE and the feed-forward's as one pass
            tau_fb, next_state, tau_id = self.law.step_sharing_id(torch, state, q, qd, q_d, qd_d, qdd_d, request)
            if tau_id is None:  # the law has no RNE pass to share: the feed-forward's own
                rne = self.emulator.rne
                tau_id = rne.inverse_dynamics_shared(position, x, [k["rate_map"]], [k["scale"]])[0]
            xt = torch.cat([x, tau_fb], 1)
            r = torch.addmm(tau_id, xt, k["law_gain"])  # (c tau_fb + g ID(...)) / trust bound
            if k["layers"]:
                h = xt
                for i, (bias, weight) in enumerate(k["layers"]):
                    h = torch.addmm(bias, h, weight)
                    if i < len(k["layers"]) - 1:
                        h = torch.relu(h)
                r = torch.addmm(r, torch.tanh(h), k["residual_scale"])
            # the trust region (hil_runtime.bundle.trust_filter is the reference)
            distance = torch.amax(torch.addmm(k["guard_offset"], xt, k["guard_map"]), 1, keepdim=True)
            alpha = torch.clamp(torch.addmm(k["alpha_offset"], distance, k["alpha_gain"]), 0.0, 1.0)
            # joints clamped while alpha > 0: |r| alpha > alpha (one comparison instead of a count times sign(alpha))
            clamped = torch.sum((torch.abs(r) * alpha > alpha).to(torch.float64), 1, keepdim=True)
            step = torch.addmm(tau_fb, alpha * torch.clamp(r, -1.0, 1.0), k["trust_bound"])
            if self.previous:  # the step from tau_prev within the rate bound (the emulator's rate_step_from)
                step = self.emulator.rate_step_from(step, parts[-1], alpha)
            tau = torch.minimum(torch.maximum(step, -self.limit), self.limit)
            if self.applied is not None:
                a, b = self.applied.start, self.applied.stop
                next_state = torch.cat([next_state[:, :a], tau, next_state[:, b:]], 1)
            out = [tau, tau_fb] + ([next_state] if size else []) + [1.0 - alpha, clamped]
            return torch.cat(out, 1)

    return _StructuredPolicy
