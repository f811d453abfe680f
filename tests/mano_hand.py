"""A synthetic, hand-shaped MANO-format model for tests (right hand, metres).

Nothing of the real MANO is used: the surface is the project's generated ``source_human`` demo
hand, decimated with libigl to a topological disk of exactly 778 vertices (closed hand, one
opening at the wrist, like MANO), its vertices reordered so that each of the 25 vertex ids of
:data:`retarget_core.clip.markers.MANO_MARKERS` sits on the landmark its name says (the demo
rig's own marker sites, :func:`retarget_core.rig.anatomy.source_markers`). Joints are the demo
rig's bind joints in MANO's order, skin weights are transferred from the demo rig, and the whole
model is moved rigidly so the wrist joint sits well off the origin, as in the real file.

The returned dict has the keys of :func:`grab_fixtures.make_mano_raw` plus ``"_marker_landmarks"``
(name -> [x, y, z], metres, same frame as ``v_template``), which
:func:`retarget_core.clip.grab.load_mano_model` ignores."""

from __future__ import annotations

import copy
import functools

import numpy as np
from scipy.optimize import nnls
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from grab_fixtures import N_JOINTS, N_VERTICES, PARENTS
from retarget_core.clip.markers import MANO_MARKERS

#: MANO joint order (wrist, index, middle, pinky, ring, thumb) as demo-rig joint names.
MANO_JOINT_SOURCES = ["wrist"] + [f"{finger}{k}" for finger in ("index", "middle", "pinky", "ring", "thumb")
                                  for k in (1, 2, 3)]
#: The rigid offset applied last: rotation (axis-angle, radians) about the wrist, then the
#: translation (metres) that puts the wrist joint (at the demo rig's origin) here.
OFFSET_ROTVEC = np.array([0.08, -0.05, 0.12])
OFFSET_TRANSLATION = np.array([0.09, 0.006, 0.006])


# ---- topology ---------------------------------------------------------------------------------

def boundary_loops(faces: np.ndarray) -> list[list[int]]:
    """The boundary loops of a triangle mesh (faces (F, 3)) as vertex-id cycles; raises
    ValueError when the boundary is not a set of simple loops (a vertex on two boundary
    stretches, an edge used by more than two faces)."""
    faces = np.asarray(faces, dtype=np.int64)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    uniq, counts = np.unique(edges, axis=0, return_counts=True)
    if counts.max() > 2:
        raise ValueError("an edge is used by more than two faces")
    boundary = uniq[counts == 1]
    neighbours: dict[int, list[int]] = {}
    for a, b in boundary.tolist():
        neighbours.setdefault(a, []).append(b)
        neighbours.setdefault(b, []).append(a)
    if any(len(n) != 2 for n in neighbours.values()):
        raise ValueError("the boundary is not a set of simple loops")
    loops, seen = [], set()
    for start in neighbours:
        if start in seen:
            continue
        loop, prev, cur = [start], None, start
        seen.add(start)
        while True:
            a, b = neighbours[cur]
            nxt = b if a == prev else a
            if nxt == start:
                break
            loop.append(nxt)
            seen.add(nxt)
            prev, cur = cur, nxt
        loops.append(loop)
    return loops


def is_oriented_disk(faces: np.ndarray, n_vertices: int) -> bool:
    """True when ``faces`` is one connected, consistently oriented, edge-manifold triangle mesh
    using all ``n_vertices`` vertices, with Euler characteristic 1 and one simple boundary loop."""
    faces = np.asarray(faces, dtype=np.int64)
    if len(faces) == 0 or np.unique(faces).size != n_vertices or faces.max() != n_vertices - 1:
        return False
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    if len(np.unique(directed, axis=0)) != len(directed):  # an edge used twice the same way
        return False
    try:
        loops = boundary_loops(faces)
    except ValueError:
        return False
    n_edges = len(np.unique(np.sort(directed, axis=1), axis=0))
    adjacency = coo_matrix((np.ones(len(directed)), (directed[:, 0], directed[:, 1])), shape=(n_vertices,) * 2)
    n_comp, _ = connected_components(adjacency, directed=False)
    return len(loops) == 1 and n_comp == 1 and n_vertices - n_edges + len(faces) == 1


# ---- geometry ---------------------------------------------------------------------------------

def _rotation(rotvec: np.ndarray) -> np.ndarray:
    angle = float(np.linalg.norm(rotvec))
    k = rotvec / angle
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * kx + (1.0 - np.cos(angle)) * kx @ kx


def _cut_disk(vertices, faces, wrist, forward):
    """Decimate the closed surface to 778 + k vertices and drop the k most proximal ones (along
    ``forward`` from ``wrist``) with their faces; k is searched around the count of vertices
    proximal of the wrist. Returns (vertices (778, 3), faces (F, 3))."""
    import igl

    v = np.asfortranarray(vertices, dtype=np.float64)
    f = np.asfortranarray(faces, dtype=np.int32)

    def attempt(k):
        n = N_VERTICES + k
        u, g, _, _ = igl.decimate(v, f, 2 * n - 4)  # closed genus 0: F = 2V - 4
        if len(u) != n:
            return None, u, g
        proj = (u - wrist) @ forward
        order = np.argsort(proj, kind="stable")
        removed = np.zeros(n, dtype=bool)
        removed[order[:k]] = True
        keep_faces = g[~removed[g].any(axis=1)]
        remap = np.cumsum(~removed) - 1
        out_v, out_f = u[~removed], remap[keep_faces]
        return (out_v, out_f) if is_oriented_disk(out_f, N_VERTICES) else None, u, g

    # First guess: decimate to ~880 and count the vertices proximal of the wrist.
    _, u, _ = attempt(100)
    k0 = int(((u - wrist) @ forward < 0.0).sum())
    for dk in sorted(range(-40, 41), key=abs):
        k = k0 + dk
        if k < 1:
            continue
        result, _, _ = attempt(k)
        if result is not None:
            return result
    raise RuntimeError("no decimation gave a 778-vertex disk")


def _closest_points(points, vertices, faces):
    """Closest points on the mesh: (face ids (P,), barycentric (P, 3))."""
    import igl

    _, face, closest = igl.point_mesh_squared_distance(
        np.ascontiguousarray(points, dtype=np.float64), np.ascontiguousarray(vertices, dtype=np.float64),
        np.ascontiguousarray(faces, dtype=np.int64))
    tri = vertices[faces[face]]
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    v0, v1, v2 = b - a, c - a, closest - a
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
    den = d00 * d11 - d01 * d01
    bv = (d11 * d20 - d01 * d21) / den
    bw = (d00 * d21 - d01 * d20) / den
    bary = np.clip(np.stack([1.0 - bv - bw, bv, bw], axis=1), 0.0, None)
    return face, bary / bary.sum(axis=1, keepdims=True)


def _assign_markers(landmarks: dict[str, np.ndarray], vertices: np.ndarray) -> dict[str, int]:
    """Each marker's nearest vertex, distinct: markers closest to a vertex claim first and a
    marker whose nearest is taken gets its next nearest."""
    dist = {n: np.linalg.norm(vertices - p, axis=1) for n, p in landmarks.items()}
    chosen, taken = {}, set()
    for name in sorted(landmarks, key=lambda n: dist[n].min()):
        for vid in np.argsort(dist[name]):
            if int(vid) not in taken:
                chosen[name] = int(vid)
                taken.add(int(vid))
                break
    return chosen


def _regressor_row(vertices: np.ndarray, joint: np.ndarray) -> np.ndarray:
    """(V,) non-negative weights summing to 1 over the vertices nearest ``joint`` whose weighted
    mean is ``joint`` (to well under a micrometre)."""
    dist = np.linalg.norm(vertices - joint, axis=1)
    for n in (24, 40, 80, 160, len(vertices)):
        ids = np.argsort(dist)[:n]
        a = np.vstack([(vertices[ids] - joint).T * 100.0, 1e3 * np.ones(n)])  # centimetres
        b = np.array([0.0, 0.0, 0.0, 1e3])
        w, _ = nnls(a, b)
        if w.sum() <= 0:
            continue
        w /= w.sum()
        if np.linalg.norm(w @ vertices[ids] - joint) < 1e-9:
            row = np.zeros(len(vertices))
            row[ids] = w
            return row
    raise RuntimeError("the joint is not inside the hull of the surface")


@functools.lru_cache(maxsize=4)
def _hand_geometry(resolution: float) -> dict:
    """The seed-independent part: v_template, f, J, J_regressor, weights, landmarks (metres)."""
    from retarget_core.rig.anatomy import source_markers
    from retarget_core.rig.demo_hands import demo_hand
    from retarget_core.rig.hand_model import hand_model

    rig = demo_hand("source_human", resolution=resolution)
    model = hand_model(rig)
    surf_v = np.asarray(rig.surface.vertices, dtype=np.float64)
    surf_f = np.asarray(rig.surface.faces, dtype=np.int64)

    verts, faces = _cut_disk(surf_v, surf_f, model.wrist, model.forward)

    names, m_faces, m_bary = source_markers(rig, model)
    landmarks = {n: m_bary[i] @ surf_v[surf_f[m_faces[i]]] for i, n in enumerate(names)}
    if set(landmarks) != set(MANO_MARKERS):
        raise RuntimeError(f"demo rig markers {sorted(landmarks)} differ from MANO_MARKERS")
    chosen = _assign_markers(landmarks, verts)
    # each marker vertex moved onto its landmark (a point of the fine surface a few mm away), as
    # MANO's marker vertices lie where the paper's markers are
    verts = verts.copy()
    for name, vid in chosen.items():
        verts[vid] = landmarks[name]

    # order[new id] = old id: marker vertices at their MANO ids, the rest in their old order.
    order = np.full(N_VERTICES, -1, dtype=np.int64)
    for name, vid in chosen.items():
        order[MANO_MARKERS[name]] = vid
    rest = np.setdiff1d(np.arange(N_VERTICES), list(chosen.values()))
    order[order < 0] = rest
    inverse = np.empty(N_VERTICES, dtype=np.int64)
    inverse[order] = np.arange(N_VERTICES)
    verts, faces = verts[order], inverse[faces]

    # Joints (MANO order) and the regressor.
    bind = rig.kinematics().bind_world[:, :3, 3]
    joint_ids = [rig.joint_names.index(n) for n in MANO_JOINT_SOURCES]
    joints = np.asarray(bind[joint_ids], dtype=np.float64)
    j_regressor = np.stack([_regressor_row(verts, j) for j in joints])

    # Skin weights from the closest point of the demo surface, rig joints -> MANO joints.
    to_mano = np.zeros((rig.n_joints, N_JOINTS))
    for mano_j, name in enumerate(MANO_JOINT_SOURCES):
        to_mano[rig.joint_names.index(name), mano_j] = 1.0
    for rig_j, name in enumerate(rig.joint_names):
        if not to_mano[rig_j].any():  # root (and anything else above the wrist)
            to_mano[rig_j, 0] = 1.0
    dense = rig.surface.dense_weights(rig.n_joints) @ to_mano
    face, bary = _closest_points(verts, surf_v, surf_f)
    weights = np.einsum("pk,pkj->pj", bary, dense[surf_f[face]])
    weights = np.clip(weights, 0.0, None)
    weights[weights < 1e-6] = 0.0
    weights /= weights.sum(axis=1, keepdims=True)

    # Rigid offset: rotate about the wrist joint (the rig's origin), then translate.
    rot = _rotation(OFFSET_ROTVEC)
    shift = OFFSET_TRANSLATION - rot @ joints[0]

    def place(p):
        return np.asarray(p) @ rot.T + shift

    # MANO's hands_mean is a relaxed, slightly curled hand: the demo rig's relaxed pose as each
    # MANO joint's rotation relative to its parent (axis-angle, in the placed frame)
    from scipy.spatial.transform import Rotation

    from retarget_core.clip.demo import relaxed_pose

    skin = rig.kinematics().pose(relaxed_pose(rig, np.eye(4))).skin[:, :3, :3]
    parent_of = {name: (MANO_JOINT_SOURCES[PARENTS[k]] if PARENTS[k] >= 0 else None)
                 for k, name in enumerate(MANO_JOINT_SOURCES)}
    relaxed = []
    for name in MANO_JOINT_SOURCES[1:]:
        local = skin[rig.joint_names.index(parent_of[name])].T @ skin[rig.joint_names.index(name)]
        relaxed.append(Rotation.from_matrix(rot @ local @ rot.T).as_rotvec())

    return {
        "v_template": place(verts),
        "f": faces.astype(np.uint32),
        "J": place(joints),
        "relaxed_pose": np.concatenate(relaxed),
        "J_regressor": j_regressor,
        "weights": weights,
        "landmarks": {n: place(p) for n, p in landmarks.items()},
    }


#: Amplitude (m per unit of pose feature) and wavelength (m) of the pose correctives.
POSEDIRS_AMPLITUDE = 0.0002
POSEDIRS_WAVELENGTH = 0.08


def _smooth_posedirs(rng, vertices: np.ndarray) -> np.ndarray:
    """(778, 3, 135) pose correctives that vary smoothly over the hand (like MANO's: a bent joint
    bulges the skin around it), a plane wave of random direction, phase and displacement each."""
    n_features = 9 * (N_JOINTS - 1)
    k = rng.normal(size=(n_features, 3))
    k *= 2 * np.pi / POSEDIRS_WAVELENGTH / np.linalg.norm(k, axis=1, keepdims=True)
    phase = rng.uniform(0, 2 * np.pi, size=n_features)
    displacement = rng.normal(size=(n_features, 3))
    displacement /= np.linalg.norm(displacement, axis=1, keepdims=True)
    wave = np.cos(vertices @ k.T + phase)  # (V, P)
    return POSEDIRS_AMPLITUDE * np.einsum("vp,pc->vcp", wave, displacement)


@functools.lru_cache(maxsize=8)
def _build(seed: int, resolution: float) -> dict:
    geo = _hand_geometry(resolution)
    rng = np.random.default_rng(seed)
    comps, _ = np.linalg.qr(rng.normal(size=(45, 45)))
    kintree = np.stack([np.where(PARENTS < 0, 2**32 - 1, PARENTS), np.arange(N_JOINTS)]).astype(np.int64)
    return {
        "v_template": geo["v_template"].copy(),
        "shapedirs": rng.normal(scale=0.0005, size=(N_VERTICES, 3, 10)),
        "posedirs": _smooth_posedirs(rng, geo["v_template"]),
        "J_regressor": geo["J_regressor"].copy(),
        "weights": geo["weights"].copy(),
        "kintree_table": kintree,
        "f": geo["f"].copy(),
        "hands_components": comps,
        "hands_mean": geo["relaxed_pose"] + rng.normal(scale=0.02, size=45),
        "hands_coeffs": rng.normal(size=(10, 45)),
        "J": geo["J"].copy(),
        "bs_style": "lbs",
        "bs_type": "lrotmin",
        "_marker_landmarks": {n: [float(x) for x in p] for n, p in geo["landmarks"].items()},
    }


def make_hand_mano_raw(seed: int = 0, *, resolution: float = 0.004) -> dict:
    """A hand-shaped MANO-format dict of plain numpy arrays (right hand, metres): 778 vertices
    forming a closed hand with one opening at the wrist, MANO's 16-joint tree (wrist at
    (0.09, 0.006, 0.006)), J_regressor reproducing "J" exactly, skin weights from the demo rig,
    the 25 MANO marker vertex ids on their landmarks (within a few mm) and ``"_marker_landmarks"``
    (name -> [x, y, z]). ``seed`` drives only the random blend shapes and pose PCA;
    ``resolution`` (metres) is the demo hand's cell size. Cached; returns a deep copy."""
    return copy.deepcopy(_build(int(seed), float(resolution)))


def hand_mano_landmarks(seed: int = 0, *, resolution: float = 0.004) -> dict[str, np.ndarray]:
    """Marker name -> (3,) landmark position (metres, the frame of ``v_template``)."""
    return {n: np.array(p) for n, p in _build(int(seed), float(resolution))["_marker_landmarks"].items()}
