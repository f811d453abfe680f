"""Objects of the demonstration clips, each a closed mesh plus the implicit function it was
extracted from (used as its signed distance while synthesising grasps).

Object frame: metres, Z up, the object resting upright with its lowest point at z = 0.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..mesh.implicit import capped_cylinder, rounded_box, smooth_union, sphere, tapered_capsule, torus_xz
from ..mesh.isosurface import closed_surface_from_field, sample_grid


@dataclass
class DemoObject:
    """vertices (V, 3), faces (F, 3) in the object frame; ``sdf(points (N, 3)) -> (N,)`` in the
    same frame, negative inside."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    sdf: Callable[[np.ndarray], np.ndarray]

    @property
    def height(self) -> float:
        return float(self.vertices[:, 2].max())


def _box(p):
    return rounded_box(p, np.array([0.0, 0.0, 0.0175]), np.eye(3), (0.0175, 0.0175, 0.0175), 0.002)


def _bottle(p):
    return capped_cylinder(p, 0.032, 0.0, 0.20, rounding=0.004)


def _apple(p):
    return sphere(p, (0.0, 0.0, 0.04), 0.04)


def _mug(p):
    outer = capped_cylinder(p, 0.040, 0.0, 0.095, rounding=0.003)
    cavity = capped_cylinder(p, 0.035, 0.007, 0.12, rounding=0.002)
    body = np.maximum(outer, -cavity)
    handle = torus_xz(p, (0.047, 0.0, 0.050), 0.026, 0.0065)
    handle = np.maximum(handle, 0.041 - p[:, 0])  # only the outer half of the ring
    return smooth_union(body, handle, 0.004)


def _hammer(p):
    # Standing on its head: head along X on the table, handle straight up.
    head = rounded_box(p, np.array([0.0, 0.0, 0.0175]), np.eye(3), (0.055, 0.0175, 0.0175), 0.003)
    handle = tapered_capsule(p, np.array([0.0, 0.0, 0.03]), np.array([0.0, 0.0, 0.30]), 0.0135, 0.0145)
    return smooth_union(head, handle, 0.004)


#: name -> (implicit function, bounding box lower, upper)
_SHAPES = {
    "box": (_box, (-0.02, -0.02, 0.0), (0.02, 0.02, 0.035)),
    "bottle": (_bottle, (-0.033, -0.033, 0.0), (0.033, 0.033, 0.20)),
    "apple": (_apple, (-0.041, -0.041, 0.0), (0.041, 0.041, 0.08)),
    "mug": (_mug, (-0.041, -0.041, 0.0), (0.081, 0.041, 0.096)),
    "hammer": (_hammer, (-0.056, -0.018, 0.0), (0.056, 0.018, 0.315)),
}

OBJECT_NAMES = tuple(_SHAPES)


def make_object(name: str, resolution: float = 0.002) -> DemoObject:
    """Build a demo object by name (box, bottle, apple, mug, hammer) at ``resolution`` metres."""
    if name not in _SHAPES:
        raise KeyError(f"unknown demo object {name!r}; known: {', '.join(_SHAPES)}")
    fn, lower, upper = _SHAPES[name]
    grid, shape, origin = sample_grid(np.array(lower), np.array(upper), resolution)
    vertices, faces = closed_surface_from_field(fn(grid).reshape(shape), origin, resolution, what=f"object {name!r}")
    # Rest exactly on z = 0.
    vertices[:, 2] -= vertices[:, 2].min()
    return DemoObject(name, vertices, faces, fn)
