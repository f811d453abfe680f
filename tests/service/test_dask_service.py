"""The service with ``--dask-scheduler``: a real ``dask scheduler`` and two ``dask worker``
processes on 127.0.0.1 run a job's frames; a worker killed mid-job does not fail it."""

from __future__ import annotations

import time

import pytest

from .conftest import FAST, Service, upload_inputs

pytest.importorskip("distributed")
from dask_cluster import Cluster  # noqa: E402


def test_job_on_dask_survives_a_killed_worker(tmp_path_factory, inputs):
    folder = tmp_path_factory.mktemp("dask_service")
    cluster = Cluster(folder)
    svc = None
    try:
        cluster.start(2)
        client = cluster.connect(2)
        svc = Service(folder / "data", "--dask-scheduler", cluster.address).start()
        c = svc.client("frank")
        ids = upload_inputs(c, inputs)
        # more evaluations than FAST so the frame passes last long enough to kill a worker in them
        job = c.submit(**ids, overrides=FAST | {"solver.maxeval": 60}, evaluate=False)
        deadline = time.monotonic() + 300
        while True:
            status = c.job(job["id"])
            assert status["state"] in ("queued", "running"), status
            if status["stage"] == "full pass":
                break
            assert time.monotonic() < deadline
            time.sleep(0.02)
        assert len(client.nthreads()) == 2
        victim = cluster.workers[0]
        cluster.kill(victim)
        assert c.job(job["id"])["state"] == "running"  # the kill landed mid-job
        final = c.wait(job["id"], timeout=300, poll=0.2)
        assert final["state"] == "succeeded", final["error"]
        assert final["attempts"] == 1  # the frames were re-run on the other worker, not the job
        assert final["summary"]["failed_frames"] == 0
        assert final["frames_done"] == final["frames_total"] == 46
        assert len(client.nthreads()) == 1  # the scheduler lost one worker and carried on
        assert final["request"]["overrides"] == FAST | {"solver.maxeval": 60}
        provenance = __import__("json").loads(c.artifact(job["id"], "result.json"))["provenance"]
        # the service, not the request, chose the cluster: the executor's, recorded beside the run configuration
        assert provenance["executor"]["dask_scheduler"] == cluster.address
        assert "dask_scheduler" not in provenance["config"]
    finally:
        if svc is not None:
            svc.stop()
        cluster.close()
