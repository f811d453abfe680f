"""Fuzzing: schemathesis generates requests for every operation of the service's OpenAPI
schema (valid and invalid ones) and sends them to a real service with a valid bearer token.
No answer may be a 5xx, and every answer must be what the schema documents (status code,
content type, body schema).

The service is small on purpose: uploads of at most 50 kB and one active job per owner, so
fuzzing cannot fill the disk or keep the CPUs busy. It cannot start a job at all: the only
assets it can name are the ``file`` assets seeded here (a job needs a clip, a rig and
annotations). To get past 404 on the job and asset endpoints, generated ids are sometimes
replaced by ids that exist: a job (seeded in the store in a final state, so its event stream
ends at once) and the seeded files (also fed to the GRAB importer as its inputs)."""

from __future__ import annotations

import time

import hypothesis
import pytest
import schemathesis
from hypothesis import strategies as st
from schemathesis.checks import not_a_server_error
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from .conftest import Service

MAX_EXAMPLES = 25  # generated cases per operation (plus the few deterministic ones of the coverage phase)
CHECKS = [not_a_server_error, status_code_conformance, content_type_conformance, response_schema_conformance]
# garbage with the names the GRAB importer expects: the importer must answer 422, not 500
SEED_FILES = {"sequence": ("seq.npz", b"not an npz"), "mano": ("mano.pkl", b"not a pickle"),
              "object_mesh": ("object.ply", b"not a mesh")}
OWNER = "fuzzer"


def _seed_store(data_dir) -> tuple[str, str]:
    """A token for OWNER and one finished (failed) job of OWNER, written to the store before the
    service starts (the job runner never sees it queued). Returns (token, job id)."""
    from server.schemas import JobCreate, JobState
    from server.storage import Store

    store = Store(data_dir)
    token = store.create_token(OWNER)
    request = JobCreate(clip="a" * 64, rig="b" * 64, annotations="c" * 64)
    job, created = store.create_job(OWNER, request, None, max_active=1)
    assert created
    assert store.update_job(job.id, state=JobState.FAILED, stage="loading", error="seeded for fuzzing",
                            started=time.time(), finished=time.time(), attempts=1)
    return token, job.id


@pytest.fixture(scope="module")
def fuzz_service(tmp_path_factory):
    data = tmp_path_factory.mktemp("fuzz") / "data"
    token, job_id = _seed_store(data)
    svc = Service(data, "--max-upload-mb", "0.05", "--max-active-jobs", "1").start()
    try:
        from dcc_client.client import RetargetClient

        client = RetargetClient(svc.url, token, timeout=60)
        files = {field: client.upload_bytes("file", payload, name)["id"]
                 for field, (name, payload) in SEED_FILES.items()}
        KNOWN.update(job_id=[job_id], asset_id=list(files.values()), files=files)
        yield dict(service=svc, token=token, job_id=job_id, files=files, client=client)
    finally:
        svc.stop()


def _served_schema() -> dict:
    """The OpenAPI document the service serves, made in this process (the fuzzed operations are
    known when tests are collected; ``test_the_service_serves_this_schema`` checks it is the
    one served). schemathesis' lazy ``from_fixture`` loader does not work with pytest 9.2."""
    import tempfile
    from pathlib import Path

    from server.app import create_app
    from server.settings import Settings

    with tempfile.TemporaryDirectory() as tmp:  # the app's store is made, never used
        return create_app(Settings(data_dir=Path(tmp))).openapi()


RAW_SCHEMA = _served_schema()
schema = schemathesis.openapi.from_dict(RAW_SCHEMA)
KNOWN = {"job_id": [], "asset_id": [], "files": {}}  # filled by the fuzz_service fixture


@schema.hook
def flatmap_path_parameters(context, path_parameters):
    """Sometimes the id of an existing job / asset instead of the generated one."""
    options = [path_parameters]
    if isinstance(path_parameters, dict):
        for name in ("job_id", "asset_id"):
            if name in path_parameters:
                options += [{**path_parameters, name: value} for value in KNOWN[name]]
    return st.sampled_from(options)


@schema.hook
def flatmap_body(context, body):
    """The GRAB importer sometimes gets the seeded (garbage) files as its inputs."""
    if context.operation is None or context.operation.path != "/v1/clips/import-grab" \
            or not isinstance(body, dict) or not KNOWN["files"]:
        return st.just(body)
    return st.sampled_from([body, {**body, **KNOWN["files"]}])


def test_the_service_serves_this_schema(fuzz_service):
    import json
    import urllib.request

    with urllib.request.urlopen(f"{fuzz_service['service'].url}/openapi.json", timeout=60) as resp:
        assert json.loads(resp.read()) == RAW_SCHEMA


@schema.parametrize()
@hypothesis.settings(max_examples=MAX_EXAMPLES, deadline=None, database=None,
                     suppress_health_check=list(hypothesis.HealthCheck))
def test_no_server_errors_and_answers_as_documented(case, fuzz_service):
    case.call_and_validate(base_url=fuzz_service["service"].url, checks=CHECKS, timeout=60,
                           headers={"Authorization": f"Bearer {fuzz_service['token']}"})


def test_fuzzing_left_the_service_sound(fuzz_service):
    """After fuzzing: the service still answers, started no job, and stored nothing big."""
    svc, client = fuzz_service["service"], fuzz_service["client"]
    assert client.health() == {"status": "ok"}
    jobs = client.jobs()
    # the seeded (failed) job is still there, or the fuzzer deleted it (DELETE /v1/jobs/{id})
    assert [j["id"] for j in jobs] in ([fuzz_service["job_id"]], []), "fuzzing created a job"
    assert all(j["state"] == "failed" for j in jobs)
    total = sum(p.stat().st_size for p in svc.data_dir.rglob("*") if p.is_file())
    assert total < 50 * 1024 * 1024, f"the fuzzed service's data directory holds {total} bytes"
    assert not [p for p in (svc.data_dir / "tmp").iterdir()], "uploads left scratch files behind"
