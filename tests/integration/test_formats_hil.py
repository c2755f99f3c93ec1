"""``hil run --record x.mcap --can-log x.blf`` on the lock-stepped pybullet target (one process):
every cycle of the run in the MCAP file (read by mcap + mcap-ros2-support), the real URDF and
manifest attached, every frame of the bus in the capture (read by python-can), decodable as CANopen.
The 10 s case at 1 kHz is heavy (benchmarks/bench_formats.py measures the cost)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import can
import numpy as np
import pytest
import yaml

from drivers.decode import Decoder
from hil_runtime.daemon import serve
from sim_target.testing.hil_target import target_in_process, unique_channel
from tests.integration.test_runtime_hil import runtime_config

mcap_reader = pytest.importorskip("mcap.reader")
mcap_ros2_decoder = pytest.importorskip("mcap_ros2.decoder")
REPO = Path(__file__).resolve().parents[2]


def _run(tmp_path: Path, duration_s: float) -> None:
    record, capture = tmp_path / "run.mcap", tmp_path / "run.blf"
    channel = unique_channel()
    with target_in_process(channel, 0.001):
        config = runtime_config(
            {"interface": "virtual", "channel": channel}, loop={"pacing": "bus", "duration_s": duration_s}
        )
        # This test is about what is recorded, not supervision: on a loaded 2-core machine the
        # in-process target's threads can miss heartbeats for seconds (seen at load average 22).
        config["bus"].update(heartbeat_timeout_s=10.0, comm_loss_timeout_s=10.0)
        (tmp_path / "rt.yaml").write_text(yaml.safe_dump(config))
        assert serve(tmp_path / "rt.yaml", record, can_log=capture) == 0

    with record.open("rb") as stream:
        reader = mcap_reader.make_reader(stream, decoder_factories=[mcap_ros2_decoder.DecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        counts = {summary.channels[i].topic: n for i, n in summary.statistics.channel_message_counts.items()}
        seqs = [json.loads(m.data)["seq"] for _, _, m in reader.iter_messages(topics=["/hil/cycle"])]
        first = next(reader.iter_decoded_messages(topics=["/joint_states"]))
        attachments = {a.name: a.data for a in reader.iter_attachments()}
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    cycles = int(round(duration_s / 0.001))
    assert counts["/joint_states"] == counts["/joint_reference"] == len(seqs) >= cycles
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))  # no cycle lost
    assert metadata["recording"]["dropped"] == "0"
    assert counts["/hil/status"] >= 2 and counts["/hil/events"] >= 1  # ACTIVE ... FINALIZED, activated
    msg = first.decoded_message
    assert list(msg.name)[0] == "shoulder_pan_joint" and len(msg.position) == 6 and np.all(np.isfinite(msg.effort))
    manifest = json.loads(attachments["manifest.json"])
    urdf_sha = hashlib.sha256(attachments[manifest["robot"]["urdf_file"]]).hexdigest()
    assert urdf_sha == manifest["robot"]["urdf_sha256"]  # the bundle's own robot description

    frames = list(can.LogReader(str(capture)))  # python-can's reader
    decoder = Decoder()
    kinds: dict[str, int] = {}
    for frame in frames:
        kind = decoder.decode(frame).kind
        kinds[kind] = kinds.get(kind, 0) + 1
    assert kinds["SYNC"] >= cycles and kinds["RPDO1"] >= 6 * cycles and kinds["TPDO1 FD"] >= 6 * cycles
    assert "malformed" not in kinds and "unknown" not in kinds
    assert {"NMT", "SDO", "heartbeat"} <= set(kinds)


def test_hil_run_records_mcap_and_captures_can_for_one_second(tmp_path: Path) -> None:
    _run(tmp_path, 1.0)


@pytest.mark.heavy
def test_ten_seconds_at_1_khz_lose_no_cycle_and_no_frame(tmp_path: Path) -> None:
    _run(tmp_path, 10.0)


def test_a_refused_start_up_leaves_no_capture_or_record(tmp_path: Path) -> None:
    from hil_runtime.bundle import BundleError

    (tmp_path / "empty_bundle").mkdir()
    config = runtime_config({"interface": "virtual", "channel": unique_channel()})
    config["bundle"]["path"] = str(tmp_path / "empty_bundle")
    (tmp_path / "rt.yaml").write_text(yaml.safe_dump(config))
    with pytest.raises(BundleError):
        serve(tmp_path / "rt.yaml", tmp_path / "run.mcap", can_log=tmp_path / "run.blf")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["empty_bundle", "rt.yaml"]
