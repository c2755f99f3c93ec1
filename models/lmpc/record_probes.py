"""(Re-)record the behavioural-check probes of bundles: for bundles exported before the loader required
them, or before the probes clamped every joint's residual (issue 13).

    python -m models.lmpc.record_probes models/bundles/ur5_paper/*

The graph is not touched (its sha256 stays); only the manifest's ``probes`` are replaced: seeded
inputs (hil_runtime.bundle.make_probe_inputs), rows that clamp each joint's residual
(clamp_probe_inputs) and this machine's onnxruntime outputs for them. The manifest is validated with
the shared schema and replaced atomically; the bundle is then loaded with every check, as the
runtime will.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from hil_runtime.bundle import PolicyBundle, record_probes
from hil_runtime.bundle_schema import MANIFEST, Manifest
from hil_runtime.bundle_security import seal_manifest
from hil_runtime.outputs import write_text_atomic


def add_probes(bundle_dir: Path) -> None:
    manifest_path = bundle_dir / MANIFEST
    manifest = json.loads(manifest_path.read_text())
    manifest["probes"] = record_probes(bundle_dir)
    Manifest.model_validate(manifest)
    write_text_atomic(manifest_path, json.dumps(seal_manifest(manifest), indent=1))  # bundle_id recomputed
    PolicyBundle.load(bundle_dir)  # every check, the probes included


def main(argv: list[str]) -> int:
    for name in argv:
        add_probes(Path(name))
        print(f"probes recorded: {name}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
