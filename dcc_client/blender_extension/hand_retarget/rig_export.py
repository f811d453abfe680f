"""Rig export: the armature and its skinned mesh through Blender's USD exporter, then made into
what the core reads (retarget_core/rig/usd_io.py), in one of two DOF modes (the armature's
``hand_retarget.dof_mode``; Automatic picks one, see :func:`resolve_dof_mode`):

**Hand model** (any armature as it is: any bone names and rolls, the hand anywhere in the
scene, a hand inside a body armature with ``hand_root_bone``). The file stays plain UsdSkel:
the service reads the hand from the bones and the skin and gives each joint DOFs by role
(flexion, abduction) with anatomical limits, and a free root around the armature's own root.
The file's world is Blender's world (the armature object's transform is the Skeleton's
parent Xform; ``metersPerUnit`` = the scene's unit scale). Limits the animator edited in the
panel (``dof_limits``, from the service's rig info) go in the Skeleton's
``handretarget:dofLimits`` string, the TOML of ``handretarget rig import --limits``. Results
come back as the baked SkelAnimation keyed on the armature's own bones (anim_import).

**Bone channels** (the ``handretarget:`` DOF spec added to the Skeleton prim), so that
imported F-curves equal the DOF curves exactly:

- The core composes a joint as ``rest_local @ A_1(q_1) @ A_2(q_2) ...``; Blender composes a
  pose bone as ``rest @ T(location) @ R(rotation_euler)``, and Euler mode "ABC" is the matrix
  product ``R_C @ R_B @ R_A``. So a bone's rotation DOFs are listed in the reverse of its Euler
  mode's letters (mode XYZ -> ``_rz, _ry, _rx``), about the bone's own axes, and rotation DOF
  values are the ``rotation_euler`` channels (radians).
- The core's solver seeds the hand with a free root named ``root_tx, root_ty, root_tz,
  root_rx, root_ry, root_rz`` (that order) at an identity rest transform
  (retarget_core/rig/anatomy.py ``set_root_transform``). So the root bone must sit at the
  armature origin with identity rest orientation (pointing +Y, roll 0; the "Add Root Bone"
  operator makes one), gets those six DOFs whatever its name, and is keyed in Euler mode ZYX
  (``R_x @ R_y @ R_z``). A locked root channel is kept with limits of +-1e-6.
- Other bones rotate only: an axis is free unless its rotation lock is set.
- Limits: an enabled Limit Rotation constraint (``use_limit_x``, ``min_x``, ``max_x``, ...)
  else the custom properties ``hr_min_x`` / ``hr_max_x`` (degrees) on the pose bone or the
  bone, else +-180 degrees (+-360 for the root, as the core's own free root), reported as a
  warning. Root translation: Limit Location (``use_min_x``, ...), else ``hr_min_tx`` /
  ``hr_max_tx`` (armature units), else +-2 m. The rest value is 0 clamped into the limits.
- Units: the file is in armature units with ``metersPerUnit`` = scene unit scale times the
  armature object's (uniform) scale, ``upAxis`` Z; the core's world is the armature's object
  space. Mesh points are carried into the skeleton's space through ``geomBindTransform``.
"""

from __future__ import annotations

import json
import math

import bpy

from .usd_util import pxr

EULER_MODES = ("XYZ", "XZY", "YXZ", "YZX", "ZXY", "ZYX")
ROOT_MODE = "ZYX"
ROOT_DOFS = ("root_tx", "root_ty", "root_tz", "root_rx", "root_ry", "root_rz")
DEFAULT_ROTATION_LIMIT = math.pi
ROOT_ROTATION_LIMIT = 2.0 * math.pi
ROOT_TRANSLATION_LIMIT_M = 2.0
ROOT_LOCK_EPS = 1e-6
AXES = "xyz"
SPEC_VERSION = 1


class RigExportError(RuntimeError):
    """The armature cannot be exported as a Hand Retarget rig (the message says why)."""


# ---- finding things ----------------------------------------------------------------------------
def skinned_mesh(arm: bpy.types.Object, prefer=()):
    """The mesh object deformed by ``arm`` through an Armature modifier (a selected one first)."""
    found = [o for o in bpy.data.objects if o.type == 'MESH'
             and any(m.type == 'ARMATURE' and m.object == arm for m in o.modifiers)]
    for o in prefer:
        if o in found:
            return o
    children = [o for o in found if o.parent == arm]
    return (children or found or [None])[0]


def export_bones(arm: bpy.types.Object, only_deform: bool = True):
    """The bones that become skeleton joints, parents first, and the root bone."""
    bones = [b for b in arm.data.bones if b.use_deform or not only_deform]
    names = {b.name for b in bones}
    roots = [b for b in bones if b.parent is None or b.parent.name not in names]
    if len(roots) != 1:
        raise RigExportError(
            f"the armature's {'deform ' if only_deform else ''}bones must form one tree, found "
            f"{len(roots)} roots: {', '.join(b.name for b in roots[:5])} (use Add Root Bone)")
    stray = [b for b in roots if b.parent is not None]
    if stray:
        raise RigExportError(f"deform bone {stray[0].name!r} hangs under the non-deform bone "
                             f"{stray[0].parent.name!r}; make that bone deform")
    return bones, roots[0]


def root_is_free(root_bone, tol: float = 1e-5) -> bool:
    """Whether the root bone's rest matrix is the identity (what the core's root expects)."""
    m = root_bone.matrix_local
    return all(abs(m[i][j] - (1.0 if i == j else 0.0)) <= tol for i in range(4) for j in range(4))


def bone_dof_settings(arm: bpy.types.Object, bones) -> list[str]:
    """Names of the bones that say something about their DOFs: a rotation lock, an enabled
    Limit Rotation constraint, or ``hr_min_*`` / ``hr_max_*`` custom properties."""
    out = []
    for bone in bones:
        pb = arm.pose.bones[bone.name]
        keys = [k for h in (pb, bone) for k in h.keys() if k.startswith(("hr_min_", "hr_max_"))]
        if any(pb.lock_rotation) or keys or any(
                any(getattr(c, f"use_limit_{a}") for a in AXES) for c in _active_constraints(pb, 'LIMIT_ROTATION')):
            out.append(bone.name)
    return out


def resolve_dof_mode(arm: bpy.types.Object, bones, root_bone) -> tuple[str, list[str]]:
    """('HAND_MODEL' | 'CHANNELS', warnings) for the armature's ``dof_mode``. Automatic takes
    the bone channels when the root bone rests at the armature origin and bones carry DOF
    settings, else the hand model (saying so when bone settings are then left unused)."""
    mode = arm.hand_retarget.dof_mode
    if mode == 'CHANNELS':
        if not root_is_free(root_bone):
            raise RigExportError(
                f"DOFs from bone channels need the root bone {root_bone.name!r} at the armature origin with "
                "identity rest orientation (use Add Root Bone), or choose DOFs: Hand model, which takes the "
                "armature as it is")
        return mode, []
    if mode == 'HAND_MODEL':
        return mode, []
    settings = bone_dof_settings(arm, bones)
    if settings and root_is_free(root_bone):
        return 'CHANNELS', []
    warnings = []
    if settings:
        warnings.append(f"{len(settings)} bones carry rotation locks or limits (e.g. {settings[0]!r}) but the root "
                        f"bone {root_bone.name!r} is not at the armature origin: the DOFs come from the hand model "
                        "and those settings are not used (Add Root Bone and choose DOFs: Bone channels to use them)")
    return 'HAND_MODEL', warnings


def limits_text(arm: bpy.types.Object) -> str:
    """The limits the animator edited in the panel as the core's limits TOML (degrees for
    rotations, metres for translations; by joint), '' when none was edited."""
    by_joint = {}
    for item in arm.hand_retarget.dof_limits:
        if item.edited:
            by_joint.setdefault(item.joint, []).append(item)
    lines = []
    for joint, items in by_joint.items():
        lines.append(f"[{json.dumps(joint)}]")
        for item in items:
            scale = 180.0 / math.pi if item.kind == "rotate" else 1.0
            lines.append(f"{json.dumps(item.name)} = [{item.lower * scale!r}, {item.upper * scale!r}]")
    return "\n".join(lines) + ("\n" if lines else "")


def meters_per_unit(context, arm: bpy.types.Object) -> float:
    """Metres per armature-space unit: scene unit scale times the armature's uniform scale."""
    scale = arm.matrix_world.to_scale()
    if max(scale) - min(scale) > 1e-6 * max(abs(s) for s in scale):
        raise RigExportError(f"the armature object {arm.name!r} has a non-uniform scale {tuple(scale)}; "
                             "apply the scale first")
    unit = context.scene.unit_settings
    length = unit.scale_length if unit.system != 'NONE' else 1.0
    return float(length * scale[0])


# ---- the DOF spec ------------------------------------------------------------------------------
def _custom(holders, key):
    for h in holders:
        try:
            if key in h:
                return float(h[key])
        except (TypeError, ValueError):
            raise RigExportError(f"custom property {key!r} of {h.name!r} is not a number") from None
    return None


def _active_constraints(pb, kind):
    return [c for c in pb.constraints if c.type == kind and not c.mute and c.influence > 0.0]


def _rotation_limits(pb, axis: str, default: float):
    for c in _active_constraints(pb, 'LIMIT_ROTATION'):
        if getattr(c, f"use_limit_{axis}"):
            return float(getattr(c, f"min_{axis}")), float(getattr(c, f"max_{axis}")), "Limit Rotation"
    lo, hi = _custom((pb, pb.bone), f"hr_min_{axis}"), _custom((pb, pb.bone), f"hr_max_{axis}")
    if lo is not None or hi is not None:
        return (math.radians(lo) if lo is not None else -default,
                math.radians(hi) if hi is not None else default, "custom property")
    return -default, default, "default"


def _translation_limits(pb, axis: str, default: float):
    lo, hi, src = -default, default, "default"
    for c in _active_constraints(pb, 'LIMIT_LOCATION'):
        if getattr(c, f"use_min_{axis}"):
            lo, src = float(getattr(c, f"min_{axis}")), "Limit Location"
        if getattr(c, f"use_max_{axis}"):
            hi, src = float(getattr(c, f"max_{axis}")), "Limit Location"
        if src != "default":
            return lo, hi, src
    clo, chi = _custom((pb, pb.bone), f"hr_min_t{axis}"), _custom((pb, pb.bone), f"hr_max_t{axis}")
    if clo is not None or chi is not None:
        return (clo if clo is not None else lo), (chi if chi is not None else hi), "custom property"
    return lo, hi, src


def euler_mode(pb, is_root: bool) -> str:
    """The Euler mode the bone is keyed in: ZYX for the root, else its own Euler mode (XYZ
    when it is in a quaternion / axis-angle mode)."""
    if is_root:
        return ROOT_MODE
    return pb.rotation_mode if pb.rotation_mode in EULER_MODES else "XYZ"


def dof_spec(arm: bpy.types.Object, bones, root_bone, mpu: float) -> list[dict]:
    """One dict per DOF in skeleton-bone order: name, bone, kind ("rotate"/"translate"),
    axis (0/1/2), channel ("rotation_euler"/"location"), lower, upper, rest (radians / armature
    units), source of the limits."""
    dofs = []
    for bone in bones:
        pb = arm.pose.bones[bone.name]
        is_root = bone == root_bone
        if is_root:
            for i, axis in enumerate(AXES):
                lo, hi, src = _translation_limits(pb, axis, ROOT_TRANSLATION_LIMIT_M / mpu)
                if pb.lock_location[i]:
                    lo, hi, src = -ROOT_LOCK_EPS, ROOT_LOCK_EPS, "locked"
                dofs.append(dict(name=f"root_t{axis}", bone=bone.name, kind="translate", axis=i,
                                 channel="location", lower=lo, upper=hi, source=src))
        mode = euler_mode(pb, is_root)
        for letter in reversed(mode):  # Euler "ABC" is R_C @ R_B @ R_A: the core lists C, B, A
            i = AXES.index(letter.lower())
            axis = AXES[i]
            if pb.lock_rotation[i] and not is_root:
                continue
            lo, hi, src = _rotation_limits(pb, axis, ROOT_ROTATION_LIMIT if is_root else DEFAULT_ROTATION_LIMIT)
            if is_root and pb.lock_rotation[i]:
                lo, hi, src = -ROOT_LOCK_EPS, ROOT_LOCK_EPS, "locked"
            name = f"root_r{axis}" if is_root else f"{bone.name}_r{axis}"
            dofs.append(dict(name=name, bone=bone.name, kind="rotate", axis=i, channel="rotation_euler",
                             lower=lo, upper=hi, source=src))
    seen = set()
    for d in dofs:
        if d["name"] in seen:
            raise RigExportError(f"two DOFs are named {d['name']!r} (rename the bone)")
        seen.add(d["name"])
        if not d["lower"] < d["upper"]:
            raise RigExportError(f"DOF {d['name']}: lower limit {d['lower']:g} is not below the upper "
                                 f"limit {d['upper']:g} ({d['source']})")
        d["rest"] = min(max(0.0, d["lower"]), d["upper"])
    if [d["name"] for d in dofs[:6]] != list(ROOT_DOFS):
        raise RigExportError("internal: the root DOFs must come first")
    return dofs


def core_triangles(mesh: bpy.types.Mesh):
    """The triangles the core makes of this mesh (fan per polygon, in polygon order: polygon p
    with corners c0..c(n-1) gives (c0, ck, ck+1)), as lists of vertex ids; the core's face ids
    index this list."""
    tris = []
    for poly in mesh.polygons:
        vs = list(poly.vertices)
        for k in range(1, len(vs) - 1):
            tris.append((vs[0], vs[k], vs[k + 1]))
    return tris


# ---- export ------------------------------------------------------------------------------------
def _usd_export(filepath: str, **options):
    """wm.usd_export with the options this Blender knows (4.2 lacks some of 5.0's)."""
    known = {p.identifier for p in bpy.ops.wm.usd_export.get_rna_type().properties}
    kwargs = {k: v for k, v in options.items() if k in known}
    result = bpy.ops.wm.usd_export(filepath=filepath, **kwargs)
    if 'FINISHED' not in result:
        raise RigExportError(f"Blender's USD export did not finish: {result}")


def export_rig(context, arm: bpy.types.Object, mesh_obj: bpy.types.Object, filepath: str,
               *, only_deform: bool = True) -> dict:
    """Write ``arm`` + ``mesh_obj`` as a Hand Retarget rig USD at ``filepath``. Returns
    {rig_name, meters_per_unit, dofs, joints, vertices, faces}."""
    if arm is None or arm.type != 'ARMATURE':
        raise RigExportError("select an armature")
    if mesh_obj is None:
        raise RigExportError(f"no mesh is deformed by {arm.name!r} (an Armature modifier pointing to it)")
    bones, root = export_bones(arm, only_deform)
    mode, mode_warnings = resolve_dof_mode(arm, bones, root)
    if mode == 'CHANNELS':
        mpu = meters_per_unit(context, arm)
        dofs = dof_spec(arm, bones, root, mpu)
    else:
        meters_per_unit(context, arm)  # the same checks (a uniform scale); the Xform carries the scale
        unit = context.scene.unit_settings
        mpu = float(unit.scale_length if unit.system != 'NONE' else 1.0)
        dofs = None

    # export at the rest pose, only these two objects; restore the user's state afterwards
    view_layer = context.view_layer
    selected = [o for o in view_layer.objects if o.select_get()]
    active = view_layer.objects.active
    pose_position = arm.data.pose_position
    if context.mode != 'OBJECT':
        bpy.ops.object.mode_set(mode='OBJECT')
    try:
        arm.data.pose_position = 'REST'
        for o in selected:
            o.select_set(False)
        arm.select_set(True)
        mesh_obj.select_set(True)
        view_layer.objects.active = arm
        _usd_export(filepath, selected_objects_only=True, export_armatures=True, only_deform_bones=only_deform,
                    export_animation=False, export_materials=False, export_custom_properties=False,
                    export_uvmaps=False, export_normals=False, export_shapekeys=False, export_hair=False,
                    export_subdivision='IGNORE', convert_orientation=False, convert_scene_units='METERS',
                    triangulate_meshes=False, evaluation_mode='VIEWPORT', root_prim_path="/root",
                    export_lights=False, export_cameras=False, export_curves=False, export_points=False,
                    export_volumes=False)
    finally:
        arm.data.pose_position = pose_position
        for o in view_layer.objects:
            o.select_set(o in selected)
        view_layer.objects.active = active
    info = finish_export(filepath, arm, mesh_obj, bones, dofs, mpu, limits_text(arm) if dofs is None else "")
    info["dof_mode"] = mode
    info["warnings"] = mode_warnings + export_warnings(arm, mesh_obj, dofs)
    return info


def finish_export(filepath: str, arm, mesh_obj, bones, dofs, mpu: float, limits: str = "") -> dict:
    """Post-process the exported file with pxr: bone names, units, the mesh's transform into
    skeleton space, checks that the core will see Blender's topology, and the DOF spec on the
    Skeleton (``dofs``; None: plain UsdSkel, with the edited ``limits`` TOML when given)."""
    p = pxr()
    Usd, UsdGeom, UsdSkel, Sdf, Gf, Vt, Tf = p.Usd, p.UsdGeom, p.UsdSkel, p.Sdf, p.Gf, p.Vt, p.Tf
    cached = Sdf.Layer.Find(filepath)
    if cached is not None:
        cached.Reload()  # the exporter has just replaced the file; a held layer would be stale
    stage = Usd.Stage.Open(filepath)
    skels = [prim for prim in stage.Traverse() if prim.IsA(UsdSkel.Skeleton)]
    if len(skels) != 1:
        raise RigExportError(f"the export holds {len(skels)} skeletons, expected 1")
    skel_prim = skels[0]
    skel = UsdSkel.Skeleton(skel_prim)
    tokens = [str(t) for t in skel.GetJointsAttr().Get() or []]
    by_token = {}
    for b in bones:
        by_token.setdefault(Tf.MakeValidIdentifier(b.name), []).append(b.name)
    names = []
    for t in tokens:
        leaf = t.rsplit("/", 1)[-1]
        cands = by_token.get(leaf, [])
        if len(cands) != 1:
            raise RigExportError(f"cannot tell which bone the exported joint {t!r} is ({cands or 'none'})")
        names.append(cands[0])
    index = {n: i for i, n in enumerate(names)}
    if dofs is not None:
        missing = [d["name"] for d in dofs if d["bone"] not in index]
        if missing:
            raise RigExportError(f"DOFs of bones that were not exported: {missing[:5]}")
        root_name = dofs[0]["bone"]
        dofs = sorted(dofs, key=lambda d: index[d["bone"]])  # stable: a joint's order is kept
    else:
        root_name = None

    # the skinned surface: carried into the skeleton's space (the core ignores prim transforms)
    skel_w = UsdGeom.Xformable(skel_prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default())
    meshes = [prim for prim in stage.Traverse() if prim.IsA(UsdGeom.Mesh)
              and UsdSkel.BindingAPI(prim).GetInheritedSkeleton()
              and UsdSkel.BindingAPI(prim).GetInheritedSkeleton().GetPath() == skel_prim.GetPath()]
    if len(meshes) != 1:
        raise RigExportError(f"the export holds {len(meshes)} meshes bound to the skeleton, expected 1")
    mesh_prim = meshes[0]
    mesh_w = UsdGeom.Xformable(mesh_prim).ComputeLocalToWorldTransform(Usd.TimeCode.Default())
    rel = mesh_w * skel_w.GetInverse()  # row vectors: p_skel = p_mesh * mesh_w * skel_w^-1
    binding = UsdSkel.BindingAPI(mesh_prim)
    binding.CreateGeomBindTransformAttr().Set(Gf.Matrix4d(rel))
    mesh_prim.CreateAttribute("handretarget:role", Sdf.ValueTypeNames.Token, custom=True).Set("surface")
    geom = UsdGeom.Mesh(mesh_prim)
    me = mesh_obj.data
    counts = list(geom.GetFaceVertexCountsAttr().Get() or [])
    indices = list(geom.GetFaceVertexIndicesAttr().Get() or [])
    n_points = len(geom.GetPointsAttr().Get() or [])
    if n_points != len(me.vertices) or counts != [len(poly.vertices) for poly in me.polygons] \
            or indices != [v for poly in me.polygons for v in poly.vertices]:
        raise RigExportError(
            f"the exported mesh ({n_points} points, {len(counts)} faces) differs from {mesh_obj.name!r} "
            f"({len(me.vertices)} vertices, {len(me.polygons)} faces): apply or disable modifiers other "
            "than the Armature, so that vertex ids (annotations) stay valid")
    orient = geom.GetOrientationAttr().Get()
    if orient == UsdGeom.Tokens.leftHanded:
        raise RigExportError("the exported mesh is left-handed; the annotation face ids would not match")
    _normalise_weights(binding, mesh_obj, Vt)

    UsdGeom.SetStageMetersPerUnit(stage, mpu)
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.z)
    T = Sdf.ValueTypeNames

    def put(short, type_name, value):
        skel_prim.CreateAttribute(f"handretarget:{short}", type_name, custom=True).Set(value)

    put("rigName", T.String, arm.name)
    put("jointNames", T.StringArray, Vt.StringArray(names))  # the bones' own names (tokens are identifiers)
    info = {"rig_name": arm.name, "meters_per_unit": mpu, "joints": names, "vertices": len(me.vertices),
            "faces": len(core_triangles(me))}
    if dofs is None:
        put("metadata", T.String, json.dumps({"blender": {"armature": arm.name, "mesh": mesh_obj.name,
                                                          "dof_mode": "HAND_MODEL"}}, sort_keys=True))
        if limits:
            put("dofLimits", T.String, limits)
        stage.GetRootLayer().Save()
        return info | {"dofs": None}
    axes = [(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)]
    modes = {b.name: euler_mode(arm.pose.bones[b.name], b.name == root_name) for b in bones}
    metadata = {"blender": {
        "armature": arm.name, "mesh": mesh_obj.name, "meters_per_unit": mpu, "dof_mode": "CHANNELS",
        "rotation_modes": modes,
        "channels": {d["name"]: [d["bone"], d["channel"], d["axis"]] for d in dofs},
        "limit_sources": {d["name"]: d["source"] for d in dofs},
    }}
    put("specVersion", T.Int, SPEC_VERSION)
    put("metadata", T.String, json.dumps(metadata, sort_keys=True))
    put("dofNames", T.StringArray, Vt.StringArray([d["name"] for d in dofs]))
    put("dofJoints", T.IntArray, Vt.IntArray([index[d["bone"]] for d in dofs]))
    put("dofKinds", T.TokenArray, Vt.TokenArray([d["kind"] for d in dofs]))
    put("dofAxes", T.Double3Array, Vt.Vec3dArray([Gf.Vec3d(*axes[d["axis"]]) for d in dofs]))
    put("dofLower", T.DoubleArray, Vt.DoubleArray([float(d["lower"]) for d in dofs]))
    put("dofUpper", T.DoubleArray, Vt.DoubleArray([float(d["upper"]) for d in dofs]))
    put("dofRest", T.DoubleArray, Vt.DoubleArray([float(d["rest"]) for d in dofs]))
    stage.GetRootLayer().Save()
    return info | {"dofs": [d["name"] for d in dofs]}


def _normalise_weights(binding, mesh_obj, Vt):
    """Scale each vertex's skin weights to sum 1, as Blender's Armature modifier does when it
    deforms (the core requires sums of 1); a vertex without bone weight is an error, since
    Blender leaves it with the object while the core would have to give it a bone."""
    pv = binding.GetJointWeightsPrimvar()
    k = pv.GetElementSize()
    w = list(pv.Get() or [])
    unweighted = []
    for v in range(len(w) // k):
        row = w[v * k:(v + 1) * k]
        total = sum(row)
        if total <= 0.0:
            unweighted.append(v)
        elif abs(total - 1.0) > 1e-7:
            w[v * k:(v + 1) * k] = [x / total for x in row]
    if unweighted:
        raise RigExportError(f"{len(unweighted)} vertices of {mesh_obj.name!r} have no bone weight (e.g. "
                             f"{unweighted[:5]}); weight every vertex to a deform bone")
    pv.Set(Vt.FloatArray(w))


def export_warnings(arm, mesh_obj, dofs=None) -> list[str]:
    """Things the core will see differently from Blender (reported, not fatal)."""
    out = []
    free = [d["name"] for d in dofs or () if d["source"] == "default" and d["kind"] == "rotate"
            and not d["name"].startswith("root_")]
    if free:
        out.append(f"{len(free)} bone rotations have no limits (e.g. {free[0]}) and turn +-180 degrees: "
                   "limit or lock them, or choose DOFs: Hand model for anatomical limits")
    for m in mesh_obj.modifiers:
        if m.type == 'ARMATURE' and m.object == arm and m.use_deform_preserve_volume:
            out.append("the Armature modifier preserves volume (dual quaternions); the service skins linearly")
    for pb in arm.pose.bones:
        for c in _active_constraints(pb, 'LIMIT_ROTATION'):
            if c.owner_space != 'LOCAL':
                out.append(f"bone {pb.name}: its Limit Rotation is not in Local Space; limits read as local")
    return out


def add_root_bone(context, arm: bpy.types.Object, name: str = "root") -> str:
    """Insert a bone at the armature origin with identity rest (pointing +Y, roll 0) above the
    current root bones; returns its name."""
    view_layer = context.view_layer
    active = view_layer.objects.active
    mode = context.mode
    if mode != 'OBJECT':
        bpy.ops.object.mode_set(mode='OBJECT')
    view_layer.objects.active = arm
    bpy.ops.object.mode_set(mode='EDIT')
    try:
        ebones = arm.data.edit_bones
        roots = [b for b in ebones if b.parent is None]
        length = max([b.length for b in ebones] + [0.01])
        new = ebones.new(name)
        new.head, new.tail, new.roll = (0.0, 0.0, 0.0), (0.0, length, 0.0), 0.0
        new.use_deform = True
        for b in roots:
            b.use_connect = False
            b.parent = new
        name = new.name
    finally:
        bpy.ops.object.mode_set(mode='OBJECT')
        view_layer.objects.active = active
    arm.pose.bones[name].rotation_mode = ROOT_MODE  # how the service's root DOFs compose
    return name
