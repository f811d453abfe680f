"""Token revocation, deletion of one's own assets and jobs, the per-owner storage quota, and
paging of assets (issue 16, Build 6), against a real service on 127.0.0.1.

Finding covered (main at 328eb67): "no token revocation, no deletion of assets or jobs, no
storage quota" (there was no `token revoke`, DELETE answered 405, and an owner could store
without bound).
"""

from __future__ import annotations

import subprocess

import pytest

from dcc_client.client import ServiceError

from .conftest import CLI, FAST, Service, upload_inputs


def test_token_revoke_refuses_the_next_request(service):
    c = service.client("quinn")
    assert c.assets() == []
    out = subprocess.run([*CLI, "token", "revoke", "quinn", "--data-dir", str(service.data_dir)],
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr
    with pytest.raises(ServiceError) as err:
        c.assets()
    assert err.value.status == 401
    again = subprocess.run([*CLI, "token", "revoke", "quinn", "--data-dir", str(service.data_dir)],
                           capture_output=True, text=True)
    assert again.returncode != 0 and "no token" in again.stderr


def test_delete_own_asset_keeps_the_blob_another_owner_uses(service, inputs):
    a, b = service.client("rae"), service.client("sol")
    data = b"# obj made in this test\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"
    mine, theirs = a.upload_bytes("file", data, "tri.obj"), b.upload_bytes("file", data, "tri.obj")
    blob = next((service.data_dir / "blobs" / mine["id"][:2]).glob(mine["id"] + "*"))
    a.delete_asset(mine["id"])
    with pytest.raises(ServiceError) as err:
        a.asset_content(mine["id"])
    assert err.value.status == 404
    assert b.asset_content(theirs["id"]) == data and blob.is_file()  # still the other owner's
    with pytest.raises(ServiceError) as err:  # deleting it again: as unknown as any other id
        a.delete_asset(mine["id"])
    assert err.value.status == 404
    b.delete_asset(theirs["id"], "file")
    assert not blob.exists()  # no owner refers to it any more


def test_delete_job_only_when_finished_and_assets_only_when_unused(service, inputs):
    c = service.client("tao")
    ids = upload_inputs(c, inputs)
    job = c.submit(**ids, overrides=FAST, evaluate=False)
    with pytest.raises(ServiceError) as err:
        c.delete_job(job["id"])
    assert err.value.status == 409 and "cancel it first" in err.value.detail
    with pytest.raises(ServiceError) as err:
        c.delete_asset(ids["clip"], "clip")
    assert err.value.status == 409 and job["id"] in err.value.detail
    final = c.wait(job["id"], timeout=300)
    assert final["state"] == "succeeded", final["error"]
    c.delete_job(job["id"])
    with pytest.raises(ServiceError) as err:
        c.job(job["id"])
    assert err.value.status == 404
    assert not (service.data_dir / "jobs" / job["id"]).exists()
    c.delete_asset(ids["clip"], "clip")
    assert sorted(a["kind"] for a in c.assets()) == ["annotations", "rig"]


def test_storage_quota_and_asset_paging(tmp_path_factory):
    svc = Service(tmp_path_factory.mktemp("quota") / "data", "--storage-quota-mb", "0.01").start()  # 10,485 bytes
    try:
        c = svc.client("uma")
        ids = [c.upload_bytes("file", f"# {i}\n".encode() + b"v 0 0 0\n" * 100, f"m{i}.obj")["id"] for i in range(5)]
        with pytest.raises(ServiceError) as err:
            c.upload_bytes("file", b"v 1 1 1\n" * 1000, "big.obj")
        assert err.value.status == 413 and "storage quota" in err.value.detail
        page = c._request("GET", "/v1/assets", query={"limit": 2})
        assert len(page["assets"]) == 2 and page["next_cursor"]
        assert [a["id"] for a in c.assets(page_size=2)] == ids  # 3 pages, oldest first
        for asset_id in ids:  # deleting frees the quota
            c.delete_asset(asset_id)
        assert c.upload_bytes("file", b"v 1 1 1\n" * 1000, "big.obj")["size"] == 8000
    finally:
        svc.stop()
