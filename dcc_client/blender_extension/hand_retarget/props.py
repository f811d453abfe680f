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


def _mark_edited(self, context):
    self.edited = True


class HR_DofLimit(bpy.types.PropertyGroup):
    """One DOF the service gave a rig from the hand model (the name is the DOF's name); the
    limits are the service's until the animator edits them, then the next export sends them."""

    joint: StringProperty(name="Bone")
    kind: StringProperty(name="Kind", default="rotate")
    lower: FloatProperty(name="Min", subtype='ANGLE', update=_mark_edited)
    upper: FloatProperty(name="Max", subtype='ANGLE', update=_mark_edited)
    edited: BoolProperty(name="Edited", default=False, description="Sent with the next export")


class HR_ObjectSettings(bpy.types.PropertyGroup):
    # on the armature: how its DOFs are made, and the last exported / uploaded rig
    dof_mode: EnumProperty(name="DOFs", items=[
        ('AUTO', "Automatic", "Bone channels when the armature has a root bone at its origin and bones carry "
                              "rotation locks or limits; else the hand model"),
        ('HAND_MODEL', "Hand model", "The service reads the hand from the bones and the skin and gives each joint "
                                     "flexion / abduction DOFs with anatomical limits (editable below); any bone "
                                     "names, rolls and placement"),
        ('CHANNELS', "Bone channels", "Each bone's free Euler channels, limited by Limit Rotation constraints or "
                                      "hr_min_x / hr_max_x properties; needs a root bone at the armature origin")],
        default='AUTO')
    hand_root_bone: StringProperty(name="Hand root", default="",
                                   description="In a body armature: the bone the hand hangs from (e.g. the "
                                               "forearm); empty: the whole armature is the hand, or the service "
                                               "finds where the fingers branch")
    dof_limits: CollectionProperty(type=HR_DofLimit)
    dof_limit_index: IntProperty(default=0)
    exported_mode: StringProperty(default="", description="The DOF mode of the last export")
    surface_map_json: StringProperty(default="", description="Where the service's hand surface (cut from a body "
                                     "mesh, or its largest piece) is in this mesh: annotation points are carried "
                                     "through it")
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
    grab_vtemp: StringProperty(name="Hand template", subtype='FILE_PATH',
                               description="The subject's hand template mesh (GRAB's tools/subject_meshes); empty: "
                                           "the MANO model's mean hand")
    grab_hand: EnumProperty(name="Hand", items=[('right', "Right", "The sequence's right hand (MANO_RIGHT.pkl)"),
                                                ('left', "Left", "The sequence's left hand (MANO_LEFT.pkl)")],
                            default='right')
    # what the service made of the GRAB files: the clip and its MANO source rig (asset ids)
    grab_clip_id: StringProperty(default="", options={'HIDDEN'})
    grab_source_rig_id: StringProperty(default="", options={'HIDDEN'})
    # a substituted object (hand_retarget.substitute_object): the clip the service made with
    # the selected mesh as its object, used by Retarget while "use_substitute" is on
    use_substitute: BoolProperty(name="Substituted object", default=False,
                                 description="Retarget the clip made with the substituted object")
    substitute_clip_id: StringProperty(default="", options={'HIDDEN'})
    substitute_object: StringProperty(name="New object", default="", options={'HIDDEN'})
    substitute_from_clip_id: StringProperty(default="", options={'HIDDEN'})
    substitute_report: StringProperty(default="", options={'HIDDEN'})
    allow_intersection: BoolProperty(name="Allow intersection", default=False,
                                     description="Substitute even when the captured hand lies inside the new object "
                                                 "(a thicker object the solve should open the hand around)")
    source_rig_path: StringProperty(name="Source rig", subtype='FILE_PATH',
                                    description="USD of the hand the clip was captured with; empty: the clip's own "
                                                "(a GRAB import's MANO hand, else the demo source hand)")
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
    use_clip_fps: BoolProperty(name="Clip frame rate", default=False,
                               description="Set the scene's frame rate to the clip's; off: the scene keeps its own "
                                           "and the result is timed into it")
    import_mode: EnumProperty(name="Re-import", items=[
        ('REPLACE', "Replace", "A new import replaces the previous result's action"),
        ('NLA', "New NLA strip", "The previous action is kept as an NLA strip; the new result is the active action")],
        default='REPLACE')
    show_annotations: BoolProperty(name="Show annotations", default=True)

    job_id: StringProperty(name="Job", default="")
    job_armature: StringProperty(default="", description="The armature the job was submitted for")
    job_state: StringProperty(default="")
    job_stage: StringProperty(default="")
    job_progress: FloatProperty(default=0.0, min=0.0, max=1.0, subtype='FACTOR')
    job_message: StringProperty(default="")


CLASSES = (HR_AddonPreferences, HR_Curve, HR_DofLimit, HR_ObjectSettings, HR_SceneSettings)


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
