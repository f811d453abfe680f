"""Contact patches keep their source size on the target (transfer/clip_transfer.size_patches)."""

import numpy as np
import trimesh

from retarget_core.mesh.surface_points import closest_surface_points
from retarget_core.transfer.atlas import TransferredContacts
from retarget_core.transfer.clip_transfer import _spread, patches, size_patches

R = 0.014  # a robot fingertip's radius (m)


def _sphere():
    s = trimesh.creation.icosphere(subdivisions=5, radius=R)
    return np.asarray(s.vertices), np.asarray(s.faces, dtype=np.int64)


def _disc(centre_xy, rms, n, rng):
    """n points of a flat source patch (z = 0) about centre_xy with RMS radius ``rms`` m."""
    p = rng.normal(size=(n, 2))
    p -= p.mean(axis=0)
    p *= rms / np.sqrt((p ** 2).sum(axis=1).mean())
    return np.column_stack([p + centre_xy, np.zeros(n)])


def _cap(direction, rms, n, rng, v, f):
    """n surface points of the sphere in a cap about ``direction`` with tangent RMS radius ``rms``."""
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    a = np.cross(d, [0.0, 0.0, 1.0] if abs(d[2]) < 0.9 else [1.0, 0.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(d, a)
    t = rng.normal(size=(n, 2))
    t -= t.mean(axis=0)
    t *= rms / np.sqrt((t ** 2).sum(axis=1).mean())
    return closest_surface_points(v, f, R * d + t[:, :1] * a + t[:, 1:] * b)


def _up(n):
    """Normals (n, 3) of the flat source patches."""
    return np.tile([0.0, 0.0, 1.0], (n if isinstance(n, int) else len(n), 1))


def _contacts(points, curve):
    n = len(points)
    return TransferredContacts(points.faces, points.barycentric, np.zeros(n, np.int64), np.asarray(curve),
                               np.zeros(n, bool), np.zeros(n), np.zeros(n))


def _place(points):
    """Where on the sphere a patch is: its centroid's direction, on the surface (3,) m (the 3-D
    centroid of a curved patch lies below the surface, deeper the larger the patch)."""
    c = points.mean(axis=0)
    return R * c / np.linalg.norm(c)


def _positions(c, v, f):
    return np.einsum("nk,nkd->nd", c.barycentric, v[f[c.face]])


def test_a_patch_the_charts_grew_gets_the_source_size_back_on_the_surface_at_its_place():
    rng = np.random.default_rng(3)
    v, f = _sphere()
    src = _disc([0.0, 0.0], 0.0034, 17, rng)  # robot4's box_pinch index patch: 3.4 mm RMS
    grown = _cap([0.0, -1.0, 1.0], 0.0088, 17, rng, v, f)  # what the charts gave: 2.6x
    before = _positions(_contacts(grown, np.zeros(17, np.int64)), v, f)
    out = size_patches(_contacts(grown, np.zeros(17, np.int64)), np.array([0, 17]), src, _up(src), v, f)
    after = _positions(out, v, f)
    assert abs(_spread(after) / _spread(src) - 1.0) < 0.1
    assert np.allclose(np.linalg.norm(after, axis=1), R, atol=2e-4)  # on the surface (faceted sphere)
    # where the charts put it: the centre moves by well under the patch's size
    assert np.linalg.norm(_place(after) - _place(before)) < 0.0005
    # each point keeps its direction from the centre (the pairing with object points holds)
    da, db = after - after.mean(axis=0), before - before.mean(axis=0)
    cos = np.einsum("nd,nd->n", da, db) / (np.linalg.norm(da, axis=1) * np.linalg.norm(db, axis=1))
    assert np.median(cos) > 0.95


def test_a_patch_of_the_right_size_stays_and_separate_patches_and_frames_are_sized_apart():
    rng = np.random.default_rng(5)
    v, f = _sphere()
    # frame 0: two patches on one curve 30 mm apart on the source, each grown 2x on the target
    # frame 1: one patch already of the source's size
    s0 = np.vstack([_disc([0.0, 0.0], 0.002, 10, rng), _disc([0.03, 0.0], 0.002, 10, rng)])
    s1 = _disc([0.0, 0.0], 0.003, 12, rng)
    t0a = _cap([1.0, 0.0, 0.2], 0.004, 10, rng, v, f)
    t0b = _cap([-1.0, 0.0, 0.2], 0.004, 10, rng, v, f)
    t1 = _cap([0.0, 0.0, 1.0], 0.003, 12, rng, v, f)
    faces = np.concatenate([t0a.faces, t0b.faces, t1.faces])
    bary = np.vstack([t0a.barycentric, t0b.barycentric, t1.barycentric])
    contacts = TransferredContacts(faces, bary, np.zeros(32, np.int64), np.zeros(32, np.int64), np.zeros(32, bool),
                                   np.zeros(32), np.zeros(32))
    assert len(np.unique(patches(s0))) == 2
    before = _positions(contacts, v, f)
    after = _positions(size_patches(contacts, np.array([0, 20, 32]), np.vstack([s0, s1]), _up(32), v, f), v, f)
    for sl, src in ((slice(0, 10), s0[:10]), (slice(10, 20), s0[10:])):
        assert abs(_spread(after[sl]) / _spread(src) - 1.0) < 0.1
        assert np.linalg.norm(_place(after[sl]) - _place(before[sl])) < 0.0005
    assert np.linalg.norm(after[20:] - before[20:], axis=1).max() < 0.0005


def test_dropped_contacts_and_single_points_are_left_alone():
    rng = np.random.default_rng(7)
    v, f = _sphere()
    t = _cap([0.0, 0.0, 1.0], 0.008, 6, rng, v, f)
    dropped = np.array([True, True, True, True, True, False])
    c = TransferredContacts(t.faces, t.barycentric, np.zeros(6, np.int64), np.zeros(6, np.int64), dropped,
                            np.zeros(6), np.zeros(6))
    out = size_patches(c, np.array([0, 6]), _disc([0.0, 0.0], 0.002, 6, rng), _up(6), v, f)
    assert np.array_equal(out.face, c.face) and np.array_equal(out.barycentric, c.barycentric)
