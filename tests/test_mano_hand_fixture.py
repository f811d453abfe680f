"""The hand-shaped synthetic MANO fixture (tests/mano_hand.py): loads, is a MANO-like disk, its
regressor, markers and skin weights make sense. Distances in metres."""

import numpy as np
import pytest
import trimesh

from grab_fixtures import PARENTS, make_mano_raw, write_mano_official, write_mano_plain
from mano_hand import boundary_loops, hand_mano_landmarks, is_oriented_disk, make_hand_mano_raw
from retarget_core.clip.grab import load_mano_model, mano_forward
from retarget_core.clip.markers import MANO_MARKERS

#: Marker vertex to landmark: the fixture moves each marker vertex onto its landmark (rounding only).
MARKER_TOLERANCE = 1e-9

FINGER_BASE = {"index": 1, "middle": 4, "pinky": 7, "ring": 10, "thumb": 13}  # MANO joint ids
PALM_MARKERS = ("BackIndex", "BackRing", "WristLeft", "WristRight", "PalmRoot")


@pytest.fixture(scope="module")
def raw():
    return make_hand_mano_raw(0)


def _capped(vertices, faces):
    """The surface with its wrist opening closed by a fan around the loop's centroid."""
    loop = boundary_loops(faces)[0]
    directed = {tuple(e) for e in np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]).tolist()}
    centre = len(vertices)
    cap = []
    for a, b in zip(loop, loop[1:] + loop[:1]):
        cap.append([b, a, centre] if (a, b) in directed else [a, b, centre])
    return np.vstack([vertices, vertices[loop].mean(axis=0)]), np.vstack([faces, cap])


def test_same_keys_as_plain_fixture_and_cached_copy(raw):
    assert set(make_mano_raw(0)) <= set(raw)
    again = make_hand_mano_raw(0)
    again["v_template"][:] = 0.0
    assert np.abs(make_hand_mano_raw(0)["v_template"]).max() > 0.05  # the cache was not touched
    other = make_hand_mano_raw(1)
    np.testing.assert_array_equal(other["v_template"], raw["v_template"])  # the seed only drives blend shapes
    assert not np.allclose(other["hands_mean"], raw["hands_mean"])


@pytest.mark.parametrize("writer", [write_mano_plain, write_mano_official])
def test_loads_through_load_mano_model(tmp_path, raw, writer):
    model = load_mano_model(writer(tmp_path / "MANO_RIGHT.pkl", raw))
    assert model.v_template.shape == (778, 3)
    np.testing.assert_allclose(model.v_template, raw["v_template"])
    np.testing.assert_array_equal(model.faces, raw["f"].astype(np.int64))
    np.testing.assert_array_equal(model.parents, PARENTS)
    assert np.abs(model.hands_mean).max() > 0.01
    rest = mano_forward(model, np.zeros(3), np.zeros(45), np.zeros(3))
    np.testing.assert_allclose(rest[0], raw["v_template"], atol=1e-9)


def test_surface_is_a_closed_hand_open_at_the_wrist(raw):
    v, f = raw["v_template"], raw["f"].astype(np.int64)
    assert v.shape == (778, 3) and f.shape[1] == 3
    assert is_oriented_disk(f, 778)
    loops = boundary_loops(f)
    assert len(loops) == 1
    mesh = trimesh.Trimesh(v, f, process=False)
    assert mesh.is_winding_consistent and not mesh.is_watertight
    assert mesh.body_count == 1
    cv, cf = _capped(v, f)
    capped = trimesh.Trimesh(cv, cf, process=False)
    assert capped.is_watertight and capped.is_winding_consistent and capped.euler_number == 2
    assert capped.volume > 1e-4  # outward (a hand is ~2.5e-4 m^3)
    # The opening is at the wrist: its loop is nearer the wrist joint than any fingertip.
    j = raw["J"]
    loop_centre = v[loops[0]].mean(axis=0)
    assert np.linalg.norm(loop_centre - j[0]) < 0.02
    assert np.linalg.norm(j[0] - [0.09, 0.006, 0.006]) < 1e-12
    # Every joint is inside the (capped) hand.
    import igl

    wn = igl.winding_number(cv, cf.astype(np.int64), np.ascontiguousarray(j))
    assert (wn > 0.5).all()


def test_regressor_reproduces_joints(raw):
    reg = raw["J_regressor"]
    assert reg.shape == (16, 778) and reg.min() >= 0.0
    np.testing.assert_allclose(reg.sum(axis=1), 1.0, atol=1e-12)
    assert np.abs(reg @ raw["v_template"] - raw["J"]).max() < 1e-6
    assert np.asarray(raw["kintree_table"]).shape == (2, 16)


def test_marker_vertices_sit_on_their_landmarks(raw):
    landmarks = hand_mano_landmarks(0)
    assert set(landmarks) == set(MANO_MARKERS)
    v = raw["v_template"]
    dist = {n: float(np.linalg.norm(v[vid] - landmarks[n])) for n, vid in MANO_MARKERS.items()}
    assert max(dist.values()) < MARKER_TOLERANCE, dist
    # Fingertips lie beyond the finger's last joint, the palm markers near the palm.
    j = raw["J"]
    for finger, base in FINGER_BASE.items():
        tip = v[MANO_MARKERS[f"{finger.capitalize()}Fingertip"]]
        along = j[base + 2] - j[base + 1]
        assert (tip - j[base + 2]) @ along > 0.0


def test_marker_vertices_are_skinned_to_their_part(raw):
    w = raw["weights"]
    assert w.shape == (778, 16) and w.min() >= 0.0
    np.testing.assert_allclose(w.sum(axis=1), 1.0, atol=1e-9)
    owner = {n: int(np.argmax(w[vid])) for n, vid in MANO_MARKERS.items()}
    for finger, base in FINGER_BASE.items():
        title = finger.capitalize()
        assert owner[f"{title}Base"] in (0, base), (finger, owner)
        assert owner[f"{title}Middle"] in (base, base + 1), (finger, owner)
        assert owner[f"{title}Tip"] in (base + 1, base + 2), (finger, owner)
        assert owner[f"{title}Fingertip"] == base + 2, (finger, owner)
    for name in PALM_MARKERS:
        assert owner[name] in (0, *FINGER_BASE.values()), (name, owner)
    assert owner["ThumbFingertip"] == 15
