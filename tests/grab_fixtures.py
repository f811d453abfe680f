"""Synthetic MANO-format models and GRAB-format sequences for the GRAB importer tests.

Nothing of MANO or GRAB is shipped: the model is a made-up 778-vertex "hand" with MANO's joint
tree, written either with plain numpy arrays or in the official Python-2 style (chumpy ``Ch``
objects and a scipy ``csc_matrix``, reproduced with stand-in classes)."""

from __future__ import annotations

import pickle
import sys
import types
from pathlib import Path

import numpy as np
import trimesh

N_VERTICES = 778
N_JOINTS = 16
#: MANO's tree: wrist, then index, middle, pinky, ring, thumb (3 joints each).
PARENTS = np.array([-1, 0, 1, 2, 0, 4, 5, 0, 7, 8, 0, 10, 11, 0, 13, 14])
VERTS_PER_FINGER_JOINT = 30  # 15 * 30 = 450; the wrist gets the other 328


def joint_of_vertex() -> np.ndarray:
    """(778,) the joint each synthetic vertex belongs to."""
    owner = np.zeros(N_VERTICES, dtype=np.int64)
    n_wrist = N_VERTICES - 15 * VERTS_PER_FINGER_JOINT
    owner[n_wrist:] = 1 + np.arange(15 * VERTS_PER_FINGER_JOINT) // VERTS_PER_FINGER_JOINT
    return owner


def joint_positions() -> np.ndarray:
    """(16, 3) rest joints: fingers along +x, spread in y; thumb off to the side."""
    joints = np.zeros((N_JOINTS, 3))
    bases = {1: (0.09, 0.03), 4: (0.095, 0.01), 7: (0.08, -0.035), 10: (0.09, -0.012), 13: (0.03, 0.04)}
    for first, (x, y) in bases.items():
        for k in range(3):
            joints[first + k] = [x + 0.03 * k, y + (0.015 * k if first == 13 else 0.0), 0.005 * k]
    return joints


def make_mano_raw(seed: int = 0, *, rigid: bool = True, zero_posedirs: bool = False, n_betas: int = 10) -> dict:
    """A MANO-format dict of plain numpy arrays (right hand)."""
    rng = np.random.default_rng(seed)
    owner = joint_of_vertex()
    joints = joint_positions()
    v_template = np.empty((N_VERTICES, 3))
    j_regressor = np.zeros((N_JOINTS, N_VERTICES))
    for j in range(N_JOINTS):
        ids = np.nonzero(owner == j)[0]
        offsets = rng.normal(scale=0.008 if j else 0.025, size=(len(ids), 3))
        offsets -= offsets.mean(axis=0)  # so the regressed joint is exactly joints[j]
        v_template[ids] = joints[j] + offsets
        j_regressor[j, ids] = 1.0 / len(ids)
    weights = np.zeros((N_VERTICES, N_JOINTS))
    weights[np.arange(N_VERTICES), owner] = 1.0
    if not rigid:
        parent = np.where(PARENTS[owner] < 0, owner, PARENTS[owner])
        weights *= 0.7
        weights[np.arange(N_VERTICES), parent] += 0.3
    faces = np.array([[i, i + 1, i + 2] for i in range(N_VERTICES - 2)], dtype=np.uint32)
    comps, _ = np.linalg.qr(rng.normal(size=(45, 45)))
    kintree = np.stack([np.where(PARENTS < 0, 2**32 - 1, PARENTS), np.arange(N_JOINTS)]).astype(np.int64)
    return {
        "v_template": v_template,
        "shapedirs": rng.normal(scale=0.002, size=(N_VERTICES, 3, n_betas)),
        "posedirs": np.zeros((N_VERTICES, 3, 135)) if zero_posedirs else rng.normal(scale=0.001, size=(N_VERTICES, 3, 135)),
        "J_regressor": j_regressor,
        "weights": weights,
        "kintree_table": kintree,
        "f": faces,
        "hands_components": comps,
        "hands_mean": rng.normal(scale=0.1, size=45),
        "hands_coeffs": rng.normal(size=(10, 45)),
        "J": joints,
        "bs_style": "lbs",
        "bs_type": "lrotmin",
    }


def write_mano_plain(path, raw: dict) -> Path:
    path = Path(path)
    with open(path, "wb") as handle:
        pickle.dump(raw, handle, protocol=4)
    return path


class _FakeCh:
    """Pickles like ``chumpy.ch.Ch`` (copy_reg._reconstructor + a state dict with 'x')."""


class _FakeCsc:
    """Pickles like ``scipy.sparse.csc.csc_matrix``."""


def _dense_to_csc_state(dense: np.ndarray) -> dict:
    data, indices, indptr = [], [], [0]
    for col in range(dense.shape[1]):
        rows = np.nonzero(dense[:, col])[0]
        indices.extend(rows.tolist())
        data.extend(dense[rows, col].tolist())
        indptr.append(len(indices))
    return {"_shape": dense.shape, "data": np.array(data), "indices": np.array(indices, dtype=np.int32),
            "indptr": np.array(indptr, dtype=np.int32), "maxprint": 50, "format": "csc"}


def write_mano_official(path, raw: dict) -> Path:
    """Write ``raw`` as an official-style MANO pickle (protocol 0, chumpy Ch, scipy csc, numpy.core
    names) without chumpy: the stand-ins are registered under the official module names only while
    dumping."""
    path = Path(path)
    chumpy = types.ModuleType("chumpy")
    chumpy_ch = types.ModuleType("chumpy.ch")
    csc_mod = types.ModuleType("scipy.sparse.csc")
    _FakeCh.__module__, _FakeCh.__qualname__, _FakeCh.__name__ = "chumpy.ch", "Ch", "Ch"
    _FakeCsc.__module__, _FakeCsc.__qualname__, _FakeCsc.__name__ = "scipy.sparse.csc", "csc_matrix", "csc_matrix"
    chumpy_ch.Ch = _FakeCh
    chumpy.ch = chumpy_ch
    csc_mod.csc_matrix = _FakeCsc

    out = {}
    for key, value in raw.items():
        if key in ("v_template", "shapedirs", "posedirs", "weights"):
            ch = _FakeCh()
            ch.__dict__.update({"x": np.asarray(value), "_dirty_vars": set(), "_itr": None, "_depends_on_deps": {}})
            out[key] = ch
        elif key == "J_regressor":
            csc = _FakeCsc()
            csc.__dict__.update(_dense_to_csc_state(np.asarray(value)))
            out[key] = csc
        else:
            out[key] = value

    saved = {name: sys.modules.get(name) for name in ("chumpy", "chumpy.ch", "scipy.sparse.csc")}
    sys.modules.update({"chumpy": chumpy, "chumpy.ch": chumpy_ch, "scipy.sparse.csc": csc_mod})
    try:
        payload = pickle.dumps(out, protocol=0)
    finally:
        for name, module in saved.items():
            if module is None:
                sys.modules.pop(name, None)
            else:
                sys.modules[name] = module
    # Old MANO files were written by numpy 1.x: use its module names.
    payload = payload.replace(b"cnumpy._core.multiarray\n", b"cnumpy.core.multiarray\n")
    path.write_bytes(payload)
    return path


# ---- GRAB -------------------------------------------------------------------------------------

def write_mesh(path, vertices, faces) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    trimesh.Trimesh(vertices=np.asarray(vertices), faces=np.asarray(faces), process=False).export(str(path))
    return path


def rotation_z(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def make_grab_sequence(root, raw: dict, *, n_frames: int = 6, seed: int = 1, n_pca: int = 24) -> dict:
    """Write meshes under ``root`` (GRAB layout) and return a GRAB-format sequence dict whose
    mesh paths are relative to ``root``. Also returns helpers under key '_truth'."""
    root = Path(root)
    rng = np.random.default_rng(seed)
    t = np.arange(n_frames)

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.04)
    obj_rel = "tools/object_meshes/contact_meshes/apple.ply"
    write_mesh(root / obj_rel, sphere.vertices, sphere.faces)
    table = trimesh.creation.box(extents=[1.0, 0.6, 0.04])
    table_vertices = table.vertices + [0.1, 0.0, -0.02]  # off-centre box in its own frame
    table_rel = "tools/object_meshes/contact_meshes/table.ply"
    write_mesh(root / table_rel, table_vertices, table.faces)
    vtemp = raw["v_template"] + rng.normal(scale=0.001, size=raw["v_template"].shape)
    vtemp_rel = "tools/subject_meshes/male/s1_rhand.ply"
    write_mesh(root / vtemp_rel, vtemp, raw["f"].astype(np.int64))

    hand_pose = rng.normal(scale=0.3, size=(n_frames, n_pca))
    fullpose = hand_pose @ raw["hands_components"][:n_pca]
    rh_params = {
        "global_orient": rng.normal(scale=0.5, size=(n_frames, 3)),
        "hand_pose": hand_pose,
        "transl": np.stack([0.01 * t, 0.02 * np.ones(n_frames), 0.8 + 0.001 * t], axis=1),
        "fullpose": fullpose,
    }
    lh_params = {k: np.zeros_like(v) for k, v in rh_params.items()}
    vo = len(sphere.vertices)
    codes = np.array([0, 0, 0, 22, 41, 47, 55, 5, 16, 26, 40, 21])  # 5/16/21 body, 26/40 left hand
    contact_object = rng.choice(codes, size=(n_frames, vo)).astype(np.int32)
    return {
        "framerate": 120.0,
        "n_frames": n_frames,
        "obj_name": "apple",
        "sbj_id": "s1",
        "motion_intent": "eat",
        "gender": "male",
        "rhand": {"params": rh_params, "vtemp": vtemp_rel},
        "lhand": {"params": lh_params, "vtemp": "tools/subject_meshes/male/s1_lhand.ply"},
        "body": {"params": {"transl": np.zeros((n_frames, 3))}, "vtemp": "tools/subject_meshes/male/s1.ply"},
        "object": {
            "params": {"transl": np.stack([0.3 + 0.002 * t, 0.1 * np.ones(n_frames), 0.85 * np.ones(n_frames)], axis=1),
                       "global_orient": rng.normal(scale=0.8, size=(n_frames, 3))},
            "object_mesh": obj_rel,
        },
        "table": {
            "params": {"transl": np.tile([0.2, 0.0, 0.75], (n_frames, 1)),
                       "global_orient": np.tile([0.0, 0.0, 0.3], (n_frames, 1))},
            "table_mesh": table_rel,
        },
        "contact": {"object": contact_object, "body": np.zeros((n_frames, 100), dtype=np.int32)},
        "_truth": {"vtemp": vtemp, "object_vertices": np.asarray(sphere.vertices), "table_vertices": table_vertices},
    }


def write_grab_npz(path, seq: dict) -> Path:
    """np.savez of dicts, as GRAB does (each top-level value becomes a 0-d object array)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **{k: v for k, v in seq.items() if k != "_truth"})
    return path


def write_grab_npz_flat(path, seq: dict) -> Path:
    """The same sequence with nested keys flattened into dotted plain-array members."""
    flat = {}

    def walk(prefix, node):
        for k, v in node.items():
            key = f"{prefix}.{k}" if prefix else k
            if isinstance(v, dict):
                walk(key, v)
            else:
                flat[key] = np.asarray(v)

    walk("", {k: v for k, v in seq.items() if k != "_truth"})
    path = Path(path)
    np.savez(path, **flat)
    return path
