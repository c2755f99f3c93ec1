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
        # A caller that needs its own ID(p_q, p_qd, p_a) in the same graph (models.lmpc.structured) sets
        # ``pending``; the law's next call then runs both as one batched RNE (one graph instead of two)
        # and leaves the caller's rows in ``pending_result``.
        self.pending: tuple[Any, Any, Any] | None = None
        self.pending_result: Any = None

    def _torch(self, q: Any, qd: Any, qdd: Any) -> Any:
        if self.pending is None:
            return self.rne.inverse_dynamics(q, qd, qdd)
        import torch

        (pq, pqd, pa), self.pending = self.pending, None
        n = q.shape[1]

        def rows(a: Any, b: Any) -> Any:  # interleaved (law, caller) rows: (2B, N)
            return torch.stack([a, b], 1).reshape(-1, n)

        out = self.rne.inverse_dynamics(rows(q, pq), rows(qd, pqd), rows(qdd, pa)).reshape(-1, 2, n)
        self.pending_result = out[:, 1]
        return out[:, 0]

    def inverse_dynamics(self, xp: Any, q: Any, qd: Any, qdd: Any) -> Any:
        import numpy as np

        if xp is np:
            return self.original.inverse_dynamics(xp, q, qd, qdd)
        return self._torch(q, qd, qdd)

    def gravity(self, xp: Any, q: Any) -> Any:
        import numpy as np

        if xp is np:
            return self.original.gravity(xp, q)
        zero = q * 0.0
        return self._torch(q, zero, zero)

    def __getattr__(self, name: str) -> Any:
        return getattr(self.original, name)
