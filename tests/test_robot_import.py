"""Robot hands from URDF and MJCF: structure, wrapper surface, kinematics vs. the source
libraries, and bad-input errors."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from installed_models import installed_or_none
from retarget_core.errors import InputError
from retarget_core.mesh.topology import check_closed_manifold
from retarget_core.rig.robot_import import WRAPPER_OFFSET, load_mjcf, load_urdf


LEAP = installed_or_none("leap")
SHADOW = installed_or_none("shadow")
RES = 0.0035

needs_leap = pytest.mark.skipif(LEAP is None, reason="ghand wheel (LEAP hand URDF) not installed")
needs_shadow = pytest.mark.skipif(SHADOW is None, reason="gymnasium-robotics wheel (Shadow hand MJCF) not installed")


@pytest.fixture(scope="module")
def leap():
    if LEAP is None:
        pytest.skip("ghand wheel (LEAP hand URDF) not installed")
    t = time.perf_counter()
    rig = load_urdf(LEAP, wrapper_resolution=RES)
    rig.metadata["test_build_seconds"] = time.perf_counter() - t
    return rig


@pytest.fixture(scope="module")
def shadow():
    if SHADOW is None:
        pytest.skip("gymnasium-robotics wheel (Shadow hand MJCF) not installed")
    t = time.perf_counter()
    rig = load_mjcf(SHADOW, wrapper_resolution=RES)
    rig.metadata["test_build_seconds"] = time.perf_counter() - t
    return rig


def _subtree(rig, joint):
    inside = np.zeros(rig.n_joints, dtype=bool)
    inside[joint] = True
    for j in range(joint + 1, rig.n_joints):
        if inside[rig.joints[j].parent]:
            inside[j] = True
    return inside


def _check_common(rig, n_actuated):
    rig.validate()
    assert rig.n_dofs == 6 + n_actuated
    assert rig.dof_names[:6] == ["root_tx", "root_ty", "root_tz", "root_rx", "root_ry", "root_rz"]
    assert rig.joints[0].name == "root" and rig.joints[1].parent == 0
    assert np.all(np.isfinite(rig.lower)) and np.all(np.isfinite(rig.upper))
    assert np.all(rig.lower < rig.upper)
    report = check_closed_manifold(rig.surface.faces, rig.surface.n_vertices)
    assert report.closed and report.manifold and report.components == 1, report.describe()
    assert rig.visual is not None and rig.visual.n_vertices > 0
    kin = rig.kinematics()
    q = rig.random_pose(np.random.default_rng(0))
    for mesh in ("surface", "visual"):
        posed = kin.skin(q, mesh=mesh)
        assert np.all(np.isfinite(posed))
    # Bound near the geometry: every wrapper vertex within offset + 2 * resolution of it.
    import igl

    d2, _, _ = igl.point_mesh_squared_distance(rig.surface.vertices, rig.visual.vertices, rig.visual.faces)
    assert np.sqrt(d2).max() <= WRAPPER_OFFSET + 2 * RES


def _check_single_dof_motion(rig, dof_name):
    kin = rig.kinematics()
    d = rig.dof_index(dof_name)
    joint = rig.dofs[d].joint
    q0 = rig.rest_pose
    q1 = q0.copy()
    q1[d] = rig.lower[d] + 0.7 * (rig.upper[d] - rig.lower[d])
    assert abs(q1[d] - q0[d]) > 0.1
    a, b = kin.skin(q0, mesh="visual"), kin.skin(q1, mesh="visual")
    owner = rig.visual.joint_indices[:, 0]
    down = _subtree(rig, joint)[owner]
    assert down.any() and (~down).any()
    np.testing.assert_allclose(a[~down], b[~down], atol=1e-12)
    moved = np.linalg.norm(a[down] - b[down], axis=1)
    assert moved.max() > 1e-3
    rng = np.random.default_rng(1)
    idx = np.nonzero(down)[0]
    i, j = rng.choice(idx, 200), rng.choice(idx, 200)
    np.testing.assert_allclose(
        np.linalg.norm(a[i] - a[j], axis=1), np.linalg.norm(b[i] - b[j], axis=1), atol=1e-9
    )


# ---- LEAP (URDF) ---------------------------------------------------------------------------
@needs_leap
def test_leap_structure_and_surface(leap):
    _check_common(leap, 16)
    assert leap.metadata["source_format"] == "urdf"
    assert leap.metadata["source_file"] == str(LEAP)
    print(
        f"LEAP: {leap.n_dofs} DOFs, {leap.n_joints} joints, wrapper {leap.surface.n_vertices} vertices "
        f"{len(leap.surface.faces)} faces, built in {leap.metadata['test_build_seconds']:.1f} s at {RES} m"
    )


@needs_leap
def test_leap_single_dof_moves_downstream_rigidly(leap):
    # A DOF in the middle of a finger chain: both upstream and downstream geometry exist.
    depth = {}
    for i, jt in enumerate(leap.joints):
        depth[i] = 0 if jt.parent < 0 else depth[jt.parent] + 1
    d = max(range(6, leap.n_dofs), key=lambda k: (depth[leap.dofs[k].joint] == 3, -k))
    _check_single_dof_motion(leap, leap.dofs[d].name)


@needs_leap
def test_leap_fk_matches_yourdfpy(leap):
    import yourdfpy

    urdf = yourdfpy.URDF.load(str(LEAP), load_meshes=False, build_scene_graph=True)
    rng = np.random.default_rng(3)
    q = leap.random_pose(rng)
    q[:6] = 0.0  # root DOFs at identity
    urdf.update_cfg({name: q[leap.dof_index(name)] for name in urdf.actuated_joint_names})
    world = leap.kinematics().pose(q).world
    for link, (joint_name, offset) in leap.metadata["link_frames"].items():
        ours = world[leap.joint_index(joint_name)] @ np.asarray(offset)
        theirs = urdf.get_transform(frame_to=link, frame_from=urdf.base_link)
        np.testing.assert_allclose(ours[:3, 3], theirs[:3, 3], atol=1e-6, err_msg=link)
        np.testing.assert_allclose(ours[:3, :3], theirs[:3, :3], atol=1e-6, err_msg=link)


# ---- Shadow (MJCF) ---------------------------------------------------------------------------
def _mujoco_body_check(rig, model_path, q):
    import mujoco

    model = mujoco.MjModel.from_xml_path(str(model_path))
    data = mujoco.MjData(model)
    data.qpos[:] = model.qpos0
    for j in range(model.njnt):
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j)
        adr = model.jnt_qposadr[j]
        if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_BALL:
            r = np.eye(3)
            for axis_name, e in (("x", 0), ("y", 1), ("z", 2)):
                axis = np.eye(3)[e]
                angle = q[rig.dof_index(f"{name}_{axis_name}")]
                k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
                r = r @ (np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k)
            quat = np.zeros(4)
            mujoco.mju_mat2Quat(quat, r.reshape(-1))
            data.qpos[adr : adr + 4] = quat
        elif int(model.jnt_type[j]) in (int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)):
            data.qpos[adr] = q[rig.dof_index(name)]
    mujoco.mj_kinematics(model, data)
    world = rig.kinematics().pose(q).world
    for body, (joint_name, offset) in rig.metadata["body_offsets"].items():
        b = mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, body)
        ours = world[rig.joint_index(joint_name)] @ np.asarray(offset)
        np.testing.assert_allclose(ours[:3, 3], data.xpos[b], atol=1e-6, err_msg=body)
        np.testing.assert_allclose(ours[:3, :3], data.xmat[b].reshape(3, 3), atol=1e-6, err_msg=body)


@needs_shadow
def test_shadow_structure_and_surface(shadow):
    import mujoco

    model = mujoco.MjModel.from_xml_path(str(SHADOW))
    n_hinges = sum(
        1
        for j in range(model.njnt)
        if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_HINGE
        and mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_JOINT, j).startswith("robot0:")
    )
    assert n_hinges == 24
    _check_common(shadow, n_hinges)
    assert shadow.metadata["source_format"] == "mjcf"
    print(
        f"Shadow: {shadow.n_dofs} DOFs, {shadow.n_joints} joints, wrapper {shadow.surface.n_vertices} vertices "
        f"{len(shadow.surface.faces)} faces, built in {shadow.metadata['test_build_seconds']:.1f} s at {RES} m"
    )


@needs_shadow
def test_shadow_single_dof_moves_downstream_rigidly(shadow):
    _check_single_dof_motion(shadow, "robot0:FFJ2")


@needs_shadow
def test_shadow_fk_matches_mujoco(shadow):
    q = shadow.random_pose(np.random.default_rng(4))
    q[:6] = 0.0
    _mujoco_body_check(shadow, SHADOW, q)


# ---- small synthetic models -------------------------------------------------------------------
TOY_MJCF = """<mujoco>
  <compiler angle="radian" autolimits="true"/>
  <worldbody>
    <geom type="plane" size="1 1 0.1"/>
    <body name="base" pos="0.1 0.2 0.3" euler="0.3 0.2 0.1">
      <geom type="box" size="0.02 0.02 0.01"/>
      <body name="link1" pos="0 0 0.02">
        <joint name="j1a" type="hinge" axis="1 0 0" pos="0 0 -0.005" range="-1 1" ref="0.3"/>
        <joint name="j1b" type="hinge" axis="0 1 1" pos="0.002 0 0" range="0.2 1.5"/>
        <geom type="capsule" fromto="0 0 -0.01 0 0 0.03" size="0.008"/>
        <body name="link2" pos="0 0 0.035">
          <joint name="ball" type="ball" range="0 0.8"/>
          <geom type="sphere" size="0.01"/>
          <body name="link3" pos="0 0 0.01">
            <joint name="slide" type="slide" axis="0 0 1" range="-0.005 0.01" ref="0.002"/>
            <geom type="cylinder" size="0.006 0.01" pos="0 0 0.005"/>
          </body>
        </body>
      </body>
    </body>
  </worldbody>
</mujoco>
"""


def test_toy_mjcf_multi_joint_ball_ref_fk(tmp_path):
    path = tmp_path / "toy.xml"
    path.write_text(TOY_MJCF)
    rig = load_mjcf(path, wrapper_resolution=0.002)
    assert rig.dof_names[6:] == ["j1a", "j1b", "ball_x", "ball_y", "ball_z", "slide"]
    assert [j.name for j in rig.joints][1:] == ["base", "link1/j1a", "link1/j1b", "link2", "link3"]
    assert rig.dofs[rig.dof_index("j1b")].rest == pytest.approx(0.2)
    for seed in range(3):
        q = rig.random_pose(np.random.default_rng(seed))
        q[:6] = 0.0
        _mujoco_body_check(rig, path, q)
    # The rest pose too (geometry is authored there).
    _mujoco_body_check(rig, path, np.where(np.arange(rig.n_dofs) < 6, 0.0, rig.rest_pose))


def _write_urdf(tmp_path, body: str, name="toy.urdf") -> Path:
    path = tmp_path / name
    path.write_text(f'<?xml version="1.0"?>\n<robot name="toy">\n{body}\n</robot>\n')
    return path


BOX_LINK = """<link name="{name}"><visual><origin xyz="0 0 0.02"/><geometry><box size="0.02 0.02 0.05"/></geometry></visual></link>"""


def test_toy_urdf_package_uri_fixed_and_continuous(tmp_path):
    import trimesh

    pkg = tmp_path / "my_pkg" / "meshes"
    pkg.mkdir(parents=True)
    trimesh.creation.box(extents=(0.02, 0.02, 0.05)).export(pkg / "part.stl")
    urdf_dir = tmp_path / "my_pkg" / "urdf"
    urdf_dir.mkdir()
    body = "\n".join(
        [
            BOX_LINK.format(name="palm"),
            '<link name="finger"><visual><origin xyz="0 0 0.02"/><geometry>'
            '<mesh filename="package://my_pkg/meshes/part.stl" scale="1 1 1"/></geometry></visual></link>',
            BOX_LINK.format(name="tip"),
            '<link name="cap"><visual><geometry><sphere radius="0.012"/></geometry></visual></link>',
            '<joint name="j_finger" type="revolute"><parent link="palm"/><child link="finger"/>'
            '<origin xyz="0 0 0.04"/><axis xyz="2 0 0"/><limit lower="0.1" upper="1.2" effort="1" velocity="1"/></joint>',
            '<joint name="j_tip" type="continuous"><parent link="finger"/><child link="tip"/>'
            '<origin xyz="0 0 0.04" rpy="0 0 0.5"/><axis xyz="0 1 0"/></joint>',
            '<joint name="j_cap" type="fixed"><parent link="tip"/><child link="cap"/><origin xyz="0 0 0.045"/></joint>',
        ]
    )
    path = _write_urdf(urdf_dir, body)
    rig = load_urdf(path, wrapper_resolution=0.002)
    assert rig.dof_names[6:] == ["j_finger", "j_tip"]
    assert [j.name for j in rig.joints] == ["root", "palm", "finger", "tip"]  # cap merged into tip
    finger = rig.dofs[rig.dof_index("j_finger")]
    assert finger.rest == pytest.approx(0.1) and np.allclose(finger.axis, (1, 0, 0))
    tip = rig.dofs[rig.dof_index("j_tip")]
    assert (tip.lower, tip.upper) == (-np.pi, np.pi)
    assert rig.metadata["link_frames"]["cap"][0] == "tip"


def test_urdf_missing_mesh_names_mesh_and_link(tmp_path):
    body = (
        '<link name="palm"><visual><geometry><mesh filename="meshes/nothere.stl"/></geometry></visual></link>'
    )
    path = _write_urdf(tmp_path, body)
    with pytest.raises(InputError) as err:
        load_urdf(path)
    message = str(err.value)
    assert "nothere.stl" in message and "palm" in message and str(path) in message


def test_urdf_revolute_without_limits_names_joint(tmp_path):
    body = "\n".join(
        [
            BOX_LINK.format(name="palm"),
            BOX_LINK.format(name="finger"),
            '<joint name="knuckle_joint" type="revolute"><parent link="palm"/><child link="finger"/>'
            '<origin xyz="0 0 0.04"/><axis xyz="1 0 0"/></joint>',
        ]
    )
    path = _write_urdf(tmp_path, body)
    with pytest.raises(InputError, match="knuckle_joint"):
        load_urdf(path)


def test_urdf_malformed_xml(tmp_path):
    path = tmp_path / "broken.urdf"
    path.write_text('<robot name="toy"><link name="palm"><visual></link>')
    with pytest.raises(InputError, match="broken.urdf"):
        load_urdf(path)


def test_mjcf_hinge_without_range_names_joint(tmp_path):
    path = tmp_path / "norange.xml"
    path.write_text(
        """<mujoco><compiler autolimits="true"/><worldbody>
        <body name="base"><geom type="box" size="0.02 0.02 0.01"/>
          <body name="finger" pos="0 0 0.02"><joint name="loose_hinge" type="hinge" axis="1 0 0"/>
            <geom type="capsule" fromto="0 0 0 0 0 0.03" size="0.008"/></body>
        </body></worldbody></mujoco>"""
    )
    with pytest.raises(InputError, match="loose_hinge"):
        load_mjcf(path)


def test_mjcf_compile_error_is_input_error(tmp_path):
    path = tmp_path / "bad.xml"
    path.write_text("<mujoco><worldbody><body><geom type='nonsense'/></body></worldbody></mujoco>")
    with pytest.raises(InputError, match="bad.xml"):
        load_mjcf(path)


# ---- build_wrapper directly -----------------------------------------------------------------
def _box(center, extents=(0.02, 0.02, 0.02)):
    import trimesh

    m = trimesh.creation.box(extents=extents)
    return np.asarray(m.vertices) + np.asarray(center, float), np.asarray(m.faces)


def test_wrapper_bridges_small_gap_and_skins_two_links():
    from retarget_core.rig.wrapper import build_wrapper

    a, b = _box((0, 0, 0)), _box((0.024, 0, 0))  # 4 mm gap
    mesh = build_wrapper([(0, *a), (1, *b)], resolution=0.002, offset=0.0015, parents=[-1, 0])
    report = mesh.topology()
    assert report.closed and report.manifold and report.components == 1
    assert set(np.unique(mesh.joint_indices[mesh.joint_weights > 0])) == {0, 1}
    np.testing.assert_allclose(mesh.joint_weights.sum(axis=1), 1.0)
    # Vertices near a box's far end belong to it alone.
    far_a = mesh.vertices[:, 0] < -0.005
    assert np.all(mesh.joint_indices[far_a, 0] == 0) and np.all(mesh.joint_weights[far_a, 0] == 1.0)


def test_wrapper_far_apart_links_raise_naming_them():
    from retarget_core.rig.wrapper import build_wrapper

    a, b = _box((0, 0, 0)), _box((0.08, 0, 0))
    with pytest.raises(InputError, match="lonely_link"):
        build_wrapper([(0, *a), (1, *b)], resolution=0.003, link_names={0: "palm", 1: "lonely_link"})
