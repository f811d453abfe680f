"""Evaluation metrics on constructed cases with known answers: intersection volumes of boxes,
a capsule "finger" pushed into a slab "palm", the demo hand on a table and bent into itself;
contact, coverage, marker, smoothness and limit metrics on small hand-computed arrays."""

import json
import math

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from retarget_core.errors import InputError
from retarget_core.mesh.geometry import SURFACE_TOLERANCE_M, box_signed_distance, signed_volume
from retarget_core.evaluate import (
    IntersectionResult,
    clip_intersections,
    contact_coverage,
    contact_distance_per_frame,
    contact_distances,
    coverage_per_frame,
    dof_derivatives,
    dof_limit_violations,
    dof_smoothness,
    hand_object_intersection,
    marker_error_per_frame,
    median_per_frame_mm,
    points_inside_mesh,
    self_intersection,
    summarize_series,
    table_intersection,
)


def box_mesh(extents, center=(0.0, 0.0, 0.0), subdivisions=5):
    """A closed box (trimesh) split ``subdivisions`` times: a regular grid on each face with
    spacing extent / 2**subdivisions."""
    mesh = trimesh.creation.box(extents=extents)
    for _ in range(subdivisions):
        mesh = mesh.subdivide()
    return np.asarray(mesh.vertices) + np.asarray(center), np.asarray(mesh.faces)


def transform(points, pose):
    return points @ pose[:3, :3].T + pose[:3, 3]


# A 4 cm "hand" cube on a 1.25 mm grid (5 subdivisions) and a large flat "object" box whose
# top is at z = 0.
A = 0.04
GRID = A / 2**5
OBJECT_EXTENTS = (0.10, 0.10, 0.02)
OBJECT_TOP = 0.0


@pytest.fixture(scope="module")
def hand_box():
    return box_mesh((A, A, A))


@pytest.fixture(scope="module")
def object_box():
    return box_mesh(OBJECT_EXTENTS, (0.0, 0.0, OBJECT_TOP - OBJECT_EXTENTS[2] / 2), subdivisions=3)


@pytest.fixture(scope="module")
def source_hand():
    from retarget_core.clip.demo import source_rig

    rig = source_rig()
    return rig, rig.kinematics().skin(rig.rest_pose), np.asarray(rig.surface.faces)


# ------------------------------------------------------------------------------------------
# hand-object
# ------------------------------------------------------------------------------------------
def test_box_pushed_into_box_gives_the_overlap_volume(hand_box, object_box):
    hv, hf = hand_box
    ov, of = object_box
    depth = 0.0055  # 4.4 grid steps: no hand vertex lies on the object's top
    hv = hv + [0.0, 0.0, OBJECT_TOP - depth + A / 2]
    r = hand_object_intersection(hv, hf, ov, of)
    assert r.available and r.reason == ""
    # Bottom face (33 x 33 grid) plus the 4 rows of side vertices below the object top
    # (at 1.25, 2.5, 3.75, 5 mm above the bottom), 128 vertices around each row.
    assert r.n_vertices == 33 * 33 + 4 * 128
    assert r.n_clusters == 1
    overlap = A * A * depth
    assert r.volume_m3 == pytest.approx(overlap, rel=1e-6)
    assert r.hand_volume_m3 == pytest.approx(A**3, rel=1e-9)
    assert r.percent_of_hand == pytest.approx(100 * depth / A, rel=1e-6)  # 13.75 %
    assert r.max_depth_m == pytest.approx(depth, abs=1e-9)
    # The paper's literal hull (penetrating vertices only) stops at the last row: 5 mm.
    vertices_only = hand_object_intersection(hv, hf, ov, of, include_crossings=False)
    assert vertices_only.volume_m3 == pytest.approx(A * A * 4 * GRID, rel=1e-6)


def test_box_over_the_object_edge_and_object_pose(hand_box, object_box):
    """Only part of the hand box is over the object: the overlap is a smaller box bounded by
    the object's top and its side wall; the object is given in its own frame with a pose."""
    hv, hf = hand_box
    ov, of = object_box
    depth, over_x = 0.0043, 0.0137  # overlap 13.7 mm in x, 40 mm in y, 4.3 mm in z
    hv = hv + [OBJECT_EXTENTS[0] / 2 - over_x + A / 2, 0.0, OBJECT_TOP - depth + A / 2]
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec([0.3, -0.5, 0.9]).as_matrix()
    pose[:3, 3] = [0.2, -0.1, 0.7]
    r = hand_object_intersection(transform(hv, pose), hf, ov, of, pose)
    assert r.available
    overlap = over_x * A * depth
    # Measured 0.39 % below: where the object's top and side wall meet between mesh edges, the
    # crossing points (on edges only) miss thin wedges. Every hull point lies in the convex
    # overlap, so the hull can never exceed it.
    assert overlap * 0.99 < r.volume_m3 <= overlap * (1 + 1e-9)
    assert r.max_depth_m == pytest.approx(depth, abs=1e-7)
    assert r.n_clusters == 1


def test_separated_and_touching_boxes_give_zero(hand_box, object_box):
    hv, hf = hand_box
    ov, of = object_box
    for gap in (0.001, 0.05):
        r = hand_object_intersection(hv + [0, 0, OBJECT_TOP + gap + A / 2], hf, ov, of)
        assert r.available and r.n_vertices == 0 and r.n_clusters == 0
        assert r.volume_m3 == 0.0 and r.percent_of_hand == 0.0 and r.max_depth_m == 0.0


def test_points_inside_a_sphere_by_ray_casting(rng):
    sphere = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    points = rng.uniform(-1.3, 1.3, size=(4000, 3))
    radius = np.linalg.norm(points, axis=1)
    clear = (radius < 0.99) | (radius > 1.001)  # the facetted sphere lies between 0.997 and 1
    inside = points_inside_mesh(points[clear], sphere.vertices, sphere.faces)
    np.testing.assert_array_equal(inside, radius[clear] < 0.99)


def test_two_separate_penetrations_are_two_clusters(hand_box, object_box):
    ov, of = object_box
    hv, hf = box_mesh((0.01, 0.01, 0.01), subdivisions=3)
    two_v = np.vstack([hv + [-0.02, 0, 0.005 - 0.002], hv + [0.02, 0, 0.005 - 0.003]])
    two_f = np.vstack([hf, hf + len(hv)])
    r = hand_object_intersection(two_v, two_f, ov, of)
    assert r.n_clusters == 2
    np.testing.assert_allclose(r.cluster_volumes_m3, [1e-4 * 0.003, 1e-4 * 0.002], rtol=1e-6)
    assert r.max_depth_m == pytest.approx(0.003, abs=1e-9)


# ------------------------------------------------------------------------------------------
# self
# ------------------------------------------------------------------------------------------
def test_finger_pushed_into_the_palm():
    """A slab 'palm' and a capsule 'finger' (one mesh, two closed components) whose rounded
    end is pushed ``depth`` into the palm: the overlap is a spherical cap."""
    palm = trimesh.creation.box(extents=(0.08, 0.08, 0.02))
    for _ in range(4):
        palm = palm.subdivide()
    radius, depth = 0.008, 0.004
    finger = trimesh.creation.capsule(height=0.04, radius=radius, count=[48, 48])
    fv = np.asarray(finger.vertices)
    fv = fv + [0.0, 0.0, 0.01 - depth - fv[:, 2].min()]  # palm top at z = 0.01
    v = np.vstack([palm.vertices, fv])
    f = np.vstack([palm.faces, np.asarray(finger.faces) + len(palm.vertices)])
    r = self_intersection(v, f)
    cap = math.pi * depth**2 * (3 * radius - depth) / 3  # 3.35e-7 m^3
    assert r.available
    # Measured 3.338e-7: the facetted capsule is slightly inside the true sphere.
    assert r.volume_m3 == pytest.approx(cap, rel=0.03)
    # Two clusters: the finger's cap inside the palm and the palm's disc inside the finger
    # (flat, so it adds no volume).
    assert r.n_clusters == 2
    assert r.max_depth_m == pytest.approx(depth, abs=2e-4)
    assert r.percent_of_hand == pytest.approx(100 * r.volume_m3 / (signed_volume(v, f)), rel=1e-9)
    # Separated by 1 mm: nothing.
    v_apart = np.vstack([palm.vertices, fv + [0.0, 0.0, depth + 0.001]])
    assert self_intersection(v_apart, f).n_vertices == 0


@pytest.mark.parametrize(
    "mesh",
    [
        trimesh.creation.icosphere(subdivisions=4, radius=0.03),
        trimesh.creation.box(extents=(0.04, 0.03, 0.02)).subdivide().subdivide(),
    ],
    ids=["sphere", "box"],
)
def test_clean_closed_meshes_have_no_self_intersection(mesh):
    r = self_intersection(mesh.vertices, mesh.faces)
    assert r.available and r.n_vertices == 0 and r.volume_m3 == 0.0


def test_demo_hand_rest_and_finger_bent_into_palm(source_hand):
    rig, v_rest, faces = source_hand
    rest = self_intersection(v_rest, faces)
    assert rest.available
    # Measured: 0.0013 % (one vertex where the generated surface folds over a 4 mm triangle
    # fan, 4e-9 m^3); 0 at 2 mm resolution.
    assert rest.percent_of_hand < 0.01
    q = rig.rest_pose.copy()
    for name in ("index1_flex", "index2_flex", "index3_flex"):
        q[rig.dof_index(name)] = 2.6  # past the limits: the finger goes through the palm
    bent = self_intersection(rig.kinematics().skin(q), faces)
    assert bent.available
    assert bent.percent_of_hand > 0.5  # measured 2.55 %
    assert bent.n_vertices > 100 and bent.max_depth_m > 0.005


# ------------------------------------------------------------------------------------------
# table
# ------------------------------------------------------------------------------------------
TABLE_HALF = np.array([0.45, 0.35, 0.02])


def table_pose_with_top_at(z, rotation=None):
    pose = np.eye(4)
    pose[:3, 3] = [0.0, 0.1, z - TABLE_HALF[2]]
    if rotation is not None:
        pose = rotation @ pose
    return pose


def test_box_resting_below_the_table_top(hand_box):
    hv, hf = hand_box
    depth = 0.0035
    hv = hv + [0.0, 0.0, -depth + A / 2]  # bottom 3.5 mm below the top at z = 0
    r = table_intersection(hv, hf, table_pose_with_top_at(0.0), TABLE_HALF)
    assert r.volume_m3 == pytest.approx(A * A * depth, rel=1e-9)
    assert r.percent_of_hand == pytest.approx(100 * depth / A, rel=1e-9)
    assert r.max_depth_m == pytest.approx(depth, abs=1e-12)
    assert r.n_vertices == 33 * 33 + 2 * 128 and r.n_clusters == 1
    # The whole scene turned and moved: same answer.
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_rotvec([0.4, 1.1, -0.2]).as_matrix()
    turn[:3, 3] = [1.0, 2.0, 3.0]
    r2 = table_intersection(transform(hv, turn), hf, table_pose_with_top_at(0.0, turn), TABLE_HALF)
    assert r2.volume_m3 == pytest.approx(r.volume_m3, rel=1e-9)
    assert r2.n_vertices == r.n_vertices
    # Resting exactly on the top, or above it: nothing.
    for lift in (0.0, 0.002):
        r0 = table_intersection(hv + [0, 0, depth + lift], hf, table_pose_with_top_at(0.0), TABLE_HALF)
        assert r0.n_vertices == 0 and r0.volume_m3 == 0.0


def test_demo_hand_on_the_table(source_hand):
    _, v, faces = source_hand
    depth = 0.003
    low = v[:, 2].min()
    r = table_intersection(v, faces, table_pose_with_top_at(low + depth), TABLE_HALF)
    assert r.available and r.n_vertices > 0
    assert r.max_depth_m == pytest.approx(depth, abs=1e-9)
    assert 0 < r.percent_of_hand < 1  # measured 0.069 %
    assert table_intersection(v, faces, table_pose_with_top_at(low), TABLE_HALF).n_vertices == 0
    below = np.array([[0.0, 0.1, low - 0.001]])
    assert box_signed_distance(below, table_pose_with_top_at(low), TABLE_HALF)[0] == pytest.approx(-0.001)


@pytest.mark.parametrize("below_top, inside", [(0.0, False), (1e-12, False), (1e-6, True)],
                         ids=["on the top", "1e-12 m in", "1e-6 m in"])
def test_table_inside_only_deeper_than_the_stated_tolerance(below_top, inside):
    """A vertex counts as in the table only deeper than SURFACE_TOLERANCE_M (1e-9 m): exactly on
    the top or 1e-12 m into it is outside, 1e-6 m into it is inside; in a turned frame too."""
    assert SURFACE_TOLERANCE_M == 1e-9
    hv, hf = box_mesh((0.01, 0.01, 0.01), subdivisions=0)  # 8 corners, 4 of them at the bottom
    hv = hv + [0.0, 0.1, 0.005 - below_top]  # bottom face below_top under the top at z = 0
    turn = np.eye(4)
    turn[:3, :3] = Rotation.from_rotvec([0.4, 1.1, -0.2]).as_matrix()
    for frame in (np.eye(4), turn):
        r = table_intersection(transform(hv, frame), hf, frame @ table_pose_with_top_at(0.0), TABLE_HALF)
        assert r.available and r.n_vertices == (4 if inside else 0)
        if inside:
            assert r.max_depth_m == pytest.approx(below_top, rel=1e-3)


@pytest.mark.parametrize("beyond, realised", [(0.0, True), (1e-12, True), (1e-6, False)],
                         ids=["at the threshold", "1e-12 m beyond", "1e-6 m beyond"])
def test_contact_realised_up_to_the_stated_tolerance_beyond_the_threshold(beyond, realised):
    c = contact_coverage(np.array([0.005 + beyond, 0.001]), threshold_m=0.005)
    assert c.n_realised == (2 if realised else 1)


# ------------------------------------------------------------------------------------------
# unavailable
# ------------------------------------------------------------------------------------------
def test_open_hand_surface_makes_the_metrics_unavailable(hand_box, object_box):
    hv, hf = hand_box
    ov, of = object_box
    open_faces = hf[1:]  # one triangle missing: three boundary edges
    results = [
        hand_object_intersection(hv, open_faces, ov, of),
        self_intersection(hv, open_faces),
        table_intersection(hv, open_faces, table_pose_with_top_at(0.0), TABLE_HALF),
    ]
    for r in results:
        assert not r.available
        assert "not a closed manifold" in r.reason and "boundary edges" in r.reason
        assert math.isnan(r.volume_m3) and math.isnan(r.percent_of_hand)
        d = r.to_dict()
        assert d["percent_of_hand"] is None and d["available"] is False
        json.dumps(d, allow_nan=False)
    r = hand_object_intersection(hv, hf, ov, of[1:])
    assert not r.available and "object surface is not closed" in r.reason
    nan_hand = hv.copy()
    nan_hand[0] = np.nan
    assert "finite" in self_intersection(nan_hand, hf).reason
    with pytest.raises(InputError):
        table_intersection(hv, hf, np.eye(3), TABLE_HALF)


def test_clip_intersections_and_their_series_summary(hand_box, object_box):
    hv, hf = hand_box
    ov, of = object_box
    depths = [0.0055, -0.01, 0.0025]  # penetration per frame (negative: apart)
    frames = np.stack([hv + [0, 0, OBJECT_TOP - d + A / 2] for d in depths])
    poses = np.repeat(np.eye(4)[None], 3, axis=0)
    out = clip_intersections(
        frames, hf, object_vertices=ov, object_faces=of, object_poses=poses,
        table_pose=table_pose_with_top_at(-0.002), table_half_extents=TABLE_HALF,
    )
    assert set(out) == {"hand_object", "self", "table"}
    percent = [r.percent_of_hand for r in out["hand_object"]]
    np.testing.assert_allclose(percent, [100 * max(d, 0) / A for d in depths], rtol=1e-6)
    assert all(r.volume_m3 == 0 for r in out["self"])
    np.testing.assert_allclose([r.max_depth_m for r in out["table"]], [0.0035, 0.0, 0.0005], atol=1e-12)
    out["hand_object"].append(IntersectionResult(kind="hand_object", available=False, reason="hand surface is open"))
    # the report's per-kind series: NaN where the metric was unavailable
    series = summarize_series([r.percent_of_hand if r.available else np.nan for r in out["hand_object"]])
    assert series["frames"] == 4 and series["finite_frames"] == 3
    assert series["max"] == pytest.approx(13.75) and series["argmax_frame"] == 0
    assert series["min"] == 0.0 and series["median"] == pytest.approx(100 * 0.0025 / A)
    json.dumps(series, allow_nan=False)


# ------------------------------------------------------------------------------------------
# contacts, markers, smoothness, limits
# ------------------------------------------------------------------------------------------
def _translating_box_rig():
    """A rig of one free root joint whose surface is a 2 cm cube at the origin: posed with
    root translation t and rotation R (Euler XYZ), a vertex v lands at R v + t."""
    from retarget_core.rig.model import Rig, SkinnedMesh, free_root

    v, f = box_mesh((0.02, 0.02, 0.02), subdivisions=0)
    joint, dofs = free_root()
    surface = SkinnedMesh(v, f.astype(np.int64), np.zeros((len(v), 1), np.int64), np.ones((len(v), 1)))
    return Rig("cube", [joint], dofs, surface)


def _at_vertices(rig, ids):
    """(faces, barycentric) of surface points lying exactly on the vertices ``ids``."""
    from retarget_core.mesh.surface_points import SurfacePoints

    points = SurfacePoints.from_vertices(np.asarray(ids), rig.surface.faces)
    return points.faces, points.barycentric


def test_contact_distance_and_marker_error_per_frame_by_hand():
    from retarget_core.solve.targets import ContactTargets, MarkerTargets

    rig = _translating_box_rig()
    kin = rig.kinematics()
    v = rig.surface.vertices
    quarter = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # root_rz = pi/2
    q = np.zeros((3, rig.n_dofs))
    q[0, :3] = [0.1, 0.0, 0.0]
    q[1, :3] = [0.0, 0.2, 0.0]
    q[2, :3], q[2, 5] = [0.0, 0.0, 0.3], np.pi / 2

    def posed(f, i):
        return (quarter if f == 2 else np.eye(3)) @ v[i] + q[f, :3]

    # frame 0: three contacts 1, 2 and 6 mm off; frame 1: none; frame 2 (turned): 3 and 5 mm
    offsets = np.array([0, 3, 3, 5])
    ids = np.array([0, 3, 6, 1, 7])
    frame_of = [0, 0, 0, 2, 2]
    off = np.array([[0.001, 0, 0], [0, 0.002, 0], [0, 0, -0.006], [0.003, 0, 0], [0, 0.003, 0.004]])
    surface = np.array([posed(f, i) for f, i in zip(frame_of, ids)]) + off
    normals = np.tile([0.0, 0.0, 1.0], (5, 1))
    gap = np.array([0.0, 0.0, 0.0, 0.01, 0.0])  # a kept source gap moves the target, not the error
    faces, bary = _at_vertices(rig, ids)
    contacts = ContactTargets(offsets, faces, bary, surface + gap[:, None] * normals, normals, gap)

    distances = contact_distances(kin, q, contacts)
    np.testing.assert_allclose(distances, [0.001, 0.002, 0.006, 0.003, 0.005], rtol=1e-9)
    median, count = contact_distance_per_frame(kin, q, contacts)
    np.testing.assert_array_equal(count, [3, 0, 2])
    assert median[0] == pytest.approx(2.0, rel=1e-9) and median[2] == pytest.approx(4.0, rel=1e-9)
    assert math.isnan(median[1])
    again, _ = median_per_frame_mm(distances, offsets)
    np.testing.assert_array_equal(again, median)

    # markers: A (one pair, on vertex 2) and B (two pairs, vertex 5), so B's pairs weigh 1/2 each
    m_faces, m_bary = _at_vertices(rig, [2, 5])
    pair_target = np.array([0, 1, 1])
    source = np.array([[posed(f, i) for i in (2, 5, 5)] for f in range(3)])
    source[:, 0] += [0.004, 0.0, 0.0]  # A 4 mm off in every frame
    source[:, 1] += [0.0, 0.0, 0.002]  # B's pairs 2 mm and 6 mm off ...
    source[:, 2] += [0.0, -0.006, 0.0]
    source[1, 1:] = posed(1, 5)  # ... except in frame 1, where B sits on its target
    markers = MarkerTargets(m_faces, m_bary, pair_target, np.array([1.0, 0.5, 0.5]), source, ["A", "B", "B"])
    error = marker_error_per_frame(kin, q, markers)
    # (1 * 4 + 0.5 * 2 + 0.5 * 6) / 2 mm, and (1 * 4 + 0) / 2 mm in frame 1
    np.testing.assert_allclose(error, [4.0, 2.0, 4.0], rtol=1e-9)

    none = MarkerTargets(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0),
                         np.zeros((3, 0, 3)), [])
    assert np.isnan(marker_error_per_frame(kin, q, none)).all()
    with pytest.raises(InputError, match="3 frames, q has 2"):
        contact_distances(kin, q[:2], contacts)


def test_coverage_per_frame_counts_dropped_source_contacts_as_not_realised():
    offsets = np.array([0, 3, 3, 4])
    distances = np.array([0.001, 0.004, 0.006, 0.002])
    share = coverage_per_frame(distances, offsets, source_count=np.array([4, 2, 1]))
    # frame 0: 1 and 4 mm realised of 4 source contacts (one dropped); frame 1: nothing transferred
    np.testing.assert_allclose(share[[0, 2]], [0.5, 1.0])
    assert math.isnan(share[1])
    np.testing.assert_allclose(coverage_per_frame(distances, offsets)[[0, 2]], [2 / 3, 1.0])


def test_contact_coverage():
    d = np.array([0.001, 0.004, 0.005, 0.006, np.nan, 0.002])
    transferred = np.array([True, True, True, True, False, False])
    c = contact_coverage(d, transferred)
    # realised: 1, 4 and 5 mm (<= 5 mm); 6 mm too far; the last two were dropped.
    assert (c.n_source, c.n_transferred, c.n_realised) == (6, 4, 3)
    assert c.share == pytest.approx(0.5)
    assert contact_coverage(d, transferred, threshold_m=0.0045).share == pytest.approx(2 / 6)
    assert contact_coverage(d[:4]).share == pytest.approx(0.75)
    assert math.isnan(contact_coverage(np.zeros(0)).share)


def test_smoothness_of_polynomials():
    fps = 10.0
    t = np.arange(20) / fps
    values = np.stack([t**2, t**3, 0.5 * t], axis=1)  # rad, m, rad
    accel, jerk = dof_derivatives(values, fps)
    np.testing.assert_allclose(accel[:, 0], 2.0, rtol=1e-9)
    np.testing.assert_allclose(jerk[:, 1], 6.0, rtol=1e-9)
    np.testing.assert_allclose(accel[:, 1], 6.0 * t[1:-1], rtol=1e-9, atol=1e-9)  # centred
    s = dof_smoothness(values, fps, ["rotate", "translate", "rotate"])
    deg = 180 / math.pi
    assert s.accel_rms[0] == pytest.approx(2 * deg) and s.accel_max[0] == pytest.approx(2 * deg)
    assert s.jerk_max[0] == pytest.approx(0.0, abs=1e-6)
    assert s.jerk_rms[1] == pytest.approx(600.0) and s.jerk_max[1] == pytest.approx(600.0)  # cm/s^3
    assert s.accel_max[1] == pytest.approx(600.0 * t[-2])  # cm/s^2 at the last centred frame
    assert s.accel_rms[1] == pytest.approx(600.0 * math.sqrt(np.mean(t[1:-1] ** 2)))
    assert s.accel_max[2] == pytest.approx(0.0, abs=1e-9)
    same = dof_smoothness(values, fps, np.array([True, False, True]))
    np.testing.assert_allclose(same.jerk_rms, s.jerk_rms)
    d = s.to_dict(["a", "b", "c"])
    assert d["dofs"]["b"]["jerk_unit"] == "cm/s^3" and d["dofs"]["a"]["accel_unit"] == "deg/s^2"
    short = dof_smoothness(values[:3], fps, ["rotate"] * 3)
    assert math.isnan(short.jerk_rms[0]) and short.accel_rms[0] == pytest.approx(2 * deg)
    with pytest.raises(InputError):
        dof_smoothness(values, fps, ["rotate", "slide", "rotate"])


def test_dof_limit_violations():
    lower = np.array([-1.0, 0.0])
    upper = np.array([1.0, 0.1])
    values = np.array(
        [
            [0.0, 0.05],
            [1.0 + 1e-9, 0.1],  # within the tolerance
            [1.3, -0.02],  # two violations: 0.3 and 0.02
            [np.nan, 0.15],  # NaN is not a violation; 0.05 over
        ]
    )
    v = dof_limit_violations(values, lower, upper)
    assert (v.count, v.frames) == (3, 2)
    np.testing.assert_array_equal(v.per_dof, [1, 2])
    assert v.worst_excess == pytest.approx(0.3) and (v.worst_frame, v.worst_dof) == (2, 0)
    assert v.to_dict(["wrist", "slide"])["worst_dof_name"] == "wrist"
    none = dof_limit_violations(values[:2], lower, upper)
    assert none.count == 0 and none.worst_excess == 0.0 and none.worst_dof == -1


def test_summarize_series_handles_nan():
    s = summarize_series(np.array([1.0, np.nan, 3.0, 2.0]))
    assert s["frames"] == 4 and s["finite_frames"] == 3
    assert s["max"] == 3.0 and s["argmax_frame"] == 2 and s["median"] == 2.0
    empty = summarize_series(np.array([np.nan]))
    assert empty["mean"] is None and empty["argmax_frame"] is None and empty["finite_frames"] == 0
    assert json.loads(json.dumps(summarize_series([0.5, np.nan]), allow_nan=False))["mean"] == 0.5
