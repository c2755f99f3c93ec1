"""CAN joint-drive layer: transports from config, CANopen CiA 402 protocol, bus-load budget.

- :mod:`drivers.config`: frozen :class:`~drivers.config.DriveBusConfig` (transport, joints, period).
- :mod:`drivers.transport`: a python-can bus from config (virtual, socketcan, remote bridge, slcan).
- :mod:`drivers.busload`: worst-case bus load per cycle; refuses configs above 85 %.
- :mod:`drivers.cia402`: pure frame/SDO codecs, state machine, scaling, EDS (shared with sim_target).
- :mod:`drivers.drive_bus`: :class:`~drivers.drive_bus.DriveBus`, what the runtime calls.
- :mod:`drivers.errors`: the typed exception tree.
"""
