"""The laws' nominal model while a bundle is traced: the one torch RNE of models.dynamics.torch_rne.

``CompactNominal`` stands in for a law's ``NominalModel`` (H-infinity: gravity, SMC: inverse
dynamics) while the bundle is exported: the torch path runs ``SpatialRne`` (~70 ONNX nodes for a
6-joint arm, against 408 / 860 for the earlier compact RNEIDA and ~1,700 for the component-wise
one), numpy calls go to the original. Kept under this name so models.lmpc.bundle_export needs no change.
"""

from __future__ import annotations

from typing import Any

from models.dynamics.torch_rne import SpatialRne


class CompactNominal:
    """inverse_dynamics / gravity with the NominalModel signature; torch path SpatialRne, numpy delegated."""

    def __init__(self, original: Any) -> None:
        self.original = original
        self.rne = SpatialRne(original.robot)

    def inverse_dynamics(self, xp: Any, q: Any, qd: Any, qdd: Any) -> Any:
        import numpy as np

        if xp is np:
            return self.original.inverse_dynamics(xp, q, qd, qdd)
        return self.rne.inverse_dynamics(q, qd, qdd)

    def gravity(self, xp: Any, q: Any) -> Any:
        import numpy as np

        if xp is np:
            return self.original.gravity(xp, q)
        return self.rne.gravity_torque(q)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.original, name)
