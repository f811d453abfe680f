"""Result import: per-DOF cubic B-splines (result.json) -> F-curves on the animator's armature,
and the manipulated object from animation.usda.

F-curves: one keyframe per spline breakpoint with FREE Bezier handles (``curves.bspline_to_keyframes``),
so each F-curve equals its DOF's B-spline (and the USD layer's Ts spline) up to float32
keyframe storage. DOF -> channel (see rig_export): ``root_t*`` -> the root bone's
``location``, ``root_r*`` -> its ``rotation_euler`` (mode ZYX), ``<bone>_r<axis>`` -> that
bone's ``rotation_euler``; each bone's rotation mode is set to an Euler mode whose product
order is the DOFs' order. Translations are metres in the result and armature units in Blender
(divided by metres-per-unit). Time: clip frame k (t = k / fps seconds) is Blender frame
``start_frame + k``; the scene's frame rate and range are set from the clip.

The object: read with pxr from the layer (``/Object``: mesh in its own frame, a per-frame
transform in the core's world = the armature's object space in metres) and built as a mesh
object parented to the armature, keyed once per frame. That is simpler and more exact than
``wm.usd_import``, which would also import a second armature (the layer sublayers the rig).
"""

from __future__ import annotations

import bpy
from mathutils import Matrix

from . import curves as curve_math
from .rig_export import AXES, EULER_MODES, ROOT_DOFS, ROOT_MODE
from .usd_util import pxr

_KEY = bpy.types.Keyframe.bl_rna.properties
BEZIER = _KEY["interpolation"].enum_items["BEZIER"].value
LINEAR = _KEY["interpolation"].enum_items["LINEAR"].value
FREE = _KEY["handle_left_type"].enum_items["FREE"].value


class ImportError_(RuntimeError):
    """The result cannot be put on this armature (the message says why)."""


def dof_channel(name: str, root_bone: str):
    """(bone, "location" | "rotation_euler", axis index) of a DOF name, or None."""
    if name in ROOT_DOFS:
        axis = AXES.index(name[-1])
        return root_bone, ("location" if name[-2] == "t" else "rotation_euler"), axis
    base, _, suffix = name.rpartition("_")
    if base and len(suffix) == 2 and suffix[0] == "r" and suffix[1] in AXES:
        return base, "rotation_euler", AXES.index(suffix[1])
    return None


def euler_mode_for(axes_in_order: list[int], current: str) -> str | None:
    """An Euler mode whose matrix product order (the reverse of its letters) lists the given
    axes in this order; the bone's current mode when it fits."""
    want = [AXES[i].upper() for i in axes_in_order]
    fits = [m for m in EULER_MODES if [c for c in reversed(m) if c in want] == want]
    if not fits:
        return None
    return current if current in fits else fits[0]


# ---- actions (Blender 5 layered actions; the legacy API before 4.4) ----------------------------
class Channels:
    """F-curves of a new action assigned to ``obj`` (through a slot where Blender has slots)."""

    def __init__(self, obj, name: str):
        self.action = bpy.data.actions.new(name)
        ad = obj.animation_data_create()
        self.groups = {}
        if hasattr(self.action, "slots"):
            from bpy_extras import anim_utils

            slot = self.action.slots.new(id_type='OBJECT', name=obj.name)
            ad.action = self.action
            ad.action_slot = slot  # after .action: assigning the action resets the slot
            self.bag = anim_utils.action_ensure_channelbag_for_slot(self.action, slot)
        else:
            ad.action = self.action
            self.bag = None

    def new(self, data_path: str, index: int, group: str):
        if self.bag is None:
            return self.action.fcurves.new(data_path, index=index, action_group=group)
        fc = self.bag.fcurves.new(data_path, index=index)
        grp = self.groups.get(group)
        if grp is None:
            grp = self.groups[group] = self.bag.groups.new(group)
        fc.group = grp
        return fc


def set_bezier_keys(fc, keys, scale: float = 1.0):
    """Key ``fc`` with curves.Keyframe tuples (values and handle heights times ``scale``)."""
    n = len(keys)
    kps = fc.keyframe_points
    kps.add(n)
    kps.foreach_set("co", [x for k in keys for x in (k.frame, k.value * scale)])
    kps.foreach_set("handle_left", [x for k in keys for x in (k.handle_left[0], k.handle_left[1] * scale)])
    kps.foreach_set("handle_right", [x for k in keys for x in (k.handle_right[0], k.handle_right[1] * scale)])
    kps.foreach_set("interpolation", [BEZIER] * n)
    kps.foreach_set("handle_left_type", [FREE] * n)
    kps.foreach_set("handle_right_type", [FREE] * n)
    fc.extrapolation = keys.extrapolation
    fc.update()  # sorts; FREE handles stay where they were put


def set_linear_keys(fc, frames, values):
    n = len(frames)
    kps = fc.keyframe_points
    kps.add(n)
    kps.foreach_set("co", [x for f, v in zip(frames, values) for x in (f, v)])
    kps.foreach_set("interpolation", [LINEAR] * n)
    fc.extrapolation = 'CONSTANT'
    fc.update()


# ---- the armature ---------------------------------------------------------------------------------
def root_bone_name(arm) -> str:
    roots = [b for b in arm.data.bones if b.parent is None and b.use_deform] or \
            [b for b in arm.data.bones if b.parent is None]
    if len(roots) != 1:
        raise ImportError_(f"the armature {arm.name!r} must have one root bone, found {len(roots)}")
    return roots[0].name


def import_curves(context, arm, doc, *, mpu: float = 1.0, start_frame: int = 1, baked: bool = False,
                  action_name: str | None = None, scene=None) -> dict:
    """Animate ``arm`` with the DOF curves of a result.json document; set the frame rate and
    range of ``scene`` (default: the context's). Returns {"action", "fcurves", "skipped": [DOF
    names], "fps", "frames"}."""
    dof_curves = curve_math.curves_from_result_json(doc)
    fps = float(doc["fps"])
    n_frames = len(doc.get("times") or [])
    if not fps > 0 or n_frames < 1:
        raise ImportError_("the result has no frames")
    root = root_bone_name(arm)
    channels, skipped = [], []
    for name in doc["dof_names"]:
        ch = dof_channel(name, root)
        if ch is None or ch[0] not in arm.pose.bones:
            skipped.append(name)
        else:
            channels.append((name, *ch))
    if not channels:
        raise ImportError_(f"no DOF of the result names a bone of {arm.name!r} (DOFs like 'index1_rx' "
                           "come from a rig exported by this add-on)")
    # rotation modes: the DOF order of each bone decides it
    order = {}
    for name, bone, channel, axis in channels:
        if channel == "rotation_euler":
            order.setdefault(bone, []).append(axis)
    for bone, axes in order.items():
        pb = arm.pose.bones[bone]
        mode = ROOT_MODE if bone == root else euler_mode_for(axes, pb.rotation_mode)
        if mode is None or (bone == root and euler_mode_for(axes, ROOT_MODE) != ROOT_MODE):
            raise ImportError_(f"bone {bone!r}: its DOF order {[AXES[a] for a in axes]} fits no Euler mode")
        pb.rotation_mode = mode
    # a fresh action: the animator's existing ones are left alone
    chans = Channels(arm, action_name or f"HR_{arm.name}")
    frames = [start_frame + k for k in range(n_frames)]
    for name, bone, channel, axis in channels:
        c = dof_curves[name]
        scale = 1.0 / mpu if channel == "location" else 1.0
        path = f'pose.bones["{bpy.utils.escape_identifier(bone)}"].{channel}'
        fc = chans.new(path, axis, bone)
        if baked:
            values = [curve_math.bspline_eval(c.knots, c.coeffs, min(max(k / fps, c.knots[0]), c.knots[-1]),
                                              degree=c.degree) * scale for k in range(n_frames)]
            set_linear_keys(fc, frames, values)
        else:
            keys = curve_math.bspline_to_keyframes(c.knots, c.coeffs, fps=fps, start_frame=start_frame,
                                                   degree=c.degree, extrapolation=c.extrapolation)
            set_bezier_keys(fc, keys, scale)
    set_scene_time(scene or context.scene, fps, start_frame, n_frames)
    return {"action": chans.action.name, "fcurves": len(channels), "skipped": skipped, "fps": fps,
            "frames": n_frames}


def set_scene_time(scene, fps: float, start_frame: int, n_frames: int):
    """Scene frame rate (integer fps over fps_base) and range from the clip."""
    whole = max(1, round(fps))
    scene.render.fps = whole
    scene.render.fps_base = whole / fps
    scene.frame_start = start_frame
    scene.frame_end = start_frame + n_frames - 1
    scene.frame_set(start_frame)


# ---- the object -----------------------------------------------------------------------------------
def import_object(context, arm, usd_path: str, *, mpu: float = 1.0, start_frame: int = 1, name: str = "HR_Object",
                  scene=None):
    """The animated object of an animation layer as a mesh object parented to ``arm``; None
    when the layer has no object."""
    p = pxr()
    Usd, UsdGeom = p.Usd, p.UsdGeom
    stage = Usd.Stage.Open(usd_path)
    if stage is None:
        raise ImportError_(f"cannot open {usd_path}")
    prim, mesh_prim = stage.GetPrimAtPath("/Object"), stage.GetPrimAtPath("/Object/Mesh")
    if not prim or not mesh_prim:
        return None
    geom = UsdGeom.Mesh(mesh_prim)
    points = [tuple(v) for v in geom.GetPointsAttr().Get()]
    counts, indices = list(geom.GetFaceVertexCountsAttr().Get()), list(geom.GetFaceVertexIndicesAttr().Get())
    faces, i = [], 0
    for n in counts:
        faces.append(indices[i:i + n])
        i += n
    me = bpy.data.meshes.new(name)
    me.from_pydata(points, [], faces)
    me.update()
    obj = bpy.data.objects.new(name, me)
    (arm.users_collection[0] if arm.users_collection else (scene or context.scene).collection).objects.link(obj)
    obj.parent = arm
    obj.matrix_parent_inverse = Matrix.Identity(4)
    obj.rotation_mode = 'QUATERNION'

    xf = UsdGeom.Xformable(prim)
    times = sorted({t for op in xf.GetOrderedXformOps() for t in op.GetTimeSamples()})
    to_units = Matrix.Scale(1.0 / mpu, 4)
    samples, prev = [], None
    for t in times:
        m = xf.GetLocalTransformation(Usd.TimeCode(t))
        world = Matrix([[m[c][r] for c in range(4)] for r in range(4)])  # USD rows -> column vectors
        loc, rot, scale = (to_units @ world).decompose()
        if prev is not None and prev.dot(rot) < 0.0:
            rot.negate()  # the shorter way between frames
        prev = rot
        samples.append((start_frame + t, loc, rot, scale))
    if samples:
        chans = Channels(obj, f"HR_{name}")
        frames = [s[0] for s in samples]
        for path, k, n in (("location", 1, 3), ("rotation_quaternion", 2, 4), ("scale", 3, 3)):
            for axis in range(n):
                fc = chans.new(path, axis, "Object Transforms")
                set_linear_keys(fc, frames, [s[k][axis] for s in samples])
    return obj
