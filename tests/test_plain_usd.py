"""Plain UsdSkel hands, as another tool's exporter writes them (tests/plain_usd.py, pxr alone):
no handretarget DOF spec, centimetres and Y-up, a transform on the SkelRoot (and one on the
Mesh, which UsdSkel ignores), a geomBindTransform, float32 matrices, the hand placed anywhere.
Each reads as the same world hand with DOFs inferred by role, and goes through rig info,
annotate propose and retarget with no edit, to within 0.1 mm of the core's own hand with the
same inferred DOFs."""

import contextlib
import io
import json
import os

import numpy as np
import pytest

from foreign_hands import foreign_demo, strip_dofs
from plain_usd import Z_UP_TO_Y_UP, skinned_world_points, write_plain_usdskel
from retarget_core.cli import main
from retarget_core.clip.demo import make_demo_clip, source_rig
from retarget_core.errors import InputError
from retarget_core.rig.dof_limits import apply_limits, limits_toml
from retarget_core.rig.dof_roles import infer_dofs
from retarget_core.rig.io import load_rig
from retarget_core.rig.usd_io import check_usd_compliance, read_rig_usd

RES = 0.004
SOURCE = f"demo:source_human@{RES}"


def _rz(deg, translation=(0.0, 0.0, 0.0)):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    m[:3, 3] = translation
    return m


def _rx(deg):
    c, s = np.cos(np.radians(deg)), np.sin(np.radians(deg))
    m = np.eye(4)
    m[1:3, 1:3] = [[c, -s], [s, c]]
    return m


#: name -> writer options (everything composes back to the same world hand)
VARIANTS = {
    "plain": {},
    "cm-yup-placed": dict(meters_per_unit=0.01, up_axis="Y", skel_root_transform=_rz(35, (12.0, -40.0, 7.0)) @ _rx(20),
                          mesh_transform=_rz(10, (3.0, 0.0, 0.0)), geom_bind=_rz(-20, (0.5, 0.2, 0.0)), float32=True),
    "scaled-root": dict(skel_root_transform=_rz(-60, (0.3, 0.1, -0.2)), skel_root_scale=2.5),
}


@pytest.fixture(scope="module")
def hand():
    rig, truth = foreign_demo("human_alt", RES)
    return rig


def _arrays(rig, world=None):
    bind = rig.kinematics().bind_world
    vertices = rig.surface.vertices
    if world is not None:
        bind = np.einsum("ab,jbc->jac", world, bind)
        vertices = vertices @ world[:3, :3].T + world[:3, 3]
    return dict(joint_names=rig.joint_names, parents=[j.parent for j in rig.joints], bind_world=bind,
                vertices=vertices, faces=rig.surface.faces, joint_indices=rig.surface.joint_indices,
                joint_weights=rig.surface.joint_weights)


#: the body-like skeleton above the hand's own root joint (the forearm): name, parent, world position
BODY = [("spine", -1, (0.0, -0.45, 0.0)), ("chest", 0, (0.0, -0.30, 0.0)), ("neck", 1, (0.0, -0.30, 0.10)),
        ("head", 2, (0.0, -0.30, 0.20)), ("upperarm", 1, (0.0, -0.15, 0.0))]
#: forearm skin proximal of this (m, along the hand's forearm axis -Y) is carried by the upper arm
ARM_CUT_Y = -0.035


def _body_arrays(rig, hands=1):
    """The hand (twice, the second 0.3 m to the side, with a suffix, for ``hands=2``) under a
    spine / chest / neck / head / upper-arm skeleton, its mesh the hand's surface whose proximal
    forearm the upper arm carries, plus a closed torso box the chest carries."""
    names = [b[0] for b in BODY]
    parents = [b[1] for b in BODY]
    bind = []
    for _, _, position in BODY:
        m = np.eye(4)
        m[:3, 3] = position
        bind.append(m)
    hand_bind = rig.kinematics().bind_world
    vertices, faces, indices, weights = [], [], [], []
    for h in range(hands):
        offset = np.array([0.3 * h, 0.0, 0.0])
        base = len(names)
        suffix = "" if h == 0 else f"_{h}"
        names += [n + suffix for n in rig.joint_names]
        parents += [4 if j.parent < 0 else base + j.parent for j in rig.joints]
        shifted = hand_bind.copy()
        shifted[:, :3, 3] += offset
        bind += list(shifted)
        v = rig.surface.vertices
        ji = rig.surface.joint_indices + base
        jw = rig.surface.joint_weights.copy()
        arm = v[:, 1] < ARM_CUT_Y
        ji[arm], jw[arm] = 4, 0.0
        jw[arm, 0] = 1.0
        faces.append(rig.surface.faces + sum(len(x) for x in vertices))
        vertices.append(v + offset)
        indices.append(ji)
        weights.append(jw)
    corners = np.array([[x, y, z] for x in (-0.12, 0.12) for y in (-0.5, -0.25) for z in (-0.08, 0.08)])
    box = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],
                    [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    faces.append(box + sum(len(x) for x in vertices))
    vertices.append(corners)
    k = rig.surface.joint_indices.shape[1]
    indices.append(np.full((8, k), 1))
    weights.append(np.column_stack([np.ones(8), np.zeros((8, k - 1))]))
    return dict(joint_names=names, parents=parents, bind_world=np.array(bind), vertices=np.concatenate(vertices),
                faces=np.concatenate(faces), joint_indices=np.concatenate(indices),
                joint_weights=np.concatenate(weights))


@pytest.fixture(scope="module")
def files(hand, tmp_path_factory):
    folder = tmp_path_factory.mktemp("plain_usd")
    out = {name: write_plain_usdskel(folder / f"{name}.usda", **_arrays(hand), **options)
           for name, options in VARIANTS.items()}
    out["body"] = write_plain_usdskel(folder / "body.usda", **_body_arrays(hand), meters_per_unit=0.01, up_axis="Y",
                                      root_name="Character")
    return out


def test_a_hand_inside_a_body_skeleton_is_found_and_cut_out(files, core, hand, tmp_path):
    rig = read_rig_usd(files["body"])
    # the spine, chest, neck, head and upper arm are gone; the forearm (the hand's own root) stays
    assert rig.joint_names == core.joint_names and rig.dof_names == core.dof_names
    assert rig.metadata["hand_root"] == hand.joint_names[0]
    # the surface: the hand's, minus the forearm skin the upper arm carried, its opening capped
    report = rig.surface.topology()
    assert report.closed and report.manifold and report.components == 1
    kept = rig.surface.vertices[:-1]  # the last vertex is the cap's centre
    assert kept[:, 1].min() >= ARM_CUT_Y - 0.01 and len(kept) < hand.surface.n_vertices
    assert rig.surface.vertices[-1][1] == pytest.approx(ARM_CUT_Y, abs=0.01)
    # where each kept vertex and triangle is in the file's mesh (what the Blender add-in maps
    # annotation points through): the same points, read by pxr alone; the cap is marked -1
    from pxr import Usd, UsdGeom

    source = rig.metadata["surface_source"]
    stage = Usd.Stage.Open(str(files["body"]))
    mesh = next(UsdGeom.Mesh(p) for p in stage.Traverse() if p.IsA(UsdGeom.Mesh))
    counts, corners = list(mesh.GetFaceVertexCountsAttr().Get()), list(mesh.GetFaceVertexIndicesAttr().Get())
    file_tris, at = [], 0
    for n in counts:  # the reader's fan triangulation
        file_tris += [(corners[at], corners[at + k], corners[at + k + 1]) for k in range(1, n - 1)]
        at += n
    world = skinned_world_points(files["body"]) * 0.01 @ Z_UP_TO_Y_UP[:3, :3]
    v_src, f_src = np.array(source["vertices"]), np.array(source["faces"])
    assert (source["file_vertices"], source["file_faces"]) == (len(world), len(file_tris))
    assert v_src[-1] == -1 and (v_src[:-1] >= 0).all()
    assert np.abs(rig.surface.vertices[:-1] - world[v_src[:-1]]).max() < 1e-6
    kept_faces = f_src >= 0
    assert (~kept_faces).sum() > 0 and all(np.asarray(rig.surface.faces)[~kept_faces].max(axis=1) == len(v_src) - 1)
    for i in np.nonzero(kept_faces)[0][::50]:
        assert list(v_src[rig.surface.faces[i]]) == list(file_tris[f_src[i]])  # corner order kept
    # the cap is no skin of the user's mesh: a contact carried onto it is dropped, others stay
    from retarget_core.transfer.atlas import TransferredContacts
    from retarget_core.transfer.clip_transfer import off_caps

    caps = np.nonzero(~kept_faces)[0]
    n = 4
    carried = TransferredContacts(face=np.array([0, caps[0], 7, caps[-1]]), barycentric=np.full((n, 3), 1 / 3),
                                  landmark=np.zeros(n, int), curve=np.zeros(n, int),
                                  dropped=np.array([False, False, True, False]), radius=np.zeros(n), angle=np.zeros(n))
    assert off_caps(carried, rig).dropped.tolist() == [False, True, True, True]
    assert off_caps(carried, core) is carried  # a hand that was never cut has no cap
    # two hands: said, and settled by naming one
    two = write_plain_usdskel(tmp_path / "two_hands.usda", **_body_arrays(hand, hands=2))
    with pytest.raises(InputError, match=r"2 hands.*--hand-root"):
        read_rig_usd(two)
    second = read_rig_usd(two, hand_root=hand.joint_names[0] + "_1")
    assert second.n_dofs == core.n_dofs
    assert second.surface.vertices[:, 0].mean() == pytest.approx(rig.surface.vertices[:, 0].mean() + 0.3, abs=1e-3)


@pytest.fixture(scope="module")
def core(hand):
    """The same hand, stripped of its DOF spec in memory, with DOFs by role from the core."""
    from foreign_hands import truth_of

    stripped, _ = strip_dofs(hand, truth_of(hand))
    return infer_dofs(stripped)


def test_the_written_files_are_plain_compliant_usdskel(files):
    for name, path in files.items():
        assert check_usd_compliance(path) == [], name
        assert "handretarget" not in path.read_text(), name


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_a_plain_file_reads_as_the_same_world_hand_with_dofs_by_role(files, core, variant):
    rig = read_rig_usd(files[variant])
    assert rig.n_dofs == core.n_dofs and rig.dof_names == core.dof_names
    assert rig.joint_names == core.joint_names
    assert "inferred by role" in rig.metadata["dof_source"]
    # float32 files round the centimetre positions to ~1e-7 of their size
    assert np.abs(rig.surface.vertices - core.surface.vertices).max() <= 1e-5
    assert np.abs(rig.kinematics().bind_world - core.kinematics().bind_world).max() <= 1e-5
    for a, b in zip(rig.dofs, core.dofs):
        assert np.allclose(a.axis, b.axis, atol=1e-4), a.name
        assert np.isclose(a.lower, b.lower, atol=1e-3) and np.isclose(a.upper, b.upper, atol=1e-3), a.name


@pytest.mark.parametrize("variant", sorted(VARIANTS))
def test_usd_skinning_of_the_file_agrees_with_the_core(files, hand, variant):
    """pxr's own skinning query (no project code) at the bind pose, converted by the file's
    metersPerUnit and upAxis, against the core's surface."""
    options = VARIANTS[variant]
    stage_points = skinned_world_points(files[variant])
    mpu = options.get("meters_per_unit", 1.0)
    axis = Z_UP_TO_Y_UP[:3, :3] if options.get("up_axis") == "Y" else np.eye(3)
    world = (stage_points * mpu) @ axis  # stage -> Z-up world (axis is a rotation: inverse = transpose)
    assert np.abs(world - read_rig_usd(files[variant]).surface.vertices).max() <= 1e-5


def test_a_hand_placed_anywhere_gets_the_free_root_around_its_own_root(hand, core, tmp_path):
    placed = _rz(75, (0.5, -0.3, 0.9)) @ _rx(-30)
    path = write_plain_usdskel(tmp_path / "anywhere.usda", **_arrays(hand, world=placed))
    rig = read_rig_usd(path)
    # the skeleton's own root sits 1.1 m away, turned: a new root joint carries the free root
    assert rig.joint_names == ["root_1"] + core.joint_names
    assert rig.metadata["free_root_added"] == "root_1"
    assert rig.n_dofs == core.n_dofs and rig.dof_names[:6] == core.dof_names[:6]
    assert np.allclose(rig.surface.vertices, core.surface.vertices @ placed[:3, :3].T + placed[:3, 3], atol=1e-6)
    # at the rest pose the rig is where the file put it; the free root moves all of it rigidly
    kin = rig.kinematics()
    assert np.allclose(kin.skin(rig.rest_pose), rig.surface.vertices, atol=1e-9)
    q = rig.rest_pose.copy()
    q[:3] = (0.1, 0.0, -0.2)
    assert np.allclose(kin.skin(q), rig.surface.vertices + (0.1, 0.0, -0.2), atol=1e-9)


def test_float32_noise_in_joint_matrices_is_accepted_and_cleaned(hand, tmp_path):
    """What Blender writes: a homogeneous entry of 0.99999994 and rotations off orthonormal by
    a few 1e-7."""
    from pxr import Gf, Usd, UsdSkel

    path = write_plain_usdskel(tmp_path / "noisy.usda", **_arrays(hand))
    stage = Usd.Stage.Open(str(path))
    skel = UsdSkel.Skeleton(stage.GetPrimAtPath("/Hand/Skeleton"))
    rest = list(skel.GetRestTransformsAttr().Get())
    m = Gf.Matrix4d(rest[5])
    m[3][3] = 0.99999994
    m[0][0] = m[0][0] * (1 + 3e-7)
    rest[5] = m
    skel.GetRestTransformsAttr().Set(rest)
    stage.GetRootLayer().Save()
    rig = read_rig_usd(path)
    local = rig.joints[5].rest_local
    assert np.array_equal(local[3], [0.0, 0.0, 0.0, 1.0])
    assert np.abs(local[:3, :3].T @ local[:3, :3] - np.eye(3)).max() < 1e-12


def test_a_skeleton_without_rest_transforms_rests_at_its_bind_pose(hand, core, tmp_path):
    from pxr import Usd

    path = write_plain_usdskel(tmp_path / "bind_only.usda", **_arrays(hand), meters_per_unit=0.01, up_axis="Y")
    stage = Usd.Stage.Open(str(path))
    stage.GetPrimAtPath("/Hand/Skeleton").RemoveProperty("restTransforms")
    stage.GetRootLayer().Save()
    assert "restTransforms" not in path.read_text()
    rig = read_rig_usd(path)
    assert np.abs(rig.kinematics().bind_world - core.kinematics().bind_world).max() <= 1e-6


def test_a_layer_over_a_hand_placed_anywhere_moves_its_own_root_joint(hand, tmp_path):
    """The free root the reader added is not in the user's skeleton: its motion lands on the
    skeleton's own root joint, and USD's skinning of the composed stage follows the core."""
    from retarget_core.export import write_animation_usd
    from retarget_core.fit.splines import fit_trajectory

    placed = _rz(75, (0.5, -0.3, 0.9)) @ _rx(-30)
    path = write_plain_usdskel(tmp_path / "anywhere.usda", **_arrays(hand, world=placed), meters_per_unit=0.01,
                               up_axis="Y", skel_root_transform=_rz(-30, (4.0, 5.0, 6.0)))
    rig = read_rig_usd(path)
    assert rig.metadata["free_root_added"] == "root_1"
    rng = np.random.default_rng(4)
    times = np.arange(12) / 24.0
    q = rig.rest_pose + np.clip(rng.normal(scale=0.2, size=(12, rig.n_dofs)), -0.3, 0.3)
    q = np.clip(q, rig.lower, rig.upper)
    curves = fit_trajectory(times, q, 6, optimize_knots=False)
    layer = tmp_path / "animation.usda"
    write_animation_usd(layer, rig=rig, rig_file=str(path), dof_curves=curves, fps=24.0, n_frames=12)
    for frame in (0, 5, 11):
        q_f = np.array([float(c(frame / 24.0)) for c in curves])
        usd_points = skinned_world_points(layer, time=frame) * 0.01 @ Z_UP_TO_Y_UP[:3, :3]
        assert np.abs(usd_points - rig.kinematics().skin(q_f)).max() <= 1e-5, frame


def test_a_separate_shell_in_the_mesh_is_left_out_with_a_warning(hand, core, tmp_path, capsys):
    """A nail modelled as its own closed shell: the hand is the largest piece, said by rig info."""
    arrays = _arrays(hand)
    tip = hand.surface.vertices[np.argmax(hand.surface.vertices[:, 1])]
    nail = tip + np.array([[x, y, z] for x in (-0.003, 0.003) for y in (-0.004, 0.0) for z in (0.0, 0.002)])
    box = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1], [2, 3, 7], [2, 7, 6],
                    [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]])
    n = len(arrays["vertices"])
    k = arrays["joint_indices"].shape[1]
    arrays["vertices"] = np.vstack([arrays["vertices"], nail])
    arrays["faces"] = np.vstack([arrays["faces"], box + n])
    arrays["joint_indices"] = np.vstack([arrays["joint_indices"], np.repeat(arrays["joint_indices"][[0]], 8, axis=0)])
    arrays["joint_weights"] = np.vstack([arrays["joint_weights"], np.column_stack([np.ones(8), np.zeros((8, k - 1))])])
    path = write_plain_usdskel(tmp_path / "nail.usda", **arrays)
    rig = read_rig_usd(path)
    assert rig.surface.n_vertices == core.surface.n_vertices
    assert np.abs(rig.surface.vertices - core.surface.vertices).max() <= 1e-6
    assert "left out 8 vertices and 12 faces" in rig.metadata["warnings"][0]
    assert main(["rig", "info", str(path)]) == 0
    assert "warning: the surface mesh has more than one piece" in capsys.readouterr().out


def test_rig_demo_plain_writes_a_plain_file_that_reads_with_dofs_by_role(tmp_path, capsys):
    assert main(["rig", "demo", "--plain", "--hand", "human_alt", "--resolution", "0.01", "--out", str(tmp_path)]) == 0
    path = tmp_path / "human_alt.usda"
    assert "handretarget" not in path.read_text()
    assert check_usd_compliance(path) == []
    rig = read_rig_usd(path)
    assert "inferred by role" in rig.metadata["dof_source"] and rig.dof_names[:6] == ["root_tx", "root_ty", "root_tz",
                                                                                        "root_rx", "root_ry", "root_rz"]


def test_bad_plain_files_are_refused_naming_prim_joint_and_number(hand, tmp_path):
    from pxr import Gf, Usd, UsdSkel

    path = write_plain_usdskel(tmp_path / "sheared.usda", **_arrays(hand))
    stage = Usd.Stage.Open(str(path))
    skel = UsdSkel.Skeleton(stage.GetPrimAtPath("/Hand/Skeleton"))
    rest = list(skel.GetRestTransformsAttr().Get())
    m = Gf.Matrix4d(rest[3])
    m.SetRow(0, m.GetRow(0) * 1.01)  # a 1 % scale in one joint's matrix
    rest[3] = m
    skel.GetRestTransformsAttr().Set(rest)
    stage.GetRootLayer().Save()
    with pytest.raises(InputError, match=r"thumb2.*not rigid.*off orthonormal by 0\.0201"):
        read_rig_usd(path)

    path = write_plain_usdskel(tmp_path / "squashed.usda", **_arrays(hand))
    stage = Usd.Stage.Open(str(path))
    from pxr import UsdGeom

    UsdGeom.Xformable(stage.GetPrimAtPath("/Hand")).AddScaleOp().Set(Gf.Vec3f(1.0, 1.0, 0.5))
    stage.GetRootLayer().Save()
    with pytest.raises(InputError, match=r"/Hand/Skeleton.*uniform scale"):
        read_rig_usd(path)


def test_limits_toml_round_trip_and_its_errors(core, tmp_path):
    text = limits_toml(core)
    assert "[index1]" in text and "root_tx" not in text
    edited = tmp_path / "limits.toml"
    edited.write_text("[index1]\nindex1_flex = [-10.0, 60.0]\n")
    rig = apply_limits(core, edited)
    d = rig.dofs[rig.dof_index("index1_flex")]
    assert np.degrees([d.lower, d.upper]) == pytest.approx([-10.0, 60.0])
    assert core.dofs[core.dof_index("index1_flex")].upper != d.upper  # the original is untouched
    for body, message in (("[index1]\nindex9_flex = [0, 1]\n", "no DOF 'index9_flex'"),
                          ("[nope]\n", "no joint 'nope'"),
                          ("[index1]\nindex1_flex = [60, 10]\n", "not below"),
                          ("[index1]\nindex1_flex = [10, 60]\n", "leaves out the DOF's rest value"),
                          ("[index1\n", "not a valid TOML")):
        edited.write_text(body)
        with pytest.raises(InputError, match=message):
            apply_limits(core, edited)


def test_limits_edited_in_the_file_itself_apply_to_the_inferred_dofs(files, core, tmp_path):
    """The add-in writes a user's edited limits into the plain file (``handretarget:dofLimits``,
    the TOML of ``rig import --limits``); only the DOFs it names change, and a bad entry is an
    error naming the prim and the entry."""
    import shutil

    from pxr import Sdf, Usd, UsdSkel

    def with_limits(text):
        path = tmp_path / "limited.usda"
        shutil.copy(files["plain"], path)
        stage = Usd.Stage.Open(str(path))
        skel = next(p for p in stage.Traverse() if p.IsA(UsdSkel.Skeleton))
        skel.CreateAttribute("handretarget:dofLimits", Sdf.ValueTypeNames.String, custom=True).Set(text)
        stage.GetRootLayer().Save()
        return path

    rig = read_rig_usd(with_limits("[index1]\nindex1_flex = [-10.0, 60.0]\n"))
    d = rig.dofs[rig.dof_index("index1_flex")]
    assert np.degrees([d.lower, d.upper]) == pytest.approx([-10.0, 60.0])
    assert rig.dof_names == core.dof_names
    def others(r):
        return np.array([(x.lower, x.upper) for x in r.dofs if x.name != "index1_flex" and not x.name.startswith("root")])

    np.testing.assert_allclose(others(rig), others(core), atol=1e-6)  # limits measured on the file's points
    assert "dofLimits" in rig.metadata["limits_from"]
    with pytest.raises(InputError, match=r"dofLimits.*no DOF 'index1_twist'"):
        read_rig_usd(with_limits("[index1]\nindex1_twist = [-10.0, 60.0]\n"))


# ---- the whole way: info, propose, retarget with no edit ----------------------------------------
@pytest.fixture(scope="module")
def clip_file(tmp_path_factory):
    clip = make_demo_clip("bottle_pick_place", time_scale=0.05, resolution=RES, rig=source_rig(RES))  # 46 frames
    path = tmp_path_factory.mktemp("plain_clip") / "clip.npz"
    clip.save(path)
    return path


def _through_the_commands(path, clip_file, out, *, plain=True):
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        assert main(["rig", "info", str(path)]) == 0
        assert ("inferred by role" in printed.getvalue()) == plain
        annotations = out / "annotations.json"
        assert main(["annotate", "propose", "--source", SOURCE, "--target", str(path), "--out", str(annotations)]) == 0
        assert main(["retarget", "--clip", str(clip_file), "--rig", str(path), "--annotations", str(annotations),
                     "--source-rig", SOURCE, "--out", str(out / "result"), "--workers", "1"]) == 0
    return json.loads((out / "result" / "result.json").read_text())


@pytest.fixture(scope="module")
def retargeted(files, core, clip_file, tmp_path_factory):
    """name -> (result.json, output folder) for the plain file, the cm / Y-up / placed one and
    the core's own hand, each through info, propose and retarget on the command line."""
    from retarget_core.rig.io import save_rig

    folder = tmp_path_factory.mktemp("plain_runs")
    core_file = folder / "core.usda"
    save_rig(core, core_file)
    out = {}
    for name, path, plain in (("plain", files["plain"], True), ("cm-yup-placed", files["cm-yup-placed"], True),
                              ("body", files["body"], True), ("core", core_file, False)):
        (folder / name).mkdir()
        out[name] = (_through_the_commands(path, clip_file, folder / name, plain=plain),
                     folder / name / "result")
    return out


def test_plain_files_retarget_like_the_core_hand(retargeted):
    # the solved frames (see tests/test_foreign_retarget.py: this clip's delivered curve is not the point)
    medians = {k: r["summary"]["solved_contact_distance_median_mm"] for k, (r, _) in retargeted.items()}
    assert all(np.isfinite(v) for v in medians.values()), medians
    for name in ("plain", "cm-yup-placed", "body"):
        assert len(retargeted[name][0]["dof_names"]) == len(retargeted["core"][0]["dof_names"])
        assert abs(medians[name] - medians["core"]) <= 0.1, medians


def test_the_result_layer_plays_on_the_users_own_file(files, retargeted):
    """The animation layer sublayers the user's cm / Y-up file as it is; USD's own skinning of
    the composed stage (pxr, no project code) gives the core's posed surface to 1e-5 m."""
    from pxr import Usd

    doc, out = retargeted["cm-yup-placed"]
    layer = out / "animation.usda"
    stage = Usd.Stage.Open(str(layer))
    assert [str(p) for p in stage.GetRootLayer().subLayerPaths] == [
        os.path.relpath(files["cm-yup-placed"], out).replace(os.sep, "/")]
    assert not (out / "rig.usda").exists()
    rig = read_rig_usd(files["cm-yup-placed"])
    from retarget_core.export import read_dof_bsplines

    curves = read_dof_bsplines(layer)
    fps = doc["fps"]
    for frame in (0, 17, len(doc["times"]) - 1):
        q = np.array([float(curves[name](frame / fps)) for name in rig.dof_names])
        core_points = rig.kinematics().skin(q)
        usd_points = skinned_world_points(layer, time=frame) * 0.01 @ Z_UP_TO_Y_UP[:3, :3]
        assert np.abs(usd_points - core_points).max() <= 1e-5, frame


def test_the_result_layer_plays_on_the_characters_own_file(files, retargeted):
    """A hand cut from a body: the layer composes over the body file, USD's skinning moves the
    hand's skin like the core's rig, the body keeps its rest, and the hand root's world motion
    is an Xform for the arm's IK."""
    from pxr import Usd, UsdGeom, UsdSkel
    from scipy.spatial import cKDTree

    from retarget_core.export import read_dof_bsplines

    doc, out = retargeted["body"]
    layer = out / "animation.usda"
    assert not (out / "rig.usda").exists()
    rig = read_rig_usd(files["body"])
    to_world = lambda p: p * 0.01 @ Z_UP_TO_Y_UP[:3, :3]  # noqa: E731  (cm, Y-up -> m, Z-up)
    rest = to_world(skinned_world_points(files["body"]))
    d, body_ids = cKDTree(rest).query(rig.surface.vertices[:-1])  # the last vertex is the cap's centre
    assert d.max() < 1e-6
    curves = read_dof_bsplines(layer)
    fps = doc["fps"]
    stage = Usd.Stage.Open(str(layer))
    anim = UsdSkel.Animation(stage.GetPrimAtPath("/Character/Animation"))
    tokens = [str(t) for t in anim.GetJointsAttr().Get()]
    head = tokens.index("spine/chest/neck/head")
    wrist = UsdGeom.Xformable(stage.GetPrimAtPath("/HandRetarget_wristTarget"))
    skel = UsdSkel.Skeleton(stage.GetPrimAtPath("/Character/Skeleton"))
    head_rest = np.array(skel.GetRestTransformsAttr().Get()[head].ExtractTranslation())
    assert np.linalg.norm(head_rest) == pytest.approx(10.0, abs=1e-4)  # 10 cm from the neck
    for frame in (0, 20, len(doc["times"]) - 1):
        q = np.array([float(curves[name](frame / fps)) for name in rig.dof_names])
        posed = rig.kinematics().skin(q)[:-1]
        usd = to_world(skinned_world_points(layer, time=frame))[body_ids]
        assert np.abs(usd - posed).max() <= 1e-5, frame
        translations = np.array(anim.GetTranslationsAttr().Get(Usd.TimeCode(frame)))
        assert np.allclose(translations[head], head_rest, atol=1e-4)  # the body keeps its rest
        hand_root = rig.kinematics().pose(q).world[0]
        m = np.array(wrist.ComputeLocalToWorldTransform(Usd.TimeCode(frame))).T
        assert np.allclose(to_world(m[:3, 3]), hand_root[:3, 3], atol=1e-6)


def test_rig_import_writes_the_inferred_spec_and_its_limits(files, tmp_path, capsys):
    out = tmp_path / "imported.usda"
    assert main(["rig", "import", str(files["cm-yup-placed"]), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "inferred by role" in printed
    limits = tmp_path / "imported.limits.toml"
    assert limits.is_file() and "[index1]" in limits.read_text()
    again = load_rig(out)  # a rig file with its DOF spec now: read as written, nothing inferred again
    plain = read_rig_usd(files["cm-yup-placed"])
    assert again.dof_names == plain.dof_names
    assert np.abs(again.surface.vertices - plain.surface.vertices).max() <= 1e-6  # float32 points
    limits.write_text("[index1]\nindex1_flex = [-10.0, 60.0]\n")
    edited = tmp_path / "edited.usda"
    assert main(["rig", "import", str(files["cm-yup-placed"]), "--limits", str(limits), "--out", str(edited)]) == 0
    d = load_rig(edited).dofs[plain.dof_index("index1_flex")]
    assert np.degrees([d.lower, d.upper]) == pytest.approx([-10.0, 60.0])
