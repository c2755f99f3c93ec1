"""CAN joint-drive layer: transports from config, CANopen CiA 301/402 by service, bus-load budget.

- :mod:`drivers.joint_bus`: the ``JointBus`` protocol the runtime's loop depends on;
  :mod:`drivers.checks` (``check_joint_bus``) and :mod:`drivers.testing` (``FakeJointBus``).
- :mod:`drivers.drive_bus`: :class:`~drivers.drive_bus.DriveBus`, the CiA 402 implementation: a
  composition of :mod:`~drivers.network`, :mod:`~drivers.nmt`, :mod:`~drivers.sdo`,
  :mod:`~drivers.pdo`, :mod:`~drivers.sync`, :mod:`~drivers.emcy`, :mod:`~drivers.supervision`
  and :mod:`drivers.profiles.p402` over one :class:`~drivers.node.DriveNode` per drive.
- :mod:`drivers.config`: frozen :class:`~drivers.config.DriveBusConfig` (transport, joints, period).
- :mod:`drivers.transport`: ``open_bus`` and its ``BACKENDS`` table (:mod:`drivers.interfaces`).
- :mod:`drivers.busload`: worst-case bus load per cycle; refuses configs above 85 %.
- :mod:`drivers.cia402`: pure frame/SDO codecs, state machine, scaling, EDS (shared with sim_target).
- :mod:`drivers.feedback`, :mod:`drivers.errors`: what a cycle returns, the typed exception tree.
"""
