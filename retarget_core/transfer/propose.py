"""Proposed annotations for a pair of generated hands, from their skeletons: a starting point
an artist can edit (the paper's annotations were made by hand).

For every finger of the source: an axial curve along the finger's palmar side from its first
joint over the pad to the apex of the fingertip; on the target, the finger of the same name (a missing finger's curve is
discarded), started at the same place, pointed along the finger, with lambda_a = the target
finger's length over the source's and lambda_s = the ratio of their girths. Two palm curves
(wrist to the middle knuckle; index knuckle across to the outermost knuckle) cover the palm.
Virtual markers: the paper's 25 names, a single point on the source and a small area (the
point and the vertices within ``area_radius``) on the target.
"""

from __future__ import annotations

import numpy as np

from ..errors import InputError
from ..mesh.surface_points import closest_surface_points
from ..rig.anatomy import FINGER_NAMES, hand_fingers, source_markers
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

PALMAR_OFFSET = 0.03  # metres: how far off the bone the palmar-side target points are placed


def _finger_geometry(rig: Rig) -> dict:
    """Per finger: rest positions of its joints and tip, the palmar direction, length, girth."""
    world = rig.kinematics().bind_world
    out = {}
    for finger in hand_fingers(rig):
        frames = [world[j] for j in finger.joints]
        joints = np.array([f[:3, 3] for f in frames])
        tip_vertices = rig.surface.vertices[finger.link_vertices[-1]]
        along = frames[-1][:3, 1]
        tip = tip_vertices[np.argmax(tip_vertices @ along)]
        owned = np.concatenate(finger.link_vertices)
        axis_start, axis_end = joints[0], tip
        ab = axis_end - axis_start
        t = np.clip((rig.surface.vertices[owned] - axis_start) @ ab / (ab @ ab), 0, 1)
        girth = np.median(np.linalg.norm(rig.surface.vertices[owned] - (axis_start + t[:, None] * ab), axis=1))
        out[finger.name] = {
            "joints": joints,
            "tip": tip,
            "palmar": -frames[0][:3, 2],
            "length": float(np.linalg.norm(np.diff(np.vstack([joints, tip]), axis=0), axis=1).sum()),
            "girth": float(girth),
        }
    return out


def _point(rig: Rig, xyz) -> PointRef:
    sp = closest_surface_points(rig.surface.vertices, rig.surface.faces, np.asarray(xyz, float)[None])
    return PointRef(face=int(sp.faces[0]), barycentric=tuple(float(x) for x in sp.barycentric[0]))


def _palm_frame(rig: Rig):
    world = rig.kinematics().bind_world
    palm = world[rig.joint_index("wrist")] if "wrist" in rig.joint_names else world[0]
    return palm[:3, 3], palm[:3, 1], -palm[:3, 2]


def propose_annotations(source: Rig, target: Rig, *, area_radius: float = 0.004, spacing: float = 0.002) -> Annotations:
    """Proposed markers and axial curves from ``source`` onto ``target`` (generated hands whose
    finger joints are named like "index1")."""
    src, tgt = _finger_geometry(source), _finger_geometry(target)
    for rig, fingers in ((source, src), (target, tgt)):
        if not fingers:
            raise InputError("cannot propose annotations: no finger joints named like 'index1'", source=rig.name)
    curves = []
    off = PALMAR_OFFSET
    for name in FINGER_NAMES:
        if name not in src:
            continue
        s = src[name]
        s_start = s["joints"][0] + s["palmar"] * off
        s_end = s["tip"]  # the apex of the fingertip: charts then cover the pad, the tip and the nail
        if name in tgt:
            t = tgt[name]
            curve_target = CurveTarget(
                start=_point(target, t["joints"][0] + t["palmar"] * off),
                direction=_point(target, t["tip"]),
                lambda_a=round(t["length"] / s["length"], 3),
                lambda_s=LambdaS.constant(round(t["girth"] / s["girth"], 3)),
            )
        else:
            curve_target = None
        curves.append(AxialCurveAnnotation(name=name, source_start=_point(source, s_start),
                                           source_end=_point(source, s_end), source_points=None, target=curve_target))

    # Palm: wrist to the middle knuckle, and across the knuckles.
    def palm_points(rig, fingers):
        origin, forward, palmar = _palm_frame(rig)
        middle = fingers.get("middle") or fingers.get("index")
        knuckles = [fingers[f]["joints"][0] for f in ("index", "middle", "ring", "pinky") if f in fingers]
        root = origin + forward * 0.015 + palmar * off
        return root, middle["joints"][0] + palmar * off, knuckles[0] + palmar * off, knuckles[-1] + palmar * off

    s_root, s_mid, s_first, s_last = palm_points(source, src)
    t_root, t_mid, t_first, t_last = palm_points(target, tgt)
    ratio_long = np.linalg.norm(t_mid - t_root) / np.linalg.norm(s_mid - s_root)
    ratio_cross = np.linalg.norm(t_last - t_first) / max(np.linalg.norm(s_last - s_first), 1e-9)
    curves.append(AxialCurveAnnotation(
        name="palm", source_start=_point(source, s_root), source_end=_point(source, s_mid), source_points=None,
        target=CurveTarget(start=_point(target, t_root), direction=_point(target, t_mid),
                           lambda_a=round(float(ratio_long), 3), lambda_s=LambdaS.constant(round(float(ratio_cross), 3)))))
    curves.append(AxialCurveAnnotation(
        name="knuckles", source_start=_point(source, s_first), source_end=_point(source, s_last), source_points=None,
        target=CurveTarget(start=_point(target, t_first), direction=_point(target, t_last),
                           lambda_a=round(float(ratio_cross), 3), lambda_s=LambdaS.constant(round(float(ratio_long), 3)))))

    # Markers by name: a point on the source, an area on the target.
    s_names, s_faces, s_bary = source_markers(source)
    t_names, t_faces, t_bary = source_markers(target)
    t_index = {n: i for i, n in enumerate(t_names)}
    markers = []
    for i, name in enumerate(s_names):
        if name not in t_index:
            continue
        j = t_index[name]
        centre = t_bary[j] @ target.surface.vertices[target.surface.faces[t_faces[j]]]
        near = np.nonzero(np.linalg.norm(target.surface.vertices - centre, axis=1) <= area_radius)[0]
        area = [PointRef(face=int(t_faces[j]), barycentric=tuple(float(x) for x in t_bary[j]))]
        area += [PointRef(vertex=int(v)) for v in near]
        markers.append(MarkerPair(name=name, source=[PointRef(face=int(s_faces[i]), barycentric=tuple(float(x) for x in s_bary[i]))],
                                  target=area))
    return Annotations(
        source=MeshSignature(rig=source.name, vertices=source.surface.n_vertices, faces=len(source.surface.faces)),
        target=MeshSignature(rig=target.name, vertices=target.surface.n_vertices, faces=len(target.surface.faces)),
        markers=markers,
        curves=curves,
        landmark_spacing=spacing,
    )
