"""Dense contact pairing: known answers on boxes, penetration, discards, files."""

import numpy as np
import pytest
import trimesh

from retarget_core.clip.format import Clip
from retarget_core.errors import InputError
from retarget_core.pairing import DISCARD_REASONS, ContactPairs, load_contact_pairs, pair_contacts

# Dyadic numbers throughout so float32 hand vertices are exact.
HALF = 0.03125  # object box half size (m): its top face is at z = HALF in the object frame
SPACING = 2 * HALF / 4  # vertex spacing on the twice-subdivided box
THICK = 0.0078125  # hand plate thickness
HOVER = 0.00390625  # hand bottom this far above the object top
SINK = 0.001953125  # ... or this far below it (penetration)
FAR = 0.03125  # farther than epsilon

# The object is rotated 90 degrees about Z and moved; everything else is built in world space.
POSE = np.array([[0.0, -1.0, 0.0, 0.25], [1.0, 0.0, 0.0, -0.125], [0.0, 0.0, 1.0, 0.5], [0.0, 0.0, 0.0, 1.0]])
TOP_WORLD = 0.5 + HALF


def _object_mesh():
    box = trimesh.creation.box(extents=[2 * HALF] * 3)
    v, f = trimesh.remesh.subdivide(box.vertices, box.faces)
    v, f = trimesh.remesh.subdivide(v, f)
    mesh = trimesh.Trimesh(v, f, process=True)  # merges the duplicated edge midpoints
    assert mesh.is_watertight and mesh.volume > 0
    return np.asarray(mesh.vertices), np.asarray(mesh.faces)


def _plate(x_range, y_range, bottom):
    """A closed, outward-wound thin box (the 'hand') in world coordinates."""
    lo = np.array([x_range[0], y_range[0], bottom])
    hi = np.array([x_range[1], y_range[1], bottom + THICK])
    box = trimesh.creation.box(bounds=np.stack([lo, hi]))
    return np.asarray(box.vertices), np.asarray(box.faces)


def _top_interior(obj_v):
    """Object vertices strictly inside the top face (their normals are exactly +Z)."""
    return np.flatnonzero((obj_v[:, 2] == HALF) & (np.abs(obj_v[:, 0]) < HALF) & (np.abs(obj_v[:, 1]) < HALF))


CENTRE = POSE[:2, 3]
WIDE = (CENTRE[0] - 0.0625, CENTRE[0] + 0.0625), (CENTRE[1] - 0.0625, CENTRE[1] + 0.0625)
# covers only world x > centre + 1/128: one of the three interior columns
PARTIAL = (CENTRE[0] + 0.0078125, CENTRE[0] + 0.0625), WIDE[1]

FRAMES = {  # frame: (hand plate, labelled?)
    0: (_plate(*WIDE, TOP_WORLD + HOVER), True),
    1: (_plate(*WIDE, TOP_WORLD - SINK), True),
    2: (_plate(*PARTIAL, TOP_WORLD + HOVER), True),
    3: (_plate(*WIDE, TOP_WORLD + FAR), True),
    4: (_plate(*WIDE, TOP_WORLD + HOVER), False),
}


def _clip(frames=FRAMES, hand_faces_flip=False):
    obj_v, obj_f = _object_mesh()
    top = _top_interior(obj_v)
    assert len(top) == 9
    hand_faces = FRAMES[0][0][1]
    hv = np.stack([frames[f][0][0] for f in sorted(frames)]).astype(np.float32)
    assert np.all(hv.astype(np.float64) == np.stack([frames[f][0][0] for f in sorted(frames)]))
    labels = np.zeros((len(frames), len(obj_v)), dtype=np.uint8)
    for f, (_, labelled) in frames.items():
        if labelled:
            labels[f, top] = 22
            labels[f, top[::2]] = 41
    clip = Clip(
        fps=30.0,
        hand_faces=hand_faces[:, ::-1].copy() if hand_faces_flip else hand_faces,
        hand_vertices=hv,
        object_vertices=obj_v,
        object_faces=obj_f,
        object_poses=np.repeat(POSE[None], len(frames), axis=0),
        contact_labels=labels,
    )
    clip.validate()
    return clip, top


@pytest.fixture(scope="module")
def clip_and_top():
    return _clip()


@pytest.fixture(scope="module")
def pairs(clip_and_top):
    clip, _ = clip_and_top
    return pair_contacts(clip)


def _hand_points(clip, fp):
    hv = clip.hand_vertices[fp.frame].astype(np.float64)
    return fp.hand_points().positions(hv, clip.hand_faces)


def _object_points(clip, fp):
    return fp.object_points().positions(clip.object_world_vertices(fp.frame), clip.object_faces)


def test_known_answer_hover(clip_and_top, pairs):
    clip, top = clip_and_top
    fp = pairs.frame(0)
    assert len(fp) == 9 and sorted(fp.object_vertex) == sorted(top)
    assert not fp.inverted.any()
    np.testing.assert_allclose(fp.gap, HOVER, atol=1e-12)
    obj = _object_points(clip, fp)
    np.testing.assert_allclose(obj[:, 2], TOP_WORLD, atol=1e-12)
    np.testing.assert_allclose(obj, clip.object_world_vertices(0)[fp.object_vertex], atol=1e-12)
    hand = _hand_points(clip, fp)
    expected = obj + [0.0, 0.0, HOVER]
    np.testing.assert_allclose(hand, expected, atol=1e-9)
    # the hit faces are bottom faces of the plate
    hv = clip.hand_vertices[0].astype(np.float64)
    corner_z = hv[clip.hand_faces[fp.hand_face]][..., 2]
    np.testing.assert_array_equal(corner_z, TOP_WORLD + HOVER)
    # and the hit is inside that face
    assert fp.hand_barycentric.min() >= 0 and np.allclose(fp.hand_barycentric.sum(axis=1), 1)
    # labels follow the clip
    np.testing.assert_array_equal(fp.label, clip.contact_labels[0, fp.object_vertex])
    assert set(fp.label) == {22, 41}
    # object ends are the vertices (one-hot barycentric on an incident face)
    corners = clip.object_faces[fp.object_face]
    picked = corners[np.arange(len(fp)), fp.object_barycentric.argmax(axis=1)]
    np.testing.assert_array_equal(picked, fp.object_vertex)
    assert pairs.n_paired[0] == 9 and pairs.n_miss[0] == 0 and pairs.n_too_far[0] == 0


def test_penetration_inverts(clip_and_top, pairs):
    clip, top = clip_and_top
    fp = pairs.frame(1)
    assert len(fp) == 9 and fp.inverted.all()
    assert pairs.n_inverted[1] == 9
    np.testing.assert_allclose(fp.gap, SINK, atol=1e-12)
    hand = _hand_points(clip, fp)
    np.testing.assert_allclose(hand, _object_points(clip, fp) - [0.0, 0.0, SINK], atol=1e-9)
    hv = clip.hand_vertices[1].astype(np.float64)
    np.testing.assert_array_equal(hv[clip.hand_faces[fp.hand_face]][..., 2], TOP_WORLD - SINK)


def test_misses_and_too_far(clip_and_top, pairs):
    clip, top = clip_and_top
    # partial plate: 3 of the 9 contacts are under it
    assert pairs.n_paired[2] == 3 and pairs.n_miss[2] == 6 and pairs.n_too_far[2] == 0
    fp = pairs.frame(2)
    obj = _object_points(clip, fp)
    assert np.all(obj[:, 0] > CENTRE[0] + 0.0078125)
    np.testing.assert_allclose(fp.gap, HOVER, atol=1e-12)
    missed = pairs.discarded(2)["miss"]
    assert len(missed) == 6 and np.all(clip.object_world_vertices(2)[missed, 0] <= CENTRE[0])
    # far plate: everything is too far at the default epsilon ...
    assert pairs.n_paired[3] == 0 and pairs.n_too_far[3] == 9 and pairs.n_miss[3] == 0
    assert len(pairs.discarded(3)["too_far"]) == 9
    # ... and kept with a larger one
    loose = pair_contacts(clip, epsilon=0.05, frames=[3])
    assert loose.n_paired[3] == 9
    np.testing.assert_allclose(loose.frame(3).gap, FAR, atol=1e-12)
    # a tighter epsilon discards the hovering pairs
    tight = pair_contacts(clip, epsilon=0.003, frames=[0])
    assert tight.n_too_far[0] == 9 and tight.n_paired[0] == 0
    # counts add up everywhere
    np.testing.assert_array_equal(pairs.n_contacts, pairs.n_paired + pairs.n_miss + pairs.n_too_far)
    np.testing.assert_array_equal(pairs.n_contacts, (clip.contact_labels > 0).sum(axis=1))
    assert set(DISCARD_REASONS) == {"miss", "too_far"}


def test_frames_without_contacts(clip_and_top, pairs):
    assert pairs.n_contacts[4] == 0 and len(pairs.frame(4)) == 0
    assert pairs.frame_offsets[4] == pairs.frame_offsets[5] == len(pairs)
    s = pairs.summary()
    assert s["frames_with_contacts"] == 4 and s["contacts"] == 36
    assert s["paired"] == 21 and s["miss"] == 6 and s["too_far"] == 9 and s["inverted"] == 9
    assert s["discarded_fraction"] == pytest.approx(15 / 36)
    assert s["gap_max_mm"] == pytest.approx(HOVER * 1e3)
    # a clip with no contacts at all
    clip, _ = clip_and_top
    empty = pair_contacts(Clip(**{**clip.__dict__, "contact_labels": np.zeros_like(clip.contact_labels)}))
    assert len(empty) == 0 and empty.summary()["gap_median_mm"] is None
    empty.validate()


def test_frames_subset_and_progress(clip_and_top):
    clip, _ = clip_and_top
    calls = []
    sub = pair_contacts(clip, frames=[1, 0], progress=lambda d, t: calls.append((d, t)))
    assert calls == [(1, 2), (2, 2)]
    assert sub.processed.tolist() == [True, True, False, False, False]
    assert sub.n_paired.tolist() == [9, 9, 0, 0, 0]
    with pytest.raises(InputError):
        pair_contacts(clip, frames=[7])
    with pytest.raises(InputError):
        pair_contacts(clip, epsilon=0.0)


def test_inward_wound_hand_same_answer(pairs):
    clip, _ = _clip(hand_faces_flip=True)
    flipped = pair_contacts(clip)
    np.testing.assert_array_equal(flipped.inverted, pairs.inverted)
    np.testing.assert_allclose(flipped.gap, pairs.gap, atol=1e-12)
    np.testing.assert_array_equal(flipped.n_miss, pairs.n_miss)


def test_save_load_round_trip(tmp_path, clip_and_top, pairs):
    path = tmp_path / "pairs.npz"
    pairs.save(path)
    back = load_contact_pairs(path)
    for name in ContactPairs.__dataclass_fields__:
        a, b = getattr(pairs, name), getattr(back, name)
        if isinstance(a, np.ndarray):
            assert a.dtype == b.dtype and a.shape == b.shape, name
            np.testing.assert_array_equal(a, b, err_msg=name)
        else:
            assert a == b, name
    back.check_clip(clip_and_top[0])


def _rewrite(src, dst, **changes):
    with np.load(src, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    for k, v in changes.items():
        if v is None:
            arrays.pop(k)
        else:
            arrays[k] = v
    np.savez(dst, **arrays)


@pytest.mark.parametrize(
    "changes, element",
    [
        ({"version": np.array(2)}, "version"),
        ({"format": np.array("handretarget.clip")}, "format"),
        ({"gap": None}, "gap"),
        ({"hand_barycentric": np.zeros((3, 3))}, "hand_barycentric"),
        ({"frame_offsets": np.array([0, 9, 18, 21, 21, 20])}, "frame_offsets"),
        ({"n_miss": np.array([0, 0, 5, 0, 0])}, "n_contacts"),
        ({"inverted": np.zeros(21, dtype=np.float64)}, "inverted"),
        ({"hand_face": np.full(21, 99)}, "hand_face"),
    ],
)
def test_load_rejects_bad_files(tmp_path, pairs, changes, element):
    good = tmp_path / "good.npz"
    pairs.save(good)
    bad = tmp_path / "bad.npz"
    _rewrite(good, bad, **changes)
    with pytest.raises(InputError) as err:
        load_contact_pairs(bad)
    assert err.value.element == element and str(bad) in str(err.value)


def test_load_rejects_non_npz(tmp_path):
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip file")
    with pytest.raises(InputError):
        load_contact_pairs(junk)
    with pytest.raises(InputError):
        load_contact_pairs(tmp_path / "missing.npz")
    obj = tmp_path / "obj.npz"
    np.savez(obj, format=np.array([{"a": 1}], dtype=object))
    with pytest.raises(InputError):
        load_contact_pairs(obj)


def test_check_clip_mismatch(clip_and_top, pairs):
    clip, _ = clip_and_top
    with pytest.raises(InputError):
        pairs.check_clip(clip.slice(0, 3))


def test_hand_exactly_at_the_contact_is_hit():
    frames = {0: (_plate(*WIDE, TOP_WORLD), True), 1: (_plate(*WIDE, TOP_WORLD + 2.0**-18), True)}
    clip, top = _clip(frames)
    pairs = pair_contacts(clip)
    assert pairs.n_paired.tolist() == [9, 9]
    assert not pairs.inverted.any()
    np.testing.assert_allclose(pairs.frame(0).gap, 0.0, atol=1e-12)
    np.testing.assert_allclose(pairs.frame(1).gap, 2.0**-18, atol=1e-12)


def test_benchmark_runs_small():
    from retarget_core.benchmarks.pairing import run_pairing_benchmark

    figures = run_pairing_benchmark(n_frames=6, contacts_per_frame=40, pin_one_core=False)
    assert figures["frames"] == 6 and figures["contacts"] == 240
    s = figures["summary"]
    assert s["paired"] > 0.5 * s["contacts"] and s["gap_max_mm"] <= 15.0
    assert figures["seconds"] > 0


def test_contact_surface_points_pair_like_the_vertices_they_stand_for(clip_and_top, pairs):
    """A format-2 clip whose contact surface points sit exactly on its labelled vertices (one
    corner's weight 1) pairs exactly like the labels; moved inside their faces, the paired
    object points follow them."""
    import dataclasses

    from retarget_core.mesh.surface_points import SurfacePoints

    clip, _ = clip_and_top
    rows = [np.flatnonzero(clip.contact_labels[f]) for f in range(clip.n_frames)]
    ids = np.concatenate(rows)
    sp = SurfacePoints.from_vertices(ids, clip.object_faces)
    frame_of = np.repeat(np.arange(clip.n_frames), [len(r) for r in rows])
    surface = dataclasses.replace(
        clip, contact_offsets=np.concatenate([[0], np.cumsum([len(r) for r in rows])]),
        contact_faces=sp.faces, contact_barycentric=sp.barycentric, contact_codes=clip.contact_labels[frame_of, ids])
    surface.validate()
    same = pair_contacts(surface)
    for name in ("frame_offsets", "object_vertex", "object_face", "object_barycentric", "hand_face", "label",
                 "n_contacts", "n_paired", "discarded_vertex"):
        np.testing.assert_array_equal(getattr(same, name), getattr(pairs, name), err_msg=name)
    np.testing.assert_allclose(same.hand_barycentric, pairs.hand_barycentric, atol=1e-12)
    moved = dataclasses.replace(surface, contact_barycentric=np.full((len(ids), 3), 1 / 3))
    off = pair_contacts(moved)
    assert off.n_paired.sum() > 0
    np.testing.assert_allclose(off.object_barycentric, 1 / 3)
