"""/v1/webhooks: the key's signing secret, and its rotation (a job's deliveries are at /v1/jobs/{id}/webhooks)."""

from __future__ import annotations

from fastapi import APIRouter, Response

from api.deps import CurrentKey, SessionDep
from api.http_semantics import StrictRoute
from api.schemas import WebhookSecretOut
from api.services import jobs

router = APIRouter(prefix="/v1/webhooks", tags=["webhooks"], route_class=StrictRoute)


@router.get("/secret", response_model=WebhookSecretOut,
            summary="This key's webhook secret: verify deliveries' webhook-signature with it (Standard Webhooks)")
def get_secret(response: Response, session: SessionDep, key: CurrentKey) -> WebhookSecretOut:
    response.headers["Cache-Control"] = "no-store"  # a secret: not kept even in the browser's cache
    return WebhookSecretOut(secret=jobs.webhook_secret(session=session, key=key))


@router.post("/secret/rotate", response_model=WebhookSecretOut,
             summary="Replace this key's webhook secret (a leaked one): every delivery attempt from now on, a retry "
                     "of an earlier one included, is signed with the new one it answers")
def rotate_secret(response: Response, session: SessionDep, key: CurrentKey) -> WebhookSecretOut:
    response.headers["Cache-Control"] = "no-store"
    return WebhookSecretOut(secret=jobs.rotate_webhook_secret(session=session, key=key))
