"""/metrics, /v1/ready and paging (issue 16, Build 6), against a real service on 127.0.0.1.

Findings covered (main at 328eb67): "unauthenticated requests with random methods grow
`/metrics` without bound (2,000 requests: 9.6 KB -> 3.4 MB)"; "`/v1/ready` and `/metrics` show
global job counts" (any owner's token read /metrics; /v1/ready had the counts of every state);
"`GET /v1/jobs` silently returns only the 1,000 oldest".
"""

from __future__ import annotations

import http.client
import json
import secrets
import subprocess
import time
import urllib.request

import pytest

from dcc_client.client import RetargetClient, ServiceError

from .conftest import CLI, Service


def _admin_token(svc: Service, name: str) -> str:
    out = subprocess.run([*CLI, "token", "create", name, "--admin", "--data-dir", str(svc.data_dir)], check=True,
                         capture_output=True, text=True)
    return out.stdout.strip()


def _metrics(svc: Service, token: str) -> str:
    return RetargetClient(svc.url, token)._request("GET", "/metrics", raw=True).decode()


def test_metrics_need_an_admin_token_and_label_only_known_routes(service):
    with pytest.raises(ServiceError) as err:  # an ordinary owner's token sees no service-wide numbers
        service.client("olga")._request("GET", "/metrics", raw=True)
    assert err.value.status == 403 and "--admin" in err.value.detail
    admin = _admin_token(service, "ops")
    before = _metrics(service, admin)
    marks = []
    for i in range(300):  # unauthenticated junk: random methods on random paths
        method, path = f"M{secrets.token_hex(4).upper()}", f"/junk/{secrets.token_hex(8)}"
        marks += [method, path]
        conn = http.client.HTTPConnection("127.0.0.1", service.port, timeout=10)
        conn.request(method, path)
        conn.getresponse().read()
        conn.close()
    after = _metrics(service, admin)
    assert not [m for m in marks if m in after]  # no method or path of the junk became a label
    assert 'route="unmatched"' in after and 'method="OTHER"' in after
    assert len(after) < len(before) + 4000, (len(before), len(after))  # a few new series, not 300


def test_ready_shows_no_counts(service):
    with urllib.request.urlopen(service.url + "/v1/ready", timeout=10) as resp:
        assert json.loads(resp.read()) == {"status": "ready"}


def test_job_list_pages_past_1000(tmp_path_factory):
    from server.schemas import JobCreate
    from server.storage import Store

    data = tmp_path_factory.mktemp("paging") / "data"
    store = Store(data)
    token = store.create_token("pat")
    request = JobCreate(clip="a" * 64, rig="b" * 64, annotations="c" * 64)
    with store.connect() as db:  # 1,005 finished jobs, written before the service starts
        db.execute("BEGIN")
        now = time.time()
        for i in range(1005):
            db.execute("INSERT INTO jobs (id, owner, state, request, created, updated) VALUES (?, ?, ?, ?, ?, ?)",
                       (f"{i:032x}", "pat", "cancelled", request.model_dump_json(), now + i * 1e-3, now))
        db.execute("COMMIT")
    svc = Service(data).start()
    try:
        c = RetargetClient(svc.url, token)
        first = c._request("GET", "/v1/jobs", query={"limit": 1000})
        assert len(first["jobs"]) == 1000 and first["next_cursor"]
        every = c.jobs(page_size=300)  # 4 pages
        assert len(every) == 1005 and len({j["id"] for j in every}) == 1005
        assert [j["id"] for j in every] == [f"{i:032x}" for i in range(1005)]  # oldest first, none twice
        with pytest.raises(ServiceError) as err:
            c._request("GET", "/v1/jobs", query={"cursor": "not-a-cursor"})
        assert err.value.status == 422 and err.value.detail.startswith("cursor:")
        with pytest.raises(ServiceError) as err:
            c._request("GET", "/v1/jobs", query={"limit": 1001})
        assert err.value.status == 422
    finally:
        svc.stop()


def test_json_bodies_have_a_size_limit(service):
    # finding: "JSON bodies ignore `--max-upload-mb`" (a JSON body was read whole, whatever its size)
    token = service.token("wes")
    body = json.dumps({"clip": "a" * 64, "rig": "b" * 64, "annotations": "c" * 64,
                       "overrides": {"pad": "x" * (2 * 1024 * 1024)}}).encode()
    for chunked in (False, True):
        conn = http.client.HTTPConnection("127.0.0.1", service.port, timeout=60)
        headers = {"Authorization": f"Bearer {token}", "Content-Type": "application/json"}
        if chunked:
            conn.request("POST", "/v1/jobs", body=iter([body[i:i + 65536] for i in range(0, len(body), 65536)]),
                         headers=headers, encode_chunked=True)
        else:
            conn.request("POST", "/v1/jobs", body=body, headers=headers)
        resp = conn.getresponse()
        doc = json.loads(resp.read())
        conn.close()
        assert resp.status == 413 and "JSON bodies" in doc["detail"], (chunked, resp.status, doc)
