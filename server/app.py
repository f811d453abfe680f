"""The FastAPI application: routers, structured request logs, Prometheus metrics, readable
errors, and the job runner started and stopped with the app."""

from __future__ import annotations

import json
import logging
import sys
import time
import uuid
from contextlib import asynccontextmanager

from fastapi import FastAPI, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from prometheus_client import CollectorRegistry, Counter, Gauge, Histogram

from .routers import assets, jobs, ops
from .runner import JobRunner
from .schemas import JobState
from .settings import Settings
from .storage import Store

API_VERSION = "1"
#: Requests that validate or compute in the service (capped per owner beside all requests).
HEAVY_PATHS = ("/v1/assets/", "/v1/clips/import-grab", "/v1/annotations/propose")
KNOWN_METHODS = frozenset({"GET", "HEAD", "POST", "PUT", "PATCH", "DELETE", "OPTIONS"})
log = logging.getLogger("server.http")


class JsonLogFormatter(logging.Formatter):
    """One JSON object per line: time, level, logger, message and any ``extra`` fields."""

    FIELDS = ("request_id", "method", "path", "status", "ms", "owner")

    def format(self, record):
        doc = {"time": round(record.created, 3), "level": record.levelname, "logger": record.name,
               "message": record.getMessage()}
        doc.update({k: getattr(record, k) for k in self.FIELDS if hasattr(record, k)})
        if record.exc_info:
            doc["exception"] = self.formatException(record.exc_info)
        return json.dumps(doc)


def configure_logging(level=logging.INFO) -> None:
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonLogFormatter())
    root = logging.getLogger("server")
    root.handlers[:] = [handler]
    root.setLevel(level)
    root.propagate = False


class Metrics:
    def __init__(self, store: Store):
        self.registry = CollectorRegistry()
        self.requests = Counter("handretarget_http_requests_total", "HTTP requests", ["method", "route", "status"],
                                registry=self.registry)
        self.latency = Histogram("handretarget_http_request_seconds", "HTTP request latency", ["method", "route"],
                                 registry=self.registry,
                                 buckets=(0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1, 2.5, 5, 10))
        jobs_gauge = Gauge("handretarget_jobs", "jobs in the store by state", ["state"], registry=self.registry)
        for state in JobState:  # read from the store at scrape time
            jobs_gauge.labels(state.value).set_function(lambda s=state.value: store.state_counts()[s])


def _readable(exc: RequestValidationError) -> str:
    parts = []
    for e in exc.errors():
        loc = ".".join(str(x) for x in e.get("loc", ()) if x not in ("body", "query", "path", "header"))
        parts.append(f"{loc or 'request'}: {e.get('msg', 'invalid')}")
    return "; ".join(parts)


def create_app(settings: Settings) -> FastAPI:
    store = Store(settings.data_dir)
    runner = JobRunner(store, settings)

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        runner.start()
        try:
            yield
        finally:
            runner.stop()

    app = FastAPI(title="Hand Retarget service", version=API_VERSION, lifespan=lifespan,
                  description="Retarget captured hand-object clips onto any hand rig; USD animation layers "
                              "with one B-spline per DOF. Every endpoint but health and readiness needs "
                              "'Authorization: Bearer <token>'.")
    app.state.store, app.state.settings, app.state.runner = store, settings, runner
    app.state.metrics = Metrics(store)
    app.state.streams = {}  # owner -> open event streams (see routers.jobs.job_events)
    for r in (ops.router, assets.router, jobs.router):
        app.include_router(r)

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, exc: RequestValidationError):
        return JSONResponse({"detail": _readable(exc)}, status_code=422)

    active: dict[str, list[int]] = {}  # owner -> [requests, heavy requests] in progress (event loop only)

    @app.middleware("http")
    async def json_body_limit(request: Request, call_next):
        """Bodies other than uploads (the JSON of jobs, imports, proposals) are read whole into
        memory: at most ``max_json_bytes`` (413 beyond; uploads have ``max_upload_bytes``)."""
        if request.method == "POST" and request.url.path.startswith("/v1/assets/"):
            return await call_next(request)
        limit = settings.max_json_bytes
        declared = request.headers.get("content-length", "")
        too_big = JSONResponse({"detail": f"the request body is over the limit of {limit} bytes for JSON bodies"},
                               status_code=413)
        if declared.isdigit() and int(declared) > limit:
            return too_big
        if declared or request.method in ("GET", "HEAD"):
            return await call_next(request)
        # no length declared (chunked): count what arrives
        receive, seen = request._receive, 0

        async def counted():
            nonlocal seen
            if seen > limit:  # the body ends here for the app; its answer is replaced below
                return {"type": "http.request", "body": b"", "more_body": False}
            message = await receive()
            seen += len(message.get("body", b""))
            return {"type": "http.request", "body": b"", "more_body": False} if seen > limit else message

        request._receive = counted
        response = await call_next(request)
        return too_big if seen > limit else response

    @app.middleware("http")
    async def per_owner_limits(request: Request, call_next):
        """At most ``max_requests_per_owner`` requests of one owner at once, of which at most
        ``max_heavy_requests_per_owner`` uploads, GRAB imports or proposals (429 beyond), so
        one owner cannot take the service's threads and validation processes from the others.
        Event streams have their own cap (``max_streams_per_owner``)."""
        auth = request.headers.get("authorization", "")
        if not auth[:7].lower() == "bearer " or request.url.path.endswith("/events"):
            return await call_next(request)
        holder = await run_in_threadpool(store.token_holder, auth[7:].strip())
        if holder is None:  # the route answers 401
            return await call_next(request)
        counts = active.setdefault(holder[0], [0, 0])
        heavy = request.method == "POST" and request.url.path.startswith(HEAVY_PATHS)
        if counts[0] >= settings.max_requests_per_owner:
            return JSONResponse({"detail": f"you already have {counts[0]} requests in progress (the limit is "
                                           f"{settings.max_requests_per_owner}); wait for one to finish"},
                                status_code=429, headers={"Retry-After": "1"})
        if heavy and counts[1] >= settings.max_heavy_requests_per_owner:
            return JSONResponse({"detail": f"you already have {counts[1]} uploads, imports or proposals in progress "
                                           f"(the limit is {settings.max_heavy_requests_per_owner}); wait for one "
                                           "to finish"}, status_code=429, headers={"Retry-After": "1"})
        counts[0] += 1
        counts[1] += heavy
        try:
            return await call_next(request)
        finally:
            counts[0] -= 1
            counts[1] -= heavy

    @app.middleware("http")
    async def log_and_measure(request: Request, call_next):
        request_id = request.headers.get("x-request-id") or uuid.uuid4().hex[:16]
        start = time.perf_counter()
        status = 500
        try:
            response = await call_next(request)
            status = response.status_code
            response.headers["X-Request-ID"] = request_id
            return response
        finally:
            seconds = time.perf_counter() - start
            # labels are bounded: route templates (not paths), known methods, 3-digit statuses
            route = request.scope.get("route")
            path = getattr(route, "path", "unmatched")
            method = request.method if request.method in KNOWN_METHODS else "OTHER"
            app.state.metrics.requests.labels(method, path, str(status)).inc()
            app.state.metrics.latency.labels(method, path).observe(seconds)
            log.info("request", extra={"request_id": request_id, "method": request.method, "path": request.url.path,
                                       "status": status, "ms": round(1000 * seconds, 2),
                                       "owner": getattr(request.state, "owner", None)})

    return app
