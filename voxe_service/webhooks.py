"""Webhooks: which addresses a job may call, the Standard Webhooks signature, the outbox and one delivery attempt.

A job created with a ``webhook_url`` gets one :class:`~voxe_service.models.WebhookDelivery` row per
event of a kind it asked for, written in the event's own transaction (:func:`enqueue`), so a
crash between the two loses nothing. The API's sender thread (:mod:`api.webhooks`) claims due
rows and calls :func:`attempt`; neither a worker nor a request ever waits on a receiver, and an attempt ends by
its deadline (resolving the name, connect, send and the whole answer) however slowly a resolver or receiver answers.

Signatures follow Standard Webhooks (standardwebhooks.com): headers ``webhook-id`` (stable across
retries), ``webhook-timestamp`` (Unix seconds of the attempt) and ``webhook-signature``
``v1,<base64 HMAC-SHA256 of "id.timestamp.body">`` under the key's ``whsec_<base64>`` secret.
"""

from __future__ import annotations

import base64
import contextvars
import hashlib
import hmac
import ipaddress
import json
import secrets
import socket
import threading
import time
from collections import Counter
from concurrent.futures import Future, TimeoutError as FutureTimeout
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import NamedTuple
from urllib.parse import SplitResult, urljoin, urlsplit

import httpcore
import httpx
from sqlalchemy import Integer, func, literal_column, or_, select, update
from sqlalchemy.orm import Session

from voxe_client.client import retry_after_s as asked_wait_s  # (the client's reading of Retry-After: one rule)
from voxe_service.models import QUEUED, ApiKey, Job, WebhookDelivery, utcnow
from voxe_service.texts import shorter

WEBHOOK_EVENTS = ("stage_started", "stage_completed", "warning", "artifact", "preview", "succeeded", "failed",
                  "canceled")
DEFAULT_WEBHOOK_EVENTS = ("succeeded", "failed", "canceled")
PENDING, DELIVERED, GAVE_UP = "pending", "delivered", "failed"
GONE = 410  # a receiver's "gone for good": its delivery is not tried again
ASKS_TO_WAIT = (429, 503)  # answers whose Retry-After says when to try again
SECRET_PREFIX = "whsec_"
ANSWER_READ_BYTES = 64 * 1024  # of a receiver's answer, read and dropped: a usual one ends within (its connection is
# reused), a flood is cut off (the rest is never read into memory)

# When the request a webhook client sends in this thread must have ended (set as the request starts).
_request_deadline: contextvars.ContextVar[float | None] = contextvars.ContextVar("webhook_request_deadline",
                                                                                 default=None)


class TargetRefused(ValueError):
    """A webhook URL the service will not call; the message names the rule and the setting that relaxes it.
    ``logged`` is the message as the operator's log may carry it (the URL's credentials hidden)."""

    def __init__(self, message: str, logged: str | None = None):
        super().__init__(message)
        self.logged = message if logged is None else logged


def log_safe_url(url: str, base: str = "") -> str:
    """``url`` as a log may carry it: its userinfo, path past its first segment, query values and fragment hidden, read
    as a URL (not picked out of a message, where a ``'`` or a relative reference had ended or hidden it). A webhook_url
    may hold credentials (``https://user:pass@host/``, ``?token=...``, or in the path, as Slack's and Discord's
    ``/services/T0/B0/<secret>`` and ``/api/webhooks/<id>/<token>`` do) that the owner sees in the delivery's
    ``last_error``, but the operator's logs must not. A relative one (a redirect's Location) is first resolved
    against ``base``. The userinfo is the netloc's, up to its last '@', or past a password an unencoded '/', '?' or
    '#' cut short (:func:`_split_past_a_password`): where even that cannot be told, as in ``bob:12?x@host``, only
    the scheme is shown, username included (it is often the token). An '@' in the path of any other netloc is the
    path's (a rule reading up to the last '@' had shown ``/hooks/ops@corp/<token>`` as ``***@corp/<token>``).
    The path keeps its first segment, which tells receivers' endpoints apart, unless it holds an '@', and the rest,
    where the tokens are, is one ``***`` (no rule tells a token from a word reliably); a query pair's name is kept, a
    pair with no '=' hidden whole.

    Examples:
        >>> log_safe_url("https://bob:pa/ss@hooks.example.com/in?token=abc&x#frag")
        'https://***@hooks.example.com/in?token=***&***#***'
        >>> log_safe_url("//bob:pw@hooks.example.com/in?t=a'b", "https://hooks.example.com/hook")
        'https://***@hooks.example.com/in?t=***'
        >>> log_safe_url("https://hooks.example.com/services/T0KEN/secret")
        'https://hooks.example.com/services/***'
        >>> log_safe_url("https://api.example.com/hooks/ops@corp/s3cretTOKEN")
        'https://api.example.com/hooks/***'
        >>> log_safe_url("https://bob:pa/ss@hooks.example.com/hooks/ops@corp/s3cretTOKEN")
        'https://***@hooks.example.com/hooks/***'
        >>> log_safe_url("https://bob:12/ab/cd@hooks.example.com/in")
        'https://***@hooks.example.com/***'
        >>> log_safe_url("https://sk_live_TOKEN:12?ab@hooks.example.com/in")
        'https://***'
        >>> log_safe_url("https://host:99999/in/tok")
        'https://host:99999/in/***'
    """
    resolved = urljoin(base, url) if base else url
    try:
        parts = urlsplit(resolved)
        past_password = _split_past_a_password(resolved, parts)
    except ValueError:  # e.g. an unclosed "[" of an IPv6 host
        return "<an unreadable URL>"
    scheme = parts.scheme + ":" if parts.scheme else ""
    if past_password is None:
        return f"{scheme}//***"
    parts, userinfo, path_hidden = past_password
    authority = ("***@" if userinfo else "") + parts.netloc.rpartition("@")[2]
    first_segment, _, rest = parts.path.removeprefix("/").partition("/")
    if "@" in first_segment or (path_hidden and parts.path.strip("/")):
        path = "/***"
    elif rest:
        path = f"/{first_segment}/***"
    else:
        path = parts.path
    query = "&".join(name + "=***" if has_value else "***"
                     for name, has_value, _ in (pair.partition("=") for pair in parts.query.split("&")))
    return (f"{scheme}{'//' if parts.netloc else ''}{authority}{path}"
            f"{'?' + query if parts.query else ''}{'#***' if parts.fragment else ''}")


def _split_past_a_password(resolved: str, parts: SplitResult) -> tuple[SplitResult, bool, bool] | None:
    """``resolved``'s parts, whether they hold a userinfo, and whether the path must be hidden whole; None where
    nothing past the scheme may be shown.

    Where the netloc's host (past its last '@', and past its last ']' for an IPv6 one) holds a ':' and an '@'
    follows the netloc, that ':' may start a password that an unencoded '/', '?' or '#' cut short (``bob:pa/ss@host``,
    ``ops@corp:s3/cret@host``): the userinfo runs to that '@'. Where the ':' also reads as a port's (a number, or
    nothing), the '@' may be the path's (``host:8443/a@b/c``), so the path is hidden whole; and where that '@' comes
    past a '?' or '#', urllib, httpx and browsers read it as the query's or fragment's (``bob:12?x@host`` as host
    ``bob``, port 12, query ``x@host``) though ``12?x`` may be a password: None, as neither the username nor the
    password's head may be shown (``host:8443/in?email=a@b.example`` loses its host with them).
    """
    host = parts.netloc.rpartition("@")[2]
    host_start = resolved.find("//") + 2 + parts.netloc.rfind("@") + 1
    password_end = resolved.find("@", host_start) if ":" in host.rpartition("]")[2] else -1
    if password_end < 0:
        return parts, "@" in parts.netloc, False
    port_readable = _port_readable(parts)
    query_or_fragment = min((at for at in (resolved.find("?", host_start), resolved.find("#", host_start)) if at >= 0),
                            default=len(resolved))
    if port_readable and password_end > query_or_fragment:
        return None
    return urlsplit(resolved[:resolved.find("//") + 2] + resolved[password_end + 1:]), True, port_readable


def _port_readable(parts: SplitResult) -> bool:
    """Whether the netloc's port, if any, is a number: not, where a password's '/' cut the netloc short."""
    try:
        parts.port
    except ValueError:
        return False
    return True


class Attempt(NamedTuple):
    """One delivery attempt's outcome: the HTTP status or None; the error or None for a 2xx, as the delivery's
    ``last_error`` keeps it for the URL's owner; that error as the operator's log may carry it; and the seconds a
    429's or 503's ``Retry-After`` asked to wait before the next, or None."""
    status: int | None
    error: str | None
    logged: str | None
    asked_s: float | None = None


def new_secret() -> str:
    return SECRET_PREFIX + base64.b64encode(secrets.token_bytes(24)).decode()


def sign(secret: str, message_id: str, timestamp: int, body: bytes) -> str:
    """The ``webhook-signature`` header value: ``v1,<base64 HMAC-SHA256("id.timestamp.body")>``.

    Examples:
        >>> sign("whsec_MfKQ9r8GKYqrTwjUPD8ILPZIo2LaLaSw", "msg_p5jXN8AQM9LWM0D4loKWxJek", 1614265330,
        ...      b'{"test": 2432232314}')  # the Standard Webhooks reference vector
        'v1,g0hM9SsE+OTPJTGt/tmIKtSyZlE3uFJELVlNIOLJ1OE='
    """
    key = base64.b64decode(secret.removeprefix(SECRET_PREFIX))
    signed = f"{message_id}.{timestamp}.".encode() + body
    return "v1," + base64.b64encode(hmac.new(key, signed, hashlib.sha256).digest()).decode()


def check_target(url: str, allow_networks: list[ipaddress._BaseNetwork], timeout_s: float) -> None:
    """Refuse (:class:`TargetRefused`) a URL that is not http(s), whose host does not resolve within ``timeout_s``
    (an attempt's deadline: a name that answers no sooner would time every delivery out), or whose host resolves
    to a loopback, private, link-local, multicast, reserved or unspecified address outside ``allow_networks``.

    Checked when the job is created, inside its request: a slow resolver had held the request for as long as it
    took. Every attempt's connection checks the address it connects to again (:func:`webhook_client`). Raises
    :class:`LookupSlotsBusy` when the host could not even be looked up in that time (the lookups are busy).
    """
    try:
        parts = urlsplit(url)
        host = parts.hostname
    except ValueError as exc:  # e.g. an unclosed "[" of an IPv6 host
        raise TargetRefused(f"webhook_url {url!r} is not a valid URL: {exc}") from None
    if parts.scheme not in ("http", "https") or not host:
        raise TargetRefused(f"webhook_url {url!r} must be an http:// or https:// URL with a host")
    try:
        port = parts.port
    except ValueError as exc:  # out of range, or not a number (its message had blamed the host's name lookup)
        raise TargetRefused(f"webhook_url {url!r} has an invalid port: {exc}") from None
    if port == 0:  # had been taken for the scheme's default and accepted, though nothing can be sent to it
        raise TargetRefused(f"webhook_url {url!r} names port 0, where nothing can listen")
    port = port or (443 if parts.scheme == "https" else 80)
    try:
        # The name as the sender looks it up (IDNA 2008): Python's resolver spells a name of another script its own
        # way (IDNA 2003: "straße.example" as "strasse.example", another domain), whose addresses had been checked.
        sent_to = httpx.URL(url).raw_host.decode("ascii")
    except httpx.InvalidURL as exc:  # e.g. a host IDNA 2008 refuses (a symbol, a soft hyphen), though it resolves
        raise TargetRefused(f"webhook_url {url!r} cannot be sent to: {exc}") from None
    try:
        allowed_addresses_within(sent_to, port, allow_networks, timeout_s)
    except LookupSlotsBusy:
        raise
    except LookupTimedOut:
        raise TargetRefused(f"webhook_url host {host!r} did not resolve within {timeout_s:g} s "
                            "(VOXE_WEBHOOK_TIMEOUT_S, a delivery's deadline)") from None
    except OSError as exc:
        raise TargetRefused(f"webhook_url host {host!r} does not resolve: {exc}") from None


def allowed_addresses(host: str, port: int, allow_networks: list[ipaddress._BaseNetwork]) -> list[str]:
    """Every address ``host`` resolves to, once: :class:`TargetRefused` naming the kind of the first that a webhook
    may not go to (``refused_rule``) unless ``allow_networks`` holds it, or a name that cannot be looked up at all
    (e.g. a label over 63 characters). A resolver that fails (``socket.gaierror``, an OSError: no such name, or none
    reachable for now) refuses nothing: the name may resolve at the next attempt.

    The refusal's message (a job's 422, a delivery's ``last_error``) names no address, its ``logged`` form does: any
    key holder could otherwise map the internal names the service's resolver knows ("resolves to 10.0.0.5")."""
    literal = _address_literal(host)
    if literal is not None:  # judged before the lookup: one of a zone it does not know had been "does not resolve"
        _refuse_unless_allowed(host, literal, allow_networks)
    try:
        infos = socket.getaddrinfo(host if literal is None else str(literal), port, proto=socket.IPPROTO_TCP)
    except ValueError as exc:
        raise TargetRefused(f"webhook_url host {host!r} does not resolve: {exc}") from None
    addresses = []
    for info in infos:
        _refuse_unless_allowed(host, ipaddress.ip_address(info[4][0].split("%")[0]), allow_networks)
        addresses.append(info[4][0])
    return list(dict.fromkeys(addresses))


def _address_literal(host: str) -> ipaddress.IPv4Address | ipaddress.IPv6Address | None:
    """The IP address ``host`` spells, None for a name. An IPv6 one's zone is read as a URL writes it, RFC 6874's
    ``%25`` for the '%' (``fe80::1%25eth0``), which ``ipaddress`` and the resolver read as ``fe80::1%eth0``.

    Examples:
        >>> _address_literal("fe80::1%25eth0"), _address_literal("10.0.0.1"), _address_literal("hooks.example")
        (IPv6Address('fe80::1%eth0'), IPv4Address('10.0.0.1'), None)
    """
    try:
        return ipaddress.ip_address(host.replace("%25", "%", 1) if ":" in host else host)
    except ValueError:
        return None


def _refuse_unless_allowed(host: str, address: ipaddress.IPv4Address | ipaddress.IPv6Address,
                           allow_networks: list[ipaddress._BaseNetwork]) -> None:
    """:class:`TargetRefused` naming ``address``'s kind (``refused_rule``) unless it is public or ``allow_networks``
    holds it."""
    if not any(address in network for network in allow_networks) and (rule := refused_rule(address)):
        kind = rule.partition(" (as ")[0]  # ("private (as 10.1.2.3)": the address it carries is the log's)
        why = ("address: webhooks go to public addresses only (an operator can allow networks with "
               "VOXE_WEBHOOK_ALLOW_NETWORKS)")
        raise TargetRefused(f"webhook_url host {host!r} resolves to {_a(kind)} {why}",
                            f"webhook_url host {host!r} resolves to {address}, {_a(rule)} {why}")


def _a(word: str) -> str:
    """``word`` after its article: "an unspecified", "a private"."""
    return ("an " if word[0] in "aeiou" else "a ") + word


class LookupTimedOut(Exception):
    """A webhook host's name lookup that had not answered by its deadline (:func:`allowed_addresses_within`)."""


class LookupSlotsBusy(LookupTimedOut):
    """No lookup slot came free by the deadline: every one is held by a lookup a resolver has not answered (other
    hosts'), so this host was never looked up. No fault of its URL: a job's creation is told to try again."""


LOOKUP_THREADS = 16
"""Name lookups running at once, at most: one that outlives its caller's deadline keeps its thread, and its slot,
until the resolver gives up, so a stuck resolver cannot pile up a thread per job created or attempt made."""
_lookup_slots = threading.BoundedSemaphore(LOOKUP_THREADS)


def allowed_addresses_within(host: str, port: int, allow_networks: list[ipaddress._BaseNetwork],
                             timeout: float | None) -> list[str]:
    """:func:`allowed_addresses`, given up after ``timeout`` seconds (:class:`LookupTimedOut`): ``getaddrinfo`` takes
    no timeout, so it runs in a thread of its own, left to end by itself (the resolver's own timeouts) while the
    caller goes on; with every one of the :data:`LOOKUP_THREADS` slots held that long, it times out unstarted. An IP
    address is judged at once, with no thread or slot: no resolver is asked (names stuck on one had held every slot,
    and a webhook to an address was refused as "did not resolve", its attempts timed out)."""
    if _address_literal(host) is not None:
        return allowed_addresses(host, port, allow_networks)
    deadline = None if timeout is None else time.monotonic() + timeout
    if not _lookup_slots.acquire(timeout=timeout):
        raise LookupSlotsBusy(host)
    answer: Future[list[str]] = Future()

    def look_up() -> None:
        try:
            answer.set_result(allowed_addresses(host, port, allow_networks))
        except Exception as exc:  # noqa: BLE001 - raised again by the caller's answer.result
            answer.set_exception(exc)
        finally:
            _lookup_slots.release()

    try:
        threading.Thread(target=look_up, name="voxe-webhook-resolve", daemon=True).start()
    except BaseException:  # (no thread to release its slot)
        _lookup_slots.release()
        raise
    try:
        return answer.result(None if deadline is None else max(0.0, deadline - time.monotonic()))
    except FutureTimeout:
        raise LookupTimedOut(host) from None


def _time_left(timeout: float | None, timed_out: type[httpcore.TimeoutException]) -> float | None:
    """``timeout`` (one socket operation's) cut to what is left of the current request's deadline; ``timed_out``
    raised once none is."""
    deadline = _request_deadline.get()
    if deadline is None:
        return timeout
    left = deadline - time.monotonic()
    if left <= 0:
        raise timed_out("the attempt's deadline (VOXE_WEBHOOK_TIMEOUT_S) passed before the exchange ended")
    return left if timeout is None else min(timeout, left)


class _DeadlineStream(httpcore.NetworkStream):
    """A connection whose every read, write and TLS handshake ends by the current request's deadline: httpx's
    timeouts bound each socket operation only, so a receiver sending its answer a byte at a time had held an
    attempt (and a sender thread) for as long as it liked."""

    def __init__(self, stream: httpcore.NetworkStream):
        self._stream = stream

    def read(self, max_bytes: int, timeout: float | None = None) -> bytes:
        return self._stream.read(max_bytes, _time_left(timeout, httpcore.ReadTimeout))

    def write(self, buffer: bytes, timeout: float | None = None) -> None:
        self._stream.write(buffer, _time_left(timeout, httpcore.WriteTimeout))

    def close(self) -> None:
        self._stream.close()

    def start_tls(self, ssl_context, server_hostname: str | None = None,
                  timeout: float | None = None) -> httpcore.NetworkStream:
        return _DeadlineStream(self._stream.start_tls(ssl_context, server_hostname,
                                                      _time_left(timeout, httpcore.ConnectTimeout)))

    def get_extra_info(self, info: str):
        return self._stream.get_extra_info(info)


class _CheckedBackend(httpcore.NetworkBackend):
    """Opens a connection only to an address it has just checked: the name is resolved once, for the check and the
    connection both, so a resolver that answers differently in between (DNS rebinding) cannot route a webhook to
    a refused address. TLS still names the host (SNI, certificate) and the request keeps its Host header.
    Connections end by the request's deadline (:class:`_DeadlineStream`)."""

    def __init__(self, allow_networks: list[ipaddress._BaseNetwork]):
        self._allow_networks = allow_networks
        self._backend = httpcore.SyncBackend()

    def connect_tcp(self, host: str, port: int, timeout: float | None = None, local_address: str | None = None,
                    socket_options=None) -> httpcore.NetworkStream:
        failure: Exception | None = None
        try:
            addresses = self._resolve(host, port, _time_left(timeout, httpcore.ConnectTimeout))
        except OSError as exc:  # e.g. "[Errno -3] Temporary failure in name resolution": retried, like any connect error
            raise httpcore.ConnectError(f"webhook_url host {host!r} does not resolve: {exc}") from None
        for address in addresses:
            try:
                return _DeadlineStream(self._backend.connect_tcp(
                    address, port, _time_left(timeout, httpcore.ConnectTimeout), local_address, socket_options))
            except (httpcore.ConnectError, httpcore.ConnectTimeout) as exc:  # the next address of the name
                failure = exc
        raise failure or httpcore.ConnectError(f"{host!r} resolves to no address")

    def _resolve(self, host: str, port: int, timeout: float | None) -> list[str]:
        """:func:`allowed_addresses_within` ``timeout`` (``httpcore.ConnectTimeout``), the attempt ending by its
        deadline. A slow resolver had held an attempt, and a sender slot, past the deadline."""
        try:
            return allowed_addresses_within(host, port, self._allow_networks, timeout)
        except LookupTimedOut:
            raise httpcore.ConnectTimeout(f"webhook_url host {host!r} did not resolve within the attempt's deadline "
                                          "(VOXE_WEBHOOK_TIMEOUT_S)") from None

    def sleep(self, seconds: float) -> None:
        self._backend.sleep(seconds)


def webhook_client(timeout_s: float, allow_networks: list[ipaddress._BaseNetwork]) -> httpx.Client:
    """The sender's HTTP client: it connects only to addresses :func:`allowed_addresses` passes (a refused one
    raises :class:`TargetRefused` from the request), directly (proxy variables are ignored: a proxy would resolve
    the name itself), and never follows a redirect (its target would go unchecked). ``timeout_s`` bounds each
    request in all: resolving the name, connecting, sending and the whole answer."""
    transport = httpx.HTTPTransport()  # (SSL_CERT_FILE / SSL_CERT_DIR still name the CAs to trust)
    # httpx takes no network backend: its pool, with httpx's limits and TLS context, connects through the checked
    # one (test_service_webhooks fails if httpx stops sending through it).
    transport._pool._network_backend = _CheckedBackend(allow_networks)

    def start_deadline(_request: httpx.Request) -> None:
        _request_deadline.set(time.monotonic() + timeout_s)

    return httpx.Client(transport=transport, timeout=timeout_s, follow_redirects=False, trust_env=False,
                        event_hooks={"request": [start_deadline]})


_NAT64 = ipaddress.ip_network("64:ff9b::/96")


def refused_rule(address: ipaddress.IPv4Address | ipaddress.IPv6Address) -> str | None:
    """Why a webhook may not go to ``address`` (None: a public address), the most specific name first.

    An IPv6 address that carries an IPv4 one is judged by it too (6to4 ``2002::/16``; mapped ``::ffff:a.b.c.d``
    addresses are already refused as reserved), and a NAT64 one (``64:ff9b::/96``) by it alone: it is what a DNS64
    resolver answers for a name with IPv4 addresses only, beside them, and its translator goes to that IPv4 address (as
    reserved, every such receiver had been refused wherever the resolver does DNS64). Anything else that is not
    globally routable (e.g. carrier-grade NAT, 100.64.0.0/10) is "non-public".

    Examples:
        >>> [refused_rule(ipaddress.ip_address(a)) for a in ("8.8.8.8", "10.1.2.3", "100.64.1.2", "2002:a01:203::1")]
        [None, 'private', 'non-public', 'private (as 10.1.2.3)']
        >>> [refused_rule(ipaddress.ip_address(a)) for a in ("64:ff9b::808:808", "64:ff9b::a01:203")]
        [None, 'private (as 10.1.2.3)']
    """
    if address.version == 6 and address in _NAT64:
        carried = ipaddress.IPv4Address(int(address) & 0xFFFFFFFF)
        return None if (rule := refused_rule(carried)) is None else f"{rule} (as {carried})"
    # Link-local and unspecified addresses are "private" to Python too: their own names come first.
    for rule, refused in (("loopback", address.is_loopback), ("link-local", address.is_link_local),
                          ("unspecified", address.is_unspecified), ("multicast", address.is_multicast),
                          ("reserved", address.is_reserved), ("private", address.is_private)):
        if refused:
            return rule
    if address.version == 6:
        carried = address.ipv4_mapped or address.sixtofour
        if carried is not None and (rule := refused_rule(carried)) is not None:
            return f"{rule} (as {carried})"
    return None if address.is_global else "non-public"


def key_secret(session: Session, key: ApiKey) -> str:
    """The key's webhook secret, made (and committed with the caller's transaction) on first use.

    Made by a write conditional on the key having none, then read back: of callers racing to make it, one writes
    it and all return that one (each had written its own, and most handed out a secret no longer the key's).
    """
    if key.webhook_secret is None:
        session.execute(update(ApiKey).where(ApiKey.id == key.id, ApiKey.webhook_secret.is_(None))
                        .values(webhook_secret=new_secret()).execution_options(synchronize_session=False))
        session.refresh(key, ["webhook_secret"])
    return key.webhook_secret


def rotate_secret(session: Session, key: ApiKey) -> str:
    """Give the key a new webhook secret (committed with the caller's transaction); it. Every attempt from then on,
    a retry of an earlier delivery included, is signed with it: the sender reads the key's secret at each attempt.

    Written only where the key still holds the secret it was read with, then read back: of rotations racing, one
    writes its secret and all return that one (each had written its own, the last kept, and the others' callers
    held a secret that never signed anything).
    """
    read = key.webhook_secret
    held = ApiKey.webhook_secret.is_(None) if read is None else ApiKey.webhook_secret == read
    session.execute(update(ApiKey).where(ApiKey.id == key.id, held)
                    .values(webhook_secret=new_secret()).execution_options(synchronize_session=False))
    session.refresh(key, ["webhook_secret"])
    return key.webhook_secret


def enqueue(session: Session, job_id: str, event) -> None:
    """Queue a delivery of ``event`` (a flushed JobEvent) when the job has a webhook wanting its kind.

    Its body carries the event's id (``data.event.id``): a job's deliveries may arrive in any order (sent side by
    side, retried apart), and receivers order them by it, as the README tells them."""
    hook = session.execute(select(Job.webhook_url, Job.webhook_events, Job.state, Job.stage)
                           .where(Job.id == job_id)).first()
    if hook is None or not hook.webhook_url or event.kind not in (hook.webhook_events or DEFAULT_WEBHOOK_EVENTS):
        return
    body = {
        "type": f"job.{event.kind}",
        "timestamp": event.at.isoformat(),
        "data": {"job_id": job_id, "state": hook.state, "stage": hook.stage,
                 "event": {"id": event.id, "kind": event.kind, "stage": event.stage, "iteration": event.iteration,
                           "detail": event.detail, "at": event.at.isoformat()},
                 "job_url": f"/v1/jobs/{job_id}"},
    }
    if event.kind in ("artifact", "preview"):
        body["data"]["artifact_url"] = f"/v1/jobs/{job_id}/artifacts/{event.detail}"
    gone = gone_delivery(session, job_id, hook.webhook_url)
    session.add(WebhookDelivery(
        id=f"msg_{secrets.token_hex(16)}", job_id=job_id, event_id=event.id, event_type=body["type"],
        url=hook.webhook_url, origin=webhook_origin(hook.webhook_url), payload=json.dumps(body, separators=(",", ":")),
        state=PENDING if gone is None else GAVE_UP, attempts=0, next_attempt_at=utcnow() if gone is None else None,
        last_error=None if gone is None else not_sent_after_gone(gone), created_at=utcnow(),
    ))


def gone_delivery(session: Session, job_id: str, url: str) -> str | None:
    """The id of the job's delivery to ``url`` that its receiver answered 410 Gone, if any."""
    return session.scalar(select(WebhookDelivery.id).where(WebhookDelivery.job_id == job_id,
                                                           WebhookDelivery.url == url,
                                                           WebhookDelivery.last_status == GONE).limit(1))


def not_sent_after_gone(gone_id: str) -> str:
    """The ``last_error`` of a job's delivery never sent because another of the job's, ``gone_id``, to the same URL
    was answered 410 Gone: Standard Webhooks' receivers answer it to stop the deliveries, and the job's later events
    had still been sent there (each failing on its own 410)."""
    return (f"not sent: the receiver answered 410 Gone to this job's delivery {gone_id} (gone for good), so none of "
            "the job's deliveries go to it any more")


def stop_after_gone(session: Session, delivery: WebhookDelivery) -> None:
    """Fail the job's other pending deliveries to ``delivery``'s URL, which its receiver answered 410 Gone, unsent
    (:func:`not_sent_after_gone`); :func:`enqueue` writes the job's later ones so at once."""
    session.execute(update(WebhookDelivery)
                    .where(WebhookDelivery.job_id == delivery.job_id, WebhookDelivery.url == delivery.url,
                           WebhookDelivery.state == PENDING, WebhookDelivery.id != delivery.id)
                    .values(state=GAVE_UP, next_attempt_at=None, last_error=not_sent_after_gone(delivery.id))
                    .execution_options(synchronize_session=False))


def record_stopped_in_flight(session: Session, delivery: WebhookDelivery, values: dict) -> None:
    """Record an attempt of ``delivery`` (its outcome's ``values``) that was in flight when another of the job's
    deliveries to its URL was answered 410 Gone, which failed it "not sent" (:func:`stop_after_gone`): what the
    attempt did, as the log says it, a 2xx delivered, else failed with its own status and error (not tried again).
    The row had kept "not sent" with the attempt counted, though the receiver was sent it and may have taken it."""
    gone = gone_delivery(session, delivery.job_id, delivery.url)
    if gone is None:
        return
    if "state" not in values:  # a retry planned: none goes to that receiver any more
        values = {**values, "state": GAVE_UP, "next_attempt_at": None,
                  "last_error": f"{values['last_error']}; not tried again: the receiver answered 410 Gone to this "
                                f"job's delivery {gone} (gone for good)"}
    session.execute(update(WebhookDelivery)
                    .where(WebhookDelivery.id == delivery.id, WebhookDelivery.state == GAVE_UP,
                           WebhookDelivery.last_error == not_sent_after_gone(gone))
                    .values(**values).execution_options(synchronize_session=False))


def webhook_origin(url: str) -> str:
    """The receiver ``url`` goes to, ``scheme://host:port`` (the host as the sender looks it up: IDNA 2008, in lower
    case, with no trailing dot; the scheme's port where it names none): what the sender's cap counts by, so a receiver
    whose URLs name each job (``https://host/hooks/job-123``) is one receiver, and so is one whose host is spelt two
    ways (``bücher.example``, ``XN--BCHER-KVA.example.``). A URL that cannot be read so (stored before the checks
    read it as they do now) is its own.

    Examples:
        >>> webhook_origin("https://Hooks.Example.com/jobs/123?x=1"), webhook_origin("http://[::1]:8080/hook")
        ('https://hooks.example.com:443', 'http://[::1]:8080')
        >>> webhook_origin("https://Bücher.example/a") == webhook_origin("https://xn--bcher-kva.example./b")
        True
    """
    try:
        parts = urlsplit(url)
        host, port = parts.hostname, parts.port
    except ValueError:
        return url
    if not host:
        return url
    try:
        host = httpx.URL(url).raw_host.decode("ascii").rstrip(".") or host
    except httpx.InvalidURL:  # a host IDNA 2008 refuses: check_target refuses it now, an older row may hold one
        pass
    scheme = parts.scheme.lower()
    host = f"[{host}]" if ":" in host else host
    return f"{scheme}://{host}:{port or (443 if scheme == 'https' else 80)}"


CLAIM_READ_FACTOR = 4
"""A claim first reads this many times its ``limit`` of the earliest due deliveries: enough, unless receivers or keys
at their share have that many due before the others' (then it walks the receivers, :func:`_walk_origins`)."""
RECEIVERS_WALKED = 1000
"""Receivers with deliveries pending that one claim's walk visits at most, each the next after where the last walk
ended: a walk of every one took 55 ms each poll with 20,000 backing off (some 3 µs each on SQLite)."""
ORIGIN_FILL_BATCH = 1000  # deliveries without an origin given one per claim, at most


class Claim(NamedTuple):
    """A delivery a claim won: the receiver (:func:`webhook_origin`) and the API key its attempt counts to; when it
    was due and the end of the claim's lease (what :func:`give_back` puts back)."""

    delivery_id: str
    origin: str
    key_id: str
    due: datetime
    leased_to: datetime


class Shares(NamedTuple):
    """The most attempts a sender has in flight to one receiver, and to one API key's jobs."""

    origin: int
    key: int

    @classmethod
    def of(cls, concurrency: int) -> "Shares":
        """Half the ``concurrency`` slots to a receiver (at least one), and all but a quarter (at least one) to a key,
        no fewer than to a receiver: a key's dead receiver, at its share, leaves the key's other receivers some
        room, and the quarter is kept for the other keys.

        Examples:
            >>> [tuple(Shares.of(n)) for n in (1, 2, 4, 8)]
            [(1, 1), (1, 1), (2, 3), (4, 6)]
        """
        origin = max(1, concurrency // 2)
        return cls(origin, max(origin, concurrency - max(1, concurrency // 4)))


@dataclass
class InFlight:
    """A sender's attempts in flight, by receiver and by API key, and the receiver its last walk of the receivers
    ended at (:func:`claim_due` moves it on; None: the next walk starts at the first)."""

    by_origin: Counter[str] = field(default_factory=Counter)
    by_key: Counter[str] = field(default_factory=Counter)
    walked_to: str | None = None


def claim_due(session: Session, now: datetime, lease_s: float, limit: int, shares: Shares,
              in_flight: InFlight) -> list[Claim]:
    """Take up to ``limit`` due deliveries, the earliest first, but no more than their ``shares`` to one receiver (its
    :func:`webhook_origin`) and to one API key (the job's owner), counting the attempts ``in_flight``: each moves its
    next attempt ``lease_s`` ahead (so no other sender takes it meanwhile) and counts the attempt; those this
    caller won. A job's are held while no broker has taken it yet (:func:`_sent_or_ended`).

    The shares keep one receiver's backlog, or one key's many receivers, from taking every slot: a receiver that
    never answers in time, with many deliveries due, had held them all, wave after wave, and so had a key whose jobs
    each named a receiver of their own; every other key's webhooks waited behind. Its cost grows neither with a
    backlog nor with the receivers backing off: it reads the earliest due few off the index on (state, due time)
    and caps them here; only when receivers or keys at their share fill that read does it walk the receivers off
    the index on (state, origin, due time), at most :data:`RECEIVERS_WALKED` of them, each walk going on after the
    last (``in_flight.walked_to``), and take the earliest of the first read's and the walk's (a walk's alone had
    dropped those of the first read's receivers outside its window, whole claims taking none; ranking every due
    delivery had taken a quarter of a second each poll with 100,000 due to a dead receiver; visiting every receiver
    with one pending, 55 ms with 20,000 backing off). Deliveries written with no origin are given their URL's first
    (:func:`_fill_origins`), committed before the claim, which leaves any still without one to the next: a sender
    holding the rows it filled while claiming others had deadlocked on PostgreSQL with one filling deliveries an
    older API had just written (one claimed, the other's pass failed).
    """
    pending = WebhookDelivery.state == PENDING
    if _fill_origins(session):
        session.commit()
    due = (select(WebhookDelivery.next_attempt_at, WebhookDelivery.id, WebhookDelivery.origin, Job.owner_key_id)
           .join(Job, Job.id == WebhookDelivery.job_id)
           .where(pending, WebhookDelivery.next_attempt_at <= now, WebhookDelivery.origin != "", _sent_or_ended())
           .order_by(WebhookDelivery.next_attempt_at, WebhookDelivery.id))
    read = CLAIM_READ_FACTOR * limit
    earliest = session.execute(due.limit(read)).all()
    chosen = _within_shares(earliest, limit, shares, in_flight)
    if len(chosen) < limit and len(earliest) == read:  # receivers or keys at their share filled the read
        candidates = []
        for origin, room in _soonest_with_room(_walk_origins(session, now, in_flight), limit, shares, in_flight):
            candidates += session.execute(due.where(WebhookDelivery.origin == origin).limit(room)).all()
        found = {row.id: row for row in (*earliest, *candidates)}  # (the walk's window may not hold the first read's)
        chosen = _within_shares(sorted(found.values()), limit, shares, in_flight)
    won = []
    leased_to = now + timedelta(seconds=lease_s)
    for due_at, delivery_id, origin, key_id in chosen:
        result = session.execute(
            update(WebhookDelivery)
            .where(WebhookDelivery.id == delivery_id, pending, WebhookDelivery.next_attempt_at <= now)
            .values(next_attempt_at=leased_to, attempts=WebhookDelivery.attempts + 1)
        )
        if result.rowcount == 1:
            won.append(Claim(delivery_id, origin, key_id, due_at, leased_to))
    return won


def give_back(session: Session, claims: list[Claim]) -> None:
    """Undo ``claims`` whose attempts were never made (their sender stopped first): each due again when it was, its
    attempt uncounted. They had kept the attempt (a restart counted one per delivery claimed, none sent, each
    lengthening the next backoff) and waited out the lease. Only where the lease still holds it (nothing recorded
    since)."""
    for claim in claims:
        session.execute(update(WebhookDelivery)
                        .where(WebhookDelivery.id == claim.delivery_id, WebhookDelivery.state == PENDING,
                               WebhookDelivery.next_attempt_at == claim.leased_to)
                        .values(next_attempt_at=claim.due, attempts=WebhookDelivery.attempts - 1)
                        .execution_options(synchronize_session=False))


def _sent_or_ended():
    """Jobs whose deliveries may go: not those queued that no broker has taken yet, never started. A job created on a
    ready scene is told its ``warning`` events before its request hands it to the broker, which may refuse it: the job
    is then withdrawn (deleted with its deliveries), and one sent meanwhile had told the receiver of a job that never
    existed. Held until sent (or ended: canceled, failed by the reaper as never sent)."""
    return or_(Job.task_id.is_not(None), Job.state != QUEUED, Job.started_at.is_not(None))


def _within_shares(due: list, limit: int, shares: Shares, in_flight: InFlight) -> list:
    """Of ``due`` (due time, id, origin, key rows, the earliest first), the first ``limit`` whose receivers and keys
    have room."""
    by_origin, by_key = Counter(in_flight.by_origin), Counter(in_flight.by_key)
    chosen = []
    for row in due:
        if len(chosen) == limit:
            break
        if by_origin[row.origin] < shares.origin and by_key[row.owner_key_id] < shares.key:
            by_origin[row.origin] += 1
            by_key[row.owner_key_id] += 1
            chosen.append(row)
    return chosen


def _soonest_with_room(origins: list[tuple[str, datetime | None, str | None]], limit: int, shares: Shares,
                       in_flight: InFlight) -> list[tuple[str, int]]:
    """Of walked receivers (each with its earliest due time and that delivery's key), the ``limit`` due soonest with
    room, each with how many of its earliest to read: those whose earliest delivery's key has room, counting one
    for each receiver of the key already taken, so one key's many receivers cannot crowd the others' out. (A
    receiver whose earliest delivery's key is at its share waits until that one goes, though other keys' are due
    behind it, unless the first read found them: looking past it would read all its due of that key, a backlog.)"""
    by_key = Counter(in_flight.by_key)
    chosen = []
    for origin, _first_due, key_id in sorted((o for o in origins if o[1] is not None), key=lambda o: (o[1], o[0])):
        room = min(shares.origin - in_flight.by_origin[origin], shares.key - by_key[key_id])
        if room > 0:
            by_key[key_id] += 1
            chosen.append((origin, room))
            if len(chosen) == limit:
                break
    return chosen


def _fill_origins(session: Session) -> bool:
    """Give pending deliveries with no origin (``''``: written by code older than migration 0012, still running in a
    rolling upgrade) their URL's, a batch at a time: all of them had shared one receiver's cap. In id order, so
    senders filling the same ones at once take their rows' locks in the same order. Whether there were any."""
    unknown = session.execute(select(WebhookDelivery.id, WebhookDelivery.url)
                              .where(WebhookDelivery.state == PENDING, WebhookDelivery.origin == "")
                              .order_by(WebhookDelivery.id).limit(ORIGIN_FILL_BATCH)).all()
    if unknown:
        session.execute(update(WebhookDelivery).where(WebhookDelivery.origin == "")
                        .execution_options(synchronize_session=False),
                        [{"id": row.id, "origin": webhook_origin(row.url)} for row in unknown])
    return bool(unknown)


def _walk_origins(session: Session, now: datetime,
                  in_flight: InFlight) -> list[tuple[str, datetime | None, str | None]]:
    """Up to :data:`RECEIVERS_WALKED` receivers with deliveries pending, the next after ``in_flight.walked_to`` on
    (then from the first), which it moves to the last visited: each with its earliest due at ``now`` and that
    delivery's key (None, None: none is due)."""
    after = in_flight.walked_to
    walked = _pending_origins(session, now, after, RECEIVERS_WALKED)
    if after is not None and len(walked) < RECEIVERS_WALKED:  # past the last receiver: on from the first
        walked += [row for row in _pending_origins(session, now, None, RECEIVERS_WALKED - len(walked))
                   if row[0] <= after]
    in_flight.walked_to = walked[-1][0] if len(walked) == RECEIVERS_WALKED else None
    return walked


def _pending_origins(session: Session, now: datetime, after: str | None,
                     count: int) -> list[tuple[str, datetime | None, str | None]]:
    """The first ``count`` receivers with deliveries pending (those after ``after``), each with its earliest due at
    ``now`` and that delivery's key (None, None: none is due), read off the index one receiver after the other (a
    recursive query: SQLite and PostgreSQL scan an index for its distinct values whole, every delivery pending).
    Never ``''``, deliveries whose origin is not filled in yet (:func:`_fill_origins`): no claim takes them, and
    walked as a receiver they had used one of the claim's picks for nothing."""
    pending = WebhookDelivery.state == PENDING
    first = (select(func.min(WebhookDelivery.origin).label("origin"), literal_column("1", Integer).label("visited"))
             .where(pending, WebhookDelivery.origin > (after or "")))
    origins = first.cte("origins", recursive=True)
    following = select(func.min(WebhookDelivery.origin)).where(pending, WebhookDelivery.origin > origins.c.origin)
    origins = origins.union_all(select(following.scalar_subquery(), origins.c.visited + 1)
                                .where(origins.c.origin.is_not(None), origins.c.visited < count))
    earliest_due = (select(WebhookDelivery.id)
                    .where(pending, WebhookDelivery.origin == origins.c.origin, WebhookDelivery.next_attempt_at <= now)
                    .order_by(WebhookDelivery.next_attempt_at, WebhookDelivery.id).limit(1).scalar_subquery())
    walked = (select(origins.c.origin, earliest_due.label("earliest_due_id"))
              .where(origins.c.origin.is_not(None)).subquery())
    return [tuple(row) for row in session.execute(  # (its due time and key joined to its id: one search a receiver)
        select(walked.c.origin, WebhookDelivery.next_attempt_at, Job.owner_key_id)
        .outerjoin(WebhookDelivery, WebhookDelivery.id == walked.c.earliest_due_id)
        .outerjoin(Job, Job.id == WebhookDelivery.job_id)
        .order_by(walked.c.origin))]


def backoff_s(attempts: int, base_s: float, max_s: float) -> float:
    """Seconds before attempt ``attempts + 1``: ``base_s`` doubling per attempt, at most ``max_s``.

    The doubling stops at a float's largest power of two: from attempt 1,025 on (a delivery retried a minute apart
    for a week gets there in 17 h) ``2 ** 1024`` had overflowed the float, so no failed attempt was recorded again
    and the delivery was retried every lease for good, past its retry window.

    Examples:
        >>> [backoff_s(n, 5, 60) for n in (1, 2, 3, 4, 5)]
        [5.0, 10.0, 20.0, 40.0, 60.0]
        >>> backoff_s(2000, 5.0, 60.0)
        60.0
    """
    return float(min(max_s, base_s * 2.0 ** min(attempts - 1, 1023)))


def retry_at(created_at: datetime, now: datetime, attempts: int, base_s: float, max_s: float,
             retry_for_s: float, asked_s: float | None = None) -> datetime | None:
    """When to try again a delivery whose attempt ``attempts`` failed at ``now``: after :func:`backoff_s`, or the
    longer wait its receiver ``asked_s`` for (a 429's or 503's ``Retry-After``, which had been ignored, the receiver
    tried again sooner than it asked), at most ``max_s`` of it; and the last time ``retry_for_s`` after its event;
    None once that has passed (the delivery has failed). A retry that fell past it had been dropped, so a delivery
    gave up as much as a backoff early: by default at 23.4 h of 24.

    Examples:
        >>> event = datetime(2026, 1, 1)
        >>> retry_at(event, event + timedelta(hours=23.5), 30, 5, 3600, 86400)  # an hour's backoff, cut to 24 h
        datetime.datetime(2026, 1, 2, 0, 0)
        >>> retry_at(event, event + timedelta(hours=24), 31, 5, 3600, 86400) is None
        True
        >>> [retry_at(event, event, 1, 5, 3600, 86400, asked) - event for asked in (120, 1, 7200)]
        [datetime.timedelta(seconds=120), datetime.timedelta(seconds=5), datetime.timedelta(seconds=3600)]
    """
    give_up_at = created_at + timedelta(seconds=retry_for_s)
    if now >= give_up_at:
        return None
    wait = max(backoff_s(attempts, base_s, max_s), min(asked_s or 0.0, max_s))
    return min(now + timedelta(seconds=wait), give_up_at)


def attempt(delivery: WebhookDelivery, secret: str, client: httpx.Client) -> Attempt:
    """POST the delivery once with a :func:`webhook_client`: its :class:`Attempt`. Raises :class:`TargetRefused`
    when the URL now resolves to a refused address, or is one httpx cannot send to (not worth a retry; it had been
    retried every lease for good, past the retry window, unrecorded).

    A 410 Gone is a :data:`GONE` attempt, which its sender does not retry; a 429's or 503's ``Retry-After`` (seconds,
    or an HTTP-date counted from the answer's ``Date``) is the attempt's ``asked_s``. The attempt ends by the client's
    deadline (a timeout error, retried); of the answer, at most
    ``ANSWER_READ_BYTES`` are read. Its status decides: a body still coming at the deadline, or cut off, is dropped
    with the connection (a 2xx whose body dripped past the deadline had been a timeout, so a receiver that took
    the event was sent it again for the whole retry window, and the delivery ended ``failed``).
    """
    body = delivery.payload.encode()
    timestamp = int(time.time())
    headers = {"content-type": "application/json", "webhook-id": delivery.id,
               "webhook-timestamp": str(timestamp), "webhook-signature": sign(secret, delivery.id, timestamp, body)}
    try:
        with client.stream("POST", delivery.url, content=body, headers=headers) as response:
            read = 0
            try:
                for chunk in response.iter_raw():
                    read += len(chunk)
                    if read >= ANSWER_READ_BYTES:
                        break
            except httpx.HTTPError:  # after the status line: the answer is in
                pass
    except httpx.HTTPError as exc:
        error = f"{type(exc).__name__}: {exc}"  # the transport's words: the URL is in exc.request, not here
        return Attempt(None, error, error)
    except httpx.InvalidURL as exc:  # stored before check_target read URLs as httpx does
        # httpx's words may quote the userinfo ("Invalid port: 'pa'" of bob:pa/ss@host): the log does without them
        raise TargetRefused(f"webhook_url {delivery.url!r} cannot be sent to: {exc}",
                            f"webhook_url {log_safe_url(delivery.url)!r} cannot be sent to: "
                            "httpx reads it as an invalid URL") from None
    if 200 <= response.status_code < 300:
        return Attempt(response.status_code, None, None)
    if response.is_redirect:  # had been a bare "answered 308", retried for the whole window with no word of why
        location = response.headers["location"]
        # the log's copy is cut once hidden: a URL cut first had left a token with no '@' to hide it by
        error, logged = (f"the receiver answered {response.status_code}, a redirect to {shorter(where)!r}: webhooks "
                         "follow no redirect (set webhook_url to where it points)"
                         for where in (location, log_safe_url(location, delivery.url)))
        return Attempt(response.status_code, error, logged)
    if response.status_code == GONE:  # had been retried for the whole window (24 h) though it says it never comes back
        error = ("the receiver answered 410 Gone: it is gone for good, so the delivery is not tried again (set "
                 "webhook_url to a receiver that takes it)")
        return Attempt(GONE, error, error)
    asked = asked_wait_s(response) if response.status_code in ASKS_TO_WAIT else None
    error = f"the receiver answered {response.status_code}" + (
        "" if asked is None else f", asking to be tried again in {asked:.0f} s (Retry-After)")
    return Attempt(response.status_code, error, error, asked)

