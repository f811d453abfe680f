"""Process hygiene (issue 16, Build 4), against a real service on 127.0.0.1.

Findings covered (all measured on main at 328eb67):
- "killing a job process leaves its pool workers running (about 300 MB each)";
- "nothing locks the data directory (a second `serve` on it, even one that fails to bind its
  port, kills the running job, runs it twice at once and spends 2 of its 3 attempts)";
- "three service restarts during one valid job leave it failed for good";
- "SIGTERM with an SSE client attached: the port closes but the process is alive after 90 s".
"""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import threading
import time

from pathlib import Path

import pytest

from dcc_client.client import ServiceError

from .conftest import CLI, FAST, Service, _job_processes, free_port, upload_inputs

# a job that stays in its frame passes long enough to be interrupted (it is always cancelled)
LONG = FAST | {"solver.maxeval": 400, "solver.root_maxeval": 200, "refinement.max_iterations": 40}


def _group_members(pgid: int) -> list[int]:
    """Pids in process group ``pgid`` (read from /proc here, independent of the service's code)."""
    members = []
    for proc in Path("/proc").iterdir():
        try:
            stat = (proc / "stat").read_text() if proc.name.isdigit() else ""
        except OSError:
            continue
        if stat and int(stat[stat.rindex(")") + 2:].split()[2]) == pgid:
            members.append(int(proc.name))
    return members


def _running_with_pid(client, svc, job_id, timeout=120.0) -> int:
    """Wait until the job runs in a job process; its pid (the leader of its process group)."""
    deadline = time.monotonic() + timeout
    while True:
        job = client.job(job_id)
        pids = _job_processes(svc.data_dir)
        if job["state"] == "running" and pids:
            return min(pids)  # the job process; forked pool workers share its command line
        assert job["state"] in ("queued", "running") and time.monotonic() < deadline, job
        time.sleep(0.05)


def _leader(pids) -> int:
    """The process-group leader among a job process and its workers."""
    for pid in pids:
        try:
            if os.getpgid(pid) == pid:
                return pid
        except ProcessLookupError:
            continue
    raise AssertionError(f"no group leader among {pids}")


def test_killed_job_process_takes_its_pool_workers(tmp_path_factory, inputs):
    # finding: "killing a job process leaves its pool workers running"
    svc = Service(tmp_path_factory.mktemp("hyg_kill") / "data", "--workers", "2").start()
    try:
        c = svc.client("kim")
        job = c.submit(**upload_inputs(c, inputs), overrides=LONG, evaluate=False)
        _running_with_pid(c, svc, job["id"])
        deadline = time.monotonic() + 180
        while True:  # the pool exists once the frame passes start: the leader and 2 workers
            leader = _leader(_job_processes(svc.data_dir))
            members = _group_members(leader)
            if len(members) >= 3:
                break
            assert time.monotonic() < deadline, f"no pool workers appeared ({members})"
            time.sleep(0.1)
        os.kill(leader, signal.SIGKILL)  # the job process alone, not its group
        deadline = time.monotonic() + 5
        while _group_members(leader):
            assert time.monotonic() < deadline, f"pool workers outlived their job process: {_group_members(leader)}"
            time.sleep(0.1)
        c.cancel(job["id"])
    finally:
        svc.stop()


def test_second_serve_on_the_same_data_dir_exits_and_leaves_the_job_alone(tmp_path_factory, inputs):
    # finding: "nothing locks the data directory (a second `serve` on it ... kills the running job)"
    svc = Service(tmp_path_factory.mktemp("hyg_lock") / "data").start()
    try:
        c = svc.client("lee")
        job = c.submit(**upload_inputs(c, inputs), overrides=LONG, evaluate=False)
        pid = _running_with_pid(c, svc, job["id"])
        try:
            second = subprocess.run([*CLI, "serve", "--data-dir", str(svc.data_dir), "--port", str(free_port())],
                                    capture_output=True, text=True, timeout=60)
        except subprocess.TimeoutExpired as err:
            raise AssertionError("a second serve on the same data directory kept running") from err
        assert second.returncode != 0
        assert "in use by another `handretarget serve`" in second.stderr, second.stderr
        now = c.job(job["id"])
        assert now["state"] == "running" and now["attempts"] == 1
        assert pid in _job_processes(svc.data_dir)  # the same job process, untouched
        c.cancel(job["id"])
    finally:
        svc.stop()


def test_service_restarts_do_not_spend_the_jobs_attempts(tmp_path_factory, inputs):
    # finding: "three service restarts during one valid job leave it failed for good"
    svc = Service(tmp_path_factory.mktemp("hyg_restart") / "data").start()
    try:
        c = svc.client("max")
        job = c.submit(**upload_inputs(c, inputs), overrides=LONG, evaluate=False)
        for _ in range(3):
            _running_with_pid(c, svc, job["id"])
            svc.kill9()
            svc.start()
        now = c.job(job["id"])
        assert now["state"] in ("queued", "running"), now["error"]
        assert now["attempts"] <= 1  # only the attempt running now counts
        c.cancel(job["id"])
    finally:
        svc.stop()


def test_sigterm_ends_event_streams_and_exits_within_5_s(tmp_path_factory, inputs):
    # finding: "SIGTERM with an SSE client attached: the port closes but the process is alive after 90 s"
    svc = Service(tmp_path_factory.mktemp("hyg_term") / "data").start()
    try:
        c = svc.client("ned")
        job = c.submit(**upload_inputs(c, inputs), overrides=LONG, evaluate=False)
        _running_with_pid(c, svc, job["id"])
        got, ended = [], threading.Event()

        def follow():
            try:
                for status in c.events(job["id"]):
                    got.append(status)
            except Exception:  # noqa: BLE001 - a closed connection ends the stream too
                pass
            ended.set()

        threading.Thread(target=follow, daemon=True).start()
        deadline = time.monotonic() + 30
        while not got:
            assert time.monotonic() < deadline, "no event arrived"
            time.sleep(0.05)
        start = time.monotonic()
        svc.proc.send_signal(signal.SIGTERM)
        try:
            svc.proc.wait(timeout=5)
        except subprocess.TimeoutExpired as err:
            raise AssertionError("the service was still alive 5 s after SIGTERM") from err
        assert time.monotonic() - start < 5
        assert ended.wait(2), "the event stream did not end"
        assert not _job_processes(svc.data_dir)  # the job's processes were stopped with it
    finally:
        svc.stop()


def _start_upload(svc: Service, token: str, declared: int, sent: bytes) -> socket.socket:
    """A raw upload that declares ``declared`` bytes and sends only ``sent``."""
    sock = socket.create_connection(("127.0.0.1", svc.port), timeout=15)
    sock.sendall(f"POST /v1/assets/file?name=slow.obj HTTP/1.1\r\nHost: 127.0.0.1\r\n"
                 f"Authorization: Bearer {token}\r\nContent-Type: application/octet-stream\r\n"
                 f"Content-Length: {declared}\r\n\r\n".encode() + sent)
    return sock


def test_a_stalled_upload_times_out_and_leaves_nothing(tmp_path_factory):
    # finding: "slow clients are never timed out" (an upload that stops sending held its request forever)
    svc = Service(tmp_path_factory.mktemp("hyg_slow") / "data", "--read-timeout", "2").start()
    try:
        sock = _start_upload(svc, svc.token("olive"), 100_000, b"v 0 0 0\n" * 10)
        start = time.monotonic()
        try:
            answer = b""
            while b"\r\n\r\n" not in answer or len(answer.split(b"\r\n\r\n", 1)[1]) < 2 or \
                    not answer.rstrip().endswith(b"}"):
                part = sock.recv(65536)
                if not part:
                    break
                answer += part
            answer = answer.decode("latin-1")
        except socket.timeout as err:
            raise AssertionError("the stalled upload got no answer in 15 s") from err
        finally:
            sock.close()
        assert answer.startswith("HTTP/1.1 408"), answer[:200]
        assert "stalled" in answer and time.monotonic() - start < 10
        assert not list((svc.data_dir / "tmp").iterdir())
    finally:
        svc.stop()


def test_a_partial_upload_of_a_killed_service_is_removed_at_restart(tmp_path_factory):
    # finding: "partial uploads stay in tmp/ after a kill"
    svc = Service(tmp_path_factory.mktemp("hyg_partial") / "data").start()
    try:
        sock = _start_upload(svc, svc.token("pia"), 10_000_000, b"v 0 0 0\n" * 5000)
        tmp = svc.data_dir / "tmp"
        deadline = time.monotonic() + 10
        while not list(tmp.iterdir()):
            assert time.monotonic() < deadline, "the upload never reached tmp/"
            time.sleep(0.05)
        svc.kill9()
        sock.close()
        assert list(tmp.iterdir())  # the killed service left it there
        svc.start()
        assert not list(tmp.iterdir())
    finally:
        svc.stop()


def test_event_streams_are_capped_per_owner(tmp_path_factory):
    # finding: "no per-owner cap on concurrent requests or SSE streams (800 streams: health p50 298 ms)"
    from server.schemas import JobCreate
    from server.storage import Store

    svc = Service(tmp_path_factory.mktemp("hyg_streams") / "data", "--max-streams", "3").start()
    try:
        c, other = svc.client("quin"), svc.client("rosa")
        store = Store(svc.data_dir)
        job_id = "f" * 32  # a job that stays running (the runner never started it): its streams stay open
        with store.connect() as db:
            db.execute("INSERT INTO jobs (id, owner, state, request, created, updated) VALUES (?, ?, ?, ?, ?, ?)",
                       (job_id, "quin", "running", JobCreate(clip="a" * 64, rig="b" * 64, annotations="c" * 64)
                        .model_dump_json(), time.time(), time.time()))
        streams = [c.events(job_id) for _ in range(3)]
        for s in streams:
            assert next(s)["id"] == job_id  # each open, its first event read
        with pytest.raises(ServiceError) as err:
            next(c.events(job_id))
        assert err.value.status == 429
        assert other.assets() == []  # another owner is not held up
        streams[0].close()
        deadline = time.monotonic() + 10
        while True:  # the closed stream's slot comes back
            try:
                fourth = c.events(job_id)
                assert next(fourth)["id"] == job_id
                break
            except ServiceError as exc:
                assert exc.status == 429 and time.monotonic() < deadline
                time.sleep(0.2)
        fourth.close()
        for s in streams[1:]:
            s.close()
        store.update_job(job_id, state="cancelled")
    finally:
        svc.stop()
