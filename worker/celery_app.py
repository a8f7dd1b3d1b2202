"""The Celery application, configured from the service settings (shared with the API).

Long GPU tasks: late acks, one prefetched message, a rejected (redelivered)
message when the worker process dies, and a broker visibility timeout above the
hard time limit so Redis never redelivers a task that is still running.
"""

from __future__ import annotations

from celery import Celery
from kombu import Queue

from api.db import ensure_sqlite_dir
from api.settings import get_settings
from worker.broker import register as register_sql_transport

GPU_QUEUE = "gpu"
TASK_NAMES = {stage: f"voxe.{stage}" for stage in ("reconstruct", "edit", "refine", "export", "evaluate")}


def job_stages(mode: str) -> list[str]:
    if mode == "evaluate":  # an evaluation job (SPEC §4) has one stage
        return ["evaluate"]
    return ["reconstruct", "edit"] + (["refine"] if mode == "local" else []) + ["export"]


def stage_chain(celery: Celery, job_id: str, mode: str, done=(), then_evaluate=()):
    """The Celery chain of a job's stages not in ``done`` (each task takes only the job id).

    ``then_evaluate``: evaluation jobs whose task follows the last stage (a sweep scores each
    edit once it is done; a failed or canceled edit still lets the evaluation record why).
    """
    from celery import chain

    stages = [s for s in job_stages(mode) if s not in done]
    return chain(*(celery.signature(TASK_NAMES[s], args=(job_id,), immutable=True) for s in stages),
                 *(celery.signature(TASK_NAMES["evaluate"], args=(e,), immutable=True) for e in then_evaluate))


def is_sql_broker(url: str) -> bool:
    return url.split("://", 1)[0].split("+", 1)[0] in ("sqla", "sqlalchemy")


def broker_transport_options(settings) -> dict:
    if is_sql_broker(settings.broker_url):
        return {"polling_interval": settings.broker_polling_interval}  # SQLite: WAL and timeouts in worker.broker
    # Redis / SQS: a message not acked within this many seconds is redelivered.
    return {"visibility_timeout": settings.broker_visibility_timeout_s}


def create_celery_app() -> Celery:
    settings = get_settings()
    register_sql_transport()
    if is_sql_broker(settings.broker_url):
        ensure_sqlite_dir(settings.broker_url.split("+", 1)[1]) if "+sqlite" in settings.broker_url else None
    app = Celery("voxe", broker=settings.broker_url, include=["worker.tasks"])
    app.conf.update(
        task_serializer="json",
        accept_content=["json"],
        result_backend=None,
        task_ignore_result=True,
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        worker_prefetch_multiplier=1,
        worker_max_tasks_per_child=settings.worker_max_tasks_per_child,
        task_soft_time_limit=settings.task_soft_time_limit_s,
        task_time_limit=settings.task_time_limit_s,
        broker_transport_options=broker_transport_options(settings),
        broker_connection_retry_on_startup=True,
        task_default_queue="celery",
        task_queues=(Queue(GPU_QUEUE), Queue("celery")),
        task_routes={"voxe.*": {"queue": GPU_QUEUE}},
        worker_send_task_events=False,
        task_track_started=False,
        worker_hijack_root_logger=False,
    )
    return app


app = create_celery_app()
celery_app = app
