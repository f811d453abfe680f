"""Proposed annotations for a pair of hands, from their hand models (:mod:`retarget_core.rig.hand_model`):
a starting point an artist can edit (the paper's annotations were made by hand).

For every finger of the source: an axial curve along the finger's palmar midline from its
knuckle over the pad to the apex of the fingertip, drawn through the skin straight palmar of
each articulation; on the target, the finger of the same role (a finger the target lacks is
discarded; fingers only the target has are reported), through the same anatomical points of its
own (``through``), with lambda_a = the target finger's length over the
source's (measured along its segments) and lambda_s = the ratio of their girths. Two palm
curves (wrist to the central knuckle; first knuckle across to the outermost) cover the palm.
Virtual markers: the paper's 25 names on anatomical landmarks (:func:`retarget_core.rig.anatomy.marker_sites`),
a single point on the source and a small area (the point and the vertices within
``area_radius``) on the target. Every point lies on the hand's own surface: a forearm or a mount
never receives one.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from ..rig.anatomy import articulation_sites, closest_hand_points, marker_sites, place_markers, surface_along
from ..rig.hand_model import HandMapping, HandModel, hand_model
from ..rig.model import Rig
from .annotations import (
    Annotations,
    AxialCurveAnnotation,
    CurveTarget,
    LambdaS,
    MarkerPair,
    MeshSignature,
    PointRef,
)

log = logging.getLogger(__name__)

PALMAR_OFFSET = 0.03  # metres: how far off the bone the palmar-side curve points are sought


@dataclass
class Proposal:
    """Proposed annotations and what the proposer noticed: ``discarded`` source fingers the
    target lacks, ``extra`` target fingers with no source finger (they receive no contacts),
    and the two hand models."""

    annotations: Annotations
    source_model: HandModel
    target_model: HandModel
    discarded: list[str] = field(default_factory=list)
    extra: list[str] = field(default_factory=list)

    def messages(self) -> list[str]:
        out = []
        if self.discarded:
            out.append(f"the target has no {', '.join(self.discarded)}: "
                       f"{'its' if len(self.discarded) == 1 else 'their'} contacts are discarded")
        if self.extra:
            out.append(f"target fingers with no source finger (they receive no contacts): {', '.join(self.extra)}")
        return out


def _point(rig: Rig, model: HandModel, xyz, *, palm_only=False) -> PointRef:
    sp = closest_hand_points(rig, model, np.asarray(xyz, float)[None], palm_only=palm_only)
    return PointRef(face=int(sp.faces[0]), barycentric=tuple(float(x) for x in sp.barycentric[0]))


def _surface_along(rig: Rig, model: HandModel, origin, direction, *, palm_only=False) -> PointRef:
    sp = surface_along(rig, model, np.asarray(origin, float)[None], np.asarray(direction, float)[None],
                       palm_only=palm_only, reach=PALMAR_OFFSET)
    return PointRef(face=int(sp.faces[0]), barycentric=tuple(float(x) for x in sp.barycentric[0]))


def _palmar_points(rig: Rig, model: HandModel, finger, ks) -> list[PointRef]:
    """The finger's palmar midline as anchor points: on the surface straight palmar of the
    articulations ``ks`` (knuckle first), then the apex of the fingertip."""
    directions = articulation_sites(rig, model, finger, ks, 1.0)
    points = [_surface_along(rig, model, finger.segments[k].start, directions[i]) for i, k in enumerate(ks)]
    return points + [_point(rig, model, finger.tip)]


def _palm_sites(rig: Rig, model: HandModel) -> list[PointRef]:
    """(root, central knuckle, first knuckle, outermost knuckle): on the palm straight palmar of
    a point 15 mm past the wrist and of points just behind the knuckles."""
    fingers = [f for f in model.fingers if not f.is_thumb]
    if not fingers:
        raise InputError("cannot propose palm curves: the hand has no finger besides the thumb",
                         source=model.rig_name)
    central = model.finger("middle") or fingers[len(fingers) // 2]
    # from points just behind the knuckles, so the rays leave through the palm, not a finger's base
    back = [f.knuckle + 0.15 * (model.wrist - f.knuckle) for f in (central, fingers[0], fingers[-1])]
    origins = (model.wrist + model.forward * 0.015, *back)
    return [_surface_along(rig, model, o, model.palmar, palm_only=True) for o in origins]


def _position(rig: Rig, point: PointRef) -> np.ndarray:
    return np.asarray(point.barycentric) @ rig.surface.vertices[rig.surface.faces[point.face]]


def propose(source: Rig, target: Rig, *, area_radius: float = 0.004, spacing: float = 0.002,
            source_mapping: HandMapping | None = None, target_mapping: HandMapping | None = None) -> Proposal:
    """Proposed markers and axial curves from ``source`` onto ``target``, any two hands the hand
    model reads (``*_mapping`` settles what it cannot)."""
    sm, tm = hand_model(source, source_mapping), hand_model(target, target_mapping)
    curves, discarded = [], []
    for s in sm.fingers:
        t = tm.finger(s.name)
        # The curve runs through the palmar midline on both hands (a single geodesic from the
        # knuckle to the apex spirals round a curled or twisted finger, differently on each hand,
        # and carried pad contacts to the finger's side); the anchors are every articulation
        # when both fingers have as many, else the knuckle and the last one.
        ks_source = list(range(len(s.segments)))
        if t is not None:
            ks_target = list(range(len(t.segments)))
            if len(ks_target) != len(ks_source):
                ks_source, ks_target = [0, ks_source[-1]], [0, ks_target[-1]]
            t_points = _palmar_points(target, tm, t, ks_target)
            curve_target = CurveTarget(
                start=t_points[0],
                direction=t_points[1],
                through=tuple(t_points[1:]),
                lambda_a=round(t.length / s.length, 3),
                lambda_s=LambdaS.constant(round(t.girth / s.girth, 3)),
            )
        else:
            curve_target = None
            discarded.append(s.name)
        # the end is the apex of the fingertip: charts then cover the pad, the tip and the nail
        curves.append(AxialCurveAnnotation(name=s.name, source_points=tuple(_palmar_points(source, sm, s, ks_source)),
                                           target=curve_target))
    extra = [f.name for f in tm.fingers if sm.finger(f.name) is None]

    s_sites, t_sites = _palm_sites(source, sm), _palm_sites(target, tm)
    s_root, s_mid, s_first, s_last = (_position(source, p) for p in s_sites)
    t_root, t_mid, t_first, t_last = (_position(target, p) for p in t_sites)
    ratio_long = np.linalg.norm(t_mid - t_root) / np.linalg.norm(s_mid - s_root)
    ratio_cross = np.linalg.norm(t_last - t_first) / max(np.linalg.norm(s_last - s_first), 1e-9)
    curves.append(AxialCurveAnnotation(
        name="palm", source_start=s_sites[0], source_end=s_sites[1], source_points=None,
        target=CurveTarget(start=t_sites[0], direction=t_sites[1], lambda_a=round(float(ratio_long), 3),
                           lambda_s=LambdaS.constant(round(float(ratio_cross), 3)))))
    curves.append(AxialCurveAnnotation(
        name="knuckles", source_start=s_sites[2], source_end=s_sites[3], source_points=None,
        target=CurveTarget(start=t_sites[2], direction=t_sites[3], lambda_a=round(float(ratio_cross), 3),
                           lambda_s=LambdaS.constant(round(float(ratio_long), 3)))))

    # Markers by name: a point on the source, an area on the target.
    s_sites, t_sites = marker_sites(source, sm), marker_sites(target, tm)
    names = [n for n in s_sites if n in t_sites]
    s_points = place_markers(source, sm, s_sites, names)
    t_points = place_markers(target, tm, t_sites, names)
    t_centres = t_points.positions(target.surface.vertices, target.surface.faces)
    hand_ids = np.nonzero(tm.hand_vertices)[0]
    markers = []
    for i, name in enumerate(names):
        near = hand_ids[np.linalg.norm(target.surface.vertices[hand_ids] - t_centres[i], axis=1) <= area_radius]
        area = [PointRef(face=int(t_points.faces[i]), barycentric=tuple(float(x) for x in t_points.barycentric[i]))]
        area += [PointRef(vertex=int(v)) for v in near]
        markers.append(MarkerPair(name=name, source=[PointRef(face=int(s_points.faces[i]),
                                                              barycentric=tuple(float(x) for x in s_points.barycentric[i]))],
                                  target=area))
    annotations = Annotations(
        source=MeshSignature(rig=source.name, vertices=source.surface.n_vertices, faces=len(source.surface.faces)),
        target=MeshSignature(rig=target.name, vertices=target.surface.n_vertices, faces=len(target.surface.faces)),
        markers=markers,
        curves=curves,
        landmark_spacing=spacing,
    )
    proposal = Proposal(annotations, sm, tm, discarded, extra)
    for message in proposal.messages():
        log.warning("%s -> %s: %s", source.name, target.name, message)
    return proposal


def propose_annotations(source: Rig, target: Rig, *, area_radius: float = 0.004, spacing: float = 0.002,
                        source_mapping: HandMapping | None = None,
                        target_mapping: HandMapping | None = None) -> Annotations:
    """The annotations of :func:`propose`."""
    return propose(source, target, area_radius=area_radius, spacing=spacing, source_mapping=source_mapping,
                   target_mapping=target_mapping).annotations
