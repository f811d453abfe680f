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
    angles (n,) radians (0 at both ends); anchors (k,) the landmark index of each of the points
    it was drawn through (the first landmark, each leg's end)."""

    lengths: np.ndarray = None
    turning: np.ndarray = None
    anchors: np.ndarray = None


def _signed_angle(a: np.ndarray, b: np.ndarray, normal: np.ndarray) -> float:
    """Angle from a to b (tangent vectors) counter-clockwise about ``normal``."""
    a = a - (a @ normal) * normal
    b = b - (b @ normal) * normal
    return float(np.arctan2(np.cross(a, b) @ normal, a @ b))


def _rotate_about(v: np.ndarray, normal: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues rotation of a tangent vector about the unit normal."""
    return v * np.cos(angle) + np.cross(normal, v) * np.sin(angle) + normal * (normal @ v) * (1 - np.cos(angle))


def initial_direction(geometry: SurfaceGeometry, face: int, bary: np.ndarray, toward: SurfacePoints,
                      iterations: int = 8, tolerance: float = 1e-5):
    """Unit direction (3,) in which the geodesic from (face, bary) to ``toward`` leaves, and its
    length (m). A first guess comes from the shortest path (edge-flip geodesics, the log-map
    direction of the point 1 cm along it); then the direction and length are corrected by
    shooting: trace, measure how far to the side and short the end lands, turn and stretch,
    until the traced geodesic ends within ``tolerance`` of the point."""
    start = SurfacePoints(np.array([face]), np.asarray(bary, float)[None])
    path = geometry.shortest_path(start, toward)
    seg_lengths = np.linalg.norm(np.diff(path, axis=0), axis=1)
    total = float(seg_lengths.sum())
    if total < 1e-9:
        raise InputError("the curve has no length (its points coincide)")
    arclength = np.concatenate([[0.0], np.cumsum(seg_lengths)])
    aim_at = min(0.01, 0.5 * total)
    aim = np.array([np.interp(aim_at, arclength, path[:, k]) for k in range(3)])
    d = geometry.direction_toward(face, bary, geometry.closest_points(aim[None]))
    goal = geometry.positions(toward)[0]
    normal = geometry.face_normals[face]
    for _ in range(iterations):
        end = geometry.trace(face, bary, d, total)
        miss = goal - end.position
        end_normal = geometry.normal_at(end.face, end.barycentric)
        left = np.cross(end_normal, end.direction)
        lateral, along = float(miss @ left), float(miss @ end.direction)
        if abs(lateral) < tolerance and abs(along) < tolerance:
            break
        d = _rotate_about(d, normal, np.arctan2(lateral, total))
        d = d - (d @ normal) * normal
        d /= np.linalg.norm(d)
        total = max(total + along, 1e-6)
    return d, total


def _geodesic_leg(geometry: SurfaceGeometry, face: int, bary: np.ndarray, toward: SurfacePoints, spacing: float):
    """Landmarks every ~spacing metres along the geodesic from (face, bary) to ``toward``
    (see :func:`initial_direction`), traced segment by segment. Returns (faces, barycentrics,
    positions, leaving directions, segment lengths)."""
    d, total = initial_direction(geometry, face, bary, toward)
    n_seg = max(1, int(round(total / spacing)))
    seg = total / n_seg
    faces, barys, positions, directions = [face], [np.asarray(bary, float)], [bary @ geometry.vertices[geometry.faces[face]]], [d]
    f, b = face, np.asarray(bary, float)
    for i in range(n_seg):
        end = geometry.trace(f, b, d, seg)
        if end.walked < seg * (1 - 1e-6) - 1e-9:
            raise InputError("the source curve runs off the mesh boundary")
        f, b, d = end.face, end.barycentric, end.direction
        faces.append(f)
        barys.append(b)
        positions.append(end.position)
        directions.append(d)
    return faces, barys, positions, directions, [seg] * n_seg


def build_source_curve(geometry: SurfaceGeometry, name: str, *, start: SurfacePoints | None = None,
                       end: SurfacePoints | None = None, points: SurfacePoints | None = None,
                       spacing: float = 0.002) -> SourceCurve:
    """Landmarks and intrinsic description of a source curve: the geodesic from ``start``
    toward ``end`` (or through each of ``points`` in turn), landmarks every ~``spacing`` m.

    Each leg is the geodesic leaving its first point in the log-map direction of the next point,
    as long as the log-map distance to it, traced in steps; turning angles are 0 inside a leg
    and, at an interior anchor point, the turn from the arriving leg to the leaving one."""
    anchors = points if points is not None else SurfacePoints(np.concatenate([start.faces, end.faces]),
                                                              np.vstack([start.barycentric, end.barycentric]))
    if len(anchors) < 2:
        raise InputError("a curve needs at least two points", element=f"axial curve {name!r}")
    faces, barys, positions, leaving, lengths, turning = [], [], [], [], [], []
    anchor_index = [0]
    arriving = None
    f, b = int(anchors.faces[0]), anchors.barycentric[0]
    for k in range(len(anchors) - 1):
        toward = SurfacePoints(anchors.faces[k + 1:k + 2], anchors.barycentric[k + 1:k + 2])
        try:
            lf, lb, lp, ld, ll = _geodesic_leg(geometry, f, b, toward, spacing)
        except InputError as err:
            raise InputError(str(err), element=f"axial curve {name!r} (source, leg {k + 1})") from err
        if arriving is not None:  # the anchor point: turn from the arriving leg to the leaving one
            normal = geometry.face_normals[lf[0]]
            turning[-1] = _signed_angle(arriving, ld[0], normal)
            leaving[-1] = ld[0]
            lf, lb, lp, ld = lf[1:], lb[1:], lp[1:], ld[1:]
        faces += lf
        barys += lb
        positions += lp
        leaving += ld
        lengths += ll
        turning += [0.0] * len(lf)
        arriving = ld[-1]
        f, b = faces[-1], barys[-1]
        anchor_index.append(len(faces) - 1)
    turning[-1] = 0.0
    return SourceCurve(name, np.array(faces, dtype=np.int64), np.array(barys), np.array(positions),
                       np.array(leaving), lengths=np.array(lengths), turning=np.array(turning),
                       anchors=np.array(anchor_index, dtype=np.int64))


def reconstruct_curve(geometry: SurfaceGeometry, source: SourceCurve, start: SurfacePoints,
                      direction_point: SurfacePoints, lambda_a: float,
                      through: SurfacePoints | None = None) -> Curve:
    """Rebuild ``source`` on another surface: from ``start`` leave toward ``direction_point``,
    then trace every segment (length * lambda_a) and turn by the source's turning angles.
    With ``through`` (one target point per source anchor after the first), the curve is
    anchored instead: leg k runs from anchor k to through[k] in the source leg's number of
    landmarks (see :func:`_anchored_curve`).
    Raises InputError when a trace stops early (the curve runs off the mesh boundary)."""
    if through is not None:
        return _anchored_curve(geometry, source, start, through)
    if not lambda_a > 0:
        raise InputError(f"lambda_a must be positive, got {lambda_a}", element=f"axial curve {source.name!r}")
    n = len(source)
    faces = np.zeros(n, dtype=np.int64)
    bary = np.zeros((n, 3))
    positions = np.zeros((n, 3))
    directions = np.zeros((n, 3))
    f, b = int(start.faces[0]), start.barycentric[0]
    d, _ = initial_direction(geometry, f, b, direction_point)
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
        d = end.direction  # already in the plane of face f
        if source.turning[i + 1] != 0.0:
            d = _rotate_about(d, geometry.face_normals[f], float(source.turning[i + 1]))
        if i + 1 == n - 1:
            directions[i + 1] = end.direction
    if n == 1:
        directions[0] = d
    return Curve(source.name, faces, bary, positions, directions)


def _anchored_curve(geometry: SurfaceGeometry, source: SourceCurve, start: SurfacePoints,
                    through: SurfacePoints) -> Curve:
    """``source`` rebuilt through target anchors: leg k is the geodesic from anchor k (``start``
    for the first) toward ``through[k]``, cut into as many equal segments as the source's leg k,
    and ends on its anchor, so the landmarks correspond one to one with the source's
    (same fraction of the same leg) and every anchor lies (to the shooting tolerance, 1e-5 m) on
    the target's own anatomy however
    differently the two fingers bend or twist."""
    anchors = source.anchors
    if anchors is None or len(anchors) != len(through) + 1:
        n_given = "no" if anchors is None else len(anchors) - 1
        raise InputError(f"the target has {len(through)} 'through' points but the source curve has {n_given} legs",
                         element=f"axial curve {source.name!r} (target)")
    n = len(source)
    faces = np.zeros(n, dtype=np.int64)
    bary = np.zeros((n, 3))
    positions = np.zeros((n, 3))
    directions = np.zeros((n, 3))
    f, b = int(start.faces[0]), np.asarray(start.barycentric[0], dtype=np.float64)
    faces[0], bary[0] = f, b
    positions[0] = b @ geometry.vertices[geometry.faces[f]]
    for k in range(len(through)):
        first, last = int(anchors[k]), int(anchors[k + 1])
        toward = SurfacePoints(through.faces[k:k + 1], through.barycentric[k:k + 1])
        try:
            d, total = initial_direction(geometry, f, b, toward)
        except InputError as err:
            raise InputError(str(err), element=f"axial curve {source.name!r} (target, leg {k + 1})") from err
        step = total / max(1, last - first)
        for i in range(first, last):
            directions[i] = d
            end = geometry.trace(f, b, d, step)
            if end.walked < step * (1 - 1e-6) - 1e-9:
                raise InputError(f"the reconstructed curve runs off the mesh boundary in leg {k + 1}",
                                 element=f"axial curve {source.name!r} (target)")
            f, b, d = end.face, end.barycentric, end.direction
            faces[i + 1], bary[i + 1], positions[i + 1] = f, b, end.position
            directions[i + 1] = d
        # the next leg leaves from where this one's trace ended (within initial_direction's
        # tolerance of the anchor), as build_source_curve does, so a hand onto itself gives its
        # own curve back
    return Curve(source.name, faces, bary, positions, directions)
