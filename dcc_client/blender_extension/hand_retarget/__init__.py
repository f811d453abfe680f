"""Hand Retarget for Blender: export your hand rig, annotate it, send a captured clip to the
Hand Retarget service and get the motion back as editable F-curves.

``client`` and ``curves`` are the project's standard-library modules (dcc_client/client.py,
dcc_client/curves.py), copied in by dcc_client/build_extension.py when the extension is built.
"""

from . import client, curves  # noqa: F401  (staged at build time)
from . import draw, jobs, ops, props, ui


def register():
    import bpy

    props.register()
    for cls in ops.CLASSES:
        bpy.utils.register_class(cls)
    ui.register()
    draw.register()


def unregister():
    import bpy

    jobs.stop_polling()
    draw.unregister()
    ui.unregister()
    for cls in reversed(ops.CLASSES):
        bpy.utils.unregister_class(cls)
    props.unregister()
