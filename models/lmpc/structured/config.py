"""The structured LMPC's settings (StructuredConfig) and their JSON form, as recorded in each bundle's
manifest and each trained file."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from typing import Any

from models.errors import ModelInputError

FF_POINTS = ("measured", "reference")
#: perturbation (sigma_e rad, sigma_e_dot rad/s) of the relabeled copies per HMPC formulation: small enough
#: that the absolute-cost HMPC (gains ~1e5 1/s^2, ~1e3 1/s) stays off its torque limits
PERTURBATION = {"absolute": (1e-4, 1e-2), "anchored": (2e-3, 2e-2), "deployable": (1e-3, 2e-2)}
#: c fixed per formulation (None: fitted): the absolute-cost optimum does not depend on the law
C_FIXED = {"absolute": -1.0, "anchored": None, "deployable": -1.0}
TARGETS = ("hmpc", "law")  # "law": the control row, the law's own torque as the label
#: the physics part's fit: "free" (g in [0, G_MAX] per joint, K_p, K_d any matrices) or "stable" (g = 1,
#: K_p, K_d symmetric with eigenvalues >= a floor: the loop e'' = -(K_p e + K_d e') is then stable by
#: construction, docs/any_arm.md "The stable physics fit") or "bounded" (g in [G_BOUNDED_MIN, G_MAX] per
#: joint, K_p, K_d on the stable fit's symmetric floors: the feed-forward kept and no negative stiffness, without
#: the stable fit's g = 1; docs/lmpc.md section 12)
PHYSICS_FITS = ("free", "stable", "bounded")
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
    # "free": every shipped bundle. "stable" removes the Panda's unstable physics loop (free fit: g_1 = 0.73,
    # K_p's symmetric part with an eigenvalue of -77 1/s^2, unstable at 62 % of C4's poses) but its refitted
    # bundles measured worse overall (docs/any_arm.md "The stable physics fit"): not a default yet
    physics_fit: str = "free"
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
    # The rate-aware emulator (docs/lmpc.md §11): the graph also reads tau_prev, the torque commanded last
    # period, and steps from it, tau = tau_prev + clip(beta (tau_static - tau_prev), +-max_torque_step).
    # Its data: tau_0 logged with every expert state, the static copies as before, and rate copies (every
    # rate_copy_stride-th on-policy row, e, e_dot and tau_0 moved: models.lmpc.structured.data.rate_copies)
    # relabeled by an HMPC solve given that tau_0 (smoothness term and rate bound active): without tau_0
    # moved, beta is not identifiable (on the expert's closed loop tau* - tau_0 is ~ 1e-3 N m). The static
    # part is fitted as before, then beta (training.fit_beta) in [beta_floor, 1]: the fit alone chose
    # 0.09-0.2 on the big joints, whose lag made the closed loop oscillate (docs/lmpc.md §11).
    previous_torque: bool = False
    rate_copy_stride: int = 1
    rate_perturb_steps: float = 2.0
    beta_floor: float = 0.3
    # the rate check (run.rate_feasible_bandwidth, docs/lmpc.md §11): opt-in. It makes the real UR5's
    # rate-aware loop hold the bound (s = 0.7) but picked s = 0.35 for the Panda's ADRC (4/4 training
    # conditions against 3/4 at s = 1), whose eta_L under `ideal` then fell from 62.6 to -16.8 %
    rate_check: bool = False
    # the rows the static part is fitted on (config.previous_torque; data.ROW_KINDS): the expert's own
    # ("on_policy": its applied torque, rate-bounded given its tau_0) and the cold copies ("static": the
    # static optimum). Under domain randomization the on-policy labels are mostly rate-bounded steps, which
    # the static structure cannot explain (docs/lmpc.md §12): ("static",) fits it on the cold copies alone
    static_rows: tuple[str, ...] = ("on_policy", "static")
    # Domain randomization (docs/lmpc.md §12): the expert's rollouts (and DAgger's) run in realism_draws
    # seeded worlds drawn around this realism profile (models.lmpc.structured.randomization); None: ideal
    train_realism: str | None = None
    realism_draws: int = 4
    # more worlds, each the nominal (ideal) one, among which the training conditions rotate too: the data
    # then hold the frictionless, noiseless plant the randomized draws never show (docs/lmpc.md §12)
    ideal_draws: int = 0
    # training conditions across the arm's envelope (models.envelope_conditions, seed train_seed) beside
    # the paper-range ones; the trust box then covers them
    envelope_conditions: int = 0
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
        if self.physics_fit not in PHYSICS_FITS:
            raise ModelInputError(
                f"structured lmpc physics_fit: unknown {self.physics_fit!r} (known: {', '.join(PHYSICS_FITS)})"
            )
        if not self.static_rows or set(self.static_rows) - {"on_policy", "static"}:
            raise ModelInputError(
                f"structured lmpc static_rows: a non-empty subset of on_policy, static, got {self.static_rows}"
            )
        if self.realism_draws < 1 or self.envelope_conditions < 0 or self.ideal_draws < 0:
            raise ModelInputError(
                "structured lmpc: realism_draws must be >= 1, envelope_conditions and ideal_draws >= 0"
            )
        if self.train_conditions < 1 or self.stride < 1:
            raise ModelInputError("structured lmpc: train_conditions and stride must be >= 1")


def jsonable_config(config: StructuredConfig) -> dict[str, Any]:
    return json.loads(json.dumps(asdict(config), default=str))


def config_from_json(raw: dict[str, Any]) -> StructuredConfig:
    """The StructuredConfig that jsonable_config recorded (fields this version does not know are refused)."""
    unknown = sorted(set(raw) - set(StructuredConfig.__dataclass_fields__))
    if unknown:
        raise ModelInputError(f"structured lmpc config: unknown fields {', '.join(unknown)}")
    values = dict(raw)
    for name in ("laws", "hidden", "static_rows"):
        if name in values:
            values[name] = tuple(values[name])
    return StructuredConfig(**values)
