"""The service takes a plain UsdSkel hand as another tool wrote it (centimetres, Y-up, a
transform on the SkelRoot, float32 matrices, no handretarget DOF spec): the rig upload reads it
with DOFs by role, and a job on it runs to a result with an animation layer."""

from __future__ import annotations

import json

import pytest
from pxr import Sdf, Usd, UsdGeom

from dcc_client.client import ServiceError

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
    # by default the layer sublayers the upload's own file name: placed beside the user's file, it plays there
    layer = tmp_path / "animation.usda"
    layer.write_bytes(dana.artifact(final["id"], "animation.usda"))
    assert b"SkelAnimation" in layer.read_bytes()
    assert list(Sdf.Layer.FindOrOpen(str(layer)).subLayerPaths) == ["plain_hand.usda"]
    stage = Usd.Stage.Open(str(layer))
    assert any(p.IsA(UsdGeom.Mesh) for p in stage.Traverse())  # the user's mesh, through the sublayer
    # what the panel shows: every DOF with its joint and limits, and where the DOFs came from
    info = uploaded["info"]
    assert [d["name"] for d in info["dof_limits"]] == rig.dof_names
    assert all(d["lower"] < d["upper"] for d in info["dof_limits"])
    assert "inferred by role" in info["dof_source"] and "free_root_added" in info


def test_the_layer_composes_over_the_users_own_file_placed_where_they_say(dana, inputs, tmp_path):
    """rig_asset_path: animation.usda sublayers the user's file by that path; placed beside it,
    USD's own skinning of the composed stage follows the core's rig (1e-5 m)."""
    import shutil

    import numpy as np
    from pxr import Usd

    from plain_usd import Z_UP_TO_Y_UP, skinned_world_points
    from retarget_core.export import read_dof_bsplines

    target = inputs["target"]
    path = write_plain_usdskel(
        tmp_path / "my_hand.usda", joint_names=target.joint_names, parents=[j.parent for j in target.joints],
        bind_world=target.kinematics().bind_world, vertices=target.surface.vertices, faces=target.surface.faces,
        joint_indices=target.surface.joint_indices, joint_weights=target.surface.joint_weights,
        meters_per_unit=0.01, up_axis="Y")
    rig = read_rig_usd(path)
    annotations = tmp_path / "annotations.json"
    save_annotations(propose(inputs["source"], rig).annotations, annotations)
    ids = {"clip": dana.upload("clip", inputs["clip"])["id"], "rig": dana.upload("rig", path)["id"],
           "annotations": dana.upload("annotations", annotations)["id"]}
    with pytest.raises(ServiceError, match="422"):
        dana.submit(**ids, overrides=FAST, evaluate=False, rig_asset_path="../outside.usda")
    final = dana.wait(dana.submit(**ids, overrides=FAST, evaluate=False, rig_asset_path="assets/my_hand.usda")["id"],
                      timeout=600, poll=0.2)
    assert final["state"] == "succeeded", final["error"]
    scene = tmp_path / "scene"
    (scene / "assets").mkdir(parents=True)
    shutil.copy(path, scene / "assets" / "my_hand.usda")
    layer = scene / "animation.usda"
    layer.write_bytes(dana.artifact(final["id"], "animation.usda"))
    stage = Usd.Stage.Open(str(layer))  # held: its layer expires with it
    assert [str(p) for p in stage.GetRootLayer().subLayerPaths] == ["assets/my_hand.usda"]
    assert b"SkelRoot" in dana.artifact(final["id"], "rig.usda")  # kept as well
    curves = read_dof_bsplines(layer)
    doc = json.loads(dana.artifact(final["id"], "result.json"))
    for frame in (0, len(doc["times"]) - 1):
        q = np.array([float(curves[n](frame / doc["fps"])) for n in rig.dof_names])
        usd = skinned_world_points(layer, time=frame) * 0.01 @ Z_UP_TO_Y_UP[:3, :3]
        assert np.abs(usd - rig.kinematics().skin(q)).max() <= 1e-5


def test_a_character_with_two_hands_is_uploaded_with_the_hand_root(dana, inputs, tmp_path):
    """Two hands in one skeleton: the upload says so and how to settle it; with ``hand_root``
    it is stored, proposed on and retargeted with that hand, and the same bytes with other
    options are refused (409) rather than silently reused."""
    from test_plain_usd import _body_arrays

    target = inputs["target"]
    path = write_plain_usdskel(tmp_path / "two_hands.usda", **_body_arrays(target, hands=2))
    with pytest.raises(ServiceError, match=r"422.*2 hands.*--hand-root"):
        dana.upload("rig", path)
    second = target.joint_names[0] + "_1"
    asset = dana.upload("rig", path, hand_root=second)
    local = read_rig_usd(path, hand_root=second)
    assert asset["info"]["load_options"] == {"hand_root": second} and asset["info"]["dofs"] == local.n_dofs
    with pytest.raises(ServiceError, match="409"):
        dana.upload("rig", path, hand_root=target.joint_names[0])
    proposed = dana.propose_annotations(asset["id"])
    ids = {"clip": dana.upload("clip", inputs["clip"])["id"], "rig": asset["id"], "annotations": proposed["id"]}
    final = dana.wait(dana.submit(**ids, overrides=FAST, evaluate=False)["id"], timeout=600, poll=0.2)
    assert final["state"] == "succeeded", final["error"]
    assert json.loads(dana.artifact(final["id"], "result.json"))["dof_names"] == local.dof_names
