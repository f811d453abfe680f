"""GRAB importer: restricted unpickling, MANO loading and forward kinematics, sequence import."""

import copy
import os
import pickle
import zipfile

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from grab_fixtures import (
    PARENTS,
    joint_of_vertex,
    make_grab_sequence,
    make_mano_raw,
    write_grab_npz,
    write_grab_npz_flat,
    write_mano_official,
    write_mano_plain,
    write_mesh,
)
from retarget_core.clip import load_clip
from retarget_core.clip.grab import (
    finger_pose_from_pca,
    import_grab,
    load_grab_sequence,
    load_mano_model,
    mano_forward,
    rodrigues,
)
from retarget_core.clip.markers import MANO_MARKERS
from retarget_core.errors import InputError


# ---- fixtures ---------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def mano_raw():
    return make_mano_raw(0, rigid=False)


@pytest.fixture(scope="module")
def mano_path(tmp_path_factory, mano_raw):
    return write_mano_official(tmp_path_factory.mktemp("mano") / "MANO_RIGHT.pkl", mano_raw)


@pytest.fixture(scope="module")
def model(mano_path):
    return load_mano_model(mano_path)


@pytest.fixture(scope="module")
def rigid_model(tmp_path_factory):
    raw = make_mano_raw(3, rigid=True, zero_posedirs=True)
    return load_mano_model(write_mano_plain(tmp_path_factory.mktemp("mano_rigid") / "MANO_RIGHT.pkl", raw))


@pytest.fixture
def grab(tmp_path, mano_raw):
    """(grab_root, sequence dict, sequence path)"""
    seq = make_grab_sequence(tmp_path, mano_raw)
    path = write_grab_npz(tmp_path / "grab" / "s1" / "apple_eat_1.npz", seq)
    return tmp_path, seq, path


def _write_variant(tmp_path, seq, mutate, name="variant.npz"):
    seq = copy.deepcopy(seq)
    mutate(seq)
    return write_grab_npz(tmp_path / "grab" / "s1" / name, seq)


# ---- restricted loader ------------------------------------------------------------------------

def test_load_grab_sequence_nested(grab):
    _, seq, path = grab
    data = load_grab_sequence(path)
    assert data["framerate"] == 120.0
    assert data["obj_name"] == "apple"
    assert data["n_frames"] == 6
    np.testing.assert_array_equal(data["rhand"]["params"]["transl"], seq["rhand"]["params"]["transl"])
    np.testing.assert_array_equal(data["contact"]["object"], seq["contact"]["object"])
    assert data["object"]["object_mesh"] == seq["object"]["object_mesh"]


def test_load_grab_sequence_flattened_members(grab, tmp_path):
    _, seq, _ = grab
    path = write_grab_npz_flat(tmp_path / "flat.npz", seq)
    with zipfile.ZipFile(path) as zf:
        assert "rhand.params.global_orient.npy" in zf.namelist()
    data = load_grab_sequence(path)
    np.testing.assert_array_equal(data["rhand"]["params"]["global_orient"], seq["rhand"]["params"]["global_orient"])
    assert data["object"]["object_mesh"] == seq["object"]["object_mesh"]
    assert data["framerate"] == 120.0


class _Evil:
    def __init__(self, marker):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"echo pwned > {self.marker}",))


def test_malicious_member_is_refused_and_never_runs(grab, tmp_path):
    _, seq, _ = grab
    marker = tmp_path / "pwned.txt"
    seq = {k: v for k, v in seq.items() if k != "_truth"}
    seq["rhand"] = dict(seq["rhand"], evil=_Evil(marker))
    path = tmp_path / "evil.npz"
    np.savez(path, **seq)
    with pytest.raises(InputError) as info:
        load_grab_sequence(path)
    message = str(info.value)
    assert "refusing to unpickle" in message and ".system" in message
    assert "rhand" in message  # the member
    assert not marker.exists()


def test_os_system_named_exactly(tmp_path):
    # A hand-made protocol-0 pickle naming os.system directly, inside a 0-d object .npy member.
    header = {"descr": "|O", "fortran_order": False, "shape": ()}
    import io

    import numpy.lib.format as fmt

    buf = io.BytesIO()
    fmt.write_array_header_1_0(buf, header)
    buf.write(b"cos\nsystem\n(Vtouch " + str(tmp_path / "x").encode() + b"\ntR.")
    path = tmp_path / "evil2.npz"
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("framerate.npy", buf.getvalue())
    with pytest.raises(InputError, match=r"refusing to unpickle os\.system"):
        load_grab_sequence(path)
    assert not (tmp_path / "x").exists()


def test_corrupt_archive_and_truncated_pickle(grab, tmp_path):
    _, _, path = grab
    bad = tmp_path / "corrupt.npz"
    bad.write_bytes(b"this is not a zip")
    with pytest.raises(InputError, match="corrupt.npz"):
        load_grab_sequence(bad)
    with zipfile.ZipFile(path) as zf:
        payload = zf.read("rhand.npy")
    trunc = tmp_path / "trunc.npz"
    with zipfile.ZipFile(trunc, "w") as zf:
        zf.writestr("rhand.npy", payload[: len(payload) // 2])
    with pytest.raises(InputError, match=r"trunc\.npz: rhand"):
        load_grab_sequence(trunc)


# ---- MANO model -------------------------------------------------------------------------------

def test_official_and_plain_mano_pickles_load_identically(tmp_path, mano_raw, mano_path):
    with open(mano_path, "rb") as handle:
        text = handle.read()
    assert b"chumpy.ch\nCh" in text and b"scipy.sparse.csc\ncsc_matrix" in text and b"copy_reg\n_reconstructor" in text
    official = load_mano_model(mano_path)
    plain = load_mano_model(write_mano_plain(tmp_path / "MANO_RIGHT.pkl", mano_raw))
    for name in ("v_template", "shapedirs", "posedirs", "J_regressor", "weights", "parents", "faces",
                 "hands_components", "hands_mean"):
        np.testing.assert_array_equal(getattr(official, name), getattr(plain, name), err_msg=name)
    np.testing.assert_array_equal(official.parents, PARENTS)
    np.testing.assert_array_equal(official.J_regressor, mano_raw["J_regressor"])
    assert official.faces.dtype == np.int64


def test_mano_wrong_posedirs_shape(tmp_path, mano_raw):
    raw = dict(mano_raw, posedirs=np.zeros((778, 3, 10)))
    with pytest.raises(InputError, match=r"posedirs has shape \(778, 3, 10\), expected \(778, 3, 135\)"):
        load_mano_model(write_mano_official(tmp_path / "MANO_RIGHT.pkl", raw))


@pytest.mark.parametrize(
    "change, pattern",
    [
        (lambda r: r.update(v_template=np.zeros((700, 3))), "v_template"),
        (lambda r: r.update(weights=r["weights"] * 2), "weights"),
        (lambda r: r.pop("kintree_table"), "kintree_table"),
        (lambda r: r.update(J_regressor=np.zeros((21, 778))), "J_regressor"),
        (lambda r: r.update(is_rhand=False), "right hand"),
    ],
)
def test_mano_bad_models(tmp_path, mano_raw, change, pattern):
    raw = dict(mano_raw)
    change(raw)
    with pytest.raises(InputError, match=pattern):
        load_mano_model(write_mano_plain(tmp_path / "MANO_RIGHT.pkl", raw))


def test_mano_left_file_refused(tmp_path, mano_raw):
    with pytest.raises(InputError, match="right hand"):
        load_mano_model(write_mano_plain(tmp_path / "MANO_LEFT.pkl", mano_raw))


def test_mano_pickle_with_foreign_global_refused(tmp_path, mano_raw):
    marker = tmp_path / "pwned"
    path = tmp_path / "MANO_RIGHT.pkl"
    path.write_bytes(pickle.dumps(dict(mano_raw, evil=_Evil(marker)), protocol=2))
    with pytest.raises(InputError, match="refusing to unpickle"):
        load_mano_model(path)
    assert not marker.exists()


# ---- MANO forward -----------------------------------------------------------------------------

def _pose(rng, n):
    return rng.normal(scale=0.4, size=(n, 3)), rng.normal(scale=0.3, size=(n, 45)), rng.normal(scale=0.1, size=(n, 3))


def test_zero_pose_is_template_plus_transl(model):
    transl = np.array([[0.1, -0.2, 0.3], [0.0, 0.0, 0.0]])
    verts = mano_forward(model, np.zeros((2, 3)), np.zeros((2, 45)), transl)
    np.testing.assert_allclose(verts, model.v_template[None] + transl[:, None], atol=1e-12)


def test_shape_only(model, rng):
    betas = rng.normal(size=10)
    verts = mano_forward(model, np.zeros((1, 3)), np.zeros((1, 45)), np.zeros((1, 3)), betas=betas)
    np.testing.assert_allclose(verts[0], model.v_template + model.shapedirs @ betas, atol=1e-12)
    per_frame = mano_forward(model, np.zeros((2, 3)), np.zeros((2, 45)), np.zeros((2, 3)), betas=np.stack([betas, 0 * betas]))
    np.testing.assert_allclose(per_frame[0], verts[0], atol=1e-12)
    np.testing.assert_allclose(per_frame[1], model.v_template, atol=1e-12)


def test_subject_template_replaces_model_template(model, rng):
    vt = model.v_template + rng.normal(scale=0.01, size=model.v_template.shape)
    verts = mano_forward(model, np.zeros((1, 3)), np.zeros((1, 45)), np.zeros((1, 3)), v_template=vt)
    np.testing.assert_allclose(verts[0], vt, atol=1e-12)


def test_rodrigues_matches_scipy(rng):
    aa = rng.normal(size=(20, 3))
    aa[0] = 0
    np.testing.assert_allclose(rodrigues(aa), Rotation.from_rotvec(aa).as_matrix(), atol=1e-12)


def test_global_rotation_about_root_joint(model):
    aa = np.array([[0.3, -0.7, 1.1]])
    transl = np.array([[0.05, 0.0, -0.1]])
    verts = mano_forward(model, aa, np.zeros((1, 45)), transl)
    rot = Rotation.from_rotvec(aa[0]).as_matrix()
    j0 = model.J_regressor[0] @ model.v_template
    expected = (model.v_template - j0) @ rot.T + j0 + transl
    np.testing.assert_allclose(verts[0], expected, atol=1e-12)


@pytest.mark.parametrize("joint", [2, 4, 14])
def test_bending_one_joint_moves_only_its_finger(rigid_model, joint):
    model = rigid_model
    owner = joint_of_vertex()
    finger = np.zeros((1, 45))
    axis_angle = np.array([0.0, 0.0, 0.9])
    finger[0, 3 * (joint - 1): 3 * joint] = axis_angle
    verts = mano_forward(model, np.zeros((1, 3)), finger, np.zeros((1, 3)))[0]
    downstream = {joint}
    for j in range(joint + 1, 16):
        if PARENTS[j] in downstream:
            downstream.add(j)
    moved = np.isin(owner, sorted(downstream))
    joints = model.J_regressor @ model.v_template
    rot = Rotation.from_rotvec(axis_angle).as_matrix()
    expected = model.v_template.copy()
    expected[moved] = (model.v_template[moved] - joints[joint]) @ rot.T + joints[joint]
    np.testing.assert_allclose(verts, expected, atol=1e-12)
    assert np.abs(verts[moved] - model.v_template[moved]).max() > 1e-3


def test_pca_hand_pose_equals_fullpose(model, rng):
    hand_pose = rng.normal(size=(4, 24))
    full = hand_pose @ model.hands_components[:24]
    np.testing.assert_allclose(finger_pose_from_pca(model, hand_pose), full, atol=1e-12)
    np.testing.assert_allclose(finger_pose_from_pca(model, hand_pose, flat_hand_mean=False), full + model.hands_mean, atol=1e-12)
    go, _, tr = _pose(rng, 4)
    np.testing.assert_allclose(mano_forward(model, go, finger_pose_from_pca(model, hand_pose), tr),
                               mano_forward(model, go, full, tr), atol=1e-12)


def test_forward_chunking_is_consistent(model, rng):
    go, fp, tr = _pose(rng, 7)
    np.testing.assert_allclose(mano_forward(model, go, fp, tr, chunk=3), mano_forward(model, go, fp, tr), atol=1e-12)


# ---- import -----------------------------------------------------------------------------------

def test_import_grab_end_to_end(grab, model, mano_path, tmp_path):
    root, seq, path = grab
    clip = import_grab(path, mano_path, grab_root=root)
    clip.validate()
    n = seq["n_frames"]
    assert clip.n_frames == n and clip.fps == 120.0
    assert clip.object_name == "apple" and clip.motion == "eat"
    assert clip.source == "grab:s1/apple_eat_1"
    np.testing.assert_array_equal(clip.hand_faces, model.faces)

    rh = seq["rhand"]["params"]
    expected = mano_forward(model, rh["global_orient"], rh["fullpose"], rh["transl"], v_template=seq["_truth"]["vtemp"])
    np.testing.assert_allclose(clip.hand_vertices, expected, atol=1e-5)

    # GRAB object convention: world = v @ R + transl
    ob = seq["object"]["params"]
    v = seq["_truth"]["object_vertices"]
    for f in range(n):
        rot = Rotation.from_rotvec(ob["global_orient"][f]).as_matrix()
        np.testing.assert_allclose(clip.object_world_vertices(f), v @ rot + ob["transl"][f], atol=1e-9)

    # Table: box from the table mesh bounds, posed like GRAB's table.
    tb = seq["table"]["params"]
    rot = Rotation.from_rotvec(tb["global_orient"][0]).as_matrix()
    tv = seq["_truth"]["table_vertices"]
    world = tv @ rot + tb["transl"][0]
    local = (world - clip.table_pose[:3, 3]) @ clip.table_pose[:3, :3]
    np.testing.assert_allclose(np.abs(local).max(axis=0), clip.table_half_extents, atol=1e-9)
    np.testing.assert_allclose(clip.table_half_extents, [0.5, 0.3, 0.02], atol=1e-9)

    # Contacts: right-hand codes only.
    raw = seq["contact"]["object"]
    keep = np.isin(raw, [22, *range(41, 56)])
    np.testing.assert_array_equal(clip.contact_labels, np.where(keep, raw, 0))
    assert clip.contact_labels.dtype == np.uint8

    markers = clip.markers()
    assert set(markers) == set(MANO_MARKERS)
    face, bary = markers["IndexTip"]
    assert clip.hand_faces[face][np.argmax(bary)] == MANO_MARKERS["IndexTip"]

    out = tmp_path / "clip.npz"
    clip.save(out)
    back = load_clip(out)
    assert back.marker_names == clip.marker_names and back.source == clip.source
    np.testing.assert_allclose(back.hand_vertices, clip.hand_vertices)
    np.testing.assert_array_equal(back.contact_labels, clip.contact_labels)


def test_import_with_explicit_paths_and_flat_archive(grab, mano_path, tmp_path):
    root, seq, _ = grab
    flat = write_grab_npz_flat(tmp_path / "flat_seq.npz", seq)
    clip = import_grab(flat, mano_path,
                       object_mesh=root / seq["object"]["object_mesh"],
                       table_mesh=root / seq["table"]["table_mesh"],
                       vtemp=root / seq["rhand"]["vtemp"])
    assert clip.has_table and "MANO mean template" not in clip.source


def test_import_without_vtemp_or_table_uses_model_template(grab, model, mano_path):
    root, seq, path = grab
    clip = import_grab(path, mano_path, object_mesh=root / seq["object"]["object_mesh"])
    assert "MANO mean template" in clip.source
    assert not clip.has_table
    rh = seq["rhand"]["params"]
    expected = mano_forward(model, rh["global_orient"], rh["fullpose"], rh["transl"])
    np.testing.assert_allclose(clip.hand_vertices, expected, atol=1e-5)


def test_import_fullpose_when_no_pca(grab, model, mano_path, tmp_path):
    root, seq, _ = grab
    path = _write_variant(tmp_path, seq, lambda s: s["rhand"]["params"].pop("hand_pose"))
    clip = import_grab(path, mano_path, grab_root=root)
    rh = seq["rhand"]["params"]
    expected = mano_forward(model, rh["global_orient"], rh["fullpose"], rh["transl"], v_template=seq["_truth"]["vtemp"])
    np.testing.assert_allclose(clip.hand_vertices, expected, atol=1e-5)


def test_missing_object_mesh_tells_user(grab, mano_path, tmp_path):
    _, _, path = grab
    with pytest.raises(InputError, match="--object-mesh"):
        import_grab(path, mano_path, grab_root=tmp_path / "nowhere")


def test_missing_key_named(grab, mano_path, tmp_path):
    root, seq, _ = grab
    path = _write_variant(tmp_path, seq, lambda s: s["rhand"]["params"].pop("transl"))
    with pytest.raises(InputError, match=r"rhand\.params\.transl"):
        import_grab(path, mano_path, grab_root=root)


def test_missing_framerate_named(grab, mano_path, tmp_path):
    root, seq, _ = grab
    path = _write_variant(tmp_path, seq, lambda s: s.pop("framerate"))
    with pytest.raises(InputError, match="framerate"):
        import_grab(path, mano_path, grab_root=root)


def test_left_hand_only_sequence(grab, mano_path, tmp_path):
    root, seq, _ = grab
    path = _write_variant(tmp_path, seq, lambda s: s.pop("rhand"))
    with pytest.raises(InputError, match="no right-hand data"):
        import_grab(path, mano_path, grab_root=root)


def test_frame_count_mismatch(grab, mano_path, tmp_path):
    root, seq, _ = grab

    def cut(s):
        s["object"]["params"]["transl"] = s["object"]["params"]["transl"][:-2]

    path = _write_variant(tmp_path, seq, cut)
    with pytest.raises(InputError, match=r"object\.params\.transl: has 4 frames but n_frames says 6"):
        import_grab(path, mano_path, grab_root=root)


def test_nan_names_frame(grab, mano_path, tmp_path):
    root, seq, _ = grab

    def poison(s):
        s["rhand"]["params"]["transl"] = s["rhand"]["params"]["transl"].copy()
        s["rhand"]["params"]["transl"][3, 1] = np.nan

    path = _write_variant(tmp_path, seq, poison)
    with pytest.raises(InputError, match=r"rhand\.params\.transl: frame 3"):
        import_grab(path, mano_path, grab_root=root)


def test_object_vertex_count_mismatch(grab, mano_path, tmp_path):
    root, seq, path = grab
    other = write_mesh(tmp_path / "small.ply", np.eye(4, 3) + [0, 0, 0.1], [[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]])
    with pytest.raises(InputError, match=r"contact\.object: has 162 vertices .* has 4"):
        import_grab(path, mano_path, grab_root=root, object_mesh=other)


def test_vtemp_with_wrong_vertex_count(grab, mano_path, tmp_path):
    root, seq, path = grab
    other = write_mesh(tmp_path / "hand.ply", np.eye(4, 3), [[0, 1, 2], [0, 2, 3]])
    with pytest.raises(InputError, match="778"):
        import_grab(path, mano_path, grab_root=root, vtemp=other)


def test_python2_style_array_pickle_in_mano_model(tmp_path):
    # numpy.core names, py2 str ('S') opcodes for the raw data, as in pickles written by Python 2.
    array = (b"cnumpy.core.multiarray\n_reconstruct\np0\n(cnumpy\nndarray\np1\n(I0\ntp2\nS'b'\np3\ntp4\nRp5\n"
             b"(I1\n(I2\ntp6\ncnumpy\ndtype\np7\n(S'f8'\np8\nI0\nI1\ntp9\nRp10\n(I3\nS'<'\np11\nNNNI-1\nI-1\nI0\n"
             b"tp12\nbI00\nS'\\x00\\x00\\x00\\x00\\x00\\x00\\xf8?\\x00\\x00\\x00\\x00\\x00\\x00\\x00@'\np13\ntp14\nb")
    path = tmp_path / "MANO_RIGHT.pkl"
    path.write_bytes(b"(dp0\nS'hands_mean'\np100\n" + array + b"s.")
    # The array decodes; the model is then refused for its missing keys (naming one).
    with pytest.raises(InputError, match="v_template: MANO model: required key is missing"):
        load_mano_model(path)
    from retarget_core.clip.grab import _mano_globals, _restricted_loads

    value = _restricted_loads(path.read_bytes(), _mano_globals(), source="s", element="e", encoding="latin1")
    np.testing.assert_array_equal(value["hands_mean"], [1.5, 2.0])


def test_npy_header_with_huge_shape_is_an_input_error(tmp_path):
    import io

    import numpy.lib.format as fmt

    buf = io.BytesIO()
    fmt.write_array_header_1_0(buf, {"descr": "<f8", "fortran_order": False, "shape": (2**40, 2**30)})
    buf.write(b"\0" * 64)
    path = tmp_path / "huge.npz"
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("framerate.npy", buf.getvalue())
    with pytest.raises(InputError, match="framerate: truncated"):
        load_grab_sequence(path)
