"""Logging a background loop's failures in a row (the database unreachable): one traceback, then a line each.

A loop that logged every failed pass with its traceback had filled the log while the database was down (the event
hub's polls, twice a second: 7,200 tracebacks an hour per API process). :class:`FailingStreak` logs the first failure
of a streak with its traceback, the next ones a line each (their error's first line), and the recovery, and says
how long the loop waits before its next try: the interval doubling per failure up to a longest delay
(:func:`voxe_service.webhooks.backoff_s`), or the interval itself where the longest is no more.
"""

from __future__ import annotations

import logging

from voxe_service.webhooks import backoff_s


class FailingStreak:
    """The failures in a row of ``what``'s tries (``one``, ``many``: e.g. "webhook sender", "pass", "passes"),
    logged to ``log``."""

    def __init__(self, log: logging.Logger, what: str, one: str, many: str):
        self.log, self.what, self.one, self.many = log, what, one, many
        self.failed = 0

    def failed_once_more(self, exc: BaseException, interval_s: float, longest_s: float) -> float:
        """Log one more failure, ``exc``; the seconds until the next try: ``interval_s`` doubling per failure, at
        most ``longest_s`` (no less than the interval)."""
        longest_s = max(interval_s, longest_s)
        delay = backoff_s(self.failed + 1, interval_s, longest_s)
        backing_off = (f", backing off up to {longest_s:g} s while {self.many} fail"
                       if longest_s > interval_s and not self.failed else "")
        self.note_failure(exc, f"; next in {delay:g} s{backing_off}")
        return delay

    def note_failure(self, exc: BaseException, next_try: str = "") -> None:
        """Log one more failure, ``exc``, of tries whose callers choose when the next comes (``next_try``, said
        after 'failed', may tell)."""
        self.failed += 1
        if self.failed == 1:
            self.log.warning("%s: %s failed%s", self.what, self.one, next_try, exc_info=exc)
        else:
            self.log.warning("%s: %s %d in a row failed%s: %s: %s", self.what, self.one, self.failed, next_try,
                             type(exc).__name__, str(exc).partition("\n")[0])

    def succeeded(self) -> None:
        """Log the recovery, if the tries had been failing."""
        if self.failed:
            self.log.warning("%s: %s succeed again, after %d failed in a row", self.what, self.many, self.failed)
            self.failed = 0
