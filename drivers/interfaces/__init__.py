"""One module per CAN interface :func:`drivers.transport.open_bus` can open (python-can's
``can/interfaces`` layout). Each exposes ``open_bus(config) -> can.BusABC``; the table that names
them is :data:`drivers.transport.BACKENDS`, and a module is imported only when its interface is
opened."""
