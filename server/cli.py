"""What ``handretarget serve`` and ``handretarget token create`` run. Their options are defined in
the core (retarget_core/cli/service.py), which imports this module only when one of them runs."""

from __future__ import annotations

from pathlib import Path

from .settings import MIB, Settings


def _cmd_serve(args) -> int:
    import uvicorn

    from .app import configure_logging, create_app

    for name, value in (("--job-slots", args.job_slots), ("--workers", args.workers),
                        ("--max-active-jobs", args.max_active_jobs)):
        if value < 1:
            raise SystemExit(f"{name} must be at least 1")
    configure_logging()
    settings = Settings(data_dir=Path(args.data_dir), job_slots=args.job_slots, frame_workers=args.workers,
                        dask_scheduler=args.dask_scheduler, max_upload_bytes=int(args.max_upload_mb * MIB),
                        max_active_jobs=args.max_active_jobs, atlas_cache_bytes=int(args.atlas_cache_mb * MIB))
    uvicorn.run(create_app(settings), host=args.host, port=args.port, log_level="warning", access_log=False)
    return 0


def _cmd_token_create(args) -> int:
    from .storage import Store

    name = args.name.strip()
    if not name or len(name) > 100:
        raise SystemExit("NAME must be 1 to 100 characters")
    print(Store(args.data_dir).create_token(name))
    return 0
