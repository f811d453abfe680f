"""Pictures of results: a small dependency-free (numpy + Pillow) z-buffer software renderer,
used by the commands that write PNGs."""

from .raster import (
    BACKGROUND,
    Camera,
    box_mesh,
    clip_frame_meshes,
    frame_camera,
    render_clip_strip,
    render_meshes,
)

__all__ = [
    "BACKGROUND",
    "Camera",
    "box_mesh",
    "clip_frame_meshes",
    "frame_camera",
    "render_clip_strip",
    "render_meshes",
]
