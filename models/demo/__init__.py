"""``hil demo``: the runtime driving the emulated arm as separate processes, watched live.

models/demo/session.py runs it (processes, configs, the stop), models/demo/view.py shows it,
models/demo/report.py scores it beside the simulation and writes the outputs, models/demo/run.py
runs it end to end; the command is models/cli/demo.py. The daemon and the target are the product's
own commands (``hil run``, ``hil target serve``); this package only composes them, which is why it
lives on the science side: it also runs the models simulator for the comparison.
"""

from models.demo.session import BEST_LMPC_LAW, DemoOptions

__all__ = ["BEST_LMPC_LAW", "DemoOptions"]
