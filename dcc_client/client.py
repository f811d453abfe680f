"""A client of the Hand Retarget job service, standard library only (so Blender's Python and
pipeline scripts can use it as is).

    from dcc_client.client import RetargetClient
    c = RetargetClient("http://127.0.0.1:8000", token)
    rig = c.upload("rig", "witch.usda")
    ...
    job = c.submit(clip=clip["id"], rig=rig["id"], annotations=ann["id"])
    job = c.wait(job["id"], on_progress=print)
    c.download(job["id"], "animation.usda", "out/animation.usda")
"""

from __future__ import annotations

import json
import os
import socket
import time
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path

FINAL_STATES = ("succeeded", "failed", "cancelled")


class ServiceError(RuntimeError):
    """The service answered with an error: ``status`` (HTTP code) and its ``detail`` message."""

    def __init__(self, status: int, detail: str, method: str = "", path: str = ""):
        super().__init__(f"{method} {path}: {status}: {detail}".strip())
        self.status, self.detail = status, detail


class RetargetClient:
    def __init__(self, base_url: str, token: str, *, timeout: float = 60.0):
        self.base = base_url.rstrip("/")
        self.token, self.timeout = token, timeout

    # ---- transport ---------------------------------------------------------------------------
    def _request(self, method: str, path: str, *, body: bytes | None = None, content_type: str | None = None,
                 headers: dict | None = None, query: dict | None = None, raw: bool = False):
        url = self.base + path
        if query:
            url += "?" + urllib.parse.urlencode({k: v for k, v in query.items() if v is not None})
        h = {"Authorization": f"Bearer {self.token}", "Accept": "application/json"}
        if content_type:
            h["Content-Type"] = content_type
        h.update(headers or {})
        req = urllib.request.Request(url, data=body, method=method, headers=h)
        try:
            with urllib.request.urlopen(req, timeout=self.timeout) as resp:
                data = resp.read()
                return data if raw else (json.loads(data) if data else None)
        except urllib.error.HTTPError as err:
            text = err.read().decode("utf-8", "replace")
            try:
                detail = json.loads(text).get("detail", text)
            except (ValueError, AttributeError):
                detail = text
            raise ServiceError(err.code, detail if isinstance(detail, str) else json.dumps(detail), method, path) \
                from None

    def _json(self, method: str, path: str, doc=None, **kw):
        body = None if doc is None else json.dumps(doc).encode("utf-8")
        return self._request(method, path, body=body, content_type="application/json" if body else None, **kw)

    # ---- service -----------------------------------------------------------------------------
    def health(self) -> dict:
        return self._request("GET", "/v1/health")

    def upload(self, kind: str, path, *, name: str | None = None, root_body: str | None = None,
               hand_root: str | None = None) -> dict:
        """Upload a file as an asset of ``kind`` ("rig", "annotations", "clip", "file"). For a
        rig: ``root_body`` picks the hand in an MJCF model (a bundle), ``hand_root`` the hand
        inside a USD character's skeleton."""
        path = Path(path)
        return self.upload_bytes(kind, path.read_bytes(), name or path.name, root_body=root_body, hand_root=hand_root)

    def upload_bytes(self, kind: str, data: bytes, name: str, *, root_body: str | None = None,
                     hand_root: str | None = None) -> dict:
        query = {"name": name} | {k: v for k, v in (("root_body", root_body), ("hand_root", hand_root)) if v}
        return self._request("POST", f"/v1/assets/{kind}", body=data, content_type="application/octet-stream",
                             query=query)

    def _pages(self, path: str, key: str, query: dict, limit: int | None):
        """Every item of a paged list (following ``next_cursor``)."""
        items, cursor = [], None
        while True:
            page = self._request("GET", path, query=query | {"limit": limit, "cursor": cursor})
            items += page[key]
            cursor = page.get("next_cursor")
            if not cursor:
                return items

    def assets(self, kind: str | None = None, *, page_size: int | None = None) -> list[dict]:
        """All your assets (every page, oldest first)."""
        return self._pages("/v1/assets", "assets", {"kind": kind}, page_size)

    def delete_asset(self, asset_id: str, kind: str | None = None) -> None:
        """Remove your asset (409 while a queued or running job of yours uses it)."""
        self._request("DELETE", f"/v1/assets/{asset_id}", query={"kind": kind})

    def asset_content(self, asset_id: str, kind: str | None = None) -> bytes:
        return self._request("GET", f"/v1/assets/{asset_id}/content", query={"kind": kind}, raw=True)

    def import_grab(self, sequence: str, mano: str, object_mesh: str, **optional) -> dict:
        return self._json("POST", "/v1/clips/import-grab",
                          {"sequence": sequence, "mano": mano, "object_mesh": object_mesh, **optional})

    def substitute_object(self, clip: str, object_mesh: str, **optional) -> dict:
        """A new clip asset: ``clip`` with its object replaced by the mesh asset ``object_mesh``
        (optional: transform (16 numbers), min_share, allow_intersection, name)."""
        return self._json("POST", "/v1/clips/substitute", {"clip": clip, "object_mesh": object_mesh, **optional})

    def propose_annotations(self, target_rig: str, source_rig: str | None = None) -> dict:
        """The core's proposed annotations for ``target_rig``, stored as an annotations asset."""
        return self._json("POST", "/v1/annotations/propose", {"target_rig": target_rig, "source_rig": source_rig})

    def submit(self, *, clip: str, rig: str, annotations: str, source_rig: str | None = None, preset: str = "default",
               overrides: dict | None = None, evaluate: bool = True, frames: tuple[int, int] | None = None,
               idempotency_key: str | None = None, rig_asset_path: str | None = None) -> dict:
        """Queue a job; ``frames``: (start, end) of the clip to retarget, end excluded (None: all
        of it). With ``idempotency_key`` a repeated call returns the same job. ``rig_asset_path``:
        the path animation.usda sublayers (your own USD rig file, relative to where the layer
        will sit); None: the rig upload's own file name (a robot bundle: the job's rig.usda)."""
        doc = {"clip": clip, "rig": rig, "annotations": annotations, "preset": preset,
               "overrides": overrides or {}, "evaluate": evaluate}
        if source_rig:
            doc["source_rig"] = source_rig
        if frames is not None:
            doc["frames"] = list(frames)
        if rig_asset_path is not None:
            doc["rig_asset_path"] = rig_asset_path
        headers = {"Idempotency-Key": idempotency_key} if idempotency_key else None
        return self._json("POST", "/v1/jobs", doc, headers=headers)

    def job(self, job_id: str) -> dict:
        return self._request("GET", f"/v1/jobs/{job_id}")

    def jobs(self, state: str | None = None, *, page_size: int | None = None) -> list[dict]:
        """All your jobs (every page, oldest first)."""
        return self._pages("/v1/jobs", "jobs", {"state": state}, page_size)

    def delete_job(self, job_id: str) -> None:
        """Remove your finished job and its artifacts (409 while queued or running)."""
        self._request("DELETE", f"/v1/jobs/{job_id}")

    def cancel(self, job_id: str) -> dict:
        return self._request("POST", f"/v1/jobs/{job_id}/cancel")

    def events(self, job_id: str):
        """The job's server-sent events, as job dicts, until it reaches a final state."""
        req = urllib.request.Request(self.base + f"/v1/jobs/{job_id}/events",
                                     headers={"Authorization": f"Bearer {self.token}", "Accept": "text/event-stream"})
        try:
            resp = urllib.request.urlopen(req, timeout=self.timeout)
        except urllib.error.HTTPError as err:
            raise ServiceError(err.code, err.read().decode("utf-8", "replace"), "GET", req.selector) from None
        with resp:
            data = []
            for line in resp:
                line = line.decode("utf-8").rstrip("\r\n")
                if line.startswith("data:"):
                    data.append(line[5:].strip())
                elif not line and data:
                    yield json.loads("\n".join(data))
                    data = []

    def wait(self, job_id: str, *, timeout: float = 3600.0, poll: float = 0.5, on_progress=None) -> dict:
        """Poll until the job reaches a final state (``TimeoutError`` after ``timeout`` s);
        ``on_progress(job)`` on every poll. Returns the final job."""
        deadline = time.monotonic() + timeout
        while True:
            job = self.job(job_id)
            if on_progress:
                on_progress(job)
            if job["state"] in FINAL_STATES:
                return job
            if time.monotonic() > deadline:
                raise TimeoutError(f"job {job_id} still {job['state']} after {timeout:g} s")
            time.sleep(poll)

    def artifact(self, job_id: str, name: str) -> bytes:
        return self._request("GET", f"/v1/jobs/{job_id}/artifacts/{name}", raw=True)

    def download(self, job_id: str, name: str, dest) -> Path:
        """Write artifact ``name`` to ``dest`` atomically (a partial download never shows)."""
        dest = Path(dest)
        dest.parent.mkdir(parents=True, exist_ok=True)
        tmp = dest.with_name(f".{dest.name}.{os.getpid()}.part")
        tmp.write_bytes(self.artifact(job_id, name))
        os.replace(tmp, dest)
        return dest

    def download_result(self, job_id: str, folder) -> dict:
        """Every artifact of a succeeded job into ``folder``; {name: path}. The USD layers
        reference rig.usda beside them, so keep the folder together."""
        job = self.job(job_id)
        return {name: self.download(job_id, name, Path(folder) / name) for name in job["artifacts"]}


def reachable(base_url: str, timeout: float = 1.0) -> bool:
    """Whether something answers /v1/health at ``base_url``."""
    try:
        with urllib.request.urlopen(base_url.rstrip("/") + "/v1/health", timeout=timeout) as resp:
            return resp.status == 200
    except (urllib.error.URLError, socket.timeout, ConnectionError):
        return False
