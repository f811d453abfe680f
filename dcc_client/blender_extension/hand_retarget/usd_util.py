"""Blender's bundled OpenUSD (``pxr``).

Inside Blender ``pxr`` is importable as is. The ``bpy`` module from PyPI ships the same
libraries under ``<bpy>/<version>/python/lib/pythonX.Y/site-packages`` without putting them on
``sys.path`` (dcc_client/BLENDER_NOTES.md, section 2), so that folder is added when needed.
"""

from __future__ import annotations

import os
import sys


def pxr():
    """The ``pxr`` package with Usd, UsdGeom, UsdSkel, Sdf, Gf, Vt, Tf imported, or ImportError."""
    try:
        return _load()
    except ImportError:
        pass
    import bpy

    local = bpy.utils.resource_path("LOCAL")
    version = f"python{sys.version_info.major}.{sys.version_info.minor}"
    for folder in (os.path.join(local, "python", "lib", version, "site-packages"),
                   os.path.join(local, "python", "lib", "site-packages")):
        if os.path.isdir(os.path.join(folder, "pxr")) and folder not in sys.path:
            sys.path.append(folder)
    return _load()


def _load():
    import pxr as mod
    from pxr import Gf, Sdf, Tf, Usd, UsdGeom, UsdSkel, Vt  # noqa: F401  (binds the submodules)
    return mod
