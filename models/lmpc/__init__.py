"""LMPC (Sec. III-C): expert dataset, Theorem 2 sampling, the MLP torque emulator, policy bundles.

- ``dataset``: D_input, feedback-only closed-loop runs logged with everything the expert needs.
- ``sampling``: Theorem 2 weights and the optimal / uniform samplers.
- ``labels``: HMPC labels on the sampled states (D_sample); the labeler is pluggable.
- ``emulator``: the MLP and its training.
- ``bundle_export``: law step + emulator fused into one ONNX graph, with its manifest.
- ``controller``: ``make_lmpc_controller`` (mode ``lmpc``) runs a bundle through hil_runtime.bundle.
- ``pipeline``: dataset -> sampling -> labels -> training -> bundles, a module per stage; the
  command is ``hil pipeline`` (models/cli/pipeline.py).

See docs/lmpc.md.
"""

from models.lmpc.controller import LMPCController, make_lmpc_controller

__all__ = ["LMPCController", "make_lmpc_controller"]
