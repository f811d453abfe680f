"""Integrity (issue 16, Build 5): blobs and artifacts are checked against the sha256 recorded
when they were stored, whenever they are served; re-uploading repairs a damaged blob; dedup is
per content and kind and never shows another owner's upload.

Findings covered (main at 328eb67): "no integrity check: a truncated artifact or a corrupted
blob is served with 200, a deleted blob gives 500 and re-uploading the same bytes does not
repair it"; "asset content whose blob is missing" (a plain-text 500); "`file` dedup ignores the
extension (one owner's `.stl` makes another owner's identical `.ply` fail to import, and
reveals the upload)".
"""

from __future__ import annotations

import json
import urllib.request

import pytest

from dcc_client.client import ServiceError

from .conftest import FAST, upload_inputs


def _blob(service, sha: str):
    (path,) = [p for p in (service.data_dir / "blobs" / sha[:2]).iterdir() if p.name.startswith(sha)]
    return path


def _raw_status(service, token: str, path: str):
    """(status, content type, body) of a GET, without the client's error mapping."""
    req = urllib.request.Request(service.url + path, headers={"Authorization": f"Bearer {token}"})
    try:
        with urllib.request.urlopen(req, timeout=60) as resp:
            return resp.status, resp.headers.get("content-type"), resp.read()
    except urllib.error.HTTPError as err:
        return err.code, err.headers.get("content-type"), err.read()


def test_a_corrupted_blob_is_refused_and_reuploading_repairs_it(service, inputs):
    c = service.client("ivy")
    data = inputs["annotations"].read_bytes()
    asset = c.upload_bytes("annotations", data, "ann.json")
    blob = _blob(service, asset["id"])
    damaged = bytearray(blob.read_bytes())
    damaged[len(damaged) // 2] ^= 0x01  # one flipped bit
    blob.write_bytes(bytes(damaged))
    status, ctype, body = _raw_status(service, c.token, f"/v1/assets/{asset['id']}/content")
    assert status == 410 and ctype == "application/json", (status, body[:200])
    assert "damaged" in json.loads(body)["detail"] and str(service.data_dir) not in body.decode()
    again = c.upload_bytes("annotations", data, "ann.json")  # the same bytes: repairs the blob
    assert again["id"] == asset["id"]
    assert c.asset_content(asset["id"]) == data


def test_a_deleted_blob_answers_410_everywhere_and_reuploading_repairs_it(service, inputs):
    c = service.client("jay")
    ids = upload_inputs(c, inputs)
    _blob(service, ids["clip"]).unlink()
    with pytest.raises(ServiceError) as err:
        c.asset_content(ids["clip"])
    assert err.value.status == 410 and "missing" in err.value.detail
    with pytest.raises(ServiceError) as err:  # a job over it is refused at submission, naming the field
        c.submit(**ids, overrides=FAST, evaluate=False)
    assert err.value.status == 410 and err.value.detail.startswith("clip:")
    c.upload("clip", inputs["clip"])
    assert c.asset_content(ids["clip"]) == inputs["clip"].read_bytes()


def test_a_truncated_artifact_is_not_served_as_200(service, inputs):
    c = service.client("kai")
    job = c.wait(c.submit(**upload_inputs(c, inputs), overrides=FAST, evaluate=False)["id"], timeout=300)
    assert job["state"] == "succeeded", job["error"]
    whole = c.artifact(job["id"], "animation.usda")
    path = service.data_dir / "jobs" / job["id"] / "animation.usda"
    path.write_bytes(whole[: len(whole) // 2])
    status, ctype, body = _raw_status(service, c.token, f"/v1/jobs/{job['id']}/artifacts/animation.usda")
    assert status == 500 and ctype == "application/json", (status, body[:200])
    assert "damaged" in json.loads(body)["detail"]
    assert json.loads(c.artifact(job["id"], "result.json"))  # the others are still served


def test_file_dedup_is_per_suffix_and_shows_nothing_of_another_owner(service):
    first, second = service.client("lou"), service.client("mia")
    payload = b"solid x\nendsolid x\n" + bytes(range(256))  # made here, the same bytes for both
    stl = first.upload_bytes("file", payload, "part.stl")
    ply = second.upload_bytes("file", payload, "part.ply")
    assert ply["id"] == stl["id"]
    # the second owner's asset is its own: its suffix, its name, nothing of the .stl upload
    assert ply["info"] == {"suffix": ".ply"} and ply["name"] == "part.ply"
    assert second.asset_content(ply["id"], "file") == payload
    assert first.assets("file")[0]["info"] == {"suffix": ".stl"}
