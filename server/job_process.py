"""One job, in its own process: ``python -m server.job_process --job ID --settings JSON``.

Reads the job's request and assets from the store, builds the run with the core's
:func:`~retarget_core.inputs.load_inputs` (which also enforces which files a job may load: a
clip may only name a demo source hand), :func:`~retarget_core.solve.config.load_config` (the
request's preset and overrides, as sent) and an :class:`~retarget_core.execute.Executor` (the
service's settings), runs :func:`~retarget_core.pipeline.retarget`, writes the artifacts into a
scratch folder, renames it into place whole, and only then marks the job ``succeeded``.
Progress goes to the store a few times a second. When the service that started it is gone
(killed), the process stops at its next progress report and the restarted service re-runs it.

Bad input (the core's :class:`~retarget_core.errors.RetargetError`) fails the job with its
message; any other exception is a bug: the job fails as "internal error (...)" and the
traceback goes to the job's log.

Limits (:class:`Watchdog`, a thread started by :func:`main`): every 0.2 s it measures the wall
time since the job process started and the memory (PSS, Linux /proc) of the job process and all
its descendants (its local frame pool), and the job process's own peak RSS since it started. Past ``Settings.job_time_limit_s`` or
``Settings.job_memory_mb`` the job fails with "exceeded the job time limit of N s" / "exceeded
the job memory limit of N MB", the pool's processes are killed and the job process exits. With
``dask_scheduler`` the frames are solved on the cluster's workers: the time limit still ends
the job (its client goes away with the job process, and the cluster drops its tasks), but the
memory limit covers only the job process and its local pool, not the cluster workers, whose
memory only the cluster's own limits (e.g. ``dask worker --memory-limit``) bound.
"""

from __future__ import annotations

import argparse
import errno
import logging
import os
import shutil
import signal
import sys
import threading
import time
from pathlib import Path

from retarget_core.errors import InputError, RetargetError

from .schemas import JobState
from .settings import Settings
from .storage import Store

log = logging.getLogger("server.job")
RUNNING = (JobState.RUNNING,)
#: request field -> (asset kind, name of the input in the core's provenance)
INPUT_ASSETS = {"clip": ("clip", "clip"), "rig": ("rig", "target_rig"), "annotations": ("annotations", "annotations"),
                "source_rig": ("rig", "source_rig")}


#: The stage of a job queued again because the disk was full (see JobRunner's back-off).
DISK_FULL_STAGE = "waiting for disk space"


class Orphaned(SystemExit):
    """The service that started this job process is gone."""


class _Progress:
    """The core's progress callback: throttled store updates, and an orphan check."""

    def __init__(self, store: Store, job_id: str, parent: int | None):
        self.store, self.job_id, self.parent = store, job_id, parent
        self.last = 0.0
        self.stage_seen = []

    def __call__(self, stage: str, done: int, total: int) -> None:
        if self.parent is not None and os.getppid() != self.parent:
            raise Orphaned(3)
        if stage not in self.stage_seen:
            self.stage_seen.append(stage)
        now = time.monotonic()
        if now - self.last < 0.25 and done < total:
            return
        self.last = now
        fields = {"stage": stage, "progress": round(done / total, 4) if total else 0.0}
        if stage == "full pass":
            fields.update(frames_done=int(done), frames_total=int(total))
        self.store.update_job(self.job_id, only_if_state=RUNNING, **fields)


def _rig_asset_path(request, rig_asset, result, rig_file) -> str | None:
    """The path animation.usda sublayers for the rig: the request's ``rig_asset_path``, else the
    rig upload's own file name (the layer then plays over the user's file placed beside it);
    None (over the job's rig.usda) for a robot bundle or USD package, which were imported, or a
    name that is not a plain relative USD path."""
    import re

    from retarget_core.export.usd_animation import layers_over

    from .schemas import RIG_ASSET_PATH

    imported = str(rig_asset.info.get("imported_from", ""))
    if request.rig_asset_path is not None:
        if imported and Path(imported).suffix.lower() not in (".usda", ".usdc", ".usd", ".usdz"):
            raise InputError("rig_asset_path: the rig was not uploaded as a USD file (a robot bundle is "
                             "kept as the imported rig.usda, which the layer composes over by default)",
                             element="rig_asset_path")
        return request.rig_asset_path
    name = Path(str(rig_asset.name or "")).name
    if imported or not re.fullmatch(RIG_ASSET_PATH, name) or not layers_over(result.rig, rig_file):
        return None
    return name

def run_job(store: Store, job_id: str, settings: Settings, *, parent: int | None = None) -> JobState:
    """Run job ``job_id`` (state ``running``) to its final state; returns that state."""
    from retarget_core.export.robot_trajectory import is_robot
    from retarget_core.execute import Executor
    from retarget_core.inputs import load_inputs
    from retarget_core.jsonio import to_jsonable
    from retarget_core.pipeline import retarget
    from retarget_core.solve.config import load_config

    job = store.job(job_id)
    request = job.request
    progress = _Progress(store, job_id, parent)
    out = store.new_tmp(".out")
    paths: dict[str, Path] = {}  # request field -> the asset's file

    def fail(error: str) -> JobState:
        shutil.rmtree(out, ignore_errors=True)
        store.update_job(job_id, only_if_state=RUNNING, state=JobState.FAILED, error=_public(error, store, paths),
                         finished=time.time(), pid=None)
        return JobState.FAILED

    try:
        for field, (kind, _) in INPUT_ASSETS.items():
            asset_id = getattr(request, field)
            if asset_id is None:
                continue
            asset = store.asset(job.owner, asset_id, kind)
            if asset is None:  # checked at submission; only a damaged store gets here
                raise RetargetError(f"{field}: asset {asset_id} is gone from the store")
            paths[field] = store.asset_path(asset)
            if field == "rig":
                rig_asset = asset
            if kind == "rig":  # the stored rig is one flat layer: it may compose no other file
                from retarget_core.rig.usd_io import check_confined_layers

                check_confined_layers(paths[field], paths[field])
        recorded_id = None
        if request.source_rig is None:  # a GRAB clip's MANO hand, found by its hash among the owner's rigs
            from .assets import recorded_source_rig

            recorded = recorded_source_rig(store, job.owner, store.asset(job.owner, request.clip, "clip"))
            if recorded is not None:
                paths["source_rig"] = store.asset_path(recorded)
                recorded_id = recorded.sha256
                from retarget_core.rig.usd_io import check_confined_layers

                check_confined_layers(paths["source_rig"], paths["source_rig"])
        config = load_config(None, request.preset, request.overrides)
        # built atlases are kept per (source, target, annotations): a rig's second job skips the build
        executor = Executor(workers=settings.frame_workers, dask_scheduler=settings.dask_scheduler,
                            atlas_cache=store.paths.atlas_cache, progress=progress)
        progress("loading", 0, 1)
        # source_rig None: load_inputs takes the demo hand the clip names, and refuses anything else
        from .assets import stored_rig_options

        inputs = load_inputs(paths["clip"], paths["rig"], paths["annotations"], source_rig=paths.get("source_rig"),
                             frames=request.frames, target_options=stored_rig_options(rig_asset.info),
                             clip_rig_files=False)  # never a path a clip records: only what is resolved above
        _asset_provenance(inputs.sources, request)
        if recorded_id is not None:
            inputs.sources["source_rig"]["asset"] = recorded_id
        if request.control_rate_hz is not None and not is_robot(inputs.target_rig):
            raise InputError("control_rate_hz resamples a robot's joint commands; the target rig is not a URDF or "
                             "MJCF robot", element="control_rate_hz")
        result = retarget(inputs, config, executor)
        # the store's folders are named relative to the data directory, as everywhere the client sees
        result.provenance["executor"]["atlas_cache"] = str(store.paths.atlas_cache.relative_to(store.paths.root))
        progress("writing", 0, 1)
        result.write(out, paths["rig"], rig_asset_path=_rig_asset_path(request, rig_asset, result, paths["rig"]),
                     control_rate_hz=request.control_rate_hz)
        _write_usdc(out)
        if request.evaluate:
            from retarget_core.evaluate.report import write_evaluation

            progress("evaluating", 0, 1)
            write_evaluation(out, stride=settings.evaluate_stride, render=False)  # the write drew the pictures
        store.publish_artifacts(job_id, out)
        timings = {k: round(float(v), 4) for k, v in result.timings.items()}
        store.update_job(job_id, only_if_state=RUNNING, state=JobState.SUCCEEDED, stage="done", progress=1.0,
                         finished=time.time(), timings=timings, summary=to_jsonable(result.summary), pid=None)
        return JobState.SUCCEEDED
    except Orphaned:
        shutil.rmtree(out, ignore_errors=True)
        raise
    except RetargetError as err:  # bad input that only shows when the job runs
        return fail(str(err))
    except OSError as err:
        if err.errno != errno.ENOSPC:
            log.exception("job %s: internal error", job_id)
            return fail(f"internal error ({type(err).__name__}): {err}")
        # the service's disk, not the job: queue it again without spending an attempt; the runner
        # waits DISK_FULL_BACKOFF_S before it claims jobs again
        shutil.rmtree(out, ignore_errors=True)
        log.error("job %s: the disk is full (%s); queued again", job_id, err)
        store.update_job(job_id, only_if_state=RUNNING, state=JobState.QUEUED, stage=DISK_FULL_STAGE, pid=None,
                         progress=0.0, frames_done=0, attempts=max(job.attempts - 1, 0),
                         error="the service's disk is full (no space left on device); the job is queued again and "
                               "runs once space is freed")
        return JobState.QUEUED
    except Exception as err:  # noqa: BLE001 - a bug: the job fails, the traceback goes to the log
        log.exception("job %s: internal error", job_id)
        return fail(f"internal error ({type(err).__name__}): {err}")


class Watchdog:
    """Fails job ``job_id`` once the process has run ``time_limit_s`` seconds or its process
    tree holds more than ``memory_bytes`` (PSS), checked every ``interval`` s; then kills the
    tree below this process and ends the process with exit code 4 (after the job is marked
    failed, so the runner does not re-run it)."""

    EXIT_CODE = 4

    def __init__(self, store: Store, job_id: str, *, time_limit_s: float, memory_bytes: int,
                 interval: float = 0.2, exit=os._exit):
        self.store, self.job_id = store, job_id
        self.time_limit_s, self.memory_bytes, self.interval = float(time_limit_s), int(memory_bytes), interval
        self.started = time.monotonic()
        self.peak = 0
        self._exit = exit
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="job-watchdog", daemon=True)

    def __enter__(self) -> "Watchdog":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()

    def check(self) -> str | None:
        """The limit exceeded now, as the job's error, or None."""
        from retarget_core.procmem import peak_rss_bytes, tree_memory_bytes
        from .isolation import MIB

        elapsed = time.monotonic() - self.started
        if elapsed > self.time_limit_s:
            return (f"exceeded the job time limit of {self.time_limit_s:g} s (ran {elapsed:.1f} s); "
                    "the job was stopped")
        # the tree's PSS now, and this process's own peak RSS since it started (a spike in the
        # job process between two samples still counts)
        used = max(tree_memory_bytes(os.getpid()), peak_rss_bytes())
        self.peak = max(self.peak, used)
        if used > self.memory_bytes:
            return (f"exceeded the job memory limit of {self.memory_bytes // MIB} MB (its processes held "
                    f"{used // MIB} MB); the job was stopped")
        return None

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            error = self.check()
            if error is not None:
                self._fail(error)
                return

    def _fail(self, error: str) -> None:
        from retarget_core.procmem import descendants

        log.error("job %s: %s", self.job_id, error)
        try:  # failed first: whatever the job's own thread writes after this is refused (only_if_state)
            self.store.update_job(self.job_id, only_if_state=RUNNING, state=JobState.FAILED, error=error,
                                  finished=time.time(), pid=None)
        finally:
            for pid in descendants(os.getpid()):  # the pool must not outlive the job
                try:
                    os.kill(pid, signal.SIGKILL)
                except (ProcessLookupError, PermissionError):
                    pass
            logging.shutdown()
            self._exit(self.EXIT_CODE)


def _asset_provenance(sources: dict, request) -> None:
    """The inputs' provenance names the request's asset ids, not the store's file paths."""
    for field, (_, name) in INPUT_ASSETS.items():
        entry = sources.get(name)
        if entry is not None and "path" in entry:
            del entry["path"]
            entry["asset"] = getattr(request, field)


def _public(message: str, store: Store, paths: dict) -> str:
    """A job's error as its owner sees it: the store's file paths replaced by what they are."""
    for field, path in paths.items():
        message = message.replace(str(path), f"the {field} asset")
    return message.replace(str(store.paths.root), "DATA")


def _write_usdc(out) -> None:
    """animation.usdc beside animation.usda: the same layer in the binary crate format."""
    from pxr import Sdf

    usda = out / "animation.usda"
    if usda.is_file():
        layer = Sdf.Layer.FindOrOpen(str(usda))
        if not layer.Export(str(out / "animation.usdc")):
            raise RuntimeError("could not write animation.usdc")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m server.job_process")
    parser.add_argument("--job", required=True)
    parser.add_argument("--parent", type=int)
    parser.add_argument("--settings", required=True, help="the service's Settings as JSON")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr)
    settings = Settings.model_validate_json(args.settings)
    store = Store(settings.data_dir)
    from .isolation import MIB

    with Watchdog(store, args.job, time_limit_s=settings.job_time_limit_s,
                  memory_bytes=settings.job_memory_mb * MIB):
        state = run_job(store, args.job, settings, parent=args.parent)
    return 0 if state == JobState.SUCCEEDED else 1


if __name__ == "__main__":
    sys.exit(main())
