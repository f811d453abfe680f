"""Demonstration clips: coverage of the motions, validity, fingers really on the surface,
the table, ground truth, and contact pairing quality. Short versions of the clips keep the
suite fast; the grasps are the same as at full length."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from retarget_core.clip.demo import (
    CONTACT_THRESHOLD,
    DEMO_CLIPS,
    build_demo_timeline,
    clip_from_timeline,
    contact_code,
    source_rig,
    world_sdf,
)
from retarget_core.pairing import pair_contacts
from retarget_core.rig.anatomy import euler_xyz_from_matrix, root_transform

TIME_SCALE = 0.12


@pytest.fixture(scope="module")
def rig():
    return source_rig()


@pytest.fixture(scope="module")
def demos(rig):
    out = {}
    for name in DEMO_CLIPS:
        obj, timeline = build_demo_timeline(name, time_scale=TIME_SCALE, rig=rig)
        out[name] = (obj, timeline, clip_from_timeline(name, obj, timeline, rig, 0.004))
    return out


def test_the_motions_the_product_promises_are_covered():
    motions = " / ".join(m for _, m, _ in DEMO_CLIPS.values())
    for wanted in ("pick up and place", "in-hand rotation", "pinch", "power grasp", "handoff"):
        assert wanted in motions
    assert {o for o, _, _ in DEMO_CLIPS.values()} == {"box", "bottle", "apple", "mug", "hammer"}
    assert len(DEMO_CLIPS) >= 5


@pytest.mark.parametrize("name", list(DEMO_CLIPS))
def test_full_length_is_600_to_1200_frames_at_120_fps(demos, name):
    _, timeline, clip = demos[name]
    assert clip.fps == 120.0
    assert 600 <= timeline.nominal_frames <= 1200


@pytest.mark.parametrize("name", list(DEMO_CLIPS))
def test_clip_is_valid_with_markers_table_and_ground_truth(demos, rig, name):
    _, _, clip = demos[name]
    clip.validate()
    assert len(clip.marker_names) == 25
    assert clip.has_table and clip.dof_values.shape == (clip.n_frames, 54)
    kin = rig.kinematics()
    for f in (0, clip.n_frames // 2, clip.n_frames - 1):
        np.testing.assert_allclose(kin.skin(clip.dof_values[f]), clip.hand_vertices[f], atol=2e-6)


@pytest.mark.parametrize("name", list(DEMO_CLIPS))
def test_object_starts_and_ends_on_the_table(demos, name):
    _, _, clip = demos[name]
    table_top = clip.table_pose[2, 3] + clip.table_half_extents[2]
    for f in (0, clip.n_frames - 1):
        lowest = clip.object_world_vertices(f)[:, 2].min()
        assert abs(lowest - table_top) < 1e-3
    # and leaves it in between
    assert max(clip.object_world_vertices(f)[:, 2].min() for f in range(clip.n_frames)) > table_top + 0.05


@pytest.mark.parametrize("name", list(DEMO_CLIPS))
def test_fingers_close_on_the_surface_without_gaps_or_deep_penetration(demos, name):
    obj, timeline, clip = demos[name]
    held = np.nonzero(timeline.held)[0]
    assert len(held) > 0
    depths = []
    for f in held[:: max(1, len(held) // 8)]:
        sdf = world_sdf(obj, clip.object_poses[f])(clip.hand_vertices[f].astype(np.float64))
        depths.append(sdf.min())
    depths = np.array(depths)
    assert depths.max() < 0.0005, "a gap between the hand and the object it holds"
    assert depths.min() > -0.002, "the hand sinks into the object"
    # contacts are labelled on every held frame, with right-hand codes
    assert (clip.contact_labels[held] > 0).any(axis=1).all()


def test_in_hand_rotation_turns_the_object_relative_to_the_hand(demos, rig):
    _, timeline, clip = demos["apple_rotate"]
    held = np.nonzero(timeline.held)[0]
    relative = [np.linalg.inv(root_transform(rig, clip.dof_values[f])) @ clip.object_poses[f] for f in held]
    angles = [np.degrees(Rotation.from_matrix(relative[0][:3, :3].T @ r[:3, :3]).magnitude()) for r in relative]
    assert max(angles) > 90


def test_held_object_moves_rigidly_with_the_hand(demos, rig):
    _, timeline, clip = demos["bottle_pick_place"]
    held = np.nonzero(timeline.held)[0]
    relative = [np.linalg.inv(root_transform(rig, clip.dof_values[f])) @ clip.object_poses[f] for f in held]
    np.testing.assert_allclose(relative[-1], relative[0], atol=1e-9)


@pytest.mark.parametrize("name", list(DEMO_CLIPS))
def test_dense_pairing_quality(demos, name):
    _, _, clip = demos[name]
    summary = pair_contacts(clip).summary()
    assert summary["gap_median_mm"] < 2.0
    assert summary["discarded_fraction"] <= 0.10


def test_contact_codes_follow_grab():
    assert contact_code("wrist") == 22 and contact_code("root") == 22
    assert [contact_code(f"index{k}") for k in (1, 2, 3)] == [41, 42, 43]
    assert contact_code("thumb3") == 55 and contact_code("pinky1") == 47 and contact_code("ring2") == 51
    assert CONTACT_THRESHOLD == 0.002


def test_euler_decomposition_round_trips_including_gimbal_lock():
    def matrix(a, b, c):
        return Rotation.from_euler("XYZ", [a, b, c]).as_matrix()

    rotations = [Rotation.random(random_state=i).as_matrix() for i in range(50)]
    rotations += [matrix(0.3, np.pi / 2, 0.2), matrix(-1.0, -np.pi / 2, 0.7)]
    for r in rotations:
        np.testing.assert_allclose(matrix(*euler_xyz_from_matrix(r)), r, atol=1e-9)


def test_contact_labels_match_measuring_every_object_vertex(demos, rig):
    """label_contacts measures only object vertices that a hand vertex is near; the labels are
    those of measuring every object vertex against the whole hand surface (libigl), on the
    four frames with most contacts of two clips, and with the object scaled (a pose that is not rigid)."""
    import igl

    from retarget_core.clip.demo import label_contacts

    faces = rig.surface.faces
    owner = rig.surface.dense_weights(rig.n_joints).argmax(axis=1)
    codes = np.array([contact_code(n) for n in rig.joint_names], dtype=np.uint8)
    for name in ("mug_drink", "box_pinch"):
        obj, _, clip = demos[name]
        frames = np.sort(np.argsort((clip.contact_labels > 0).sum(axis=1), kind="stable")[-4:])
        poses = clip.object_poses[frames].copy()
        poses[-1, :3, :3] *= 1.05  # scaled about the object's origin
        hand = clip.hand_vertices[frames]
        labels = label_contacts(rig, hand, clip.object_vertices, poses)
        for k in range(len(frames)):
            world = clip.object_vertices @ poses[k][:3, :3].T + poses[k][:3, 3]
            d2, face, _ = igl.point_mesh_squared_distance(world, hand[k].astype(np.float64), faces)
            expected = np.where(d2 <= CONTACT_THRESHOLD**2, codes[owner[faces[face, 0]]], 0)
            assert (expected > 0).sum() > 10, (name, k)  # a grasp frame (a pinch touches ~20 vertices): something to compare
            np.testing.assert_array_equal(labels[k], expected)


def test_a_demo_clip_asked_again_is_an_independent_copy():
    """make_demo_clip keeps what it generated: asked again it gives the same clip, and what a
    caller does to its copy does not reach the next one."""
    from retarget_core.clip.demo import make_demo_clip

    rig = source_rig(0.006)
    first = make_demo_clip("box_pinch", time_scale=0.05, resolution=0.006, rig=rig)
    kept = first.contact_labels.copy()
    first.contact_labels[:] = 0
    first.hand_vertices += 1.0
    again = make_demo_clip("box_pinch", time_scale=0.05, resolution=0.006, rig=rig)
    np.testing.assert_array_equal(again.contact_labels, kept)
    assert (kept > 0).any() and np.abs(again.hand_vertices).max() < 1.0
    assert again is not first and again.hand_vertices is not first.hand_vertices
    # another rig under the same name (the surface moved 1 cm) is another clip, not the kept one
    moved = source_rig(0.006)
    moved.surface.vertices = moved.surface.vertices + np.array([0.01, 0.0, 0.0])
    other = make_demo_clip("box_pinch", time_scale=0.05, resolution=0.006, rig=moved)
    assert moved.name == rig.name and not np.array_equal(other.hand_vertices, again.hand_vertices)
