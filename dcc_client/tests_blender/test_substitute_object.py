"""Substituting the clip's object from Blender: the selected mesh (the clip's bottle as a
Blender object, turned and moved as if modelled elsewhere) is exported as OBJ, registered by
the real service onto the clip's object, and Retarget then uses the clip it made."""

import math

import numpy as np
import pytest

from conftest import SKIP_REASON

if SKIP_REASON:
    pytest.skip(SKIP_REASON, allow_module_level=True)

from conftest import bpy, ext

pytestmark = pytest.mark.usefixtures("addon")


def _bottle_object(clip_path, name="NewBottle"):
    """The clip's bottle as a Blender object in the scene's units (another test may have left the
    scene in centimetres: 1 unit = scale_length metres), turned and moved."""
    with np.load(clip_path) as data:
        vertices, faces = data["object_vertices"], data["object_faces"]
    unit = bpy.context.scene.unit_settings.scale_length or 1.0
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata((vertices / unit).tolist(), [], faces.tolist())
    mesh.update()
    obj = bpy.data.objects.new(name, mesh)
    bpy.context.scene.collection.objects.link(obj)
    obj.rotation_euler = (math.radians(35), math.radians(-20), math.radians(110))
    obj.location = tuple(np.array([0.4, -0.3, 0.2]) / unit)
    return obj


@pytest.fixture
def scene_unit():
    """Sets the scene's unit scale for a test and puts the previous one back after it."""
    settings = bpy.context.scene.unit_settings
    before = settings.scale_length

    def set_unit(value):
        settings.scale_length = value
    yield set_unit
    settings.scale_length = before


@pytest.mark.parametrize("unit", [1.0, 0.01])
def test_the_selected_mesh_becomes_the_clips_object(addon, service, inputs, unit, scene_unit):
    """In metres and in a centimetre scene: the object is exported in metres either way."""
    scene_unit(unit)
    url, token = service
    addon.server_url, addon.token = url, token
    s = bpy.context.scene.hand_retarget
    s.clip_kind, s.clip_path = 'NATIVE', str(inputs["clip"])
    obj = _bottle_object(inputs["clip"])
    for other in bpy.context.selected_objects:
        other.select_set(False)
    obj.select_set(True)
    bpy.context.view_layer.objects.active = obj
    assert 'FINISHED' in bpy.ops.hand_retarget.substitute_object()
    assert len(s.substitute_clip_id) == 64 and s.use_substitute and s.substitute_object == obj.name
    assert "% of the contacts carried over" in s.substitute_report
    client = ext("jobs").make_client(bpy.context)
    (made,) = [a for a in client.assets("clip") if a["id"] == s.substitute_clip_id]
    sub = made["info"]["substitution"]
    assert sub["share"] >= 0.95 and sub["residual_mm"] < 1.0  # the same bottle, turned and moved
    # the transform found undoes the object's turn and move (Blender's axes are the clip's) up
    # to a turn of the round bottle about its own axis (z)
    metres = np.diag([unit, unit, unit, 1.0])  # scene units -> metres
    placed = np.array(sub["transform"]) @ metres @ np.array(obj.matrix_world) @ np.linalg.inv(metres)
    np.testing.assert_allclose(placed[:3, 2], [0, 0, 1], atol=2e-3)
    np.testing.assert_allclose(placed[2, :3], [0, 0, 1], atol=2e-3)
    np.testing.assert_allclose(placed[:3, 3], 0.0, atol=1e-3)
    # Retarget would send that clip; with the clip changed underneath it refuses
    ops = ext("ops")
    assert ops.HAND_RETARGET_OT_submit.upload_clip(client, s) == s.substitute_clip_id
    s.use_substitute = False
    assert ops.HAND_RETARGET_OT_submit.upload_clip(client, s) == s.substitute_from_clip_id


def test_a_skinned_or_missing_selection_is_refused(addon, service, inputs):
    url, token = service
    addon.server_url, addon.token = url, token
    for other in bpy.context.selected_objects:
        other.select_set(False)
    bpy.context.view_layer.objects.active = None
    with pytest.raises(RuntimeError, match="select the new object"):
        bpy.ops.hand_retarget.substitute_object()
