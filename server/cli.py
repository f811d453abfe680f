"""What ``handretarget serve`` and ``handretarget token create`` / ``revoke`` run. Their options
are defined in the core (retarget_core/cli/service.py), which imports this module only when one
of them runs."""

from __future__ import annotations

from pathlib import Path

from .settings import MIB, Settings


#: Seconds uvicorn waits for open connections at shutdown before closing them.
SHUTDOWN_GRACE = 2

#: The serve option behind each setting (for error messages).
FLAGS = {"data_dir": "--data-dir", "job_slots": "--job-slots", "frame_workers": "--workers",
         "dask_scheduler": "--dask-scheduler", "max_upload_bytes": "--max-upload-mb",
         "max_active_jobs": "--max-active-jobs", "atlas_cache_bytes": "--atlas-cache-mb",
         "job_time_limit_s": "--job-time-limit", "job_memory_mb": "--job-memory-mb",
         "validation_memory_mb": "--validation-memory-mb", "storage_quota_bytes": "--storage-quota-mb",
         "max_streams_per_owner": "--max-streams", "read_timeout_s": "--read-timeout",
         "max_requests_per_owner": "--max-requests", "max_heavy_requests_per_owner": "--max-heavy-requests"}


def settings_from_args(args) -> Settings:
    """The :class:`Settings` of ``serve``'s options; SystemExit naming the option when one is bad."""
    from pydantic import ValidationError

    try:
        return Settings(data_dir=Path(args.data_dir), job_slots=args.job_slots, frame_workers=args.workers,
                        dask_scheduler=args.dask_scheduler, max_upload_bytes=int(args.max_upload_mb * MIB),
                        max_active_jobs=args.max_active_jobs, atlas_cache_bytes=int(args.atlas_cache_mb * MIB),
                        job_time_limit_s=args.job_time_limit, job_memory_mb=args.job_memory_mb,
                        validation_memory_mb=args.validation_memory_mb,
                        storage_quota_bytes=int(args.storage_quota_mb * MIB), max_streams_per_owner=args.max_streams,
                        read_timeout_s=args.read_timeout, max_requests_per_owner=args.max_requests,
                        max_heavy_requests_per_owner=args.max_heavy_requests)
    except ValidationError as err:
        raise SystemExit("; ".join(f"{FLAGS.get(str(e['loc'][0]), e['loc'][0])}: {e['msg']}"
                                   for e in err.errors())) from None


def _cmd_serve(args) -> int:
    import uvicorn

    from .app import configure_logging, create_app

    from .storage import DataDirLocked, lock_data_dir

    settings = settings_from_args(args)
    # one service per data directory: a second one exits here, before it touches any job
    try:
        lock = lock_data_dir(settings.data_dir)
    except DataDirLocked as err:
        raise SystemExit(f"handretarget serve: {err}") from None
    configure_logging()
    app = create_app(settings)
    # streams end when shutdown starts (they watch server.should_exit); whatever is still open
    # after SHUTDOWN_GRACE s is closed, so SIGTERM / SIGINT exit within a few seconds
    server = uvicorn.Server(uvicorn.Config(app, host=args.host, port=args.port, log_level="warning",
                                           access_log=False, timeout_graceful_shutdown=SHUTDOWN_GRACE))
    app.state.server = server
    try:
        server.run()
    finally:
        lock.close()
    return 0 if server.started else 1


def _cmd_token_create(args) -> int:
    from .storage import Store

    name = args.name.strip()
    if not name or len(name) > 100:
        raise SystemExit("NAME must be 1 to 100 characters")
    print(Store(args.data_dir).create_token(name, admin=args.admin))
    return 0


def _cmd_token_revoke(args) -> int:
    from .storage import Store

    removed = Store(args.data_dir).revoke_tokens(args.name.strip())
    if not removed:
        raise SystemExit(f"no token of {args.name.strip()!r} in {args.data_dir}")
    print(f"revoked {removed} token{'s' if removed != 1 else ''} of {args.name.strip()!r}")
    return 0
