"""What a bundle from elsewhere must pass before onnxruntime sees it (docs/security.md, "Bundles").

- Names: ``files`` and ``graph.file`` are plain file names (no ``/``, no ``..``), regular files
  inside the bundle directory, never symlinks (a graph loaded from outside the bundle is refused).
- Sizes: the manifest, the graph and the probe rows are bounded (10^6 probe rows took 22.5 GB).
- The graph: one ONNX model, no external data (its tensors would be read from files no sha256
  covers), no local functions, only the ``ai.onnx`` operators this project's exporter emits
  (:data:`ALLOWED_OPERATORS`): no Loop, If or Scan (a Loop of 10^12 iterations hung the loader),
  no Where (a trojan ``Where(q0 > 2 rad, full torque)`` is refused by name).
- The manifest's identity: ``bundle_id`` is the sha256 of the manifest's canonical JSON (sorted
  keys, no whitespace) without ``bundle_id`` and ``signatures``; any edit changes it. It proves
  integrity, not origin: whoever can edit the manifest can recompute it. Origin is an Ed25519
  ``signatures`` entry over the id by a key the runtime config trusts (``bundle.trusted_keys``),
  made with ``hil bundle sign``.

Only the standard library, ``onnx`` (the protobuf reader; no graph is run here) and
``cryptography`` (Ed25519).
"""

from __future__ import annotations

import base64
import hashlib
import json
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any

MAX_MANIFEST_BYTES = 1 << 20  # the shipped manifests are 25-45 kB
MAX_GRAPH_BYTES = 64 << 20  # the shipped graphs are 0.2-0.3 MB
MAX_PROBE_ROWS = 256  # the exporter records 12 seeded rows and one per clamped joint (+1)
PROBE_RUN_TIMEOUT_S = 10.0  # the loader's graph runs (probes, saturation) are cancelled after this
FILE_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.-]{0,127}$")  # a plain name: no '/', no '..' prefix

# What models.lmpc.bundle_export emits (torch.onnx, opset 17) for every law and emulator design, read
# from the shipped bundles (models/bundles) and the freshly exported ones of the tests. Elementwise
# arithmetic, matrix products, reductions and shape plumbing; no control flow, no selection.
ALLOWED_OPERATORS = frozenset(
    {
        "Abs",
        "Add",
        "Cast",
        "Clip",
        "Concat",
        "Constant",
        "Div",
        "Gemm",
        "Greater",
        "MatMul",
        "Max",
        "Min",
        "Mul",
        "Neg",
        "ReduceMax",
        "ReduceSum",
        "Relu",
        "Reshape",
        "Sin",
        "Cos",
        "Slice",
        "Split",
        "Sub",
        "Tanh",
    }
)
_UNSIGNED_FIELDS = ("bundle_id", "signatures")


class BundleSecurityError(ValueError):
    """A bundle refused by these checks; the loader turns it into a BundleError."""


def canonical_manifest(raw: dict[str, Any]) -> bytes:
    """The manifest's canonical JSON (sorted keys, no whitespace) without its id and signatures."""
    body = {k: v for k, v in raw.items() if k not in _UNSIGNED_FIELDS}
    return json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=False, allow_nan=False).encode()


def compute_bundle_id(raw: dict[str, Any]) -> str:
    return hashlib.sha256(canonical_manifest(raw)).hexdigest()


def seal_manifest(raw: dict[str, Any]) -> dict[str, Any]:
    """``raw`` with its ``bundle_id`` set (and any signature dropped: it covered another id)."""
    sealed = {k: v for k, v in raw.items() if k not in _UNSIGNED_FIELDS}
    sealed["bundle_id"] = compute_bundle_id(sealed)
    return sealed


def write_manifest(path: Path, raw: dict[str, Any]) -> dict[str, Any]:
    """Seal ``raw`` and write it to ``path`` (the bundle's manifest.json); returns the sealed dict."""
    sealed = seal_manifest(raw)
    path.write_text(json.dumps(sealed, indent=1))
    return sealed


def check_bundle_id(raw: dict[str, Any], where: str) -> str:
    expected = compute_bundle_id(raw)
    got = raw.get("bundle_id")
    if got is None:
        raise BundleSecurityError(f"{where}: bundle_id: missing (re-export with `hil pipeline`, or `hil bundle seal`)")
    if got != expected:
        raise BundleSecurityError(
            f"{where}: bundle_id: {str(got)[:12]}… does not match the manifest's content ({expected[:12]}…): "
            "the manifest was edited after export"
        )
    return expected


def member_file(directory: Path, name: str, where: str) -> Path:
    """``directory / name`` for a plain file name naming a regular file inside it, never a symlink."""
    if not FILE_NAME.match(name) or name in (".", ".."):
        raise BundleSecurityError(f"{where}: '{name[:80]}' is not a plain file name inside the bundle")
    file = directory / name
    if file.is_symlink():
        raise BundleSecurityError(f"{where}: {file} is a symlink (a bundle holds its own files)")
    if not file.is_file():
        raise BundleSecurityError(f"{file}: missing file")
    if file.resolve().parent != directory.resolve():
        raise BundleSecurityError(f"{where}: {file} is not inside the bundle directory")
    return file


def read_bounded(file: Path, limit: int, what: str) -> bytes:
    size = file.stat().st_size
    if size > limit:
        raise BundleSecurityError(f"{file}: {size} bytes, above the {what} limit of {limit}")
    with open(file, "rb") as handle:
        data = handle.read(limit + 1)
    if len(data) > limit:
        raise BundleSecurityError(f"{file}: above the {what} limit of {limit} bytes")
    return data


def check_graph_bytes(data: bytes, file: Path) -> None:
    """One self-contained ONNX model of allowed operators (no external data, no functions)."""
    import onnx

    try:
        model = onnx.load_model_from_string(data)
    except Exception as exc:  # noqa: BLE001 - protobuf's DecodeError and onnx's own errors
        raise BundleSecurityError(f"{file}: not an ONNX model ({str(exc)[:120]})") from None
    if model.functions:
        raise BundleSecurityError(f"{file}: the graph defines local functions (not emitted by the exporter)")
    tensors = list(model.graph.initializer) + [
        a.t for n in model.graph.node for a in n.attribute if a.type == onnx.AttributeProto.TENSOR
    ]
    if any(t.data_location == onnx.TensorProto.EXTERNAL or t.external_data for t in tensors):
        raise BundleSecurityError(f"{file}: the graph reads tensors from external data files (refused)")
    for node in model.graph.node:
        if node.domain not in ("", "ai.onnx") or node.op_type not in ALLOWED_OPERATORS:
            domain = f"{node.domain}." if node.domain else ""
            raise BundleSecurityError(
                f"{file}: operator {domain}{node.op_type} (node '{node.name[:60]}') is not one the exporter emits "
                "(allowed: hil_runtime.bundle_security.ALLOWED_OPERATORS)"
            )
        if any(a.type in (onnx.AttributeProto.GRAPH, onnx.AttributeProto.GRAPHS) for a in node.attribute):
            raise BundleSecurityError(f"{file}: node '{node.name[:60]}' carries a subgraph (refused)")


def _key_id(public_raw: bytes) -> str:
    return hashlib.sha256(public_raw).hexdigest()[:16]


def load_public_key(path: Path) -> Any:
    """An Ed25519 public key from a PEM file (``hil bundle keygen`` writes one)."""
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey
    from cryptography.hazmat.primitives.serialization import load_pem_public_key

    try:
        key = load_pem_public_key(path.read_bytes())
    except (OSError, ValueError) as exc:
        raise BundleSecurityError(f"{path}: not a PEM public key ({str(exc)[:80]})") from None
    if not isinstance(key, Ed25519PublicKey):
        raise BundleSecurityError(f"{path}: not an Ed25519 public key")
    return key


def _raw_public(key: Any) -> bytes:
    from cryptography.hazmat.primitives.serialization import Encoding, PublicFormat

    raw: bytes = key.public_bytes(Encoding.Raw, PublicFormat.Raw)
    return raw


def sign_manifest(raw: dict[str, Any], private_key: Any) -> dict[str, Any]:
    """``raw`` sealed and signed (Ed25519 over the ASCII bundle id) by ``private_key``; earlier
    signatures over the same id are kept, one per key."""
    bundle_id = compute_bundle_id(raw)
    key_id = _key_id(_raw_public(private_key.public_key()))
    signature = base64.b64encode(private_key.sign(bundle_id.encode("ascii"))).decode("ascii")
    kept = [s for s in raw.get("signatures", []) if raw.get("bundle_id") == bundle_id and s.get("key") != key_id]
    return {**seal_manifest(raw), "signatures": [*kept, {"key": key_id, "ed25519": signature}]}


def check_signature(raw: dict[str, Any], bundle_id: str, trusted: Sequence[Any], where: str) -> str:
    """The key id of a trusted key whose signature over ``bundle_id`` verifies; refused otherwise."""
    from cryptography.exceptions import InvalidSignature

    by_id = {_key_id(_raw_public(k)): k for k in trusted}
    signatures = raw.get("signatures") or []
    for entry in signatures:
        key = by_id.get(str(entry.get("key")))
        if key is None:
            continue
        try:
            key.verify(base64.b64decode(str(entry.get("ed25519", "")), validate=True), bundle_id.encode("ascii"))
        except (InvalidSignature, ValueError):
            raise BundleSecurityError(
                f"{where}: signatures: the signature of key {entry.get('key')} does not verify"
            ) from None
        return str(entry["key"])
    raise BundleSecurityError(
        f"{where}: signatures: none by a trusted key ({', '.join(sorted(by_id)) or 'none configured'}; "
        f"the bundle has {len(signatures)}): sign it with `hil bundle sign`"
    )
