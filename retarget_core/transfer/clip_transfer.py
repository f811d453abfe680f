"""Transfer of a whole clip's paired contacts onto a target hand, its report and its picture."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from ..errors import InputError
from ..mesh.geometry import vertex_normals
from ..mesh.surface_points import SurfacePoints, closest_surface_points
from ..pairing.dense import ContactPairs
from ..rig.hand_cut import cap_faces, uncapped_faces
from ..rig.model import Rig
from .annotations import Annotations
from .atlas import Atlas, TransferredContacts, get_atlas


@dataclass
class ClipTransfer:
    """All frames' contacts of a clip carried to the target: ``contacts`` is aligned with the
    pairs (N), ``frame_offsets`` (T+1,) splits them by frame (as in ContactPairs)."""

    atlas: Atlas
    pairs: ContactPairs
    contacts: TransferredContacts

    def frame(self, f: int) -> slice:
        return slice(int(self.pairs.frame_offsets[f]), int(self.pairs.frame_offsets[f + 1]))


def atlas_for(source: Rig, target: Rig, annotations: Annotations, *, workers: int = 1,
              cache_dir=None) -> Atlas:
    """The (cached) atlas of two rigs' rest surfaces, built by ``workers`` processes; with
    ``cache_dir`` (a folder) also kept on disk for other processes (see :func:`get_atlas`)."""
    return get_atlas(source.surface.vertices, source.surface.faces, target.surface.vertices, target.surface.faces,
                     annotations, workers=workers, cache_dir=cache_dir)


def transfer_clip(pairs: ContactPairs, source: Rig, target: Rig, annotations: Annotations, *,
                  keep_patch_size: bool = False, workers: int = 1, cache_dir=None) -> ClipTransfer:
    """Carry every paired contact of every frame (the hand ends of ``pairs``, on ``source``'s
    surface) onto ``target`` in one vectorised pass (``workers``, ``cache_dir``: see
    :func:`atlas_for`); with ``keep_patch_size`` (the configuration's
    ``contacts.keep_patch_size``) each contact patch then keeps its size on the source
    (:func:`size_patches`); without, it is the charts' alone (the paper)."""
    if pairs.n_hand_faces not in (len(source.surface.faces), uncapped_faces(source)):
        raise InputError(
            f"the contact pairs were made on a hand with {pairs.n_hand_faces} faces; the source rig "
            f"{source.name!r} has {len(source.surface.faces)}", element="source rig")
    atlas = atlas_for(source, target, annotations, workers=workers, cache_dir=cache_dir)
    contacts = atlas.transfer(SurfacePoints(pairs.hand_face, pairs.hand_barycentric))
    if keep_patch_size:
        sv, sf = source.surface.vertices, source.surface.faces
        src = SurfacePoints(pairs.hand_face, pairs.hand_barycentric).positions(sv, sf)
        src_normals = np.einsum("nk,nkd->nd", pairs.hand_barycentric, vertex_normals(sv, sf)[sf[pairs.hand_face]])
        contacts = size_patches(contacts, pairs.frame_offsets, src, src_normals, target.surface.vertices,
                                target.surface.faces)
    return ClipTransfer(atlas, pairs, off_caps(contacts, target))


#: Source contacts of one frame and one axial curve closer than this (m, on the source's rest
#: surface) belong to one patch (single linkage); patches are sized one by one. (4 mm split
#: box_pinch's one index-tip patch into pieces whose centres kept the charts' spacing.)
PATCH_LINK = 0.01
#: A patch is resized by at most this factor either way, and not when it is within this share
#: of its source size.
PATCH_SCALE_LIMIT = 4.0
PATCH_SCALE_TOLERANCE = 0.01


def patches(points: np.ndarray, link: float = PATCH_LINK) -> np.ndarray:
    """(N,) patch label of each point (N, 3): connected components of the points closer than
    ``link`` m (single linkage)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    n = len(points)
    if n < 2:
        return np.zeros(n, dtype=np.int64)
    pairs = cKDTree(points).query_pairs(link, output_type="ndarray")
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)[1].astype(np.int64)


def size_patches(contacts: TransferredContacts, frame_offsets: np.ndarray, source_points: np.ndarray,
                 source_normals: np.ndarray, target_vertices: np.ndarray, target_faces: np.ndarray, *,
                 link: float = PATCH_LINK, passes: int = 2) -> TransferredContacts:
    """``contacts`` with each contact patch resized about its centre on the target's rest
    surface to the spread (RMS distance from the centroid) it had on the source.

    A patch is a frame's contacts (``frame_offsets`` (T+1,) splits them) on one axial curve,
    split into :func:`patches` by their source positions ``source_points`` (N, 3) m (surface
    normals there ``source_normals`` (N, 3)); spreads are measured in each patch's tangent plane
    on both hands. The charts place a patch and scale it with the finger (lambda_s, and the
    target's curvature on top), but its points are paired one by one with the same object points, so a patch larger
    than the object's leaves each point millimetres from its object point whatever the pose
    (robot4's index tip in box_pinch: 2.6x the source's, 8.3 mm contact error with the best
    rigid fit of the patch 8.3 mm). The object sizes a contact, the charts place it. Each
    point moves in the patch's tangent plane by (scale - 1) times its offset from the centroid
    and is put back on the surface (closest point); a second pass corrects what the surface's
    curvature took off."""
    src = np.asarray(source_points, dtype=np.float64)
    src_normals = np.asarray(source_normals, dtype=np.float64)
    # interpolated vertex normals: a point on an edge has one normal whichever face holds it
    normals = vertex_normals(target_vertices, target_faces)

    def positions(c):
        return np.einsum("nk,nkd->nd", c.barycentric, target_vertices[target_faces[c.face]])

    def scale_of(patch, tgt, c):
        """(scale, tangent offsets (K, 3)) of one patch at the target positions tgt."""
        at = np.einsum("nk,nkd->nd", c.barycentric[patch], normals[target_faces[c.face[patch]]])
        offset = _tangent_offsets(tgt[patch], at)
        spread = float(np.sqrt((offset ** 2).sum(axis=1).mean()))
        if spread < 1e-9:
            return 1.0, offset
        source_spread = float(np.sqrt((_tangent_offsets(src[patch], src_normals[patch]) ** 2).sum(axis=1).mean()))
        return float(np.clip(source_spread / spread, 1 / PATCH_SCALE_LIMIT, PATCH_SCALE_LIMIT)), offset

    # which patches to size is decided once, at the charts' positions: a later pass corrects
    # every one of them (a threshold met again after the first pass would pick by rounding)
    tgt = positions(contacts)
    chosen = [patch for patch in _contact_patches(contacts, frame_offsets, src, link)
              if abs(scale_of(patch, tgt, contacts)[0] - 1.0) >= PATCH_SCALE_TOLERANCE]
    if not chosen:
        return contacts  # every patch as on the source (identical hands give their contacts back exactly)
    moved = np.concatenate(chosen)
    for _ in range(max(1, int(passes))):
        tgt = positions(contacts)
        desired = tgt.copy()
        for patch in chosen:
            scale, offset = scale_of(patch, tgt, contacts)
            # each point moved along its tangent offset only: the least move that sizes the
            # patch (laying the offsets flat through the central point instead left the
            # alternate human's patches 0.2-0.4 mm further from a rigid fit of the source's)
            desired[patch] = tgt[patch] + (scale - 1.0) * offset
        placed = closest_surface_points(target_vertices, target_faces, desired[moved])
        face, bary = contacts.face.copy(), contacts.barycentric.copy()
        face[moved], bary[moved] = placed.faces, placed.barycentric
        contacts = replace(contacts, face=face, barycentric=bary)
    return contacts


def _contact_patches(contacts: TransferredContacts, frame_offsets: np.ndarray, source_points: np.ndarray,
                     link: float) -> list[np.ndarray]:
    """The contact ids of each patch (of two or more kept contacts): per frame and axial curve,
    the :func:`patches` of their source points (N, 3)."""
    out = []
    keep = ~contacts.dropped
    for f in range(len(frame_offsets) - 1):
        lo, hi = int(frame_offsets[f]), int(frame_offsets[f + 1])
        ids = lo + np.flatnonzero(keep[lo:hi])
        for c in np.unique(contacts.curve[ids]):
            mine = ids[contacts.curve[ids] == c]
            labels = patches(source_points[mine], link)
            out.extend(p for p in (mine[labels == k] for k in range(labels.max(initial=-1) + 1)) if len(p) >= 2)
    return out


def _tangent_offsets(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """(K, 3) the points' (K, 3) offsets from their centroid in the plane normal to the mean of
    ``normals`` (K, 3)."""
    n = normals.sum(axis=0)
    n /= max(float(np.linalg.norm(n)), 1e-12)
    offset = points - points.mean(axis=0)
    return offset - np.outer(offset @ n, n)


def off_caps(contacts: TransferredContacts, target: Rig) -> TransferredContacts:
    """``contacts`` with those carried onto a cap of ``target`` (the triangles that close a hand
    cut from a larger mesh, :func:`~retarget_core.rig.hand_cut.cap_faces`) dropped: a cap is no
    skin of the user's mesh."""
    caps = cap_faces(target)
    on_cap = np.isin(contacts.face, caps) & ~contacts.dropped
    if not on_cap.any():
        return contacts
    return replace(contacts, dropped=contacts.dropped | on_cap)


def _spread(points: np.ndarray) -> float:
    """RMS distance (m) of points (N, 3) from their centroid."""
    return float(np.sqrt(((points - points.mean(axis=0)) ** 2).sum(axis=1).mean())) if len(points) else 0.0


def transfer_report(result: ClipTransfer, source: Rig, target: Rig) -> dict:
    """Shares transferred and dropped (in total and per curve; ``unmapped``: dropped because no
    chart of the source lays the point out one-to-one, see
    :class:`~retarget_core.transfer.atlas.TransferredContacts`) and how the contacts' spread
    changes: per frame, the RMS distance of the contacts from their centroid on the target's rest
    surface over the same on the source's (median over frames with contacts)."""
    c = result.contacts
    names = result.atlas.curve_names
    total = len(c.dropped)
    unmapped = c.unmapped if c.unmapped is not None else np.zeros(total, dtype=bool)
    per_curve = {}
    for i, name in enumerate(names):
        mine = c.curve == i
        per_curve[name] = {"contacts": int(mine.sum()), "dropped": int((mine & c.dropped).sum()),
                           "unmapped": int((mine & unmapped).sum()),
                           "discarded_chart": result.atlas.target_curves[i] is None}
    src_pos = SurfacePoints(result.pairs.hand_face, result.pairs.hand_barycentric).positions(
        source.surface.vertices, source.surface.faces)
    tgt_pos = np.einsum("nk,nkd->nd", c.barycentric, target.surface.vertices[target.surface.faces[c.face]])
    ratios = []
    for f in range(len(result.pairs.frame_offsets) - 1):
        sl = result.frame(f)
        keep = ~c.dropped[sl]
        if keep.sum() < 3:
            continue
        s = _spread(src_pos[sl][keep])
        if s > 1e-6:
            ratios.append(_spread(tgt_pos[sl][keep]) / s)
    expected_drop = sum(v["contacts"] for v in per_curve.values() if v["discarded_chart"])
    return {
        "contacts": total,
        "transferred": int(total - c.dropped.sum()),
        "transferred_share": float(1 - c.dropped.mean()) if total else 1.0,
        "dropped_share": float(c.dropped.mean()) if total else 0.0,
        "dropped_on_discarded_charts": expected_drop,
        # source points no chart (and no geodesic) finds again: the source mesh is too coarse there
        "unmapped": int(unmapped.sum()),
        "per_curve": per_curve,
        "spread_ratio_median": float(np.median(ratios)) if ratios else None,
        "spread_ratio_p10": float(np.percentile(ratios, 10)) if ratios else None,
        "spread_ratio_p90": float(np.percentile(ratios, 90)) if ratios else None,
    }


CURVE_COLOURS = np.array([[220, 40, 40], [40, 150, 40], [40, 80, 220], [210, 160, 0], [160, 40, 200],
                          [0, 160, 160], [120, 120, 120], [240, 120, 40], [90, 60, 30]], dtype=float)
SKIN = np.array([230, 195, 170], dtype=float)


def _painted(rig: Rig, points: SurfacePoints, curves: np.ndarray) -> np.ndarray:
    """Per-vertex colours: skin, with each contact's nearest face corner painted by its curve."""
    colours = np.tile(SKIN, (rig.surface.n_vertices, 1))
    if len(points):
        corners = rig.surface.faces[points.faces]
        nearest = corners[np.arange(len(points)), np.argmax(points.barycentric, axis=1)]
        colours[nearest] = CURVE_COLOURS[curves % len(CURVE_COLOURS)]
    return colours


def render_transfer(result: ClipTransfer, source: Rig, target: Rig, frames: list[int], path, *,
                    size: int = 320) -> Path:
    """PNG: one row per frame, the source hand with that frame's contacts and the target hand
    with the transferred ones, both at rest seen from the palm side, contacts coloured by
    their axial curve (the paper's contact-retarget figure)."""
    from PIL import Image, ImageDraw

    from ..render import Camera, render_meshes

    c = result.contacts
    rows = []
    for f in frames:
        if not 0 <= f < len(result.pairs.frame_offsets) - 1:
            raise InputError(f"frame {f} is out of range", element="frames")
        sl = result.frame(f)
        keep = ~c.dropped[sl]
        src_pts = SurfacePoints(result.pairs.hand_face[sl], result.pairs.hand_barycentric[sl])
        tgt_pts = SurfacePoints(c.face[sl][keep], c.barycentric[sl][keep])
        panels = []
        for rig, pts, curves in ((source, src_pts, c.curve[sl]), (target, tgt_pts, c.curve[sl][keep])):
            v = rig.surface.vertices
            centre = 0.5 * (v.min(axis=0) + v.max(axis=0))
            extent = float(np.ptp(v[:, :2], axis=0).max())
            camera = Camera(eye=centre - np.array([0.0, 0.0, 1.0]), target=centre, up=(0, 1, 0),
                            projection="orthographic", ortho_height=extent * 1.08)
            image = render_meshes([(v, rig.surface.faces, _painted(rig, pts, curves))], camera, (size, size))
            panels.append(Image.fromarray(image))
        row = Image.new("RGB", (2 * size, size), (255, 255, 255))
        row.paste(panels[0], (0, 0))
        row.paste(panels[1], (size, 0))
        draw = ImageDraw.Draw(row)
        n = sl.stop - sl.start
        draw.text((6, 4), f"frame {f}: source ({n} contacts)", fill=(0, 0, 0))
        draw.text((size + 6, 4), f"{target.name} ({int(keep.sum())} transferred)", fill=(0, 0, 0))
        rows.append(row)
    sheet = Image.new("RGB", (2 * size, size * len(rows)), (255, 255, 255))
    for i, row in enumerate(rows):
        sheet.paste(row, (0, i * size))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    sheet.save(path)
    return path
