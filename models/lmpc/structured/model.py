"""The structured emulator in torch: r = c tau_fb + g ID(p, qdd_d + Kp e + Kd e_dot) + b tanh(MLP(s) / b)
(package docstring, models.lmpc.structured); with ``previous_torque`` also the step from tau_prev,
tau = tau_prev + clip(beta (tau_fb + r - tau_prev), +-step) (docs/lmpc.md §11)."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from models.robots import RobotModel


class StructuredEmulator(nn.Module):
    """s = (q, e, qd, e_dot, qdd_d, tau_fb) (B, 6N) -> r = tau_L - tau_fb (B, N); package docstring.

    ``in_mean``/``in_std`` normalize the residual MLP's input; ``net`` is that MLP (the names the
    bundle exporter reads).
    """

    #: kp, kd scales (1/s^2, 1/s): the optimizer sees numbers of order 1
    KP_SCALE, KD_SCALE = 1.0e4, 1.0e2
    G_MAX = 1.2
    #: the "bounded" physics fit's floor of g: the model's inverse dynamics stays at least half the torque (the
    #: free fit on randomized data dropped the base's feed-forward, g_1 = 0, and leaned on friction instead)
    G_BOUNDED_MIN = 0.5
    C_MIN = -1.05  # c = -1: the law's torque removed (the absolute-cost HMPC does not depend on the law)

    def __init__(
        self,
        robot: RobotModel,
        hidden: tuple[int, ...],
        bound_nm: np.ndarray,
        ff_point: str = "measured",
        c_max: float = 0.0,
        previous_torque: bool = False,
        period_s: float = 1e-3,
        g_min: float = 0.0,
    ) -> None:
        super().__init__()
        self.c_max = float(c_max)
        self.g_min = float(g_min)  # the "bounded" fit's G_BOUNDED_MIN, else 0
        from models.dynamics.torch_rne import SpatialRne

        n = robot.n_joints
        self.n, self.ff_point = n, ff_point
        self.rne = SpatialRne(robot)
        # c in [C_MIN, 0.5], g in [g_min, G_MAX] (kept there by projection after every optimizer step); Kp, Kd
        # free. Initial: c = 0 (the law as it is), g = G_MAX / 2 (or g_min if above), Kp = 100 I 1/s^2, Kd = 20 I 1/s
        self.c = nn.Parameter(torch.zeros(n, dtype=torch.float64))
        self.g = nn.Parameter(torch.full((n,), max(self.G_MAX / 2, self.g_min), dtype=torch.float64))
        self.theta_kp = nn.Parameter(torch.eye(n, dtype=torch.float64) * (100.0 / self.KP_SCALE))
        self.theta_kd = nn.Parameter(torch.eye(n, dtype=torch.float64) * (20.0 / self.KD_SCALE))
        layers: list[nn.Module] = []
        width = 6 * n
        for size in hidden:
            layers += [nn.Linear(width, size), nn.ReLU()]
            width = size
        layers.append(nn.Linear(width, n))
        self.net = nn.Sequential(*layers).double()
        with torch.no_grad():  # the residual starts at zero: the emulator starts as the physics part
            self.net[-1].weight.zero_()
            self.net[-1].bias.zero_()
        self.register_buffer("in_mean", torch.zeros(6 * n, dtype=torch.float64))
        self.register_buffer("in_std", torch.ones(6 * n, dtype=torch.float64))
        self.register_buffer("bound", torch.as_tensor(np.asarray(bound_nm, float), dtype=torch.float64))
        self.use_residual = True
        self.frozen: tuple[torch.Tensor, ...] | None = None
        # The rate-aware step (docs/lmpc.md §11): beta per joint in [BETA_MIN, 1] (1: straight to the static
        # target, as fast as the rate bound allows), step = the robot's torque-rate bound x the period
        self.previous_torque = bool(previous_torque)
        if self.previous_torque:
            from hil_runtime.rate_limit import max_torque_step_nm

            step = max_torque_step_nm(robot.torque_rate_nm_s, period_s)
            self.beta = nn.Parameter(torch.full((n,), 0.5, dtype=torch.float64))
            self.register_buffer("rate_step", torch.as_tensor(step, dtype=torch.float64))

    def split(self, s: torch.Tensor) -> tuple[torch.Tensor, ...]:
        n = self.n
        return tuple(s[:, i * n : (i + 1) * n] for i in range(6))

    def freeze(self) -> None:
        """Bake (c, g, kp, kd) into constants (the exported graph then holds four vectors, no sigmoid/softplus)."""
        with torch.no_grad():
            self.frozen = tuple(t.detach().clone() for t in self.coefficients(live=True))

    def coefficients(self, live: bool = False) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(c, g, Kp, Kd): r = c tau_fb + g ID(p, qdd_d + Kp e + Kd e_dot); c, g per joint, Kp, Kd (N, N)."""
        if self.frozen is not None and not live:
            return self.frozen  # type: ignore[return-value]  # frozen is the 4-tuple coefficients() made
        return self.c, self.g, self.KP_SCALE * self.theta_kp, self.KD_SCALE * self.theta_kd

    def project(self) -> None:
        """Back into the bounds of c and g."""
        with torch.no_grad():
            if self.c.requires_grad:
                self.c.clamp_(self.C_MIN, self.c_max)
            self.g.clamp_(self.g_min, self.G_MAX)
            if self.previous_torque:
                self.beta.clamp_(BETA_MIN, 1.0)

    def physics(self, s: torch.Tensor) -> torch.Tensor:
        q, e, qd, e_dot, qdd_d, tau_fb = self.split(s)
        c, g, kp, kd = self.coefficients()
        accel = qdd_d + e @ kp.T + e_dot @ kd.T
        if self.ff_point == "measured":
            tau_id = self.rne.inverse_dynamics(q, qd, accel)
        else:
            tau_id = self.rne.inverse_dynamics(q + e, qd + e_dot, accel)
        return c * tau_fb + g * tau_id

    def forward(self, s: torch.Tensor) -> torch.Tensor:
        r = self.physics(s)
        if self.use_residual:
            r = r + self.bound * torch.tanh(self.net((s - self.in_mean) / self.in_std) / self.bound)
        return r

    def rate_step_from(self, target: torch.Tensor, tau_prev: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
        """tau_prev + clip(share (target - tau_prev), +-step), share = 1 - alpha (1 - beta): the learned beta
        where the trust region trusts the emulator (alpha = 1), 1 where it hands over to the law (alpha = 0:
        the law's torque, reached at the rate bound)."""
        share = 1.0 + alpha * (self.beta - 1.0)
        change = share * (target - tau_prev)
        return tau_prev + torch.minimum(torch.maximum(change, -self.rate_step), self.rate_step)


BETA_MIN = 0.005  # the smallest step share the fit may choose (0 would never move)
