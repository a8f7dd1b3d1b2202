"""The webhook sender: a background thread of the API process that POSTs due deliveries from the outbox.

Attempts run on a small thread pool, each ending by its deadline (``VOXE_WEBHOOK_TIMEOUT_S``: name lookup,
connect, send and the whole answer), so a slow or dead receiver holds one pool thread for at most that long and
never a request or a worker. A failed attempt (an error, a timeout, a non-2xx) is retried after
``VOXE_WEBHOOK_BACKOFF_S`` doubling per attempt, until ``VOXE_WEBHOOK_RETRY_FOR_S`` after the event (the last
try at that time); then the delivery is ``failed`` with the last error. Claims are conditional updates, so several API
processes may send side by side without sending one attempt twice.
"""

from __future__ import annotations

import logging
import threading
from concurrent.futures import ThreadPoolExecutor

from sqlalchemy import select, update

from voxe_service.db import session_scope
from voxe_service.models import ApiKey, Job, WebhookDelivery, utcnow
from voxe_service.settings import Settings
from voxe_service.webhooks import (
    DELIVERED, GAVE_UP, PENDING, TargetRefused, attempt, claim_due, retry_at, webhook_client,
)

log = logging.getLogger("voxe.webhooks")

# A claim outlasts its attempt's deadline by this much (reading the delivery, recording the outcome), so no other
# sender takes a delivery whose attempt is still running.
CLAIM_MARGIN_S = 30.0


class WebhookSender:
    def __init__(self, settings: Settings):
        self.settings = settings
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._pool = ThreadPoolExecutor(settings.webhook_concurrency, thread_name_prefix="voxe-webhook")
        self._client = webhook_client(settings.webhook_timeout_s, settings.webhook_networks)
        self._in_flight = threading.Semaphore(settings.webhook_concurrency)

    def start(self) -> "WebhookSender":
        self._thread = threading.Thread(target=self._loop, name="voxe-webhooks", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        self._pool.shutdown(wait=False, cancel_futures=True)
        self._client.close()

    def _loop(self) -> None:
        while not self._stop.is_set():
            try:
                self.send_due()
            except Exception:  # noqa: BLE001 - a database hiccup: try again next interval
                log.warning("webhook sender: pass failed", exc_info=True)
            self._stop.wait(self.settings.webhook_poll_interval_s)

    def send_due(self) -> int:
        """Claim what the pool has room for and hand it over; how many attempts were started."""
        free = 0
        while self._in_flight.acquire(blocking=False):
            free += 1
        if not free:
            return 0
        ids: list[str] = []
        try:
            with session_scope() as session:
                won = claim_due(session, utcnow(), self.settings.webhook_timeout_s + CLAIM_MARGIN_S, free)
            ids = won  # once committed: a claim whose commit failed took nothing
        finally:  # the slots left over: all of them when the claim failed (a database hiccup had kept them for good)
            for _ in range(free - len(ids)):
                self._in_flight.release()
        for delivery_id in ids:
            self._pool.submit(self._send, delivery_id)
        return len(ids)

    def _send(self, delivery_id: str) -> None:
        try:
            with session_scope() as session:
                delivery = session.get(WebhookDelivery, delivery_id)
                secret = session.scalar(select(ApiKey.webhook_secret).join(Job, Job.owner_key_id == ApiKey.id)
                                        .where(Job.id == delivery.job_id))
            try:
                status, error = attempt(delivery, secret, self._client)
                refused = False
            except TargetRefused as exc:
                status, error, refused = None, str(exc), True
            self._record(delivery, status, error, refused)
        except Exception:  # noqa: BLE001 - the claim's lease lapses and the next pass retries it
            log.warning("webhook delivery %s: attempt failed", delivery_id, exc_info=True)
        finally:
            self._in_flight.release()

    def _record(self, delivery: WebhookDelivery, status: int | None, error: str | None, refused: bool) -> None:
        now = utcnow()
        values: dict = {"last_status": status, "last_error": error}
        if error is None:
            values.update(state=DELIVERED, delivered_at=now, next_attempt_at=None)
        else:
            again = None if refused else retry_at(
                delivery.created_at, now, delivery.attempts, self.settings.webhook_backoff_s,
                self.settings.webhook_max_backoff_s, self.settings.webhook_retry_for_s)
            if again is None:
                values.update(state=GAVE_UP, next_attempt_at=None)
            else:
                values.update(next_attempt_at=again)
            log.info("webhook delivery %s (job %s) attempt %d: %s", delivery.id, delivery.job_id, delivery.attempts,
                     error)
        with session_scope() as session:
            session.execute(update(WebhookDelivery).where(WebhookDelivery.id == delivery.id,
                                                          WebhookDelivery.state == PENDING).values(**values))
