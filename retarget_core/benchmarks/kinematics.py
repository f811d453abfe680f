"""Timing of forward kinematics plus analytic Jacobians of many surface points."""

from __future__ import annotations

import time

import numpy as np

from ..mesh.surface_points import SurfacePoints
from ..rig.demo_hands import demo_hand


def _time_call(fn, repeats: int) -> dict:
    for _ in range(min(50, repeats)):
        fn()
    samples = np.empty(repeats)
    for i in range(repeats):
        start = time.perf_counter()
        fn()
        samples[i] = time.perf_counter() - start
    ms = samples * 1e3
    return {"median_ms": float(np.median(ms)), "p10_ms": float(np.percentile(ms, 10)), "p90_ms": float(np.percentile(ms, 90))}


def run_kinematics_benchmark(hand: str = "source_human", n_points: int = 500, repeats: int = 2000,
                             resolution: float = 0.002, seed: int = 0) -> dict:
    """Time, per call and for ``n_points`` random surface points of a demo hand at a random
    in-limit pose: FK alone; FK + point positions and Jacobians; FK + points, normals and both
    Jacobians; FK + the vector-Jacobian product a solver uses. Returns the figures."""
    rig = demo_hand(hand, resolution=resolution)
    kin = rig.kinematics()
    rng = np.random.default_rng(seed)
    points = SurfacePoints(rng.integers(0, len(rig.surface.faces), n_points), rng.dirichlet([1, 1, 1], n_points))
    binding = kin.bind(points)
    q = rig.random_pose(rng)
    cotangent = rng.normal(size=(n_points, 3))

    def fk_points_jacobians():
        kin.points_jacobian(kin.pose(q), binding)

    def fk_points_normals_jacobians():
        pose = kin.pose(q)
        kin.points_jacobian(pose, binding)
        kin.normals_jacobian(pose, binding)

    def fk_vjp():
        kin.points_vjp(kin.pose(q), binding, cotangent)

    return {
        "hand": hand,
        "dofs": rig.n_dofs,
        "joints": rig.n_joints,
        "points": n_points,
        "surface_vertices": rig.surface.n_vertices,
        "fk": _time_call(lambda: kin.pose(q), repeats),
        "fk_points_jacobians": _time_call(fk_points_jacobians, repeats),
        "fk_points_normals_jacobians": _time_call(fk_points_normals_jacobians, repeats),
        "fk_points_vjp": _time_call(fk_vjp, repeats),
        "skin_all_vertices": _time_call(lambda: kin.skin(q), max(repeats // 10, 20)),
    }
