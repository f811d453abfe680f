"""What each frame's solve aims at: marker pairs (source marker positions of the frame, target
marker points) and contact pairs (target-hand contact points, object points and normals).

Built once per clip from the clip, its contact pairs, their transfer onto the target and the
annotations; stored as flat arrays so frames can be sent to worker processes cheaply.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from ..clip.format import Clip
from ..errors import InputError
from ..mesh.geometry import rigid_fit, vertex_normals
from ..mesh.surface_points import SurfacePoints
from ..pairing.dense import ContactPairs
from ..rig.hand_cut import surface_matches_hand
from ..rig.model import Rig
from ..transfer.annotations import Annotations, resolve_points
from ..transfer.atlas import TransferredContacts


@dataclass
class MarkerTargets:
    """Marker pairs. target_faces (Mt,), target_barycentric (Mt, 3): every target marker point;
    pair_target (Np,) index into them; pair_weight (Np,) (1/K for a marker of K pairs, so each
    marker counts once); source_positions (T, Np, 3) metres: the source side of each pair per
    frame; names (Np,) the marker of each pair; source_faces (Np,), source_barycentric (Np, 3): the source
    side of each pair on the source rig's surface; proportion: per marker, its rest mismatch
    and weight when weighted by the hand's proportions (:func:`proportion_weights`)."""

    target_faces: np.ndarray
    target_barycentric: np.ndarray
    pair_target: np.ndarray
    pair_weight: np.ndarray
    source_positions: np.ndarray
    names: list
    source_faces: np.ndarray | None = None
    source_barycentric: np.ndarray | None = None
    proportion: dict = dataclasses.field(default_factory=dict)


@dataclass
class ContactTargets:
    """Contact pairs of all frames, split by frame_offsets (T+1,): target_faces (N,),
    target_barycentric (N, 3) on the target surface, object_points (N, 3) and object_normals
    (N, 3) in world coordinates (metres, unit normals); gap (N,) metres: how far each object
    point was moved out along its normal (``keep_source_gap``; zeros otherwise), so the point
    on the object's surface is ``object_points - gap * object_normals``."""

    frame_offsets: np.ndarray
    target_faces: np.ndarray
    target_barycentric: np.ndarray
    object_points: np.ndarray
    object_normals: np.ndarray
    gap: np.ndarray

    def surface_points(self, f: int) -> np.ndarray:
        """(N_f, 3) the object-surface points of frame f (without the kept gap)."""
        sl = slice(int(self.frame_offsets[f]), int(self.frame_offsets[f + 1]))
        return self.object_points[sl] - self.gap[sl, None] * self.object_normals[sl]

    def frame(self, f: int):
        sl = slice(int(self.frame_offsets[f]), int(self.frame_offsets[f + 1]))
        return (SurfacePoints(self.target_faces[sl], self.target_barycentric[sl]), self.object_points[sl],
                self.object_normals[sl])

    def count(self, f: int) -> int:
        return int(self.frame_offsets[f + 1] - self.frame_offsets[f])


def marker_targets(clip: Clip, source: Rig, target: Rig, annotations: Annotations) -> MarkerTargets:
    """Marker pairs of every frame. The annotations' source side lives on the clip's hand mesh."""
    if not surface_matches_hand(source, clip.hand_faces):
        raise InputError(f"the clip's hand mesh ({len(clip.hand_faces)} triangles) is not the source rig "
                         f"{source.name!r}'s surface ({len(source.surface.faces)} triangles)", element="source rig")
    t_faces, t_bary, s_faces, s_bary = [], [], [], []
    pair_t, pair_s, weight, names = [], [], [], []
    for marker in annotations.markers:
        src = resolve_points(list(marker.source), source.surface.faces, source.surface.n_vertices,
                             what=f"marker {marker.name!r} source")
        tgt = resolve_points(list(marker.target), target.surface.faces, target.surface.n_vertices,
                             what=f"marker {marker.name!r} target")
        base_t, base_s = len(t_faces), len(s_faces)
        t_faces += list(tgt.faces)
        t_bary += list(tgt.barycentric)
        s_faces += list(src.faces)
        s_bary += list(src.barycentric)
        pairs = marker.pairs()
        for i, j in pairs:
            pair_s.append(base_s + i)
            pair_t.append(base_t + j)
            weight.append(1.0 / len(pairs))
            names.append(marker.name)
    if not pair_t:
        return MarkerTargets(np.zeros(0, np.int64), np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0),
                             np.zeros((clip.n_frames, 0, 3)), [])
    s_points = SurfacePoints(np.array(s_faces), np.array(s_bary))
    corners = clip.hand_faces[s_points.faces]  # (Ms, 3)
    src_pos = np.einsum("mk,tmkd->tmd", s_points.barycentric, clip.hand_vertices[:, corners].astype(np.float64))
    pair_s = np.array(pair_s)
    return MarkerTargets(np.array(t_faces), np.array(t_bary), np.array(pair_t), np.array(weight),
                         src_pos[:, pair_s], names, s_points.faces[pair_s], s_points.barycentric[pair_s])


def contact_targets(clip: Clip, pairs: ContactPairs, transferred: TransferredContacts, *,
                    keep_source_gap: bool = False) -> ContactTargets:
    """Contact pairs of every frame: the transferred target point, the object point and the
    object's outward normal there, in world coordinates. Dropped contacts are left out.

    ``keep_source_gap``: move each object point out along its normal by the source pair's
    gap along that normal (never inward), so the target touches where the source hand was
    rather than closing the millimetres a captured contact leaves open (a contact is "within
    threshold", not "on the surface"). Off, the points are on the object (the paper)."""
    normals = vertex_normals(clip.object_vertices, clip.object_faces)
    keep = ~transferred.dropped
    frame_of = np.repeat(np.arange(len(pairs.frame_offsets) - 1), np.diff(pairs.frame_offsets))
    frame_of = frame_of[keep]
    obj_corners = clip.object_faces[pairs.object_face[keep]]
    local_p = np.einsum("nk,nkd->nd", pairs.object_barycentric[keep], clip.object_vertices[obj_corners])
    local_n = np.einsum("nk,nkd->nd", pairs.object_barycentric[keep], normals[obj_corners])
    rot = clip.object_poses[frame_of, :3, :3]
    world_p = np.einsum("nab,nb->na", rot, local_p) + clip.object_poses[frame_of, :3, 3]
    world_n = np.einsum("nab,nb->na", rot, local_n)
    world_n /= np.linalg.norm(world_n, axis=1, keepdims=True)
    gap = np.zeros(len(world_p))
    if keep_source_gap:
        hand_corners = clip.hand_faces[pairs.hand_face[keep]]
        hand_p = np.einsum("nk,nkd->nd", pairs.hand_barycentric[keep],
                           clip.hand_vertices[frame_of[:, None], hand_corners].astype(np.float64))
        gap = np.maximum(np.einsum("nd,nd->n", hand_p - world_p, world_n), 0.0)
        world_p = world_p + gap[:, None] * world_n
    offsets = np.zeros(clip.n_frames + 1, dtype=np.int64)
    np.cumsum(np.bincount(frame_of, minlength=clip.n_frames), out=offsets[1:])
    return ContactTargets(offsets, transferred.face[keep], transferred.barycentric[keep], world_p, world_n, gap)


FINGER_CHAIN = ("Base", "Middle", "Tip", "Fingertip")
"""The paper's markers along each finger, from the knuckle out (``IndexBase`` ... ``IndexFingertip``)."""


def scale_finger_markers(markers: MarkerTargets, source: Rig, target: Rig) -> MarkerTargets:
    """The source markers of each finger re-placed for the target's finger proportions.

    Along each finger chain (``<Finger>Base``, ``Middle``, ``Tip``, ``Fingertip``: whichever of
    them the annotations have), every link from one marker to the next keeps its direction in
    each frame and is scaled by the target's link length over the source's, both at the rigs'
    rest poses (a marker of several points: their weighted centroid). The knuckle marker and
    all other markers stay where they are, so a target with the source's proportions gets the
    same markers back. Returns a new :class:`MarkerTargets` (source_positions (T, Np, 3), m)."""
    if not len(markers.pair_target):
        return markers
    if markers.source_faces is None:
        raise ValueError("marker targets built without their source points")
    names = np.asarray(markers.names, dtype=object)
    s_kin, t_kin = source.kinematics(), target.kinematics()
    s_rest = s_kin.points(source.rest_pose, s_kin.bind(SurfacePoints(markers.source_faces, markers.source_barycentric)))
    t_rest = t_kin.points(target.rest_pose, t_kin.bind(SurfacePoints(markers.target_faces, markers.target_barycentric)))
    t_rest = t_rest[markers.pair_target]  # (Np, 3)
    positions = markers.source_positions.copy()
    fingers = sorted({n[: -len(part)] for n in set(markers.names) for part in FINGER_CHAIN if n.endswith(part)})
    for finger in fingers:
        sel = [np.flatnonzero(names == finger + part) for part in FINGER_CHAIN if np.any(names == finger + part)]
        if len(sel) < 2:
            continue
        w = [markers.pair_weight[s] / markers.pair_weight[s].sum() for s in sel]
        def centroid(x):  # (..., Np, 3) -> (..., K, 3): each chain marker's weighted centroid
            return np.stack([(x[..., s, :] * wi[:, None]).sum(axis=-2) for s, wi in zip(sel, w)], axis=-2)

        src = centroid(markers.source_positions)  # (T, K, 3)
        links = np.diff(src, axis=1)  # (T, K-1, 3)
        s_len = np.linalg.norm(np.diff(centroid(s_rest), axis=0), axis=1)
        t_len = np.linalg.norm(np.diff(centroid(t_rest), axis=0), axis=1)
        ratio = np.where(s_len > 1e-9, t_len / np.maximum(s_len, 1e-9), 1.0)
        placed = np.concatenate([src[:, :1], src[:, :1] + np.cumsum(links * ratio[None, :, None], axis=1)], axis=1)
        for k, s in enumerate(sel):
            positions[:, s] += (placed[:, k] - src[:, k])[:, None]
    return dataclasses.replace(markers, source_positions=positions)


def rest_marker_mismatch(markers: MarkerTargets, source: Rig, target: Rig) -> tuple[list, np.ndarray, np.ndarray]:
    """(marker names (M,) in order of first appearance, the marker of every pair (Np,) as an
    index into them, distance (M,) m of each marker from the source's after the rigid fit of
    the target's markers onto the source's, both hands at rest). A marker's point is its
    pairs' weighted centroid on each side; the fit weighs every marker once."""
    if markers.source_faces is None:
        raise ValueError("marker targets built without their source points")
    s_kin, t_kin = source.kinematics(), target.kinematics()
    s_rest = s_kin.points(source.rest_pose, s_kin.bind(SurfacePoints(markers.source_faces, markers.source_barycentric)))
    t_rest = t_kin.points(target.rest_pose, t_kin.bind(SurfacePoints(markers.target_faces, markers.target_barycentric)))
    t_rest = t_rest[markers.pair_target]  # (Np, 3), pair by pair like s_rest
    index = {n: i for i, n in enumerate(dict.fromkeys(markers.names))}
    names = list(index)
    of = np.array([index[n] for n in markers.names], dtype=np.int64)
    w = markers.pair_weight / np.bincount(of, markers.pair_weight)[of]
    centroid = np.zeros((2, len(names), 3))
    for side, x in enumerate((s_rest, t_rest)):
        for a in range(3):
            centroid[side, :, a] = np.bincount(of, w * x[:, a], minlength=len(names))
    fit = rigid_fit(centroid[1], centroid[0])
    placed = centroid[1] @ fit[:3, :3].T + fit[:3, 3]
    return names, of, np.linalg.norm(placed - centroid[0], axis=1)


def proportion_weights(markers: MarkerTargets, source: Rig, target: Rig, width: float) -> MarkerTargets:
    """Markers weighted by the target's proportions (``markers.proportion_width``): a marker d
    metres from the source's at rest (:func:`rest_marker_mismatch`) has its pairs' weights
    multiplied by 1 / (1 + (d / width)^2), then all pair weights rescaled to their old sum, so
    the markers as a whole weigh as before against the contacts and the prior. ``width`` (m).
    The new targets' ``proportion`` gives {marker: {"rest_mismatch_mm", "weight"}} (result.json)."""
    if width <= 0 or len(markers.pair_target) == 0:
        return markers
    names, of, d = rest_marker_mismatch(markers, source, target)
    factor = 1.0 / (1.0 + (d / width) ** 2)
    weight = markers.pair_weight * factor[of]
    weight *= markers.pair_weight.sum() / weight.sum()
    per_marker = np.bincount(of, weight, minlength=len(names)) / np.bincount(of, markers.pair_weight, minlength=len(names))
    report = {n: {"rest_mismatch_mm": round(float(1000 * d[i]), 2), "weight": round(float(per_marker[i]), 4)}
              for i, n in enumerate(names)}
    return dataclasses.replace(markers, pair_weight=weight, proportion=report)
