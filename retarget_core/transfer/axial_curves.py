"""Axial curves (paper section "Contact Alignment"): ordered landmarks joined by geodesics.

A source curve is the shortest geodesic between two artist points (or an explicit polyline),
resampled every ``spacing`` metres of arclength so that landmarks are evenly spread. It is
described intrinsically by its segment lengths and the turning angle at each landmark (from
the arriving direction to the leaving one, counter-clockwise about the outward normal), which
is what lets it be rebuilt on another surface: from the target start point and an initial
direction, trace each segment (length scaled by lambda_a), turn, and trace again. A target
given points of its own to pass through (``through``) is rebuilt leg by leg instead, every leg
ending on its point (:func:`_anchored_curve`).
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


def initial_direction(geometry: SurfaceGeometry, face: int, bary: np.ndarray, toward: SurfacePoints) -> np.ndarray:
    """Unit direction (3,) in which the geodesic from (face, bary) to ``toward`` leaves: the
    straightest geodesic's when a shot lands on the point (:func:`_shoot`, as :func:`_leg`
    accepts one), else the shortest path's (its chord to the point 1 cm along it, in the start
    face's plane)."""
    start = SurfacePoints(np.array([face]), np.asarray(bary, float)[None])
    path = geometry.shortest_path(start, toward)
    d, total, miss = _shoot(geometry, face, bary, toward, path)
    chord = None if miss <= 1e-4 and total <= 1.01 * _length(path) + 1e-4 else _chord_direction(geometry, face, path)
    return d if chord is None else chord


def _length(path: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum())


def _chord_direction(geometry: SurfaceGeometry, face: int, path: np.ndarray) -> np.ndarray | None:
    """Unit direction (3,) in ``face``'s plane from the path's start to its point 1 cm along it
    (or halfway, on a shorter path); None when that chord is along the normal."""
    seg_lengths = np.linalg.norm(np.diff(path, axis=0), axis=1)
    arclength = np.concatenate([[0.0], np.cumsum(seg_lengths)])
    aim_at = min(0.01, 0.5 * arclength[-1])
    aim = np.array([np.interp(aim_at, arclength, path[:, k]) for k in range(3)])
    normal = geometry.face_normals[face]
    chord = aim - path[0] - ((aim - path[0]) @ normal) * normal
    norm = np.linalg.norm(chord)
    return chord / norm if norm > 1e-9 else None


def _shoot(geometry: SurfaceGeometry, face: int, bary: np.ndarray, toward: SurfacePoints, path: np.ndarray,
           iterations: int = 60, tolerance: float = 1e-5):
    """The straightest geodesic from (face, bary) that ends on ``toward``: its unit leaving
    direction (3,), length (m) and how far (m) its end missed the point. ``path`` (K, 3) is the
    shortest path between the two (first guesses: the log-map direction of the point 1 cm along
    it, and the chord to that point). Each shot is traced, then turned by how far to the side it
    landed and stretched by how short, until it ends within ``tolerance`` (m); the turn uses the
    end's measured sideways sensitivity to the angle (a secant over the last two shots), not the
    flat-plane value ``length``: on a tapering finger geodesics converge, the flat estimate
    under-corrects, and eight flat-plane shots had still missed by 8 mm on a witch's pinky."""
    total = _length(path)
    if total < 1e-9:
        raise InputError("the curve has no length (its points coincide)")
    seg_lengths = np.linalg.norm(np.diff(path, axis=0), axis=1)
    arclength = np.concatenate([[0.0], np.cumsum(seg_lengths)])
    aim = np.array([np.interp(min(0.01, 0.5 * total), arclength, path[:, k]) for k in range(3)])
    goal = geometry.positions(toward)[0]
    normal = geometry.face_normals[face]
    # the log map can point the wrong way at a crease on a coarse mesh: of the two first
    # guesses, the shot that lands nearer the goal starts the search
    guesses = [geometry.direction_toward(face, bary, geometry.closest_points(aim[None]))]
    chord = _chord_direction(geometry, face, path)
    if chord is not None:
        guesses.append(chord)
    d0 = min(guesses, key=lambda g: float(np.linalg.norm(goal - geometry.trace(face, bary, g, total).position)))
    angle, previous = 0.0, None  # angle turned from d0 about the normal; (angle, lateral) of the last shot
    best = (np.inf, d0, total)
    for _ in range(iterations):
        d = _rotate_about(d0, normal, angle)
        d = d - (d @ normal) * normal
        d /= np.linalg.norm(d)
        end = geometry.trace(face, bary, d, total)
        miss = goal - end.position
        if np.linalg.norm(miss) < best[0]:
            best = (float(np.linalg.norm(miss)), d, total)
        end_normal = geometry.normal_at(end.face, end.barycentric)
        left = np.cross(end_normal, end.direction)
        lateral, along = float(miss @ left), float(miss @ end.direction)
        if abs(lateral) < tolerance and abs(along) < tolerance:
            break
        # sideways metres the end moves per radian of turn: the flat plane's `total`, or the
        # secant over the last two shots when it is plausible (a fold or a tip can make the
        # local slope meaningless; then the flat value stands)
        slope = total
        if previous is not None and abs(angle - previous[0]) > 1e-9:
            measured = (previous[1] - lateral) / (angle - previous[0])
            if 0.1 * total < measured < 10 * total:
                slope = measured
        previous = (angle, lateral)
        angle += float(np.clip(lateral / slope, -0.5, 0.5))
        total = max(total + along, 1e-6)
    miss, d, total = best
    return d, total, miss


def _leg(geometry: SurfaceGeometry, start: SurfacePoints, end: SurfacePoints,
         n_segments: int | None = None, spacing: float | None = None):
    """``n_segments + 1`` landmarks (or one every ~``spacing`` m) at equal arclength along the
    geodesic from ``start`` to ``end``, both ends exactly on their points. Returns faces (m,),
    barycentrics (m, 3), positions (m, 3) and unit leaving directions (m, 3) (arriving at the
    end).

    The geodesic is the straightest one traced from ``start`` (exact between any two surface
    points) when a shot reaches ``end`` within 0.1 mm and is no longer than the shortest path
    (+1 %); otherwise (a shot that cannot land, or one that lands after winding round a finger)
    the shortest path itself, which runs between the vertices nearest the two points."""
    path = geometry.shortest_path(start, end)
    f, b = int(start.faces[0]), np.asarray(start.barycentric[0], dtype=np.float64)
    d, total, miss = _shoot(geometry, f, b, end, path)
    landed = miss <= 1e-4 and total <= 1.01 * _length(path) + 1e-4
    if n_segments is None:
        n_segments = max(1, int(round((total if landed else _length(path)) / spacing)))
    if not landed:
        return _polyline_leg(geometry, start, end, path, n_segments)
    step = total / n_segments
    faces, barys, positions, directions = [f], [b], [b @ geometry.vertices[geometry.faces[f]]], [d]
    for _ in range(n_segments):
        traced = geometry.trace(f, b, d, step)
        if traced.walked < step * (1 - 1e-6) - 1e-9:
            raise InputError("the curve runs off the mesh boundary")
        f, b, d = traced.face, traced.barycentric, traced.direction
        faces.append(f)
        barys.append(b)
        positions.append(traced.position)
        directions.append(d)
    # the trace ended within 0.1 mm of the point: put the last landmark on it exactly
    faces[-1], barys[-1] = int(end.faces[0]), np.asarray(end.barycentric[0], dtype=np.float64)
    positions[-1] = barys[-1] @ geometry.vertices[geometry.faces[faces[-1]]]
    directions[-1] = geometry._tangent_in_face(faces[-1], directions[-1])
    return np.array(faces, dtype=np.int64), np.array(barys), np.array(positions), np.array(directions)


def build_source_curve(geometry: SurfaceGeometry, name: str, *, start: SurfacePoints | None = None,
                       end: SurfacePoints | None = None, points: SurfacePoints | None = None,
                       spacing: float = 0.002) -> SourceCurve:
    """Landmarks and intrinsic description of a source curve: the geodesic from ``start``
    toward ``end`` (or through each of ``points`` in turn), landmarks every ~``spacing`` m.

    Each leg is the shortest geodesic to its next point (see :func:`_leg`); turning
    angles are 0 inside a leg and, at an interior anchor point, the turn from the arriving leg
    to the leaving one."""
    anchors = points if points is not None else SurfacePoints(np.concatenate([start.faces, end.faces]),
                                                              np.vstack([start.barycentric, end.barycentric]))
    if len(anchors) < 2:
        raise InputError("a curve needs at least two points", element=f"axial curve {name!r}")
    faces, barys, positions, leaving, lengths, turning = [], [], [], [], [], []
    anchor_index = [0]
    arriving = None
    leg_start = SurfacePoints(anchors.faces[:1], anchors.barycentric[:1])
    for k in range(len(anchors) - 1):
        toward = SurfacePoints(anchors.faces[k + 1:k + 2], anchors.barycentric[k + 1:k + 2])
        try:
            lf, lb, lp, ld = _leg(geometry, leg_start, toward, spacing=spacing)
        except InputError as err:
            raise InputError(str(err), element=f"axial curve {name!r} (source, leg {k + 1})") from err
        lf, lb, lp, ld = list(lf), list(lb), list(lp), list(ld)
        ll = list(np.linalg.norm(np.diff(np.asarray(lp), axis=0), axis=1))
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
        leg_start = toward
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
    d = initial_direction(geometry, f, b, direction_point)
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
    """``source`` rebuilt through target anchors: leg k follows the geodesic from anchor k
    (``start`` for the first) to ``through[k]`` (see :func:`_leg`), cut into as many
    equal segments as the source's leg k, so the landmarks correspond one to one with the
    source's (same fraction of the same leg) and every anchor lies exactly on its point, on the
    target's own anatomy however differently the two fingers bend or twist."""
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
    leg_start = SurfacePoints(np.asarray(start.faces[:1]), np.asarray(start.barycentric[:1], dtype=np.float64))
    for k in range(len(through)):
        first, last = int(anchors[k]), int(anchors[k + 1])
        toward = SurfacePoints(through.faces[k:k + 1], through.barycentric[k:k + 1])
        try:
            lf, lb, lp, ld = _leg(geometry, leg_start, toward, max(1, last - first))
        except InputError as err:
            raise InputError(str(err), element=f"axial curve {source.name!r} (target, leg {k + 1})") from err
        faces[first:last + 1], bary[first:last + 1], positions[first:last + 1] = lf, lb, lp
        directions[first:last] = ld[:-1]
        directions[last] = ld[-1]  # arriving; the next leg overwrites it with its leaving direction
        leg_start = toward
    return Curve(source.name, faces, bary, positions, directions)


def _polyline_leg(geometry: SurfaceGeometry, start: SurfacePoints, end: SurfacePoints, path: np.ndarray,
                  n_segments: int):
    """``n_segments + 1`` landmarks at equal arclength along the polyline ``path`` (K, 3) from
    ``start`` to ``end`` (both ends exact), in the layout :func:`_leg` returns; directions are
    the tangent of the landmarks' polyline in each landmark's face."""
    lengths = np.linalg.norm(np.diff(path, axis=0), axis=1)
    keep = np.concatenate([[True], lengths > 1e-12])
    path, lengths = path[keep], lengths[lengths > 1e-12]
    if len(path) < 2:
        raise InputError("the curve has no length (its points coincide)")
    arclength = np.concatenate([[0.0], np.cumsum(lengths)])
    s = np.linspace(0.0, arclength[-1], n_segments + 1)
    positions = np.stack([np.interp(s, arclength, path[:, j]) for j in range(3)], axis=1)
    points = geometry.closest_points(positions)
    faces, bary = points.faces.copy(), points.barycentric.copy()
    faces[0], bary[0] = int(start.faces[0]), np.asarray(start.barycentric[0], dtype=np.float64)
    faces[-1], bary[-1] = int(end.faces[0]), np.asarray(end.barycentric[0], dtype=np.float64)
    positions = np.einsum("ij,ijk->ik", bary, geometry.vertices[geometry.faces[faces]])
    # the tangent over the landmarks on either side (one side at the ends): the path between
    # vertices kinks where it leaves the exact start and reaches the exact end (27 deg on a
    # 14 mm cylinder), and a landmark's direction fixes its chart's angle 0
    tangents = np.gradient(positions, axis=0)
    normals = geometry.face_normals[faces]
    tangents = tangents - np.sum(tangents * normals, axis=1, keepdims=True) * normals
    norms = np.linalg.norm(tangents, axis=1, keepdims=True)
    if np.any(norms < 1e-9):
        raise InputError("the shortest path runs along a surface normal (a degenerate face under a landmark)")
    return faces, bary, positions, tangents / norms
