"""Object substitution: contacts traced onto a new object, then the normal pipeline."""

import contextlib
import io

import numpy as np
import pytest
import trimesh

from retarget_core.cli import main
from retarget_core.clip import load_clip
from retarget_core.clip.demo import make_demo_clip, source_rig
from retarget_core.clip.substitute import substitute_object, trace_onto
from retarget_core.errors import InputError
from retarget_core.pairing import pair_contacts


@pytest.fixture(scope="module")
def clip():
    return make_demo_clip("bottle_pick_place", time_scale=0.05, resolution=0.004, rig=source_rig(0.004))


def test_trace_onto_a_concentric_sphere_lands_straight_out():
    """Points on a unit-ish sphere traced along their normals onto a sphere 5 mm larger land on
    the new vertex nearest the radial hit; beyond max_distance nothing is found."""
    small = trimesh.creation.icosphere(subdivisions=3, radius=0.03)
    big = trimesh.creation.icosphere(subdivisions=4, radius=0.035)
    hit = trace_onto(small.vertices, small.vertex_normals, big.vertices, big.faces, max_distance=0.01)
    assert np.all(hit >= 0)
    radial = small.vertices / np.linalg.norm(small.vertices, axis=1, keepdims=True) * 0.035
    assert np.linalg.norm(big.vertices[hit] - radial, axis=1).max() < 0.004  # within a mesh edge
    assert np.all(trace_onto(small.vertices, small.vertex_normals, big.vertices, big.faces, max_distance=0.004) < 0)
    inner = trace_onto(big.vertices, big.vertex_normals, small.vertices, small.faces, max_distance=0.01)
    assert np.all(inner >= 0)  # inward when nothing is outward


def test_substituting_the_same_object_keeps_every_label(clip):
    same, report = substitute_object(clip, clip.object_vertices, clip.object_faces, name="bottle")
    assert report["dropped"] == 0 and report["traced"] == report["labelled_vertices"] > 0
    assert np.array_equal(same.contact_labels, clip.contact_labels)
    assert np.array_equal(same.hand_vertices, clip.hand_vertices)


def test_a_wider_object_gets_the_contacts_and_pairs_with_the_hand(clip):
    wide = clip.object_vertices * [1.1, 1.1, 1.0]
    new, report = substitute_object(clip, wide, clip.object_faces, name="wide bottle")
    assert report["dropped"] == 0 and new.object_name == "wide bottle"
    frames = (clip.contact_labels > 0).any(axis=1)
    assert np.array_equal((new.contact_labels > 0).any(axis=1), frames)
    pairs = pair_contacts(new)
    assert np.diff(pairs.frame_offsets)[frames].sum() > 0.8 * np.diff(pair_contacts(clip).frame_offsets)[frames].sum()


def test_bad_new_objects_are_named(clip, tmp_path):
    box = trimesh.creation.box([0.05, 0.05, 0.2])
    with pytest.raises(InputError, match="closed manifold"):
        substitute_object(clip, box.vertices, box.faces[:-1])
    with pytest.raises(InputError, match="finite"):
        substitute_object(clip, np.full((8, 3), np.nan), box.faces)
    clip.save(tmp_path / "c.npz")
    (tmp_path / "junk.obj").write_text("this is not a mesh\n")
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = main(["clip", "substitute", str(tmp_path / "c.npz"), "--object", "demo:teapot", "--out",
                     str(tmp_path / "n.npz")])
    assert code == 2 and "teapot" in err.getvalue() and not (tmp_path / "n.npz").exists()


def test_cli_substitute_writes_a_valid_clip(clip, tmp_path):
    clip.save(tmp_path / "c.npz")
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(["clip", "substitute", str(tmp_path / "c.npz"), "--object", "demo:bottle", "--scale", "1.1,1.1,1",
                     "--out", str(tmp_path / "n.npz")])
    assert code == 0
    new = load_clip(tmp_path / "n.npz")
    assert new.object_name == "bottle" and (new.contact_labels > 0).any()
    assert "traced" in out.getvalue()
