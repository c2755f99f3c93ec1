"""HMPC: the paper's hybrid MPC-feedback expert (Sec. III-A, Eq. 17), fast enough for 1 kHz.

- ``HMPCConfig``: weights, preview, budgets, tolerances, backend (frozen, validated).
- ``HMPCSolver``: the optimizer for a batch of states (candidates w * tau_fb, then Gauss-Newton
  with a box-constrained QP over the torque sequence).
- ``make_hmpc_controller``: the closed-loop controller the simulator runs (mode ``hmpc``).
- ``solve_batch``: many independent states, spread over an executor's workers (labeling;
  ``models.executors``).

See docs/hmpc.md.
"""

from models.hmpc.batch import solve_batch
from models.hmpc.config import HMPCConfig
from models.hmpc.controller import HMPCController, make_hmpc_controller
from models.hmpc.result import STATUS_NAMES, HMPCResult
from models.hmpc.solver import HMPCSolver

__all__ = [
    "HMPCConfig",
    "HMPCController",
    "HMPCResult",
    "HMPCSolver",
    "STATUS_NAMES",
    "make_hmpc_controller",
    "solve_batch",
]
