"""Mirrored hands: a right rig as a left one (and back), and annotations carried to the mirror.

The mirror is the reflection across a plane through the rig's origin, normal to one of its axes
(``M = diag(-1, 1, 1)`` for "x"). Everything keeps its index: vertex i of the mirror is M times
vertex i, triangle (a, b, c) becomes (a, c, b) so the surface still faces outward, joints keep
their names, parents and skin weights. A joint's rest transform L becomes M L M, and a rotation
DOF's axis a becomes -M a (M R(a, q) M = R(-M a, q)), a translation's M a: the same DOF values
pose the mirror image of the same pose, with the same limits. The free root keeps its world
axes (root_tx .. root_rz: the solver finds the root of every frame). A face point (face,
barycentric (u, v, w)) is (face, (u, w, v)) on the mirror, a vertex the same vertex, and a
log-map angle theta is -theta (the charts turn the other way), so an angular lambda_s is
mirrored too."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from ..errors import InputError
from .hand_model import HAND_MAPPING_METADATA
from .model import Dof, Joint, Rig, SkinnedMesh

AXES = {"x": 0, "y": 1, "z": 2}


def _reflection(axis: str) -> np.ndarray:
    if axis not in AXES:
        raise InputError(f"mirror axis must be x, y or z, got {axis!r}", element="axis")
    m = np.eye(3)
    m[AXES[axis], AXES[axis]] = -1.0
    return m


def _mirror_mesh(mesh: SkinnedMesh | None, m: np.ndarray) -> SkinnedMesh | None:
    if mesh is None:
        return None
    return SkinnedMesh(vertices=mesh.vertices @ m.T, faces=mesh.faces[:, [0, 2, 1]],
                       joint_indices=mesh.joint_indices.copy(), joint_weights=mesh.joint_weights.copy())


def _other_side(text: str) -> str:
    swaps = (("right", "left"), ("Right", "Left"), ("RIGHT", "LEFT"))
    for a, b in swaps:
        if a in text:
            return text.replace(a, b)
        if b in text:
            return text.replace(b, a)
    return f"{text}_mirrored"


def mirror_rig(rig: Rig, axis: str = "x", *, name: str | None = None) -> Rig:
    """The mirror image of ``rig`` across the plane normal to ``axis`` through its origin (see
    the module docstring); ``name``: the mirror's name (default: right <-> left swapped in the
    rig's name, else ``<name>_mirrored``). The hand's own mapping, if it has one, changes side."""
    m = _reflection(axis)
    m4 = np.eye(4)
    m4[:3, :3] = m
    joints = [Joint(j.name, j.parent, m4 @ np.asarray(j.rest_local, float) @ m4) for j in rig.joints]
    free_root = rig.dof_names[:6] == ["root_tx", "root_ty", "root_tz", "root_rx", "root_ry", "root_rz"]
    dofs = []
    for k, d in enumerate(rig.dofs):
        if free_root and k < 6:
            axis_ = np.array(d.axis, float)
        else:
            axis_ = (m @ d.axis) if d.kind == "translate" else -(m @ d.axis)
        dofs.append(Dof(d.name, d.joint, d.kind, axis_, d.lower, d.upper, d.rest))
    metadata = dict(rig.metadata)
    mapping = metadata.get(HAND_MAPPING_METADATA)
    if mapping and mapping.get("handedness") in ("right", "left"):
        metadata[HAND_MAPPING_METADATA] = {**mapping,
                                           "handedness": "left" if mapping["handedness"] == "right" else "right"}
    if "mano" in metadata:
        metadata["mano"] = {**metadata["mano"], "handedness": "left" if metadata["mano"].get("handedness") == "right"
                            else "right", "mirrored": axis}
    metadata["mirrored_from"] = {"rig": rig.name, "axis": axis}
    mirrored = Rig(name=name or _other_side(rig.name), joints=joints, dofs=dofs,
                   surface=_mirror_mesh(rig.surface, m), visual=_mirror_mesh(rig.visual, m), metadata=metadata)
    mirrored.validate(source=f"{rig.name} mirrored across {axis}", require_closed=False)
    return mirrored


def mirror_annotations(annotations, *, axis: str = "x", source_rig: str | None = None,
                       target_rig: str | None = None):
    """``annotations`` made for a (source, target) pair, for the mirrored pair (both hands
    mirrored across ``axis``: a left clip's MANO hand onto the left mirror of a right target):
    every point on the mirrored triangles, positions reflected, angular lambda_s mirrored
    (theta -> -theta). ``source_rig`` / ``target_rig``: the mirrored rigs' names for the
    signatures (default: right <-> left swapped). Only both sides together: a right hand's
    charts onto a left hand would turn the other way (a contact on a finger's thumb side would
    land on its other side)."""
    from ..transfer.annotations import Annotations, AxialCurveAnnotation, CurveTarget, LambdaS, MarkerPair, PointRef

    m = _reflection(axis)

    def point(p: PointRef) -> PointRef:
        position = None if p.position is None else tuple(float(x) for x in m @ np.asarray(p.position))
        if p.vertex is not None:
            return PointRef(vertex=p.vertex, position=position)
        a, b, c = p.barycentric
        return PointRef(face=p.face, barycentric=(a, c, b), position=position)

    def lambda_s(ls: LambdaS) -> LambdaS:
        if ls.uniform is not None:
            return ls
        knots = sorted(((360.0 - a) % 360.0, v) for a, v in zip(ls.angles_deg, ls.knot_values))
        return LambdaS.piecewise([a for a, _ in knots], [v for _, v in knots])

    markers = [MarkerPair(mk.name, tuple(point(p) for p in mk.source), tuple(point(p) for p in mk.target))
               for mk in annotations.markers]
    curves = []
    for c in annotations.curves:
        tgt = None if c.target is None else CurveTarget(
            point(c.target.start), point(c.target.direction), c.target.lambda_a, lambda_s(c.target.lambda_s),
            None if c.target.through is None else tuple(point(p) for p in c.target.through))
        curves.append(AxialCurveAnnotation(
            name=c.name,
            source_start=None if c.source_start is None else point(c.source_start),
            source_end=None if c.source_end is None else point(c.source_end),
            source_points=None if c.source_points is None else tuple(point(p) for p in c.source_points),
            target=tgt))

    def signature(sig, name):
        return replace(sig, rig=name or _other_side(sig.rig), surface_sha256=None)

    return Annotations(source=signature(annotations.source, source_rig),
                       target=signature(annotations.target, target_rig),
                       markers=markers, curves=curves, landmark_spacing=annotations.landmark_spacing)
