"""Intersection metrics (paper, section "Results"): hand-object, self and table, as exact volumes.

The paper measures intersection as convex hulls of clusters of penetrating hand vertices. That
misses an object corner poking into the hand (no hand vertex is inside the object) and
over-counts concave penetrations, so here every volume is an exact mesh boolean (the manifold
library, :mod:`retarget_core.mesh.booleans`) on the posed meshes:

* **The hand as a solid.** The posed hand surface is one solid as it is. For self
  intersection it is also cut into closed parts by dominant skin weight or robot link
  (:mod:`retarget_core.rig.parts`); without skin weights each connected component is a part.
  Where two non-adjacent parts overlap, the surface's solid holds the overlap twice (booleans
  integrate the winding number), so each such overlap is counted once: subtracted from the
  hand's volume and from what the hand shares with the object or the table. The posed hand's
  volume is the percentage's denominator unless ``hand_volume_m3`` is given.
* **Hand-object**: volume of (hand) ∩ (object), with the object posed in world.
* **Self**: the sum over every pair of parts that do not share a surface edge (a fingertip and
  the palm, two fingers) of the volume of their intersection. Adjacent parts overlap at their
  joint by construction (their caps coincide), which is not self intersection.
* **Table**: volume of (hand solid) ∩ (the table box).
* **Depths** (m), in both directions, at the vertices of the intersection solid (hand
  vertices inside, the other body's vertices inside, and the crossing curve):
  ``hand_depth_m``, the deepest point of the hand inside the other body (its distance to the
  other body's surface); ``other_depth_m``, the deepest point of the other body (object, table,
  or the other part for self) inside the hand (its distance to the hand's surface). Depths not
  above :data:`~retarget_core.mesh.geometry.SURFACE_TOLERANCE_M` (1 nm) are 0: a vertex on a
  surface up to round-off is not in it.

Every volume is exact for the meshes as given (float64 round-off aside). The parts are closed
by caps inside the hand, so an overlap of two parts near a joint can include a sliver of cap
volume; adjacent parts are never compared, and at rest the demo hands read 0. Overlaps of
three parts at once are subtracted per pair (counted twice).

Units: metres, cubic metres; percentages are of the posed hand's volume.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass
from typing import Iterable, Sequence

import numpy as np

from ..errors import InputError
from ..mesh import booleans
from ..mesh.geometry import SURFACE_TOLERANCE_M, box_signed_distance, signed_volume
from ..mesh.topology import check_closed_manifold
from ..rig.parts import HandParts, hand_parts

KINDS = ("hand_object", "self", "table")


# ------------------------------------------------------------------------------------------
# result
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class IntersectionResult:
    """One frame's intersection of one kind ("hand_object", "self" or "table").

    ``available`` is False when the metric cannot be computed (open or non-manifold hand or
    object, non-finite vertices); ``reason`` then says why and the numbers are NaN.
    ``volume_m3``: exact intersection volume (m^3); ``percent_of_hand``: ``100 * volume_m3 /
    hand_volume_m3``; ``hand_depth_m`` / ``other_depth_m``: deepest penetration of the hand into
    the other body and of the other body into the hand (m, 0 when none; see the module notes);
    ``pieces``: connected pieces of the intersection; ``pairs``: for self, the overlapping part
    pairs as (part, part, volume m^3), largest first.
    """

    kind: str
    available: bool
    reason: str = ""
    volume_m3: float = math.nan
    percent_of_hand: float = math.nan
    hand_volume_m3: float = math.nan
    hand_depth_m: float = math.nan
    other_depth_m: float = math.nan
    pieces: int = 0
    pairs: tuple = ()

    @property
    def max_depth_m(self) -> float:
        """The deeper of the two directions (m)."""
        return max(self.hand_depth_m, self.other_depth_m)

    def to_dict(self) -> dict:
        """JSON-serialisable summary (NaN -> None)."""

        def num(x):
            return None if x is None or not math.isfinite(x) else float(x)

        return {
            "kind": self.kind,
            "available": self.available,
            "reason": self.reason,
            "volume_m3": num(self.volume_m3),
            "percent_of_hand": num(self.percent_of_hand),
            "hand_volume_m3": num(self.hand_volume_m3),
            "hand_depth_m": num(self.hand_depth_m),
            "other_depth_m": num(self.other_depth_m),
            "pieces": int(self.pieces),
            "pairs": [[a, b, float(v)] for a, b, v in self.pairs],
        }


def _unavailable(kind: str, reason: str) -> IntersectionResult:
    return IntersectionResult(kind=kind, available=False, reason=reason)


# ------------------------------------------------------------------------------------------
# the posed hand
# ------------------------------------------------------------------------------------------
def component_parts(faces: np.ndarray, vertices: np.ndarray) -> HandParts:
    """Parts of a hand surface without skin weights: one per connected component."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = np.asarray(faces, dtype=np.int64)
    n = len(vertices)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]]])
    _, label = connected_components(coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)), directed=False)
    k = int(label.max()) + 1
    return hand_parts(f, np.eye(k)[label], [f"component {i}" for i in range(k)], rest_vertices=vertices, min_faces=1)


def _distance(points: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(P,) unsigned distance (m) of points (P, 3) to the mesh, over the faces near the points.

    Every point here lies in an intersection solid whose boundary touches the mesh, so its
    nearest surface point is within the diagonal of the points' bounding box: only faces whose
    box comes that close are searched (the whole mesh when that guarantee fails)."""
    import igl

    if len(points) == 0:
        return np.zeros(0)
    p = np.ascontiguousarray(points, dtype=np.float64)
    lo, hi = p.min(axis=0), p.max(axis=0)
    reach = float(np.linalg.norm(hi - lo)) + 1e-9
    tri = vertices[faces]
    near = np.all((tri.max(axis=1) >= lo - reach) & (tri.min(axis=1) <= hi + reach), axis=1)
    for keep in (faces[near], faces):
        if len(keep) == 0:
            continue
        sq, _, _ = igl.point_mesh_squared_distance(p, np.ascontiguousarray(vertices, dtype=np.float64),
                                                   np.ascontiguousarray(keep, dtype=np.int64))
        d = np.sqrt(np.maximum(sq, 0.0))
        if d.max() <= reach or keep is faces:
            return d
    return d


def _depth(d: np.ndarray) -> float:
    worst = float(d.max()) if len(d) else 0.0
    return worst if worst > SURFACE_TOLERANCE_M else 0.0


def _boxes_overlap(a, b) -> bool:
    return bool(np.all(np.maximum(a[:3], b[:3]) <= np.minimum(a[3:], b[3:])))


class PosedHand:
    """The hand at one pose as solids, built once per frame and shared by the kinds.

    The posed surface is one solid as it is (its volume exact); where non-adjacent parts
    overlap, that solid holds the overlap twice (booleans integrate the winding number), so the
    overlaps found by :meth:`self_overlap` are subtracted from what the hand shares with the
    object or the table."""

    def __init__(self, parts: HandParts, vertices: np.ndarray, faces: np.ndarray,
                 hand_volume_m3: float | None = None):
        self.parts = parts
        self.vertices = vertices
        faces = np.asarray(faces, dtype=np.int64)
        self.faces = faces if signed_volume(vertices, faces) >= 0 else faces[:, ::-1]
        self.solid = booleans.solid(vertices, self.faces, what="hand surface")
        self._given_volume = hand_volume_m3
        self._overlaps = None  # [(a, b, overlap solid, volume)]
        self._volume = None

    @property
    def volume(self) -> float:
        """The percentages' denominator (m^3): as given, else the posed hand's own volume
        (each overlap counted once)."""
        if self._volume is None:
            v = self._given_volume
            if v is None:
                v = float(self.solid.volume()) - sum(o[3] for o in self.overlaps())
            if not (v > 0 and math.isfinite(v)):
                raise InputError(f"hand volume is not positive ({v!r} m^3)", element="hand")
            self._volume = float(v)
        return self._volume

    def overlaps(self) -> list:
        """Overlapping pairs of non-adjacent parts: (a, b, overlap solid, volume m^3)."""
        if self._overlaps is None:
            self._solids = [booleans.solid(v, f, what=f"hand part {name}")
                            for (v, f), name in zip(self.parts.posed(self.vertices), self.parts.names)]
            boxes = [s_.bounding_box() for s_ in self._solids]
            self._overlaps = []
            for a, b in self.parts.non_adjacent_pairs():
                if not _boxes_overlap(boxes[a], boxes[b]):
                    continue
                inter = self._solids[a] ^ self._solids[b]
                vol = float(inter.volume())
                if vol > 0.0:
                    self._overlaps.append((a, b, inter, vol))
        return self._overlaps

    def _shared(self, kind, other_solid, other_distance) -> IntersectionResult:
        inter = self.solid ^ other_solid
        vol = float(inter.volume())
        if inter.is_empty() or vol <= 0.0:
            return IntersectionResult(kind, True, volume_m3=0.0, percent_of_hand=0.0, hand_volume_m3=self.volume,
                                      hand_depth_m=0.0, other_depth_m=0.0)
        box = other_solid.bounding_box()
        for _, _, overlap, _ in self.overlaps():
            if _boxes_overlap(overlap.bounding_box(), box):
                vol -= float((overlap ^ other_solid).volume())  # held twice by the surface's solid
        vol = max(vol, 0.0)
        iv, _ = booleans.mesh_of(inter)
        return IntersectionResult(kind, True, volume_m3=vol, percent_of_hand=100.0 * vol / self.volume,
                                  hand_volume_m3=self.volume, hand_depth_m=_depth(other_distance(iv)),
                                  other_depth_m=_depth(_distance(iv, self.vertices, self.faces)),
                                  pieces=len(inter.decompose()))

    def with_object(self, object_solid, object_vertices, object_faces) -> IntersectionResult:
        """Hand-object: the object as a solid and its mesh, both in world."""
        return self._shared("hand_object", object_solid, lambda p: _distance(p, object_vertices, object_faces))

    def with_table(self, pose, half_extents) -> IntersectionResult:
        return self._shared("table", booleans.box_solid(pose, half_extents),
                            lambda p: np.maximum(-box_signed_distance(p, pose, half_extents), 0.0))

    def self_overlap(self) -> IntersectionResult:
        """Self: overlaps of the pairs of parts that do not share a surface edge."""
        total, depth, pieces, pairs = 0.0, 0.0, 0, []
        meshes = {}
        for a, b, inter, vol in self.overlaps():
            for k in (a, b):
                if k not in meshes:
                    meshes[k] = booleans.mesh_of(self._solids[k])
            iv, _ = booleans.mesh_of(inter)
            # a's points inside b lie at their distance from b's surface, and b's inside a
            depth = max(depth, _depth(_distance(iv, *meshes[b])), _depth(_distance(iv, *meshes[a])))
            total += vol
            pieces += len(inter.decompose())
            pairs.append((self.parts.names[a], self.parts.names[b], vol))
        pairs.sort(key=lambda p: -p[2])
        return IntersectionResult("self", True, volume_m3=total, percent_of_hand=100.0 * total / self.volume,
                                  hand_volume_m3=self.volume, hand_depth_m=depth, other_depth_m=depth,
                                  pieces=pieces, pairs=tuple(pairs))


def _as_points(points, element: str) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise InputError(f"must be a (N, 3) array, got shape {p.shape}", element=element)
    return p


_SURFACE_REPORTS: dict = {}  # (vertex count, faces digest) -> topology report; a clip's frames share one


def _surface_report(faces: np.ndarray, n_vertices: int):
    """check_closed_manifold of ``faces``, computed once per face content (every frame of a
    clip is the same surface posed; the check is ~30 ms on a 16k-vertex hand)."""
    key = (int(n_vertices), hashlib.blake2b(np.ascontiguousarray(faces).tobytes(), digest_size=16).digest())
    report = _SURFACE_REPORTS.get(key)
    if report is None:
        if len(_SURFACE_REPORTS) >= 16:
            _SURFACE_REPORTS.clear()
        report = _SURFACE_REPORTS[key] = check_closed_manifold(faces, n_vertices)
    return report


def _check_hand(hand_vertices, hand_faces, parts: HandParts | None):
    """(vertices, parts) or the reason the hand cannot be measured."""
    v = _as_points(hand_vertices, "hand_vertices")
    f = np.asarray(hand_faces, dtype=np.int64)
    if f.ndim != 2 or f.shape[1] != 3 or (len(f) and (f.min() < 0 or f.max() >= len(v))):
        raise InputError(f"must be (F, 3) ids into the {len(v)} hand vertices", element="hand_faces")
    report = _surface_report(f, len(v))
    if not (report.closed and report.manifold):
        return "hand surface is not a closed manifold: " + report.describe()
    if not np.all(np.isfinite(v)):
        return "hand vertices are not all finite"
    if parts is None:
        parts = component_parts(f, v)
    elif len(parts.face_part) != len(f):
        raise InputError(f"the hand parts cover {len(parts.face_part)} faces, the hand has {len(f)}",
                         element="parts")
    return v, parts


def _check_box(pose, half_extents) -> tuple[np.ndarray, np.ndarray]:
    pose = np.asarray(pose, dtype=np.float64)
    he = np.asarray(half_extents, dtype=np.float64)
    if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
        raise InputError(f"must be a finite (4, 4) matrix, got shape {pose.shape}", element="table_pose")
    if he.shape != (3,) or not np.all(he > 0):
        raise InputError(f"must be 3 positive half extents, got {he.tolist()}", element="table_half_extents")
    return pose, he


class SceneObject:
    """The object as a solid in its own frame (built once per clip); ``at(pose)`` in world."""

    def __init__(self, vertices, faces):
        self.vertices = _as_points(vertices, "object_vertices")
        self.faces = np.asarray(faces, dtype=np.int64)
        self.reason = ""
        self.solid = None
        report = check_closed_manifold(self.faces, len(self.vertices))
        if not report.closed:
            self.reason = "object surface is not closed: " + report.describe()
        elif not np.all(np.isfinite(self.vertices)):
            self.reason = "object vertices are not all finite"
        else:
            if signed_volume(self.vertices, self.faces) < 0:  # wound inside out: read it outward
                self.faces = self.faces[:, ::-1]
            try:
                self.solid = booleans.solid(self.vertices, self.faces, what="object")
            except InputError as exc:
                self.reason = "object: " + str(exc)
            else:
                if not self.solid.volume() > 0:
                    self.solid, self.reason = None, "object surface encloses no volume"

    def at(self, pose):
        """(solid, vertices, faces) in world for the (4, 4) world-from-object pose (None: as is)."""
        if pose is None:
            return self.solid, self.vertices, self.faces
        pose = np.asarray(pose, dtype=np.float64)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise InputError(f"must be a finite (4, 4) matrix, got shape {pose.shape}", element="object_pose")
        return (booleans.transformed(self.solid, pose), self.vertices @ pose[:3, :3].T + pose[:3, 3], self.faces)


def frame_intersections(
    hand_vertices: np.ndarray,
    hand_faces: np.ndarray,
    *,
    parts: HandParts | None = None,
    scene_object: SceneObject | None = None,
    object_pose: np.ndarray | None = None,
    table_pose: np.ndarray | None = None,
    table_half_extents: np.ndarray | None = None,
    kinds: Sequence[str] = KINDS,
    hand_volume_m3: float | None = None,
) -> dict[str, IntersectionResult]:
    """Every requested kind for one frame (kinds whose inputs are missing are skipped).

    hand_vertices (V, 3) world metres, hand_faces (F, 3) (a closed manifold); ``parts``: the
    hand cut into closed parts (:func:`retarget_core.rig.parts.rig_parts`; default: one part
    per connected component); ``scene_object`` with its (4, 4) ``object_pose``; the table as
    a (4, 4) pose and (3,) half extents.
    """
    for k in kinds:
        if k not in KINDS:
            raise InputError(f"unknown kind {k!r}; known: {', '.join(KINDS)}", element="kinds")
    wanted = [k for k in kinds if (k != "hand_object" or scene_object is not None)
              and (k != "table" or (table_pose is not None and table_half_extents is not None))]
    if "table" in wanted:
        table_pose, table_half_extents = _check_box(table_pose, table_half_extents)
    checked = _check_hand(hand_vertices, hand_faces, parts)
    if isinstance(checked, str):
        return {k: _unavailable(k, checked) for k in wanted}
    v, parts = checked
    out = {}
    try:
        hand = PosedHand(parts, v, hand_faces, hand_volume_m3)
        for k in wanted:
            if k == "hand_object":
                if scene_object.solid is None:
                    out[k] = _unavailable(k, scene_object.reason)
                else:
                    out[k] = hand.with_object(*scene_object.at(object_pose))
            elif k == "self":
                out[k] = hand.self_overlap()
            else:
                out[k] = hand.with_table(table_pose, table_half_extents)
    except InputError as exc:
        return {k: _unavailable(k, str(exc)) for k in wanted}
    return out


# ------------------------------------------------------------------------------------------
# one kind of one frame
# ------------------------------------------------------------------------------------------
def hand_object_intersection(hand_vertices, hand_faces, object_vertices, object_faces, object_pose=None, *,
                             parts: HandParts | None = None, hand_volume_m3: float | None = None
                             ) -> IntersectionResult:
    """Hand-object intersection of one frame: object_vertices (W, 3) metres / object_faces
    (G, 3) (closed) in the object's frame when ``object_pose`` (4, 4 world-from-object) is
    given, else in world."""
    return frame_intersections(hand_vertices, hand_faces, parts=parts, kinds=("hand_object",),
                               scene_object=SceneObject(object_vertices, object_faces), object_pose=object_pose,
                               hand_volume_m3=hand_volume_m3)["hand_object"]


def table_intersection(hand_vertices, hand_faces, table_pose, table_half_extents, *,
                       parts: HandParts | None = None, hand_volume_m3: float | None = None) -> IntersectionResult:
    """Hand-table intersection of one frame, the table a box of ``table_half_extents`` (3,) m
    centred on the rigid ``table_pose`` (4, 4, world-from-box)."""
    return frame_intersections(hand_vertices, hand_faces, parts=parts, kinds=("table",), table_pose=table_pose,
                               table_half_extents=table_half_extents, hand_volume_m3=hand_volume_m3)["table"]


def self_intersection(hand_vertices, hand_faces, *, parts: HandParts | None = None,
                      hand_volume_m3: float | None = None) -> IntersectionResult:
    """Self intersection of one frame: overlaps of non-adjacent hand parts (see the module
    notes). Without ``parts`` each connected component of the surface is a part."""
    return frame_intersections(hand_vertices, hand_faces, parts=parts, kinds=("self",),
                               hand_volume_m3=hand_volume_m3)["self"]


# ------------------------------------------------------------------------------------------
# a clip
# ------------------------------------------------------------------------------------------
def clip_intersections(
    hand_vertices: np.ndarray,
    hand_faces: np.ndarray,
    *,
    parts: HandParts | None = None,
    object_vertices: np.ndarray | None = None,
    object_faces: np.ndarray | None = None,
    object_poses: np.ndarray | None = None,
    table_pose: np.ndarray | None = None,
    table_half_extents: np.ndarray | None = None,
    kinds: Sequence[str] = KINDS,
    frames: Iterable[int] | None = None,
    hand_volume_m3: float | None = None,
) -> dict[str, list[IntersectionResult]]:
    """Every requested kind for every frame of a clip.

    hand_vertices (T, V, 3) metres, hand_faces (F, 3); object_vertices (W, 3) in the object's
    frame with object_faces (G, 3) and object_poses (T, 4, 4) world-from-object; table_pose
    (4, 4) and table_half_extents (3,). ``hand_volume_m3``: a fixed denominator for every
    frame (default: each posed frame's own volume). Returns kind -> list of
    :class:`IntersectionResult`, one per evaluated frame.
    """
    hv = np.asarray(hand_vertices, dtype=np.float64)
    if hv.ndim != 3 or hv.shape[2] != 3:
        raise InputError(f"must be a (T, V, 3) array, got shape {hv.shape}", element="hand_vertices")
    frame_list = list(range(len(hv))) if frames is None else [int(f) for f in frames]
    poses = None if object_poses is None else np.asarray(object_poses, dtype=np.float64)
    if poses is not None and (poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) != len(hv)):
        raise InputError(f"must be (T, 4, 4) with T = {len(hv)}, got {poses.shape}", element="object_poses")
    obj = None
    if object_vertices is not None and object_faces is not None:
        obj = SceneObject(object_vertices, object_faces)
    out: dict[str, list[IntersectionResult]] = {}
    for f in frame_list:
        found = frame_intersections(hv[f], hand_faces, parts=parts, scene_object=obj,
                                    object_pose=None if poses is None else poses[f], table_pose=table_pose,
                                    table_half_extents=table_half_extents, kinds=kinds, hand_volume_m3=hand_volume_m3)
        for k, r in found.items():
            out.setdefault(k, []).append(r)
    return out
