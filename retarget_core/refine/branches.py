"""Frames that left their neighbours' branch: where the solved hand turns or moves between two
frames far more than the captured hand does.

The full pass solves every frame independently (so the result does not depend on the worker
count), and a hand that fits the markers poorly can have two equally good poses: the solved
root then flips between them from one frame to the next while the source hand barely moves.
The coherence pass (``retarget_core/pipeline.py`` ``coherence_pass``) finds those steps here
and re-solves the frames after (and before) each one seeded from the other side, keeping a
new solution only when its objective is lower.

A step is measured as a rigid motion of marker points between consecutive frames (Kabsch):
the rotation angle and the shift of their centroid, on the target hand (its marker points
posed) and on the source (the source side of the same marker pairs)."""

from __future__ import annotations

import numpy as np

#: A step is a jump when it exceeds both this floor and ``JUMP_RATIO`` times the source's step.
JUMP_MIN_ANGLE = np.radians(5.0)
JUMP_MIN_SHIFT = 0.005  # m
JUMP_RATIO = 2.0


def rigid_steps(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per step between consecutive frames of ``points`` (T, M, 3) metres: the rotation angle
    (T-1,) radians of the best rigid fit and the shift (T-1,) metres of the centroid."""
    points = np.asarray(points, dtype=np.float64)
    a, b = points[:-1], points[1:]
    ca, cb = a.mean(axis=1, keepdims=True), b.mean(axis=1, keepdims=True)
    h = np.einsum("tmi,tmj->tij", a - ca, b - cb)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(np.einsum("tij,tjk->tik", vt.transpose(0, 2, 1), u.transpose(0, 2, 1))))
    fix = np.ones((len(h), 3))
    fix[:, 2] = d
    r = np.einsum("tji,tj,tkj->tik", vt, fix, u)  # V diag(1, 1, d) U^T
    cos = np.clip((np.trace(r, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return np.arccos(cos), np.linalg.norm(cb[:, 0] - ca[:, 0], axis=1)


def branch_jumps(target_points: np.ndarray, source_points: np.ndarray) -> np.ndarray:
    """(T-1,) True for the steps where the target hand (marker points (T, M, 3)) turns or moves
    more than the floors and more than :data:`JUMP_RATIO` times the source (its points of the
    same marker pairs (T, M, 3)) does."""
    ta, ts = rigid_steps(target_points)
    sa, ss = rigid_steps(source_points)
    return (ta > np.maximum(JUMP_MIN_ANGLE, JUMP_RATIO * sa)) | (ts > np.maximum(JUMP_MIN_SHIFT, JUMP_RATIO * ss))


def branch_runs(jumps: np.ndarray, direction: int) -> list[np.ndarray]:
    """The frame runs to re-solve across each jump (a step ``k`` between frames k and k+1):
    forward (``direction`` 1) frames k+1, k+2, ... up to the next jump's far side, each seeded
    from the one before; backward (-1) frames k, k-1, ... down to the previous jump."""
    steps = np.nonzero(np.asarray(jumps, dtype=bool))[0]
    n_frames = len(jumps) + 1
    runs = []
    for i, k in enumerate(steps):
        if direction > 0:
            end = steps[i + 1] + 1 if i + 1 < len(steps) else n_frames - 1
            runs.append(np.arange(k + 1, end + 1))
        else:
            start = steps[i - 1] if i > 0 else 0
            runs.append(np.arange(k, start - 1, -1))
    return runs
