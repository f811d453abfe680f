"""Pictures of a retarget (retarget_core/render/preview.py): depth buffers, the view chosen so the
contacts can be seen (checked by ray casting, not by the renderer that chose it), the labelled
contact sheet and the animated preview written with every result."""

import json

import imageio.v3 as iio
import numpy as np
import pytest
import trimesh
from PIL import Image

from retarget_core.render.preview import (
    PREVIEW_MAX_FRAMES,
    SHEET_ROWS,
    VISIBLE_GOAL,
    PictureScene,
    choose_views,
    picture_frames,
    unoccluded,
)
from retarget_core.render.raster import Camera, box_mesh, depth_buffer, frame_camera, render_meshes


def ray_cast_visible(points, eye, meshes, tolerance=1.5e-3):
    """(N,) bool by embree ray casting: nothing in ``meshes`` (vertices, faces) is hit between the
    eye and each point, short of the point by more than ``tolerance`` metres."""
    mesh = trimesh.util.concatenate([trimesh.Trimesh(v, f, process=False) for v, f in meshes])
    eye = np.asarray(eye, dtype=np.float64)
    points = np.asarray(points, dtype=np.float64)
    offsets = points - eye
    reach = np.linalg.norm(offsets, axis=1)
    locations, index_ray, _ = mesh.ray.intersects_location(np.tile(eye, (len(points), 1)),
                                                           offsets / reach[:, None], multiple_hits=True)
    first = np.full(len(points), np.inf)
    np.minimum.at(first, index_ray, np.linalg.norm(locations - eye, axis=1))
    return first >= reach - tolerance


def test_depth_buffer_gives_the_distance_of_the_nearest_surface():
    near_plane = box_mesh((0.05, 0.05, 0.001), np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.02], [0, 0, 0, 1.0]]))
    far_plane = box_mesh((0.4, 0.4, 0.001))
    camera = Camera(eye=(0, 0, 0.5), target=(0, 0, 0), up=(0, 1, 0), projection="perspective", fov=40)
    depth = depth_buffer([near_plane, far_plane], camera, (64, 48))
    # the centre pixel sees the near plate's top (z = 0.021), a corner pixel the far plate (z = 0.001)
    assert depth[24, 32] == pytest.approx(0.5 - 0.021, abs=1e-9)
    assert depth[2, 2] > 0.5 - 0.001 and np.isfinite(depth[2, 2])
    image, also = render_meshes([near_plane, far_plane], camera, (64, 48), return_depth=True)
    np.testing.assert_allclose(also, depth)
    assert image.shape == (48, 64, 3)
    ortho = Camera(eye=(0, 0, 0.5), target=(0, 0, 0), up=(0, 1, 0), projection="orthographic", ortho_height=0.3)
    assert np.isinf(depth_buffer([near_plane], ortho, (64, 48))[0, 0])
    assert depth_buffer([near_plane], ortho, (64, 48))[24, 32] == pytest.approx(0.479, abs=1e-9)


def test_unoccluded_points_in_front_behind_and_outside():
    plate = box_mesh((0.05, 0.05, 0.005))  # 10 mm thick, seen with 3.8 mm pixels: tolerance 4.8 mm
    camera = Camera(eye=(0, 0, 0.5), target=(0, 0, 0), up=(0, 1, 0), fov=40)
    depth = depth_buffer([plate], camera, (96, 96))
    points = np.array([[0.0, 0.0, 0.005],  # on the plate's top: visible
                       [0.01, 0.0, -0.005],  # on its underside: hidden by the plate
                       [0.0, 0.0, -0.02],  # below it: hidden
                       [0.0, 0.0, 0.05],  # above it: visible
                       [1.0, 0.0, 0.0]])  # outside the image
    np.testing.assert_array_equal(unoccluded(points, depth, camera), [True, False, False, True, False])


def test_frame_camera_looks_along_a_given_direction():
    pts = np.random.default_rng(0).normal(size=(50, 3)) * 0.05
    cam = frame_camera(pts, view=(0.0, 0.0, -2.0), size=(100, 100))
    forward = cam.basis()[2]
    np.testing.assert_allclose(forward, [0, 0, 1], atol=1e-9)  # the eye below, looking up
    px = cam.project(pts, (100, 100))
    assert px.min() >= 0 and px.max() <= 100
    with pytest.raises(Exception, match="direction"):
        frame_camera(pts, view=(0.0, 0.0, 0.0))


def test_picture_frames():
    count = np.zeros(300)
    count[100:220] = 5
    sheet, preview = picture_frames(300, 120.0, count)
    assert len(sheet) == SHEET_ROWS and sheet[0] == 100 and sheet[-1] == 219 and np.all(count[sheet] > 0)
    assert np.all(np.diff(preview) == 5)  # 120 Hz shown at 24 Hz
    _, long_preview = picture_frames(5000, 120.0, count)
    assert len(long_preview) <= PREVIEW_MAX_FRAMES and long_preview[0] == 0
    sheet, _ = picture_frames(3, 30.0, None)  # no contacts: spread over all frames
    np.testing.assert_array_equal(sheet, [0, 1, 2])


def _top_down_scene():
    """A flat "hand" plate resting on top of a cube, its contacts on the plate's underside: seen
    from above (the usual view) the plate hides every contact."""
    cube_v, cube_f = box_mesh((0.03, 0.03, 0.03))
    plate_v, plate_f = box_mesh((0.06, 0.05, 0.01), np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.04],
                                                                [0, 0, 0, 1.0]]))
    g = np.linspace(-0.025, 0.025, 5)
    contacts = np.array([[x, y, 0.03] for x in g for y in g])

    return PictureScene(n_frames=3, fps=30.0, target_vertices=lambda f: plate_v, target_faces=plate_f,
                        target_contacts=lambda f: (contacts, contacts), object_vertices=cube_v, object_faces=cube_f,
                        object_poses=np.tile(np.eye(4), (3, 1, 1)), contact_count=np.full(3, len(contacts))), \
        (plate_v, plate_f), contacts


def test_the_view_shows_the_contacts_of_a_top_down_grasp():
    assert VISIBLE_GOAL == 0.7  # issue 21: at least 70 % of the contact points unoccluded
    scene, plate, contacts = _top_down_scene()
    directions, seen = choose_views(scene, [0, 1])
    assert len(directions) == 1 and seen["target_share"] >= VISIBLE_GOAL and seen["source_share"] is None
    assert directions[0][2] < 0  # from below, through the translucent cube
    visible = ray_cast_visible(contacts, seen["cameras"][0].eye, [plate])
    assert visible.mean() >= VISIBLE_GOAL
    # the usual three-quarter view from above sees none of them
    above = frame_camera(np.vstack([plate[0], scene.object_vertices]), view="three_quarter", size=(96, 96))
    assert ray_cast_visible(contacts, above.eye, [plate]).mean() < 0.1


def test_contacts_facing_two_ways_get_a_second_view():
    """Two thick plates either side of a block, contacts on their outer faces (facing +x and -x):
    any one view sees at most one face's half, two views see them all."""
    block_v, block_f = box_mesh((0.02, 0.03, 0.05))
    plates = [box_mesh((0.005, 0.035, 0.05), np.array([[1, 0, 0, s * 0.025], [0, 1, 0, 0], [0, 0, 1, 0],
                                                       [0, 0, 0, 1.0]])) for s in (-1, 1)]
    hand_v = np.vstack([plates[0][0], plates[1][0]])
    hand_f = np.vstack([plates[0][1], plates[1][1] + len(plates[0][0])])
    g = np.linspace(-0.02, 0.02, 5)
    contacts = np.array([[s * 0.03, y, z] for s in (-1, 1) for y in g for z in g])
    scene = PictureScene(n_frames=1, fps=30.0, target_vertices=lambda f: hand_v, target_faces=hand_f,
                         target_contacts=lambda f: (contacts, contacts), object_vertices=block_v,
                         object_faces=block_f, object_poses=np.eye(4)[None], contact_count=np.array([50]))
    directions, seen = choose_views(scene, [0])
    assert len(directions) == 2 and seen["view_shares"][0] <= 0.55 and seen["share"] >= VISIBLE_GOAL
    assert directions[0][0] * directions[1][0] < 0  # from either side
    by_rays = np.zeros(len(contacts), bool)
    for camera in seen["cameras"]:
        by_rays |= ray_cast_visible(contacts, camera.eye, [(hand_v, hand_f)])
    assert by_rays.mean() >= VISIBLE_GOAL
    assert ray_cast_visible(contacts, seen["cameras"][0].eye, [(hand_v, hand_f)]).mean() <= 0.55


@pytest.fixture(scope="module")
def apple_output(tmp_path_factory):
    """A short retarget of the top-down apple grasp onto another human hand, written with its pictures."""
    from retarget_core.clip.demo import grasp_window, make_demo_clip, source_rig
    from retarget_core.execute import Executor
    from retarget_core.inputs import RunInputs
    from retarget_core.pipeline import retarget
    from retarget_core.rig.demo_hands import demo_hand
    from retarget_core.solve.config import load_config
    from retarget_core.transfer.propose import propose_annotations

    source = source_rig(0.005)
    target = demo_hand("human_alt", resolution=0.005)
    clip = grasp_window(make_demo_clip("apple_rotate", resolution=0.005, rig=source), 40)
    config = load_config(None, "default", {"solver.maxeval": 15, "solver.root_maxeval": 10,
                                           "refinement.max_iterations": 2})
    result = retarget(RunInputs.of(clip, source, target, propose_annotations(source, target)), config,
                      Executor(workers=1))
    out = tmp_path_factory.mktemp("pictures")
    return result, target, clip, out, result.write(out)


def test_retarget_writes_a_contact_sheet_whose_view_shows_the_contacts(apple_output):
    result, target, clip, out, paths = apple_output
    doc = json.loads(paths["pictures.json"].read_text())
    sheet_frames = doc["sheet_frames"]
    assert 1 <= len(sheet_frames) <= SHEET_ROWS
    assert all(result.contact_count[f] > 0 for f in sheet_frames)
    assert doc["contacts_unoccluded_share"] >= VISIBLE_GOAL
    # checked again by ray casting against the delivered hand and the table, from the same eyes
    kin = target.kinematics()
    q = result.sampled()
    table = box_mesh(clip.table_half_extents, clip.table_pose)
    seen, total = 0, 0
    for f in sheet_frames:
        hand_points, _ = _contact_points(result, kin, q, f)
        visible = np.zeros(len(hand_points), bool)
        for view in doc["views"]:
            visible |= ray_cast_visible(hand_points, view["camera"]["eye"],
                                        [(kin.skin(q[f]), target.surface.faces), table], tolerance=3e-3)
        seen, total = seen + int(visible.sum()), total + len(visible)
    assert total > 0 and seen / total >= VISIBLE_GOAL
    image = Image.open(paths["contact_sheet.png"])
    assert image.size == (120 + 2 * 240 * len(doc["views"]), 34 + 22 + 240 * len(sheet_frames) + 46)
    pixels = np.asarray(image.convert("RGB")).astype(int)
    for r in range(len(sheet_frames)):  # each row's label column carries text
        top = 34 + 22 + 240 * r
        assert (pixels[top + 8:top + 70, 4:110] < 128).any()
        tile = pixels[top + 2:top + 238, 120 + 240 + 2:120 + 480 - 2]
        assert (np.abs(tile - 255).sum(axis=2) > 30).mean() > 0.05  # the target tile is not blank


def _contact_points(result, kin, q, f):
    from retarget_core.mesh.surface_points import SurfacePoints

    c = result.contacts
    sl = slice(int(c.frame_offsets[f]), int(c.frame_offsets[f + 1]))
    points = SurfacePoints(c.target_faces[sl], c.target_barycentric[sl])
    return kin.points(kin.pose(q[f]), kin.bind(points)), c.surface_points(f)


def test_the_preview_plays_the_delivered_curve_in_real_time(apple_output):
    result, target, clip, out, paths = apple_output
    doc = json.loads(paths["pictures.json"].read_text())
    frames = iio.imread(paths["preview.gif"], index=None)
    assert len(frames) == len(doc["preview_frames"]) and doc["preview_frames"][0] == 0
    step_ms = 1000.0 * doc["preview_frame_seconds"]
    assert step_ms == pytest.approx(1000.0 * (doc["preview_frames"][1] - doc["preview_frames"][0]) / clip.fps)
    assert abs(iio.immeta(paths["preview.gif"])["duration"] - step_ms) <= 10.0  # GIF times are in 10 ms
    assert iio.immeta(paths["preview.gif"])["loop"] == 0
    # the hand moves: the first and last pictures differ
    assert np.abs(frames[0].astype(int) - frames[-1].astype(int)).mean() > 1.0


def test_evaluate_draws_the_same_pictures_from_the_output_folder(apple_output):
    from retarget_core.evaluate.report import write_output_pictures

    _, _, _, out, paths = apple_output
    before = json.loads(paths["pictures.json"].read_text())
    again = write_output_pictures(out)
    after = json.loads(again["pictures.json"].read_text())
    # the folder keeps the object as float32 and the curves through JSON: the same views up to rounding
    views_before, views_after = before.pop("views"), after.pop("views")
    assert after == before
    assert [v["direction"] for v in views_after] == [v["direction"] for v in views_before]
    for a, b in zip(views_after, views_before):
        for key in ("eye", "target", "up"):
            np.testing.assert_allclose(a["camera"][key], b["camera"][key], atol=1e-6)
    redrawn = np.asarray(Image.open(again["contact_sheet.png"])).astype(int)
    assert np.abs(redrawn - np.asarray(Image.open(paths["contact_sheet.png"])).astype(int)).mean() < 0.5
