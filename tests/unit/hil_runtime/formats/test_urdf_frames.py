"""The /tf transforms of the live view against pybullet's forward kinematics of the same URDF."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hil_runtime.formats.urdf import _multiply, _rotate, find_urdf, joint_frames

pybullet = pytest.importorskip("pybullet")
URDF = Path(__file__).resolve().parents[4] / "models" / "robots" / "data" / "ur5_paper.urdf"


def test_composed_joint_transforms_match_pybullet_link_frames() -> None:
    frames = joint_frames(URDF.read_text())
    q = np.array([0.3, -0.7, 1.1, -0.4, 0.9, -1.3])
    client = pybullet.connect(pybullet.DIRECT)
    try:
        body = pybullet.loadURDF(str(URDF), useFixedBase=True, physicsClientId=client)
        by_name = {
            pybullet.getJointInfo(body, i, physicsClientId=client)[1].decode(): i
            for i in range(pybullet.getNumJoints(body, physicsClientId=client))
        }
        for j, frame in enumerate(frames[:6]):
            pybullet.resetJointState(body, by_name[frame.name], float(q[j]), physicsClientId=client)
        position, rotation = np.zeros(3), (0.0, 0.0, 0.0, 1.0)
        for j, frame in enumerate(frames):
            translation, local = frame.transform(float(q[j]) if j < 6 else 0.0)
            position = position + np.array(_rotate(rotation, translation))
            rotation = _multiply(rotation, local)
            state = pybullet.getLinkState(
                body, by_name[frame.name], computeForwardKinematics=True, physicsClientId=client
            )
            np.testing.assert_allclose(position, state[4], atol=1e-6, err_msg=frame.child)
            assert abs(abs(float(np.dot(rotation, state[5]))) - 1.0) < 1e-6, (
                frame.child
            )  # same rotation (q or -q); pybullet: float32
    finally:
        pybullet.disconnect(client)


def test_find_urdf_accepts_only_the_pinned_hash(tmp_path: Path) -> None:
    import hashlib

    digest = hashlib.sha256(URDF.read_bytes()).hexdigest()
    assert find_urdf("ur5_paper.urdf", digest) is not None
    assert find_urdf("ur5_paper.urdf", "0" * 64) is None
    other = tmp_path / "ur5_paper.urdf"
    other.write_text("<robot name='other'/>")
    assert find_urdf("ur5_paper.urdf", digest, bundle_dir=tmp_path) != other
