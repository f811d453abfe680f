"""A real job service on 127.0.0.1: ``handretarget serve`` in its own process, driven over HTTP
with the standard-library client of dcc_client/."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dcc_client.client import RetargetClient, reachable

RES = 0.004
# few evaluations, a short refinement: fast, not accurate
FAST = {"solver.maxeval": 15, "solver.root_maxeval": 10, "refinement.max_iterations": 2}
CLI = [sys.executable, "-c", "import sys; from retarget_core.cli import main; sys.exit(main())"]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Service:
    """``handretarget serve`` on a free port over ``data_dir``; restartable."""

    def __init__(self, data_dir: Path, *args: str):
        self.data_dir, self.args = Path(data_dir), list(args)
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.proc = None
        self.log = self.data_dir.parent / f"{self.data_dir.name}-server.log"

    def start(self, timeout: float = 60.0) -> "Service":
        with self.log.open("ab") as log:
            self.proc = subprocess.Popen([*CLI, "serve", "--data-dir", str(self.data_dir), "--port", str(self.port),
                                          *self.args], stdout=log, stderr=subprocess.STDOUT)
        deadline = time.monotonic() + timeout
        while not reachable(self.url):
            if self.proc.poll() is not None:
                raise RuntimeError(f"the service exited: {self.log.read_text()[-2000:]}")
            if time.monotonic() > deadline:
                raise TimeoutError("the service did not answer /v1/health")
            time.sleep(0.2)
        return self

    def token(self, name: str) -> str:
        out = subprocess.run([*CLI, "token", "create", name, "--data-dir", str(self.data_dir)], check=True,
                             capture_output=True, text=True)
        return out.stdout.strip()

    def client(self, name: str) -> RetargetClient:
        return RetargetClient(self.url, self.token(name), timeout=120)

    def kill9(self) -> None:
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait()

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGINT)  # uvicorn's graceful shutdown stops the job runner
            try:
                self.proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        # job processes of a killed service stop themselves; make sure none outlives the test
        for pid in _job_processes(self.data_dir):
            try:
                os.killpg(pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass


def _job_processes(data_dir: Path) -> list[int]:
    """Job processes of the service over ``data_dir`` (their --settings JSON names it)."""
    pids, needle = [], json.dumps(str(Path(data_dir).resolve())).encode()
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit():
            continue
        try:
            cmd = (proc / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"server.job_process" in cmd and any(needle in part for part in cmd):
            pids.append(int(proc.name))
    return pids


@pytest.fixture(scope="session")
def inputs(tmp_path_factory):
    """A short demo clip (46 frames), a coarse target rig as USD and its proposed annotations."""
    from retarget_core.clip.demo import make_demo_clip, source_rig
    from retarget_core.rig.demo_hands import demo_hand
    from retarget_core.rig.io import save_rig
    from retarget_core.transfer.annotations import save_annotations
    from retarget_core.transfer.propose import propose_annotations

    folder = tmp_path_factory.mktemp("service_inputs")
    source, target = source_rig(RES), demo_hand("human_alt", RES)
    clip = make_demo_clip("bottle_pick_place", time_scale=0.05, resolution=RES, rig=source)
    clip.save(folder / "clip.npz")
    save_rig(target, folder / "target.usda")
    save_annotations(propose_annotations(source, target), folder / "annotations.json")
    return dict(folder=folder, clip=folder / "clip.npz", rig=folder / "target.usda",
                annotations=folder / "annotations.json", source=source, target=target)


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    svc = Service(tmp_path_factory.mktemp("svc") / "data", "--job-slots", "2").start()
    yield svc
    svc.stop()


def upload_inputs(client: RetargetClient, inputs) -> dict:
    return {k: client.upload(kind, inputs[k])["id"]
            for k, kind in (("clip", "clip"), ("rig", "rig"), ("annotations", "annotations"))}
