"""Re-export the structured LMPC bundles from the trained weights, without rollouts or a refit.

    python -m models.lmpc.reexport                                  # results/lmpc -> models/bundles
    python -m models.lmpc.reexport --work W --bundles B --laws pd,smc --residual-bound-scale 10

``hil pipeline --design structured --work W`` keeps each law's trained emulator in
``W/trained_<law>.pt`` (torch weights, the frozen physics coefficients, the trust box and the labels'
max |tau* - tau_fb|: models.lmpc.structured.save_trained). This rebuilds the bundles with the graph
code of the working tree (e.g. after a change to the ONNX graph) in about a second per law; every
bundle is verified (onnxruntime vs torch, the loader's checks with freshly recorded probes).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from models.errors import ModelInputError

DEFAULT_WORK = Path("results/lmpc")  # hil pipeline's default --work


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m models.lmpc.reexport", description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=DEFAULT_WORK, help="where the pipeline left trained_<law>.pt")
    parser.add_argument("--bundles", type=Path, default=Path("models/bundles"), help="<bundles>/<robot>/<law>/")
    parser.add_argument("--laws", default="", help="comma-separated laws (default: every trained file)")
    parser.add_argument("--residual-bound-scale", type=float, default=None, help="override the recorded scale")
    args = parser.parse_args(argv)
    from hil_runtime.bundle import BundleError
    from models.lmpc.structured import reexport

    try:
        if args.residual_bound_scale is not None and not args.residual_bound_scale > 0:
            raise ModelInputError(f"--residual-bound-scale: must be > 0, got {args.residual_bound_scale}")
        laws = tuple(x.strip() for x in args.laws.split(",") if x.strip())
        reexport(args.work, args.bundles, laws, args.residual_bound_scale)
    except (ModelInputError, BundleError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return exc.exit_code
    return 0


if __name__ == "__main__":
    sys.exit(main())
