"""The atlas of log-map charts (paper section "Contact Alignment").

Landmarks are the axis points of every source axial curve. Each source contact belongs to its
geodesically nearest landmark (a geodesic Voronoi partition of the source hand), and is written
in that landmark's log map as (r, theta), theta measured from the curve's own direction at the
landmark. On the target the contact is rebuilt at (lambda_s(theta) * r, theta) from the
corresponding target landmark, in that landmark's own log-map chart, whose zero angle is the
reconstructed curve's direction. Contacts of a discarded curve's charts are dropped.

Everything that does not depend on the contacts (the curves, one log map per landmark on each
hand, the charts' layouts) is computed once per hand pair; :func:`get_atlas` caches it, so a
second clip onto the same hand pays nothing for set-up. Transfer is then a handful of
vectorised look-ups per contact.

Given a ``cache_dir``, :func:`get_atlas` also keeps built atlases on disk for other processes:
``<cache_dir>/<key>.npz``, ``key`` = :func:`atlas_key` (sha256 of the surfaces, the
annotations, the options and :data:`ATLAS_CACHE_VERSION`), holding the plain arrays of
:meth:`Atlas.to_arrays` (np.savez, no pickled objects) plus ``cache_version`` and ``cache_key``.
Files are written atomically; an unreadable, foreign or stale file is rebuilt and replaced.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import zipfile
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..files import atomic_path
from ..mesh.surface_points import SurfacePoints
from .annotations import Annotations, annotations_to_dict, resolve_points
from .axial_curves import Curve, SourceCurve, build_source_curve, reconstruct_curve
from .geodesics import LogChart, SurfaceGeometry

#: Target charts are laid out within this geodesic radius of their landmark (metres).
CHART_RADIUS = 0.06
#: A point carried by its geodesic (no chart lays it out one-to-one) must be found again on the
#: source within this (m): the geodesic's own round trip.
TRACE_TOLERANCE = 0.001

#: Version of the on-disk atlas (part of the cache key and stored in the file): bump it whenever
#: the arrays of :meth:`Atlas.to_arrays` or the way an atlas is built change.
ATLAS_CACHE_VERSION = 4  # 2: SurfaceGeometry.edge_length over all three edges of each face; 3: curve legs shot with
# a secant or taken from the shortest path, landmarks of a leg end exactly on its point; 4: a
# shortest-path leg's directions by central differences

log = logging.getLogger(__name__)


@dataclass
class TransferredContacts:
    """Transfer of N source surface points. face (N,), barycentric (N, 3) on the target
    (meaningless where dropped); landmark (N,) index of the chart used; curve (N,) index of its
    axial curve; dropped (N,) True for contacts of discarded charts; radius (N,) metres and
    angle (N,) radians in the source chart; traced (N,) True where no chart lays the source
    point out one-to-one (a sliver or folded triangle), so the point was carried by tracing its
    geodesic from the target landmark (the exponential map) instead of the chart layout;
    unmapped (N,) True for points neither a chart nor their geodesic finds again on the source
    (they are dropped too)."""

    face: np.ndarray
    barycentric: np.ndarray
    landmark: np.ndarray
    curve: np.ndarray
    dropped: np.ndarray
    radius: np.ndarray
    angle: np.ndarray
    traced: np.ndarray | None = None
    unmapped: np.ndarray | None = None

    def target_points(self) -> SurfacePoints:
        keep = ~self.dropped
        return SurfacePoints(self.face[keep], self.barycentric[keep])


class Atlas:
    """Charts of one (source surface, target surface, annotations) triple. Build with
    :func:`get_atlas` (cached) or directly."""

    def __init__(self, source: SurfaceGeometry, target: SurfaceGeometry, annotations: Annotations, *,
                 chart_radius: float = CHART_RADIUS, reconstruction: str = "chart", workers: int = 1):
        """``reconstruction``: "chart" (default) rebuilds a contact at chart coordinates
        (lambda_s r, theta) by inverting the target landmark's discrete log map, the same map
        type that wrote it on the source, so an identical pair of hands gives every contact
        back exactly; "trace" walks the geodesic (the exponential map) from the landmark
        instead, as the paper describes: as accurate on smooth surfaces, about 10x slower.
        ``workers`` > 1 computes the per-landmark log maps in that many processes."""
        if reconstruction not in ("chart", "trace"):
            raise InputError(f"reconstruction must be 'chart' or 'trace', got {reconstruction!r}")
        self.reconstruction = reconstruction
        annotations.check_meshes(source.faces, len(source.vertices), target.faces, len(target.vertices))
        self.annotations = annotations
        self.source, self.target = source, target
        spacing = annotations.landmark_spacing
        self.curve_names = [c.name for c in annotations.curves]
        self.source_curves: list[SourceCurve] = []
        self.target_curves: list[Curve | None] = []
        landmark_curve, landmark_index = [], []
        for ci, ann in enumerate(annotations.curves):
            what = f"axial curve {ann.name!r}"
            if ann.source_points:
                pts = resolve_points(ann.source_points, source.faces, len(source.vertices), what=f"{what} source points")
                src = build_source_curve(source, ann.name, points=pts, spacing=spacing)
            else:
                start = resolve_points([ann.source_start], source.faces, len(source.vertices), what=f"{what} source start")
                end = resolve_points([ann.source_end], source.faces, len(source.vertices), what=f"{what} source end")
                src = _with_element(lambda: build_source_curve(source, ann.name, start=start, end=end, spacing=spacing), what)
            self.source_curves.append(src)
            if ann.discard:
                self.target_curves.append(None)
            else:
                t = ann.target
                start = resolve_points([t.start], target.faces, len(target.vertices), what=f"{what} target start")
                toward = resolve_points([t.direction], target.faces, len(target.vertices), what=f"{what} target direction")
                through = None if t.through is None else resolve_points(
                    list(t.through), target.faces, len(target.vertices), what=f"{what} target through points")
                self.target_curves.append(_with_element(
                    lambda: reconstruct_curve(target, src, start, toward, t.lambda_a, through=through), what))
            landmark_curve += [ci] * len(src)
            landmark_index += list(range(len(src)))
        if not landmark_curve:
            raise InputError("the annotations have no axial curve", element="axial_curves")
        self.landmark_curve = np.array(landmark_curve, dtype=np.int64)
        self.landmark_index = np.array(landmark_index, dtype=np.int64)

        # One log map per landmark on each hand. Source charts: over all source vertices, angle
        # 0 along the curve, and where each is trustworthy. Target charts: laid out for point
        # location. Both hands' charts go to one pool of workers (no idle tail between them).
        n_landmarks = len(self.landmark_curve)
        source_items = []
        for m in range(n_landmarks):
            c = self.source_curves[self.landmark_curve[m]]
            k = self.landmark_index[m]
            source_items.append((int(c.faces[k]), c.barycentric[k], c.directions[k], chart_radius, True))
        target_items, charted = [], []
        for m in range(n_landmarks):
            tc = self.target_curves[self.landmark_curve[m]]
            if tc is None:
                continue
            k = self.landmark_index[m]
            lambda_s = annotations.curves[self.landmark_curve[m]].target.lambda_s
            scale = float(np.max(lambda_s(np.linspace(-np.pi, np.pi, 73))))
            target_items.append((int(tc.faces[k]), tc.barycentric[k], tc.directions[k],
                                 chart_radius * max(scale, 1.0), False))
            charted.append(m)
        source_fields, target_fields = chart_fields([(source, source_items), (target, target_items)], workers)

        self.source_coords = np.zeros((n_landmarks, len(source.vertices), 2), dtype=np.float32)
        self.source_valid_faces = np.zeros((n_landmarks, len(source.faces)), dtype=bool)
        self.source_charts: list[LogChart] = []
        radius = np.full((n_landmarks, len(source.vertices)), np.inf)
        for m, (coords, valid, valid_faces, chart) in enumerate(source_fields):
            self.source_coords[m] = coords
            self.source_valid_faces[m] = valid_faces
            self.source_charts.append(LogChart.from_arrays(*chart))
            radius[m, valid] = np.linalg.norm(coords[valid], axis=1)
        # geodesic Voronoi cell of every vertex (vertices no chart trusts go to the nearest by
        # the plain log-map radius)
        untrusted = ~np.isfinite(radius).any(axis=0)
        if untrusted.any():
            radius[:, untrusted] = np.linalg.norm(self.source_coords[:, untrusted], axis=2)
        self.vertex_landmark = np.argmin(radius, axis=0)
        self.target_charts: list[LogChart | None] = [None] * n_landmarks
        for m, (_, _, _, chart) in zip(charted, target_fields):
            self.target_charts[m] = LogChart.from_arrays(*chart)

    @property
    def n_landmarks(self) -> int:
        return len(self.landmark_curve)

    # ---- plain-array form (the on-disk cache) ---------------------------------------------
    def to_arrays(self) -> dict[str, np.ndarray]:
        """The expensive results as plain numeric arrays (L landmarks, C curves, V / F source
        vertices / faces, K the charts' laid-out faces, concatenated landmark by landmark):
        curve_sizes (C,) landmarks per curve; source_curve_{faces (L,), barycentric (L, 3),
        positions (L, 3) m, directions (L, 3), turning (L,) rad, lengths (L - C,) m};
        target_curve_kept (C,) and target_curve_{faces, barycentric, positions, directions}
        (zeros on discarded curves); source_coords (L, V, 2) m float32; source_valid_faces
        (L, F); vertex_landmark (V,); {source,target}_chart_{offsets (L+1,), face_ids (K,),
        tri (K, 3, 2) m, reach (K,) m} (a target landmark of a discarded curve has no faces).
        The surfaces' geodesic solvers are not part of it (:meth:`from_arrays` gets them)."""
        n_curves = len(self.curve_names)
        out = {"curve_sizes": np.bincount(self.landmark_curve, minlength=n_curves).astype(np.int64)}
        for name in _CURVE_FIELDS:
            out[f"source_curve_{name}"] = np.concatenate([getattr(c, name) for c in self.source_curves])
            out[f"target_curve_{name}"] = np.concatenate([
                getattr(t, name) if t is not None else np.zeros_like(getattr(s, name))
                for s, t in zip(self.source_curves, self.target_curves)])
        out["source_curve_turning"] = np.concatenate([c.turning for c in self.source_curves])
        out["source_curve_lengths"] = np.concatenate([c.lengths for c in self.source_curves])
        out["target_curve_kept"] = np.array([t is not None for t in self.target_curves], dtype=bool)
        out["source_coords"] = self.source_coords
        out["source_valid_faces"] = self.source_valid_faces
        out["vertex_landmark"] = self.vertex_landmark
        for side, charts in (("source", self.source_charts), ("target", self.target_charts)):
            parts = [c.to_arrays() for c in charts if c is not None] or [
                (np.zeros(0, np.int64), np.zeros((0, 3, 2)), np.zeros(0))]
            sizes = [0 if c is None else len(c.face_ids) for c in charts]
            out[f"{side}_chart_offsets"] = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
            for k, name in enumerate(("face_ids", "tri", "reach")):
                out[f"{side}_chart_{name}"] = np.concatenate([p[k] for p in parts])
        return out

    @classmethod
    def from_arrays(cls, source: SurfaceGeometry, target: SurfaceGeometry, annotations: Annotations,
                    arrays, *, reconstruction: str = "chart") -> "Atlas":
        """The atlas whose :meth:`to_arrays` gave ``arrays`` (a mapping of name to array), on the
        same surfaces and annotations; transfers exactly as the original. Computes no log map.
        Raises ValueError (or KeyError) when the arrays do not fit the surfaces / annotations."""
        if reconstruction not in ("chart", "trace"):
            raise InputError(f"reconstruction must be 'chart' or 'trace', got {reconstruction!r}")
        annotations.check_meshes(source.faces, len(source.vertices), target.faces, len(target.vertices))
        n_curves = len(annotations.curves)
        nv, nf = len(source.vertices), len(source.faces)

        def get(name, shape, dtype):
            a = arrays[name]
            if a.dtype != np.dtype(dtype) or a.shape != tuple(shape):
                raise ValueError(f"atlas array {name}: {a.dtype}{a.shape}, expected {np.dtype(dtype)}{tuple(shape)}")
            return a

        sizes = get("curve_sizes", (n_curves,), np.int64)
        if n_curves == 0 or (sizes < 1).any():
            raise ValueError("atlas arrays: every curve needs a landmark")
        n = int(sizes.sum())
        atlas = cls.__new__(cls)
        atlas.reconstruction = reconstruction
        atlas.annotations = annotations
        atlas.source, atlas.target = source, target
        atlas.curve_names = [c.name for c in annotations.curves]
        atlas.landmark_curve = np.repeat(np.arange(n_curves, dtype=np.int64), sizes)
        atlas.landmark_index = np.concatenate([np.arange(k, dtype=np.int64) for k in sizes])
        starts = np.concatenate([[0], np.cumsum(sizes)])
        src = {name: get(f"source_curve_{name}", (n,) + tail, dtype) for name, (tail, dtype) in _CURVE_FIELDS.items()}
        tgt = {name: get(f"target_curve_{name}", (n,) + tail, dtype) for name, (tail, dtype) in _CURVE_FIELDS.items()}
        turning = get("source_curve_turning", (n,), np.float64)
        lengths = get("source_curve_lengths", (n - n_curves,), np.float64)
        kept = get("target_curve_kept", (n_curves,), bool)
        if list(kept) != [not c.discard for c in annotations.curves]:
            raise ValueError("atlas arrays: discarded curves differ from the annotations")
        atlas.source_curves, atlas.target_curves = [], []
        for ci, name in enumerate(atlas.curve_names):
            rows = slice(starts[ci], starts[ci + 1])
            atlas.source_curves.append(SourceCurve(
                name, *(src[f][rows] for f in _CURVE_FIELDS),
                lengths=lengths[starts[ci] - ci:starts[ci + 1] - ci - 1], turning=turning[rows]))
            atlas.target_curves.append(Curve(name, *(tgt[f][rows] for f in _CURVE_FIELDS)) if kept[ci] else None)
        for curves, faces in ((atlas.source_curves, nf), (atlas.target_curves, len(target.faces))):
            if any(c is not None and ((c.faces < 0) | (c.faces >= faces)).any() for c in curves):
                raise ValueError("atlas arrays: a landmark face is out of range")
        atlas.source_coords = get("source_coords", (n, nv, 2), np.float32)
        atlas.source_valid_faces = get("source_valid_faces", (n, nf), bool)
        atlas.vertex_landmark = get("vertex_landmark", (nv,), np.int64)
        if ((atlas.vertex_landmark < 0) | (atlas.vertex_landmark >= n)).any():
            raise ValueError("atlas arrays: vertex_landmark out of range")
        atlas.source_charts = _unpack_charts(arrays, "source", np.ones(n, dtype=bool), nf, get)
        atlas.target_charts = _unpack_charts(arrays, "target", kept[atlas.landmark_curve], len(target.faces), get)
        return atlas

    def _trace_from_landmark(self, m: int, radius: np.ndarray, angle: np.ndarray, side: str = "target"):
        """Exponential map at landmark m of ``side``'s curve: trace (radius, angle) geodesics,
        angle measured counter-clockwise about the outward normal from the curve's direction."""
        geometry = self.target if side == "target" else self.source
        curves = self.target_curves if side == "target" else self.source_curves
        curve = curves[self.landmark_curve[m]]
        k = self.landmark_index[m]
        f0, b0 = int(curve.faces[k]), curve.barycentric[k]
        normal = geometry.face_normals[f0]
        zero = curve.directions[k] - (curve.directions[k] @ normal) * normal
        zero /= np.linalg.norm(zero)
        turn = np.cross(normal, zero)
        faces = np.zeros(len(radius), dtype=np.int64)
        barys = np.zeros((len(radius), 3))
        for i, (r, a) in enumerate(zip(radius, angle)):
            if r < 1e-9:
                faces[i], barys[i] = f0, b0
                continue
            end = geometry.trace(f0, b0, np.cos(a) * zero + np.sin(a) * turn, float(r))
            faces[i], barys[i] = end.face, end.barycentric
        return faces, barys

    def source_chart_coordinates(self, points: SurfacePoints, *, with_faithful: bool = False):
        """Nearest landmark (N,) and chart coordinates (N, 2) of source surface points (and with
        ``with_faithful``, (N,) whether that chart gives the point back).

        A point belongs to the nearest of its face corners' landmarks whose chart lays it out
        one-to-one: locating its coordinates in that chart must give the point back (near a
        fingertip's cut locus a chart can fold over itself, and a folded chart could not tell
        the point from another). A point no chart gives back keeps its nearest landmark's
        log-map coordinates (its chart's layout is then not used for it, see :meth:`transfer`)."""
        points.validate(self.source.faces)
        n = len(points)
        corners = self.source.faces[points.faces]  # (N, 3)
        bary = points.barycentric
        positions = points.positions(self.source.vertices, self.source.faces)
        candidates = self.vertex_landmark[corners]  # (N, 3): the corners' own cells
        coords = self.source_coords[candidates[:, :, None], corners[:, None, :]].astype(np.float64)  # (N, 3c, 3k, 2)
        xy = np.einsum("nk,nckd->ncd", bary, coords)  # (N, 3c, 2)
        r = np.linalg.norm(xy, axis=2)
        faithful = self.source_valid_faces[candidates, points.faces[:, None]]
        order = np.argsort(np.where(faithful, r, r + 1.0), axis=1)
        rows = np.arange(n)
        landmark, chart_xy = candidates[rows, order[:, 0]].copy(), xy[rows, order[:, 0]].copy()
        accepted = np.zeros(n, dtype=bool)
        for attempt in range(3):
            todo = np.nonzero(~accepted)[0]
            if len(todo) == 0:
                break
            cand = candidates[todo, order[todo, attempt]]
            cxy = xy[todo, order[todo, attempt]]
            ok = self._round_trips(cand, cxy, positions[todo])
            hit = todo[ok]
            landmark[hit], chart_xy[hit], accepted[hit] = cand[ok], cxy[ok], True
        # The rest: the nearest landmark of all whose chart gives the point back, if any.
        for i in np.nonzero(~accepted)[0]:
            usable = np.nonzero(self.source_valid_faces[:, points.faces[i]])[0]
            if len(usable) == 0:
                continue
            cxy = np.einsum("k,mkd->md", bary[i], self.source_coords[usable][:, corners[i]].astype(np.float64))
            for j in np.argsort(np.linalg.norm(cxy, axis=1))[:4]:
                if self._round_trips(usable[j:j + 1], cxy[j:j + 1], positions[i:i + 1])[0]:
                    landmark[i], chart_xy[i], accepted[i] = usable[j], cxy[j], True
                    break
        return (landmark, chart_xy, accepted) if with_faithful else (landmark, chart_xy)

    def _round_trips(self, landmark: np.ndarray, xy: np.ndarray, positions: np.ndarray) -> np.ndarray:
        """(N,) whether locating xy in the source chart of each landmark gives ``positions``."""
        ok = np.zeros(len(landmark), dtype=bool)
        for m in np.unique(landmark):
            rows = np.nonzero(landmark == m)[0]
            f, b, _ = self.source_charts[m].locate(xy[rows])
            back = np.einsum("nk,nkd->nd", b, self.source.vertices[self.source.faces[f]])
            ok[rows] = np.linalg.norm(back - positions[rows], axis=1) < 1e-6
        return ok

    def transfer(self, points: SurfacePoints) -> TransferredContacts:
        """Carry source surface points (N) onto the target: through the target chart's layout
        (``reconstruction`` "chart"), or by tracing the geodesic (r, theta) from the target
        landmark ("trace", and for the points no source chart lays out one-to-one)."""
        landmark, xy, faithful = self.source_chart_coordinates(points, with_faithful=True)
        n = len(points)
        positions = points.positions(self.source.vertices, self.source.faces)
        unmapped = np.zeros(n, dtype=bool)
        radius = np.linalg.norm(xy, axis=1)
        angle = np.arctan2(xy[:, 1], xy[:, 0])
        curve = self.landmark_curve[landmark]
        face = np.zeros(n, dtype=np.int64)
        bary = np.zeros((n, 3))
        dropped = np.array([self.target_curves[c] is None for c in range(len(self.target_curves))])[curve]
        order = np.argsort(landmark, kind="stable")
        bounds = np.searchsorted(landmark[order], np.arange(self.n_landmarks + 1))
        for m in range(self.n_landmarks):
            rows = order[bounds[m]:bounds[m + 1]]
            if len(rows) == 0 or self.target_charts[m] is None:
                continue
            lambda_s = self.annotations.curves[self.landmark_curve[m]].target.lambda_s
            scale = lambda_s(angle[rows])
            traced = rows if self.reconstruction == "trace" else rows[~faithful[rows]]
            if self.reconstruction == "chart":
                f, b, _ = self.target_charts[m].locate(xy[rows] * scale[:, None])
                face[rows], bary[rows] = f, b
            if len(traced) and self.reconstruction == "chart":
                # no chart lays these points out one-to-one: their geodesic from the landmark
                # carries them only where it finds them again on the source itself; where even
                # that fails (a fingertip too coarse for any log map) they are dropped, never
                # placed somewhere else on the hand
                sf, sb = self._trace_from_landmark(m, radius[traced], angle[traced], side="source")
                back = np.einsum("nk,nkd->nd", sb, self.source.vertices[self.source.faces[sf]])
                lost = np.linalg.norm(back - positions[traced], axis=1) > TRACE_TOLERANCE
                unmapped[traced[lost]] = True
                traced = traced[~lost]
            if len(traced):
                t_scale = lambda_s(angle[traced])
                face[traced], bary[traced] = self._trace_from_landmark(m, radius[traced] * t_scale, angle[traced])
        return TransferredContacts(face, bary, landmark, curve, dropped | unmapped, radius, angle,
                                   traced=~faithful if self.reconstruction == "chart" else np.ones(n, dtype=bool),
                                   unmapped=unmapped)


#: Per-landmark curve fields stored by :meth:`Atlas.to_arrays`: trailing shape and dtype.
_CURVE_FIELDS = {"faces": ((), np.int64), "barycentric": ((3,), np.float64),
                 "positions": ((3,), np.float64), "directions": ((3,), np.float64)}


def _unpack_charts(arrays, side: str, charted: np.ndarray, n_faces: int, get) -> list:
    """The LogCharts (None where not ``charted`` (L,)) from ``{side}_chart_*`` arrays."""
    n = len(charted)
    offsets = get(f"{side}_chart_offsets", (n + 1,), np.int64)
    steps = np.diff(offsets)
    if offsets[0] != 0 or (steps < 0).any() or ((steps > 0) != charted).any():
        raise ValueError(f"atlas arrays: bad {side} chart offsets")
    k = int(offsets[-1])
    face_ids = get(f"{side}_chart_face_ids", (k,), np.int64)
    tri = get(f"{side}_chart_tri", (k, 3, 2), np.float64)
    reach = get(f"{side}_chart_reach", (k,), np.float64)
    if ((face_ids < 0) | (face_ids >= n_faces)).any():
        raise ValueError(f"atlas arrays: {side} chart face out of range")
    return [LogChart.from_arrays(face_ids[a:b], tri[a:b], reach[a:b]) if ok else None
            for a, b, ok in zip(offsets[:-1], offsets[1:], charted)]


def _with_element(fn, element: str):
    """Run fn, re-raising an InputError with the annotation element in front."""
    try:
        return fn()
    except InputError as err:
        if element in str(err):
            raise
        raise InputError(str(err), element=element) from err


# ---- cache per hand pair -----------------------------------------------------------------
_CACHE: "OrderedDict[str, Atlas]" = OrderedDict()
_CACHE_SIZE = 8


def clear_memory_cache() -> None:
    """Forget the atlases kept in this process (:func:`get_atlas`): the next run builds its
    atlas again (or loads it from a disk cache), as a fresh process would."""
    _CACHE.clear()


def _potpourri3d_version() -> str:
    try:
        from importlib.metadata import version

        return version("potpourri3d")
    except Exception:  # pragma: no cover - not installed as a distribution
        return "unknown"


def atlas_key(source_vertices: np.ndarray, source_faces: np.ndarray, target_vertices: np.ndarray,
              target_faces: np.ndarray, annotations: Annotations, *, chart_radius: float = CHART_RADIUS,
              reconstruction: str = "chart") -> str:
    """sha256 (64 hex digits) naming the atlas of these surfaces (vertices (V, 3) m as float64,
    faces (F, 3) as int64: dtype, shape and bytes), the annotations' canonical JSON, the options,
    :data:`ATLAS_CACHE_VERSION` and the potpourri3d version."""
    h = hashlib.sha256()
    h.update(f"handretarget.atlas/{ATLAS_CACHE_VERSION}/potpourri3d {_potpourri3d_version()}\0".encode())
    for a, dtype in ((source_vertices, np.float64), (source_faces, np.int64),
                     (target_vertices, np.float64), (target_faces, np.int64)):
        a = np.ascontiguousarray(a, dtype=dtype)
        h.update(f"{a.dtype.str}{a.shape}\0".encode())
        h.update(a.tobytes())
    h.update(json.dumps(annotations_to_dict(annotations), sort_keys=True, separators=(",", ":")).encode())
    h.update(f"\0chart_radius={float(chart_radius)!r}\0reconstruction={reconstruction}".encode())
    return h.hexdigest()


def get_atlas(source_vertices: np.ndarray, source_faces: np.ndarray, target_vertices: np.ndarray,
              target_faces: np.ndarray, annotations: Annotations, *, workers: int = 1,
              chart_radius: float = CHART_RADIUS, reconstruction: str = "chart", cache_dir=None) -> Atlas:
    """The atlas of a hand pair, built once per (surfaces, annotations, options) and kept in
    memory; ``workers`` processes build its charts. With ``cache_dir`` (a folder, made when
    missing) a built atlas is also saved to / loaded from ``<cache_dir>/<atlas_key>.npz``, so
    other processes skip the build; a bad cache file is rebuilt, an unwritable folder only
    logs a warning."""
    key = atlas_key(source_vertices, source_faces, target_vertices, target_faces, annotations,
                    chart_radius=chart_radius, reconstruction=reconstruction)
    path = Path(cache_dir).expanduser() / f"{key}.npz" if cache_dir else None
    if key in _CACHE:
        _CACHE.move_to_end(key)
        atlas = _CACHE[key]
        if path is not None and not path.is_file():
            _save_cached(path, key, atlas)
        return atlas
    source = SurfaceGeometry(source_vertices, source_faces, name="source surface")
    target = SurfaceGeometry(target_vertices, target_faces, name="target surface")
    atlas = _load_cached(path, key, source, target, annotations, reconstruction) if path is not None else None
    if atlas is None:
        atlas = Atlas(source, target, annotations, chart_radius=chart_radius, reconstruction=reconstruction,
                      workers=workers)
        if path is not None:
            _save_cached(path, key, atlas)
    _CACHE[key] = atlas
    while len(_CACHE) > _CACHE_SIZE:
        _CACHE.popitem(last=False)
    return atlas


def _load_cached(path: Path, key: str, source: SurfaceGeometry, target: SurfaceGeometry,
                 annotations: Annotations, reconstruction: str) -> Atlas | None:
    """The atlas saved at ``path``, or None when it is missing or unusable (never raises for a
    bad file: truncated, not an npz, pickled objects, another version or key)."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {name: data[name] for name in data.files}
        if int(arrays["cache_version"]) != ATLAS_CACHE_VERSION or str(arrays["cache_key"]) != key:
            raise ValueError("another cache version or key")
        atlas = Atlas.from_arrays(source, target, annotations, arrays, reconstruction=reconstruction)
        with contextlib.suppress(OSError):  # its modification time is its last use (prune_atlas_cache)
            os.utime(path)
        return atlas
    except InputError:
        raise  # the annotations do not fit the surfaces: the build would say the same
    except (OSError, ValueError, KeyError, IndexError, TypeError, EOFError, zipfile.BadZipFile) as err:
        # a truncated, foreign or stale file: say so, remove it, rebuild (the caller saves anew)
        log.warning("corrupt atlas cache file %s (%s: %s): removed, rebuilding", path, type(err).__name__, err)
        with contextlib.suppress(OSError):
            path.unlink()
        return None


def _save_cached(path: Path, key: str, atlas: Atlas) -> None:
    """Write ``atlas`` to ``path`` (np.savez of plain arrays) through a temporary file in the
    same folder and an atomic rename; an OSError (read-only folder, full disk) is logged."""
    arrays = atlas.to_arrays()
    arrays["cache_version"] = np.array(ATLAS_CACHE_VERSION, dtype=np.int64)
    arrays["cache_key"] = np.array(key)
    try:
        with atomic_path(path, suffix=".npz.tmp") as tmp:
            with open(tmp, "wb") as handle:
                np.savez(handle, **arrays)
    except (OSError, ValueError) as err:
        log.warning("cannot write atlas cache file %s: %s", path, err)


def prune_atlas_cache(cache_dir, max_bytes: int, *, stale_tmp_seconds: float = 3600.0) -> tuple[int, int]:
    """Keep ``cache_dir``'s atlas files within ``max_bytes`` by removing the least recently used
    (a file's modification time is its last save or load), and remove temporary files left by
    a process killed mid-save (older than ``stale_tmp_seconds``). Returns (files removed,
    bytes freed). A missing folder is empty; files vanishing meanwhile are skipped."""
    folder = Path(cache_dir)
    if not folder.is_dir():
        return 0, 0
    now, removed, freed = time.time(), 0, 0
    entries = []
    for path in folder.iterdir():
        try:
            st = path.stat()
        except OSError:
            continue
        if path.name.endswith(".npz.tmp"):
            if now - st.st_mtime > stale_tmp_seconds and _unlink(path):
                removed, freed = removed + 1, freed + st.st_size
        elif path.suffix == ".npz":
            entries.append((st.st_mtime, st.st_size, path))
    total = sum(size for _, size, _ in entries)
    for _, size, path in sorted(entries, key=lambda e: e[0]):
        if total <= max_bytes:
            break
        if _unlink(path):
            total, removed, freed = total - size, removed + 1, freed + size
    return removed, freed


def _unlink(path: Path) -> bool:
    try:
        path.unlink()
        return True
    except OSError:
        return False


# ---- per-landmark charts, optionally in worker processes ----------------------------------------
def _one_chart(geometry: SurfaceGeometry, item):
    face, barycentric, direction, reach, with_coords = item
    coords = geometry.log_map(face, barycentric, direction)
    distance = geometry.geodesic_distance(face, barycentric)
    valid = geometry.valid_chart_vertices(face, barycentric, coords, distance)
    valid_faces = geometry.valid_chart_faces(coords, valid, distance, reach)
    chart = LogChart(geometry.faces, coords, reach, valid_faces, distance).to_arrays()
    if not with_coords:  # a target chart needs its layout only: send back no more than that
        return None, None, None, chart
    return coords, valid, valid_faces, chart


_CHART_WORKER: dict = {}


def _init_chart_worker(meshes):
    _CHART_WORKER["meshes"], _CHART_WORKER["geometry"] = meshes, {}


def _chart_batch(surface: int, items):
    geometry = _CHART_WORKER["geometry"].get(surface)
    if geometry is None:  # built (and its solvers factorised) on this worker's first use
        vertices, faces, name = _CHART_WORKER["meshes"][surface]
        geometry = _CHART_WORKER["geometry"][surface] = SurfaceGeometry(vertices, faces, name=name)
    return [_one_chart(geometry, item) for item in items]


def chart_fields(jobs, workers: int = 1) -> list[list]:
    """Charts of landmarks on one or more surfaces. ``jobs``: [(geometry, items)], an item being
    (face, barycentric (3,), zero direction (3,), reach m, with_coords). Per job, per item: log-map
    coordinates (V, 2), trusted vertices (V,) and chart faces (F,) (all three None unless
    with_coords), and the chart's :meth:`LogChart.to_arrays`. Worker processes rebuild the geometries
    (potpourri3d solvers do not pickle) and take small batches from one queue, so neither hand
    waits for the other."""
    total = sum(len(items) for _, items in jobs)
    workers = max(1, min(int(workers), total // 8))
    if workers == 1:
        return [[_one_chart(geometry, item) for item in items] for geometry, items in jobs]
    from concurrent.futures import ProcessPoolExecutor

    chunk = max(1, min(16, total // (workers * 4)))
    tasks = [(j, items[k:k + chunk]) for j, (_, items) in enumerate(jobs) for k in range(0, len(items), chunk)]
    meshes = [(g.vertices, g.faces, g.name) for g, _ in jobs]
    with ProcessPoolExecutor(workers, initializer=_init_chart_worker, initargs=(meshes,)) as pool:
        parts = list(pool.map(_chart_batch, *zip(*tasks)))
    out: list[list] = [[] for _ in jobs]
    for (j, _), part in zip(tasks, parts):
        out[j] += part
    return out
