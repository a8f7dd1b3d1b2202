"""Live job events over real HTTP: a uvicorn API and a Celery worker (subprocesses) run short jobs with the
random-weight SMOKE-TEST model (VOXE_SDS_MODEL=tiny); a real httpx client reads their Server-Sent Events, and
a real local HTTP receiver takes their webhooks. The event hub's own tests read its streams in this process,
on jobs of an in-process API (no worker).

Plumbing only, never edit quality.
"""

from __future__ import annotations

import asyncio
import base64
import hashlib
import hmac
import json
import signal
import time
from contextlib import aclosing

import httpx
import pytest

from fastapi.testclient import TestClient

from needs import MIC, require_data
from service_helpers import (
    WebhookReceiver, job_events, poll_job, reset_service_caches, service, service_env, small_mic, wait_for_scene,
    zip_folder,
)
from test_service_api import make_scene
from voxe_client import Client
from voxe_client.client import parse_sse

pytestmark = pytest.mark.slow

PARAMS = {
    "downsample": 16, "max_images": 3, "iterations": 6, "render_size": 32, "preview_every": 2,
    # no step at the coarse stage's 5 voxels, whose steps on 3 views left no positive density (an edit it refuses)
    "reconstruction": {"preset": "fast", "resolution": 16, "iterations": [0, 10, 20], "rays_per_step": 512},
    "export": {"views": 1, "view_size": 32, "turntable_frames": 4, "turntable_size": 32, "gif": False},
}
TERMINAL = ("succeeded", "failed", "canceled")


def read_sse(response: httpx.Response, stop=None):
    """The stream's events (voxe_client's parser), each stamped with its arrival; stop early once ``stop(event)``."""
    events = []
    for event in parse_sse(response.iter_lines()):
        events.append({**event, "at": time.monotonic()})
        if stop is not None and stop(event):
            break
    return events


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    require_data(MIC)
    root = tmp_path_factory.mktemp("events")
    data = small_mic(root / "mic_small", frames=3)
    with service(root / "svc", VOXE_CHECKPOINT_EVERY="2", VOXE_PROGRESS_INTERVAL_S="0.5",
                 VOXE_WEBHOOK_ALLOW_NETWORKS="127.0.0.0/8", VOXE_WEBHOOK_BACKOFF_S="0.2") as svc:
        with httpx.Client(base_url=svc.base, timeout=60) as client:
            with open(zip_folder(data, root / "mic.zip", prefix="mic_small"), "rb") as handle:
                response = client.post("/v1/scenes", files={"archive": ("mic.zip", handle, "application/zip")})
            assert response.status_code == 201, response.text
            scene = wait_for_scene(client, svc, response.json()["id"])
            assert scene["state"] == "ready", scene
            yield svc, client, scene


def test_a_stream_reconnected_with_last_event_id_misses_nothing(live):
    svc, client, scene = live
    job = client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": "a mic made of gold",
                                        "params": PARAMS}).json()
    url, sse = f"/v1/jobs/{job['id']}/events", {"Accept": "text/event-stream"}
    # First connection: read until the first stage is done, then drop the connection.
    with client.stream("GET", url, headers=sse) as response:
        assert response.status_code == 200 and response.headers["content-type"].startswith("text/event-stream")
        first = read_sse(response, stop=lambda e: e["event"] == "stage_completed")
    assert first[-1]["data"]["stage"] == "reconstruct", first
    last_id = [e["id"] for e in first if e["id"] is not None][-1]
    # Reconnect where it stopped and read to the end: the server closes the stream after the terminal event.
    with client.stream("GET", url, headers={**sse, "Last-Event-ID": last_id}) as response:
        second = read_sse(response)
    assert second[-1]["event"] == "progress" and second[-1]["data"]["state"] == "succeeded", second[-3:]
    timeline = [e for e in first + second if e["id"] is not None]
    stored = job_events(client, job["id"])
    assert [int(e["id"]) for e in timeline] == [e["id"] for e in stored]  # every event, in order, none twice
    assert [e["data"] for e in timeline] == stored
    kinds = [e["event"] for e in timeline]
    assert kinds[-1] == "succeeded" and "preview" in kinds and "checkpoint" in kinds
    published = {e["data"]["detail"] for e in timeline if e["event"] == "artifact"}
    listed = {a["name"] for a in client.get(f"/v1/jobs/{job['id']}/artifacts").json()}
    assert published == listed - {"preview.png"}, (published, listed)
    # Progress: snapshots, at most one per poll interval (0.5 s), never a repeat, stages in order.
    progress = [e for e in first + second if e["event"] == "progress"]
    assert len(progress) >= 3
    for stream in (first, second):  # counted, not spaced: a client's reads may bunch what was sent apart
        times = [e["at"] for e in stream if e["event"] == "progress"]
        assert len(times) <= 2 * (stream[-1]["at"] - stream[0]["at"]) + 2, times
    assert all(a["data"] != b["data"] for a, b in zip(progress, progress[1:]))
    overall = [e["data"]["overall_progress"] for e in progress]
    assert overall == sorted(overall) and overall[-1] == 1.0, overall
    # A finished job's stream replays its timeline and ends at once.
    with client.stream("GET", url, headers={**sse, "Last-Event-ID": str(stored[-3]["id"])}) as response:
        replay = read_sse(response)
    assert [int(e["id"]) for e in replay if e["id"]] == [e["id"] for e in stored[-2:]]
    # The JSON form is still the default.
    assert client.get(url).json() == stored
    # byte 0xB2 reads as "²" (latin-1): a digit to str.isdigit, not to int(); past 2^63 - 1 the event hub's one
    # query for every open stream had failed (live events stopped for all), 5,000 digits had been a 500
    for value in ("soon", b"\xb2", str(2**63), "9" * 5000):
        bad = client.get(url, headers={**sse, "Last-Event-ID": value})
        assert bad.status_code == 422 and "Last-Event-ID" in bad.json()["detail"], value


def test_streams_hold_no_database_connection_between_polls(live):
    """20 streams open on a queued job (no worker picks it up fast enough to matter) and the status
    route still answers: the streams share the hub's polls instead of each holding a pooled connection
    (SQLAlchemy's default pool has 5 + 10 overflow; 20 held ones would block the 21st request)."""
    svc, client, scene = live
    job = client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": "a mic made of gold",
                                        "params": PARAMS}).json()
    url = f"{svc.base}/v1/jobs/{job['id']}/events"
    clients = [httpx.Client(timeout=30) for _ in range(20)]
    try:
        streams = [c.stream("GET", url, headers={"Accept": "text/event-stream"}) for c in clients]
        responses = [s.__enter__() for s in streams]
        assert all(r.status_code == 200 for r in responses)
        started = time.monotonic()
        for _ in range(10):
            assert client.get(f"/v1/jobs/{job['id']}", timeout=5).status_code == 200
        assert time.monotonic() - started < 5
        for s in streams:
            s.__exit__(None, None, None)
    finally:
        for c in clients:
            c.close()
    poll_job(client, svc, job["id"])


def verify(secret: str, request: dict) -> bool:
    """The Standard Webhooks check a receiver does: HMAC-SHA256 of "id.timestamp.body" under the secret."""
    h = request["headers"]
    signed = f"{h['webhook-id']}.{h['webhook-timestamp']}.".encode() + request["body"]
    expected = base64.b64encode(hmac.new(base64.b64decode(secret.removeprefix("whsec_")), signed,
                                         hashlib.sha256).digest()).decode()
    return any(hmac.compare_digest(f"v1,{expected}", s) for s in h["webhook-signature"].split())


def test_webhooks_are_signed_retried_and_deduplicable(live):
    svc, client, scene = live
    receiver = WebhookReceiver(fail_first=True)  # a 500 to the first request, 200 after
    try:
        body = {"scene_id": scene["id"], "prompt": "a mic made of wood", "params": PARAMS,
                "webhook_url": receiver.url, "webhook_events": ["stage_completed", "succeeded"]}
        job = client.post("/v1/jobs", json=body).json()
        assert job["webhook_url"] == receiver.url, job
        assert poll_job(client, svc, job["id"])["state"] == "succeeded"
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            deliveries = client.get(f"/v1/jobs/{job['id']}/webhooks").json()
            if len(deliveries) == 4 and all(d["state"] == "delivered" for d in deliveries):
                break
            time.sleep(0.2)
        assert [d["event_type"] for d in deliveries] == ["job.stage_completed"] * 3 + ["job.succeeded"], deliveries
        assert all(d["state"] == "delivered" and d["last_status"] == 200 for d in deliveries), deliveries
        # Deliveries go out concurrently: whichever reached the receiver first got its 500 and was retried.
        retried = [d for d in deliveries if d["attempts"] == 2]
        assert len(retried) == 1 and sorted(d["attempts"] for d in deliveries) == [1, 1, 1, 2], deliveries
        secret = client.get("/v1/webhooks/secret").json()["secret"]
        requests = receiver.requests
        assert len(requests) == 5 and all(verify(secret, r) for r in requests)
        assert not verify(secret, {**requests[0], "body": requests[0]["body"] + b" "})  # a changed body fails
        # The retry after the 500 is the same message: same webhook-id (the dedupe key), same bytes.
        again = [r for r in requests[1:] if r["headers"]["webhook-id"] == requests[0]["headers"]["webhook-id"]]
        assert requests[0]["headers"]["webhook-id"] == retried[0]["id"] and len(again) == 1
        assert again[0]["body"] == requests[0]["body"]
        # One message per delivery (sent concurrently: receivers must not rely on their order).
        assert sorted(r["headers"]["webhook-id"] for r in requests[1:]) == sorted(d["id"] for d in deliveries)
        payloads = sorted((json.loads(r["body"]) for r in requests[1:]), key=lambda p: p["data"]["event"]["id"])
        assert [p["data"]["event"]["stage"] for p in payloads] == ["reconstruct", "edit", "export", "export"]
        assert payloads[-1]["type"] == "job.succeeded" and payloads[-1]["data"]["state"] == "succeeded"
        stored = {e["id"] for e in job_events(client, job["id"])}
        assert {d["event_id"] for d in deliveries} <= stored
    finally:
        receiver.close()


@pytest.mark.parametrize("url, rule", [("http://10.1.2.3/hook", "private"), ("http://169.254.169.254/", "link-local"),
                                       ("http://[::1]:9/hook", "loopback"), ("http://0.0.0.0/", "unspecified")])
def test_a_webhook_to_a_private_address_is_refused_naming_the_rule(live, url, rule):
    """127.0.0.0/8 is allowed here (VOXE_WEBHOOK_ALLOW_NETWORKS); every other private target is not."""
    _svc, client, scene = live
    before = client.get("/v1/jobs").json()["total"]
    response = client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": "a mic made of wood",
                                             "webhook_url": url})
    assert response.status_code == 422, response.text
    assert f"{'an' if rule == 'unspecified' else 'a'} {rule} address" in response.json()["detail"] and "VOXE_WEBHOOK_ALLOW_NETWORKS" in response.json()["detail"]
    assert client.get("/v1/jobs").json()["total"] == before  # nothing recorded


def test_the_client_uploads_submits_waits_over_events_and_downloads_verified(live, tmp_path):
    svc, _client, _scene = live
    data = small_mic(tmp_path / "mic_small", frames=3)
    seen = []
    with Client(svc.base) as client:
        scene = client.upload_scene(zip_folder(data, tmp_path / "mic.zip", prefix="mic_small"))
        wait_for_scene(_client, svc, scene["id"])
        job = client.create_job(scene["id"], "a mic made of glass", params=PARAMS)
        done = client.wait(job["id"], on_progress=seen.append)
        assert done["state"] == "succeeded" and done["overall_progress"] == 1.0, done
        assert len(seen) >= 2 and seen[-1]["state"] == "succeeded"
        assert [p["overall_progress"] for p in seen] == sorted(p["overall_progress"] for p in seen)
        listing = client.artifacts(job["id"])
        assert {"edited_grid.safetensors", "turntable.mp4", "preview.png"} <= {a["name"] for a in listing}
        for artifact in listing:
            path = client.download(job["id"], artifact["name"], tmp_path / "out" / artifact["name"])
            assert hashlib.sha256(path.read_bytes()).hexdigest() == artifact["sha256"]


def test_the_cli_submits_waits_downloads_and_reports_errors(live, tmp_path, capsys):
    from voxe_core.cli import main

    svc, client, scene = live
    api = ["--api", svc.base]
    assert main(["submit", "a mic made of copper", "--scene", scene["id"], "--params", json.dumps(PARAMS),
                 "--wait", *api]) == 0
    out = capsys.readouterr()
    job = json.loads(out.out)
    assert job["state"] == "succeeded" and "100.0%" in out.err  # the progress bar reached the end
    assert main(["download", job["id"], "--name", "turntable.mp4", "--out", str(tmp_path), *api]) == 0
    listed = {a["name"]: a for a in client.get(f"/v1/jobs/{job['id']}/artifacts").json()}
    data = (tmp_path / "turntable.mp4").read_bytes()
    assert hashlib.sha256(data).hexdigest() == listed["turntable.mp4"]["sha256"]
    assert main(["status", job["id"], *api]) == 0 and json.loads(capsys.readouterr().out)["id"] == job["id"]
    assert main(["cancel", job["id"], *api]) == 2  # a succeeded job cannot be canceled: the service's 409
    assert "HTTP 409" in capsys.readouterr().err


def test_an_open_event_stream_lets_the_api_stop(tmp_path):
    """SIGTERM with a stream open on a job that waits (no worker): the stream ends (its client resumes with
    Last-Event-ID) and the API exits, after its lifespan's shutdown (webhook sender, reaper). uvicorn waits for
    open responses before that shutdown, and a stream ends only with its job: the API had run on for good."""
    require_data(MIC)
    with service(tmp_path / "svc", worker=False) as svc, httpx.Client(base_url=svc.base, timeout=30) as client:
        with open(zip_folder(small_mic(tmp_path / "mic_small"), tmp_path / "mic.zip", prefix="mic_small"), "rb") as h:
            scene = client.post("/v1/scenes", files={"archive": ("mic.zip", h, "application/zip")}).json()
        job = client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": "a mic made of gold"}).json()
        with client.stream("GET", f"/v1/jobs/{job['id']}/events", headers={"Accept": "text/event-stream"}) as stream:
            events = parse_sse(stream.iter_lines())
            assert next(events)["data"]["state"] == "queued"  # the first progress snapshot
            svc.api.proc.send_signal(signal.SIGTERM)
            svc.api.proc.wait(15)
            assert list(events) == []  # the stream had ended cleanly


# ------------------------------------------------------------------------------------------ the hub in-process
@pytest.fixture
def in_process(tmp_path, monkeypatch):
    """An in-process API (TestClient, no worker) polling every 0.2 s, and the small mic's data."""
    require_data(MIC)
    for key, value in service_env(tmp_path, VOXE_PROGRESS_INTERVAL_S="0.2").items():
        monkeypatch.setenv(key, value)
    reset_service_caches()
    from api.main import create_app

    with TestClient(create_app()) as client:
        yield client, small_mic(tmp_path / "mic_small")
    reset_service_caches()


def follow(job_ids: list[str], timeout: float, on_progress=None, key_id: str = "local") -> list[list[dict]]:
    """Each job's stream (opened by ``key_id``) from a fresh event hub until it ends: its events (``event`` and
    ``data``), at most ``timeout`` seconds in all. ``on_progress(job_id, data)`` may end a stream early by
    returning True."""
    from api.events import EventHub
    from api.routes.jobs import progress_view

    async def read(hub, job_id):
        events = []
        async with aclosing(hub.stream(job_id, key_id)) as stream:
            async for chunk in stream:
                for event in parse_sse(chunk.splitlines()):
                    events.append({"event": event["event"], "data": event["data"]})
                    if event["event"] == "progress" and on_progress and await on_progress(job_id, event["data"]):
                        return events
        return events

    async def main():
        hub = EventHub(0.2, progress_view)
        try:
            return await asyncio.wait_for(asyncio.gather(*(read(hub, j) for j in job_ids)), timeout)
        finally:
            await hub.close()

    return asyncio.run(main())


def test_a_thousand_streams_get_their_events_from_one_poll(in_process, tmp_path):
    """Streams on 1,000 jobs (a key following its finished jobs): each gets its terminal event and ends. The
    hub's events query had one OR term per job, which SQLite refuses from 998 jobs: every poll failed, and every
    stream of the process stopped."""
    from sqlalchemy import insert, select

    from voxe_service.db import session_scope
    from voxe_service.models import Job, JobEvent

    client, data = in_process
    scene = make_scene(client, data, tmp_path)
    job = client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": "a mic made of gold"}).json()
    client.post(f"/v1/jobs/{job['id']}/cancel")
    ids = [f"copy{i:04d}" for i in range(1000)]
    with session_scope() as session:  # copies of the canceled job, each with its canceled event
        row = dict(session.execute(select(Job.__table__).where(Job.id == job["id"])).mappings().one())
        event = dict(session.execute(select(JobEvent.__table__).where(JobEvent.job_id == job["id"])).mappings().one())
        session.execute(insert(Job.__table__), [{**row, "id": i} for i in ids])
        session.execute(insert(JobEvent.__table__), [{**event, "id": None, "job_id": i} for i in ids])
    streams = follow(ids, timeout=30)
    assert all([e["event"] for e in events] == ["canceled", "progress"] for events in streams), streams[:3]


def test_a_stream_shows_the_message_of_a_job_its_scenes_ingest_sent(in_process, tmp_path):
    """A job waiting for its scene: once the ingest sends it, its stream's progress drops "waiting for the scene
    ..." as the job resource does (the message changed without updated_at, so the hub kept the old one)."""
    from service_helpers import ingest
    from test_service_api import upload_zip

    client, data = in_process
    scene = upload_zip(client, zip_folder(data, tmp_path / "mic.zip", prefix="mic_small")).json()
    job = client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": "a mic made of gold"}).json()
    assert job["message"].startswith("waiting for the scene")

    async def on_progress(_job_id, progress):
        if progress["message"] == job["message"]:  # the first snapshot: the ingest sends the job now
            await asyncio.to_thread(ingest, scene["id"])
            return False
        return True

    [events] = follow([job["id"]], timeout=15, on_progress=on_progress)
    sent = client.get(f"/v1/jobs/{job['id']}").json()
    assert [e["data"]["message"] for e in events] == [job["message"], sent["message"]], events


def test_a_streams_progress_says_a_cancel_was_requested_while_the_job_runs_on(in_process, tmp_path):
    """A running job's cancel is seen at its next check: until then its stream's progress says it was asked for,
    as the job resource does (the snapshot had left cancel_requested out, and the web UI's "(cancel requested)"
    went at the next progress)."""
    from sqlalchemy import update

    from voxe_service.db import session_scope
    from voxe_service.models import RUNNING, Job

    client, data = in_process
    scene = make_scene(client, data, tmp_path)
    job = client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": "a mic made of gold"}).json()
    with session_scope() as session:
        session.execute(update(Job).where(Job.id == job["id"]).values(state=RUNNING, stage="edit"))
    assert client.post(f"/v1/jobs/{job['id']}/cancel").json()["cancel_requested"] is True

    async def first_progress(_job_id, _progress):
        return True

    [events] = follow([job["id"]], timeout=15, on_progress=first_progress)
    assert [(e["data"]["state"], e["data"].get("cancel_requested")) for e in events] == [("running", True)], events


def test_a_stream_whose_job_changes_without_news_still_gets_its_keepalives(in_process, tmp_path, monkeypatch):
    """A job waiting on another job's reconstruction rewrites its unchanged progress every second (its updated_at
    moves, nothing it shows does): each rewrite woke its stream, which had nothing to send and started its keepalive
    wait over, so no keepalive ever went while the wait lasted, and a proxy's idle timeout (or the web UI's 45 s)
    cut the stream. The keepalive is counted from the stream's last words."""
    from sqlalchemy import update

    import api.events
    from api.events import EventHub
    from api.routes.jobs import progress_view
    from voxe_service.db import session_scope
    from voxe_service.models import RUNNING, Job, utcnow

    monkeypatch.setattr(api.events, "KEEPALIVE_S", 1.0)
    client, data = in_process
    scene = make_scene(client, data, tmp_path)
    job = client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": "a mic made of gold"}).json()
    waiting = {"state": RUNNING, "stage": "reconstruct", "message": "waiting for the scene's reconstruction r1"}

    def rewrite_unchanged():  # as worker/tasks.py's wait for a reconstruction does, faster
        with session_scope() as session:
            session.execute(update(Job).where(Job.id == job["id"]).values(updated_at=utcnow(), **waiting))

    async def main():
        hub, said = EventHub(0.1, progress_view), []

        async def read():
            async for chunk in hub.stream(job["id"], "local"):
                said.append((asyncio.get_running_loop().time(), chunk))

        reader = asyncio.create_task(read())
        try:
            for _ in range(50):  # 5 s
                await asyncio.to_thread(rewrite_unchanged)
                await asyncio.sleep(0.1)
        finally:
            reader.cancel()
            await hub.close()
        return said

    said = asyncio.run(main())
    assert any('"state":"running"' in chunk for _, chunk in said if "event: progress" in chunk), said
    quiet_from = max(at for at, chunk in said if "event: progress" in chunk)
    keepalives = [at for at, chunk in said if chunk == ": keepalive\n\n" and at > quiet_from]
    assert len(keepalives) >= 2, said  # (5 s of rewrites, the first running snapshot within the first second)
    # (1 s apart, with room for a loaded machine's delays)
    assert keepalives[0] - quiet_from < 2.5 and all(b - a < 2.5 for a, b in zip(keepalives, keepalives[1:])), said


@pytest.mark.parametrize("ending", ["revoked_at", "expires_at"])
def test_a_stream_ends_once_the_key_that_opened_it_is_revoked_or_expires(in_process, tmp_path, ending):
    """A revoked token stops working at once (README, ``revoke-key``), an expired one at its expiry: a stream opened
    before had gone on delivering the job's events for as long as the job ran."""
    from api.auth import create_key
    from voxe_service.db import session_scope
    from voxe_service.models import ApiKey, utcnow

    client, data = in_process
    scene = make_scene(client, data, tmp_path)
    job = client.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": "a mic made of gold"}).json()
    with session_scope() as session:
        key, _ = create_key(session, "streamer")
        key_id = key.id
    ended_at = []

    async def on_progress(_job_id, _progress):  # the first snapshot: revoke the key (or pass its expiry), read on
        def end():
            with session_scope() as session:
                setattr(session.get(ApiKey, key_id), ending, utcnow())
                ended_at.append(getattr(session.get(ApiKey, key_id), ending))
        await asyncio.to_thread(end)
        return False

    [events] = follow([job["id"]], timeout=15, on_progress=on_progress, key_id=key_id)
    assert [e["event"] for e in events] == ["progress", "error"], events
    how = "was revoked" if ending == "revoked_at" else f"expired at {ended_at[0].isoformat(timespec='seconds')}"
    assert events[-1]["data"] == {"detail": f"the API key of this stream {how}"}
    assert client.get(f"/v1/jobs/{job['id']}").json()["state"] == "queued"  # the job itself goes on


def test_a_hub_whose_polls_fail_logs_one_traceback_backs_off_and_says_when_they_succeed_again(monkeypatch, caplog):
    """With the database down, every poll (twice a second while a stream is open) had logged a warning with its
    traceback: 7,200 an hour per API process. Now the first failure is logged with its traceback, the next ones a
    line each, the polls back off while they fail, and the recovery is said."""
    import logging

    from api.events import EventHub

    polls = []

    def poll(after, fresh, keys):
        polls.append(time.monotonic())
        if len(polls) <= 5:
            raise ConnectionError("the database is unreachable")
        return {}, {}, {}, set()  # the job is gone: its stream ends

    async def read() -> list[str]:
        hub = EventHub(0.05, view=lambda job: {})
        monkeypatch.setattr(hub, "_poll", poll)
        try:
            async with aclosing(hub.stream("job1", "key1")) as stream:
                return [text async for text in stream]
        finally:
            await hub.close()

    with caplog.at_level(logging.WARNING, logger="voxe.api"):
        texts = asyncio.run(read())
    assert "was deleted" in texts[-1]
    records = [r for r in caplog.records if r.name == "voxe.api"]
    assert [r.exc_info is not None for r in records] == [True, False, False, False, False, False], records
    assert "poll 5 in a row failed" in records[4].getMessage()
    assert records[-1].getMessage() == "event streams: polls succeed again, after 5 failed in a row"
    gaps = [later - earlier for earlier, later in zip(polls, polls[1:])]
    assert gaps[3] > 3 * gaps[0] and gaps[3] >= 0.35, gaps  # 0.05 s doubling per failure: 0.4 s after the 4th
