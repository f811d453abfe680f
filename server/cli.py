"""What ``handretarget serve`` and ``handretarget token create`` run. Their options are defined in
the core (retarget_core/cli/service.py), which imports this module only when one of them runs."""

from __future__ import annotations

from pathlib import Path

from .settings import MIB, Settings


#: The serve option behind each setting (for error messages).
FLAGS = {"data_dir": "--data-dir", "job_slots": "--job-slots", "frame_workers": "--workers",
         "dask_scheduler": "--dask-scheduler", "max_upload_bytes": "--max-upload-mb",
         "max_active_jobs": "--max-active-jobs", "atlas_cache_bytes": "--atlas-cache-mb"}


def settings_from_args(args) -> Settings:
    """The :class:`Settings` of ``serve``'s options; SystemExit naming the option when one is bad."""
    from pydantic import ValidationError

    try:
        return Settings(data_dir=Path(args.data_dir), job_slots=args.job_slots, frame_workers=args.workers,
                        dask_scheduler=args.dask_scheduler, max_upload_bytes=int(args.max_upload_mb * MIB),
                        max_active_jobs=args.max_active_jobs, atlas_cache_bytes=int(args.atlas_cache_mb * MIB))
    except ValidationError as err:
        raise SystemExit("; ".join(f"{FLAGS.get(str(e['loc'][0]), e['loc'][0])}: {e['msg']}"
                                   for e in err.errors())) from None


def _cmd_serve(args) -> int:
    import uvicorn

    from .app import configure_logging, create_app

    settings = settings_from_args(args)
    configure_logging()
    uvicorn.run(create_app(settings), host=args.host, port=args.port, log_level="warning", access_log=False)
    return 0


def _cmd_token_create(args) -> int:
    from .storage import Store

    name = args.name.strip()
    if not name or len(name) > 100:
        raise SystemExit("NAME must be 1 to 100 characters")
    print(Store(args.data_dir).create_token(name))
    return 0
