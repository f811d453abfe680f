"""Assets: upload (content-addressed, validated by the core's readers), list, describe,
download; the GRAB importer; proposed annotations."""

from __future__ import annotations

import asyncio
import errno
import hashlib
import shutil
from pathlib import PurePath

from fastapi import APIRouter, Depends, HTTPException, Path, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import FileResponse

from ..assets import UploadError, annotations_info, stored_rig_options
from ..isolation import (MIB, MemoryLimitExceeded, ValidatorCrashed, import_grab_isolated, substitute_isolated,
                         validate_isolated)
from ..deps import current_owner, decode_cursor, encode_cursor, get_settings, get_store, require_intact
from ..schemas import (DEFAULT_PAGE, MAX_PAGE, SHA256, Asset, AssetKind, AssetList, GrabImport, Problem, ProposeRequest,
                       SubstituteRequest)
from ..settings import Settings
from ..storage import AssetRow, Store
from ..zipcheck import check_zip

router = APIRouter(prefix="/v1", tags=["assets"])
ERRORS = {401: {"model": Problem}, 404: {"model": Problem}, 413: {"model": Problem}, 422: {"model": Problem}}
# a JSON body that cannot be read at all (e.g. not UTF-8) is refused by FastAPI with 400
BAD_BODY = {400: {"model": Problem, "description": "the body could not be parsed"}}


def owned(store: Store, owner: str, asset_id: str, kind: str, field: str) -> AssetRow:
    """The owner's asset of ``kind``, its stored file intact; 404 naming the request field
    otherwise (another owner's asset is as unknown as a missing one), 410 if damaged."""
    asset = store.asset(owner, asset_id, kind)
    if asset is None:
        raise HTTPException(404, f"{field}: no {kind} asset {asset_id} of yours; upload it with POST /v1/assets/{kind}")
    require_intact(store, asset, field)  # 410 when its stored file is missing or damaged
    return asset


async def _receive(request: Request, store: Store, limit: int, timeout: float | None = None):
    """Stream the body to a scratch file; (path, sha256, size). 413 beyond ``limit``, 408 when
    no byte arrives for ``timeout`` s (a stalled client), 507 when the disk is full; the
    scratch file is removed in every case."""
    declared = request.headers.get("content-length")
    if declared is not None and declared.isdigit() and int(declared) > limit:
        raise HTTPException(413, f"upload of {int(declared)} bytes is over the limit of {limit} bytes")
    tmp = store.new_tmp()
    digest, size = hashlib.sha256(), 0
    try:
        with tmp.open("wb") as out:
            chunks = request.stream().__aiter__()
            while True:
                try:
                    chunk = await asyncio.wait_for(chunks.__anext__(), timeout)
                except StopAsyncIteration:
                    break
                except asyncio.TimeoutError:
                    raise HTTPException(408, f"the upload stalled: no data for {timeout:g} s "
                                             f"(after {size} bytes); send the body again") from None
                size += len(chunk)
                if size > limit:
                    raise HTTPException(413, f"upload is over the limit of {limit} bytes")
                digest.update(chunk)
                out.write(chunk)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        if err.errno == errno.ENOSPC:
            raise HTTPException(507, "the server's disk is full; try again later") from None
        raise
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    if size == 0:
        tmp.unlink(missing_ok=True)
        raise HTTPException(422, "the upload is empty: send the file's bytes as the request body")
    return tmp, digest.hexdigest(), size


def _store_validated(store: Store, owner: str, kind: str, name: str, tmp, sha: str, size: int,
                     settings: Settings, rig_options: dict | None = None) -> tuple[AssetRow, bool]:
    options = {k: v for k, v in (rig_options or {}).items() if v is not None}
    # Only the caller's own identical upload is returned as is (and only while its blob is
    # intact: otherwise this upload repairs it). Another owner's identical upload is never
    # looked at: it would show in the timing and the info; the blob store keeps one copy.
    mine = store.asset(owner, sha, kind)
    if mine is not None and kind == "file" and PurePath(mine.path).suffix != PurePath(name).suffix.lower():
        tmp.unlink(missing_ok=True)
        raise HTTPException(409, f"you uploaded these bytes as a {PurePath(mine.path).suffix} file before (asset "
                                 f"{sha}); delete that asset to upload them as {PurePath(name).suffix or 'no suffix'}")
    if mine is not None and kind == "rig":
        before = mine.info.get("load_options") or mine.info.get("import_options") or {}
        if before != options:
            tmp.unlink(missing_ok=True)
            raise HTTPException(409, f"you uploaded these bytes as a rig with options {before or 'none'} before "
                                     f"(asset {sha}); delete that asset to upload them with {options or 'none'}")
    if mine is not None and store.blob_problem(store.asset_path(mine)) is None:
        tmp.unlink(missing_ok=True)
        return mine, False
    scratch = store.new_tmp(".d")
    scratch.mkdir()
    try:
        with tmp.open("rb") as head:
            zipped = head.read(4) == b"PK\x03\x04"
        if kind == "rig" and zipped:  # a malformed zip: 422 naming the problem, before the import
            check_zip(tmp, max_bytes=4 * settings.max_upload_bytes)
        # in a child process with a memory limit: a hostile upload never grows the server
        path, ext, info = validate_isolated(kind, tmp, name, scratch=scratch, bundle_bytes=4 * settings.max_upload_bytes,
                                            memory_bytes=settings.validation_memory_mb * MIB, rig_options=options)
        final = store.put_blob(path, sha, ext)
        return store.add_asset(owner, sha, kind, name, size, final, info)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
        for leftover in store.paths.tmp.glob(tmp.name + "*"):
            leftover.unlink(missing_ok=True)


@router.post("/assets/{kind}", response_model=Asset, status_code=201, responses=ERRORS | {200: {"model": Asset}},
             openapi_extra={"requestBody": {"required": True, "content": {
                 "application/octet-stream": {"schema": {"type": "string", "format": "binary"}}}}})
async def upload_asset(request: Request, response: Response, kind: AssetKind,
                       name: str = Query(..., min_length=1, max_length=200, description="the file's name"),
                       root_body: str | None = Query(None, min_length=1, max_length=200,
                                                     description="rig bundle with an MJCF hand: the hand's root body"),
                       hand_root: str | None = Query(None, min_length=1, max_length=200,
                                                     description="USD rig: the hand's root joint inside a larger "
                                                                 "skeleton (default: found)"),
                       owner: str = Depends(current_owner), store: Store = Depends(get_store),
                       settings: Settings = Depends(get_settings)):
    """Upload a rig (USD, or a zip of a URDF / MJCF hand), annotations (JSON), a clip (npz) or
    a raw file for the GRAB importer, as the request body. The asset's id is the sha256 of the
    bytes; uploading the same bytes again returns the same asset (200)."""
    tmp, sha, size = await _receive(request, store, settings.max_upload_bytes, settings.read_timeout_s)
    used = await run_in_threadpool(store.usage, owner)
    if used + size > settings.storage_quota_bytes:
        tmp.unlink(missing_ok=True)
        raise HTTPException(413, f"storage quota: you store {used} bytes and this upload is {size}; the quota is "
                                 f"{settings.storage_quota_bytes} bytes (--storage-quota-mb): delete assets or jobs "
                                 "(DELETE /v1/assets/{id}, DELETE /v1/jobs/{id})")
    try:
        asset, created = await run_in_threadpool(_store_validated, store, owner, kind, name, tmp, sha, size, settings,
                                                 {"root_body": root_body, "hand_root": hand_root})
    except UploadError as err:
        raise HTTPException(422, f"not a valid {kind}: {err}") from err
    except MemoryLimitExceeded as err:
        raise HTTPException(413, f"validating this {kind} {err}; the service refuses uploads that need more "
                                 "(--validation-memory-mb)") from err
    except ValidatorCrashed as err:
        raise HTTPException(422, f"not a valid {kind}: {err}") from err
    response.status_code = 201 if created else 200
    return asset.public()


@router.get("/assets", response_model=AssetList, responses=ERRORS)
def list_assets(kind: AssetKind | None = None,
                limit: int = Query(default=DEFAULT_PAGE, ge=1, le=MAX_PAGE, description="assets per page"),
                cursor: str | None = Query(default=None, max_length=500,
                                           description="the next_cursor of the previous page"),
                owner: str = Depends(current_owner), store: Store = Depends(get_store)):
    """Your assets, oldest first, ``limit`` per page; follow ``next_cursor`` for the rest."""
    rows = store.assets(owner, kind, limit=limit + 1, after=decode_cursor(cursor, (float, str, str)))
    more = len(rows) > limit
    rows = rows[:limit]
    return AssetList(assets=[a.public() for a in rows],
                     next_cursor=encode_cursor(rows[-1].created, rows[-1].sha256, rows[-1].kind) if more else None)


@router.delete("/assets/{asset_id}", status_code=204, response_class=Response,
               responses=ERRORS | {409: {"model": Problem}})
def delete_asset(asset_id: str = Path(..., pattern=SHA256), kind: AssetKind | None = None,
                 owner: str = Depends(current_owner), store: Store = Depends(get_store)):
    """Remove your asset (of ``kind``, or of every kind with this id); 409 while a queued or
    running job of yours uses it. The stored file goes once no owner's asset refers to it."""
    try:
        deleted = store.delete_asset(owner, asset_id, kind)
    except LookupError as err:
        raise HTTPException(409, str(err)) from err
    if not deleted:
        raise HTTPException(404, f"no asset {asset_id} of yours")
    return Response(status_code=204)


@router.get("/assets/{asset_id}", response_model=Asset, responses=ERRORS)
def get_asset(asset_id: str = Path(..., pattern=SHA256), kind: AssetKind | None = None,
              owner: str = Depends(current_owner), store: Store = Depends(get_store)):
    asset = store.asset(owner, asset_id, kind)
    if asset is None:
        raise HTTPException(404, f"no asset {asset_id} of yours")
    return asset.public()


@router.get("/assets/{asset_id}/content", response_class=FileResponse, responses=ERRORS)
def download_asset(asset_id: str = Path(..., pattern=SHA256), kind: AssetKind | None = None,
                   owner: str = Depends(current_owner), store: Store = Depends(get_store)):
    """The stored file (for a robot bundle: the USD rig imported from it)."""
    asset = store.asset(owner, asset_id, kind)
    if asset is None:
        raise HTTPException(404, f"no asset {asset_id} of yours")
    require_intact(store, asset)
    path = store.asset_path(asset)
    return FileResponse(path, filename=f"{asset.name.rsplit('.', 1)[0]}{path.suffix}",
                        media_type="application/octet-stream")


def _save_new_asset(store: Store, owner: str, kind: str, name: str, write, info: dict,
                    suffix: str | None = None) -> tuple[AssetRow, bool]:
    """Store a file the service made (``write(path)``) as ``owner``'s asset; (asset, created)."""
    tmp = store.new_tmp(suffix or (".npz" if kind == "clip" else ".json"))
    try:
        write(tmp)
        data = tmp.read_bytes()
        sha = hashlib.sha256(data).hexdigest()
        final = store.put_blob(tmp, sha, tmp.suffix)
    finally:
        tmp.unlink(missing_ok=True)
    return store.add_asset(owner, sha, kind, name, len(data), final, info)


def _isolated(what: str, doing: str, call):
    """``call()`` (work on uploads in a memory-limited child): a refusal or a crash of the child
    is a 422 ("cannot <what>: ..."), the memory limit a 413."""
    try:
        return call()
    except (UploadError, ValidatorCrashed) as err:
        raise HTTPException(422, f"cannot {what}: {err}") from err
    except MemoryLimitExceeded as err:
        raise HTTPException(413, f"{doing} {err}; the service refuses work that needs more "
                                 "(--validation-memory-mb)") from err


@router.post("/clips/import-grab", response_model=Asset, status_code=201, responses=ERRORS | BAD_BODY)
def import_grab(body: GrabImport, response: Response, owner: str = Depends(current_owner),
                store: Store = Depends(get_store), settings: Settings = Depends(get_settings)):
    """Convert one hand of a GRAB sequence (with the user's MANO model of that hand and the
    object's mesh, uploaded as ``file`` assets) into a clip asset and its MANO source rig, a rig
    asset (the clip's ``info.source_rig_asset``): a job on the clip finds that rig by its content
    hash among your assets, so no source_rig is needed."""
    def path(field):
        value = getattr(body, field)
        return None if value is None else store.asset_path(owned(store, owner, value, "file", field))

    paths = {f: path(f) for f in ("sequence", "mano", "object_mesh", "table_mesh", "vtemp")}
    scratch = store.new_tmp(".d")
    scratch.mkdir()
    try:  # in a child process with the validation memory limit, like an upload
        imported = _isolated("import the GRAB sequence", "importing the GRAB sequence",
                             lambda: import_grab_isolated(paths, scratch / "clip.npz", scratch=scratch, hand=body.hand,
                                                          memory_bytes=settings.validation_memory_mb * MIB))
        rig_name = body.name.removesuffix(".npz") + ".source_rig.usda"
        rig_asset, _ = _save_new_asset(store, owner, "rig", rig_name,
                                       lambda p: shutil.move(imported["rig_path"], str(p)),
                                       imported["rig_info"] | {"imported_from": "grab"}, suffix=".usda")
        asset, created = _save_new_asset(store, owner, "clip", body.name,
                                         lambda p: shutil.move(str(scratch / "clip.npz"), str(p)),
                                         imported["info"] | {"imported_from": "grab", "source_rig_asset": rig_asset.sha256})
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    response.status_code = 201 if created else 200
    return asset.public()


@router.post("/clips/substitute", response_model=Asset, status_code=201, responses=ERRORS | BAD_BODY)
def substitute(body: SubstituteRequest, response: Response, owner: str = Depends(current_owner),
               store: Store = Depends(get_store), settings: Settings = Depends(get_settings)):
    """A new clip asset: ``clip`` with its object replaced by the mesh ``object_mesh`` (placed
    by registration onto the old object, or by ``transform``), the contacts traced onto it.
    Refused with a 422 naming the figure when too few contacts reach the new object or the
    source hand would lie inside it (the frames named); the asset's ``info.substitution`` has
    the share carried over, the fit's residual, the transform used and any mesh repairs."""
    clip = owned(store, owner, body.clip, "clip", "clip")
    mesh = owned(store, owner, body.object_mesh, "file", "object_mesh")
    if PurePath(mesh.path).suffix.lower() not in (".ply", ".obj", ".stl", ".off"):
        raise HTTPException(422, f"object_mesh: asset {mesh.sha256} is a {PurePath(mesh.path).suffix} file, "
                                 "not a mesh (.ply / .obj / .stl / .off)")
    options = {"register": body.transform is None, "transform": body.transform, "min_share": body.min_share,
               "allow_intersection": body.allow_intersection}
    scratch = store.new_tmp(".d")
    scratch.mkdir()
    try:  # in a child process with the validation memory limit: the mesh is an upload
        made = _isolated("substitute the object", "substituting the object",
                         lambda: substitute_isolated(store.asset_path(clip), store.asset_path(mesh), mesh.name,
                                                     scratch / "clip.npz", options, scratch=scratch,
                                                     memory_bytes=settings.validation_memory_mb * MIB))
        info = made["info"] | {"substituted_from": clip.sha256, "object_mesh": mesh.sha256,
                               "substitution": made["report"]}
        asset, created = _save_new_asset(store, owner, "clip", body.name,
                                         lambda p: shutil.move(str(scratch / "clip.npz"), str(p)), info)
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    response.status_code = 201 if created else 200
    return asset.public()


@router.post("/annotations/propose", response_model=Asset, status_code=201, responses=ERRORS | BAD_BODY)
def propose(body: ProposeRequest, response: Response, owner: str = Depends(current_owner),
            store: Store = Depends(get_store)):
    """Proposed annotations (markers by name, one axial curve per finger and two on the palm)
    from the source rig onto the target rig, stored as an annotations asset to edit or use."""
    from retarget_core.errors import InputError
    from retarget_core.inputs import DEFAULT_SOURCE_RIG
    from retarget_core.rig.io import load_rig, resolve_rig
    from retarget_core.transfer.annotations import save_annotations, with_positions
    from retarget_core.transfer.propose import propose_annotations

    def stored_rig(asset):  # a stored rig is one flat layer: it may compose no other file
        path = store.asset_path(asset)
        return load_rig(path, confine_to=path, **stored_rig_options(asset.info))

    target_asset = owned(store, owner, body.target_rig, "rig", "target_rig")
    source_asset = owned(store, owner, body.source_rig, "rig", "source_rig") if body.source_rig else None
    try:
        source = stored_rig(source_asset) if source_asset is not None else resolve_rig(DEFAULT_SOURCE_RIG)
        target = stored_rig(target_asset)
        annotations = with_positions(propose_annotations(source, target), source, target)  # survive mesh edits
    except InputError as err:
        raise HTTPException(422, f"cannot propose annotations: {err}") from err
    name = f"{source.name}_to_{target_asset.info.get('name', 'target')}.json"
    asset, created = _save_new_asset(store, owner, "annotations", name, lambda p: save_annotations(annotations, p),
                                     annotations_info(annotations) | {"proposed": True})
    response.status_code = 201 if created else 200
    return asset.public()



