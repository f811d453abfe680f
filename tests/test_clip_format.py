"""The clip format: round trip, and every bad field named by the validator."""

import io
import zipfile

import numpy as np
import pytest
import trimesh

from retarget_core.clip import Clip, load_clip
from retarget_core.errors import InputError


def small_clip(n_frames=4) -> Clip:
    hand = trimesh.creation.icosphere(subdivisions=1, radius=0.02)
    obj = trimesh.creation.box((0.05, 0.05, 0.05))
    hv = np.repeat(np.asarray(hand.vertices, np.float32)[None], n_frames, axis=0)
    hv += np.linspace(0, 0.01, n_frames, dtype=np.float32)[:, None, None]
    poses = np.repeat(np.eye(4)[None], n_frames, axis=0)
    labels = np.zeros((n_frames, len(obj.vertices)), dtype=np.uint8)
    labels[1, :3] = 22
    labels[2, 4] = 45
    return Clip(
        fps=120.0, hand_faces=np.asarray(hand.faces), hand_vertices=hv,
        object_vertices=np.asarray(obj.vertices), object_faces=np.asarray(obj.faces), object_poses=poses,
        contact_labels=labels, table_pose=np.eye(4), table_half_extents=np.array([0.5, 0.3, 0.02]),
        marker_names=["A", "B"], marker_faces=np.array([0, 3]), marker_barycentric=np.array([[1, 0, 0], [0.2, 0.3, 0.5]]),
        dof_names=["a", "b"], dof_values=np.zeros((n_frames, 2)), object_name="cube", motion="test", source="unit",
    )


def test_round_trip(tmp_path):
    clip = small_clip()
    clip.save(tmp_path / "c.npz")
    back = load_clip(tmp_path / "c.npz")
    for name in ("hand_vertices", "hand_faces", "object_vertices", "object_faces", "object_poses", "contact_labels",
                 "table_pose", "table_half_extents", "marker_faces", "marker_barycentric", "dof_values"):
        np.testing.assert_array_equal(getattr(back, name), getattr(clip, name))
    assert back.marker_names == ["A", "B"] and back.dof_names == ["a", "b"]
    assert (back.object_name, back.motion, back.source, back.fps) == ("cube", "test", "unit", 120.0)
    assert back.markers()["B"][0] == 3
    assert not list(tmp_path.glob(".*tmp"))  # atomic write leaves nothing behind


@pytest.mark.parametrize("mutate, field, text", [
    (lambda c: c.hand_vertices.__setitem__((2, 5, 1), np.nan), "hand_vertices", "frame 2"),
    (lambda c: setattr(c, "object_poses", c.object_poses[:3]), "object_poses", "T=4"),
    (lambda c: c.object_poses.__setitem__((1, 0, 0), 2.0), "object_poses", "frame 1: not a rigid transform"),
    (lambda c: c.hand_faces.__setitem__((3, 1), 10_000), "hand_faces", "face 3"),
    (lambda c: setattr(c, "contact_labels", c.contact_labels[:, :5]), "contact_labels", "Vo="),
    (lambda c: c.contact_labels.__setitem__((3, 0), 30), "contact_labels", "frame 3: code 30"),
    (lambda c: setattr(c, "fps", -1.0), "fps", "positive"),
    (lambda c: setattr(c, "marker_faces", np.array([0])), "marker_faces", "must agree"),
    (lambda c: setattr(c, "dof_values", np.zeros((4, 3))), "dof_values", "D=2"),
    (lambda c: setattr(c, "table_half_extents", None), "table_pose", "go together"),
])
def test_validator_names_the_field(mutate, field, text):
    clip = small_clip()
    mutate(clip)
    with pytest.raises(InputError) as err:
        clip.validate(source="clip.npz")
    message = str(err.value)
    assert "clip.npz" in message and field in message and text in message


def test_bad_clip_is_never_written(tmp_path):
    clip = small_clip()
    clip.save(tmp_path / "c.npz")
    before = (tmp_path / "c.npz").read_bytes()
    clip.hand_vertices[0, 0, 0] = np.inf
    with pytest.raises(InputError):
        clip.save(tmp_path / "c.npz")
    assert (tmp_path / "c.npz").read_bytes() == before


def _rewrite(path, **changes):
    data = dict(np.load(path, allow_pickle=False))
    for k, v in changes.items():
        if v is None:
            data.pop(k)
        else:
            data[k] = v
    np.savez(path, **data)


def test_file_level_errors(tmp_path):
    path = tmp_path / "c.npz"
    small_clip().save(path)
    _rewrite(path, object_faces=None)
    with pytest.raises(InputError, match="object_faces.*missing"):
        load_clip(path)
    small_clip().save(path)
    _rewrite(path, format=np.array("something.else"))
    with pytest.raises(InputError, match="not a Hand Retarget clip"):
        load_clip(path)
    small_clip().save(path)
    _rewrite(path, version=np.array(7))
    with pytest.raises(InputError, match="version 7"):
        load_clip(path)
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match="not a clip"):
        load_clip(tmp_path / "junk.npz")
    with pytest.raises(InputError, match="no such file"):
        load_clip(tmp_path / "missing.npz")


def test_pickled_field_is_refused_not_unpickled(tmp_path):
    path = tmp_path / "c.npz"
    small_clip().save(path)
    data = dict(np.load(path, allow_pickle=False))
    data["motion"] = np.array([{"evil": 1}], dtype=object)
    buffer = io.BytesIO()
    np.savez(buffer, **data)
    path.write_bytes(buffer.getvalue())
    with zipfile.ZipFile(path) as z:
        assert "motion.npy" in z.namelist()
    with pytest.raises(InputError, match="motion.*Python objects"):
        load_clip(path)


def test_slice_keeps_frames(tmp_path):
    part = small_clip(6).slice(2, 5)
    assert part.n_frames == 3 and part.dof_values.shape == (3, 2)
    part.validate()
