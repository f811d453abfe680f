"""The job service end to end over HTTP on 127.0.0.1: upload, submit, follow, download (equal to
the core's own output), ownership, and bad requests that get a 4xx saying what to fix."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from pxr import Usd, UsdSkel

from dcc_client.client import ServiceError

from .conftest import CLI, FAST, upload_inputs


@pytest.fixture(scope="module")
def alice(service):
    return service.client("alice")


@pytest.fixture(scope="module")
def finished(service, alice, inputs, tmp_path_factory):
    """One job followed over the event stream to its end, and its artifacts downloaded."""
    ids = upload_inputs(alice, inputs)
    job = alice.submit(**ids, overrides=FAST, idempotency_key="first-job")
    events = list(alice.events(job["id"]))
    folder = tmp_path_factory.mktemp("downloaded")
    final = alice.job(job["id"])
    files = alice.download_result(job["id"], folder) if final["state"] == "succeeded" else {}
    # the layer sublayers the rig upload's own file name: the user's file sits beside it
    shutil.copy(inputs["rig"], folder / Path(inputs["rig"]).name)
    return dict(ids=ids, job=job, events=events, final=final, files=files, folder=folder)


def test_job_runs_and_reports_progress(finished):
    final, events = finished["final"], finished["events"]
    assert final["state"] == "succeeded", final["error"]
    states = [e["state"] for e in events]
    assert states[-1] == "succeeded" and "running" in states
    stages = [e["stage"] for e in events]
    assert "full pass" in stages and "spline fit" in stages
    assert final["frames_done"] == final["frames_total"] == 46
    assert final["attempts"] == 1 and final["progress"] == 1.0
    assert {"animation.usda", "animation.usdc", "result.json", "metrics.json", "contact_sheet.png",
            "preview.gif", "pictures.json"} <= set(final["artifacts"])
    assert final["summary"]["frames"] == 46 and final["timings"]["total"] > 0


def test_downloaded_usd_equals_the_cores_output(finished, inputs, tmp_path):
    """The same input files through the core in this process give the same curves and poses."""
    from retarget_core.execute import Executor
    from retarget_core.export import read_dof_bsplines
    from retarget_core.inputs import load_inputs
    from retarget_core.pipeline import retarget
    from retarget_core.solve.config import load_config

    result = retarget(load_inputs(inputs["clip"], inputs["rig"], inputs["annotations"]),
                      load_config(None, "default", FAST), Executor())
    result.write(tmp_path)
    ours, theirs = read_dof_bsplines(tmp_path / "animation.usda"), read_dof_bsplines(finished["files"]["animation.usda"])
    assert set(ours) == set(theirs) and len(ours) == inputs["target"].n_dofs
    for name in ours:
        np.testing.assert_array_equal(theirs[name].knots, ours[name].knots, err_msg=name)
        np.testing.assert_allclose(theirs[name].coeffs, ours[name].coeffs, rtol=0, atol=1e-12, err_msg=name)
    # the binary layer holds the same animation, and both resolve the rig beside them
    for layer in ("animation.usda", "animation.usdc"):
        stage = Usd.Stage.Open(str(finished["files"][layer]))
        root = stage.GetDefaultPrim()
        skel = UsdSkel.Skeleton(root.GetChild("Skeleton"))
        cache = UsdSkel.Cache()
        cache.Populate(UsdSkel.Root(root), Usd.TraverseInstanceProxies())
        query = cache.GetSkelQuery(skel)
        mine = Usd.Stage.Open(str(tmp_path / "animation.usda"))
        mine_cache = UsdSkel.Cache()
        mine_root = mine.GetDefaultPrim()
        mine_cache.Populate(UsdSkel.Root(mine_root), Usd.TraverseInstanceProxies())
        mine_query = mine_cache.GetSkelQuery(UsdSkel.Skeleton(mine_root.GetChild("Skeleton")))
        for frame in (0, 20, 45):
            got = np.array(query.ComputeJointLocalTransforms(Usd.TimeCode(frame)))
            want = np.array(mine_query.ComputeJointLocalTransforms(Usd.TimeCode(frame)))
            assert got.size and np.allclose(got, want, atol=1e-9), (layer, frame)
    doc = json.loads(finished["files"]["result.json"].read_text())
    np.testing.assert_allclose(np.array(doc["q"], dtype=float), result.q, atol=1e-12)


def test_resubmitting_with_the_same_idempotency_key_returns_the_same_job(alice, finished):
    again = alice.submit(**finished["ids"], overrides=FAST, idempotency_key="first-job")
    assert again["id"] == finished["job"]["id"]
    with pytest.raises(ServiceError) as err:
        alice.submit(**finished["ids"], overrides=FAST | {"solver.maxeval": 16}, idempotency_key="first-job")
    assert err.value.status == 409 and "Idempotency-Key" in err.value.detail
    assert [j["id"] for j in alice.jobs()].count(finished["job"]["id"]) == 1


def test_uploads_are_content_addressed(alice, inputs, finished):
    again = alice.upload("rig", inputs["rig"])
    assert again["id"] == finished["ids"]["rig"]
    import hashlib

    assert again["id"] == hashlib.sha256(inputs["rig"].read_bytes()).hexdigest()
    assert again["info"]["dofs"] == inputs["target"].n_dofs
    assert alice.asset_content(finished["ids"]["annotations"]) == inputs["annotations"].read_bytes()


def test_another_owner_sees_nothing(service, alice, finished):
    bob = service.client("bob")
    job_id, ids = finished["job"]["id"], finished["ids"]
    assert bob.jobs() == [] and bob.assets() == []
    calls = [lambda: bob.job(job_id), lambda: bob.cancel(job_id), lambda: bob.artifact(job_id, "animation.usda"),
             lambda: list(bob.events(job_id)), lambda: bob.asset_content(ids["clip"]),
             lambda: bob.submit(**ids)]  # cannot use alice's assets either
    for call in calls:
        with pytest.raises(ServiceError) as err:
            call()
        assert err.value.status == 404, err.value
    assert alice.job(job_id)["state"] == "succeeded"  # untouched


def test_requests_without_a_valid_token_are_refused(service, finished):
    import urllib.error
    import urllib.request

    for headers in ({}, {"Authorization": "Bearer hr_not-a-token"}, {"Authorization": "Basic abc"}):
        req = urllib.request.Request(f"{service.url}/v1/jobs", headers=headers)
        with pytest.raises(urllib.error.HTTPError) as err:
            urllib.request.urlopen(req)
        assert err.value.code == 401
        assert "token" in json.loads(err.value.read())["detail"]
    with urllib.request.urlopen(f"{service.url}/v1/health") as resp:  # health needs none
        assert json.loads(resp.read()) == {"status": "ok"}


@pytest.mark.parametrize("kind, payload, message", [
    ("clip", b"PK\x03\x04 not really a zip", "not a valid clip"),
    ("clip", b"#usda 1.0\n", "native clip .npz"),
    ("rig", b"hello", "USD file"),
    ("rig", b"#usda 1.0\ndef Xform \"x\" {}\n", "not a valid rig"),
    ("annotations", b"{\"markers\": 3}", "not a valid annotations"),
    ("annotations", b"\xff\xfe", "not a valid annotations"),
    ("file", b"abc", "needs a name ending"),
    ("movie", b"abc", "kind"),
])
def test_bad_uploads_are_422_and_store_nothing(alice, kind, payload, message):
    before = alice.assets()
    with pytest.raises(ServiceError) as err:
        alice.upload_bytes(kind, payload, "x.bin")
    assert err.value.status == 422 and message in err.value.detail, err.value.detail
    assert "/tmp" not in err.value.detail  # the service's own paths are never shown
    assert alice.assets() == before


def test_bad_job_requests_name_the_field(service, alice, inputs, finished, tmp_path):
    ids = finished["ids"]
    cases = [
        (dict(ids, clip="0" * 64), 404, "clip: no clip asset"),
        (dict(ids, rig=ids["clip"]), 404, "rig: no rig asset"),
        (dict(ids, overrides={"solver.maxevals": 5}), 422, "solver.maxevals"),
        (dict(ids, overrides={"weights.lambda_m": -1}), 422, "weights.lambda_m"),
        # how a run executes is the service's (its executor), never part of a job's run configuration
        (dict(ids, overrides={"workers": 8}), 422, "use the executor's worker count"),
        (dict(ids, overrides={"atlas_cache": "/etc"}), 422, "use the executor's atlas cache"),
        (dict(ids, overrides={"dask_scheduler": "tcp://10.0.0.1:8786"}), 422, "use the executor's Dask scheduler"),
        (dict(ids, preset="fastest"), 422, "preset"),
        (dict(ids, clip="not-a-hash"), 422, "clip"),
    ]
    for body, status, message in cases:
        with pytest.raises(ServiceError) as err:
            alice.submit(**body)
        assert err.value.status == status and message in err.value.detail, (body, err.value.detail)
    # annotations made for another rig
    from retarget_core.rig.demo_hands import demo_hand
    from retarget_core.rig.io import save_rig

    save_rig(demo_hand("witch", 0.006), tmp_path / "witch.usda")
    witch = alice.upload("rig", tmp_path / "witch.usda")
    with pytest.raises(ServiceError) as err:
        alice.submit(**dict(ids, rig=witch["id"]))
    assert err.value.status == 422 and "annotations: made for a target mesh" in err.value.detail


def test_artifacts_only_of_succeeded_jobs_and_by_name(service, alice, finished):
    job_id = finished["job"]["id"]
    for name, status in (("secrets.txt", 404), ("..%2F..%2Fservice.sqlite3", 404), ("scene.npz", 404)):
        with pytest.raises(ServiceError) as err:
            alice.artifact(job_id, name)
        assert err.value.status == status, name


def test_oversized_upload_is_413(tmp_path_factory):
    from .conftest import Service

    svc = Service(tmp_path_factory.mktemp("small") / "data", "--max-upload-mb", "0.01").start()
    try:
        c = svc.client("carol")
        with pytest.raises(ServiceError) as err:
            c.upload_bytes("file", b"x" * 20000, "seq.npz")
        assert err.value.status == 413 and "limit" in err.value.detail
        assert c.assets() == [] and not list((svc.data_dir / "tmp").iterdir())
    finally:
        svc.stop()


def test_cancel_a_running_job_and_the_active_job_limit(tmp_path_factory, inputs):
    """One job slot, at most 2 active jobs: a third is 429; a queued job is cancelled at once,
    a running one is stopped (its processes too) and leaves no artifacts; then the owner may
    submit again."""
    import time

    from .conftest import Service, _job_processes

    svc = Service(tmp_path_factory.mktemp("limits") / "data", "--max-active-jobs", "2").start()
    try:
        c = svc.client("dave")
        ids = upload_inputs(c, inputs)
        first = c.submit(**ids, evaluate=False)
        second = c.submit(**ids, evaluate=False, overrides={"solver.maxeval": 20})
        with pytest.raises(ServiceError) as err:
            c.submit(**ids, overrides={"solver.maxeval": 21})
        assert err.value.status == 429 and "limit is 2" in err.value.detail
        assert c.cancel(second["id"])["state"] == "cancelled"  # it was queued behind the first
        deadline = time.monotonic() + 60
        while c.job(first["id"])["state"] != "running":
            assert time.monotonic() < deadline
            time.sleep(0.05)
        assert c.cancel(first["id"])["state"] == "running"  # asked; the runner stops it
        final = c.wait(first["id"], timeout=60, poll=0.1)
        assert final["state"] == "cancelled" and final["artifacts"] == []
        assert not (svc.data_dir / "jobs" / first["id"]).exists()
        deadline = time.monotonic() + 10
        while _job_processes(svc.data_dir):
            assert time.monotonic() < deadline, "the cancelled job's process is still alive"
            time.sleep(0.1)
        with pytest.raises(ServiceError) as err:
            c.cancel(first["id"])
        assert err.value.status == 409
        third = c.submit(**ids, evaluate=False, overrides={"solver.maxeval": 22})
        assert third["state"] == "queued"
    finally:
        svc.stop()


def test_readiness_docs_and_metrics(service, alice, finished):
    import urllib.request

    with urllib.request.urlopen(f"{service.url}/v1/ready") as resp:
        doc = json.loads(resp.read())
    assert doc == {"status": "ready"}  # no counts of anyone's jobs (issue 16)
    with urllib.request.urlopen(f"{service.url}/openapi.json") as resp:
        schema = json.loads(resp.read())
    assert {"/v1/jobs", "/v1/jobs/{job_id}/events", "/v1/assets/{kind}"} <= set(schema["paths"])
    assert schema["info"]["version"] == "1"
    with urllib.request.urlopen(f"{service.url}/docs") as resp:
        assert b"swagger" in resp.read().lower()
    with pytest.raises(ServiceError) as err:  # an owner's token is not enough: service-wide numbers
        alice._request("GET", "/metrics", raw=True)
    assert err.value.status == 403
    admin = subprocess.run([*CLI, "token", "create", "ops", "--admin", "--data-dir", str(service.data_dir)],
                           check=True, capture_output=True, text=True).stdout.strip()
    text = type(alice)(service.url, admin)._request("GET", "/metrics", raw=True).decode()
    succeeded = [line for line in text.splitlines() if line.startswith('handretarget_jobs{state="succeeded"}')]
    assert succeeded and float(succeeded[0].split()[-1]) >= 1
    assert 'handretarget_http_requests_total{method="POST",route="/v1/jobs",status="201"}' in text
    assert "handretarget_http_request_seconds_bucket" in text
    with pytest.raises(ServiceError) as err:  # metrics need a token
        type(alice)(service.url, "hr_wrong")._request("GET", "/metrics", raw=True)
    assert err.value.status == 401
    # one JSON log line per request, with its status and the caller
    lines = [json.loads(line) for line in service.log.read_text().splitlines() if line.startswith("{")]
    assert any(r.get("path") == "/v1/jobs" and r.get("method") == "POST" and r.get("owner") == "alice" for r in lines)


def test_proposed_annotations_fit_the_rig(alice, finished):
    rig = alice.assets("rig")[0]
    ann = alice.propose_annotations(rig["id"])
    assert ann["kind"] == "annotations" and ann["info"]["proposed"] is True
    assert (ann["info"]["target"]["vertices"], ann["info"]["target"]["faces"]) == \
        (rig["info"]["vertices"], rig["info"]["faces"])
    assert ann["info"]["markers"] >= 20 and ann["info"]["curves"] >= 5
    doc = json.loads(alice.asset_content(ann["id"]))
    assert len(doc["markers"]) == ann["info"]["markers"]
    with pytest.raises(ServiceError) as err:  # a clip is not a rig
        alice.propose_annotations(finished["ids"]["clip"])
    assert err.value.status == 404 and "target_rig" in err.value.detail
