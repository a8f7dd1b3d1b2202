"""The worker's Celery app: ``celery -A worker.celery_app worker -Q gpu``.

Built by the service core's factory (``voxe_service.queue.create_celery_app``) with the
task module registered; only the worker imports this module, so only the worker builds
an app with tasks at import. The API sends by task name through its own sender.
"""

from __future__ import annotations

import sys

from voxe_service.queue import create_celery_app
from voxe_service.settings import SettingsError, check_worker_device, get_settings, refuse_settings

try:
    check_worker_device(get_settings())  # (a device this machine lacks had failed every job instead)
except SettingsError as exc:  # one line naming the setting, as Celery's traceback had ended with
    sys.exit(refuse_settings("Vox-E worker", exc))
app = create_celery_app(include=["worker.tasks"])
