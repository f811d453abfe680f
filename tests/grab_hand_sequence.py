"""GRAB-format sequences with known poses and real contacts, on the hand-shaped MANO model of
:mod:`mano_hand`: the fixture of the GRAB end-to-end tests.

A demo grasp (:func:`retarget_core.clip.demo.build_demo_timeline`, fingers closed until they
touch the object) is planned on the MANO rig of the subject's template, its DOF trajectory turned
into MANO parameters (:func:`retarget_core.rig.mano.mano_params`), the hand posed by MANO's own
forward function (pose correctives included) and the object's vertices within 2 mm of it labelled
with GRAB's codes of the nearest hand joint. Everything is written in GRAB's folder layout:
``<root>/grab/<subject>/<sequence>.npz`` with the meshes under ``<root>/tools/``."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import igl
import numpy as np
from scipy.spatial.transform import Rotation

from grab_fixtures import write_grab_npz, write_mano_plain, write_mesh
from mano_hand import make_hand_mano_raw
from retarget_core.clip.demo import CONTACT_THRESHOLD, build_demo_timeline, contact_code
from retarget_core.clip.grab import load_mano_model, mano_forward
from retarget_core.rig.mano import MANO_JOINT_NAMES, mano_params, mano_rig

#: GRAB's left-hand codes are the right-hand codes minus 15 (fingers) and 22 -> 21 (palm).
LEFT_OF = {22: 21, **{c: c - 15 for c in range(41, 56)}}


@dataclass
class KnownSequence:
    """A written GRAB sequence and its truth: ``path`` (the .npz), ``root`` (the GRAB folder),
    ``mano`` (MANO_RIGHT.pkl path), ``finger_pose`` (T, 45) and ``global_orient`` (T, 3) radians,
    ``transl`` (T, 3) m, ``hand_vertices`` (T, 778, 3) m, ``contact_frames`` (T,) bool."""

    path: Path
    root: Path
    mano: Path
    finger_pose: np.ndarray
    global_orient: np.ndarray
    transl: np.ndarray
    hand_vertices: np.ndarray
    contact_frames: np.ndarray


def _labels(model, hand_vertices, object_vertices, object_poses) -> np.ndarray:
    """GRAB-style right-hand codes (T, Vo) of object vertices within CONTACT_THRESHOLD of the hand."""
    owner = model.weights.argmax(axis=1)
    codes = np.array([contact_code(MANO_JOINT_NAMES[j]) for j in range(16)], dtype=np.int32)
    labels = np.zeros((len(hand_vertices), len(object_vertices)), dtype=np.int32)
    for f, hand in enumerate(hand_vertices):
        world = object_vertices @ object_poses[f][:3, :3].T + object_poses[f][:3, 3]
        d2, face, _ = igl.point_mesh_squared_distance(np.ascontiguousarray(world), np.ascontiguousarray(hand),
                                                      np.ascontiguousarray(model.faces))
        hit = d2 <= CONTACT_THRESHOLD ** 2
        labels[f, hit] = codes[owner[model.faces[np.asarray(face)[hit], 0]]]
    return labels


def write_known_sequence(root, *, clip: str = "bottle_pick_place", n_frames: int = 200, lead: int = 40, seed: int = 3,
                         subject: str = "s1", name: str | None = None, n_pca: int = 45,
                         posedirs: bool = True) -> KnownSequence:
    """Plan, pose and write one sequence (``n_frames`` at 120 fps from ``lead`` frames before the
    first contact: reach, grasp and hold at the clip's real speed); the hand template is the
    model's plus 1 mm of subject noise."""
    root = Path(root)
    raw = make_hand_mano_raw()
    if not posedirs:
        raw["posedirs"] = np.zeros_like(raw["posedirs"])
    mano_path = root / "mano" / "MANO_RIGHT.pkl"
    if not mano_path.exists():
        mano_path.parent.mkdir(parents=True, exist_ok=True)
        write_mano_plain(mano_path, raw)
    model = load_mano_model(mano_path)
    rng = np.random.default_rng(seed)
    vtemp = model.v_template + rng.normal(scale=0.001, size=model.v_template.shape)
    rig = mano_rig(model, vtemp)
    obj, timeline = build_demo_timeline(clip, rig=rig)
    q = np.array(timeline.q)
    poses = np.array(timeline.objects)

    go, finger, transl = mano_params(rig, q)
    hand = mano_forward(model, go, finger, transl, v_template=vtemp)
    labels = _labels(model, hand, obj.vertices, poses)
    first = int(np.argmax((labels > 0).any(axis=1)))
    start = max(0, min(first - lead, len(q) - n_frames))
    window = slice(start, start + n_frames)
    go, finger, transl, hand, labels, poses = (a[window] for a in (go, finger, transl, hand, labels, poses))

    name = name or f"{clip}_1"
    obj_rel = f"tools/object_meshes/contact_meshes/{clip}.ply"
    write_mesh(root / obj_rel, obj.vertices, obj.faces)
    vtemp_rel = f"tools/subject_meshes/male/{subject}_rhand.ply"
    write_mesh(root / vtemp_rel, vtemp, model.faces)
    comps = raw["hands_components"][:n_pca]
    # GRAB's objects: world = v @ R + transl, so R is the transpose of the world-from-object rotation
    orient = Rotation.from_matrix(np.swapaxes(poses[:, :3, :3], 1, 2)).as_rotvec()
    seq = {
        "framerate": 120.0,
        "n_frames": n_frames,
        "obj_name": clip.split("_")[0],
        "sbj_id": subject,
        "motion_intent": "pass",
        "gender": "male",
        "rhand": {"params": {"global_orient": go, "transl": transl, "fullpose": finger,
                             "hand_pose": finger @ np.linalg.pinv(comps)}, "vtemp": vtemp_rel},
        "object": {"params": {"global_orient": orient, "transl": poses[:, :3, 3]}, "object_mesh": obj_rel},
        "contact": {"object": labels, "body": np.zeros((n_frames, 10), dtype=np.int32)},
    }
    path = write_grab_npz(root / "grab" / subject / f"{name}.npz", seq)
    return KnownSequence(path, root, mano_path, finger, go, transl, hand, (labels > 0).any(axis=1))


def geodesic_degrees(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(...,) angle in degrees of the rotation between rotation matrices a and b (..., 3, 3)."""
    rel = np.einsum("...ji,...jk->...ik", a, b)
    cos = (np.trace(rel, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
