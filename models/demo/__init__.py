"""``hil demo``: the runtime driving the emulated arm as separate processes, watched live.

    options.py     what is asked (law, mode, condition), checked before anything starts
    configs.py     the configs of the two processes (hil target serve, hil run)
    processes.py   what must not outlive the demo: the children, signals, the private directory
    session.py     the HIL run: the children started in order, followed, stopped in order
    view.py        the live view (and the --gui mirror)
    analysis.py    the run's numbers: scored beside the simulation twin, timing, telemetry check
    report.py      the output files
    run.py         all of it end to end; the command is models/cli/demo.py

The daemon and the target are the product's own commands (``hil run``, ``hil target serve``);
this package only composes them, which is why it lives on the science side: it also runs the
models simulator for the comparison.
"""

from models.demo.options import BEST_LMPC_LAW, DemoOptions

__all__ = ["BEST_LMPC_LAW", "DemoOptions"]
