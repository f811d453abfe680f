"""The sidebar panel (View3D > Sidebar > Hand Retarget), the curve list and the status bar."""

import bpy

from .ops import targets

ACTIVE_STATES = ("queued", "running")


class HAND_RETARGET_UL_curves(bpy.types.UIList):
    def draw_item(self, context, layout, data, item, icon, active_data, active_propname, index):
        row = layout.row(align=True)
        row.prop(item, "name", text="", emboss=False)
        row.prop(item, "discard", text="", icon='TRASH' if item.discard else 'CHECKMARK', emboss=False)
        if not item.discard:
            row.label(text=f"{item.start_vertex}→{item.direction_vertex}")
            row.label(text=f"λa {item.lambda_a:.2f} λs {item.lambda_s:.2f}")


class HAND_RETARGET_UL_dof_limits(bpy.types.UIList):
    """The hand-model DOFs the service gave the rig; limits editable (sent with the next export)."""

    def draw_item(self, context, layout, data, item, icon, active_data, active_propname, index):
        row = layout.row(align=True)
        row.label(text=item.name, icon='CHECKMARK' if item.edited else 'BLANK1')
        row.prop(item, "lower", text="")
        row.prop(item, "upper", text="")


class HAND_RETARGET_PT_panel(bpy.types.Panel):
    bl_label = "Hand Retarget"
    bl_space_type = 'VIEW_3D'
    bl_region_type = 'UI'
    bl_category = "Hand Retarget"

    def draw(self, context):
        layout = self.layout
        s = context.scene.hand_retarget
        arm, mesh = targets(context)

        box = layout.box()
        box.label(text="Rig", icon='ARMATURE_DATA')
        if arm is None:
            box.label(text="Select a hand armature")
        else:
            box.label(text=f"{arm.name} / {mesh.name if mesh else 'no skinned mesh'}")
            rs = arm.hand_retarget
            box.prop(rs, "dof_mode")
            box.prop_search(rs, "hand_root_bone", arm.data, "bones")
            row = box.row(align=True)
            row.operator("hand_retarget.export_rig", icon='EXPORT')
            if rs.dof_mode == 'CHANNELS':
                row.operator("hand_retarget.add_root_bone", text="", icon='BONE_DATA')
            if rs.rig_id:
                box.label(text=f"uploaded {rs.rig_id[:12]} ({rs.exported_mode.replace('_', ' ').lower()} DOFs)")
            if rs.dof_limits:
                box.label(text="DOF limits (edits go with the next export)")
                box.template_list("HAND_RETARGET_UL_dof_limits", "", rs, "dof_limits", rs, "dof_limit_index", rows=4)

        box = layout.box()
        box.label(text="Annotations", icon='GROUP_VERTEX')
        box.operator("hand_retarget.propose_annotations", icon='LIGHT')
        row = box.row(align=True)
        row.operator("hand_retarget.load_annotations", icon='FILE_FOLDER')
        row.operator("hand_retarget.save_annotations", icon='FILE_TICK')
        if mesh is not None:
            ms = mesh.hand_retarget
            box.label(text="Markers: vertex groups named like the marker")
            box.operator("hand_retarget.marker_at_cursor", icon='PIVOT_CURSOR')
            row = box.row()
            row.template_list("HAND_RETARGET_UL_curves", "", ms, "curves", ms, "curve_index", rows=4)
            col = row.column(align=True)
            col.operator("hand_retarget.curve_add", text="", icon='ADD')
            col.operator("hand_retarget.curve_remove", text="", icon='REMOVE')
            if ms.curves and 0 <= ms.curve_index < len(ms.curves):
                item = ms.curves[ms.curve_index]
                col = box.column(align=True)
                r = col.row(align=True)
                r.prop(item, "start_vertex")
                r.operator("hand_retarget.curve_pick", text="", icon='EYEDROPPER').which = 'START'
                op = r.operator("hand_retarget.curve_pick", text="", icon='PIVOT_CURSOR')
                op.which, op.at_cursor = 'START', True
                r = col.row(align=True)
                r.prop(item, "direction_vertex")
                r.operator("hand_retarget.curve_pick", text="", icon='EYEDROPPER').which = 'DIRECTION'
                op = r.operator("hand_retarget.curve_pick", text="", icon='PIVOT_CURSOR')
                op.which, op.at_cursor = 'DIRECTION', True
                r = col.row(align=True)
                r.prop(item, "lambda_a")
                r.prop(item, "lambda_s")
            box.prop(s, "show_annotations")

        box = layout.box()
        box.label(text="Clip", icon='SEQUENCE')
        box.prop(s, "clip_kind", expand=True)
        if s.clip_kind == 'NATIVE':
            box.prop(s, "clip_path")
        else:
            box.prop(s, "grab_hand", expand=True)
            box.prop(s, "grab_sequence")
            box.prop(s, "grab_mano")
            box.prop(s, "grab_object_mesh")
            box.prop(s, "grab_vtemp")
        row = box.row(align=True)
        row.operator("hand_retarget.substitute_object", icon='MESH_DATA')
        row.prop(s, "allow_intersection", text="", icon='MOD_BOOLEAN')
        if s.substitute_clip_id:
            box.prop(s, "use_substitute", text=f"Object: {s.substitute_object}")
            if s.substitute_report:
                box.label(text=s.substitute_report)
        box.prop(s, "source_rig_path")
        row = box.row()
        row.prop(s, "preset")
        row.prop(s, "evaluate")
        box.prop(s, "overrides")
        row = box.row(align=True)
        row.prop(s, "use_frame_range")
        sub = row.row(align=True)
        sub.enabled = s.use_frame_range
        sub.prop(s, "frame_first")
        sub.prop(s, "frame_end")
        row = box.row(align=True)
        row.operator("hand_retarget.submit", icon='PLAY')
        row.operator("hand_retarget.cancel", text="", icon='CANCEL')
        box.prop(s, "auto_import")

        if s.job_id:
            box = layout.box()
            box.label(text=f"Job {s.job_id[:12]}", icon='TIME')
            if s.job_state in ACTIVE_STATES and hasattr(box, "progress"):
                box.progress(factor=s.job_progress, type='BAR', text=s.job_message)
            else:
                box.label(text=s.job_message or s.job_state)
            row = box.row()
            row.prop(s, "baked")
            row.prop(s, "import_object")
            row = box.row()
            row.prop(s, "start_frame")
            row.prop(s, "use_clip_fps")
            box.prop(s, "import_mode")
            box.operator("hand_retarget.import_result", icon='IMPORT')


def draw_status(self, context):
    """Status-bar entry while a job runs."""
    s = getattr(context.scene, "hand_retarget", None)
    if s is None or s.job_state not in ACTIVE_STATES:
        return
    text = f"Hand Retarget: {s.job_stage or s.job_state}"
    if hasattr(self.layout, "progress"):
        self.layout.progress(factor=s.job_progress, type='RING', text=text)
    else:
        self.layout.label(text=f"{text} {100 * s.job_progress:.0f}%")


CLASSES = (HAND_RETARGET_UL_curves, HAND_RETARGET_UL_dof_limits, HAND_RETARGET_PT_panel)


def register():
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.STATUSBAR_HT_header.append(draw_status)


def unregister():
    bpy.types.STATUSBAR_HT_header.remove(draw_status)
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)
