"""The software renderer: coverage, z-buffer, shading, near-plane clipping and clip strips."""

import numpy as np
import pytest
import trimesh
from PIL import Image

from retarget_core.clip import Clip
from retarget_core.render import Camera, frame_camera, render_clip_strip, render_meshes
from retarget_core.render.raster import CONTACT_RED

WHITE = np.array([255, 255, 255])


def _front_ortho(height=2.0):
    return Camera(eye=(0, -5, 0), target=(0, 0, 0), up=(0, 0, 1), projection="orthographic", ortho_height=height)


def _is_bg(img):
    return np.all(img == 255, axis=-1)


def test_unit_cube_front_fills_centre_square():
    cube = trimesh.creation.box(extents=(1, 1, 1))
    img = render_meshes([(cube.vertices, cube.faces, (180, 120, 90))], _front_ortho(2.0), (200, 200))
    assert img.shape == (200, 200, 3) and img.dtype == np.uint8
    bg = _is_bg(img)
    # 1 m of a 2 m view over 200 px = a 100 px square, pixels 50..149 in both directions
    assert not bg[50:150, 50:150].any()
    assert bg[:49].all() and bg[151:].all() and bg[:, :49].all() and bg[:, 151:].all()
    ys, xs = np.nonzero(~bg)
    assert (ys.min(), ys.max(), xs.min(), xs.max()) == (50, 149, 50, 149)
    # the front face is flat: one colour well inside it
    inner = img[60:140, 60:140].reshape(-1, 3)
    assert np.ptp(inner, axis=0).max() <= 1
    # the silhouette is outlined (darker than the face inside it) unless outlines are off
    assert img[50, 100].sum() < img[100, 100].sum() - 60
    plain = render_meshes([(cube.vertices, cube.faces, (180, 120, 90))], _front_ortho(2.0), (200, 200), outline=False)
    assert np.array_equal(plain[50, 100], plain[100, 100])


def test_non_square_image_keeps_aspect():
    cube = trimesh.creation.box(extents=(1, 1, 1))
    img = render_meshes([(cube.vertices, cube.faces, (180, 120, 90))], _front_ortho(2.0), (300, 100))
    ys, xs = np.nonzero(~_is_bg(img))
    assert (ys.min(), ys.max()) == (25, 74)
    assert (xs.min(), xs.max()) == (125, 174)


@pytest.mark.parametrize("projection", ["orthographic", "perspective"])
def test_zbuffer_nearer_triangle_wins_in_either_order(projection):
    # red is nearer the eye (at y = -5) than blue; both cover the image centre
    red = (np.array([[-1.0, -1, -1], [1, -1, -1], [0, -1, 1]]), np.array([[0, 1, 2]]), (255, 0, 0))
    blue = (np.array([[-1.0, 1, -1], [1, 1, -1], [0, 1, 1]]) * [2, 1, 2], np.array([[0, 2, 1]]), (0, 0, 255))
    cam = Camera(eye=(0, -5, 0), target=(0, 0, 0), up=(0, 0, 1), projection=projection, ortho_height=3.0, fov=50)
    for meshes in ([red, blue], [blue, red]):
        img = render_meshes(meshes, cam, (120, 120), outline=False).astype(int)
        centre = img[60, 60]
        assert centre[0] > 100 and centre[1] == 0 and centre[2] == 0
        # outside the red triangle but inside the big blue one: blue
        corner = img[100, 20]
        assert corner[2] > 100 and corner[0] == 0


def test_face_turned_away_from_light_is_darker():
    # two squares side by side: one facing the camera (headlight), one turned 70 degrees away
    quad = np.array([[-0.5, 0, -0.5], [0.5, 0, -0.5], [0.5, 0, 0.5], [-0.5, 0, 0.5]])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    a = np.radians(70)
    rot = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    facing = quad + [-0.8, 0, 0]
    turned = quad @ rot.T + [0.8, 0, 0]
    cam = Camera(eye=(0, -5, 0), target=(0, 0, 0), up=(0, 0, 1), projection="orthographic", ortho_height=3.0)
    img = render_meshes([(facing, faces, (200, 200, 200)), (turned, faces, (200, 200, 200))], cam, (150, 150),
                        outline=False).astype(int)
    bright = img[75, 75 - 40].sum()
    dark = img[75, 75 + 40].sum()
    assert bright > dark + 60
    # back faces are lit too (two-sided): the same square wound the other way looks the same
    img2 = render_meshes([(facing, faces[:, ::-1], (200, 200, 200))], cam, (150, 150), outline=False).astype(int)
    assert abs(img2[75, 35].sum() - bright) <= 3


def test_per_vertex_colours_and_float_colours():
    cube = trimesh.creation.box(extents=(1, 1, 1))
    cols = np.zeros((len(cube.vertices), 3))
    cols[:, 1] = 1.0  # float 0-1 green
    img = render_meshes([(cube.vertices, cube.faces, cols)], _front_ortho(2.0), (100, 100), outline=False)
    px = img[50, 50].astype(int)
    assert px[1] > 100 and px[0] == 0 and px[2] == 0


def test_perspective_clips_geometry_behind_the_camera():
    # a big floor passing under and behind the eye: must still cover the lower half of the image
    floor = (np.array([[-10.0, -10, -1], [10, -10, -1], [10, 10, -1], [-10, 10, -1]]), np.array([[0, 1, 2], [0, 2, 3]]),
             (150, 120, 90))
    cam = Camera(eye=(0, 0, 0), target=(0, 1, 0), up=(0, 0, 1), projection="perspective", fov=60)
    img = render_meshes([floor], cam, (64, 64))
    bg = _is_bg(img)
    assert not bg[40:].any()  # below the horizon: floor
    assert bg[:28].all()  # above it: sky


def test_frame_camera_frames_points():
    pts = trimesh.creation.icosphere(subdivisions=3).vertices * 0.05 + [0.3, -0.2, 1.0]
    for view in ("front", "top", "side", "three_quarter"):
        for projection in ("orthographic", "perspective"):
            cam = frame_camera(pts, view=view, margin=0.1, size=(200, 100), projection=projection)
            px = cam.project(pts, (200, 100))
            assert px[:, 0].min() >= 0 and px[:, 0].max() <= 200
            assert px[:, 1].min() >= 0 and px[:, 1].max() <= 100
            # and reasonably tightly: the points span most of the height
            assert px[:, 1].max() - px[:, 1].min() > 55


def test_large_mesh_is_fast_enough():
    import time

    sphere = trimesh.creation.icosphere(subdivisions=6)  # 81,920 triangles
    cam = frame_camera(sphere.vertices, size=(320, 320))
    start = time.perf_counter()
    img = render_meshes([(sphere.vertices, sphere.faces, (200, 160, 130))], cam, (320, 320))
    assert time.perf_counter() - start < 5.0
    assert (~_is_bg(img)).mean() > 0.3


def _synthetic_clip(n_frames=3):
    hand = trimesh.creation.icosphere(subdivisions=2, radius=0.04)
    box = trimesh.creation.box(extents=(0.06, 0.06, 0.12))
    box = box.subdivide().subdivide()  # enough vertices for contact patches
    hv = np.stack([hand.vertices + [0.02 * t, -0.08 + 0.01 * t, 0.12] for t in range(n_frames)]).astype(np.float32)
    poses = np.repeat(np.eye(4)[None], n_frames, axis=0)
    poses[:, 2, 3] = 0.06  # box resting on the table top (z = 0)
    labels = np.zeros((n_frames, len(box.vertices)), dtype=np.uint8)
    near_hand = box.vertices[:, 1] < -0.02  # the face towards the hand
    labels[:, near_hand] = 22
    table = np.eye(4)
    table[2, 3] = -0.02
    clip = Clip(
        fps=30.0,
        hand_faces=np.asarray(hand.faces, dtype=np.int64),
        hand_vertices=hv,
        object_vertices=np.asarray(box.vertices, dtype=np.float64),
        object_faces=np.asarray(box.faces, dtype=np.int64),
        object_poses=poses,
        contact_labels=labels,
        table_pose=table,
        table_half_extents=np.array([0.4, 0.3, 0.02]),
    )
    clip.validate()
    return clip


def test_render_clip_strip(tmp_path):
    clip = _synthetic_clip()
    out = render_clip_strip(clip, [0, 1, 2], tmp_path / "sub" / "strip.png", size=(160, 120))
    assert out.exists()
    img = np.asarray(Image.open(out).convert("RGB")).astype(int)
    assert img.shape == (120, 480, 3)
    for i in range(3):
        panel = img[20:, i * 160 + 2:(i + 1) * 160 - 2]  # below the caption, inside the separators
        assert (~np.all(panel == 255, axis=-1)).mean() > 0.1
    red = (img[..., 0] > 150) & (img[..., 1] < 80) & (img[..., 2] < 80)
    assert red.sum() > 20
    # without contacts: no red
    out2 = render_clip_strip(clip, [1], tmp_path / "plain.png", size=(160, 120), show_contacts=False, view="top")
    img2 = np.asarray(Image.open(out2).convert("RGB")).astype(int)
    assert img2.shape == (120, 160, 3)
    assert not ((img2[..., 0] > 150) & (img2[..., 1] < 80) & (img2[..., 2] < 80)).any()
    assert tuple(CONTACT_RED) == (220, 32, 32)


def test_render_clip_strip_rejects_bad_frames(tmp_path):
    clip = _synthetic_clip()
    with pytest.raises(ValueError):
        render_clip_strip(clip, [5], tmp_path / "x.png")
    with pytest.raises(ValueError):
        render_clip_strip(clip, [], tmp_path / "x.png")
