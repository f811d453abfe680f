"""Procedural hand rigs: a joint tree with DOFs and limits and a watertight, manifold,
linear-blend-skinned surface, from a handful of shape parameters.

Hand frame (metres): the wrist centre is the origin, fingers extend along +Y, the back of the
hand faces +Z (palm faces -Z), and for a right hand the thumb lies on the -X side. Each finger
joint's frame has its Y axis along the bone; a finger "curls toward" a given direction
(-Z for fingers, across the palm for the thumb), and the joint frame is set up so that DOF
names mean the same on every hand:

- ``flex``: rotation about -X of the joint frame, positive curls toward the palm;
- ``abduct``: rotation about Z (sideways spread); ``twist``: rotation about Y (along the bone).

The surface is the zero level set of a smooth union of tapered capsules (organic style) or
rounded boxes (robot style) around the bones and a rounded box for the palm, extracted by
marching cubes at ``resolution`` metres; skin weights fall off with the distance of each
vertex to each bone's surface.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ..errors import InputError
from ..mesh.implicit import rounded_box, smooth_union, tapered_capsule
from ..mesh.isosurface import closed_surface_from_field, sample_grid
from .model import ROOT_TRANSLATION_LIMIT, Dof, Joint, Rig, SkinnedMesh, free_root

#: DOF name -> axis in the joint frame (see module docstring).
JOINT_AXES = {"flex": "-x", "abduct": "z", "twist": "y"}
_AXIS_VECTORS = {"-x": (-1.0, 0.0, 0.0), "z": (0.0, 0.0, 1.0), "y": (0.0, 1.0, 0.0)}


@dataclass
class JointSpec:
    """DOFs of one joint in application order, with limits in degrees."""

    dofs: tuple[str, ...]
    limits_deg: dict[str, tuple[float, float]]

    def __post_init__(self):
        for name in self.dofs:
            if name not in JOINT_AXES:
                raise InputError(f"unknown DOF {name!r}; known: {sorted(JOINT_AXES)}", element="joint spec")
            if name not in self.limits_deg:
                raise InputError(f"DOF {name!r} has no limits", element="joint spec")


@dataclass
class FingerSpec:
    """One finger: ``base`` (3,) is the first joint's position in the hand frame,
    ``direction`` (3,) the rest direction of the finger, ``curl_toward`` (3,) where it curls.
    ``lengths``: one bone length per joint (m); ``radii``: radius at each joint and at the tip
    (len(lengths) + 1, m); ``joints``: one JointSpec per joint."""

    name: str
    base: tuple[float, float, float]
    direction: tuple[float, float, float]
    lengths: tuple[float, ...]
    radii: tuple[float, ...]
    joints: tuple[JointSpec, ...]
    curl_toward: tuple[float, float, float] = (0.0, 0.0, -1.0)

    def __post_init__(self):
        if len(self.radii) != len(self.lengths) + 1 or len(self.joints) != len(self.lengths):
            raise InputError(
                "a finger needs one length and one joint per bone and one more radius than bones",
                element=f"finger {self.name!r}",
            )


@dataclass
class PalmSpec:
    """Palm block from the wrist to the knuckles: width (X), length (Y), thickness (Z), all in
    metres; the block starts ``start`` metres past the wrist centre."""

    width: float
    length: float
    thickness: float
    start: float = 0.0
    rounding: float = 0.008


@dataclass
class HandSpec:
    """Everything the generator needs. ``wrist``: None makes the root drive the palm directly
    (robot and prosthetic hands whose root joint is the wrist). ``forearm_length`` > 0 adds a
    forearm stub skinned to the root. ``style``: "organic" (tapered capsules, smooth
    blends) or "robot" (rounded boxes). ``resolution``: marching-cubes cell size (m)."""

    name: str
    palm: PalmSpec
    fingers: tuple[FingerSpec, ...]
    wrist: JointSpec | None = None
    forearm_length: float = 0.0
    forearm_radius: float = 0.02
    style: str = "organic"
    blend: float = 0.006
    resolution: float = 0.002
    root_translation_limit: float = ROOT_TRANSLATION_LIMIT
    metadata: dict = field(default_factory=dict)


def _rotation_from(direction, curl_toward) -> np.ndarray:
    """Frame (3, 3), columns X, Y, Z: Y along ``direction``, -Z toward ``curl_toward``."""
    y = np.asarray(direction, float)
    y = y / np.linalg.norm(y)
    toward = np.asarray(curl_toward, float)
    z = -(toward - (toward @ y) * y)
    if np.linalg.norm(z) < 1e-9:
        raise InputError("curl direction is parallel to the finger direction", element="finger spec")
    z /= np.linalg.norm(z)
    x = np.cross(y, z)
    return np.column_stack([x, y, z])


def _transform(rotation=None, translation=None) -> np.ndarray:
    m = np.eye(4)
    if rotation is not None:
        m[:3, :3] = rotation
    if translation is not None:
        m[:3, 3] = translation
    return m


@dataclass
class _Bone:
    joint: int
    start: np.ndarray
    end: np.ndarray
    radius_start: float
    radius_end: float
    frame: np.ndarray  # (3, 3) bone frame at rest, Y along the bone
    role: str = "finger"  # "finger" and "forearm" bones shape the surface; "palm" bones only carry skin weights


def build_hand(spec: HandSpec) -> Rig:
    """Build the rig described by ``spec``: joints, DOFs, surface and skin weights."""
    joints: list[Joint] = []
    bones: list[_Bone] = []

    root, dofs = free_root(spec.root_translation_limit)
    joints.append(root)

    palm_joint = 0
    if spec.wrist is not None:
        joints.append(Joint("wrist", 0, np.eye(4)))
        palm_joint = 1
        _add_joint_dofs(dofs, "wrist", palm_joint, spec.wrist)

    palm = spec.palm
    if spec.forearm_length > 0:
        bones.append(
            _Bone(0, np.array([0.0, -spec.forearm_length, 0.0]), np.zeros(3), spec.forearm_radius,
                  spec.forearm_radius, np.eye(3), role="forearm")
        )
    # Palm bones run from the wrist to each finger base so palm skin follows the palm joint.
    palm_origin = np.array([0.0, palm.start, 0.0])

    finger_names = set()
    for finger in spec.fingers:
        if finger.name in finger_names:
            raise InputError("finger name is used twice", element=f"finger {finger.name!r}")
        finger_names.add(finger.name)
        frame = _rotation_from(finger.direction, finger.curl_toward)
        base = np.asarray(finger.base, float)
        bones.append(_Bone(palm_joint, palm_origin, base, palm.thickness / 2, finger.radii[0], np.eye(3), role="palm"))
        parent = palm_joint
        position = base
        for k, (length, joint_spec) in enumerate(zip(finger.lengths, finger.joints)):
            name = f"{finger.name}{k + 1}"
            if k == 0:
                rest_local = _transform(frame, base)
            else:
                rest_local = _transform(None, (0.0, finger.lengths[k - 1], 0.0))
            joints.append(Joint(name, parent, rest_local))
            index = len(joints) - 1
            _add_joint_dofs(dofs, name, index, joint_spec)
            end = position + frame[:, 1] * length
            bones.append(_Bone(index, position.copy(), end, finger.radii[k], finger.radii[k + 1], frame))
            position = end
            parent = index

    vertices, faces = _surface(spec, bones)
    joint_indices, joint_weights = _skin_weights(vertices, bones)
    rig = Rig(
        name=spec.name,
        joints=joints,
        dofs=dofs,
        surface=SkinnedMesh(vertices, faces, joint_indices, joint_weights),
        metadata={"generator": "retarget_core.rig.handgen", "style": spec.style, **spec.metadata},
    )
    rig.validate(source=f"generated hand {spec.name!r}")
    return rig


def _add_joint_dofs(dofs: list[Dof], joint_name: str, joint_index: int, spec: JointSpec) -> None:
    for dof_name in spec.dofs:
        lo, hi = spec.limits_deg[dof_name]
        dofs.append(
            Dof(
                f"{joint_name}_{dof_name}",
                joint_index,
                "rotate",
                np.array(_AXIS_VECTORS[JOINT_AXES[dof_name]]),
                float(np.radians(lo)),
                float(np.radians(hi)),
                0.0,
            )
        )


def _bone_field(points: np.ndarray, bone: _Bone, style: str) -> np.ndarray:
    if style == "robot":
        length = float(np.linalg.norm(bone.end - bone.start))
        r = max(bone.radius_start, bone.radius_end)
        # Boxes overlap their neighbours by a little so the links join at the joints.
        center = (bone.start + bone.end) / 2
        return rounded_box(points, center, bone.frame, (r, length / 2 + 0.4 * r, r * 0.9), 0.45 * r)
    return tapered_capsule(points, bone.start, bone.end, bone.radius_start, bone.radius_end)


def _surface(spec: HandSpec, bones: list[_Bone]):
    palm = spec.palm
    lower = np.min([np.minimum(b.start, b.end) - max(b.radius_start, b.radius_end) for b in bones], axis=0)
    upper = np.max([np.maximum(b.start, b.end) + max(b.radius_start, b.radius_end) for b in bones], axis=0)
    palm_lo = np.array([-palm.width / 2, palm.start, -palm.thickness / 2])
    palm_hi = np.array([palm.width / 2, palm.start + palm.length, palm.thickness / 2])
    lower = np.minimum(lower, palm_lo) - spec.blend
    upper = np.maximum(upper, palm_hi) + spec.blend
    grid, shape, origin = sample_grid(lower, upper, spec.resolution)

    palm_center = (palm_lo + palm_hi) / 2
    body = rounded_box(grid, palm_center, np.eye(3), (palm_hi - palm_lo) / 2, palm.rounding)
    fingers = np.full(len(grid), np.inf)
    for bone in bones:
        if bone.role == "palm":
            continue
        d = _bone_field(grid, bone, spec.style)
        if bone.role == "forearm":
            body = smooth_union(body, d, spec.blend)
        else:
            fingers = np.minimum(fingers, d)
    field = smooth_union(body, fingers, spec.blend)
    return closed_surface_from_field(field.reshape(shape), origin, spec.resolution, what=f"surface of {spec.name!r}")


def _skin_weights(vertices: np.ndarray, bones: list[_Bone], max_influences: int = 4):
    """Weights from each vertex's distance to each bone's surface: bones within a few
    millimetres of the nearest one share the vertex (smooth creases at joints), farther ones
    (a neighbouring finger) get nothing. Weights of bones of the same joint are summed."""
    dist = np.stack(
        [tapered_capsule(vertices, b.start, b.end, b.radius_start, b.radius_end) for b in bones], axis=1
    )
    falloff = 0.0025
    raw = np.exp(-(dist - dist.min(axis=1, keepdims=True)) / falloff)
    n_joints = max(b.joint for b in bones) + 1
    per_joint = np.zeros((len(vertices), n_joints))
    for i, b in enumerate(bones):
        per_joint[:, b.joint] += raw[:, i]
    per_joint[per_joint < 1e-3 * per_joint.max(axis=1, keepdims=True)] = 0.0
    order = np.argsort(-per_joint, axis=1)[:, :max_influences]
    weights = np.take_along_axis(per_joint, order, axis=1)
    weights /= weights.sum(axis=1, keepdims=True)
    return order, weights


def with_resolution(spec: HandSpec, resolution: float) -> HandSpec:
    """The same hand at another mesh resolution (m)."""
    return replace(spec, resolution=resolution)
