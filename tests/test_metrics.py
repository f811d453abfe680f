"""Evaluation metrics on small hand-computed arrays with known answers: contact, coverage,
marker, smoothness and limit metrics (the intersection volumes: test_intersection.py)."""

import json
import math

import numpy as np
import pytest

from boxes import box_mesh
from retarget_core.errors import InputError
from retarget_core.evaluate import (
    contact_coverage,
    contact_distance_per_frame,
    contact_distances,
    coverage_per_frame,
    dof_derivatives,
    dof_limit_violations,
    dof_smoothness,
    marker_error_per_frame,
    median_per_frame_mm,
    summarize_series,
)



@pytest.mark.parametrize("beyond, realised", [(0.0, True), (1e-12, True), (1e-6, False)],
                         ids=["at the threshold", "1e-12 m beyond", "1e-6 m beyond"])
def test_contact_realised_up_to_the_stated_tolerance_beyond_the_threshold(beyond, realised):
    c = contact_coverage(np.array([0.005 + beyond, 0.001]), threshold_m=0.005)
    assert c.n_realised == (2 if realised else 1)


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
