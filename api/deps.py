"""FastAPI dependencies: settings, database session, storage, Celery app."""

from __future__ import annotations

from functools import lru_cache

from celery import Celery

from api.db import get_session  # noqa: F401 - re-exported for the routes
from api.settings import Settings, get_settings
from api.storage import Storage, get_storage


def settings_dep() -> Settings:
    return get_settings()


def storage_dep() -> Storage:
    return get_storage(get_settings())


@lru_cache
def get_celery() -> Celery:
    """The Celery app the API sends job chains with (configured from the same settings as the workers)."""
    from worker.celery_app import create_celery_app

    return create_celery_app()


def celery_dep() -> Celery:
    return get_celery()
