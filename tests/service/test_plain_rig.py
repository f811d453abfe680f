"""The service takes a plain UsdSkel hand as another tool wrote it (centimetres, Y-up, a
transform on the SkelRoot, float32 matrices, no handretarget DOF spec): the rig upload reads it
with DOFs by role, and a job on it runs to a result with an animation layer."""

from __future__ import annotations

import json

import pytest

from plain_usd import write_plain_usdskel
from retarget_core.rig.usd_io import read_rig_usd
from retarget_core.transfer.annotations import save_annotations
from retarget_core.transfer.propose import propose

from .conftest import FAST


@pytest.fixture(scope="module")
def dana(service):
    return service.client("dana")


def test_a_plain_usdskel_hand_is_accepted_and_retargets(dana, inputs, tmp_path):
    import numpy as np

    target = inputs["target"]
    placed = np.eye(4)
    placed[:3, 3] = (40.0, -12.0, 3.0)  # cm
    path = write_plain_usdskel(
        tmp_path / "plain_hand.usda", joint_names=target.joint_names, parents=[j.parent for j in target.joints],
        bind_world=target.kinematics().bind_world, vertices=target.surface.vertices, faces=target.surface.faces,
        joint_indices=target.surface.joint_indices, joint_weights=target.surface.joint_weights,
        meters_per_unit=0.01, up_axis="Y", skel_root_transform=placed, float32=True)
    rig = read_rig_usd(path)
    annotations = tmp_path / "annotations.json"
    save_annotations(propose(inputs["source"], rig).annotations, annotations)
    uploaded = dana.upload("rig", path)
    ids = {"clip": dana.upload("clip", inputs["clip"])["id"], "rig": uploaded["id"],
           "annotations": dana.upload("annotations", annotations)["id"]}
    final = dana.wait(dana.submit(**ids, overrides=FAST, evaluate=False)["id"], timeout=600, poll=0.2)
    assert final["state"] == "succeeded", final["error"]
    doc = json.loads(dana.artifact(final["id"], "result.json"))
    assert doc["dof_names"] == rig.dof_names
    assert b"SkelAnimation" in dana.artifact(final["id"], "animation.usda")
