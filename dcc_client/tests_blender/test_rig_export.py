"""Rig export: the core reads what the add-on writes, and puts the surface where Blender has it."""

import json
import math
import random
import zipfile

import pytest

from conftest import SKIP_REASON

if SKIP_REASON:
    pytest.skip(SKIP_REASON, allow_module_level=True)

from conftest import bpy, build_demo_armature, core, ext

pytestmark = pytest.mark.usefixtures("addon")


def test_extension_builds_and_validates(extension_zip):
    names = set(zipfile.ZipFile(extension_zip).namelist())
    # the project's stdlib modules are staged in; they are not copied by hand into the source
    assert {"blender_manifest.toml", "__init__.py", "client.py", "curves.py"} <= names


def _armature_space_vertices(arm, mesh):
    dg = bpy.context.evaluated_depsgraph_get()
    ev = mesh.evaluated_get(dg)
    me = ev.to_mesh()
    try:
        m = arm.matrix_world.inverted() @ ev.matrix_world
        return [tuple(m @ v.co) for v in me.vertices]
    finally:
        ev.to_mesh_clear()


def test_rig_export_reads_in_core(inputs, work):
    import numpy as np

    arm, mesh = build_demo_armature(inputs["rig"], inputs["spec"])
    path = work / "exported_rig.usda"
    assert 'FINISHED' in bpy.ops.hand_retarget.export_rig(filepath=str(path), upload=False)
    settings = arm.hand_retarget
    assert settings.rig_file == str(path) and settings.meters_per_unit == pytest.approx(1.0)

    # a random pose within the limits, set on the Blender channels the DOFs name
    rng = random.Random(7)
    spec_names = {}
    pose = {}
    rest_verts = _armature_space_vertices(arm, mesh)
    for pb in arm.pose.bones:
        if pb.name == "root":
            pb.location = (0.01, -0.02, 0.03)
            pb.rotation_euler = (0.3, -0.2, 0.5)
            pose.update(root_tx=0.01, root_ty=-0.02, root_tz=0.03, root_rx=0.3, root_ry=-0.2, root_rz=0.5)
            continue
        for i, a in enumerate("xyz"):
            if pb.lock_rotation[i]:
                continue
            c = next((c for c in pb.constraints if c.type == 'LIMIT_ROTATION'), None)
            if c is not None:
                lo, hi = getattr(c, f"min_{a}"), getattr(c, f"max_{a}")
            else:
                lo, hi = [math.radians(pb[f"hr_{k}_{a}"]) for k in ("min", "max")]
            v = rng.uniform(lo, hi) * 0.8
            pb.rotation_euler[i] = v
            pose[f"{pb.name}_r{a}"] = v
            spec_names[pb.name] = pb.rotation_mode
    bpy.context.view_layer.update()
    posed_verts = _armature_space_vertices(arm, mesh)
    (work / "pose.json").write_text(json.dumps(pose))
    info = core("rig", path, work / "pose.json", work / "skinned.npy")
    skinned = np.load(work / "skinned.npy")

    # the DOF spec: root first, then each bone's rotations in its Euler mode's product order
    assert info["dofs"][:6] == ["root_tx", "root_ty", "root_tz", "root_rx", "root_ry", "root_rz"]
    assert set(info["dofs"]) == set(pose)
    assert info["joints"] == [b.name for b in arm.data.bones]
    for bone, mode in spec_names.items():
        mine = [d for d in info["dofs"] if d.startswith(bone + "_")]
        assert mine == [f"{bone}_r{c.lower()}" for c in reversed(mode) if f"{bone}_r{c.lower()}" in mine]
    # the demo hand's limits came through the constraints and the custom properties
    demo = {d["name"]: d for d in inputs["spec"]}
    idx = info["dofs"].index("index1_rx")
    assert (info["lower"][idx], info["upper"][idx]) == pytest.approx(
        (-demo["index1_flex"]["upper"], -demo["index1_flex"]["lower"]), abs=1e-6)
    idx = info["dofs"].index("wrist_rz")
    assert (info["lower"][idx], info["upper"][idx]) == pytest.approx(
        (demo["wrist_abduct"]["lower"], demo["wrist_abduct"]["upper"]), abs=1e-6)
    # topology: the core's triangles are the add-on's fan triangulation (annotation face ids)
    assert info["faces"] == [list(t) for t in ext("rig_export").core_triangles(mesh.data)]
    # the core's kinematics put the surface where Blender has it: at rest and posed
    assert np.abs(skinned[0] - np.array(rest_verts)).max() < 1e-5
    assert np.abs(skinned[1] - np.array(posed_verts)).max() < 1e-5
    # and the joints
    for j, name in enumerate(info["joints"]):
        world = np.array(info["world_at_pose"][j])
        assert np.abs(world - np.array(arm.pose.bones[name].matrix)).max() < 1e-5, name


def _synthetic_rig():
    """A finger-like chain built with bpy: centimetre scene units, a scaled, moved and turned
    armature object, a mesh offset from it, a first bone that is not a valid root, locks, a
    Limit Rotation / Limit Location constraint, custom-property limits on a bone, and skin
    weights that do not sum to 1."""
    import bmesh

    bpy.ops.wm.read_homefile(use_empty=True)
    scene = bpy.context.scene
    scene.unit_settings.system, scene.unit_settings.scale_length = 'METRIC', 0.01
    arm_data = bpy.data.armatures.new("Chain")
    arm = bpy.data.objects.new("Chain", arm_data)
    scene.collection.objects.link(arm)
    arm.location, arm.rotation_euler, arm.scale = (1.0, 2.0, 3.0), (0.3, 0.0, 0.8), (2.0, 2.0, 2.0)
    bpy.context.view_layer.objects.active = arm
    bpy.ops.object.mode_set(mode='EDIT')
    parent = None
    for name, z0, z1 in (("Hand", 0.0, 2.0), ("finger1", 2.0, 3.0), ("finger2", 3.0, 4.0)):
        eb = arm_data.edit_bones.new(name)
        eb.head, eb.tail = (0.0, 0.0, z0), (0.0, 0.0, z1)
        if parent is not None:
            eb.parent, eb.use_connect = parent, True
        parent = eb
    bpy.ops.object.mode_set(mode='OBJECT')

    me = bpy.data.meshes.new("ChainSkin")
    bm = bmesh.new()
    bmesh.ops.create_cube(bm, size=1.0)
    bmesh.ops.subdivide_edges(bm, edges=bm.edges[:], cuts=7, use_grid_fill=True)
    for v in bm.verts:
        v.co.x, v.co.y, v.co.z = v.co.x * 0.6 - 0.1, v.co.y * 0.6, (v.co.z + 0.5) * 3.8 + 0.1
    bm.to_mesh(me)
    bm.free()
    skin = bpy.data.objects.new("ChainSkin", me)
    scene.collection.objects.link(skin)
    skin.parent, skin.location = arm, (0.1, 0.0, 0.0)
    skin.modifiers.new("Armature", 'ARMATURE').object = arm
    groups = {n: skin.vertex_groups.new(name=n) for n in ("Hand", "finger1", "finger2")}
    for v in me.vertices:
        z = v.co.z
        if z < 2.0:
            groups["Hand"].add([v.index], 1.0, 'REPLACE')
        elif z < 3.0:
            groups["finger1"].add([v.index], 0.6, 'REPLACE')
            groups["Hand"].add([v.index], 0.6 * (3.0 - z), 'REPLACE')
        else:
            groups["finger2"].add([v.index], 0.5, 'REPLACE')

    pose = arm.pose.bones
    pose["Hand"].lock_rotation = (True, True, True)
    f1 = pose["finger1"]
    f1.rotation_mode, f1.lock_rotation = 'XZY', (False, True, False)
    c = f1.constraints.new('LIMIT_ROTATION')
    c.owner_space, c.use_limit_x, c.min_x, c.max_x = 'LOCAL', True, math.radians(-10), math.radians(90)
    f2 = pose["finger2"]
    f2.lock_rotation = (True, False, True)  # left in quaternion mode: exported as XYZ
    f2.bone["hr_min_y"], f2.bone["hr_max_y"] = -20.0, 30.0
    for o in scene.objects:
        o.select_set(o in (arm, skin))
    bpy.context.view_layer.objects.active = arm
    return arm, skin


def test_units_locks_limits_and_root(work):
    import numpy as np

    arm, skin = _synthetic_rig()
    path = work / "chain.usda"
    # Automatic: locks and limits, but no root bone at the origin: the hand model, saying the settings go unused
    info = ext("rig_export").export_rig(bpy.context, arm, skin, str(path))
    assert info["dof_mode"] == 'HAND_MODEL' and info["dofs"] is None
    assert any("not used" in w and "Bone channels" in w for w in info["warnings"]), info["warnings"]
    assert "handretarget:specVersion" not in path.read_text() and "handretarget:jointNames" in path.read_text()
    arm.hand_retarget.dof_mode = 'CHANNELS'
    with pytest.raises(RuntimeError, match="root bone 'Hand'.*Hand model"):
        bpy.ops.hand_retarget.export_rig(filepath=str(path), upload=False)
    assert 'FINISHED' in bpy.ops.hand_retarget.add_root_bone()
    root = arm.pose.bones["root"]
    root.lock_rotation = (False, True, False)
    c = root.constraints.new('LIMIT_LOCATION')
    c.owner_space, c.use_min_x, c.min_x, c.use_max_x, c.max_x = 'LOCAL', True, -1.0, True, 1.0
    assert 'FINISHED' in bpy.ops.hand_retarget.export_rig(filepath=str(path), upload=False)
    mpu = arm.hand_retarget.meters_per_unit
    assert mpu == pytest.approx(0.02)

    values = {"root_tx": 0.5, "root_tz": -0.3, "root_rx": 0.2, "root_rz": -0.4,
              "finger1_rz": 0.3, "finger1_rx": 0.9, "finger2_ry": 0.25}
    rest = _armature_space_vertices(arm, skin)
    root.location = (0.5, 0.0, -0.3)
    root.rotation_euler = (0.2, 0.0, -0.4)
    arm.pose.bones["finger1"].rotation_euler = (0.9, 0.0, 0.3)
    arm.pose.bones["finger2"].rotation_mode = 'XYZ'  # what an import sets
    arm.pose.bones["finger2"].rotation_euler = (0.0, 0.25, 0.0)
    bpy.context.view_layer.update()
    posed = _armature_space_vertices(arm, skin)
    # the core's DOF values: translations in metres
    values.update({k: v * mpu for k, v in values.items() if k.startswith("root_t")})
    (work / "chain_pose.json").write_text(json.dumps(values))
    info = core("rig", path, work / "chain_pose.json", work / "chain.npy")
    skinned = np.load(work / "chain.npy")

    assert info["joints"] == ["root", "Hand", "finger1", "finger2"]
    # root: six DOFs whatever its locks; mode XZY lists z then x (y locked); finger2 only y
    assert info["dofs"] == ["root_tx", "root_ty", "root_tz", "root_rx", "root_ry", "root_rz",
                            "finger1_rz", "finger1_rx", "finger2_ry"]
    lim = dict(zip(info["dofs"], zip(info["lower"], info["upper"])))
    assert lim["root_tx"] == pytest.approx((-mpu, mpu))          # Limit Location, armature units -> m
    assert lim["root_ty"] == pytest.approx((-2.0, 2.0))          # default, metres
    assert lim["root_ry"] == pytest.approx((-1e-6, 1e-6))        # locked root channel
    assert lim["root_rx"] == pytest.approx((-2 * math.pi, 2 * math.pi))
    assert lim["finger1_rx"] == pytest.approx((math.radians(-10), math.radians(90)))
    assert lim["finger1_rz"] == pytest.approx((-math.pi, math.pi))
    assert lim["finger2_ry"] == pytest.approx((math.radians(-20), math.radians(30)))
    # metres = armature units x metersPerUnit; weights normalised as Blender's modifier does
    assert np.abs(skinned[0] - np.array(rest) * mpu).max() < 1e-7
    assert np.abs(skinned[1] - np.array(posed) * mpu).max() < 1e-7


def test_import_units_and_rotation_modes(work):
    """Curves onto the centimetre chain: translations divided by metres-per-unit, each bone's
    Euler mode chosen from its DOF order, one FREE-handle key per breakpoint."""
    arm, _ = _synthetic_rig()
    bpy.ops.hand_retarget.add_root_bone()
    arm.pose.bones["finger2"].rotation_mode = 'QUATERNION'
    assert 'FINISHED' in bpy.ops.hand_retarget.export_rig(filepath=str(work / "chain2.usda"), upload=False)
    mpu = arm.hand_retarget.meters_per_unit
    names = ["root_tx", "root_ty", "root_tz", "root_rx", "root_ry", "root_rz", "finger1_rz", "finger1_rx",
             "finger2_ry"]
    knots = [0.0] * 4 + [0.1, 0.2] + [0.3] * 4
    curves = [{"knots": knots, "coefficients": [0.01 * (i + 1) * (-1) ** k for k in range(6)], "degree": 3,
               "extrapolation": "held"} for i in range(len(names))]
    doc = {"format": "handretarget.result", "version": 1, "fps": 30.0, "times": [k / 30 for k in range(10)],
           "dof_names": names, "curves": curves}
    scene = bpy.context.scene
    scene.render.fps, scene.render.fps_base = 24, 1.0  # the scene keeps its own rate: a 30 fps result is timed into it
    info = ext("anim_import").import_curves(bpy.context, arm, doc, mpu=mpu, start_frame=5)
    assert info["fcurves"] == 9 and not info["skipped"]
    pose = arm.pose.bones
    assert (pose["root"].rotation_mode, pose["finger1"].rotation_mode, pose["finger2"].rotation_mode) == \
        ('ZYX', 'XZY', 'XYZ')
    assert (scene.render.fps, scene.frame_start, scene.frame_end) == (24, 5, 5 + math.ceil(0.3 * 24))
    from bpy_extras import anim_utils
    fcurves = anim_utils.animdata_get_channelbag_for_assigned_slot(arm.animation_data).fcurves
    curve_math = ext("curves")
    for name, c in zip(names, curves):
        bone, channel, axis = ext("anim_import").dof_channel(name, "root")
        fc = fcurves.find(f'pose.bones["{bone}"].{channel}', index=axis)
        assert len(fc.keyframe_points) == 4  # one per breakpoint: 0, 0.1, 0.2, 0.3 s
        scale = 1.0 / mpu if channel == "location" else 1.0
        for k in range(40):
            t = 0.3 * k / 39
            want = curve_math.bspline_eval(c["knots"], c["coefficients"], t) * scale
            # 1e-5 as SPLINE_TOL in test_end_to_end: at 24 fps the breakpoints and their handles sit on
            # fractional frames, stored as float32, which bends Blender's Bezier time parameter slightly
            assert fc.evaluate(5 + 24 * t) == pytest.approx(want, abs=1e-5 * max(1.0, abs(want)))
