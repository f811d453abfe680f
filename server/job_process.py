"""One job, in its own process: ``python -m server.job_process --data-dir D --job ID``.

Reads the job's request and assets from the store, runs the core's :func:`retarget` (frames
in a local process pool, or on Dask), writes the artifacts into a scratch folder, renames it
into place whole, and only then marks the job ``succeeded``. Progress goes to the store a few
times a second. When the service that started it is gone (killed), the process stops at its
next progress report and the restarted service re-runs the job.
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import sys
import time
import traceback

from retarget_core.errors import RetargetError

from .storage import Store

log = logging.getLogger("server.job")


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
        self.store.update_job(self.job_id, only_if_state=("running",), **fields)


def run_job(store: Store, job_id: str, *, frame_workers: int = 1, dask_scheduler: str = "",
            parent: int | None = None, evaluate_stride: int = 4) -> str:
    """Run job ``job_id`` (state ``running``) to its final state; returns that state."""
    from retarget_core.clip import load_clip
    from retarget_core.evaluate.metrics import to_jsonable
    from retarget_core.retarget import retarget
    from retarget_core.rig.io import load_rig, resolve_rig
    from retarget_core.solve.config import load_config
    from retarget_core.transfer.annotations import load_annotations

    job = store.job(job_id)
    request, owner = job["request"], job["owner"]
    progress = _Progress(store, job_id, parent)
    out = store.new_tmp(".out")
    try:
        def asset_path(field, kind):
            asset = store.asset(owner, request[field], kind)
            if asset is None:  # checked at submission; only a damaged store gets here
                raise RetargetError(f"{field}: asset {request[field]} is gone from the store")
            return store.asset_path(asset)

        overrides = dict(request.get("overrides") or {})
        overrides["workers"] = frame_workers
        # built atlases are kept per (source, target, annotations): a rig's second job skips the build
        overrides["atlas_cache"] = str(store.paths.atlas_cache)
        if dask_scheduler:
            overrides["dask_scheduler"] = dask_scheduler
        config = load_config(None, request.get("preset", "default"), overrides)
        progress("loading", 0, 1)
        clip = load_clip(asset_path("clip", "clip"))
        target = load_rig(asset_path("rig", "rig"))
        if request.get("source_rig"):
            source = load_rig(asset_path("source_rig", "rig"))
        else:  # only a demo hand by name: a clip's own field never names a server path
            source = resolve_rig(clip.source_rig)
        annotations = load_annotations(asset_path("annotations", "annotations"))
        result = retarget(clip, source, target, annotations, config, progress=progress)
        progress("writing", 0, 1)
        result.write(out)
        _write_usdc(out)
        if request.get("evaluate", True):
            from retarget_core.evaluate.report import write_evaluation

            progress("evaluating", 0, 1)
            write_evaluation(out, stride=evaluate_stride)
        store.publish_artifacts(job_id, out)
        timings = {k: round(float(v), 4) for k, v in result.timings.items()}
        store.update_job(job_id, only_if_state=("running",), state="succeeded", stage="done", progress=1.0,
                         finished=time.time(), timings=timings, summary=to_jsonable(result.summary), pid=None)
        return "succeeded"
    except Orphaned:
        shutil.rmtree(out, ignore_errors=True)
        raise
    except (RetargetError, ValueError) as err:  # bad input that only shows when the job runs
        shutil.rmtree(out, ignore_errors=True)
        store.update_job(job_id, only_if_state=("running",), state="failed", error=str(err), finished=time.time(),
                         pid=None)
        return "failed"
    except Exception as err:  # noqa: BLE001 - any other failure is reported, with its trace in the log
        shutil.rmtree(out, ignore_errors=True)
        traceback.print_exc()
        store.update_job(job_id, only_if_state=("running",), state="failed", pid=None, finished=time.time(),
                         error=f"internal error ({type(err).__name__}): {err}")
        return "failed"


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
    parser.add_argument("--data-dir", required=True)
    parser.add_argument("--job", required=True)
    parser.add_argument("--parent", type=int)
    parser.add_argument("--frame-workers", type=int, default=1)
    parser.add_argument("--dask-scheduler", default="")
    parser.add_argument("--evaluate-stride", type=int, default=4)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, stream=sys.stderr)
    store = Store(args.data_dir)
    state = run_job(store, args.job, frame_workers=args.frame_workers, dask_scheduler=args.dask_scheduler,
                    parent=args.parent, evaluate_stride=args.evaluate_stride)
    return 0 if state == "succeeded" else 1


if __name__ == "__main__":
    sys.exit(main())
