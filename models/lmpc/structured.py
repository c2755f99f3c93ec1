"""The structured LMPC emulator: the nominal model's feed-forward in the graph + a bounded learned residual.

Why (issue 13, docs/lmpc.md section 9): tau* - tau_fb is dominated by gravity and inertia
feed-forward (4-44x |tau_fb| for PD), which a plain MLP has to invent from a few trajectories and does
not generalize. Here the physics is computed, not learned:

    a      = qdd_d + Kp e + Kd e_dot                                        (gain matrices, learned)
    tau_id = ID(q, qd, a)        ("measured": the project's RNE at the measured state)
           | ID(q_d, qd_d, a)    ("reference": along the reference)
    r      = c * tau_fb + g * tau_id + b * tanh(MLP(s) / b)                b: the residual's absolute bound
    c in [-1.05, c_max = 0], g in [0, 1.2] per joint; Kp, Kd (N x N): learned
    tau_L  = tau_fb + r = (1 + c) tau_fb + g tau_id + residual, then the trust region and saturation

i.e. the law (kept, reduced or removed) plus a share of the model's computed torque. The bounds
keep a fit on thin data (the expert's closed loop has e ~ 0, tau_fb ~ 0) from producing negative
damping or terms that cancel each other (an unconstrained fit did both on the wrists: c = 8.7, g = -9.7, kd = -378).

so the learned part is 4N numbers plus a small residual whose size is bounded by construction. With
g -> 0, w -> 1 and the MLP at zero the emulator is the feedback law itself (the control row). The RNE is
``models.dynamics.torch_rne.SpatialRne`` (the same one the laws' nominal model traces to).

Training data: HMPC closed-loop rollouts over the paper's amplitude/frequency range (seeded,
models.lmpc.paper_range), optionally DAgger rounds (the LMPC's own closed loop, relabeled by the
HMPC). The feature set of the bundle is "eq22+qdd_d" (q, e, qd, e_dot, qdd_d, tau_fb): everything
the structure reads.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from models.errors import ModelInputError
from models.executors import Executor
from models.feedback import make_law
from models.robots import RobotModel, load_robot
from models.sim import ControllerStack, SimConfig, simulate

FF_POINTS = ("measured", "reference")
#: perturbation (sigma_e rad, sigma_e_dot rad/s) of the relabeled copies per HMPC formulation: small enough
#: that the absolute-cost HMPC (gains ~1e5 1/s^2, ~1e3 1/s) stays off its torque limits
PERTURBATION = {"absolute": (1e-4, 1e-2), "anchored": (2e-3, 2e-2)}
#: c fixed per formulation (None: fitted): the absolute-cost optimum does not depend on the law
C_FIXED = {"absolute": -1.0, "anchored": None}
TARGETS = ("hmpc", "law")  # "law": the control row, the law's own torque as the label
TRAINED_FORMAT = "structured-lmpc-trained/1"  # <work>/trained_<law>.pt (save_trained, reexport)


@dataclass(frozen=True)
class StructuredConfig:
    """Everything that decides a structured LMPC (recorded in each bundle's manifest)."""

    robot: str = "ur5_paper"
    laws: tuple[str, ...] = ("pd", "pid", "adrc", "hinf", "smc", "mrac")
    gain_set: str = "stabilized"
    hmpc_options: dict[str, Any] = field(
        default_factory=dict
    )  # HMPCConfig fields (torque_cost, prediction_step_s, ...)
    target: str = "hmpc"
    ff_point: str = "measured"
    train_conditions: int = 16
    train_seed: int = 7101  # paper-range conditions for training; the held-out experiment uses other seeds
    duration_s: float = 5.0
    stride: int = 5  # log every 5th period
    period_s: float = 1e-3
    substeps: int = 2
    hidden: tuple[int, ...] = (32, 32)
    residual_bound_fraction: float = 0.02  # b_j = fraction * torque limit_j
    # upper bound of c (tau_L = (1 + c) tau_fb + ...): 0 = the law is kept or reduced, never amplified. The
    # expert's closed loop has tau_fb ~ 0, so c is weakly identified; c = +0.5 on MRAC's joints 2-3 (fitted
    # with the bound at 0.5) drove its adaptation unstable on all five paper conditions.
    c_max: float = 0.0
    # c fixed (not fitted) when the expert does not depend on the law: the absolute-cost HMPC's optimum is
    # the same for every law (docs/hmpc.md), so tau_L should not depend on tau_fb either (c = -1). A fitted
    # c is noise there (tau_fb ~ 0 on the expert's states) and c = 0 on MRAC's joints 2-3 fed its
    # adaptation back into the torque: every paper condition left the limits.
    c_fixed: float | None = None
    residual_min_gain: float = 0.10  # the residual MLP is kept only if it lowers the validation loss by this fraction
    physics_steps: int = 1500  # full-batch projected Adam steps on (c, g, Kp, Kd)
    physics_learning_rate: float = 0.05
    residual_epochs: int = 40
    batch_size: int = 512
    learning_rate: float = 3e-3
    seed: int = 0
    box_margin: float = 1.0  # trust region: alpha fades to 0 at one box range outside the training states
    # The box over (q, e, qd, e_dot, qdd_d, tau_fb): the training states' min/max for q, qd, qdd_d (where
    # the model was fitted); for e, e_dot at least +-these envelopes and tau_fb the torque limits (the
    # expert's own closed loop has errors of ~0, and the structure is exact in e: a box of the expert's
    # errors would hand every cycle back to the law).
    error_envelope_rad: float = 0.1
    rate_envelope_rad_s: float = 3.0  # the 2 s impulse alone moves the wrist by ~1.6 rad/s
    # trust region residual bound: bound_scale x max |tau* - tau_fb| over the training labels. 10 lets ADRC
    # and SMC cancel their own torque after the impulse (3 clamped it: eta_L 73.3 / 67.1 -> 81.2 / 77.0,
    # docs/lmpc.md section 9); the bundle's probes clamp each joint whatever the bound
    # (hil_runtime.bundle.clamp_probe_inputs), so the loader still catches a changed bound
    bound_scale: float = 10.0
    # DART-style excitation of the expert rollouts: the plant gets tau* + noise (the label stays tau*),
    # noise = accel_noise * M_ii(0) * a standard normal held for noise_hold_steps periods, seeded; a
    # fraction noise_fraction of the training conditions run with it. Without it the expert's own
    # closed loop has e ~ 0, tau_fb ~ 0: its feedback gains are not identifiable from its data.
    accel_noise_rad_s2: float = 0.0
    noise_hold_steps: int = 20
    noise_fraction: float = 0.75
    # Perturbed copies of the expert's states, relabeled by cold HMPC solves: the expert's feedback
    # (its response to e, e_dot) seen without running it off its own closed loop. Per copy, every
    # joint's e and e_dot get N(0, sigma) added (q, qd moved; reference and law state kept).
    perturbed_copies: int = 1
    perturb_error_rad: float = 0.01
    perturb_rate_rad_s: float = 0.05
    dagger_rounds: int = 0
    dagger_conditions: int = 8
    dagger_seed: int = 7201

    def __post_init__(self) -> None:
        if self.target not in TARGETS:
            raise ModelInputError(f"structured lmpc target: unknown {self.target!r} (known: {', '.join(TARGETS)})")
        if self.ff_point not in FF_POINTS:
            raise ModelInputError(
                f"structured lmpc ff_point: unknown {self.ff_point!r} (known: {', '.join(FF_POINTS)})"
            )
        if self.train_conditions < 1 or self.stride < 1:
            raise ModelInputError("structured lmpc: train_conditions and stride must be >= 1")


# --- data ------------------------------------------------------------------------------------
def _logged_rollouts(
    robot: RobotModel,
    controllers: list[Any],
    conditions: list[Any],
    sim: SimConfig,
    stride: int,
    excite: tuple[np.ndarray, np.ndarray] | None = None,
    hold: int = 1,
    seed: int = 0,
) -> list[dict[str, np.ndarray]]:
    """Run controllers side by side on ``conditions``; per controller the logged states and torques."""
    from models.lmpc.expert_rollouts import StateLogger

    steps = int(round(conditions[0].duration_s / sim.period_s))
    loggers = []
    for c in controllers:
        # the law's sizes: FB and HMPC controllers hold the law, the LMPC (DAgger rounds) its bundle
        sizes = c.bundle if hasattr(c, "bundle") else c.law
        n, size = sizes.n_joints, sizes.state_size
        state_of = (lambda ctl: ctl._law_state) if hasattr(c, "_law_state") else (lambda ctl: ctl.state)
        loggers.append(StateLogger(c, len(conditions), steps, stride, n, size, law_state=state_of, log_applied=True))
    runners: list[Any] = loggers
    if excite is not None:
        runners = [_Excited(lg, excite[0], hold, excite[1], seed + 1000 * k) for k, lg in enumerate(loggers)]
    traj = simulate(
        robot, ControllerStack(runners, [len(conditions)] * len(runners)), [x for _ in loggers for x in conditions], sim
    )
    out = []
    for k, logger in enumerate(loggers):
        rows = logger.log["t_s"].size
        part = slice(k * len(conditions), (k + 1) * len(conditions))
        ok = np.repeat(traj.finite[part] & traj.within_limits[part], rows)
        data = {
            "t_s": np.tile(logger.log["t_s"], len(conditions)),
            **{key: v.reshape(len(conditions) * rows, -1) for key, v in logger.log.items() if key != "t_s"},
        }
        out.append({key: v[ok] for key, v in data.items()})
    return out


class _Excited:
    """Adds held, seeded noise (per row of the batch) to a controller's torque; the label is the clean one."""

    def __init__(self, inner: Any, amplitude_nm: np.ndarray, hold: int, rows_on: np.ndarray, seed: int) -> None:
        self.inner, self.amplitude, self.hold, self.rows_on = inner, amplitude_nm, hold, rows_on
        self.name = inner.name + "-excited"
        self.cycle_times_s: list[float] = []
        self.last_tau_fb: np.ndarray | None = None
        self.seed = seed

    def reset(self, q0: np.ndarray) -> None:
        self.inner.reset(q0)
        self.k, self.rng, self.noise = 0, np.random.default_rng(self.seed), np.zeros_like(np.atleast_2d(q0))

    def __call__(self, t_s, q, qd, q_d, qd_d, qdd_d):  # type: ignore[no-untyped-def]
        tau = self.inner(t_s, q, qd, q_d, qd_d, qdd_d)
        self.last_tau_fb = self.inner.last_tau_fb
        if self.k % self.hold == 0:
            self.noise = self.rng.standard_normal(q.shape) * self.amplitude * self.rows_on[:, None]
        self.k += 1
        return tau + self.noise


def collect(
    config: StructuredConfig,
    conditions: list[Any],
    law_names: tuple[str, ...] | None = None,
    policy_dir: Path | None = None,
    executor: Executor | None = None,
) -> dict[str, dict[str, np.ndarray]]:
    """Per law: logged states with the label ``tau_star``.

    Expert (policy_dir None): the HMPC's own closed loop, label = the torque it applied (target
    "hmpc") or the FB closed loop labeled with tau_fb (target "law"). DAgger (policy_dir given):
    the LMPC of ``policy_dir`` runs, the visited states are labeled by cold HMPC solves.
    """
    from models.hmpc import make_hmpc_controller
    from models.sim import FeedbackController

    robot = load_robot(config.robot)
    sim = SimConfig(period_s=config.period_s, substeps=config.substeps)
    laws = law_names or config.laws
    made = [make_law(name, robot, config.period_s, config.gain_set) for name in laws]
    if policy_dir is not None:
        from models.lmpc import make_lmpc_controller

        controllers = [make_lmpc_controller(law, robot, bundle_dir=policy_dir) for law in made]
    elif config.target == "law":
        controllers = [FeedbackController(law) for law in made]
    else:
        controllers = [make_hmpc_controller(law, robot, **config.hmpc_options) for law in made]
    excite = None
    if policy_dir is None and config.target == "hmpc" and config.accel_noise_rad_s2 > 0:
        from models.dynamics import make_dynamics

        n = robot.n_joints
        inertia0 = np.diag(np.asarray(make_dynamics(robot, "rne").mass_matrix(np.zeros(n))).reshape(n, n))
        rows_on = (np.arange(len(conditions)) < round(config.noise_fraction * len(conditions))).astype(float)
        excite = (config.accel_noise_rad_s2 * inertia0, rows_on)
    logs = _logged_rollouts(
        robot, controllers, conditions, sim, config.stride, excite, config.noise_hold_steps, config.seed
    )
    data = {}
    for name, law, log in zip(laws, made, logs, strict=True):
        if policy_dir is not None and config.target == "hmpc":
            log["tau_star"] = relabel(law, robot, log, config.hmpc_options, executor)
        elif config.target == "law":
            log["tau_star"] = log["tau_fb"].copy()
        if policy_dir is None and config.perturbed_copies > 0 and config.target == "hmpc":
            extra = perturbed(
                log, config.perturbed_copies, config.perturb_error_rad, config.perturb_rate_rad_s, config.seed + 17
            )
            with np.errstate(all="ignore"):
                extra["tau_fb"] = np.asarray(
                    law.step(
                        np, extra["law_state"], extra["q"], extra["qd"], extra["q_d"], extra["qd_d"], extra["qdd_d"]
                    )[0],
                    float,
                )
            extra["tau_star"] = (
                extra["tau_fb"].copy()
                if config.target == "law"
                else relabel(law, robot, extra, config.hmpc_options, executor)
            )
            log = {k: np.concatenate([log[k], extra[k]]) for k in log}
        data[name] = log
    return data


def perturbed(
    log: dict[str, np.ndarray], copies: int, sigma_e: float, sigma_rate: float, seed: int
) -> dict[str, np.ndarray]:
    """``copies`` perturbed copies of logged rows (module StructuredConfig.perturbed_copies); labels not set."""
    rng = np.random.default_rng(seed)
    rows = {k: np.concatenate([v] * copies) for k, v in log.items() if k != "tau_star"}
    rows["q"] = rows["q"] + rng.normal(0.0, sigma_e, rows["q"].shape)
    rows["qd"] = rows["qd"] + rng.normal(0.0, sigma_rate, rows["qd"].shape)
    return rows


def relabel(
    law: Any,
    robot: RobotModel,
    log: dict[str, np.ndarray],
    hmpc_options: dict[str, Any],
    executor: Executor | None = None,
) -> np.ndarray:
    """The HMPC torque at logged states (cold solves from the logged law state), in chunks of 1024
    on ``executor``'s workers (models.executors; None: this process)."""
    from models.hmpc import HMPCConfig, solve_batch

    options = {**hmpc_options, "on_budget_exhausted": "best_iterate"}
    rows = (log[k] for k in ("q", "qd", "q_d", "qd_d", "qdd_d", "law_state"))
    tau, _ = solve_batch(
        law, robot, *rows, config=HMPCConfig.from_options(**options), executor=executor, chunk_states=1024
    )
    return tau


# --- the emulator -----------------------------------------------------------------------------
class StructuredEmulator(nn.Module):
    #: kp, kd scales (1/s^2, 1/s): the optimizer sees numbers of order 1
    KP_SCALE, KD_SCALE = 1.0e4, 1.0e2
    G_MAX = 1.2
    C_MIN = -1.05  # c = -1: the law's torque removed (the absolute-cost HMPC does not depend on the law)

    """s = (q, e, qd, e_dot, qdd_d, tau_fb) (B, 6N) -> r = tau_L - tau_fb (B, N); module docstring.

    ``in_mean``/``in_std`` normalize the residual MLP's input; ``net`` is that MLP (the names the
    bundle exporter reads).
    """

    def __init__(
        self,
        robot: RobotModel,
        hidden: tuple[int, ...],
        bound_nm: np.ndarray,
        ff_point: str = "measured",
        c_max: float = 0.0,
    ) -> None:
        super().__init__()
        self.c_max = float(c_max)
        from models.dynamics.torch_rne import SpatialRne

        n = robot.n_joints
        self.n, self.ff_point = n, ff_point
        self.rne = SpatialRne(robot)
        # c in [C_MIN, 0.5], g in [0, G_MAX] (kept there by projection after every optimizer step); Kp, Kd
        # free. Initial: c = 0 (the law as it is), g = G_MAX / 2, Kp = 100 I 1/s^2, Kd = 20 I 1/s
        self.c = nn.Parameter(torch.zeros(n, dtype=torch.float64))
        self.g = nn.Parameter(torch.full((n,), self.G_MAX / 2, dtype=torch.float64))
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
            return self.frozen  # type: ignore[return-value]
        return self.c, self.g, self.KP_SCALE * self.theta_kp, self.KD_SCALE * self.theta_kd

    def project(self) -> None:
        """Back into the bounds of c and g."""
        with torch.no_grad():
            if self.c.requires_grad:
                self.c.clamp_(self.C_MIN, self.c_max)
            self.g.clamp_(0.0, self.G_MAX)

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


def _structured_policy_class() -> type:
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
    from models.feedback._common import SharedId
    from models.lmpc.bundle_export import FusedPolicy

    class _StructuredPolicy(FusedPolicy):  # type: ignore[misc, valid-type]
        _compact: dict[str, Any] | None = None

        def compact_constants(self) -> dict[str, Any]:
            """The folded constants of the graph (built once from the frozen emulator and the trust box)."""
            if self._compact is not None:
                return self._compact
            emulator, n, size = self.emulator, self.n, self.s
            width = 5 * n + size  # x; xt = [x, tau_fb]
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
            parts = torch.split(x, [n] * 5 + ([size] if size else []), 1)
            q, qd, q_d, qd_d, qdd_d = parts[:5]
            state = parts[5] if size else x[:, 5 * n : 5 * n]
            position = q if self.emulator.ff_point == "measured" else q_d
            request = SharedId(position, x, k["rate_map"], k["scale"])
            # a law with a nominal model (H-infinity, SMC) runs its RNE and the feed-forward's as one pass
            nominal = getattr(self.law, "nominal", None)
            if nominal is not None:
                nominal.pending, nominal.pending_result = request, None
            tau_fb, next_state = self.law.step(torch, state, q, qd, q_d, qd_d, qdd_d)
            tau_id = None
            if nominal is not None:
                tau_id, nominal.pending, nominal.pending_result = nominal.pending_result, None, None
            if tau_id is None:
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
            tau = torch.minimum(torch.maximum(step, -self.limit), self.limit)
            if self.applied is not None:
                a, b = self.applied.start, self.applied.stop
                next_state = torch.cat([next_state[:, :a], tau, next_state[:, b:]], 1)
            out = [tau, tau_fb] + ([next_state] if size else []) + [1.0 - alpha, clamped]
            return torch.cat(out, 1)

    return _StructuredPolicy


def _physics_terms(robot: RobotModel, s: np.ndarray, ff_point: str) -> tuple[np.ndarray, np.ndarray]:
    """M (B, N, N) and h (B, N) at the feed-forward point, for fast training: ID(p, a) = M a + h."""
    from models.dynamics import make_dynamics

    n = robot.n_joints
    q, e, qd, e_dot = (s[:, i * n : (i + 1) * n] for i in range(4))
    if ff_point == "reference":
        q, qd = q + e, qd + e_dot
    dyn = make_dynamics(robot, "pinocchio")
    mass = np.concatenate(
        [np.asarray(dyn.mass_matrix(q[a : a + 4096])).reshape(-1, n, n) for a in range(0, len(q), 4096)]
    )
    bias = np.concatenate(
        [
            np.asarray(dyn.nonlinear_effects(q[a : a + 4096], qd[a : a + 4096])).reshape(-1, n)
            for a in range(0, len(q), 4096)
        ]
    )
    return mass, bias


def features(log: dict[str, np.ndarray]) -> np.ndarray:
    """s = (q, e, qd, e_dot, qdd_d, tau_fb) of logged rows."""
    return np.concatenate(
        [log["q"], log["q_d"] - log["q"], log["qd"], log["qd_d"] - log["qd"], log["qdd_d"], log["tau_fb"]], 1
    )


def train_structured(
    robot: RobotModel, s: np.ndarray, y: np.ndarray, config: StructuredConfig, log: Callable[[str], None] = print
) -> tuple[StructuredEmulator, dict[str, Any]]:
    """Fit c, g, kp, kd (full batch, L-BFGS), then the bounded residual MLP (Adam); y = tau* - tau_fb."""
    torch.manual_seed(config.seed)
    n = robot.n_joints
    limit = np.asarray(robot.torque_limit_nm, float)
    bound = config.residual_bound_fraction * limit
    model = StructuredEmulator(robot, config.hidden, bound, config.ff_point, config.c_max)
    if config.c_fixed is not None:
        with torch.no_grad():
            model.c.fill_(config.c_fixed)
        model.c.requires_grad_(False)
    mass, bias = _physics_terms(robot, s, config.ff_point)
    from models.dynamics import make_dynamics

    inertia0 = np.diag(np.asarray(make_dynamics(robot, "rne").mass_matrix(np.zeros(n))).reshape(n, n))
    # loss in acceleration units: a torque error on a 1e-4 kg m^2 wrist matters as much as 1e3x on the base
    scale = torch.as_tensor(1.0 / inertia0, dtype=torch.float64)
    st, yt = torch.as_tensor(s), torch.as_tensor(y)
    mt, ht = torch.as_tensor(mass), torch.as_tensor(bias)
    q, e, qd, e_dot, qdd_d, tau_fb = (st[:, i * n : (i + 1) * n] for i in range(6))

    def physics_fast() -> torch.Tensor:
        c, g, kp, kd = model.coefficients()
        accel = qdd_d + e @ kp.T + e_dot @ kd.T
        tau_id = (mt @ accel.unsqueeze(-1)).squeeze(-1) + ht
        return c * tau_fb + g * tau_id

    params = [p for p in (model.c, model.g, model.theta_kp, model.theta_kd) if p.requires_grad]
    # relative to the label's size (+ 1 % of the law's torque: the control row has y = 0)
    denom = float(torch.mean((yt * scale) ** 2)) + 1e-2 * float(torch.mean((tau_fb * scale) ** 2)) + 1e-30
    started = time.perf_counter()
    # projected Adam, full batch, cosine-decayed step (a sigmoid-bounded L-BFGS stalled short of the bounds:
    # the control row's optimum c = g = 0 sits on them)
    optimizer = torch.optim.Adam(params, lr=config.physics_learning_rate)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(
        optimizer, config.physics_steps, eta_min=1e-3 * config.physics_learning_rate
    )
    for _ in range(config.physics_steps):
        optimizer.zero_grad()
        loss = torch.mean(((physics_fast() - yt) * scale) ** 2) / denom
        loss.backward()
        optimizer.step()
        schedule.step()
        model.project()
    # polish the unconstrained gains with c, g fixed (L-BFGS: the gains' optimum is interior)
    polish = torch.optim.LBFGS(
        [model.theta_kp, model.theta_kd],
        lr=1.0,
        max_iter=200,
        tolerance_grad=1e-12,
        tolerance_change=1e-14,
        history_size=50,
        line_search_fn="strong_wolfe",
    )

    def closure() -> torch.Tensor:
        polish.zero_grad()
        value = torch.mean(((physics_fast() - yt) * scale) ** 2) / denom
        value.backward()
        return value

    polish.step(closure)
    model.freeze()
    with torch.no_grad():
        physics_loss = float(torch.mean(((physics_fast() - yt) * scale) ** 2) / denom)
        remainder = (yt - physics_fast()).detach()
    coef = [t.detach().numpy() for t in model.coefficients()]
    log(
        f"  physics fit: relative loss {physics_loss:.4f}; c {np.round(coef[0], 3).tolist()} "
        f"g {np.round(coef[1], 3).tolist()} "
        f"diag Kp {np.round(np.diag(coef[2]), 1).tolist()} diag Kd {np.round(np.diag(coef[3]), 1).tolist()}"
    )
    # residual MLP on what the physics leaves, bounded by construction
    model.in_mean.copy_(st.mean(0))
    model.in_std.copy_(st.std(0).clamp_min(1e-6))
    rng = np.random.default_rng(config.seed)
    order = rng.permutation(len(s))
    n_val = max(1, len(s) // 10)
    val, train = order[:n_val], order[n_val:]
    optimizer2 = torch.optim.Adam(model.net.parameters(), lr=config.learning_rate)
    sched = torch.optim.lr_scheduler.ExponentialLR(optimizer2, 0.93)
    bound_t = model.bound
    sn = (st - model.in_mean) / model.in_std

    def residual(idx: np.ndarray) -> torch.Tensor:
        return bound_t * torch.tanh(model.net(sn[idx]) / bound_t)

    best, best_state = float("inf"), None
    residual_history = []
    for _ in range(config.residual_epochs):
        perm = rng.permutation(train)
        for a in range(0, len(perm), config.batch_size):
            idx = perm[a : a + config.batch_size]
            optimizer2.zero_grad()
            loss = torch.mean(((residual(idx) - remainder[idx]) * scale) ** 2) / denom
            loss.backward()
            optimizer2.step()
        sched.step()
        with torch.no_grad():
            v = float(torch.mean(((residual(val) - remainder[val]) * scale) ** 2) / denom)
        residual_history.append(v)
        if v < best:
            best, best_state = v, {k: t.clone() for k, t in model.net.state_dict().items()}
    if best_state is not None:
        model.net.load_state_dict(best_state)
    model.freeze()
    with torch.no_grad():
        before = float(torch.mean((remainder[val] * scale) ** 2) / denom)
    # keep the MLP only where it pays for its graph nodes (t_L): >= 10 % lower validation loss
    model.use_residual = best < (1.0 - config.residual_min_gain) * before
    log(f"  residual MLP: val relative loss {before:.4g} -> {best:.4g} ({'kept' if model.use_residual else 'dropped'})")
    summary = {
        "physics": {
            "c": coef[0].tolist(),
            "g": coef[1].tolist(),
            "kp_1_s2": coef[2].tolist(),
            "kd_1_s": coef[3].tolist(),
            "relative_loss": physics_loss,
        },
        "residual": {
            "hidden": list(config.hidden),
            "bound_nm": bound.tolist(),
            "used": bool(model.use_residual),
            "val_relative_loss_before": before,
            "val_relative_loss": best,
            "history": residual_history,
        },
        "loss": "mean(((pred - (tau* - tau_fb)) / M_ii(0))^2) / mean(((tau* - tau_fb) / M_ii(0))^2)",
        "samples": int(len(s)),
        "train_s": time.perf_counter() - started,
    }
    return model.eval(), summary


# --- export ------------------------------------------------------------------------------------
def export_structured(
    out_dir: Path,
    law_name: str,
    robot: RobotModel,
    model: StructuredEmulator,
    s: np.ndarray,
    y: np.ndarray,
    config: StructuredConfig,
    summary: dict[str, Any],
) -> dict[str, Any]:
    """A policy bundle through models.lmpc.bundle_export (trust region: the training states' box)."""
    box, label_max = trust_box(s, robot, config), np.abs(y).max(0)
    return export_trained(out_dir, law_name, robot, model, box, label_max, config, summary)


def export_trained(
    out_dir: Path,
    law_name: str,
    robot: RobotModel,
    model: StructuredEmulator,
    box: tuple[np.ndarray, np.ndarray],
    label_max_nm: np.ndarray,
    config: StructuredConfig,
    summary: dict[str, Any],
) -> dict[str, Any]:
    """export_structured from what it needs of the data: the trust box and max |tau* - tau_fb| per joint
    (what ``save_trained`` keeps, so a bundle can be re-exported without the rollouts or a refit)."""
    from models.lmpc.bundle_export import export_bundle

    law = make_law(law_name, robot, config.period_s, config.gain_set)
    low, high = box
    bound = config.bound_scale * np.asarray(label_max_nm, float) + 1e-3
    training = {
        "design": "structured (models/lmpc/structured.py, docs/lmpc.md section 9)",
        "gain_set": config.gain_set,
        "config": jsonable_config(config),
        "summary": summary,
        "structure": "r = c*tau_fb + g*ID(p, qdd_d + kp*e + kd*e_dot) + b*tanh(MLP(s)/b); p = "
        + ("(q, qd) measured" if config.ff_point == "measured" else "(q_d, qd_d) reference"),
        "trust": {
            "box": "min/max of the training states, at least the paper's range (q, qd, qdd_d) 10 % beyond, "
            "e, e_dot +-error/rate envelopes, tau_fb the torque limits",
            "box_margin": config.box_margin,
            "residual_bound": f"{config.bound_scale} x max |tau* - tau_fb| over the training labels",
        },
    }
    validation = {
        "physics_relative_loss": summary["physics"]["relative_loss"],
        "residual_val_relative_loss": summary["residual"]["val_relative_loss"],
    }
    # onnxruntime-vs-torch parity on the exporter's seeded random rows; probes recorded by the exporter
    return export_bundle(
        out_dir,
        law,
        robot,
        model,
        training,
        validation,
        trust_region=(low, high),
        residual=True,
        residual_bound_nm=bound,
        box_margin=config.box_margin,
        feature_set="eq22+qdd_d",
        policy_class=_structured_policy_class(),
    )


def trust_box(s: np.ndarray, robot: RobotModel, config: StructuredConfig) -> tuple[np.ndarray, np.ndarray]:
    """(low, high) of the trust box over s = (q, e, qd, e_dot, qdd_d, tau_fb); see StructuredConfig."""
    from models.lmpc.paper_range import PAPER_AMPLITUDE_RAD, PAPER_FREQUENCY_RANGE_HZ

    n = robot.n_joints
    low, high = s.min(0).copy(), s.max(0).copy()
    # the paper's range (models.lmpc.paper_range), 10 % beyond: where the physics part was trained to hold
    omega = 2.0 * np.pi * PAPER_FREQUENCY_RANGE_HZ[1]
    reference = (
        1.1 * PAPER_AMPLITUDE_RAD,
        1.1 * 0.5 * PAPER_AMPLITUDE_RAD * omega * 2.0,
        1.1 * 0.5 * PAPER_AMPLITUDE_RAD * omega**2,
    )
    for block, envelope in (
        (0, reference[0]),
        (2, reference[1]),
        (4, reference[2]),
        (1, config.error_envelope_rad),
        (3, config.rate_envelope_rad_s),
        (5, np.asarray(robot.torque_limit_nm, float)),
    ):
        part = slice(block * n, (block + 1) * n)
        low[part] = np.minimum(low[part], -envelope)
        high[part] = np.maximum(high[part], envelope)
    return low, high


def jsonable_config(config: StructuredConfig) -> dict[str, Any]:
    return json.loads(json.dumps(asdict(config), default=str))


# --- the whole stage ---------------------------------------------------------------------------
_DATA_FIELDS = (
    "robot",
    "gain_set",
    "hmpc_options",
    "target",
    "train_conditions",
    "train_seed",
    "duration_s",
    "stride",
    "period_s",
    "substeps",
    "accel_noise_rad_s2",
    "noise_hold_steps",
    "noise_fraction",
    "perturbed_copies",
    "perturb_error_rad",
    "perturb_rate_rad_s",
    "seed",
)


def _data_key(config: StructuredConfig) -> str:
    """What the rollouts depend on (a cache made with other settings is not reused)."""
    return json.dumps({k: jsonable_config(config)[k] for k in _DATA_FIELDS}, sort_keys=True)


def _cached_rollouts(
    work: Path,
    config: StructuredConfig,
    conditions: list[Any],
    log: Callable[[str], None],
    executor: Executor | None = None,
) -> dict[str, Any]:
    """Per law, <work>/rollouts_<law>.pkl when made with the same settings; the missing laws are run
    (side by side in one plant) and cached."""
    import pickle

    key = _data_key(config)
    data: dict[str, Any] = {}
    for name in config.laws:
        path = work / f"rollouts_{name}.pkl"
        if path.exists():
            try:
                stored_key, value = pickle.loads(path.read_bytes())
                if stored_key == key:
                    data[name] = value
            except Exception:  # noqa: BLE001, S110 - an unreadable cache is regenerated, never trusted
                pass
    if data:
        log(f"rollouts: reusing {', '.join(sorted(data))} from {work}")
    missing = tuple(name for name in config.laws if name not in data)
    if missing:
        fresh = collect(config, conditions, law_names=missing, executor=executor)
        for name in missing:
            path = work / f"rollouts_{name}.pkl"
            tmp = path.with_suffix(".tmp")
            tmp.write_bytes(pickle.dumps((key, fresh[name])))
            tmp.replace(path)
            data[name] = fresh[name]
    return {name: data[name] for name in config.laws}


def save_trained(
    path: Path,
    model: StructuredEmulator,
    config: StructuredConfig,
    fit: dict[str, Any],
    box: tuple[np.ndarray, np.ndarray],
    label_max_nm: np.ndarray,
) -> None:
    """The trained emulator (torch weights, frozen coefficients) and what its export needs of the data:
    ``reexport`` rebuilds the bundle from it (another residual bound, a changed graph) without a refit."""
    payload = {
        "format": TRAINED_FORMAT,
        "config": jsonable_config(config),
        "state_dict": model.state_dict(),
        "frozen": [t.detach().clone() for t in model.coefficients()],
        "use_residual": bool(model.use_residual),
        "fit": fit,
        "box": [np.asarray(box[0], float), np.asarray(box[1], float)],
        "label_max_nm": np.asarray(label_max_nm, float),
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    torch.save(payload, tmp)
    tmp.replace(path)


def config_from_json(raw: dict[str, Any]) -> StructuredConfig:
    """The StructuredConfig that jsonable_config recorded (fields this version does not know are refused)."""
    unknown = sorted(set(raw) - set(StructuredConfig.__dataclass_fields__))
    if unknown:
        raise ModelInputError(f"structured lmpc config: unknown fields {', '.join(unknown)}")
    values = dict(raw)
    for name in ("laws", "hidden"):
        if name in values:
            values[name] = tuple(values[name])
    return StructuredConfig(**values)


def reexport(
    work: Path,
    bundles: Path,
    laws: tuple[str, ...] = (),
    bound_scale: float | None = None,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """Bundles from run_structured's trained files (<work>/trained_<law>.pt) with today's graph code: no
    rollouts, no refit. ``bound_scale`` overrides the recorded residual-bound scale."""
    work, bundles = Path(work), Path(bundles)
    names = laws or tuple(sorted(p.stem.removeprefix("trained_") for p in work.glob("trained_*.pt")))
    if not names:
        raise ModelInputError(f"reexport: no trained_<law>.pt in {work} (made by `hil pipeline --design structured`)")
    summary: dict[str, Any] = {}
    for name in names:
        path = work / f"trained_{name}.pt"
        if not path.is_file():
            raise ModelInputError(f"reexport: {path}: missing")
        try:
            payload = torch.load(path, weights_only=False)
        except Exception as exc:  # noqa: BLE001 - torch raises pickle, zip and runtime errors alike
            raise ModelInputError(f"reexport: {path}: unreadable ({str(exc).splitlines()[0][:120]})") from None
        if not isinstance(payload, dict) or payload.get("format") != TRAINED_FORMAT:
            raise ModelInputError(f"reexport: {path}: not a {TRAINED_FORMAT} file")
        config = config_from_json(payload["config"])
        if bound_scale is not None:
            config = replace(config, bound_scale=float(bound_scale))
        robot = load_robot(config.robot)
        bound = config.residual_bound_fraction * np.asarray(robot.torque_limit_nm, float)
        model = StructuredEmulator(robot, config.hidden, bound, config.ff_point, config.c_max)
        model.load_state_dict(payload["state_dict"])
        model.frozen = tuple(payload["frozen"])
        model.use_residual = bool(payload["use_residual"])
        box = (payload["box"][0], payload["box"][1])
        out = bundles / robot.name / name
        manifest = export_trained(out, name, robot, model.eval(), box, payload["label_max_nm"], config, payload["fit"])
        error = float(manifest["validation"]["onnx_vs_torch_max_abs_nm"])
        summary[name] = {"path": str(out), "bound_scale": config.bound_scale, "onnx_vs_torch_max_abs_nm": error}
        log(f"{name}: re-exported {out} (residual bound {config.bound_scale}x; onnx vs torch {error:.1e} N m)")
    return summary


def run_structured(
    config: StructuredConfig,
    bundles: Path,
    work: Path,
    log: Callable[[str], None] = print,
    executor: Executor | None = None,
) -> dict[str, Any]:
    """Rollouts -> fit -> export (-> DAgger rounds); returns a summary (also written to work/structured.json).
    The cold HMPC relabeling runs on ``executor`` (models.executors; None: this process)."""
    from models.lmpc.paper_range import paper_range_conditions

    robot = load_robot(config.robot)
    work.mkdir(parents=True, exist_ok=True)
    started = time.perf_counter()
    conditions = paper_range_conditions(robot, config.train_conditions, config.train_seed, prefix="T")
    conditions = [replace(c, duration_s=config.duration_s) for c in conditions]
    data = _cached_rollouts(work, config, conditions, log, executor)
    counts = ", ".join(f"{k} {len(v['q'])}" for k, v in data.items())
    log(f"rollouts: {counts} states ({time.perf_counter() - started:.0f} s)")
    summary: dict[str, Any] = {"config": jsonable_config(config), "rounds": []}
    for round_index in range(config.dagger_rounds + 1):
        per_law = {}
        for name in config.laws:
            s, y = features(data[name]), data[name]["tau_star"] - data[name]["tau_fb"]
            log(f"{name}: fit on {len(s)} states (round {round_index})")
            model, fit = train_structured(robot, s, y, config, log)
            box, label_max = trust_box(s, robot, config), np.abs(y).max(0)
            save_trained(work / f"trained_{name}.pt", model, config, fit, box, label_max)
            manifest = export_trained(bundles / robot.name / name, name, robot, model, box, label_max, config, fit)
            per_law[name] = {"fit": fit, "onnx_vs_torch_max_abs_nm": manifest["validation"]["onnx_vs_torch_max_abs_nm"]}
        summary["rounds"].append(per_law)
        if round_index == config.dagger_rounds:
            break
        dagger = paper_range_conditions(robot, config.dagger_conditions, config.dagger_seed + round_index, prefix="D")
        dagger = [replace(c, duration_s=config.duration_s) for c in dagger]
        extra = collect(config, dagger, policy_dir=bundles, executor=executor)
        for name in config.laws:
            data[name] = {k: np.concatenate([data[name][k], extra[name][k]]) for k in data[name]}
        counts = ", ".join(f"{k} {len(v['q'])}" for k, v in extra.items())
        log(f"DAgger round {round_index + 1}: + {counts} states")
    summary["wall_s"] = time.perf_counter() - started
    (work / "structured.json").write_text(json.dumps(summary, indent=1, default=float))
    return summary
