"""Database engine, sessions and migrations (one engine per process, for the API and the workers alike)."""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import timedelta
from functools import lru_cache
from pathlib import Path

from sqlalchemy import Engine, create_engine, event, select, text, update
from sqlalchemy.engine import make_url
from sqlalchemy.exc import OperationalError, TimeoutError as PoolTimeout
from sqlalchemy.orm import Session, sessionmaker
from sqlalchemy.pool import NullPool

from voxe_service import models
from voxe_service.failing import FailingStreak
from voxe_service.settings import get_settings, sqlite_file

log = logging.getLogger("voxe.db")

CLOCK_WARN_S = 1.0  # a measured offset beyond this is logged: the machine's clock is off (NTP)

MIGRATIONS = Path(__file__).resolve().parent / "migrations"


DATABASE_UNAVAILABLE = (PoolTimeout, OperationalError)
"""The errors a database that cannot serve now raises, among others (:func:`database_outage` tells them apart)."""
_SQLITE_UNAVAILABLE = ("database is locked", "database table is locked", "unable to open database", "disk i/o error")


def database_outage(exc: Exception) -> str | None:
    """Why ``exc`` means the database cannot serve now (down, unreachable, locked, its pool in use), or None when
    it does not: a fault of the service, its schema or its settings (SQLite raises its OperationalError for a
    missing table or bad SQL too), which a retry would meet again. The API answers an outage 503, a worker sends
    a stage it could not start back to the queue without counting it."""
    if isinstance(exc, PoolTimeout):
        return ("every database connection of this process is in use (VOXE_DATABASE_POOL_SIZE + "
                "VOXE_DATABASE_MAX_OVERFLOW)")
    if not isinstance(exc, OperationalError):
        return None
    cause = getattr(exc, "orig", None)
    is_sqlite = type(cause).__module__.startswith("sqlite3")
    if exc.connection_invalidated or not is_sqlite or str(cause).lower().startswith(_SQLITE_UNAVAILABLE):
        return "the database cannot be reached or is locked"
    return None


def outage_line(exc: BaseException) -> str | None:
    """``exc`` said in one line naming VOXE_DATABASE_URL where it is an outage (:func:`database_outage`), else None:
    ``python -m api.admin`` and the API's start say it so, where SQLAlchemy's traceback, a page of it, had been."""
    if not isinstance(exc, DATABASE_UNAVAILABLE) or (why := database_outage(exc)) is None:
        return None
    cause = str(getattr(exc, "orig", None) or exc).strip().partition("\n")[0]
    return f"{why} (VOXE_DATABASE_URL): {cause}"


def ensure_sqlite_dir(url: str) -> None:
    """Create the folder of a file-backed SQLite URL (``sqlite:///./var/voxe.db``)."""
    path = sqlite_file(url)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)


POSTGRES_CONNECT_TIMEOUT_S = 10
"""How long a PostgreSQL connect waits for the server where the URL sets no ``connect_timeout``: libpq waits for ever,
so a server that accepts and never answers (hung, partitioned) had held every request and /readyz thread for good."""


POSTGRES_KEEPALIVE = {"keepalives": 1, "keepalives_idle": 30, "keepalives_interval": 10, "keepalives_count": 3,
                      "tcp_user_timeout": 60_000}
"""libpq's TCP settings for a PostgreSQL connection where the URL sets none of its own: libpq has no read timeout, and
the system's keepalives first probe after 2 hours, so a query whose server's machine went away (crashed, partitioned,
a fail-over's old primary) had waited that long, holding its request, heartbeat or stage; now it fails, as an outage,
within about a minute. (A server process stopped while its machine still answers TCP is not bounded by them.)"""


def connect_timeout_args(url: str) -> dict:
    """``connect_args`` bounding a psycopg connection's waits: its connect :data:`POSTGRES_CONNECT_TIMEOUT_S`, a dead
    server's machine :data:`POSTGRES_KEEPALIVE`, each setting unless the URL says its own."""
    parsed = make_url(url)
    if (parsed.get_backend_name(), parsed.get_driver_name()) not in (("postgresql", "psycopg"),
                                                                      ("postgresql", "psycopg2")):
        return {}
    defaults = {"connect_timeout": POSTGRES_CONNECT_TIMEOUT_S, **POSTGRES_KEEPALIVE}
    return {key: value for key, value in defaults.items() if key not in parsed.query}


def make_engine(url: str, *, pool_size: int = 5, max_overflow: int = 10, pool_timeout_s: float = 30.0) -> Engine:
    """An engine for ``url`` whose pool holds ``pool_size`` connections, opens up to ``max_overflow`` more under load,
    and makes a caller finding all in use wait ``pool_timeout_s`` before ``sqlalchemy.exc.TimeoutError``.

    Its errors (and echo) leave out a statement's bound values: a failed UPDATE of a webhook delivery had logged its
    last_error, webhook_url credentials and all, and any other secret a statement binds (a key's webhook secret)."""
    parsed = make_url(url)
    pool = {"pool_size": pool_size, "max_overflow": max_overflow, "pool_timeout": pool_timeout_s}
    if parsed.get_backend_name() == "sqlite":
        ensure_sqlite_dir(url)
        if parsed.database in (None, "", ":memory:"):  # one connection per thread (SingletonThreadPool): no sizes
            pool = {}
        engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": 30}, hide_parameters=True,
                               **pool)

        @event.listens_for(engine, "connect")
        def _sqlite_pragmas(dbapi_connection, _record):  # API and workers write concurrently
            cursor = dbapi_connection.cursor()
            cursor.execute("PRAGMA journal_mode=WAL")
            cursor.execute("PRAGMA busy_timeout=30000")
            cursor.execute("PRAGMA foreign_keys=ON")
            cursor.close()

        return engine
    return create_engine(url, pool_pre_ping=True, hide_parameters=True, connect_args=connect_timeout_args(url), **pool)


@lru_cache
def get_engine() -> Engine:
    settings = get_settings()
    return make_engine(settings.database_url, pool_size=settings.database_pool_size,
                       max_overflow=settings.database_max_overflow, pool_timeout_s=settings.database_pool_timeout_s)


@lru_cache
def get_sessionmaker() -> sessionmaker[Session]:
    return sessionmaker(bind=get_engine(), expire_on_commit=False)


def get_session() -> Iterator[Session]:
    """FastAPI dependency: one session per request."""
    with get_sessionmaker()() as session:
        yield session


@contextmanager
def session_scope() -> Iterator[Session]:
    """A session that commits on success and rolls back on error (workers, scripts)."""
    with get_sessionmaker()() as session:
        try:
            yield session
            session.commit()
        except BaseException:
            session.rollback()
            raise


def locked(session: Session, model, row_id: str):
    """The row ``row_id`` of ``model`` (a model with ``id`` and ``updated_at``; None: no such row), locked until
    the transaction ends, on either database.

    PostgreSQL: ``SELECT ... FOR UPDATE``. SQLite has no row locks (its ``FOR UPDATE`` locks nothing: concurrent
    writers had overwritten each other's results): a write of the row's own ``updated_at`` first takes the
    database's write lock. Not so on PostgreSQL: a row updated twice in one transaction has its foreign keys
    checked again, which waits for the rows they name, and job submission holds its key's row while it locks
    the scene (a deadlock).
    """
    query = select(model).where(model.id == row_id).execution_options(populate_existing=True)
    if session.get_bind().dialect.name == "sqlite":
        session.execute(update(model).where(model.id == row_id).values(updated_at=model.updated_at))
        return session.scalars(query).first()
    return session.scalars(query.with_for_update(of=model)).first()


_CLOCK_READINGS = FailingStreak(log, "database clock", "reading", "readings")
"""This process's readings of the database's clock failing in a row (a traceback at every heartbeat and reaper pass
had filled the log while PostgreSQL was down). A process forked from this one (a Celery pool process, re-forked
while the worker's heartbeats failed) counts its own from zero: it had logged its first failure "reading 5 in a
row failed", with no traceback."""
os.register_at_fork(after_in_child=lambda: setattr(_CLOCK_READINGS, "failed", 0))


def sync_clock(engine: Engine | None = None) -> timedelta | None:
    """Measure this process's clock against the database server's and set ``utcnow``'s offset to it; the offset,
    or None when it could not be measured (logged; the last one stays).

    PostgreSQL: ``clock_timestamp()`` against the midpoint of the round trip (off by at most half of it). SQLite
    lives on this machine, whose processes share its clock: offset zero. Processes call it as they start and
    then at their heartbeats, reaper passes and stage starts, so machines whose clocks drift apart still agree.
    """
    engine = engine or get_engine()
    if engine.dialect.name != "postgresql":
        offset = timedelta(0)
    else:
        try:
            with engine.connect() as connection:
                before = models.system_now()
                server = connection.execute(text("SELECT clock_timestamp()")).scalar_one()
                after = models.system_now()
        except Exception as exc:  # noqa: BLE001 - the database unreachable: the last offset stays until the next try
            _CLOCK_READINGS.note_failure(exc, "; the last offset measured stays")
            return None
        _CLOCK_READINGS.succeeded()
        offset = server - (before + (after - before) / 2)
        if abs(offset.total_seconds()) > CLOCK_WARN_S:
            log.warning("this machine's clock is %.1f s off the database server's: the service uses the "
                        "database's (keep the machines NTP-synchronised)", -offset.total_seconds())
    models.set_clock_offset(offset)
    return offset


def alembic_config(database_url: str):
    """Alembic's configuration for the service's migrations on ``database_url`` (no alembic.ini needed)."""
    from alembic.config import Config

    config = Config()
    config.set_main_option("script_location", str(MIGRATIONS))
    config.set_main_option("sqlalchemy.url", database_url.replace("%", "%%"))
    return config


def run_migrations(database_url: str) -> None:
    """``alembic upgrade head`` on ``database_url``; existing databases upgrade in place.

    Processes starting together (API replicas) upgrade one after another: PostgreSQL under an advisory lock
    (``migrations/env.py``), a SQLite file under a lock file beside it (SQLite runs DDL outside transactions).

    A SQLite file is set up under :func:`database_setup` (in WAL mode before its tables are made).
    """
    from alembic import command

    with database_setup(database_url):
        command.upgrade(alembic_config(database_url), "head")


SETUP_LOCK = 0x766F7866
"""The PostgreSQL advisory lock :func:`database_setup` holds (not the migrations' own, which they take inside it)."""
SETUP_LOCK_WAIT_S = 600.0
"""How long :func:`database_setup` waits for :data:`SETUP_LOCK` held by another session before it fails naming that
session: ``pg_advisory_lock`` waits without limit, and a stuck holder (a process hung in its migration, a session left
open by hand) had held every API and worker start silently for good."""


@contextmanager
def database_setup(url: str) -> Iterator[None]:
    """Set up a database (make its tables) inside: one process at a time. A SQLite file under a lock file beside it,
    the file turned to WAL mode (which it keeps) first; a PostgreSQL database under an advisory lock; other databases
    as they are, with no lock.

    The metadata database (:func:`run_migrations`) and the SQL broker's (``voxe_service.broker``), each opened at
    once by the API and a worker on a fresh install: the service's connections (:func:`make_engine`) each ask for
    WAL at connect, and on a file still in rollback mode one of two doing so at once was refused "database is
    locked" (SQLite's deadlock rule: no busy timeout is waited); two making the same tables, one was refused
    "table ... already exists" (SQLite runs DDL outside transactions), on PostgreSQL a duplicate key in its catalog
    (kombu's tables: each process looks for them, then makes them).
    """
    if make_url(url).get_backend_name() == "postgresql":
        engine = create_engine(url, poolclass=NullPool, hide_parameters=True, connect_args=connect_timeout_args(url))
        try:  # held by the session, in no transaction; released as its connection closes, or its process dies
            with engine.connect().execution_options(isolation_level="AUTOCOMMIT") as connection:
                _take_setup_lock(connection)
                yield
        finally:
            engine.dispose()
        return
    path = sqlite_file(url)
    if path is None:
        yield
        return
    import fcntl

    ensure_sqlite_dir(url)
    with open(f"{path}.migrate.lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes, or its process dies
        engine = make_engine(url, pool_size=1, max_overflow=0)
        with engine.connect():  # (its connect turns the file to WAL)
            pass
        engine.dispose()
        yield


def _take_setup_lock(connection) -> None:
    """Take :data:`SETUP_LOCK` for ``connection``'s session, waiting at most :data:`SETUP_LOCK_WAIT_S`: a warning
    names the session holding it as the wait begins, and a RuntimeError names it, and how long it waited, at the end."""
    started, holder = time.monotonic(), None
    while not connection.execute(text("SELECT pg_try_advisory_lock(:key)"), {"key": SETUP_LOCK}).scalar_one():
        waited = time.monotonic() - started
        if waited >= SETUP_LOCK_WAIT_S:
            raise RuntimeError(f"gave up after waiting {waited:.0f} s for the database setup lock (PostgreSQL advisory "
                               f"lock {SETUP_LOCK}), held by {_setup_lock_holder(connection)}: a process still setting "
                               "up the database, or a stuck one (SELECT pg_terminate_backend(<its pid>) ends it)")
        if holder is None:
            holder = _setup_lock_holder(connection)
            log.warning("waiting for the database setup lock (PostgreSQL advisory lock %d), held by %s; giving up "
                        "after %.0f s", SETUP_LOCK, holder, SETUP_LOCK_WAIT_S)
        time.sleep(min(0.5, max(SETUP_LOCK_WAIT_S - waited, 0.01)))


def _setup_lock_holder(connection) -> str:
    """The session holding :data:`SETUP_LOCK`, in words (its pid, application, client, state and since when)."""
    row = connection.execute(text(
        "SELECT a.pid, a.application_name, a.client_addr, a.state, a.state_change FROM pg_locks l "
        "JOIN pg_stat_activity a ON a.pid = l.pid WHERE l.locktype = 'advisory' AND l.granted "
        "AND l.database = (SELECT oid FROM pg_database WHERE datname = current_database()) "
        "AND l.classid::bigint = 0 AND l.objid::bigint = :key AND l.objsubid = 1"), {"key": SETUP_LOCK}).first()
    if row is None:  # (released meanwhile, or a session this role may not see)
        return "another session"
    since = f" since {row.state_change:%Y-%m-%d %H:%M:%S %Z}" if row.state_change else ""
    return (f"the session of pid {row.pid} (application {row.application_name or '(none)'!r}, client "
            f"{row.client_addr or 'local socket'}, {row.state or 'state not shown'}{since})")


def reset_caches() -> None:
    """Forget the settings, engine and session factory (tests that change the environment)."""
    if get_engine.cache_info().currsize:
        get_engine().dispose()
    get_engine.cache_clear()
    get_sessionmaker.cache_clear()
    get_settings.cache_clear()
    models.set_clock_offset(timedelta(0))
