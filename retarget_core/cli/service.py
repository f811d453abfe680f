"""``handretarget serve`` and ``handretarget token create`` / ``revoke``: the job service
(server/) behind the one ``handretarget`` entry point. The options are defined here, so
``--help`` needs no service dependency; the service is imported only when one of these commands runs, and a failed import
is an error that shows the ImportError."""

from __future__ import annotations

from .common import _UsageError


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
    serve.add_argument("--job-time-limit", type=float, default=3600, metavar="SECONDS",
                       help="wall time of one job's process; beyond it the job fails")
    serve.add_argument("--job-memory-mb", type=int, default=4096,
                       help="memory (PSS) of one job's process and its local pool; beyond it the job fails")
    serve.add_argument("--validation-memory-mb", type=int, default=1024,
                       help="memory of the child process validating one upload; beyond it the upload gets 413")
    serve.add_argument("--storage-quota-mb", type=float, default=10240,
                       help="bytes one owner may store (assets as uploaded + job artifacts); beyond: 413")
    serve.add_argument("--max-streams", type=int, default=8, help="open event streams per owner; beyond: 429")
    serve.add_argument("--read-timeout", type=float, default=60, metavar="SECONDS",
                       help="an upload with no data for this long gets 408 (its partial file is removed)")
    serve.add_argument("--max-requests", type=int, default=16, help="requests of one owner at once; beyond: 429")
    serve.add_argument("--max-heavy-requests", type=int, default=2,
                       help="uploads, GRAB imports and proposals of one owner at once; beyond: 429")
    serve.set_defaults(func=_cmd_serve)

    token = sub.add_parser("token", help="API tokens of the job service")
    token_sub = token.add_subparsers(dest="token_command", required=True)
    create = token_sub.add_parser("create", help="create a token for NAME and print it (shown once)")
    create.add_argument("name")
    create.add_argument("--data-dir", default="service_data")
    create.add_argument("--admin", action="store_true", help="the token may also read /metrics (service-wide)")
    create.set_defaults(func=_cmd_token_create)
    revoke = token_sub.add_parser("revoke", help="revoke every token of NAME (their requests get 401 at once; "
                                                 "NAME's assets and jobs stay)")
    revoke.add_argument("name")
    revoke.add_argument("--data-dir", default="service_data")
    revoke.set_defaults(func=_cmd_token_revoke)


def _service(*modules: str):
    """``server.cli`` after importing ``modules`` (what the command needs of the service), or a
    usage error (exit 2) naming the ImportError when one of them or a dependency is missing.
    Only ImportError becomes that message; any other exception propagates."""
    import importlib

    try:
        for name in modules:
            importlib.import_module(name)
        return importlib.import_module("server.cli")
    except ImportError as exc:
        raise _UsageError("the job service needs its dependencies (fastapi, uvicorn, prometheus-client, pydantic; "
                          f"pip install -e . installs them): {exc}") from exc


def _cmd_serve(args) -> int:
    return _service("server", "uvicorn", "server.app")._cmd_serve(args)


def _cmd_token_create(args) -> int:
    return _service("server", "server.storage")._cmd_token_create(args)


def _cmd_token_revoke(args) -> int:
    return _service("server", "server.storage")._cmd_token_revoke(args)
