"""Axial curves (paper section "Contact Alignment"): ordered landmarks joined by geodesics.

A source curve is the shortest geodesic between two artist points (or an explicit polyline),
resampled every ``spacing`` metres of arclength so that landmarks are evenly spread. It is
described intrinsically by its segment lengths and the turning angle at each landmark (from
the arriving direction to the leaving one, counter-clockwise about the outward normal), which
is what lets it be rebuilt on another surface: from the target start point and an initial
direction, trace each segment (length scaled by lambda_a), turn, and trace again.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..errors import InputError
from ..mesh.surface_points import SurfacePoints
from .geodesics import SurfaceGeometry


@dataclass
class Curve:
    """n landmarks on one surface: faces (n,), barycentric (n, 3), positions (n, 3), and each
    landmark's curve direction (n, 3) (leaving direction; the arriving one at the last)."""

    name: str
    faces: np.ndarray
    barycentric: np.ndarray
    positions: np.ndarray
    directions: np.ndarray

    def __len__(self) -> int:
        return len(self.faces)


@dataclass
class SourceCurve(Curve):
    """A source curve plus its intrinsic description: segment lengths (n-1,) metres and turning
    angles (n,) radians (0 at both ends)."""

    lengths: np.ndarray = None
    turning: np.ndarray = None


def _signed_angle(a: np.ndarray, b: np.ndarray, normal: np.ndarray) -> float:
    """Angle from a to b (tangent vectors) counter-clockwise about ``normal``."""
    a = a - (a @ normal) * normal
    b = b - (b @ normal) * normal
    return float(np.arctan2(np.cross(a, b) @ normal, a @ b))


def _rotate_about(v: np.ndarray, normal: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues rotation of a tangent vector about the unit normal."""
    return v * np.cos(angle) + np.cross(normal, v) * np.sin(angle) + normal * (normal @ v) * (1 - np.cos(angle))


def resample_polyline(path: np.ndarray, spacing: float) -> np.ndarray:
    """Points every ``spacing`` metres of arclength along path (K, 3), both ends included."""
    seg = np.linalg.norm(np.diff(path, axis=0), axis=1)
    arclength = np.concatenate([[0.0], np.cumsum(seg)])
    total = arclength[-1]
    if total <= 0:
        return path[:1].copy()
    n = max(1, int(np.round(total / spacing)))
    s = np.linspace(0.0, total, n + 1)
    return np.column_stack([np.interp(s, arclength, path[:, k]) for k in range(3)])


def build_source_curve(geometry: SurfaceGeometry, name: str, *, start: SurfacePoints | None = None,
                       end: SurfacePoints | None = None, points: SurfacePoints | None = None,
                       spacing: float = 0.002) -> SourceCurve:
    """Landmarks and intrinsic description of a source curve: the shortest geodesic from
    ``start`` to ``end`` (or the polyline through ``points``), resampled every ``spacing`` m."""
    if points is not None:
        anchors = geometry.positions(points)
        pieces = [geometry.shortest_path(SurfacePoints(points.faces[i:i + 1], points.barycentric[i:i + 1]),
                                         SurfacePoints(points.faces[i + 1:i + 2], points.barycentric[i + 1:i + 2]))
                  for i in range(len(anchors) - 1)]
        path = np.vstack([pieces[0]] + [p[1:] for p in pieces[1:]])
    else:
        path = geometry.shortest_path(start, end)
    samples = resample_polyline(path, spacing)
    if len(samples) < 2:
        raise InputError("the curve has no length (start and end coincide)", element=f"axial curve {name!r}")
    located = geometry.closest_points(samples)
    first = start if start is not None else SurfacePoints(points.faces[:1], points.barycentric[:1])
    faces, bary = located.faces.copy(), located.barycentric.copy()
    faces[0], bary[0] = first.faces[0], first.barycentric[0]
    positions = SurfacePoints(faces, bary).positions(geometry.vertices, geometry.faces)
    n = len(faces)
    normals = np.array([geometry.normal_at(int(faces[i]), bary[i]) for i in range(n)])
    chords = np.diff(positions, axis=0)
    lengths = np.linalg.norm(chords, axis=1)
    leaving = np.zeros((n, 3))
    arriving = np.zeros((n, 3))
    for i in range(n):
        if i < n - 1:
            leaving[i] = _tangent(chords[i], normals[i])
        if i > 0:
            arriving[i] = _tangent(chords[i - 1], normals[i])
    turning = np.zeros(n)
    for i in range(1, n - 1):
        turning[i] = _signed_angle(arriving[i], leaving[i], normals[i])
    directions = leaving.copy()
    directions[-1] = arriving[-1]
    return SourceCurve(name, faces, bary, positions, directions, lengths=lengths, turning=turning)


def _tangent(v: np.ndarray, normal: np.ndarray) -> np.ndarray:
    t = v - (v @ normal) * normal
    return t / np.linalg.norm(t)


def reconstruct_curve(geometry: SurfaceGeometry, source: SourceCurve, start: SurfacePoints,
                      direction_point: SurfacePoints, lambda_a: float) -> Curve:
    """Rebuild ``source`` on another surface: from ``start`` leave toward ``direction_point``,
    then trace every segment (length * lambda_a) and turn by the source's turning angles.
    Raises InputError when a trace stops early (the curve runs off the mesh boundary)."""
    if not lambda_a > 0:
        raise InputError(f"lambda_a must be positive, got {lambda_a}", element=f"axial curve {source.name!r}")
    n = len(source)
    faces = np.zeros(n, dtype=np.int64)
    bary = np.zeros((n, 3))
    positions = np.zeros((n, 3))
    directions = np.zeros((n, 3))
    f, b = int(start.faces[0]), start.barycentric[0]
    d = geometry.direction_toward(f, b, direction_point)
    faces[0], bary[0] = f, b
    positions[0] = b @ geometry.vertices[geometry.faces[f]]
    for i in range(n - 1):
        directions[i] = d
        length = float(source.lengths[i] * lambda_a)
        end = geometry.trace(f, b, d, length)
        if end.walked < length * (1 - 1e-6) - 1e-9:
            raise InputError(
                f"the reconstructed curve runs off the mesh boundary after {i + 1} of {n - 1} segments",
                element=f"axial curve {source.name!r} (target)",
            )
        f, b = end.face, end.barycentric
        faces[i + 1], bary[i + 1], positions[i + 1] = f, b, end.position
        normal = geometry.normal_at(f, b)
        d = _rotate_about(end.direction, normal, float(source.turning[i + 1]))
        d = d - (d @ normal) * normal
        d /= np.linalg.norm(d)
        if i + 1 == n - 1:
            directions[i + 1] = end.direction
    if n == 1:
        directions[0] = d
    return Curve(source.name, faces, bary, positions, directions)
