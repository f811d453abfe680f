"""GRAB captures end to end (issue 19): a GRAB-format sequence with known poses on a hand-shaped
MANO model the test builds itself (tests/mano_hand.py: the 25 marker vertex ids on their
landmarks, non-zero hands_mean, the wrist off the origin), imported with its MANO source rig,
proposed MANO -> MANO and onto every demo hand, retargeted with no source-rig flag.

Figures printed with ``pytest -s``: finger rotation RMSE (degrees) over contact frames and the
median contact distance (mm) at the delivered curves."""

from __future__ import annotations

import json
import shutil
from dataclasses import replace

import numpy as np
import pytest

from grab_hand_sequence import geodesic_degrees, run_cli, write_known_sequence
from retarget_core.clip import load_clip
from retarget_core.clip.grab import rodrigues
from retarget_core.clip.markers import MANO_MARKERS
from retarget_core.errors import InputError
from retarget_core.inputs import clip_source_rig, file_sha256, load_inputs
from retarget_core.rig.hand_cut import cap_faces, surface_matches_hand, uncapped_faces
from retarget_core.rig.hand_model import hand_model
from retarget_core.rig.io import load_rig
from retarget_core.rig.mano import dofs_from_mano, joint_rotations
from retarget_core.transfer.annotations import load_annotations

#: Done-when bounds: finger rotation RMSE (degrees) and median contact distance (mm) MANO -> MANO;
#: median contact distance onto the human-like demo hands and onto the others (mm).
MANO_RMSE_DEG, MANO_CONTACT_MM = 2.0, 2.0
HUMAN_MM, OTHER_MM = 3.0, 5.0
HUMAN_LIKE = ("source_human", "human_alt")
OTHERS = ("witch", "alien", "prosthetic_1dof", "prosthetic_2dof", "robot4")


@pytest.fixture(scope="module")
def imported(tmp_path_factory):
    root = tmp_path_factory.mktemp("grab")
    known = write_known_sequence(root)
    clip_path = root / "clips" / "s1_bottle.npz"
    clip_path.parent.mkdir()
    printed = run_cli("import-grab", known.path, "--mano", known.mano, "--grab-root", root, "--out", clip_path)
    return known, clip_path, clip_path.with_name("s1_bottle.source_rig.usda"), printed


def test_import_writes_the_mano_rig_beside_the_clip(imported):
    known, clip_path, rig_path, printed = imported
    assert rig_path.is_file() and str(rig_path) in printed
    clip = load_clip(clip_path)
    assert clip.source_rig == rig_path.name and clip.source_rig_sha256 == file_sha256(rig_path)
    assert clip_source_rig(clip, clip_path) == str(rig_path.resolve())
    rig = load_rig(rig_path)
    assert rig.n_dofs == 51 and rig.dof_names[:6] == ["root_tx", "root_ty", "root_tz", "root_rx", "root_ry", "root_rz"]
    # the capped surface: the model's triangles first, the wrist's fan after them
    n = len(clip.hand_faces)
    assert uncapped_faces(rig) == n < len(rig.surface.faces)
    np.testing.assert_array_equal(rig.surface.faces[:n], clip.hand_faces)
    np.testing.assert_array_equal(cap_faces(rig), np.arange(n, len(rig.surface.faces)))
    assert surface_matches_hand(rig, clip.hand_faces, clip.hand_vertices.shape[1])
    assert rig.surface.topology().closed
    assert rig.metadata["markers"] == MANO_MARKERS
    model = hand_model(rig)  # the rig's own mapping: MANO's fingers, right hand
    assert model.handedness == "right" and model.finger_names == ["thumb", "index", "middle", "ring", "pinky"]
    # the rig's skin at the true DOFs is MANO's blend skinning (without MANO's pose correctives)
    q = dofs_from_mano(rig, known.global_orient, known.finger_pose, known.transl)
    skinned = rig.kinematics().skin(q[60])[:778]
    assert np.abs(skinned - known.hand_vertices[60]).max() < 0.003
    np.testing.assert_allclose(joint_rotations(rig, q[:5]), rodrigues(known.finger_pose[:5].reshape(5, 15, 3)),
                               atol=1e-9)


def test_recorded_rig_is_used_only_beside_the_clip_and_unchanged(imported, tmp_path):
    _, clip_path, rig_path, _ = imported
    clip = load_clip(clip_path)
    with pytest.raises(InputError, match="not a demo hand"):
        clip_source_rig(clip)  # no clip path: the service's case, a path is never opened
    moved = tmp_path / "elsewhere.npz"
    shutil.copy(clip_path, moved)
    with pytest.raises(InputError, match="is not beside the clip"):
        clip_source_rig(clip, moved)
    shutil.copy(rig_path, tmp_path / rig_path.name)
    (tmp_path / rig_path.name).write_text((tmp_path / rig_path.name).read_text() + "\n# edited\n")
    with pytest.raises(InputError, match="has changed since the clip was made"):
        clip_source_rig(clip, moved)
    for bad in ("../s1_bottle.source_rig.usda", str(rig_path.resolve()), "rig.obj"):
        with pytest.raises(InputError, match="USD file in the clip's own folder"):
            clip_source_rig(replace(clip, source_rig=bad), clip_path)


def test_proposal_from_mano_uses_the_paper_marker_vertices(imported, tmp_path):
    _, clip_path, _, _ = imported
    out = tmp_path / "ann.json"
    run_cli("annotate", "propose", "--source", clip_path, "--target", "demo:human_alt@0.006", "--out", out)
    ann = load_annotations(out)
    rig = load_rig(clip_path.with_name("s1_bottle.source_rig.usda"))
    assert sorted(m.name for m in ann.markers) == sorted(MANO_MARKERS)
    for marker in ann.markers:
        (point,) = marker.source
        corners = rig.surface.faces[point.face]
        assert corners[int(np.argmax(point.barycentric))] == MANO_MARKERS[marker.name]
        assert max(point.barycentric) == pytest.approx(1.0)


def _retarget(clip_path, rig, annotations, out, *frames) -> dict:
    run_cli("retarget", "--clip", clip_path, "--rig", rig, "--annotations", annotations, "--out", out, "--workers", 2,
            *frames)
    return json.loads((out / "result.json").read_text())


def test_mano_to_mano_recovers_the_finger_rotations(imported, tmp_path):
    known, clip_path, rig_path, _ = imported
    ann = tmp_path / "mano.json"
    run_cli("annotate", "propose", "--source", clip_path, "--target", rig_path, "--out", ann)
    result = _retarget(clip_path, rig_path, ann, tmp_path / "out")  # no --source-rig: the clip's own
    assert result["provenance"]["inputs"]["source_rig"]["path"] == str(rig_path.resolve())
    rig = load_rig(rig_path)
    delivered = np.array(json.loads((tmp_path / "out" / "animation.json").read_text())["values"])
    errors = geodesic_degrees(rodrigues(known.finger_pose.reshape(-1, 15, 3)), joint_rotations(rig, delivered))
    rmse = float(np.sqrt(np.mean(errors[known.contact_frames] ** 2)))
    contact = result["summary"]["contact_distance_median_mm"]
    print(f"\nMANO -> MANO: finger rotation RMSE {rmse:.2f} deg over {int(known.contact_frames.sum())} contact frames "
          f"(worst joint {np.sqrt(np.mean(errors[known.contact_frames] ** 2, axis=0)).max():.2f}), "
          f"median contact distance {contact:.2f} mm (delivered curves)")
    assert rmse < MANO_RMSE_DEG
    assert contact < MANO_CONTACT_MM


@pytest.mark.parametrize("hand", HUMAN_LIKE + OTHERS)
def test_onto_every_demo_hand_without_a_source_rig_flag(imported, tmp_path, hand):
    _, clip_path, _, _ = imported
    rig = f"demo:{hand}@0.004"
    ann = tmp_path / f"{hand}.json"
    run_cli("annotate", "propose", "--source", clip_path, "--target", rig, "--out", ann)
    inputs = load_inputs(clip_path, rig, ann)
    assert inputs.source_rig.name == "mano_right"
    # the grasp and the start of the hold (frames 40:140 of the 200), to keep the suite short
    contact = _retarget(clip_path, rig, ann, tmp_path / hand, "--frames", "40:140")["summary"][
        "contact_distance_median_mm"]
    bound = HUMAN_MM if hand in HUMAN_LIKE else OTHER_MM
    print(f"\nMANO -> {hand}: median contact distance {contact:.2f} mm (bound {bound})")
    assert contact <= bound


def test_sequence_without_table_or_contacts(imported, tmp_path):
    """GRAB sequences may have no table and a hand that never touches the object: both import,
    the latter says so, and its retarget follows the markers alone."""
    from grab_fixtures import write_grab_npz
    from retarget_core.clip.grab import load_grab_sequence

    known, clip_path, _, _ = imported
    assert load_clip(clip_path).table_pose is None  # the sequence has no table: the clip has none
    seq = load_grab_sequence(known.path)
    seq["contact"]["object"] = np.zeros_like(seq["contact"]["object"])
    seq["rhand"]["vtemp"] = "tools/subject_meshes/male/nobody_rhand.ply"  # a template that is not there
    variant = write_grab_npz(tmp_path / "grab" / "s1" / "untouched.npz", seq)
    out = tmp_path / "untouched.npz"
    printed = run_cli("import-grab", variant, "--mano", known.mano, "--grab-root", known.root, "--out", out)
    assert "touches the object in no frame" in printed and "MANO's mean shape" in printed
    ann = tmp_path / "ann.json"
    run_cli("annotate", "propose", "--source", out, "--target", "demo:human_alt@0.006", "--out", ann)
    run_cli("retarget", "--clip", out, "--rig", "demo:human_alt@0.006", "--annotations", ann, "--out", tmp_path / "r",
            "--frames", "0:60", "--workers", 2)
    summary = json.loads((tmp_path / "r" / "result.json").read_text())["summary"]
    assert summary["contact_frames"] == 0 and summary["contact_distance_median_mm"] is None
    assert summary["marker_error_median_mm"] < 10


def test_missing_object_mesh_names_grab_layout(imported, tmp_path):
    known, _, _, _ = imported
    with pytest.raises(InputError, match=r"tools/object_meshes/contact_meshes/<object>\.ply"):
        from retarget_core.clip.grab import import_grab

        import_grab(known.path, known.mano, grab_root=tmp_path)
