"""Bounded work (issue 16, Build 2) against a real service on 127.0.0.1: hostile clips built here
(nothing hostile is committed), overrides beyond their bounds, a clip choosing a tiny source
resolution, and jobs past a small time or memory limit. Each test names the finding it covers;
each failed on main at 328eb67 (upload validation ran in the API process and read arrays whole,
overrides had no upper bound, a clip's demo resolution was unbounded, jobs had no limits)."""

from __future__ import annotations

import io
import json
import time
import urllib.error
import urllib.request
import zipfile

import numpy as np
import pytest

from dcc_client.client import ServiceError

from .conftest import FAST, Service, upload_inputs


def _pss(pid: int) -> int:
    with open(f"/proc/{pid}/smaps_rollup") as fh:
        for line in fh:
            if line.startswith("Pss:"):
                return int(line.split()[1]) * 1024
    return 0


def _peak_during(pid: int, fn):
    """(fn(), the peak PSS of process ``pid`` while fn ran, sampled every 20 ms)."""
    import threading

    peak, stop = [_pss(pid)], threading.Event()

    def sample():
        while not stop.wait(0.02):
            peak.append(_pss(pid))

    thread = threading.Thread(target=sample, daemon=True)
    thread.start()
    try:
        result = fn()
    finally:
        stop.set()
        thread.join()
    return result, max(peak)


def _post(svc: Service, token: str, path: str, body: bytes, content_type: str = "application/octet-stream"):
    """(status, content type, parsed JSON or text) of a raw POST."""
    req = urllib.request.Request(svc.url + path, data=body, method="POST",
                                 headers={"Authorization": f"Bearer {token}", "Content-Type": content_type})
    try:
        with urllib.request.urlopen(req, timeout=120) as resp:
            status, ctype, data = resp.status, resp.headers.get("content-type", ""), resp.read()
    except urllib.error.HTTPError as err:
        status, ctype, data = err.code, err.headers.get("content-type", ""), err.read()
    try:
        return status, ctype, json.loads(data)
    except ValueError:
        return status, ctype, data.decode("utf-8", "replace")


def _npy(array=None, *, header=None, data=b"") -> bytes:
    buf = io.BytesIO()
    if array is not None:
        np.lib.format.write_array(buf, np.asarray(array), allow_pickle=False)
    else:
        np.lib.format.write_array_header_1_0(buf, header)
        buf.write(data)
    return buf.getvalue()


def _clip_bytes(inputs, **members) -> bytes:
    """The test clip's npz with ``members`` (field -> npy bytes) replaced."""
    with zipfile.ZipFile(inputs["clip"]) as z:
        content = {n.removesuffix(".npy"): z.read(n) for n in z.namelist()}
    content.update(members)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as z:
        for name, payload in content.items():
            z.writestr(name + ".npy", payload)
    return buf.getvalue()


@pytest.fixture(scope="module")
def limited(tmp_path_factory):
    """A service whose upload validation may use 250 MB."""
    svc = Service(tmp_path_factory.mktemp("limits") / "data", "--validation-memory-mb", "250").start()
    yield svc
    svc.stop()


@pytest.fixture(scope="module")
def token(limited):
    return limited.token("mallory")


# ---- High: "a 1.18 MB clip (an npz decompression bomb) took the server from 311 MB to 1.5 GB" ----

def test_an_npz_bomb_is_refused_and_the_server_stays_small(limited, token, inputs):
    # 400 MB of zeros as hand_vertices, about 400 KB compressed: over the 250 MB validation limit
    bomb = _clip_bytes(inputs, hand_vertices=_npy(np.zeros((100, 333_334, 3), np.float32)))
    assert len(bomb) < 1_000_000
    before = _pss(limited.proc.pid)
    t0 = time.monotonic()
    (status, ctype, body), peak = _peak_during(
        limited.proc.pid, lambda: _post(limited, token, "/v1/assets/clip?name=bomb.npz", bomb))
    # on 328eb67 the API process read the 400 MB array itself
    assert peak - before < 60 * 2**20, f"the server grew by {(peak - before) / 2**20:.0f} MB"
    assert status == 422, body
    assert "application/json" in ctype
    assert "hand_vertices" in body["detail"] and "over the limit" in body["detail"]
    assert time.monotonic() - t0 < 20


def test_a_bomb_within_the_header_limit_is_stopped_by_the_memory_limit(limited, token, inputs):
    # 200 MB of zeros: fits the 250 MB header check, but reading and checking it needs more
    bomb = _clip_bytes(inputs, hand_vertices=_npy(np.zeros((100, 175_000, 3), np.float32)))
    before = _pss(limited.proc.pid)
    (status, ctype, body), peak = _peak_during(
        limited.proc.pid, lambda: _post(limited, token, "/v1/assets/clip?name=bomb2.npz", bomb))
    assert peak - before < 60 * 2**20, f"the server grew by {(peak - before) / 2**20:.0f} MB"
    assert status == 413, body
    assert "application/json" in ctype
    assert "validation memory limit of 250 MB" in body["detail"]
    assert limited.client("mallory").health()["status"] == "ok"


# ---- Medium: malformed clips answered a plain-text 500 -------------------------------------

HUGE_HEADER = {"descr": "<f4", "fortran_order": False, "shape": (1_000_000, 1_000_000, 3)}


@pytest.mark.parametrize("field,payload,text", [
    ("fps", lambda: _npy(np.array([120.0, 60.0])), "fps"),
    ("fps", lambda: _npy(np.array("fast")), "fps"),
    ("version", lambda: _npy(np.array("one")), "version"),
    ("version", lambda: _npy(np.array([1, 1])), "version"),
    ("hand_faces", lambda: _npy(np.array([["a", "b", "c"]] * 10)), "hand_faces"),
    ("hand_vertices", lambda: _npy(header=HUGE_HEADER, data=b"\0" * 256), "hand_vertices"),
])
def test_malformed_clip_fields_get_a_4xx_json_error(limited, token, inputs, field, payload, text):
    status, ctype, body = _post(limited, token, f"/v1/assets/clip?name={field}.npz",
                                _clip_bytes(inputs, **{field: payload()}))
    assert 400 <= status < 500, body
    assert "application/json" in ctype
    assert text in body["detail"]


def test_a_clip_with_a_flipped_byte_gets_a_4xx_json_error(limited, token, inputs):
    raw = bytearray(inputs["clip"].read_bytes())
    with zipfile.ZipFile(inputs["clip"]) as z:
        info = z.getinfo("hand_vertices.npy")
    start = info.header_offset + 30 + len(info.filename) + len(info.extra)
    raw[start + info.compress_size // 2] ^= 0xFF
    status, ctype, body = _post(limited, token, "/v1/assets/clip?name=flipped.npz", bytes(raw))
    assert 400 <= status < 500, body
    assert "application/json" in ctype


# ---- High: overrides without upper bounds; Low: maxeval >= 2^31, lowpass_order 1e6 ----------

@pytest.mark.parametrize("key,value", [("refinement.max_iterations", 10**9), ("solver.maxeval", 2**31),
                                       ("refinement.lowpass_order", 10**6), ("solver.root_maxeval", 2**31)])
def test_overrides_beyond_their_bounds_are_refused_at_submission(limited, inputs, key, value):
    client = limited.client("bounds")
    ids = upload_inputs(client, inputs)
    with pytest.raises(ServiceError) as err:
        client.submit(**ids, overrides={key: value})
    assert err.value.status == 422
    assert key in err.value.detail and "must be in" in err.value.detail
    assert client.jobs() == []


# ---- High: a clip's source_rig "demo:source_human@0.0007" built an enormous hand; Low: "@0" ----

@pytest.mark.parametrize("res", ["0.0007", "0", "nan", "-0.004"])
def test_a_clip_choosing_a_tiny_source_resolution_is_refused(limited, inputs, tmp_path, res):
    from retarget_core.clip import load_clip

    clip = load_clip(inputs["clip"])
    clip.source_rig = f"demo:source_human@{res}"
    clip.save(tmp_path / "tiny.npz")
    client = limited.client("tiny")
    ids = upload_inputs(client, inputs)
    ids["clip"] = client.upload("clip", tmp_path / "tiny.npz")["id"]
    with pytest.raises(ServiceError) as err:
        client.submit(**ids, overrides=FAST)
    assert err.value.status == 422
    assert "source_rig" in err.value.detail and "resolution" in err.value.detail


# ---- High: "jobs no time limit"; and no memory limit (@0.0005 passed 3.9 GB) --------------

# work within every bound, but far more than 5 s of it
SLOW = {"solver.maxeval": 10_000, "solver.root_maxeval": 10_000, "solver.xtol_rel": 0.0,
        "solver.warm_start_iterations": 200, "refinement.max_iterations": 200}


def _run_to_end(svc: Service, inputs, overrides, timeout: float = 180) -> dict:
    client = svc.client("limited")
    job = client.submit(**upload_inputs(client, inputs), overrides=overrides)
    return client.wait(job["id"], timeout=timeout)


def test_a_job_past_its_time_limit_fails_with_a_clear_message(tmp_path_factory, inputs):
    svc = Service(tmp_path_factory.mktemp("timelimit") / "data", "--job-time-limit", "5").start()
    try:
        t0 = time.monotonic()
        final = _run_to_end(svc, inputs, SLOW)
        assert final["state"] == "failed"
        assert "exceeded the job time limit of 5 s" in final["error"]
        assert time.monotonic() - t0 < 60
        assert final["attempts"] == 1  # failed for good, not re-run
    finally:
        svc.stop()


def test_a_job_past_its_memory_limit_fails_with_a_clear_message(tmp_path_factory, inputs):
    svc = Service(tmp_path_factory.mktemp("memlimit") / "data", "--job-memory-mb", "300", "--workers", "2").start()
    try:
        final = _run_to_end(svc, inputs, FAST)
        assert final["state"] == "failed"
        assert "exceeded the job memory limit of 300 MB" in final["error"], final
        assert final["attempts"] == 1
    finally:
        svc.stop()


def test_limits_are_settings_with_documented_defaults():
    from server.settings import Settings

    s = Settings(data_dir="x")
    assert (s.job_time_limit_s, s.job_memory_mb, s.validation_memory_mb) == (3600.0, 4096, 1024)


WATCHDOG_SCRIPT = """
import json, subprocess, sys, time
from server.job_process import Watchdog

class FakeStore:
    def update_job(self, job_id, **fields):
        with open(sys.argv[1], "w") as fh:
            json.dump({"job": job_id, "state": str(fields["state"].value), "error": fields["error"]}, fh)

pool = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
with open(sys.argv[2], "w") as fh:
    fh.write(str(pool.pid))
with Watchdog(FakeStore(), "job1", time_limit_s=1.0, memory_bytes=2**40, interval=0.05):
    time.sleep(30)
"""


def test_the_watchdog_fails_the_job_and_stops_its_pool(tmp_path):
    """The job process's watchdog, in a process of its own with a fake store: past the time limit
    it marks the job failed with the limit's message, kills the processes below it (its pool)
    and exits with code 4."""
    import subprocess
    import sys
    from pathlib import Path

    from server.job_process import Watchdog

    record, pool_pid = tmp_path / "record.json", tmp_path / "pool.pid"
    t0 = time.monotonic()
    proc = subprocess.run([sys.executable, "-c", WATCHDOG_SCRIPT, str(record), str(pool_pid)], timeout=60,
                          cwd=str(Path(__file__).resolve().parents[2]), capture_output=True, text=True)
    assert proc.returncode == Watchdog.EXIT_CODE, proc.stderr
    assert time.monotonic() - t0 < 20
    doc = json.loads(record.read_text())
    assert doc["job"] == "job1" and doc["state"] == "failed"
    assert doc["error"].startswith("exceeded the job time limit of 1 s")
    pid = int(pool_pid.read_text())
    time.sleep(0.2)
    # gone, or a zombie its new parent has not reaped yet
    assert not Path(f"/proc/{pid}").exists() or "Z" in Path(f"/proc/{pid}/stat").read_text().split(")")[1][:3]


def test_the_memory_check_names_the_limit():
    from server.job_process import Watchdog

    small = Watchdog(None, "job2", time_limit_s=3600, memory_bytes=10 * 2**20)
    assert small.check().startswith("exceeded the job memory limit of 10 MB")
