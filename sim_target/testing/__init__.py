"""Test support for code that talks to drives or to the simulated target (as ``drivers.testing``
is for code that drives joints): importable by the tests and the benchmarks alike, no ``sys.path``
edits, no bare-name imports.

- :mod:`sim_target.testing.fake_plant`: a double-integrator plant, lock-stepped to emulated drives.
- :mod:`sim_target.testing.drive_rig`: ``DriveBus`` + emulated drives + fake plant on one
  in-process virtual bus.
- :mod:`sim_target.testing.hil_target`: the pybullet target in this process or as
  ``hil target serve`` in another one, ``hil run`` as a child process, and the driver master's
  config for it.
- :mod:`sim_target.testing.drive_process`: emulated drives + fake plant in a process of their own
  (bridge or ipc bus), for the cross-process drive-bus test and benchmark.
- :mod:`sim_target.testing.notify`: a stand-in for systemd's ``$NOTIFY_SOCKET``.
- :mod:`sim_target.testing.ur5`: ur5_paper's six emulated drives (joint names, node ids, max
  torques, start pose, the shipped PD bundle) as the HIL tests, benchmarks and fault rig configure them.
"""
