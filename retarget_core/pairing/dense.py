"""Dense contact pairing by ray casting (paper section "Dense Contact Pairing").

GRAB-style clips label contact on the *object* only. For every labelled object vertex of a
frame we trace a ray from the vertex along its outward (area-weighted) vertex normal until it
hits the posed source hand, and store both ends as surface points (face, barycentric):

* object end: the contact vertex itself, as ``SurfacePoints.from_vertices`` would give it;
* hand end: the first triangle hit and the barycentric coordinates of the hit point.

Penetration: when the object vertex lies *inside* the hand, the ray along the normal leaves
the hand through a back face (hit triangle normal points along the ray). Those rays are
re-cast along the inverted normal (into the object), and the hit found there is the pair; the
pair is flagged ``inverted``. The back-face test is exact for a closed, consistently oriented,
non-self-intersecting hand surface (what rigs guarantee), and costs nothing extra: no
containment query is needed.

Discarded contacts: a ray (forward or, for inverted contacts, backward) that hits nothing is a
``"miss"``; a pair whose ends are more than ``epsilon`` apart is ``"too_far"``. Both are kept
in the result (``discarded_*`` arrays and the per-frame counts) so a report can say why.

Precision: embree works in float32 (trimesh scales the hand to a ~100-unit box first), so we
only take the *triangle index* from embree and recompute the hit point in float64 as the
intersection of the ray with the triangle's plane; the hand barycentric coordinates then
reproduce the hit to float64 precision. Ray origins are stepped back by ``ray_offset`` (1e-5 m)
against the ray so that a hand surface exactly at the contact point is still hit.
"""

from __future__ import annotations

import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

from ..errors import InputError
from ..files import save_npz_atomic
from ..mesh.geometry import signed_volume, vertex_normals
from ..mesh.surface_points import SurfacePoints

PAIRS_FORMAT = "handretarget.contact_pairs"
PAIRS_VERSION = 1

#: Reason codes stored in ``discarded_reason`` (index into this tuple).
DISCARD_REASONS = ("miss", "too_far")
MISS, TOO_FAR = 0, 1

DEFAULT_EPSILON = 0.015  # metres; the paper's code used about 1.5 cm
DEFAULT_RAY_OFFSET = 1e-5  # metres


# ------------------------------------------------------------------------------------------
# result containers
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class FramePairs:
    """The pairs of one frame (views into the flat arrays of :class:`ContactPairs`)."""

    frame: int
    object_vertex: np.ndarray
    object_face: np.ndarray
    object_barycentric: np.ndarray
    hand_face: np.ndarray
    hand_barycentric: np.ndarray
    gap: np.ndarray
    inverted: np.ndarray
    label: np.ndarray

    def __len__(self) -> int:
        return len(self.object_vertex)

    def object_points(self) -> SurfacePoints:
        return SurfacePoints(self.object_face, self.object_barycentric)

    def hand_points(self) -> SurfacePoints:
        return SurfacePoints(self.hand_face, self.hand_barycentric)


# name -> (dtype kind used on save, per-pair?)
_PAIR_FIELDS = {
    "object_vertex": np.int64,
    "object_face": np.int64,
    "object_barycentric": np.float64,
    "hand_face": np.int64,
    "hand_barycentric": np.float64,
    "gap": np.float64,
    "inverted": np.bool_,
    "label": np.uint8,
}
_FRAME_FIELDS = {
    "n_contacts": np.int64,
    "n_paired": np.int64,
    "n_miss": np.int64,
    "n_too_far": np.int64,
    "n_inverted": np.int64,
    "processed": np.bool_,
}
_DISCARD_FIELDS = {"discarded_frame": np.int64, "discarded_vertex": np.int64, "discarded_reason": np.uint8}


@dataclass
class ContactPairs:
    """Paired hand-object contact points of a whole clip, as flat arrays.

    The pairs of frame ``f`` are rows ``frame_offsets[f]:frame_offsets[f + 1]``. T is the
    clip's frame count even when only some frames were processed (``processed``).

    per pair (N rows): object_vertex, object_face, object_barycentric (N, 3), hand_face,
    hand_barycentric (N, 3), gap (metres between the two ends, world, at that frame),
    inverted (found by the inverted ray: the object point was inside the hand), label (GRAB
    contact code). per frame (T,): n_contacts = n_paired + n_miss + n_too_far, n_inverted,
    processed. per discarded contact (M rows): discarded_frame, discarded_vertex,
    discarded_reason (index into :data:`DISCARD_REASONS`).
    """

    frame_offsets: np.ndarray
    object_vertex: np.ndarray
    object_face: np.ndarray
    object_barycentric: np.ndarray
    hand_face: np.ndarray
    hand_barycentric: np.ndarray
    gap: np.ndarray
    inverted: np.ndarray
    label: np.ndarray
    n_contacts: np.ndarray
    n_paired: np.ndarray
    n_miss: np.ndarray
    n_too_far: np.ndarray
    n_inverted: np.ndarray
    processed: np.ndarray
    discarded_frame: np.ndarray
    discarded_vertex: np.ndarray
    discarded_reason: np.ndarray
    epsilon: float = DEFAULT_EPSILON
    ray_offset: float = DEFAULT_RAY_OFFSET
    n_object_vertices: int = 0
    n_object_faces: int = 0
    n_hand_faces: int = 0

    # ---- access ----------------------------------------------------------------------------
    @property
    def n_frames(self) -> int:
        return int(len(self.n_contacts))

    def __len__(self) -> int:
        return int(len(self.object_vertex))

    def frame(self, f: int) -> FramePairs:
        """The pairs of frame ``f``."""
        f = int(f)
        if not 0 <= f < self.n_frames:
            raise IndexError(f"frame {f} out of range [0, {self.n_frames})")
        s = slice(int(self.frame_offsets[f]), int(self.frame_offsets[f + 1]))
        return FramePairs(
            f,
            self.object_vertex[s],
            self.object_face[s],
            self.object_barycentric[s],
            self.hand_face[s],
            self.hand_barycentric[s],
            self.gap[s],
            self.inverted[s],
            self.label[s],
        )

    def discarded(self, f: int) -> dict[str, np.ndarray]:
        """{reason: object vertex ids} of the contacts of frame ``f`` that were discarded."""
        here = self.discarded_frame == int(f)
        return {r: self.discarded_vertex[here & (self.discarded_reason == i)] for i, r in enumerate(DISCARD_REASONS)}

    def summary(self) -> dict:
        """Totals, discarded fraction, gap statistics (mm) and frames with contacts."""
        contacts = int(self.n_contacts.sum())
        paired = int(len(self))
        discarded = int(self.n_miss.sum() + self.n_too_far.sum())
        gap_mm = self.gap * 1e3
        stats = {
            "frames": self.n_frames,
            "frames_processed": int(self.processed.sum()),
            "frames_with_contacts": int((self.n_contacts > 0).sum()),
            "frames_with_pairs": int((self.n_paired > 0).sum()),
            "contacts": contacts,
            "paired": paired,
            "inverted": int(self.inverted.sum()),
            "miss": int(self.n_miss.sum()),
            "too_far": int(self.n_too_far.sum()),
            "discarded": discarded,
            "discarded_fraction": discarded / contacts if contacts else 0.0,
            "epsilon_mm": float(self.epsilon) * 1e3,
            "gap_median_mm": float(np.median(gap_mm)) if paired else None,
            "gap_p90_mm": float(np.percentile(gap_mm, 90)) if paired else None,
            "gap_max_mm": float(gap_mm.max()) if paired else None,
        }
        return stats

    # ---- consistency -----------------------------------------------------------------------
    def validate(self, *, source: str = "") -> None:
        """Raise InputError naming the first inconsistent field."""

        def bad(name, message):
            raise InputError(message, source=source, element=name)

        n = len(self.object_vertex)
        t = len(self.n_contacts)
        for name in _PAIR_FIELDS:
            a = getattr(self, name)
            want = (n, 3) if name.endswith("barycentric") else (n,)
            if not isinstance(a, np.ndarray) or a.shape != want:
                bad(name, f"must have shape {want}, got {getattr(a, 'shape', None)}")
        for name in _FRAME_FIELDS:
            a = getattr(self, name)
            if not isinstance(a, np.ndarray) or a.shape != (t,):
                bad(name, f"must have shape (T={t},), got {getattr(a, 'shape', None)}")
        m = len(self.discarded_frame)
        for name in _DISCARD_FIELDS:
            a = getattr(self, name)
            if not isinstance(a, np.ndarray) or a.shape != (m,):
                bad(name, f"must have shape (M={m},), got {getattr(a, 'shape', None)}")
        off = self.frame_offsets
        if not isinstance(off, np.ndarray) or off.shape != (t + 1,):
            bad("frame_offsets", f"must have shape (T+1={t + 1},), got {getattr(off, 'shape', None)}")
        if off[0] != 0 or off[-1] != n or np.any(np.diff(off) < 0):
            bad("frame_offsets", f"must rise from 0 to the pair count {n}")
        if not np.array_equal(np.diff(off), self.n_paired):
            bad("n_paired", "does not match frame_offsets")
        for name in ("n_contacts", "n_paired", "n_miss", "n_too_far", "n_inverted"):
            if np.any(getattr(self, name) < 0):
                bad(name, "counts must be non-negative")
        mismatch = np.nonzero(self.n_contacts != self.n_paired + self.n_miss + self.n_too_far)[0]
        if len(mismatch):
            bad("n_contacts", f"frame {int(mismatch[0])}: n_contacts != n_paired + n_miss + n_too_far")
        frame_of_pair = np.repeat(np.arange(t), self.n_paired)
        if not np.array_equal(np.bincount(frame_of_pair[self.inverted], minlength=t), self.n_inverted):
            bad("n_inverted", "does not match the inverted flags")
        if np.any(self.n_contacts[~self.processed] != 0):
            bad("processed", "an unprocessed frame has contacts")
        if m:
            if self.discarded_frame.min() < 0 or self.discarded_frame.max() >= t:
                bad("discarded_frame", f"frame index out of range [0, {t})")
            if self.discarded_reason.max() >= len(DISCARD_REASONS):
                bad("discarded_reason", f"reason code must be < {len(DISCARD_REASONS)}")
        for code, name in ((MISS, "n_miss"), (TOO_FAR, "n_too_far")):
            counts = np.bincount(self.discarded_frame[self.discarded_reason == code], minlength=t)
            if not np.array_equal(counts, getattr(self, name)):
                bad(name, "does not match the discarded contacts")
        if not (np.isfinite(self.epsilon) and self.epsilon > 0):
            bad("epsilon", f"must be a positive number, got {self.epsilon!r}")
        if n:
            if not np.all(np.isfinite(self.gap)) or self.gap.min() < 0 or self.gap.max() > self.epsilon * (1 + 1e-9):
                bad("gap", f"must be finite, in [0, epsilon={self.epsilon}]")
            for name, limit in (("object_vertex", self.n_object_vertices), ("object_face", self.n_object_faces),
                                ("hand_face", self.n_hand_faces)):
                a = getattr(self, name)
                if a.min() < 0 or (limit and a.max() >= limit):
                    bad(name, f"index out of range [0, {limit})")
            for name in ("object_barycentric", "hand_barycentric"):
                b = getattr(self, name)
                if not np.all(np.isfinite(b)) or b.min() < -1e-6 or np.abs(b.sum(axis=1) - 1).max() > 1e-6:
                    bad(name, "rows must be non-negative and sum to 1")
        if m and self.n_object_vertices and (self.discarded_vertex.min() < 0
                                             or self.discarded_vertex.max() >= self.n_object_vertices):
            bad("discarded_vertex", f"index out of range [0, {self.n_object_vertices})")

    def check_clip(self, clip, *, source: str = "") -> None:
        """Raise InputError unless these pairs were made for a clip with ``clip``'s meshes."""
        for name, mine, theirs in (("n_frames", self.n_frames, clip.n_frames),
                                   ("n_object_vertices", self.n_object_vertices, len(clip.object_vertices)),
                                   ("n_object_faces", self.n_object_faces, len(clip.object_faces)),
                                   ("n_hand_faces", self.n_hand_faces, len(clip.hand_faces))):
            if mine != theirs:
                raise InputError(f"contact pairs have {mine}, the clip {theirs}", source=source, element=name)

    # ---- files -----------------------------------------------------------------------------
    def save(self, path) -> None:
        """Write an .npz (compressed, no pickles) atomically."""
        self.validate(source=str(path))
        path = Path(path)
        arrays = {
            "format": np.array(PAIRS_FORMAT),
            "version": np.array(PAIRS_VERSION),
            "epsilon": np.array(float(self.epsilon)),
            "ray_offset": np.array(float(self.ray_offset)),
            "n_object_vertices": np.array(int(self.n_object_vertices)),
            "n_object_faces": np.array(int(self.n_object_faces)),
            "n_hand_faces": np.array(int(self.n_hand_faces)),
            "frame_offsets": np.asarray(self.frame_offsets, dtype=np.int64),
        }
        for table in (_PAIR_FIELDS, _FRAME_FIELDS, _DISCARD_FIELDS):
            for name, dtype in table.items():
                arrays[name] = np.asarray(getattr(self, name), dtype=dtype)
        save_npz_atomic(path, arrays)


_SCALARS = ("epsilon", "ray_offset", "n_object_vertices", "n_object_faces", "n_hand_faces")


def load_contact_pairs(path) -> ContactPairs:
    """Read contact pairs written by :meth:`ContactPairs.save` (never unpickling) and validate."""
    path = Path(path)
    src = str(path)
    if not path.is_file():
        raise InputError("no such file", source=src)
    try:
        data = np.load(path, allow_pickle=False)
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as err:
        raise InputError(f"not a contact-pairs .npz file ({err})", source=src) from err
    if not hasattr(data, "files"):  # a bare .npy
        raise InputError("not a contact-pairs .npz file (a single array)", source=src)
    with data:
        required = ("format", "version", *_SCALARS, "frame_offsets", *_PAIR_FIELDS, *_FRAME_FIELDS, *_DISCARD_FIELDS)
        missing = [k for k in required if k not in data.files]
        if "format" in missing:
            raise InputError("not a contact-pairs file (no format field)", source=src, element="format")

        def get(key):
            try:
                return data[key]
            except (ValueError, zipfile.BadZipFile, OSError, EOFError) as err:
                raise InputError(f"unreadable field ({err})", source=src, element=key) from err

        fmt = get("format")
        if fmt.shape != () or str(fmt) != PAIRS_FORMAT:
            raise InputError(f"not a contact-pairs file (format {str(fmt)!r})", source=src, element="format")
        if "version" in missing:
            raise InputError("required field is missing", source=src, element="version")
        version = get("version")
        if version.shape != () or not np.issubdtype(version.dtype, np.integer) or int(version) != PAIRS_VERSION:
            raise InputError(f"contact-pairs version {version!s} is not supported (this build reads {PAIRS_VERSION})",
                             source=src, element="version")
        if missing:
            raise InputError("required field is missing", source=src, element=missing[0])

        def typed(key, dtype):
            a = get(key)
            if dtype is np.bool_:
                ok = a.dtype == np.bool_
            elif dtype is np.float64:
                ok = np.issubdtype(a.dtype, np.floating)
            else:
                ok = np.issubdtype(a.dtype, np.integer)
            if not ok:
                raise InputError(f"wrong dtype {a.dtype}", source=src, element=key)
            return a.astype(dtype)

        scalars = {}
        for key in _SCALARS:
            a = get(key)
            if a.shape != () or not np.issubdtype(a.dtype, np.number):
                raise InputError(f"must be a number, got {a!r}", source=src, element=key)
            scalars[key] = float(a) if key in ("epsilon", "ray_offset") else int(a)
        arrays = {"frame_offsets": typed("frame_offsets", np.int64)}
        for table in (_PAIR_FIELDS, _FRAME_FIELDS, _DISCARD_FIELDS):
            for name, dtype in table.items():
                arrays[name] = typed(name, dtype)
    pairs = ContactPairs(**arrays, **scalars)
    pairs.validate(source=src)
    return pairs


# ------------------------------------------------------------------------------------------
# pairing
# ------------------------------------------------------------------------------------------
def _hits(hand_vertices, hand_faces, tri, origins, directions):
    """Float64 hit points of rays (origins + t * directions) on the triangles ``tri``.

    Returns (location (H, 3), facing (H,) = dot(triangle normal, direction) unnormalised,
    triangle corners (H, 3, 3))."""
    corners = hand_vertices[hand_faces[tri]]
    e1 = corners[:, 1] - corners[:, 0]
    e2 = corners[:, 2] - corners[:, 0]
    fn = np.cross(e1, e2)
    denom = np.einsum("ij,ij->i", fn, directions)
    scale = np.linalg.norm(fn, axis=1)
    ok = np.abs(denom) > 1e-9 * scale
    t = np.einsum("ij,ij->i", fn, corners[:, 0] - origins) / np.where(ok, denom, 1.0)
    loc = origins + t[:, None] * directions
    if not ok.all():  # ray parallel to (or degenerate) triangle: the triangle point nearest the origin
        import trimesh

        bad = ~ok
        loc[bad] = trimesh.triangles.closest_point(corners[bad], origins[bad])
    return loc, denom, corners


def _barycentric(corners: np.ndarray, points: np.ndarray) -> np.ndarray:
    import trimesh

    bary = trimesh.triangles.points_to_barycentric(corners, points)
    bary = np.where(np.isfinite(bary), bary, 1.0 / 3.0)
    bary = np.clip(bary, 0.0, None)
    total = bary.sum(axis=1, keepdims=True)
    bary = np.where(total > 0, bary / np.where(total > 0, total, 1.0), 1.0 / 3.0)
    return bary


def _intersector(vertices: np.ndarray, faces: np.ndarray):
    import trimesh
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False, validate=False)
    return RayMeshIntersector(mesh)


def _object_contacts(clip, labels, obj_v, obj_f, normals, todo):
    """A function of a frame f giving its object-side contacts, in the object's frame:
    (vertex ids (n,), faces (n,), barycentric (n, 3), points (n, 3), unit normals (n, 3),
    contact codes (n,)). From the clip's contact surface points when it has them (format 2:
    e.g. a substituted object's contacts where they were traced, never snapped to a vertex;
    the vertex is the nearest corner), else from its labelled vertices."""
    if getattr(clip, "contact_offsets", None) is not None:
        offsets = np.asarray(clip.contact_offsets, dtype=np.int64)
        faces = np.asarray(clip.contact_faces, dtype=np.int64)
        bary = np.asarray(clip.contact_barycentric, dtype=np.float64)
        codes = np.asarray(clip.contact_codes)
        corners = obj_f[faces]  # (N, 3)
        points = np.einsum("nk,nkd->nd", bary, obj_v[corners])
        normal = np.einsum("nk,nkd->nd", bary, normals[corners])
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
        nearest = corners[np.arange(len(faces)), np.argmax(bary, axis=1)] if len(faces) else np.zeros(0, np.int64)

        def surface(f):
            r = slice(offsets[f], offsets[f + 1])
            return nearest[r], faces[r], bary[r], points[r], normal[r], codes[r]
        return surface

    has_contact = labels[todo].any(axis=1) if len(todo) else np.zeros(0, dtype=bool)
    used = np.nonzero(labels[todo[has_contact]].any(axis=0))[0] if has_contact.any() else np.zeros(0, np.int64)
    vertex_face = np.full(len(obj_v), -1, dtype=np.int64)
    vertex_bary = np.zeros((len(obj_v), 3))
    if len(used):
        sp = SurfacePoints.from_vertices(used, obj_f)
        vertex_face[used] = sp.faces
        vertex_bary[used] = sp.barycentric

    def labelled(f):
        ids = np.flatnonzero(labels[f])
        return ids, vertex_face[ids], vertex_bary[ids], obj_v[ids], normals[ids], labels[f, ids]
    return labelled


def pair_contacts(
    clip,
    *,
    epsilon: float = DEFAULT_EPSILON,
    frames: Iterable[int] | None = None,
    progress: Callable[[int, int], None] | None = None,
    ray_offset: float = DEFAULT_RAY_OFFSET,
) -> ContactPairs:
    """Pair every object contact of ``clip`` (its contact surface points when it has them,
    else its labelled vertices) with a point on the source hand.

    ``frames``: clip frame indices to process (default all); the others get no pairs and
    ``processed`` False. ``progress(done, total)`` is called after each processed frame.
    See the module docstring for the method; ``epsilon`` (metres) is the largest gap kept.
    """
    epsilon = float(epsilon)
    if not (np.isfinite(epsilon) and epsilon > 0):
        raise InputError(f"epsilon must be a positive number of metres, got {epsilon!r}", element="epsilon")
    ray_offset = float(ray_offset)
    if not (np.isfinite(ray_offset) and ray_offset >= 0):
        raise InputError(f"ray_offset must be >= 0, got {ray_offset!r}", element="ray_offset")

    hand_all = clip.hand_vertices
    hand_faces = np.asarray(clip.hand_faces, dtype=np.int64)
    obj_v = np.asarray(clip.object_vertices, dtype=np.float64)
    obj_f = np.asarray(clip.object_faces, dtype=np.int64)
    labels = np.asarray(clip.contact_labels)
    poses = np.asarray(clip.object_poses, dtype=np.float64)
    n_frames = int(hand_all.shape[0])
    if hand_all.ndim != 3 or hand_all.shape[2] != 3:
        raise InputError(f"must have shape (T, Vh, 3), got {hand_all.shape}", element="hand_vertices")
    if labels.shape != (n_frames, len(obj_v)):
        raise InputError(f"must have shape (T={n_frames}, Vo={len(obj_v)}), got {labels.shape}",
                         element="contact_labels")
    if poses.shape != (n_frames, 4, 4):
        raise InputError(f"must have shape (T={n_frames}, 4, 4), got {poses.shape}", element="object_poses")

    if frames is None:
        todo = np.arange(n_frames)
    else:
        todo = np.unique(np.asarray(list(frames), dtype=np.int64))
        if len(todo) and (todo[0] < 0 or todo[-1] >= n_frames):
            raise InputError(f"frame index out of range [0, {n_frames})", element="frames")
    processed = np.zeros(n_frames, dtype=bool)
    processed[todo] = True

    # Object side, once: outward vertex normals and each vertex as a surface point.
    normals = vertex_normals(obj_v, obj_f)
    if signed_volume(obj_v, obj_f) < 0:  # inward-wound mesh
        normals = -normals
    object_contacts = _object_contacts(clip, labels, obj_v, obj_f, normals, todo)

    n_contacts = np.zeros(n_frames, dtype=np.int64)
    n_paired = np.zeros(n_frames, dtype=np.int64)
    n_miss = np.zeros(n_frames, dtype=np.int64)
    n_too_far = np.zeros(n_frames, dtype=np.int64)
    n_inverted = np.zeros(n_frames, dtype=np.int64)
    out = {k: [] for k in ("vertex", "face", "bary", "hand_face", "hand_bary", "gap", "inverted", "label")}
    disc = {k: [] for k in ("frame", "vertex", "reason")}
    hand_sign = None
    total = len(todo)

    for done, f in enumerate(todo, start=1):
        f = int(f)
        ids, faces_f, bary_f, local_p, local_n, codes = object_contacts(f)
        if len(ids):
            hv = np.asarray(hand_all[f], dtype=np.float64)
            if hand_sign is None:  # outward-wound hand: +1; inward: -1
                hand_sign = 1.0 if signed_volume(hv, hand_faces) >= 0 else -1.0
            rot, trans = poses[f, :3, :3], poses[f, :3, 3]
            p = local_p @ rot.T + trans
            d = local_n @ rot.T
            inter = _intersector(hv, hand_faces)
            tri = np.asarray(inter.intersects_first(p - ray_offset * d, d), dtype=np.int64)

            hit = tri >= 0
            loc = np.zeros_like(p)
            corners = np.zeros((len(ids), 3, 3))
            inverted = np.zeros(len(ids), dtype=bool)
            if hit.any():
                loc[hit], facing, corners[hit] = _hits(hv, hand_faces, tri[hit], p[hit], d[hit])
                back = np.zeros(len(ids), dtype=bool)
                back[hit] = facing * hand_sign > 0  # left the hand: the point is inside it
                if back.any():
                    inverted = back
                    pb, db = p[back], -d[back]
                    tri_b = np.asarray(inter.intersects_first(pb - ray_offset * db, db), dtype=np.int64)
                    tri[back] = tri_b
                    hit_b = tri_b >= 0
                    if hit_b.any():
                        rows = np.flatnonzero(back)[hit_b]
                        loc[rows], _, corners[rows] = _hits(hv, hand_faces, tri_b[hit_b], pb[hit_b], db[hit_b])
                    hit = tri >= 0
            bary = np.zeros((len(ids), 3))
            gap = np.full(len(ids), np.inf)
            if hit.any():
                bary[hit] = _barycentric(corners[hit], loc[hit])
                hand_pt = np.einsum("pk,pkd->pd", bary[hit], corners[hit])
                gap[hit] = np.linalg.norm(hand_pt - p[hit], axis=1)
            keep = hit & (gap <= epsilon)
            far = hit & ~keep
            miss = ~hit

            n_contacts[f] = len(ids)
            n_paired[f] = int(keep.sum())
            n_miss[f] = int(miss.sum())
            n_too_far[f] = int(far.sum())
            n_inverted[f] = int((keep & inverted).sum())
            out["vertex"].append(ids[keep])
            out["face"].append(faces_f[keep])
            out["bary"].append(bary_f[keep])
            out["hand_face"].append(tri[keep])
            out["hand_bary"].append(bary[keep])
            out["gap"].append(gap[keep])
            out["inverted"].append(inverted[keep])
            out["label"].append(codes[keep])
            if not keep.all():
                reason = np.where(miss, MISS, TOO_FAR)[~keep]
                disc["frame"].append(np.full(len(reason), f, dtype=np.int64))
                disc["vertex"].append(ids[~keep])
                disc["reason"].append(reason)
        if progress is not None:
            progress(done, total)

    def cat(key, store, shape, dtype):
        return np.concatenate(store[key]).astype(dtype) if store[key] else np.zeros(shape, dtype=dtype)

    vertex = cat("vertex", out, (0,), np.int64)
    offsets = np.zeros(n_frames + 1, dtype=np.int64)
    np.cumsum(n_paired, out=offsets[1:])
    pairs = ContactPairs(
        frame_offsets=offsets,
        object_vertex=vertex,
        object_face=cat("face", out, (0,), np.int64),
        object_barycentric=cat("bary", out, (0, 3), np.float64),
        hand_face=cat("hand_face", out, (0,), np.int64),
        hand_barycentric=cat("hand_bary", out, (0, 3), np.float64),
        gap=cat("gap", out, (0,), np.float64),
        inverted=cat("inverted", out, (0,), np.bool_),
        label=cat("label", out, (0,), np.uint8),
        n_contacts=n_contacts,
        n_paired=n_paired,
        n_miss=n_miss,
        n_too_far=n_too_far,
        n_inverted=n_inverted,
        processed=processed,
        discarded_frame=cat("frame", disc, (0,), np.int64),
        discarded_vertex=cat("vertex", disc, (0,), np.int64),
        discarded_reason=cat("reason", disc, (0,), np.uint8),
        epsilon=epsilon,
        ray_offset=ray_offset,
        n_object_vertices=len(obj_v),
        n_object_faces=len(obj_f),
        n_hand_faces=len(hand_faces),
    )
    return pairs
