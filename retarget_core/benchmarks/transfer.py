"""Timing of contact transfer: 1000 frames x 300 contacts onto a ~10k-vertex target."""

from __future__ import annotations

import time

import numpy as np

from ..mesh.surface_points import SurfacePoints
from ..rig.demo_hands import demo_hand
from ..transfer.atlas import get_atlas
from ..transfer.propose import propose_annotations


def run_transfer_benchmark(n_frames: int = 1000, contacts_per_frame: int = 300, target: str = "human_alt",
                           target_resolution: float = 0.0025, seed: int = 0) -> dict:
    """Set up the atlas of the demo source hand and ``target`` (timed apart), then transfer
    n_frames x contacts_per_frame source contacts in one call. Contacts are drawn on the
    source faces that lie within 1.5 cm of a landmark (where grasps touch: the palmar side)."""
    rng = np.random.default_rng(seed)
    source = demo_hand("source_human", resolution=0.004)
    target_rig = demo_hand(target, resolution=target_resolution)
    annotations = propose_annotations(source, target_rig)
    start = time.perf_counter()
    atlas = get_atlas(source.surface.vertices, source.surface.faces, target_rig.surface.vertices,
                      target_rig.surface.faces, annotations)
    setup = time.perf_counter() - start
    own = np.linalg.norm(atlas.source_coords[atlas.vertex_landmark, np.arange(source.surface.n_vertices)], axis=1)
    near_faces = np.nonzero((own[source.surface.faces] < 0.015).all(axis=1))[0]
    n = n_frames * contacts_per_frame
    points = SurfacePoints(rng.choice(near_faces, n), rng.dirichlet([1, 1, 1], n))
    start = time.perf_counter()
    result = atlas.transfer(points)
    seconds = time.perf_counter() - start
    return {
        "frames": n_frames,
        "contacts_per_frame": contacts_per_frame,
        "contacts": n,
        "target": target,
        "target_vertices": int(target_rig.surface.n_vertices),
        "landmarks": int(atlas.n_landmarks),
        "setup_seconds": setup,
        "transfer_seconds": seconds,
        "contacts_per_second": n / seconds,
        "dropped": int(result.dropped.sum()),
    }
