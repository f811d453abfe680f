"""How a run executes, kept apart from what it computes.

:class:`Executor` says where the frame solves of the passes run (in-process, a local process
pool, or a Dask ``distributed`` cluster), where built contact-transfer atlases are cached, who
hears progress, and how many BLAS threads a frame solve may use. None of it changes the result:
:func:`retarget_core.pipeline.retarget` gives the same DOF values with any executor (the
frames a pass sends out are cut by the data, never by the worker count).

A runner (:meth:`Executor.frame_runner`) solves batches of independent frames of one
:class:`~retarget_core.solve.problem.Problem`; every worker builds its own solver objects from
the plain problem sent to it once (nlopt and potpourri3d objects do not pickle).
"""

from __future__ import annotations

import os
import threading
import uuid
from collections import OrderedDict
from concurrent.futures import CancelledError, ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from .errors import InputError
from .solve.problem import (Problem, build_solver_state, frame_systems, frame_values, solve_frames,
                            solve_root_sequence, trace_branch)

Progress = Callable[[str, int, int], None]

#: Frames per task in-process; a pool gets about 8 tasks per slot (at least 4 frames each).
#: Only how work is batched, never what is computed.
CHUNK_FRAMES = 16
#: Seconds to wait for a Dask scheduler to answer.
DASK_CONNECT_TIMEOUT = 10.0
#: Times a chunk whose function raised is re-run (a chunk whose worker died is always re-run
#: elsewhere, up to the scheduler's ``distributed.scheduler.allowed-failures``).
DASK_RETRIES = 3


def default_workers() -> int:
    """The CPU count: the command line's and the service's default pool size."""
    return os.cpu_count() or 1


@dataclass
class Executor:
    """Where and how a run's work is done. ``workers``: frame solves at once in a local process
    pool (1 = in this process). ``dask_scheduler``: ``"tcp://HOST:PORT"`` runs the frame chunks
    on that Dask cluster instead ("" = local). ``atlas_cache``: a folder where built atlases are
    kept across runs and processes (None = in memory only). ``progress(stage, done, total)``:
    called as stages advance. ``blas_threads``: BLAS / OpenMP threads per frame solve."""

    workers: int = 1
    dask_scheduler: str = ""
    atlas_cache: str | os.PathLike | None = None
    progress: Progress | None = None
    blas_threads: int = 1

    def __post_init__(self):
        from .solve.config import check_dask_address

        if isinstance(self.workers, bool) or not isinstance(self.workers, int) or self.workers < 1:
            raise InputError(f"must be a positive integer, got {self.workers!r}", element="executor.workers")
        if isinstance(self.blas_threads, bool) or not isinstance(self.blas_threads, int) or self.blas_threads < 1:
            raise InputError(f"must be a positive integer, got {self.blas_threads!r}",
                             element="executor.blas_threads")
        check_dask_address(self.dask_scheduler, "executor.dask_scheduler")
        if self.atlas_cache is not None:
            if not isinstance(self.atlas_cache, (str, os.PathLike)):
                raise InputError(f"expected a folder path, got {type(self.atlas_cache).__name__} {self.atlas_cache!r}",
                                 element="executor.atlas_cache")
            if "\0" in str(self.atlas_cache):
                raise InputError("a folder path must not contain a NUL character", element="executor.atlas_cache")

    def report(self, stage: str, done: int, total: int) -> None:
        if self.progress is not None:
            self.progress(stage, done, total)

    @property
    def cache_dir(self) -> Path | None:
        return None if self.atlas_cache in (None, "") else Path(self.atlas_cache).expanduser()

    def describe(self) -> dict:
        """The executor as plain data, for provenance (result.json, the USD layer)."""
        return {"workers": self.workers, "dask_scheduler": self.dask_scheduler,
                "atlas_cache": "" if self.cache_dir is None else str(self.cache_dir),
                "blas_threads": self.blas_threads}

    def connect(self):
        """The Dask client when ``dask_scheduler`` is set (connected now, so an unreachable
        scheduler is reported before any work), else None."""
        return connect_dask(self.dask_scheduler) if self.dask_scheduler else None

    def frame_runner(self, problem: Problem, client=None) -> "FrameRunner":
        """A runner for ``problem``'s frames: on the Dask cluster of ``client`` (connected to
        ``dask_scheduler`` here when not given), else local. Close it (or use ``with``)."""
        if self.dask_scheduler:
            return DaskFrameRunner(problem, self, client or connect_dask(self.dask_scheduler))
        return FrameRunner(problem, self)


# ---- worker side ------------------------------------------------------------------------------
_WORKER: dict = {}


def _init_worker(problem: Problem, blas_threads: int) -> None:
    _WORKER.clear()
    _WORKER.update(build_solver_state(problem, blas_threads))


def _pool_task(function, *args):
    """One chunk in a pool worker (or in-process): ``function(state, *args)``."""
    return function(_WORKER, *args)


# A Dask worker runs tasks in threads and the objectives are stateful (set_frame,
# focus_samples), so every thread keeps its own solver objects, a few problems deep (keyed by
# the run's token) so that concurrent runs sharing a cluster do not rebuild them every chunk.
_DASK_LOCAL = threading.local()
_DASK_CACHED_PROBLEMS = 2


def _dask_task(token: str, problem: Problem, blas_threads: int, function, *args):
    """One chunk on a Dask worker thread, with that thread's solver objects for run ``token``."""
    cache = getattr(_DASK_LOCAL, "states", None)
    if cache is None:
        cache = _DASK_LOCAL.states = OrderedDict()
    state = cache.get(token)
    if state is None:
        state = cache[token] = build_solver_state(problem, blas_threads)
        while len(cache) > _DASK_CACHED_PROBLEMS:
            cache.popitem(last=False)
    cache.move_to_end(token)
    return function(state, *args)


# ---- runners ----------------------------------------------------------------------------------
class FrameRunner:
    """Solves batches of frames in-process (``workers`` = 1) or in a local process pool."""

    def __init__(self, problem: Problem, executor: Executor):
        self.executor = executor
        self.pool = None
        self.slots = executor.workers  # chunks that can run at once (sizing only)
        if executor.workers > 1:
            self.pool = ProcessPoolExecutor(executor.workers, initializer=_init_worker,
                                            initargs=(problem, executor.blas_threads))
        else:
            _init_worker(problem, executor.blas_threads)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    def _submit(self, function, *args):
        return self.pool.submit(_pool_task, function, *args)

    def _as_completed(self, futures):
        return as_completed(futures)

    def _result(self, future, function, args):
        return future.result()

    def _run(self, function, calls, total: int, stage: str) -> list:
        """``function(state, *args)`` for every ``args`` in ``calls`` (each returns a list of
        per-frame tuples); the lists concatenated in call order, whatever order they finish in."""
        done = 0
        if self.pool is None and not isinstance(self, DaskFrameRunner):
            results = []
            for args in calls:
                part = function(_WORKER, *args)
                results += part
                done += len(part)
                if stage:
                    self.executor.report(stage, done, total)
            return results
        futures = {self._submit(function, *args): k for k, args in enumerate(calls)}
        parts = [None] * len(futures)
        for fut in self._as_completed(list(futures)):
            k = futures[fut]
            parts[k] = self._result(fut, function, calls[k])
            done += len(parts[k])
            if stage:  # None: the caller reports its own progress (passes that call many times)
                self.executor.report(stage, done, total)
        return [r for part in parts for r in part]

    def solve(self, frames, seeds, *, stage: str, keyed: bool = False, label: str = "") -> list:
        """Solve ``frames`` (F,) independently from ``seeds`` (F, D) with the objective of
        ``stage`` ("root" / "fingers"); [(frame, q, evaluations, error)] in frame order.
        ``label``: the progress stage name."""
        return self._run(solve_frames, self._chunks(frames, seeds, stage, keyed), len(frames), label or stage)

    def solve_root_sequences(self, segments, seeds, *, label: str = "root pass") -> list:
        """The root-only pass over ``segments`` (a list of consecutive frame arrays), each solved
        sequentially from its seed in ``seeds``, the segments in parallel."""
        calls = [(np.asarray(frames, dtype=np.int64), seed) for frames, seed in zip(segments, seeds)]
        return self._run(solve_root_sequence, calls, sum(len(s) for s in segments), label)

    def trace_branches(self, runs, seeds, currents, *, label: str | None = None) -> list:
        """:func:`~retarget_core.solve.problem.trace_branch` over each run of ``runs`` (frame
        arrays) from its seed, against its frames' ``currents``; the runs in parallel, each
        sequential (so the result does not depend on the worker count)."""
        calls = [(np.asarray(r, dtype=np.int64), np.asarray(s, dtype=np.float64), np.asarray(c, dtype=np.float64))
                 for r, s, c in zip(runs, seeds, currents)]
        return self._run(trace_branch, calls, sum(len(r) for r in runs), label)

    def _chunks(self, frames, qs, *extra):
        """Calls of (frames, qs (F, D), *extra) in chunks sized for the workers."""
        frames = np.asarray(frames, dtype=np.int64)
        qs = np.asarray(qs, dtype=np.float64)
        chunk = CHUNK_FRAMES if self.pool is None and self.slots == 1 else max(4, len(frames) // (self.slots * 8) + 1)
        return [(frames[k:k + chunk], qs[k:k + chunk], *extra) for k in range(0, len(frames), chunk)]

    def systems(self, frames, qs, *, label: str | None = None) -> list:
        """:func:`~retarget_core.solve.problem.frame_systems` of ``frames`` at poses ``qs``
        (F, D), in frame order."""
        return self._run(frame_systems, self._chunks(frames, qs), len(frames), label)

    def values(self, frames, qs, *, label: str | None = None) -> list:
        """:func:`~retarget_core.solve.problem.frame_values` of ``frames`` at ``qs`` (F, D)."""
        return self._run(frame_values, self._chunks(frames, qs), len(frames), label)

    def close(self):
        if self.pool is not None:
            self.pool.shutdown()
            self.pool = None


def connect_dask(address: str, timeout: float | None = None):
    """A ``distributed.Client`` connected to the scheduler at ``address`` (``tcp://HOST:PORT``);
    :class:`InputError` naming ``executor.dask_scheduler`` when it cannot be reached within
    ``timeout`` seconds (default :data:`DASK_CONNECT_TIMEOUT`)."""
    try:
        from distributed import Client
    except ImportError as err:  # a declared dependency, but say what is missing
        raise InputError(f"needs the 'distributed' package ({err})", element="executor.dask_scheduler") from None
    timeout = DASK_CONNECT_TIMEOUT if timeout is None else timeout
    try:
        return Client(address, timeout=timeout, set_as_default=False)
    except (OSError, TimeoutError) as err:
        raise InputError(f"cannot connect to the Dask scheduler at {address} within {timeout:g} s: {err}",
                         element="executor.dask_scheduler") from None


class DaskFrameRunner(FrameRunner):
    """:class:`FrameRunner` whose chunks run on a Dask cluster. The problem is scattered once
    per run (a copy on every worker then present, so losing one worker loses no copy); each
    worker thread builds its solver objects once per run. Tasks are impure: a fresh key per
    submission, so a re-submitted chunk never meets the key of the one it replaces and two runs
    never share a result; a chunk that raised is retried."""

    def __init__(self, problem: Problem, executor: Executor, client):
        self.executor = executor
        self.pool = None
        self.client = client
        self.token = uuid.uuid4().hex
        self.problem = problem
        try:
            try:
                client.wait_for_workers(1, timeout=DASK_CONNECT_TIMEOUT)
            except TimeoutError:
                raise InputError(f"the Dask scheduler at {client.scheduler.address} has no workers after "
                                 f"{DASK_CONNECT_TIMEOUT:g} s", element="executor.dask_scheduler") from None
            self._scatter()
        except BaseException:
            client.close()
            raise
        self.slots = max(executor.workers, sum(client.nthreads().values()))

    def _scatter(self):
        self._problem = self.client.scatter(self.problem, broadcast=True, hash=False)

    def _submit(self, function, *args):
        if self._problem.status not in ("pending", "finished"):
            self._scatter()  # every copy lost (all workers holding it died): send it again
        return self.client.submit(_dask_task, self.token, self._problem, self.executor.blas_threads, function,
                                  *args, retries=DASK_RETRIES, pure=False)

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
