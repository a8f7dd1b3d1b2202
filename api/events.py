"""Live job events as Server-Sent Events: one poller per API process serves every open stream.

A stream holds no database session or connection: the :class:`EventHub` reads, once per
``VOXE_PROGRESS_INTERVAL_S`` (twice a second by default), in one short session, which of the jobs
that open streams watch changed (their ``updated_at`` and newest event id), then only those jobs
and their new events, and hands each stream what is new for it. Streams on jobs where nothing
happens cost two index lookups per poll (bench/service_load.py measures 50 of them beside the
status pollers).

What a stream sends (``event:`` names):

* every timeline event (``stage_started``, ``stage_completed``, ``checkpoint``, ``resumed``,
  ``requeued``, ``warning``, ``artifact``, ``preview``, then ``succeeded`` / ``failed`` / ``canceled``), with
  its ``id:`` -- a client reconnecting with ``Last-Event-ID`` gets every event after it, none twice;
* ``progress`` (no id: it is a snapshot, sent again on reconnect) when the job's state, stage, cancel request,
  iteration or losses changed since the last one, at most once per interval;
* and the stream ends after the job's terminal event, or when the server stops (:meth:`EventHub.end_streams`;
  the client resumes with ``Last-Event-ID``), or with an ``error`` event once the job is deleted or the key that
  opened it is revoked or expires (its token stops working then, open streams included).
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field

import anyio
from sqlalchemy import and_, func, or_, select

from api.schemas import JobEventOut
from voxe_service.db import get_sessionmaker
from voxe_service.failing import FailingStreak
from voxe_service.models import TERMINAL_STATES, ApiKey, Job, JobEvent, utcnow

log = logging.getLogger("voxe.api")

SSE_MEDIA_TYPE = "text/event-stream"
KEEPALIVE_S = 15.0  # a comment line this often keeps proxies from closing a quiet stream
RETRY_MS = 2000  # what EventSource waits before reconnecting
# Jobs whose new events one query reads: SQLite parses its OR of one term per job that many levels deep, and refuses
# a query over 1,000 ("Expression tree is too large"; every stream of the process had stopped at 998 jobs).
EVENT_QUERY_JOBS = 400
# While polls fail (the database unreachable), the next one waits the interval doubling per failure, up to this: what a
# stream's news may wait once the database is back (streams still get their keepalives meanwhile).
FAILING_POLL_MAX_DELAY_S = 10.0


@dataclass
class _Watch:
    """One open stream: the job it follows and what the hub has handed it since it last woke."""

    job_id: str
    after_id: int
    key_id: str
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    events: list[dict] = field(default_factory=list)
    job: dict | None = None
    polled: bool = False
    key_ended: str | None = None
    """How the stream's key stopped working ("was revoked", "expired at <time>"); None while it works."""


def sse(data: dict, event: str, event_id: int | None = None) -> str:
    """One Server-Sent Event; ``data`` as one line of JSON."""
    head = f"id: {event_id}\n" if event_id is not None else ""
    return f"{head}event: {event}\ndata: {json.dumps(data, separators=(',', ':'), default=str)}\n\n"


class EventHub:
    """The shared poller behind every event stream of one API process.

    ``view(job) -> dict`` is what a ``progress`` event carries (the job resource's progress fields).
    """

    def __init__(self, interval_s: float, view: Callable[[Job], dict]):
        self.interval_s, self.view = interval_s, view
        self._watches: list[_Watch] = []
        self._stamps: dict[str, tuple] = {}  # job id -> (updated_at, newest event id) at its last full read
        self._task: asyncio.Task | None = None
        self._ending = False

    async def stream(self, job_id: str, key_id: str, after_id: int = 0, root: str = "") -> AsyncIterator[str]:
        """The job's events after ``after_id`` as SSE text, for key ``key_id``, ending after its terminal event (or
        at :meth:`end_streams`, or once the key is revoked or expires); a ``progress`` event's ``preview_url`` under
        ``root``, the prefix a proxy serves the service under, as the job resource's."""
        watch = _Watch(job_id, after_id, key_id)
        self._watches.append(watch)
        if self._task is None or self._task.done():
            self._task = asyncio.get_running_loop().create_task(self._run())
        clock = asyncio.get_running_loop().time
        try:
            yield f"retry: {RETRY_MS}\n\n"
            sent_progress, said_at = None, clock()
            while True:
                # Counted from the stream's last words, not its last wake: a job whose row changes without news (one
                # waiting on another job's reconstruction rewrites its unchanged progress every second) had woken it
                # too often for a keepalive ever to go, and a proxy's or the web UI's idle timeout cut it.
                try:
                    await asyncio.wait_for(watch.wake.wait(), max(0.0, said_at + KEEPALIVE_S - clock()))
                except TimeoutError:
                    yield ": keepalive\n\n"
                    said_at = clock()
                    continue
                if self._ending:
                    return
                watch.wake.clear()
                events, watch.events = watch.events, []
                for event in events:
                    yield sse(event, event["kind"], event["id"])
                    said_at = clock()
                if watch.key_ended:
                    yield sse({"detail": f"the API key of this stream {watch.key_ended}"}, "error")
                    return
                if watch.job is None:
                    yield sse({"detail": f"job {job_id!r} was deleted"}, "error")
                    return
                if watch.job != sent_progress:
                    sent_progress = watch.job
                    preview = watch.job.get("preview_url")
                    yield sse({**watch.job, "preview_url": root + preview} if root and preview else watch.job,
                              "progress")
                    said_at = clock()
                if watch.job["state"] in TERMINAL_STATES:
                    return
        finally:
            self._watches.remove(watch)

    async def _run(self) -> None:
        streak = FailingStreak(log, "event streams", "poll", "polls")
        while self._watches:
            watches, after, fresh = list(self._watches), {}, set()
            keys = {watch.key_id for watch in watches}
            for watch in watches:
                after[watch.job_id] = min(after.get(watch.job_id, math.inf), watch.after_id)
                if not watch.polled:
                    fresh.add(watch.job_id)
            try:
                stamps, jobs, events, ended = await anyio.to_thread.run_sync(self._poll, after, fresh, keys)
            except Exception as exc:  # noqa: BLE001 - a database hiccup or outage: streams wait for a later poll
                # (the first logged with its traceback, the next a line each: a traceback every poll had filled the
                # log while the database was down, 7,200 an hour; the polls back off up to FAILING_POLL_MAX_DELAY_S)
                await asyncio.sleep(streak.failed_once_more(exc, self.interval_s, FAILING_POLL_MAX_DELAY_S))
                continue
            else:
                streak.succeeded()
                self._stamps = {job_id: stamp for job_id, stamp in {**self._stamps, **stamps}.items()
                                if job_id in after}
                for watch in watches:  # one opened during this poll waits for the next
                    if watch.key_id in ended:
                        watch.key_ended = ended[watch.key_id]
                        watch.wake.set()
                        continue
                    new = [e for e in events.get(watch.job_id, ()) if e["id"] > watch.after_id]
                    if new:
                        watch.events.extend(new)
                        watch.after_id = new[-1]["id"]
                    if watch.job_id not in stamps:
                        watch.job = None  # deleted
                    elif watch.job_id in jobs:
                        watch.job = jobs[watch.job_id]
                    elif not new and watch.polled:
                        continue  # nothing happened to its job
                    watch.polled = True
                    watch.wake.set()
            await asyncio.sleep(self.interval_s)

    def _poll(self, after: dict[str, int], fresh: set[str], keys: set[str]):
        """(every watched job's change stamp, the views of the jobs that changed, the events past ``after`` of
        the jobs that have new ones, how each of the streams' ``keys`` that no longer works stopped: "was revoked",
        "expired at <time>"), in one short session.

        A poll where nothing happened costs two index lookups per job and builds nothing: what changed is
        read from ``updated_at`` and the newest event id. Events are read after the job rows, so a job seen
        terminal comes with its terminal event.
        """
        ids = list(after)
        with get_sessionmaker()() as session:
            ended = {key_id: "was revoked" if revoked_at else f"expired at {expires_at.isoformat(timespec='seconds')}"
                     for key_id, revoked_at, expires_at in session.execute(
                         select(ApiKey.id, ApiKey.revoked_at, ApiKey.expires_at).where(
                             ApiKey.id.in_(keys), or_(ApiKey.revoked_at.is_not(None), ApiKey.expires_at <= utcnow())))}
            updated = dict(session.execute(select(Job.id, Job.updated_at).where(Job.id.in_(ids))).all())
            newest = dict(session.execute(select(JobEvent.job_id, func.max(JobEvent.id))
                                          .where(JobEvent.job_id.in_(ids)).group_by(JobEvent.job_id)).all())
            stamps = {job_id: (at, newest.get(job_id)) for job_id, at in updated.items()}
            changed = [i for i in updated if i in fresh or self._stamps.get(i, (None, None))[0] != updated[i]]
            jobs = {job.id: self.view(job) for job in session.scalars(select(Job).where(Job.id.in_(changed)))} \
                if changed else {}
            reading = [i for i in updated if i in jobs or (newest.get(i) or 0) > after[i]]
            events: dict[str, list[dict]] = {}
            for start in range(0, len(reading), EVENT_QUERY_JOBS):
                rows = session.scalars(
                    select(JobEvent)
                    .where(or_(*(and_(JobEvent.job_id == i, JobEvent.id > after[i])
                                 for i in reading[start:start + EVENT_QUERY_JOBS])))
                    .order_by(JobEvent.id)
                )
                for e in rows:
                    events.setdefault(e.job_id, []).append(
                        JobEventOut.model_validate(e, from_attributes=True).model_dump(mode="json"))
        return stamps, jobs, events, ended

    def end_streams(self) -> None:
        """End every stream, and any opened from now on, at its next wake: the server is stopping, and waits for
        open responses to end first (a stream ends only with its job). Clients resume with ``Last-Event-ID``."""
        self._ending = True
        for watch in self._watches:
            watch.wake.set()

    async def close(self) -> None:
        if self._task is not None and not self._task.done():
            self._task.cancel()
