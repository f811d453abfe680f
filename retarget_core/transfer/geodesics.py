"""Geodesic tools on one hand surface, built once and reused: log maps centred at any surface
point, geodesic tracing (the exponential map) from surface points, shortest paths, and point
location in a log-map chart.

Conventions: a surface point is (face, barycentric); tangent angles are measured
counter-clockwise about the outward normal (potpourri3d's tangent frames agree with the outward
vertex normals of a consistently oriented closed mesh).
"""

from __future__ import annotations

from dataclasses import dataclass

import igl
import numpy as np
import potpourri3d as pp3d
from scipy.spatial import cKDTree

from ..errors import InputError
from ..mesh.geometry import face_normals, vertex_normals
from ..mesh.surface_points import SurfacePoints, barycentric_of
from ..mesh.topology import check_closed_manifold

#: Barycentric coordinates closer than this to 0 or 1 are snapped (a trace that ends on a
#: vertex or edge comes back a few 1e-6 off, which sends the next trace to the wrong side).
SNAP = 1e-4


@dataclass(frozen=True)
class TraceResult:
    """End of a traced geodesic: the surface point, its position (3,), the unit arrival
    direction (3,) and the length actually walked (m; shorter than asked at a boundary)."""

    face: int
    barycentric: np.ndarray
    position: np.ndarray
    direction: np.ndarray
    walked: float


class SurfaceGeometry:
    """Geodesic machinery of one mesh. vertices (V, 3) metres, faces (F, 3). The mesh must be a
    2-manifold (closed or with boundary), consistently oriented."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, *, name: str = "surface"):
        self.vertices = np.ascontiguousarray(vertices, dtype=np.float64)
        self.faces = np.ascontiguousarray(faces, dtype=np.int64)
        self.name = name
        report = check_closed_manifold(self.faces, len(self.vertices))
        if not report.manifold or report.nonmanifold_edges:
            raise InputError(f"geodesics need a manifold surface, but it is {report.describe()}", element=name)
        self.components = report.components
        self._vhm = pp3d.MeshVectorHeatSolver(self.vertices, self.faces)
        self._tracer = pp3d.GeodesicTracer(self.vertices, self.faces)
        self._paths = None
        bx, by, bn = self._vhm.get_tangent_frames()
        self.basis_x, self.basis_y, self.basis_n = (np.asarray(a, dtype=np.float64) for a in (bx, by, bn))
        self.vertex_normals = vertex_normals(self.vertices, self.faces)
        self.face_normals = face_normals(self.vertices, self.faces)  # zero (not NaN) on a robot wrapper's zero-area face
        self._aabb = igl.AABB()
        self._aabb.init(self.vertices, self.faces)
        self._component = None
        self._heat = None
        # the median over every face's three edges: one edge per face would depend on where each
        # face's corner list starts, so a mirrored hand (faces (a, c, b)) would read another length
        self.edge_length = float(np.median(self._edge_lengths))

    # ---- points -----------------------------------------------------------------------------
    def positions(self, points: SurfacePoints) -> np.ndarray:
        return points.positions(self.vertices, self.faces)

    def closest_points(self, xyz: np.ndarray) -> SurfacePoints:
        """Surface points nearest to xyz (N, 3), barycentrics snapped near vertices and edges."""
        xyz = np.ascontiguousarray(np.asarray(xyz, dtype=np.float64).reshape(-1, 3))
        _, face, closest = self._aabb.squared_distance(self.vertices, self.faces, xyz)
        face = np.asarray(face, dtype=np.int64)
        bary = _snap(barycentric_of(self.vertices[self.faces[face]], closest))
        return SurfacePoints(face, bary)

    def normal_at(self, face: int, barycentric: np.ndarray) -> np.ndarray:
        n = barycentric @ self.vertex_normals[self.faces[face]]
        return n / np.linalg.norm(n)

    def component_of(self, vertex: int) -> int:
        if self._component is None:
            from scipy.sparse import coo_matrix
            from scipy.sparse.csgraph import connected_components

            e = np.concatenate([self.faces[:, [0, 1]], self.faces[:, [1, 2]]])
            n = len(self.vertices)
            _, self._component = connected_components(coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)), directed=False)
        return int(self._component[vertex])

    def nearest_vertex(self, face: int, barycentric: np.ndarray) -> int:
        return int(self.faces[face][int(np.argmax(barycentric))])

    # ---- log maps ---------------------------------------------------------------------------
    def log_map(self, face: int, barycentric: np.ndarray, zero_direction: np.ndarray | None = None) -> np.ndarray:
        """(V, 2) log-map coordinates (metres) of every vertex about the surface point, with the
        angle measured from ``zero_direction`` (3D, any vector with a tangent part) or from the
        nearest vertex's tangent X axis. The map comes from the nearest vertex
        (potpourri3d, "AffineLocal") and is shifted by the point's own coordinates in it, which
        is accurate for points within a triangle of that vertex."""
        barycentric = np.asarray(barycentric, dtype=np.float64)
        corners = self.faces[face]
        origin = int(corners[int(np.argmax(barycentric))])
        coords = np.asarray(self._vhm.compute_log_map(origin, "AffineLocal"), dtype=np.float64)
        coords = coords - barycentric @ coords[corners]
        if zero_direction is not None:
            angle = self._tangent_angle(origin, zero_direction)
            c, s = np.cos(-angle), np.sin(-angle)
            coords = coords @ np.array([[c, s], [-s, c]])
        return coords

    def geodesic_distance(self, face: int, barycentric: np.ndarray) -> np.ndarray:
        """(V,) heat-method geodesic distance (m) of every vertex from the point's nearest vertex."""
        if self._heat is None:
            self._heat = pp3d.MeshHeatMethodDistanceSolver(self.vertices, self.faces)
        return np.asarray(self._heat.compute_distance(self.nearest_vertex(face, barycentric)), dtype=np.float64)

    def valid_chart_vertices(self, face: int, barycentric: np.ndarray, coords: np.ndarray,
                             distance: np.ndarray | None = None) -> np.ndarray:
        """(V,) where the log map about the point is trustworthy: its radius agrees with the
        heat-method distance (past the cut locus the log map folds and they part)."""
        if distance is None:
            distance = self.geodesic_distance(face, barycentric)
        radius = np.linalg.norm(coords, axis=1)
        return np.abs(radius - distance) <= 0.15 * distance + self.edge_length

    def valid_chart_faces(self, coords: np.ndarray, valid_vertices: np.ndarray, distance: np.ndarray,
                          radius: float = np.inf) -> np.ndarray:
        """(F,) faces laid out faithfully by a chart: corners trustworthy, positively oriented,
        edges neither squashed nor stretched by more than a factor 4 (a log map stretches
        angularly near the cut locus of a fingertip, but stays usable), and not covered in the
        layout by a face geodesically nearer the landmark (where the map folds over itself only
        the near sheet is kept, so the chart is one-to-one); within ``radius`` metres."""
        # the chart's extent first: most of the surface lies beyond it
        r = np.sqrt(np.einsum("ij,ij->i", coords, coords))
        keep = r[self.faces].max(axis=1) <= radius
        ids = np.nonzero(keep)[0]
        keep[ids] = self._faithful_faces(coords, valid_vertices, ids)
        ids = np.nonzero(keep)[0]
        if len(ids) < 2:
            return keep
        tri2 = coords[self.faces[ids]]
        centroid = tri2.mean(axis=1)
        near = distance[self.faces[ids]].mean(axis=1)
        # A triangle whose centroid lies strictly inside a geodesically nearer triangle overlaps it
        # in the layout (partial overlaps that miss the centroid are caught at transfer time).
        # Each triangle's barycentric map (inverse of its edge matrix) is formed once, and only
        # the nearer of the 16 closest triangles are tested.
        _, cand = cKDTree(centroid).query(centroid, k=min(16, len(ids)))
        rows, cols = np.nonzero((near[cand] < near[:, None] - 1e-12) & (cand != np.arange(len(ids))[:, None]))
        other = cand[rows, cols]
        origin = tri2[:, 0]
        e1, e2 = tri2[:, 1] - origin, tri2[:, 2] - origin
        det = e1[:, 0] * e2[:, 1] - e2[:, 0] * e1[:, 1]
        inv = 1.0 / np.where(np.abs(det) < 1e-300, 1e-300, det)
        d = centroid[rows] - origin[other]
        beta = (d[:, 0] * e2[other, 1] - e2[other, 0] * d[:, 1]) * inv[other]
        gamma = (e1[other, 0] * d[:, 1] - d[:, 0] * e1[other, 1]) * inv[other]
        inside = (beta > 1e-9) & (gamma > 1e-9) & (1 - beta - gamma > 1e-9)
        shadowed = np.zeros(len(ids), dtype=bool)
        shadowed[rows[inside]] = True
        keep[ids[shadowed]] = False
        return keep

    def _faithful_faces(self, coords: np.ndarray, valid_vertices: np.ndarray, ids: np.ndarray) -> np.ndarray:
        """(len(ids),) for faces ``ids``: see :meth:`valid_chart_faces`."""
        faces = self.faces[ids]
        tri2 = coords[faces]
        area = 0.5 * ((tri2[:, 1, 0] - tri2[:, 0, 0]) * (tri2[:, 2, 1] - tri2[:, 0, 1])
                      - (tri2[:, 2, 0] - tri2[:, 0, 0]) * (tri2[:, 1, 1] - tri2[:, 0, 1]))
        edge2 = tri2[:, [1, 2, 0]] - tri2
        ratio = np.sqrt(np.einsum("fkd,fkd->fk", edge2, edge2)) / self._edge_lengths[ids]
        return (valid_vertices[faces].all(axis=1) & (area > 1e-14)
                & (ratio.min(axis=1) > 0.25) & (ratio.max(axis=1) < 4.0))

    @property
    def _edge_lengths(self) -> np.ndarray:
        """(F, 3) 3D lengths of each face's edges k -> k+1 (m), computed once."""
        if getattr(self, "_edge_cache", None) is None:
            tri3 = self.vertices[self.faces]
            self._edge_cache = np.maximum(np.linalg.norm(tri3[:, [1, 2, 0]] - tri3, axis=2), 1e-12)
        return self._edge_cache

    def _tangent_angle(self, vertex: int, direction: np.ndarray) -> float:
        return float(np.arctan2(direction @ self.basis_y[vertex], direction @ self.basis_x[vertex]))

    def direction_toward(self, face: int, barycentric: np.ndarray, target: SurfacePoints) -> np.ndarray:
        """Unit 3D tangent direction at the surface point of the geodesic toward ``target`` (one
        point), read from the log map at the point."""
        coords = self.log_map(face, barycentric)
        corners = self.faces[target.faces[0]]
        xy = target.barycentric[0] @ coords[corners]
        if np.linalg.norm(xy) < 1e-9:
            raise InputError("the direction point coincides with the start point", element=self.name)
        origin = int(self.faces[face][int(np.argmax(barycentric))])
        d = xy[0] * self.basis_x[origin] + xy[1] * self.basis_y[origin]
        return self._tangent_in_face(face, d)

    def _tangent_in_face(self, face: int, direction: np.ndarray) -> np.ndarray:
        n = self.face_normals[face]
        d = direction - (direction @ n) * n
        return d / np.linalg.norm(d)

    # ---- exponential map ---------------------------------------------------------------------
    def trace(self, face: int, barycentric: np.ndarray, direction: np.ndarray, length: float) -> TraceResult:
        """Walk ``length`` metres along the geodesic leaving the surface point in ``direction``
        (3D; its component in the start face's plane is used)."""
        d = self._tangent_in_face(face, np.asarray(direction, dtype=np.float64))
        path = np.asarray(self._tracer.trace_geodesic_from_face(int(face), np.asarray(barycentric, dtype=np.float64), d * float(length)))
        steps = np.diff(path, axis=0)
        seg = np.linalg.norm(steps, axis=1)
        walked = float(seg.sum())
        end = path[-1]
        long_enough = np.nonzero(seg > 1e-6)[0]
        arrival = steps[long_enough[-1]] / seg[long_enough[-1]] if len(long_enough) else d
        point = self.closest_points(end[None])
        f, b = int(point.faces[0]), point.barycentric[0]
        arrival = self._tangent_in_face(f, arrival)
        return TraceResult(f, b, b @ self.vertices[self.faces[f]], arrival, walked)

    # ---- shortest paths ----------------------------------------------------------------------
    def shortest_path(self, start: SurfacePoints, end: SurfacePoints) -> np.ndarray:
        """(K, 3) polyline of the shortest geodesic between two surface points (edge-flip
        geodesics between their nearest vertices, the ends moved onto the exact points)."""
        if self._paths is None:
            self._paths = pp3d.EdgeFlipGeodesicSolver(self.vertices, self.faces)
        a = self.nearest_vertex(int(start.faces[0]), start.barycentric[0])
        b = self.nearest_vertex(int(end.faces[0]), end.barycentric[0])
        if self.component_of(a) != self.component_of(b):
            raise InputError("start and end lie on different (disconnected) parts of the surface", element=self.name)
        if a == b:
            path = self.vertices[[a]]
        else:
            path = np.asarray(self._paths.find_geodesic_path(a, b), dtype=np.float64)
        p0, p1 = self.positions(start)[0], self.positions(end)[0]
        return np.vstack([p0, path[1:-1], p1]) if len(path) > 2 else np.vstack([p0, p1])


def _snap(bary: np.ndarray) -> np.ndarray:
    bary = np.where(bary < SNAP, 0.0, bary)
    return bary / bary.sum(axis=1, keepdims=True)


class LogChart:
    """A log-map chart of one landmark laid out in the plane, for locating the surface point
    with given chart coordinates (the inverse of the log map, i.e. the exponential map of the
    same discrete chart). coords: (V, 2) chart coordinates of the mesh's vertices."""

    def __init__(self, faces: np.ndarray, coords: np.ndarray, radius: float, valid_faces: np.ndarray,
                 distance: np.ndarray):
        """faces (F, 3); coords (V, 2); radius (m): the chart's extent; valid_faces (F,) bool;
        distance (V,) geodesic distance of the vertices from the landmark (ranks the sheets
        where the layout still overlaps itself)."""
        # Only the faithful part near the landmark (see SurfaceGeometry.valid_chart_faces); laid
        # out from the valid faces alone, a small part of a large mesh.
        valid = np.nonzero(valid_faces)[0]
        tri = coords[faces[valid]]  # (K', 3, 2)
        inside = np.linalg.norm(tri, axis=2).max(axis=1) <= radius
        keep, tri = valid[inside], tri[inside]
        if len(keep) == 0:
            keep = np.argsort(np.linalg.norm(coords[faces], axis=2).max(axis=1))[:1]
            tri = coords[faces[keep]]
        self.face_ids = keep
        self.tri = tri
        self.reach = distance[faces[keep]].mean(axis=1)
        self._tree = cKDTree(self.tri.mean(axis=1))

    def to_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The laid-out part: face ids (K,), their triangles in the chart (K, 3, 2) m and the
        geodesic reach of each (K,) m; :meth:`from_arrays` rebuilds the same chart."""
        return self.face_ids, self.tri, self.reach

    @classmethod
    def from_arrays(cls, face_ids: np.ndarray, tri: np.ndarray, reach: np.ndarray) -> "LogChart":
        """The chart of :meth:`to_arrays`' output (only the point-location tree is rebuilt)."""
        chart = cls.__new__(cls)
        chart.face_ids, chart.tri, chart.reach = face_ids, tri, reach
        chart._tree = cKDTree(tri.mean(axis=1))
        return chart

    def locate(self, xy: np.ndarray, k: int = 24):
        """Faces (N,) and barycentrics (N, 3) of chart points xy (N, 2); points outside the
        chart's injective part go to the nearest triangle (clamped)."""
        xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        k = min(k, len(self.face_ids))
        _, cand = self._tree.query(xy, k=k)
        cand = np.asarray(cand).reshape(len(xy), k)
        t = self.tri[cand]  # (N, k, 3, 2)
        a, b, c = t[..., 0, :], t[..., 1, :], t[..., 2, :]
        v0, v1, v2 = b - a, c - a, xy[:, None, :] - a
        den = v0[..., 0] * v1[..., 1] - v1[..., 0] * v0[..., 1]
        den = np.where(np.abs(den) < 1e-300, 1e-300, den)
        beta = (v2[..., 0] * v1[..., 1] - v1[..., 0] * v2[..., 1]) / den
        gamma = (v0[..., 0] * v2[..., 1] - v2[..., 0] * v0[..., 1]) / den
        bary = np.stack([1.0 - beta - gamma, beta, gamma], axis=-1)  # (N, k, 3)
        worst = bary.min(axis=-1)
        # Where the layout overlaps itself (past the cut locus) several triangles contain the
        # point: take the one geodesically nearest the landmark. Else the least-outside one.
        inside = worst >= -1e-9
        score = np.where(inside, 1.0 + 1.0 / (1.0 + self.reach[cand]), worst)
        best = np.argmax(score, axis=1)
        rows = np.arange(len(xy))
        chosen = bary[rows, best]
        chosen = np.clip(chosen, 0.0, None)
        chosen /= chosen.sum(axis=1, keepdims=True)
        return self.face_ids[cand[rows, best]], _snap(chosen), worst[rows, best]
