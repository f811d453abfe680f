"""Both hands of a GRAB sequence (issue 19): the left hand with its own MANO_LEFT model, a right
rig's mirror (``rig mirror``) with the annotations mirrored too; on a sequence whose left hand is
the mirror image of the right (the same bottle held from both sides), the left result mirrors
the right one."""

from __future__ import annotations

import json

import numpy as np
import pytest

from grab_hand_sequence import MIRROR, run_cli, write_known_sequence
from retarget_core.clip import load_clip
from retarget_core.errors import InputError
from retarget_core.rig.hand_model import hand_model
from retarget_core.rig.io import load_rig
from retarget_core.rig.mirror import mirror_rig

#: Done-when bound: the left result's delivered hand against the mirror of the right one, mean
#: over the hand's vertices in each frame (m).
MIRROR_TOLERANCE = 0.001
#: Every vertex in every frame stays within this (m): the frame solves are not bitwise mirrored
#: (measured: the last 40 frames drift to 1.47 mm at worst while the root's Euler angles sit near
#: gimbal lock, ry = 85 deg, where the two hands' solves part by 0.1 deg).
MIRROR_VERTEX_MAX = 0.002


@pytest.fixture(scope="module")
def both(tmp_path_factory):
    root = tmp_path_factory.mktemp("grab2")
    known = write_known_sequence(root, n_frames=140, lead=40, both_hands=True, name="bottle_both")
    out = root / "clips" / "s1.npz"
    out.parent.mkdir()
    run_cli("import-grab", known.path, "--mano", known.mano, "--mano-left", root / "mano" / "MANO_LEFT.pkl",
         "--hand", "both", "--grab-root", root, "--out", out)
    return root, known


def test_both_hands_import_as_two_clips_sharing_the_object(both):
    root, _ = both
    right, left = load_clip(root / "clips" / "s1_right.npz"), load_clip(root / "clips" / "s1_left.npz")
    assert (right.hand, left.hand) == ("right", "left")
    np.testing.assert_array_equal(right.object_poses, left.object_poses)
    # the left hand's GRAB codes (21, 26-40) are stored in the right-hand numbering
    assert set(np.unique(left.contact_labels)) <= {0, 22, *range(41, 56)} and left.contact_labels.any()
    # mirrored motion: the left hand is the right one reflected, the same vertex ids
    np.testing.assert_allclose(left.hand_vertices, right.hand_vertices @ MIRROR, atol=1e-6)
    np.testing.assert_array_equal((left.contact_labels > 0).sum(axis=1) > 0, (right.contact_labels > 0).sum(axis=1) > 0)
    rig = load_rig(root / "clips" / "s1_left.source_rig.usda")
    assert hand_model(rig).handedness == "left" and rig.surface.topology().closed


def test_right_model_as_left_is_refused(both):
    root, known = both
    with pytest.raises(InputError, match="right"):
        from retarget_core.clip.grab import load_mano_model

        load_mano_model(known.mano, "left")


def test_mirror_rig_poses_the_mirror_image():
    from retarget_core.rig.demo_hands import demo_hand

    rig = demo_hand("human_alt", 0.006)
    left = mirror_rig(rig)
    assert left.dof_names == rig.dof_names and hand_model(left).handedness != hand_model(rig).handedness
    rng = np.random.default_rng(4)
    for _ in range(3):
        q = rig.random_pose(rng)
        q[:6] = 0.0  # the free root keeps its world axes
        np.testing.assert_allclose(left.kinematics().skin(q), rig.kinematics().skin(q) @ MIRROR, atol=1e-9)
    assert left.surface.topology().closed


def test_left_result_mirrors_the_right(both, tmp_path):
    root, _ = both
    clips = root / "clips"
    right_rig, left_rig = tmp_path / "human_alt_right.usda", tmp_path / "human_alt_left.usda"
    run_cli("rig", "demo", "--out", tmp_path / "lib", "--hand", "human_alt", "--resolution", "0.006")
    (tmp_path / "lib" / "human_alt.usda").rename(right_rig)
    ann_right, ann_left = tmp_path / "right.json", tmp_path / "left.json"
    run_cli("annotate", "propose", "--source", clips / "s1_right.npz", "--target", right_rig, "--out", ann_right)
    printed = run_cli("rig", "mirror", right_rig, "--out", left_rig, "--annotations", ann_right, "--annotations-out", ann_left)
    assert str(left_rig) in printed
    results = {}
    for side, rig, ann in (("right", right_rig, ann_right), ("left", left_rig, ann_left)):
        out = tmp_path / side
        run_cli("retarget", "--clip", clips / f"s1_{side}.npz", "--rig", rig, "--annotations", ann, "--out", out,
             "--workers", 2)
        values = np.array(json.loads((out / "animation.json").read_text())["values"])
        target = load_rig(rig)
        results[side] = (np.stack([target.kinematics().skin(q) for q in values]),
                         json.loads((out / "result.json").read_text())["summary"])
    gap = np.linalg.norm(results["left"][0] - results["right"][0] @ MIRROR, axis=2)
    contact = {side: results[side][1]["contact_distance_median_mm"] for side in results}
    print(f"\nleft vs mirrored right: median {1000 * np.median(gap):.3f} mm, max {1000 * gap.max():.3f} mm over "
          f"{gap.shape[0]} frames; contact medians right {contact['right']:.2f}, left {contact['left']:.2f} mm")
    per_frame = gap.mean(axis=1)
    print(f"per-frame mean vertex gap: worst {1000 * per_frame.max():.3f} mm")
    assert per_frame.max() < MIRROR_TOLERANCE  # every frame's hand mirrors the right one's within 1 mm
    assert gap.max() < MIRROR_VERTEX_MAX
    assert abs(contact["left"] - contact["right"]) < 0.1
