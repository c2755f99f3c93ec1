"""The deployable HIL daemon: config, bundle loading, the control loop, safety, telemetry, CLI.

Imports only light packages (numpy, onnxruntime, python-can, zenoh) and ``drivers``; never
``models``, torch, pinocchio or pybullet (docs/architecture.md).
"""
