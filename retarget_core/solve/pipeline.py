"""The retargeting pipeline (paper section "Motion Retargeting" and its appendix): pairing,
transfer, root-only pass, full-pose pass, filtering, acceleration refinement, spline fit.

Frames of the full pass are independent (never seeded from their neighbours), so they run in
a process pool; every worker builds its own solver objects (nlopt and potpourri3d objects do
not pickle) from plain arrays sent once when it starts. With ``config.dask_scheduler`` set the
same frame chunks run on a Dask ``distributed`` cluster instead (:class:`DaskFrameRunner`).
"""

from __future__ import annotations

import threading
import time
import uuid
from collections import OrderedDict
from concurrent.futures import CancelledError, ProcessPoolExecutor, as_completed
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from threadpoolctl import threadpool_limits

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


def _init_worker(problem: Problem, state: dict | None = None) -> dict:
    """Build the solver objects of ``problem`` into ``state`` (default this process's)."""
    # The solver's matrices are small (54 x a few thousand at most): a second BLAS thread per
    # worker only fights the other workers for the cores (measured: the whole bench 44 s with
    # one thread per worker, 80 s with two).
    threadpool_limits(limits=1)
    state = _WORKER if state is None else state
    state["problem"] = problem
    state["objective"] = problem.objective()
    # the baselines solve the fingers with their own objective under the root pass's root
    state["finger_objective"] = (state["objective"] if problem.config.method == "contacts"
                                 else problem.finger_objective())
    return state


# Dask worker side. A Dask worker runs tasks in threads and the objectives are stateful
# (set_frame, focus_samples), so every thread keeps its own solver objects, a few problems
# deep (keyed by the run's token) so that concurrent runs sharing a cluster do not rebuild
# them on every chunk.
_DASK_LOCAL = threading.local()
_DASK_CACHED_PROBLEMS = 2


def _dask_state(token: str, problem: Problem) -> dict:
    cache = getattr(_DASK_LOCAL, "states", None)
    if cache is None:
        cache = _DASK_LOCAL.states = OrderedDict()
    state = cache.get(token)
    if state is None:
        state = cache[token] = _init_worker(problem, {})
        while len(cache) > _DASK_CACHED_PROBLEMS:
            cache.popitem(last=False)
    cache.move_to_end(token)
    return state


def _dask_task(token: str, problem: Problem, function, *args):
    """One chunk on a Dask worker: ``function`` (:func:`_solve_frames` or
    :func:`_solve_sequence`) with this thread's solver objects for the run ``token``."""
    return function(*args, state=_dask_state(token, problem))


def _solve_sequence(frames, seed, state: dict | None = None):
    """Root-only solves of consecutive ``frames``, each seeded from the previous solution (a
    failed frame keeps its seed and passes it on). ``state``: the solver objects (as built by
    :func:`_init_worker`; default this process's)."""
    out = []
    for f in frames:
        (_, q, evals, error), = _solve_frames([f], [seed], True, state=state)
        if not error:
            seed = q
        out.append((int(f), seed, evals, error))
    return out


def _solve_frames(frames, seeds, root_only: bool, keyed: bool = False, state: dict | None = None):
    """Solve ``frames`` from ``seeds`` (F, D). ``keyed``: the prior pulls toward the seed (the
    paper's "previously existing keyed value at frame f": the filtered or interpolated value
    in the later passes) instead of the rest pose, so a re-solve stays near the smooth key
    where the data allow it rather than returning to the same spike. ``state``: as in
    :func:`_solve_sequence`. Returns [(frame, q (D,), evaluations, error)]."""
    state = _WORKER if state is None else state
    problem: Problem = state["problem"]
    objective: FrameObjective = state["objective"] if root_only else state["finger_objective"]
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
    """Solves batches of independent frames, in-process (workers = 1) or in a process pool.

    ``workers`` also cuts the root-only pass into that many sequences (see
    :func:`solve_trajectory`); ``slots`` is how many chunks can run at once (chunk sizing
    only, which never changes a result)."""

    def __init__(self, problem: Problem, workers: int):
        self.workers = max(1, int(workers))
        self.slots = self.workers
        self.pool = None
        if self.workers > 1:
            self.pool = ProcessPoolExecutor(self.workers, initializer=_init_worker, initargs=(problem,))
        else:
            _init_worker(problem)

    @property
    def parallel(self) -> bool:
        return self.pool is not None

    def _submit(self, function, *args):
        return self.pool.submit(function, *args)

    def _as_completed(self, futures):
        return as_completed(futures)

    def _result(self, future, function, args):
        """The result of ``future`` (``function(*args)``), which has completed."""
        return future.result()

    def _run(self, function, calls, total: int, progress: Progress | None, stage: str) -> list:
        """``function(*args)`` for every ``args`` in ``calls`` (each returns a list of per-frame
        tuples); the lists concatenated in call order. ``progress(stage, frames done, total)``
        after every chunk, in the order they complete."""
        if not self.parallel:
            results, done = [], 0
            for args in calls:
                part = function(*args)
                results += part
                done += len(part)
                if progress:
                    progress(stage, done, total)
            return results
        futures = {self._submit(function, *args): k for k, args in enumerate(calls)}
        parts = [None] * len(futures)
        done = 0
        for fut in self._as_completed(list(futures)):
            k = futures[fut]
            part = self._result(fut, function, calls[k])
            parts[k] = part
            done += len(part)
            if progress:
                progress(stage, done, total)
        return [r for part in parts for r in part]

    def solve(self, frames, seeds, *, root_only=False, keyed=False, progress: Progress | None = None,
              stage: str = ""):
        """Solve ``frames`` (F,) independently from ``seeds`` (F, D); [(frame, q, evaluations,
        error)] in frame order."""
        frames = np.asarray(frames, dtype=np.int64)
        chunk = max(4, len(frames) // (self.slots * 8) + 1) if self.parallel else 16
        calls = [(frames[k:k + chunk], seeds[k:k + chunk], root_only, keyed) for k in range(0, len(frames), chunk)]
        return self._run(_solve_frames, calls, len(frames), progress, stage)

    def solve_sequences(self, starts, seeds, n_frames: int, *, progress: Progress | None = None, stage: str = ""):
        """Root-only pass over frames [starts[k], starts[k+1]) each, sequentially within a
        sequence from seeds[k], sequences in parallel."""
        bounds = list(starts) + [n_frames]
        calls = [(np.arange(bounds[k], bounds[k + 1]), seeds[k]) for k in range(len(starts))]
        return self._run(_solve_sequence, calls, n_frames, progress, stage)

    def close(self):
        if self.pool is not None:
            self.pool.shutdown()


#: Seconds to wait for a Dask scheduler to answer.
DASK_CONNECT_TIMEOUT = 10.0
#: Times a chunk whose function raised is re-run (a chunk whose worker died is always re-run
#: elsewhere, up to the scheduler's ``distributed.scheduler.allowed-failures``).
DASK_RETRIES = 3


def connect_dask(address: str, timeout: float | None = None):
    """A ``distributed.Client`` connected to the scheduler at ``address`` (``tcp://HOST:PORT``);
    :class:`InputError` naming ``dask_scheduler`` when it cannot be reached within ``timeout``
    seconds (default :data:`DASK_CONNECT_TIMEOUT`)."""
    try:
        from distributed import Client
    except ImportError as err:  # a declared dependency, but say what is missing
        raise InputError(f"needs the 'distributed' package ({err})", element="dask_scheduler") from None
    timeout = DASK_CONNECT_TIMEOUT if timeout is None else timeout
    try:
        return Client(address, timeout=timeout, set_as_default=False)
    except (OSError, TimeoutError) as err:
        raise InputError(f"cannot connect to the Dask scheduler at {address} within {timeout:g} s: {err}",
                         element="dask_scheduler") from None


class DaskFrameRunner(FrameRunner):
    """:class:`FrameRunner` whose chunks run on a Dask cluster. The problem is scattered once
    per run (a copy on every worker then present, so losing one worker loses no copy); each
    worker thread builds its solver objects once per run (:func:`_dask_state`). Tasks are
    impure: a fresh key per submission, so a re-submitted chunk never meets the key of the one
    it replaces and two runs never share a result; a chunk that raised is retried."""

    def __init__(self, problem: Problem, workers: int, client):
        self.workers = max(1, int(workers))
        self.pool = None
        self.client = client
        self.token = uuid.uuid4().hex
        self.problem = problem
        try:
            try:
                client.wait_for_workers(1, timeout=DASK_CONNECT_TIMEOUT)
            except TimeoutError:
                raise InputError(f"the Dask scheduler at {client.scheduler.address} has no workers after "
                                 f"{DASK_CONNECT_TIMEOUT:g} s", element="dask_scheduler") from None
            self._scatter()
        except BaseException:
            client.close()
            raise
        # chunk for the cluster's threads when it has more than `workers`
        self.slots = max(self.workers, sum(client.nthreads().values()))

    def _scatter(self):
        self._problem = self.client.scatter(self.problem, broadcast=True, hash=False)

    @property
    def parallel(self) -> bool:
        return True

    def _submit(self, function, *args):
        if self._problem.status not in ("pending", "finished"):
            self._scatter()  # every copy lost (all workers holding it died): send it again
        return self.client.submit(_dask_task, self.token, self._problem, function, *args,
                                  retries=DASK_RETRIES, pure=False)

    def _result(self, future, function, args):
        # A dead worker's chunks are re-run by the scheduler itself. Only when every copy of
        # the scattered problem is gone (all workers holding it died) are the chunks that
        # need it cancelled ("lost dependencies"; also on a scheduler restart): re-run them,
        # sending the problem again (_submit).
        for attempt in range(DASK_RETRIES + 1):
            try:
                return future.result()
            except CancelledError:  # distributed's FutureCancelledError derives from it
                if attempt == DASK_RETRIES:
                    raise
                future = self._submit(function, *args)

    def _as_completed(self, futures):
        from distributed import as_completed as dask_as_completed

        return dask_as_completed(futures, loop=self.client.loop)  # not the default client's loop

    def close(self):
        self._problem = None
        self.client.close()


def make_frame_runner(problem: Problem, config: RetargetConfig, client=None) -> FrameRunner:
    """The runner for ``config``: on the Dask cluster of ``client`` (connected to
    ``config.dask_scheduler``; connected here when not given), else local."""
    if config.dask_scheduler:
        return DaskFrameRunner(problem, config.workers, client or connect_dask(config.dask_scheduler))
    return FrameRunner(problem, config.workers)


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

    # connect first: an unreachable scheduler is reported before pairing and transfer
    client = connect_dask(config.dask_scheduler) if config.dask_scheduler else None
    runner = None
    # One BLAS / OpenMP thread here and in the workers forked from here (see _init_worker).
    limits = threadpool_limits(limits=1)
    try:
        timings = {}
        t0 = time.perf_counter()
        if pairs is None:
            pairs = pair_contacts(clip)
        timings["pairing"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        transferred = transfer_clip(pairs, source, target, annotations, workers=config.workers,
                                   cache_dir=config.atlas_cache or None)
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
        runner = make_frame_runner(problem, config, client)
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
        limits.restore_original_limits()
        if runner is not None:
            runner.close()
        elif client is not None:
            client.close()
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
