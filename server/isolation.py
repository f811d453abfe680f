"""Work on untrusted input outside the API process, with a memory limit; and the memory
measure the job limits use.

:func:`validate_isolated` runs :func:`server.assets.validate_upload` in a child process
(``python -m server.isolation``, its own session), samples the child's memory every
``interval`` s and kills it (its whole process group) past the limit: an upload that would
need more memory than ``Settings.validation_memory_mb`` is refused (HTTP 413) and never grows
the server. The measure is the PSS of the child and its descendants (Linux /proc, as the bench's
``PeakMemory`` samples it) and the child's peak RSS (``VmHWM``, read while it runs and reported
by the child itself when it is done), so a short peak between two samples still counts. An
address-space rlimit is not used: embree and OpenBLAS reserve far more address space than they
touch and fail under one. The child ends itself if the service goes away mid-upload.

The GRAB importer (``POST /v1/clips/import-grab``, :func:`import_grab_isolated`) runs the same
way under the same limit.

A clip upload's npz headers are also checked against the same limit before anything is
decompressed (:func:`retarget_core.clip.format.check_npz_members`): arrays that could not fit
are refused at once, naming the member (422).

The service runs on Linux: the limits read ``/proc``.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from retarget_core.procmem import peak_rss_bytes, tree_memory_bytes

MIB = 1024 * 1024
log = logging.getLogger("server.isolation")


class MemoryLimitExceeded(Exception):
    """The isolated work needed more memory than its limit (the child was killed)."""

    def __init__(self, limit_bytes: int, used_bytes: int):
        self.limit_bytes, self.used_bytes = limit_bytes, used_bytes
        super().__init__(f"exceeded the validation memory limit of {limit_bytes // MIB} MB "
                         f"(reached {used_bytes // MIB} MB)")


class ValidatorCrashed(Exception):
    """The child died without an answer (a crash in a reader on a hostile file)."""


# ---- upload validation in a child process -----------------------------------------------------

def validate_isolated(kind: str, tmp: Path, filename: str, *, scratch: Path, bundle_bytes: int,
                      memory_bytes: int, interval: float = 0.05, rig_options: dict | None = None):
    """:func:`server.assets.validate_upload` in a child process limited to ``memory_bytes``;
    returns its (path, suffix, info). Raises :class:`server.assets.UploadError` as the
    validator did, :class:`MemoryLimitExceeded` past the limit, :class:`ValidatorCrashed` when
    the child died otherwise."""
    tmp = Path(tmp).resolve()
    result = _run_child({"task": "validate", "kind": kind, "tmp": str(tmp), "filename": filename,
                         "bundle_bytes": int(bundle_bytes), "max_clip_bytes": int(memory_bytes),
                         "rig_options": dict(rig_options or {})},
                        scratch=scratch, memory_bytes=memory_bytes, interval=interval, what=f"{kind} {filename!r}")
    return Path(result["path"]), result["suffix"], result["info"]


def import_grab_isolated(paths: dict, out: Path, *, scratch: Path, memory_bytes: int, hand: str = "right",
                         interval: float = 0.05) -> dict:
    """:func:`server.assets.import_grab_clip` on the uploaded files ``paths`` in a child
    process limited to ``memory_bytes``: the clip is saved at ``out`` and its MANO source rig
    beside it; returns {"info": the clip's info, "rig_path", "rig_info"}. Raises as
    :func:`validate_isolated`."""
    return _run_child({"task": "grab", "paths": {k: None if v is None else str(Path(v).resolve())
                                                 for k, v in paths.items()},
                       "out": str(Path(out).resolve()), "hand": hand},
                      scratch=scratch, memory_bytes=memory_bytes, interval=interval, what="GRAB import")


def substitute_isolated(clip: Path, mesh: Path, mesh_name: str, out: Path, options: dict, *, scratch: Path,
                        memory_bytes: int, interval: float = 0.05) -> dict:
    """:func:`retarget_core.clip.substitute.substitute_object` of the stored ``clip`` with the
    uploaded ``mesh`` in a child process limited to ``memory_bytes`` (the mesh is untrusted):
    the new clip is saved at ``out``; returns {"info": its clip info, "report": the
    substitution's report}. ``options``: register / transform / min_share /
    allow_intersection. Raises as :func:`validate_isolated` (a refused substitution as
    :class:`server.assets.UploadError`, with the core's message)."""
    return _run_child({"task": "substitute", "clip": str(Path(clip).resolve()), "mesh": str(Path(mesh).resolve()),
                       "mesh_name": mesh_name, "out": str(Path(out).resolve()), "options": options},
                      scratch=scratch, memory_bytes=memory_bytes, interval=interval, what="object substitution")


def _run_child(request_doc: dict, *, scratch: Path, memory_bytes: int, interval: float, what: str) -> dict:
    """Run ``python -m server.isolation`` on ``request_doc`` under the memory limit; its answer."""
    from .assets import UploadError

    scratch = Path(scratch).resolve()
    request_doc = dict(request_doc, scratch=str(scratch))
    request = scratch / "isolation-request.json"
    answer = scratch / "isolation-answer.json"
    request.write_text(json.dumps(request_doc))
    errors = scratch / "isolation-stderr.txt"
    with errors.open("wb") as err_file:  # a file, not a pipe: a chatty reader never blocks on it
        proc = subprocess.Popen([sys.executable, "-m", "server.isolation", str(request), str(answer)],
                                stdin=subprocess.DEVNULL, stdout=err_file, stderr=subprocess.STDOUT,
                                start_new_session=True, cwd=str(Path(__file__).resolve().parent.parent))
    peak = 0
    try:
        # exited, not yet reaped: while the child is a zombie its pid (its group's id) is not
        # reused, so what it left behind in its group can still be killed safely
        while os.waitid(os.P_PID, proc.pid, os.WEXITED | os.WNOHANG | os.WNOWAIT) is None:
            peak = max(peak, tree_memory_bytes(proc.pid), peak_rss_bytes(proc.pid))
            if peak > memory_bytes:
                raise MemoryLimitExceeded(memory_bytes, peak)
            time.sleep(interval)
    finally:
        _kill_group(proc.pid)
        proc.wait()
        request.unlink(missing_ok=True)
    stderr = errors.read_text(errors="replace") if errors.is_file() else ""
    errors.unlink(missing_ok=True)
    try:
        result = json.loads(answer.read_text()) if answer.is_file() else None
        peak = max(peak, int((result or {}).get("peak_rss", 0)))
        if peak > memory_bytes:
            raise MemoryLimitExceeded(memory_bytes, peak)
        if result is None:  # the details (a traceback naming server paths) go to the log only
            log.warning("isolated %s exited with %s without an answer:\n%s", what, proc.returncode, stderr[-4000:])
            raise ValidatorCrashed(f"the validator stopped without an answer (exit code {proc.returncode})")
    finally:
        answer.unlink(missing_ok=True)
    if "upload_error" in result:
        raise UploadError(result["upload_error"])
    return result


def _kill_group(pgid: int) -> None:
    try:
        os.killpg(pgid, signal.SIGKILL)
    except (ProcessLookupError, PermissionError):
        pass


def _child(request_path: str, answer_path: str) -> int:
    """The child: validate, write the answer as JSON. An UploadError (or the core's InputError)
    is an answer; anything else is a crash (the traceback goes to stderr)."""
    from retarget_core.errors import InputError

    from .assets import UploadError, _without_path

    req = json.loads(Path(request_path).read_text())
    _exit_with_parent()
    try:
        if req["task"] == "grab":
            answer = _grab(req)
        elif req["task"] == "substitute":
            answer = _substitute(req)
        else:
            answer = _validate(req)
    except UploadError as err:
        answer = {"upload_error": str(err)}
    except InputError as err:  # a core check the validator did not wrap
        answer = {"upload_error": _without_path(str(err), Path(req.get("tmp", "upload")))}
    answer["peak_rss"] = peak_rss_bytes()
    partial = Path(answer_path + ".part")
    partial.write_text(json.dumps(answer))
    partial.rename(answer_path)
    return 0


def _exit_with_parent(interval: float = 0.5) -> None:
    """End this child when the service that watches its memory is gone (killed mid-upload)."""
    import threading

    parent = os.getppid()

    def watch():
        while os.getppid() == parent:
            time.sleep(interval)
        os._exit(3)

    threading.Thread(target=watch, name="parent-watch", daemon=True).start()


def _validate(req: dict) -> dict:
    from retarget_core.errors import InputError

    from .assets import UploadError, validate_upload

    tmp = Path(req["tmp"])
    if req["kind"] == "clip" and tmp.open("rb").read(4) == b"PK\x03\x04":
        from retarget_core.clip.format import check_npz_members

        try:  # arrays that could not fit in the limit are refused before any is decompressed
            check_npz_members(tmp, max_bytes=req["max_clip_bytes"], source="npz upload")
        except InputError as err:
            raise UploadError(str(err)) from err
    path, suffix, info = validate_upload(req["kind"], tmp, req["filename"], scratch=Path(req["scratch"]),
                                         bundle_bytes=req["bundle_bytes"], rig_options=req.get("rig_options"))
    return {"path": str(path), "suffix": suffix, "info": info}


def _grab(req: dict) -> dict:
    from retarget_core.clip.grab import save_grab_hand
    from retarget_core.rig.io import load_rig

    from .assets import clip_info, import_grab_clip, rig_info

    from retarget_core.clip import load_clip
    from retarget_core.errors import InputError

    from .assets import UploadError

    paths = {k: None if v is None else Path(v) for k, v in req["paths"].items()}
    imported = import_grab_clip(**paths, hand=req.get("hand", "right"))
    try:
        clip_path, rig_path = save_grab_hand(imported, Path(req["out"]))
    except InputError as err:  # a MANO file whose mesh is no hand (the clip alone would have no source)
        raise UploadError(f"cannot build the MANO source rig: {err}") from err
    return {"info": clip_info(load_clip(clip_path)), "rig_path": str(rig_path),
            "rig_info": rig_info(load_rig(rig_path))}


def _substitute(req: dict) -> dict:
    import numpy as np

    from retarget_core.clip import load_clip
    from retarget_core.clip.substitute import substitute_object
    from retarget_core.errors import InputError
    from retarget_core.mesh.io import load_mesh_file

    from .assets import UploadError, _without_path, clip_info

    options = dict(req["options"])
    if options.get("transform") is not None:
        options["transform"] = np.asarray(options["transform"], dtype=np.float64).reshape(4, 4)
    try:
        clip = load_clip(req["clip"])
        vertices, faces = load_mesh_file(req["mesh"], "the new object's", "object_mesh")
        new, report = substitute_object(clip, vertices, faces, name=Path(req["mesh_name"]).stem, **options)
        new.save(req["out"])
    except InputError as err:  # the stored files' paths are the service's business, not the user's
        text = str(err)
        for stored in (req["mesh"], req["clip"]):
            text = _without_path(text, Path(stored))
        raise UploadError(text) from err
    depth = report.pop("hand_depth_mm")
    report["hand_depth_max_mm"] = max(depth, default=0.0)
    return {"info": clip_info(new), "report": report}


if __name__ == "__main__":
    sys.exit(_child(sys.argv[1], sys.argv[2]))
