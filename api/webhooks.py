"""The webhook sender: a background thread of the API process that POSTs due deliveries from the outbox.

Attempts run on a small thread pool, each ending by its deadline (``VOXE_WEBHOOK_TIMEOUT_S``: name lookup,
connect, send and the whole answer), so a slow or dead receiver holds one pool thread for at most that long and
never a request or a worker; at most half the pool's threads go to one receiver (``scheme://host:port``, whatever
path each job's URL names) and all but a quarter to one API key's jobs (:class:`Shares`), so neither a receiver that
never answers nor a key whose jobs each name a receiver of their own can hold them all while its deliveries pile up. A
failed attempt (an error, a timeout, a non-2xx) is retried after ``VOXE_WEBHOOK_BACKOFF_S`` doubling per attempt
(or the longer wait a 429's or 503's ``Retry-After`` asks, at most ``VOXE_WEBHOOK_MAX_BACKOFF_S``),
until ``VOXE_WEBHOOK_RETRY_FOR_S`` after the event (the last try at that time); then the delivery is ``failed`` with
the last error, as it is at once when the receiver answered 410 Gone (it says it is gone for good), and so are the
job's other deliveries to that URL, pending or later, never sent (one in flight then is recorded as it went).
Claims are conditional updates, so several API processes may send side by side without sending one attempt twice; a
claim no attempt had begun when the sender stops is given back, uncounted. The pool and the shares are this process's
own: N API processes hold up to N times as many.
"""

from __future__ import annotations

import logging
import threading
from collections import Counter
from concurrent.futures import ThreadPoolExecutor

from sqlalchemy import select, update

from voxe_service.db import session_scope
from voxe_service.failing import FailingStreak
from voxe_service.models import ApiKey, Job, WebhookDelivery, utcnow
from voxe_service.settings import Settings
from voxe_service.webhooks import (
    DELIVERED, GAVE_UP, GONE, PENDING, Attempt, Claim, InFlight, Shares, TargetRefused, attempt, claim_due, give_back,
    record_stopped_in_flight, retry_at, stop_after_gone, webhook_client,
)

log = logging.getLogger("voxe.webhooks")

# A claim outlasts its attempt's deadline by this much (reading the delivery, recording the outcome), so no other
# sender takes a delivery whose attempt is still running.
CLAIM_MARGIN_S = 30.0
# While passes fail (the database unreachable), the next one waits the poll interval doubling per failure, up to this.
FAILING_PASS_MAX_DELAY_S = 30.0


class WebhookSender:
    def __init__(self, settings: Settings):
        self.settings = settings
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._pool = ThreadPoolExecutor(settings.webhook_concurrency, thread_name_prefix="voxe-webhook")
        self._client = webhook_client(settings.webhook_timeout_s, settings.webhook_networks)
        self._slots = threading.Semaphore(settings.webhook_concurrency)
        self._shares = Shares.of(settings.webhook_concurrency)  # so no receiver or key ever holds every slot
        self._in_flight = InFlight()  # attempts in flight, by receiver (webhook_origin) and key
        self._in_flight_lock = threading.Lock()
        self._unsent: dict[str, Claim] = {}  # claimed, not yet taken by an attempt: given back at stop

    def start(self) -> "WebhookSender":
        self._thread = threading.Thread(target=self._loop, name="voxe-webhooks", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=5)
        self._pool.shutdown(wait=False, cancel_futures=True)
        self._give_back(list(self._unsent.values()))
        self._client.close()

    def _loop(self) -> None:
        """Pass after pass, backing off while they fail: the first failure is logged with its traceback, the next
        ones a line each, and the recovery too (a traceback every poll interval had filled the log while the
        database was down: 7,200 an hour per API process)."""
        interval = self.settings.webhook_poll_interval_s
        streak = FailingStreak(log, "webhook sender", "pass", "passes")
        while not self._stop.is_set():
            try:
                self.send_due()
            except Exception as exc:  # noqa: BLE001 - a database hiccup or outage: try again, later each time
                self._stop.wait(streak.failed_once_more(exc, interval, FAILING_PASS_MAX_DELAY_S))
                continue
            streak.succeeded()
            self._stop.wait(interval)

    def send_due(self) -> int:
        """Claim what the pool has room for and hand it over; how many attempts were started."""
        free = 0
        while self._slots.acquire(blocking=False):
            free += 1
        if not free:
            return 0
        claimed: list[Claim] = []
        try:
            with self._in_flight_lock:
                in_flight = InFlight(self._in_flight.by_origin.copy(), self._in_flight.by_key.copy(),
                                     self._in_flight.walked_to)
            with session_scope() as session:
                won = claim_due(session, utcnow(), self.settings.webhook_timeout_s + CLAIM_MARGIN_S, free,
                                self._shares, in_flight)
            claimed = won  # once committed: a claim whose commit failed took nothing
        finally:  # the slots left over: all of them when the claim failed (a database hiccup had kept them for good)
            for _ in range(free - len(claimed)):
                self._slots.release()
        with self._in_flight_lock:
            self._in_flight.walked_to = in_flight.walked_to
            self._in_flight.by_origin.update(claim.origin for claim in claimed)
            self._in_flight.by_key.update(claim.key_id for claim in claimed)
            self._unsent.update((claim.delivery_id, claim) for claim in claimed)
        for claim in claimed:
            try:
                self._pool.submit(self._send, claim)
            except RuntimeError:  # stop() shut the pool since the claim
                self._give_back([claim])
        return len(claimed)

    def _take(self, claims: list[Claim]) -> list[Claim]:
        """Of ``claims``, those not yet taken (by an attempt or a give-back), now taken: each is taken once."""
        with self._in_flight_lock:
            return [claim for claim in claims if self._unsent.pop(claim.delivery_id, None) is not None]

    def _give_back(self, claims: list[Claim]) -> None:
        """Claims no attempt took, the sender stopping: due again, uncounted (:func:`give_back`). Where that fails
        (the database gone), their leases lapse and the attempts stay counted, as before."""
        if claims := self._take(claims):
            try:
                with session_scope() as session:
                    give_back(session, claims)
            except Exception:  # noqa: BLE001 - stopping: the leases lapse instead
                log.warning("webhook sender: %d claimed deliveries not given back", len(claims), exc_info=True)

    def _send(self, claim: Claim) -> None:
        delivery_id = claim.delivery_id
        try:
            if not self._take([claim]):  # given back (stop) before this attempt began
                return
            with session_scope() as session:
                delivery = session.get(WebhookDelivery, delivery_id)
                if delivery is None:  # its job was deleted (with its scene) since the claim: nothing to send
                    return
                secret = session.scalar(select(ApiKey.webhook_secret).join(Job, Job.owner_key_id == ApiKey.id)
                                        .where(Job.id == delivery.job_id))
            try:
                answer = attempt(delivery, secret, self._client)
                refused = False
            except TargetRefused as exc:
                answer, refused = Attempt(None, str(exc), exc.logged), True
            self._record(delivery, answer, refused)
        except Exception:  # noqa: BLE001 - the claim's lease lapses and the next pass retries it
            log.warning("webhook delivery %s: attempt failed", delivery_id, exc_info=True)
        finally:
            with self._in_flight_lock:
                self._in_flight.by_origin -= Counter({claim.origin: 1})
                self._in_flight.by_key -= Counter({claim.key_id: 1})
            self._slots.release()

    def _record(self, delivery: WebhookDelivery, answer: Attempt, refused: bool) -> None:
        status, error, logged, asked_s = answer
        now = utcnow()
        values: dict = {"last_status": status, "last_error": error}
        if error is None:
            values.update(state=DELIVERED, delivered_at=now, next_attempt_at=None)
        else:
            again = None if refused or status == GONE else retry_at(
                delivery.created_at, now, delivery.attempts, self.settings.webhook_backoff_s,
                self.settings.webhook_max_backoff_s, self.settings.webhook_retry_for_s, asked_s)
            if again is None:
                values.update(state=GAVE_UP, next_attempt_at=None)
            else:
                values.update(next_attempt_at=again)
            log.info("webhook delivery %s (job %s) attempt %d: %s", delivery.id, delivery.job_id, delivery.attempts,
                     logged)
        with session_scope() as session:
            if not session.execute(update(WebhookDelivery).where(WebhookDelivery.id == delivery.id,
                                                                 WebhookDelivery.state == PENDING)
                                   .values(**values)).rowcount:
                record_stopped_in_flight(session, delivery, values)
            if status == GONE:  # the receiver stops the job's deliveries, not this one only
                stop_after_gone(session, delivery)
