"""Real Dask clusters on 127.0.0.1 for tests: a ``dask scheduler`` and ``dask worker``
subprocesses (used by tests/test_dask.py and the service's Dask test)."""

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

distributed = pytest.importorskip("distributed")

DASK = Path(sys.executable).with_name("dask")


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Cluster:
    """A ``dask scheduler`` and ``dask worker`` subprocesses, each in its own process group
    (a worker is a nanny plus its worker process: killing the group kills both)."""

    def __init__(self, folder: Path):
        self.folder = folder
        self.address = ""
        self.procs: list[subprocess.Popen] = []
        self.workers: list[subprocess.Popen] = []
        self.scheduler = None
        self.client = None

    def start(self, n_workers: int):
        """Spawn the scheduler and ``n_workers`` workers; they start up in the background."""
        port = free_port()
        self.address = f"tcp://127.0.0.1:{port}"
        self.scheduler = self._spawn("scheduler", ["scheduler", "--host", "127.0.0.1", "--port", str(port),
                                                   "--no-dashboard"])
        for _ in range(n_workers):
            self.add_worker()

    def _spawn(self, name, args):
        log = open(self.folder / f"{name}-{len(self.procs)}.log", "wb")
        # scratch space (lock files, spilled data) in the test's folder, not the system temp dir
        # the whole transition log: a test reads the story of a full-pass chunk after the later
        # passes (coherence, curve polish) have run many small tasks
        env = dict(os.environ, DASK_TEMPORARY_DIRECTORY=str(self.folder / "scratch"),
                   DASK_DISTRIBUTED__ADMIN__LOW_LEVEL_LOG_LENGTH="1000000")
        proc = subprocess.Popen([str(DASK), *args], stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
                                cwd=self.folder, env=env)
        log.close()
        self.procs.append(proc)
        return proc

    def add_worker(self):
        proc = self._spawn("worker", ["worker", self.address, "--nworkers", "1", "--nthreads", "1", "--no-dashboard"])
        self.workers.append(proc)
        return proc

    def logs(self) -> str:
        return "\n".join(f"--- {p.name}\n{p.read_text(errors='replace')[-3000:]}"
                         for p in sorted(self.folder.glob("*.log")))

    def connect(self, n_workers: int, timeout: float = 90.0):
        """A client of this cluster once ``n_workers`` workers are running."""
        deadline = time.monotonic() + timeout
        while self.client is None:
            if self.scheduler.poll() is not None:
                pytest.fail(f"dask scheduler exited\n{self.logs()}")
            try:
                self.client = distributed.Client(self.address, timeout=5, set_as_default=False)
            except OSError:
                if time.monotonic() > deadline:
                    pytest.fail(f"dask scheduler not reachable\n{self.logs()}")
        try:
            if n_workers:
                self.client.wait_for_workers(n_workers, timeout=max(1.0, deadline - time.monotonic()))
        except TimeoutError:
            pytest.fail(f"fewer than {n_workers} dask workers\n{self.logs()}")
        return self.client

    def kill(self, proc: subprocess.Popen):
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        proc.wait(timeout=30)

    def close(self):
        try:
            if self.client is not None:
                self.client.close()
        finally:
            for proc in reversed(self.procs):
                try:
                    self.kill(proc)
                except Exception:  # still kill the others
                    pass
