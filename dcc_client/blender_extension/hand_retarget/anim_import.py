"""Result import: the retargeted motion on the animator's own armature, and the manipulated
object (and, for a hand inside a body, the wrist target) from animation.usda.

Bone-channel rigs (rig_export, DOF mode "Bone channels"): per-DOF cubic B-splines (result.json)
-> F-curves with one keyframe per spline breakpoint and FREE Bezier handles
(``curves.bspline_to_keyframes``), so each F-curve equals its DOF's B-spline (and the USD
layer's Ts spline) up to float32 keyframe storage. DOF -> channel: ``root_t*`` -> the root
bone's ``location``, ``root_r*`` -> its ``rotation_euler`` (mode ZYX), ``<bone>_r<axis>`` ->
that bone's ``rotation_euler``; each bone's rotation mode is set to an Euler mode whose product
order is the DOFs' order. Translations are metres in the result and armature units in Blender
(divided by metres-per-unit).

Hand-model rigs (DOFs by role about axes of the hand, not of the bones): the layer's baked
SkelAnimation, which keys the armature's own joint tokens, sampled at every scene frame
(UsdSkel interpolates between the clip's frames) and keyed on the bones' own channels
(location, and rotation in each bone's own rotation mode): ``matrix_basis = rest_local^-1 @
animated_local``.

Time: clip second t lands on scene frame ``start_frame + t * scene_fps``; the scene keeps its
own frame rate (a 24 fps scene stays 24 fps) unless the user asks for the clip's
(``use_clip_fps``). Re-import (``import_mode``): "REPLACE" removes the previous result's action
and objects; "NLA" keeps the previous action as an NLA strip. An action the animator made is
never removed: it is kept as an NLA strip.

The object: read with pxr from the layer (``/Object``: mesh in its own frame, a per-frame
transform in the layer's world and units) and built as a mesh object parented to the
armature. That is simpler and more exact than ``wm.usd_import``, which would also import a
second armature (the layer sublayers the rig).
"""

from __future__ import annotations

import math

import bpy
from mathutils import Matrix, Quaternion

from . import curves as curve_math
from .rig_export import AXES, EULER_MODES, ROOT_DOFS, ROOT_MODE
from .usd_util import pxr

WRIST_TARGET = "HandRetarget_wristTarget"  # as retarget_core/export/usd_animation.py writes it

_KEY = bpy.types.Keyframe.bl_rna.properties
BEZIER = _KEY["interpolation"].enum_items["BEZIER"].value
LINEAR = _KEY["interpolation"].enum_items["LINEAR"].value
FREE = _KEY["handle_left_type"].enum_items["FREE"].value


class ImportError_(RuntimeError):
    """The result cannot be put on this armature (the message says why)."""


#: custom property on the actions and objects an import made (value: the job id)
RESULT_TAG = "hand_retarget_result"


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

    def __init__(self, obj, name: str, tag: str = ""):
        self.action = bpy.data.actions.new(name)
        self.action[RESULT_TAG] = tag or name
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


def clear_previous(obj, mode: str = 'REPLACE') -> None:
    """Before an import onto ``obj``: its current action leaves the active slot. A previous
    result (tagged) is removed with "REPLACE" and kept as an NLA strip with "NLA"; an action
    the animator made is always kept as an NLA strip."""
    ad = obj.animation_data
    prev = ad.action if ad is not None else None
    if prev is None:
        return
    ad.action = None
    if mode == 'REPLACE' and RESULT_TAG in prev:
        if prev.users == 0:
            bpy.data.actions.remove(prev)
        return
    track = ad.nla_tracks.new()
    track.name = prev.name
    strip = track.strips.new(prev.name, int(prev.frame_range[0]), prev)
    if hasattr(strip, "action_slot") and getattr(prev, "slots", None):
        strip.action_slot = prev.slots[0]


def scene_frame_rate(scene, clip_fps: float, use_clip_fps: bool) -> float:
    """Frames per second the result is timed into: the scene's own, or (``use_clip_fps``)
    the clip's, which the scene is then set to."""
    if use_clip_fps:
        whole = max(1, round(clip_fps))
        scene.render.fps = whole
        scene.render.fps_base = whole / clip_fps
    return scene.render.fps / scene.render.fps_base


def scene_frames(duration: float, scene_fps: float) -> int:
    """Number of scene frames from 0 to ``duration`` seconds inclusive (a float32-safe floor)."""
    return int(math.floor(duration * scene_fps + 1e-6)) + 1


def import_curves(context, arm, doc, *, mpu: float = 1.0, start_frame: float = 1, baked: bool = False,
                  action_name: str | None = None, scene=None, scene_fps: float | None = None,
                  tag: str = "") -> dict:
    """Animate ``arm`` with the DOF curves of a result.json document, timed at ``scene_fps``
    (default: the scene's), the clip's t = 0 at ``start_frame``; the scene's frame range is
    set to the result. Returns {"action", "fcurves", "skipped": [DOF names], "fps",
    "frames"} (fps and frames of the clip)."""
    scene = scene or context.scene
    dof_curves = curve_math.curves_from_result_json(doc)
    fps = float(doc["fps"])
    n_frames = len(doc.get("times") or [])
    if not fps > 0 or n_frames < 1:
        raise ImportError_("the result has no frames")
    scene_fps = scene_fps or scene.render.fps / scene.render.fps_base
    root = root_bone_name(arm)
    channels, skipped = [], []
    for name in doc["dof_names"]:
        ch = dof_channel(name, root)
        if ch is None or ch[0] not in arm.pose.bones:
            skipped.append(name)
        else:
            channels.append((name, *ch))
    if not channels:
        raise ImportError_(f"no DOF of the result names a bone channel of {arm.name!r} (DOFs like 'index1_rx' "
                           "come from a rig exported with DOFs: Bone channels; a hand-model rig imports "
                           "from its animation layer)")
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
    chans = Channels(arm, action_name or f"HR_{arm.name}", tag)
    duration = (n_frames - 1) / fps
    n_scene = scene_frames(duration, scene_fps)
    frames = [start_frame + k for k in range(n_scene)]
    for name, bone, channel, axis in channels:
        c = dof_curves[name]
        scale = 1.0 / mpu if channel == "location" else 1.0
        path = f'pose.bones["{bpy.utils.escape_identifier(bone)}"].{channel}'
        fc = chans.new(path, axis, bone)
        if baked:
            values = [curve_math.bspline_eval(c.knots, c.coeffs, min(max(k / scene_fps, c.knots[0]), c.knots[-1]),
                                              degree=c.degree) * scale for k in range(n_scene)]
            set_linear_keys(fc, frames, values)
        else:
            keys = curve_math.bspline_to_keyframes(c.knots, c.coeffs, fps=scene_fps, start_frame=start_frame,
                                                   degree=c.degree, extrapolation=c.extrapolation)
            set_bezier_keys(fc, keys, scale)
    set_scene_range(scene, start_frame, start_frame + duration * scene_fps)
    return {"action": chans.action.name, "fcurves": len(channels), "skipped": skipped, "fps": fps,
            "frames": n_frames}


def set_scene_range(scene, first: float, last: float):
    """The scene's frame range from the result's first to last frame (rounded outwards)."""
    scene.frame_start = int(math.floor(first + 1e-6))
    scene.frame_end = max(scene.frame_start, int(math.ceil(last - 1e-6)))
    scene.frame_set(scene.frame_start)


# ---- the baked SkelAnimation (hand-model rigs) ------------------------------------------------------
def _open_layer(usd_path: str):
    p = pxr()
    stage = p.Usd.Stage.Open(usd_path)
    if stage is None:
        raise ImportError_(f"cannot open {usd_path}")
    return p, stage


def _layer_times(stage):
    """(first time code, last time code, time codes per second) of a result layer."""
    return stage.GetStartTimeCode(), stage.GetEndTimeCode(), stage.GetTimeCodesPerSecond()


def subtree(arm, root: str) -> list[str]:
    """``root`` and every bone below it."""
    bone = arm.data.bones[root]
    return [bone.name] + [b.name for b in bone.children_recursive]


def import_skel_animation(context, arm, usd_path: str, *, start_frame: float = 1, scene=None,
                          scene_fps: float | None = None, bones=None, action_name: str | None = None,
                          tag: str = "") -> dict:
    """Key ``arm``'s own bones (``bones``, default all the animation names) from the layer's
    SkelAnimation at every scene frame; each bone keeps its rotation mode (a quaternion stays
    a quaternion, an Euler mode is kept continuous). Returns {"action", "fcurves", "bones",
    "fps", "frames"} (fps and frames of the clip)."""
    scene = scene or context.scene
    p, stage = _open_layer(usd_path)
    anims = [prim for prim in stage.Traverse() if prim.IsA(p.UsdSkel.Animation)]
    if len(anims) != 1:
        raise ImportError_(f"{usd_path}: expected one SkelAnimation, found {len(anims)}")
    query = p.UsdSkel.Cache().GetAnimQuery(p.UsdSkel.Animation(anims[0]))
    by_token = {}
    for b in arm.data.bones:
        by_token.setdefault(p.Tf.MakeValidIdentifier(b.name), []).append(b.name)
    names = []
    for t in query.GetJointOrder():
        cands = by_token.get(str(t).rsplit("/", 1)[-1], [])
        names.append(cands[0] if len(cands) == 1 else None)
    wanted = set(bones) if bones is not None else {n for n in names if n}
    keyed = [(j, n) for j, n in enumerate(names) if n in wanted]
    missing = sorted(wanted - {n for _, n in keyed})
    if missing or not keyed:
        raise ImportError_(f"the animation does not key the bones {missing[:5] or sorted(wanted)[:5]} of "
                           f"{arm.name!r}: was the rig exported from this armature?")
    first, last, tcps = _layer_times(stage)
    clip_frames = int(round(last - first)) + 1
    scene_fps = scene_fps or scene.render.fps / scene.render.fps_base
    duration = (last - first) / tcps
    n_scene = scene_frames(duration, scene_fps)
    rest = {}
    for _, name in keyed:
        bone = arm.data.bones[name]
        rest[name] = (bone.parent.matrix_local.inverted() @ bone.matrix_local if bone.parent
                      else bone.matrix_local.copy()).inverted()
    samples = {name: [] for _, name in keyed}
    for k in range(n_scene):
        code = first + min(k / scene_fps * tcps, last - first)
        local = query.ComputeJointLocalTransforms(p.Usd.TimeCode(code))
        for j, name in keyed:
            m = local[j]
            basis = rest[name] @ Matrix([[m[c][r] for c in range(4)] for r in range(4)])
            loc, rot, _ = basis.decompose()
            samples[name].append((loc, rot))
    chans = Channels(arm, action_name or f"HR_{arm.name}", tag)
    frames = [start_frame + k for k in range(n_scene)]
    count = 0
    for _, name in keyed:
        pb = arm.pose.bones[name]
        group = name
        path = f'pose.bones["{bpy.utils.escape_identifier(name)}"]'
        locs = [s[0] for s in samples[name]]
        if any((v - locs[0]).length > 1e-7 for v in locs) or locs[0].length > 1e-7:
            for axis in range(3):
                set_linear_keys(chans.new(f"{path}.location", axis, group), frames, [v[axis] for v in locs])
                count += 1
        if pb.rotation_mode == 'AXIS_ANGLE':
            pb.rotation_mode = 'QUATERNION'  # keyed as what it is; an axis-angle channel flips at pi
        rots, prev = [], None
        for _, q in samples[name]:
            q = Quaternion(q)
            if prev is not None and prev.dot(q) < 0.0:
                q.negate()  # the shorter way between frames
            rots.append(q)
            prev = q
        if pb.rotation_mode == 'QUATERNION':
            for axis in range(4):
                set_linear_keys(chans.new(f"{path}.rotation_quaternion", axis, group), frames, [q[axis] for q in rots])
                count += 1
        else:
            eulers, prev_e = [], None
            for q in rots:
                e = q.to_euler(pb.rotation_mode, prev_e) if prev_e is not None else q.to_euler(pb.rotation_mode)
                eulers.append(e)
                prev_e = e
            for axis in range(3):
                set_linear_keys(chans.new(f"{path}.rotation_euler", axis, group), frames, [e[axis] for e in eulers])
                count += 1
    set_scene_range(scene, start_frame, start_frame + duration * scene_fps)
    return {"action": chans.action.name, "fcurves": count, "bones": [n for _, n in keyed],
            "fps": tcps, "frames": clip_frames, "skipped": []}


# ---- the object -----------------------------------------------------------------------------------
def _rigid_samples(xf, first: float, last: float, tcps: float, scene_fps: float, to_arm: Matrix):
    """(loc, rot, scale) of an Xformable at every scene frame in armature space: the layer's
    per-frame transforms decomposed, rotations slerped between the clip frames around."""
    Usd = pxr().Usd

    def at(code):
        m = xf.GetLocalTransformation(Usd.TimeCode(code))
        return (to_arm @ Matrix([[m[c][r] for c in range(4)] for r in range(4)])).decompose()  # USD rows -> columns

    out, prev = [], None
    for k in range(scene_frames((last - first) / tcps, scene_fps)):
        code = first + min(k / scene_fps * tcps, last - first)
        lo = math.floor(code + 1e-9)
        loc, rot, scale = at(lo)
        if code - lo > 1e-9:
            loc1, rot1, scale1 = at(min(lo + 1, last))
            w = code - lo
            loc, rot, scale = loc.lerp(loc1, w), rot.slerp(rot1, w), scale.lerp(scale1, w)
        if prev is not None and prev.dot(rot) < 0.0:
            rot.negate()  # the shorter way between frames
        prev = rot
        out.append((loc, rot, scale))
    return out


def _key_transform(obj, samples, start_frame: float, tag: str):
    chans = Channels(obj, f"HR_{obj.name}", tag)
    frames = [start_frame + k for k in range(len(samples))]
    for path, k, n in (("location", 0, 3), ("rotation_quaternion", 1, 4), ("scale", 2, 3)):
        for axis in range(n):
            fc = chans.new(path, axis, "Object Transforms")
            set_linear_keys(fc, frames, [s[k][axis] for s in samples])


def layer_to_armature(arm, plain: bool) -> Matrix:
    """From the layer's world (its units) to ``arm``'s object space: the armature's inverse
    world matrix for a plain (hand-model) rig, whose file world is Blender's; the identity for
    a bone-channel rig, whose file is in armature space and units."""
    return arm.matrix_world.inverted() if plain else Matrix.Identity(4)


def remove_previous_objects(arm, prefix: str) -> None:
    """Objects of an earlier import onto ``arm`` (tagged, named ``prefix``...): removed."""
    for obj in [o for o in bpy.data.objects if o.parent == arm and RESULT_TAG in o and o.name.startswith(prefix)]:
        bpy.data.objects.remove(obj, do_unlink=True)


def import_object(context, arm, usd_path: str, *, start_frame: float = 1, name: str = "HR_Object",
                  scene=None, scene_fps: float | None = None, plain: bool = False, tag: str = ""):
    """The animated object of an animation layer as a mesh object parented to ``arm``, keyed
    at every scene frame; None when the layer has no object."""
    scene = scene or context.scene
    p, stage = _open_layer(usd_path)
    UsdGeom = p.UsdGeom
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
    obj = _new_child(context, arm, name, me, scene, tag)
    first, last, tcps = _layer_times(stage)
    fps = scene_fps or scene.render.fps / scene.render.fps_base
    _key_transform(obj, _rigid_samples(UsdGeom.Xformable(prim), first, last, tcps, fps,
                                       layer_to_armature(arm, plain)), start_frame, tag)
    return obj


def import_wrist_target(context, arm, usd_path: str, *, start_frame: float = 1, scene=None,
                        scene_fps: float | None = None, plain: bool = True, tag: str = ""):
    """The wrist's world motion of a hand cut from a body armature (the layer's
    ``/HandRetarget_wristTarget``) as a keyed Empty of that name parented to ``arm``, for the
    arm's IK to follow; None when the layer has none."""
    scene = scene or context.scene
    p, stage = _open_layer(usd_path)
    prim = stage.GetPrimAtPath(f"/{WRIST_TARGET}")
    if not prim:
        return None
    obj = _new_child(context, arm, WRIST_TARGET, None, scene, tag)
    obj.empty_display_type = 'ARROWS'
    obj.empty_display_size = max(0.02, max(arm.dimensions) * 0.05)
    first, last, tcps = _layer_times(stage)
    fps = scene_fps or scene.render.fps / scene.render.fps_base
    _key_transform(obj, _rigid_samples(p.UsdGeom.Xformable(prim), first, last, tcps, fps,
                                       layer_to_armature(arm, plain)), start_frame, tag)
    return obj


def _new_child(context, arm, name: str, data, scene, tag: str):
    obj = bpy.data.objects.new(name, data)
    (arm.users_collection[0] if arm.users_collection else scene.collection).objects.link(obj)
    obj.parent = arm
    obj.matrix_parent_inverse = Matrix.Identity(4)
    obj.rotation_mode = 'QUATERNION'
    obj[RESULT_TAG] = tag or name
    return obj
