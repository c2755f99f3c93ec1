"""CANopen CiA 301/402 for cyclic synchronous torque: pure frame codecs, the power state machine,
per-joint scaling and the drive's EDS. Shared by the driver (drivers.drive_bus) and the emulated
drives (sim_target.drives) so both ends agree byte for byte.
"""
