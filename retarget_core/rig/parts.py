"""The hand surface cut into closed parts, one per joint that dominates a piece of it.

Self intersection is the overlap of hand parts that do not touch on the surface (a fingertip
pushed into the palm, two fingers through each other), and a hand that passes through itself
encloses its overlap twice: the exact intersection measures (:mod:`retarget_core.evaluate.
intersection`) therefore work on these parts, never on the raw surface as one solid.

The cut, for any skinned surface (a human hand's blended weights, a robot wrapper bound to
its nearest link):

1. each face goes to the joint with the largest summed skin weight over its three vertices;
2. a joint's faces that fall into several edge-connected pieces keep the largest piece; each
   other piece goes to the part it shares the most edges with;
3. a part with fewer than :data:`MIN_PART_FACES` faces, or whose openings are not simple loops
   (two of its pieces touch at a single vertex), is merged into the neighbouring part it shares
   the most edges with, and the cut is repeated until every part closes;
4. each opening of a part is closed by a fan around the loop's centroid
   (:func:`retarget_core.rig.hand_cut.cap_openings`). Two parts meeting along a loop get the
   same cap with opposite winding, so the union of the parts is the hand's own volume
   (up to the small pockets where three parts meet); the cap centres move with the hand as the
   mean of their loop's posed vertices.

Two parts are *adjacent* when they share a surface edge: their caps coincide, so their
overlap is the joint's own flesh and never counts as self intersection.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.sparse import coo_matrix, csr_matrix
from scipy.sparse.csgraph import connected_components

from ..errors import InputError
from ..mesh.geometry import signed_volume
from ..mesh.topology import check_closed_manifold

#: A joint's piece with fewer faces than this is merged into its neighbour (too small to
#: overlap anything measurably, and its caps would be most of it).
MIN_PART_FACES = 12


@dataclass(frozen=True)
class HandParts:
    """The closed parts of one hand surface.

    ``names`` (P,): the joint owning each part; ``face_part`` (F,): the part of every surface
    face; ``centres`` (C, V) sparse averaging matrix of the cap centres; ``part_vertices``:
    per part, ids into the extended vertex array (V surface vertices then C cap centres);
    ``part_faces``: per part (Fp, 3) ids into ``part_vertices``, wound outward;
    ``adjacent``: pairs (a, b), a < b, of parts sharing a surface edge; ``merged``: joints
    whose pieces went to a neighbour.
    """

    names: tuple[str, ...]
    face_part: np.ndarray
    centres: csr_matrix
    part_vertices: tuple[np.ndarray, ...]
    part_faces: tuple[np.ndarray, ...]
    adjacent: frozenset
    merged: tuple[str, ...]

    @property
    def n_parts(self) -> int:
        return len(self.names)

    def extended(self, vertices: np.ndarray) -> np.ndarray:
        """(V + C, 3): the posed surface vertices (V, 3) followed by their cap centres."""
        v = np.asarray(vertices, dtype=np.float64)
        return np.concatenate([v, self.centres @ v])

    def posed(self, vertices: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        """Per part (vertices (Vp, 3), faces (Fp, 3)) at the posed surface vertices (V, 3)."""
        ext = self.extended(vertices)
        return [(ext[ids], f) for ids, f in zip(self.part_vertices, self.part_faces)]

    def non_adjacent_pairs(self) -> list[tuple[int, int]]:
        """Every pair (a, b), a < b, of parts that do not share a surface edge."""
        return [(a, b) for a in range(self.n_parts) for b in range(a + 1, self.n_parts)
                if (a, b) not in self.adjacent]


def _edge_faces(faces: np.ndarray) -> np.ndarray:
    """(E, 2) the two faces of every interior edge of a closed manifold."""
    n_f = len(faces)
    a = faces.reshape(-1)
    b = np.roll(faces, -1, axis=1).reshape(-1)
    key = np.minimum(a, b) * (int(faces.max()) + 1) + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    k = key[order]
    face = np.repeat(np.arange(n_f), 3)[order]
    same = np.flatnonzero(k[1:] == k[:-1])
    return np.stack([face[same], face[same + 1]], axis=1)


def _shared_edges(label: np.ndarray, pairs: np.ndarray, n_labels: int) -> np.ndarray:
    """(L, L) count of surface edges between faces of label i and label j (i != j)."""
    la, lb = label[pairs[:, 0]], label[pairs[:, 1]]
    cross = la != lb
    m = coo_matrix((np.ones(int(cross.sum())), (la[cross], lb[cross])), shape=(n_labels, n_labels)).toarray()
    return m + m.T


def _close(part_faces_global: np.ndarray, what: str):
    """Cap one part; returns (local->global vertex ids, local faces incl. caps, loops as
    global vertex id arrays) or raises InputError when an opening is not a simple loop."""
    from .hand_cut import cap_openings

    ids, local = np.unique(part_faces_global, return_inverse=True)
    local = local.reshape(-1, 3)
    n = len(ids)
    _, faces, _ = cap_openings(np.zeros((n, 3)), local, np.zeros((n, 0)), what=what)
    caps = faces[len(local):]
    loops = [ids[caps[caps[:, 2] == c, 1]] for c in range(n, n + int(caps[:, 2].max() - n + 1))] if len(caps) else []
    report = check_closed_manifold(faces, n + len(loops))
    if not (report.closed and report.manifold):
        raise InputError("the capped part is not a closed manifold: " + report.describe(), element=what)
    return ids, faces, loops


def hand_parts(faces: np.ndarray, weights: np.ndarray, names: Sequence[str], *, rest_vertices: np.ndarray,
               min_faces: int = MIN_PART_FACES) -> HandParts:
    """Cut a closed manifold hand surface into closed parts (see the module notes).

    faces (F, 3) int; weights (V, J) dense skin weights; names (J,) joint names;
    rest_vertices (V, 3) metres (only their winding is read: parts are wound outward).
    Raises :class:`InputError` when the surface is not a closed manifold.
    """
    faces = np.asarray(faces, dtype=np.int64)
    w = np.asarray(weights, dtype=np.float64)
    report = check_closed_manifold(faces, len(w))
    if not (report.closed and report.manifold):
        raise InputError("the hand surface is not a closed manifold: " + report.describe(), element="surface")
    if signed_volume(rest_vertices, faces) < 0:
        faces = faces[:, ::-1]
    n_j = w.shape[1]
    label = np.argmax(w[faces].sum(axis=1), axis=1)
    pairs = _edge_faces(faces)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(len(faces),) * 2).tocsr()
    merged: list[str] = []

    def merge(faces_mask: np.ndarray, own: int) -> None:
        shared = _shared_edges(label, pairs, n_j)[own]
        shared[own] = 0
        if shared.max() <= 0:
            return
        label[faces_mask] = int(np.argmax(shared))

    while True:
        changed = False
        # 2: one edge-connected piece per joint
        for j in np.unique(label):
            mask = label == j
            idx = np.flatnonzero(mask)
            n_c, comp = connected_components(graph[idx][:, idx], directed=False)
            if n_c > 1:
                keep = np.argmax(np.bincount(comp))
                for c in range(n_c):
                    if c != keep:
                        piece = np.zeros(len(faces), bool)
                        piece[idx[comp == c]] = True
                        # the piece's own neighbours decide, not the rest of its joint
                        la = label.copy()
                        la[piece] = n_j  # a temporary label of its own
                        shared = _shared_edges(la, pairs, n_j + 1)[n_j][:n_j]
                        label[piece] = int(np.argmax(shared))
                changed = True
        if changed:
            continue
        # 3: too small, or not closable
        present = np.unique(label)
        if len(present) > 1:
            counts = np.bincount(label, minlength=n_j)
            small = [j for j in present if counts[j] < min_faces]
            if small:
                j = min(small, key=lambda k: counts[k])
                merged.append(str(names[j]))
                merge(label == j, j)
                continue
        closed = {}
        for j in present:
            try:
                closed[j] = _close(faces[label == j], what=f"part {names[j]}")
            except InputError:
                if len(present) == 1:
                    raise
                merged.append(str(names[j]))
                merge(label == j, j)
                changed = True
                break
        if not changed:
            break

    present = sorted(closed)
    index = {j: p for p, j in enumerate(present)}
    n_v = len(w)
    loops_all: list[np.ndarray] = []
    part_vertices, part_faces = [], []
    for j in present:
        ids, f, loops = closed[j]
        cap_ids = n_v + len(loops_all) + np.arange(len(loops))
        loops_all.extend(loops)
        part_vertices.append(np.concatenate([ids, cap_ids]).astype(np.int64))
        part_faces.append(f.astype(np.int64))
    if loops_all:
        rows = np.concatenate([np.full(len(lp), i) for i, lp in enumerate(loops_all)])
        cols = np.concatenate(loops_all)
        vals = np.concatenate([np.full(len(lp), 1.0 / len(lp)) for lp in loops_all])
        centres = csr_matrix((vals, (rows, cols)), shape=(len(loops_all), n_v))
    else:
        centres = csr_matrix((0, n_v))
    face_part = np.array([index[j] for j in label], dtype=np.int64)
    shared = _shared_edges(face_part, pairs, len(present))
    adjacent = frozenset((a, b) for a, b in zip(*np.nonzero(np.triu(shared))) if a != b)
    return HandParts(tuple(str(names[j]) for j in present), face_part, centres, tuple(part_vertices),
                     tuple(part_faces), frozenset((int(a), int(b)) for a, b in adjacent), tuple(merged))


def rig_parts(rig) -> HandParts:
    """:func:`hand_parts` of a rig's surface."""
    s = rig.surface
    return hand_parts(s.faces, s.dense_weights(rig.n_joints), rig.joint_names, rest_vertices=s.vertices)
