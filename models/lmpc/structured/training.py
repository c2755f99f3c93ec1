"""Fitting the structured emulator: the physics coefficients (projected Adam, L-BFGS polish), then the
bounded residual MLP."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch

from models.lmpc.structured.config import StructuredConfig
from models.lmpc.structured.model import StructuredEmulator
from models.robots import RobotModel


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


#: the stable fit's eigenvalue floors of K_p (1/s^2) and K_d (1/s): e'' = -(K_p e + K_d e') with K_p, K_d
#: symmetric and >= these is asymptotically stable (V = e'^T e' / 2 + e^T K_p e / 2, V' = -e'^T K_d e' < 0)
STABLE_KP_MIN_1_S2, STABLE_KD_MIN_1_S = 1.0, 0.1


def _symmetric_floor(theta: torch.Tensor, floor: float) -> torch.Tensor:
    """The nearest symmetric matrix (Frobenius) whose eigenvalues are >= floor."""
    sym = (theta + theta.T) / 2
    values, vectors = torch.linalg.eigh(sym)
    return (vectors * values.clamp_min(floor)) @ vectors.T


#: the stable fit keeps the unconstrained gains (with g = 1) when e'' = -(K_p e + K_d e') decays at least
#: this fast; else it projects them (the Panda's unconstrained K_p with g = 1: 0.96 1/s, its loss 0.0019
#: against the projected fit's 0.0025, docs/any_arm.md "SMC on the real arms")
STABLE_DECAY_MIN_1_S = 0.1


def loop_decay_rate_1_s(model: StructuredEmulator, mass0: np.ndarray) -> float:
    """-max Re eig of e'' = -M0^-1 G M0 (K_p e + K_d e'): the physics loop on the nominal plant at q = 0 (M0 its
    mass matrix there, G = diag(g); with g = 1, the stable fit's, e'' = -(K_p e + K_d e'))."""
    _, g, kp, kd = (t.detach().numpy() for t in model.coefficients(live=True))
    n = kp.shape[0]
    b = np.linalg.solve(mass0, g[:, None] * mass0)
    a = np.block([[np.zeros((n, n)), np.eye(n)], [-b @ kp, -b @ kd]])
    return float(-np.linalg.eigvals(a).real.max())


def project_stable_gains(model: StructuredEmulator) -> None:
    """K_p, K_d onto symmetric matrices with eigenvalues >= the stable floors (in the optimizer's scale)."""
    with torch.no_grad():
        model.theta_kp.copy_(_symmetric_floor(model.theta_kp, STABLE_KP_MIN_1_S2 / model.KP_SCALE))
        model.theta_kd.copy_(_symmetric_floor(model.theta_kd, STABLE_KD_MIN_1_S / model.KD_SCALE))


def train_structured(
    robot: RobotModel, s: np.ndarray, y: np.ndarray, config: StructuredConfig, log: Callable[[str], None] = print
) -> tuple[StructuredEmulator, dict[str, Any]]:
    """Fit c, g, kp, kd (full batch, projected Adam + L-BFGS), then the bounded residual MLP (Adam);
    y = tau* - tau_fb. ``config.physics_fit == "stable"``: g = 1; K_p, K_d projected onto symmetric matrices
    with eigenvalue floors when the loop they make with g = 1 does not decay. ``"bounded"``: g >= G_BOUNDED_MIN
    per joint and K_p, K_d on those symmetric floors throughout (projected Adam, no unconstrained polish)."""
    torch.manual_seed(config.seed)
    n = robot.n_joints
    limit = np.asarray(robot.torque_limit_nm, float)
    bound = config.residual_bound_fraction * limit
    bounded = config.physics_fit == "bounded"
    g_min = StructuredEmulator.G_BOUNDED_MIN if bounded else 0.0
    model = StructuredEmulator(robot, config.hidden, bound, config.ff_point, config.c_max, g_min=g_min)  # static part
    if config.c_fixed is not None:
        with torch.no_grad():
            model.c.fill_(config.c_fixed)
        model.c.requires_grad_(False)
    stable = config.physics_fit == "stable"
    if stable:  # g = 1: the model's whole inverse dynamics (a per-joint g makes M^-1 G M non-symmetric)
        with torch.no_grad():
            model.g.fill_(1.0)
        model.g.requires_grad_(False)
    mass, bias = _physics_terms(robot, s, config.ff_point)
    from models.dynamics import make_dynamics

    mass0 = np.asarray(make_dynamics(robot, "rne").mass_matrix(np.zeros(n))).reshape(n, n)
    inertia0 = np.diag(mass0)
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

    def adam(project_gains: bool) -> None:
        # projected Adam, full batch, cosine-decayed step (a sigmoid-bounded L-BFGS stalled short of the
        # bounds: the control row's optimum c = g = 0 sits on them)
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
            if project_gains:
                project_stable_gains(model)

    adam(bounded)
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

    if not bounded:  # the bounded fit's optimum sits on its floors: the unconstrained polish would leave them
        polish.step(closure)
    projected = bounded
    if stable and loop_decay_rate_1_s(model, mass0) < STABLE_DECAY_MIN_1_S:
        # g = 1 alone left a loop that does not decay: refit K_p, K_d on the symmetric matrices above the
        # eigenvalue floors (stable by the Lyapunov argument; the polish would leave that set)
        adam(True)
        projected = True
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
            "fit": config.physics_fit,
            "gains_projected": projected,
            "loop_decay_rate_1_s": loop_decay_rate_1_s(model, mass0) if stable or bounded else None,
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


BETA_GRID = 400  # log-spaced candidates of beta per joint in [BETA_MIN, 1]


def rate_aware(static: StructuredEmulator, robot: RobotModel, config: StructuredConfig) -> StructuredEmulator:
    """The rate-aware emulator around a fitted static one (its coefficients, MLP and normalization), beta 1."""
    bound = static.bound.numpy()
    model = StructuredEmulator(robot, config.hidden, bound, config.ff_point, config.c_max, True, config.period_s)
    model.load_state_dict(static.state_dict(), strict=False)  # everything but beta and the rate step
    with torch.no_grad():
        model.beta.fill_(1.0)
    model.frozen, model.use_residual = static.frozen, static.use_residual
    return model.eval()


def fit_beta(
    model: StructuredEmulator,
    s: np.ndarray,
    tau_prev: np.ndarray,
    tau_star: np.ndarray,
    floor: float,
    log: Callable[[str], None] = print,
) -> dict[str, Any]:
    """beta per joint with the static part fixed: each joint's beta minimizes
    mean((tau_prev + clip(beta (target - tau_prev), +-step) - tau*)^2) over a log grid in [floor, 1]
    (the joints are independent given the static target; a grid is exact to its spacing). The rows: the
    expert's closed loop and the rate copies (labels given their tau_0)."""
    from models.lmpc.structured.model import BETA_MIN

    floor = max(float(floor), BETA_MIN)
    n = model.n
    with torch.no_grad():
        target = s[:, -n:] + model(torch.as_tensor(s)).numpy()
    step = model.rate_step.numpy()
    grid = np.exp(np.linspace(np.log(floor), 0.0, BETA_GRID))
    gap, label = target - tau_prev, tau_star - tau_prev
    losses = np.stack([np.mean((np.clip(b * gap, -step, step) - label) ** 2, 0) for b in grid])  # (G, N)
    best = np.argmin(losses, 0)
    beta = grid[best]
    denominator = np.mean(label**2, 0) + 1e-30
    relative, relative_one = losses[best, np.arange(n)] / denominator, losses[-1] / denominator
    with torch.no_grad():
        model.beta.copy_(torch.as_tensor(beta))
    log(
        f"  rate step: beta {np.round(beta, 3).tolist()}; relative loss {np.round(relative, 3).tolist()} "
        f"(beta = 1: {np.round(relative_one, 3).tolist()})"
    )
    return {
        "beta": beta.tolist(),
        "beta_floor": floor,
        "rate_step_nm": step.tolist(),
        "relative_loss": relative.tolist(),
        "relative_loss_beta_1": relative_one.tolist(),
        "samples": int(len(s)),
        "loss": "per joint mean((tau_prev + clip(beta (target - tau_prev), +-step) - tau*)^2)"
        " / mean((tau* - tau_prev)^2)",
    }
