"""Jobs: submit (with an Idempotency-Key), list, status, a server-sent events stream of
progress, cancel, and the artifacts of a finished job."""

from __future__ import annotations

import asyncio
import json
import time

from fastapi import APIRouter, Depends, Header, HTTPException, Path, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse, StreamingResponse

from ..deps import current_owner, decode_cursor, encode_cursor, get_settings, get_store, require_intact
from ..schemas import DEFAULT_PAGE, MAX_PAGE, Job, JobCreate, JobList, JobState, Problem
from ..settings import Settings
from ..storage import JobRow, Store
from .assets import BAD_BODY, owned

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])
JOB_ID = r"^[0-9a-f]{32}$"
ARTIFACTS = {  # name -> media type; nothing else under a job's folder is ever served
    "animation.usda": "text/plain", "animation.usdc": "application/octet-stream", "rig.usda": "text/plain",
    "result.json": "application/json", "animation.json": "application/json", "metrics.json": "application/json",
    "intersection.png": "image/png", "contact_error.png": "image/png", "contact_sheet.png": "image/png",
    "preview.gif": "image/gif", "pictures.json": "application/json",
}
ERRORS = {401: {"model": Problem}, 404: {"model": Problem}, 409: {"model": Problem}, 422: {"model": Problem},
          429: {"model": Problem}}


def public(store: Store, job: JobRow) -> Job:
    """The job as the API shows it (no owner, pid or idempotency key), with its artifacts."""
    folder = store.paths.job(job.id)
    artifacts = sorted(n for n in ARTIFACTS if (folder / n).is_file()) if job.state == JobState.SUCCEEDED else []
    return Job(id=job.id, state=job.state, stage=job.stage, progress=job.progress, frames_done=job.frames_done,
               frames_total=job.frames_total, attempts=job.attempts, created=job.created, started=job.started,
               finished=job.finished, timings=job.timings, summary=job.summary, error=job.error, request=job.request,
               artifacts=artifacts)


def _own_job(store: Store, owner: str, job_id: str) -> JobRow:
    job = store.job(job_id, owner)
    if job is None:
        raise HTTPException(404, f"no job {job_id} of yours")
    return job


def check_request(body: JobCreate, owner: str, store: Store) -> None:
    """Everything that can be checked before the job runs, with the core's own rules: the
    assets are the caller's and of the right kind, a clip without ``source_rig`` names a demo
    hand (:func:`~retarget_core.inputs.clip_source_rig`; the job process's ``load_inputs``
    enforces it again), the frame range fits the clip, the config is valid, and the
    annotations were made for these meshes."""
    from types import SimpleNamespace

    from retarget_core.clip import load_clip
    from retarget_core.errors import InputError
    from retarget_core.inputs import clip_source_rig, frame_range
    from retarget_core.solve.config import load_config

    from ..assets import recorded_source_rig

    clip = owned(store, owner, body.clip, "clip", "clip")
    rig = owned(store, owner, body.rig, "rig", "rig")
    annotations = owned(store, owner, body.annotations, "annotations", "annotations")
    source = owned(store, owner, body.source_rig, "rig", "source_rig") if body.source_rig else None
    if source is None:
        try:  # a GRAB clip's MANO hand: by its content hash, among the caller's own rigs
            source = recorded_source_rig(store, owner, clip)
        except InputError as err:
            raise HTTPException(422, str(err)) from err
        if source is not None:
            require_intact(store, source, "source_rig")
    try:
        load_config(None, body.preset, body.overrides)
    except InputError as err:  # e.g. "workers" names the executor option (the service's --workers)
        raise HTTPException(422, str(err) if err.source == "overrides" else f"overrides: {err}") from err
    try:
        frame_range(body.frames, clip.info["frames"])
        if source is None:  # no rig given or recorded by hash: the clip must name a demo hand
            # the clip's source_rig field as recorded at upload: the clip is not read again here
            named = (SimpleNamespace(source_rig=clip.info["source_rig"]) if "source_rig" in clip.info
                     else load_clip(store.asset_path(clip)))
            clip_source_rig(named)
    except InputError as err:  # its message names the field ("frames: ...", "clip: source_rig: ...")
        raise HTTPException(422, _without_paths(str(err), store)) from err
    ann = annotations.info
    for side, asset, field in (("target", rig, "rig"), ("source", source, "source_rig")):
        if asset is not None:
            _same_mesh(ann[side], asset.info["vertices"], asset.info["faces"], side, f"{field} {asset.info['name']!r}")
    # the clip's hand is the source hand's surface (before any caps that close it): checked
    # here too, also for a demo source hand
    hand_mesh = (source.info.get("hand_mesh") if source is not None else None) or ann["source"]
    if (hand_mesh["vertices"], hand_mesh["faces"]) != (clip.info["hand_vertices"], clip.info["hand_faces"]):
        what = f"source_rig {source.info['name']!r}" if source is not None else "the annotations' source hand"
        raise HTTPException(422, f"the clip's hand has {clip.info['hand_vertices']} vertices and "
                                 f"{clip.info['hand_faces']} faces, but {what} carries {hand_mesh['vertices']} and "
                                 f"{hand_mesh['faces']}: pass the rig the clip was made with as source_rig (a GRAB "
                                 "import makes it: its clip's info.source_rig_asset) with annotations made for it")


def _same_mesh(sig: dict, vertices: int, faces: int, side: str, what: str, hint: str = "") -> None:
    """422 unless the annotations' ``side`` mesh signature has these vertex and face counts."""
    if (sig["vertices"], sig["faces"]) != (vertices, faces):
        raise HTTPException(422, f"annotations: made for a {side} mesh of {sig['vertices']} vertices and "
                                 f"{sig['faces']} faces ({sig['rig']!r}), but {what} has {vertices} and {faces}; "
                                 + (hint or "annotate this rig (or ask POST /v1/annotations/propose)"))


def _without_paths(message: str, store: Store) -> str:
    """The client never sees the store's paths."""
    return message.replace(str(store.paths.root), "DATA")


@router.post("", response_model=Job, status_code=201, responses=ERRORS | BAD_BODY | {200: {"model": Job}})
def create_job(body: JobCreate, response: Response, owner: str = Depends(current_owner),
               idempotency_key: str | None = Header(default=None, max_length=200,
                                                    description="repeat a submission safely: the same key returns "
                                                                "the same job"),
               store: Store = Depends(get_store), settings: Settings = Depends(get_settings)):
    """Queue a retarget of ``clip`` onto ``rig`` with ``annotations``."""
    check_request(body, owner, store)
    try:
        job, created = store.create_job(owner, body, idempotency_key, settings.max_active_jobs)
    except LookupError as err:
        raise HTTPException(429, f"{err}; wait for some to finish or cancel them", headers={"Retry-After": "10"}) from err
    except ValueError as err:
        raise HTTPException(409, f"Idempotency-Key: {err}; use a new key for a new job") from err
    response.status_code = 201 if created else 200
    return public(store, job)


@router.get("", response_model=JobList, responses=ERRORS)
def list_jobs(state: JobState | None = Query(default=None),
              limit: int = Query(default=DEFAULT_PAGE, ge=1, le=MAX_PAGE, description="jobs per page"),
              cursor: str | None = Query(default=None, max_length=500,
                                         description="the next_cursor of the previous page"),
              owner: str = Depends(current_owner), store: Store = Depends(get_store)):
    """Your jobs, oldest first, ``limit`` per page; follow ``next_cursor`` for the rest."""
    after = decode_cursor(cursor, (float, str))
    rows = store.jobs(owner, (state,) if state else None, limit=limit + 1, after=after)
    more = len(rows) > limit
    rows = rows[:limit]
    return {"jobs": [public(store, j) for j in rows],
            "next_cursor": encode_cursor(rows[-1].created, rows[-1].id) if more else None}


@router.delete("/{job_id}", status_code=204, response_class=Response, responses=ERRORS)
def delete_job(job_id: str = Path(..., pattern=JOB_ID), owner: str = Depends(current_owner),
               store: Store = Depends(get_store)):
    """Remove one of your finished jobs with its artifacts (409 while queued or running:
    cancel it first)."""
    try:
        if not store.delete_job(owner, job_id):
            raise HTTPException(404, f"no job {job_id} of yours")
    except LookupError as err:
        raise HTTPException(409, str(err)) from err
    return Response(status_code=204)


@router.get("/{job_id}", response_model=Job, responses=ERRORS)
def get_job(job_id: str = Path(..., pattern=JOB_ID), owner: str = Depends(current_owner),
            store: Store = Depends(get_store)):
    return public(store, _own_job(store, owner, job_id))


@router.post("/{job_id}/cancel", response_model=Job, status_code=202, responses=ERRORS)
def cancel_job(job_id: str = Path(..., pattern=JOB_ID), owner: str = Depends(current_owner),
               store: Store = Depends(get_store)):
    """Cancel a queued job at once, or ask a running one to stop (it turns ``cancelled``)."""
    job = _own_job(store, owner, job_id)
    if job.state.final:
        raise HTTPException(409, f"job {job_id} already {job.state}; nothing to cancel")
    if not store.update_job(job_id, only_if_state=(JobState.QUEUED,), state=JobState.CANCELLED, stage="cancelled",
                            cancel_requested=1, finished=time.time()):
        store.update_job(job_id, only_if_state=(JobState.RUNNING,), cancel_requested=1)
    return public(store, store.job(job_id))


@router.get("/{job_id}/events", responses=ERRORS | {200: {"content": {"text/event-stream": {}}}})
async def job_events(request: Request, job_id: str = Path(..., pattern=JOB_ID), owner: str = Depends(current_owner),
                     store: Store = Depends(get_store), settings: Settings = Depends(get_settings)):
    """Server-sent events: a ``status`` event (the job as JSON) whenever it changes, ending
    after a final state (or when the service shuts down). At most ``max_streams_per_owner``
    streams per owner at once (429 beyond)."""
    await run_in_threadpool(_own_job, store, owner, job_id)
    app = request.app
    streams = app.state.streams  # owner -> open streams (create_app makes it)
    if streams.get(owner, 0) >= settings.max_streams_per_owner:
        raise HTTPException(429, f"you already have {streams[owner]} event streams open (the limit is "
                                 f"{settings.max_streams_per_owner}); close one or poll GET /v1/jobs/{{id}}",
                            headers={"Retry-After": "5"})

    def shutting_down() -> bool:
        server = getattr(app.state, "server", None)
        return server is not None and server.should_exit

    async def stream():
        last = None
        streams[owner] = streams.get(owner, 0) + 1  # counted once it runs: its finally always follows
        try:
            while not shutting_down():
                job = await run_in_threadpool(store.job, job_id)
                if job is None:  # deleted meanwhile
                    return
                data = json.dumps(public(store, job).model_dump(mode="json"))
                if data != last:
                    last = data
                    yield f"event: status\ndata: {data}\n\n"
                if job.state.final:
                    return
                await asyncio.sleep(0.2)
        finally:
            streams[owner] -= 1

    return StreamingResponse(stream(), media_type="text/event-stream", headers={"Cache-Control": "no-cache"})


@router.get("/{job_id}/artifacts/{name}", response_class=FileResponse, responses=ERRORS)
def get_artifact(name: str, job_id: str = Path(..., pattern=JOB_ID), owner: str = Depends(current_owner),
                 store: Store = Depends(get_store)):
    """One artifact of a succeeded job: animation.usda / .usdc (over rig.usda, which is also
    served), result.json, animation.json (joint values per frame), metrics.json, and the
    report's plots (intersection.png, contact_error.png) and the pictures of the delivered curve
    (contact_sheet.png, preview.gif, pictures.json)."""
    if name not in ARTIFACTS:
        raise HTTPException(404, f"no artifact {name!r}; artifacts are: {', '.join(sorted(ARTIFACTS))}")
    job = _own_job(store, owner, job_id)
    if job.state != JobState.SUCCEEDED:
        raise HTTPException(409, f"job {job_id} is {job.state}; artifacts exist once it has succeeded")
    path = store.paths.job(job_id) / name
    if not path.is_file():
        raise HTTPException(404, f"job {job_id} has no {name} (see the job's artifacts list)")
    problem = store.artifact_problem(job_id, name)
    if problem is not None:
        raise HTTPException(500, f"artifact {name} of job {job_id} is {problem} on the server (its sha256 no longer "
                                 "matches the one recorded when the job finished); submit the job again")
    return FileResponse(path, media_type=ARTIFACTS[name], filename=name)
