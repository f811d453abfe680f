"""Rigs round-trip through USD (UsdSkel + the handretarget DOF spec); bad files are rejected
with errors naming the file and the element."""

import copy
from dataclasses import replace

import numpy as np
import pytest
from pxr import Gf, Usd, UsdGeom, UsdSkel, Vt

from retarget_core.errors import InputError
from retarget_core.rig import SkinnedMesh
from retarget_core.rig.usd_io import Y_UP_TO_Z_UP, check_usd_compliance, read_rig_usd, write_rig_usd

HANDS = ("source_human", "prosthetic_2dof", "robot4")
TOL = 1e-6  # metres


def assert_same_rig(a, b, rng, n_poses=5):
    assert b.name == a.name
    assert b.metadata == a.metadata
    assert b.joint_names == a.joint_names
    assert [j.parent for j in b.joints] == [j.parent for j in a.joints]
    assert b.dof_names == a.dof_names
    assert [d.kind for d in b.dofs] == [d.kind for d in a.dofs]
    assert [d.joint for d in b.dofs] == [d.joint for d in a.dofs]
    np.testing.assert_allclose([d.axis for d in b.dofs], [d.axis for d in a.dofs], atol=1e-12)
    np.testing.assert_allclose(b.lower, a.lower, atol=1e-12)
    np.testing.assert_allclose(b.upper, a.upper, atol=1e-12)
    np.testing.assert_allclose(b.rest_pose, a.rest_pose, atol=1e-12)
    np.testing.assert_array_equal(b.surface.faces, a.surface.faces)
    assert (b.visual is None) == (a.visual is None)
    ka, kb = a.kinematics(), b.kinematics()
    for _ in range(n_poses):
        q = a.random_pose(rng)
        assert np.abs(kb.skin(q) - ka.skin(q)).max() < TOL
        if a.visual is not None:
            assert np.abs(kb.skin(q, "visual") - ka.skin(q, "visual")).max() < TOL


@pytest.mark.parametrize("ext", [".usda", ".usdc"])
@pytest.mark.parametrize("hand", HANDS)
def test_round_trip(demo_rigs, tmp_path, rng, hand, ext):
    rig = demo_rigs[hand]
    path = tmp_path / f"{hand}{ext}"
    write_rig_usd(rig, path)
    back = read_rig_usd(path)
    assert_same_rig(rig, back, rng)
    assert check_usd_compliance(path) == []
    assert [p.name for p in tmp_path.iterdir()] == [path.name]  # no temp file left behind


def test_file_layout(demo_rigs, tmp_path):
    rig = demo_rigs["prosthetic_2dof"]
    path = tmp_path / "hand.usda"
    write_rig_usd(rig, path)
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageMetersPerUnit(stage) == 1.0
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    root = stage.GetDefaultPrim()
    assert root.IsA(UsdSkel.Root) and root.GetName() == "prosthetic_2dof"
    skel = UsdSkel.Skeleton(root.GetChild("Skeleton"))
    joints = list(skel.GetJointsAttr().Get())
    assert joints[0] == "root" and joints[1] == "root/thumb1" and joints[2] == "root/thumb1/thumb2"
    rest = np.array(skel.GetRestTransformsAttr().Get()).transpose(0, 2, 1)
    np.testing.assert_allclose(rest[3], rig.joints[3].rest_local, atol=1e-15)
    mesh = root.GetChild("Surface")
    assert mesh.HasAPI(UsdSkel.BindingAPI)
    binding = UsdSkel.BindingAPI(mesh)
    assert binding.GetJointIndicesPrimvar().GetElementSize() == rig.surface.joint_indices.shape[1]
    assert binding.GetJointIndicesPrimvar().GetInterpolation() == UsdGeom.Tokens.vertex
    assert not root.GetChild("Visual")


def test_visual_mesh_and_odd_names(demo_rigs, tmp_path, rng):
    rig = copy.deepcopy(demo_rigs["robot4"])
    rig.joints[1].name = "thumb base/1"  # not a valid prim name
    rig.joints[2].name = "thumb_base_1"  # would collide after sanitising
    rig.name = "robot hand #4"
    s = rig.surface
    rig.visual = SkinnedMesh(s.vertices * 1.01, s.faces[::2], s.joint_indices, s.joint_weights)
    rig.__dict__.pop("_kinematics", None)
    path = tmp_path / "robot.usdc"
    write_rig_usd(rig, path)
    back = read_rig_usd(path)
    assert_same_rig(rig, back, rng)
    stage = Usd.Stage.Open(str(path))
    visual = UsdGeom.Mesh(stage.GetDefaultPrim().GetChild("Visual"))
    assert visual.GetPurposeAttr().Get() == UsdGeom.Tokens.render
    assert check_usd_compliance(path) == []


def test_nonzero_rest_pose(demo_rigs, tmp_path, rng):
    """rest pose != 0: restTransforms hold q = 0, bindTransforms the rest pose."""
    base = demo_rigs["prosthetic_2dof"]
    q0 = base.random_pose(np.random.default_rng(7), root_scale=0.0)
    dofs = [replace(d, rest=float(v)) for d, v in zip(base.dofs, q0)]
    s = base.surface
    posed = SkinnedMesh(base.kinematics().skin(q0), s.faces, s.joint_indices, s.joint_weights)
    rig = replace(base, dofs=dofs, surface=posed)
    rig.__dict__.pop("_kinematics", None)
    path = tmp_path / "rest.usda"
    write_rig_usd(rig, path)
    back = read_rig_usd(path)
    assert_same_rig(rig, back, rng)


def _edit(src, dst, fn):
    """Open src, apply fn(stage), export to dst."""
    stage = Usd.Stage.Open(str(src))
    fn(stage)
    stage.GetRootLayer().Export(str(dst))
    return dst


def _skeleton(stage):
    return UsdSkel.Skeleton(stage.GetDefaultPrim().GetChild("Skeleton"))


def _surface(stage):
    return UsdGeom.Mesh(stage.GetDefaultPrim().GetChild("Surface"))


def _mats_in(attr):
    return np.array(attr.Get()).transpose(0, 2, 1)


def _mats_out(attr, mats):
    attr.Set(Vt.Matrix4dArray.FromNumpy(np.ascontiguousarray(mats.transpose(0, 2, 1))))


def test_centimetres_y_up(demo_rigs, tmp_path, rng):
    rig = demo_rigs["source_human"]
    metres = tmp_path / "m.usda"
    write_rig_usd(rig, metres)
    to_y_up = np.linalg.inv(Y_UP_TO_Z_UP)

    def to_cm_y_up(stage):
        UsdGeom.SetStageMetersPerUnit(stage, 0.01)
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
        skel = _skeleton(stage)
        rest = _mats_in(skel.GetRestTransformsAttr())
        rest[:, :3, 3] *= 100.0
        rest[0] = to_y_up @ rest[0]
        _mats_out(skel.GetRestTransformsAttr(), rest)
        bind = _mats_in(skel.GetBindTransformsAttr())
        bind[:, :3, 3] *= 100.0
        _mats_out(skel.GetBindTransformsAttr(), to_y_up @ bind)
        pts = np.array(_surface(stage).GetPointsAttr().Get(), dtype=np.float64)
        pts = 100.0 * pts @ to_y_up[:3, :3].T
        _surface(stage).GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(pts.astype(np.float32)))
        prim = skel.GetPrim()
        kinds = list(prim.GetAttribute("handretarget:dofKinds").Get())
        for name in ("dofLower", "dofUpper", "dofRest"):
            attr = prim.GetAttribute(f"handretarget:{name}")
            vals = np.array(attr.Get())
            vals[[k == "translate" for k in kinds]] *= 100.0
            attr.Set(Vt.DoubleArray(vals.tolist()))

    cm = _edit(metres, tmp_path / "cm.usda", to_cm_y_up)
    text = cm.read_text()
    assert "metersPerUnit = 0.01" in text and 'upAxis = "Y"' in text
    back = read_rig_usd(cm)
    assert_same_rig(rig, back, rng)
    assert check_usd_compliance(cm) == []


def test_joints_out_of_order_and_mesh_joint_remap(demo_rigs, tmp_path, rng):
    """A skeleton listing children before parents is reordered; skel:joints on the mesh is honoured."""
    rig = demo_rigs["prosthetic_2dof"]
    path = tmp_path / "h.usda"
    write_rig_usd(rig, path)
    n = rig.n_joints
    perm = np.r_[n - 1 : 0 : -1, 0]  # new position i holds old joint perm[i]; root last
    inv = np.empty(n, dtype=int)
    inv[perm] = np.arange(n)

    def shuffle(stage):
        skel = _skeleton(stage)
        prim = skel.GetPrim()
        joints = list(skel.GetJointsAttr().Get())
        skel.GetJointsAttr().Set(Vt.TokenArray([joints[i] for i in perm]))
        names = list(skel.GetJointNamesAttr().Get())
        skel.GetJointNamesAttr().Set(Vt.TokenArray([names[i] for i in perm]))
        prim.GetAttribute("handretarget:jointNames").Set(Vt.StringArray([names[i] for i in perm]))
        _mats_out(skel.GetRestTransformsAttr(), _mats_in(skel.GetRestTransformsAttr())[perm])
        _mats_out(skel.GetBindTransformsAttr(), _mats_in(skel.GetBindTransformsAttr())[perm])
        dj = np.array(prim.GetAttribute("handretarget:dofJoints").Get())
        prim.GetAttribute("handretarget:dofJoints").Set(Vt.IntArray(inv[dj].tolist()))
        # the mesh keeps its indices but names the joints in the original order
        UsdSkel.BindingAPI(_surface(stage).GetPrim()).CreateJointsAttr(Vt.TokenArray(joints))

    shuffled = _edit(path, tmp_path / "shuffled.usda", shuffle)
    back = read_rig_usd(shuffled)  # validates: parents come first again
    # the order differs from the original (file order is kept where possible): compare by name
    assert back.joint_names[0] == "root" and back.joint_names[1] == "pinky1"
    assert sorted(back.joint_names) == sorted(rig.joint_names)
    name_of = lambda r, i: r.joints[i].name if i >= 0 else None  # noqa: E731
    parents = {j.name: name_of(rig, j.parent) for j in rig.joints}
    assert {j.name: name_of(back, j.parent) for j in back.joints} == parents
    assert sorted(back.dof_names) == sorted(rig.dof_names)
    to_back = np.array([back.dof_index(name) for name in rig.dof_names])
    for d in rig.dofs:
        e = back.dofs[back.dof_index(d.name)]
        assert (e.kind, back.joints[e.joint].name) == (d.kind, rig.joints[d.joint].name)
        np.testing.assert_allclose([e.lower, e.upper, e.rest], [d.lower, d.upper, d.rest])
    for _ in range(5):
        q = rig.random_pose(rng)
        q_back = np.empty_like(q)
        q_back[to_back] = q
        assert np.abs(back.kinematics().skin(q_back) - rig.kinematics().skin(q)).max() < TOL


def test_bind_transforms_other_than_rest_pose(demo_rigs, tmp_path, rng):
    """Points bound at another pose (bindTransforms != rest-pose world) are carried to the rest pose."""
    rig = demo_rigs["robot4"]
    path = tmp_path / "h.usdc"
    write_rig_usd(rig, path)
    q1 = rig.random_pose(np.random.default_rng(3), root_scale=0.2)
    kin = rig.kinematics()

    def rebind(stage):
        _mats_out(_skeleton(stage).GetBindTransformsAttr(), kin.pose(q1).world)
        _surface(stage).GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(kin.skin(q1).astype(np.float32)))

    back = read_rig_usd(_edit(path, tmp_path / "rebound.usdc", rebind))
    # UsdSkel semantics: rest points = sum_j w_j G_j(rest) inv(bind_j) p_bind
    skin = kin.bind_world @ np.linalg.inv(kin.pose(q1).world)
    homog = np.c_[kin.skin(q1), np.ones(rig.surface.n_vertices)]
    expected = np.einsum("vj,jab,vb->va", rig.surface.dense_weights(rig.n_joints), skin[:, :3], homog)
    assert np.abs(back.surface.vertices - expected).max() < TOL
    # rigidly bound vertices come back exactly (blended ones cannot: LBS is not invertible)
    rigid = rig.surface.joint_weights.max(axis=1) > 1 - 1e-9
    assert rigid.sum() > 100
    assert np.abs(back.surface.vertices[rigid] - rig.surface.vertices[rigid]).max() < TOL
    np.testing.assert_allclose(back.kinematics().bind_world, kin.bind_world, atol=1e-12)


def test_polygons_are_fan_triangulated(demo_rigs, tmp_path):
    rig = demo_rigs["prosthetic_2dof"]
    path = tmp_path / "h.usda"
    write_rig_usd(rig, path)

    def add_quad(stage):
        mesh = _surface(stage)
        counts = list(mesh.GetFaceVertexCountsAttr().Get())
        idx = list(mesh.GetFaceVertexIndicesAttr().Get())
        # append a quad of existing vertices: it must come back as two fan triangles
        mesh.GetFaceVertexCountsAttr().Set(Vt.IntArray(counts + [4]))
        mesh.GetFaceVertexIndicesAttr().Set(Vt.IntArray(idx + [0, 1, 2, 3]))

    stage_path = _edit(path, tmp_path / "quad.usda", add_quad)
    # a quad appended to a closed surface breaks closedness: read through the private path
    from retarget_core.rig import usd_io

    stage = Usd.Stage.Open(str(stage_path))
    skel = _skeleton(stage)
    paths = [str(t) for t in skel.GetJointsAttr().Get()]
    _, faces, _, _ = usd_io._read_mesh(_surface(stage).GetPrim(), paths, src="x", element="surface")
    assert len(faces) == len(rig.surface.faces) + 2
    np.testing.assert_array_equal(faces[-2:], [[0, 1, 2], [0, 2, 3]])
    with pytest.raises(InputError, match="closed"):
        read_rig_usd(stage_path)


# ---- bad input ---------------------------------------------------------------------------
@pytest.fixture
def written(demo_rigs, tmp_path):
    path = tmp_path / "hand.usda"
    write_rig_usd(demo_rigs["prosthetic_2dof"], path)
    return path


def test_missing_file(tmp_path):
    path = tmp_path / "nope.usda"
    with pytest.raises(InputError, match="nope.usda.*not found"):
        read_rig_usd(path)


def test_not_a_usd_file(tmp_path):
    path = tmp_path / "junk.usda"
    path.write_text("this is not USD\n")
    with pytest.raises(InputError, match="junk.usda.*not a readable USD file"):
        read_rig_usd(path)
    other = tmp_path / "hand.obj"
    other.write_text("v 0 0 0\n")
    with pytest.raises(InputError, match="not a USD file"):
        read_rig_usd(other)


def test_mesh_without_skeleton(tmp_path):
    path = tmp_path / "mesh_only.usda"
    stage = Usd.Stage.CreateNew(str(path))
    mesh = UsdGeom.Mesh.Define(stage, "/Hand")
    mesh.CreatePointsAttr([Gf.Vec3f(0, 0, 0), Gf.Vec3f(1, 0, 0), Gf.Vec3f(0, 1, 0)])
    mesh.CreateFaceVertexCountsAttr([3])
    mesh.CreateFaceVertexIndicesAttr([0, 1, 2])
    stage.GetRootLayer().Save()
    with pytest.raises(InputError, match="mesh_only.usda.*skeleton"):
        read_rig_usd(path)


def test_missing_skinned_mesh(written, tmp_path):
    bad = _edit(written, tmp_path / "bad.usda", lambda s: s.RemovePrim(s.GetDefaultPrim().GetChild("Surface").GetPath()))
    with pytest.raises(InputError, match="bad.usda.*skinned mesh"):
        read_rig_usd(bad)


def test_missing_dof_lower(written, tmp_path):
    def drop(stage):
        _skeleton(stage).GetPrim().RemoveProperty("handretarget:dofLower")

    bad = _edit(written, tmp_path / "bad.usda", drop)
    with pytest.raises(InputError, match="bad.usda.*handretarget:dofLower.*missing"):
        read_rig_usd(bad)


def test_short_dof_lower(written, tmp_path):
    def shorten(stage):
        attr = _skeleton(stage).GetPrim().GetAttribute("handretarget:dofLower")
        attr.Set(Vt.DoubleArray(list(attr.Get())[:-1]))

    bad = _edit(written, tmp_path / "bad.usda", shorten)
    with pytest.raises(InputError, match="handretarget:dofLower.*entries"):
        read_rig_usd(bad)


def test_nan_limit(written, tmp_path):
    def nan(stage):
        attr = _skeleton(stage).GetPrim().GetAttribute("handretarget:dofUpper")
        vals = list(attr.Get())
        vals[8] = float("nan")
        attr.Set(Vt.DoubleArray(vals))

    bad = _edit(written, tmp_path / "bad.usda", nan)
    with pytest.raises(InputError, match="bad.usda.*DOF .*upper limit is missing or not finite"):
        read_rig_usd(bad)


def test_unknown_dof_kind(written, tmp_path):
    def kind(stage):
        attr = _skeleton(stage).GetPrim().GetAttribute("handretarget:dofKinds")
        vals = list(attr.Get())
        vals[7] = "screw"
        attr.Set(Vt.TokenArray(vals))

    bad = _edit(written, tmp_path / "bad.usda", kind)
    with pytest.raises(InputError, match="unknown DOF kind 'screw'"):
        read_rig_usd(bad)


def test_unnormalised_weights(written, tmp_path):
    def heavier(stage):
        pv = UsdSkel.BindingAPI(_surface(stage).GetPrim()).GetJointWeightsPrimvar()
        pv.Set(Vt.FloatArray.FromNumpy(np.array(pv.Get(), dtype=np.float32) * 1.5))

    bad = _edit(written, tmp_path / "bad.usda", heavier)
    with pytest.raises(InputError, match="bad.usda.*skin weights.*sum to"):
        read_rig_usd(bad)


def test_unknown_mesh_joint_name(written, tmp_path):
    def rename(stage):
        joints = list(_skeleton(stage).GetJointsAttr().Get())
        joints[3] = "root/nonexistent"
        UsdSkel.BindingAPI(_surface(stage).GetPrim()).CreateJointsAttr(Vt.TokenArray(joints))

    bad = _edit(written, tmp_path / "bad.usda", rename)
    with pytest.raises(InputError, match="skel:joints.*root/nonexistent"):
        read_rig_usd(bad)


def test_two_root_joints(written, tmp_path):
    def orphan(stage):
        attr = _skeleton(stage).GetJointsAttr()
        joints = list(attr.Get())
        joints[-1] = "stray"
        attr.Set(Vt.TokenArray(joints))

    bad = _edit(written, tmp_path / "bad.usda", orphan)
    with pytest.raises(InputError, match="exactly one root joint"):
        read_rig_usd(bad)


def test_compliance_reports_problems(tmp_path):
    path = tmp_path / "loose.usda"
    stage = Usd.Stage.CreateNew(str(path))
    UsdGeom.Mesh.Define(stage, "/A")
    UsdGeom.Mesh.Define(stage, "/A/B")
    stage.GetRootLayer().Save()
    problems = check_usd_compliance(path)
    text = "\n".join(problems)
    assert "upAxis" in text and "metersPerUnit" in text and "defaultPrim" in text
    with pytest.raises(InputError):
        check_usd_compliance(tmp_path / "missing.usda")


def test_failed_write_leaves_no_file(demo_rigs, tmp_path):
    rig = copy.deepcopy(demo_rigs["prosthetic_2dof"])
    rig.metadata = {"bad": object()}
    path = tmp_path / "hand.usda"
    with pytest.raises(InputError, match="metadata"):
        write_rig_usd(rig, path)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(InputError, match="must end in"):
        write_rig_usd(demo_rigs["prosthetic_2dof"], tmp_path / "hand.fbx")
