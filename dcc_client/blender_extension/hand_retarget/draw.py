"""Viewport drawing of the annotations (gpu module): marker vertices as points, each axial
curve's target as a segment from its start to its direction vertex. Not registered in
background mode: there is no viewport, and the gpu module refuses to draw ("GPU functions for
drawing are not available in background mode"), so this part is not covered by the tests."""

from __future__ import annotations

import bpy

from . import annotations
from .ops import targets

MARKER_COLOR = (1.0, 0.55, 0.0, 1.0)
CURVE_COLOR = (0.1, 0.8, 1.0, 1.0)
_HANDLE = None


def _shader(point: bool):
    import gpu

    for name in (("POINT_UNIFORM_COLOR",) if point else ()) + ("UNIFORM_COLOR",):
        try:
            return gpu.shader.from_builtin(name)
        except (ValueError, TypeError):
            continue
    raise RuntimeError("no uniform-colour shader")


def _positions(context, mesh_obj):
    """World positions of the posed (evaluated) mesh's vertices, as a list."""
    depsgraph = context.evaluated_depsgraph_get()
    ev = mesh_obj.evaluated_get(depsgraph)
    me = ev.to_mesh()
    try:
        mw = ev.matrix_world
        return [mw @ v.co for v in me.vertices]
    finally:
        ev.to_mesh_clear()


def draw_annotations():
    context = bpy.context
    s = getattr(context.scene, "hand_retarget", None)
    if s is None or not s.show_annotations:
        return
    arm, mesh_obj = targets(context)
    if mesh_obj is None:
        return
    import gpu
    from gpu_extras.batch import batch_for_shader

    groups = annotations.marker_vertices(mesh_obj, exclude=annotations.bone_names(arm))
    curves = [c for c in mesh_obj.hand_retarget.curves if not c.discard]
    if not any(groups.values()) and not curves:
        return
    pos = _positions(context, mesh_obj)
    n = len(pos)
    points = [pos[v] for verts in groups.values() for v in verts if v < n]
    lines = [pos[i] for c in curves for i in (c.start_vertex, c.direction_vertex) if max(c.start_vertex, c.direction_vertex) < n]
    gpu.state.depth_test_set('NONE')
    if points:
        sh = _shader(True)
        gpu.state.point_size_set(8.0)
        batch = batch_for_shader(sh, 'POINTS', {"pos": points})
        sh.uniform_float("color", MARKER_COLOR)
        batch.draw(sh)
    if lines:
        region = context.region
        try:  # wide lines need the polyline shader on Metal / Vulkan
            sh = gpu.shader.from_builtin("POLYLINE_UNIFORM_COLOR")
            sh.uniform_float("viewportSize", (region.width, region.height))
            sh.uniform_float("lineWidth", 3.0)
        except (ValueError, TypeError, AttributeError):
            sh = _shader(False)
        batch = batch_for_shader(sh, 'LINES', {"pos": lines})
        sh.uniform_float("color", CURVE_COLOR)
        batch.draw(sh)


def register():
    global _HANDLE
    if bpy.app.background or _HANDLE is not None:
        return
    _HANDLE = bpy.types.SpaceView3D.draw_handler_add(draw_annotations, (), 'WINDOW', 'POST_VIEW')


def unregister():
    global _HANDLE
    if _HANDLE is not None:
        bpy.types.SpaceView3D.draw_handler_remove(_HANDLE, 'WINDOW')
        _HANDLE = None
