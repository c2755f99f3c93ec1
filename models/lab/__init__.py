"""The composition root of lab work: where the runtime, the pybullet target and their processes are
put together, once, for the demo (``hil demo``), the HIL experiment (``hil experiment --plant hil``)
and the fault campaign (``hil faults``), as ros2_control's node is the one place that builds and runs
its controller manager.

- :mod:`models.lab.configs`: the one runtime-config builder and the one target-config builder (and
  the writing and checking of both before any process starts)
- :mod:`models.lab.deploy`: ``hil config runtime``, a deployment's runtime config from a bundle and
  a drive table, checked as ``hil run`` checks it
- :mod:`models.lab.ports`: the one free loopback port helper
- :mod:`models.lab.rigs`: the rigs, runtime and target in one process or in two
- :mod:`models.lab.runs`: one HIL run of the experiment on a launched target (a runtime built by
  :func:`hil_runtime.factory.build_runtime`, its fault classified by :class:`FaultKind`)
- :mod:`models.lab.processes`: the demo's child processes, their signals, the private directory
- :mod:`models.lab.deploy`: ``hil config runtime``, a deployment config from a bundle and a drive table
- :mod:`models.lab.faults`: the fault campaign

Only this package may import ``drivers`` and the runtime beyond its public client APIs (the guard:
tests/unit/test_import_boundaries.py); the rest of ``models`` asks the lab.
"""
