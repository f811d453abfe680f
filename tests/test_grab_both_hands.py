"""Both hands of a GRAB sequence (issue 19): the left hand with its own MANO_LEFT model, a right
rig's mirror (``rig mirror``) with the annotations mirrored too; on a sequence whose left hand is
the mirror image of the right (the same bottle held from both sides), the left result mirrors
the right one."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial import cKDTree

from grab_hand_sequence import MIRROR, run_cli, write_known_sequence
from retarget_core.clip import load_clip
from retarget_core.errors import InputError
from retarget_core.execute import Executor
from retarget_core.inputs import load_inputs
from retarget_core.mesh.surface_points import SurfacePoints
from retarget_core.pairing.dense import pair_contacts
from retarget_core.pipeline import build_problem
from retarget_core.rig.hand_model import hand_model
from retarget_core.rig.io import load_rig
from retarget_core.rig.mirror import mirror_rig
from retarget_core.solve.config import load_config

#: Done-when bound: the left result's delivered hand against the mirror of the right one, mean
#: over the hand's vertices in each frame (m).
MIRROR_TOLERANCE = 0.001
#: The left and right runs' delivered curves score the same summed objective within this share:
#: the hand poses themselves may part where the objective is flat (below).
MIRROR_OBJECTIVE_SHARE = 0.01
#: The two runs' problems are mirror images to float rounding: every contact's and marker's
#: target point on the rest hand (m).
MIRROR_TARGET_TOLERANCE = 1e-7


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
        written = json.loads((out / "result.json").read_text())
        results[side] = (np.stack([target.kinematics().skin(q) for q in values]), written["summary"],
                         written["counts"]["fit"])
    gap = np.linalg.norm(results["left"][0] - results["right"][0] @ MIRROR, axis=2)
    contact = {side: results[side][1]["contact_distance_median_mm"] for side in results}
    print(f"\nleft vs mirrored right: median {1000 * np.median(gap):.3f} mm, max {1000 * gap.max():.3f} mm over "
          f"{gap.shape[0]} frames; contact medians right {contact['right']:.2f}, left {contact['left']:.2f} mm")
    per_frame = gap.mean(axis=1)
    print(f"per-frame mean vertex gap: worst {1000 * per_frame.max():.3f} mm")
    assert per_frame.max() < MIRROR_TOLERANCE  # every frame's hand mirrors the right one's within 1 mm
    assert abs(contact["left"] - contact["right"]) < 0.1
    # Both runs solved the mirror image of one problem ...
    problems = {side: _problem(clips / f"s1_{side}.npz", rig, ann)
                for side, rig, ann in (("right", right_rig, ann_right), ("left", left_rig, ann_left))}
    for f in range(problems["right"][1].contacts.frame_offsets.size - 1):
        right_points, left_points = (_target_points(problems[side], f) for side in ("right", "left"))
        assert len(right_points) == len(left_points)
        if len(right_points):
            # the frame's contacts may come in another order: each left one against its mirror
            nearest = cKDTree(right_points @ MIRROR).query(left_points)[0]
            assert nearest.max() < MIRROR_TARGET_TOLERANCE, f"frame {f}: a contact target {nearest.max()} m off"
    markers = {side: _marker_points(problems[side]) for side in problems}
    np.testing.assert_allclose(markers["left"], markers["right"] @ MIRROR, atol=MIRROR_TARGET_TOLERANCE)
    # ... and deliver curves that score the same on it. Single vertices may still part by a few mm
    # (3.5 mm measured): near the root's gimbal lock the redundant finger twists leave the
    # objective flat, so poses of equal score (within 0.1 % per frame) differ, and which one a
    # solve ends in depends on float rounding (a mirrored problem, or another BLAS kernel).
    score = {side: results[side][2]["polish"]["objective_after"] for side in results}
    print(f"delivered objective: right {score['right']:.1f}, left {score['left']:.1f}")
    assert abs(score["left"] - score["right"]) <= MIRROR_OBJECTIVE_SHARE * score["right"]


def _problem(clip, rig, annotations):
    """(target rig, problem) of a run with the default preset (the contact and marker targets)."""
    inputs = load_inputs(clip, rig, annotations)
    config = load_config(None, "default", {})
    problem, _ = build_problem(inputs.clip, pair_contacts(inputs.clip), inputs.source_rig, inputs.target_rig,
                               inputs.annotations, config, Executor())
    return inputs.target_rig, problem


def _target_points(rig_problem, f: int) -> np.ndarray:
    """(N_f, 3) frame f's contact targets on the rest hand (m)."""
    rig, problem = rig_problem
    points, _, _ = problem.contacts.frame(f)
    return points.positions(rig.surface.vertices, rig.surface.faces)


def _marker_points(rig_problem) -> np.ndarray:
    rig, problem = rig_problem
    m = problem.markers
    return SurfacePoints(m.target_faces, m.target_barycentric).positions(rig.surface.vertices, rig.surface.faces)
