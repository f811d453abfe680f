"""Frames that left their neighbours' branch: where the solved hand turns or moves between two
frames far more than the captured hand does, and the path through the branches that has none.

The full pass solves every frame independently (so the result does not depend on the worker
count), and a hand that fits the markers poorly can have two equally good poses: the solved
root then flips between them from one frame to the next while the source hand barely moves.
The coherence pass (``retarget_core/pipeline.py`` ``coherence_pass``) finds those steps here,
carries each stretch between two jumps on across the clip (every frame re-solved seeded from
the one before, :func:`~retarget_core.solve.problem.trace_branch`), so frames get one candidate
solution per branch, and picks one candidate per frame with :func:`choose_branch_path`: the
fewest jumps first, then the lowest summed objective.

A step is measured as a rigid motion of marker points between consecutive frames (Kabsch):
the rotation angle and the shift of their centroid, on the target hand (its marker points
posed) and on the source (the source side of the same marker pairs)."""

from __future__ import annotations

import numpy as np

#: A step is a jump when it exceeds both this floor and ``JUMP_RATIO`` times the source's step.
JUMP_MIN_ANGLE = np.radians(5.0)
JUMP_MIN_SHIFT = 0.005  # m
JUMP_RATIO = 2.0


def rigid_step(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rigid motion from points ``a`` to points ``b`` (N, M, 3) metres, pair by pair: the
    rotation angle (N,) radians of the best rigid fit (Kabsch) and the shift (N,) metres of the
    centroid."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    ca, cb = a.mean(axis=1, keepdims=True), b.mean(axis=1, keepdims=True)
    h = np.einsum("tmi,tmj->tij", a - ca, b - cb)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(np.einsum("tij,tjk->tik", vt.transpose(0, 2, 1), u.transpose(0, 2, 1))))
    fix = np.ones((len(h), 3))
    fix[:, 2] = d
    r = np.einsum("tji,tj,tkj->tik", vt, fix, u)  # V diag(1, 1, d) U^T
    cos = np.clip((np.trace(r, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    return np.arccos(cos), np.linalg.norm(cb[:, 0] - ca[:, 0], axis=1)


def rigid_steps(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per step between consecutive frames of ``points`` (T, M, 3) metres: the rotation angle
    (T-1,) radians of the best rigid fit and the shift (T-1,) metres of the centroid."""
    points = np.asarray(points, dtype=np.float64)
    return rigid_step(points[:-1], points[1:])


def _is_jump(angle, shift, source_angle, source_shift):
    return (angle > np.maximum(JUMP_MIN_ANGLE, JUMP_RATIO * source_angle)) | \
        (shift > np.maximum(JUMP_MIN_SHIFT, JUMP_RATIO * source_shift))


def branch_jumps(target_points: np.ndarray, source_points: np.ndarray) -> np.ndarray:
    """(T-1,) True for the steps where the target hand (marker points (T, M, 3)) turns or moves
    more than the floors and more than :data:`JUMP_RATIO` times the source (its points of the
    same marker pairs (T, M, 3)) does."""
    return _is_jump(*rigid_steps(target_points), *rigid_steps(source_points))


def branch_runs(jumps: np.ndarray, direction: int) -> list[np.ndarray]:
    """The frame runs that carry each stretch between jumps across the clip (a jump ``k`` is
    the step between frames k and k+1): forward (``direction`` 1) frames k+1, k+2, ... to the
    last frame, each seeded from the one before (the first from frame k); backward (-1) frames
    k, k-1, ... to frame 0 (the first seeded from frame k+1). A run is cut short where it
    rejoins the solution already there (see :func:`~retarget_core.solve.problem.trace_branch`)."""
    steps = np.nonzero(np.asarray(jumps, dtype=bool))[0]
    n_frames = len(jumps) + 1
    if direction > 0:
        return [np.arange(k + 1, n_frames) for k in steps]
    return [np.arange(k, -1, -1) for k in steps]


def choose_branch_path(points: list, values: list, source_points: np.ndarray) -> tuple[np.ndarray, int]:
    """One candidate per frame such that the path has the fewest jumps and, among those, the
    lowest summed objective (dynamic programming over the frames; ties go to the lower
    candidate index, so candidate 0, the frame's own solution, wins a tie).

    points[t]: (K_t, M, 3) the marker points of frame t's candidates; values[t]: (K_t,) their
    objectives; source_points (T, M, 3) the source side. Returns the chosen index per frame
    (T,) and the number of jumps left on the path."""
    n = len(points)
    sa, ss = rigid_steps(source_points)
    jumps = [np.zeros(len(values[0]), dtype=np.int64)]
    total = [np.asarray(values[0], dtype=np.float64)]
    back = []
    for t in range(1, n):
        a, b = np.asarray(points[t - 1]), np.asarray(points[t])
        ka, kb = len(a), len(b)
        angle, shift = rigid_step(np.repeat(a, kb, axis=0), np.tile(b, (ka, 1, 1)))
        step_jump = _is_jump(angle, shift, sa[t - 1], ss[t - 1]).reshape(ka, kb).astype(np.int64)
        j = jumps[-1][:, None] + step_jump  # (ka, kb): jumps of the best path ending in a then b
        s = np.broadcast_to(total[-1][:, None], (ka, kb))
        best = np.empty(kb, dtype=np.int64)
        for k in range(kb):  # lexicographic (jumps, value); np.lexsort is stable: lower index wins ties
            best[k] = np.lexsort((s[:, k], j[:, k]))[0]
        back.append(best)
        jumps.append(j[best, np.arange(kb)])
        total.append(s[best, np.arange(kb)] + np.asarray(values[t], dtype=np.float64))
    last = int(np.lexsort((total[-1], jumps[-1]))[0])
    path = np.empty(n, dtype=np.int64)
    path[-1] = last
    for t in range(n - 1, 0, -1):
        path[t - 1] = back[t - 1][path[t]]
    return path, int(jumps[-1][last])
