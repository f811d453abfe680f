"""Keypoint-only retargeting benchmark (``handretarget bench keypoints``): a rig posed along a
smooth trajectory within its limits gives the keypoints, which the solve must find again; wall
time per frame (root included), evaluations, and the keypoint error, whose answer is 0."""

from __future__ import annotations

import numpy as np

from ..solve.keypoints import KeypointObjective, Keypoints, keypoint_sites, solve_keypoints

#: The bench's keypoints: every marker of the rig's proposed annotations (on a five-finger hand 21:
#: four per finger from base to pad, the back, the wrist's sides and the palm root; about what
#: a hand-tracking capture gives). Fingertips alone leave DOFs free (a four-DOF finger, three
#: coordinates): what they leave free stays near the frame before, and a finger seeded that
#: way can end against a limit a few mm off (LEAP, fingertips and palm points: 56 of 300 frames
#: solved again, the worst 14.8 mm off).
BENCH_KEYPOINTS = None


def posed_trajectory(rig, n_frames: int, fps: float, seed: int = 0, share: float = 0.6) -> np.ndarray:
    """(T, D) poses: each finger DOF a sine of its own period (1-3 s) over ``share`` of its range
    about the range's middle; the root turning and moving smoothly (a few cm, up to ~30 deg)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n_frames) / fps
    mid, amp = (rig.lower + rig.upper) / 2, (rig.upper - rig.lower) / 2
    phase = rng.uniform(0, 2 * np.pi, rig.n_dofs)
    freq = rng.uniform(1 / 3, 1.0, rig.n_dofs)
    q = mid + share * amp * np.sin(2 * np.pi * freq * t[:, None] + phase)
    root = np.flatnonzero([d.joint == 0 for d in rig.dofs])
    swing = np.where([rig.dofs[i].kind == "rotate" for i in root], 0.5, 0.05)
    q[:, root] = rig.rest_pose[root] + swing * np.sin(2 * np.pi * freq[root] * t[:, None] + phase[root])
    return q


def synthetic_keypoints(rig, annotations, n_frames: int, fps: float = 120.0, seed: int = 0,
                        names=BENCH_KEYPOINTS):
    """(Keypoints of the rig posed along :func:`posed_trajectory`, the poses (T, D), the sites):
    markers ``names`` of the annotations (None: all; names they do not have are left out)."""
    have = [m.name for m in annotations.markers]
    names = tuple(have) if names is None else tuple(n for n in names if n in have)
    sites = keypoint_sites(rig, names, annotations)
    objective = KeypointObjective(rig, sites)
    q = posed_trajectory(rig, n_frames, fps, seed)
    positions = np.stack([objective.positions(objective.kin.pose(qf)) for qf in q])
    return Keypoints(names, positions, float(fps)), q, sites


def run_keypoints_benchmark(rig_spec: str = "installed:leap", n_frames: int = 1000, fps: float = 120.0) -> dict:
    """Solve :func:`synthetic_keypoints` of ``rig_spec``; figures as plain data."""
    from ..clip.demo import source_rig
    from ..rig.io import resolve_rig
    from ..transfer.propose import propose_annotations

    rig = resolve_rig(rig_spec)
    annotations = propose_annotations(source_rig(), rig)
    keypoints, _, sites = synthetic_keypoints(rig, annotations, n_frames, fps)
    solved = solve_keypoints(rig, sites, keypoints)
    err = solved.error_mm[np.isfinite(solved.error_mm)]
    return {"rig": rig_spec, "dofs": rig.n_dofs, "frames": n_frames, "fps": fps, "keypoints": list(keypoints.names),
            "seconds": solved.seconds, "ms_per_frame": 1000.0 * solved.seconds / n_frames,
            "evaluations_per_frame": solved.evaluations / n_frames, "frames_retried": solved.retried,
            "error_median_mm": float(np.median(err)), "error_max_mm": float(err.max())}
