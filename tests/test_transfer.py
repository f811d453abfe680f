"""Contact transfer through the atlas: identity, analytic cylinders checked against exact
geodesics, lambda_a / lambda_s, discarded charts, caching and bad input."""

import json

import numpy as np
import pygeodesic.geodesic as pygeodesic
import pytest

from retarget_core.clip.demo import build_demo_timeline, clip_from_timeline, source_rig
from retarget_core.errors import InputError
from retarget_core.mesh.implicit import capped_cylinder
from retarget_core.mesh.isosurface import closed_surface_from_field, sample_grid
from retarget_core.mesh.surface_points import SurfacePoints, closest_surface_points
from retarget_core.pairing import pair_contacts
from retarget_core.rig.demo_hands import demo_hand
from retarget_core.transfer.annotations import (
    Annotations,
    AxialCurveAnnotation,
    CurveTarget,
    LambdaS,
    MeshSignature,
    PointRef,
    annotations_from_dict,
    annotations_to_dict,
)
from retarget_core.transfer.atlas import Atlas, get_atlas
from retarget_core.transfer.clip_transfer import transfer_clip, transfer_report
from retarget_core.transfer.geodesics import SurfaceGeometry
from retarget_core.transfer.propose import propose_annotations


@pytest.fixture(scope="module")
def source():
    return source_rig()


@pytest.fixture(scope="module")
def clip_pairs(source):
    obj, timeline = build_demo_timeline("apple_rotate", time_scale=0.12, rig=source)
    clip = clip_from_timeline("apple_rotate", obj, timeline, source, 0.004)
    return clip, pair_contacts(clip)


def test_identity_transfer_returns_every_contact_where_it_started(source, clip_pairs):
    _, pairs = clip_pairs
    annotations = propose_annotations(source, source)
    result = transfer_clip(pairs, source, source, annotations)
    assert not result.contacts.dropped.any()
    start = SurfacePoints(pairs.hand_face, pairs.hand_barycentric).positions(source.surface.vertices, source.surface.faces)
    end = result.contacts.target_points().positions(source.surface.vertices, source.surface.faces)
    error = np.linalg.norm(end - start, axis=1)
    assert len(error) > 500
    assert error.max() < 0.0005


def test_second_clip_onto_the_same_hand_reuses_the_atlas(source):
    annotations = propose_annotations(source, source)
    v, f = source.surface.vertices, source.surface.faces
    assert get_atlas(v, f, v, f, annotations) is get_atlas(v, f, v, f, annotations)


def test_three_fingered_hand_drops_exactly_the_discarded_charts(source, clip_pairs):
    _, pairs = clip_pairs
    alien = demo_hand("alien", resolution=0.004)
    annotations = propose_annotations(source, alien)
    assert {c.name for c in annotations.curves if c.discard} == {"ring", "pinky"}
    result = transfer_clip(pairs, source, alien, annotations)
    report = transfer_report(result, source, alien)
    assert report["dropped_on_discarded_charts"] == report["contacts"] - report["transferred"]
    assert report["per_curve"]["ring"]["dropped"] == report["per_curve"]["ring"]["contacts"]
    assert report["per_curve"]["index"]["dropped"] == 0
    assert 0 < report["dropped_share"] < 0.5
    # transferred contacts land on the target surface, on the finger their chart belongs to
    kept = ~result.contacts.dropped
    owner = alien.surface.dense_weights(alien.n_joints).argmax(axis=1)
    faces = alien.surface.faces[result.contacts.face[kept]]
    curves = np.array(result.atlas.curve_names)[result.contacts.curve[kept]]
    on_index = curves == "index"
    joint_names = np.array(alien.joint_names)[owner[faces[on_index, 0]]]
    assert np.mean([n.startswith("index") for n in joint_names]) > 0.9


def test_proposals_follow_the_hands():
    src = demo_hand("source_human", resolution=0.005)
    witch = propose_annotations(src, demo_hand("witch", resolution=0.005))
    assert all(c.target.lambda_a > 1.3 for c in witch.curves if c.name in ("index", "middle", "ring"))
    assert all(c.target.lambda_s.uniform < 1.0 for c in witch.curves if c.name in ("index", "middle", "ring"))
    robot = propose_annotations(src, demo_hand("robot4", resolution=0.005))
    assert [c.name for c in robot.curves if c.discard] == ["pinky"]
    # the proposal is a valid annotation file
    annotations_from_dict(json.loads(json.dumps(annotations_to_dict(robot))))


# ---- analytic case: cylinders ------------------------------------------------------------------
def cylinder(radius, length, resolution=0.0012):
    lower, upper = (-radius, -radius, 0.0), (radius, radius, length)
    grid, shape, origin = sample_grid(np.array(lower), np.array(upper), resolution)
    field = capped_cylinder(grid, radius, 0.0, length, rounding=0.4 * radius)
    return closed_surface_from_field(field.reshape(shape), origin, resolution)


def surface_point(vertices, faces, xyz):
    sp = closest_surface_points(vertices, faces, np.asarray(xyz, float)[None])
    return PointRef(face=int(sp.faces[0]), barycentric=tuple(float(x) for x in sp.barycentric[0]))


def finger_annotations(src, tgt, r1, r2, length1, length2, lambda_a, lambda_s):
    """One axial curve along each cylinder's side (the generator line at angle 0, +X)."""
    z0 = 0.02
    return Annotations(
        source=MeshSignature("cylinder1", len(src[0]), len(src[1])),
        target=MeshSignature("cylinder2", len(tgt[0]), len(tgt[1])),
        markers=(),
        curves=(AxialCurveAnnotation(
            name="finger",
            source_start=surface_point(*src, (r1, 0, z0)), source_end=surface_point(*src, (r1, 0, length1 - z0)),
            target=CurveTarget(start=surface_point(*tgt, (r2, 0, z0)), direction=surface_point(*tgt, (r2, 0, length2 - z0)),
                               lambda_a=lambda_a, lambda_s=LambdaS.constant(lambda_s))),),
    )


@pytest.fixture(scope="module")
def cylinders():
    return cylinder(0.010, 0.10), cylinder(0.014, 0.13)


def patch(r1, heights, angles):
    """Points on the side of the source cylinder (radius r1) at given heights and angles."""
    h, a = np.meshgrid(heights, angles)
    return np.column_stack([r1 * np.cos(a.ravel()), r1 * np.sin(a.ravel()), h.ravel()])


@pytest.mark.parametrize("lambda_a, lambda_s, reconstruction", [
    (1.0, 1.0, "chart"), (1.3, 1.0, "chart"), (1.0, 1.4, "chart"), (1.3, 1.4, "chart"), (1.3, 1.4, "trace")])
def test_cylinder_patch_moves_where_geodesics_say(cylinders, lambda_a, lambda_s, reconstruction):
    (v1, f1), (v2, f2) = cylinders
    r1, r2 = 0.010, 0.014
    annotations = finger_annotations((v1, f1), (v2, f2), r1, r2, 0.10, 0.13, lambda_a, lambda_s)
    atlas = Atlas(SurfaceGeometry(v1, f1), SurfaceGeometry(v2, f2), annotations, reconstruction=reconstruction)
    heights = np.array([0.035, 0.05, 0.065])
    angles = np.array([-0.5, -0.25, 0.0, 0.25, 0.5])  # radians around the source cylinder
    points = closest_surface_points(v1, f1, patch(r1, heights, angles))
    result = atlas.transfer(points)
    assert not result.dropped.any()
    out = SurfacePoints(result.face, result.barycentric).positions(v2, f2)
    start = 0.02
    # Along the axis: the landmark's arclength stretched by lambda_a (the contact sits beside it).
    expected_z = start + (points.positions(v1, f1)[:, 2] - start) * lambda_a
    assert np.abs(out[:, 2] - expected_z).max() < 0.0015
    # Around the axis: the geodesic distance from the curve, r1 * angle, scaled by lambda_s,
    # wraps the larger cylinder by that arc.
    h, a = np.meshgrid(heights, angles)
    expected_angle = r1 * a.ravel() * lambda_s / r2
    got_angle = np.arctan2(out[:, 1], out[:, 0])
    assert np.abs(got_angle - expected_angle).max() < 0.03
    # And against exact (MMP) geodesics on the target mesh: the distance from each contact's
    # target landmark equals lambda_s times its source chart radius.
    exact = pygeodesic.PyGeodesicAlgorithmExact(v2, f2)
    for i in range(0, len(out), 3):
        m = result.landmark[i]
        curve = atlas.target_curves[atlas.landmark_curve[m]]
        k = atlas.landmark_index[m]
        landmark_vertex = int(f2[curve.faces[k]][np.argmax(curve.barycentric[k])])
        corner = int(f2[result.face[i]][np.argmax(result.barycentric[i])])
        distance, _ = exact.geodesicDistance(landmark_vertex, corner)
        # both ends snapped to vertices: allow an edge length or so
        assert abs(distance - lambda_s * result.radius[i]) < 0.0025


def test_lambda_s_as_a_function_of_angle(cylinders):
    (v1, f1), (v2, f2) = cylinders
    annotations = finger_annotations((v1, f1), (v2, f2), 0.010, 0.014, 0.10, 0.13, 1.0, 1.0)
    curve = annotations.curves[0]
    # twice as far to the left of the curve (+90 deg), unchanged to the right (-90 deg)
    stretched = LambdaS.piecewise([0, 90, 180, 270], [1.0, 2.0, 1.0, 1.0])
    annotations = Annotations(annotations.source, annotations.target, (), (AxialCurveAnnotation(
        name=curve.name, source_start=curve.source_start, source_end=curve.source_end,
        target=CurveTarget(curve.target.start, curve.target.direction, 1.0, stretched)),))
    atlas = Atlas(SurfaceGeometry(v1, f1), SurfaceGeometry(v2, f2), annotations)
    # Walking up the curve (+Z) on the +X side, "left" (counter-clockwise about the outward
    # normal +X) is toward -Y: the point at -0.3 rad around the axis.
    left_right = closest_surface_points(v1, f1, patch(0.010, [0.05], [-0.3, 0.3]))
    result = atlas.transfer(left_right)
    assert result.angle[0] == pytest.approx(np.pi / 2, abs=0.05)
    assert result.angle[1] == pytest.approx(-np.pi / 2, abs=0.05)
    out = SurfacePoints(result.face, result.barycentric).positions(v2, f2)
    arc = np.abs(np.arctan2(out[:, 1], out[:, 0])) * 0.014
    assert arc[0] == pytest.approx(2 * arc[1], rel=0.15)


# ---- bad input ---------------------------------------------------------------------------------
def test_curve_across_disconnected_parts_is_named(cylinders):
    (v1, f1), _ = cylinders
    two_v = np.vstack([v1, v1 + [0.1, 0, 0]])
    two_f = np.vstack([f1, f1 + len(v1)])
    annotations = Annotations(
        MeshSignature("two", len(two_v), len(two_f)), MeshSignature("one", len(v1), len(f1)), (),
        (AxialCurveAnnotation(name="bridge", source_start=surface_point(two_v, two_f, (0.01, 0, 0.05)),
                              source_end=surface_point(two_v, two_f, (0.11, 0, 0.05)),
                              target=CurveTarget(surface_point(v1, f1, (0.01, 0, 0.03)), surface_point(v1, f1, (0.01, 0, 0.08)),
                                                 1.0, LambdaS.constant(1.0))),))
    with pytest.raises(InputError, match="axial curve 'bridge'.*disconnected"):
        Atlas(SurfaceGeometry(two_v, two_f), SurfaceGeometry(v1, f1), annotations)


def open_tube(radius, length, n_around=32, n_along=40):
    a = np.linspace(0, 2 * np.pi, n_around, endpoint=False)
    z = np.linspace(0, length, n_along)
    v = np.array([[radius * np.cos(t), radius * np.sin(t), h] for h in z for t in a])
    faces = []
    for i in range(n_along - 1):
        for j in range(n_around):
            p, q = i * n_around + j, i * n_around + (j + 1) % n_around
            faces += [[p, q, p + n_around], [q, q + n_around, p + n_around]]
    return v, np.array(faces)


def test_target_curve_running_off_the_boundary_is_named(cylinders):
    (v1, f1), _ = cylinders
    v2, f2 = open_tube(0.01, 0.05)
    annotations = finger_annotations((v1, f1), (v2, f2), 0.010, 0.010, 0.10, 0.05, 1.0, 1.0)
    with pytest.raises(InputError, match="axial curve 'finger'.*runs off the mesh boundary"):
        Atlas(SurfaceGeometry(v1, f1), SurfaceGeometry(v2, f2), annotations)


def test_non_manifold_target_is_rejected(cylinders):
    (v1, f1), _ = cylinders
    bad_f = np.vstack([f1, [[f1[0, 0], f1[0, 1], len(v1)]]])
    bad_v = np.vstack([v1, [[0.0, 0.0, 0.2]]])
    with pytest.raises(InputError, match="manifold"):
        SurfaceGeometry(bad_v, bad_f, name="target surface")


def test_annotations_for_another_rig_are_rejected(source, cylinders):
    annotations = propose_annotations(source, source)
    (v1, f1), _ = cylinders
    with pytest.raises(InputError, match="another rig"):
        Atlas(SurfaceGeometry(v1, f1), SurfaceGeometry(v1, f1), annotations)


def test_point_outside_the_mesh_is_named(source):
    data = annotations_to_dict(propose_annotations(source, source))
    data["axial_curves"][1]["target"]["start"] = {"vertex": 10**7}
    with pytest.raises(InputError, match=r"axial_curves\[1\]\.target\.start: vertex 10000000 out of range"):
        annotations_from_dict(data)
    data = annotations_to_dict(propose_annotations(source, source))
    data["axial_curves"][1]["target"]["lambda_a"] = 0
    with pytest.raises(InputError, match="lambda_a"):
        annotations_from_dict(data)


def test_face_winding_does_not_change_the_geometry_tolerances(source):
    """The chart-trust tolerance (``edge_length``) is a property of the surface, not of where
    each face's corner list starts: the same mesh with its corners rolled, and its mirror image
    (faces (a, c, b)), read the same length."""
    v, f = source.surface.vertices, source.surface.faces
    plain = SurfaceGeometry(v, f)
    rolled = SurfaceGeometry(v, f[:, [1, 2, 0]])
    mirrored = SurfaceGeometry(v * np.array([-1.0, 1.0, 1.0]), f[:, [0, 2, 1]])
    assert rolled.edge_length == pytest.approx(plain.edge_length, rel=1e-12)
    assert mirrored.edge_length == pytest.approx(plain.edge_length, rel=1e-12)
    tri = v[f]
    every_edge = np.linalg.norm(tri[:, [1, 2, 0]] - tri, axis=2)
    assert plain.edge_length == pytest.approx(np.median(every_edge), rel=1e-12)


def test_mirrored_hands_carry_mirrored_contacts_to_mirrored_places(source, clip_pairs):
    """A left pair (both hands mirrored, annotations mirrored) is the right pair's mirror image:
    every contact picks the same chart and lands at the mirror of the right one's target point
    (the left and right results of a two-handed clip depend on it)."""
    from retarget_core.rig.mirror import mirror_annotations, mirror_rig

    _, pairs = clip_pairs
    target = demo_hand("human_alt", 0.008)
    annotations = propose_annotations(source, target)
    right = transfer_clip(pairs, source, target, annotations)
    left_source, left_target = mirror_rig(source), mirror_rig(target)
    left_pairs = type(pairs)(**{**vars(pairs), "hand_barycentric": pairs.hand_barycentric[:, [0, 2, 1]]})
    left = transfer_clip(left_pairs, left_source, left_target, mirror_annotations(annotations))
    np.testing.assert_array_equal(left.contacts.landmark, right.contacts.landmark)
    np.testing.assert_array_equal(left.contacts.dropped, right.contacts.dropped)
    kept = ~right.contacts.dropped
    assert kept.sum() > 500
    at_right = right.contacts.target_points().positions(target.surface.vertices, target.surface.faces)
    at_left = left.contacts.target_points().positions(left_target.surface.vertices, left_target.surface.faces)
    gap = np.linalg.norm(at_left[kept] - at_right[kept] * np.array([-1.0, 1.0, 1.0]), axis=1)
    assert gap.max() < 1e-6  # metres: the same chart gives the same point, up to float rounding


def test_vertex_and_face_order_do_not_change_where_contacts_land(source, clip_pairs):
    """Another exporter writes the same target hand with its vertices and faces in another order
    and each face's corners starting elsewhere: the annotations are carried onto it by position,
    and every contact lands at the same point of the hand."""
    from dataclasses import replace

    from retarget_core.rig.model import SkinnedMesh
    from retarget_core.transfer.annotations import remap_to_meshes, with_positions

    _, pairs = clip_pairs
    target = demo_hand("human_alt", 0.008)
    annotations = with_positions(propose_annotations(source, target), source, target)
    s = target.surface
    rng = np.random.default_rng(3)
    order = rng.permutation(len(s.vertices))  # new vertex i is old vertex order[i]
    faces = np.argsort(order)[s.faces]
    faces = np.stack([np.roll(f, -k) for f, k in zip(faces, rng.integers(0, 3, len(faces)))])
    faces = faces[rng.permutation(len(faces))]
    shuffled = replace(target, surface=SkinnedMesh(s.vertices[order], faces, s.joint_indices[order],
                                                   s.joint_weights[order]))
    carried, _ = remap_to_meshes(annotations, source, shuffled)
    before = transfer_clip(pairs, source, target, annotations).contacts
    after = transfer_clip(pairs, source, shuffled, carried).contacts
    np.testing.assert_array_equal(after.dropped, before.dropped)
    np.testing.assert_array_equal(after.landmark, before.landmark)
    kept = ~before.dropped
    assert kept.sum() > 500
    gap = np.linalg.norm(after.target_points().positions(shuffled.surface.vertices, faces)[kept]
                         - before.target_points().positions(s.vertices, s.faces)[kept], axis=1)
    assert gap.max() < 1e-9  # metres


def test_proposed_finger_curves_run_along_the_palmar_midline_on_both_hands():
    """Over the first 80 % of every proposed finger curve, on the source and on the target, the
    landmark lies within 45 deg of straight palmar of its bone (the side it is on: its offset
    from the nearest bone segment, across the bone). The old curves, one geodesic shot from
    the knuckle to the apex, spiralled round the fingers (to 170 deg on the prosthetic's
    middle finger, 118 deg on the witch's pinky), so pad contacts landed on the fingers' sides."""
    from retarget_core.rig.hand_model import hand_model

    src = demo_hand("source_human", resolution=0.005)
    for name in ("prosthetic_1dof", "witch"):
        tgt = demo_hand(name, resolution=0.005)
        annotations = propose_annotations(src, tgt)
        atlas = Atlas(SurfaceGeometry(src.surface.vertices, src.surface.faces),
                      SurfaceGeometry(tgt.surface.vertices, tgt.surface.faces), annotations)
        for ci, c in enumerate(annotations.curves):
            if c.name in ("thumb", "palm", "knuckles") or c.discard:
                continue
            for rig, curve in ((src, atlas.source_curves[ci]), (tgt, atlas.target_curves[ci])):
                finger = hand_model(rig).finger(c.name)
                for k in range(int(0.8 * len(curve.positions))):
                    point = curve.positions[k]
                    seg = min(finger.segments, key=lambda g: _distance_to_segment(point, g))
                    t = np.clip((point - seg.start) @ seg.direction, 0.0, seg.length)
                    offset = point - (seg.start + t * seg.direction)
                    side = offset - (offset @ seg.direction) * seg.direction
                    cosine = side @ seg.palmar / np.linalg.norm(side)
                    assert cosine > np.cos(np.radians(45)), (name, c.name, k, np.degrees(np.arccos(cosine)))


def _distance_to_segment(point, segment) -> float:
    """Distance (m) from point (3,) to the bone segment's line piece start..end."""
    t = np.clip((point - segment.start) @ segment.direction / segment.length, 0.0, 1.0)
    return float(np.linalg.norm(point - (segment.start + t * segment.length * segment.direction)))


def test_a_target_curve_through_anchors_follows_them(cylinders):
    """Known answer on cylinders: the source curve along the generator at angle 0 through three
    points; the target through points at angle 0 then pi/2 (a helix leg, then a straight one).
    Landmarks correspond one to one, anchors land on their points, and a contact beside the
    second leg lands beside the target's second leg at the same offset."""
    (v1, f1), (v2, f2) = cylinders
    r1, r2 = 0.010, 0.014
    src_pts = [surface_point(v1, f1, (r1, 0, z)) for z in (0.02, 0.05, 0.08)]
    a = np.pi / 2
    through = [surface_point(v2, f2, (r2 * np.cos(a), r2 * np.sin(a), z)) for z in (0.06, 0.11)]
    annotations = Annotations(
        MeshSignature("cylinder1", len(v1), len(f1)), MeshSignature("cylinder2", len(v2), len(f2)), (),
        (AxialCurveAnnotation(name="finger", source_points=tuple(src_pts), target=CurveTarget(
            start=surface_point(v2, f2, (r2, 0, 0.02)), direction=through[0], lambda_a=1.0,
            lambda_s=LambdaS.constant(1.0), through=tuple(through))),))
    atlas = Atlas(SurfaceGeometry(v1, f1), SurfaceGeometry(v2, f2), annotations)
    s, t = atlas.source_curves[0], atlas.target_curves[0]
    assert len(s) == len(t)
    for k, point in zip(s.anchors[1:], through):
        expected = SurfacePoints(np.array([point.face]), np.array([point.barycentric])).positions(v2, f2)[0]
        assert np.linalg.norm(t.positions[k] - expected) < 1e-4
    # a contact 0.2 rad round the source cylinder, 15 mm into the second leg (of 30 mm)
    contact = closest_surface_points(v1, f1, np.array([[r1 * np.cos(0.2), r1 * np.sin(0.2), 0.065]]))
    out = SurfacePoints(*(lambda r: (r.face, r.barycentric))(atlas.transfer(contact))).positions(v2, f2)[0]
    assert abs(np.arctan2(out[1], out[0]) - (a + r1 * 0.2 / r2)) < 0.05
    assert abs(out[2] - (0.06 + 0.5 * 0.05)) < 0.003


def test_through_points_are_checked():
    p = PointRef(vertex=1)
    with pytest.raises(InputError, match="begin with the direction point"):
        CurveTarget(start=p, direction=PointRef(vertex=2), lambda_a=1.0, lambda_s=LambdaS.constant(1.0),
                    through=(PointRef(vertex=3),))
    target = CurveTarget(start=p, direction=PointRef(vertex=2), lambda_a=1.0, lambda_s=LambdaS.constant(1.0),
                         through=(PointRef(vertex=2), PointRef(vertex=3)))
    with pytest.raises(InputError, match="need source points"):
        AxialCurveAnnotation(name="f", source_start=p, source_end=PointRef(vertex=4), target=target)
    with pytest.raises(InputError, match="needs 1 'through' points, not 2"):
        AxialCurveAnnotation(name="f", source_points=(p, PointRef(vertex=4)), target=target)
    ok = AxialCurveAnnotation(name="f", source_points=(p, PointRef(vertex=4), PointRef(vertex=5)), target=target)
    assert ok.to_dict()["target"]["through"] == [{"vertex": 2}, {"vertex": 3}]


def test_a_leg_no_shot_lands_on_follows_the_shortest_path(cylinders, monkeypatch):
    """When shooting cannot land on the leg's end (here forced: every shot reported 1 cm off),
    the leg is the shortest path cut into equal pieces, both ends exactly on their points
    (known answer: the generator line of the cylinder, to its vertices' spacing)."""
    from retarget_core.transfer import axial_curves

    _, (v2, f2) = cylinders
    r2 = 0.014
    g = SurfaceGeometry(v2, f2)
    start, end = (closest_surface_points(v2, f2, np.array([p])) for p in ((r2, 0, 0.02), (r2, 0, 0.11)))
    monkeypatch.setattr(axial_curves, "_shoot", lambda *a, **k: (np.array([0.0, 0.0, 1.0]), 0.09, 0.01))
    faces, bary, positions, directions = axial_curves._leg(g, start, end, n_segments=9)
    assert len(positions) == 10
    assert np.linalg.norm(positions[0] - start.positions(v2, f2)[0]) < 1e-12
    assert np.linalg.norm(positions[-1] - end.positions(v2, f2)[0]) < 1e-12
    assert np.abs(np.arctan2(positions[:, 1], positions[:, 0])).max() < 0.05  # on the generator
    steps = np.diff(positions[:, 2])
    assert np.abs(steps - 0.01).max() < 0.001  # 9 equal steps of 10 mm
    assert (directions[:, 2] > 0.99).all()  # along the axis, toward the end
    assert np.abs(np.einsum("ij,ij->i", directions, g.face_normals[faces])).max() < 1e-9  # in each face
