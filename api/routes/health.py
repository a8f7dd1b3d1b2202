"""Liveness and readiness."""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from datetime import timedelta

from fastapi import APIRouter
from fastapi.responses import JSONResponse
from sqlalchemy import select, text

from api.deps import QueueDep, SettingsDep, StorageDep
from voxe_service.db import session_scope
from voxe_service.models import WorkerHeartbeat, utcnow
from voxe_service.settings import Settings, model_label

router = APIRouter(tags=["health"])


@router.get("/healthz", summary="Liveness: the API process answers")
def healthz() -> dict:
    return {"status": "ok"}


def _check_db() -> dict:
    with session_scope() as session:
        session.execute(text("SELECT 1"))
    return {"ok": True}


def _check_broker(celery, timeout: float) -> dict:
    with celery.connection_for_write() as connection:
        connection.ensure_connection(max_retries=1, timeout=timeout)
        return {"ok": True, "url": connection.as_uri()}


def _check_storage(storage) -> dict:
    storage.check_writable()
    return {"ok": True, "backend": storage.describe()}


def _check_workers(celery, settings: Settings) -> dict:
    with celery.connection_for_read() as connection:
        can_broadcast = "fanout" in connection.transport.implements.exchange_type
    if can_broadcast:
        replies = celery.control.ping(timeout=settings.readiness_timeout_s) or []
        names = sorted(name for reply in replies for name in reply)
        return {"ok": bool(names), "method": "celery control ping", "workers": names}
    # The SQL broker cannot broadcast: workers record a heartbeat in the database instead.
    fresh = utcnow() - timedelta(seconds=max(3 * settings.worker_heartbeat_s, 15))
    with session_scope() as session:
        names = sorted(session.scalars(select(WorkerHeartbeat.hostname).where(WorkerHeartbeat.last_seen >= fresh)))
    return {"ok": bool(names), "method": "database heartbeat", "workers": names}


@router.get("/readyz", summary="Readiness: database, broker, storage and at least one worker",
            responses={503: {"description": "a dependency is down; the body says which"}})
def readyz(settings: SettingsDep, queue: QueueDep, storage: StorageDep):
    celery = queue.app
    checks = {
        "database": lambda: _check_db(),
        "broker": lambda: _check_broker(celery, settings.readiness_timeout_s),
        "storage": lambda: _check_storage(storage),
        "worker": lambda: _check_workers(celery, settings),
    }
    results: dict[str, dict] = {}
    started = time.monotonic()
    pool = ThreadPoolExecutor(len(checks), thread_name_prefix="readyz")
    try:
        futures = {name: pool.submit(check) for name, check in checks.items()}
        deadline = started + settings.readiness_timeout_s * 3 + 2
        for name, future in futures.items():
            try:
                results[name] = future.result(timeout=max(0.0, deadline - time.monotonic()))
            except TimeoutError:
                results[name] = {"ok": False, "error": "timed out"}
            except Exception as exc:  # noqa: BLE001 - reported, not raised
                results[name] = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
    finally:
        pool.shutdown(wait=False, cancel_futures=True)
    ready = all(r.get("ok") for r in results.values())
    body = {
        "status": "ready" if ready else "not ready",
        "checks": results,
        "models": {"sds": model_label(settings.sds_model), "attention": model_label(settings.attention_model)},
        "seconds": round(time.monotonic() - started, 3),
    }
    return JSONResponse(body, status_code=200 if ready else 503)
