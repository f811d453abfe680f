"""Intersection metrics (paper, section "Results"): hand-object, self and table intersection.

The paper's recipe, per frame:

1. find the penetrating hand vertices by ray casting;
2. group them into clusters by depth-first search over the hand mesh (its vertex adjacency);
3. take the convex hull of each cluster and its volume;
4. report the sum of the hull volumes relative to the hand's own volume, as a percentage.

Choices made here (the paper leaves them open):

* **Inside tests.** Hand-object: each hand vertex casts rays along three fixed generic
  directions through the object mesh (trimesh with the embree backend, every hit along the
  ray); a vertex is inside when the hit count is odd for at least two of the three rays (a
  ray grazing an edge can be counted twice or not at all; the vote removes that).
  Self: each hand vertex casts three rays from a point just outside its own surface
  (``vertex + delta * outward normal``), tilted 0.3 rad from the normal, through the hand
  itself, and sums the *signed* crossings (+1 leaving a closed part, -1 entering it): that
  sum is the winding number of the hand surface at the start point. It is 0 for every vertex
  of a hand whose surface does not pass through itself, and 1 for a finger vertex pushed into
  the palm (and for a palm vertex inside the finger). Table: the box's signed distance is
  exact, so the test is analytic: inside when ``sdf < -SURFACE_TOLERANCE_M`` (1e-9 m, see
  :data:`retarget_core.mesh.geometry.SURFACE_TOLERANCE_M`), so a vertex lying on the table top
  up to round-off is not in the table. Both ray tests gave exactly the vertex sets of
  libigl's generalized winding number (> 0.5) on the demo hand (rest, fingers bent through
  the palm) and on every 10th frame of a demo clip.
* **Volume of a cluster.** The hull is taken over the cluster's penetrating vertices *and*
  the points where the hand edges leaving the cluster cross the other surface (found by a
  ray along each such edge; for the table analytically). Those crossing points lie on the
  intersection curve, so the hull covers the whole penetrating region of the hand surface
  instead of stopping one mesh ring short of it: a box pushed 5.5 mm into another on a 1.25 mm
  grid gives the exact overlap, not the 5 mm the vertices alone span. Pass
  ``include_crossings=False`` for the vertices-only hull. A cluster whose points are fewer
  than four or coplanar has volume 0 (Qhull's error is caught). As in the paper, hull volumes
  over-estimate non-convex penetrations. When two parts of the hand overlap, the overlap's
  boundary is made of two clusters (the finger's piece inside the palm and the palm's piece
  inside the finger); their hulls split the overlap along the intersection curve, so their sum
  approximates the overlap volume without counting it twice when that curve is (near) planar.
* **Hand volume.** The closed posed surface's volume from signed tetrahedra (a surface wound
  inside out is read with its orientation flipped). Without a closed manifold hand surface no
  volume exists, and the metric is returned as unavailable with the reason, never guessed.
  (A surface that overlaps itself encloses its overlap twice in this volume.)
* **Depth** (``max_depth_m``): hand-object, exact distance of the penetrating vertices to the
  object surface (libigl); table, exact (box SDF); self, an estimate: the distance of a
  cluster's vertices to the hand surface away from that cluster (faces not touching it), never
  more than the distance to the cluster's crossing points, which lie on the other surface.

Units: metres, cubic metres; percentages are of the posed hand's volume.

Topology, edges and the object's ray scene are cached by array content (a few per process),
so a clip's frames pay for them once.
"""

from __future__ import annotations

import hashlib
import math
import threading
from collections import OrderedDict
from dataclasses import dataclass, field
from typing import Iterable, Sequence

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import ConvexHull, QhullError

from ..errors import InputError
from ..mesh.geometry import (
    SURFACE_TOLERANCE_M,
    box_local,
    box_signed_distance_local,
    face_normals,
    signed_volume,
    vertex_normals,
)
from ..mesh.topology import MeshTopologyReport, check_closed_manifold

KINDS = ("hand_object", "self", "table")

#: Ray directions of the hand-object parity test (generic: no mesh of axis-aligned or
#: regularly spaced features lines up with them).
_PARITY_DIRECTIONS = np.array(
    [
        [0.4395064455, 0.617598629942, 0.652231566745],
        [-0.7071067812 * 0.913, 0.2588190451, -0.3141592654],
        [0.1736481777, -0.8660254038, 0.4694715628],
    ]
)
_PARITY_DIRECTIONS /= np.linalg.norm(_PARITY_DIRECTIONS, axis=1, keepdims=True)

#: Self test: tilt of the rays from the outward normal (rad) and their azimuths.
_SELF_TILT = 0.3
_SELF_AZIMUTHS = (0.37, 0.37 + 2.0 * math.pi / 3.0, 0.37 + 4.0 * math.pi / 3.0)
#: Self test: rays start this fraction of the mean edge length outside the surface.
_SELF_OFFSET = 1e-3


# ------------------------------------------------------------------------------------------
# result
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class IntersectionResult:
    """One frame's intersection of one kind ("hand_object", "self" or "table").

    ``available`` is False when the metric cannot be computed (open or non-manifold hand
    surface, open object, non-finite vertices); ``reason`` then says why and the numbers are
    NaN / 0. ``volume_m3``: total convex-hull volume of the clusters (m^3);
    ``percent_of_hand``: ``100 * volume_m3 / hand_volume_m3``; ``n_vertices``: penetrating
    hand vertices; ``n_clusters``: clusters of them; ``max_depth_m``: deepest penetration
    (m, 0 when none); ``cluster_volumes_m3``: hull volume per cluster, largest first;
    ``penetrating``: (P,) indices of the penetrating hand vertices.
    """

    kind: str
    available: bool
    reason: str = ""
    volume_m3: float = math.nan
    percent_of_hand: float = math.nan
    hand_volume_m3: float = math.nan
    n_vertices: int = 0
    n_clusters: int = 0
    max_depth_m: float = math.nan
    cluster_volumes_m3: tuple[float, ...] = ()
    penetrating: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64), repr=False)

    def to_dict(self) -> dict:
        """JSON-serialisable summary (NaN -> None; vertex indices left out)."""

        def num(x):
            return None if x is None or not math.isfinite(x) else float(x)

        return {
            "kind": self.kind,
            "available": self.available,
            "reason": self.reason,
            "volume_m3": num(self.volume_m3),
            "percent_of_hand": num(self.percent_of_hand),
            "hand_volume_m3": num(self.hand_volume_m3),
            "n_vertices": int(self.n_vertices),
            "n_clusters": int(self.n_clusters),
            "max_depth_m": num(self.max_depth_m),
            "cluster_volumes_m3": [float(v) for v in self.cluster_volumes_m3],
        }


def _unavailable(kind: str, reason: str) -> IntersectionResult:
    return IntersectionResult(kind=kind, available=False, reason=reason)


# ------------------------------------------------------------------------------------------
# surface preparation (cached by face array content: a clip's hand faces never change)
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Topology:
    report: MeshTopologyReport
    faces: np.ndarray  # (F, 3) int64
    edges: np.ndarray  # (E, 2) unique undirected edges
    referenced: np.ndarray  # (V,) bool: used by a face (loose vertices never penetrate)

    @property
    def closed_manifold(self) -> bool:
        return self.report.closed and self.report.manifold


_TOPOLOGY_CACHE: "OrderedDict[tuple, _Topology]" = OrderedDict()
_SCENE_CACHE: "OrderedDict[tuple, object]" = OrderedDict()
_CACHE_SIZE = 8
_CACHE_LOCK = threading.Lock()


def _digest(*arrays: np.ndarray) -> tuple:
    h = hashlib.blake2b(digest_size=16)
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype.str, a.shape)).encode())
        h.update(a.tobytes())
    return (h.hexdigest(),)


def _cache_get(cache: OrderedDict, key, build):
    with _CACHE_LOCK:
        if key in cache:
            cache.move_to_end(key)
            return cache[key]
    value = build()  # outside the lock: two threads may both build; either result is right
    with _CACHE_LOCK:
        cache[key] = value
        while len(cache) > _CACHE_SIZE:
            cache.popitem(last=False)
    return value


def _as_faces(faces, n_vertices: int, element: str) -> np.ndarray:
    faces = np.asarray(faces)
    if faces.ndim != 2 or faces.shape[1] != 3 or not np.issubdtype(faces.dtype, np.integer):
        raise InputError(f"must be an (F, 3) integer array, got {faces.dtype} {faces.shape}", element=element)
    if len(faces) and (faces.min() < 0 or faces.max() >= n_vertices):
        raise InputError(f"indices must lie in [0, {n_vertices}), got [{faces.min()}, {faces.max()}]", element=element)
    return faces.astype(np.int64)


def _as_points(points, element: str) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"must be a (V, 3) array, got shape {points.shape}", element=element)
    return points


def _faces_key(faces) -> tuple:
    """Content key of a face array as given (before any dtype conversion)."""
    return _digest(np.asarray(faces))


def _topology(faces: np.ndarray, n_vertices: int, key: tuple | None = None) -> _Topology:
    def build():
        report = check_closed_manifold(faces, n_vertices)
        e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
        e = np.unique(np.sort(e, axis=1), axis=0)
        referenced = np.zeros(n_vertices, dtype=bool)
        referenced[faces.reshape(-1)] = True
        return _Topology(report=report, faces=faces, edges=e, referenced=referenced)

    key = _digest(faces) if key is None else key
    return _cache_get(_TOPOLOGY_CACHE, (n_vertices,) + key, build)


class _Scene:
    """A fixed closed mesh to test against: embree ray intersector (trimesh) and, built on
    first use, a libigl AABB tree for exact distances."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        import trimesh
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        mesh = trimesh.Trimesh(vertices=self.vertices, faces=self.faces, process=False, validate=False)
        self.intersector = RayMeshIntersector(mesh)
        self._aabb = None

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance (N,) of points (N, 3) to the surface."""
        import igl

        if self._aabb is None:
            self._aabb = igl.AABB()
            self._aabb.init(self.vertices, self.faces)
        query = np.ascontiguousarray(points, dtype=np.float64)
        sq, _, _ = self._aabb.squared_distance(self.vertices, self.faces, query)
        return np.sqrt(sq)


def _scene(vertices: np.ndarray, faces: np.ndarray, faces_key: tuple | None = None, *, cache: bool = True) -> _Scene:
    """The :class:`_Scene` of (vertices, faces), cached by content unless ``cache`` is False
    (a posed hand changes every frame)."""
    if not cache:
        return _Scene(vertices, faces)
    key = _digest(vertices) + (faces_key if faces_key is not None else _digest(faces))
    return _cache_get(_SCENE_CACHE, key, lambda: _Scene(vertices, faces))


# ------------------------------------------------------------------------------------------
# input checks and ray helpers
# ------------------------------------------------------------------------------------------
def _check_box(pose, half_extents) -> tuple[np.ndarray, np.ndarray]:
    pose = np.asarray(pose, dtype=np.float64)
    he = np.asarray(half_extents, dtype=np.float64)
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise InputError(f"must be a finite (4, 4) matrix, got shape {pose.shape}", element="table_pose")
    r = pose[:3, :3]
    if not np.allclose(r.T @ r, np.eye(3), atol=1e-6):
        raise InputError("must be rigid (its 3x3 block a rotation)", element="table_pose")
    if he.shape != (3,) or not np.all(np.isfinite(he)) or np.any(he <= 0):
        raise InputError(f"must be 3 positive numbers, got {he!r}", element="table_half_extents")
    return pose, he


def _tangent_basis(n: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    helper = np.where(np.abs(n[:, :1]) < 0.9, np.array([[1.0, 0.0, 0.0]]), np.array([[0.0, 1.0, 0.0]]))
    t1 = np.cross(n, helper)
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(n, t1)
    return t1, t2


def _ray_hits(intersector, origins: np.ndarray, directions: np.ndarray):
    """Every hit of every ray: (triangle (H,), ray (H,), location (H, 3))."""
    if len(origins) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros((0, 3))
    tri, ray, loc = intersector.intersects_id(
        origins, directions, multiple_hits=True, return_locations=True, max_hits=200
    )
    return np.asarray(tri, np.int64), np.asarray(ray, np.int64), np.asarray(loc, np.float64).reshape(-1, 3)


def _first_valid_hit(ray: np.ndarray, t: np.ndarray, valid: np.ndarray, n_rays: int) -> np.ndarray:
    """Smallest valid ``t`` per ray, ``inf`` when none: (n_rays,)."""
    best = np.full(n_rays, np.inf)
    if len(ray):
        np.minimum.at(best, ray[valid], t[valid])
    return best


def points_inside_mesh(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Which points (N, 3) lie inside the closed mesh (vertices (V, 3), faces (F, 3)):
    (N,) bool. Ray casting (embree): parity of the hits along three generic directions, the
    majority of the three decides. Points outside the mesh's bounding box are outside."""
    points = _as_points(points, "points")
    vertices = _as_points(vertices, "vertices")
    key = _faces_key(faces)
    faces = _as_faces(faces, len(vertices), "faces")
    if len(points) == 0 or len(faces) == 0:
        return np.zeros(len(points), dtype=bool)
    return _inside(points, _scene(vertices, faces, key))


def _inside(points: np.ndarray, scene: _Scene) -> np.ndarray:
    inside = np.zeros(len(points), dtype=bool)
    lo, hi = scene.vertices.min(axis=0), scene.vertices.max(axis=0)
    pad = 1e-9 + 1e-6 * float(np.linalg.norm(hi - lo))
    candidates = np.flatnonzero(np.all((points >= lo - pad) & (points <= hi + pad), axis=1))
    if len(candidates) == 0:
        return inside
    n = len(candidates)
    origins = np.tile(points[candidates], (3, 1))
    dirs = np.repeat(_PARITY_DIRECTIONS, n, axis=0)
    _, ray, _ = _ray_hits(scene.intersector, origins, dirs)
    counts = np.bincount(ray, minlength=3 * n).reshape(3, n)
    inside[candidates] = (counts % 2 == 1).sum(axis=0) >= 2
    return inside


# ------------------------------------------------------------------------------------------
# clusters and hulls
# ------------------------------------------------------------------------------------------
def _clusters(edges: np.ndarray, inside: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """Connected components of the penetrating vertices over the mesh edges (the paper's
    depth-first search). Returns (penetrating (P,), labels (P,), n_clusters)."""
    pen = np.flatnonzero(inside)
    if len(pen) == 0:
        return pen, np.zeros(0, np.int64), 0
    local = np.full(len(inside), -1, dtype=np.int64)
    local[pen] = np.arange(len(pen))
    both = inside[edges[:, 0]] & inside[edges[:, 1]]
    a, b = local[edges[both, 0]], local[edges[both, 1]]
    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(len(pen), len(pen)))
    n, labels = connected_components(graph, directed=False)
    return pen, labels.astype(np.int64), int(n)


def _hull_volume(points: np.ndarray) -> float:
    if len(points) < 4:
        return 0.0
    pts = points - points.mean(axis=0)
    try:
        return float(ConvexHull(pts).volume)
    except (QhullError, ValueError):
        return 0.0  # coplanar / collinear / coincident: a flat patch has no volume


def _leaving_edges(edges: np.ndarray, inside: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Edges with exactly one penetrating end, oriented (inside end p, outside end q)."""
    ia, ib = inside[edges[:, 0]], inside[edges[:, 1]]
    cross = ia != ib
    e = edges[cross]
    flip = ~inside[e[:, 0]]
    p = np.where(flip, e[:, 1], e[:, 0])
    q = np.where(flip, e[:, 0], e[:, 1])
    return p, q


def _cluster_volumes(
    vertices: np.ndarray,
    pen: np.ndarray,
    labels: np.ndarray,
    n_clusters: int,
    p: np.ndarray,
    crossings: np.ndarray | None,
) -> np.ndarray:
    """Hull volume per cluster (n_clusters,) of its vertices plus its crossing points."""
    cluster_of = np.full(len(vertices), -1, dtype=np.int64)
    cluster_of[pen] = labels
    order = np.argsort(labels, kind="stable")
    starts = np.searchsorted(labels[order], np.arange(n_clusters + 1))
    if crossings is not None and len(p):
        c_lab = cluster_of[p]
        c_order = np.argsort(c_lab, kind="stable")
        c_starts = np.searchsorted(c_lab[c_order], np.arange(n_clusters + 1))
    volumes = np.zeros(n_clusters)
    for c in range(n_clusters):
        pts = vertices[pen[order[starts[c]:starts[c + 1]]]]
        if crossings is not None and len(p):
            pts = np.concatenate([pts, crossings[c_order[c_starts[c]:c_starts[c + 1]]]])
        volumes[c] = _hull_volume(pts)
    return volumes


# ------------------------------------------------------------------------------------------
# shared frame checks
# ------------------------------------------------------------------------------------------
def _hand(kind: str, hand_vertices, hand_faces, hand_volume_m3):
    """Validate the hand; returns (vertices, topology, faces outward, hand volume) or an
    unavailable result."""
    v = _as_points(hand_vertices, "hand_vertices")
    key = _faces_key(hand_faces)
    f = _as_faces(hand_faces, len(v), "hand_faces")
    topo = _topology(f, len(v), key)
    if not topo.closed_manifold:
        return _unavailable(kind, "hand surface is not a closed manifold: " + topo.report.describe())
    if not np.all(np.isfinite(v)):
        return _unavailable(kind, "hand vertices are not all finite")
    vol = signed_volume(v, f)
    faces_out = f if vol >= 0 else f[:, ::-1]
    if hand_volume_m3 is None:
        hand_volume_m3 = abs(vol)
    if not (hand_volume_m3 > 0 and math.isfinite(hand_volume_m3)):
        return _unavailable(kind, f"hand volume is not positive ({hand_volume_m3!r} m^3)")
    return v, topo, faces_out, float(hand_volume_m3)


def _result(kind, hand_volume, pen, n_clusters, volumes, max_depth) -> IntersectionResult:
    total = float(volumes.sum()) if len(volumes) else 0.0
    return IntersectionResult(
        kind=kind,
        available=True,
        volume_m3=total,
        percent_of_hand=100.0 * total / hand_volume,
        hand_volume_m3=hand_volume,
        n_vertices=int(len(pen)),
        n_clusters=int(n_clusters),
        max_depth_m=float(max_depth) if len(pen) else 0.0,
        cluster_volumes_m3=tuple(float(x) for x in np.sort(volumes)[::-1]),
        penetrating=pen,
    )


# ------------------------------------------------------------------------------------------
# the three kinds
# ------------------------------------------------------------------------------------------
def hand_object_intersection(
    hand_vertices: np.ndarray,
    hand_faces: np.ndarray,
    object_vertices: np.ndarray,
    object_faces: np.ndarray,
    object_pose: np.ndarray | None = None,
    *,
    hand_volume_m3: float | None = None,
    include_crossings: bool = True,
) -> IntersectionResult:
    """Hand-object intersection of one frame.

    hand_vertices (V, 3) world metres, hand_faces (F, 3) int (a closed manifold);
    object_vertices (W, 3) metres and object_faces (G, 3) int (closed), in the object's frame
    when ``object_pose`` (4, 4 world-from-object) is given, else in world. ``hand_volume_m3``
    overrides the posed hand's own volume as the percentage's denominator.
    """
    kind = "hand_object"
    hand = _hand(kind, hand_vertices, hand_faces, hand_volume_m3)
    if isinstance(hand, IntersectionResult):
        return hand
    v, topo, _, hand_volume = hand
    ov = _as_points(object_vertices, "object_vertices")
    o_key = _faces_key(object_faces)
    of = _as_faces(object_faces, len(ov), "object_faces")
    o_topo = _topology(of, len(ov), o_key)
    if not o_topo.report.closed:
        return _unavailable(kind, "object surface is not closed: " + o_topo.report.describe())
    if not np.all(np.isfinite(ov)):
        return _unavailable(kind, "object vertices are not all finite")
    if object_pose is not None:
        pose = np.asarray(object_pose, dtype=np.float64)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise InputError(f"must be a finite (4, 4) matrix, got shape {pose.shape}", element="object_pose")
        inv = np.linalg.inv(pose)
        v = v @ inv[:3, :3].T + inv[:3, 3]  # the hand in the object's frame: volumes are invariant

    scene = _scene(ov, of, o_key)
    inside = _inside(v, scene) & topo.referenced
    pen, labels, n_clusters = _clusters(topo.edges, inside)
    if n_clusters == 0:
        return _result(kind, hand_volume, pen, 0, np.zeros(0), 0.0)

    crossings = None
    p = np.zeros(0, np.int64)
    if include_crossings:
        p, q = _leaving_edges(topo.edges, inside)
        seg = v[q] - v[p]
        length = np.linalg.norm(seg, axis=1)
        d = seg / np.where(length > 0, length, 1.0)[:, None]
        tri, ray, loc = _ray_hits(scene.intersector, v[p], d)
        t = np.einsum("ij,ij->i", loc - v[p][ray], d[ray]) if len(ray) else np.zeros(0)
        best = _first_valid_hit(ray, t, t >= 0, len(p))
        ok = best <= length * (1 + 1e-6)
        tt = np.where(ok, best, 0.5 * length)
        crossings = v[p] + d * tt[:, None]

    volumes = _cluster_volumes(v, pen, labels, n_clusters, p, crossings)
    return _result(kind, hand_volume, pen, n_clusters, volumes, float(scene.distance(v[pen]).max()))


def table_intersection(
    hand_vertices: np.ndarray,
    hand_faces: np.ndarray,
    table_pose: np.ndarray,
    table_half_extents: np.ndarray,
    *,
    hand_volume_m3: float | None = None,
    include_crossings: bool = True,
) -> IntersectionResult:
    """Hand-table intersection of one frame, the table a box.

    hand_vertices (V, 3) world metres, hand_faces (F, 3) int (a closed manifold);
    table_pose (4, 4) world-from-box (rigid), the box centred on its frame's origin;
    table_half_extents (3,) metres. Inside test and crossings are analytic (exact box SDF); a
    vertex is inside only deeper than ``SURFACE_TOLERANCE_M`` (1e-9 m) below the surface.
    """
    kind = "table"
    pose, he = _check_box(table_pose, table_half_extents)
    hand = _hand(kind, hand_vertices, hand_faces, hand_volume_m3)
    if isinstance(hand, IntersectionResult):
        return hand
    v, topo, _, hand_volume = hand
    local = box_local(v, pose)  # rigid: distances and volumes are the same in the box frame
    sdf = box_signed_distance_local(local, he)
    inside = (sdf < -SURFACE_TOLERANCE_M) & topo.referenced  # on the surface (within 1 nm) is outside
    pen, labels, n_clusters = _clusters(topo.edges, inside)
    if n_clusters == 0:
        return _result(kind, hand_volume, pen, 0, np.zeros(0), 0.0)
    crossings = None
    p = np.zeros(0, np.int64)
    if include_crossings:
        p, q = _leaving_edges(topo.edges, inside)
        a, d = local[p], local[q] - local[p]
        # The segment a + s d (s in [0, 1]) leaves the box where it first reaches a face.
        with np.errstate(divide="ignore", invalid="ignore"):
            s_axis = np.where(d > 0, (he - a) / d, np.where(d < 0, (-he - a) / d, np.inf))
        s = np.clip(np.min(s_axis, axis=1), 0.0, 1.0)
        crossings = a + d * s[:, None]
    volumes = _cluster_volumes(local, pen, labels, n_clusters, p, crossings)
    return _result(kind, hand_volume, pen, n_clusters, volumes, float(-sdf[pen].min()))


def self_intersection(
    hand_vertices: np.ndarray,
    hand_faces: np.ndarray,
    *,
    hand_volume_m3: float | None = None,
    include_crossings: bool = True,
) -> IntersectionResult:
    """Self intersection (hand-hand) of one frame: hand vertices inside the volume of another
    part of the same hand surface (a finger bent into the palm, two fingers through each other).

    hand_vertices (V, 3) metres, hand_faces (F, 3) int (a closed manifold; several closed
    components are fine). Winding number by signed ray crossings from just outside each
    vertex (see the module notes); 0 for a surface that does not pass through itself.
    """
    kind = "self"
    hand = _hand(kind, hand_vertices, hand_faces, hand_volume_m3)
    if isinstance(hand, IntersectionResult):
        return hand
    v, topo, faces, hand_volume = hand
    n_v = len(v)
    vn = vertex_normals(v, faces)
    vn[~np.any(vn != 0, axis=1)] = (0.0, 0.0, 1.0)  # a vertex no face uses: any direction
    fn = face_normals(v, faces)
    edge_len = np.linalg.norm(v[topo.edges[:, 0]] - v[topo.edges[:, 1]], axis=1)
    delta = _SELF_OFFSET * float(edge_len.mean())
    inter = _scene(v, faces, cache=False).intersector

    t1, t2 = _tangent_basis(vn)
    origins = v + delta * vn
    dirs = np.concatenate(
        [
            math.cos(_SELF_TILT) * vn + math.sin(_SELF_TILT) * (math.cos(a) * t1 + math.sin(a) * t2)
            for a in _SELF_AZIMUTHS
        ]
    )
    tri, ray, _ = _ray_hits(inter, np.tile(origins, (3, 1)), dirs)
    sign = np.sign(np.einsum("ij,ij->i", fn[tri], dirs[ray])) if len(ray) else np.zeros(0)
    winding = np.bincount(ray, weights=sign, minlength=3 * n_v).reshape(3, n_v)
    inside = ((winding >= 0.5).sum(axis=0) >= 2) & topo.referenced
    pen, labels, n_clusters = _clusters(topo.edges, inside)
    if n_clusters == 0:
        return _result(kind, hand_volume, pen, 0, np.zeros(0), 0.0)

    # Crossings: along each leaving edge p -> q, from just outside p, the first hit on a face
    # that touches neither p nor q (the other part's surface).
    p, q = _leaving_edges(topo.edges, inside)
    seg = v[q] - v[p]
    length = np.linalg.norm(seg, axis=1)
    d = seg / np.where(length > 0, length, 1.0)[:, None]
    start = v[p] + delta * vn[p]
    e_tri, e_ray, e_loc = _ray_hits(inter, start, d)
    if len(e_ray):
        own = (faces[e_tri] == p[e_ray, None]).any(axis=1) | (faces[e_tri] == q[e_ray, None]).any(axis=1)
        t = np.einsum("ij,ij->i", e_loc - start[e_ray], d[e_ray])
        best = _first_valid_hit(e_ray, t, (~own) & (t >= 0), len(p))
    else:
        best = np.full(len(p), np.inf)
    hit = best <= length * (1 + 1e-3) + delta
    crossing_pts = np.where(hit[:, None], start + d * np.where(hit, best, 0.0)[:, None], v[p] + 0.5 * seg)

    volumes = _cluster_volumes(v, pen, labels, n_clusters, p, crossing_pts if include_crossings else None)
    depth = _self_depth(v, faces, pen, labels, n_clusters, p, crossing_pts, hit, float(edge_len.max()))
    return _result(kind, hand_volume, pen, n_clusters, volumes, depth)


def _self_depth(v, faces, pen, labels, n_clusters, p, crossing_pts, hit, max_edge) -> float:
    """Estimated deepest self penetration (m): per cluster, the distance of its vertices to
    the faces that do not touch it, bounded by the distance to its crossing points."""
    import igl

    cluster_of = np.full(len(v), -1, dtype=np.int64)
    cluster_of[pen] = labels
    face_cluster = cluster_of[faces]
    worst = 0.0
    for c in range(n_clusters):
        pts = v[pen[labels == c]]
        on_curve = crossing_pts[(cluster_of[p] == c) & hit]
        bound = np.full(len(pts), np.inf)
        if len(on_curve):
            bound = np.sqrt(((pts[:, None, :] - on_curve[None, :, :]) ** 2).sum(-1)).min(axis=1)
        everything = np.concatenate([pts, on_curve])
        lo, hi = everything.min(axis=0), everything.max(axis=0)
        reach = float(np.linalg.norm(hi - lo)) + max_edge
        near = np.all((v >= lo - reach) & (v <= hi + reach), axis=1)
        keep = near[faces].any(axis=1) & ~(face_cluster == c).any(axis=1)
        if keep.any():
            sq, _, _ = igl.point_mesh_squared_distance(np.ascontiguousarray(pts), v, np.ascontiguousarray(faces[keep]))
            bound = np.minimum(bound, np.sqrt(sq))
        finite = bound[np.isfinite(bound)]
        if len(finite):
            worst = max(worst, float(finite.max()))
    return worst


# ------------------------------------------------------------------------------------------
# a clip
# ------------------------------------------------------------------------------------------
def clip_intersections(
    hand_vertices: np.ndarray,
    hand_faces: np.ndarray,
    *,
    object_vertices: np.ndarray | None = None,
    object_faces: np.ndarray | None = None,
    object_poses: np.ndarray | None = None,
    table_pose: np.ndarray | None = None,
    table_half_extents: np.ndarray | None = None,
    kinds: Sequence[str] = KINDS,
    frames: Iterable[int] | None = None,
    hand_volume_m3: float | None = None,
    include_crossings: bool = True,
) -> dict[str, list[IntersectionResult]]:
    """Every requested kind for every frame of a clip.

    hand_vertices (T, V, 3) metres, hand_faces (F, 3); object_vertices (W, 3) in the object's
    frame with object_faces (G, 3) and object_poses (T, 4, 4) world-from-object; table_pose
    (4, 4) and table_half_extents (3,). ``hand_volume_m3``: a fixed denominator for every
    frame (default: each posed frame's own volume). A kind whose inputs are missing is
    skipped. Returns
    kind -> list of :class:`IntersectionResult`, one per evaluated frame.
    """
    hv = np.asarray(hand_vertices, dtype=np.float64)
    if hv.ndim != 3 or hv.shape[2] != 3:
        raise InputError(f"must be a (T, V, 3) array, got shape {hv.shape}", element="hand_vertices")
    for k in kinds:
        if k not in KINDS:
            raise InputError(f"unknown kind {k!r}; known: {', '.join(KINDS)}", element="kinds")
    frame_list = list(range(len(hv))) if frames is None else [int(f) for f in frames]
    out: dict[str, list[IntersectionResult]] = {}
    if "hand_object" in kinds and object_vertices is not None and object_faces is not None:
        poses = None if object_poses is None else np.asarray(object_poses, dtype=np.float64)
        if poses is not None and (poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) != len(hv)):
            raise InputError(f"must be (T, 4, 4) with T = {len(hv)}, got {poses.shape}", element="object_poses")
        out["hand_object"] = [
            hand_object_intersection(
                hv[f], hand_faces, object_vertices, object_faces, None if poses is None else poses[f],
                hand_volume_m3=hand_volume_m3, include_crossings=include_crossings,
            )
            for f in frame_list
        ]
    if "self" in kinds:
        out["self"] = [
            self_intersection(hv[f], hand_faces, hand_volume_m3=hand_volume_m3, include_crossings=include_crossings)
            for f in frame_list
        ]
    if "table" in kinds and table_pose is not None and table_half_extents is not None:
        out["table"] = [
            table_intersection(
                hv[f], hand_faces, table_pose, table_half_extents,
                hand_volume_m3=hand_volume_m3, include_crossings=include_crossings,
            )
            for f in frame_list
        ]
    return out
