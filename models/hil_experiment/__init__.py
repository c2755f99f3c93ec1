"""The paper's Table II as hardware-in-the-loop: ``hil experiment --plant hil``.

For each law, mode (``fb``, ``lmpc``) and condition, the real runtime loop
(:class:`hil_runtime.runtime.Runtime`) runs the shipped bundle against the pybullet target
(sim_target) in lock-step over the CAN bus; the target places the arm on the condition's initial
state when the drives are enabled and injects the condition's disturbance; the trajectory is the
runtime's own record; it is scored by the simulation's scoring code (models.scoring, the same
normalization as ``hil experiment``).

Parity (unless ``parity=False``): the simulation of the same laws, modes and conditions runs in a
second process meanwhile (``out_dir/sim/``, a complete ``hil experiment`` output), and every run is
compared with its simulated twin: composite score difference and trajectory RMS difference
(docs/hil.md says why they differ).

Outputs in ``out_dir``, as ``hil experiment``:
  results.json   raw metrics per run, composite scores, eta, runtime compute per cycle, parity
  table.md       the layout of the paper's Table II (FB -> LMPC per law, the paper's values beside),
                 then the parity table
  trajectories/  one .npz per run: the runtime's record (t, q, qd, q_ref, qd_ref, tau, tau_fb, ...)
  plots/         tracking errors (as the simulation's), plots/parity/ HIL vs simulation
  sim/           the simulation's own outputs (parity)
  bundles/       the bundles both ran, copied at the start (a re-export meanwhile changes nothing)

    config.py       what is asked, checked; what the runtime and the target are handed per run
    target_runs.py  one run on the target: the runtime loop, its record, its results entry
    run.py          the whole experiment: the runs, the simulation twin meanwhile, the outputs
    parity.py       HIL against the simulation, run by run
    tables.py       table.md (Table II's layout, the parity table) and the parity plots
"""

from models.hil_experiment.config import (
    HIL_MODES,
    HilOptions,
    conditions_yaml,
    initial_state,
    run_start,
)
from models.hil_experiment.parity import parity
from models.hil_experiment.run import run_hil_experiment
from models.hil_experiment.tables import PAPER_TABLE_II, format_hil_table
from models.hil_experiment.target_runs import HilRun, run_on_target

__all__ = [
    "HIL_MODES",
    "PAPER_TABLE_II",
    "HilOptions",
    "HilRun",
    "conditions_yaml",
    "format_hil_table",
    "initial_state",
    "parity",
    "run_hil_experiment",
    "run_on_target",
    "run_start",
]
