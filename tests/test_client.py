"""voxe_client: what it sends and how it reports the service's errors (httpx's MockTransport, no server), and
the files an OBJ upload sends, against the API app served in-process.

The calls against a real service are in tests/test_evaluate.py (``voxe sweep`` end to end).
"""

from __future__ import annotations

import argparse
import functools
import itertools
import json
import re
import reprlib
import subprocess
import sys
import zlib
from pathlib import Path

import httpx
import pytest

from voxe_client import Client, ServiceError

REPO = Path(__file__).resolve().parents[1]


def test_it_sends_json_with_the_key_and_returns_the_answer():
    seen = []

    def answer(request: httpx.Request) -> httpx.Response:
        seen.append(request)
        return httpx.Response(201, json=sweep)

    sweep = {"id": "s1", "state": "queued", "entries": [], "counts": {"queued": 12}, "table": ""}
    with Client("http://svc.test/", api_key="k-123", transport=httpx.MockTransport(answer)) as client:
        scenes = [{"scene_id": "a", "object": "mic"}]
        assert client.create_sweep(scenes, evaluation={"views": 4}) == sweep
        client.get_sweep("s1")
    post, get = seen
    assert (post.method, str(post.url)) == ("POST", "http://svc.test/v1/sweeps")
    assert json.loads(post.content) == {"scenes": scenes, "evaluation": {"views": 4}}  # no params: the service's
    assert post.headers["authorization"] == "Bearer k-123"
    assert (get.method, get.url.path) == ("GET", "/v1/sweeps/s1")


def test_an_answer_with_no_content_is_none():
    """``DELETE /v1/scenes/{id}`` answers 204 with no body: it had been a ServiceError calling the service's answer
    not the API's JSON, the scene deleted all the same."""
    def answer(request: httpx.Request) -> httpx.Response:
        return httpx.Response(204, headers={"content-type": "application/json"})

    with Client(transport=httpx.MockTransport(answer)) as client:
        assert client.request("DELETE", "/v1/scenes/s1") is None


def test_error_statuses_name_the_call_the_status_and_the_detail():
    def answer(request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("/plain"):
            return httpx.Response(502, text="<html>bad gateway</html>")
        if request.url.path.endswith("/gateway-json"):  # a gateway's JSON error, no detail in it
            return httpx.Response(504, json={"message": "upstream request timeout"})
        return httpx.Response(422, json={"detail": [{"loc": ["body", "scenes"], "msg": "lists a scene twice"}]})

    with Client(transport=httpx.MockTransport(answer)) as client:
        with pytest.raises(ServiceError) as error:
            client.create_sweep([])
        assert error.value.status == 422 and error.value.detail[0]["msg"] == "lists a scene twice"
        assert str(error.value) == "POST /v1/sweeps: HTTP 422: body.scenes: lists a scene twice"  # not a dict list
        with pytest.raises(ServiceError, match=r"^GET /plain: HTTP 502: Bad Gateway$"):
            client.request("GET", "/plain")
        with pytest.raises(ServiceError, match=r"^GET /gateway-json: HTTP 504: Gateway Timeout$"):  # not "None"
            client.request("GET", "/gateway-json")


def test_an_unreachable_service_is_a_service_error_naming_it():
    def refuse(request: httpx.Request) -> httpx.Response:
        raise httpx.ConnectError("connection refused", request=request)

    with Client("http://127.0.0.1:9", transport=httpx.MockTransport(refuse)) as client:
        with pytest.raises(ServiceError, match="cannot reach the service at http://127.0.0.1:9: connection refused") as error:
            client.get_sweep("x")
        assert error.value.status is None
        with pytest.raises(ServiceError, match="^cannot reach the service at http://127.0.0.1:9: connection "
                                               "refused$"):  # a stream never opened: no reconnect window
            list(client.events("j1"))


def test_the_packages_example_runs(tmp_path, monkeypatch):
    """voxe_client's docstring example swept ``scene_id``, a name it never set (a NameError for whoever ran it)."""
    import hashlib

    import voxe_client

    body = b"frame"

    def answer(request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("/events"):
            return httpx.Response(200, headers={"content-type": "text/event-stream"},
                                  content=b'event: progress\ndata: {"state": "succeeded", "overall_progress": 1.0}\n\n')
        if request.url.path.endswith("/artifacts"):
            return httpx.Response(200, json=[{"name": "turntable.mp4", "size": len(body),
                                              "sha256": hashlib.sha256(body).hexdigest()}])
        if "/artifacts/" in request.url.path:
            return httpx.Response(200, content=body)
        if request.url.path == "/v1/sweeps":
            assert json.loads(request.content)["scenes"] == [{"scene_id": "s1", "object": "microphone"}]
            return httpx.Response(201, json={"id": "w1", "state": "queued", "entries": [], "counts": {}, "table": ""})
        return httpx.Response(200, json={"id": "s1" if "scenes" in request.url.path else "j1", "state": "succeeded"})

    monkeypatch.chdir(tmp_path)
    (tmp_path / "mic.zip").write_bytes(b"PK")
    example = "\n".join(line[4:] for line in voxe_client.__doc__.splitlines() if line.startswith("    "))
    monkeypatch.setattr(voxe_client, "Client", lambda url, api_key: Client(url, api_key=api_key,
                                                                            transport=httpx.MockTransport(answer)))
    exec(example, {})
    assert (tmp_path / "out" / "turntable.mp4").read_bytes() == body


def test_a_url_without_http_or_a_host_is_bad_input_not_a_service_not_reached(capsys):
    """``--api 127.0.0.1:8000`` (no scheme), ``ftp://...`` or ``http://`` had been taken, each call then failing as a
    service not reached: exit 3, which tells a script to try again later, for a typo."""
    from voxe_core.cli import main

    for url in ("127.0.0.1:8000", "ftp://svc.test", "http://"):
        with pytest.raises(ValueError, match=f"^{re.escape(repr(url))} is not a service URL: it takes http:// or "
                                             "https:// and a host, as http://127.0.0.1:8000$"):
            Client(url)
        assert main(["status", "j1", "--api", url]) == 2
        assert capsys.readouterr().err == (f"voxe status: error: --api: {url!r} is not a service URL: it takes http:// or "
                                           "https:// and a host, as http://127.0.0.1:8000\n")
    Client("https://svc.test:8443/voxe/").close()


def test_a_service_url_with_a_query_or_fragment_is_refused_naming_it_not_sent_calls_under_the_query(capsys):
    """httpx appends each call's path to the base URL's query: ``--api "http://host:8000/?x=1"`` had sent every call
    to ``/?x=1/v1/...`` (the service's front page, or a proxy's, answering each). A query or fragment, even an empty
    one, is bad input naming it."""
    from voxe_core.cli import main

    asked = []
    for url, part, tail in (("http://127.0.0.1:8000/?x=1", "query", "?x=1"), ("https://svc.test/voxe?", "query", "?"),
                            ("http://127.0.0.1:8000/docs#/", "fragment", "#")):
        message = (f"{url!r} is not a service URL: it has a {part}, {tail!r}, which a base URL takes none of (as "
                   "http://127.0.0.1:8000 or https://host/prefix)")
        with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
            Client(url, transport=httpx.MockTransport(lambda request: asked.append(request.url)))
        assert main(["status", "j1", "--api", url]) == 2
        assert capsys.readouterr().err == f"voxe status: error: --api: {message}\n"
    assert asked == []
    Client("https://svc.test:8443/voxe/").close()


def assert_url_refused(capsys, url: str, message: str, **client_options) -> None:
    """``url`` is refused with ``message`` by the client and, as the usage error it is, by ``voxe status --api``."""
    from voxe_core.cli import main

    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        Client(url, **client_options)
    assert main(["status", "j1", "--api", url]) == 2
    assert capsys.readouterr().err == f"voxe status: error: --api: {message}\n"


def test_a_service_url_with_a_user_or_password_is_refused_without_saying_the_password(capsys):
    """``--api http://user:secret@host:8000`` had been taken: httpx sent the user and password as Basic auth in place of
    the API key's Bearer header (the service answering 401), and every error quoted the URL, the password with it
    ("cannot reach the service at http://user:secret@..."). It is bad input, the password not said."""
    asked = []
    for url, shown in (("http://user:secret@127.0.0.1:8000", "http://***@127.0.0.1:8000"),
                       ("https://s3cr%40t@svc.test/voxe?x=1", "https://***@svc.test/voxe?x=1"),
                       ("http://user@svc.test", "http://***@svc.test")):
        message = (f"{shown!r} is not a service URL: it has a user name or password, which the service takes none of "
                   "(its API key goes as --api-key or VOXE_API_KEY; the client's api_key)")
        assert_url_refused(capsys, url, message, api_key="k",
                           transport=httpx.MockTransport(lambda request: asked.append(request.headers)))
    assert asked == []


def test_a_service_url_whose_scheme_is_left_out_is_refused_without_saying_its_password(capsys):
    """``--api admin:s3cret@svc.test:8000`` (the scheme forgotten) and ``http:/admin:s3cret@svc.test`` (a slash
    short) were refused as no http(s) URL quoting the whole of it, the password with it, where one written with its
    ``//`` is quoted masked: each is now quoted with what stands before its ``@`` masked."""
    for url, shown in (("admin:s3cret@svc.test:8000", "admin:***@svc.test:8000"),
                       ("http:/admin:s3cret@svc.test", "http:/***@svc.test"),
                       ("http:///admin:s3cret@svc.test", "http:///***@svc.test")):
        message = (f"{shown!r} is not a service URL: it takes http:// or https:// and a host, as "
                   "http://127.0.0.1:8000")
        assert_url_refused(capsys, url, message)


def test_a_redirect_answered_says_where_it_points_not_that_it_may_not_be_the_service(capsys):
    """An http:// --api that a proxy redirects to https:// had been "answered 301 with no content type, not the API's
    JSON (is it the Vox-E service?)", the redirect's target unsaid (the client follows none); one with a JSON body
    "answered {...}, not a job". Each call, the event stream's opening too, says where it points."""
    def answer(request: httpx.Request) -> httpx.Response:
        body = {"json": {"detail": "moved"}} if request.url.path == "/v1/jobs" else {}
        return httpx.Response(308 if body else 301, headers={"location": f"https://svc.test{request.url.path}"}, **body)

    with Client(transport=httpx.MockTransport(answer)) as client:
        for call, method, path, status in ((lambda: client.get_job("j1"), "GET", "/v1/jobs/j1", 301),
                                           (lambda: list(client.events("j1")), "GET", "/v1/jobs/j1/events", 301),
                                           (lambda: client.create_job("s1", "a mic"), "POST", "/v1/jobs", 308)):
            with pytest.raises(ServiceError) as raised:
                call()
            assert str(raised.value) == (
                f"{method} {path}: http://127.0.0.1:8000 answered {status}, a redirect to 'https://svc.test{path}', "
                "which this client does not follow: give it the URL the service answers at (voxe: --api)")


def test_an_ipv6_service_url_written_wrong_is_refused_naming_the_option_and_the_fault(capsys):
    """``--api 'http://[::1'`` (the bracket unclosed) and ``http://::1`` (no brackets) had been refused as httpx's
    "Invalid port: ':1'", naming neither the option nor the fault; a password in such a URL is not quoted."""
    for url, shown, fault in (
            ("http://[::1", "http://[::1", "its IPv6 address's '[' has no closing ']'"),
            ("http://[::1/v1x", "http://[::1/v1x", "its IPv6 address's '[' has no closing ']'"),
            ("http://user:secret@[::1", "http://***@[::1", "its IPv6 address's '[' has no closing ']'"),
            ("http://::1:8000", "http://::1:8000", "an IPv6 address is written in [ ]")):
        message = f"{shown!r} is not a service URL: {fault}, as http://[::1]:8000"
        assert_url_refused(capsys, url, message)
    Client("http://[::1]:8000/voxe/").close()


def test_an_ipv6_service_url_with_text_after_its_bracket_is_refused_naming_that_text(capsys):
    """``--api 'http://[::1]x'`` had been refused as httpx's "Invalid port: 'x'" (of ``http://[::1]x:8000``: "Invalid
    port: 'x:8000'"): no port was written; what follows the ']' is named, a password in the URL not quoted."""
    for url, shown, after in (("http://[::1]x", "http://[::1]x", "x"),
                              ("http://user:secret@[::1]x:8000/v1", "http://***@[::1]x:8000/v1", "x:8000"),
                              ("https://[::1]]", "https://[::1]]", "]")):
        message = (f"{shown!r} is not a service URL: its IPv6 address's ']' is followed by {after!r}, where only a "
                   ":port may be, as http://[::1]:8000")
        assert_url_refused(capsys, url, message)
    Client("http://[::1]/voxe").close()


def test_a_service_url_whose_port_is_past_65535_or_0_is_refused_not_another_ports_service_asked(capsys):
    """httpx takes any port number and the socket connects to it modulo 65536: ``--api http://127.0.0.1:99999`` had
    asked (with the API key) whatever listens on port 34463, and port 0 failed as a service not reached (exit 3, try
    again later), for a typo. Both are bad input naming the port; 1 and 65535 are ports."""
    from voxe_core.cli import main

    for url, port in (("http://127.0.0.1:99999", 99999), ("https://svc.test:65536/voxe", 65536),
                      ("http://127.0.0.1:0", 0)):
        message = f"{url!r} is not a service URL: its port {port} is none of 1 to 65535"
        with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
            Client(url, api_key="k")
        assert main(["status", "j1", "--api", url]) == 2
        assert capsys.readouterr().err == f"voxe status: error: --api: {message}\n"
    for url in ("http://127.0.0.1:1", "https://svc.test:65535/voxe/"):
        Client(url).close()


class _Dropping(httpx.SyncByteStream):
    """A response body that sends ``chunks`` and then loses the connection."""

    def __init__(self, chunks: list[bytes]):
        self.chunks = chunks

    def __iter__(self):
        yield from self.chunks
        raise httpx.ReadError("connection reset")


def test_events_resume_after_a_dropped_stream_with_last_event_id():
    sent = []

    def answer(request: httpx.Request) -> httpx.Response:
        sent.append(request.headers.get("last-event-id"))
        headers = {"content-type": "text/event-stream"}
        if len(sent) == 1:
            return httpx.Response(200, headers=headers, stream=_Dropping([
                b'id: 1\nevent: stage_started\ndata: {"stage": "edit"}\n\n',
                b'event: progress\ndata: {"state": "running", "overall_progress": 0.5}\n\n']))
        return httpx.Response(200, headers=headers, content=b'id: 2\nevent: succeeded\ndata: {"stage": "export"}\n\n'
                                                            b'event: progress\ndata: {"state": "succeeded"}\n\n')

    with Client(transport=httpx.MockTransport(answer)) as client:
        events = list(client.events("j1"))
    assert sent == [None, "1"]  # the reconnect asked for what came after event 1
    assert [(e["event"], e["id"]) for e in events] == [("stage_started", "1"), ("progress", None),
                                                       ("succeeded", "2"), ("progress", None)]


@pytest.mark.parametrize("sent, said", [
    (b"event: progress\ndata: not json\n\n", "progress event's data 'not json' is not JSON"),
    (b"id: x7\nevent: checkpoint\ndata: {}\n\n", "event id 'x7' is not a number"),
    (b"event: progress\ndata: [1]\n\n", "progress snapshot [1] is not an object"),
    (b'event: progress\ndata: "running"\n\n', "progress snapshot 'running' is not an object"),
])
def test_an_event_that_is_not_the_services_is_a_service_error_quoting_it(sent, said):
    """A stream bringing what is not the service's events (a broken proxy's, a hostile service's) had failed
    ``events()`` and ``wait()`` with json's "Expecting value: line 1 column 1", int()'s "invalid literal" or an
    AttributeError: it is a ServiceError of the job's stream, quoting it, an event before it still heard."""
    def answer(request: httpx.Request) -> httpx.Response:
        return httpx.Response(200, headers={"content-type": "text/event-stream"},
                              content=b'id: 1\nevent: stage_started\ndata: {"stage": "edit"}\n\n' + sent)

    heard = []
    with Client(transport=httpx.MockTransport(answer)) as client:
        with pytest.raises(ServiceError, match=rf"^event stream of job j1: {re.escape(said)}: not the service's "
                                               "events$") as refused:
            heard.extend(event["event"] for event in client.events("j1"))
        assert heard == ["stage_started"] and not refused.value.service_failed
        with pytest.raises(ServiceError, match=re.escape(said)):
            client.wait("j1")


def test_an_answer_that_is_no_event_stream_is_not_waited_on_for_good(monkeypatch):
    """An events route answered 200 with what is no event stream (a captive portal's or a proxy's page, the timeline
    as JSON) had been read as a stream the server ended, and each of its lines restarted the reconnect window: the
    client asked again for good, past any ``reconnect_for``. One never opened is the error at once; once a stream
    opened, it counts as lost, reconnected for ``reconnect_for`` only."""
    import voxe_client.client as client_module
    from voxe_client.client import EventStreamLost

    clock, sent = [0.0], []
    monkeypatch.setattr(client_module.time, "monotonic", lambda: clock[0])
    monkeypatch.setattr(client_module.time, "sleep", lambda seconds: clock.__setitem__(0, clock[0] + seconds))
    portal = httpx.Response(200, headers={"content-type": "text/html"}, text="<html>\n<body>Sign in</body>\n</html>\n")

    def answer(request: httpx.Request) -> httpx.Response:
        sent.append(clock[0])
        if len(sent) > 100:
            pytest.fail(f"still asking at {clock[0]} s")
        if opens_first and len(sent) == 1:
            return httpx.Response(200, headers={"content-type": "text/event-stream; charset=utf-8"},
                                  content=b'id: 1\nevent: stage_started\ndata: {"stage": "edit"}\n\n')
        return portal

    opens_first = False
    with Client(transport=httpx.MockTransport(answer)) as client:
        with pytest.raises(ServiceError, match=r"^GET /v1/jobs/j1/events: http://127.0.0.1:8000 answered 200 with "
                                               r"text/html, not an event stream \(is it the Vox-E service\?\)$"):
            list(client.events("j1", reconnect_for=10))
        assert len(sent) == 1
        opens_first, sent[:] = True, []
        with pytest.raises(EventStreamLost, match=r"lost: http://127.0.0.1:8000 answered 200 with text/html, not an "
                                                  r"event stream \(\d+ attempts over 10 s"):
            list(client.events("j1", reconnect_for=10))
    assert clock[0] == 10.0 and 2 < len(sent) < 10


def test_events_resume_a_stream_the_server_ended_before_the_job_ended(monkeypatch):
    """A stopping API ends its open streams cleanly: the client asks again with Last-Event-ID until the job's
    terminal event (it had taken any end of a stream for the job's, and wait() returned a running job)."""
    import voxe_client.client as client_module

    monkeypatch.setattr(client_module.time, "sleep", lambda _s: None)
    sent = []

    def answer(request: httpx.Request) -> httpx.Response:
        sent.append(request.headers.get("last-event-id"))
        headers = {"content-type": "text/event-stream"}
        if len(sent) == 1:  # the API stops
            return httpx.Response(200, headers=headers,
                                  content=b'id: 1\nevent: stage_started\ndata: {"stage": "edit"}\n\n')
        if len(sent) == 2:  # it is not back yet
            raise httpx.ConnectError("connection refused")
        return httpx.Response(200, headers=headers, content=b'id: 2\nevent: canceled\ndata: {"stage": "edit"}\n\n'
                                                            b'event: progress\ndata: {"state": "canceled"}\n\n')

    with Client(transport=httpx.MockTransport(answer)) as client:
        events = list(client.events("j1"))
    assert sent == [None, "1", "1"]
    assert [e["event"] for e in events] == ["stage_started", "canceled", "progress"]


def test_events_resume_a_stream_gone_silent_without_a_reset(monkeypatch):
    """A connection that dies with no reset (a NAT's or Wi-Fi's drop) delivers nothing more, not even the service's
    15 s keepalive: with no read timeout the stream waited on it for good, and ``voxe wait`` with it. A stream silent
    for ``STREAM_SILENCE_S`` is lost and resumed with Last-Event-ID (here a server silent for 10 s at most, then
    closing, and a silence of 0.5 s)."""
    import socket
    import threading
    import time

    import voxe_client.client as client_module

    monkeypatch.setattr(client_module, "STREAM_SILENCE_S", 0.5)
    asked, done = [], threading.Event()
    head = b"HTTP/1.1 200 OK\r\ncontent-type: text/event-stream\r\nconnection: close\r\n\r\n"
    server = socket.create_server(("127.0.0.1", 0))

    def answer(connection: socket.socket) -> None:
        with connection:
            request = b""
            while b"\r\n\r\n" not in request:
                request += connection.recv(4096)
            asked.append(re.search(rb"(?im)^last-event-id: *(\S+)", request))
            if len(asked) == 1:
                connection.sendall(head + b'id: 1\nevent: stage_started\ndata: {"stage": "edit"}\n\n')
                done.wait(10)  # silent, the connection open
            else:
                connection.sendall(head + b'id: 2\nevent: succeeded\ndata: {"stage": "export"}\n\n')

    def serve() -> None:
        for _ in range(2):
            threading.Thread(target=answer, args=(server.accept()[0],), daemon=True).start()

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    lost = []
    try:
        with Client(f"http://127.0.0.1:{server.getsockname()[1]}") as client:
            started = time.monotonic()
            events = [e["id"] for e in client.events("j1", on_reconnect=lost.append)]
            took = time.monotonic() - started
    finally:
        done.set()
        thread.join(5)
        server.close()
    assert events == ["1", "2"] and asked[0] is None and asked[1].group(1) == b"1"
    assert took < 5, f"the silent stream was waited on for {took:.1f} s"
    assert lost[0].startswith("event stream of job j1 lost (nothing received for 0.5 s); reconnecting")


def test_events_reconnect_through_an_api_restart_of_minutes_then_give_up_saying_how_long(monkeypatch):
    """The stream had given up after 5 reconnects, about 15 s: an API restarted during a long job (its proxy
    answering 502 meanwhile) ended ``voxe wait``. It now reconnects for ``reconnect_for`` seconds from the loss."""
    import voxe_client.client as client_module

    clock = [0.0]
    monkeypatch.setattr(client_module.time, "monotonic", lambda: clock[0])
    monkeypatch.setattr(client_module.time, "sleep", lambda seconds: clock.__setitem__(0, clock[0] + seconds))
    back_at, sent = 120.0, []

    def answer(request: httpx.Request) -> httpx.Response:
        sent.append((clock[0], request.headers.get("last-event-id")))
        if len(sent) == 1:
            return httpx.Response(200, headers={"content-type": "text/event-stream"},
                                  content=b'id: 4\nevent: checkpoint\ndata: {"iteration": 250}\n\n')
        if clock[0] < back_at / 2:
            raise httpx.ConnectError("connection refused")
        if clock[0] < back_at:
            return httpx.Response(502, text="<html>bad gateway</html>")
        return httpx.Response(200, headers={"content-type": "text/event-stream"},
                              content=b'id: 5\nevent: succeeded\ndata: {}\n\n')

    with Client(transport=httpx.MockTransport(answer)) as client:
        assert [e["id"] for e in client.events("j1")] == ["4", "5"]
        assert sent[-1][1] == "4" and back_at <= sent[-1][0] <= back_at + 5  # at most 5 s between tries
        assert max(b[0] - a[0] for a, b in zip(sent, sent[1:])) == 5.0
        sent.clear()
        clock[0] = 0.0
        with pytest.raises(ServiceError, match=r"lost: HTTP 502 Bad Gateway \(\d+ attempts over 60 s, reconnecting "
                                               r"for up to 60 s\); the job goes on in the service$"):
            list(client.events("j1", reconnect_for=60))
    assert sent[-1][0] == 60.0  # a last try at the window's end


def test_a_reconnect_window_of_hours_keeps_its_pauses_and_a_quiet_stream_restarts_it(monkeypatch):
    """Two flaws of the reconnect window: its pause doubled without bound (2 ** 1024 overflowed the float at the
    1,025th attempt: any --reconnect-for past ~85 min raised OverflowError mid-outage), and only an event restarted
    it, so a stream reconnected onto keepalives alone for longer than the window gave up at its next drop, at once."""
    import voxe_client.client as client_module

    clock = [0.0]
    monkeypatch.setattr(client_module.time, "monotonic", lambda: clock[0])
    monkeypatch.setattr(client_module.time, "sleep", lambda seconds: clock.__setitem__(0, clock[0] + seconds))
    sent = []

    def answer(request: httpx.Request) -> httpx.Response:
        sent.append(clock[0])
        if len(sent) == 1:
            return httpx.Response(200, headers={"content-type": "text/event-stream"},
                                  content=b'id: 4\nevent: checkpoint\ndata: {}\n\n')
        raise httpx.ConnectError("connection refused")

    with Client(transport=httpx.MockTransport(answer)) as client:
        with pytest.raises(ServiceError, match=r"over 7200 s, reconnecting for up to 7200 s"):
            list(client.events("j1", reconnect_for=7200))
    assert len(sent) > 1025 and max(b - a for a, b in zip(sent, sent[1:])) == 5.0

    sent.clear()
    clock[0] = 0.0

    def quiet(request: httpx.Request) -> httpx.Response:
        sent.append(clock[0])
        if len(sent) == 1:
            return httpx.Response(200, headers={"content-type": "text/event-stream"},
                                  content=b'id: 4\nevent: checkpoint\ndata: {}\n\n')
        if len(sent) == 2:  # reconnected: keepalives for 990 s, then dropped
            clock[0] += 990.0
            return httpx.Response(200, headers={"content-type": "text/event-stream"}, content=b": keepalive\n\n")
        if len(sent) == 3:
            raise httpx.ConnectError("connection refused")
        return httpx.Response(200, headers={"content-type": "text/event-stream"},
                              content=b'id: 5\nevent: succeeded\ndata: {}\n\n')

    with Client(transport=httpx.MockTransport(quiet)) as client:
        assert [e["id"] for e in client.events("j1", reconnect_for=300)] == ["4", "5"]

    sent.clear()
    clock[0] = 0.0

    def flapping(request: httpx.Request) -> httpx.Response:  # opens every stream, then drops it at once
        sent.append(clock[0])
        if len(sent) > 1000:
            raise AssertionError("still reconnecting")
        return httpx.Response(200, headers={"content-type": "text/event-stream"}, content=b"retry: 2000\n\n")

    with Client(transport=httpx.MockTransport(flapping)) as client:
        with pytest.raises(ServiceError, match=r"over 60 s, reconnecting for up to 60 s"):
            list(client.events("j1", reconnect_for=60))


def test_a_stream_dropped_after_the_same_snapshot_each_time_is_given_up_at_the_window(monkeypatch):
    """Every line but ``retry:`` restarted the reconnect window, the progress snapshot each stream opens with too: a
    stream dropped after it each time (a proxy cutting streams short), the job going nowhere, was asked again every
    0.5 s for good. Only news restarts it: a timeline event after the last one heard, a snapshot that changed (or a
    keepalive); a job moving on between drops is followed to its end, one not moving is given up."""
    import voxe_client.client as client_module
    from voxe_client.client import EventStreamLost

    clock = [0.0]
    monkeypatch.setattr(client_module.time, "monotonic", lambda: clock[0])
    monkeypatch.setattr(client_module.time, "sleep", lambda seconds: clock.__setitem__(0, clock[0] + seconds))
    asked = []

    def answer(request: httpx.Request) -> httpx.Response:
        asked.append(request.headers.get("last-event-id"))
        if len(asked) > 1000:
            raise AssertionError(f"still reconnecting at {clock[0]} s")
        clock[0] += 1.0
        iteration = len(asked) if moving else 0
        if moving and len(asked) == 200:  # 200 s of drops, longer than the window: the job ends
            return httpx.Response(200, headers={"content-type": "text/event-stream"},
                                  content=b'id: 2\nevent: succeeded\ndata: {}\n\n')
        head = b'id: 1\nevent: stage_started\ndata: {"stage": "edit"}\n\n' if len(asked) == 1 else b""
        snapshot = json.dumps({"state": "running", "iteration": iteration}).encode()
        return httpx.Response(200, headers={"content-type": "text/event-stream"}, stream=_Dropping(
            [b"retry: 2000\n\n" + head + b"event: progress\ndata: " + snapshot + b"\n\n"]))

    moving = False
    with Client(transport=httpx.MockTransport(answer)) as client:
        with pytest.raises(EventStreamLost, match=r"lost: connection reset \(\d+ attempts over 6\d s, reconnecting for "
                                                  r"up to 60 s\)"):
            list(client.events("j1", reconnect_for=60))
    assert set(asked[1:]) == {"1"} and clock[0] < 70

    asked.clear(), clock.__setitem__(0, 0.0)
    moving = True
    with Client(transport=httpx.MockTransport(answer)) as client:
        events = list(client.events("j1", reconnect_for=60))
    assert len(asked) == 200 and events[-1]["event"] == "succeeded" and events[-2]["data"]["iteration"] == 199


def test_a_stream_back_says_how_long_that_loss_lasted_not_the_reconnect_window(monkeypatch):
    """The reconnect window runs from the first loss since news, over reconnects that bring none; "back after N s"
    was counted from there too, so a stream up 10 s between drops said "back after 12 s", then 24, 38, 52 s, for
    outages of 1 to 5 s. It counts from the loss it ends; the window (its "up to N s" and the error) is unchanged."""
    import voxe_client.client as client_module
    from voxe_client.client import EventStreamLost

    clock = [0.0]
    monkeypatch.setattr(client_module.time, "monotonic", lambda: clock[0])
    monkeypatch.setattr(client_module.time, "sleep", lambda seconds: clock.__setitem__(0, clock[0] + seconds))
    asked = []

    class UpTenSeconds(_Dropping):
        def __iter__(self):
            yield from self.chunks
            clock[0] += 10
            raise httpx.ReadError("connection reset")

    def answer(request: httpx.Request) -> httpx.Response:
        asked.append(request)
        head = b'id: 1\nevent: stage_started\ndata: {}\n\n' if len(asked) == 1 else b""
        return httpx.Response(200, headers={"content-type": "text/event-stream"},
                              stream=UpTenSeconds([head + b'event: progress\ndata: {"state": "queued"}\n\n']))

    said = []
    with Client(transport=httpx.MockTransport(answer)) as client:
        with pytest.raises(EventStreamLost, match=r"\(6 attempts over 62 s, reconnecting for up to 60 s\)"):
            list(client.events("j1", reconnect_for=60, on_reconnect=said.append))
    assert [re.search(r"back after (\d+) s$", line)[1] for line in said if "back" in line] == ["0", "1", "2", "4", "5"]
    assert [re.search(r"up to (\d+) s", line)[1] for line in said if "lost" in line] == ["60", "50", "38", "26", "12"]


def test_wait_with_a_timeout_gives_up_then_naming_the_job_and_its_last_state(monkeypatch):
    """``wait()`` had no overall deadline: a job stuck queued or running (its stream alive on keepalives, or lost
    and reconnecting) held the caller for good. With ``timeout`` it raises JobWaitTimeout once that has passed,
    naming the job and the state it was last heard in, through keepalives and through reconnects alike."""
    import voxe_client.client as client_module
    from voxe_client import JobWaitTimeout

    clock = [0.0]
    monkeypatch.setattr(client_module.time, "monotonic", lambda: clock[0])
    monkeypatch.setattr(client_module.time, "sleep", lambda seconds: clock.__setitem__(0, clock[0] + seconds))
    snapshot = b'event: progress\ndata: {"state": "running", "stage": "edit", "overall_progress": 0.4}\n\n'
    sent = []

    class Keepalives(httpx.SyncByteStream):  # a stream on a job that does not end: 15 s between keepalives
        def __init__(self, dropped: bool):
            self.dropped = dropped

        def __iter__(self):
            yield snapshot
            for _ in range(1000):
                clock[0] += 15.0
                if self.dropped:
                    raise httpx.ReadError("connection reset")
                yield b": keepalive\n\n"

    def answer(request: httpx.Request) -> httpx.Response:
        sent.append((clock[0], request.extensions["timeout"]["read"]))
        lost = request.url.path == "/v1/jobs/lost/events"
        if lost and len(sent) > 1:
            raise httpx.ConnectError("connection refused")
        return httpx.Response(200, headers={"content-type": "text/event-stream"}, stream=Keepalives(lost))

    with Client(transport=httpx.MockTransport(answer)) as client:
        with pytest.raises(JobWaitTimeout) as late:
            client.wait("j1", timeout=100)
        assert 100 <= clock[0] <= 115 and len(sent) == 1  # within a keepalive of it
        assert str(late.value) == ("job j1 did not end within 100 s (last heard running, stage edit, 40% done); it "
                                   "goes on in the service")
        assert (late.value.job_id, late.value.state, late.value.progress["overall_progress"]) == ("j1", "running", 0.4)
        assert isinstance(late.value, TimeoutError)
        clock[0], sent[:] = 0.0, []
        with pytest.raises(JobWaitTimeout, match=r"^job lost did not end within 20 s \(last heard running"):
            client.wait("lost", timeout=20, reconnect_for=300)  # lost at 15 s, reconnecting: not for 300 s
        assert clock[0] == 20.0 and sent[0][1] == 20.0 and all(read <= 20.0 - at for at, read in sent)
        clock[0] = 0.0
        with pytest.raises(JobWaitTimeout, match=r"^job j1 did not end within 0 s \(no progress heard from its event "
                                                 r"stream\)"):
            client.wait("j1", timeout=0)
        with pytest.raises(ValueError, match="timeout must be 0 or more seconds, got nan"):
            client.wait("j1", timeout=float("nan"))
        with pytest.raises(JobWaitTimeout, match="^job j1 did not end within 30 s"):
            list(client.events("j1", timeout=30))


@pytest.mark.parametrize("done, said", [(0.5, ", 50% done"), ("50%", ""), (True, ""), (float("nan"), ""),
                                        pytest.param(10 ** 400, "", id="1e400-int"), (float("inf"), ""), (1e9, "")])
def test_a_wait_timeout_says_the_progress_heard_only_where_it_is_a_number(done, said):
    """A progress snapshot whose ``overall_progress`` was no number (a broken service's "50%") had made the
    JobWaitTimeout's message a ValueError ("Unknown format code '%'"), said in place of the timeout, and an integer
    too large for a float (JSON's 1 and 400 zeros) an OverflowError; a bool had read as "100% done", 1e9 as
    "100000000000% done"."""
    from voxe_client import JobWaitTimeout

    timed_out = JobWaitTimeout("j1", 5, {"state": "running", "stage": "edit", "overall_progress": done})
    assert str(timed_out) == f"job j1 did not end within 5 s (last heard running, stage edit{said}); it goes on in " \
                             "the service"


@pytest.mark.parametrize("reconnect_for", [float("nan"), -1.0])
def test_a_reconnect_for_that_is_no_number_of_seconds_is_refused(reconnect_for, monkeypatch):
    """``events(reconnect_for=nan)`` never ran out: a lost stream was asked for again for good (``timeout`` had been
    checked so, not this). It is a ValueError before any request, as a negative one."""
    import voxe_client.client as client_module

    sent = []
    monkeypatch.setattr(client_module.time, "sleep", lambda seconds: None)

    def answer(request: httpx.Request) -> httpx.Response:
        sent.append(request.url.path)
        if len(sent) > 20:
            pytest.fail("still reconnecting")
        if len(sent) == 1:
            return httpx.Response(200, headers={"content-type": "text/event-stream"},
                                  content=b'id: 1\nevent: stage_started\ndata: {"stage": "edit"}\n\n')
        raise httpx.ConnectError("connection refused")

    with Client(transport=httpx.MockTransport(answer)) as client:
        with pytest.raises(ValueError, match=f"^reconnect_for must be 0 or more seconds, got {reconnect_for}$"):
            client.wait("j1", reconnect_for=reconnect_for)
    assert sent == []


def test_wait_with_a_timeout_cuts_a_retry_after_at_it(monkeypatch):
    """A stream lost and its reconnect answered 503 + Retry-After: 30 (a proxy while the API restarts) had been
    waited out ``retries`` times before the deadline was looked at: ``wait(timeout=5)`` held the caller 91 s. The
    wait is cut at the deadline, and the timeout is said then, the stream not opened again there: a first opening
    answered so had been sent again at the deadline, sooner than asked, and its 503 said instead of the timeout."""
    import voxe_client.client as client_module
    from voxe_client import JobWaitTimeout

    clock, sent = [0.0], []
    monkeypatch.setattr(client_module.time, "monotonic", lambda: clock[0])
    monkeypatch.setattr(client_module.time, "sleep", lambda seconds: clock.__setitem__(0, clock[0] + seconds))

    class Dropped(httpx.SyncByteStream):
        def __iter__(self):
            yield b'event: progress\ndata: {"state": "running"}\n\n'
            clock[0] += 1.0
            raise httpx.ReadError("connection reset")

    def answer(request: httpx.Request) -> httpx.Response:
        sent.append(clock[0])
        if len(sent) == 1:
            return httpx.Response(200, headers={"content-type": "text/event-stream"}, stream=Dropped())
        return httpx.Response(503, headers={"retry-after": "30"}, text="Service Unavailable")

    with Client(transport=httpx.MockTransport(answer), retries=3) as client:
        with pytest.raises(JobWaitTimeout, match=r"^job j1 did not end within 5 s \(last heard running\)"):
            client.wait("j1", timeout=5)
        assert clock[0] == 5.0 and sent == [0.0, 1.5]  # reconnected after a 0.5 s pause, the 30 s cut to 3.5
        clock[0], sent[:] = 0.0, [None]  # (counted as one sending: every opening is answered 503 + Retry-After: 30)
        with pytest.raises(JobWaitTimeout, match=r"^job j1 did not end within 5 s \(no progress heard"):
            list(client.events("j1", timeout=5))
        assert clock[0] == 5.0 and sent == [None, 0.0]


@pytest.mark.parametrize("tail, ended_as", [
    (b'event: progress\ndata: {"id": "j1", "state": "succeeded", "stage": null, "overall_progress": 1.0}\n\n',
     {"id": "j1", "state": "succeeded", "stage": None, "overall_progress": 1.0}),
    (b"", {"id": "j1", "state": "succeeded", "stage": "export", "overall_progress": 0.9}),  # gone before its snapshot
    (b'event: error\ndata: {"detail": "job \'j1\' was deleted"}\n\n',
     {"id": "j1", "state": "succeeded", "stage": "export", "overall_progress": 0.9}),
])
def test_wait_on_a_job_deleted_after_its_stream_said_it_ended_returns_the_end_it_said(tail, ended_as, monkeypatch,
                                                                                     capsys):
    """A job that ended and was deleted (its owner, a retention sweep) before wait's final read had ended the wait on
    that read's 404 ("GET /v1/jobs/j1: HTTP 404: job 'j1' not found", voxe wait's exit 2) although the stream had said
    "succeeded": it returns the job as the stream last gave it, with the terminal state it heard."""
    import voxe_core.cli.service as service
    from voxe_core.cli import main

    stream = (b'event: progress\ndata: {"id": "j1", "state": "running", "stage": "export", "overall_progress": 0.9}\n\n'
              b'id: 9\nevent: succeeded\ndata: {"id": 9, "kind": "succeeded"}\n\n' + tail)

    def answer(request: httpx.Request) -> httpx.Response:
        if request.url.path == "/v1/jobs/j1/events":
            return httpx.Response(200, headers={"content-type": "text/event-stream"}, content=stream)
        return httpx.Response(404, json={"detail": "job 'j1' not found"})

    with Client(transport=httpx.MockTransport(answer)) as client:
        assert client.wait("j1") == ended_as
    monkeypatch.setattr(service, "_client", lambda args: Client(transport=httpx.MockTransport(answer)))
    assert main(["wait", "j1", "--quiet"]) == 0
    assert json.loads(capsys.readouterr().out) == ended_as


def test_wait_with_no_time_left_looks_at_the_job_once(monkeypatch):
    """``wait(job, timeout=0)`` had raised JobWaitTimeout "did not end" on a job long succeeded, asking nothing: a
    wait that ran out before the stream said where the job stood looks at it once, and returns it if it has ended;
    one not ended, or a look that fails, is the timeout. The look lasts at most LOOK_AT_JOB_S (5 s): under the
    client's own timeout (60 s), ``wait(timeout=1)`` against a hung service had taken 61 s."""
    from voxe_client import JobWaitTimeout

    states, sent, limits = {"done": "succeeded", "busy": "running"}, [], []

    def answer(request: httpx.Request) -> httpx.Response:
        sent.append(request.url.path)
        limits.append(set(request.extensions["timeout"].values()))
        job = request.url.path.rsplit("/", 1)[-1]
        if job not in states:
            return httpx.Response(503, json={"detail": "down"})
        return httpx.Response(200, json={"id": job, "state": states[job]})

    with Client(transport=httpx.MockTransport(answer), retries=3) as client:
        assert client.wait("done", timeout=0) == {"id": "done", "state": "succeeded"}
        assert sent == ["/v1/jobs/done"]
        for job in ("busy", "gone"):
            sent.clear()
            with pytest.raises(JobWaitTimeout, match=rf"^job {job} did not end within 0 s"):
                client.wait(job, timeout=0)
            assert sent == [f"/v1/jobs/{job}"]
    assert limits == [{5.0}] * 3
    with Client(transport=httpx.MockTransport(answer), timeout=httpx.Timeout(2.0, connect=None)) as client:
        assert client.wait("done", timeout=0)["state"] == "succeeded" and limits[-1] == {2.0, 5.0}


def test_wait_with_a_timeout_is_not_held_past_it_by_a_silent_stream():
    """A stream gone silent (no keepalive: dead without a reset) had been read for STREAM_SILENCE_S (60 s) before
    anything was checked: against a socket server that goes silent, ``wait(timeout=1)`` gives up in about 1 s."""
    import socket
    import threading
    import time

    from voxe_client import JobWaitTimeout

    done = threading.Event()
    server = socket.create_server(("127.0.0.1", 0))

    def serve() -> None:
        connection = server.accept()[0]
        with connection:
            while b"\r\n\r\n" not in connection.recv(4096):
                pass
            connection.sendall(b"HTTP/1.1 200 OK\r\ncontent-type: text/event-stream\r\n\r\n"
                               b'event: progress\ndata: {"state": "queued"}\n\n')
            done.wait(10)  # silent, the connection open

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    try:
        with Client(f"http://127.0.0.1:{server.getsockname()[1]}") as client:
            started = time.monotonic()
            with pytest.raises(JobWaitTimeout, match=r"^job j1 did not end within 1 s \(last heard queued\)"):
                client.wait("j1", timeout=1)
            took = time.monotonic() - started
    finally:
        done.set()
        thread.join(5)
        server.close()
    assert 1 <= took < 3, f"the silent stream was waited on for {took:.1f} s"


def test_reads_answered_503_with_retry_after_are_sent_again_and_writes_are_not(monkeypatch):
    """A GET (and the event stream) answered 503 + Retry-After waits that long and asks again, at most ``retries``
    times; a POST, which the service may have acted on, a 503 without Retry-After, and one asking longer than
    MAX_RETRY_WAIT_S (it had been sent again after 30 s, sooner than asked) are errors at once, naming that wait,
    rounded up (30.4 s had read "30 s, longer than ... 30 s"); a write never sent again does not say it (a cancel's
    had read "longer than this client waits")."""
    import voxe_client.client as client_module

    waits, sent = [], []
    monkeypatch.setattr(client_module.time, "sleep", waits.append)
    busy = {"GET /v1/jobs/j1": 2, "GET /v1/jobs/j1/events": 1, "GET /v1/jobs/j2": 99, "POST /v1/jobs/j1/cancel": 1,
            "GET /v1/jobs/j4": 1}
    asks = {"GET /v1/jobs/j1/events": "120", "POST /v1/jobs/j1/cancel": "120", "GET /v1/jobs/j4": "30.4"}

    def answer(request: httpx.Request) -> httpx.Response:
        call = f"{request.method} {request.url.path}"
        sent.append(call)
        if busy.get(call, 0) > 0:
            busy[call] -= 1
            return httpx.Response(503, headers={"retry-after": asks.get(call, "2")},
                                  json={"detail": "the database is busy"})
        if call == "GET /v1/jobs/j3":
            return httpx.Response(503, json={"detail": "down"})
        if call.endswith("events"):
            return httpx.Response(200, headers={"content-type": "text/event-stream"},
                                  content=b'id: 1\nevent: succeeded\ndata: {"stage": "export"}\n\n')
        return httpx.Response(200, json={"id": "j1", "state": "running"})

    with Client(transport=httpx.MockTransport(answer), retries=3) as client:
        assert client.get_job("j1")["state"] == "running"
        assert sent == ["GET /v1/jobs/j1"] * 3 and waits == [2.0, 2.0]
        sent.clear()
        with pytest.raises(ServiceError, match=r"^GET /v1/jobs/j1/events: HTTP 503: the database is busy \(the "
                                               r"service asks to send it again in 120 s, longer than this client "
                                               r"waits: 30 s\)$"):
            list(client.events("j1"))
        assert sent == ["GET /v1/jobs/j1/events"] and waits == [2.0, 2.0]
        assert [e["event"] for e in client.events("j1")] == ["succeeded"]
        sent.clear()
        with pytest.raises(ServiceError) as refused:
            client.cancel_job("j1")
        assert str(refused.value) == "POST /v1/jobs/j1/cancel: HTTP 503: the database is busy"
        assert refused.value.status == 503 and sent == ["POST /v1/jobs/j1/cancel"]
        with pytest.raises(ServiceError, match=r"busy \(the service asks to send it again in 31 s, longer than this "
                                               r"client waits: 30 s\)$"):
            client.get_job("j4")
        with pytest.raises(ServiceError) as exhausted:
            client.get_job("j2")
        assert exhausted.value.status == 503 and sent.count("GET /v1/jobs/j2") == 4
        with pytest.raises(ServiceError, match="HTTP 503: down"):
            client.get_job("j3")
        assert sent.count("GET /v1/jobs/j3") == 1


def test_reads_answered_429_with_retry_after_wait_it_out_and_unkeyed_writes_do_not(monkeypatch):
    """A rate or quota limit's 429 + Retry-After had failed a read at once: it is waited out as a 503's, at most
    ``retries`` times; a 429 without Retry-After, or one to a write without an Idempotency-Key, is the error."""
    import voxe_client.client as client_module

    waits, sent, answers = [], [], []
    monkeypatch.setattr(client_module.time, "sleep", waits.append)

    def answer(request: httpx.Request) -> httpx.Response:
        sent.append(f"{request.method} {request.url.path}")
        status, headers = answers.pop(0)
        return httpx.Response(status, headers=headers, json={"id": "j1", "state": "running",
                              "detail": "over the rate"})

    with Client(transport=httpx.MockTransport(answer), retries=3) as client:
        answers[:] = [(429, {"retry-after": "2"}), (429, {"retry-after": "3"}), (200, {})]
        assert client.get_job("j1")["id"] == "j1" and waits == [2.0, 3.0] and len(sent) == 3
        answers[:] = [(429, {"retry-after": "1"})] * 4
        with pytest.raises(ServiceError, match="HTTP 429: over the rate") as gave_up:
            client.get_job("j1")
        assert gave_up.value.status == 429 and len(sent) == 3 + 4
        for call, refused in ((client.get_job, (429, {})), (client.cancel_job, (429, {"retry-after": "1"}))):
            answers[:], waits[:], sent[:] = [refused, (200, {})], [], []
            with pytest.raises(ServiceError, match="HTTP 429"):
                call("j1")
            assert len(sent) == 1 and waits == []


def test_reads_whose_connection_dropped_before_the_answer_are_sent_again(monkeypatch):
    """A GET whose connection was reset or closed before its answer (a kept-alive connection the service or a proxy
    had closed, an API restarting) had failed at once: it goes again after a doubling pause, at most ``retries``
    times. A connection refused is said at once (a wrong URL), and an unkeyed write is not sent again. Against a
    socket server: the errors a real close and a real reset raise are the ones resent."""
    import socket
    import struct
    import threading

    import voxe_client.client as client_module
    from voxe_client.client import ServiceUnreachable

    waits, sent, answers = [], [], []
    monkeypatch.setattr(client_module.time, "sleep", waits.append)

    def answer(request: httpx.Request) -> httpx.Response:
        sent.append(request.method)
        raised = answers.pop(0)
        if raised is not None:
            raise raised
        return httpx.Response(200, json={"id": "j1", "state": "running"})

    dropped = httpx.RemoteProtocolError("Server disconnected without sending a response.")
    with Client(transport=httpx.MockTransport(answer), retries=3) as client:
        answers[:] = [dropped, httpx.ReadError("connection reset"), httpx.WriteError("broken pipe"), None]
        assert client.get_job("j1")["id"] == "j1" and waits == [0.5, 1.0, 2.0] and sent == ["GET"] * 4
        answers[:], sent[:] = [dropped] * 5, []
        with pytest.raises(ServiceUnreachable, match="cannot reach the service .*without sending a response"):
            client.get_job("j1")
        assert sent == ["GET"] * 4
        for call, raised in ((client.get_job, httpx.ConnectError("connection refused")), (client.cancel_job, dropped)):
            answers[:], sent[:] = [raised, None], []
            with pytest.raises(ServiceUnreachable):
                call("j1")
            assert len(sent) == 1

    server = socket.create_server(("127.0.0.1", 0))
    asked = []

    def serve() -> None:
        for way in ("close", "reset", "answer"):
            connection = server.accept()[0]
            with connection:
                request = b""
                while b"\r\n\r\n" not in request:
                    request += connection.recv(4096)
                asked.append(request.split(b"\r\n")[0])
                if way == "reset":  # an RST, not a FIN
                    connection.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
                elif way == "answer":
                    connection.sendall(b"HTTP/1.1 200 OK\r\ncontent-type: application/json\r\ncontent-length: 32"
                                       b"\r\nconnection: close\r\n\r\n{\"id\": \"j1\", \"state\": \"running\"}")

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    waits.clear()
    try:
        with Client(f"http://127.0.0.1:{server.getsockname()[1]}", retries=3) as client:
            assert client.get_job("j1") == {"id": "j1", "state": "running"}
    finally:
        thread.join(5)
        server.close()
    assert asked == [b"GET /v1/jobs/j1 HTTP/1.1"] * 3 and waits == [0.5, 1.0]


def test_a_negative_number_of_retries_is_refused_and_none_sends_once(monkeypatch):
    """``retries=-1`` had been taken: no sending was ever the last, so a read whose connection kept dropping was sent
    for good. It is a ValueError; 0 sends once."""
    import voxe_client.client as client_module

    monkeypatch.setattr(client_module.time, "sleep", lambda _s: None)
    sent = []

    def answer(request: httpx.Request) -> httpx.Response:
        sent.append(request.method)
        if len(sent) > 10:
            raise AssertionError("still sending")
        raise httpx.ReadError("connection reset")

    with pytest.raises(ValueError, match="^retries must be a whole number, 0 or more, got -1$"):
        Client(transport=httpx.MockTransport(answer), retries=-1)
    with Client(transport=httpx.MockTransport(answer), retries=0) as client:
        with pytest.raises(ServiceError, match="connection reset"):
            client.get_job("j1")
    assert sent == ["GET"]


TIMEOUT_REFUSED = "timeout must be seconds above 0 and at most 1000000 (or None: none), got "


@pytest.mark.parametrize("given, said", [
    ({"timeout": float("nan")}, TIMEOUT_REFUSED + "nan"),
    ({"timeout": -1}, TIMEOUT_REFUSED + "-1"),
    ({"timeout": 0}, TIMEOUT_REFUSED + "0"),
    ({"timeout": "5"}, TIMEOUT_REFUSED + "'5'"),
    ({"timeout": 1e10}, TIMEOUT_REFUSED + "10000000000.0"),
    ({"timeout": httpx.Timeout(2.0, connect=-1.0)},
     TIMEOUT_REFUSED + "Timeout(connect=-1.0, read=2.0, write=2.0, pool=2.0) (connect -1.0)"),
    ({"timeout": httpx.Timeout(2.0, read=1e10)},
     TIMEOUT_REFUSED + "Timeout(connect=2.0, read=10000000000.0, write=2.0, pool=2.0) (read 10000000000.0)"),
    ({"retries": 2.5}, "retries must be a whole number, 0 or more, got 2.5"),
    ({"retries": float("nan")}, "retries must be a whole number, 0 or more, got nan"),
    ({"retries": True}, "retries must be a whole number, 0 or more, got True"),
])
def test_a_timeout_or_retries_that_is_no_such_number_is_refused_before_any_request(given, said):
    """``Client(timeout=nan)`` or a negative timeout had been taken, each request then failing as the service not
    reached (or never timing out), and ``retries=2.5`` or NaN never reached its last sending: each is a ValueError
    before any request, as ``events(reconnect_for=...)``'s is; None, seconds and an ``httpx.Timeout`` go."""
    sent = []
    transport = httpx.MockTransport(lambda request: sent.append(request) or httpx.Response(200, json={}))
    with pytest.raises(ValueError, match=rf"^{re.escape(said)}$"):
        Client(transport=transport, **given)
    assert sent == []
    for timeout in (None, 3, httpx.Timeout(2.0, connect=None)):
        Client(transport=transport, timeout=timeout).close()


def test_the_longest_timeout_taken_is_one_a_real_connection_takes():
    """``Client(timeout=1e10)`` had been taken, each request then an OverflowError ("timestamp out of range for
    platform time_t") from the socket's timeout: it is refused (above), and MAX_TIMEOUT_S, the longest taken, serves a
    request over a real socket."""
    from service_helpers import answering

    from voxe_client.client import MAX_TIMEOUT_S

    with answering(json.dumps({"id": "j1", "state": "running"}).encode()) as url:
        with Client(url, timeout=MAX_TIMEOUT_S) as client:
            assert client.get_job("j1") == {"id": "j1", "state": "running"}


def test_a_retry_after_given_as_an_http_date_is_waited_out_counted_from_the_servers_clock(monkeypatch):
    """``Retry-After`` may be an HTTP-date (RFC 9110 §10.2.3): it had been ignored, a read or a keyed submission
    answered so failing at once. The wait is the date less the answer's ``Date`` (the server's clock), else less
    now; a date past is no wait, one further off than MAX_RETRY_WAIT_S the error at once, and one unreadable (as
    RFC 9110's digits or a date: Python's float() had taken "1_0", "1e1" and "+5") is no Retry-After."""
    from datetime import datetime, timedelta, timezone
    from email.utils import format_datetime

    import voxe_client.client as client_module

    waits, answers = [], []
    monkeypatch.setattr(client_module.time, "sleep", waits.append)

    def answer(request: httpx.Request) -> httpx.Response:
        status, headers = answers.pop(0)
        return httpx.Response(status, headers=headers, json={"id": "j1", "state": "running", "detail": "busy"})

    def http_date(seconds_from_now: float) -> str:
        return format_datetime(datetime.now(timezone.utc) + timedelta(seconds=seconds_from_now), usegmt=True)

    served = "Wed, 21 Oct 2015 07:28:00 GMT"
    with Client(transport=httpx.MockTransport(answer), retries=3) as client:
        answers[:] = [(503, {"retry-after": "Wed, 21 Oct 2015 07:28:07 GMT", "date": served}), (200, {})]
        assert client.get_job("j1")["id"] == "j1"
    assert waits == [7.0]  # from the server's clock (7 s after its Date), not this machine's (years after)
    waits.clear()
    with Client(transport=httpx.MockTransport(answer), retries=3) as client:
        answers[:] = [(503, {"retry-after": http_date(20)}), (409, {"retry-after": http_date(-60)}), (201, {})]
        assert client.create_job("s1", "gold")["id"] == "j1"
        assert 18 < waits[0] <= 20 and waits[1:] == [0.0]
        answers[:] = [(503, {"retry-after": http_date(3600)}), (201, {})]
        with pytest.raises(ServiceError, match=r"HTTP 503: busy \(the service asks to send it again in 3[56]\d\d s"):
            client.create_job("s1", "gold")
        assert answers == [(201, {})] and len(waits) == 2
        for unreadable in ("soon", "1_0", "1e1", "+5", "0x10", "5, 10"):  # (float() had read the middle four)
            answers[:] = [(503, {"retry-after": unreadable}), (200, {})]
            with pytest.raises(ServiceError, match="HTTP 503: busy"):
                client.get_job("j1")
            assert answers == [(200, {})]


def test_a_submission_is_sent_again_a_bounded_number_of_times_and_only_while_its_answer_is_lost(monkeypatch):
    """A keyed submission waits Retry-After, else a doubling pause, between its sendings, at most ``retries`` times;
    the service's own answers (a 422, a 500, a 429 or 409 without Retry-After) are errors at once, and a 409 with
    Retry-After (its first sending not answered yet) or a 429 with it (over the quota: it had been an error at once)
    is waited for, unless it asks longer than MAX_RETRY_WAIT_S: the quota's 60 s had been waited 30 s, three times,
    each time the whole upload sent again. A write without a key (a cancel) is never sent again."""
    import voxe_client.client as client_module

    waits, sent = [], []
    monkeypatch.setattr(client_module.time, "sleep", waits.append)
    answers: list = []

    def answer(request: httpx.Request) -> httpx.Response:
        sent.append((request.method, request.url.path, request.headers.get("idempotency-key")))
        status, headers = answers.pop(0)
        if status == "drop":
            raise httpx.RemoteProtocolError("Server disconnected without sending a response.", request=request)
        return httpx.Response(status, headers=headers, json={"id": "j1", "state": "queued", "detail": "said"})

    def submit(client, *given):
        answers[:] = given
        sent.clear()
        waits.clear()
        return client.create_job("s1", "gold")

    with Client(transport=httpx.MockTransport(answer), retries=3) as client:
        assert submit(client, ("drop", {}), (502, {}), (503, {"retry-after": "7"}), (201, {}))["id"] == "j1"
        assert waits == [0.5, 1.0, 7.0] and len({key for *_, key in sent}) == 1
        with pytest.raises(ServiceError, match="HTTP 504: said") as gave_up:
            submit(client, *[(504, {})] * 5)
        assert gave_up.value.status == 504 and len(sent) == 4 and waits == [0.5, 1.0, 2.0]
        with pytest.raises(ServiceError, match="cannot reach the service") as gave_up:
            submit(client, *[("drop", {})] * 5)
        assert gave_up.value.status is None and len(sent) == 4
        assert submit(client, (409, {"retry-after": "1"}), (200, {}))["id"] == "j1" and waits == [1.0]
        assert submit(client, (429, {"retry-after": "30"}), (201, {}))["id"] == "j1"
        assert waits == [client_module.MAX_RETRY_WAIT_S] and len({key for *_, key in sent}) == 1
        with pytest.raises(ServiceError, match=r"^POST /v1/jobs: HTTP 429: said \(the service asks to send it again in "
                                               r"60 s, longer than this client waits: 30 s\)$"):
            submit(client, (429, {"retry-after": "60"}), (201, {}))
        assert len(sent) == 1 and waits == []
        with pytest.raises(ServiceError, match="HTTP 429: said") as gave_up:
            submit(client, *[(429, {"retry-after": "2"})] * 5)
        assert gave_up.value.status == 429 and len(sent) == 4 and waits == [2.0] * 3
        for status, headers in ((422, {}), (429, {}), (500, {}), (409, {})):
            with pytest.raises(ServiceError, match=f"HTTP {status}: said"):
                submit(client, (status, headers), (201, {}))
            assert len(sent) == 1 and waits == []
        answers[:] = [("drop", {}), (200, {})]
        sent.clear()
        with pytest.raises(ServiceError, match="cannot reach the service"):
            client.cancel_job("j1")
        assert sent == [("POST", "/v1/jobs/j1/cancel", None)]


@pytest.mark.parametrize("timeout", [httpx.ReadTimeout, httpx.WriteTimeout])
def test_a_submission_not_answered_in_time_is_not_sent_again_and_the_error_names_its_key(timeout, tmp_path,
                                                                                         monkeypatch):
    """An upload whose staging took the service longer than the read timeout had been sent again, whole, up to
    ``retries`` times, each staged again (the service records its key only once it is done): a submission not
    answered in time goes once, and the error says why and names its key, to send it again with for what it made. A
    request that never reached the service (a connect timeout) is still sent again."""
    import voxe_client.client as client_module
    from voxe_client.client import ServiceUnreachable

    monkeypatch.setattr(client_module.time, "sleep", lambda _s: None)
    (tmp_path / "scene.zip").write_bytes(b"PK" + b"x" * 1000)
    sent, answers = [], []

    def answer(request: httpx.Request) -> httpx.Response:
        sent.append((len(request.read()), request.headers.get("idempotency-key")))
        raised = answers.pop(0)
        if raised is not None:
            raise raised("timed out", request=request)
        return httpx.Response(201, json={"id": "s1", "state": "processing"})

    with Client(transport=httpx.MockTransport(answer), retries=3) as client:
        answers[:] = [timeout, None]
        with pytest.raises(ServiceUnreachable) as no_answer:
            client.upload_scene(tmp_path / "scene.zip", idempotency_key="upload-1")
        assert sent == [(sent[0][0], "upload-1")] and sent[0][0] > 1000
        assert str(no_answer.value) == (
            f"POST /v1/scenes: {client.base_url} did not answer in time ({timeout.__name__}: timed out); the service "
            "may have taken the request and still be working on it, so it was not sent again (it would be done "
            "twice): send it again later with Idempotency-Key 'upload-1' (voxe: --idempotency-key) for what it made")
        sent.clear()
        answers[:] = [httpx.ConnectTimeout, None]
        assert client.upload_scene(tmp_path / "scene.zip")["id"] == "s1" and len(sent) == 2


def test_a_download_answered_503_with_retry_after_is_sent_again(tmp_path, monkeypatch):
    """The class promises it for every GET, but download() streamed its GET outside the retry rule: a busy service
    (a 503 + Retry-After) failed the download at once."""
    import hashlib

    import voxe_client.client as client_module

    waits, sent, data = [], [], b"artifact bytes" * 100
    monkeypatch.setattr(client_module.time, "sleep", waits.append)

    def answer(request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("/artifacts"):
            return httpx.Response(200, json=[{"name": "a.bin", "size": len(data),
                                              "sha256": hashlib.sha256(data).hexdigest()}])
        sent.append(request.url.path)
        if len(sent) < 3:
            return httpx.Response(503, headers={"retry-after": "1"}, json={"detail": "the database is busy"})
        return httpx.Response(200, content=data)

    with Client(transport=httpx.MockTransport(answer), retries=3) as client:
        assert client.download("j1", "a.bin", tmp_path / "a.bin").read_bytes() == data
    assert sent == ["/v1/jobs/j1/artifacts/a.bin"] * 3 and waits == [1.0, 1.0]


def test_a_download_broken_off_goes_on_where_it_stopped_and_a_dead_one_fails_keeping_its_bytes(tmp_path, monkeypatch):
    """A connection reset, a stall or a body cut short mid-download had failed it, the bytes received thrown away
    (a multi-GB result started over by hand, or never arriving over a flaky link). It goes on with Range from the
    bytes it has, If-Range the listed SHA-256 (the ETag); an answer of the whole file (a server ignoring Range, an
    artifact replaced) starts it over; ``retries`` breaks in a row with no byte more fail it, its bytes kept in its
    part file for the next call (test_an_interrupted_download_goes_on_from_its_part_file_at_the_next_call)."""
    import hashlib

    import voxe_client.client as client_module

    waits, asked, served = [], [], [0]
    monkeypatch.setattr(client_module.time, "sleep", waits.append)
    data = bytes(range(256)) * 40
    sha = hashlib.sha256(data).hexdigest()
    breaks = [httpx.ReadError("connection reset"), httpx.ReadTimeout("timed out"),
              httpx.RemoteProtocolError("peer closed connection without sending complete message body")]
    whole_at = set()  # the sendings answered with the whole file, Range or not

    class Breaking(httpx.SyncByteStream):
        def __init__(self, body: bytes, cut: Exception | None):
            self.body, self.cut = body, cut

        def __iter__(self):
            part = self.body[:3000] if self.cut else self.body
            served[0] += len(part)
            yield part
            if self.cut:
                raise self.cut

    def answer(request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("/artifacts"):
            return httpx.Response(200, json=[{"name": "a.bin", "size": len(data), "sha256": sha}])
        asked.append((request.headers.get("range"), request.headers.get("if-range")))
        cut = breaks.pop(0) if breaks else None
        if isinstance(cut, httpx.ConnectError):
            raise cut
        start = int(re.fullmatch(r"bytes=(\d+)-", asked[-1][0]).group(1)) if asked[-1][0] else 0
        if len(asked) in whole_at or not start:
            return httpx.Response(200, stream=Breaking(data, cut))
        return httpx.Response(206, headers={"content-range": f"bytes {start}-{len(data) - 1}/{len(data)}"},
                              stream=Breaking(data[start:], cut))

    with Client(transport=httpx.MockTransport(answer), retries=1) as client:
        assert client.download("j1", "a.bin", tmp_path / "a.bin").read_bytes() == data
        assert asked == [(None, None), ("bytes=3000-", f'"{sha}"'), ("bytes=6000-", f'"{sha}"'),
                         ("bytes=9000-", f'"{sha}"')]
        assert served == [len(data)] and len(waits) == 3  # each byte sent once: one more try after each break
        asked.clear()
        breaks[:], whole_at = [httpx.ReadError("connection reset")], {2}
        assert client.download("j1", "a.bin", tmp_path / "b.bin").read_bytes() == data  # not the head twice
        assert [r for r, _ in asked] == [None, "bytes=3000-"]
        breaks[:] = [httpx.ReadError("connection reset")] + [httpx.ConnectError("connection refused")] * 2
        part = tmp_path / f".c.bin.{sha[:16]}.part"
        with pytest.raises(ServiceError, match=rf"^cannot download a.bin of job j1 \(3000 of 10240 bytes here, kept in "
                                               rf"{re.escape(str(part))} for the next download of it to go on from\): "
                                               "connection refused$"):
            client.download("j1", "a.bin", tmp_path / "c.bin")
    assert sorted(p.name for p in tmp_path.iterdir()) == [part.name, "a.bin", "b.bin"]  # none of a.bin's, b.bin's
    assert part.read_bytes() == data[:3000]


def test_an_interrupted_download_goes_on_from_its_part_file_at_the_next_call(tmp_path, monkeypatch):
    """A download that failed (the service gone) or was interrupted (Ctrl-C) had deleted its bytes: the next run
    fetched it all again. They stay in ``.<name>.<ETag head>.part`` beside it, and the next call, in a new run,
    asks for the rest with Range and If-Range that ETag, replacing the target only once the whole is checked. A part
    of another version of the artifact is deleted; one not a head of it (longer, or bytes that fail the check) is
    fetched whole, once more (a failing check had blamed the service), a whole one (a run stopped before its rename)
    checked without a request (it had been fetched again), and none is left by a download that got no byte."""
    import hashlib

    import voxe_client.client as client_module

    monkeypatch.setattr(client_module.time, "sleep", lambda _s: None)
    data = bytes(range(256)) * 40
    sha = hashlib.sha256(data).hexdigest()
    asked, plan = [], []
    dest = tmp_path / "out" / "a.bin"
    part = dest.with_name(f".a.bin.{sha[:16]}.part")

    class Cut(httpx.SyncByteStream):
        def __init__(self, body: bytes, at: int | None, cut: BaseException):
            self.body, self.at, self.cut = body, at, cut

        def __iter__(self):
            yield self.body[:self.at]
            if self.at is not None:
                raise self.cut

    def answer(request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("/artifacts"):
            return httpx.Response(200, json=[{"name": "a.bin", "size": len(data), "sha256": sha}])
        asked.append((request.headers.get("range"), request.headers.get("if-range")))
        at, cut = plan.pop(0) if plan else (None, None)
        if isinstance(cut, httpx.ConnectError):
            raise cut
        start = int(asked[-1][0].removeprefix("bytes=").rstrip("-")) if asked[-1][0] else 0
        headers = {"content-range": f"bytes {start}-{len(data) - 1}/{len(data)}"} if start else {}
        return httpx.Response(206 if start else 200, headers=headers, stream=Cut(data[start:], at, cut))

    def run(*steps) -> Path:  # a run of its own: a new client
        plan[:], asked[:] = steps, []
        with Client(transport=httpx.MockTransport(answer), retries=1) as client:
            return client.download("j1", "a.bin", dest)

    with pytest.raises(ServiceError, match=r"\(2500 of 10240 bytes here, kept in "):
        run((2500, httpx.ReadError("connection reset")), (None, httpx.ConnectError("refused")),
            (None, httpx.ConnectError("refused")))
    assert part.read_bytes() == data[:2500] and not dest.exists()
    with pytest.raises(KeyboardInterrupt):
        run((3000, KeyboardInterrupt()))
    assert part.read_bytes() == data[:5500] and asked == [("bytes=2500-", f'"{sha}"')]
    assert run().read_bytes() == data and asked == [("bytes=5500-", f'"{sha}"')]
    assert sorted(p.name for p in dest.parent.iterdir()) == ["a.bin"]  # the part became it

    earlier = dest.with_name(f".a.bin.{'0' * 16}.part")  # of a version of a.bin listed before: not completed now
    mine = dest.with_name("a.bin.0000000000000000.part")  # not a part file's name: a file of the caller's
    mine.write_bytes(b"mine")
    earlier.write_bytes(b"z" * 100)
    part.write_bytes(data[:4000] + b"x" * 20000)  # longer than the artifact: not a head of it, fetched whole
    assert run().read_bytes() == data and asked == [(None, None)]
    assert sorted(p.name for p in dest.parent.iterdir()) == ["a.bin", mine.name]
    part.write_bytes(b"y" * 4000)  # not a head of it (a crash's zeroed tail): the check fails, fetched whole once
    assert run().read_bytes() == data and asked == [("bytes=4000-", f'"{sha}"'), (None, None)]
    assert sorted(p.name for p in dest.parent.iterdir()) == ["a.bin", mine.name]
    dest.unlink()
    part.write_bytes(data)  # every byte, the run stopped (Ctrl-C) before its rename: checked, nothing fetched again
    assert run().read_bytes() == data and asked == []
    with pytest.raises(ServiceError, match=r"\(0 of 10240 bytes here\): refused$"):
        run(*[(None, httpx.ConnectError("refused"))] * 2)
    assert sorted(p.name for p in dest.parent.iterdir()) == ["a.bin", mine.name]


def _serving(data: bytes, name: str = "a.bin", refuse=lambda request: None):
    """A MockTransport answer serving ``data`` as the artifact ``name`` of a job, from a Range's start (206) or
    whole, unless ``refuse(request)`` answers first; the Range headers asked go to its ``asked``."""
    import hashlib

    asked = []

    def answer(request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("/artifacts"):
            return httpx.Response(200, json=[{"name": name, "size": len(data),
                                              "sha256": hashlib.sha256(data).hexdigest()}])
        asked.append(request.headers.get("range"))
        if (refused := refuse(request)) is not None:
            return refused
        start = int(asked[-1].removeprefix("bytes=").rstrip("-")) if asked[-1] else 0
        headers = {"content-range": f"bytes {start}-{len(data) - 1}/{len(data)}"} if start else {}
        return httpx.Response(206 if start else 200, headers=headers, content=data[start:])

    answer.asked = asked
    return answer


def test_a_download_over_a_file_keeps_its_permissions_and_a_symlink_stays_one(tmp_path):
    """A download over a 0600 file had left it readable by all (the umask's mode of the new file), and one to a
    symlink (latest.mp4 -> runs/1/spot.mp4) had put a file of its own in place of the link, as outputs written by
    voxe_core.files.replacing no longer do."""
    import stat

    data = b"the new turntable" * 100
    run = tmp_path / "runs" / "1"
    run.mkdir(parents=True)
    spot, latest = run / "spot.mp4", tmp_path / "latest.mp4"
    spot.write_bytes(b"old")
    spot.chmod(0o600)
    latest.symlink_to(spot)
    with Client(transport=httpx.MockTransport(_serving(data, "turntable.mp4"))) as client:
        assert client.download("j1", "turntable.mp4", latest) == latest
    assert latest.is_symlink() and spot.read_bytes() == data and stat.S_IMODE(spot.stat().st_mode) == 0o600
    assert sorted(p.name for p in tmp_path.iterdir()) == ["latest.mp4", "runs"] and list(run.iterdir()) == [spot]


def test_a_downloaded_artifact_is_on_the_disk_before_it_replaces_the_target(tmp_path, monkeypatch, flushed_renames):
    """The checked part file was renamed over the target without a flush: a power loss or kernel crash soon after
    could leave the target empty or torn (XFS, Btrfs, ext4 writing a new file), the part gone and the download said
    done, as voxe_core.files.replacing no longer leaves its files. It is flushed before the rename; a flush that finds
    the write failed (EIO) fails the download, the earlier file kept."""
    import errno
    import os

    data = b"the turntable" * 100
    with Client(transport=httpx.MockTransport(_serving(data, "turntable.mp4"))) as client:
        client.download("j1", "turntable.mp4", tmp_path / "turntable.mp4")
        assert flushed_renames == [("turntable.mp4", True)] and (tmp_path / "turntable.mp4").read_bytes() == data

        def failing(fd):
            raise OSError(errno.EIO, os.strerror(errno.EIO))

        monkeypatch.setattr(os, "fsync", failing)
        (tmp_path / "turntable.mp4").write_bytes(b"earlier")
        with pytest.raises(OSError) as error:
            client.download("j1", "turntable.mp4", tmp_path / "turntable.mp4")
    assert error.value.errno == errno.EIO and (tmp_path / "turntable.mp4").read_bytes() == b"earlier"


def test_a_416_to_a_kept_part_fetches_it_whole_and_an_error_names_the_part_kept(tmp_path, monkeypatch):
    """A 416 to a kept part's Range (bytes no head of the artifact) had failed the download and left the part, so
    every later call was answered 416 again: the part goes and the artifact is fetched whole, once: a 416 to bytes
    the call fetched itself is the error (a whole fetch broken off mid-way every time had been started over for
    good). An error answered while going on from a part says where its bytes are kept (it had not)."""
    import hashlib

    import voxe_client.client as client_module

    data = bytes(range(256)) * 40
    part = tmp_path / f".a.bin.{hashlib.sha256(data).hexdigest()[:16]}.part"
    unsatisfiable = httpx.Response(416, headers={"content-range": f"bytes */{len(data)}"}, json={"detail": "no range"})
    answer = _serving(data, refuse=lambda request: unsatisfiable if "range" in request.headers else None)
    part.write_bytes(data[:5000])
    with Client(transport=httpx.MockTransport(answer)) as client:
        assert client.download("j1", "a.bin", tmp_path / "a.bin").read_bytes() == data
    assert answer.asked == ["bytes=5000-", None] and sorted(p.name for p in tmp_path.iterdir()) == ["a.bin"]
    gone = httpx.Response(404, json={"detail": "job 'j1' not found"})
    answer = _serving(data, refuse=lambda request: gone)
    part.write_bytes(data[:5000])
    with Client(transport=httpx.MockTransport(answer)) as client:
        with pytest.raises(ServiceError, match=rf"^GET /v1/jobs/j1/artifacts/a.bin: HTTP 404: job 'j1' not found "
                                               rf"\(5000 of 10240 bytes here, kept in {re.escape(str(part))} for the "
                                               r"next download of it to go on from\)$") as refused:
            client.download("j1", "a.bin", tmp_path / "a.bin")
    assert refused.value.status == 404 and part.read_bytes() == data[:5000]

    def cut(request: httpx.Request) -> httpx.Response:  # every whole fetch broken off mid-way
        if len(answer.asked) > 10:
            pytest.fail(f"still asking after {answer.asked[:4]}")
        return unsatisfiable if "range" in request.headers else httpx.Response(200, stream=_CutAt(data, 3000))

    monkeypatch.setattr(client_module.time, "sleep", lambda seconds: None)
    answer = _serving(data, refuse=cut)
    with Client(transport=httpx.MockTransport(answer), retries=3) as client:
        with pytest.raises(ServiceError, match=r"HTTP 416: no range \(3000 of 10240 bytes here, kept in "):
            client.download("j1", "a.bin", tmp_path / "a.bin")  # had started over for good
    assert answer.asked == ["bytes=5000-", None, "bytes=3000-"] and part.read_bytes() == data[:3000]


def test_a_206_from_another_byte_than_asked_is_not_appended(tmp_path, monkeypatch):
    """A resumed download's Range answered 206 from another byte than asked (a proxy or server sending the whole
    as 206, its Content-Range "bytes 0-"; one sending another range) had been appended to the bytes held, failing
    the check, which threw them away, and saying "downloaded 13240 bytes". A 206 from byte 0 is the whole, written
    from its start; one from another byte is the error, the bytes held kept."""
    import hashlib

    import voxe_client.client as client_module

    monkeypatch.setattr(client_module.time, "sleep", lambda seconds: None)
    data = bytes(range(256)) * 40
    part = tmp_path / f".b.bin.{hashlib.sha256(data).hexdigest()[:16]}.part"
    starts = []

    def refuse(request: httpx.Request) -> httpx.Response:
        if "range" not in request.headers:
            return httpx.Response(200, stream=_CutAt(data, 3000))
        start = starts.pop(0)
        return httpx.Response(206, headers={"content-range": f"bytes {start}-{len(data) - 1}/{len(data)}"},
                              content=data[start:])

    answer = _serving(data, refuse=refuse)
    with Client(transport=httpx.MockTransport(answer)) as client:
        starts[:] = [0]
        assert client.download("j1", "a.bin", tmp_path / "a.bin").read_bytes() == data
        starts[:] = [1000]
        with pytest.raises(ServiceError, match=r"^GET /v1/jobs/j1/artifacts/a.bin: asked for its bytes from 3000 on, "
                                               r"answered 206 with Content-Range 'bytes 1000-10239/10240' \(3000 of "
                                               r"10240 bytes here, kept in "):
            client.download("j1", "a.bin", tmp_path / "b.bin")
    assert answer.asked == [None, "bytes=3000-", None, "bytes=3000-"]
    assert part.read_bytes() == data[:3000]


@pytest.mark.parametrize("unit", ["Bytes", "BYTES", "bytes "])
def test_a_206_whose_content_range_writes_its_unit_otherwise_resumes(unit, tmp_path, monkeypatch):
    """A Content-Range unit is read case-blind (RFC 9110 14.1): a proxy's "Bytes 3000-10239/10240" had failed a
    resumed download as answered from an unreadable byte."""
    import voxe_client.client as client_module

    monkeypatch.setattr(client_module.time, "sleep", lambda seconds: None)
    data = bytes(range(256)) * 40

    def refuse(request: httpx.Request) -> httpx.Response:
        if "range" not in request.headers:
            return httpx.Response(200, stream=_CutAt(data, 3000))
        return httpx.Response(206, headers={"content-range": f"{unit} 3000-{len(data) - 1}/{len(data)}"},
                              content=data[3000:])

    answer = _serving(data, refuse=refuse)
    with Client(transport=httpx.MockTransport(answer)) as client:
        assert client.download("j1", "a.bin", tmp_path / "a.bin").read_bytes() == data
    assert answer.asked == [None, "bytes=3000-"]


def test_a_body_ended_by_its_connection_closing_short_of_the_size_goes_on_where_it_stopped(tmp_path, monkeypatch):
    """A body delimited by its connection's close (no Content-Length, not chunked: HTTP/1.0, some proxies) that a
    dropped connection cut short ends as a whole one does, httpx saying nothing: the download had failed the check,
    its bytes thrown away. It goes on with Range from them, as after any break, and one that stays cut fails keeping
    them (a body whose Content-Length says it is whole is checked as it is: long.bin of
    test_download_checks_size_and_sha256_and_leaves_nothing_on_a_mismatch)."""
    import hashlib

    import voxe_client.client as client_module

    monkeypatch.setattr(client_module.time, "sleep", lambda seconds: None)
    data = bytes(range(256)) * 40
    part = tmp_path / f".b.bin.{hashlib.sha256(data).hexdigest()[:16]}.part"

    class ClosedAt3000(httpx.SyncByteStream):
        def __iter__(self):
            yield data[:3000]

    answer = _serving(data, refuse=lambda request: None if "range" in request.headers else
                      httpx.Response(200, stream=ClosedAt3000()))
    with Client(transport=httpx.MockTransport(answer), retries=1) as client:
        assert client.download("j1", "a.bin", tmp_path / "a.bin").read_bytes() == data
    assert answer.asked == [None, "bytes=3000-"]
    answer = _serving(data, refuse=lambda request: httpx.Response(200, stream=ClosedAt3000()))  # Range ignored
    with Client(transport=httpx.MockTransport(answer), retries=1) as client:
        with pytest.raises(ServiceError, match=rf"^cannot download a.bin of job j1 \(3000 of 10240 bytes here, kept "
                                               rf"in {re.escape(str(part))} for the next download of it to go on "
                                               r"from\): the connection closed at byte 3000 of the 10240 listed$"):
            client.download("j1", "a.bin", tmp_path / "b.bin")
    assert answer.asked == [None, "bytes=3000-", "bytes=3000-"] and part.read_bytes() == data[:3000]


def test_a_second_download_of_it_at_once_is_refused_and_the_part_file_itself_is_checked(tmp_path):
    """Two downloads of one artifact to one place at once (two ``voxe download`` runs) had appended their bytes to
    one part file, interleaved, and the first to end renamed it over the target, the bytes it received having been
    checked, not the file. The part is locked: a second is an OSError naming it, the first's part left alone. And
    the file itself is checked: bytes another writer added to it are a mismatch, the target left as it was."""
    import fcntl
    import hashlib

    data = bytes(range(256)) * 40
    sha = hashlib.sha256(data).hexdigest()
    part, dest = tmp_path / f".a.bin.{sha[:16]}.part", tmp_path / "a.bin"
    answer = _serving(data)
    part.write_bytes(data[:100])
    with open(part, "ab") as held, Client(transport=httpx.MockTransport(answer)) as client:
        fcntl.flock(held, fcntl.LOCK_EX)  # another download of it, running
        with pytest.raises(OSError, match=rf"^another download of a.bin of job j1 to {re.escape(str(tmp_path))} is "
                                          rf"running \(its part file {re.escape(str(part))} is locked\)"):
            client.download("j1", "a.bin", dest)
    assert answer.asked == [] and part.read_bytes() == data[:100] and not dest.exists()

    class Meddled(httpx.SyncByteStream):  # a writer that takes no lock (an older client) adds bytes as they come
        def __iter__(self):
            yield data[:4000]
            with open(part, "ab") as other:
                other.write(b"X" * 4000)
            yield data[4000:]

    part.unlink()
    dest.write_bytes(b"earlier")
    with Client(transport=httpx.MockTransport(_serving(data, refuse=lambda r: httpx.Response(200, stream=Meddled())))) \
            as client:
        with pytest.raises(ServiceError, match=f"downloaded {len(data) + 4000} bytes with sha256 (?!{sha})"):
            client.download("j1", "a.bin", dest)
    assert dest.read_bytes() == b"earlier" and sorted(p.name for p in tmp_path.iterdir()) == ["a.bin"]


def test_a_download_leaves_the_part_of_another_version_that_another_download_holds(tmp_path):
    """A download deletes the part files of the artifact's other versions beside its target, which no call
    completes now: it had deleted one that another download (another run, fetching the version it had listed) held
    locked and was writing, which then lost its bytes mid-way. That one stays, its lock held in another process; an
    unlocked one still goes."""

    data = bytes(range(256)) * 40
    held = tmp_path / f".a.bin.{'1' * 16}.part"  # another version's, being downloaded by another process
    stale = tmp_path / f".a.bin.{'2' * 16}.part"  # another version's, its download over
    held.write_bytes(b"h" * 100)
    stale.write_bytes(b"s" * 100)
    holder = subprocess.Popen(
        [sys.executable, "-c", "import fcntl, sys\n"
         f"part = open({str(held)!r}, 'ab')\nfcntl.flock(part, fcntl.LOCK_EX)\nprint('locked', flush=True)\n"
         "sys.stdin.read()"], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline() == "locked\n"
        with Client(transport=httpx.MockTransport(_serving(data))) as client:
            assert client.download("j1", "a.bin", tmp_path / "a.bin").read_bytes() == data
    finally:
        holder.communicate("")
    assert sorted(p.name for p in tmp_path.iterdir()) == [held.name, "a.bin"]
    assert held.read_bytes() == b"h" * 100


def test_a_download_drops_a_stale_part_where_locks_need_a_file_open_for_writing(tmp_path, monkeypatch):
    """On NFS ``flock`` is a whole-file POSIX lock, which refuses an exclusive lock on a file open only for reading
    (EBADF): the part of an earlier version, opened read-only to be dropped, had stayed for good there."""
    import errno
    import fcntl
    import os

    import voxe_client.client as client_module

    def posix_flock(file, operation):  # NFS's flock, as flock(2) describes it
        mode = fcntl.fcntl(file.fileno(), fcntl.F_GETFL) & os.O_ACCMODE
        if operation & fcntl.LOCK_EX and mode == os.O_RDONLY:
            raise OSError(errno.EBADF, os.strerror(errno.EBADF))
        return fcntl.lockf(file, operation)

    monkeypatch.setattr(client_module.fcntl, "flock", posix_flock)
    stale = tmp_path / f".a.bin.{'2' * 16}.part"
    stale.write_bytes(b"s" * 100)
    data = bytes(range(256)) * 40
    with Client(transport=httpx.MockTransport(_serving(data))) as client:
        assert client.download("j1", "a.bin", tmp_path / "a.bin").read_bytes() == data
    assert [p.name for p in tmp_path.iterdir()] == ["a.bin"]


def test_a_download_opening_a_part_as_another_call_drops_it_opens_it_again(tmp_path, monkeypatch):
    """A part that another call deletes as this download opens it (an earlier version's, dropped while locked) had
    refused the download as held by another running download: it is opened again and the download goes on."""
    import hashlib
    import os

    import voxe_client.client as client_module

    data = bytes(range(256)) * 40
    part = tmp_path / f".a.bin.{hashlib.sha256(data).hexdigest()[:16]}.part"
    lock_alone = client_module._lock_alone
    dropped = []

    def dropped_as_opened(file, path):
        if not dropped:  # the first open's file is unlinked by another call's drop before it is locked
            dropped.append(os.fstat(file.fileno()).st_ino)
            path.unlink()
        return lock_alone(file, path)

    monkeypatch.setattr(client_module, "_lock_alone", dropped_as_opened)
    monkeypatch.setattr(client_module.time, "sleep", lambda seconds: None)
    with Client(transport=httpx.MockTransport(_serving(data))) as client:
        assert client.download("j1", "a.bin", tmp_path / "a.bin").read_bytes() == data
    assert dropped and not part.exists()


def test_a_zero_byte_download_leaves_the_part_another_download_opened_after_its_rename(tmp_path, monkeypatch):
    """A zero-byte artifact's download, once its part was renamed over the target, deleted the part file's path as
    holding nothing to go on from: a second download of it had opened a new part there by then, and lost it."""
    import hashlib
    import os

    import voxe_client.client as client_module

    rename = os.replace
    part = tmp_path / f".e.txt.{hashlib.sha256(b'').hexdigest()[:16]}.part"

    def replace_then_another_opens(source, target):
        rename(source, target)
        part.write_bytes(b"")  # a second download's part, opened as the first renamed its own

    monkeypatch.setattr(client_module.os, "replace", replace_then_another_opens)
    listed = [{"name": "e.txt", "size": 0, "sha256": hashlib.sha256(b"").hexdigest()}]
    with Client(transport=httpx.MockTransport(lambda request: httpx.Response(200, json=listed))) as client:
        assert client.download("j1", "e.txt", tmp_path / "e.txt").read_bytes() == b""
    assert sorted(p.name for p in tmp_path.iterdir()) == [part.name, "e.txt"]


@pytest.mark.parametrize("refused", ["ENOLCK", "EOPNOTSUPP", "ENOSYS", "EINVAL"])
def test_a_download_into_a_folder_that_takes_no_locks_goes_on_unlocked(refused, tmp_path, monkeypatch):
    """A folder whose file system refuses ``flock`` (NFSv3 without lockd: ENOLCK; some SMB or FUSE mounts:
    EOPNOTSUPP, ENOSYS, EINVAL to the valid operation asked) had failed every download with that OSError, an empty
    part file left behind: the download goes on unlocked, and one that fails before a byte came leaves no part
    either."""
    import errno
    import os

    import voxe_client.client as client_module

    def flock(file, operation):
        raise OSError(getattr(errno, refused), os.strerror(getattr(errno, refused)))

    monkeypatch.setattr(client_module.fcntl, "flock", flock)
    data = bytes(range(256)) * 40
    with Client(transport=httpx.MockTransport(_serving(data))) as client:
        assert client.download("j1", "a.bin", tmp_path / "a.bin").read_bytes() == data
    assert [p.name for p in tmp_path.iterdir()] == ["a.bin"]
    down = httpx.Response(503, json={"detail": "down"})
    with Client(transport=httpx.MockTransport(_serving(data, refuse=lambda request: down))) as client:
        with pytest.raises(ServiceError, match="HTTP 503: down"):
            client.download("j1", "a.bin", tmp_path / "b.bin")
    assert [p.name for p in tmp_path.iterdir()] == ["a.bin"]


def test_a_part_file_whose_lock_fails_with_an_io_error_fails_the_download_naming_it(tmp_path, monkeypatch):
    """``flock`` failing for another reason than a file system that takes no locks (EIO: a disk or a network mount
    failing) is no licence to go on unlocked: the download fails before asking for a byte, and its OSError keeps the
    errno and names the part file (it had said a bare "[Errno 5] Input/output error")."""
    import errno
    import hashlib
    import os

    import voxe_client.client as client_module

    def flock(file, operation):
        raise OSError(errno.EIO, os.strerror(errno.EIO))

    monkeypatch.setattr(client_module.fcntl, "flock", flock)
    data = bytes(range(256)) * 40
    part = tmp_path / f".a.bin.{hashlib.sha256(data).hexdigest()[:16]}.part"
    answer = _serving(data)
    with Client(transport=httpx.MockTransport(answer)) as client:
        with pytest.raises(OSError, match=rf"cannot lock the download's part file \(Input/output error\): "
                                          rf"'{re.escape(str(part))}'$") as failed:
            client.download("j1", "a.bin", tmp_path / "a.bin")
    assert failed.value.errno == errno.EIO and failed.value.filename == str(part)
    assert answer.asked == [] and list(tmp_path.iterdir()) == []  # the empty part it made is not left behind


def test_an_artifact_with_a_long_name_downloads_through_a_part_file_of_a_name_that_fits(tmp_path):
    """The part file's name adds 23 characters to the artifact's: one of 240 (names go up to 255 bytes) failed with
    "File name too long". A part's name is at most 255 bytes, and a download broken off goes on from it."""
    import hashlib
    import os

    data = bytes(range(256)) * 40
    down = [True]

    def refuse(request: httpx.Request) -> httpx.Response | None:  # while down: cut at 3000 bytes, then unreachable
        if down[0] and request.headers.get("range"):
            raise httpx.ConnectError("connection refused")
        return httpx.Response(200, stream=_CutAt(data, 3000)) if down[0] else None

    for name in ("n" * 236 + ".bin", "é" * 125 + ".bin"):  # 240 bytes; 254 bytes in UTF-8
        answer, down[0] = _serving(data, name, refuse), True
        with Client(transport=httpx.MockTransport(answer), retries=0) as client:
            with pytest.raises(ServiceError, match=r"\(3000 of 10240 bytes here, kept in "):
                client.download("j1", name, tmp_path / name)
            part, = tmp_path.iterdir()
            assert len(os.fsencode(part.name)) <= 255 and part.name.startswith(".nnn" if name[0] == "n" else ".éé")
            assert part.name.endswith(f".{hashlib.sha256(data).hexdigest()[:16]}.part")
            down[0] = False
            assert client.download("j1", name, tmp_path / name).read_bytes() == data
        assert answer.asked == [None, "bytes=3000-", "bytes=3000-"] and [p.name for p in tmp_path.iterdir()] == [name]
        (tmp_path / name).unlink()


def test_a_download_to_a_name_longer_than_a_file_name_is_refused_before_any_byte_is_fetched(tmp_path, monkeypatch):
    """The part file's name is cut to fit 255 bytes, the target's is not: where ``Path.is_dir`` says False for a name
    too long (Python 3.14's, which raises nothing) the whole artifact was fetched, then its rename refused "File name
    too long" naming the part, which stayed for the next run to fail the same way. It is refused before any request,
    naming the target and the limit; nothing is left."""
    import errno
    import os
    import pathlib

    monkeypatch.setattr(pathlib.Path, "is_dir", lambda self, **kwargs: os.path.isdir(self))  # as Python 3.14's
    data = b"frame" * 100
    for name in ("n" * 252 + ".bin", "é" * 126 + ".bin"):  # 256 bytes each (in UTF-8)
        answer = _serving(data, name)
        with Client(transport=httpx.MockTransport(answer)) as client:
            with pytest.raises(OSError, match=rf"^\[Errno 36\] cannot download {name} of job j1 to {tmp_path / name}: "
                                              "its name is 256 bytes, more than the 255 of a file name; nothing "
                                              "downloaded$") as refused:
                client.download("j1", name, tmp_path / name)
            assert refused.value.errno == errno.ENAMETOOLONG
        assert answer.asked == [] and list(tmp_path.iterdir()) == []


def test_a_download_to_a_folder_is_refused_before_any_byte_is_fetched(tmp_path, monkeypatch, capsys):
    """``voxe download J --out DIR`` where DIR/a.png is a folder had fetched the whole artifact, then failed its rename
    with "[Errno 21] Is a directory: '.../.a.png.<etag>.part' -> '.../a.png'", the hidden part file left in DIR."""
    import voxe_core.cli.service as service
    from voxe_core.cli import main

    data = b"frame" * 100
    answer = _serving(data, "a.png")
    (tmp_path / "a.png").mkdir()
    (tmp_path / "a.png" / "mine.txt").write_text("kept")
    with Client(transport=httpx.MockTransport(answer)) as client:
        with pytest.raises(IsADirectoryError, match=f"^cannot download a.png of job j1 to {tmp_path / 'a.png'}: it "
                                                    "is a folder; nothing downloaded$"):
            client.download("j1", "a.png", tmp_path / "a.png")
    def job_or_artifact(request: httpx.Request) -> httpx.Response:
        if request.url.path == "/v1/jobs/j1":
            return httpx.Response(200, json={"id": "j1", "state": "succeeded"})
        return answer(request)

    monkeypatch.setattr(service, "_client", lambda args: Client(transport=httpx.MockTransport(job_or_artifact)))
    assert main(["download", "j1", "--out", str(tmp_path), "--quiet"]) == 2
    assert capsys.readouterr().err == (f"voxe download: error: cannot download a.png of job j1 to "
                                       f"{tmp_path / 'a.png'}: it is a folder; nothing downloaded\n")
    assert answer.asked == []  # no byte of it fetched
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["a.png", "mine.txt"]  # no part file left


def test_a_download_whose_part_file_cannot_be_written_names_it_and_the_bytes_kept(tmp_path):
    """A part file that could not be written (a full disk; here a file size limit, EFBIG) had failed the download as
    "[Errno 27] File too large" alone (``voxe download``'s whole message), naming no file, its bytes kept unsaid."""
    import errno
    import hashlib
    import resource
    import signal

    data = bytes(range(256)) * 400
    answer = _serving(data)
    part = tmp_path / f".a.bin.{hashlib.sha256(data).hexdigest()[:16]}.part"
    limits, ignored = resource.getrlimit(resource.RLIMIT_FSIZE), signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    try:
        resource.setrlimit(resource.RLIMIT_FSIZE, (30000, limits[1]))
        with Client(transport=httpx.MockTransport(answer)) as client:
            with pytest.raises(OSError) as error:
                client.download("j1", "a.bin", tmp_path / "a.bin")
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, limits)
        signal.signal(signal.SIGXFSZ, ignored)
    assert error.value.errno == errno.EFBIG and str(error.value) == (
        f"[Errno 27] cannot download a.bin of job j1 to {tmp_path / 'a.bin'} (30000 of {len(data)} bytes here, kept "
        f"in {part} for the next download of it to go on from): File too large")
    with Client(transport=httpx.MockTransport(answer)) as client:  # and the next one goes on from them
        assert client.download("j1", "a.bin", tmp_path / "a.bin").read_bytes() == data
    assert answer.asked == [None, "bytes=30000-"] and [p.name for p in tmp_path.iterdir()] == ["a.bin"]


class _CutAt(httpx.SyncByteStream):
    """A body broken off (a connection reset) after its first ``at`` bytes."""

    def __init__(self, body: bytes, at: int):
        self.body, self.at = body, at

    def __iter__(self):
        yield self.body[:self.at]
        raise httpx.ReadError("connection reset")


def test_upload_scene_sends_the_display_name_as_the_name_field_and_keeps_the_file_name(tmp_path):
    """``name`` had been sent as the uploaded file's name: a mesh named "My spot" lost its .obj (422 "no dataset
    found"), and a zip's display name lost the text after its last dot (the service took the file name's stem)."""
    bodies = []

    def answer(request: httpx.Request) -> httpx.Response:
        bodies.append(request.read())
        return httpx.Response(201, json={"id": "s1", "state": "processing"})

    (tmp_path / "spot.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    (tmp_path / "scene.zip").write_bytes(b"PK\x05\x06" + bytes(18))
    with Client(transport=httpx.MockTransport(answer)) as client:
        client.upload_scene(tmp_path / "spot.obj", name="My spot")
        client.upload_scene(tmp_path / "scene.zip", name="take 2.final")
        client.upload_scene(tmp_path / "scene.zip")
    field = b'Content-Disposition: form-data; name="name"\r\n\r\n'
    assert b'name="files"; filename="spot.obj"' in bodies[0] and field + b"My spot\r\n" in bodies[0]
    assert b'name="archive"; filename="scene.zip"' in bodies[1] and field + b"take 2.final\r\n" in bodies[1]
    assert b'filename="scene.zip"' in bodies[2] and field not in bodies[2]


def test_a_mesh_uploaded_without_a_name_is_named_by_its_file_as_a_zip_is(api, tmp_path, capsys):
    """The service names an upload by its zip's name, but a mesh goes as files, so ``upload_scene("spot.obj")`` and
    ``voxe submit --upload spot.obj`` had made a scene named "scene-1a2b3c4d", the mesh's name nowhere in the
    listing. It is named (by the service) by the mesh's file name without its suffix, as a zip is, "scene-<id>"
    where that is blank; a name given stays."""
    import zipfile

    from voxe_core.cli import main

    url, _ = api
    (tmp_path / "my plane.v2.obj").write_text(PLANE_OBJ)
    with zipfile.ZipFile(tmp_path / "plane.zip", "w") as archive:
        archive.writestr("plane.obj", PLANE_OBJ)
    with Client(url) as client:
        assert client.upload_scene(tmp_path / "my plane.v2.obj")["name"] == "my plane.v2"
        assert client.upload_scene(tmp_path / "plane.zip")["name"] == "plane"
        assert client.upload_scene(tmp_path / "my plane.v2.obj", name="given")["name"] == "given"
        assert main(["submit", "a plane", "--upload", str(tmp_path / "my plane.v2.obj"), "--api", url]) == 0
        job = client.get_job(capsys.readouterr().out.strip())
        assert client.get_scene(job["scene_id"])["name"] == "my plane.v2"
        (tmp_path / " .obj").write_text(PLANE_OBJ)  # (a blank stem: the client had sent the name " ", refused 422)
        blank = client.upload_scene(tmp_path / " .obj")
        assert blank["name"] == f"scene-{blank['id'][:8]}"


def test_voxe_submit_names_the_scene_it_uploads_as_asked(api, tmp_path, capsys):
    """``POST /v1/scenes`` takes the scene's display name (``upload_scene(name=)``), but ``voxe submit --upload`` had
    no option for it: every scene it made was named by its file. --scene-name names it; with --scene (a scene named
    already) it is refused."""
    from voxe_core.cli import main

    url, _ = api
    (tmp_path / "plane.obj").write_text(PLANE_OBJ)
    submit = ["submit", "a plane", "--api", url, "--scene-name", "plane, take 2"]
    assert main([*submit, "--upload", str(tmp_path / "plane.obj")]) == 0
    with Client(url) as client:
        scene = client.get_scene(client.get_job(capsys.readouterr().out.strip())["scene_id"])
    assert scene["name"] == "plane, take 2"
    assert main([*submit, "--scene", scene["id"]]) == 2
    assert capsys.readouterr().err == ("voxe submit: error: --scene-name names the scene --upload makes; --scene is "
                                       "one uploaded, named already\n")


def test_an_upload_of_a_file_whose_name_is_not_utf8_is_refused_naming_it(tmp_path, monkeypatch, capsys):
    """A file named in another encoding (b"sc\\xffene.zip", a Latin-1 system's) had failed in httpx's multipart
    encoder, "'utf-8' codec can't encode character '\\udcff' in position 12: surrogates not allowed", naming no file."""
    import os

    import voxe_core.cli.service as service
    from voxe_core.cli import main

    sent = []
    path = Path(os.fsdecode(bytes(tmp_path) + b"/sc\xffene.zip"))
    path.write_bytes(b"PK\x05\x06" + bytes(18))
    said = f"cannot upload {tmp_path}/sc\\xffene.zip: its name is not UTF-8, which the upload sends names as: rename it"
    with Client(transport=httpx.MockTransport(lambda request: sent.append(request))) as client:
        with pytest.raises(ValueError, match=f"^{re.escape(said)}$"):
            client.upload_scene(path)
    monkeypatch.setattr(service, "_client", lambda args: Client(transport=httpx.MockTransport(sent.append)))
    assert main(["submit", "p", "--upload", str(path)]) == 2
    assert capsys.readouterr().err == f"voxe submit: error: {said}\n" and sent == []


def test_a_folder_upload_is_refused_saying_to_zip_it(tmp_path):
    """A dataset folder given to upload_scene (``voxe submit --upload DIR``) had failed as "[Errno 21] Is a
    directory"; nothing is sent."""
    def answer(request: httpx.Request) -> httpx.Response:
        raise AssertionError("nothing is sent")

    with Client(transport=httpx.MockTransport(answer)) as client:
        with pytest.raises(ValueError, match=f"^{tmp_path} is a folder: upload a dataset as a .zip of it, or one mesh "
                                             r"file \(.obj, .ply\)$"):
            client.upload_scene(tmp_path)


def test_download_checks_size_and_sha256_and_leaves_nothing_on_a_mismatch(tmp_path):
    import hashlib

    data = b"artifact bytes" * 1000
    sha = hashlib.sha256(data).hexdigest()
    listing = [{"name": "good.bin", "size": len(data), "sha256": sha},
               {"name": "bad.bin", "size": len(data), "sha256": sha},
               {"name": "long.bin", "size": len(data) + 1, "sha256": sha},  # the bytes' sha256, not their size
               {"name": "odd.bin", "size": len(data), "sha256": "../../" + sha},  # (it names the part file)
               {"name": "text.bin", "size": str(len(data)), "sha256": sha},  # (these had been a TypeError,
               {"name": "none.bin", "sha256": sha},  # a KeyError, a mismatch of -1 bytes)
               {"name": "minus.bin", "size": -1, "sha256": sha}]

    def answer(request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("/artifacts"):
            return httpx.Response(200, json=listing)
        return httpx.Response(200, content=data[:-1] + b"X" if request.url.path.endswith("bad.bin") else data)

    with Client(transport=httpx.MockTransport(answer)) as client:
        assert client.download("j1", "good.bin", tmp_path / "good.bin").read_bytes() == data
        with pytest.raises(ServiceError, match=f"with sha256 (?!{sha})[0-9a-f]{{64}}, the service lists {len(data)} "
                                               f"bytes with sha256 {sha}"):
            client.download("j1", "bad.bin", tmp_path / "bad.bin")
        with pytest.raises(ServiceError, match=f"downloaded {len(data)} bytes .* lists {len(data) + 1} bytes"):
            client.download("j1", "long.bin", tmp_path / "long.bin")
        with pytest.raises(ServiceError, match="no artifact 'nope.bin'"):
            client.download("j1", "nope.bin", tmp_path / "nope.bin")
        with pytest.raises(ServiceError, match=r"^artifact 'odd.bin' of job j1 is listed with sha256 "
                                               r"'\.\./\.\./[0-9a-f]+', not a SHA-256; nothing written$"):
            client.download("j1", "odd.bin", tmp_path / "odd.bin")
        for name, size in (("text.bin", f"'{len(data)}'"), ("none.bin", "None"), ("minus.bin", "-1")):
            with pytest.raises(ServiceError, match=rf"^artifact '{name}' of job j1 is listed with size {size}, not a "
                                                   r"number of bytes; nothing written$"):
                client.download("j1", name, tmp_path / name)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["good.bin"]  # no partial file, no bad one


@pytest.mark.parametrize("answered", [{"detail": "moved"}, [["a.bin"]], [{"size": 1}], [{"name": 7}]])
def test_an_answer_that_is_no_artifact_listing_is_a_service_error_quoting_it(answered, tmp_path):
    """A listing that is no list of named artifacts (a proxy's JSON, a broken service's) had been a TypeError or a
    KeyError from the code reading it, out of ``artifacts()``, ``download()`` and ``voxe download``."""
    with Client(transport=httpx.MockTransport(lambda request: httpx.Response(200, json=answered))) as client:
        for call in (lambda: client.artifacts("j1"), lambda: client.download("j1", "a.bin", tmp_path / "a.bin")):
            with pytest.raises(ServiceError, match=rf"^GET /v1/jobs/j1/artifacts: http://127.0.0.1:8000 answered "
                                                   rf"{re.escape(repr(answered))}, not a list of artifacts each with "
                                                   r"a name$"):
                call()
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("answered", [["a", "job"], {"detail": "moved"}, {"id": "j1", "state": None},
                                      {"state": "queued"}])
def test_a_record_answered_with_no_id_or_state_is_a_service_error_quoting_it(answered, tmp_path, monkeypatch,
                                                                               capsys):
    """``wait()`` had returned whatever the final GET answered (a proxy's JSON, a broken service's), and ``voxe wait``
    ended in a KeyError or TypeError reading its state; ``create_job()``'s, ``upload_scene()``'s and the sweeps'
    answers were not read at all: a 201 ``{"detail": "moved"}`` made ``voxe submit`` end in a KeyError 'id'. Each
    call answering a job, scene or sweep takes only an object with an id and a state."""
    import voxe_core.cli.service as service
    from voxe_core.cli import main

    def answer(request: httpx.Request) -> httpx.Response:
        if request.url.path.endswith("/events"):
            return httpx.Response(200, headers={"content-type": "text/event-stream"},
                                  text='id: 1\nevent: succeeded\ndata: {}\n\n')
        return httpx.Response(201 if request.method == "POST" else 200, json=answered)

    def said(kind: str) -> str:
        return rf"answered {re.escape(repr(answered))}, not a {kind} with an id and a state$"

    archive = tmp_path / "mic.zip"
    archive.write_bytes(b"PK\x05\x06" + bytes(18))
    with Client(transport=httpx.MockTransport(answer)) as client:
        for call, asked, kind in ((lambda: client.wait("j1"), "GET /v1/jobs/j1", "job"),
                                  (lambda: client.get_job("j1"), "GET /v1/jobs/j1", "job"),
                                  (lambda: client.cancel_job("j1"), "POST /v1/jobs/j1/cancel", "job"),
                                  (lambda: client.create_job("s1", "gold"), "POST /v1/jobs", "job"),
                                  (lambda: client.upload_scene(archive), "POST /v1/scenes", "scene"),
                                  (lambda: client.create_sweep([{"scene_id": "s1", "object": "mic"}]),
                                   "POST /v1/sweeps", "sweep"),
                                  (lambda: client.get_sweep("w1"), "GET /v1/sweeps/w1", "sweep")):
            with pytest.raises(ServiceError, match=rf"^{asked}: http://127.0.0.1:8000 {said(kind)}"):
                call()
    monkeypatch.setattr(service, "_client", lambda args: Client(args.api, transport=httpx.MockTransport(answer)))
    for command, asked, kind in ((["wait", "j1", "--quiet"], "GET /v1/jobs/j1", "job"),
                                 (["submit", "--scene", "s1", "a mic"], "POST /v1/jobs", "job"),
                                 (["submit", "--upload", str(archive), "a mic"], "POST /v1/scenes", "scene"),
                                 (["sweep", "--scene", "s1=mic"], "POST /v1/sweeps", "sweep")):
        assert main(command) == 2
        assert re.search(rf"^voxe {command[0]}: error: {asked}: http://127.0.0.1:8000 {said(kind)}",
                         capsys.readouterr().err, re.MULTILINE)


@pytest.mark.parametrize("answered", [{"id": "w1", "state": "queued"},
                                      {"id": "w1", "state": "queued", "entries": [], "counts": {}},
                                      {"id": "w1", "state": "queued", "entries": {}, "counts": {}, "table": ""},
                                      {"id": "w1", "state": "queued", "entries": [], "counts": [], "table": ""},
                                      {"id": "w1", "state": "queued", "entries": [], "counts": {}, "table": None}])
def test_a_sweep_answered_without_its_entries_counts_or_table_is_a_service_error_quoting_it(answered, monkeypatch,
                                                                                            capsys):
    """A sweep answered with an id and a state but no list of ``entries``, object of ``counts`` or string ``table``
    (a proxy's partial JSON) had been returned as it came, and ``voxe sweep`` ended in a KeyError 'entries' (or
    'counts', 'table' at its polls) traceback: each sweep call refuses it, quoting it, and ``voxe sweep`` says so,
    exit 2, whether the sweep's creation or a poll of ``--wait`` answered it."""
    import voxe_core.cli.service as service
    from voxe_core.cli import main

    whole = {"id": "w1", "state": "queued", "entries": [], "counts": {"queued": 12}, "table": ""}
    answers = {}

    def answer(request: httpx.Request) -> httpx.Response:
        return httpx.Response(201 if request.method == "POST" else 200, json=answers[request.method])

    said = rf"answered {re.escape(reprlib.repr(answered))}, not a sweep with its entries, counts and table$"
    answers.update(POST=answered, GET=answered)
    with Client(transport=httpx.MockTransport(answer)) as client:
        for call, asked in ((lambda: client.create_sweep([{"scene_id": "s1", "object": "mic"}]), "POST /v1/sweeps"),
                            (lambda: client.get_sweep("w1"), "GET /v1/sweeps/w1"),
                            (lambda: client.cancel_sweep("w1"), "POST /v1/sweeps/w1/cancel")):
            with pytest.raises(ServiceError, match=rf"^{asked}: http://127.0.0.1:8000 {said}"):
                call()
    monkeypatch.setattr(service, "_client", lambda args: Client(args.api, transport=httpx.MockTransport(answer)))
    monkeypatch.setattr(service, "SWEEP_POLL_S", 0.01)
    for command, created, asked in ((["sweep", "--scene", "s1=mic"], answered, "POST /v1/sweeps"),
                                    (["sweep", "--scene", "s1=mic", "--wait", "--quiet"], whole, "GET /v1/sweeps/w1"),
                                    (["cancel-sweep", "w1"], answered, "POST /v1/sweeps/w1/cancel")):
        answers["POST"] = created
        assert main(command) == 2
        assert re.search(rf"^voxe {command[0]}: error: {asked}: http://127.0.0.1:8000 {said}", capsys.readouterr().err,
                         re.MULTILINE)


def test_an_answer_or_error_page_is_read_up_to_its_limit_only(tmp_path):
    """A JSON answer or an error page (the event stream's, a download's too) had been buffered whole however long: a
    hostile or broken server's 64 MiB (or endless) body is read to MAX_ANSWER_BYTES, then a ServiceError naming it."""
    from voxe_client.client import MAX_ANSWER_BYTES

    pulled = []

    def long_body():
        for chunk in range(64):
            pulled.append(chunk)
            yield b" " * 2**20

    def answer(request: httpx.Request) -> httpx.Response:
        if request.url.path == "/v1/jobs/j1/artifacts":
            return httpx.Response(200, json=[{"name": "a.bin", "size": 4, "sha256": "0" * 64}])
        return httpx.Response(200 if request.url.path == "/v1/jobs/j1" else 502, content=long_body())

    with Client(transport=httpx.MockTransport(answer), retries=0) as client:
        for call, status, path, said in (
                (lambda: client.get_job("j1"), 200, "/v1/jobs/j1",
                 "its answer runs over 8 MiB, the most this client reads of one"),
                (lambda: list(client.events("j2")), 502, "/v1/jobs/j2/events", "Bad Gateway$"),
                (lambda: client.download("j1", "a.bin", tmp_path / "a.bin"), 502, "/v1/jobs/j1/artifacts/a.bin",
                 "Bad Gateway$")):
            pulled.clear()
            with pytest.raises(ServiceError, match=rf"^GET {path}: HTTP {status}: {said}") as raised:
                call()
            assert raised.value.status == status and len(pulled) == MAX_ANSWER_BYTES // 2**20 + 1


def test_an_error_page_past_the_answer_limit_still_says_its_status(monkeypatch):
    """The limit's error replaced an error page's status: a 503 with a page of 9 MiB (a proxy's) was no retry, nor a
    submission's 502. The page is cut at the limit and reads as empty: the status decides, as for one none can
    decode."""
    import voxe_client.client as client_module
    from voxe_client.client import MAX_ANSWER_BYTES

    monkeypatch.setattr(client_module.time, "sleep", lambda _s: None)
    def page():
        for _ in range(MAX_ANSWER_BYTES // 2**20 + 1):
            yield b"<html>busy</html>" + b" " * 2**20

    answers = [httpx.Response(503, headers={"retry-after": "0"}, content=page()), httpx.Response(200, content=JOB),
               httpx.Response(502, content=page()), httpx.Response(201, content=JOB)]
    sent = []

    def answer(request: httpx.Request) -> httpx.Response:
        sent.append((request.method, request.headers.get("idempotency-key")))
        return answers.pop(0)

    with Client(transport=httpx.MockTransport(answer), retries=1) as client:
        assert client.get_job("j1") == {"id": "j1", "state": "running"}
        assert client.create_job("s1", "gold", idempotency_key="k1") == {"id": "j1", "state": "running"}
    assert sent == [("GET", None)] * 2 + [("POST", "k1")] * 2


@functools.cache
def _gzip_bomb(decoded_mib: int) -> bytes:
    """``decoded_mib`` MiB of zero bytes gzipped: about 1 KiB on the wire per MiB decoded (made in about 30 ms per
    MiB: once)."""
    gzipper = zlib.compressobj(9, zlib.DEFLATED, zlib.MAX_WBITS | 16)
    return b"".join(gzipper.compress(bytes(2**20)) for _ in range(decoded_mib)) + gzipper.flush()


@pytest.mark.parametrize("content_type, call, said, cap", [
    ("application/json", lambda client: client.get_job("j1"),
     r"^GET /v1/jobs/j1: HTTP 200: its answer runs over 8 MiB, the most this client reads of one", "MAX_ANSWER_BYTES"),
    ("text/event-stream", lambda client: list(client.events("j1", reconnect_for=0)),
     r"^event stream of job j1: an event runs over 1 MiB, the most this client reads of one: not the service's "
     r"events$", "MAX_EVENT_BYTES"),
], ids=["answer", "event stream"])
def test_a_gzip_bomb_is_capped_on_its_decoded_bytes_as_they_are_read(content_type, call, said, cap):
    """A gzip-encoded answer was capped on the bytes httpx had decoded, and httpx inflates each chunk read whole: a
    bomb's 32 KiB on the wire, 32 MiB of zeros decoded, sat in memory at once before any cap was checked (an event
    stream's line too, held whole), a larger one hundreds of MiB. Inflated a piece at a time, reading stops at the
    cap: the ServiceError names it and the memory the client took stays near it."""
    import tracemalloc

    from service_helpers import answering

    import voxe_client.client as client_module

    limit = getattr(client_module, cap)
    with answering(_gzip_bomb(32), {"content-type": content_type, "content-encoding": "gzip"}) as url:
        with Client(url) as client:
            tracemalloc.start()
            try:
                with pytest.raises(ServiceError, match=said):
                    call(client)
                peak = tracemalloc.get_traced_memory()[1]
            finally:
                tracemalloc.stop()
    assert peak < limit + limit // 2 + 2**20, f"{peak / 2**20:.1f} MiB taken reading it"


def test_a_gzip_encoded_event_stream_is_read_event_by_event():
    """An event stream gzip-encoded (by a proxy), its lines ended by CRLF, is read as the service's plain one."""
    import gzip

    from service_helpers import answering

    stream = (b'retry: 2000\r\n\r\nid: 1\r\nevent: stage_started\r\ndata: {"stage": "edit"}\r\n\r\n: keepalive\r\n\r\n'
              b'event: progress\r\ndata: {"state": "succeeded"}\r\n\r\n')
    with answering(gzip.compress(stream), {"content-type": "text/event-stream", "content-encoding": "gzip"}) as url:
        with Client(url) as client:
            events = list(client.events("j1"))
    assert events == [{"event": "stage_started", "id": "1", "data": {"stage": "edit"}},
                      {"event": "progress", "id": None, "data": {"state": "succeeded"}}]


def test_a_gzip_event_stream_cut_short_after_the_job_ended_ends_it_as_the_service_would():
    """The check that an encoded body is not cut short (its checksum, at its end) failed a job's events whose
    stream, gzipped by a proxy, was cut short after the job's end and its last snapshot: the events were all read, the
    job ended. One broken (its checksum wrong) before the job's end is still the error, an UndecodableAnswer, not a
    loss resumed (EventStreamLost once ``reconnect_for`` ran out)."""
    import gzip

    from service_helpers import answering
    from voxe_client.client import EventStreamLost, UndecodableAnswer

    ended = (b'id: 1\nevent: stage_started\ndata: {"stage": "edit"}\n\nid: 2\nevent: succeeded\ndata: {}\n\n'
             b'event: progress\ndata: {"state": "succeeded"}\n\n')
    broken = bytearray(gzip.compress(ended.split(b"id: 2")[0]))
    broken[-8] ^= 1
    for body, said in ((gzip.compress(ended)[:-8], None), (bytes(broken), "its answer's gzip encoding is broken")):
        with answering(body, {"content-type": "text/event-stream", "content-encoding": "gzip"}) as url:
            with Client(url, retries=0) as client:
                if said is None:
                    assert [event["event"] for event in client.events("j1")] == ["stage_started", "succeeded",
                                                                                 "progress"]
                else:
                    with pytest.raises(UndecodableAnswer, match=said) as raised:
                        list(client.events("j1", reconnect_for=0))
                    assert not isinstance(raised.value, EventStreamLost)

def test_a_gzip_event_stream_cut_short_before_the_job_ended_is_resumed_as_a_dropped_one(monkeypatch):
    """An event stream gzipped by a proxy and cut short (its connection closed where the body ends at the close,
    before its gzip stream ended) before the job's end was the error, 'its answer's gzip encoding is broken', where a
    plain stream's drop is resumed: it is a loss, resumed with Last-Event-ID after the doubling pause, within
    ``reconnect_for``; cut short every time, it is given up then, as a dropped one."""
    import gzip

    import voxe_client.client as client_module
    from voxe_client.client import EventStreamLost

    clock = [0.0]
    monkeypatch.setattr(client_module.time, "monotonic", lambda: clock[0])
    monkeypatch.setattr(client_module.time, "sleep", lambda seconds: clock.__setitem__(0, clock[0] + seconds))
    head = b'id: 1\nevent: stage_started\ndata: {"stage": "edit"}\n\nevent: progress\ndata: {"state": "running"}\n\n'
    tail = b'id: 2\nevent: succeeded\ndata: {}\n\nevent: progress\ndata: {"state": "succeeded"}\n\n'
    asked = []

    def answer(request: httpx.Request) -> httpx.Response:
        asked.append((clock[0], request.headers.get("last-event-id")))
        if len(asked) > 100:
            pytest.fail("still reconnecting")
        body = gzip.compress(head)[:-8] if len(asked) == 1 else gzip.compress(tail) if ends else \
            gzip.compress(b"retry: 2000\n\n")[:-8]
        return httpx.Response(200, headers={"content-type": "text/event-stream", "content-encoding": "gzip"},
                              stream=httpx.ByteStream(body))  # (no Content-Length or chunks: it ends at the close)

    said = []
    ends = True
    with Client(transport=httpx.MockTransport(answer)) as client:
        events = [(event["event"], event["id"]) for event in client.events("j1", on_reconnect=said.append)]
    assert events == [("stage_started", "1"), ("progress", None), ("succeeded", "2"), ("progress", None)]
    assert asked == [(0.0, None), (0.5, "1")]
    assert said[0].startswith("event stream of job j1 lost (GET /v1/jobs/j1/events: HTTP 200: its answer's gzip "
                              "encoding is broken (cut short: the body ended before its stream did)); reconnecting")

    asked.clear(), clock.__setitem__(0, 0.0)
    ends = False
    with Client(transport=httpx.MockTransport(answer)) as client:
        with pytest.raises(EventStreamLost, match=r"cut short: the body ended before its stream did\)? \(\d+ "
                                                  r"attempts over 60 s, reconnecting for up to 60 s\)"):
            list(client.events("j1", reconnect_for=60))
    assert {last for _, last in asked[1:]} == {"1"} and clock[0] == 60.0


@pytest.mark.parametrize("head, endless", [(b"data: ", b"x" * 2**16),
                                           (b"event: checkpoint\n", b"data: " + b"x" * (2**16 - 7) + b"\n")],
                         ids=["a line never ended", "an event never ended"])
def test_an_event_stream_stops_reading_an_event_past_its_limit(head, endless):
    """The event stream's lines were read by httpx's ``iter_lines``, which holds a line until its newline: a server
    sending one never ended (or an event whose data lines no empty one ends, joined as they came) had the client hold
    all of it, for good. Reading stops at the first piece past MAX_EVENT_BYTES, a ServiceError naming that limit, an
    event before it still heard."""
    from voxe_client.client import MAX_EVENT_BYTES

    pulled = []

    def long_event():
        yield b'id: 1\nevent: stage_started\ndata: {"stage": "edit"}\n\n' + head
        for piece in range(256):  # 16 MiB, then the stream ends
            pulled.append(piece)
            yield endless

    def answer(request: httpx.Request) -> httpx.Response:
        return httpx.Response(200, headers={"content-type": "text/event-stream"}, content=long_event())

    heard = []
    with Client(transport=httpx.MockTransport(answer)) as client:
        with pytest.raises(ServiceError, match=r"^event stream of job j1: an event runs over 1 MiB, the most this "
                                               r"client reads of one: not the service's events$"):
            heard.extend(event["event"] for event in client.events("j1", reconnect_for=0))
    pieces_to_cap = MAX_EVENT_BYTES // len(endless)
    assert heard == ["stage_started"] and pieces_to_cap <= len(pulled) <= pieces_to_cap + 1


def test_an_answer_is_read_through_the_encodings_the_client_asks_for_and_no_other():
    """The client asks for gzip and deflate, the encodings it inflates a piece at a time (above), and reads them
    in turn; another (brotli, which httpx had decoded whole where installed, else passed on undecoded to fail as
    not JSON) or one broken (httpx's DecodingError, a traceback in ``voxe``) is a ServiceError naming it."""
    import gzip

    job = json.dumps({"id": "j1", "state": "running"}).encode()
    asked, answers = [], [({"content-encoding": "deflate, gzip"}, gzip.compress(zlib.compress(job))),
                          ({"content-encoding": "br"}, job), ({"content-encoding": "gzip"}, b"not gzip")]

    def answer(request: httpx.Request) -> httpx.Response:
        asked.append(request.headers["accept-encoding"])
        headers, body = answers.pop(0)
        return httpx.Response(200, headers={"content-type": "application/json", **headers}, content=iter([body]))

    with Client(transport=httpx.MockTransport(answer), retries=0) as client:
        assert client.get_job("j1") == {"id": "j1", "state": "running"}
        for said in (r"its answer is encoded as 'br', which this client does not read \(it asks for gzip, deflate\)$",
                     r"its answer's gzip encoding is broken \(Error -3 while decompressing data: incorrect header "
                     r"check\)$"):
            with pytest.raises(ServiceError, match=rf"^GET /v1/jobs/j1: HTTP 200: {said}"):
                client.get_job("j1")
    assert asked == ["gzip, deflate"] * 3


def _encoded_answers(answers: list[tuple[int, dict, bytes]], ends_at_close: bool = False):
    """A MockTransport answer giving ``answers`` (status, headers, body) in turn, each body streamed a byte at a time
    (read raw, as off a socket, not decoded by httpx already), chunked, or with ``ends_at_close`` ending at the
    connection's close (no Content-Length or chunks); the requests it got go to its ``asked``."""
    asked = []

    def answer(request: httpx.Request) -> httpx.Response:
        asked.append(request)
        status, headers, body = answers.pop(0)
        response = httpx.Response(status, headers={"content-type": "application/json", **headers},
                                  content=iter([body[at:at + 1] for at in range(len(body))]))
        if ends_at_close:
            del response.headers["transfer-encoding"]
        return response

    answer.asked = asked
    return answer


def _deflated(data: bytes, wbits: int) -> bytes:
    deflater = zlib.compressobj(6, zlib.DEFLATED, wbits)
    return deflater.compress(data) + deflater.flush()


JOB = json.dumps({"id": "j1", "state": "running"}).encode()


@pytest.mark.parametrize("encoding, body", [
    ("deflate", _deflated(JOB, -zlib.MAX_WBITS)), ("deflate", _deflated(JOB, zlib.MAX_WBITS)),
    ("gzip,", _deflated(JOB, zlib.MAX_WBITS | 16)), ("", JOB), ("x-gzip", _deflated(JOB, zlib.MAX_WBITS | 16)),
    ("identity, , GZip", _deflated(JOB, zlib.MAX_WBITS | 16)),
], ids=["raw deflate", "zlib deflate", "an empty coding after gzip", "an empty header", "x-gzip", "identity then gzip"])
def test_an_answer_is_decoded_as_httpx_decoded_it(encoding, body):
    """Reading answers raw to inflate them a piece at a time had read less than httpx had: a raw deflate body (no zlib
    wrapper, which servers and proxies send as deflate; httpx falls back to it) was called broken, and an empty coding
    (``gzip,``, an empty header) or x-gzip (gzip, RFC 9110 8.4.1.3) one the client does not read."""
    answer = _encoded_answers([(200, {"content-encoding": encoding}, body)])
    with Client(transport=httpx.MockTransport(answer), retries=0) as client:
        assert client.get_job("j1") == {"id": "j1", "state": "running"}


@pytest.mark.parametrize("encoding, cut", [("gzip", _deflated(JOB, zlib.MAX_WBITS | 16)[:-8]),
                                          ("deflate", _deflated(JOB, zlib.MAX_WBITS)[:-4]),
                                          ("deflate", _deflated(JOB, -zlib.MAX_WBITS)[:-2]),
                                          ("gzip", _deflated(JOB, zlib.MAX_WBITS | 16)[:1])],
                         ids=["gzip without its trailer", "zlib deflate without its checksum", "raw deflate",
                              "gzip's first byte"])
def test_an_encoded_answer_cut_short_is_a_service_error(encoding, cut):
    """A gzip or deflate body ending before its stream did (its checksum, at the end, never checked) had been read as
    whole, the JSON in it taken: it is a ServiceError naming the encoding. An empty body (a 204's) is none."""
    answer = _encoded_answers([(200, {"content-encoding": encoding}, cut), (204, {"content-encoding": encoding}, b"")])
    with Client(transport=httpx.MockTransport(answer), retries=0) as client:
        with pytest.raises(ServiceError, match=rf"^GET /v1/jobs/j1: HTTP 200: its answer's {encoding} encoding is "
                                               r"broken \(cut short: the body ended before its stream did\)$"):
            client.get_job("j1")
        assert client.request("DELETE", "/v1/scenes/s1") is None


def test_an_encoded_answer_cut_short_is_sent_again_as_a_dropped_one_where_that_is_safe(monkeypatch):
    """A gzip answer cut short by its connection's close (where the body ends at the close) is a dropped connection,
    but was the error at once, where a plain one dropped is sent again: a read or a keyed submission is now sent
    again (the submission with its key), a cancel (no key) is not."""
    import gzip

    import voxe_client.client as client_module

    monkeypatch.setattr(client_module.time, "sleep", lambda _s: None)
    cut, whole = gzip.compress(JOB)[:-8], gzip.compress(JOB)
    answer = _encoded_answers([(200, {"content-encoding": "gzip"}, cut), (200, {"content-encoding": "gzip"}, whole),
                               (201, {"content-encoding": "gzip"}, cut), (201, {"content-encoding": "gzip"}, whole),
                               (200, {"content-encoding": "gzip"}, cut)], ends_at_close=True)
    with Client(transport=httpx.MockTransport(answer)) as client:
        assert client.get_job("j1") == {"id": "j1", "state": "running"}
        assert client.create_job("s1", "gold", idempotency_key="k1") == {"id": "j1", "state": "running"}
        with pytest.raises(ServiceError, match=r"^POST /v1/jobs/j1/cancel: HTTP 200: its answer's gzip encoding is "
                                               r"broken \(cut short"):
            client.cancel_job("j1")
    assert [(request.method, request.headers.get("idempotency-key")) for request in answer.asked] == [
        ("GET", None), ("GET", None), ("POST", "k1"), ("POST", "k1"), ("POST", None)]


def test_an_encoded_answer_cut_short_every_time_is_the_service_failing_as_a_dropped_one(monkeypatch, capsys):
    """A read whose gzip answer its connection's close cut short each time is sent again as a dropped one, but then
    ended as a refusal (``service_failed`` false, status 200), where a drop ends as the service failing: ``voxe``
    exited 2 (bad input) not 3, and ``voxe sweep --wait`` gave up at its first such poll instead of polling on."""
    import gzip

    import voxe_client.client as client_module
    from service_helpers import answering
    from voxe_client.client import EncodedAnswerCutShort
    from voxe_core.cli import main
    from voxe_core.cli.service import _poll_failed

    monkeypatch.setattr(client_module.time, "sleep", lambda _s: None)
    with answering(gzip.compress(JOB)[:-8], {"content-encoding": "gzip"}, ends_at_close=True) as url:
        with Client(url) as client, pytest.raises(EncodedAnswerCutShort, match="cut short") as raised:
            client.get_job("j1")
        assert raised.value.service_failed
        assert isinstance(_poll_failed(raised.value, None), float)  # (polling on, not raised)
        assert main(["status", "j1", "--api", url]) == 3
    assert "gzip encoding is broken (cut short" in capsys.readouterr().err


def test_an_encoded_answer_that_came_whole_but_short_is_broken_not_sent_again(monkeypatch):
    """A gzip answer whose bytes all came, as its Content-Length or chunks said, but whose gzip stream is short, was
    called cut short and sent again as a dropped connection (4 GETs, 4 s): its sender broke it, and it comes as broken
    again. It is an UndecodableAnswer at once; only a body ending at its connection's close is a drop."""
    import gzip

    import voxe_client.client as client_module
    from service_helpers import answering
    from voxe_client.client import EncodedAnswerCutShort, UndecodableAnswer

    waits = []
    monkeypatch.setattr(client_module.time, "sleep", waits.append)
    short = gzip.compress(JOB)[:-8]
    chunked = _encoded_answers([(200, {"content-encoding": "gzip"}, short)])
    with answering(short, {"content-encoding": "gzip"}) as url:  # (with its Content-Length)
        for client in (Client(url), Client(transport=httpx.MockTransport(chunked))):
            with client, pytest.raises(UndecodableAnswer, match=r"gzip encoding is broken \(cut short") as raised:
                client.get_job("j1")
            assert not isinstance(raised.value, EncodedAnswerCutShort)
    assert waits == [] and len(chunked.asked) == 1


def test_an_error_page_none_can_decode_still_says_its_status():
    """An answer's body is read before its status decides whether it is sent again: an error page whose encoding
    could not be undone (a proxy's broken one) had replaced its status with the encoding's error, a 503's retry
    called off. It reads as empty: the 503 is sent again, and a 404's error is the 404's."""
    broken, page = {"content-encoding": "deflate", "content-type": "text/html"}, b"<html>busy</html>"
    answer = _encoded_answers([(503, {**broken, "retry-after": "0"}, page[:9]), (200, {}, JOB),
                               (404, {"content-encoding": "br"}, page)])
    with Client(transport=httpx.MockTransport(answer), retries=1) as client:
        assert client.get_job("j1") == {"id": "j1", "state": "running"}
        with pytest.raises(ServiceError, match=r"^GET /v1/jobs/j1: HTTP 404: Not Found$") as raised:
            client.get_job("j1")
    assert raised.value.status == 404 and len(answer.asked) == 3


def test_a_download_asks_for_the_artifact_unencoded_and_refuses_an_encoded_answer(tmp_path):
    """An artifact was read through httpx's decoder, which inflates each chunk whole, and asked for gzip: a 64 KiB
    gzip bomb took 141 MiB (a ``gzip, gzip`` one of 1.8 KiB, 2 GiB) and wrote its 64 MiB to the part file, past the
    1 MiB listed, before the check. A Range counts an encoded body's bytes, no offset into the file: the artifact is
    asked for unencoded (``Accept-Encoding: identity``) and an encoded answer is a ServiceError naming its encoding,
    nothing written."""
    import tracemalloc

    bomb = httpx.Response(200, headers={"content-encoding": "gzip"}, content=iter([_gzip_bomb(64)]))
    asked = []
    answer = _serving(bytes(2**20), refuse=lambda request: asked.append(request.headers["accept-encoding"]) or bomb)
    with Client(transport=httpx.MockTransport(answer), retries=0) as client:
        tracemalloc.start()
        try:
            with pytest.raises(ServiceError, match=r"^GET /v1/jobs/j1/artifacts/a.bin: answered 200 encoded as gzip, "
                                                   r"not the artifact's own bytes this client asks for "
                                                   r"\(Accept-Encoding: identity\)$"):
                client.download("j1", "a.bin", tmp_path / "a.bin")
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
    assert asked == ["identity"] and list(tmp_path.iterdir()) == []
    assert peak < 4 * 2**20, f"{peak / 2**20:.1f} MiB taken"


def test_a_download_writes_no_byte_past_the_listed_size_and_keeps_no_part(tmp_path):
    """A body going on past the size the listing gives (a broken proxy's or a hostile service's endless one) had
    been written to the part file to its end (the disk filled), then a chunk past it before the check refused it:
    no byte past the listed size is written, whether the body runs past it (the chunk crossing it is not written,
    reading stops there) or its Content-Length says it will (nothing read), from byte 0 or resuming a kept part,
    and no part is left."""
    import hashlib

    data = bytes(range(256)) * 1024  # 256 KiB, written in chunks of 64 KiB: past a file's buffer, on disk at once
    part = tmp_path / f".a.bin.{hashlib.sha256(data).hexdigest()[:16]}.part"
    on_disk, chunks = [], []

    class Longer(httpx.SyncByteStream):
        """The artifact's bytes from ``start`` on, 64 KiB at a time, then more for good; the part file's size is
        noted as each chunk is asked for and as the client hangs up."""

        def __init__(self, start: int):
            self.start = start

        def __iter__(self):
            try:
                for at in itertools.count(self.start, 2**16):
                    on_disk.append(part.stat().st_size)
                    chunks.append(at)
                    yield (data + b"z" * 2**20)[at:at + 2**16]
            finally:
                on_disk.append(part.stat().st_size)

    def longer(request: httpx.Request) -> httpx.Response:
        start = int(request.headers.get("range", "bytes=0-")[6:-1])
        return httpx.Response(206 if start else 200, stream=Longer(start),
                              headers={"content-range": f"bytes {start}-{len(data) - 1}/{len(data)}"} if start else {})

    def announcing(request: httpx.Request) -> httpx.Response:
        return httpx.Response(200, headers={"content-length": str(len(data) + 1)}, stream=Longer(0))

    for refuse, kept, runs in ((longer, 0, "its body runs"), (longer, 3 * 2**16, "its body runs"),
                               (announcing, 0, rf"its Content-Length, {len(data) + 1} bytes from byte 0, runs")):
        on_disk.clear(), chunks.clear()
        part.write_bytes(data[:kept])
        answer = _serving(data, refuse=refuse)
        with Client(transport=httpx.MockTransport(answer)) as client:
            with pytest.raises(ServiceError, match=rf"^GET /v1/jobs/j1/artifacts/a.bin: answered 20[06]: {runs} "
                                                   rf"past the {len(data)} bytes the artifact is listed with; "
                                                   r"nothing kept$"):
                client.download("j1", "a.bin", tmp_path / "a.bin")
        assert max(on_disk, default=0) <= len(data) and list(tmp_path.iterdir()) == []
        assert chunks == ([] if refuse is announcing else list(range(kept, len(data) + 1, 2**16)))


def test_ids_are_one_path_segment_and_names_stay_inside_the_download_folder(tmp_path):
    """A job id holding "/" had addressed another resource ("../scenes" printed the scene listing), and a listed
    artifact named "../escape.bin" was written outside the download folder."""
    seen = []

    def answer(request: httpx.Request) -> httpx.Response:
        seen.append(request.url.raw_path.decode())
        if request.url.path.endswith("/artifacts"):
            return httpx.Response(200, json=[{"name": "../escape.bin", "size": 1, "sha256": "0" * 64}])
        if "redirect" in request.url.raw_path.decode():
            return httpx.Response(200, text="<html>moved</html>", headers={"content-type": "text/html"})
        sweep = {"entries": [], "counts": {}, "table": ""} if request.url.path.startswith("/v1/sweeps/") else {}
        return httpx.Response(200, json={"id": "x", "state": "running", **sweep})

    with Client("http://svc.test", transport=httpx.MockTransport(answer)) as client:
        client.get_job("../scenes")
        client.get_sweep("a?b#c")
        for name in ("../escape.bin", "sub/x.bin", "..", ""):
            with pytest.raises(ServiceError, match="is not a plain file name; nothing written"):
                client.download("j1", name, tmp_path / "inner" / "x.bin")
        with pytest.raises(ServiceError, match=r"^job j1 has no artifact 'escape.bin'; it has \.\./escape\.bin$"):
            client.download("j1", "escape.bin", tmp_path / "x.bin")  # the names it has, to pick from
        with pytest.raises(ServiceError, match=r"answered 200 with text/html, not the API's JSON"):
            client.get_job("redirect")  # had surfaced as json's "Expecting value"
        client.get_job("line\nbreak")  # quoted, as any id: it had been a bare InvalidURL
        for dots in (".", ".."):  # a URL drops them: "." had listed every job
            with pytest.raises(ServiceError, match=f"'{dots}' is not an id"):
                client.get_job(dots)
        for call in (client.get_job, client.cancel_job, client.artifacts):  # "" had asked for /v1/jobs/ or /v1/jobs//
            with pytest.raises(ServiceError, match="^'' is not an id$"):
                call("")
        with pytest.raises(ServiceError, match="cannot reach the service"):
            client.request("GET", "/v1/jobs/line\nbreak")  # a path httpx refuses is the client's error too
    assert seen[:2] == ["/v1/jobs/..%2Fscenes", "/v1/sweeps/a%3Fb%23c"] and "/v1/jobs/line%0Abreak" in seen
    assert list(tmp_path.iterdir()) == []  # nothing written anywhere
    with pytest.raises(ValueError, match=r"'http://\[::1' is not a service URL"):
        Client("http://[::1")


# ------------------------------------------------------------------ OBJ uploads, against the API app
@pytest.fixture
def api(tmp_path, monkeypatch):
    """The API app served in-process (embedded broker and SQLite under ``tmp_path``, no worker: ingests run via
    ``service_helpers.ingest``), meshes rendered into 2 views of 32 px: (its URL, its storage folder)."""
    from service_helpers import api_in_thread, reset_service_caches, service_env
    from voxe_service import datasets

    for key, value in service_env(tmp_path).items():
        monkeypatch.setenv(key, value)
    monkeypatch.setattr(datasets, "MESH_VIEWS", 2)
    monkeypatch.setattr(datasets, "MESH_VIEW_SIZE", 32)
    reset_service_caches()
    with api_in_thread() as url:
        yield url, tmp_path / "storage"
    reset_service_caches()


PLANE_OBJ = ("v -1 0 -1\nv 1 0 -1\nv 1 0 1\nv -1 0 1\nvt 0.5 0.5\nusemtl skin\n"  # seen from above, one texel
             "f 1/1 2/1 3/1\nf 1/1 3/1 4/1\n")
GREEN = (0, 255, 0)


def _ingested(scene_id: str, storage) -> tuple[dict, object]:
    """The scene's ingest run here: its stored archive's mesh/ files ({name: bytes}) and its views' surface
    colours (N, 3)."""
    import zipfile

    from service_helpers import ingest
    from voxe_core.data import load_scene
    from voxe_service.db import session_scope
    from voxe_service.models import Scene

    assert ingest(scene_id)["state"] == "ready"
    with session_scope() as session:
        key = session.get(Scene, scene_id).storage_key
    with zipfile.ZipFile(storage / key) as archive:
        archive.extractall(storage.parent / "ingested")
        kept = {n.removeprefix("mesh/"): archive.read(n) for n in archive.namelist() if n.startswith("mesh/")}
    views = load_scene(storage.parent / "ingested", "train")
    return kept, views.images[views.alphas > 0.999].numpy()


def test_an_obj_is_uploaded_with_the_mtl_and_texture_it_names_and_arrives_in_colour(api, tmp_path):
    """The .obj had been sent alone: a textured or Kd-coloured OBJ arrived grey. Its .mtl paints it red (Kd) but
    names a green texture (map_Kd), which the service's ingest applies."""
    from PIL import Image

    url, storage = api
    (tmp_path / "assets").mkdir()
    (tmp_path / "assets" / "plane.obj").write_text("mtllib materials/plane.mtl\n" + PLANE_OBJ)  # found by base name
    (tmp_path / "assets" / "plane.mtl").write_text("newmtl skin\nKd 1 0 0\nmap_Kd C:\\export\\grass.png\n")
    Image.new("RGB", (2, 2), GREEN).save(tmp_path / "assets" / "grass.png")
    with Client(url) as client:
        scene = client.upload_scene(tmp_path / "assets" / "plane.obj", name="plane")
    kept, surface = _ingested(scene["id"], storage)
    assert json.loads(kept["names.json"]) == {"mesh.obj": "plane.obj", "plane.mtl": "plane.mtl",
                                              "texture.png": "grass.png"}
    assert kept["mesh.obj"] == (tmp_path / "assets" / "plane.obj").read_bytes()
    assert kept["texture.png"] == (tmp_path / "assets" / "grass.png").read_bytes()
    assert len(surface) > 0 and abs(surface - [0, 1, 0]).max() < 0.01


def test_submit_texture_colours_an_obj_without_a_library(api, tmp_path, capsys):
    """``voxe submit --upload X.obj --texture IMAGE``: the image colours the OBJ at its UVs, as mesh-to-grid's."""
    from PIL import Image

    from voxe_core.cli import main
    from voxe_service.db import session_scope
    from voxe_service.models import Job

    url, storage = api
    (tmp_path / "plane.obj").write_text(PLANE_OBJ)
    Image.new("RGB", (2, 2), GREEN).save(tmp_path / "green.png")
    assert main(["submit", "a plane of grass", "--upload", str(tmp_path / "plane.obj"), "--texture",
                 str(tmp_path / "green.png"), "--api", url]) == 0
    job_id = capsys.readouterr().out.strip()
    with session_scope() as session:
        scene_id = session.get(Job, job_id).scene_id
    kept, surface = _ingested(scene_id, storage)
    assert json.loads(kept["names.json"]) == {"mesh.obj": "plane.obj", "texture.png": "green.png"}
    assert len(surface) > 0 and abs(surface - [0, 1, 0]).max() < 0.01
    assert main(["submit", "x", "--scene", scene_id, "--texture", str(tmp_path / "green.png"), "--api", url]) == 2
    assert "--texture goes with --upload (an OBJ or a PLY)" in capsys.readouterr().err
    (tmp_path / "notes.txt").write_text("not a texture")  # the service keeps only a texture it reads: said first
    assert main(["submit", "x", "--upload", str(tmp_path / "plane.obj"), "--texture", str(tmp_path / "notes.txt"),
                 "--api", url]) == 2
    assert "texture notes.txt: send it as one of .png, .jpg, .jpeg" in capsys.readouterr().err


def test_a_meshs_up_axis_and_shading_are_sent_by_the_client_and_voxe_submit(api, tmp_path, capsys):
    """``POST /v1/scenes`` takes ``mesh_up_axis`` and ``mesh_shading``, but neither ``upload_scene`` nor ``voxe submit
    --upload`` could send them: a CAD or scanner mesh (z up) was ingested lying on its side, and a coloured one could
    not be baked. They go as the form fields (the stored mesh's options say them), none where not given (the
    service's defaults); --up and --shading without --upload are refused."""
    import zipfile

    from voxe_core.cli import main
    from voxe_service.datasets import MESH_OPTIONS
    from voxe_service.db import session_scope
    from voxe_service.models import Job, Scene

    url, storage = api
    (tmp_path / "plane.obj").write_text(PLANE_OBJ)

    def options(scene_id: str) -> dict:
        with session_scope() as session:
            key = session.get(Scene, scene_id).storage_key
        with zipfile.ZipFile(storage / key) as archive:
            return json.loads(archive.read(f"mesh/{MESH_OPTIONS}"))

    assert main(["submit", "a plane of gold", "--upload", str(tmp_path / "plane.obj"), "--up", "z", "--shading",
                 "baked", "--api", url]) == 0
    with session_scope() as session:
        scene_id = session.get(Job, capsys.readouterr().out.strip()).scene_id
    assert {k: options(scene_id)[k] for k in ("up_axis", "shading")} == {"up_axis": "z", "shading": "baked"}
    with Client(url) as client:
        default = client.upload_scene(tmp_path / "plane.obj")["id"]
        assert {k: options(default)[k] for k in ("up_axis", "shading")} == {"up_axis": "y", "shading": "auto"}
        assert options(client.upload_scene(tmp_path / "plane.obj", mesh_up_axis="x")["id"])["up_axis"] == "x"
    for option in (["--up", "z"], ["--shading", "none"]):
        assert main(["submit", "x", "--scene", scene_id, *option, "--api", url]) == 2
        assert f"{option[0]} goes with --upload (an OBJ or a PLY)" in capsys.readouterr().err


def test_an_obj_naming_missing_files_goes_without_them_and_one_naming_too_many_textures_is_refused(api, tmp_path,
                                                                                                  capsys):
    """Files an OBJ names but that are not beside it are said (the OBJ goes without them, as before they were looked
    for); more textures than the service takes are refused before anything is sent."""
    from PIL import Image

    from voxe_client.client import MissingCompanionWarning, obj_upload_files
    from voxe_core.cli import main
    from voxe_service.db import session_scope
    from voxe_service.models import Job

    url, storage = api
    obj = tmp_path / "plane.obj"
    obj.write_text("mtllib plane.mtl\n" + PLANE_OBJ)
    with pytest.warns(MissingCompanionWarning, match=f"^plane.obj names the material library 'plane.mtl' \\(mtllib\\), "
                                                     f"not found in {tmp_path}: the OBJ goes without it, uncoloured"):
        assert obj_upload_files(obj) == [obj]
    (tmp_path / "plane.mtl").write_text("newmtl a\nmap_Kd a.png\nnewmtl b\nmap_kd b b.png\nnewmtl c\nmap_Kd -s 2 2 1 a.png\n")
    with pytest.warns(MissingCompanionWarning) as said:  # none found: the library's Kd colours it
        assert obj_upload_files(obj) == [obj, tmp_path / "plane.mtl"]
    assert str(said[0].message) == (
        f"plane.mtl names textures not found in {tmp_path} (map_Kd): 'a.png', 'b b.png', '-s 2 2 1 a.png'; the OBJ "
        "goes without, coloured by the library's Kd alone (put them beside the OBJ; map_Kd options such as -s are "
        "not read: write the file name alone)")
    Image.new("RGB", (2, 2), GREEN).save(tmp_path / "a.png")
    with pytest.raises(FileNotFoundError) as some:  # some found: that one would colour the others' parts too
        obj_upload_files(obj)
    assert str(some.value) == (
        f"plane.mtl names textures not found in {tmp_path} (map_Kd): 'b b.png', '-s 2 2 1 a.png'; sent without them, "
        "the texture found would colour every part (put them beside the OBJ; map_Kd options such as -s are not "
        "read: write the file name alone)")
    (tmp_path / "plane.mtl").write_text("newmtl a\nmap_Kd a.png\nnewmtl b\nmap_kd b b.png\n")
    Image.new("RGB", (2, 2), GREEN).save(tmp_path / "b b.png")
    with Client(url) as client, pytest.raises(ValueError, match=r"^plane.mtl names 2 textures \('a.png', 'b b.png'\); "
                                                               "the service takes one texture per OBJ"):
        client.upload_scene(obj)
    with Client(url) as client, pytest.raises(ValueError, match=r"a texture goes with a mesh upload \(.obj or .ply\); "
                                                               "x.zip is neither"):
        client.upload_scene(tmp_path / "x.zip", texture=tmp_path / "a.png")
    assert not storage.exists() or not any(p.is_file() for p in storage.rglob("*"))
    (tmp_path / "plane.mtl").unlink()
    assert main(["submit", "a plane", "--upload", str(obj), "--api", url]) == 0
    out, err = capsys.readouterr()
    assert err.count("voxe submit: warning: plane.obj names the material library 'plane.mtl' (mtllib), not found "
                     "in") == 1  # once, though the files are looked for before the service is asked and as sent
    with session_scope() as session:
        scene_id = session.get(Job, out.strip()).scene_id
    kept, _ = _ingested(scene_id, storage)
    assert json.loads(kept["names.json"]) == {"mesh.obj": "plane.obj"}


PLANE_PLY = ("ply\nformat ascii 1.0\ncomment TextureFile {texture}\nelement vertex 4\nproperty float x\n"
             "property float y\nproperty float z\nproperty float s\nproperty float t\nelement face 2\n"
             "property list uchar int vertex_indices\nend_header\n-1 0 -1 0.5 0.5\n1 0 -1 0.5 0.5\n1 0 1 0.5 0.5\n"
             "-1 0 1 0.5 0.5\n3 0 1 2\n3 0 2 3\n")


def test_a_mesh_naming_files_outside_its_folder_does_not_send_them(tmp_path):
    """An OBJ or its .mtl naming a file out of the mesh's folder (``mtllib /home/me/.aws/credentials.mtl``,
    ``map_Kd ../../private/photo.png``: a mesh downloaded from elsewhere) had had that file of the user's uploaded
    to the service with it: such a name is looked for in the mesh's folder by its base name, as a Windows path's is,
    else the mesh goes without it (said); a subfolder of the mesh's folder is found as written."""
    from PIL import Image

    from voxe_client.client import MissingCompanionWarning, obj_upload_files, ply_upload_files

    private, mesh = tmp_path / "private", tmp_path / "downloads" / "mesh"
    private.mkdir()
    (mesh / "textures").mkdir(parents=True)
    (private / "secret.mtl").write_text("newmtl a\nKd 1 0 0\n")
    Image.new("RGB", (2, 2), GREEN).save(private / "photo.png")
    obj = mesh / "plane.obj"
    for library in (private / "secret.mtl", "../../private/secret.mtl"):
        obj.write_text(f"mtllib {library}\n" + PLANE_OBJ)
        with pytest.warns(MissingCompanionWarning, match="names the material library .* not found in"):
            assert obj_upload_files(obj) == [obj]
    (mesh / "plane.mtl").write_text("newmtl a\nmap_Kd ../../private/photo.png\n")
    obj.write_text("mtllib plane.mtl\n" + PLANE_OBJ)
    with pytest.warns(MissingCompanionWarning, match="names textures not found in"):
        assert obj_upload_files(obj) == [obj, mesh / "plane.mtl"]
    ply = mesh / "plane.ply"
    ply.write_text(PLANE_PLY.format(texture=private / "photo.png"))
    with pytest.warns(MissingCompanionWarning, match="not found in"):
        assert ply_upload_files(ply) == [ply]
    Image.new("RGB", (2, 2), GREEN).save(mesh / "textures" / "photo.png")
    (mesh / "plane.mtl").write_text("newmtl a\nmap_Kd textures/photo.png\n")
    assert obj_upload_files(obj) == [obj, mesh / "plane.mtl", mesh / "textures" / "photo.png"]
    Image.new("RGB", (2, 2), GREEN).save(mesh / "photo.png")  # by its base name, beside the mesh: that one
    assert ply_upload_files(ply) == [ply, mesh / "photo.png"]


def test_a_ply_is_uploaded_with_the_texture_its_header_names_and_arrives_in_colour(api, tmp_path, capsys):
    """The .ply had been sent alone (and a texture given with it refused): a textured PLY arrived uncoloured. The
    image its ``comment TextureFile`` names goes with it, or ``--texture``'s instead; one not found is said."""
    from PIL import Image

    from voxe_client.client import MissingCompanionWarning, ply_upload_files
    from voxe_core.cli import main
    from voxe_service.db import session_scope
    from voxe_service.models import Job

    url, storage = api
    ply = tmp_path / "plane.ply"
    ply.write_text(PLANE_PLY.format(texture="C:\\export\\grass.png"))  # found by its base name
    with pytest.warns(MissingCompanionWarning) as said:
        assert ply_upload_files(ply) == [ply]
    assert str(said[0].message) == (f"plane.ply names the texture 'C:\\\\export\\\\grass.png' (comment TextureFile), not "
                                    f"found in {tmp_path}: the PLY goes without it (put it beside the PLY)")
    Image.new("RGB", (2, 2), GREEN).save(tmp_path / "grass.png")
    assert ply_upload_files(ply) == [ply, tmp_path / "grass.png"]
    with Client(url) as client:
        scene = client.upload_scene(ply, name="plane")
    kept, surface = _ingested(scene["id"], storage)
    assert json.loads(kept["names.json"]) == {"mesh.ply": "plane.ply", "texture.png": "grass.png"}
    assert len(surface) > 0 and abs(surface - [0, 1, 0]).max() < 0.01
    Image.new("RGB", (2, 2), (255, 0, 0)).save(tmp_path / "red.png")  # --texture instead of the one it names
    assert main(["submit", "a red plane", "--upload", str(ply), "--texture", str(tmp_path / "red.png"),
                 "--api", url]) == 0
    with session_scope() as session:
        scene_id = session.get(Job, capsys.readouterr().out.strip()).scene_id
    kept, surface = _ingested(scene_id, storage)
    assert json.loads(kept["names.json"]) == {"mesh.ply": "plane.ply", "texture.png": "red.png"}
    assert len(surface) > 0 and abs(surface - [1, 0, 0]).max() < 0.01
    ply.write_text(PLANE_PLY.format(texture="notes.txt"))
    (tmp_path / "notes.txt").write_text("not a texture")  # refused before anything is sent, as an OBJ's
    with pytest.raises(ValueError, match="^texture notes.txt: send it as one of .png"):
        ply_upload_files(ply)
    coloured = tmp_path / "coloured.ply"  # vertex colours, no texture coordinates: the image it names stays (the
    coloured.write_text(PLANE_PLY.format(texture="grass.png").replace(  # service refuses an image it cannot map)
        "property float s\nproperty float t", "property uchar red\nproperty uchar green\nproperty uchar blue")
        .replace(" 0.5 0.5\n", " 0 255 0\n"))
    with pytest.warns(MissingCompanionWarning) as said:
        assert ply_upload_files(coloured) == [coloured]
    assert str(said[0].message) == ("coloured.ply names the texture 'grass.png' (comment TextureFile) but declares no "
                                    "texture coordinates to map it with: the PLY goes without it (its vertex or face "
                                    "colours)")
    with pytest.warns(MissingCompanionWarning), Client(url) as client:
        scene = client.upload_scene(coloured)
    kept, surface = _ingested(scene["id"], storage)
    assert json.loads(kept["names.json"]) == {"mesh.ply": "coloured.ply"}
    assert len(surface) > 0 and abs(surface - [0, 1, 0]).max() < 0.01


def test_a_submit_refused_deletes_the_scene_it_uploaded_and_no_other(api, tmp_path, capsys):
    """``voxe submit --upload`` whose job the service refuses (4xx) had left the scene it had just uploaded behind,
    unnamed in the error; one given with --scene was there before and stays."""
    from voxe_core.cli import main

    url, _ = api
    (tmp_path / "plane.obj").write_text(PLANE_OBJ)
    # (refused for the scene's images, 32 px; params refused on any scene upload nothing)
    bad = ["--params", '{"downsample": 64}', "--api", url]
    assert main(["submit", "a plane", "--upload", str(tmp_path / "plane.obj"), *bad]) == 2
    err = capsys.readouterr().err
    scene_id = err.split("scene ", 1)[1].split()[0]
    assert "HTTP 422" in err and f"the scene {scene_id} this command uploaded is deleted" in err
    with Client(url) as client:
        assert client.request("GET", "/v1/scenes")["items"] == []
        kept = client.upload_scene(tmp_path / "plane.obj")["id"]
        assert main(["submit", "a plane", "--scene", kept, *bad]) == 2
        assert "HTTP 422" in capsys.readouterr().err
        assert [scene["id"] for scene in client.request("GET", "/v1/scenes")["items"]] == [kept]


def test_submit_and_sweep_run_again_with_their_idempotency_key_make_one(api, tmp_path, capsys):
    """``voxe submit`` and ``voxe sweep`` had sent a new key each run, so a script running one again after a failure
    made a second job. With ``--idempotency-key`` a run again answers with what the first made; the key the job
    refused (bad params) made nothing, and the scene it uploaded stays for the run that fixes them: it may be an
    earlier run's, whose job deleting it would take too."""
    from voxe_core.cli import main

    url, _ = api
    (tmp_path / "plane.obj").write_text(PLANE_OBJ)
    submit = ["submit", "a plane of gold", "--upload", str(tmp_path / "plane.obj"), "--api", url,
              "--idempotency-key", "nightly-7"]
    assert main([*submit, "--params", '{"downsample": 64}']) == 2  # (past the scene's images, 32 px)
    err = capsys.readouterr().err
    scene_id = err.split("scene ", 1)[1].split()[0]
    assert "HTTP 422" in err and err.endswith(f"the scene {scene_id} stays: a run with --idempotency-key 'nightly-7' "
                                              f"takes it up again, as --scene {scene_id} does\n")
    runs = []
    for _ in range(2):
        assert main(submit) == 0
        runs.append(capsys.readouterr().out.strip())
    assert main(["submit", "a plane of tin", *submit[2:]]) == 2
    assert "Idempotency-Key 'nightly-7' was already used with a different request body" in capsys.readouterr().err
    with Client(url) as client:
        assert [scene["id"] for scene in client.request("GET", "/v1/scenes")["items"]] == [scene_id]
        assert [job["id"] for job in client.request("GET", "/v1/jobs")["items"]] == runs[:1] and runs[0] == runs[1]
        assert client.get_job(runs[0])["scene_id"] == scene_id
    sweep = ["sweep", "--scene", f"{scene_id}=plane", "--api", url, "--idempotency-key", "nightly-7"]
    sweeps = []
    for _ in range(2):
        assert main(sweep) == 0
        sweeps.append(capsys.readouterr().out.strip())
    with Client(url) as client:
        assert sweeps[0] == sweeps[1] and len(client.request("GET", "/v1/jobs", params={"limit": 200})["items"]) == \
            1 + 2 * len(client.get_sweep(sweeps[0])["entries"])


def test_an_idempotency_key_is_sent_as_utf8_and_one_no_header_carries_is_refused_naming_it(api, tmp_path, capsys):
    """The service takes a key of UTF-8 text, but the client had sent headers as ASCII: ``--idempotency-key clé``
    failed with "'ascii' codec can't encode characters"; a key with a line break had been said as "cannot reach the
    service" (exit 3, for a script: try again later)."""
    from voxe_core.cli import main

    url, _ = api
    (tmp_path / "plane.obj").write_text(PLANE_OBJ)
    submit = ["submit", "a plane of gold", "--upload", str(tmp_path / "plane.obj"), "--api", url]
    jobs = []
    for _ in range(2):
        assert main([*submit, "--idempotency-key", "clé du soir"]) == 0
        jobs.append(capsys.readouterr().out.strip())
    assert jobs[0] == jobs[1]
    assert main([*submit, "--idempotency-key", "run\n7"]) == 2
    assert capsys.readouterr().err == ("voxe submit: error: Idempotency-Key 'run\\n7' cannot be sent: a header "
                                       "carries no line break, NUL or other whitespace than spaces and tabs\n")
    with Client(url) as client:
        assert len(client.request("GET", "/v1/scenes")["items"]) == 1
        assert [job["id"] for job in client.request("GET", "/v1/jobs")["items"]] == jobs[:1]


def _voxe_in_a_process(*argv: str) -> tuple[subprocess.CompletedProcess, set[str]]:
    """``voxe ARGV`` run as its own process (``python -m voxe_core.cli``): what it ended with, its stderr without
    the lines of ``-X importtime``, and the modules it imported (those lines' names)."""
    result = subprocess.run([sys.executable, "-X", "importtime", "-m", "voxe_core.cli", *argv], cwd=REPO,
                            capture_output=True, text=True, timeout=120)
    lines = result.stderr.splitlines(keepends=True)
    imported = {line.rsplit("|", 1)[1].strip() for line in lines if line.startswith("import time:")}
    result.stderr = "".join(line for line in lines if not line.startswith("import time:"))
    return result, imported


def test_the_service_commands_talk_to_the_service_without_loading_torch(api, tmp_path):
    """Every ``voxe`` command had imported torch as it started (its error handling imported the library's dataset
    and tensor-file modules), so ``voxe status`` took seconds; the commands that only talk to the service load
    neither torch nor the library's stages, and answer as before."""
    url, _ = api
    (tmp_path / "plane.obj").write_text(PLANE_OBJ)
    with Client(url) as client:
        scene_id = client.upload_scene(tmp_path / "plane.obj")["id"]
    service = ["--api", url]
    submitted, imported = _voxe_in_a_process("submit", "a plane of gold", "--scene", scene_id, *service)
    assert submitted.returncode == 0, submitted.stderr
    job_id = submitted.stdout.strip()
    assert "torch" not in imported and "voxe_core.data" not in imported and "voxe_client" in imported
    said = {}
    for argv in (["status", job_id], ["cancel", job_id], ["wait", job_id, "--quiet"],
                 ["download", job_id, "--out", str(tmp_path / "artifacts")], ["sweep", "--scene", f"{scene_id}=plane"],
                 ["webhook-secret"]):
        result, imported = _voxe_in_a_process(*argv, *service)
        said[argv[0]] = result.returncode, "torch" in imported, result.stdout
    assert {command: said[command][:2] for command in said} == {
        "status": (0, False), "cancel": (0, False), "wait": (1, False), "download": (0, False), "sweep": (0, False),
        "webhook-secret": (0, False)}
    assert json.loads(said["status"][2])["id"] == job_id and json.loads(said["wait"][2])["state"] == "canceled"
    refused, imported = _voxe_in_a_process("status", job_id, "--api", "http://127.0.0.1:9")
    assert (refused.returncode, "torch" in imported) == (3, False)
    assert refused.stderr == "voxe status: error: cannot reach the service at http://127.0.0.1:9: [Errno 111] " \
                             "Connection refused\n"


class _LosingAnswers(httpx.HTTPTransport):
    """The network between client and service, losing the answers ``lose`` lists per ``METHOD path`` (in turn) once
    the service has acted: "drop" as a connection reset, a status as a proxy's page; ``sent`` is each request's call
    and Idempotency-Key."""

    def __init__(self, lose: dict[str, list]):
        super().__init__()
        self.lose, self.sent = lose, []

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        response = super().handle_request(request)
        call = f"{request.method} {request.url.path}"
        self.sent.append((call, request.headers.get("idempotency-key")))
        if not self.lose.get(call):
            return response
        response.read()
        response.close()
        lost = self.lose[call].pop(0)
        if lost == "drop":
            raise httpx.ReadError("connection reset by peer", request=request)
        return httpx.Response(lost, text="<html>bad gateway</html>")


def test_a_submission_whose_answer_is_lost_is_sent_again_with_its_key_and_makes_one(api, tmp_path, monkeypatch):
    """An upload, job or sweep whose answer a dropped connection or a proxy's 502 / 504 lost had been an error, the
    service having made it all the same (a script trying again made a second): each goes with an Idempotency-Key and
    is sent again with it (an upload's files read again whole), and the service answers with what it made first. A
    key the caller gives makes its repeated call answer so too."""
    import voxe_client.client as client_module

    monkeypatch.setattr(client_module.time, "sleep", lambda _s: None)
    url, _ = api
    (tmp_path / "plane.obj").write_text(PLANE_OBJ)
    network = _LosingAnswers({"POST /v1/scenes": ["drop"], "POST /v1/jobs": [502, "drop"], "POST /v1/sweeps": [504]})
    with Client(url, transport=network) as client:
        scene = client.upload_scene(tmp_path / "plane.obj", name="plane")
        job = client.create_job(scene["id"], "a plane of gold")
        sweep = client.create_sweep([{"scene_id": scene["id"], "object": "plane"}])
        assert [s["id"] for s in client.request("GET", "/v1/scenes")["items"]] == [scene["id"]]
        jobs = client.request("GET", "/v1/jobs", params={"limit": 200})  # one job, one sweep's edits and evaluations
        assert jobs["total"] == 1 + 2 * len(sweep["entries"]) and job["id"] in [j["id"] for j in jobs["items"]]
        assert client.create_job(scene["id"], "a plane of wood", idempotency_key="run-7")["id"] == \
            client.create_job(scene["id"], "a plane of wood", idempotency_key="run-7")["id"]
        with pytest.raises(ServiceError, match="Idempotency-Key 'run-7' was already used with a different request"):
            client.create_job(scene["id"], "a plane of tin", idempotency_key="run-7")
    keys = {call: [key for sent, key in network.sent if sent == call]
            for call in ("POST /v1/scenes", "POST /v1/jobs", "POST /v1/sweeps")}
    upload, (first, again, third, *_), sweeps = keys.values()
    assert len(upload) == 2 and len(set(upload)) == 1 and None not in upload
    assert first == again == third and len(sweeps) == 2 and len(set(sweeps)) == 1
    assert len({upload[0], first, sweeps[0]}) == 3  # one key per submission


def _job_with_a_grid_artifact(url: str, tmp_path: Path) -> tuple[dict, bytes]:
    """A job made through the API at ``url`` on an uploaded plane, with a 1,024,000-byte ``grid.npz`` artifact
    recorded; the job and the artifact's bytes."""
    from voxe_service.db import session_scope
    from voxe_service.models import Artifact
    from voxe_service.storage import get_storage

    (tmp_path / "plane.obj").write_text(PLANE_OBJ)
    data = bytes(range(256)) * 4000
    with Client(url) as client:
        job = client.create_job(client.upload_scene(tmp_path / "plane.obj")["id"], "a plane of gold")
    stored = get_storage().put_bytes(f"jobs/{job['id']}/grid.npz", data)
    with session_scope() as session:
        session.add(Artifact(job_id=job["id"], name="grid.npz", key=stored.key, size=stored.size, sha256=stored.sha256,
                             content_type="application/octet-stream", kind="grid"))
    return job, data


class _CutStream(httpx.SyncByteStream):
    """A response body the connection drops after ``keep`` bytes."""

    def __init__(self, inner: httpx.SyncByteStream, keep: int):
        self.inner, self.keep = inner, keep

    def __iter__(self):
        for chunk in self.inner:
            yield chunk[:self.keep]
            self.keep -= len(chunk)
            if self.keep < 0:
                raise httpx.ReadError("connection reset by peer")

    def close(self) -> None:
        self.inner.close()


def test_voxe_download_broken_off_goes_on_from_the_service_where_it_stopped(api, tmp_path, monkeypatch):
    """Against the API app: a download whose connection drops mid-way is resumed with the Range and If-Range the
    service serves a 206 for, and lands whole (``voxe download`` had failed it, exit 3, the bytes thrown away); and
    one whose service then stopped answering (exit 3) goes on from its part file at the next ``voxe download``."""
    import hashlib

    import voxe_core.cli.service as service_commands
    from voxe_core.cli import main

    url, _ = api
    job, data = _job_with_a_grid_artifact(url, tmp_path)
    sent = []

    class Cutting(httpx.HTTPTransport):
        def handle_request(self, request: httpx.Request) -> httpx.Response:
            response = super().handle_request(request)
            if request.url.path.endswith("/grid.npz"):
                sent.append((request.headers.get("range"), response.status_code))
                if len(sent) == 1:
                    response.stream = _CutStream(response.stream, 300_000)
            return response

    monkeypatch.setattr(service_commands, "_client", lambda args: Client(args.api, transport=Cutting()))
    assert main(["download", job["id"], "--out", str(tmp_path / "out"), "--api", url, "--quiet"]) == 0
    assert (tmp_path / "out" / "grid.npz").read_bytes() == data
    assert sent[0] == (None, 200) and sent[1][1] == 206 and sent[1][0].startswith("bytes=")
    assert 0 < int(sent[1][0].removeprefix("bytes=").rstrip("-")) <= 300_000  # went on, not over

    import voxe_client.client as client_module

    class CutThenDown(Cutting):  # the service stops answering after the cut: the run fails
        def handle_request(self, request: httpx.Request) -> httpx.Response:
            if sent and request.url.path.endswith("/grid.npz"):
                raise httpx.ConnectError("connection refused")
            return super().handle_request(request)

    class Recording(httpx.HTTPTransport):
        def handle_request(self, request: httpx.Request) -> httpx.Response:
            response = super().handle_request(request)
            if request.url.path.endswith("/grid.npz"):
                sent.append((request.headers.get("range"), response.status_code))
            return response

    monkeypatch.setattr(client_module.time, "sleep", lambda _s: None)
    out = tmp_path / "again"
    for transport, exit_status in ((CutThenDown, 3), (Recording, 0)):  # two runs
        sent.clear()
        monkeypatch.setattr(service_commands, "_client",
                            lambda args, made=transport: Client(args.api, transport=made()))
        assert main(["download", job["id"], "--out", str(out), "--api", url, "--quiet"]) == exit_status
        if exit_status:
            part = out / f".grid.npz.{hashlib.sha256(data).hexdigest()[:16]}.part"
            kept = part.stat().st_size
            assert sent == [(None, 200)] and 0 < kept <= 300_000 and not (out / "grid.npz").exists()
    assert sent == [(f"bytes={kept}-", 206)] and (out / "grid.npz").read_bytes() == data and not part.exists()


@pytest.mark.parametrize("cut", [False, True], ids=["before-its-first-byte", "before-its-resume"])
def test_a_download_of_an_artifact_replaced_since_its_listing_lands_the_new_version_checked(cut, api, tmp_path,
                                                                                            monkeypatch):
    """Against the API app: preview.png republished (a running job's next stage) after ``download()`` read the
    listing, before its GET or before the GET resuming it: the service served the new version whole (no If-Range,
    or one naming the old ETag), and checked against the old listing it failed as a body "past the 500000 bytes the
    artifact is listed with" (a larger version; a broken proxy's or hostile service's, the message says) or as bytes
    whose sha256 is not the listed one, as if they had come corrupted (``voxe download`` of a running job, as it
    allows, met it). The answer's ETag says which version it is: the listing is read again and
    the new version lands, checked against it, no part file left."""
    import hashlib

    import voxe_client.client as client_module
    from worker.runtime import publish_artifact

    url, _ = api
    (tmp_path / "plane.obj").write_text(PLANE_OBJ)
    with Client(url) as client:
        job = client.create_job(client.upload_scene(tmp_path / "plane.obj")["id"], "a plane of gold")
    old, new = tmp_path / "old.png", tmp_path / "new.png"
    old.write_bytes(b"A" * 500_000)
    new.write_bytes(b"B" * 600_000)
    publish_artifact(job["id"], "preview.png", old, "preview")
    sent = []

    class Republishing(httpx.HTTPTransport):
        def handle_request(self, request: httpx.Request) -> httpx.Response:
            if request.url.path.endswith("/preview.png") and len(sent) == cut:
                publish_artifact(job["id"], "preview.png", new, "preview")
            response = super().handle_request(request)
            if request.url.path.endswith("/preview.png"):
                sent.append((request.headers.get("range"), response.status_code))
                if cut and len(sent) == 1:
                    response.stream = _CutStream(response.stream, 300_000)
            return response

    monkeypatch.setattr(client_module.time, "sleep", lambda _s: None)
    with Client(url, transport=Republishing()) as client:
        landed = client.download(job["id"], "preview.png", tmp_path / "out" / "preview.png")
    assert landed.read_bytes() == new.read_bytes()
    assert hashlib.sha256(landed.read_bytes()).hexdigest() == hashlib.sha256(new.read_bytes()).hexdigest()
    # the new version answered whole (to its If-Range too), then once more, asked as the new listing names it
    assert sent == ([(None, 200), ("bytes=300000-", 200), (None, 200)] if cut else [(None, 200), (None, 200)])
    assert sorted(path.name for path in (tmp_path / "out").iterdir()) == ["preview.png"]  # no part file left


def test_a_download_of_an_artifact_replaced_each_time_it_is_listed_says_so_and_keeps_nothing(api, tmp_path):
    """One republished before each of its GETs (faster than it downloads) fails after :data:`REPLACED_TRIES`
    listings, saying it was replaced, no part file left."""
    from voxe_client.client import REPLACED_TRIES
    from worker.runtime import publish_artifact

    url, _ = api
    (tmp_path / "plane.obj").write_text(PLANE_OBJ)
    with Client(url) as client:
        job = client.create_job(client.upload_scene(tmp_path / "plane.obj")["id"], "a plane of gold")
    version = tmp_path / "version.png"
    version.write_bytes(b"0" * 1000)
    publish_artifact(job["id"], "preview.png", version, "preview")
    sent = []

    class Republishing(httpx.HTTPTransport):
        def handle_request(self, request: httpx.Request) -> httpx.Response:
            if request.url.path.endswith("/preview.png"):
                sent.append(request.headers.get("range"))
                version.write_bytes(str(len(sent)).encode() * 1000)
                publish_artifact(job["id"], "preview.png", version, "preview")
            return super().handle_request(request)

    with Client(url, transport=Republishing()) as client, pytest.raises(
            ServiceError, match=f"answered 200 with ETag .*, not the listed sha256 [0-9a-f]{{64}}: the artifact was "
                                f"replaced {REPLACED_TRIES} times as it downloaded; nothing kept"):
        client.download(job["id"], "preview.png", tmp_path / "out" / "preview.png")
    assert sent == [None] * REPLACED_TRIES and list((tmp_path / "out").iterdir()) == []


def test_a_download_of_an_artifact_stored_shorter_than_listed_says_it_is_damaged_at_once(api, tmp_path, monkeypatch):
    """Against the API app: preview.png listed at 500,000 bytes, its stored object cut to 300,000. Its body had been
    dropped at byte 300,000 and resumed from there again and again, the error then "cannot download ... " as a
    service out of reach; the service says, before any byte, that the stored artifact is shorter than listed, and the
    error says so after one GET, nothing kept."""
    import voxe_client.client as client_module
    from worker.runtime import publish_artifact

    url, storage = api
    (tmp_path / "plane.obj").write_text(PLANE_OBJ)
    with Client(url) as client:
        job = client.create_job(client.upload_scene(tmp_path / "plane.obj")["id"], "a plane of gold")
    (tmp_path / "preview.png").write_bytes(b"A" * 500_000)
    publish_artifact(job["id"], "preview.png", tmp_path / "preview.png", "preview")
    (stored,) = [path for path in storage.rglob("*preview.png") if path.is_file()]
    stored.write_bytes(b"A" * 300_000)
    sent = []

    class Counting(httpx.HTTPTransport):
        def handle_request(self, request: httpx.Request) -> httpx.Response:
            if request.url.path.endswith("/preview.png"):
                sent.append(request.headers.get("range"))
            return super().handle_request(request)

    monkeypatch.setattr(client_module.time, "sleep", lambda _s: None)
    with Client(url, transport=Counting()) as client, pytest.raises(ServiceError) as failed:
        client.download(job["id"], "preview.png", tmp_path / "out" / "preview.png")
    assert failed.value.status == 500 and str(failed.value).endswith(
        "HTTP 500: artifact 'preview.png' is stored with 300000 bytes, not the 500000 it is listed with: its stored "
        "object is damaged")
    assert sent == [None] and list((tmp_path / "out").iterdir()) == []


def test_a_download_through_a_proxy_rewriting_etags_lands_checked_by_its_bytes(api, tmp_path):
    """A proxy answering with ETags of its own: the listing read again still names the version asked for, so the
    ETag says no version and the bytes' check decides (the download lands, one whole GET more)."""
    url, _ = api
    (tmp_path / "plane.obj").write_text(PLANE_OBJ)
    with Client(url) as client:
        job = client.create_job(client.upload_scene(tmp_path / "plane.obj")["id"], "a plane of gold")
    from worker.runtime import publish_artifact

    (tmp_path / "preview.png").write_bytes(b"P" * 70_000)
    publish_artifact(job["id"], "preview.png", tmp_path / "preview.png", "preview")
    sent = []

    class Rewriting(httpx.HTTPTransport):
        def handle_request(self, request: httpx.Request) -> httpx.Response:
            response = super().handle_request(request)
            if request.url.path.endswith("/preview.png"):
                sent.append((request.headers.get("range"), response.status_code))
                response.headers["etag"] = '"proxy-1"'
            return response

    with Client(url, transport=Rewriting()) as client:
        landed = client.download(job["id"], "preview.png", tmp_path / "out" / "preview.png")
    assert landed.read_bytes() == b"P" * 70_000 and sent == [(None, 200), (None, 200)]


def test_voxe_download_interrupted_says_what_it_kept_and_where_and_the_next_run_goes_on(api, tmp_path, monkeypatch,
                                                                                        capsys):
    """Ctrl-C mid-download: its bytes stay in the hidden part file for the next run (as README says), but ``voxe
    download`` said only "voxe: interrupted", the file and what it holds unsaid (a failure's error names them). It
    says them now, exit 130, and the next run goes on from them with a Range."""
    import hashlib

    import voxe_core.cli.service as service_commands
    from voxe_core.cli import main

    url, _ = api
    job, data = _job_with_a_grid_artifact(url, tmp_path)
    sent = []

    class CtrlC(httpx.SyncByteStream):  # the keyboard's, once 100,000 bytes came
        def __init__(self, inner: httpx.SyncByteStream):
            self.inner = inner

        def __iter__(self):
            got = 0
            for chunk in self.inner:
                for at in range(0, len(chunk), 50_000):
                    yield chunk[at:at + 50_000]
                    got += len(chunk[at:at + 50_000])
                    if got >= 100_000:
                        raise KeyboardInterrupt

        def close(self) -> None:
            self.inner.close()

    class Recording(httpx.HTTPTransport):
        def handle_request(self, request: httpx.Request) -> httpx.Response:
            response = super().handle_request(request)
            if request.url.path.endswith("/grid.npz"):
                sent.append((request.headers.get("range"), response.status_code))
                if len(sent) == 1:
                    response.stream = CtrlC(response.stream)
            return response

    monkeypatch.setattr(service_commands, "_client", lambda args: Client(args.api, transport=Recording()))
    out = tmp_path / "out"
    assert main(["download", job["id"], "--out", str(out), "--api", url, "--quiet"]) == 130
    part = out / f".grid.npz.{hashlib.sha256(data).hexdigest()[:16]}.part"
    kept = part.stat().st_size
    assert 100_000 <= kept < len(data) and not (out / "grid.npz").exists()
    assert capsys.readouterr().err.splitlines()[-1] == (
        f"voxe download: interrupted downloading grid.npz of job {job['id']} ({kept} of {len(data)} bytes here, kept "
        f"in {part} for the next download of it to go on from)")
    assert main(["download", job["id"], "--out", str(out), "--api", url, "--quiet"]) == 0
    assert sent[1] == (f"bytes={kept}-", 206) and (out / "grid.npz").read_bytes() == data and not part.exists()


def test_an_empty_webhook_url_is_sent_and_refused_not_dropped(api, tmp_path, capsys):
    """``voxe submit --webhook-url "$HOOK"`` with HOOK unset had made the job without a webhook, exit 0: an empty
    value was taken for none given. The service refuses it, naming the field."""
    from voxe_core.cli import main

    url, _ = api
    (tmp_path / "plane.obj").write_text(PLANE_OBJ)
    with Client(url) as client:
        scene_id = client.upload_scene(tmp_path / "plane.obj")["id"]
        assert main(["submit", "a plane", "--scene", scene_id, "--webhook-url", "", "--api", url]) == 2
        assert "HTTP 422: body.webhook_url: String should match pattern" in capsys.readouterr().err
        assert client.request("GET", "/v1/jobs")["items"] == []


def _plane_with_loopback_webhooks_allowed(tmp_path, monkeypatch) -> Path:
    """A plane's OBJ written under ``tmp_path``, the service letting webhooks go to loopback addresses."""
    from service_helpers import reset_service_caches

    monkeypatch.setenv("VOXE_WEBHOOK_ALLOW_NETWORKS", "127.0.0.0/8")
    reset_service_caches()
    (tmp_path / "plane.obj").write_text(PLANE_OBJ)
    return tmp_path / "plane.obj"


def test_voxe_submit_sends_the_webhook_events_asked_for(api, tmp_path, monkeypatch, capsys):
    """``POST /v1/jobs`` takes ``webhook_events`` (which events go to the webhook_url), but ``voxe submit`` had no
    option for them: a job submitted with voxe was told only its end. --webhook-event (repeated) sends them; the
    service's refusals name the field (an event it does not send, one without --webhook-url)."""
    from voxe_core.cli import main

    url, _ = api
    plane = _plane_with_loopback_webhooks_allowed(tmp_path, monkeypatch)
    with Client(url) as client:
        scene_id = client.upload_scene(plane)["id"]
        submit = ["submit", "a plane", "--scene", scene_id, "--api", url, "--quiet"]
        hook = ["--webhook-url", "http://127.0.0.1:9/hook"]
        assert main([*submit, *hook, "--webhook-event", "warning", "--webhook-event", "succeeded"]) == 0
        job = client.get_job(capsys.readouterr().out.strip())
        assert (job["webhook_url"], job["webhook_events"]) == ("http://127.0.0.1:9/hook", ["warning", "succeeded"])
        assert main([*submit, *hook]) == 0
        assert client.get_job(capsys.readouterr().out.strip())["webhook_events"] is None
        assert main([*submit, *hook, "--webhook-event", "done"]) == 2
        assert "HTTP 422: body.webhook_events.0: Input should be 'stage_started'" in capsys.readouterr().err
        assert main([*submit, "--webhook-event", "warning"]) == 2
        assert "webhook_events needs a webhook_url to send them to" in capsys.readouterr().err


@pytest.mark.parametrize("options, said", [
    (["--mode", "local"], "--mode local needs --edit-word: the word(s) of the prompt naming the edit"),
    (["--edit-word", "hat"], "--edit-word applies to local edits only (--mode local)"),
    (["--webhook-event", "warning"], "--webhook-event needs a --webhook-url to send the events to")])
def test_a_submit_whose_job_options_the_service_refuses_uploads_nothing(options, said, tmp_path, capsys):
    """``voxe submit P --upload big.zip --mode local`` without --edit-word (or --edit-word without --mode local, or
    --webhook-event without --webhook-url) had uploaded the whole scene, then been refused the job (422) and deleted
    the scene again: options any job is refused for are said before the upload, which is not sent."""
    from voxe_core.cli import main

    (tmp_path / "plane.obj").write_text(PLANE_OBJ)
    assert main(["submit", "a dog wearing a hat", "--upload", str(tmp_path / "plane.obj"), *options,
                 "--api", "http://127.0.0.1:9"]) == 2  # (no service there: an upload tried is exit 3)
    assert capsys.readouterr().err == f"voxe submit: error: {said}; nothing uploaded\n"


def test_submit_and_the_service_refuse_job_options_by_one_set_of_rules():
    """``voxe submit --upload``'s checks before the upload had restated three rules of ``POST /v1/jobs`` in their own
    code, free to drift from the service's: both now read ``presets.broken_job_option_rule``, each saying every rule
    in its own words. Over every mix of the fields, the CLI refuses exactly what the service refuses, for the same
    rule."""
    from pydantic import ValidationError

    from api import schemas
    from voxe_core import presets
    from voxe_core.cli import service

    assert set(schemas.JOB_OPTION_RULES) == set(service.JOB_OPTION_RULES) == set(presets.JOB_OPTION_RULES)
    refused = set()
    for mode, words, url, events in itertools.product(("global", "local"), ([], ["hat"]),
                                                      (None, "https://example.com/hook"), (None, ["warning"])):
        args = argparse.Namespace(mode=mode, edit_word=words, webhook_url=url, webhook_event=events)
        try:
            schemas.JobCreate(scene_id="s", prompt="a dog wearing a hat", mode=mode, edit_words=words,
                              webhook_url=url, webhook_events=events)
        except ValidationError as exc:
            rule = next(r for r, said in schemas.JOB_OPTION_RULES.items() if said in str(exc))
            with pytest.raises(ValueError) as cli:
                service._check_job_options(args)
            assert str(cli.value) == f"{service.JOB_OPTION_RULES[rule]}; nothing uploaded"
            refused.add(rule)
        else:
            service._check_job_options(args)
    assert refused == set(presets.JOB_OPTION_RULES)


@pytest.mark.parametrize("options, said", [
    (["--params", '{"iterations": 10, "colour": 1}'], "body.params.colour: Extra inputs are not permitted"),
    (["--params", '{"iterations": "10"}'], "body.params.iterations: Input should be a valid integer"),
    (["--params", '{"refine": {"iterations": 2147483648}}'],
     "body.params.refine.iterations: Input should be less than or equal to 100000"),
    (["--webhook-url", "http://10.1.2.3/hook"], "webhook_url host '10.1.2.3' resolves to a private address")])
def test_a_submit_whose_job_the_service_refuses_on_any_scene_uploads_nothing(options, said, api, tmp_path, capsys):
    """``voxe submit P --upload big.zip --params '{"colour": 1}'`` (a field the service does not take, a value of
    another type or past its bound; or a webhook URL it will not call) had uploaded the whole scene before the job
    was refused (422) and the scene deleted again: the service checks the job first (``POST /v1/jobs?check=true``),
    its 422 said as it names the field, nothing uploaded; a job it takes is made as before."""
    from voxe_core.cli import main

    url, _ = api
    (tmp_path / "plane.obj").write_text(PLANE_OBJ)
    upload = ["submit", "a plane", "--upload", str(tmp_path / "plane.obj"), "--api", url, "--quiet"]
    assert main([*upload, *options]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"voxe submit: error: POST /v1/jobs: HTTP 422: {said}") and err.endswith("; nothing uploaded\n")
    with Client(url) as client:
        assert client.list_scenes()["total"] == 0 and client.list_jobs()["total"] == 0
        assert main([*upload, "--params", '{"iterations": 10}']) == 0
        job = client.get_job(capsys.readouterr().out.strip())
        assert job["params"]["iterations"] == 10 and client.list_scenes()["total"] == 1


@pytest.mark.parametrize("job_status, delete_status, said, exit_status", [
    (429, 204, "the scene s1 this command uploaded is deleted", 2),
    (429, 409, "the scene s1 this command uploaded stays, its deletion failed (DELETE /v1/scenes/s1: HTTP 409: busy)",
     2),
    (503, None, "the scene s1 this command uploaded stays (use it with --scene s1)", 3),  # the job may have been made
])
def test_a_submit_not_taken_says_what_became_of_the_scene_it_uploaded(job_status, delete_status, said, exit_status,
                                                                       tmp_path, monkeypatch, capsys):
    """A refused job's scene is deleted, or said to stay when that fails; a job the service may have made (5xx, or
    no answer, after the submission's retries) keeps its scene, named for --scene, and exits as a service that
    failed."""
    import voxe_client.client as client_module
    import voxe_core.cli.service as service
    from voxe_core.cli import main

    monkeypatch.setattr(client_module.time, "sleep", lambda _s: None)
    sent = []

    def answer(request: httpx.Request) -> httpx.Response:
        sent.append(f"{request.method} {request.url.path}")
        if request.method == "POST" and request.url.path == "/v1/scenes":
            return httpx.Response(201, json={"id": "s1", "state": "processing"})
        if request.method == "POST" and request.url.params.get("check") == "true":
            return httpx.Response(204)  # (checked before the upload, as the service does)
        if request.method == "POST":
            return httpx.Response(job_status, json={"detail": "not now"})
        return httpx.Response(delete_status, json={"detail": "busy"} if delete_status == 409 else None)

    monkeypatch.setattr(service, "_client", lambda args: Client(transport=httpx.MockTransport(answer)))
    (tmp_path / "plane.obj").write_text(PLANE_OBJ)
    assert main(["submit", "a plane", "--upload", str(tmp_path / "plane.obj")]) == exit_status
    assert capsys.readouterr().err.endswith(f"HTTP {job_status}: not now; {said}\n")
    retried = client_module.DEFAULT_RETRIES if job_status == 503 else 0
    assert sent == (["POST /v1/jobs", "POST /v1/scenes"] + ["POST /v1/jobs"] * (1 + retried)
                    + ["DELETE /v1/scenes/s1"] * (delete_status is not None))


def test_voxe_sweep_that_cannot_write_its_out_file_keeps_the_earlier_one(tmp_path, monkeypatch, fill_disk, capsys):
    """A full disk while ``voxe sweep --out`` wrote the summary had left it torn, the earlier one destroyed: it is
    written whole or not at all."""
    import voxe_core.cli.service
    from voxe_core.cli import main

    sweeps = iter(["s1", "s2"])

    def answer(request: httpx.Request) -> httpx.Response:
        return httpx.Response(201, json={"id": next(sweeps), "state": "queued", "entries": [], "counts": {},
                                         "table": ""})

    monkeypatch.setattr(voxe_core.cli.service, "_client",
                        lambda args: Client("http://svc.test/", transport=httpx.MockTransport(answer)))
    out = tmp_path / "sweep.json"
    assert main(["sweep", "--scene", "a=mic", "--out", str(out)]) == 0
    fill_disk()
    assert main(["sweep", "--scene", "a=mic", "--out", str(out)]) == 1  # a full disk: the machine's failure
    assert "No space left on device" in capsys.readouterr().err
    assert json.loads(out.read_text())["id"] == "s1" and [p.name for p in tmp_path.iterdir()] == ["sweep.json"]


@pytest.mark.parametrize("change, now", [("shrinks", 10), ("grows", len(PLANE_OBJ) + 5000)])
def test_an_upload_whose_file_changes_as_it_is_sent_names_the_file(change, now, api, tmp_path, monkeypatch, capsys):
    """A file cut short (or still being written) between the upload's opening it and sending it had been h11's
    traceback, "LocalProtocolError: Too little (much) data for declared Content-Length" (exit 1), naming no file."""
    import os

    from voxe_core.cli import main

    url, _ = api
    obj = tmp_path / "plane.obj"
    send = httpx.Client.send

    def changing_then_sending(self, request, **kwargs):
        if request.method == "POST" and request.url.path == "/v1/scenes":
            obj.write_text(PLANE_OBJ)  # as it was opened, then cut short or written on
            if change == "shrinks":
                os.truncate(obj, 10)
            else:
                with open(obj, "a") as more:
                    more.write("#" * 5000)
        return send(self, request, **kwargs)

    monkeypatch.setattr(httpx.Client, "send", changing_then_sending)
    said = (f"{obj} ({len(PLANE_OBJ)} bytes when the upload opened it, {now} bytes now) changed as it was uploaded "
            "(still being written?): upload it once it is whole")
    obj.write_text(PLANE_OBJ)
    with Client(url) as client:
        with pytest.raises(ValueError, match=f"^{re.escape(said)}$"):
            client.upload_scene(obj)
    obj.write_text(PLANE_OBJ)
    assert main(["submit", "a plane", "--upload", str(obj), "--api", url, "--quiet"]) == 2
    assert capsys.readouterr().err == f"voxe submit: error: {said}\n"


def test_an_api_key_no_header_carries_is_refused_without_saying_it_and_one_not_ascii_is_sent(api, capsys):
    """A key with a line break (a key file's CRLF) had failed every call as "cannot reach the service at URL: Illegal
    header value b'Bearer <the key>\\r'" (exit 3: try again later; the secret in the log), and one not in ASCII
    with "'ascii' codec can't encode character ..." (naming no key); UTF-8 is what the service reads."""
    from voxe_core.cli import main

    url, _ = api
    for key in ("voxe_k1_secret\r", "voxe_k1_secret\n", "voxe_k1\0secret"):
        with pytest.raises(ValueError, match="^the API key cannot be sent: it holds a line break, NUL or other "
                                             "whitespace than spaces and tabs"):
            Client(url, api_key=key)
        assert main(["status", "j1", "--api", url, "--api-key", key]) == 2
        err = capsys.readouterr().err
        assert err.startswith("voxe status: error: the API key cannot be sent") and "secret" not in err
    assert main(["status", "j1", "--api", url, "--api-key", "voxe_clé"]) == 2  # sent: the service's answer
    assert "voxe status: error: GET /v1/jobs/j1: HTTP " in capsys.readouterr().err


def test_the_webhook_secret_is_read_and_rotated_through_the_client_and_voxe(api, capsys):
    """The client had no call for ``GET /v1/webhooks/secret`` nor ``POST /v1/webhooks/secret/rotate`` (nor ``voxe``
    a command): a key holder verifying its deliveries had to curl the API. Read twice it is the same ``whsec_``
    secret; rotated, the new one is what is read from then on; an answer with no secret is a ServiceError quoting it."""
    from service_helpers import answering
    from voxe_core.cli import main

    url, _ = api
    with Client(url) as client:
        secret = client.webhook_secret()
        assert secret.startswith("whsec_") and client.webhook_secret() == secret
        rotated = client.rotate_webhook_secret()
        assert rotated.startswith("whsec_") and rotated != secret and client.webhook_secret() == rotated
    assert main(["webhook-secret", "--api", url]) == 0
    assert capsys.readouterr().out == f"{rotated}\n"
    assert main(["webhook-secret", "--rotate", "--api", url]) == 0
    newest = capsys.readouterr().out.strip()
    assert newest.startswith("whsec_") and newest != rotated
    with Client(url) as client:
        assert client.webhook_secret() == newest
    with answering(b'{"detail": "moved"}') as elsewhere:
        assert main(["webhook-secret", "--api", elsewhere]) == 2
    assert capsys.readouterr().err == (f"voxe webhook-secret: error: GET /v1/webhooks/secret: {elsewhere} answered "
                                       "{'detail': 'moved'}, not a webhook secret\n")



def assert_refused(call, said: str) -> None:
    """``call()`` raises the ServiceError whose message starts with ``said`` ("GET /v1/jobs: HTTP 422: ..."), its
    ``status`` the one said."""
    with pytest.raises(ServiceError, match="^" + re.escape(said)) as refused:
        call()
    assert refused.value.status == int(said.split("HTTP ", 1)[1][:3])


def assert_a_moved_answer_is_refused_as_not(calls: dict) -> None:
    """Each call (what it reads: the call), answered a proxy's ``{"detail": "moved"}``, is a ServiceError quoting it
    and saying what it is not."""
    from service_helpers import answering

    with answering(b'{"detail": "moved"}') as elsewhere, Client(elsewhere) as client:
        for what, call in calls.items():
            with pytest.raises(ServiceError, match=rf"answered \{{'detail': 'moved'\}}, not {what}"):
                call(client)


def test_scenes_are_read_and_listed_page_by_page_through_the_client(api, tmp_path):
    """The client had no call for ``GET /v1/scenes/{id}``, ``GET /v1/scenes`` nor ``GET /v1/scenes/{id}/reconstructions``:
    an upload's caller could not see it become ready (or why it failed) but through ``request``. A scene is read
    processing, then ready; the listing pages by its cursor, newest first; refusals are the service's."""
    from service_helpers import ingest

    url, _ = api
    (tmp_path / "plane.obj").write_text(PLANE_OBJ)
    with Client(url) as client:
        first = client.upload_scene(tmp_path / "plane.obj", name="first")["id"]
        second = client.upload_scene(tmp_path / "plane.obj", name="second")["id"]
        assert client.get_scene(first)["state"] == "processing"
        assert ingest(first)["state"] == "ready"
        assert (client.get_scene(first)["state"], client.get_scene(first)["name"]) == ("ready", "first")
        page = client.list_scenes(limit=1)
        assert ([scene["id"] for scene in page["items"]], page["total"]) == ([second], 2)
        last = client.list_scenes(limit=1, cursor=page["next_cursor"])
        assert [scene["id"] for scene in last["items"]] == [first] and last["next_cursor"] is None
        assert [scene["id"] for scene in client.list_scenes(offset=1)["items"]] == [first]
        assert client.scene_reconstructions(first) == []
        assert_refused(lambda: client.list_scenes(limit=0), "GET /v1/scenes: HTTP 422: query.limit: ")
        assert_refused(lambda: client.scene_reconstructions("nope"), "GET /v1/scenes/nope/reconstructions: HTTP 404: ")
    assert_a_moved_answer_is_refused_as_not({
        "a page of a listing": lambda client: client.list_scenes(),
        "a list of reconstructions": lambda client: client.scene_reconstructions("s1"),
        "a scene with an id": lambda client: client.get_scene("s1")})


def test_jobs_are_listed_and_their_timeline_and_webhook_deliveries_read_through_the_client(api, tmp_path,
                                                                                         monkeypatch):
    """The client had no call for ``GET /v1/jobs``, the JSON timeline of ``GET /v1/jobs/{id}/events`` (only its live
    stream) nor ``GET /v1/jobs/{id}/webhooks``: a caller could not find its jobs, read what a finished one went
    through, nor see whether its webhook was delivered. A job canceled has its ``canceled`` event in its timeline and
    a delivery of it; the listing filters by state and scene and pages by its cursor."""
    url, _ = api
    plane = _plane_with_loopback_webhooks_allowed(tmp_path, monkeypatch)
    with Client(url) as client:
        scene_id = client.upload_scene(plane)["id"]
        other_scene = client.upload_scene(plane)["id"]
        hooked = client.create_job(scene_id, "a plane of gold", webhook_url="http://127.0.0.1:9/hook")["id"]
        queued = client.create_job(scene_id, "a plane of tin")["id"]
        elsewhere = client.create_job(other_scene, "a plane of wood")["id"]
        client.cancel_job(hooked)
        assert [event["kind"] for event in client.job_timeline(hooked)] == ["canceled"]
        assert [(hook["event_type"], hook["url"]) for hook in client.job_webhooks(hooked)] == \
            [("job.canceled", "http://127.0.0.1:9/hook")]
        assert client.job_webhooks(queued) == [] and client.job_timeline(queued) == []
        assert [job["id"] for job in client.list_jobs(state="canceled")["items"]] == [hooked]
        assert [job["id"] for job in client.list_jobs(scene_id=scene_id)["items"]] == [queued, hooked]
        page = client.list_jobs(limit=2)
        assert [job["id"] for job in page["items"]] == [elsewhere, queued] and page["total"] == 3
        assert [job["id"] for job in client.list_jobs(cursor=page["next_cursor"])["items"]] == [hooked]
        assert_refused(lambda: client.list_jobs(state="done"), "GET /v1/jobs: HTTP 422: query.state: ")
        assert_refused(lambda: client.job_timeline("nope"), "GET /v1/jobs/nope/events: HTTP 404: ")
    assert_a_moved_answer_is_refused_as_not({
        "a page of a listing": lambda client: client.list_jobs(),
        "a list of events": lambda client: client.job_timeline("j1"),
        "a list of webhook deliveries": lambda client: client.job_webhooks("j1")})


def test_an_evaluation_is_created_through_the_client_once_per_idempotency_key(api, tmp_path):
    """The client had no call for ``POST /v1/evaluations``: scoring finished edits (SPEC §4) outside a sweep took the
    raw ``request``, with no Idempotency-Key (a lost answer, sent again, made a second one). ``create_evaluation``
    queues it, a repeated call with its key answers the one the first made, and the service's refusals (an edit not
    succeeded, no such job) are its errors."""
    from voxe_service.db import session_scope
    from voxe_service.models import SUCCEEDED, Job

    url, _ = api
    (tmp_path / "plane.obj").write_text(PLANE_OBJ)
    with Client(url) as client:
        scene_id = client.upload_scene(tmp_path / "plane.obj")["id"]
        edit = client.create_job(scene_id, "a plane of gold")["id"]
        with pytest.raises(ServiceError, match=f"^POST /v1/evaluations: HTTP 409: job '{edit}' is queued: only "
                                               "succeeded edit jobs can be evaluated") as refused:
            client.create_evaluation([edit], "plane")
        assert refused.value.status == 409
        with session_scope() as session:
            session.get(Job, edit).state = SUCCEEDED
        made = [client.create_evaluation([edit], "plane", {"views": 4, "size": 32}, idempotency_key="eval-1")
                for _ in range(2)]
        assert made[0]["id"] == made[1]["id"] and (made[0]["mode"], made[0]["state"]) == ("evaluate", "queued")
        assert made[0]["params"]["views"] == 4 and made[0]["params"]["object"] == "plane"
        assert [job["id"] for job in client.list_jobs(limit=200)["items"]] == [made[0]["id"], edit]
        with pytest.raises(ServiceError, match="^POST /v1/evaluations: HTTP 404: "):
            client.create_evaluation(["nope"], "plane")


def test_a_sweep_is_canceled_through_the_client_and_voxe_cancel_sweep(api, tmp_path, capsys):
    """The client had no call for ``POST /v1/sweeps/{id}/cancel`` nor ``voxe`` a command: a sweep's twelve jobs per
    scene, once submitted, could be stopped only by curl or one ``voxe cancel`` per job (and ``voxe sweep --wait``
    stopped by Ctrl-C named no way to). ``cancel_sweep`` and ``voxe cancel-sweep`` cancel its unfinished jobs and
    answer the sweep; an unknown one is the service's 404, exit 2."""
    from voxe_core.cli import main

    url, _ = api
    (tmp_path / "plane.obj").write_text(PLANE_OBJ)
    with Client(url) as client:
        scene_id = client.upload_scene(tmp_path / "plane.obj")["id"]
        sweep = client.create_sweep([{"scene_id": scene_id, "object": "plane"}])
        jobs = len(sweep["entries"]) * 2
        assert sweep["counts"] == {"queued": jobs}
        canceled = client.cancel_sweep(sweep["id"])
        assert (canceled["id"], canceled["state"], canceled["counts"]) == (sweep["id"], "canceled", {"canceled": jobs})
        assert client.get_sweep(sweep["id"])["counts"] == {"canceled": jobs}
    assert main(["cancel-sweep", sweep["id"], "--api", url]) == 0
    assert json.loads(capsys.readouterr().out)["counts"] == {"canceled": jobs}
    assert main(["cancel-sweep", "nope", "--api", url]) == 2
    assert capsys.readouterr().err.startswith("voxe cancel-sweep: error: POST /v1/sweeps/nope/cancel: HTTP 404: ")
