"""Exact intersection volumes and penetration depths on cases with known answers: boxes pushed
into boxes, a cube corner poking into a hand without any hand vertex inside it, a capsule
"finger" in a slab "palm", the demo hand on a table and bent into itself, robot and foreign
hands cut into parts."""

import json
import math

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from boxes import box_mesh
from retarget_core.errors import InputError
from retarget_core.evaluate import (
    IntersectionResult,
    clip_intersections,
    hand_object_intersection,
    self_intersection,
    summarize_series,
    table_intersection,
)
from retarget_core.mesh.geometry import SURFACE_TOLERANCE_M, signed_volume
from retarget_core.rig.parts import hand_parts, rig_parts



def transform(points, pose):
    return points @ pose[:3, :3].T + pose[:3, 3]


def turned(rotvec, translation):
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec(rotvec).as_matrix()
    pose[:3, 3] = translation
    return pose


# A 4 cm "hand" cube and a large flat "object" box whose top is at z = 0.
A = 0.04
OBJECT_EXTENTS = (0.10, 0.10, 0.02)


@pytest.fixture(scope="module")
def hand_box():
    return box_mesh((A, A, A), subdivisions=2)


@pytest.fixture(scope="module")
def object_box():
    return box_mesh(OBJECT_EXTENTS, (0.0, 0.0, -OBJECT_EXTENTS[2] / 2), subdivisions=1)


@pytest.fixture(scope="module")
def source_hand():
    from retarget_core.clip.demo import source_rig

    rig = source_rig()
    return rig, rig.kinematics().skin(rig.rest_pose), np.asarray(rig.surface.faces), rig_parts(rig)


# ------------------------------------------------------------------------------------------
# hand-object
# ------------------------------------------------------------------------------------------
def test_box_pushed_into_box_gives_the_exact_overlap_and_both_depths(hand_box, object_box):
    hv, hf = hand_box
    ov, of = object_box
    depth = 0.0055
    r = hand_object_intersection(hv + [0.0, 0.0, -depth + A / 2], hf, ov, of)
    assert r.available and r.reason == ""
    assert r.volume_m3 == pytest.approx(A * A * depth, rel=1e-9)
    assert r.hand_volume_m3 == pytest.approx(A**3, rel=1e-9)
    assert r.percent_of_hand == pytest.approx(100 * depth / A, rel=1e-9)  # 13.75 %
    # the hand's bottom is 5.5 mm under the object's top; the object's top 5.5 mm inside the hand
    assert r.hand_depth_m == pytest.approx(depth, abs=1e-9)
    assert r.other_depth_m == pytest.approx(depth, abs=1e-9)
    assert r.pieces == 1


def test_box_over_the_object_edge_with_an_object_pose(hand_box, object_box):
    """Part of the hand box is over the object: the overlap is the box bounded by the top and
    the side wall, exactly (the old vertex hull missed 0.4 % in the wedges between edges)."""
    hv, hf = hand_box
    ov, of = object_box
    depth, over_x = 0.0043, 0.0137
    hv = hv + [OBJECT_EXTENTS[0] / 2 - over_x + A / 2, 0.0, -depth + A / 2]
    pose = turned([0.3, -0.5, 0.9], [0.2, -0.1, 0.7])
    r = hand_object_intersection(transform(hv, pose), hf, ov, of, pose)
    assert r.volume_m3 == pytest.approx(over_x * A * depth, rel=1e-9)
    assert r.hand_depth_m == pytest.approx(depth, abs=1e-9)
    # the object's top corner edge is 4.3 mm above the hand's bottom, 13.7 mm from its side
    assert r.other_depth_m == pytest.approx(depth, abs=1e-9)


def test_an_object_corner_in_the_hand_counts_without_any_hand_vertex_inside():
    """A cube stood on its corner poking h into a coarse hand box (8 vertices, none inside the
    cube): the overlap is the corner tetrahedron, (sqrt(3) h)^3 / 6, and the object reaches h
    into the hand."""
    hv, hf = box_mesh((A, A, A), subdivisions=0)  # bottom face at z = -A / 2
    cube_v, cube_f = box_mesh((0.02, 0.02, 0.02), center=(0.01, 0.01, 0.01), subdivisions=0)  # corner at 0
    # turn the body diagonal (1, 1, 1) to point down, then put the corner h above the hand bottom
    diag = np.ones(3) / math.sqrt(3)
    rot, _ = Rotation.align_vectors([[0.0, 0.0, -1.0]], [diag])
    h = 0.003
    pose = np.eye(4)
    pose[:3, :3] = rot.as_matrix()
    pose[:3, 3] = [0.002, -0.001, -A / 2 + h]
    r = hand_object_intersection(hv, hf, cube_v, cube_f, pose)
    assert r.volume_m3 == pytest.approx((math.sqrt(3) * h) ** 3 / 6, rel=1e-9)
    assert r.other_depth_m == pytest.approx(h, abs=1e-9)
    # the hand's vertices are all outside the cube: at the intersection's vertices the hand is 0 deep
    assert r.hand_depth_m == 0.0


def test_separated_and_touching_boxes_give_zero(hand_box, object_box):
    hv, hf = hand_box
    ov, of = object_box
    for gap in (0.001, 0.05, 0.0):
        r = hand_object_intersection(hv + [0, 0, gap + A / 2], hf, ov, of)
        assert r.available and r.volume_m3 <= 1e-15 and r.max_depth_m == 0.0


def test_a_hand_passing_through_itself_is_one_solid_for_the_object(hand_box, object_box):
    """Two copies of the hand box overlapping each other by half: the object's overlap with
    the hand is counted once (the union of the parts), not once per copy."""
    hv, hf = hand_box
    ov, of = object_box
    depth = 0.004
    low = hv + [0.0, 0.0, -depth + A / 2]
    v = np.vstack([low, low + [A / 2, 0.0, 0.0]])
    f = np.vstack([hf, hf + len(hv)])
    r = hand_object_intersection(v, f, ov, of)
    assert r.volume_m3 == pytest.approx(1.5 * A * A * depth, rel=1e-9)
    assert r.hand_volume_m3 == pytest.approx(1.5 * A**3, rel=1e-9)


# ------------------------------------------------------------------------------------------
# self
# ------------------------------------------------------------------------------------------
def palm_and_finger(depth, radius=0.008):
    palm = trimesh.creation.box(extents=(0.08, 0.08, 0.02))
    finger = trimesh.creation.capsule(height=0.04, radius=radius, count=[48, 48])
    fv = np.asarray(finger.vertices)
    fv = fv + [0.0, 0.0, 0.01 - depth - fv[:, 2].min()]  # palm top at z = 0.01
    v = np.vstack([palm.vertices, fv])
    f = np.vstack([palm.faces, np.asarray(finger.faces) + len(palm.vertices)])
    return v, f, np.asarray(finger.vertices), np.asarray(finger.faces)


def test_finger_pushed_into_the_palm_is_the_spherical_cap():
    radius, depth = 0.008, 0.004
    v, f, _, _ = palm_and_finger(depth, radius)
    r = self_intersection(v, f)
    cap = math.pi * depth**2 * (3 * radius - depth) / 3  # 3.35e-7 m^3 for the true sphere
    assert r.available
    # the facetted capsule lies inside the true sphere: measured 0.6 % below
    assert cap * 0.98 < r.volume_m3 < cap
    assert len(r.pairs) == 1 and r.pairs[0][2] == pytest.approx(r.volume_m3)
    assert r.max_depth_m == pytest.approx(depth, abs=1e-9)
    union = signed_volume(v, f) - r.volume_m3
    assert r.percent_of_hand == pytest.approx(100 * r.volume_m3 / union, rel=1e-9)
    apart, f2, _, _ = palm_and_finger(-0.001, radius)
    assert self_intersection(apart, f2).volume_m3 == 0.0


@pytest.mark.parametrize(
    "mesh",
    [trimesh.creation.icosphere(subdivisions=4, radius=0.03),
     trimesh.creation.box(extents=(0.04, 0.03, 0.02)).subdivide().subdivide()],
    ids=["sphere", "box"],
)
def test_clean_closed_meshes_have_no_self_intersection(mesh):
    r = self_intersection(mesh.vertices, mesh.faces)
    assert r.available and r.volume_m3 == 0.0 and r.pairs == ()


def test_demo_hand_rest_and_finger_bent_into_palm(source_hand):
    rig, v_rest, faces, parts = source_hand
    rest = self_intersection(v_rest, faces, parts=parts)
    assert rest.available and rest.percent_of_hand < 0.01
    q = rig.rest_pose.copy()
    for name in ("index1_flex", "index2_flex", "index3_flex"):
        q[rig.dof_index(name)] = 2.6  # past the limits: the finger goes through the palm
    bent = self_intersection(rig.kinematics().skin(q), faces, parts=parts)
    assert bent.percent_of_hand > 0.5
    assert bent.max_depth_m > 0.005
    assert any("index" in a + b for a, b, _ in bent.pairs)
    # without the parts the hand is one solid: a single component cannot overlap itself
    assert self_intersection(rig.kinematics().skin(q), faces).volume_m3 == 0.0


# ------------------------------------------------------------------------------------------
# hand parts
# ------------------------------------------------------------------------------------------
def test_demo_hand_parts_are_closed_and_make_up_the_hand(source_hand):
    from retarget_core.mesh import booleans

    rig, v, faces, parts = source_hand
    assert parts.n_parts >= 15 and not parts.merged
    solids = [booleans.solid(pv, pf) for pv, pf in parts.posed(v)]  # each closed (raises otherwise)
    whole = signed_volume(v, faces)
    union = booleans.union(solids).volume()
    assert 0.99 * whole < union <= whole * (1 + 1e-9)  # pockets where three parts meet: measured 0.2 %
    # every part touches another one, and the palm's part touches each finger's first
    assert all(any(p in pair for pair in parts.adjacent) for p in range(parts.n_parts))


def test_parts_of_a_foreign_weighting_are_cut_and_merged_where_too_small():
    """A capsule skinned to two joints along its length and a third joint owning fewer faces
    than ``min_faces``: the third is merged into its neighbour, the other two close."""
    m = trimesh.creation.capsule(height=0.06, radius=0.01, count=[24, 24])
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    w = np.zeros((len(v), 3))
    w[:, 0] = v[:, 2] < 0.0
    w[:, 1] = v[:, 2] >= 0.0
    ring = np.unique(np.sort(v[:, 2]))[-2]  # the pole and the ring around it: a fan of 24 faces
    w[v[:, 2] >= ring] = (0.0, 0.0, 1.0)
    nail_faces = int((np.argmax(w[f].sum(axis=1), axis=1) == 2).sum())
    assert nail_faces >= 24
    parts = hand_parts(f, w, ["base", "tip", "nail"], rest_vertices=v, min_faces=nail_faces + 1)
    assert parts.names == ("base", "tip") and parts.merged == ("nail",)
    assert parts.adjacent == frozenset({(0, 1)})
    assert parts.non_adjacent_pairs() == []


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
    hv = hv + [0.0, 0.0, -depth + A / 2]
    r = table_intersection(hv, hf, table_pose_with_top_at(0.0), TABLE_HALF)
    assert r.volume_m3 == pytest.approx(A * A * depth, rel=1e-9)
    assert r.hand_depth_m == pytest.approx(depth, abs=1e-9)
    turn = turned([0.4, 1.1, -0.2], [1.0, 2.0, 3.0])
    r2 = table_intersection(transform(hv, turn), hf, table_pose_with_top_at(0.0, turn), TABLE_HALF)
    assert r2.volume_m3 == pytest.approx(r.volume_m3, rel=1e-9)
    assert r2.hand_depth_m == pytest.approx(depth, abs=1e-9)
    for lift in (0.0, 0.002):
        r0 = table_intersection(hv + [0, 0, depth + lift], hf, table_pose_with_top_at(0.0), TABLE_HALF)
        assert r0.volume_m3 <= 1e-15 and r0.hand_depth_m == 0.0


def test_demo_hand_on_the_table(source_hand):
    _, v, faces, parts = source_hand
    depth = 0.003
    low = v[:, 2].min()
    r = table_intersection(v, faces, table_pose_with_top_at(low + depth), TABLE_HALF, parts=parts)
    assert r.hand_depth_m == pytest.approx(depth, abs=1e-9)
    assert 0 < r.percent_of_hand < 1
    assert table_intersection(v, faces, table_pose_with_top_at(low), TABLE_HALF, parts=parts).hand_depth_m == 0.0


@pytest.mark.parametrize("below_top, inside", [(0.0, False), (1e-12, False), (1e-6, True)],
                         ids=["on the top", "1e-12 m in", "1e-6 m in"])
def test_table_depth_counts_only_beyond_the_stated_tolerance(below_top, inside):
    """A depth of SURFACE_TOLERANCE_M (1e-9 m) or less is 0, in a turned frame too."""
    assert SURFACE_TOLERANCE_M == 1e-9
    hv, hf = box_mesh((0.01, 0.01, 0.01), subdivisions=0)
    hv = hv + [0.0, 0.1, 0.005 - below_top]
    for frame in (np.eye(4), turned([0.4, 1.1, -0.2], [0.0, 0.0, 0.0])):
        r = table_intersection(transform(hv, frame), hf, frame @ table_pose_with_top_at(0.0), TABLE_HALF)
        assert r.available
        if inside:
            assert r.hand_depth_m == pytest.approx(below_top, rel=1e-3)
            assert r.volume_m3 == pytest.approx(1e-4 * below_top, rel=1e-3)
        else:
            assert r.hand_depth_m == 0.0 and r.volume_m3 < 1e-15


# ------------------------------------------------------------------------------------------
# unavailable, bad input, a clip
# ------------------------------------------------------------------------------------------
def test_open_hand_surface_makes_the_metrics_unavailable(hand_box, object_box):
    hv, hf = hand_box
    ov, of = object_box
    open_faces = hf[1:]
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
    with pytest.raises(InputError, match="hand_faces"):
        self_intersection(hv, hf + len(hv))


def test_an_object_wound_inside_out_is_read_outward(hand_box, object_box):
    hv, hf = hand_box
    ov, of = object_box
    hv = hv + [0.0, 0.0, -0.002 + A / 2]
    a = hand_object_intersection(hv, hf, ov, of)
    b = hand_object_intersection(hv, hf, ov, of[:, ::-1])
    assert b.volume_m3 == pytest.approx(a.volume_m3, rel=1e-12) and a.volume_m3 > 0


def test_clip_intersections_and_their_series_summary(hand_box, object_box):
    hv, hf = hand_box
    ov, of = object_box
    depths = [0.0055, -0.01, 0.0025]
    frames = np.stack([hv + [0, 0, -d + A / 2] for d in depths])
    poses = np.repeat(np.eye(4)[None], 3, axis=0)
    out = clip_intersections(frames, hf, object_vertices=ov, object_faces=of, object_poses=poses,
                             table_pose=table_pose_with_top_at(-0.002), table_half_extents=TABLE_HALF)
    assert set(out) == {"hand_object", "self", "table"}
    np.testing.assert_allclose([r.percent_of_hand for r in out["hand_object"]],
                               [100 * max(d, 0) / A for d in depths], rtol=1e-9, atol=1e-12)
    assert all(r.volume_m3 == 0 for r in out["self"])
    np.testing.assert_allclose([r.hand_depth_m for r in out["table"]], [0.0035, 0.0, 0.0005], atol=1e-9)
    out["hand_object"].append(IntersectionResult(kind="hand_object", available=False, reason="hand surface is open"))
    series = summarize_series([r.percent_of_hand if r.available else np.nan for r in out["hand_object"]])
    assert series["frames"] == 4 and series["finite_frames"] == 3
    assert series["max"] == pytest.approx(13.75) and series["argmax_frame"] == 0
    json.dumps(series, allow_nan=False)
