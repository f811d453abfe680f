"""The MANO source rig: a user's own MANO model (MANO_RIGHT.pkl / MANO_LEFT.pkl) and a subject's
hand template (GRAB's ``vtemp``) as a rig every pipeline stage takes, so a GRAB clip has its
source hand. Nothing of MANO is shipped: the rig is built from the user's files at import.

- Joints: MANO's 16 (``wrist``, then ``index1..3``, ``middle1..3``, ``pinky1..3``, ``ring1..3``,
  ``thumb1..3``, MANO's order), at the joints MANO's ``J_regressor`` gives the template.
- DOFs: the free root on the wrist (``root_tx .. root_rz``, in place of MANO's
  ``global_orient`` and ``transl``), then three rotations for each of the 15 finger joints about
  that joint's anatomical axes (``<joint>_flex``, ``_abduct``, ``_twist``): 6 + 45 = 51. The
  joint frames keep MANO's (world-aligned at rest), so a joint's rotation relative to its parent
  is MANO's own axis-angle rotation of that joint (:func:`mano_params`, :func:`dofs_from_mano`).
- Bind pose: the template at MANO's zero pose, moved so the wrist joint is at the origin (the
  root then turns about the wrist); ``metadata["mano"]["wrist"]`` keeps where it was.
- Skin: MANO's linear blend weights. MANO's pose correctives (``posedirs``) are not part of the
  rig: retargeting solves blend-skinned hands.
- Surface: the template's 778 vertices and the model's triangles, then the wrist opening closed
  by a fan (one vertex and the cap triangles appended after the model's own), so geodesics and
  inside/outside tests see a closed hand. The caps never receive contacts
  (:func:`~retarget_core.rig.hand_cut.cap_faces`) and a clip's hand mesh matches the rig on the
  uncapped prefix (:func:`~retarget_core.rig.hand_cut.surface_matches_hand`).
- Markers: the paper's 25 MANO marker vertices (:data:`~retarget_core.clip.markers.MANO_MARKERS`)
  in ``metadata["markers"]``; proposals from this rig use them as the source markers.
"""

from __future__ import annotations

import hashlib

import numpy as np

from ..clip.grab import rodrigues
from ..clip.markers import MANO_MARKERS, MANO_N_VERTICES
from ..errors import InputError
from .anatomy import MARKERS_METADATA, euler_xyz_from_matrix
from .hand_cut import SURFACE_SOURCE, cap_openings
from .hand_model import HAND_MAPPING_METADATA, HandMapping, hand_model
from .model import Dof, Joint, Rig, SkinnedMesh, free_root

#: MANO's fingers in its joint order and the index of each one's first joint.
MANO_FINGERS = (("index", 1), ("middle", 4), ("pinky", 7), ("ring", 10), ("thumb", 13))
MANO_JOINT_NAMES = ["wrist"] + [f"{name}{k}" for name, _ in MANO_FINGERS for k in (1, 2, 3)]
#: rig metadata key of the MANO facts (handedness, triangle count, wrist, model digest)
MANO_METADATA = "mano"

#: DOF limits (radians) of the finger joints by finger and joint (0 = knuckle / the thumb's CMC),
#: (flex, abduct, twist) as (lower, upper): the human ranges of the project's generated hands, the
#: sideways and twist ranges of the distal joints widened to +-0.3 for MANO fits of captured hands
#: (they twist those joints by up to ~15 degrees). A MANO rig as a target stays within them.
MANO_LIMITS = {
    ("finger", 0): ((-0.44, 1.66), (-0.44, 0.44), (-0.35, 0.35)),
    ("finger", 1): ((-0.17, 1.92), (-0.3, 0.3), (-0.3, 0.3)),
    ("finger", 2): ((-0.26, 1.57), (-0.3, 0.3), (-0.3, 0.3)),
    ("thumb", 0): ((-0.52, 1.13), (-0.7, 0.7), (-0.79, 0.79)),
    ("thumb", 1): ((-0.35, 1.31), (-0.35, 0.35), (-0.35, 0.35)),
    ("thumb", 2): ((-0.35, 1.57), (-0.3, 0.3), (-0.3, 0.3)),
}
_ROLES = ("flex", "abduct", "twist")


def mano_hand_mapping(handedness: str = "right") -> HandMapping:
    """What MANO's joint tree says for certain: the palm joint, each finger's joints, the side."""
    return HandMapping(palm="wrist", handedness=handedness,
                       fingers={name: [f"{name}{k}" for k in (1, 2, 3)] for name, _ in MANO_FINGERS})


def _limits(finger: str, k: int):
    return MANO_LIMITS[("thumb" if finger == "thumb" else "finger", k)]


def _mano_joints(joints: np.ndarray, parents: np.ndarray) -> list[Joint]:
    out = [Joint("wrist", -1, np.eye(4))]
    for j in range(1, len(parents)):
        local = np.eye(4)
        local[:3, 3] = joints[j] - joints[parents[j]]
        out.append(Joint(MANO_JOINT_NAMES[j], int(parents[j]), local))
    return out


def _finger_dofs(frames: dict[int, np.ndarray]) -> list[Dof]:
    """The root's six DOFs, then (flex, abduct, twist) of every finger joint about the columns of
    its frame (3, 3)."""
    _, dofs = free_root()
    for name, first in MANO_FINGERS:
        for k in range(3):
            j = first + k
            for role, axis, (lo, hi) in zip(_ROLES, frames[j].T, _limits(name, k)):
                dofs.append(Dof(f"{MANO_JOINT_NAMES[j]}_{role}", j, "rotate", np.array(axis, float), lo, hi, 0.0))
    return dofs


def mano_rig(model, v_template=None, *, name: str | None = None, rest: str = "mean") -> Rig:
    """The source rig of a MANO ``model`` (:class:`~retarget_core.clip.grab.ManoModel`) with the
    subject's hand template ``v_template`` (778, 3) m (None: the model's mean template).
    ``rest``: the rest (bind) pose of the fingers, "mean" (MANO's ``hands_mean``, the average of
    its captured hands: a relaxed, slightly curled hand, so that the prior E_J pulls a MANO
    target toward a natural pose) or "flat" (the template as it is). See the module docstring."""
    if rest not in ("mean", "flat"):
        raise InputError(f"rest must be 'mean' or 'flat', got {rest!r}", element="rest")
    handedness = getattr(model, "handedness", "right")
    template = model.v_template if v_template is None else np.asarray(v_template, dtype=np.float64)
    if template.shape != (MANO_N_VERTICES, 3) or not np.all(np.isfinite(template)):
        raise InputError(f"a MANO hand template is ({MANO_N_VERTICES}, 3) finite numbers, got {template.shape}",
                         element="vtemp")
    joints = model.J_regressor @ template  # (16, 3)
    wrist = joints[0].copy()
    vertices, joints = template - wrist, joints - wrist
    weights = np.asarray(model.weights, dtype=np.float64)
    n_faces = len(model.faces)
    try:
        vertices, faces, weights = cap_openings(vertices, np.asarray(model.faces, dtype=np.int64), weights,
                                                what="the MANO model's surface")
    except InputError as err:
        raise InputError(f"the MANO model's triangles do not form a hand surface with a wrist opening ({err}): is "
                         "this MANO_RIGHT.pkl / MANO_LEFT.pkl as released?", source=getattr(model, "source", ""),
                         element="f") from None
    k = max(1, int((weights > 1e-8).sum(axis=1).max()))
    order = np.argsort(-weights, axis=1, kind="stable")[:, :k]
    top = np.take_along_axis(weights, order, axis=1)
    top = np.where(top > 1e-8, top, 0.0)
    top /= top.sum(axis=1, keepdims=True)
    surface = SkinnedMesh(vertices=vertices, faces=faces, joint_indices=order, joint_weights=top)
    mano_joints = _mano_joints(joints, model.parents)
    mapping = mano_hand_mapping(handedness)
    name = name or f"mano_{handedness}"

    # The anatomical axes come from the hand model of the rig with plain x, y, z rotations.
    plain = _finger_dofs({j: np.eye(3) for j in range(1, 16)})
    probe = Rig(name=name, joints=mano_joints, dofs=plain, surface=surface)
    hm = hand_model(probe, mapping)
    frames = {}
    for finger in hm.fingers:
        for segment in finger.segments:
            flex = segment.flexion_axis / np.linalg.norm(segment.flexion_axis)
            abduct = segment.abduction_axis - (segment.abduction_axis @ flex) * flex
            abduct /= np.linalg.norm(abduct)
            for j in segment.joints:
                frames[j] = np.column_stack([flex, abduct, np.cross(flex, abduct)])
    missing = [MANO_JOINT_NAMES[j] for j in range(1, 16) if j not in frames]
    if missing:
        raise InputError(f"the MANO model's joints {', '.join(missing)} are not on a finger the hand model "
                         "reads (is this a MANO hand model?)", source=getattr(model, "source", ""), element="J_regressor")
    n_cap_vertices = len(vertices) - MANO_N_VERTICES
    digest = hashlib.sha256()
    for array in (template, model.J_regressor, model.weights, model.faces):
        digest.update(np.ascontiguousarray(array, dtype=np.float64).tobytes())
    metadata = {
        MANO_METADATA: {"handedness": handedness, "model_faces": n_faces, "wrist": wrist.tolist(),
                        "template": "model" if v_template is None else "subject",
                        "content_sha256": digest.hexdigest()},
        MARKERS_METADATA: dict(MANO_MARKERS),
        HAND_MAPPING_METADATA: mapping.to_dict(),
        SURFACE_SOURCE: {"vertices": list(range(MANO_N_VERTICES)) + [-1] * n_cap_vertices,
                         "faces": list(range(n_faces)) + [-1] * (len(faces) - n_faces),
                         "file_vertices": MANO_N_VERTICES, "file_faces": n_faces},
    }
    dofs = _finger_dofs(frames)
    if rest == "mean":
        flat = Rig(name=name, joints=mano_joints, dofs=dofs, surface=surface)
        local = rodrigues(np.asarray(model.hands_mean, dtype=np.float64).reshape(15, 3))
        angles = _euler_xyz(np.einsum("jba,jbc,jcd->jad", np.array([frames[j] for j in range(1, 16)]), local,
                                      np.array([frames[j] for j in range(1, 16)])))
        q_rest = np.zeros(len(dofs))
        for j in range(1, 16):
            for r, role in enumerate(_ROLES):
                k = flat.dof_index(f"{MANO_JOINT_NAMES[j]}_{role}")
                span = dofs[k].upper - dofs[k].lower
                q_rest[k] = np.clip(angles[j - 1, r], dofs[k].lower + 0.05 * span, dofs[k].upper - 0.05 * span)
        surface = SkinnedMesh(vertices=flat.kinematics().skin(q_rest), faces=surface.faces,
                              joint_indices=surface.joint_indices, joint_weights=surface.joint_weights)
        for d, value in zip(dofs, q_rest):
            d.rest = float(value)
    metadata[MANO_METADATA]["rest"] = rest
    rig = Rig(name=name, joints=mano_joints, dofs=dofs, surface=surface, metadata=metadata)
    rig.validate(source=f"MANO rig {name}")
    return rig


def _euler_xyz(rotations: np.ndarray) -> np.ndarray:
    """(..., 3, 3) -> (..., 3) angles (a, b, c) with rotation = Rx(a) Ry(b) Rz(c)."""
    r = np.asarray(rotations, dtype=np.float64)
    flat = r.reshape(-1, 3, 3)
    return np.array([euler_xyz_from_matrix(m) for m in flat]).reshape(r.shape[:-2] + (3,))


def _joint_frames(rig: Rig) -> np.ndarray:
    """(16, 3, 3): the three rotation axes of each MANO joint as columns (identity for the wrist)."""
    frames = np.tile(np.eye(3), (16, 1, 1))
    for j in range(1, 16):
        frames[j] = np.column_stack([rig.dofs[rig.dof_index(f"{MANO_JOINT_NAMES[j]}_{role}")].axis for role in _ROLES])
    return frames


def dofs_from_mano(rig: Rig, global_orient, finger_pose, transl) -> np.ndarray:
    """(T, 51) DOF values of :func:`mano_rig` for MANO parameters: ``global_orient`` (T, 3) and
    ``finger_pose`` (T, 45) axis-angles (radians, MANO's joint order), ``transl`` (T, 3) m. The
    rig's skin then matches MANO's blend skinning without pose correctives."""
    go = np.asarray(global_orient, dtype=np.float64).reshape(-1, 3)
    n = len(go)
    fp = np.asarray(finger_pose, dtype=np.float64).reshape(n, 15, 3)
    tr = np.asarray(transl, dtype=np.float64).reshape(n, 3)
    wrist = np.asarray(rig.metadata[MANO_METADATA]["wrist"])
    frames = _joint_frames(rig)
    q = np.zeros((n, rig.n_dofs))
    q[:, 0:3] = tr + wrist
    q[:, 3:6] = _euler_xyz(rodrigues(go))
    local = rodrigues(fp)  # (T, 15, 3, 3)
    angles = _euler_xyz(np.einsum("jba,tjbc,jcd->tjad", frames[1:], local, frames[1:]))  # F^T R F
    for j in range(1, 16):
        for r, role in enumerate(_ROLES):
            q[:, rig.dof_index(f"{MANO_JOINT_NAMES[j]}_{role}")] = angles[:, j - 1, r]
    return q


def joint_rotations(rig: Rig, q) -> np.ndarray:
    """(T, 15, 3, 3): each MANO finger joint's rotation relative to its parent at DOF values q
    (T, D) (MANO's own per-joint rotation)."""
    q = np.atleast_2d(np.asarray(q, dtype=np.float64))
    kin = rig.kinematics()
    out = np.empty((len(q), 15, 3, 3))
    ids = [rig.joint_index(n) for n in MANO_JOINT_NAMES]
    for t, qt in enumerate(q):
        world = kin.pose(qt).world
        for j in range(1, 16):
            me, parent = ids[j], rig.joints[ids[j]].parent
            out[t, j - 1] = world[parent][:3, :3].T @ world[me][:3, :3]
    return out


def mano_params(rig: Rig, q) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Inverse of :func:`dofs_from_mano`: (global_orient (T, 3), finger_pose (T, 45), transl (T, 3))."""
    from scipy.spatial.transform import Rotation

    q = np.atleast_2d(np.asarray(q, dtype=np.float64))
    kin = rig.kinematics()
    wrist = np.asarray(rig.metadata[MANO_METADATA]["wrist"])
    go = np.empty((len(q), 3))
    tr = np.empty((len(q), 3))
    for t, qt in enumerate(q):
        w0 = kin.pose(qt).world[rig.joint_index("wrist")]
        go[t] = Rotation.from_matrix(w0[:3, :3]).as_rotvec()
        tr[t] = w0[:3, 3] - wrist
    finger = Rotation.from_matrix(joint_rotations(rig, q).reshape(-1, 3, 3)).as_rotvec().reshape(len(q), 45)
    return go, finger, tr
