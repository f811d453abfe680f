"""Artist annotations pairing a source hand with a target hand: virtual markers and axial curves.

Paper: "Virtual Marker Alignment", "Contact Alignment" and the appendix "Artist Annotation
Procedures". The annotations are made once per (source hand, target hand) pair and stored as
JSON (``format`` "handretarget.annotations", ``version`` 2, or 1 without positions); the
published JSON Schema (draft 2020-12) is ``annotations.schema.json`` beside this module
(:func:`annotations_schema`)::

    {
      "format": "handretarget.annotations", "version": 1,
      "source": {"rig": "source_human", "vertices": 3784, "faces": 7564},
      "target": {"rig": "alien", "vertices": 9000, "faces": 17996},
      "landmark_spacing": 0.002,
      "markers": [{"name": "IndexTip", "source": [{"vertex": 316}],
                   "target": [{"face": 10, "barycentric": [0.2, 0.3, 0.5]}, {"vertex": 77}]}],
      "axial_curves": [
        {"name": "index",
         "source": {"start": {"vertex": 1}, "end": {"vertex": 2}},
         "target": {"start": {"vertex": 9}, "direction": {"vertex": 30},
                    "lambda_a": 1.27, "lambda_s": 1.5}},
        {"name": "ring", "source": {"points": [{"vertex": 5}, {"vertex": 6}]}, "target": "discard"}
      ]
    }

* A point is ``{"vertex": v}`` or ``{"face": f, "barycentric": [a, b, c]}`` (non-negative, sum
  1 within 1e-6); indices refer to the mesh named by the ``source`` / ``target`` signature.
* A marker's two sides are lists of points: 1 and 1 (one-to-one), 1 and n (one-to-many),
  n and 1 (many-to-one), n and n (area-to-area, paired by index). n and m (both > 1, n != m)
  is an error.
* An axial curve's source is ``{start, end}`` (the shortest geodesic between them, traced
  elsewhere) or ``{points: [...]}`` (an explicit ordered polyline, >= 2 points). Its target is
  ``"discard"`` (contacts of its charts are dropped) or ``{start, direction, lambda_a,
  lambda_s}``: ``start`` is the origin of the reconstructed axis, the geodesic from ``start``
  towards ``direction`` gives its initial outgoing direction, ``lambda_a`` > 0 scales lengths
  along the axis and ``lambda_s`` (a positive number, or a periodic piecewise-linear function
  of the log-map angle) scales the radial log-map coordinate of transferred contacts.
* ``landmark_spacing`` (metres, > 0, default 0.002): resampling density of curves into
  landmarks.
* Version 2 adds, optionally, a point's rest ``"position": [x, y, z]`` (metres: where the point
  lies on the mesh it was made for, at that rig's bind pose) and a signature's
  ``"surface_sha256"`` (:func:`surface_sha256` of that mesh's vertices and faces, so an edit
  that keeps the counts is noticed too). With positions, annotations survive a mesh edit:
  :func:`remap_to_meshes` moves every point to the closest point of the edited surface and
  reports (and bounds) the displacement. :func:`with_positions` fills them in; a file is
  written as version 2 when it carries any, else as version 1. Version 1 files still read.
"""

from __future__ import annotations

import functools
import hashlib
import json
import logging
import math
from dataclasses import dataclass, field, replace
from importlib import resources
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import atomic_path
from ..mesh.surface_points import SurfacePoints, closest_surface_points

logger = logging.getLogger(__name__)

ANNOTATIONS_FORMAT = "handretarget.annotations"
#: The version written when points carry positions; :data:`READ_VERSIONS` are read.
ANNOTATIONS_VERSION = 2
READ_VERSIONS = (1, 2)
#: :func:`remap_to_meshes` refuses to move a point further than this by default (metres).
DEFAULT_MAX_DISPLACEMENT = 0.003
#: A remapped point counts as moved when it moves further than this (metres).
MOVED_TOLERANCE = 1e-9
DEFAULT_LANDMARK_SPACING = 0.002  # metres
SCHEMA_RESOURCE = "annotations.schema.json"
BARYCENTRIC_TOLERANCE = 1e-6

MARKER_KINDS = ("one-to-one", "one-to-many", "many-to-one", "area-to-area")

__all__ = [
    "ANNOTATIONS_FORMAT",
    "ANNOTATIONS_VERSION",
    "READ_VERSIONS",
    "DEFAULT_LANDMARK_SPACING",
    "DEFAULT_MAX_DISPLACEMENT",
    "MARKER_KINDS",
    "PointRef",
    "resolve_points",
    "MarkerPair",
    "LambdaS",
    "CurveTarget",
    "AxialCurveAnnotation",
    "MeshSignature",
    "Annotations",
    "annotations_schema",
    "annotations_from_dict",
    "annotations_to_dict",
    "load_annotations",
    "save_annotations",
    "surface_sha256",
    "with_positions",
    "SideRemap",
    "RemapReport",
    "remap_to_meshes",
]


def _finite_number(value, what: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InputError(f"{what} must be a number, not {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise InputError(f"{what} must be finite, not {value}")
    return value


def _index(value, what: str) -> int:
    if isinstance(value, (float, np.floating)) and float(value).is_integer():
        value = int(value)  # JSON Schema counts 3.0 as an integer
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise InputError(f"{what} must be an integer, not {value!r}")
    if value < 0:
        raise InputError(f"{what} must be >= 0, not {int(value)}")
    return int(value)


# --------------------------------------------------------------------------------------------
# Points


@dataclass(frozen=True)
class PointRef:
    """One annotated point: a vertex id, or a face id with barycentric coordinates (a, b, c)
    (non-negative, summing to 1 within 1e-6) on that face's corners in order. ``position``:
    optionally, where the point lies (metres, x y z) on the mesh it was made for at that rig's
    bind pose (what lets :func:`remap_to_meshes` carry it onto an edited mesh)."""

    vertex: int | None = None
    face: int | None = None
    barycentric: tuple[float, float, float] | None = None
    position: tuple[float, float, float] | None = None

    def __post_init__(self):
        if self.position is not None:
            pos = tuple(self.position)
            if len(pos) != 3:
                raise InputError(f"position needs 3 coordinates, got {len(pos)}")
            object.__setattr__(self, "position", tuple(_finite_number(x, "position coordinate") for x in pos))
        if self.vertex is not None:
            if self.face is not None or self.barycentric is not None:
                raise InputError("a point is either a vertex or a face with barycentric coordinates, not both")
            object.__setattr__(self, "vertex", _index(self.vertex, "vertex"))
            return
        if self.face is None or self.barycentric is None:
            raise InputError("a point needs a vertex, or a face and barycentric coordinates")
        object.__setattr__(self, "face", _index(self.face, "face"))
        bary = tuple(self.barycentric)
        if len(bary) != 3:
            raise InputError(f"barycentric needs 3 coordinates, got {len(bary)}")
        bary = tuple(_finite_number(b, "barycentric coordinate") for b in bary)
        if any(b < 0 for b in bary):
            raise InputError(f"barycentric {list(bary)} has a negative coordinate")
        total = math.fsum(bary)
        if abs(total - 1.0) > BARYCENTRIC_TOLERANCE:
            raise InputError(f"barycentric {list(bary)} sums to {total:.9g}, not 1")
        object.__setattr__(self, "barycentric", bary)

    @classmethod
    def at_vertex(cls, vertex: int, position=None) -> "PointRef":
        return cls(vertex=vertex, position=None if position is None else tuple(position))

    @classmethod
    def on_face(cls, face: int, barycentric, position=None) -> "PointRef":
        return cls(face=face, barycentric=tuple(barycentric), position=None if position is None else tuple(position))

    def with_position(self, position) -> "PointRef":
        """This point with its rest ``position`` (None: without)."""
        return replace(self, position=None if position is None else tuple(float(x) for x in position))

    @property
    def is_vertex(self) -> bool:
        return self.vertex is not None

    def to_surface_points(self, mesh_faces: np.ndarray, n_vertices: int | None = None) -> SurfacePoints:
        """This point as a one-element :class:`SurfacePoints` on a mesh with faces (F, 3).
        ``n_vertices`` defaults to ``mesh_faces.max() + 1``."""
        mesh_faces = np.asarray(mesh_faces, dtype=np.int64).reshape(-1, 3)
        if n_vertices is None:
            n_vertices = int(mesh_faces.max()) + 1 if len(mesh_faces) else 0
        return resolve_points([self], mesh_faces, n_vertices, what="point")

    def to_dict(self) -> dict:
        out = {"vertex": self.vertex} if self.vertex is not None else {"face": self.face,
                                                                      "barycentric": list(self.barycentric)}
        if self.position is not None:
            out["position"] = list(self.position)
        return out

    @classmethod
    def from_dict(cls, data) -> "PointRef":
        if not isinstance(data, dict):
            raise InputError(f"a point must be an object, not {data!r}")
        position = data.get("position")
        if position is not None and not isinstance(position, (list, tuple)):
            raise InputError(f"position must be [x, y, z], not {position!r}")
        if "vertex" in data:
            return cls(vertex=data["vertex"], position=position)
        return cls(face=data.get("face"), barycentric=data.get("barycentric"), position=position)


def _first_incident_slot(mesh_faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """(V,) index into ``mesh_faces.reshape(-1)`` of each vertex's first use, -1 if unused."""
    first = np.full(n_vertices, -1, dtype=np.int64)
    all_flat = mesh_faces.reshape(-1)
    ok = (all_flat >= 0) & (all_flat < n_vertices)
    slots = np.nonzero(ok)[0]
    first[all_flat[slots][::-1]] = slots[::-1]
    return first


def _point_problem(point: PointRef, n_faces: int, n_vertices: int) -> str | None:
    if point.vertex is not None:
        if not 0 <= point.vertex < n_vertices:
            return f"vertex {point.vertex} out of range [0, {n_vertices})"
    elif not 0 <= point.face < n_faces:
        return f"face {point.face} out of range [0, {n_faces})"
    return None


def resolve_points(
    points, faces: np.ndarray, n_vertices: int, *, what: str, source: str = ""
) -> SurfacePoints:
    """The annotated ``points`` (a sequence of :class:`PointRef`) as :class:`SurfacePoints` on a
    mesh with faces (F, 3) and ``n_vertices`` vertices; a vertex becomes barycentric (1, 0, 0)
    (up to corner order) on its first incident face.

    Raises InputError naming ``what`` and the point's index, e.g. "marker 'IndexTip' target
    point 2: vertex 99999 out of range [0, 3784)"."""
    points = list(points)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    n_faces = len(faces)
    first = None
    out_faces = np.zeros(len(points), dtype=np.int64)
    out_bary = np.zeros((len(points), 3))
    for i, point in enumerate(points):
        element = f"{what} point {i}"
        problem = _point_problem(point, n_faces, n_vertices)
        if problem:
            raise InputError(problem, source=source, element=element)
        if point.vertex is None:
            out_faces[i] = point.face
            out_bary[i] = point.barycentric
            continue
        if first is None:
            first = _first_incident_slot(faces, n_vertices)
        slot = first[point.vertex]
        if slot < 0:
            raise InputError(f"vertex {point.vertex} is used by no face", source=source, element=element)
        out_faces[i] = slot // 3
        out_bary[i, slot % 3] = 1.0
    return SurfacePoints(out_faces, out_bary)


def _check_point_range(point: PointRef, n_faces: int, n_vertices: int, *, element: str, source: str):
    problem = _point_problem(point, n_faces, n_vertices)
    if problem:
        raise InputError(problem, source=source, element=element)


# --------------------------------------------------------------------------------------------
# Markers


@dataclass(frozen=True)
class MarkerPair:
    """A virtual marker: corresponding points on the source and target hand.

    1 and 1 points: one-to-one; 1 and n: one-to-many; n and 1: many-to-one; n and n:
    area-to-area, paired by index. Lists are stored as tuples."""

    name: str
    source: tuple[PointRef, ...]
    target: tuple[PointRef, ...]

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise InputError(f"a marker name must be a non-empty string, not {self.name!r}")
        for side in ("source", "target"):
            pts = tuple(getattr(self, side))
            if not pts:
                raise InputError(f"marker '{self.name}' has no {side} points")
            if not all(isinstance(p, PointRef) for p in pts):
                raise InputError(f"marker '{self.name}' {side} points must be PointRef")
            object.__setattr__(self, side, pts)
        n, m = len(self.source), len(self.target)
        if n > 1 and m > 1 and n != m:
            raise InputError(
                f"marker '{self.name}' has {n} source points and {m} target points; an area-to-area "
                "marker needs the same number on both sides (or use 1 point on one side)"
            )

    @property
    def kind(self) -> str:
        """"one-to-one", "one-to-many", "many-to-one" or "area-to-area"."""
        n, m = len(self.source), len(self.target)
        if n == 1 and m == 1:
            return "one-to-one"
        if n == 1:
            return "one-to-many"
        if m == 1:
            return "many-to-one"
        return "area-to-area"

    def pairs(self) -> list[tuple[int, int]]:
        """Corresponding (source index, target index) pairs."""
        n, m = len(self.source), len(self.target)
        if n == 1:
            return [(0, j) for j in range(m)]
        if m == 1:
            return [(i, 0) for i in range(n)]
        return [(i, i) for i in range(n)]

    def to_dict(self) -> dict:
        return {
            "name": self.name,
            "source": [p.to_dict() for p in self.source],
            "target": [p.to_dict() for p in self.target],
        }


# --------------------------------------------------------------------------------------------
# Axial curves


@dataclass(frozen=True)
class LambdaS:
    """The angular scale lambda_S of an axial curve's target: either uniform (a positive number)
    or a periodic piecewise-linear function of the log-map angle, given by knots
    ``angles_deg`` (strictly increasing, in [0, 360) degrees) and positive ``values``.

    ``uniform`` is the number or None; ``angles`` the knots in radians; ``values`` the knot
    values (both arrays, empty when uniform)."""

    uniform: float | None = None
    angles_deg: tuple[float, ...] = ()
    knot_values: tuple[float, ...] = ()

    def __post_init__(self):
        if self.uniform is not None:
            if self.angles_deg or self.knot_values:
                raise InputError("lambda_s is either uniform or given by knots, not both")
            value = _finite_number(self.uniform, "lambda_s")
            if value <= 0:
                raise InputError(f"lambda_s must be > 0, not {value:g}")
            object.__setattr__(self, "uniform", value)
            return
        angles = tuple(_finite_number(a, "lambda_s angle") for a in self.angles_deg)
        values = tuple(_finite_number(v, "lambda_s value") for v in self.knot_values)
        if not angles:
            raise InputError("lambda_s needs a uniform value or at least one knot")
        if len(angles) != len(values):
            raise InputError(f"lambda_s has {len(angles)} angles but {len(values)} values")
        for i, a in enumerate(angles):
            if not 0 <= a < 360:
                raise InputError(f"lambda_s angles_deg[{i}] = {a:g} is not in [0, 360)")
            if i and a <= angles[i - 1]:
                raise InputError(
                    f"lambda_s angles_deg must be strictly increasing: angles_deg[{i}] = {a:g} "
                    f"follows {angles[i - 1]:g}"
                )
        for i, v in enumerate(values):
            if v <= 0:
                raise InputError(f"lambda_s values[{i}] = {v:g} must be > 0")
        object.__setattr__(self, "angles_deg", angles)
        object.__setattr__(self, "knot_values", values)

    @classmethod
    def constant(cls, value: float) -> "LambdaS":
        return cls(uniform=value)

    @classmethod
    def piecewise(cls, angles_deg, values) -> "LambdaS":
        return cls(angles_deg=tuple(angles_deg), knot_values=tuple(values))

    @property
    def angles(self) -> np.ndarray:
        """(K,) knot angles in radians (empty when uniform)."""
        return np.deg2rad(np.asarray(self.angles_deg, dtype=np.float64))

    @property
    def values(self) -> np.ndarray:
        """(K,) knot values (empty when uniform)."""
        return np.asarray(self.knot_values, dtype=np.float64)

    def __call__(self, theta) -> np.ndarray:
        """lambda_S at log-map angles ``theta`` (radians, any shape, any range): constant when
        uniform, else linear between neighbouring knots, wrapping from the last knot through
        360 degrees to the first."""
        theta = np.asarray(theta, dtype=np.float64)
        if self.uniform is not None:
            return np.full(theta.shape, self.uniform)
        if len(self.knot_values) == 1:
            return np.full(theta.shape, self.knot_values[0])
        two_pi = 2.0 * np.pi
        return np.interp(np.mod(theta, two_pi), self.angles, self.values, period=two_pi)

    def to_json(self):
        if self.uniform is not None:
            return self.uniform
        return {"angles_deg": list(self.angles_deg), "values": list(self.knot_values)}

    @classmethod
    def from_json(cls, data) -> "LambdaS":
        if isinstance(data, dict):
            return cls.piecewise(data.get("angles_deg", ()), data.get("values", ()))
        return cls.constant(data)


@dataclass(frozen=True)
class CurveTarget:
    """Where an axial curve lands on the target hand: the axis origin ``start``, a point
    ``direction`` whose geodesic from ``start`` fixes the initial outgoing direction, the
    length scale ``lambda_a`` (> 0, dimensionless) and the angular scale ``lambda_s``.

    ``through`` (optional, only for a curve given by source points): the target points the
    curve passes through, one for each source point after the first, so the target curve is
    anchored on the target's own anatomy leg by leg (each leg keeps its source leg's number of
    landmarks, evenly spaced) instead of copying the source's turns; ``direction`` is then
    ``through[0]`` and ``lambda_a`` is not used (the lengths are the target's own)."""

    start: PointRef
    direction: PointRef
    lambda_a: float
    lambda_s: LambdaS
    through: tuple[PointRef, ...] | None = None

    def __post_init__(self):
        if not isinstance(self.start, PointRef) or not isinstance(self.direction, PointRef):
            raise InputError("curve target start and direction must be PointRef")
        if self.through is not None:
            through = tuple(self.through)
            if not through or not all(isinstance(p, PointRef) for p in through):
                raise InputError("curve target 'through' must be a non-empty list of points")
            if through[0] != self.direction:
                raise InputError("curve target 'through' must begin with the direction point (the first "
                                 "leg leaves toward it); set direction to through[0]")
            object.__setattr__(self, "through", through)
        value = _finite_number(self.lambda_a, "lambda_a")
        if value <= 0:
            raise InputError(f"lambda_a must be > 0, not {value:g}")
        object.__setattr__(self, "lambda_a", value)
        if not isinstance(self.lambda_s, LambdaS):
            object.__setattr__(self, "lambda_s", LambdaS.from_json(self.lambda_s))

    def to_dict(self) -> dict:
        return {
            "start": self.start.to_dict(),
            "direction": self.direction.to_dict(),
            "lambda_a": self.lambda_a,
            "lambda_s": self.lambda_s.to_json(),
            **({"through": [p.to_dict() for p in self.through]} if self.through is not None else {}),
        }


@dataclass(frozen=True)
class AxialCurveAnnotation:
    """An axial curve. Source: either ``source_start`` and ``source_end`` (the curve is the
    shortest geodesic between them, traced elsewhere) or ``source_points`` (an explicit ordered
    polyline of >= 2 points); the others are None. ``target`` is None when the curve is
    discarded (the contacts of its charts are dropped)."""

    name: str
    source_start: PointRef | None = None
    source_end: PointRef | None = None
    source_points: tuple[PointRef, ...] | None = None
    target: CurveTarget | None = None

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise InputError(f"a curve name must be a non-empty string, not {self.name!r}")
        ends = (self.source_start, self.source_end)
        if self.source_points is not None:
            if any(e is not None for e in ends):
                raise InputError(f"axial curve '{self.name}' has both start/end and points")
            pts = tuple(self.source_points)
            if len(pts) < 2:
                raise InputError(f"axial curve '{self.name}' needs at least 2 source points, got {len(pts)}")
            if not all(isinstance(p, PointRef) for p in pts):
                raise InputError(f"axial curve '{self.name}' source points must be PointRef")
            object.__setattr__(self, "source_points", pts)
        elif not all(isinstance(e, PointRef) for e in ends):
            raise InputError(f"axial curve '{self.name}' needs a source start and end, or source points")
        if self.target is not None and not isinstance(self.target, CurveTarget):
            raise InputError(f"axial curve '{self.name}' target must be a CurveTarget or None")
        if self.target is not None and self.target.through is not None:
            if self.source_points is None:
                raise InputError(f"axial curve '{self.name}': target 'through' points need source points "
                                 "(one target point for each source point after the first)")
            if len(self.target.through) != len(self.source_points) - 1:
                raise InputError(f"axial curve '{self.name}' has {len(self.source_points)} source points, so its "
                                 f"target needs {len(self.source_points) - 1} 'through' points, not "
                                 f"{len(self.target.through)}")

    @property
    def discard(self) -> bool:
        """True when contacts of this curve's charts are dropped."""
        return self.target is None

    @property
    def is_polyline(self) -> bool:
        """True when the source curve is given as explicit points."""
        return self.source_points is not None

    def source_point_refs(self) -> list[tuple[str, PointRef]]:
        """(label, point) of every source point, for messages."""
        if self.source_points is not None:
            return [(f"source points[{i}]", p) for i, p in enumerate(self.source_points)]
        return [("source start", self.source_start), ("source end", self.source_end)]

    def to_dict(self) -> dict:
        if self.source_points is not None:
            src = {"points": [p.to_dict() for p in self.source_points]}
        else:
            src = {"start": self.source_start.to_dict(), "end": self.source_end.to_dict()}
        return {
            "name": self.name,
            "source": src,
            "target": "discard" if self.target is None else self.target.to_dict(),
        }


# --------------------------------------------------------------------------------------------
# The whole file


@dataclass(frozen=True)
class MeshSignature:
    """The mesh a side was annotated on: rig name, vertex / face counts and optionally the
    :func:`surface_sha256` of its vertices and faces."""

    rig: str
    vertices: int
    faces: int
    surface_sha256: str | None = None

    def to_dict(self) -> dict:
        out = {"rig": self.rig, "vertices": self.vertices, "faces": self.faces}
        if self.surface_sha256 is not None:
            out["surface_sha256"] = self.surface_sha256
        return out

    def matches(self, vertices: np.ndarray, faces: np.ndarray) -> bool:
        """True when a mesh with these vertices (V, 3) and faces (F, 3) is the one described
        (counts, and the hash when the signature has one)."""
        faces = np.asarray(faces).reshape(-1, 3)
        if (self.vertices, self.faces) != (len(vertices), len(faces)):
            return False
        return self.surface_sha256 is None or self.surface_sha256 == surface_sha256(vertices, faces)


@dataclass(frozen=True)
class Annotations:
    """Every annotation of one (source hand, target hand) pair. ``markers`` and ``curves`` are
    stored as tuples; names are unique within each. ``landmark_spacing`` in metres."""

    source: MeshSignature
    target: MeshSignature
    markers: tuple[MarkerPair, ...] = ()
    curves: tuple[AxialCurveAnnotation, ...] = ()
    landmark_spacing: float = DEFAULT_LANDMARK_SPACING

    def __post_init__(self):
        object.__setattr__(self, "markers", tuple(self.markers))
        object.__setattr__(self, "curves", tuple(self.curves))
        spacing = _finite_number(self.landmark_spacing, "landmark_spacing")
        if spacing <= 0:
            raise InputError(f"landmark_spacing must be > 0, not {spacing:g}")
        object.__setattr__(self, "landmark_spacing", spacing)
        for kind, items in (("marker", self.markers), ("axial curve", self.curves)):
            seen = set()
            for item in items:
                if item.name in seen:
                    raise InputError(f"duplicate {kind} name '{item.name}'")
                seen.add(item.name)

    def marker(self, name: str) -> MarkerPair:
        for m in self.markers:
            if m.name == name:
                return m
        raise KeyError(name)

    def curve(self, name: str) -> AxialCurveAnnotation:
        for c in self.curves:
            if c.name == name:
                return c
        raise KeyError(name)

    def _point_sites(self):
        """(side, element name, point) of every annotated point, side "source" or "target"."""
        for m in self.markers:
            for side in ("source", "target"):
                for i, p in enumerate(getattr(m, side)):
                    yield side, f"marker '{m.name}' {side} point {i}", p
        for c in self.curves:
            for label, p in c.source_point_refs():
                yield "source", f"axial curve '{c.name}' {label}", p
            if c.target is not None:
                yield "target", f"axial curve '{c.name}' target start", c.target.start
                yield "target", f"axial curve '{c.name}' target direction", c.target.direction
                for i, p in enumerate(c.target.through or ()):
                    yield "target", f"axial curve '{c.name}' target through[{i}]", p

    def has_positions(self, side: str | None = None) -> bool:
        """True when any point (of ``side``, "source" or "target", or of either) has a position."""
        return any(p.position is not None for s, _, p in self._point_sites() if side in (None, s))

    def map_points(self, fn) -> "Annotations":
        """A copy with every point replaced by ``fn(side, element, point)`` (the element names the
        marker or curve as in messages); signatures and everything else unchanged."""
        markers = [
            MarkerPair(m.name, *(tuple(fn(side, f"marker '{m.name}' {side} point {i}", p)
                                       for i, p in enumerate(getattr(m, side))) for side in ("source", "target")))
            for m in self.markers
        ]
        curves = []
        for c in self.curves:
            kw = {}
            if c.source_points is not None:
                kw["source_points"] = tuple(fn("source", f"axial curve '{c.name}' source points[{i}]", p)
                                            for i, p in enumerate(c.source_points))
            else:
                kw["source_start"] = fn("source", f"axial curve '{c.name}' source start", c.source_start)
                kw["source_end"] = fn("source", f"axial curve '{c.name}' source end", c.source_end)
            if c.target is not None:
                kw["target"] = replace(
                    c.target,
                    start=fn("target", f"axial curve '{c.name}' target start", c.target.start),
                    direction=fn("target", f"axial curve '{c.name}' target direction", c.target.direction),
                    through=None if c.target.through is None else tuple(
                        fn("target", f"axial curve '{c.name}' target through[{i}]", p)
                        for i, p in enumerate(c.target.through)))
            curves.append(AxialCurveAnnotation(c.name, **kw))
        return Annotations(self.source, self.target, markers, curves, self.landmark_spacing)

    def check_meshes(
        self,
        source_faces: np.ndarray,
        source_n_vertices: int,
        target_faces: np.ndarray,
        target_n_vertices: int,
        *,
        source: str = "",
    ) -> None:
        """Raise InputError unless the meshes match the signatures the annotations were made on
        and every annotated point exists on them (naming the marker or curve)."""
        meshes = {
            "source": (np.asarray(source_faces).reshape(-1, 3), int(source_n_vertices), self.source),
            "target": (np.asarray(target_faces).reshape(-1, 3), int(target_n_vertices), self.target),
        }
        for side, (faces, n_vertices, sig) in meshes.items():
            for what, expected, actual in (("vertices", sig.vertices, n_vertices), ("faces", sig.faces, len(faces))):
                if expected != actual:
                    raise InputError(
                        f"annotations were made for rig '{sig.rig}' with {expected} {what}; this {side} "
                        f"has {actual} (annotations made for another rig?{REMAP_HINT})",
                        source=source,
                        element=f"{side} hand",
                    )
        first = {}
        for side, element, point in self._point_sites():
            faces, n_vertices, _ = meshes[side]
            _check_point_range(point, len(faces), n_vertices, element=element, source=source)
            if point.vertex is not None:
                if side not in first:
                    first[side] = _first_incident_slot(faces.astype(np.int64), n_vertices)
                if first[side][point.vertex] < 0:
                    raise InputError(f"vertex {point.vertex} is used by no face", source=source, element=element)


# --------------------------------------------------------------------------------------------
# JSON


@functools.lru_cache(maxsize=1)
def _schema_text() -> str:
    return resources.files(__package__).joinpath(SCHEMA_RESOURCE).read_text(encoding="utf-8")


def annotations_schema() -> dict:
    """The published JSON Schema (draft 2020-12) of the annotation file, loaded from
    ``retarget_core/transfer/annotations.schema.json`` (a fresh copy each call)."""
    return json.loads(_schema_text())


@functools.lru_cache(maxsize=1)
def _validator():
    import jsonschema

    schema = annotations_schema()
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


def _json_path(parts) -> str:
    out = ""
    for part in parts:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out


def _schema_check(data, source: str) -> None:
    from jsonschema.exceptions import best_match

    error = best_match(_validator().iter_errors(data))
    if error is None:
        return
    # Descend into if/then/else or combinator context for the most specific message.
    while error.context:
        error = best_match(error.context)
    path = list(error.absolute_path)
    message = error.message
    if error.validator == "const":
        message = f"{error.instance!r} is not {error.validator_value!r}"
        if len(path) == 3 and path[0] == "axial_curves" and path[2] == "target":
            message = (
                f"unknown target {error.instance!r}: a curve target is \"discard\" or an object "
                "{start, direction, lambda_a, lambda_s}"
            )
    raise InputError(message, source=source, element=_json_path(path))


def _at(path: str, source: str, build, *args, **kwargs):
    """Call ``build``; re-raise its InputError with the JSON path as the element."""
    try:
        return build(*args, **kwargs)
    except InputError as exc:
        raise InputError(str(exc), source=source, element=path) from None


def annotations_from_dict(data, *, source: str = "") -> Annotations:
    """Annotations from a parsed JSON document. Validated against the published schema first
    (an error names the JSON path of the bad element, e.g. "axial_curves[1].target.lambda_a"),
    then checked semantically (barycentric sums, knot order, marker sizes, unique names, point
    indices below the signatures' counts). ``source`` names the file in messages."""
    if not isinstance(data, dict):
        raise InputError(f"an annotation file is a JSON object, not {type(data).__name__}", source=source)
    if data.get("format") != ANNOTATIONS_FORMAT:
        raise InputError(
            f"not an annotation file: format is {data.get('format')!r}, expected {ANNOTATIONS_FORMAT!r}",
            source=source,
            element="format",
        )
    if data.get("version") not in READ_VERSIONS or isinstance(data.get("version"), bool):
        raise InputError(
            f"unsupported annotation format version {data.get('version')!r}; this library reads "
            f"versions {', '.join(map(str, READ_VERSIONS))}",
            source=source,
            element="version",
        )
    _schema_check(data, source)

    sigs = {side: MeshSignature(data[side]["rig"], int(data[side]["vertices"]), int(data[side]["faces"]),
                                data[side].get("surface_sha256"))
            for side in ("source", "target")}

    def point(path: str, side: str, raw) -> PointRef:
        p = _at(path, source, PointRef.from_dict, raw)
        sig = sigs[side]
        _check_point_range(p, sig.faces, sig.vertices, element=path, source=source)
        return p

    markers = []
    names: dict[str, int] = {}
    for i, raw in enumerate(data["markers"]):
        path = f"markers[{i}]"
        pts = {
            side: [point(f"{path}.{side}[{j}]", side, r) for j, r in enumerate(raw[side])]
            for side in ("source", "target")
        }
        if raw["name"] in names:
            raise InputError(
                f"duplicate marker name '{raw['name']}' (also markers[{names[raw['name']]}])",
                source=source, element=f"{path}.name",
            )
        names[raw["name"]] = i
        markers.append(_at(path, source, MarkerPair, raw["name"], pts["source"], pts["target"]))

    curves = []
    names = {}
    for i, raw in enumerate(data["axial_curves"]):
        path = f"axial_curves[{i}]"
        src = raw["source"]
        if "points" in src:
            kwargs = {"source_points": [point(f"{path}.source.points[{j}]", "source", r)
                                        for j, r in enumerate(src["points"])]}
        else:
            kwargs = {"source_start": point(f"{path}.source.start", "source", src["start"]),
                      "source_end": point(f"{path}.source.end", "source", src["end"])}
        tgt = raw["target"]
        target = None
        if tgt != "discard":
            lambda_s = _at(f"{path}.target.lambda_s", source, LambdaS.from_json, tgt["lambda_s"])
            target = _at(
                f"{path}.target", source, CurveTarget,
                point(f"{path}.target.start", "target", tgt["start"]),
                point(f"{path}.target.direction", "target", tgt["direction"]),
                tgt["lambda_a"], lambda_s,
                None if tgt.get("through") is None else [point(f"{path}.target.through[{j}]", "target", r)
                                                         for j, r in enumerate(tgt["through"])],
            )
        if raw["name"] in names:
            raise InputError(
                f"duplicate axial curve name '{raw['name']}' (also axial_curves[{names[raw['name']]}])",
                source=source, element=f"{path}.name",
            )
        names[raw["name"]] = i
        curves.append(_at(path, source, AxialCurveAnnotation, raw["name"], target=target, **kwargs))

    return _at(
        "", source, Annotations, sigs["source"], sigs["target"], markers, curves,
        data.get("landmark_spacing", DEFAULT_LANDMARK_SPACING),
    )


def annotations_to_dict(a: Annotations) -> dict:
    """The JSON document of ``a`` (inverse of :func:`annotations_from_dict`): version 2 when a
    point carries a position or a signature a surface hash, else version 1."""
    v2 = a.has_positions() or any(sig.surface_sha256 is not None for sig in (a.source, a.target))
    return {
        "format": ANNOTATIONS_FORMAT,
        "version": 2 if v2 else 1,
        "source": a.source.to_dict(),
        "target": a.target.to_dict(),
        "landmark_spacing": a.landmark_spacing,
        "markers": [m.to_dict() for m in a.markers],
        "axial_curves": [c.to_dict() for c in a.curves],
    }


def _reject_constant(name: str):
    raise ValueError(f"{name} is not valid JSON")


def load_annotations(path) -> Annotations:
    """Read and validate an annotation file; InputError (naming the file) when it is missing,
    unreadable, not JSON or not valid annotations."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError("annotation file not found", source=str(path)) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read annotation file: {exc}", source=str(path)) from None
    try:
        data = json.loads(text, parse_constant=_reject_constant)
    except json.JSONDecodeError as exc:
        raise InputError(
            f"invalid JSON: {exc.msg} at line {exc.lineno} column {exc.colno}", source=str(path)
        ) from None
    except ValueError as exc:
        raise InputError(f"invalid JSON: {exc}", source=str(path)) from None
    return annotations_from_dict(data, source=str(path))


def save_annotations(a: Annotations, path) -> None:
    """Write ``a`` as pretty JSON, atomically; :func:`load_annotations` reads back an equal
    object."""
    text = json.dumps(annotations_to_dict(a), indent=2, allow_nan=False) + "\n"
    with atomic_path(path, suffix=".json.tmp") as tmp:
        Path(tmp).write_text(text, encoding="utf-8")


# --------------------------------------------------------------------------------------------
# Positions, and remapping onto an edited mesh

#: How to give annotations their positions (in the messages refusing an edited mesh).
REMAP_HINT = (
    "; if the rig's mesh was edited, re-save the annotations with their positions against the rigs they were "
    "made for (handretarget annotate remap ANNOTATIONS --source RIG --target RIG --out NEW.json): annotations "
    "with positions survive mesh edits"
)


def surface_sha256(vertices: np.ndarray, faces: np.ndarray) -> str:
    """Hex sha256 of a mesh's vertices (V, 3) as little-endian float64 and faces (F, 3) as
    little-endian int64, each preceded by its shape."""
    v = np.ascontiguousarray(np.asarray(vertices, dtype="<f8").reshape(-1, 3))
    f = np.ascontiguousarray(np.asarray(faces, dtype="<i8").reshape(-1, 3))
    digest = hashlib.sha256()
    digest.update(f"vertices{v.shape}".encode())
    digest.update(v.tobytes())
    digest.update(f"faces{f.shape}".encode())
    digest.update(f.tobytes())
    return digest.hexdigest()


def _surface(rig):
    surface = rig.surface
    return np.asarray(surface.vertices, dtype=np.float64), np.asarray(surface.faces, dtype=np.int64).reshape(-1, 3)


def _signature_of(rig) -> MeshSignature:
    vertices, faces = _surface(rig)
    return MeshSignature(rig.name, len(vertices), len(faces), surface_sha256(vertices, faces))


def _side_positions(annotations: Annotations, side: str, rig) -> dict[str, np.ndarray]:
    """{element: (3,) rest position on ``rig``} of every point of ``side`` (by its indices)."""
    vertices, faces = _surface(rig)
    sites = [(element, p) for s, element, p in annotations._point_sites() if s == side]
    if not sites:
        return {}
    pts = resolve_points([p for _, p in sites], faces, len(vertices), what=f"{side} hand")
    return dict(zip([e for e, _ in sites], pts.positions(vertices, faces)))


def with_positions(annotations: Annotations, source_rig, target_rig) -> Annotations:
    """``annotations`` with every point's rest position (on the rig its indices refer to, at its
    bind pose) and both signatures carrying their rig's :func:`surface_sha256`. The rigs must be
    the ones the annotations were made for (:meth:`Annotations.check_meshes`); a point that already
    has a position gets the one its indices give."""
    rigs = {"source": source_rig, "target": target_rig}
    (sv, sf), (tv, tf) = _surface(source_rig), _surface(target_rig)
    annotations.check_meshes(sf, len(sv), tf, len(tv))
    positions = {side: _side_positions(annotations, side, rig) for side, rig in rigs.items()}
    out = annotations.map_points(lambda side, element, p: p.with_position(positions[side][element]))
    sigs = {side: replace(getattr(annotations, side), surface_sha256=_signature_of(rig).surface_sha256)
            for side, rig in rigs.items()}
    return replace(out, source=sigs["source"], target=sigs["target"])


@dataclass(frozen=True)
class SideRemap:
    """What :func:`remap_to_meshes` did to one side. ``remapped``: the side's mesh differed
    from its signature, so every point was moved to the closest point of the new surface;
    ``points``: points on this side; ``moved``: how many moved (further than 1e-9 m);
    ``max_displacement_mm`` and ``worst`` (the element, e.g. "marker 'IndexTip' target point
    0") of the largest move; ``old`` and ``new``: the signatures before and after."""

    side: str
    remapped: bool
    points: int
    moved: int = 0
    max_displacement_mm: float = 0.0
    worst: str | None = None
    old: MeshSignature | None = None
    new: MeshSignature | None = None

    def line(self) -> str:
        if not self.remapped:
            return f"{self.side}: mesh unchanged, {self.points} points kept"
        return (f"{self.side}: mesh of rig '{self.new.rig}' changed ({self.old.vertices} -> {self.new.vertices} "
                f"vertices, {self.old.faces} -> {self.new.faces} faces): {self.points} points remapped to the "
                f"closest surface point, {self.moved} moved, largest displacement {self.max_displacement_mm:.3f} mm"
                + (f" ({self.worst})" if self.worst else ""))

    def to_dict(self) -> dict:
        return {"remapped": self.remapped, "points": self.points, "moved": self.moved,
                "max_displacement_mm": self.max_displacement_mm, "worst": self.worst}


@dataclass(frozen=True)
class RemapReport:
    """Per side (``source``, ``target``) what :func:`remap_to_meshes` did."""

    source: SideRemap
    target: SideRemap
    max_displacement_mm: float = field(default=DEFAULT_MAX_DISPLACEMENT * 1e3)

    @property
    def changed(self) -> bool:
        """True when either side was remapped."""
        return self.source.remapped or self.target.remapped

    def lines(self) -> list[str]:
        return [self.source.line(), self.target.line()]

    def __str__(self) -> str:
        return "annotations remapped onto edited meshes: " + "; ".join(self.lines()) if self.changed else \
            "annotations match both meshes"

    def to_dict(self) -> dict:
        return {"source": self.source.to_dict(), "target": self.target.to_dict(),
                "threshold_mm": self.max_displacement_mm}


def remap_to_meshes(annotations: Annotations, source_rig, target_rig, *,
                    max_displacement: float = DEFAULT_MAX_DISPLACEMENT,
                    source: str = "annotations") -> tuple[Annotations, RemapReport]:
    """Carry ``annotations`` onto the rigs' current surfaces. A side whose signature (counts, and
    surface hash when present) matches its rig's surface is kept as it is. A side that does not
    match needs every point's rest position (version 2 files, :func:`with_positions`): each point
    becomes the closest point (face, barycentric) of the rig's surface at its bind pose, with that
    point as its new position, and the side's signature becomes the rig's. Without positions the
    mismatch is the InputError of :meth:`Annotations.check_meshes`.

    Raises InputError naming the point that would move furthest when it moves further than
    ``max_displacement`` (metres). Returns the new annotations and a :class:`RemapReport` (also
    logged when a side was remapped)."""
    limit = _finite_number(max_displacement, "max_displacement")
    if limit <= 0:
        raise InputError(f"the largest annotation displacement must be > 0, not {limit:g} m")
    rigs = {"source": source_rig, "target": target_rig}
    counts = {side: sum(1 for s, _, _ in annotations._point_sites() if s == side) for side in rigs}
    sides, new_points, sigs = {}, {}, {}
    for side, rig in rigs.items():
        vertices, faces = _surface(rig)
        sig = getattr(annotations, side)
        sigs[side] = sig
        if sig.matches(vertices, faces):
            sides[side] = SideRemap(side, False, counts[side])
            continue
        sites = [(element, p) for s, element, p in annotations._point_sites() if s == side]
        missing = next((element for element, p in sites if p.position is None), None)
        if missing is not None:
            for what, expected, actual in (("vertices", sig.vertices, len(vertices)), ("faces", sig.faces, len(faces))):
                if expected != actual:  # the message of check_meshes
                    raise InputError(
                        f"annotations were made for rig '{sig.rig}' with {expected} {what}; this {side} "
                        f"has {actual} (annotations made for another rig?{REMAP_HINT}; {missing} has no position)",
                        source=source, element=f"{side} hand")
            raise InputError(
                f"annotations were made for rig '{sig.rig}' with another surface of {sig.vertices} vertices and "
                f"{sig.faces} faces (its surface_sha256 differs): this {side}'s mesh was edited, and {missing} has "
                f"no position to carry it over{REMAP_HINT}",
                source=source, element=f"{side} hand")
        old = np.array([p.position for _, p in sites], dtype=np.float64).reshape(-1, 3)
        closest = closest_surface_points(vertices, faces, old)
        new = closest.positions(vertices, faces)
        moved = np.linalg.norm(new - old, axis=1)
        worst = int(np.argmax(moved)) if len(moved) else None
        largest = float(moved[worst]) if worst is not None else 0.0
        if largest > limit:
            raise InputError(
                f"{sites[worst][0]} would move {largest * 1e3:.3f} mm onto the edited {side} mesh of rig "
                f"{rig.name!r}, more than the {limit * 1e3:g} mm allowed: check the edit, or raise the limit "
                "(handretarget retarget --max-annotation-displacement-mm MM, handretarget annotate remap "
                "--max-displacement-mm MM)",
                source=source, element=sites[worst][0])
        new_points[side] = {
            element: PointRef.on_face(int(f), b, position=x)
            for (element, _), f, b, x in zip(sites, closest.faces, closest.barycentric, new)
        }
        sigs[side] = _signature_of(rig)
        sides[side] = SideRemap(side, True, len(sites), int(np.sum(moved > MOVED_TOLERANCE)), largest * 1e3,
                                sites[worst][0] if worst is not None and largest > MOVED_TOLERANCE else None,
                                sig, sigs[side])
    report = RemapReport(sides["source"], sides["target"], limit * 1e3)
    if not report.changed:
        return annotations, report
    out = annotations.map_points(lambda side, element, p: new_points[side][element] if side in new_points else p)
    out = replace(out, source=sigs["source"], target=sigs["target"])
    logger.info("%s", report)
    return out, report
