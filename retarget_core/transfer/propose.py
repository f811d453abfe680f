"""Proposed annotations for a pair of hands, from their hand models (:mod:`retarget_core.rig.hand_model`):
a starting point an artist can edit (the paper's annotations were made by hand).

For every finger of the source: an axial curve along the finger's palmar midline from its
knuckle over the pad to the apex of the fingertip; on the target, the finger of the same role
(a finger the target lacks is discarded; fingers only the target has are reported), started at
the same place, pointed along the finger, with lambda_a = the target finger's length over the
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
from ..rig.anatomy import closest_hand_points, marker_sites
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


def _point(rig: Rig, model: HandModel, xyz) -> PointRef:
    sp = closest_hand_points(rig, model, np.asarray(xyz, float)[None])
    return PointRef(face=int(sp.faces[0]), barycentric=tuple(float(x) for x in sp.barycentric[0]))


def _palm_sites(model: HandModel):
    """(root, central knuckle, first knuckle, outermost knuckle) sites on the palmar side."""
    off = max(PALMAR_OFFSET, model.palm_thickness)
    fingers = [f for f in model.fingers if not f.is_thumb]
    if not fingers:
        raise InputError("cannot propose palm curves: the hand has no finger besides the thumb",
                         source=model.rig_name)
    central = model.finger("middle") or fingers[len(fingers) // 2]
    root = model.wrist + model.forward * 0.015 + model.palmar * off
    return (root, central.knuckle + model.palmar * off, fingers[0].knuckle + model.palmar * off,
            fingers[-1].knuckle + model.palmar * off)


def propose(source: Rig, target: Rig, *, area_radius: float = 0.004, spacing: float = 0.002,
            source_mapping: HandMapping | None = None, target_mapping: HandMapping | None = None) -> Proposal:
    """Proposed markers and axial curves from ``source`` onto ``target``, any two hands the hand
    model reads (``*_mapping`` settles what it cannot)."""
    sm, tm = hand_model(source, source_mapping), hand_model(target, target_mapping)
    curves, discarded = [], []
    for s in sm.fingers:
        s_start = s.knuckle + s.segments[0].palmar * max(PALMAR_OFFSET, 2 * s.girth)
        t = tm.finger(s.name)
        if t is not None:
            curve_target = CurveTarget(
                start=_point(target, tm, t.knuckle + t.segments[0].palmar * max(PALMAR_OFFSET, 2 * t.girth)),
                direction=_point(target, tm, t.tip),
                lambda_a=round(t.length / s.length, 3),
                lambda_s=LambdaS.constant(round(t.girth / s.girth, 3)),
            )
        else:
            curve_target = None
            discarded.append(s.name)
        # the end is the apex of the fingertip: charts then cover the pad, the tip and the nail
        curves.append(AxialCurveAnnotation(name=s.name, source_start=_point(source, sm, s_start),
                                           source_end=_point(source, sm, s.tip), source_points=None,
                                           target=curve_target))
    extra = [f.name for f in tm.fingers if sm.finger(f.name) is None]

    s_root, s_mid, s_first, s_last = _palm_sites(sm)
    t_root, t_mid, t_first, t_last = _palm_sites(tm)
    ratio_long = np.linalg.norm(t_mid - t_root) / np.linalg.norm(s_mid - s_root)
    ratio_cross = np.linalg.norm(t_last - t_first) / max(np.linalg.norm(s_last - s_first), 1e-9)
    curves.append(AxialCurveAnnotation(
        name="palm", source_start=_point(source, sm, s_root), source_end=_point(source, sm, s_mid), source_points=None,
        target=CurveTarget(start=_point(target, tm, t_root), direction=_point(target, tm, t_mid),
                           lambda_a=round(float(ratio_long), 3), lambda_s=LambdaS.constant(round(float(ratio_cross), 3)))))
    curves.append(AxialCurveAnnotation(
        name="knuckles", source_start=_point(source, sm, s_first), source_end=_point(source, sm, s_last),
        source_points=None,
        target=CurveTarget(start=_point(target, tm, t_first), direction=_point(target, tm, t_last),
                           lambda_a=round(float(ratio_cross), 3), lambda_s=LambdaS.constant(round(float(ratio_long), 3)))))

    # Markers by name: a point on the source, an area on the target.
    s_sites, t_sites = marker_sites(source, sm), marker_sites(target, tm)
    names = [n for n in s_sites if n in t_sites]
    s_points = closest_hand_points(source, sm, np.array([s_sites[n] for n in names]))
    t_points = closest_hand_points(target, tm, np.array([t_sites[n] for n in names]))
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
