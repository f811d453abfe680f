"""Preferences (server URL, token) and the properties stored in the .blend file.

The token lives only in the add-on preferences (saved to userpref.blend when the user saves
preferences, never to a .blend file); nothing here copies it into scene or object data.
"""

import bpy
from bpy.props import (BoolProperty, CollectionProperty, EnumProperty, FloatProperty, IntProperty,
                       StringProperty)


class HR_AddonPreferences(bpy.types.AddonPreferences):
    bl_idname = __package__

    server_url: StringProperty(name="Server URL", default="http://127.0.0.1:8000",
                               description="Base URL of the Hand Retarget service")
    token: StringProperty(name="Token", subtype='PASSWORD',
                          description="Bearer token (handretarget token create NAME); kept in the "
                                      "preferences only, never in .blend files")

    def draw(self, context):
        col = self.layout.column()
        col.prop(self, "server_url")
        col.prop(self, "token")
        col.operator("hand_retarget.ping", icon='URL')


class HR_Curve(bpy.types.PropertyGroup):
    """One axial curve's target side (the name is the PropertyGroup's ``name``)."""

    start_vertex: IntProperty(name="Start", min=0, description="Vertex where the target axis starts")
    direction_vertex: IntProperty(name="Direction", min=0,
                                  description="Vertex giving the axis' initial direction (geodesic from start)")
    lambda_a: FloatProperty(name="λa", default=1.0, min=1e-6, precision=4,
                            description="Length scale along the axis (target length / source length)")
    lambda_s: FloatProperty(name="λs", default=1.0, min=1e-6, precision=4,
                            description="Angular (radial) scale of transferred contacts")
    lambda_s_json: StringProperty(name="λs function", default="",
                                  description="A piecewise λs as JSON {angles_deg, values}; overrides λs when set")
    discard: BoolProperty(name="Discard", default=False, description="Drop the contacts of this curve's charts")


class HR_ObjectSettings(bpy.types.PropertyGroup):
    # on the armature: the last exported / uploaded rig
    rig_id: StringProperty(name="Rig asset", default="")
    rig_file: StringProperty(name="Rig file", default="", subtype='FILE_PATH')
    meters_per_unit: FloatProperty(name="Metres per unit", default=1.0, min=1e-9, precision=6)
    # on the mesh: the annotations being authored
    curves: CollectionProperty(type=HR_Curve)
    curve_index: IntProperty(default=0)
    source_json: StringProperty(default="", description="Source side of the annotations (from a proposal or file)")
    target_json: StringProperty(default="", description="Target points kept as (face, barycentric) from a "
                                "proposal, file or 3D cursor pick")
    annotations_id: StringProperty(name="Annotations asset", default="")


class HR_SceneSettings(bpy.types.PropertyGroup):
    clip_kind: EnumProperty(name="Clip", items=[
        ('NATIVE', "Clip file", "A native clip (.npz)"),
        ('GRAB', "GRAB", "A GRAB sequence with the MANO model and the object mesh")], default='NATIVE')
    clip_path: StringProperty(name="Clip", subtype='FILE_PATH', description="Native clip (.npz)")
    grab_sequence: StringProperty(name="Sequence", subtype='FILE_PATH')
    grab_mano: StringProperty(name="MANO model", subtype='FILE_PATH')
    grab_object_mesh: StringProperty(name="Object mesh", subtype='FILE_PATH')
    source_rig_path: StringProperty(name="Source rig", subtype='FILE_PATH',
                                    description="USD of the hand the clip was captured with (GRAB: the MANO "
                                                "hand); empty: the demo source hand")
    preset: EnumProperty(name="Preset", items=[('default', "Default", "The service's default settings"),
                                               ('paper', "Paper", "The paper's settings")], default='default')
    overrides: StringProperty(name="Overrides", default="",
                              description='Config overrides as JSON, e.g. {"solver.maxeval": 50}')
    use_frame_range: BoolProperty(name="Frame range", default=False,
                                  description="Retarget only part of the clip (GRAB sequences are long)")
    frame_first: IntProperty(name="First", default=0, min=0, description="First clip frame to retarget")
    frame_end: IntProperty(name="End", default=120, min=1, description="Clip frame after the last one to retarget")
    evaluate: BoolProperty(name="Evaluate", default=True, description="Let the service compute quality metrics")
    auto_import: BoolProperty(name="Import when done", default=False)
    baked: BoolProperty(name="Baked", default=False, description="One key per frame instead of the spline keys")
    import_object: BoolProperty(name="Object", default=True, description="Import the animated object too")
    start_frame: IntProperty(name="Start frame", default=1, description="Blender frame of the clip's first frame")
    show_annotations: BoolProperty(name="Show annotations", default=True)

    job_id: StringProperty(name="Job", default="")
    job_armature: StringProperty(default="", description="The armature the job was submitted for")
    job_state: StringProperty(default="")
    job_stage: StringProperty(default="")
    job_progress: FloatProperty(default=0.0, min=0.0, max=1.0, subtype='FACTOR')
    job_message: StringProperty(default="")


CLASSES = (HR_AddonPreferences, HR_Curve, HR_ObjectSettings, HR_SceneSettings)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Object.hand_retarget = bpy.props.PointerProperty(type=HR_ObjectSettings)
    bpy.types.Scene.hand_retarget = bpy.props.PointerProperty(type=HR_SceneSettings)


def unregister():
    del bpy.types.Scene.hand_retarget
    del bpy.types.Object.hand_retarget
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
