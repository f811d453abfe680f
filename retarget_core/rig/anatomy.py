"""Hand anatomy of a rig for its consumers (the demo clip generator, the proposer, the source
markers): its finger chains, its palm vertices, the free root as a rigid transform, and the
paper's marker sites, all read from the hand model (:mod:`retarget_core.rig.hand_model`), so
they work on any rig the hand model reads, whatever its joint names and bone rolls.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..mesh.surface_points import SurfacePoints, closest_surface_points
from .hand_model import FINGER_NAMES, HandModel, hand_model
from .model import Rig

__all__ = ["FINGER_NAMES", "Finger", "hand_fingers", "palm_vertices", "source_markers", "closest_hand_points",
           "set_root_transform", "root_transform", "euler_xyz_from_matrix"]

# ---- the free root as a rigid transform -------------------------------------------------------
def euler_xyz_from_matrix(rotation: np.ndarray) -> np.ndarray:
    """Angles (a, b, c) with rotation = Rx(a) @ Ry(b) @ Rz(c) (the root's DOF order); at gimbal
    lock (b = +-90 degrees) c is set to 0."""
    r = np.asarray(rotation, dtype=np.float64)
    sb = np.clip(r[0, 2], -1.0, 1.0)
    b = np.arcsin(sb)
    if abs(sb) < 1.0 - 1e-9:
        a = np.arctan2(-r[1, 2], r[2, 2])
        c = np.arctan2(-r[0, 1], r[0, 0])
    else:  # Rx(a) Ry(+-pi/2): only a +- c is defined; take c = 0
        a = np.arctan2(r[2, 1], r[1, 1])
        b = np.copysign(np.pi / 2, sb)
        c = 0.0
    return np.array([a, b, c])


def set_root_transform(rig: Rig, q: np.ndarray, transform: np.ndarray) -> np.ndarray:
    """A copy of q whose six root DOFs put the root joint at ``transform`` (4, 4), world.
    Assumes the free root of :func:`retarget_core.rig.model.free_root` with an identity rest."""
    q = np.array(q, dtype=np.float64)
    names = rig.dof_names[:6]
    if names != ["root_tx", "root_ty", "root_tz", "root_rx", "root_ry", "root_rz"]:
        raise ValueError(f"rig {rig.name!r} does not start with the standard free root DOFs")
    q[0:3] = transform[:3, 3]
    q[3:6] = euler_xyz_from_matrix(transform[:3, :3])
    return q


def root_transform(rig: Rig, q: np.ndarray) -> np.ndarray:
    """(4, 4) world transform of the root joint at q."""
    return rig.kinematics().pose(q).world[0]


# ---- fingers -----------------------------------------------------------------------------------
@dataclass
class Finger:
    """One finger chain: joint indices (knuckle to distal), their flexion DOF indices (-1 where a
    joint has none), and the surface vertices each joint's link owns (largest skin weight)."""

    name: str
    joints: list[int]
    flex_dofs: list[int]
    link_vertices: list[np.ndarray]
    closing_rate: np.ndarray = field(default_factory=lambda: np.ones(0))


def hand_fingers(rig: Rig, model: HandModel | None = None) -> list[Finger]:
    """The fingers of a hand, thumb first and then across the palm (the hand model's names)."""
    model = model or hand_model(rig)
    fingers = []
    for f in model.fingers:
        n = len(f.joints)
        rate = np.linspace(0.7, 1.0, n) if f.is_thumb else np.linspace(0.8, 1.1, n)
        fingers.append(Finger(f.name, list(f.joints), list(f.flex_dofs), list(f.link_vertices), rate))
    return fingers


def palm_vertices(rig: Rig, model: HandModel | None = None) -> np.ndarray:
    """Ids of the palm's surface vertices on the palmar side (normal within 45 degrees of the
    palm's palmar normal)."""
    model = model or hand_model(rig)
    normals = rig.surface.vertex_normals()
    ids = model.palm_vertices
    return ids[normals[ids] @ model.palmar > 0.7]


def closest_hand_points(rig: Rig, model: HandModel, points: np.ndarray) -> SurfacePoints:
    """The points of the hand's own surface (not a forearm or a mount) closest to points (N, 3)."""
    faces = model.hand_faces(rig.surface.faces)
    sp = closest_surface_points(rig.surface.vertices, rig.surface.faces[faces], points)
    return SurfacePoints(faces[sp.faces], sp.barycentric)


# ---- source markers ---------------------------------------------------------------------------
#: metres: how far off the bone (toward the back or the palm) marker and curve sites are sought
#: before they are put on the surface; at least twice the finger's girth on thick fingers.
MARKER_REACH = 0.03


def marker_sites(rig: Rig, model: HandModel) -> dict[str, np.ndarray]:
    """The paper's 25 marker names and their sites (3,) near the surface, at rest:
    <Finger>Base/Middle/Tip on the back of the finger over its first, second and third
    articulations, <Finger>Fingertip at the end of the finger, BackIndex/BackRing on the back of
    the palm, WristLeft (thumb side) / WristRight at the sides of the wrist, PalmRoot on the palm
    near the wrist. Fingers the hand lacks are skipped."""
    targets: dict[str, np.ndarray] = {}
    for finger in model.fingers:
        title = finger.name.capitalize()
        reach = max(MARKER_REACH, 2.0 * finger.girth)
        for label, k in (("Base", 0), ("Middle", 1), ("Tip", 2)):
            if k < len(finger.segments):
                seg = finger.segments[k]
                targets[f"{title}{label}"] = seg.start - seg.palmar * reach
        targets[f"{title}Fingertip"] = finger.tip + finger.segments[-1].direction * 0.005
    reach = max(MARKER_REACH, model.palm_thickness)
    for label, name in (("BackIndex", "index"), ("BackRing", "ring")):
        finger = model.finger(name)
        if finger is not None:
            targets[label] = 0.5 * (model.wrist + finger.knuckle) - model.palmar * reach
    side = max(0.06, 0.75 * model.palm_width)
    targets["WristLeft"] = model.wrist + model.lateral * side + model.forward * 0.005
    targets["WristRight"] = model.wrist - model.lateral * side + model.forward * 0.005
    targets["PalmRoot"] = model.wrist + model.forward * 0.02 + model.palmar * reach
    return targets


def source_markers(rig: Rig, model: HandModel | None = None) -> tuple[list[str], np.ndarray, np.ndarray]:
    """The marker sites of :func:`marker_sites` put on the hand's surface.
    Returns (names, faces (M,), barycentric (M, 3))."""
    model = model or hand_model(rig)
    targets = marker_sites(rig, model)
    names = list(targets)
    points = closest_hand_points(rig, model, np.array([targets[n] for n in names]))
    return names, points.faces, points.barycentric
