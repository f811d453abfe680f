"""``handretarget serve`` and ``handretarget token create``: wired into the core's CLI."""

from __future__ import annotations

from pathlib import Path

from .settings import MIB, Settings


def add_commands(sub) -> None:
    serve = sub.add_parser("serve", help="run the job service (FastAPI on uvicorn)")
    serve.add_argument("--data-dir", default="service_data", help="the store: SQLite, blobs, artifacts")
    serve.add_argument("--host", default="127.0.0.1")
    serve.add_argument("--port", type=int, default=8000)
    serve.add_argument("--job-slots", type=int, default=1, help="jobs run at once")
    serve.add_argument("--workers", type=int, default=1, help="frame-solving processes per job")
    serve.add_argument("--dask-scheduler", default="", help="tcp://HOST:PORT: solve frames on this Dask cluster")
    serve.add_argument("--max-upload-mb", type=float, default=256)
    serve.add_argument("--max-active-jobs", type=int, default=32, help="queued + running jobs per owner")
    serve.add_argument("--atlas-cache-mb", type=float, default=4096,
                       help="disk kept for built contact atlases (least recently used removed)")
    serve.set_defaults(func=_cmd_serve)

    token = sub.add_parser("token", help="API tokens of the job service")
    token_sub = token.add_subparsers(dest="token_command", required=True)
    create = token_sub.add_parser("create", help="create a token for NAME and print it (shown once)")
    create.add_argument("name")
    create.add_argument("--data-dir", default="service_data")
    create.set_defaults(func=_cmd_token_create)


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
