"""FastAPI dependencies as ``Annotated`` aliases: the session, settings, storage, task queue and current key.

Routes declare ``session: SessionDep, key: CurrentKey`` and hand them to the keyword-only
service functions in :mod:`api.services`; nothing here builds anything at import.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, HTTPException, Request, status
from sqlalchemy.orm import Session

from api.auth import CHALLENGE, idempotency_key, key_of_token, presented_token, refusal
from api.http_semantics import root_of
from voxe_service.db import get_session
from voxe_service.models import LOCAL_KEY_ID, ApiKey
from voxe_service.queue import TaskQueue, get_queue
from voxe_service.settings import Settings, get_settings
from voxe_service.storage import Storage, get_storage


def settings_dep() -> Settings:
    return get_settings()


def storage_dep() -> Storage:
    return get_storage(get_settings())


def queue_dep() -> TaskQueue:
    """The sender of task messages (by name: the API imports no worker code)."""
    return get_queue()


SessionDep = Annotated[Session, Depends(get_session)]
SettingsDep = Annotated[Settings, Depends(settings_dep)]
StorageDep = Annotated[Storage, Depends(storage_dep)]
QueueDep = Annotated[TaskQueue, Depends(queue_dep)]
IdempotencyKey = Annotated[str | None, Depends(idempotency_key)]


def root_dep(request: Request) -> str:
    return root_of(request.scope)


RootPath = Annotated[str, Depends(root_dep)]  # the proxy's prefix the links an answer gives start with


def current_key(request: Request, session: SessionDep) -> ApiKey:
    """The key this request acts as (401 when authentication is on and it has none).

    :class:`api.auth.RequireKey` has already authenticated /v1 requests; its key id is only looked up again.
    """
    if not get_settings().auth_enabled:
        return session.get(ApiKey, LOCAL_KEY_ID)
    key_id = getattr(request.state, "api_key_id", None)
    token = presented_token(request)
    key = session.get(ApiKey, key_id) if key_id else key_of_token(session, token) if token else None
    if (refused := refusal(key, token)) is not None:
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, refused, headers=CHALLENGE)
    return key


CurrentKey = Annotated[ApiKey, Depends(current_key)]
