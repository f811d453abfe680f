"""Durability: the service killed with SIGKILL in the middle of a job, started again over the
same data directory, finishes the job; earlier artifacts are untouched."""

from __future__ import annotations

import hashlib
import time

from .conftest import FAST, Service, _job_processes, upload_inputs


def test_kill9_mid_job_then_restart_finishes_it(tmp_path_factory, inputs):
    data = tmp_path_factory.mktemp("restart") / "data"
    svc = Service(data).start()
    try:
        c = svc.client("erin")
        ids = upload_inputs(c, inputs)
        done = c.wait(c.submit(**ids, overrides=FAST, evaluate=False)["id"], timeout=300)
        assert done["state"] == "succeeded", done["error"]
        usd = data / "jobs" / done["id"] / "animation.usda"
        before = hashlib.sha256(usd.read_bytes()).hexdigest()

        job = c.submit(**ids, overrides=FAST | {"solver.maxeval": 16}, evaluate=False)
        deadline = time.monotonic() + 300
        while c.job(job["id"])["stage"] not in ("root pass", "full pass"):  # well inside the job
            assert time.monotonic() < deadline and c.job(job["id"])["state"] in ("queued", "running")
            time.sleep(0.05)
        svc.kill9()
        # the orphaned job process notices at its next progress report and stops
        deadline = time.monotonic() + 60
        while _job_processes(data):
            assert time.monotonic() < deadline, "the orphaned job process kept running"
            time.sleep(0.2)

        svc.start()
        final = c.wait(job["id"], timeout=300, poll=0.2)
        assert final["state"] == "succeeded", final["error"]
        assert final["attempts"] == 1  # the service went away, not the job: not counted (issue 16)
        assert "animation.usda" in final["artifacts"]
        assert [j["id"] for j in c.jobs()] == [done["id"], job["id"]]  # nothing lost, nothing duplicated
        assert hashlib.sha256(usd.read_bytes()).hexdigest() == before
        assert c.job(done["id"])["state"] == "succeeded"
        assert not list((data / "tmp").glob("*.out"))  # the killed attempt's scratch output was removed
    finally:
        svc.stop()


def test_atlas_cache_is_pruned_to_its_budget(tmp_path_factory, inputs):
    """A job's atlas lands in DATA/cache/atlas; with a budget smaller than one atlas the runner
    removes it once the job has finished (and the job's result is unaffected)."""
    data = tmp_path_factory.mktemp("prune") / "data"
    svc = Service(data, "--atlas-cache-mb", "1").start()
    try:
        c = svc.client("judy")
        ids = upload_inputs(c, inputs)
        job = c.wait(c.submit(**ids, overrides=FAST, evaluate=False)["id"], timeout=300)
        assert job["state"] == "succeeded", job["error"]
        # the runner unlinks the file and then logs it: wait for both, the test must not read the
        # log in between (CI once did)
        deadline = time.monotonic() + 10
        while list((data / "cache" / "atlas").glob("*.npz")) or "atlas cache: removed" not in svc.log.read_text():
            assert time.monotonic() < deadline, "the atlas cache was not pruned"
            time.sleep(0.1)
        assert not list((data / "cache" / "atlas").glob("*.npz"))
        assert "atlas cache: removed 1 files" in svc.log.read_text()  # it was there, and went
    finally:
        svc.stop()
