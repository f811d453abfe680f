"""Shared mesh and box geometry (retarget_core.mesh.geometry) on shapes with known answers."""

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from retarget_core.mesh.geometry import (
    box_inside,
    box_local,
    box_signed_distance,
    box_signed_distance_and_gradient,
    box_signed_distance_local,
    face_normals,
    signed_volume,
    vertex_normals,
)
from retarget_core.mesh.implicit import rounded_box


def _box(extents=(0.04, 0.03, 0.02), center=(0.1, -0.2, 0.3)):
    mesh = trimesh.creation.box(extents=extents)
    return np.asarray(mesh.vertices) + np.asarray(center), np.asarray(mesh.faces)


def test_signed_volume_of_a_box_and_its_inside_out_copy():
    v, f = _box()
    assert signed_volume(v, f) == pytest.approx(0.04 * 0.03 * 0.02, rel=1e-12)
    assert signed_volume(v, f[:, ::-1]) == pytest.approx(-0.04 * 0.03 * 0.02, rel=1e-12)
    assert signed_volume(v, np.zeros((0, 3), np.int64)) == 0.0


def test_signed_volume_of_a_sphere_approaches_four_thirds_pi_r_cubed():
    sphere = trimesh.creation.icosphere(subdivisions=5, radius=0.05)
    # the inscribed polyhedron is a little smaller than the sphere (measured -0.05 %)
    assert signed_volume(sphere.vertices, sphere.faces) == pytest.approx(4 / 3 * np.pi * 0.05**3, rel=1e-3)
    assert signed_volume(sphere.vertices, sphere.faces) < 4 / 3 * np.pi * 0.05**3


def test_vertex_normals_of_a_box_point_out_along_the_diagonals():
    v, f = _box(extents=(2.0, 2.0, 2.0), center=(0, 0, 0))
    n = vertex_normals(v, f)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, rtol=1e-12)
    # trimesh's box: two triangles per face, so corners carry uneven area weights, but every
    # normal points out of the box (into the octant of its corner)
    assert np.all(np.sign(n) == np.sign(v))


def test_vertex_normals_of_a_flat_square_and_an_unused_vertex():
    v = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [5, 5, 5]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    n = vertex_normals(v, f)
    np.testing.assert_array_equal(n[:4], np.tile([0.0, 0.0, 1.0], (4, 1)))
    np.testing.assert_array_equal(n[4], [0.0, 0.0, 0.0])  # no face uses it


def test_face_normals_unit_and_zero_for_a_zero_area_face():
    v = np.array([[0.0, 0, 0], [0.002, 0, 0], [0, 0.003, 0], [0.004, 0, 0]])
    f = np.array([[0, 1, 2], [0, 2, 1], [0, 1, 3]])  # the last one is degenerate (collinear)
    n = face_normals(v, f)
    np.testing.assert_allclose(n, [[0, 0, 1], [0, 0, -1], [0, 0, 0]], atol=0)


def test_box_signed_distance_known_values_and_gradient():
    pose = np.eye(4)
    pose[:3, 3] = [1.0, 0.0, 0.0]
    half = np.array([0.5, 0.2, 0.1])
    points = np.array([[1.0, 0.0, 0.05],    # inside, 5 cm below the top face
                       [1.0, 0.0, 0.3],     # 20 cm above the top face
                       [1.8, 0.5, 0.0]])    # off an edge: (0.3, 0.3) away
    sdf, grad = box_signed_distance_and_gradient(points, pose, half)
    assert np.allclose(sdf, [-0.05, 0.2, np.hypot(0.3, 0.3)])
    assert np.allclose(grad[0], [0, 0, 1]) and np.allclose(grad[1], [0, 0, 1])
    assert np.allclose(grad[2], [np.sqrt(0.5), np.sqrt(0.5), 0])
    np.testing.assert_array_equal(box_signed_distance(points, pose, half), sdf)


def test_box_signed_distance_in_a_turned_frame_and_its_gradient_by_differences(rng):
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec([0.3, -0.5, 0.9]).as_matrix()
    pose[:3, 3] = [0.2, -0.1, 0.7]
    half = np.array([0.05, 0.03, 0.02])
    local = rng.uniform(-0.08, 0.08, size=(200, 3))
    points = local @ pose[:3, :3].T + pose[:3, 3]
    np.testing.assert_allclose(box_local(points, pose), local, atol=1e-15)
    sdf, grad = box_signed_distance_and_gradient(points, pose, half)
    np.testing.assert_allclose(sdf, box_signed_distance_local(local, half), atol=1e-15)
    h = 1e-7
    numeric = np.stack([(box_signed_distance(points + h * e, pose, half) - box_signed_distance(points - h * e, pose, half))
                        / (2 * h) for e in np.eye(3)], axis=1)
    np.testing.assert_allclose(grad, numeric, atol=1e-6)


def test_box_inside_gives_the_inside_points_with_the_full_signed_distance_and_gradient(rng):
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec([-0.4, 0.2, 0.7]).as_matrix()
    pose[:3, 3] = [0.1, 0.3, -0.2]
    half = np.array([0.05, 0.03, 0.02])
    local = rng.uniform(-1.5, 1.5, size=(400, 3)) * half  # about 30 % inside
    local[:3] = [[0.0, 0.0, 0.0], [0.0501, 0.0, 0.0], [0.0, -0.03 + 1e-6, 0.01]]  # centre, just out, just in
    points = local @ pose[:3, :3].T + pose[:3, 3]
    sdf, grad = box_signed_distance_and_gradient(points, pose, half)
    ids, depth, normal = box_inside(points, pose, half)
    expected = np.flatnonzero(sdf < 0)
    assert 50 < len(expected) < 350  # both kinds of point are there
    np.testing.assert_array_equal(ids, expected)
    np.testing.assert_array_equal(depth, sdf[expected])
    np.testing.assert_array_equal(normal, grad[expected])
    assert 0 in ids and 1 not in ids and 2 in ids
    np.testing.assert_allclose(depth[ids == 2], -1e-6, atol=1e-12)
    empty = box_inside(points[sdf >= 0], pose, half)
    assert [len(a) for a in empty] == [0, 0, 0] and empty[2].shape == (0, 3)


def test_rounded_box_without_rounding_is_the_box_and_with_rounding_is_smaller(rng):
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec([0.1, 0.2, -0.3]).as_matrix()
    pose[:3, 3] = [0.0, 0.1, -0.02]
    half = np.array([0.45, 0.35, 0.02])
    points = pose[:3, 3] + rng.uniform(-0.6, 0.6, size=(500, 3))
    sharp = rounded_box(points, pose[:3, 3], pose[:3, :3], half, 0.0)
    np.testing.assert_array_equal(sharp, box_signed_distance(points, pose, half))
    # rounding keeps the outer size: a face centre stays on the surface, a corner moves in
    corner = pose[:3, 3] + pose[:3, :3] @ half
    top = pose[:3, 3] + pose[:3, :3] @ np.array([0.0, 0.0, half[2]])
    round_ = rounded_box(np.array([corner, top]), pose[:3, 3], pose[:3, :3], half, 0.005)
    assert round_[0] == pytest.approx((np.sqrt(3) - 1) * 0.005, rel=1e-9)
    assert round_[1] == pytest.approx(0.0, abs=1e-15)
