"""GRAB-format sequences with known poses and real contacts, on the hand-shaped MANO model of
:mod:`mano_hand`: the fixture of the GRAB end-to-end tests.

A demo grasp (:func:`retarget_core.clip.demo.build_demo_timeline`, fingers closed until they
touch the object) is planned on the MANO rig of the subject's template, its DOF trajectory turned
into MANO parameters (:func:`retarget_core.rig.mano.mano_params`), the hand posed by MANO's own
forward function (pose correctives included) and the object's vertices within 2 mm of it labelled
with GRAB's codes of the nearest hand joint. Everything is written in GRAB's folder layout:
``<root>/grab/<subject>/<sequence>.npz`` with the meshes under ``<root>/tools/``."""

from __future__ import annotations

import contextlib
import functools
import io
from dataclasses import dataclass
from pathlib import Path

import igl
import numpy as np
from scipy.spatial.transform import Rotation

from grab_fixtures import PARENTS, write_grab_npz, write_mano_plain, write_mesh
from mano_hand import make_hand_mano_raw
from retarget_core.cli import main
from retarget_core.clip.demo import CONTACT_THRESHOLD, build_demo_timeline, contact_code
from retarget_core.clip.grab import ManoModel, load_mano_model, mano_forward
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
        # only the object vertices inside the hand's box (grown by the threshold) can touch it
        lo, hi = hand.min(axis=0) - CONTACT_THRESHOLD, hand.max(axis=0) + CONTACT_THRESHOLD
        near = np.nonzero(np.all((world >= lo) & (world <= hi), axis=1))[0]
        if len(near) == 0:
            continue
        d2, face, _ = igl.point_mesh_squared_distance(np.ascontiguousarray(world[near]), np.ascontiguousarray(hand),
                                                      np.ascontiguousarray(model.faces))
        hit = d2 <= CONTACT_THRESHOLD ** 2
        labels[f, near[hit]] = codes[owner[model.faces[np.asarray(face)[hit], 0]]]
    return labels


@functools.lru_cache(maxsize=4)
def _planned(clip: str, seed: int, posedirs: bool):
    """The planned grasp of :func:`write_known_sequence` (cached: planning takes ~15 s):
    (vtemp (778, 3), object, global_orient, finger_pose, transl, object poses, hand vertices,
    contact labels), whole clip."""
    raw = make_hand_mano_raw()
    if not posedirs:
        raw["posedirs"] = np.zeros_like(raw["posedirs"])
    model = ManoModel(**{k: np.asarray(raw[k], dtype=np.float64) for k in (
        "v_template", "shapedirs", "posedirs", "J_regressor", "weights", "hands_components", "hands_mean")},
        parents=PARENTS.copy(), faces=np.asarray(raw["f"], dtype=np.int64))
    rng = np.random.default_rng(seed)
    vtemp = model.v_template + rng.normal(scale=0.001, size=model.v_template.shape)
    rig = mano_rig(model, vtemp)
    obj, timeline = build_demo_timeline(clip, rig=rig)
    go, finger, transl = mano_params(rig, np.array(timeline.q))
    poses = np.array(timeline.objects)
    hand = mano_forward(model, go, finger, transl, v_template=vtemp)
    return vtemp, obj, go, finger, transl, poses, hand, _labels(model, hand, obj.vertices, poses)


#: The mirror of the two-hand sequences: world x -> -x (the bottle stands on that plane).
MIRROR = np.diag([-1.0, 1.0, 1.0])


def mirrored_mano_raw(raw: dict) -> dict:
    """The MANO-format left hand that is the mirror (x -> -x) of the right-hand ``raw``: the
    same vertex order and triangles, shape and pose blend shapes, PCA components and mean pose
    mirrored (a joint's axis-angle r becomes -M r, so rotation R becomes M R M)."""
    out = dict(raw)
    sign = np.diag(MIRROR)
    out["v_template"] = raw["v_template"] * sign
    out["J"] = raw["J"] * sign
    out["shapedirs"] = raw["shapedirs"] * sign[None, :, None]
    # feature (R - I)[a, b] of each joint turns into M_aa M_bb (R - I)[a, b]
    feature_sign = np.tile(np.outer(sign, sign).reshape(-1), 15)
    out["posedirs"] = raw["posedirs"] * sign[None, :, None] * feature_sign[None, None, :]
    axis_sign = np.tile(-sign, 15)
    out["hands_components"] = raw["hands_components"] * axis_sign[None, :]
    out["hands_mean"] = raw["hands_mean"] * axis_sign
    out["is_rhand"] = False
    out.pop("_marker_landmarks", None)
    return out


def write_known_sequence(root, *, clip: str = "bottle_pick_place", n_frames: int = 200, lead: int = 40, seed: int = 3,
                         subject: str = "s1", name: str | None = None, n_pca: int = 45,
                         posedirs: bool = True, both_hands: bool = False) -> KnownSequence:
    """Plan, pose and write one sequence (``n_frames`` at 120 fps from ``lead`` frames before the
    first contact: reach, grasp and hold at the clip's real speed); the hand template is the
    model's plus 1 mm of subject noise. ``both_hands``: also the left hand (``lhand``, with
    ``mano/MANO_LEFT.pkl``), the mirror image of the right across x = 0 in every frame,
    holding the same bottle from the other side (the window must end before the bottle leaves
    the mirror plane)."""
    root = Path(root)
    raw = make_hand_mano_raw()
    if not posedirs:
        raw["posedirs"] = np.zeros_like(raw["posedirs"])
    mano_path = root / "mano" / "MANO_RIGHT.pkl"
    if not mano_path.exists():
        mano_path.parent.mkdir(parents=True, exist_ok=True)
        write_mano_plain(mano_path, raw)
    model = load_mano_model(mano_path)
    vtemp, obj, go, finger, transl, poses, hand, labels = _planned(clip, seed, posedirs)
    first = int(np.argmax((labels > 0).any(axis=1)))
    start = max(0, min(first - lead, len(go) - n_frames))
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
    if both_hands:
        left_raw = mirrored_mano_raw(raw)
        left_path = root / "mano" / "MANO_LEFT.pkl"
        write_mano_plain(left_path, left_raw)
        left = load_mano_model(left_path, "left")
        if np.abs(poses[:, 0, 3]).max() > 1e-9 or np.abs(poses[:, :3, :3] - np.eye(3)).max() > 1e-9:
            raise ValueError("the bottle leaves the mirror plane in this window: shorten it")
        axis_sign = -np.diag(MIRROR)
        l_go, l_finger = go * axis_sign, finger * np.tile(axis_sign, 15)
        l_transl = transl * np.diag(MIRROR)
        l_vtemp = vtemp * np.diag(MIRROR)
        l_hand = mano_forward(left, l_go, l_finger, l_transl, v_template=l_vtemp)
        l_labels = _labels(left, l_hand, obj.vertices, poses)
        # GRAB stores one code per object vertex: where both hands' fingers reach the same spot
        # (they wrap round the bottle from both sides) neither keeps it, so the contacts stay mirrored
        shared = (labels > 0) & (l_labels > 0)
        labels, l_labels = np.where(shared, 0, labels), np.where(shared, 0, l_labels)
        seq["contact"]["object"] = np.where(labels > 0, labels,
                                            np.where(l_labels == 22, 21, np.where(l_labels > 0, l_labels - 15, 0)))
        l_rel = f"tools/subject_meshes/male/{subject}_lhand.ply"
        write_mesh(root / l_rel, l_vtemp, left.faces)
        l_comps = left_raw["hands_components"][:n_pca]
        seq["lhand"] = {"params": {"global_orient": l_go, "transl": l_transl, "fullpose": l_finger,
                                   "hand_pose": l_finger @ np.linalg.pinv(l_comps)}, "vtemp": l_rel}
    path = write_grab_npz(root / "grab" / subject / f"{name}.npz", seq)
    return KnownSequence(path, root, mano_path, finger, go, transl, hand, (labels > 0).any(axis=1))


def geodesic_degrees(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(...,) angle in degrees of the rotation between rotation matrices a and b (..., 3, 3)."""
    rel = np.einsum("...ji,...jk->...ik", a, b)
    cos = (np.trace(rel, axis1=-2, axis2=-1) - 1.0) / 2.0
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def run_cli(*args) -> str:
    """``handretarget ARGS`` in this process (arguments str()-ed); asserts it succeeded and
    returns what it printed."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main([str(a) for a in args]) == 0
    return out.getvalue()

