"""Timing of dense contact pairing on a synthetic clip (no files needed).

The demo source hand (coarse resolution) moves its fingers slowly through random in-limit
poses while an icosphere (radius 4 cm, 2562 vertices) slowly turns against its palm. Each
frame the ``contacts_per_frame`` object vertices nearest to the hand are labelled as contacts
(code 22), then :func:`pair_contacts` is timed on one core.
"""

from __future__ import annotations

import os
import sys
import time

_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "TBB_NUM_THREADS")


def _single_thread_env() -> str:
    """Ask for one thread where that can still take effect (numpy not imported yet)."""
    if "numpy" in sys.modules:
        return "numpy already imported: thread env vars left as they are"
    for var in _THREAD_VARS:
        os.environ[var] = "1"
    return "thread env vars set to 1"


def _smooth_noise(rng, n_frames: int, n_dofs: int, knots_every: int = 30):
    """(T, D) values in [0, 1] that vary slowly (cubic interpolation of random knots)."""
    import numpy as np
    from scipy.interpolate import CubicSpline

    n_knots = max(2, n_frames // knots_every + 2)
    knots = rng.uniform(0.0, 1.0, size=(n_knots, n_dofs))
    spline = CubicSpline(np.arange(n_knots) * knots_every, knots, axis=0)
    return np.clip(spline(np.arange(n_frames)), 0.0, 1.0)


def make_pairing_clip(n_frames: int = 1000, contacts_per_frame: int = 300, seed: int = 0,
                      press: float = 0.003):
    """The synthetic clip the benchmark pairs."""
    import numpy as np
    import trimesh
    from scipy.spatial import cKDTree
    from scipy.spatial.transform import Rotation

    from ..clip.format import Clip
    from ..rig.demo_hands import demo_hand

    rng = np.random.default_rng(seed)
    rig = demo_hand("source_human", resolution=0.005)
    kin = rig.kinematics()
    lo, hi, rest = rig.lower, rig.upper, rig.rest_pose
    # fingers (every joint but the root and the wrist) wander within a third of their range
    finger = np.array([d.joint > 1 for d in rig.dofs])
    noise = _smooth_noise(rng, n_frames, rig.n_dofs)
    span = (hi - lo) / 3.0
    base = np.clip(rest, lo, hi - span)
    q = np.where(finger, base + noise * span, rest)

    hand = np.empty((n_frames, rig.surface.n_vertices, 3), dtype=np.float32)
    for f in range(n_frames):
        hand[f] = kin.skin(q[f])

    sphere = trimesh.creation.icosphere(subdivisions=4, radius=0.04)
    obj_v, obj_f = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    # the palm's underside (-Z) at the rest pose: put the sphere against it, ``press`` metres in
    rest_v = kin.skin(rest)
    palm = (np.abs(rest_v[:, 0]) < 0.02) & (np.abs(rest_v[:, 1] - 0.045) < 0.02)
    centre = np.array([0.0, 0.045, rest_v[palm, 2].min() - 0.04 + press])
    angles = _smooth_noise(rng, n_frames, 3, knots_every=120) - 0.5  # +-0.5 rad, slowly
    poses = np.repeat(np.eye(4)[None], n_frames, axis=0)
    poses[:, :3, :3] = Rotation.from_rotvec(angles).as_matrix()
    poses[:, :3, 3] = centre

    labels = np.zeros((n_frames, len(obj_v)), dtype=np.uint8)
    k = min(contacts_per_frame, len(obj_v))
    for f in range(n_frames):
        world = obj_v @ poses[f, :3, :3].T + poses[f, :3, 3]
        dist, _ = cKDTree(hand[f]).query(world)
        labels[f, np.argpartition(dist, k - 1)[:k]] = 22

    clip = Clip(
        fps=30.0,
        hand_faces=np.asarray(rig.surface.faces),
        hand_vertices=hand,
        object_vertices=obj_v,
        object_faces=obj_f,
        object_poses=poses,
        contact_labels=labels,
        source_rig="demo:source_human@0.005",
        object_name="icosphere",
        motion="benchmark",
        source="benchmark",
    )
    return clip


def run_pairing_benchmark(n_frames: int = 1000, contacts_per_frame: int = 300, seed: int = 0,
                          pin_one_core: bool = True) -> dict:
    """Build the synthetic clip, time :func:`pair_contacts` over it and return the figures.

    With ``pin_one_core`` (Linux) the process is confined to one CPU while timing, so embree's
    own worker threads cannot spread the BVH builds over several cores; the affinity is
    restored afterwards."""
    threads = _single_thread_env()
    from ..pairing import pair_contacts

    build_start = time.perf_counter()
    clip = make_pairing_clip(n_frames, contacts_per_frame, seed)
    build_s = time.perf_counter() - build_start

    pinned = None
    old_affinity = None
    if pin_one_core and hasattr(os, "sched_setaffinity"):
        old_affinity = os.sched_getaffinity(0)
        pinned = min(old_affinity)
        os.sched_setaffinity(0, {pinned})
    try:
        pair_contacts(clip, frames=range(min(5, n_frames)))  # warm up imports and embree
        start = time.perf_counter()
        pairs = pair_contacts(clip)
        seconds = time.perf_counter() - start
    finally:
        if old_affinity is not None:
            os.sched_setaffinity(0, old_affinity)

    summary = pairs.summary()
    contacts = summary["contacts"]
    return {
        "frames": n_frames,
        "contacts_per_frame": contacts_per_frame,
        "contacts": contacts,
        "hand_vertices": int(clip.hand_vertices.shape[1]),
        "hand_faces": int(len(clip.hand_faces)),
        "object_vertices": int(len(clip.object_vertices)),
        "seconds": seconds,
        "ms_per_frame": 1e3 * seconds / max(n_frames, 1),
        "contacts_per_second": contacts / seconds if seconds > 0 else float("inf"),
        "pinned_cpu": pinned,
        "threads": threads,
        "clip_build_seconds": build_s,
        "summary": summary,
    }
