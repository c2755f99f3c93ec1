"""``hil faults``: the fault-injection campaign (issue 15; docs/faults.md).

The campaign composes the pybullet target with the runtime (:class:`hil_runtime.runtime.Runtime`,
or ``hil run`` as its own process), injects every fault the rig can make, and writes a table of
what the runtime did. It is the one part of sim_target that imports hil_runtime (lazily, as
``models.hil_experiment`` does): the target itself never does.

- :mod:`models.lab.rigs`: the compositions (in process, or two processes) and what observes them
- :mod:`models.lab.faults.cases`: each fault's injection and the checks of its row
- :mod:`models.lab.faults.crafted`: misbehaving bundles, built at run time from a shipped one
- :mod:`models.lab.faults.campaign`: the list of faults, repeats, results.json and the table
"""
