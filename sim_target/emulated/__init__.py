"""The emulated CiA 402 drive, one module per protocol service (mirroring ``drivers/``).

- :mod:`.node`: the per-drive record :class:`~.node.EmulatedDrive`, the bank's config, counters;
- :mod:`.link`: sending frames, with the injected frame faults (drop, delay, corrupt);
- :mod:`.nmt`: boot-up, NMT commands, heartbeat producer (0x1017);
- :mod:`.objects`: the object dictionary behind canopen's SDO server (read/write hooks, resets);
- :mod:`.pdo`: RPDO reception, TPDO answers to SYNC, the PDO mappings a drive accepts;
- :mod:`.p402`: the power state machine step at SYNC, statusword, faults and EMCY;
- :mod:`.supervision`: loss of the master (heartbeat consumer 0x1016, RPDO timeout 0x1400:05,
  SYNC timeout 0x2101) and the reaction 0x6007.

:class:`sim_target.drives.EmulatedDrives` composes them with one receive thread.
"""
