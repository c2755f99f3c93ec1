"""Bundles from elsewhere (issue 20): member names, sizes, the graph's operators and external data,
the manifest's bundle_id and Ed25519 signatures. Every refusal is one line naming the file."""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import onnx
import pytest
from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PrivateKey
from onnx import helper, numpy_helper

from hil_runtime.bundle import BundleError, PolicyBundle, sha256_file
from hil_runtime.bundle_security import (
    ALLOWED_OPERATORS,
    compute_bundle_id,
    seal_manifest,
    sign_manifest,
)

SHIPPED = Path(__file__).resolve().parents[3] / "models" / "bundles" / "ur5_paper"


def _copy(tmp_path: Path, law: str = "pd") -> Path:
    path = tmp_path / law
    shutil.copytree(SHIPPED / law, path)
    return path


def _manifest(path: Path) -> dict[str, Any]:
    data: dict[str, Any] = json.loads((path / "manifest.json").read_text())
    return data


def _write(path: Path, manifest: dict[str, Any], seal: bool = True) -> None:
    """The manifest as a careful attacker writes it: hashes fixed up and, with ``seal``, its id too."""
    (path / "manifest.json").write_text(json.dumps(seal_manifest(manifest) if seal else manifest))


def _refused(path: Path, *fragments: str, **kwargs: Any) -> str:
    with pytest.raises(BundleError) as info:
        PolicyBundle.load(path, **kwargs)
    text = str(info.value)
    assert "\n" not in text and info.value.exit_code == 2
    for fragment in fragments:
        assert fragment in text, text
    return text


def _edit_graph(path: Path, change: Callable[[onnx.ModelProto], None]) -> None:
    """Change the graph, then fix up its sha256 and reseal the manifest (so only the graph checks remain)."""
    model = onnx.load(str(path / "policy.onnx"))
    change(model)
    (path / "policy.onnx").write_bytes(model.SerializeToString())  # onnx.save would resolve external data
    manifest = _manifest(path)
    manifest["files"]["policy.onnx"] = sha256_file(path / "policy.onnx")
    _write(path, manifest)


def test_every_operator_of_the_shipped_graphs_is_allowed_and_control_flow_is_not() -> None:
    used = set()
    for law in ("pd", "pid", "adrc", "hinf", "smc", "mrac"):
        used |= {node.op_type for node in onnx.load(str(SHIPPED / law / "policy.onnx")).graph.node}
    assert used <= ALLOWED_OPERATORS
    assert not {"Loop", "If", "Scan", "Where"} & ALLOWED_OPERATORS


@pytest.mark.parametrize("name", ["../pd/policy.onnx", "/etc/passwd", "sub/policy.onnx", ".."])
def test_member_names_must_be_plain_file_names(tmp_path: Path, name: str) -> None:
    path = _copy(tmp_path)
    manifest = _manifest(path)
    manifest["files"] = {**manifest["files"], name: "0" * 64}
    _write(path, manifest)
    _refused(path, "is not a plain file name inside the bundle")


def test_a_graph_that_is_a_symlink_out_of_the_bundle_is_refused(tmp_path: Path) -> None:
    path = _copy(tmp_path)
    outside = tmp_path / "elsewhere.onnx"
    shutil.copy(path / "policy.onnx", outside)
    (path / "policy.onnx").unlink()
    os.symlink(outside, path / "policy.onnx")
    _refused(path, "is a symlink")


def test_a_manifest_edited_after_export_is_refused_by_its_bundle_id(tmp_path: Path) -> None:
    path = _copy(tmp_path)
    manifest = _manifest(path)
    manifest["limits"]["position_rad"] = [100.0] * 6  # widened limits, schema-valid
    manifest["law"]["name"] = "pd_renamed"
    _write(path, manifest, seal=False)
    _refused(path, "bundle_id:", "does not match the manifest's content")
    manifest.pop("bundle_id")
    _write(path, manifest, seal=False)
    _refused(path, "bundle_id: missing")


def test_a_manifest_with_a_key_twice_is_refused(tmp_path: Path) -> None:
    path = _copy(tmp_path)
    text = (path / "manifest.json").read_text()
    (path / "manifest.json").write_text(text.replace('{\n "schema"', '{\n "created": "x",\n "schema"', 1))
    _refused(path, "duplicate key 'created'")


def test_a_trojan_where_graph_is_refused_by_its_operator(tmp_path: Path) -> None:
    # Where(q0 > 2 rad, full torque, y): the graph passes every probe (no probe has q0 > 2)
    path = _copy(tmp_path)

    def trojan(model: onnx.ModelProto) -> None:
        graph = model.graph
        out = graph.output[0].name
        for node in graph.node:
            node.output[:] = ["y_raw" if o == out else o for o in node.output]
        for name, value in (("t_q0", 2.0), ("t_full", 102.0)):
            graph.initializer.append(numpy_helper.from_array(np.array([value]), name))
        for name, value in (("t_0", 0), ("t_1", 1), ("t_ax", -1)):
            graph.initializer.append(numpy_helper.from_array(np.array([value], np.int64), name))
        graph.node.extend(
            [
                helper.make_node("Slice", [graph.input[0].name, "t_0", "t_1", "t_ax"], ["t_q"]),
                helper.make_node("Greater", ["t_q", "t_q0"], ["t_on"]),
                helper.make_node("Where", ["t_on", "t_full", "y_raw"], [out]),
            ]
        )

    _edit_graph(path, trojan)
    _refused(path, "operator Where", "is not one the exporter emits")


def test_a_loop_graph_is_refused_before_onnxruntime_runs_it(tmp_path: Path) -> None:
    path = _copy(tmp_path)

    def loop(model: onnx.ModelProto) -> None:
        body = helper.make_graph(
            [helper.make_node("Identity", ["cond_in"], ["cond_out"])],
            "body",
            [
                helper.make_tensor_value_info("i", onnx.TensorProto.INT64, []),
                helper.make_tensor_value_info("cond_in", onnx.TensorProto.BOOL, []),
            ],
            [helper.make_tensor_value_info("cond_out", onnx.TensorProto.BOOL, [])],
        )
        model.graph.initializer.append(numpy_helper.from_array(np.array(10**12, np.int64), "l_trip"))
        model.graph.initializer.append(numpy_helper.from_array(np.array(True), "l_cond"))
        model.graph.node.insert(0, helper.make_node("Loop", ["l_trip", "l_cond"], [], body=body))

    _edit_graph(path, loop)
    _refused(path, "operator Loop")


def test_external_data_is_refused(tmp_path: Path) -> None:
    path = _copy(tmp_path)

    def external(model: onnx.ModelProto) -> None:
        tensor = model.graph.initializer[0]
        tensor.data_location = onnx.TensorProto.EXTERNAL
        entry = tensor.external_data.add()
        entry.key, entry.value = "location", "../../etc/hostname"

    _edit_graph(path, external)
    _refused(path, "external data")


def test_oversized_manifests_and_probe_tables_are_refused(tmp_path: Path) -> None:
    path = _copy(tmp_path)
    manifest = _manifest(path)
    manifest["training"]["padding"] = "x" * (1 << 20)
    _write(path, manifest)
    _refused(path, "above the manifest limit")
    manifest = _manifest(_copy(tmp_path / "b"))
    manifest["probes"]["inputs"] = manifest["probes"]["inputs"] * 20  # 320 rows
    manifest["probes"]["outputs"] = manifest["probes"]["outputs"] * 20
    _write(tmp_path / "b" / "pd", manifest)
    _refused(tmp_path / "b" / "pd", "probes.inputs")


def test_signatures_by_a_trusted_key(tmp_path: Path) -> None:
    path = _copy(tmp_path)
    lab, stranger = Ed25519PrivateKey.generate(), Ed25519PrivateKey.generate()
    trusted = [lab.public_key()]
    _refused(path, "signatures: none by a trusted key", trusted_keys=trusted)  # the shipped one is unsigned
    _write(path, sign_manifest(_manifest(path), stranger), seal=False)
    _refused(path, "none by a trusted key", trusted_keys=trusted)
    signed = sign_manifest(_manifest(path), lab)
    assert len(signed["signatures"]) == 2 and signed["bundle_id"] == compute_bundle_id(signed)
    _write(path, signed, seal=False)
    assert PolicyBundle.load(path, trusted_keys=trusted).law_name == "pd"
    forged = json.loads(json.dumps(signed))
    forged["signatures"][-1]["ed25519"] = forged["signatures"][0]["ed25519"]  # the stranger's bytes
    _write(path, forged, seal=False)
    _refused(path, "does not verify", trusted_keys=trusted)
    widened = json.loads(json.dumps(signed))
    widened["limits"]["velocity_rad_s"] = [1e9] * 6
    widened["bundle_id"] = compute_bundle_id(widened)  # resealed by the attacker, signatures kept:
    _write(path, widened, seal=False)  # they cover the old id
    _refused(path, "does not verify", trusted_keys=trusted)
    _write(path, widened)  # resealed without them: unsigned
    _refused(path, "none by a trusted key", trusted_keys=trusted)
