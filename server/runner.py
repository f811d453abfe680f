"""Runs queued jobs, each in its own process, and keeps them durable.

One thread in the service claims queued jobs round-robin across owners (up to ``job_slots`` at
once; see :meth:`Store.claim_next_job`) and
starts ``python -m server.job_process`` for each in a new process group, so a cancel or a
restart can stop the job with every process of its pool (the pool's workers are forked by the
job process and stay in its group; when the job process itself dies, the runner kills what is
left of its group before reaping it). At start-up, jobs the store still calls ``running`` (the
service was stopped or killed mid-job) get their leftover processes stopped and go back to the
queue without counting that attempt (the service went away, not the job); a job whose own
process dies is tried at most ``max_attempts`` times.
"""

from __future__ import annotations

import logging
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

from .job_process import DISK_FULL_STAGE
from .schemas import JobState
from .settings import Settings
from .storage import JobRow, Store

log = logging.getLogger("server.runner")

#: Seconds the runner claims no job after one was queued again because the disk was full.
DISK_FULL_BACKOFF_S = 30.0


def _alive_job_process(pid: int | None, job_id: str) -> bool:
    """Whether ``pid`` is still a job process of ``job_id`` (and not a reused pid)."""
    if not pid:
        return False
    try:
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
    except OSError:
        return False
    return b"server.job_process" in cmdline and job_id.encode() in cmdline


def _group_members(pgid: int) -> list[int]:
    """Pids of the processes in process group ``pgid`` (from /proc/PID/stat)."""
    members = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            stat = (proc / "stat").read_text()
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()  # after "pid (comm) ": state ppid pgrp ...
        if len(fields) > 2 and int(fields[2]) == pgid:
            members.append(int(proc.name))
    return members


def _leftover_job_group(pgid: int | None, job_id: str) -> bool:
    """Whether process group ``pgid`` still holds processes of job ``job_id``: its leader, or
    the pool workers it forked (their command line is the job process's)."""
    if not pgid:
        return False
    for pid in _group_members(pgid):
        try:
            cmdline = Path(f"/proc/{pid}/cmdline").read_bytes()
        except OSError:
            continue
        if (b"server.job_process" in cmdline and job_id.encode() in cmdline) or b"multiprocessing" in cmdline:
            return True
    return False


def _stop_groups(pids, grace: float = 2.0) -> None:
    """SIGTERM the process groups led by ``pids`` (all at once), SIGKILL what is left after
    ``grace`` s."""
    pids = list(pids)
    for sig, wait in ((signal.SIGTERM, grace), (signal.SIGKILL, 0.0)):
        for pid in pids:
            try:
                os.killpg(pid, sig)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + wait
        while time.monotonic() < deadline:
            alive = False
            for pid in pids:
                try:
                    os.killpg(pid, 0)
                    alive = True
                except ProcessLookupError:
                    pass
            if not alive:
                return
            time.sleep(0.05)


def _stop_group(pid: int, grace: float = 2.0) -> None:
    """SIGTERM the process group led by ``pid``, SIGKILL what is left after ``grace`` s."""
    _stop_groups([pid], grace)


def _exited(proc: subprocess.Popen) -> bool:
    """Whether the job process has exited, without reaping it: while it is an unreaped zombie
    its pid (its group's id) cannot be reused, so its group can still be killed safely."""
    try:
        return os.waitid(os.P_PID, proc.pid, os.WEXITED | os.WNOHANG | os.WNOWAIT) is not None
    except ChildProcessError:
        return True


class JobRunner:
    def __init__(self, store: Store, settings: Settings):
        self.store, self.settings = store, settings
        self.children: dict[str, subprocess.Popen] = {}
        self._hold_until = 0.0  # monotonic time before which no job is claimed (a full disk)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="job-runner", daemon=True)
        self.logs = store.paths.root / "logs"
        self.logs.mkdir(exist_ok=True)

    # ---- life cycle --------------------------------------------------------------------------
    def start(self) -> None:
        self.recover()
        self._thread.start()

    def alive(self) -> bool:
        return self._thread.is_alive()

    def stop(self) -> None:
        """Stop the loop; running jobs are stopped too and stay ``running`` in the store, so
        the next start re-runs them (the same path as after a crash)."""
        self._stop.set()
        self._thread.join(timeout=10)
        _stop_groups([proc.pid for proc in self.children.values()])
        for proc in self.children.values():
            proc.wait(timeout=10)
        self.children.clear()

    def recover(self) -> None:
        for job in self.store.jobs(states=(JobState.RUNNING,), limit=None):
            if _alive_job_process(job.pid, job.id) or _leftover_job_group(job.pid, job.id):
                _stop_group(job.pid)
            # the service went away, not the job: this attempt does not count
            self._requeue_or_fail(job, "the service stopped while the job was running", counted=False)
        # nothing else writes under tmp/ now (this service holds the data directory's lock and
        # serves no request yet; every job process is stopped): what is there was left by a
        # killed service (partial uploads, a killed job's output)
        for leftover in self.store.paths.tmp.iterdir():
            shutil.rmtree(leftover, ignore_errors=True) if leftover.is_dir() else leftover.unlink(missing_ok=True)

    def _requeue_or_fail(self, job: JobRow, why: str, counted: bool = True) -> None:
        running = (JobState.RUNNING,)
        if not counted and not job.cancel_requested:
            log.info("re-queueing job %s (%s; attempt not counted)", job.id, why)
            self.store.update_job(job.id, only_if_state=running, state=JobState.QUEUED, pid=None, stage="queued",
                                  progress=0.0, frames_done=0, attempts=max(job.attempts - 1, 0))
        elif job.cancel_requested:
            self.store.update_job(job.id, only_if_state=running, state=JobState.CANCELLED, pid=None,
                                  finished=time.time(), stage="cancelled")
        elif job.attempts >= self.settings.max_attempts:
            self.store.update_job(job.id, only_if_state=running, state=JobState.FAILED, pid=None,
                                  finished=time.time(), error=f"{why}; gave up after {job.attempts} attempts")
        else:
            log.info("re-queueing job %s (%s)", job.id, why)
            self.store.update_job(job.id, only_if_state=running, state=JobState.QUEUED, pid=None, stage="queued",
                                  progress=0.0, frames_done=0)

    # ---- the loop ----------------------------------------------------------------------------
    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                self._tick()
            except Exception:  # noqa: BLE001 - the loop must outlive one bad tick (e.g. a locked store)
                log.exception("job runner tick failed")
            self._stop.wait(0.1)

    def _tick(self) -> None:
        for job_id, proc in list(self.children.items()):
            job = self.store.job(job_id)
            if not _exited(proc):
                if job is not None and job.cancel_requested:
                    _stop_group(proc.pid)
                    proc.wait()
                    self.children.pop(job_id)
                    self.store.update_job(job_id, only_if_state=(JobState.RUNNING,), state=JobState.CANCELLED,
                                          pid=None, finished=time.time(), stage="cancelled")
                continue
            # the job process is gone (maybe killed): its pool workers go with it, then it is reaped
            try:
                os.killpg(proc.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
            proc.wait()
            self.children.pop(job_id)
            if job is not None and job.state == JobState.RUNNING:  # died without a final state
                self._requeue_or_fail(job, f"the job process exited with code {proc.returncode}")
            elif job is not None and job.state == JobState.QUEUED and job.stage == DISK_FULL_STAGE:
                # the disk was full: claim nothing for a while rather than fail jobs in a loop
                self._hold_until = time.monotonic() + DISK_FULL_BACKOFF_S
                log.error("the disk is full; no job is started for %g s", DISK_FULL_BACKOFF_S)
            self._prune_cache()
        if time.monotonic() < self._hold_until:
            return
        while len(self.children) < self.settings.job_slots and not self._stop.is_set():
            job = self.store.claim_next_job()
            if job is None:
                break
            self._spawn(job)

    def _prune_cache(self) -> None:
        from retarget_core.transfer.atlas import prune_atlas_cache

        removed, freed = prune_atlas_cache(self.store.paths.atlas_cache, self.settings.atlas_cache_bytes)
        if removed:
            log.info("atlas cache: removed %d files (%.0f MB)", removed, freed / 1e6)

    def _spawn(self, job: JobRow) -> None:
        # the job process gets the settings whole, with the data directory the store resolved
        settings = self.settings.model_copy(update={"data_dir": self.store.paths.root})
        cmd = [sys.executable, "-m", "server.job_process", "--job", job.id, "--parent", str(os.getpid()),
               "--settings", settings.model_dump_json()]
        with (self.logs / f"{job.id}.log").open("ab") as log_file:
            proc = subprocess.Popen(cmd, stdout=log_file, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                    start_new_session=True, cwd=str(Path(__file__).resolve().parent.parent))
        self.children[job.id] = proc
        self.store.update_job(job.id, only_if_state=(JobState.RUNNING,), pid=proc.pid)
        log.info("started job %s (attempt %d, pid %d)", job.id, job.attempts, proc.pid)
