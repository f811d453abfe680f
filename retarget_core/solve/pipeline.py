"""The retargeting pipeline (paper section "Motion Retargeting" and its appendix): pairing,
transfer, root-only pass, full-pose pass, filtering, acceleration refinement, spline fit.

Frames of the full pass are independent (never seeded from their neighbours), so they run in
a process pool; every worker builds its own solver objects (nlopt and potpourri3d objects do
not pickle) from plain arrays sent once when it starts.
"""

from __future__ import annotations

import os
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from typing import Callable

import numpy as np

from ..clip.format import Clip
from ..clip.grasp import set_root_transform
from ..errors import InputError
from ..mesh.surface_points import SurfacePoints
from ..pairing.dense import ContactPairs, pair_contacts
from ..rig.model import Rig
from ..transfer.annotations import Annotations
from ..transfer.clip_transfer import transfer_clip
from .baselines import FingertipObjective, KeyvectorObjective, keyvector_beta
from .config import RetargetConfig
from .frame_solver import solve_frame
from .objective import FrameData, FrameObjective
from .targets import ContactTargets, MarkerTargets, contact_targets, marker_targets, scale_finger_markers

Progress = Callable[[str, int, int], None]


@dataclass
class PassReport:
    frames: int = 0
    evaluations: int = 0
    failed: list = field(default_factory=list)
    seconds: float = 0.0


@dataclass
class Problem:
    """Everything a worker needs, as plain data."""

    rig: Rig
    config: RetargetConfig
    markers: MarkerTargets
    contacts: ContactTargets
    object_poses: np.ndarray
    table_pose: np.ndarray | None
    table_half_extents: np.ndarray | None
    object_vertices: np.ndarray
    object_faces: np.ndarray

    def objective(self) -> FrameObjective:
        return FrameObjective(self.rig, self.config, self.markers.target_faces, self.markers.target_barycentric,
                              self.markers.pair_target, self.markers.pair_weight, self.table_pose,
                              self.table_half_extents, self.object_vertices, self.object_faces)

    def finger_objective(self):
        """The objective of the full-pose passes: the same as :meth:`objective` for the paper's
        method, a baseline's (:mod:`.baselines`) otherwise."""
        method = self.config.method
        if method == "contacts":
            return self.objective()
        m = self.markers
        common = dict(table_pose=self.table_pose, table_half_extents=self.table_half_extents,
                      object_vertices=self.object_vertices, object_faces=self.object_faces)
        if method == "fingertips":
            return FingertipObjective(self.rig, self.config, m.target_faces, m.target_barycentric, m.pair_target,
                                      m.pair_weight, m.names, **common)
        kin = self.rig.kinematics()
        rest_markers = kin.points(self.rig.rest_pose, kin.bind(SurfacePoints(m.target_faces, m.target_barycentric)))
        beta = keyvector_beta(rest_markers, m.pair_target, m.names, m.source_positions)
        return KeyvectorObjective(self.rig, self.config, m.target_faces, m.target_barycentric, m.pair_target,
                                  m.pair_weight, m.names, beta=beta, **common)

    def frame_data(self, f: int) -> FrameData:
        points, obj_p, obj_n = self.contacts.frame(f)
        return FrameData(self.markers.source_positions[f], points, obj_p, obj_n, self.object_poses[f])


# ---- worker side ------------------------------------------------------------------------------
_WORKER: dict = {}


def _init_worker(problem: Problem) -> None:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    _WORKER["problem"] = problem
    _WORKER["objective"] = problem.objective()
    # the baselines solve the fingers with their own objective under the root pass's root
    _WORKER["finger_objective"] = (_WORKER["objective"] if problem.config.method == "contacts"
                                   else problem.finger_objective())


def _solve_sequence(frames, seed):
    """Root-only solves of consecutive ``frames``, each seeded from the previous solution (a
    failed frame keeps its seed and passes it on)."""
    out = []
    for f in frames:
        (_, q, evals, error), = _solve_frames([f], [seed], True)
        if not error:
            seed = q
        out.append((int(f), seed, evals, error))
    return out


def _solve_frames(frames, seeds, root_only: bool, keyed: bool = False):
    """Solve ``frames`` from ``seeds`` (F, D). ``keyed``: the prior pulls toward the seed (the
    paper's "previously existing keyed value at frame f": the filtered or interpolated value
    in the later passes) instead of the rest pose, so a re-solve stays near the smooth key
    where the data allow it rather than returning to the same spike."""
    problem: Problem = _WORKER["problem"]
    objective: FrameObjective = _WORKER["objective"] if root_only else _WORKER["finger_objective"]
    cfg = problem.config.solver
    rig = problem.rig
    lower, upper = rig.lower, rig.upper
    root = np.array([d.joint == 0 for d in rig.dofs])
    if root_only:
        active = root
    elif problem.config.method != "contacts":
        active = ~root  # a baseline keeps the root of the root pass (the paper's "ground truth root")
    else:
        active = np.ones(rig.n_dofs, dtype=bool)
    out = []
    settings = dict(maxeval=cfg.root_maxeval if root_only else cfg.maxeval, xtol_rel=cfg.xtol_rel,
                    ftol_rel=cfg.ftol_rel, gradient=cfg.gradient, fd_step=cfg.fd_step,
                    kinds=[d.kind for d in rig.dofs], root_mask=[d.joint == 0 for d in rig.dofs],
                    algorithm=cfg.algorithm)
    rest = rig.rest_pose
    for f, seed in zip(frames, seeds):
        objective.set_frame(problem.frame_data(int(f)))
        objective.reference = np.asarray(seed, dtype=np.float64) if keyed else rest
        objective.focus_samples(seed)
        # the root pass starts from the previous frame's root: MMA alone is enough there
        sol = solve_frame(objective, seed, lower, upper, active,
                          warm_start_iterations=0 if root_only else cfg.warm_start_iterations, **settings)
        evaluations = sol.evaluations
        if sol.ok and objective.unseen_table_contact(sol.q):
            # a point that was far from the table at the seed ended inside it: polish with it
            objective.focus_samples(sol.q)
            polished = solve_frame(objective, sol.q, lower, upper, active, **settings)
            evaluations += polished.evaluations
            if polished.ok:
                sol = polished
        out.append((int(f), sol.q, evaluations, sol.error))
    return out


class FrameRunner:
    """Solves batches of independent frames, in-process (workers = 1) or in a process pool."""

    def __init__(self, problem: Problem, workers: int):
        self.workers = max(1, int(workers))
        self.pool = None
        if self.workers > 1:
            self.pool = ProcessPoolExecutor(self.workers, initializer=_init_worker, initargs=(problem,))
        else:
            _init_worker(problem)

    def solve(self, frames, seeds, *, root_only=False, keyed=False, progress: Progress | None = None,
              stage: str = ""):
        frames = np.asarray(frames, dtype=np.int64)
        results = []
        if self.pool is None:
            for k in range(0, len(frames), 16):
                results += _solve_frames(frames[k:k + 16], seeds[k:k + 16], root_only, keyed)
                if progress:
                    progress(stage, min(k + 16, len(frames)), len(frames))
        else:
            chunk = max(4, len(frames) // (self.workers * 8) + 1)
            futures = [self.pool.submit(_solve_frames, frames[k:k + chunk], seeds[k:k + chunk], root_only, keyed)
                       for k in range(0, len(frames), chunk)]
            done = 0
            for fut in futures:
                part = fut.result()
                results += part
                done += len(part)
                if progress:
                    progress(stage, done, len(frames))
        return results

    def solve_sequences(self, starts, seeds, n_frames: int, *, progress: Progress | None = None, stage: str = ""):
        """Root-only pass over frames [starts[k], starts[k+1]) each, sequentially within a
        sequence from seeds[k], sequences in parallel."""
        bounds = list(starts) + [n_frames]
        chunks = [(np.arange(bounds[k], bounds[k + 1]), seeds[k]) for k in range(len(starts))]
        if self.pool is None:
            results = []
            for frames, seed in chunks:
                results += _solve_sequence(frames, seed)
                if progress:
                    progress(stage, len(results), n_frames)
            return results
        futures = [self.pool.submit(_solve_sequence, frames, seed) for frames, seed in chunks]
        results = []
        for fut in futures:
            results += fut.result()
            if progress:
                progress(stage, len(results), n_frames)
        return results

    def close(self):
        if self.pool is not None:
            self.pool.shutdown()


# ---- driver -----------------------------------------------------------------------------------
def kabsch(source: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Rigid transform (4, 4) moving points ``source`` (N, 3) onto ``target`` (N, 3)."""
    cs, ct = source.mean(axis=0), target.mean(axis=0)
    h = (source - cs).T @ (target - ct)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T))
    r = vt.T @ np.diag([1, 1, d]) @ u.T
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = ct - r @ cs
    return m


@dataclass
class Trajectory:
    """Per-frame solutions of the passes and their reports."""

    q: np.ndarray
    unresolved: np.ndarray
    reports: dict
    timings: dict
    pairs: ContactPairs
    contacts: ContactTargets
    markers: MarkerTargets
    transferred_share: float


def solve_trajectory(clip: Clip, source: Rig, target: Rig, annotations: Annotations, config: RetargetConfig, *,
                     progress: Progress | None = None, pairs: ContactPairs | None = None) -> Trajectory:
    """Every pass up to (not including) the spline fit. Returns per-frame DOF values (T, D)."""
    from ..refine.trajectory import lowpass_and_remove_peaks, refine_trajectory

    timings = {}
    t0 = time.perf_counter()
    if pairs is None:
        pairs = pair_contacts(clip)
    timings["pairing"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    transferred = transfer_clip(pairs, source, target, annotations, workers=config.workers)
    markers = marker_targets(clip, source, target, annotations)
    if config.markers.scale_fingers:
        markers = scale_finger_markers(markers, source, target)
    contacts = contact_targets(clip, pairs, transferred.contacts, keep_source_gap=config.contacts.keep_source_gap)
    timings["transfer"] = time.perf_counter() - t0
    if len(markers.pair_target) < 3:
        raise InputError("at least three marker pairs are needed to place the hand", element="markers")

    problem = Problem(target, config, markers, contacts, clip.object_poses, clip.table_pose, clip.table_half_extents,
                      clip.object_vertices, clip.object_faces)
    if config.method != "contacts":
        problem.finger_objective()  # a baseline's missing markers are an input error, before any work
    n_frames, n_dofs = clip.n_frames, target.n_dofs
    rest = target.rest_pose
    reports = {}
    runner = FrameRunner(problem, config.workers)
    try:
        # Root-only pass: each frame seeded from the previous one, the first of each sequence
        # from a rigid fit of the target markers at rest onto that frame's source markers. The
        # clip is cut into one sequence per worker so the pass runs in parallel too.
        t0 = time.perf_counter()
        kin = target.kinematics()
        rest_markers = kin.points(rest, kin.bind(SurfacePoints(markers.target_faces, markers.target_barycentric)))
        root_now = kin.pose(rest).world[0]
        starts = np.unique(np.linspace(0, n_frames, runner.workers + 1).astype(int)[:-1])
        seeds = [set_root_transform(target, rest, kabsch(rest_markers[markers.pair_target],
                                                         markers.source_positions[s]) @ root_now) for s in starts]
        q_root = np.array([seeds[np.searchsorted(starts, f, side="right") - 1] for f in range(n_frames)])
        report = PassReport(frames=n_frames)
        if config.passes.root:
            for f, q, evals, error in runner.solve_sequences(starts, seeds, n_frames, progress=progress,
                                                             stage="root pass"):
                report.evaluations += evals
                if error:
                    report.failed.append((f, error))
                q_root[f] = q
        report.seconds = time.perf_counter() - t0
        reports["root"] = report
        timings["root pass"] = report.seconds

        # Full-pose pass: independent frames seeded from the root estimate.
        q = q_root.copy()
        if config.passes.full:
            t0 = time.perf_counter()
            q, report = _pass(runner, np.arange(n_frames), q_root, progress, "full pass")
            reports["full"] = report
            timings["full pass"] = report.seconds

        rot = target.kinematics().is_rotation
        if config.passes.filter and n_frames >= 8:
            t0 = time.perf_counter()
            ref = config.refinement
            filtered, changed = lowpass_and_remove_peaks(
                q, clip.fps, ref.lowpass_cutoff_hz, ref.peak_thresholds(rot), peak_window=ref.peak_window,
                order=ref.lowpass_order, change_tolerance=ref.resolve_tolerances(rot))
            frames = np.nonzero(changed)[0]
            if len(frames):
                q[frames], report = _pass(runner, frames, filtered, progress, "filter re-solve", keyed=True)
                reports["filter"] = report
            timings["filter"] = time.perf_counter() - t0

        unresolved = np.zeros((n_frames, n_dofs), dtype=bool)
        if config.passes.refine and n_frames >= 3:
            t0 = time.perf_counter()
            ref = config.refinement
            evals = {"n": 0}

            def resolve(frames, seeds):
                solved = runner.solve(frames, seeds, keyed=True, progress=progress, stage="refinement")
                evals["n"] += sum(r[2] for r in solved)
                out = np.array(seeds, dtype=np.float64)
                index = {int(f): i for i, f in enumerate(frames)}
                for f, qq, _, error in solved:
                    if not error:
                        out[index[f]] = qq
                return out

            q, refinement = refine_trajectory(q, clip.fps, rot, resolve, e_acc_angular=ref.e_acc_angular_si,
                                              e_acc_linear=ref.e_acc_linear_si, max_iterations=ref.max_iterations,
                                              patience=ref.patience)
            unresolved = refinement.unresolved
            reports["refine"] = refinement
            timings["refinement"] = time.perf_counter() - t0
    finally:
        runner.close()
    return Trajectory(q, unresolved, reports, timings, pairs, contacts, markers,
                      float(1 - transferred.contacts.dropped.mean()) if len(transferred.contacts.dropped) else 1.0)


def _pass(runner: FrameRunner, frames, seeds, progress, stage, keyed=False):
    t0 = time.perf_counter()
    solved = runner.solve(frames, seeds[frames], keyed=keyed, progress=progress, stage=stage)
    out = seeds[frames].copy()
    report = PassReport(frames=len(frames))
    index = {int(f): i for i, f in enumerate(frames)}
    for f, q, evals, error in solved:
        report.evaluations += evals
        if error:
            report.failed.append((f, error))
        else:
            out[index[f]] = q
    report.seconds = time.perf_counter() - t0
    return out, report
