"""Hand anatomy of a rig: its finger chains, its palm vertices, the free root as a rigid
transform, and the paper's marker sites placed by the hand's geometry.

Works on any generated hand whose finger joints are named ``<finger><k>`` with a
``<finger><k>_flex`` DOF (see :mod:`retarget_core.rig.handgen`) and a palm joint ``wrist``, and
on any rig whose first six DOFs are the standard free root (:func:`retarget_core.rig.model.free_root`).
Moved here unchanged from the demo clip generator (``clip/grasp.py``, ``clip/demo.py``) so the
pipeline, the transfer and the demo share them; a later issue replaces them with a hand model.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..mesh.surface_points import closest_surface_points
from .model import Rig

FINGER_NAMES = ("thumb", "index", "middle", "ring", "pinky")


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
    """One finger chain: joint indices, their flex DOF indices, and the surface vertices each
    joint's link owns (vertex ids whose largest skin weight is that joint)."""

    name: str
    joints: list[int]
    flex_dofs: list[int]
    link_vertices: list[np.ndarray]
    closing_rate: np.ndarray = field(default_factory=lambda: np.ones(0))


def hand_fingers(rig: Rig) -> list[Finger]:
    """The fingers of a generated hand, in FINGER_NAMES order."""
    dense = rig.surface.dense_weights(rig.n_joints)
    owner = dense.argmax(axis=1)
    fingers = []
    for name in FINGER_NAMES:
        joints, flex = [], []
        k = 1
        while True:
            jname = f"{name}{k}"
            if jname not in rig.joint_names:
                break
            j = rig.joint_index(jname)
            joints.append(j)
            flex.append(rig.dof_index(f"{jname}_flex") if f"{jname}_flex" in rig.dof_names else -1)
            k += 1
        if joints:
            rate = np.linspace(0.8, 1.1, len(joints)) if name != "thumb" else np.linspace(0.7, 1.0, len(joints))
            fingers.append(Finger(name, joints, flex, [np.nonzero(owner == j)[0] for j in joints], rate))
    return fingers


def palm_vertices(rig: Rig) -> np.ndarray:
    """Ids of surface vertices owned by the palm joint ("wrist", else the root) on the palm side
    (normal within 45 degrees of -Z in the hand frame)."""
    dense = rig.surface.dense_weights(rig.n_joints)
    palm_joint = rig.joint_index("wrist") if "wrist" in rig.joint_names else 0
    normals = rig.surface.vertex_normals()
    return np.nonzero((dense.argmax(axis=1) == palm_joint) & (normals[:, 2] < -0.7))[0]


# ---- source markers ---------------------------------------------------------------------------
def source_markers(rig: Rig) -> tuple[list[str], np.ndarray, np.ndarray]:
    """The paper's 25 marker names placed on a generated hand by its geometry (rest pose):
    <Finger>Base/Middle/Tip on the back of the finger over its first, second and third joints,
    <Finger>Fingertip at the end of the finger, BackIndex/BackRing on the back of the palm,
    WristLeft (thumb side) / WristRight at the sides of the wrist, PalmRoot on the palm near
    the wrist. Returns (names, faces (M,), barycentric (M, 3)); fingers the hand lacks are skipped."""
    kin = rig.kinematics()
    world = kin.bind_world
    targets: dict[str, np.ndarray] = {}
    reach = 0.03
    for finger in hand_fingers(rig):
        title = finger.name.capitalize()
        frames = [world[j] for j in finger.joints]
        back = frames[0][:3, 2]
        for label, k in (("Base", 0), ("Middle", 1), ("Tip", 2)):
            if k < len(frames):
                targets[f"{title}{label}"] = frames[k][:3, 3] + back * reach
        tip_vertices = rig.surface.vertices[finger.link_vertices[-1]]
        along = frames[-1][:3, 1]
        targets[f"{title}Fingertip"] = tip_vertices[np.argmax(tip_vertices @ along)] + along * 0.005
    wrist = world[rig.joint_index("wrist")] if "wrist" in rig.joint_names else world[0]
    origin, x_axis, y_axis, z_axis = wrist[:3, 3], wrist[:3, 0], wrist[:3, 1], wrist[:3, 2]
    for label, finger in (("BackIndex", "index1"), ("BackRing", "ring1")):
        if finger in rig.joint_names:
            mid = 0.5 * (origin + world[rig.joint_index(finger)][:3, 3])
            targets[label] = mid + z_axis * reach
    targets["WristLeft"] = origin - x_axis * 0.06 + y_axis * 0.005
    targets["WristRight"] = origin + x_axis * 0.06 + y_axis * 0.005
    targets["PalmRoot"] = origin + y_axis * 0.02 - z_axis * reach
    names = list(targets)
    points = closest_surface_points(rig.surface.vertices, rig.surface.faces, np.array([targets[n] for n in names]))
    return names, points.faces, points.barycentric
