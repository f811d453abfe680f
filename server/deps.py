"""Dependencies of the routers: the store, the settings and the caller's identity."""

from __future__ import annotations

from fastapi import Depends, HTTPException, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from .settings import Settings
from .storage import Store

_bearer = HTTPBearer(auto_error=False, description="a token from `handretarget token create NAME`")


def get_store(request: Request) -> Store:
    return request.app.state.store


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def current_owner(request: Request, credentials: HTTPAuthorizationCredentials | None = Depends(_bearer),
                  store: Store = Depends(get_store)) -> str:
    """The owner of the bearer token; 401 without a valid one."""
    if credentials is None or credentials.scheme.lower() != "bearer":
        raise HTTPException(401, "missing bearer token: send 'Authorization: Bearer <token>' "
                                 "(create one with `handretarget token create NAME`)",
                            headers={"WWW-Authenticate": "Bearer"})
    owner = store.owner_of(credentials.credentials)
    if owner is None:
        raise HTTPException(401, "unknown or revoked token", headers={"WWW-Authenticate": "Bearer"})
    request.state.owner = owner
    return owner


def require_intact(store: Store, asset, what: str = "") -> None:
    """410 when the stored file of ``asset`` (an :class:`~server.storage.AssetRow`) is missing
    or no longer matches its recorded sha256; uploading the same bytes again repairs it."""
    problem = store.blob_problem(store.asset_path(asset))
    if problem is not None:
        raise HTTPException(410, f"{what + ': ' if what else ''}the stored content of {asset.kind} asset {asset.id} "
                                 f"is {problem} on the server (its sha256 no longer matches); upload the same file "
                                 f"again to repair it")
