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


# ---- bounded reading (issue 16, High: "a 1.18 MB clip (an npz decompression bomb) took the server
# from 311 MB to 1.5 GB"; Medium: malformed clips answered 500). Every hostile file is built here.

def _npy(array=None, *, header=None, data=b"") -> bytes:
    """An npy member: ``array`` as numpy writes it, or a hand-made ``header`` dict and ``data``."""
    buf = io.BytesIO()
    if array is not None:
        np.lib.format.write_array(buf, np.asarray(array), allow_pickle=False)
    else:
        np.lib.format.write_array_header_1_0(buf, header)
        buf.write(data)
    return buf.getvalue()


def _write_members(path, members: dict[str, bytes]) -> None:
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED) as z:
        for name, payload in members.items():
            z.writestr(name + ".npy", payload)


def _clip_members(tmp_path) -> dict[str, bytes]:
    small_clip().save(tmp_path / "good.npz")
    with zipfile.ZipFile(tmp_path / "good.npz") as z:
        return {n.removesuffix(".npy"): z.read(n) for n in z.namelist()}


def test_a_decompression_bomb_is_refused_before_it_is_read(tmp_path, monkeypatch):
    members = _clip_members(tmp_path)
    members["hand_vertices"] = _npy(np.zeros((50, 20_000, 3), np.float32))  # 12 MB of zeros
    path = tmp_path / "bomb.npz"
    _write_members(path, members)
    assert path.stat().st_size < 100_000
    monkeypatch.setattr(np, "load", lambda *a, **k: pytest.fail("np.load reached"))
    with pytest.raises(InputError, match="over the limit of 4000000 bytes") as err:
        load_clip(path, max_bytes=4_000_000)
    assert err.value.element == "hand_vertices"


def test_a_header_declaring_a_huge_array_is_refused(tmp_path, monkeypatch):
    members = _clip_members(tmp_path)
    members["hand_vertices"] = _npy(header={"descr": "<f4", "fortran_order": False,
                                            "shape": (1_000_000, 1_000_000, 3)}, data=b"\0" * 64)
    path = tmp_path / "huge.npz"
    _write_members(path, members)
    monkeypatch.setattr(np, "load", lambda *a, **k: pytest.fail("np.load reached"))
    with pytest.raises(InputError, match=r"declares an array of shape \(1000000, 1000000, 3\)") as err:
        load_clip(path)
    assert err.value.element == "hand_vertices"


@pytest.mark.parametrize("field,value,text", [
    ("fps", np.array([120.0, 60.0]), "single value"),
    ("fps", np.array("fast"), "must be a number"),
    ("version", np.array("one"), "must be an integer"),
    ("version", np.array([1, 1]), "single value"),
    ("hand_faces", np.array([["a", "b", "c"]]), "must be an integer"),
    ("marker_names", np.array("A"), "1-d array"),
    ("source_rig", np.array(5), "must be a string"),
    ("format", np.array(["handretarget.clip"]), "single value"),
])
def test_malformed_fields_are_input_errors(tmp_path, field, value, text):
    members = _clip_members(tmp_path)
    members[field] = _npy(value)
    path = tmp_path / "bad.npz"
    _write_members(path, members)
    with pytest.raises(InputError, match=text) as err:
        load_clip(path)
    assert err.value.element == field


def test_a_malformed_header_is_an_input_error(tmp_path):
    members = _clip_members(tmp_path)
    members["fps"] = b"\x93NUMPY\x01\x00\x10\x00{'descr': 'zz'}  \n"
    path = tmp_path / "bad.npz"
    _write_members(path, members)
    with pytest.raises(InputError, match="bad npy header") as err:
        load_clip(path)
    assert err.value.element == "fps"


def test_a_flipped_byte_is_an_input_error(tmp_path):
    path = tmp_path / "c.npz"
    small_clip(40).save(path)
    raw = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as z:
        info = z.getinfo("hand_vertices.npy")
    start = info.header_offset + 30 + len(info.filename) + len(info.extra)
    for k in range(start + 20, start + info.compress_size - 4, 37):  # several data bytes
        raw[k] ^= 0xFF
    path.write_bytes(bytes(raw))
    with pytest.raises(InputError) as err:
        load_clip(path)
    assert err.value.element in ("hand_vertices", "")


def test_the_default_limit_reads_ordinary_clips(tmp_path):
    from retarget_core.clip.format import MAX_CLIP_BYTES, check_npz_members

    assert MAX_CLIP_BYTES == 2 * 1024 ** 3
    small_clip().save(tmp_path / "c.npz")
    heads = check_npz_members(tmp_path / "c.npz")
    assert heads["hand_vertices"][0] == (4, 42, 3)
    assert load_clip(tmp_path / "c.npz", max_bytes=10**6).n_frames == 4


@pytest.mark.parametrize("fps", [1e-300, 0.5, 1e5, 1e300])
def test_fps_is_bounded(fps):
    clip = small_clip()
    clip.fps = fps
    with pytest.raises(InputError, match="frames per second") as err:
        clip.validate()
    assert err.value.element == "fps"


# ---- version 2: contact surface points -------------------------------------------------------------
def _with_surface_points(clip: Clip) -> Clip:
    """``clip`` with contact surface points: frame 1 two points, frame 2 one, others none."""
    clip.contact_offsets = np.array([0, 0, 2, 3] + [3] * (clip.n_frames - 3))
    clip.contact_faces = np.array([0, 5, 7])
    clip.contact_barycentric = np.array([[0.2, 0.3, 0.5], [1.0, 0.0, 0.0], [0.1, 0.1, 0.8]])
    clip.contact_codes = np.array([22, 22, 45], dtype=np.uint8)
    return clip


def test_version_2_keeps_the_surface_points_and_version_1_still_reads(tmp_path):
    clip = _with_surface_points(small_clip(6))
    clip.save(tmp_path / "c.npz")
    back = load_clip(tmp_path / "c.npz")
    for name in ("contact_offsets", "contact_faces", "contact_barycentric", "contact_codes"):
        np.testing.assert_array_equal(getattr(back, name), getattr(clip, name))
    with np.load(tmp_path / "c.npz") as data:
        assert int(data["version"]) == 2
    # a version-1 file (no surface points) as earlier builds wrote it
    small_clip().save(tmp_path / "v1.npz")
    _rewrite(tmp_path / "v1.npz", version=np.array(1))
    old = load_clip(tmp_path / "v1.npz")
    assert old.contact_offsets is None and old.contact_labels.any()


def test_slice_keeps_each_frames_surface_points():
    clip = _with_surface_points(small_clip(6))
    part = clip.slice(2, 5)  # frames 2, 3, 4: only frame 2's point
    part.validate()
    np.testing.assert_array_equal(part.contact_offsets, [0, 1, 1, 1])
    np.testing.assert_array_equal(part.contact_faces, [7])
    np.testing.assert_array_equal(part.contact_codes, [45])
    part = clip.slice(1, 2)
    np.testing.assert_array_equal(part.contact_offsets, [0, 2])
    np.testing.assert_array_equal(part.contact_faces, [0, 5])


@pytest.mark.parametrize("field, value, text", [
    ("contact_codes", None, "go together"),
    ("contact_offsets", np.array([0, 0, 2, 3]), "T \\+ 1"),
    ("contact_offsets", np.array([0, 2, 1, 3, 3, 3, 3]), "non-decreasing"),
    ("contact_faces", np.array([0, 5, 999]), "face index out of range"),
    ("contact_barycentric", np.array([[0.2, 0.3, 0.6], [1.0, 0, 0], [0.1, 0.1, 0.8]]), "sum to 1"),
    ("contact_codes", np.array([22, 22, 7], dtype=np.uint8), "code 7"),
    ("contact_faces", np.array([0, 5]), "N = contact_offsets"),
])
def test_bad_surface_points_are_named(field, value, text):
    clip = _with_surface_points(small_clip(6))
    setattr(clip, field, value)
    with pytest.raises(InputError, match=text):
        clip.validate()
