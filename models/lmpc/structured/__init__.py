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

from models.lmpc.structured.config import (
    C_FIXED,
    FF_POINTS,
    PERTURBATION,
    TARGETS,
    TRAINED_FORMAT,
    StructuredConfig,
    config_from_json,
    jsonable_config,
)
from models.lmpc.structured.data import collect, features, perturbed, relabel
from models.lmpc.structured.export import export_structured, export_trained, reexport, save_trained, trust_box
from models.lmpc.structured.graph import structured_policy_class
from models.lmpc.structured.model import StructuredEmulator
from models.lmpc.structured.run import run_structured
from models.lmpc.structured.training import train_structured

__all__ = [
    "C_FIXED",
    "FF_POINTS",
    "PERTURBATION",
    "TARGETS",
    "TRAINED_FORMAT",
    "StructuredConfig",
    "StructuredEmulator",
    "structured_policy_class",
    "collect",
    "config_from_json",
    "export_structured",
    "export_trained",
    "features",
    "jsonable_config",
    "perturbed",
    "reexport",
    "relabel",
    "run_structured",
    "save_trained",
    "train_structured",
    "trust_box",
]
