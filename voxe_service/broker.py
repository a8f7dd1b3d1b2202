"""kombu's SQLAlchemy transport (the embedded broker) with a configurable polling interval, keeping no delivered
message.

Stock ``kombu.transport.sqlalchemy`` polls the message table every 1 s (the
virtual transport's default), and it hands *every* transport option to
``sqlalchemy.create_engine`` -- so the generic ``polling_interval`` option
crashes engine creation ("Invalid argument(s) 'polling_interval' sent to
create_engine()"). This subclass keeps the options that are not engine
arguments away from ``create_engine``; the virtual transport itself reads
``polling_interval``. Registered under the ``sqla`` / ``sqlalchemy`` URL schemes.

Stock ``_get`` also keeps every delivered message, marked invisible, for ever: the table grew with every
stage message and each poll scanned past them all (~200 ms under SQLite's write lock at 200,000). kombu
never reads an invisible row again (a message not acknowledged goes back through ``_put``, as a new row,
when its channel closes or it is rejected), so here a delivered message's row is deleted, and the rows an
earlier version left invisible go when a process first opens the database.
"""

from __future__ import annotations

import logging
from base64 import b64decode
from json import loads
from queue import Empty

from kombu import Connection
from kombu.transport import TRANSPORT_ALIASES
from kombu.transport import sqlalchemy as _sqla
from kombu.utils.encoding import bytes_to_str
from sqlalchemy import create_engine, delete, text
from sqlalchemy.engine import make_url
from sqlalchemy.exc import IntegrityError

from voxe_service.db import connect_timeout_args, database_setup, make_engine

log = logging.getLogger("voxe.broker")

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
        # Bound parameters out of its errors, as the metadata engines' (voxe_service.db): a message's body is a task's.
        return create_engine(conninfo.hostname, hide_parameters=True,
                             connect_args=connect_timeout_args(conninfo.hostname), **options)

    def _open(self):
        url = self.connection.client.hostname
        if url in self._engines:
            return super()._open()
        with database_setup(url):  # kombu makes its tables as it first opens the database
            engine, session_factory = super()._open()
        with engine.begin() as conn:  # the delivered messages an earlier version kept
            conn.execute(delete(self.message_cls.__table__).where(self.message_cls.visible.is_(False)))
        return engine, session_factory

    def _get_or_create(self, queue):
        """kombu's, but where another process made the queue's row at once (UNIQUE constraint failed: the API and a
        worker first sending to and reading a queue) its row is read, not the error raised."""
        try:
            return super()._get_or_create(queue)
        except IntegrityError:
            self.session.rollback()
            return super()._get_or_create(queue)

    def _get(self, queue):
        """kombu's, but the delivered message's row is deleted instead of kept invisible."""
        obj = self._get_or_create(queue)
        if self.session.bind.name == "sqlite":
            self.session.execute(text("BEGIN IMMEDIATE TRANSACTION"))
        try:
            msg = (self.session.query(self.message_cls).with_for_update()
                   .filter(self.message_cls.queue_id == obj.id, self.message_cls.visible.is_not(False))
                   .order_by(self.message_cls.sent_at, self.message_cls.id).limit(1).first())
            if msg is None:
                raise Empty()
            self.session.delete(msg)
            return loads(bytes_to_str(msg.payload))
        finally:
            self.session.commit()


class Transport(_sqla.Transport):
    Channel = Channel


def waiting_tasks(url: str) -> set[tuple[str, str]]:
    """(task name, its argument) of every task the broker's waiting messages are to run: each message's own and those
    of the chain it sends next (Celery's message protocol 2: the chain rides in the body). A message a worker has
    taken is not here (its row went as it was delivered): running, or lost with a worker killed before it ended.
    A message not of that shape (no JSON, no task) is skipped, as a warning says once: one had made the whole table
    unreadable, the reaper taking no queued job's message as lost until a worker took it."""
    register()
    tasks = set()
    with Connection(url) as conn:
        channel = conn.default_channel
        try:
            rows = channel.session.query(channel.message_cls.id, channel.message_cls.payload).filter(
                channel.message_cls.visible.is_not(False)).all()
        finally:  # kombu's channel never closes its session, whose connection stayed checked out until collected:
            channel.session.close()  # reapers reading at once ran the broker's pool dry, each read timing out
        for message_id, payload in rows:
            try:
                message = loads(bytes_to_str(payload))
                args, _kwargs, embed = loads(b64decode(message["body"]))
                # (one argument each: voxe_service.queue's contract; a message of another shape, `celery call`'s say,
                # is no job's)
                found = {(task, task_args[0]) for task, task_args in (
                    (message["headers"]["task"], args),
                    *((step["task"], step.get("args")) for step in embed.get("chain") or ()))
                    if task_args and len(task_args) == 1}
            except (ValueError, TypeError, KeyError, AttributeError) as exc:
                if (url, message_id) not in _malformed_seen:
                    _malformed_seen.add((url, message_id))
                    log.warning("the SQL broker's waiting message %s is no Celery task message (%s: %s): skipped",
                                message_id, type(exc).__name__, exc)
                continue
            tasks |= found
    return tasks


_malformed_seen: set[tuple[str, int]] = set()
"""(broker URL, message id) of the malformed waiting messages a warning has named."""


def register() -> None:
    TRANSPORT_ALIASES["sqla"] = TRANSPORT_ALIASES["sqlalchemy"] = "voxe_service.broker:Transport"
