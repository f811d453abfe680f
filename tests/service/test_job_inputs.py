"""What a job may run on: a frame range of the clip, no execution settings in the overrides,
only a demo source hand named by a clip, and the job process's failures told apart (bad input
fails with the core's message; any other exception is an internal error with its traceback
in the log)."""

from __future__ import annotations

import dataclasses
import json
import logging
import shutil

import pytest

from dcc_client.client import ServiceError

from .conftest import FAST, RES, upload_inputs


@pytest.fixture(scope="module")
def carl(service):
    return service.client("carl")


@pytest.fixture(scope="module")
def long_clip(inputs):
    """The demo clip at a slower time scale: 87 frames, so a range [10, 70) fits in it."""
    from retarget_core.clip.demo import make_demo_clip

    clip = make_demo_clip("bottle_pick_place", time_scale=0.1, resolution=RES, rig=inputs["source"])
    assert clip.n_frames > 70
    path = inputs["folder"] / "long_clip.npz"
    clip.save(path)
    return path


@pytest.fixture(scope="module")
def foreign_clip(inputs):
    """The demo clip naming a rig file on disk (a readable USD rig) as its source rig."""
    from retarget_core.clip import load_clip

    clip = dataclasses.replace(load_clip(inputs["clip"]), source_rig=str(inputs["rig"]))
    path = inputs["folder"] / "foreign_clip.npz"
    clip.save(path)
    return path


def test_a_frame_range_retargets_that_part_of_the_clip(carl, inputs, long_clip):
    ids = upload_inputs(carl, inputs) | {"clip": carl.upload("clip", long_clip)["id"]}
    job = carl.submit(**ids, overrides=FAST, evaluate=False, frames=(10, 70))
    assert job["request"]["frames"] == [10, 70]
    final = carl.wait(job["id"], timeout=600, poll=0.2)
    assert final["state"] == "succeeded", final["error"]
    assert final["frames_done"] == final["frames_total"] == 60 and final["summary"]["frames"] == 60
    doc = json.loads(carl.artifact(job["id"], "result.json"))
    assert doc["frames"] == [10, 70] and len(doc["q"]) == 60 and len(doc["times"]) == 60
    assert doc["provenance"]["frames"] == [10, 70]
    # provenance names the assets, never the store's files
    clip_entry = doc["provenance"]["inputs"]["clip"]
    assert clip_entry["asset"] == ids["clip"] and "path" not in clip_entry
    assert doc["provenance"]["executor"]["atlas_cache"] == "cache/atlas"


@pytest.mark.parametrize("frames, message", [
    ([10, 999], "frames 10:999 are not a non-empty range within the clip's 0:46"),  # checked against the clip
    ([30, 30], "0 <= start < end"),
    ([-1, 20], "0 <= start < end"),
    ([10.5, 20], "frames"),
    (["10", 20], "frames"),
    ([10], "frames"),
])
def test_a_bad_frame_range_is_refused_at_submission(carl, inputs, frames, message):
    ids = upload_inputs(carl, inputs)
    before = carl.jobs()
    with pytest.raises(ServiceError) as err:
        carl.submit(**ids, frames=frames)
    assert err.value.status == 422 and message in err.value.detail, err.value.detail
    assert carl.jobs() == before


def test_workers_in_the_overrides_names_the_executor_option(carl, inputs):
    ids = upload_inputs(carl, inputs)
    before = carl.jobs()
    with pytest.raises(ServiceError) as err:
        carl.submit(**ids, overrides={"workers": 2})
    detail = err.value.detail
    assert err.value.status == 422, detail
    assert "workers" in detail and "executor's worker count" in detail and "the service's --workers" in detail
    assert carl.jobs() == before


def test_a_clip_naming_a_rig_file_as_its_source_is_refused(carl, inputs, foreign_clip):
    ids = upload_inputs(carl, inputs) | {"clip": carl.upload("clip", foreign_clip)["id"]}
    with pytest.raises(ServiceError) as err:
        carl.submit(**ids, overrides=FAST)
    detail = err.value.detail
    assert err.value.status == 422, detail
    assert "source_rig" in detail and "not a demo hand" in detail and str(inputs["rig"]) in detail


# ---- the job process, run in this process on a store filled directly --------------------------
OWNER = "olga"


def _running_job(data_dir, files: dict, **request):
    """A store holding ``files`` ({request field: (kind, path)}) as OWNER's assets and one job
    on them, claimed (``running``), as the runner would hand it to a job process. The router's
    checks are bypassed on purpose: the job process must enforce its own."""
    from retarget_core.inputs import file_sha256
    from server.schemas import JobCreate
    from server.storage import Store

    store = Store(data_dir)
    ids = {}
    for field, (kind, path) in files.items():
        sha = file_sha256(path)
        tmp = store.new_tmp(path.suffix)
        shutil.copyfile(path, tmp)
        store.add_asset(OWNER, sha, kind, path.name, path.stat().st_size, store.put_blob(tmp, sha, path.suffix), {})
        ids[field] = sha
    job, _ = store.create_job(OWNER, JobCreate(**ids, **request), None, max_active=10)
    claimed = store.claim_next_job()
    assert claimed.id == job.id
    return store, job.id


def _files(inputs, clip):
    return {"clip": ("clip", clip), "rig": ("rig", inputs["rig"]),
            "annotations": ("annotations", inputs["annotations"])}


def test_the_job_process_itself_refuses_a_clip_naming_a_rig_file(tmp_path, inputs, foreign_clip, caplog,
                                                                  monkeypatch):
    from retarget_core.rig import io
    from server.job_process import run_job
    from server.schemas import JobState
    from server.settings import Settings

    opened = []
    real_load_rig = io.load_rig
    monkeypatch.setattr(io, "load_rig", lambda path, **kw: (opened.append(str(path)), real_load_rig(path, **kw))[1])
    store, job_id = _running_job(tmp_path / "data", _files(inputs, foreign_clip), overrides=FAST)
    with caplog.at_level(logging.INFO, logger="server.job"):
        state = run_job(store, job_id, Settings(data_dir=store.paths.root))
    job = store.job(job_id)
    assert state == job.state == JobState.FAILED
    assert "not a demo hand" in job.error and not job.error.startswith("internal error")
    assert str(inputs["rig"]) not in opened  # refused, never opened
    assert str(store.paths.root) not in job.error  # the store's paths are not shown to the owner
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]  # bad input is not a bug


def test_a_value_error_inside_the_run_is_an_internal_error_with_its_traceback(tmp_path, inputs, caplog, monkeypatch):
    """A numpy-style ValueError raised by the pipeline is a bug, not bad input. It is injected
    here with monkeypatch (in this process, run_job called directly): the contact pairing raises
    as a shape mismatch in numpy would."""
    import retarget_core.pipeline
    from server.job_process import run_job
    from server.schemas import JobState
    from server.settings import Settings

    message = "operands could not be broadcast together with shapes (46,3) (45,3)"

    def broken_pairing(clip):
        raise ValueError(message)

    monkeypatch.setattr(retarget_core.pipeline, "pair_contacts", broken_pairing)
    store, job_id = _running_job(tmp_path / "data", _files(inputs, inputs["clip"]), overrides=FAST)
    with caplog.at_level(logging.INFO, logger="server.job"):
        state = run_job(store, job_id, Settings(data_dir=store.paths.root))
    job = store.job(job_id)
    assert state == job.state == JobState.FAILED
    assert job.error == f"internal error (ValueError): {message}"
    errors = [r for r in caplog.records if r.name == "server.job" and r.levelno == logging.ERROR]
    assert len(errors) == 1 and errors[0].exc_info and errors[0].exc_info[0] is ValueError
    assert "Traceback" in caplog.text and "broken_pairing" in caplog.text
    assert not store.paths.job(job_id).exists() and not list(store.paths.tmp.glob("*.out"))


def test_a_full_disk_queues_the_job_again_without_spending_an_attempt(tmp_path, inputs, caplog, monkeypatch):
    """Issue 16 (Low: "a full disk fails the job for good with a 500"): ENOSPC is injected at the
    storage layer with monkeypatch (a disk cannot be filled in CI): Store.publish_artifacts raises
    it as a full disk would. The job is queued again with a clear message and its attempt back,
    its scratch output removed; a job process that ends so makes the runner hold off claiming."""
    import errno
    import subprocess
    import sys

    from server.job_process import DISK_FULL_STAGE, run_job
    from server.runner import DISK_FULL_BACKOFF_S, JobRunner
    from server.schemas import JobState
    from server.settings import Settings
    from server.storage import Store

    def full_disk(self, job_id, folder):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(Store, "publish_artifacts", full_disk)
    store, job_id = _running_job(tmp_path / "data", _files(inputs, inputs["clip"]), overrides=FAST)
    attempts = store.job(job_id).attempts
    with caplog.at_level(logging.INFO, logger="server.job"):
        state = run_job(store, job_id, Settings(data_dir=store.paths.root))
    job = store.job(job_id)
    assert state == job.state == JobState.QUEUED
    assert job.stage == DISK_FULL_STAGE and "disk is full" in job.error
    assert job.attempts == max(attempts - 1, 0)
    assert not list(store.paths.tmp.glob("*.out"))
    # the runner sees the job process end with its job queued again for the disk: it claims nothing
    runner = JobRunner(store, Settings(data_dir=store.paths.root))
    proc = subprocess.Popen([sys.executable, "-c", "pass"], start_new_session=True)
    proc.wait()
    runner.children[job_id] = proc
    runner._tick()
    assert runner._hold_until - DISK_FULL_BACKOFF_S <= __import__("time").monotonic() < runner._hold_until
    runner._tick()
    assert store.job(job_id).state == JobState.QUEUED and not runner.children  # not claimed during the hold
