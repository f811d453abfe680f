"""Dependencies of the routers: the store, the settings and the caller's identity."""

from __future__ import annotations

import base64
import json

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
    holder = store.token_holder(credentials.credentials)
    if holder is None:
        raise HTTPException(401, "unknown or revoked token", headers={"WWW-Authenticate": "Bearer"})
    request.state.owner, request.state.admin = holder
    return holder[0]


def admin_owner(request: Request, owner: str = Depends(current_owner)) -> str:
    """The owner of an admin token (``handretarget token create NAME --admin``); 403 otherwise."""
    if not request.state.admin:
        raise HTTPException(403, "this needs an admin token (`handretarget token create NAME --admin`)")
    return owner


def encode_cursor(*key) -> str:
    """An opaque paging cursor: the sort key of the last item of a page."""
    return base64.urlsafe_b64encode(json.dumps(list(key)).encode()).decode().rstrip("=")


def decode_cursor(cursor: str | None, types: tuple) -> tuple | None:
    """The sort key in ``cursor`` (None for the first page); 422 unless it is one this service
    gave, with values of ``types``."""
    if cursor is None:
        return None
    try:
        key = json.loads(base64.urlsafe_b64decode(cursor + "=" * (-len(cursor) % 4)))
        if not (isinstance(key, list) and len(key) == len(types)
                and all(isinstance(v, t) and not isinstance(v, bool) for v, t in zip(key, types))):
            raise ValueError(cursor)
    except ValueError:
        raise HTTPException(422, "cursor: not a cursor of this list; pass the next_cursor of the previous page "
                                 "(or none for the first page)") from None
    return tuple(key)


def require_intact(store: Store, asset, what: str = "") -> None:
    """410 when the stored file of ``asset`` (an :class:`~server.storage.AssetRow`) is missing
    or no longer matches its recorded sha256; uploading the same bytes again repairs it."""
    problem = store.blob_problem(store.asset_path(asset))
    if problem is not None:
        raise HTTPException(410, f"{what + ': ' if what else ''}the stored content of {asset.kind} asset {asset.id} "
                                 f"is {problem} on the server (its sha256 no longer matches); upload the same file "
                                 f"again to repair it")
