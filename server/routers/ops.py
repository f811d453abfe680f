"""Operations: health (public), readiness (public) and Prometheus metrics (admin token needed)."""

from __future__ import annotations

from fastapi import APIRouter, Depends, HTTPException, Request, Response
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest

from ..deps import admin_owner, get_store
from ..schemas import Problem
from ..storage import Store

router = APIRouter(tags=["operations"])


@router.get("/v1/health")
def health():
    """The process answers (liveness)."""
    return {"status": "ok"}


@router.get("/v1/ready", responses={503: {"description": "the store or the job runner is not usable"}})
def ready(request: Request, store: Store = Depends(get_store)):
    """The store answers and the job runner is alive (readiness)."""
    try:
        store.ping()
    except Exception as err:  # noqa: BLE001 - any store failure means not ready
        raise HTTPException(503, f"store not usable ({type(err).__name__})") from err
    if not request.app.state.runner.alive():
        raise HTTPException(503, "the job runner is not running")
    return {"status": "ready"}  # no counts: nothing of other owners' work shows here


@router.get("/metrics", response_class=Response, responses={401: {"model": Problem}, 403: {"model": Problem}})
def metrics(request: Request, owner: str = Depends(admin_owner)):
    """Prometheus text format: requests (labelled by route template, unknown paths as one
    ``unmatched`` label), latencies, jobs by state. Needs an admin token
    (``handretarget token create NAME --admin``)."""
    return Response(generate_latest(request.app.state.metrics.registry), media_type=CONTENT_TYPE_LATEST)
