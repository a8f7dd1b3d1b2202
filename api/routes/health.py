"""Liveness and readiness."""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import JSONResponse
from sqlalchemy import text

from api.auth import key_of_token, not_local, presented_token, refusal
from api.deps import QueueDep, SettingsDep, StorageDep
from voxe_service.db import session_scope
from voxe_service.model_inventory import ROLES, live_worker_models
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
    with session_scope() as session:
        names = sorted(live_worker_models(session, settings))
    return {"ok": bool(names), "method": "database heartbeat", "workers": names}


def _model_report(settings: Settings) -> dict:
    """Per role, the model jobs will ask for (this API's settings) and the live workers that have it / lack it.

    From the workers' heartbeats (each checks the models of its own settings offline at its start and at every
    heartbeat); a worker configured with another model for a role is in neither list but in ``workers_reporting_other``.
    ``reported`` is false when no live worker reports on the model: nothing then says whether jobs will find it, and
    each learns only when its chain starts.
    """
    with session_scope() as session:
        inventories = live_worker_models(session, settings)
    report = {}
    for role in ROLES.values():
        model = getattr(settings, role.setting)
        found = {host: inv[role.name]["present"] for host, inv in inventories.items()
                 if inv and inv.get(role.name, {}).get("model") == model}
        report[role.name] = {"model": model_label(model), "setting": role.variable,
                             "workers_with": sorted(h for h, ok in found.items() if ok),
                             "workers_without": sorted(h for h, ok in found.items() if not ok),
                             "reported": bool(found),
                             "workers_reporting_other": sorted(h for h, inv in inventories.items()
                                                               if inv and role.name in inv and h not in found)}
    return report


_ASK_FOR_A_KEY = "send an API key for each check's details and the models' availability"
_KEY_UNCHECKED = ("the API key sent could not be checked (the database is not reachable): each check's details and the "
                  "models' availability are shown to a live key's holder once it is")


def _hidden_because(request: Request, settings: Settings) -> str | None:
    """Why /readyz shows this caller none of its checks' details (None: it shows them, a live key presented, or
    authentication off and the request one the API serves as the local key). They name the deployment's internals
    (the storage path or bucket, the broker's URL, worker hostnames, the errors' text), and /readyz needs no key: a
    load balancer needs only the status and which check failed. With authentication off they had been shown to any
    caller, one a proxy relayed or a page of another site too, which /v1 refuses (``not_local``). A key that cannot be
    checked (the database down) is told so: "send an API key" had answered the operator who sent theirs. Two
    different keys sent are not checked and are said so, not answered /v1's 401: the probe needs no key, and a probe
    or proxy adding a header had failed it with "2 different API keys sent"."""
    if not settings.auth_enabled:
        why = not_local(request.scope, settings)
        return None if why is None else ("authentication is off, so each check's details and the models' availability "
                                         f"are shown only to loopback connections from this machine, and {why}")
    try:
        token = presented_token(request)
    except HTTPException as exc:
        return f"{exc.detail} for each check's details and the models' availability"
    if not token:
        return _ASK_FOR_A_KEY
    try:
        with session_scope() as session:
            return None if refusal(key_of_token(session, token), token) is None else _ASK_FOR_A_KEY
    except Exception:  # noqa: BLE001 - no database to check the key in: the checks say so
        return _KEY_UNCHECKED


@router.get("/readyz", summary="Readiness: database, broker, storage and at least one worker",
            responses={503: {"description": "a dependency is down; the body says which (its details only to a "
                                            "caller presenting a live key, or with authentication off to a local "
                                            "one)"}})
def readyz(request: Request, settings: SettingsDep, queue: QueueDep, storage: StorageDep):
    celery = queue.app
    checks = {
        "database": lambda: _check_db(),
        "broker": lambda: _check_broker(celery, settings.readiness_timeout_s),
        "storage": lambda: _check_storage(storage),
        "worker": lambda: _check_workers(celery, settings),
    }
    results: dict[str, dict] = {}
    started = time.monotonic()
    pool = ThreadPoolExecutor(len(checks) + 2, thread_name_prefix="readyz")
    try:
        futures = {name: pool.submit(check) for name, check in checks.items()}
        # The models' availability and the key's check read the database too: under the same deadline (a database
        # that never answers had held the answer, and the request's thread, a connect timeout for each after it).
        models, key_check = pool.submit(_model_report, settings), pool.submit(_hidden_because, request, settings)
        deadline = started + settings.readiness_timeout_s * 3 + 2

        def by_deadline(future):
            return future.result(timeout=max(0.0, deadline - time.monotonic()))

        for name, future in futures.items():
            try:
                results[name] = by_deadline(future)
            except TimeoutError:
                results[name] = {"ok": False, "error": "timed out"}
            except Exception as exc:  # noqa: BLE001 - reported, not raised
                results[name] = {"ok": False, "error": f"{type(exc).__name__}: {exc}"}
        try:
            availability = by_deadline(models)
        except TimeoutError:
            availability = {"error": "timed out"}
        except Exception as exc:  # noqa: BLE001 - the database check above says why
            availability = {"error": f"{type(exc).__name__}: {exc}"}
        try:
            hidden = by_deadline(key_check)
        except TimeoutError:
            hidden = _KEY_UNCHECKED
    finally:
        pool.shutdown(wait=False, cancel_futures=True)
    ready = all(r.get("ok") for r in results.values())
    if hidden is not None:
        return JSONResponse({"status": "ready" if ready else "not ready",
                             "checks": {name: {"ok": bool(result.get("ok"))} for name, result in results.items()},
                             "details": hidden},
                            status_code=200 if ready else 503)
    body = {
        "status": "ready" if ready else "not ready",
        "checks": results,
        "models": {"sds": model_label(settings.sds_model), "attention": model_label(settings.attention_model)},
        "model_availability": availability,
        "seconds": round(time.monotonic() - started, 3),
    }
    return JSONResponse(body, status_code=200 if ready else 503)
