"""Fair scheduling (issue 16, Build 3): job slots are shared round-robin across owners.

Finding covered: "slots are FIFO across owners: one owner's 4.9 s job waited 161 s behind
another owner's long ones". On main at 328eb67 the runner claimed the oldest queued job, so
with one slot owner A's second job started before owner B's only job.
"""

from __future__ import annotations

import time

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
