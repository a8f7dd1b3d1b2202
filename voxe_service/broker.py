"""kombu's SQLAlchemy transport (the embedded broker) with a configurable polling interval.

Stock ``kombu.transport.sqlalchemy`` polls the message table every 1 s (the
virtual transport's default), and it hands *every* transport option to
``sqlalchemy.create_engine`` -- so the generic ``polling_interval`` option
crashes engine creation ("Invalid argument(s) 'polling_interval' sent to
create_engine()"). This subclass keeps the options that are not engine
arguments away from ``create_engine``; the virtual transport itself reads
``polling_interval``. Registered under the ``sqla`` / ``sqlalchemy`` URL schemes.
"""

from __future__ import annotations

from kombu.transport import TRANSPORT_ALIASES
from kombu.transport import sqlalchemy as _sqla
from sqlalchemy import create_engine
from sqlalchemy.engine import make_url

from voxe_service.db import make_engine

# Options kombu / Celery use themselves; none of them is a create_engine() argument.
_NOT_ENGINE_OPTIONS = frozenset({
    "queue_tablename", "message_tablename", "callback", "errback", "max_retries", "interval_start",
    "interval_step", "interval_max", "retry_errors", "polling_interval", "visibility_timeout",
    "confirm_publish", "fanout_prefix", "fanout_patterns",
})


class Channel(_sqla.Channel):
    def _engine_from_config(self):
        conninfo = self.connection.client
        if make_url(conninfo.hostname).get_backend_name() == "sqlite":
            # The metadata database's SQLite setup: WAL (the API publishing never waits for a polling
            # worker's read, and a commit is one WAL append) and a 30 s busy timeout.
            return make_engine(conninfo.hostname)
        options = {k: v for k, v in conninfo.transport_options.items() if k not in _NOT_ENGINE_OPTIONS}
        return create_engine(conninfo.hostname, **options)


class Transport(_sqla.Transport):
    Channel = Channel


def register() -> None:
    TRANSPORT_ALIASES["sqla"] = TRANSPORT_ALIASES["sqlalchemy"] = "voxe_service.broker:Transport"
