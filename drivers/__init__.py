"""CAN joint-drive layer: transports from config, CANopen CiA 402 protocol, bus-load budget."""
