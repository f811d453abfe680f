"""Fair scheduling (issue 16, Build 3): job slots are shared round-robin across owners.

Findings covered: "slots are FIFO across owners: one owner's 4.9 s job waited 161 s behind
another owner's long ones". On main at 328eb67 the runner claimed the oldest queued job, so
with one slot owner A's second job started before owner B's only job. And "no per-owner cap on
concurrent requests or SSE streams" (requests here; streams in test_hygiene.py).
"""

from __future__ import annotations

import socket
import time

import pytest

from dcc_client.client import RetargetClient, ServiceError

from .conftest import FAST, Service, upload_inputs

LONG = FAST | {"solver.maxeval": 200, "refinement.max_iterations": 20}


def _wait(client, job_id, states, timeout=120.0):
    deadline = time.monotonic() + timeout
    while True:
        job = client.job(job_id)
        if job["state"] in states:
            return job
        assert time.monotonic() < deadline, f"job {job_id} still {job['state']}"
        time.sleep(0.05)


def test_one_slot_is_shared_round_robin_across_owners(tmp_path_factory, inputs):
    svc = Service(tmp_path_factory.mktemp("fair") / "data", "--job-slots", "1").start()
    try:
        a, b = svc.client("owner-a"), svc.client("owner-b")
        ids_a, ids_b = upload_inputs(a, inputs), upload_inputs(b, inputs)
        a_jobs = [a.submit(**ids_a, overrides=LONG, evaluate=False)["id"] for _ in range(3)]
        _wait(a, a_jobs[0], ("running",))
        b_job = b.submit(**ids_b, overrides=FAST, evaluate=False)["id"]  # queued after A's three
        # A's first job gives up its slot (cancelled: the test need not wait for a long solve);
        # the next claim must go to B, who has nothing running, not to A's older second job
        a.cancel(a_jobs[0])
        started = _wait(b, b_job, ("running", "succeeded", "failed"))
        assert started["state"] != "failed", started["error"]
        assert [a.job(j)["state"] for j in a_jobs[1:]] == ["queued", "queued"]
        for j in a_jobs[1:]:
            a.cancel(j)
        b.cancel(b_job)
        second = a.job(a_jobs[1])
        assert second["started"] is None and started["started"] is not None
    finally:
        svc.stop()


def _stalled_upload(svc: Service, token: str) -> socket.socket:
    """An upload that declares 1 MB and sends 80 bytes: its request stays in progress."""
    sock = socket.create_connection(("127.0.0.1", svc.port), timeout=15)
    sock.sendall(f"POST /v1/assets/file?name=slow.obj HTTP/1.1\r\nHost: x\r\nAuthorization: Bearer {token}\r\n"
                 f"Content-Length: 1000000\r\n\r\n".encode() + b"v 0 0 0\n" * 10)
    return sock


def _until(check, timeout=10.0):
    deadline = time.monotonic() + timeout
    while not check():
        assert time.monotonic() < deadline
        time.sleep(0.1)


@pytest.mark.parametrize("flag", ["--max-heavy-requests", "--max-requests"])
def test_one_owner_cannot_take_every_request_slot(tmp_path_factory, flag):
    # finding: "no per-owner cap on concurrent requests ... (45 concurrent proposals: health 6.1 s)"
    svc = Service(tmp_path_factory.mktemp("caps") / "data", flag, "1").start()
    try:
        a_token = svc.token("hog")
        a, b = RetargetClient(svc.url, a_token), svc.client("other")
        held = _stalled_upload(svc, a_token)
        _until(lambda: list((svc.data_dir / "tmp").iterdir()))  # the upload is in progress
        with pytest.raises(ServiceError) as err:
            a.upload_bytes("file", b"v 1 1 1\n", "one.obj")
        assert err.value.status == 429 and "in progress" in err.value.detail
        if flag == "--max-requests":  # every request of that owner waits, not only uploads
            with pytest.raises(ServiceError) as err:
                a.jobs()
            assert err.value.status == 429
        else:
            assert a.jobs() == []
        assert b.upload_bytes("file", b"v 2 2 2\n", "two.obj")["size"] == 8  # the other owner is served
        held.close()  # the slot comes back once the stalled request ends
        _until(lambda: not list((svc.data_dir / "tmp").iterdir()))
        assert a.upload_bytes("file", b"v 1 1 1\n", "one.obj")["size"] == 8
    finally:
        svc.stop()
