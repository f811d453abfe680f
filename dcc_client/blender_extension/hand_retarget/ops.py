"""Operators: connection test, rig export, annotations (propose, load, save, curve list), job
submit / cancel, result import."""

import json
import os
import uuid

import bpy
from bpy.props import BoolProperty, EnumProperty, StringProperty
from bpy_extras.io_utils import ExportHelper, ImportHelper

from . import anim_import, annotations, jobs, rig_export
from .client import ServiceError

ERRORS = (ServiceError, OSError, ValueError, RuntimeError, jobs.ConnectionSettingsError)


# ---- helpers --------------------------------------------------------------------------------------
def targets(context):
    """(armature, skinned mesh) from the active / selected objects; either may be None."""
    obj = context.active_object
    arm = None
    if obj is not None and obj.type == 'ARMATURE':
        arm = obj
    elif obj is not None and obj.type == 'MESH':
        arm = next((m.object for m in obj.modifiers if m.type == 'ARMATURE' and m.object), None)
    if arm is None:
        return None, None
    prefer = [obj] + list(context.selected_objects or [])
    return arm, rig_export.skinned_mesh(arm, prefer=prefer)


def work_folder(*parts) -> str:
    """A folder for exported and downloaded files: beside the saved .blend, else Blender's temp."""
    base = bpy.path.abspath("//hand_retarget") if bpy.data.filepath else os.path.join(bpy.app.tempdir, "hand_retarget")
    folder = os.path.join(base, *parts)
    os.makedirs(folder, exist_ok=True)
    return folder


def export_and_upload(context, arm, mesh, filepath: str = "", upload: bool = True) -> dict:
    """Export the rig (and upload it); stores file, id and units on the armature."""
    filepath = bpy.path.abspath(filepath) if filepath else os.path.join(work_folder(), f"{bpy.path.clean_name(arm.name)}.usda")
    info = rig_export.export_rig(context, arm, mesh, filepath)
    settings = arm.hand_retarget
    settings.rig_file, settings.meters_per_unit = filepath, info["meters_per_unit"]
    settings.exported_mode = info["dof_mode"]
    if upload:
        hand_root = settings.hand_root_bone.strip() or None
        if hand_root is not None and hand_root not in arm.data.bones:
            raise rig_export.RigExportError(f"the hand root {hand_root!r} is not a bone of {arm.name!r}")
        asset = jobs.make_client(context).upload("rig", filepath, name=os.path.basename(filepath),
                                                 hand_root=hand_root)
        settings.rig_id = asset["id"]
        info["asset"] = asset
        show_dof_limits(arm, asset.get("info") or {})
        source = (asset.get("info") or {}).get("surface_source")
        settings.surface_map_json = json.dumps(source) if source else ""
    info["filepath"] = filepath
    return info


def show_dof_limits(arm, rig_info: dict) -> None:
    """Fill the armature's DOF list from the service's rig info (hand-model DOFs, without the
    free root); limits the animator edited stay as they were edited."""
    items = arm.hand_retarget.dof_limits
    edited = {i.name: (i.lower, i.upper) for i in items if i.edited}
    items.clear()
    if arm.hand_retarget.exported_mode != 'HAND_MODEL':
        return
    for d in rig_info.get("dof_limits") or ():
        if d["name"] in rig_export.ROOT_DOFS:
            continue  # the free root: the solver's search box, not the hand's
        item = items.add()
        item.name, item.joint, item.kind = d["name"], d["joint"], d["kind"]
        lower, upper = edited.get(d["name"], (d["lower"], d["upper"]))
        item.lower, item.upper = lower, upper
        item.edited = d["name"] in edited  # set last: the limits' update marks an item edited


class _Op:
    bl_options = {'REGISTER'}

    def fail(self, err) -> set:
        self.report({'ERROR'}, str(err))
        return {'CANCELLED'}


# ---- connection / rig -----------------------------------------------------------------------------
class HAND_RETARGET_OT_ping(_Op, bpy.types.Operator):
    """Check that the service answers and accepts the token"""
    bl_idname = "hand_retarget.ping"
    bl_label = "Test Connection"

    def execute(self, context):
        try:
            c = jobs.make_client(context, timeout=10)
            health = c.health()
            c.assets("rig")  # needs a valid token
        except ERRORS as err:
            return self.fail(err)
        self.report({'INFO'}, f"service {health.get('status', 'ok')}, token accepted")
        return {'FINISHED'}


class HAND_RETARGET_OT_add_root_bone(_Op, bpy.types.Operator):
    """Insert a bone at the armature origin with identity rest above the current root bones (the
    service's solver moves the hand through such a root)"""
    bl_idname = "hand_retarget.add_root_bone"
    bl_label = "Add Root Bone"
    bl_options = {'REGISTER', 'UNDO'}

    def execute(self, context):
        arm, _ = targets(context)
        if arm is None:
            return self.fail("select an armature")
        name = rig_export.add_root_bone(context, arm)
        self.report({'INFO'}, f"added root bone {name!r}")
        return {'FINISHED'}


class HAND_RETARGET_OT_export_rig(_Op, bpy.types.Operator):
    """Export the armature and its skinned mesh as a Hand Retarget rig (USD: DOFs from the hand
    model, or from the bone channels) and upload it to the service"""
    bl_idname = "hand_retarget.export_rig"
    bl_label = "Export Rig"

    filepath: StringProperty(subtype='FILE_PATH', default="", options={'SKIP_SAVE'},
                             description="Where to write the USD (empty: a work folder)")
    upload: BoolProperty(default=True, name="Upload", options={'SKIP_SAVE'})

    def execute(self, context):
        arm, mesh = targets(context)
        if arm is None:
            return self.fail("select an armature (or its mesh)")
        try:
            info = export_and_upload(context, arm, mesh, self.filepath, self.upload)
        except ERRORS as err:
            return self.fail(err)
        served = (info.get("asset") or {}).get("info") or {}
        for w in info["warnings"] + list(served.get("rig_warnings") or ()):
            self.report({'WARNING'}, w)
        if info["dofs"] is not None:
            dofs = f"{len(info['dofs'])} DOFs from bone channels"
        elif served:
            dofs = f"{served['dofs']} DOFs from the hand model"
        else:
            dofs = "DOFs from the hand model (given at upload)"
        self.report({'INFO'}, f"rig {info['rig_name']}: {dofs}, {info['vertices']} vertices"
                              + (f", uploaded {info['asset']['id'][:12]}" if self.upload else ""))
        return {'FINISHED'}


# ---- annotations ----------------------------------------------------------------------------------
class HAND_RETARGET_OT_propose_annotations(_Op, bpy.types.Operator):
    """Ask the service for proposed markers and axial curves (exports and uploads the rig first)"""
    bl_idname = "hand_retarget.propose_annotations"
    bl_label = "Propose Annotations"
    bl_options = {'REGISTER', 'UNDO'}

    def execute(self, context):
        arm, mesh = targets(context)
        if arm is None or mesh is None:
            return self.fail("select an armature with a skinned mesh")
        scene = context.scene.hand_retarget
        try:
            export_and_upload(context, arm, mesh)
            client = jobs.make_client(context)
            source = None
            if scene.source_rig_path:
                source = client.upload("rig", bpy.path.abspath(scene.source_rig_path))["id"]
            elif scene.clip_kind == 'GRAB':  # the MANO hand the import makes from the user's model
                _, source = import_grab(client, scene)
            asset = client.propose_annotations(arm.hand_retarget.rig_id, source_rig=source)
            counts = annotations.load_document(client.asset_content(asset["id"], kind="annotations"), arm, mesh)
        except (annotations.AnnotationError, rig_export.RigExportError) + ERRORS as err:
            return self.fail(err)
        mesh.hand_retarget.annotations_id = asset["id"]
        for w in counts["warnings"]:
            self.report({'WARNING'}, w)
        self.report({'INFO'}, f"proposed {counts['markers']} markers and {counts['curves']} curves")
        return {'FINISHED'}


class HAND_RETARGET_OT_load_annotations(_Op, bpy.types.Operator, ImportHelper):
    """Load an annotation file (markers become vertex groups, curves fill the list)"""
    bl_idname = "hand_retarget.load_annotations"
    bl_label = "Load Annotations"
    bl_options = {'REGISTER', 'UNDO'}
    filename_ext = ".json"
    filter_glob: StringProperty(default="*.json", options={'HIDDEN'})

    def execute(self, context):
        arm, mesh = targets(context)
        if mesh is None:
            return self.fail("select an armature with a skinned mesh")
        try:
            with open(self.filepath, "rb") as fh:
                counts = annotations.load_document(fh.read(), arm, mesh)
        except (OSError, annotations.AnnotationError) as err:
            return self.fail(err)
        for w in counts["warnings"]:
            self.report({'WARNING'}, w)
        self.report({'INFO'}, f"loaded {counts['markers']} markers and {counts['curves']} curves")
        return {'FINISHED'}


class HAND_RETARGET_OT_save_annotations(_Op, bpy.types.Operator, ExportHelper):
    """Save the annotations (the core's JSON format)"""
    bl_idname = "hand_retarget.save_annotations"
    bl_label = "Save Annotations"
    filename_ext = ".json"
    filter_glob: StringProperty(default="*.json", options={'HIDDEN'})

    def execute(self, context):
        arm, mesh = targets(context)
        if mesh is None:
            return self.fail("select an armature with a skinned mesh")
        try:
            doc, warnings = annotations.build_document(arm, mesh)
            with open(self.filepath, "w", encoding="utf-8") as fh:
                json.dump(doc, fh, indent=1)
        except (OSError, annotations.AnnotationError) as err:
            return self.fail(err)
        for w in warnings:
            self.report({'WARNING'}, w)
        self.report({'INFO'}, f"saved {len(doc['markers'])} markers and {len(doc['axial_curves'])} curves")
        return {'FINISHED'}


class HAND_RETARGET_OT_curve_add(_Op, bpy.types.Operator):
    """Add an axial curve (name it like a source curve)"""
    bl_idname = "hand_retarget.curve_add"
    bl_label = "Add Curve"
    bl_options = {'REGISTER', 'UNDO'}

    def execute(self, context):
        _, mesh = targets(context)
        if mesh is None:
            return self.fail("select an armature with a skinned mesh")
        s = mesh.hand_retarget
        item = s.curves.add()
        item.name = f"curve{len(s.curves)}"
        s.curve_index = len(s.curves) - 1
        return {'FINISHED'}


class HAND_RETARGET_OT_curve_remove(_Op, bpy.types.Operator):
    """Remove the selected axial curve"""
    bl_idname = "hand_retarget.curve_remove"
    bl_label = "Remove Curve"
    bl_options = {'REGISTER', 'UNDO'}

    def execute(self, context):
        _, mesh = targets(context)
        if mesh is None or not mesh.hand_retarget.curves:
            return {'CANCELLED'}
        s = mesh.hand_retarget
        s.curves.remove(s.curve_index)
        s.curve_index = max(0, min(s.curve_index, len(s.curves) - 1))
        return {'FINISHED'}


def cursor_point(context, mesh):
    """The core point (face, barycentric) of the mesh closest to the 3D cursor, and its nearest
    corner vertex (see annotations.surface_point)."""
    if mesh.mode == 'EDIT':
        mesh.update_from_editmode()
    co = mesh.matrix_world.inverted() @ context.scene.cursor.location
    return annotations.surface_point(mesh.data, co)


class HAND_RETARGET_OT_curve_pick(_Op, bpy.types.Operator):
    """Set the selected curve's start or direction to the selected vertex of the mesh (the
    lowest id when several are selected), or to the point of the mesh at the 3D cursor (kept
    as a face and barycentric coordinates, not snapped to a vertex)"""
    bl_idname = "hand_retarget.curve_pick"
    bl_label = "Pick Vertex"
    bl_options = {'REGISTER', 'UNDO'}

    which: EnumProperty(items=[('START', "Start", ""), ('DIRECTION', "Direction", "")])
    at_cursor: BoolProperty(name="At 3D Cursor", default=False,
                            description="The point of the mesh closest to the 3D cursor instead of a selected vertex")

    def execute(self, context):
        _, mesh = targets(context)
        if mesh is None or not mesh.hand_retarget.curves:
            return self.fail("add a curve first")
        item = mesh.hand_retarget.curves[mesh.hand_retarget.curve_index]
        which = "start" if self.which == 'START' else "direction"
        if self.at_cursor:
            try:
                point, v = cursor_point(context, mesh)
            except annotations.AnnotationError as err:
                return self.fail(err)
            setattr(item, f"{which}_vertex", v)
            annotations.keep_target(mesh, "curves", item.name, {which: point, f"{which}_vertex": v})
            return {'FINISHED'}
        if mesh.mode == 'EDIT':
            mesh.update_from_editmode()
        v = next((x.index for x in mesh.data.vertices if x.select), None)
        if v is None:
            return self.fail("select a vertex of the mesh (Edit Mode)")
        setattr(item, f"{which}_vertex", v)
        annotations.forget_target(mesh, "curves", item.name, which)
        return {'FINISHED'}


class HAND_RETARGET_OT_marker_at_cursor(_Op, bpy.types.Operator):
    """Make a marker's target the point of the mesh at the 3D cursor (kept as a face and
    barycentric coordinates; its vertex group shows the nearest vertex)"""
    bl_idname = "hand_retarget.marker_at_cursor"
    bl_label = "Marker at 3D Cursor"
    bl_options = {'REGISTER', 'UNDO'}

    marker: StringProperty(name="Marker", description="Marker name (its vertex group is replaced)")

    def invoke(self, context, event):
        return context.window_manager.invoke_props_dialog(self)

    def execute(self, context):
        arm, mesh = targets(context)
        if mesh is None:
            return self.fail("select an armature with a skinned mesh")
        if not self.marker or self.marker in annotations.bone_names(arm):
            return self.fail("name a marker (not a bone)")
        try:
            point, v = cursor_point(context, mesh)
        except annotations.AnnotationError as err:
            return self.fail(err)
        was_edit = mesh.mode == 'EDIT'
        if was_edit:
            bpy.ops.object.mode_set(mode='OBJECT')
        group = mesh.vertex_groups.get(self.marker)
        if group is not None:
            mesh.vertex_groups.remove(group)
        mesh.vertex_groups.new(name=self.marker).add([v], 1.0, 'REPLACE')
        if was_edit:
            bpy.ops.object.mode_set(mode='EDIT')
        annotations.forget_target(mesh, "markers", self.marker)
        annotations.keep_target(mesh, "markers", self.marker, {"points": [point], "vertices": [v]})
        return {'FINISHED'}


# ---- jobs -----------------------------------------------------------------------------------------
def _after_job(scene, job):
    """on_done of the poller: import at once when asked to."""
    s = scene.hand_retarget
    if job["state"] == "succeeded" and s.auto_import:
        arm = bpy.data.objects.get(s.job_armature)
        if arm is not None:
            try:
                import_result(bpy.context, arm, job["id"], scene=scene)
            except Exception as err:  # a timer must not raise
                s.job_message = f"import failed: {err}"


class HAND_RETARGET_OT_submit(_Op, bpy.types.Operator):
    """Upload the rig, the annotations and the clip, and start a retargeting job"""
    bl_idname = "hand_retarget.submit"
    bl_label = "Retarget"

    def execute(self, context):
        arm, mesh = targets(context)
        if arm is None or mesh is None:
            return self.fail("select an armature with a skinned mesh")
        s = context.scene.hand_retarget
        if jobs.is_polling():
            return self.fail(f"job {jobs.STATE['job_id']} is still being followed; cancel it first")
        try:
            doc, warnings = annotations.build_document(arm, mesh)
            overrides = json.loads(s.overrides) if s.overrides.strip() else {}
            if not isinstance(overrides, dict):
                raise ValueError("overrides must be a JSON object")
            frames = frame_range(s)
            export_and_upload(context, arm, mesh)
            client = jobs.make_client(context)
            ann = client.upload_bytes("annotations", json.dumps(doc).encode("utf-8"), f"{arm.name}.json")
            mesh.hand_retarget.annotations_id = ann["id"]
            clip = self.upload_clip(client, s)
            source = client.upload("rig", bpy.path.abspath(s.source_rig_path))["id"] if s.source_rig_path else None
            job = client.submit(clip=clip, rig=arm.hand_retarget.rig_id, annotations=ann["id"], source_rig=source,
                                preset=s.preset, overrides=overrides, evaluate=s.evaluate, frames=frames,
                                idempotency_key=uuid.uuid4().hex)
        except (annotations.AnnotationError, rig_export.RigExportError) + ERRORS as err:
            return self.fail(err)
        for w in warnings:
            self.report({'WARNING'}, w)
        s.job_armature = arm.name
        jobs.apply_job(s, job)
        jobs.start_polling(client, job["id"], context.scene, on_done=_after_job)
        self.report({'INFO'}, f"job {job['id'][:12]} {job['state']}")
        return {'FINISHED'}

    @staticmethod
    def upload_clip(client, s) -> str:
        if s.use_substitute and s.substitute_clip_id:
            if clip_asset(client, s) != s.substitute_from_clip_id:
                raise ValueError("the clip changed since its object was substituted: substitute it again, or turn "
                                 "'Substituted object' off")
            return s.substitute_clip_id
        return clip_asset(client, s)


def clip_asset(client, s) -> str:
    """The asset id of the scene's clip: the native file uploaded, or the GRAB files imported
    (the same files give the same id)."""
    if s.clip_kind == 'NATIVE':
        if not s.clip_path:
            raise ValueError("choose a clip file")
        return client.upload("clip", bpy.path.abspath(s.clip_path))["id"]
    return import_grab(client, s)[0]


class HAND_RETARGET_OT_substitute_object(_Op, bpy.types.Operator):
    """Replace the clip's object with the selected mesh: the service registers it onto the clip's object and
    traces the contacts onto it; Retarget then uses that clip"""
    bl_idname = "hand_retarget.substitute_object"
    bl_label = "Substitute Object"

    def execute(self, context):
        obj = context.active_object
        if obj is None or obj.type != 'MESH' or any(m.type == 'ARMATURE' for m in obj.modifiers):
            return self.fail("select the new object: a mesh that is not a skinned hand")
        s = context.scene.hand_retarget
        try:
            client = jobs.make_client(context)
            clip = clip_asset(client, s)
            path = os.path.join(work_folder("objects"), f"{bpy.path.clean_name(obj.name)}.obj")
            export_object_mesh(context, obj, path)
            mesh = client.upload("file", path)
            made = client.substitute_object(clip=clip, object_mesh=mesh["id"], allow_intersection=s.allow_intersection,
                                            name=f"{bpy.path.clean_name(obj.name)}_clip.npz")
        except ERRORS as err:
            return self.fail(err)
        sub = made["info"]["substitution"]
        s.substitute_clip_id, s.substitute_from_clip_id, s.substitute_object = made["id"], clip, obj.name
        s.use_substitute = True
        s.substitute_report = (f"{100 * sub['share']:.0f} % of the contacts carried over"
                               + (f", fit RMS {sub['residual_mm']:.2f} mm" if "residual_mm" in sub else ""))
        for line in sub.get("repairs") or ():
            self.report({'WARNING'}, f"the mesh was repaired: {line}")
        self.report({'INFO'}, f"{obj.name}: {s.substitute_report}")
        return {'FINISHED'}


def export_object_mesh(context, obj, path: str) -> None:
    """``obj`` as a triangulated OBJ in metres, in Blender's own axes (Z up): only the
    geometry, modifiers applied (the service registers it onto the clip's object)."""
    scale = context.scene.unit_settings.scale_length or 1.0
    for other in context.selected_objects:
        other.select_set(other == obj)
    obj.select_set(True)
    context.view_layer.objects.active = obj
    result = bpy.ops.wm.obj_export(filepath=path, export_selected_objects=True, apply_modifiers=True,
                                   export_triangulated_mesh=True, export_materials=False, export_uv=False,
                                   export_normals=False, forward_axis='Y', up_axis='Z', global_scale=scale)
    if 'FINISHED' not in result:
        raise RuntimeError(f"could not export {obj.name!r} as OBJ")


class HAND_RETARGET_OT_cancel(_Op, bpy.types.Operator):
    """Cancel the running job"""
    bl_idname = "hand_retarget.cancel"
    bl_label = "Cancel Job"

    def execute(self, context):
        s = context.scene.hand_retarget
        if not s.job_id:
            return self.fail("no job")
        try:
            job = jobs.make_client(context).cancel(s.job_id)
        except ERRORS as err:
            return self.fail(err)
        jobs.apply_job(s, job)
        self.report({'INFO'}, f"job {s.job_id[:12]}: {job['state']}")
        return {'FINISHED'}


def import_grab(client, s) -> tuple[str, str]:
    """Upload the scene's GRAB files and let the service import the chosen hand: (the clip's
    asset id, its MANO source rig's). The same files give the same assets (content ids), so
    proposing and then submitting imports once. A job on the clip needs no source rig: the
    service finds the MANO hand by the hash the clip records."""
    paths = {k: bpy.path.abspath(getattr(s, f"grab_{k}")) for k in ("sequence", "mano", "object_mesh")}
    missing = [k.replace("_", " ") for k, p in paths.items() if not p]
    if missing:
        raise ValueError(f"GRAB needs the {', '.join(missing)} file(s)")
    if s.grab_vtemp:
        paths["vtemp"] = bpy.path.abspath(s.grab_vtemp)
    ids = {k: client.upload("file", p)["id"] for k, p in paths.items()}
    clip = client.import_grab(ids.pop("sequence"), ids.pop("mano"), ids.pop("object_mesh"), hand=s.grab_hand, **ids)
    s.grab_clip_id, s.grab_source_rig_id = clip["id"], clip["info"].get("source_rig_asset", "")
    return s.grab_clip_id, s.grab_source_rig_id


def frame_range(s):
    """The scene settings' clip frame range as [first, end) for the job request, or None."""
    if not s.use_frame_range:
        return None
    if s.frame_end <= s.frame_first:
        raise ValueError(f"the frame range {s.frame_first}:{s.frame_end} is empty: End must be after First")
    return [int(s.frame_first), int(s.frame_end)]


def result_layer_path(arm, job_id: str) -> str:
    """Where a job's animation.usda is put: beside the rig file exported from ``arm``, whose
    name the layer sublayers, so that it plays over that file in any USD tool
    (``<rig>.<job>.animation.usda``); else in the job's work folder beside its rig.usda."""
    rig_file = arm.hand_retarget.rig_file
    if rig_file:
        stem = os.path.splitext(os.path.basename(rig_file))[0]
        return os.path.join(os.path.dirname(rig_file), f"{stem}.{job_id[:8]}.animation.usda")
    return os.path.join(work_folder(job_id), "animation.usda")


def import_result(context, arm, job_id: str, *, scene=None, baked=None, with_object=None, start_frame=None,
                  mode=None) -> dict:
    """Fetch a succeeded job's result and put it on ``arm`` (and the object beside it), timed
    into the scene's frame rate (or the clip's, with the scene setting). A job that retargeted
    a frame range [first, end) lands where those frames of the clip are. A bone-channel rig
    gets its DOF curves; a hand-model rig the layer's SkelAnimation on its own bones (only the
    hand's, below the hand root, in a body armature) and the wrist target."""
    scene = scene or context.scene
    s = scene.hand_retarget
    baked = s.baked if baked is None else baked
    with_object = s.import_object if with_object is None else with_object
    start_frame = s.start_frame if start_frame is None else start_frame
    mode = mode or s.import_mode
    settings = arm.hand_retarget
    client = jobs.make_client(context)
    doc = json.loads(client.artifact(job_id, "result.json"))
    scene_fps = anim_import.scene_frame_rate(scene, float(doc["fps"]), s.use_clip_fps)
    start = start_frame + int((doc.get("frames") or [0])[0]) / float(doc["fps"]) * scene_fps
    plain = settings.exported_mode == 'HAND_MODEL'
    layer = result_layer_path(arm, job_id)
    if plain or with_object:
        client.download(job_id, "animation.usda", layer)
        if not settings.rig_file:
            client.download(job_id, "rig.usda", os.path.join(os.path.dirname(layer), "rig.usda"))
    tag, action_name = job_id, f"HR_{arm.name}_{job_id[:8]}"
    anim_import.clear_previous(arm, mode)
    if mode == 'REPLACE':
        anim_import.remove_previous_objects(arm, "HR_Object_")
        anim_import.remove_previous_objects(arm, anim_import.WRIST_TARGET)
    if plain:
        hand_root = settings.hand_root_bone.strip()
        bones = anim_import.subtree(arm, hand_root) if hand_root else None
        info = anim_import.import_skel_animation(context, arm, layer, start_frame=start, scene=scene,
                                                 scene_fps=scene_fps, bones=bones, action_name=action_name, tag=tag)
        wrist = anim_import.import_wrist_target(context, arm, layer, start_frame=start, scene=scene,
                                                scene_fps=scene_fps, plain=True, tag=tag)
        info["wrist_target"] = wrist.name if wrist is not None else None
    else:
        mpu = settings.meters_per_unit
        if not settings.rig_file:  # never exported here: the same rule as the export
            mpu = rig_export.meters_per_unit(context, arm)
        info = anim_import.import_curves(context, arm, doc, mpu=mpu, start_frame=start, baked=baked,
                                         action_name=action_name, scene=scene, scene_fps=scene_fps, tag=tag)
    if with_object:
        obj = anim_import.import_object(context, arm, layer, start_frame=start, name=f"HR_Object_{job_id[:8]}",
                                        scene=scene, scene_fps=scene_fps, plain=plain, tag=tag)
        info["object"] = obj.name if obj is not None else None
    info["scene_fps"] = scene_fps
    return info


class HAND_RETARGET_OT_import_result(_Op, bpy.types.Operator):
    """Put the job's curves on the armature as F-curves (and import the animated object)"""
    bl_idname = "hand_retarget.import_result"
    bl_label = "Import Result"
    bl_options = {'REGISTER', 'UNDO'}

    job_id: StringProperty(default="", options={'SKIP_SAVE'}, description="Job (empty: the scene's last job)")

    def execute(self, context):
        s = context.scene.hand_retarget
        job_id = self.job_id or s.job_id
        arm, _ = targets(context)
        arm = arm or bpy.data.objects.get(s.job_armature)
        if not job_id or arm is None:
            return self.fail("needs a finished job and an armature")
        try:
            info = import_result(context, arm, job_id)
        except (anim_import.ImportError_, rig_export.RigExportError) + ERRORS as err:
            return self.fail(err)
        if info["skipped"]:
            self.report({'WARNING'}, f"DOFs without a bone: {', '.join(info['skipped'][:8])}")
        self.report({'INFO'}, f"{info['fcurves']} F-curves: {info['frames']} clip frames at {info['fps']:g} fps "
                              f"into the scene at {info['scene_fps']:g} fps")
        return {'FINISHED'}


CLASSES = (HAND_RETARGET_OT_ping, HAND_RETARGET_OT_add_root_bone, HAND_RETARGET_OT_export_rig,
           HAND_RETARGET_OT_propose_annotations, HAND_RETARGET_OT_load_annotations,
           HAND_RETARGET_OT_save_annotations, HAND_RETARGET_OT_curve_add, HAND_RETARGET_OT_curve_remove,
           HAND_RETARGET_OT_marker_at_cursor,
           HAND_RETARGET_OT_curve_pick, HAND_RETARGET_OT_submit, HAND_RETARGET_OT_substitute_object,
           HAND_RETARGET_OT_cancel,
           HAND_RETARGET_OT_import_result)
