"""Test support for code that talks to drives or to the simulated target (as ``drivers.testing``
is for code that drives joints): importable by the tests and the benchmarks alike, no ``sys.path``
edits, no bare-name imports.

- :mod:`sim_target.testing.fake_plant`: a double-integrator plant, lock-stepped to emulated drives.
- :mod:`sim_target.testing.drive_rig`: ``DriveBus`` + emulated drives + fake plant on one
  in-process virtual bus.
- :mod:`sim_target.testing.hil_target`: the pybullet target in this process or as
  ``hil target serve`` in another one, and the driver master's config for it.
"""
