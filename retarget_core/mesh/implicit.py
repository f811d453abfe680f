"""Implicit shapes (signed distance, negative inside) used to build closed hand surfaces.

All functions take points (N, 3) in metres and return (N,) values. The tapered capsule is a
bound rather than an exact distance, which is all a level-set extraction needs.
"""

from __future__ import annotations

import numpy as np

from .geometry import box_signed_distance_local


def tapered_capsule(points: np.ndarray, a: np.ndarray, b: np.ndarray, radius_a: float, radius_b: float) -> np.ndarray:
    """Segment a-b swept by a sphere whose radius varies linearly from radius_a to radius_b."""
    ab = np.asarray(b, float) - np.asarray(a, float)
    t = np.clip((points - a) @ ab / max(float(ab @ ab), 1e-30), 0.0, 1.0)
    closest = a + t[:, None] * ab
    return np.linalg.norm(points - closest, axis=1) - (radius_a + t * (radius_b - radius_a))


def rounded_box(points: np.ndarray, center: np.ndarray, rotation: np.ndarray, half_extents, rounding: float) -> np.ndarray:
    """Box with the given centre, rotation (3, 3, columns = box axes in world) and half
    extents (3,), its edges rounded with radius ``rounding`` (the outer size is kept)."""
    local = (points - center) @ rotation
    return box_signed_distance_local(local, np.asarray(half_extents, float) - rounding) - rounding


def smooth_union(d1: np.ndarray, d2: np.ndarray, k: float) -> np.ndarray:
    """Union of two shapes blended over a band of width ``k`` (metres); k = 0 is a plain min."""
    if k <= 0:
        return np.minimum(d1, d2)
    h = np.clip(0.5 + 0.5 * (d2 - d1) / k, 0.0, 1.0)
    return d2 + (d1 - d2) * h - k * h * (1.0 - h)


def capped_cylinder(points: np.ndarray, radius: float, z0: float, z1: float, rounding: float = 0.0) -> np.ndarray:
    """Cylinder about the Z axis from z0 to z1 with the given radius; edges rounded by ``rounding``."""
    radial = np.linalg.norm(points[:, :2], axis=1) - (radius - rounding)
    axial = np.abs(points[:, 2] - 0.5 * (z0 + z1)) - (0.5 * (z1 - z0) - rounding)
    outside = np.sqrt(np.maximum(radial, 0.0) ** 2 + np.maximum(axial, 0.0) ** 2)
    return outside + np.minimum(np.maximum(radial, axial), 0.0) - rounding


def sphere(points: np.ndarray, center, radius: float) -> np.ndarray:
    return np.linalg.norm(points - np.asarray(center, float), axis=1) - radius


def torus_xz(points: np.ndarray, center, major: float, minor: float) -> np.ndarray:
    """Torus whose ring lies in the XZ plane around ``center``."""
    p = points - np.asarray(center, float)
    ring = np.sqrt(p[:, 0] ** 2 + p[:, 2] ** 2) - major
    return np.sqrt(ring**2 + p[:, 1] ** 2) - minor
