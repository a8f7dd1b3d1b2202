"""Faults: orphaned jobs (the reaper), uploads that fail half way, an API and a Redis that restart.

The in-process tests run on a private SQLite database and storage; the process tests start real
uvicorn / Celery / redis-server subprocesses (tests/service_helpers.py) with the random-weight
SMOKE-TEST model (VOXE_SDS_MODEL=tiny): they prove the plumbing, never edit quality.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import logging
import math
import os
import time
import uuid
from datetime import timedelta

import pytest

from needs import MIC, missing, require_data
from service_helpers import (
    check_resumed_from_the_last_checkpoint, checkpoint_at_least, entered, job_events, poll_job, reset_service_caches,
    service_env, wait_for_event,
)


@pytest.fixture
def db(tmp_path, monkeypatch, database_url):
    """A migrated private database (SQLite, then PostgreSQL) and local storage under ``tmp_path``; the settings."""
    for key, value in service_env(tmp_path, database_url=database_url).items():
        monkeypatch.setenv(key, value)
    reset_service_caches()
    from voxe_service.db import run_migrations
    from voxe_service.settings import get_settings

    settings = get_settings()
    run_migrations(settings.database_url)
    yield settings
    reset_service_caches()


def owner() -> dict:
    """The owning API key's column, where the schema has one (the built-in key of the embedded default)."""
    from voxe_service import models

    return {"owner_key_id": models.LOCAL_KEY_ID} if hasattr(models.Scene, "owner_key_id") else {}


def add_scene(state: str = "ready", age_s: float = 0, task_id: str | None = "ingest",
              worker: str | None = None, **columns) -> str:
    from voxe_service.db import session_scope
    from voxe_service.models import Scene, utcnow

    then = utcnow() - timedelta(seconds=age_s)
    with session_scope() as session:
        scene = Scene(name="s", format="nerf_synthetic", image_count=1, width=8, height=8, splits=["train"],
                      storage_key="scenes/s/dataset.zip", size_bytes=1, sha256="0" * 64, state=state,
                      task_id=task_id, worker_hostname=worker, created_at=then, updated_at=then, **owner(), **columns)
        session.add(scene)
        session.flush()
        return scene.id


def add_job(scene_id: str, state: str, age_s: float, worker: str | None = None, stage: str | None = None,
            task_id: str | None = "task", **columns) -> str:
    from voxe_service.db import session_scope
    from voxe_service.models import Job, utcnow

    then = utcnow() - timedelta(seconds=age_s)
    with session_scope() as session:
        job = Job(**{"mode": "global", **columns}, scene_id=scene_id, prompt="a yarn doll of a mic", params={},
                  sds_model="tiny", attention_model="tiny", device="cpu", state=state, stage=stage,
                  worker_hostname=worker, task_id=task_id, created_at=then, updated_at=then, **owner())
        session.add(job)
        session.flush()
        return job.id


def add_reconstruction(scene_id: str, params: dict | None = None) -> str:
    """A pending shared fit of the scene, no job holding it."""
    from voxe_service.db import session_scope
    from voxe_service.models import Reconstruction

    with session_scope() as session:
        rec = Reconstruction(scene_id=scene_id, params_key="k", params=params or {})
        session.add(rec)
        session.flush()
        return rec.id


def add_heartbeat(hostname: str, age_s: float) -> None:
    from voxe_service.db import session_scope
    from voxe_service.models import WorkerHeartbeat, utcnow

    with session_scope() as session:
        session.add(WorkerHeartbeat(hostname=hostname, pid=1, queues="gpu", device="cpu",
                                    last_seen=utcnow() - timedelta(seconds=age_s)))


def job_row(job_id: str):
    from worker.runtime import load_job

    return load_job(job_id)


def scene_row(scene_id: str):
    from voxe_service.db import session_scope
    from voxe_service.models import Scene

    with session_scope() as session:
        scene = session.get(Scene, scene_id)
        session.expunge(scene)
        return scene


# ---------------------------------------------------------------------------------------------- the reaper
def test_reaper_sends_again_or_fails_only_jobs_nothing_will_finish(db):
    """A running job whose worker is gone is sent again (queued, its run's hold released), up to
    VOXE_JOB_MAX_REQUEUES times, then failed; so is one between stages whose worker is gone, without counting (one
    on a live worker waits, its next message maybe behind others', for VOXE_JOB_LOST_MESSAGE_TIMEOUT_S); an
    accepted job never sent is sent; only what
    nothing can carry fails, and one its user asked to cancel ends canceled. The ids returned are the ended ones."""
    from sqlalchemy import update

    from api.reaper import reap_orphaned_jobs
    from voxe_service.db import session_scope
    from voxe_service.models import Job, utcnow

    timeout, limit = db.job_stale_timeout_s, db.job_max_requeues
    scene = add_scene()
    add_heartbeat("alive@host", age_s=1)
    add_heartbeat("dead@host", age_s=2 * timeout)
    lapsed = utcnow() - timedelta(seconds=timeout)
    long_lapsed = utcnow() - timedelta(seconds=2 * timeout)
    requeued = {  # (a run held the first three: their stage was interrupted, which counts)
        "dead worker": add_job(scene, "running", 2 * timeout, "dead@host", "edit", run_token="t1",
                               run_lease_until=lapsed, completed_stages=["reconstruct"]),
        "no heartbeat ever": add_job(scene, "running", 2 * timeout, "gone@host", "refine", run_token="t3",
                                     run_lease_until=lapsed),
        "a live worker's run that stopped renewing long ago": add_job(
            scene, "running", 2 * timeout, "alive@host", "edit", run_token="t4", run_lease_until=long_lapsed),
        "between stages, its worker gone": add_job(scene, "running", 2 * timeout, "dead@host", "edit",
                                                   completed_stages=["reconstruct", "edit"], requeues=limit),
        "no worker recorded": add_job(scene, "running", 2 * timeout, None, "reconstruct"),
        "between stages on a live worker, its next message lost unseen": add_job(
            scene, "running", 2 * db.job_lost_message_timeout_s, "alive@host", "edit",
            completed_stages=["reconstruct", "edit"]),
    }
    counted = {"dead worker", "no heartbeat ever", "a live worker's run that stopped renewing long ago"}
    orphans = {"sent again too often": add_job(scene, "running", 2 * timeout, "dead@host", "edit", requeues=limit,
                                               run_token="t5", run_lease_until=lapsed, batch_id="b3")}
    asked_to_cancel = {  # had been sent again (to end "canceled before" its next stage) or failed at the limit
        "below the limit": add_job(scene, "running", 2 * timeout, "dead@host", "edit", run_token="t7",
                                   run_lease_until=lapsed, cancel_requested=True),
        "at the limit": add_job(scene, "running", 2 * timeout, "dead@host", "edit", run_token="t8",
                                run_lease_until=lapsed, cancel_requested=True, requeues=limit, batch_id="b4"),
    }
    cancel_rides_along = add_job(scene, "queued", 2 * timeout, mode="evaluate", batch_id="b4",  # sent alone after
                                 source_job_ids=[asked_to_cancel["at the limit"]])  # the canceled edit
    orphans.update(asked_to_cancel)
    rides_along = add_job(scene, "queued", 2 * timeout, mode="evaluate", batch_id="b3",  # in that edit's chain
                          source_job_ids=[orphans["sent again too often"]])
    never_sent = add_job(scene, "queued", 2 * timeout, task_id=None)  # accepted, never sent: sent now, not failed
    # A sweep's evaluation goes with its edit's chain when that is sent; one whose edit is done has no chain left.
    sweep_edit = add_job(scene, "queued", 2 * timeout, task_id=None, batch_id="b1")
    carried = add_job(scene, "queued", 2 * timeout, task_id=None, mode="evaluate", batch_id="b1",
                      source_job_ids=[sweep_edit])
    orphans["evaluation of a finished edit"] = add_job(
        scene, "queued", 2 * timeout, task_id=None, mode="evaluate", batch_id="b2",
        source_job_ids=[add_job(scene, "succeeded", 2 * timeout, batch_id="b2")])
    processing = add_scene("processing", age_s=1)
    kept = {
        "waiting for its scene's ingest": add_job(processing, "queued", 2 * timeout, task_id=None),
        "between stages on a live worker, lately": add_job(scene, "running", timeout / 2, "alive@host", "edit",
                                                           completed_stages=["reconstruct", "edit"]),
        "between stages on a live worker, its next message behind others'": add_job(
            scene, "running", 2 * timeout, "alive@host", "edit", completed_stages=["reconstruct", "edit"]),
        "recent progress": add_job(scene, "running", timeout / 2, "dead@host", "edit"),
        "a run holds it (its lease renewed)": add_job(scene, "running", 2 * timeout, "dead@host", "edit",
                                                      run_token="t2", run_lease_until=utcnow() + timedelta(60)),
        "a live worker's run, its hold lapsed lately": add_job(scene, "running", 2 * timeout, "alive@host", "edit",
                                                               run_token="t6",
                                                               run_lease_until=utcnow() - timedelta(seconds=60)),
        "queued in the broker": add_job(scene, "queued", 2 * timeout),
        "queued just now, not yet sent": add_job(scene, "queued", timeout / 2, task_id=None),
        "succeeded": add_job(scene, "succeeded", 2 * timeout, "dead@host", "export"),
        "canceled": add_job(scene, "canceled", 2 * timeout, "dead@host", "edit"),
    }
    assert sorted(reap_orphaned_jobs(db)) == sorted(orphans.values())
    for what, job_id in requeued.items():
        job = job_row(job_id)
        before = limit if what == "between stages, its worker gone" else 0
        assert (job.state, job.requeues, job.run_token, job.run_lease_until, job.error) == (
            "queued", before + (what in counted), None, None, None), what
        assert job.task_id not in (None, "task"), what  # its remaining stages are in the broker again
        assert [(e["kind"], e["stage"]) for e in events_of(job_id)] == [("requeued", job.stage)], what
    dead = job_row(requeued["dead worker"])
    reason = (f"worker dead@host stopped while the job was in edit: no heartbeat and no progress for "
              f"{timeout:.0f} s (VOXE_JOB_STALE_TIMEOUT_S)")
    assert events_of(dead.id)[0]["detail"] == reason and dead.message == f"re-queued: {reason}"
    assert dead.completed_stages == ["reconstruct"]
    assert job_row(requeued["no worker recorded"]).message.startswith(
        "re-queued: worker (unknown) stopped while the job was in reconstruct")
    assert job_row(requeued["between stages on a live worker, its next message lost unseen"]).message == (
        f"re-queued: no stage started for {db.job_lost_message_timeout_s:.0f} s after edit "
        "(VOXE_JOB_LOST_MESSAGE_TIMEOUT_S, doubled for each earlier such re-send): sent again, its next message taken "
        "as lost")
    assert job_row(requeued["a live worker's run that stopped renewing long ago"]).message == (
        f"re-queued: the run of edit on worker alive@host stopped renewing its hold {timeout:.0f} s ago and made "
        f"no progress (VOXE_JOB_STALE_TIMEOUT_S)")
    for what, job_id in asked_to_cancel.items():
        job = job_row(job_id)
        assert (job.state, job.message, job.error) == ("canceled", f"canceled: {reason}", None), what
        assert job.finished_at is not None, what
    assert job_row(asked_to_cancel["below the limit"]).task_id == "task"  # ended, nothing sent
    assert job_row(cancel_rides_along).task_id not in (None, "task")  # its evaluation sent alone, the message kept
    too_often = job_row(orphans["sent again too often"])
    assert too_often.state == "failed" and too_often.finished_at is not None
    assert too_often.error == (f"{reason}; it was sent again {limit} time(s) already, the limit "
                               f"(VOXE_JOB_MAX_REQUEUES={limit})")
    evaluation = job_row(rides_along)  # sent alone, to record why its edit failed
    assert evaluation.state == "queued" and evaluation.task_id not in (None, "task")
    sent = job_row(never_sent)
    assert sent.state == "queued" and sent.task_id not in (None, "task") and sent.error is None
    assert job_row(carried).state == "queued" and job_row(carried).task_id == job_row(sweep_edit).task_id is not None
    assert job_row(orphans["evaluation of a finished edit"]).error.startswith(
        "the sweep's evaluation was never handed to the broker with its edit")
    assert [e["kind"] for e in events_of(never_sent)] == ["requeued"]
    assert events_of(never_sent)[0]["detail"].startswith("sent by the reaper: recorded but not handed to the broker")
    for what, job_id in kept.items():
        before = job_row(job_id)
        assert before.error is None and before.state in ("running", "queued", "succeeded", "canceled"), what
        assert before.requeues == 0 and events_of(job_id) == [], what
    assert {job_row(j).state for j in kept.values()} == {"running", "queued", "succeeded", "canceled"}
    # A second pass changes nothing: the jobs sent again wait in the broker for a worker, like any sent job (for up
    # to VOXE_JOB_LOST_MESSAGE_TIMEOUT_S: then their message is taken as lost).
    with session_scope() as session:
        session.execute(update(Job).where(Job.id.in_(list(requeued.values())))
                        .values(updated_at=utcnow() - timedelta(seconds=2 * timeout)))
    assert reap_orphaned_jobs(db) == []
    assert [job_row(j).state for j in requeued.values()] == ["queued"] * len(requeued)
    assert [e["kind"] for e in events_of(orphans["sent again too often"])] == ["failed"]  # on the job's timeline


def test_reaper_sends_again_a_queued_job_whose_message_the_broker_lost(db):
    """A queued job handed to the broker that no stage has taken for VOXE_JOB_LOST_MESSAGE_TIMEOUT_S: its message is
    taken as lost (Redis's last second before a crash, under appendfsync everysec; a flushed broker), as the reaper's
    own re-send of a dead worker's job can be. It had stayed queued for ever, holding a place in its key's quota,
    where a job between stages is sent again; now it is sent again too, its done stages left out. One waiting less
    long, and a sweep's evaluation riding in a live or lately ended edit's chain, are left waiting."""
    from api.reaper import reap_orphaned_jobs
    from voxe_service.broker import waiting_tasks
    from voxe_service.models import utcnow
    from voxe_service.queue import TASK_NAMES

    lost_after = db.job_lost_message_timeout_s
    scene = add_scene()
    lost = add_job(scene, "queued", 2 * lost_after, completed_stages=["reconstruct"], requeues=1)
    long_ended = add_job(scene, "succeeded", 3 * lost_after, finished_at=utcnow() - timedelta(seconds=2 * lost_after))
    lost_evaluation = add_job(scene, "queued", 2 * lost_after, mode="evaluate", source_job_ids=[long_ended])
    lately_ended = add_job(scene, "succeeded", 3 * lost_after, finished_at=utcnow() - timedelta(seconds=60))
    kept = {
        "waiting its turn": add_job(scene, "queued", lost_after / 2),
        "a sweep's evaluation, its edit running": add_job(
            scene, "queued", 2 * lost_after, mode="evaluate", batch_id="b1",
            source_job_ids=[add_job(scene, "running", 60, "alive@host", "export", batch_id="b1")]),
        "a sweep's evaluation, its edit ended lately": add_job(
            scene, "queued", 2 * lost_after, mode="evaluate", batch_id="b2", source_job_ids=[lately_ended]),
    }
    assert reap_orphaned_jobs(db) == []
    reason = (f"no stage started for {lost_after:.0f} s after the job was sent (VOXE_JOB_LOST_MESSAGE_TIMEOUT_S, "
              "doubled for each earlier such re-send): sent again, its message taken as lost")
    for job_id in (lost, lost_evaluation):
        job = job_row(job_id)
        assert (job.state, job.message, job.error) == ("queued", f"re-queued: {reason}", None)
        assert job.task_id not in (None, "task") and job.requeues == (1 if job_id == lost else 0)
        assert [(e["kind"], e["detail"]) for e in events_of(job_id)] == [("requeued", reason)]
    sent = waiting_tasks(db.broker_url)
    assert {task for task, job_id in sent if job_id == lost} == {TASK_NAMES[s] for s in ("edit", "export")}
    assert {task for task, job_id in sent if job_id == lost_evaluation} == {TASK_NAMES["evaluate"]}
    for what, job_id in kept.items():
        assert (job_row(job_id).task_id, events_of(job_id)) == ("task", []), what
    assert reap_orphaned_jobs(db) == [] and len(events_of(lost)) == 1  # sent once: it waits again as sent


@pytest.mark.parametrize("sent_as", ["lost message", None])
def test_a_resend_the_broker_refused_is_tried_again_at_the_reapers_next_pass(db, monkeypatch, sent_as):
    """A re-send of a job (its message taken as lost, or never sent) that the broker refused left the job's time at
    the claim's: the reaper waited a whole window (6 h by default) before trying again, where a scene's refused
    ingest re-send is tried at the next pass. The job gets its time back with its task id."""
    from kombu.exceptions import OperationalError

    from api.reaper import reap_orphaned_jobs
    from voxe_service.models import utcnow
    from voxe_service.queue import TaskQueue

    window = db.job_lost_message_timeout_s if sent_as else db.job_stale_timeout_s
    job = add_job(add_scene(), "queued", 1.01 * window, task_id=sent_as)
    before = job_row(job).updated_at
    send = TaskQueue.send

    def refused_once(self, signature):
        monkeypatch.setattr(TaskQueue, "send", send)
        raise OperationalError("Connection refused.")

    monkeypatch.setattr(TaskQueue, "send", refused_once)
    assert reap_orphaned_jobs(db) == []
    assert (job_row(job).task_id, job_row(job).updated_at, events_of(job)) == (sent_as, before, [])
    assert reap_orphaned_jobs(db, now=utcnow() + timedelta(minutes=1)) == []  # the broker back: sent
    assert job_row(job).task_id not in (None, sent_as) and [e["kind"] for e in events_of(job)] == ["requeued"]


def test_the_jobs_a_scene_just_made_ready_is_sending_are_left_to_its_ingest_for_a_stale_window(db):
    """A job created on a processing scene waits for its ingest, which sends it once the scene is ready. One created
    longer than VOXE_JOB_STALE_TIMEOUT_S ago (a long ingest) looked never sent to a reaper pass between the scene's
    readiness and the ingest's send: the reaper sent it too (a second chain, and a ``requeued`` event saying it was
    never handed to the broker). The ingest sends it alone; should the ingest stop first, a stale window later the
    reaper does."""
    from api.reaper import reap_orphaned_jobs
    from voxe_service.db import session_scope
    from voxe_service.models import utcnow
    from voxe_service.scenes import mark_ready

    timeout = db.job_stale_timeout_s
    scene = add_scene("processing")
    job = add_job(scene, "queued", 2 * timeout, task_id=None, reconstruction_id=add_reconstruction(scene))
    with session_scope() as session:  # the ingest's readiness, committed before it sends the jobs
        assert [waiting.id for waiting in mark_ready(session, scene)] == [job]
    assert reap_orphaned_jobs(db) == []
    assert (job_row(job).task_id, events_of(job)) == (None, [])  # the ingest's to send
    assert reap_orphaned_jobs(db, now=utcnow() + timedelta(seconds=2 * timeout)) == []  # the ingest stopped
    assert job_row(job).task_id is not None and [e["kind"] for e in events_of(job)] == ["requeued"]


def test_a_job_waiting_its_turn_behind_a_long_backlog_is_sent_again_ever_more_rarely(db, monkeypatch):
    """A sent job no stage has taken for VOXE_JOB_LOST_MESSAGE_TIMEOUT_S had been sent again each period, without
    end, a "requeued" event each time, while its message was only waiting its turn. On the SQL broker a job a waiting
    message carries is not sent again at all; its message gone, it is sent once. Elsewhere (a Redis, whose queue the
    reaper does not read) each earlier such re-send doubles the wait before the next, between stages or queued."""
    from sqlalchemy import update

    import api.reaper as reaper
    from voxe_service.broker import waiting_tasks
    from voxe_service.db import session_scope
    from voxe_service.models import Job, utcnow

    lost_after = db.job_lost_message_timeout_s
    scene = add_scene()
    add_heartbeat("alive@host", age_s=1)
    queued = add_job(scene, "queued", 2 * lost_after)
    between = add_job(scene, "running", 2 * lost_after, "alive@host", "edit", completed_stages=["reconstruct", "edit"])
    jobs = [queued, between]

    def waited(age_in_periods: float) -> list[int]:
        """One reaper pass after the jobs were last sent ``age_in_periods`` VOXE_JOB_LOST_MESSAGE_TIMEOUT_S ago; how
        many times each has been sent again."""
        with session_scope() as session:
            session.execute(update(Job).where(Job.id.in_(jobs))
                            .values(updated_at=utcnow() - timedelta(seconds=age_in_periods * lost_after)))
        assert reaper.reap_orphaned_jobs(db) == []
        return [len(events_of(job_id)) for job_id in jobs]

    assert waited(2) == [1, 1]  # no message for them in the SQL broker: sent again
    assert job_row(between).message.startswith(f"re-queued: no stage started for {lost_after:.0f} s after edit (")
    assert all(job_id in {j for _, j in waiting_tasks(db.broker_url)} for job_id in jobs)
    assert [waited(2) for _ in range(4)] == [[1, 1]] * 4  # their messages wait their turn: never again
    assert events_of(queued)[0]["detail"] == (
        f"no stage started for {lost_after:.0f} s after the job was sent (VOXE_JOB_LOST_MESSAGE_TIMEOUT_S, doubled "
        "for each earlier such re-send): sent again, its message taken as lost")
    monkeypatch.setattr(reaper, "is_sql_broker", lambda url: False)  # a broker whose queue the reaper cannot read
    assert [waited(age) for age in (1.5, 2.5, 3.5, 4.5, 7.5, 8.5)] == [
        [1, 1], [2, 2], [2, 2], [3, 3], [3, 3], [4, 4]]  # after 2, 4, then 8 periods
    for job_id in jobs:  # (the job between stages was queued by its first re-send)
        assert job_row(job_id).message.startswith(f"re-queued: no stage started for {8 * lost_after:.0f} s after the "
                                                  "job was sent")


def test_a_sql_broker_that_cannot_be_read_stops_no_other_reaper_work(db, monkeypatch, caplog):
    """The SQL broker's table of waiting messages could not be read (its database unreachable): the whole reaper
    pass raised, a cancel between stages, a dead worker's job and a job never sent all left for as long. Now no
    queued job's message is taken as lost meanwhile, as a warning says once, and the rest of the pass is done; once
    the table is read again, the job whose message is lost is sent."""
    import api.reaper as reaper

    lost_after, timeout = db.job_lost_message_timeout_s, db.job_stale_timeout_s
    scene = add_scene()
    add_heartbeat("alive@host", age_s=1)
    add_heartbeat("dead@host", age_s=2 * timeout)
    lost = add_job(scene, "running", 2 * lost_after, "alive@host", "edit", completed_stages=["reconstruct", "edit"])
    canceled = add_job(scene, "running", 10, "alive@host", "edit", completed_stages=["reconstruct", "edit"],
                       cancel_requested=True)
    dead_workers = add_job(scene, "running", 2 * timeout, "dead@host", "edit", completed_stages=["reconstruct"])
    never_sent = add_job(scene, "queued", 2 * timeout, task_id=None)
    readable = reaper.waiting_tasks

    def unreadable(url):
        raise OSError("unable to open database file")

    monkeypatch.setattr(reaper, "waiting_tasks", unreadable)
    with caplog.at_level(logging.WARNING, logger="voxe.reaper"):
        assert reaper.reap_orphaned_jobs(db) == [canceled]
        assert reaper.reap_orphaned_jobs(db) == []
    assert [(r.getMessage()) for r in caplog.records if "cannot be read" in r.getMessage()] == [
        "reaper: the SQL broker's waiting messages cannot be read (OSError: unable to open database file): no "
        "queued job's message is taken as lost until they can"]
    assert job_row(canceled).state == "canceled"
    assert (job_row(dead_workers).state, job_row(never_sent).state) == ("queued", "queued")
    assert job_row(never_sent).task_id is not None and job_row(dead_workers).task_id is not None
    assert (job_row(lost).state, events_of(lost)) == ("running", [])
    monkeypatch.setattr(reaper, "waiting_tasks", readable)
    assert reaper.reap_orphaned_jobs(db) == [] and job_row(lost).state == "queued"


def _assert_one_traceback_then_lines(records: list, first: str, fourth: str, back: str) -> None:
    """Four failures in a row and the recovery, logged as a FailingStreak logs them: the first with its traceback
    (``first``), the next ones a line each (the fourth's ``fourth``), then ``back``."""
    assert [r.exc_info is not None for r in records] == [True, False, False, False, False], records
    assert [records[0].getMessage(), records[3].getMessage(), records[4].getMessage()] == [first, fourth, back]


def test_a_reaper_whose_passes_fail_logs_one_traceback_then_a_line_each_and_says_when_they_succeed_again(
        monkeypatch, caplog):
    """With the database down, every reaper pass (a minute apart) had logged 'reaper pass failed' with its whole
    traceback for as long as the outage lasted. Now the first failed pass is logged with its traceback, the next
    ones a line each (the error's first line), and the recovery is said; the passes keep their interval."""
    import threading
    import types

    from sqlalchemy.exc import OperationalError

    import api.reaper as reaper

    passes, recovered = [], threading.Event()

    def scenes(settings):
        passes.append(time.monotonic())
        if len(passes) <= 4:
            raise OperationalError("SELECT scenes", {}, Exception("connection refused\nIs it running?"))
        recovered.set()
        return []

    monkeypatch.setattr(reaper, "sync_clock", lambda: None)
    monkeypatch.setattr(reaper, "reap_orphaned_scenes", scenes)
    monkeypatch.setattr(reaper, "reap_orphaned_jobs", lambda settings: [])
    monkeypatch.setattr(reaper, "reap_orphaned_uploads", lambda settings: [])
    monkeypatch.setattr(reaper, "reap_idempotency_records", lambda settings: 0)
    monkeypatch.setattr(reaper, "get_storage", lambda settings: types.SimpleNamespace(
        discard_prefixes=lambda *prefixes: None))
    with caplog.at_level(logging.INFO, logger="voxe.reaper"):
        running = reaper.Reaper(types.SimpleNamespace(reaper_interval_s=0.05)).start()
        try:
            assert recovered.wait(10)
        finally:
            running.stop()
    records = [r for r in caplog.records if r.name == "voxe.reaper"]
    _assert_one_traceback_then_lines(
        records, "reaper: pass failed; next in 0.05 s",
        "reaper: pass 4 in a row failed; next in 0.05 s: OperationalError: "
        "(builtins.Exception) connection refused",
        "reaper: passes succeed again, after 4 failed in a row")


def test_the_reaper_sweeps_for_unrecorded_uploads_at_its_start_then_hourly_not_each_pass(monkeypatch):
    """The sweep lists every scene's objects (and reads their rows): at the start, then each UPLOAD_SWEEP_INTERVAL_S,
    not on every pass a minute apart; so is the Idempotency-Key records' retention kept."""
    import threading
    import types

    import api.reaper as reaper

    passes, sweeps, records, enough = [], [], [], threading.Event()

    def jobs(settings):
        passes.append(1)
        if len(passes) >= 5:
            enough.set()
        return []

    monkeypatch.setattr(reaper, "sync_clock", lambda: None)
    monkeypatch.setattr(reaper, "reap_orphaned_scenes", lambda settings: [])
    monkeypatch.setattr(reaper, "reap_orphaned_jobs", jobs)
    monkeypatch.setattr(reaper, "reap_orphaned_uploads", lambda settings: sweeps.append(1) or [])
    monkeypatch.setattr(reaper, "reap_idempotency_records", lambda settings: records.append(1) or 0)
    monkeypatch.setattr(reaper, "get_storage", lambda settings: types.SimpleNamespace(
        discard_prefixes=lambda *prefixes: None))
    running = reaper.Reaper(types.SimpleNamespace(reaper_interval_s=0.01)).start()
    try:
        assert enough.wait(10)
        assert len(sweeps) == len(records) == 1
        monkeypatch.setattr(reaper, "UPLOAD_SWEEP_INTERVAL_S", 0.0)  # (an hour passed)
        passes.clear()
        enough.clear()
        assert enough.wait(10)
    finally:
        running.stop()
    assert len(sweeps) >= 4 and len(records) >= 4


def test_reading_the_database_clock_while_postgresql_is_down_logs_one_traceback_then_a_line_each(monkeypatch,
                                                                                                  caplog):
    """Every heartbeat, reaper pass and stage start reads PostgreSQL's clock (sync_clock): with the database down,
    each reading had logged "could not read the database's clock" with its whole traceback. Now the first failed
    reading is logged with its traceback, the next ones a line each, and the recovery is said; the offset stays."""
    import types

    from sqlalchemy.exc import OperationalError

    from voxe_service import models
    from voxe_service.db import sync_clock

    class PostgreSQL:
        dialect = types.SimpleNamespace(name="postgresql")
        up = True

        def connect(self):
            if not self.up:
                raise OperationalError("SELECT clock_timestamp()", {}, Exception("connection refused\nIs it up?"))
            later = models.system_now() + timedelta(seconds=30)
            return contextlib.nullcontext(types.SimpleNamespace(
                execute=lambda statement: types.SimpleNamespace(scalar_one=lambda: later)))

    monkeypatch.setattr(models, "_clock_offset", timedelta(0))  # (put back after the test)
    database = PostgreSQL()
    assert abs(sync_clock(database).total_seconds() - 30) < 1
    database.up = False
    with caplog.at_level(logging.INFO, logger="voxe.db"):
        assert [sync_clock(database) for _ in range(4)] == [None] * 4
        assert abs((models.utcnow() - models.system_now()).total_seconds() - 30) < 1  # the last offset kept
        database.up = True
        assert sync_clock(database) is not None
    records = [r for r in caplog.records if r.name == "voxe.db" and "clock is" not in r.getMessage()]
    _assert_one_traceback_then_lines(
        records, "database clock: reading failed; the last offset measured stays",
        "database clock: reading 4 in a row failed; the last offset measured stays: "
        "OperationalError: (builtins.Exception) connection refused",
        "database clock: readings succeed again, after 4 failed in a row")


def test_a_process_forked_while_the_database_clock_readings_fail_counts_its_own_from_zero(monkeypatch):
    """The count of failed readings lives in the module: a Celery pool process forked while its worker's heartbeats
    failed to read the clock took the worker's count, and logged its own first failure "reading 4 in a row failed",
    with no traceback. A forked process counts its own from zero."""
    import types

    from sqlalchemy.exc import OperationalError

    from voxe_service import db

    class Down:
        dialect = types.SimpleNamespace(name="postgresql")

        def connect(self):
            raise OperationalError("SELECT clock_timestamp()", {}, Exception("connection refused"))

    monkeypatch.setattr(db._CLOCK_READINGS, "failed", 0)  # (put back after the test)
    assert [db.sync_clock(Down()) for _ in range(3)] == [None] * 3
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the forked process: its first reading's log line, sent back
        try:
            os.close(read)
            records = []
            handler = logging.Handler()
            handler.emit = records.append
            db.log.addHandler(handler)
            db.sync_clock(Down())
            os.write(write, f"{records[0].getMessage()} | traceback: {records[0].exc_info is not None}".encode())
        finally:
            os._exit(0)
    os.close(write)
    os.waitpid(pid, 0)
    with os.fdopen(read) as said:
        assert said.read() == "database clock: reading failed; the last offset measured stays | traceback: True"
    assert db._CLOCK_READINGS.failed == 3  # this process's own count goes on


def _beat_until(event, monkeypatch, caplog, session_scope, check_models, models: dict) -> None:
    """Run the worker's heartbeat loop (a beat each 10 ms, the clock not read, nothing swept; its database
    ``session_scope``, its ``check_models`` and the ``models`` it starts with) until ``event`` is set, logging at INFO
    into ``caplog``."""
    import threading
    import types

    from worker import runtime, tasks

    monkeypatch.setattr(tasks, "get_settings", lambda: types.SimpleNamespace(worker_heartbeat_s=0.01))
    monkeypatch.setattr(tasks, "sync_clock", lambda: None)
    monkeypatch.setattr(tasks, "check_models", check_models)
    monkeypatch.setattr(runtime, "session_scope", session_scope)
    for sweep in ("sweep_scratch", "sweep_scene_datasets", "sweep_ingest_scratch"):
        monkeypatch.setattr(runtime, sweep, lambda settings: [])
    monkeypatch.setattr(tasks, "_heartbeat_stop", threading.Event())
    with caplog.at_level(logging.INFO, logger=tasks.log.name):
        beating = threading.Thread(target=tasks._beat, args=("w@host", "q", "cpu", models), daemon=True)
        beating.start()
        try:
            assert event.wait(10)
        finally:
            tasks._heartbeat_stop.set()
            beating.join(10)


def test_a_workers_heartbeats_failing_log_one_traceback_then_a_line_each_and_say_when_they_succeed_again(
        monkeypatch, caplog):
    """With the database down, every heartbeat (5 s apart) had logged "worker heartbeat failed" with its whole
    traceback. Now the first failed one is logged with its traceback, the next ones a line each, and the recovery is
    said."""
    import threading
    import types

    from sqlalchemy.exc import OperationalError

    from worker import tasks

    beats, recovered = [], threading.Event()

    @contextlib.contextmanager
    def session_scope():
        beats.append(time.monotonic())
        if len(beats) <= 4:
            raise OperationalError("SELECT worker_heartbeats", {}, Exception("connection refused\nIs it running?"))
        recovered.set()
        yield types.SimpleNamespace(get=lambda model, hostname: types.SimpleNamespace())

    _beat_until(recovered, monkeypatch, caplog, session_scope, lambda settings: {}, {})
    records = [r for r in caplog.records if r.name == tasks.log.name and "heartbeat" in r.getMessage()]
    _assert_one_traceback_then_lines(
        records, "worker w@host: heartbeat failed",
        "worker w@host: heartbeat 4 in a row failed: OperationalError: "
        "(builtins.Exception) connection refused",
        "worker w@host: heartbeats succeed again, after 4 failed in a row")


def test_a_heartbeat_beating_as_its_worker_stops_leaves_the_workers_row_deleted(db, monkeypatch):
    """At shutdown the worker deletes its heartbeat row (it is no longer alive); a beat already under way wrote the
    row again after that delete, so the stopped worker looked alive for one more VOXE_JOB_STALE_TIMEOUT_S. A beat the
    stop overtakes writes nothing."""
    import threading
    import types

    from sqlalchemy import select

    from voxe_service.db import session_scope
    from voxe_service.models import WorkerHeartbeat
    from worker import runtime, tasks

    checks, second_beat, stopped = [], threading.Event(), threading.Event()

    def check_models(settings):
        checks.append(1)
        if len(checks) == 2:  # the second beat, under way as the worker stops
            second_beat.set()
            assert stopped.wait(10)
        return {}

    monkeypatch.setattr(db, "worker_heartbeat_s", 0.01)
    monkeypatch.setattr(tasks, "check_models", check_models)
    for sweep in ("sweep_scratch", "sweep_scene_datasets", "sweep_ingest_scratch"):
        monkeypatch.setattr(runtime, sweep, lambda settings: [])
    monkeypatch.setattr(tasks, "_heartbeat_stop", threading.Event())
    beating = threading.Thread(target=tasks._beat, args=("w@host", "q", "cpu", {}), daemon=True)
    beating.start()
    try:
        assert second_beat.wait(10)
        with session_scope() as session:  # the first beat's row: the worker alive
            assert session.scalars(select(WorkerHeartbeat.hostname)).all() == ["w@host"]
        tasks._stop_heartbeat(sender=types.SimpleNamespace(hostname="w@host"))
    finally:
        stopped.set()
        beating.join(10)
    assert not beating.is_alive()
    with session_scope() as session:
        assert session.scalars(select(WorkerHeartbeat.hostname)).all() == []


def test_a_workers_model_checks_failing_log_one_traceback_then_a_line_each_and_the_last_answer_stands(monkeypatch,
                                                                                                       caplog):
    """A model folder that cannot be read (an NFS cache gone stale) had logged "could not check its models" with its
    whole traceback at every heartbeat. Now the first failed check is logged with its traceback, the next ones a line
    each, and the recovery is said; the heartbeats record the last answer meanwhile."""
    import threading
    import types

    from worker import tasks

    checks, recorded, recovered = [], [], threading.Event()
    answer = {"sds": {"model": "tiny", "present": True}}

    def check_models(settings):
        checks.append(time.monotonic())
        if len(checks) <= 4:
            raise OSError(116, "Stale file handle")
        recovered.set()
        return answer

    @contextlib.contextmanager
    def session_scope():
        row = types.SimpleNamespace()
        yield types.SimpleNamespace(get=lambda model, hostname: row)
        recorded.append(row.models)

    _beat_until(recovered, monkeypatch, caplog, session_scope, check_models, answer)
    records = [r for r in caplog.records if r.name == tasks.log.name and "models" in r.getMessage()]
    _assert_one_traceback_then_lines(
        records, "worker w@host: check of its models failed; the last answer stands",
        "worker w@host: check of its models 4 in a row failed; the last answer stands: "
        "OSError: [Errno 116] Stale file handle",
        "worker w@host: checks of its models succeed again, after 4 failed in a row")
    assert recorded[:4] == [answer] * 4


def test_a_reaper_pass_meeting_a_broker_outage_fails_nothing_and_a_later_pass_sends_the_jobs(db, monkeypatch):
    """The broker refuses every message (a Redis restarting) during a pass: a dead worker's job, an accepted job
    never sent and a sweep's edit never sent had been failed for good, their checkpoints deleted. Now they wait,
    queued with no task id (the evaluation that rides with the edit kept too), nothing is returned to be cleaned
    up, and the first pass after the broker is back sends them, the evaluation with its edit."""
    from kombu.exceptions import OperationalError
    from sqlalchemy import update

    from api.reaper import reap_orphaned_jobs
    from voxe_service.db import session_scope
    from voxe_service.models import Job, utcnow
    from voxe_service.queue import TaskQueue

    timeout = db.job_stale_timeout_s
    scene = add_scene()
    add_heartbeat("dead@host", age_s=2 * timeout)
    interrupted = add_job(scene, "running", 2 * timeout, "dead@host", "edit", run_token="t",
                          run_lease_until=utcnow() - timedelta(seconds=timeout), completed_stages=["reconstruct"])
    never_sent = add_job(scene, "queued", 2 * timeout, task_id=None)
    sweep_edit = add_job(scene, "queued", 2 * timeout, task_id=None, batch_id="b1")
    evaluation = add_job(scene, "queued", 2 * timeout, task_id=None, mode="evaluate", batch_id="b1",
                         source_job_ids=[sweep_edit])
    jobs = [interrupted, never_sent, sweep_edit, evaluation]

    def refused(self, signature):
        raise OperationalError("Error 111 connecting to 127.0.0.1:6379. Connection refused.")

    with monkeypatch.context() as broker_down:
        broker_down.setattr(TaskQueue, "send", refused)
        assert reap_orphaned_jobs(db) == []  # nothing ended: no checkpoints for the API's reaper to delete
    for job_id in jobs:
        job = job_row(job_id)
        assert (job.state, job.task_id, job.error, job.finished_at) == ("queued", None, None, None), job_id
    assert job_row(interrupted).requeues == 1 and job_row(interrupted).run_token is None
    with session_scope() as session:  # the broker is back, as long after
        session.execute(update(Job).where(Job.id.in_(jobs))
                        .values(updated_at=utcnow() - timedelta(seconds=2 * timeout)))
    assert reap_orphaned_jobs(db) == []
    for job_id in jobs:
        job = job_row(job_id)
        assert job.state == "queued" and job.task_id is not None and job.error is None, job_id
    assert job_row(evaluation).task_id == job_row(sweep_edit).task_id
    assert job_row(interrupted).requeues == 1  # sent now without counting the interruption twice


def test_a_lost_message_resend_the_broker_refuses_keeps_the_sweep_evaluation_for_a_later_pass(db, monkeypatch):
    """The reaper's re-send of a sweep's evaluation whose message was taken as lost meets a broker outage: the claim
    had left it queued with no task id, and the next pass failed it as "never handed to the broker with its edit".
    Its task id comes back (as a starting worker's re-send does), and the pass after the broker is back sends it."""
    from kombu.exceptions import OperationalError
    from sqlalchemy import update

    from api.reaper import reap_orphaned_jobs
    from voxe_service.db import session_scope
    from voxe_service.models import Job, utcnow
    from voxe_service.queue import TaskQueue

    lost_after = db.job_lost_message_timeout_s
    scene = add_scene()
    edit = add_job(scene, "succeeded", 3 * lost_after, batch_id="b1",
                   finished_at=utcnow() - timedelta(seconds=2 * lost_after))
    evaluation = add_job(scene, "queued", 2 * lost_after, mode="evaluate", batch_id="b1", source_job_ids=[edit])

    def refused(self, signature):
        raise OperationalError("Error 111 connecting to 127.0.0.1:6379. Connection refused.")

    with monkeypatch.context() as broker_down:
        broker_down.setattr(TaskQueue, "send", refused)
        assert reap_orphaned_jobs(db) == []
    job = job_row(evaluation)
    assert (job.state, job.task_id, job.error) == ("queued", "task", None)
    with session_scope() as session:  # the broker is back, a stale period later
        session.execute(update(Job).where(Job.id == evaluation)
                        .values(updated_at=utcnow() - timedelta(seconds=2 * lost_after)))
    assert reap_orphaned_jobs(db) == []
    job = job_row(evaluation)
    assert job.state == "queued" and job.task_id not in (None, "task") and job.error is None
    assert [e["kind"] for e in events_of(evaluation)] == ["requeued"]  # (the refused re-send none)


def test_a_resend_the_broker_refused_is_not_on_the_timeline_nor_doubles_the_next_wait(db, monkeypatch):
    """The reaper's re-send of a job whose message was taken as lost meets a broker outage: its ``requeued`` event
    ("sent again") had been committed before the send and stayed, so the timeline said a re-send that never
    happened, and the next pass counted it, waiting twice as long before the first real one. A refused re-send
    leaves no event, and the job is sent one period after the refusal; that re-send (an event) doubles the wait."""
    from kombu.exceptions import OperationalError
    from sqlalchemy import update

    import api.reaper as reaper
    from voxe_service.db import session_scope
    from voxe_service.models import Job, utcnow
    from voxe_service.queue import TaskQueue

    lost_after = db.job_lost_message_timeout_s
    monkeypatch.setattr(reaper, "is_sql_broker", lambda url: False)  # a Redis, whose queue the reaper cannot read
    job = add_job(add_scene(), "queued", 2 * lost_after)

    def refused(self, signature):
        raise OperationalError("Error 111 connecting to 127.0.0.1:6379. Connection refused.")

    def reaped(age_in_periods: float):
        """The job after a reaper pass, its last try ``age_in_periods`` VOXE_JOB_LOST_MESSAGE_TIMEOUT_S ago."""
        with session_scope() as session:
            session.execute(update(Job).where(Job.id == job)
                            .values(updated_at=utcnow() - timedelta(seconds=age_in_periods * lost_after)))
        assert reaper.reap_orphaned_jobs(db) == []
        return job_row(job)

    with monkeypatch.context() as broker_down:
        broker_down.setattr(TaskQueue, "send", refused)
        assert (reaped(2).task_id, events_of(job)) == ("task", [])
    sent = reaped(1.5)
    assert sent.task_id not in (None, "task")
    assert [e["kind"] for e in events_of(job)] == ["requeued"]
    assert reaped(1.5).task_id == sent.task_id  # the next waits twice as long
    assert reaped(2.5).task_id != sent.task_id and len(events_of(job)) == 2


def test_a_job_canceled_while_the_broker_takes_its_resend_ends_its_timeline_canceled(db, monkeypatch):
    """A job canceled while a re-send of it was with the broker had a ``requeued`` event (and webhook) after its
    ``canceled`` one: a timeline going on past its end. The message goes (its stages skip the canceled job), and the
    timeline ends with the cancel."""
    from api.services.jobs import request_cancel
    from voxe_service.db import session_scope
    from voxe_service.queue import TaskQueue, get_queue, send_queued_again

    job = add_job(add_scene(), "queued", 0, task_id=None)
    send = TaskQueue.send

    def canceled_meanwhile(self, signature):
        with session_scope() as other:  # the user's cancel, committed while the broker takes the message
            request_cancel(session=other, job_ids=[job])
        return send(self, signature)

    monkeypatch.setattr(TaskQueue, "send", canceled_meanwhile)
    with session_scope() as session:
        assert send_queued_again(session, get_queue(), job, sent_as=None, reason="sent by the reaper")
    assert (job_row(job).state, job_row(job).message) == ("canceled", "canceled while queued")
    assert [e["kind"] for e in events_of(job)] == ["canceled"]


def test_a_job_canceled_just_after_its_resend_was_claimed_keeps_its_cancels_message_and_is_not_sent(db, monkeypatch):
    """A cancel committed between a re-send's claim and its reading of the job found the job canceled, and the
    re-send went on: its message replaced "canceled while queued" (None, from the reaper, wiped it) and a chain
    was sent for the canceled job. The re-send now stops there, nothing sent."""
    from sqlalchemy import event

    from api.services.jobs import request_cancel
    from voxe_service.db import session_scope
    from voxe_service.queue import TaskQueue, get_queue, send_queued_again

    job = add_job(add_scene(), "queued", 0, task_id=None)
    sent = []
    monkeypatch.setattr(TaskQueue, "send", lambda self, signature: sent.append(signature) or "task")
    with session_scope() as session:
        def canceled_after_the_claim(_session):
            with session_scope() as other:
                request_cancel(session=other, job_ids=[job])

        event.listen(session, "after_commit", canceled_after_the_claim, once=True)
        assert not send_queued_again(session, get_queue(), job, sent_as=None, reason="sent by the reaper")
    assert (job_row(job).state, job_row(job).message, sent) == ("canceled", "canceled while queued", [])
    assert [e["kind"] for e in events_of(job)] == ["canceled"]


def test_a_refused_resend_gives_the_task_id_back_only_to_the_job_as_it_claimed_it(db, monkeypatch):
    """A refused re-send gave the job its old task id back wherever it had none, though another sender had taken
    it meanwhile (the reaper sending again a dead worker's job, queued with no task id after its own refusal): the
    job then looked sent, its old message's, and waited to be taken as lost rather than being sent as never sent."""
    from kombu.exceptions import OperationalError
    from sqlalchemy import update

    from voxe_service.db import session_scope
    from voxe_service.models import Job, utcnow
    from voxe_service.queue import QueueUnavailable, TaskQueue, get_queue, send_queued_again

    job = add_job(add_scene(), "queued", 0)

    def taken_then_refused(self, signature):
        with session_scope() as other:  # another sender's claim of the job, its send refused too
            other.execute(update(Job).where(Job.id == job).values(task_id=None, updated_at=utcnow()))
        raise OperationalError("Connection refused.")

    monkeypatch.setattr(TaskQueue, "send", taken_then_refused)
    with session_scope() as session, pytest.raises(QueueUnavailable):
        send_queued_again(session, get_queue(), job, sent_as="task", reason="taken as lost")
    assert (job_row(job).state, job_row(job).task_id, events_of(job)) == ("queued", None, [])


def test_a_broker_refusal_names_the_queue_unavailable_and_leaves_the_brokers_words_to_the_log(db, monkeypatch,
                                                                                             caplog):
    """A refused send had put the broker's own text (the embedded broker's SQL statement and parameters, a Redis
    address) into the jobs' error and timeline: they read the cause, and the log keeps the broker's words."""
    import sqlite3

    from sqlalchemy.exc import OperationalError

    from voxe_service.db import session_scope
    from voxe_service.models import Job
    from voxe_service.queue import QueueUnavailable, TaskQueue, dispatch_job, get_queue

    statement = "INSERT INTO kombu_message (queue_id, visible, sent_at, payload, version) VALUES (?, ?, ?, ?, ?)"

    def refused(self, signature):
        raise OperationalError(statement, (1, 1, "2026-12-06", "{}", 1), sqlite3.OperationalError("database is locked"))

    scene = add_scene()
    edit = add_job(scene, "queued", 0, task_id=None, batch_id="b")
    evaluation = add_job(scene, "queued", 0, task_id=None, mode="evaluate", batch_id="b", source_job_ids=[edit])
    monkeypatch.setattr(TaskQueue, "send", refused)
    with (caplog.at_level(logging.ERROR, logger="voxe.queue"), session_scope() as session,
          pytest.raises(QueueUnavailable) as refusal):
        dispatch_job(session, get_queue(), session.get(Job, edit))
    reason = "could not queue the job: the job queue is unavailable"
    assert str(refusal.value) == reason
    for job_id in (edit, evaluation):
        assert (job_row(job_id).state, job_row(job_id).error) == ("failed", reason)
        assert [e["detail"] for e in events_of(job_id)] == [reason]
    assert "INSERT INTO kombu_message" in caplog.text and "database is locked" in caplog.text


def test_a_stage_whose_next_message_the_broker_refuses_leaves_its_job_for_the_reaper_to_send(db, monkeypatch):
    """Celery sends a chain's next message after the task returns; refused, the task fails with the job running
    between stages, held by no run, which the reaper leaves alone on a live worker (it may be waiting its turn).
    The worker says so: the job is queued with no task id (sent at once if the broker takes it), and the reaper's
    pass once the broker is back sends it, its done stages kept, no re-queue counted. A job that had ended carried
    only its sweep's evaluation in the lost message: it is sent alone. A task that fails otherwise touches nothing."""
    from celery import Celery
    from kombu.exceptions import OperationalError
    from sqlalchemy import update

    from api.reaper import reap_orphaned_jobs
    from voxe_service.db import session_scope
    from voxe_service.models import Job, utcnow
    from worker import tasks

    timeout = db.job_stale_timeout_s
    add_heartbeat("alive@host", age_s=1)
    scene = add_scene()
    # The redelivered edit message of a job whose edit is done: skipped, and its chain goes on to refine.
    job_id = add_job(scene, "running", 0, "alive@host", "edit", mode="local", completed_stages=["reconstruct", "edit"])
    ended = add_job(scene, "succeeded", 0, "alive@host", "export", batch_id="b", task_id="chain",
                    completed_stages=["reconstruct", "edit", "export"])
    evaluation = add_job(scene, "queued", 0, mode="evaluate", batch_id="b", task_id="chain", source_job_ids=[ended])
    refusals = []

    def refused(*args, **kwargs):
        refusals.append(args)
        raise OperationalError("Error 111 connecting to 127.0.0.1:6379. Connection refused.")

    with monkeypatch.context() as broker_down:
        broker_down.setattr(Celery, "send_task", refused)
        result = tasks.edit_task.apply(args=(job_id,), link=tasks.refine_task.si(job_id), throw=False)
        assert result.state == "FAILURE" and isinstance(result.result, OperationalError)
    job = job_row(job_id)
    assert (job.state, job.task_id, job.run_token, job.requeues, job.error) == ("queued", None, None, 0, None)
    # The user reads the cause; the broker's own words (its address here) stay in the log.
    reason = "the message of the stage after edit could not be sent: the job queue is unavailable"
    assert job.message == f"re-queued: {reason}"
    assert [(e["kind"], e["detail"]) for e in events_of(job_id)] == [("requeued", reason)]
    with session_scope() as session:  # the broker is back, a stale window later
        session.execute(update(Job).where(Job.id == job_id).values(updated_at=utcnow() - timedelta(seconds=2 * timeout)))
    assert reap_orphaned_jobs(db) == []
    sent = job_row(job_id)
    assert (sent.state, sent.completed_stages, sent.requeues) == ("queued", ["reconstruct", "edit"], 0)
    assert sent.task_id is not None

    send_task, sends = Celery.send_task, []

    def refused_once(self, *args, **kwargs):  # the ended job's evaluation, riding after its export: refused once
        sends.append(args)
        if len(sends) == 1:
            raise OperationalError("Error 111 connecting to 127.0.0.1:6379. Connection refused.")
        return send_task(self, *args, **kwargs)

    with monkeypatch.context() as broker_blip:
        broker_blip.setattr(Celery, "send_task", refused_once)
        assert tasks.export_task.apply(args=(ended,), link=tasks.evaluate_task.si(evaluation), throw=False).failed()
    assert job_row(evaluation).task_id not in (None, "chain") and job_row(evaluation).state == "queued"
    assert (job_row(ended).state, job_row(ended).error) == ("succeeded", None)  # sent alone, the job's end standing
    # A stage's task failing otherwise (its job held by a run, or its stage not done) leaves the job as it is.
    held = add_job(scene, "running", 0, "alive@host", "edit", run_token="t", completed_stages=["reconstruct", "edit"])
    undone = add_job(scene, "running", 0, "alive@host", "edit", completed_stages=["reconstruct"])
    for other in (held, undone):
        tasks._next_stage_unsent(sender=tasks.edit_task, args=(other,), exception=RuntimeError("boom"))
        assert (job_row(other).state, events_of(other)) == ("running", []), other


def test_a_cancel_between_stages_ends_the_job_at_the_next_reaper_pass(db):
    """A cancel request flags a running job (only queued ones end at once); one between stages, whose next message
    was lost or waits, has no run to see the flag: the reaper's next pass ends it canceled, not waiting
    VOXE_JOB_STALE_TIMEOUT_S (the request refreshed it); one a run holds is left to stop at its next check."""
    from api.reaper import reap_orphaned_jobs
    from api.services.jobs import request_cancel
    from voxe_service.db import session_scope
    from voxe_service.models import utcnow

    scene = add_scene()
    add_heartbeat("alive@host", age_s=1)
    between = add_job(scene, "running", 0, "alive@host", "edit", completed_stages=["reconstruct", "edit"])
    held = add_job(scene, "running", 0, "alive@host", "edit", run_token="t",
                   run_lease_until=utcnow() + timedelta(seconds=60))
    given_back = add_job(scene, "running", 0, "alive@host", "edit", completed_stages=["reconstruct"])  # (an outage
    with session_scope() as session:  # kept its run from recording the cancel: it released the job, edit not done)
        request_cancel(session=session, job_ids=[between, held, given_back])
    assert sorted(reap_orphaned_jobs(db)) == sorted([between, given_back])
    ended = job_row(between)
    assert (ended.state, ended.message, ended.error) == ("canceled", "canceled: asked between stages, after edit", None)
    assert (job_row(given_back).state, job_row(given_back).message) == ("canceled", "canceled: asked during edit")
    assert ended.finished_at is not None and [e["kind"] for e in events_of(between)] == ["canceled"]
    assert (job_row(held).state, job_row(held).cancel_requested) == ("running", True)


def test_machines_whose_clocks_disagree_read_leases_and_heartbeats_on_the_database_clock(db, monkeypatch):
    """A worker whose clock runs 100 s behind takes a job and beats; an API whose clock runs 100 s ahead reaps.
    Each process measures its offset to the database server's clock (sync_clock), so the API sees the worker
    alive, the job's progress recent and its hold live: nothing is re-queued. (Read on their own clocks, the
    hold would have lapsed 40 s before and the heartbeat be 200 s old: the job would be sent again.) SQLite
    lives on one machine: its offset is zero."""
    from sqlalchemy import text

    from api.reaper import reap_orphaned_jobs
    from voxe_service import models
    from voxe_service.db import get_engine, sync_clock
    from worker.runtime import begin_stage

    skew = {"s": 0.0}
    real_now = models.system_now
    monkeypatch.setattr(models, "system_now", lambda: real_now() + timedelta(seconds=skew["s"]))
    if get_engine().dialect.name == "sqlite":
        skew["s"] = -100.0
        assert sync_clock() == timedelta(0)
        assert abs((models.utcnow() - real_now()).total_seconds() + 100) < 1  # one machine, one clock
        return

    def database_clock():
        with get_engine().connect() as connection:
            return connection.execute(text("SELECT clock_timestamp()")).scalar_one()

    monkeypatch.setattr(db, "job_stale_timeout_s", 30.0)
    job_id = add_job(add_scene(), "queued", 0)
    skew["s"] = -100.0  # the worker's machine
    begin_stage(job_id, "edit", "w@host", "cpu", db)  # measures its offset first
    assert abs((models.utcnow() - database_clock()).total_seconds()) < 1
    add_heartbeat("w@host", age_s=0)
    skew["s"] = 100.0  # the API's machine: a reaper pass measures first
    offset = sync_clock()
    assert abs(offset.total_seconds() + 100) < 1 and abs((models.utcnow() - database_clock()).total_seconds()) < 1
    held = job_row(job_id)
    assert held.run_lease_until > models.utcnow() + timedelta(seconds=db.stage_lease_s - 5)
    assert reap_orphaned_jobs(db) == []
    after = job_row(job_id)
    assert (after.state, after.run_token, after.requeues) == ("running", held.run_token, 0)
    assert [e["kind"] for e in events_of(job_id)] == ["stage_started"]  # no "requeued"


def test_a_redis_that_accepts_and_never_answers_refuses_a_submission_within_its_timeouts(tmp_path, monkeypatch):
    """A hung or partitioned Redis (the TCP connection made, no reply ever): a send had blocked for ever, so a
    POST held its request, and every /readyz left a thread behind. Now each try times out after
    VOXE_BROKER_SOCKET_TIMEOUT_S, and after Celery's publish retries the send fails as a broker that refuses."""
    import time

    from service_helpers import outcome_within, silent_server
    from voxe_service.queue import get_queue

    with silent_server() as (port, accepted):
        for key, value in service_env(tmp_path, f"redis://127.0.0.1:{port}/0",
                                      VOXE_BROKER_SOCKET_TIMEOUT_S="0.5").items():
            monkeypatch.setenv(key, value)
        reset_service_caches()
        try:
            queue, started = get_queue(), time.monotonic()
            outcome = outcome_within(lambda: queue.send(queue.stage_chain("job-1", "global")), 30)
            assert outcome, "the send still waited on the silent server after 30 s"
            assert "Timeout reading from 127.0.0.1" in str(outcome[0]) and accepted, outcome
            assert time.monotonic() - started < 15  # four tries of 0.5 s
        finally:
            reset_service_caches()


def test_an_artifact_a_stalled_run_records_as_its_job_is_taken_over_lands_before_the_takeover(db, tmp_path,
                                                                                              monkeypatch):
    """A stalled run (its lease lapsing, no renewals) records an artifact just as another run takes its job over:
    the takeover waits for the record, so the artifact is on the timeline before the new run's start. On SQLite
    the superseded check's FOR UPDATE had locked nothing: the takeover committed between the check and the
    record, and the stalled run's artifact was recorded after it."""
    import threading
    import time

    from voxe_service.storage import get_storage
    from worker import runtime

    monkeypatch.setattr(db, "stage_lease_s", 0.2)
    job_id = add_job(add_scene(), "queued", 0, completed_stages=["reconstruct"])
    stalled = runtime.begin_stage(job_id, "edit", "a@host", "cpu", db)
    grid = tmp_path / "edited_grid.safetensors"
    grid.write_bytes(b"grid")
    checked, check, calls = threading.Event(), runtime._refuse_if_superseded, []

    def slow_check(*args):
        check(*args)
        calls.append(threading.current_thread())
        if calls.count(publisher) == 2:  # its check as it records (the first is before the upload)
            checked.set()
            time.sleep(0.5)

    def publish():
        runtime._HOLDING.set((job_id, stalled.run_token))  # the stalled run's stage, renewing nothing
        runtime.publish_artifact(job_id, "edited_grid.safetensors", grid, "grid", get_storage(db))

    monkeypatch.setattr(runtime, "_refuse_if_superseded", slow_check)
    publisher = threading.Thread(target=publish)
    publisher.start()
    assert checked.wait(30)
    runtime.begin_stage(job_id, "edit", "b@host", "cpu", db)  # the stalled run's lease has lapsed
    publisher.join(30)
    kinds = [e["kind"] for e in events_of(job_id)]
    starts = [i for i, kind in enumerate(kinds) if kind == "stage_started"]  # the stalled run's, the new run's
    assert len(starts) == 2 and starts[0] < kinds.index("artifact") < starts[1], kinds


@pytest.mark.parametrize("database_url", ["postgres"], indirect=True)
def test_a_result_written_while_a_submission_holds_its_key_neither_waits_nor_deadlocks(db):
    """Job submission locks its key's row, then the scene's. A result merge that updated the job's row twice
    (a lock by writing, then the result) had its foreign keys checked again on PostgreSQL: it waited for the
    key's row, and the submission's scene lock then deadlocked with it."""
    import threading

    from sqlalchemy import create_engine, text

    from voxe_service.models import LOCAL_KEY_ID
    from worker import runtime

    scene, engine = add_scene(), create_engine(db.database_url)
    job_id, merged = add_job(scene, "running", 0), threading.Event()
    try:
        with engine.connect() as submission:
            submission.execute(text("SELECT id FROM api_keys WHERE id = :key FOR UPDATE"), {"key": LOCAL_KEY_ID})
            writer = threading.Thread(target=lambda: (runtime.merge_job_result(job_id, {"k": 1}), merged.set()))
            writer.start()
            assert merged.wait(10), "the merge waited for the submission's lock on its key"
            submission.execute(text("SET lock_timeout = '5s'"))
            submission.execute(text("SELECT id FROM scenes WHERE id = :scene FOR UPDATE"), {"scene": scene})
            submission.rollback()
            writer.join(10)
    finally:
        engine.dispose()
    assert job_row(job_id).result == {"k": 1}


def test_stages_writing_a_jobs_result_at_once_lose_nothing(db, monkeypatch):
    """Four writers merge their own key into ``Job.result`` at once, each pausing between its read and its write
    as a busy machine may: every key is kept. On SQLite, which has no row locks, the read-modify-write had lost
    three of the four (PostgreSQL's FOR UPDATE held)."""
    import threading
    import time

    from worker import runtime

    job_id = add_job(add_scene(), "running", 0)
    check = runtime._refuse_if_superseded

    def slow_check(*args):
        check(*args)
        time.sleep(0.3)

    monkeypatch.setattr(runtime, "_refuse_if_superseded", slow_check)
    barrier = threading.Barrier(4)

    def merge(i: int) -> None:
        barrier.wait()
        runtime.merge_job_result(job_id, {f"k{i}": i})

    writers = [threading.Thread(target=merge, args=(i,)) for i in range(4)]
    for writer in writers:
        writer.start()
    for writer in writers:
        writer.join(60)
    assert runtime.load_job(job_id).result == {"k0": 0, "k1": 1, "k2": 2, "k3": 3}


def test_a_cancel_that_lands_between_stages_ends_the_job_when_the_next_stage_begins(db):
    """The cancel is seen as the next stage begins: that stage is skipped and the job ends canceled (the cancel
    was once rolled back with the skip, leaving the job running for ever)."""
    from voxe_service.db import session_scope
    from voxe_service.models import Job
    from worker.runtime import JobSkipped, begin_stage

    job_id = add_job(add_scene(), "running", 0, "w@host", "reconstruct")
    with session_scope() as session:
        job = session.get(Job, job_id)
        job.completed_stages, job.cancel_requested = ["reconstruct"], True
    with pytest.raises(JobSkipped, match="canceled"):
        begin_stage(job_id, "edit", "w@host", "cpu", db)
    ended = job_row(job_id)
    assert ended.state == "canceled" and ended.message == "canceled before edit" and ended.finished_at is not None


@pytest.mark.parametrize("stage", ["export", "evaluate"])
def test_a_cancel_during_a_final_stages_last_uploads_ends_the_job_canceled(db, monkeypatch, stage):
    """A cancel that landed after the final stage's last cancel check (while it uploaded its last artifacts) was
    answered as accepted (the job running, flagged), and the job then ended succeeded. It ends canceled, as during
    the stage; a cancel asked once the job succeeded is refused (409), the job left succeeded."""
    from fastapi import HTTPException

    from api.services.jobs import cancel_job, request_cancel
    from voxe_service.db import session_scope
    from voxe_service.models import ApiKey
    from worker import tasks

    def body(job, *_args):
        with session_scope() as session:
            request_cancel(session=session, job_ids=[job.id])  # (the API's cancel of the running job)

    monkeypatch.setattr(tasks, "_check_job_can_start", lambda job, settings: None)
    monkeypatch.setattr(tasks, "_export" if stage == "export" else "run_evaluation", body)
    done = ["reconstruct", "edit"] if stage == "export" else []
    job_id = add_job(add_scene(), "queued", 0, mode="global" if stage == "export" else "evaluate",
                     completed_stages=done)
    task = tasks.export_task if stage == "export" else tasks.evaluate_task
    assert task.apply(args=(job_id,)).get() == {"job_id": job_id, "stage": stage, "state": "canceled"}
    job = job_row(job_id)
    assert (job.state, job.message, job.completed_stages) == ("canceled", f"canceled during {stage}", done)
    assert [e["kind"] for e in events_of(job_id)] == ["stage_started", "canceled"]

    succeeded = add_job(add_scene(), "queued", 0, completed_stages=["reconstruct", "edit"])
    monkeypatch.setattr(tasks, "_export", lambda *_args: None)
    assert tasks.export_task.apply(args=(succeeded,)).get()["state"] == "done"
    with session_scope() as session, pytest.raises(HTTPException) as refused:
        cancel_job(session=session, key=session.get(ApiKey, job_row(succeeded).owner_key_id), job_id=succeeded)
    assert refused.value.status_code == 409 and job_row(succeeded).state == "succeeded"


def listed_artifacts(job_id: str) -> dict[str, str]:
    """The job's listed artifacts: name -> storage key."""
    from sqlalchemy import select

    from voxe_service.db import session_scope
    from voxe_service.models import Artifact

    with session_scope() as session:
        return dict(session.execute(select(Artifact.name, Artifact.key).where(Artifact.job_id == job_id)).all())


@pytest.mark.parametrize("seen", ["at the mesh's check", "at the stage's end", "by the redelivery"])
def test_a_job_canceled_during_its_export_lists_none_of_the_exports_outputs(db, tmp_path, monkeypatch, seen):
    """A cancel landing just after the export published its first set (the turntable) ended the job canceled
    with the turntables, the views (and, seen at the stage's end, the mesh) listed: half an export. The stage's
    outputs are withdrawn as it ends canceled, their rows and then their bytes, whether the cancel is seen at the
    mesh's check, at the stage's end, or by the redelivery of a run a database outage stopped after it; the
    outputs of the stages it completed, and the preview, stay listed and whole."""
    from sqlalchemy.exc import OperationalError

    from api.services.jobs import request_cancel
    from voxe_service.db import session_scope
    from voxe_service.storage import get_storage
    from worker import runtime, tasks

    storage = get_storage(db)

    def publish(job_id: str, name: str, kind: str) -> None:
        (tmp_path / name).write_bytes(f"{job_id} {name}".encode())
        runtime.publish_artifact(job_id, name, tmp_path / name, kind, storage)

    def edit(job, *_args):
        publish(job.id, "edited_grid.safetensors", "grid")
        publish(job.id, "preview.png", "preview")

    def export(job, settings, *_args):  # as tasks._export publishes
        publish(job.id, "render_000.png", "render")
        for name in ("turntable.mp4", "turntable.gif"):  # (one set in tasks._export)
            publish(job.id, name, "video")
        with session_scope() as session:  # the fault: the user's cancel, just after the turntables are listed
            request_cancel(session=session, job_ids=[job.id])
        if seen == "by the redelivery":  # the run's end refused by an outage: it gives the job back unended
            raise OperationalError("UPDATE jobs", {}, Exception("server closed the connection unexpectedly"))
        runtime.StageCallbacks(job, "export", settings).callbacks.check_cancel("export")  # the mesh's check
        for name in ("mesh.ply", "mesh.glb", "mesh.obj", "mesh.mtl"):  # (one set in tasks._export)
            publish(job.id, name, "mesh")

    monkeypatch.setattr(tasks, "_check_job_can_start", lambda job, settings: None)
    monkeypatch.setattr(tasks, "_edit", edit)
    monkeypatch.setattr(tasks, "_export", export)
    monkeypatch.setattr(runtime.StageCallbacks, "should_cancel",
                        lambda callbacks: seen == "at the mesh's check" and runtime.load_job(job_id).cancel_requested)
    job_id = add_job(add_scene(), "queued", 0, completed_stages=["reconstruct"])
    assert tasks.edit_task.apply(args=(job_id,)).get()["state"] == "done"
    kept = listed_artifacts(job_id)
    assert set(kept) == {"edited_grid.safetensors", "preview.png"}
    result = tasks.export_task.apply(args=(job_id,), throw=False)
    if seen == "by the redelivery":
        assert result.state == "REJECTED" and result.result.requeue, result.result  # back to the queue
        assert set(listed_artifacts(job_id)) > set(kept)  # (the stopped run's outputs, listed until the job ends)
        assert "canceled" in tasks.export_task.apply(args=(job_id,)).get()["skipped"]
    else:
        assert result.get() == {"job_id": job_id, "stage": "export", "state": "canceled"}
    job = job_row(job_id)
    assert (job.state, job.message, job.completed_stages) == ("canceled", "canceled during export",
                                                              ["reconstruct", "edit"])
    assert listed_artifacts(job_id) == kept
    for name, key in kept.items():
        assert b"".join(storage.open_range(key)) == f"{job_id} {name}".encode()
    assert storage.list(f"jobs/{job_id}/") == sorted(kept.values())  # the withdrawn outputs' bytes are gone


def test_a_worker_dying_as_it_withdraws_a_canceled_evaluations_outputs_leaves_none_listed(db, tmp_path, monkeypatch):
    """A cancel landing as the evaluation published its results (after its last check) ended it canceled with
    evaluation.json and its rings listed. They are withdrawn: their rows go with the job's ending, in one
    transaction, and their bytes after; a worker dying between the two leaves bytes no row lists, never a listed
    artifact whose bytes are gone."""
    from api.services.jobs import request_cancel
    from voxe_service.db import session_scope
    from voxe_service.storage import get_storage
    from worker import runtime, tasks

    class WorkerKilled(BaseException):
        pass

    storage = get_storage(db)

    def evaluation(job, *_args):  # as worker.evaluation publishes: one set, after the last cancel check
        for name in ("ring_initial_000.png", "evaluation.json", "evaluation.md"):
            (tmp_path / name).write_bytes(name.encode())
        runtime.publish_artifacts(job.id, [(name, tmp_path / name, kind) for name, kind in (
            ("ring_initial_000.png", "render"), ("evaluation.json", "evaluation"), ("evaluation.md", "evaluation"))],
            storage)
        with session_scope() as session:
            request_cancel(session=session, job_ids=[job.id])

    def killed(key: str) -> None:
        raise WorkerKilled(f"the worker died deleting {key}")

    monkeypatch.setattr(tasks, "_check_job_can_start", lambda job, settings: None)
    monkeypatch.setattr(tasks, "run_evaluation", evaluation)
    monkeypatch.setattr(storage, "delete", killed)
    job_id = add_job(add_scene(), "queued", 0, mode="evaluate")
    with pytest.raises(WorkerKilled):
        tasks.evaluate_task.apply(args=(job_id,))
    job = job_row(job_id)
    assert (job.state, job.message) == ("canceled", "canceled during evaluate")
    assert listed_artifacts(job_id) == {}
    assert len(storage.list(f"jobs/{job_id}/")) == 3  # unlisted, deleted with the job


def _job_mid_export_with_outputs(db, tmp_path) -> tuple[str, dict[str, str]]:
    """A job whose export has published a render and listed the shared reconstruction's grid, both stored: the
    job's id and its listed artifacts."""
    from voxe_service.storage import get_storage
    from worker import runtime

    storage = get_storage(db)
    job_id = add_job(add_scene(), "queued", 0, completed_stages=["reconstruct", "edit"])
    runtime.begin_stage(job_id, "export", "a@host", "cpu", db)
    for name, key in (("render_000.png", None), ("initial_grid.safetensors", "reconstructions/r/grid.safetensors")):
        (tmp_path / name).write_bytes(name.encode())
        if key:
            storage.put_file(key, tmp_path / name)
        runtime.publish_artifact(job_id, name, tmp_path / name, "render", storage, key=key)
    return job_id, listed_artifacts(job_id)


def test_ending_a_job_canceled_withdraws_its_unfinished_stages_outputs_rows_then_bytes_once_committed(db, tmp_path):
    """finish_jobs itself withdraws what a job ended canceled published in its unfinished stage (its four callers each
    did, after it): the rows go in the ending's transaction, the bytes only once it commits, and only the job's own
    (the shared reconstruction's grid, listed by the job, stays stored)."""
    from voxe_service.db import session_scope
    from voxe_service.jobs import finish_jobs
    from voxe_service.models import CANCELED, Artifact
    from voxe_service.storage import get_storage

    storage = get_storage(db)
    job_id, listed = _job_mid_export_with_outputs(db, tmp_path)
    with session_scope() as session:
        assert finish_jobs(session, [job_id], CANCELED, message="canceled") == [job_id]
        assert session.query(Artifact).filter_by(job_id=job_id).all() == []  # in the ending's transaction
        assert storage.exists(listed["render_000.png"])  # not yet committed: the bytes stay
    assert listed_artifacts(job_id) == {}
    assert not storage.exists(listed["render_000.png"])
    assert storage.exists(listed["initial_grid.safetensors"])


@pytest.mark.parametrize("undone", ["rolled back", "rolled back, then the session commits something else",
                                    "its session closed uncommitted", "in a savepoint rolled back",
                                    "in a savepoint released, its transaction rolled back"])
def test_a_canceled_ending_that_is_not_committed_withdraws_nothing(db, tmp_path, undone):
    """A canceled ending rolled back (or never committed) deletes no bytes, then or at a later commit of the same
    session: its rows are listed again, and their bytes must be there."""
    from sqlalchemy import update

    from voxe_service.db import get_sessionmaker
    from voxe_service.jobs import finish_jobs
    from voxe_service.models import CANCELED, Job
    from voxe_service.storage import get_storage

    storage = get_storage(db)
    job_id, listed = _job_mid_export_with_outputs(db, tmp_path)
    other = add_job(add_scene(), "queued", 0)
    with get_sessionmaker()() as session:
        if undone == "in a savepoint rolled back":
            savepoint = session.begin_nested()
            assert finish_jobs(session, [job_id], CANCELED, message="canceled") == [job_id]
            savepoint.rollback()
        elif undone == "in a savepoint released, its transaction rolled back":
            session.execute(update(Job).where(Job.id == other).values(message="first"))  # (SQLite: a transaction
            with session.begin_nested():  # before the savepoint, whose release would otherwise commit)
                assert finish_jobs(session, [job_id], CANCELED, message="canceled") == [job_id]
            session.rollback()
        else:
            assert finish_jobs(session, [job_id], CANCELED, message="canceled") == [job_id]
            if undone == "its session closed uncommitted":
                session.close()
            else:
                session.rollback()
        if undone != "rolled back":
            session.execute(update(Job).where(Job.id == other).values(message="something else"))
            session.commit()
    assert job_row(job_id).state == "running"
    assert listed_artifacts(job_id) == listed
    assert all(storage.exists(key) for key in listed.values())


def test_a_canceled_ending_in_a_savepoint_discards_its_bytes_once_the_transaction_commits(db, tmp_path):
    """A savepoint's release is no commit: the bytes it withdrew go when the transaction holding it commits."""
    from voxe_service.db import get_sessionmaker
    from voxe_service.jobs import finish_jobs
    from voxe_service.models import CANCELED
    from voxe_service.storage import get_storage

    storage = get_storage(db)
    job_id, listed = _job_mid_export_with_outputs(db, tmp_path)
    with get_sessionmaker()() as session:
        with session.begin_nested():
            assert finish_jobs(session, [job_id], CANCELED, message="canceled") == [job_id]
        assert storage.exists(listed["render_000.png"])
        session.commit()
    assert listed_artifacts(job_id) == {}
    assert not storage.exists(listed["render_000.png"])
    assert storage.exists(listed["initial_grid.safetensors"])


def test_a_storage_refusing_a_withdrawn_outputs_delete_leaves_the_committed_ending_unraised(db, tmp_path, monkeypatch,
                                                                                             caplog):
    """The bytes go after the ending has committed: a storage refusing their delete is logged, the ending stands and
    its caller sees no error (the bytes, listed by no row, go with the job)."""
    from voxe_service.models import CANCELED
    from voxe_service.storage import StorageUnavailable, get_storage
    from worker import runtime

    storage = get_storage(db)
    job_id, listed = _job_mid_export_with_outputs(db, tmp_path)

    def refused(key: str) -> None:
        raise StorageUnavailable(f"S3 bucket 'voxe': SlowDown when deleting {key}")

    monkeypatch.setattr(storage, "delete", refused)
    with caplog.at_level(logging.WARNING, logger="voxe.storage"):
        assert runtime.finish_job(job_id, CANCELED, message="canceled during export")
    assert job_row(job_id).state == "canceled" and listed_artifacts(job_id) == {}
    assert storage.exists(listed["render_000.png"])
    assert f"could not delete the stored object {listed['render_000.png']}" in caplog.text


@pytest.mark.parametrize("asked", ["before the reaper's pass", "once the reaper re-queued it"])
def test_a_job_whose_worker_died_mid_export_canceled_lists_none_of_the_exports_outputs(db, tmp_path, monkeypatch,
                                                                                       asked):
    """A job whose worker died after its export published the turntable ends canceled by the reaper (its cancel
    asked while it ran) or by the API (asked once the reaper re-queued it): either way it listed the dead run's
    turntable. The interrupted stage's outputs are withdrawn with the ending, rows then bytes; the completed
    edit's grid and the preview stay."""
    from sqlalchemy import update

    from api.reaper import reap_orphaned_jobs
    from api.services.jobs import cancel_job, request_cancel
    from voxe_service.db import session_scope
    from voxe_service.models import ApiKey, Job, utcnow
    from voxe_service.storage import get_storage
    from worker import runtime, tasks

    storage = get_storage(db)

    def publish(job_id: str, name: str, kind: str) -> None:
        (tmp_path / name).write_bytes(name.encode())
        runtime.publish_artifact(job_id, name, tmp_path / name, kind, storage)

    def edit(job, *_args):
        publish(job.id, "edited_grid.safetensors", "grid")
        publish(job.id, "preview.png", "preview")

    monkeypatch.setattr(tasks, "_check_job_can_start", lambda job, settings: None)
    monkeypatch.setattr(tasks, "_edit", edit)
    job_id = add_job(add_scene(), "queued", 0, completed_stages=["reconstruct"])
    assert tasks.edit_task.apply(args=(job_id,)).get()["state"] == "done"
    kept = listed_artifacts(job_id)
    runtime.begin_stage(job_id, "export", "dead@host", "cpu", db)
    publish(job_id, "turntable.mp4", "video")  # ... and the worker died
    if asked == "before the reaper's pass":
        with session_scope() as session:
            request_cancel(session=session, job_ids=[job_id])
    add_heartbeat("dead@host", age_s=2 * db.job_stale_timeout_s)
    long_ago = utcnow() - timedelta(seconds=2 * db.job_stale_timeout_s)
    with session_scope() as session:
        session.execute(update(Job).where(Job.id == job_id).values(updated_at=long_ago, run_lease_until=long_ago))
    if asked == "before the reaper's pass":
        assert reap_orphaned_jobs(db) == [job_id]
    else:
        assert reap_orphaned_jobs(db) == [] and job_row(job_id).state == "queued"
        with session_scope() as session:
            cancel_job(session=session, key=session.get(ApiKey, job_row(job_id).owner_key_id), job_id=job_id)
    assert job_row(job_id).state == "canceled"
    assert listed_artifacts(job_id) == kept
    assert storage.list(f"jobs/{job_id}/") == sorted(kept.values())


@pytest.mark.parametrize("ender", ["its redelivery, canceled", "the reaper, canceled", "the reaper, at the limit"])
def test_a_stalled_run_publishes_nothing_into_the_job_another_ended(db, tmp_path, ender):
    """A run whose lease lapsed with its process alive (stalled) while its job was ended (canceled by its redelivery's
    start or the reaper, its unfinished stage's outputs withdrawn, or failed at the re-queue limit) went on
    publishing into the ended job when it woke: the ending left its hold (``run_token``), which was all the
    publication checked, so a canceled job listed an output of the stage it was canceled in. The ending releases
    the hold: the stalled run's publication and result writes are refused (RunSuperseded) and list nothing."""
    from sqlalchemy import update

    from api.reaper import reap_orphaned_jobs
    from api.services.jobs import request_cancel
    from voxe_service.db import session_scope
    from voxe_service.models import Job, utcnow
    from voxe_service.storage import get_storage
    from worker import runtime

    storage = get_storage(db)

    def publish(name: str, kind: str) -> None:
        (tmp_path / name).write_bytes(name.encode())
        runtime.publish_artifact(job_id, name, tmp_path / name, kind, storage)

    job_id = add_job(add_scene(), "queued", 0, completed_stages=["reconstruct", "edit"],
                     requeues=db.job_max_requeues if ender.endswith("at the limit") else 0)
    stalled = runtime.begin_stage(job_id, "export", "a@host", "cpu", db)
    outside = runtime._HOLDING.set((job_id, stalled.run_token))  # this thread is the stalled run's
    try:
        publish("render_000.png", "render")
        if ender.endswith("canceled"):
            with session_scope() as session:
                request_cancel(session=session, job_ids=[job_id])
        long_ago = utcnow() - timedelta(seconds=2 * db.job_stale_timeout_s)
        with session_scope() as session:
            session.execute(update(Job).where(Job.id == job_id).values(updated_at=long_ago, run_lease_until=long_ago))
        if ender.startswith("its redelivery"):
            runtime._HOLDING.set(None)  # (the redelivery runs on another worker)
            with pytest.raises(runtime.JobSkipped, match="canceled"):
                runtime.begin_stage(job_id, "export", "b@host", "cpu", db)
            runtime._HOLDING.set((job_id, stalled.run_token))
        else:
            add_heartbeat("a@host", age_s=2 * db.job_stale_timeout_s)
            assert reap_orphaned_jobs(db) == [job_id]
        ended = job_row(job_id)
        assert ended.state == ("failed" if ender.endswith("at the limit") else "canceled")
        left = listed_artifacts(job_id)  # the withdrawal took the render; a failed job keeps it
        assert left == ({} if ended.state == "canceled" else {"render_000.png": f"jobs/{job_id}/render_000.png"})
        with pytest.raises(runtime.RunSuperseded):  # the stalled run wakes and goes on
            publish("turntable.mp4", "video")
        with pytest.raises(runtime.RunSuperseded):
            runtime.merge_job_result(job_id, {"video_frames": 60})
    finally:
        runtime._HOLDING.reset(outside)
    assert listed_artifacts(job_id) == left and job_row(job_id).state == ended.state
    assert "video_frames" not in (job_row(job_id).result or {})


def test_one_run_holds_a_job_a_duplicate_message_is_dropped_and_a_dead_run_is_taken_over(db, monkeypatch):
    """A chain message sent twice (a worker died after its stage sent the next one, before its ack) must not run
    a stage on two workers: while the run holding the job renews its lease, the duplicate is dropped (StageHeld,
    after seeing one renewal); once the holder stops renewing (its process died), the next run takes the job over
    when the lease runs out, and the stalled run's later outcome changes nothing and its cancel check stops it."""
    import time

    from voxe_service.db import session_scope
    from voxe_service.models import Job
    from worker import runtime

    monkeypatch.setattr(db, "stage_lease_s", 2.0)  # renewed every 0.5 s: a busy CPU does not let it lapse
    job_id = add_job(add_scene(), "queued", 0, completed_stages=["reconstruct"])
    first = runtime.begin_stage(job_id, "edit", "a@host", "cpu", db)
    stalled = runtime.StageCallbacks(first, "edit", db)
    assert (first.state, first.stage, first.worker_hostname) == ("running", "edit", "a@host") and first.run_token
    with runtime.stage_lease(job_id, first.run_token, db):
        started = time.monotonic()
        with pytest.raises(runtime.StageHeld, match="this edit message is a duplicate"):
            runtime.begin_stage(job_id, "edit", "b@host", "cpu", db)
        assert time.monotonic() - started < 2.0  # one renewal seen (every 0.5 s), not the lease waited out
        held = job_row(job_id)
        assert (held.run_token, held.worker_hostname) == (first.run_token, "a@host")
    started = time.monotonic()  # the holder stopped renewing: taken over once its lease ran out
    second = runtime.begin_stage(job_id, "edit", "b@host", "cpu", db)
    assert second.run_token not in (None, first.run_token) and second.worker_hostname == "b@host"
    assert time.monotonic() - started > 0.5
    # The stalled run, back: its ending, its completion and its progress loop all see the job is not its own.
    assert not runtime.finish_job(job_id, "failed", error="edit: the stalled run failed", run_token=first.run_token)
    assert not runtime.complete_stage(job_id, "edit", first.run_token)
    stalled.settings = db.model_copy(update={"cancel_check_interval_s": 0.0})
    assert stalled.should_cancel()
    assert not runtime.StageCallbacks(second, "edit", stalled.settings).should_cancel()
    assert job_row(job_id).state == "running" and job_row(job_id).completed_stages == ["reconstruct"]
    assert runtime.complete_stage(job_id, "edit", second.run_token)  # released between stages
    done = job_row(job_id)
    assert (done.run_token, done.completed_stages) == (None, ["reconstruct", "edit"])
    with pytest.raises(runtime.JobSkipped, match="edit already done"):  # a redelivered edit: its chain goes on
        runtime.begin_stage(job_id, "edit", "c@host", "cpu", db)
    assert job_row(job_id).run_token is None  # the skip gave its claim back
    with session_scope() as session:
        assert session.get(Job, job_id).stage == "edit"


def test_a_redelivered_message_of_a_done_stage_carries_its_chain_on_only_while_the_next_stage_has_not_begun(db):
    """A copy of a stage's message delivered again after the stage was done (Redis redelivering an unacknowledged
    message) was skipped and carried its chain on, whatever the job had done since: a second chain of messages
    followed the first's to the end of the job, each copy taking a worker (and waiting there on a held stage). Once a
    later stage has begun, the first run's chain carries the job: the copy is dropped at once (Ignore, no chain).
    While the next stage has not begun, its message may be the one a worker killed before sending it lost: the copy
    still goes on."""
    from worker import tasks

    job_id = add_job(add_scene(), "running", 0, stage="refine", completed_stages=["reconstruct", "edit", "refine"],
                     mode="local")
    assert tasks.edit_task.apply(args=(job_id,)).state == "IGNORED"
    carried_on = tasks.refine_task.apply(args=(job_id,))
    assert carried_on.state == "SUCCESS" and "refine already done" in carried_on.get()["skipped"]
    job = job_row(job_id)
    assert (job.state, job.stage, job.run_token, job.requeues) == ("running", "refine", None, 0)
    assert events_of(job_id) == []


def test_a_stage_that_kills_its_worker_each_time_fails_at_the_requeue_limit_leaving_no_checkpoint(db):
    """A stage whose worker process dies (the OOM killer, a segfault) comes back as a redelivered message that
    takes the lapsed hold over: each takeover counts as a re-queue, so after VOXE_JOB_MAX_REQUEUES the next one
    fails the job with the reason instead of running the stage again, and its checkpoints go (they had looped
    for ever, the takeover refreshing the job so the reaper never saw it)."""
    from sqlalchemy import update

    from voxe_service.db import session_scope
    from voxe_service.models import Job, utcnow
    from voxe_service.storage import get_storage, job_key
    from worker import runtime, tasks

    limit = db.job_max_requeues
    job_id = add_job(add_scene(), "queued", 0, completed_stages=["reconstruct"])
    holder = "first@host"
    for requeues in range(limit + 1):
        run = runtime.begin_stage(job_id, "edit", holder, "cpu", db)
        assert (run.state, run.requeues, run.worker_hostname) == ("running", requeues, holder)
        with session_scope() as session:  # the run's process is killed: its hold lapses
            session.execute(update(Job).where(Job.id == job_id)
                            .values(run_lease_until=utcnow() - timedelta(seconds=1)))
        holder = f"w{requeues}@host"
    checkpoint = job_key(job_id, "checkpoints/edit.safetensors")
    get_storage(db).put_bytes(checkpoint, b"edit at 6000")
    result = tasks.edit_task.apply(args=(job_id,)).get()
    assert result["skipped"].startswith(f"job {job_id} failed")
    job = job_row(job_id)
    assert (job.state, job.requeues) == ("failed", limit) and job.finished_at is not None
    assert job.error == (f"the run of edit on worker w{limit - 1}@host stopped renewing its hold on the job (its "
                         f"process died: killed, out of memory or crashed; or the database refused its give-back in an outage); "
                         f"it was sent again {limit} time(s) "
                         f"already, the limit (VOXE_JOB_MAX_REQUEUES={limit})")
    assert [e["kind"] for e in events_of(job_id)] == ["stage_started"] * (limit + 1) + ["failed"]
    assert not get_storage(db).exists(checkpoint)


CUDA_OOM = ("CUDA out of memory. Tried to allocate 2.00 GiB. GPU 0 has a total capacity of 79.15 GiB of which 1.06 GiB "
            "is free. Including non-PyTorch memory, this process has 78.08 GiB memory in use. Of the allocated memory "
            "76.50 GiB is allocated by PyTorch, and 1.08 GiB is reserved by PyTorch but unallocated. If reserved but "
            "unallocated memory is large try setting PYTORCH_CUDA_ALLOC_CONF=expandable_segments:True to avoid "
            "fragmentation.  See documentation for Memory Management  (https://pytorch.org/docs/stable/notes/"
            "cuda.html#environment-variables)")  # one line, as PyTorch's caching allocator words it


@pytest.mark.parametrize("raised,said", [
    (MemoryError, "edit: out of memory on the worker (MemoryError)"),
    (lambda: __import__("torch").cuda.OutOfMemoryError(CUDA_OOM),
     "edit: out of memory on the worker (CUDA out of memory. Tried to allocate 2.00 GiB. GPU 0 has a total capacity "
     "of 79.15 GiB of which 1.06 GiB is free. Including non-PyTorch memory, this process has 78.08 GiB memory in use. "
     "Of the allocated memory 76.50 GiB is allocated by PyTorch, and 1.08 GiB is reserved by PyTorch but "
     "unallocated.)"),
    (KeyError, "edit: KeyError"),
    (lambda: ValueError("render size 0"), "edit: ValueError: render size 0"),
], ids=["MemoryError", "CUDA OOM", "no words", "words"])
def test_a_stage_that_runs_out_of_memory_fails_its_job_saying_so(db, monkeypatch, raised, said):
    """Python's MemoryError has no words: the job had failed as "edit: MemoryError: ", and CUDA's out of memory with
    a page of allocator advice. The job fails (its next run would ask for as much), said in one line, its checkpoints
    gone."""
    from voxe_service.storage import get_storage, job_key
    from worker import tasks

    def body(*args):
        raise raised()

    monkeypatch.setattr(tasks, "_edit", body)
    job_id = add_job(add_scene(), "queued", 0, completed_stages=["reconstruct"])
    checkpoint = job_key(job_id, "checkpoints/edit.safetensors")
    get_storage(db).put_bytes(checkpoint, b"edit at 600")
    assert tasks.edit_task.apply(args=(job_id,)).get()["state"] == "failed"
    job = job_row(job_id)
    assert (job.state, job.error) == ("failed", said) and job.finished_at is not None
    assert not get_storage(db).exists(checkpoint)


@pytest.mark.parametrize("fault", ["scratch", "sql"])
def test_a_stage_failure_says_what_failed_without_the_workers_paths_or_statements(db, monkeypatch, fault):
    """A job's error is the user's to read: a worker's scratch folder that cannot be made (a file in its place, a
    full disk) had failed the job naming the worker's path (``/var/lib/voxe/work/jobs/<id>``), and a statement the
    database refused (a worker of another version, a column it lacks) with SQLAlchemy's text: the SQL, its
    parameters and a link. They say the error's own words; the worker's log keeps the rest. The scratch's says the
    fault is the worker's (its bare errno had read as the user's doing)."""
    from pathlib import Path

    from sqlalchemy import text

    from voxe_service.db import session_scope
    from worker import runtime, tasks

    def body(job, settings, device, storage):
        if fault == "scratch":
            runtime.scratch_dir(job.id, settings)
        else:
            with session_scope() as session:
                session.execute(text("SELECT no_such_column FROM jobs WHERE id = :id"), {"id": job.id})

    (Path(db.work_dir) / "jobs").parent.mkdir(parents=True, exist_ok=True)
    (Path(db.work_dir) / "jobs").write_text("not a folder")
    monkeypatch.setattr(tasks, "_edit", body)
    job_id = add_job(add_scene(), "queued", 0, completed_stages=["reconstruct"])
    assert tasks.edit_task.apply(args=(job_id,)).get()["state"] == "failed"
    error = job_row(job_id).error
    assert str(db.work_dir) not in error and "SELECT" not in error and "sqlalche.me" not in error, error
    if fault == "scratch":
        assert error == "edit: NotADirectoryError: [Errno 20] Not a directory on the worker (see its log)"
    else:
        assert error.startswith("edit: ") and "no_such_column" in error and "\n" not in error, error


def test_a_run_that_lost_its_job_writes_nothing_on_it_waiting_for_the_fit_or_after(db):
    """A reconstruct run that stalled past its lease (its job taken over by a redelivery) wrote the job's progress
    as if it still held it: "waiting for the scene's reconstruction" (and the fit's iteration and total) while it
    waited, and once the fit was done "reused the scene's reconstruction", over the new run's words, or over an
    ending (the job failed or canceled meanwhile) until its next cancel check stopped it. Those writes are the held
    run's only, as its progress writes are: the new run's message, iteration and total stay, and no reuse is said."""
    from voxe_core.progress import StageCancelled
    from voxe_service.db import session_scope
    from voxe_service.models import Reconstruction, utcnow
    from voxe_service.storage import get_storage
    from worker import runtime, tasks

    storage = get_storage(db)
    scene = add_scene()
    rec_id = add_reconstruction(scene, params={"route": "voxelize"})
    fitter = add_job(scene, "running", 0, reconstruction_id=rec_id)
    job_id = add_job(scene, "running", 0, stage="reconstruct", reconstruction_id=rec_id, run_token="new",
                     iteration=3, total=10, message="the new run's words")
    with session_scope() as session:  # the fit another job runs, its lease live
        rec = session.get(Reconstruction, rec_id)
        rec.state, rec.owner_job_id, rec.lease_until = "running", fitter, utcnow() + timedelta(hours=1)
    stale = runtime.load_job(job_id)
    stale.run_token = "old"  # the run that lost the job

    def progress():
        row = job_row(job_id)
        return row.message, row.iteration, row.total, row.reconstruction_reused

    new_run = ("the new run's words", 3, 10, job_row(job_id).reconstruction_reused)
    with runtime.holding_job(job_id, "old", db), pytest.raises(StageCancelled):  # (its cancel check finds it lost)
        tasks._reconstruct(stale, db, "cpu", storage)
    assert progress() == new_run
    grid = storage.put_bytes(f"reconstructions/{rec_id}/grid.safetensors", b"G_i")
    with session_scope() as session:  # the fit done
        rec = session.get(Reconstruction, rec_id)
        rec.state, rec.grid_key, rec.grid_size, rec.grid_sha256 = "succeeded", grid.key, grid.size, grid.sha256
    with runtime.holding_job(job_id, "old", db), pytest.raises(runtime.RunSuperseded):  # (refused its artifact)
        tasks._reconstruct(stale, db, "cpu", storage)
    assert progress() == new_run


def test_a_run_that_lost_its_job_writes_neither_its_model_download_nor_its_preview_on_it(db, monkeypatch):
    """An edit or refine run that lost its job (stalled past its lease and taken over, or the job ended) still wrote
    its model's first-use "downloading <model> (N GB)" as the job's message, over the new run's (or an ending's),
    and a run taken over just after publishing its preview still named it the job's preview. Both are written only
    while the run holds the job, as its progress is."""
    from collections import OrderedDict

    import torch

    from voxe_core.guidance.sds import StableDiffusionGuidance
    from voxe_service.storage import get_storage
    from worker import runtime, tasks

    class Downloaded(Exception):
        """The stage stops once the download was said: only its message is looked at."""

    def downloading(path, device, on_message=None, **kwargs):
        on_message(f"downloading {path} (4.0 GB)")
        raise Downloaded

    monkeypatch.setattr(runtime, "_GUIDANCE_CACHE", OrderedDict())
    monkeypatch.setattr(runtime, "resolve_model", lambda model, settings: model)
    monkeypatch.setattr(StableDiffusionGuidance, "from_pretrained", downloading)
    storage = get_storage(db)
    job_id = add_job(add_scene(), "running", 0, mode="local", stage="edit", completed_stages=["reconstruct"],
                     run_token="new", message="the new run's words")
    stale = runtime.load_job(job_id)
    stale.run_token = "old"  # the run that lost the job
    for stage in (tasks._edit, tasks._refine):
        with holding(job_id, "old"), pytest.raises(Downloaded):
            stage(stale, db, "cpu", storage)
        assert job_row(job_id).message == "the new run's words", stage
    stale.run_token = "new"  # (held, it is said)
    with holding(job_id, "new"), pytest.raises(Downloaded):
        tasks._edit(stale, db, "cpu", storage)
    assert job_row(job_id).message == "downloading tiny (4.0 GB)"

    runtime.update_job(job_id, run_token="old")
    stale.run_token, published = "old", runtime.publish_artifact

    def published_as_another_run_takes_the_job_over(*args, **kwargs):
        artifact = published(*args, **kwargs)
        runtime.update_job(job_id, run_token="new")
        return artifact

    monkeypatch.setattr(runtime, "publish_artifact", published_as_another_run_takes_the_job_over)
    with holding(job_id, "old"):
        tasks._preview(stale, None, db, storage, "cpu", image=torch.zeros(4, 4, 3))
    assert job_row(job_id).preview_artifact is None


def test_a_fit_that_runs_out_of_memory_fails_its_job_alone_and_a_job_waiting_on_it_takes_it_over(db, monkeypatch):
    """Out of memory is its worker's fault, not the scene's, as when the OOM killer ends the process (whose lapsed
    lease a waiting job takes over): the fitting job fails saying so, and the job waiting on the shared fit (on a
    worker with more memory) fits it, where it had failed with "the scene's reconstruction failed: MemoryError: "."""
    import threading

    from conftest import make_sphere_grid
    from voxe_service.storage import get_storage
    from worker import runtime, tasks

    scene = add_scene()
    rec_id = add_reconstruction(scene, params={"route": "voxelize"})  # (a mesh scene's fit: its G_i in one step)
    fitter, waiting = (add_job(scene, "queued", 0, reconstruction_id=rec_id) for _ in range(2))

    def voxelize(job, rec, settings, storage):
        if job.id == fitter:
            raise MemoryError()
        return make_sphere_grid(8)

    monkeypatch.setattr(tasks, "_check_job_can_start", lambda job, settings: None)
    monkeypatch.setattr(tasks, "_voxelize", voxelize)
    assert runtime.try_claim_reconstruction(rec_id, fitter, "a@host", db, allow_failed=False)  # the fitter's first run
    outcome = {}

    def wait():
        try:
            tasks._reconstruct(runtime.load_job(waiting), db, "cpu", get_storage(db))
            outcome["done"] = True
        except BaseException as exc:  # noqa: BLE001
            outcome["error"] = exc

    thread = threading.Thread(target=wait)
    thread.start()
    deadline = time.monotonic() + 60  # until it records that it waits (however busy the machine is)
    while not (job_row(waiting).message or "").startswith("waiting") and time.monotonic() < deadline:
        time.sleep(0.05)
    assert (job_row(waiting).message or "").startswith(f"waiting for the scene's reconstruction {rec_id}")
    assert tasks.reconstruct_task.apply(args=(fitter,)).get()["state"] == "failed"  # its redelivered run
    thread.join(60)
    assert outcome == {"done": True}
    assert job_row(fitter).error == "reconstruct: out of memory on the worker (MemoryError)"
    rec = runtime.load_reconstruction(rec_id)
    assert (rec.state, rec.owner_job_id, rec.error) == ("succeeded", waiting, None)


def test_a_fit_out_of_memory_says_so_on_the_reconstruction_and_fails_it_once_no_job_is_left_to_take_it_over(
        db, monkeypatch):
    """A fit whose worker ran out of memory was handed back with no word: the reconstruction listed pending, its
    error empty, as if a job were about to fit it, while each job that took it over failed. It records the error,
    pending while a job of it has not ended (that job takes it over), failed once none is left; a later job tries
    it again. The sweep's evaluation of those jobs, which shares their reconstruction and never fits, is no job to
    take it over (the fit of a sweep had stayed pending for ever)."""
    from conftest import make_sphere_grid
    from voxe_service.storage import get_storage
    from worker import runtime, tasks

    scene = add_scene()
    rec_id = add_reconstruction(scene, params={"route": "voxelize"})
    fitter, queued = (add_job(scene, "queued", 0, reconstruction_id=rec_id, batch_id="b1") for _ in range(2))
    add_job(scene, "queued", 0, mode="evaluate", batch_id="b1", source_job_ids=[fitter, queued],
            reconstruction_id=rec_id)

    def voxelize(job, rec, settings, storage):
        if job.id in (fitter, queued):
            raise MemoryError()
        return make_sphere_grid(8)

    monkeypatch.setattr(tasks, "_check_job_can_start", lambda job, settings: None)
    monkeypatch.setattr(tasks, "_voxelize", voxelize)

    def reconstruction():
        rec = runtime.load_reconstruction(rec_id)
        return rec.state, rec.error

    assert tasks.reconstruct_task.apply(args=(fitter,)).get()["state"] == "failed"
    said = "out of memory on the worker (MemoryError)"
    assert job_row(fitter).error == f"reconstruct: {said}"
    assert reconstruction() == ("pending", f"job {fitter}'s fit: {said}")  # the queued job takes it over ...
    assert tasks.reconstruct_task.apply(args=(queued,)).get()["state"] == "failed"
    assert job_row(queued).error == f"reconstruct: {said}"
    assert reconstruction() == ("failed", f"job {queued}'s fit: {said}")  # ... and none is left
    assert runtime.load_reconstruction(rec_id).finished_at is not None
    later = add_job(scene, "queued", 0, reconstruction_id=rec_id)  # (on a worker with more memory)
    tasks._reconstruct(runtime.load_job(later), db, "cpu", get_storage(db))
    assert reconstruction() == ("succeeded", None)


@pytest.mark.parametrize("failing", ["upload", "save"])
def test_a_fit_whose_grid_cannot_be_stored_is_handed_back_at_once(db, monkeypatch, failing):
    """A fit that made its G_i and could not keep it (the storage refusing its upload, the worker's scratch disk
    full) had left the reconstruction running under a failed job, its lease unrenewed: a job waiting on it took it
    over only once the lease ran out, and with none waiting it was listed running for good. The fit is no failure of
    the scene's: it is handed back at once. The job fails naming a storage fault a retry meets again (access denied),
    the fit handed back as one out of memory is, saying why (it had been listed pending, its error empty, for good):
    pending while another job waits on it, failed once none is left. A full disk (safetensors' own error, as a real
    one raises it), the worker's state, gives the job back to the queue instead, the fit pending for its redelivery."""
    from safetensors import SafetensorError

    import voxe_core.tensorio
    from conftest import make_sphere_grid
    from service_helpers import failing_uploads
    from voxe_service.storage import StorageError, get_storage
    from worker import runtime, tasks

    scene = add_scene()
    rec_id = add_reconstruction(scene, params={"route": "voxelize"})
    job_id, waiting = (add_job(scene, "queued", 0, reconstruction_id=rec_id) for _ in range(2))
    if failing == "upload":
        failing_uploads(monkeypatch, get_storage(db), ".safetensors",
                        StorageError("S3 bucket 'voxe': AccessDenied when uploading"))
    else:
        def full(tensors, path, metadata=None):
            raise SafetensorError("Error while serializing: I/O error: No space left on device (os error 28)")

        monkeypatch.setattr(voxe_core.tensorio, "save_file", full)
    monkeypatch.setattr(tasks, "_check_job_can_start", lambda job, settings: None)
    monkeypatch.setattr(tasks, "_voxelize", lambda *args: make_sphere_grid(8))
    monkeypatch.setattr(runtime, "OUTAGE_PAUSE_S", 0.0)

    def reconstruction():
        rec = runtime.load_reconstruction(rec_id)
        return rec.state, rec.owner_job_id, rec.owner_run_token, rec.lease_until, rec.error

    result = tasks.reconstruct_task.apply(args=(job_id,))
    said = "StorageError: S3 bucket 'voxe': AccessDenied when uploading"
    if failing == "upload":
        assert result.get()["state"] == "failed"
        assert job_row(job_id).error == f"reconstruct: {said}"
        assert reconstruction() == ("pending", None, None, None,
                                    f"job {job_id}'s fit: its grid could not be stored: {said}")
        assert tasks.reconstruct_task.apply(args=(waiting,)).get()["state"] == "failed"  # ... and none is left
        assert reconstruction()[::4] == ("failed", f"job {waiting}'s fit: its grid could not be stored: {said}")
    else:
        assert result.state == "REJECTED" and result.result.requeue
        said = "the worker's disk full (OSError: [Errno 28] No space left on device)"
        assert (job_row(job_id).state, job_row(job_id).error) == ("running", None)
        assert job_row(job_id).message == f"re-queued: reconstruct stopped by {said}"
        assert reconstruction() == ("pending", None, None, None, f"job {job_id}'s fit: stopped by {said}")
    assert get_storage(db).list(f"reconstructions/{rec_id}/") == []


def _fit_stopped_as_its_grid_is_recorded(db, monkeypatch) -> tuple[str, str]:
    """(job id, reconstruction id) of a voxelize-route fit whose run stored its grid, then met the database down as it
    recorded it: the job went back to the queue, the run's grid left in the storage, recorded nowhere."""
    import sqlite3

    from sqlalchemy.exc import OperationalError

    from conftest import make_sphere_grid
    from voxe_service.storage import get_storage
    from worker import runtime, tasks

    scene = add_scene()
    rec_id = add_reconstruction(scene, params={"route": "voxelize"})
    job_id = add_job(scene, "queued", 0, reconstruction_id=rec_id)
    monkeypatch.setattr(tasks, "_check_job_can_start", lambda job, settings: None)
    monkeypatch.setattr(tasks, "_voxelize", lambda *args: make_sphere_grid(8))
    monkeypatch.setattr(runtime, "OUTAGE_PAUSE_S", 0.0)
    with monkeypatch.context() as outage:
        set_reconstruction = runtime.set_reconstruction

        def down_as_the_grid_is_recorded(*args, **values):
            if values.get("state") == "succeeded":
                raise OperationalError("UPDATE reconstructions", {}, sqlite3.OperationalError("database is locked"))
            return set_reconstruction(*args, **values)

        outage.setattr(runtime, "set_reconstruction", down_as_the_grid_is_recorded)
        result = tasks.reconstruct_task.apply(args=(job_id,))
    assert result.state == "REJECTED" and result.result.requeue, result.result
    assert len(get_storage(db).list(f"reconstructions/{rec_id}/grid-")) == 1  # the first run's, recorded nowhere
    return job_id, rec_id


def test_a_fit_whose_grid_record_meets_a_database_outage_leaves_no_orphan_grid_once_fitted_again(db, monkeypatch):
    """The database down exactly as a finished fit recorded its stored grid: the job went back to the queue and its
    redelivery fitted again, storing its grid under its own run's name, while the first run's grid stayed in the
    storage for good, recorded nowhere. Once the fit's grid is recorded, the others go."""
    from voxe_service.storage import get_storage
    from worker import runtime, tasks

    job_id, rec_id = _fit_stopped_as_its_grid_is_recorded(db, monkeypatch)
    assert tasks.reconstruct_task.apply(args=(job_id,)).get()["state"] == "done"  # the redelivery
    rec = runtime.load_reconstruction(rec_id)
    assert rec.state == "succeeded" and get_storage(db).list(f"reconstructions/{rec_id}/") == [rec.grid_key]
    assert runtime.recorded_key(job_id, "initial_grid.safetensors") == rec.grid_key


def test_a_fit_handed_back_by_a_database_outage_that_then_fails_leaves_no_grid_in_the_storage(db, monkeypatch):
    """The database down as a finished fit recorded its stored grid: the fit was handed back, the run's grid stored
    under its own name and recorded nowhere, left for the fit's next success to delete. When the fit then failed (its
    redelivery's voxelizing raising), that grid stayed in the storage for good. A fit that ends failed deletes the
    grids stored for it; the failure is the job's and the fit's as before."""
    from voxe_core.mesh_input import MeshError
    from voxe_service.storage import get_storage
    from worker import runtime, tasks

    job_id, rec_id = _fit_stopped_as_its_grid_is_recorded(db, monkeypatch)

    def unreadable(*args):
        raise MeshError("mesh.obj: no faces")

    monkeypatch.setattr(tasks, "_voxelize", unreadable)
    assert tasks.reconstruct_task.apply(args=(job_id,)).get()["state"] == "failed"  # the redelivery
    rec = runtime.load_reconstruction(rec_id)
    assert (rec.state, rec.error) == ("failed", "MeshError: mesh.obj: no faces")
    assert job_row(job_id).error == "reconstruct: MeshError: mesh.obj: no faces"
    assert get_storage(db).list(f"reconstructions/{rec_id}/") == []


def _shared_fit_fitted_by_the_first_of_two_jobs(db, monkeypatch) -> tuple:
    """(storage, reconstruction id, first job, later job): a voxelize-route fit two queued jobs share, fitted by the
    first's reconstruct stage (voxelizing a sphere; the jobs' start checks skipped)."""
    from conftest import make_sphere_grid
    from voxe_service.storage import get_storage
    from worker import tasks

    storage, scene = get_storage(db), add_scene()
    rec_id = add_reconstruction(scene, params={"route": "voxelize"})
    first, later = (add_job(scene, "queued", 0, reconstruction_id=rec_id) for _ in range(2))
    monkeypatch.setattr(tasks, "_check_job_can_start", lambda job, settings: None)
    monkeypatch.setattr(tasks, "_voxelize", lambda *args: make_sphere_grid(8))
    assert tasks.reconstruct_task.apply(args=(first,)).get()["state"] == "done"
    return storage, rec_id, first, later


def test_a_shared_fit_whose_grid_was_deleted_from_the_storage_is_fitted_again_by_the_next_job(db, monkeypatch):
    """The scene's fitted grid G_i deleted from the storage (by hand, a bucket's lifecycle rule): every later job
    with its reconstruction parameters failed at once, "reconstruct: StorageError: reconstructions/<id>/grid-...: not
    in the storage", for good, and no job could ever fit it again. The next job fits it again, saying so in a warning
    on its timeline, and goes on with the new grid."""
    from sqlalchemy import select

    from voxe_service.db import session_scope
    from voxe_service.models import JobEvent
    from worker import runtime, tasks

    storage, rec_id, first, later = _shared_fit_fitted_by_the_first_of_two_jobs(db, monkeypatch)
    lost = runtime.load_reconstruction(rec_id).grid_key
    storage.delete(lost)
    assert tasks.reconstruct_task.apply(args=(later,)).get()["state"] == "done", job_row(later).error
    rec = runtime.load_reconstruction(rec_id)
    assert (rec.state, rec.owner_job_id, rec.run_count, rec.error) == ("succeeded", later, 2, None)
    assert rec.grid_key != lost and storage.list(f"reconstructions/{rec_id}/") == [rec.grid_key]
    assert runtime.recorded_key(later, "initial_grid.safetensors") == rec.grid_key
    with session_scope() as session:
        warnings = list(session.scalars(select(JobEvent.detail).where(JobEvent.job_id == later,
                                                                      JobEvent.kind == "warning")))
    assert warnings == [f"the scene's reconstruction {rec_id} had its grid {lost} deleted from the storage: fitting "
                        "it again"]


def test_a_refit_that_ran_out_of_memory_with_only_jobs_past_their_reconstruct_left_ends_failed(db, monkeypatch):
    """A shared fit refitted after its grid was deleted from the storage, the refit stopped by its worker running out
    of memory: the hand-back counted the job that had reused the old grid and gone on to its edit as waiting for the
    fit, so the fit was handed back pending, with no job left ever to take it over, and the refit's stray grids kept.
    A job past its reconstruct stage waits for no fit: it ends failed, nothing of its left in the storage."""
    from worker import runtime, tasks

    storage, rec_id, first, later = _shared_fit_fitted_by_the_first_of_two_jobs(db, monkeypatch)
    assert job_row(first).state == "running"  # (past its reconstruct, its edit to come)
    storage.delete(runtime.load_reconstruction(rec_id).grid_key)

    def out_of_memory(*args):
        raise MemoryError("the refit")

    monkeypatch.setattr(tasks, "_voxelize", out_of_memory)
    tasks.reconstruct_task.apply(args=(later,))
    rec = runtime.load_reconstruction(rec_id)
    assert (rec.state, rec.error) == ("failed", f"job {later}'s fit: out of memory on the worker (the refit)")
    assert storage.list(f"reconstructions/{rec_id}/") == []


def test_a_job_whose_lost_grid_another_job_fitted_again_first_says_no_refit_of_its_own(db, monkeypatch, tmp_path):
    """Two jobs met the shared fit's grid deleted from the storage, and the other set it back and fitted it again
    before this one's refit call, which then did nothing: this job still said "fitting it again" in a warning, and went
    on to reuse the other's new grid. It says nothing of a refit it did not make, and reuses the new grid."""
    from sqlalchemy import select

    from conftest import make_sphere_grid
    from voxe_service.db import session_scope
    from voxe_service.models import JobEvent
    from voxe_service.storage import get_storage, reconstruction_storage_key
    from worker import runtime, tasks

    storage, scene = get_storage(db), add_scene()
    rec_id = add_reconstruction(scene, params={"route": "voxelize"})
    first, later = (add_job(scene, "queued", 0, reconstruction_id=rec_id) for _ in range(2))
    other = add_job(scene, "running", 0, "alive@host", "reconstruct", reconstruction_id=rec_id)
    monkeypatch.setattr(tasks, "_check_job_can_start", lambda job, settings: None)
    monkeypatch.setattr(tasks, "_voxelize", lambda *args: make_sphere_grid(8))
    assert tasks.reconstruct_task.apply(args=(first,)).get()["state"] == "done"
    lost = runtime.load_reconstruction(rec_id).grid_key
    storage.delete(lost)
    refit_lost_grid = runtime.refit_lost_grid

    def the_other_refitted_it_first(rec, key):
        assert refit_lost_grid(rec, key)
        assert runtime.try_claim_reconstruction(rec, other, "alive@host", db, allow_failed=False)
        make_sphere_grid(8).save(tmp_path / "others.safetensors")
        stored = storage.put_file(reconstruction_storage_key(rec, "grid-the-other.safetensors"),
                                  tmp_path / "others.safetensors")
        assert runtime.set_reconstruction(rec, other, state="succeeded", grid_key=stored.key, grid_size=stored.size,
                                          grid_sha256=stored.sha256, iteration=1, total=1)
        return refit_lost_grid(rec, key)

    monkeypatch.setattr(runtime, "refit_lost_grid", the_other_refitted_it_first)
    assert tasks.reconstruct_task.apply(args=(later,)).get()["state"] == "done", job_row(later).error
    rec = runtime.load_reconstruction(rec_id)
    assert (rec.state, rec.owner_job_id) == ("succeeded", other)
    assert runtime.recorded_key(later, "initial_grid.safetensors") == rec.grid_key != lost
    assert job_row(later).reconstruction_reused
    with session_scope() as session:
        warnings = list(session.scalars(select(JobEvent.detail).where(JobEvent.job_id == later,
                                                                      JobEvent.kind == "warning")))
    assert warnings == []


def test_a_refit_of_a_lost_grid_reads_as_not_yet_fitted_until_it_ends(db, monkeypatch):
    """A shared fit set back to pending as its grid was deleted from the storage kept the old fit's iteration and
    total: through a refit that reports no progress until its end (a mesh's voxelizing), it read as done, and every
    job waiting on it showed its fit complete. It reads as a fit not begun until the refit reports."""
    from conftest import make_sphere_grid
    from worker import runtime, tasks

    storage, rec_id, first, later = _shared_fit_fitted_by_the_first_of_two_jobs(db, monkeypatch)
    assert (runtime.load_reconstruction(rec_id).iteration, runtime.load_reconstruction(rec_id).total) == (1, 1)
    storage.delete(runtime.load_reconstruction(rec_id).grid_key)
    seen = []

    def voxelize_read_the_fit(*args):
        rec = runtime.load_reconstruction(rec_id)
        seen.append((rec.state, rec.iteration, rec.total))
        return make_sphere_grid(8)

    monkeypatch.setattr(tasks, "_voxelize", voxelize_read_the_fit)
    assert tasks.reconstruct_task.apply(args=(later,)).get()["state"] == "done", job_row(later).error
    assert seen == [("running", 0, 0)]
    rec = runtime.load_reconstruction(rec_id)
    assert (rec.state, rec.iteration, rec.total) == ("succeeded", 1, 1)


def test_a_fit_whose_grid_record_meets_a_database_outage_is_handed_back_to_the_jobs_waiting_on_it(db, monkeypatch):
    """The database down exactly as a finished fit recorded its grid: the record raised out of the fit's hand-back, so
    the fit stayed running, owned by the job gone back to the queue, and another job waiting on it could not take it
    over before its lease ran out. It is handed back as an outage met anywhere else in the fit is: pending, saying
    why, at once taken over by the waiting job. A record that went through as its answer was lost stays succeeded."""
    import sqlite3

    from sqlalchemy.exc import OperationalError

    from conftest import make_sphere_grid
    from voxe_service.storage import get_storage
    from worker import runtime, tasks

    scene = add_scene()
    rec_id = add_reconstruction(scene, params={"route": "voxelize"})
    job_id = add_job(scene, "queued", 0, reconstruction_id=rec_id)
    waiting = add_job(scene, "running", 0, "alive@host", "reconstruct", reconstruction_id=rec_id)
    monkeypatch.setattr(tasks, "_check_job_can_start", lambda job, settings: None)
    monkeypatch.setattr(tasks, "_voxelize", lambda *args: make_sphere_grid(8))
    monkeypatch.setattr(runtime, "OUTAGE_PAUSE_S", 0.0)
    set_reconstruction = runtime.set_reconstruction
    for answer_lost in (False, True):
        def down_as_the_grid_is_recorded(*args, **values):
            if values.get("state") == "succeeded":
                if answer_lost:
                    set_reconstruction(*args, **values)
                raise OperationalError("UPDATE reconstructions", {}, sqlite3.OperationalError("database is locked"))
            return set_reconstruction(*args, **values)

        with monkeypatch.context() as outage:
            outage.setattr(runtime, "set_reconstruction", down_as_the_grid_is_recorded)
            result = tasks.reconstruct_task.apply(args=(job_id,))
        assert result.state == "REJECTED" and result.result.requeue, result.result
        rec = runtime.load_reconstruction(rec_id)
        if answer_lost:
            assert (rec.state, rec.owner_job_id, rec.error) == ("succeeded", job_id, None)
            assert rec.grid_key in get_storage(db).list(f"reconstructions/{rec_id}/grid-")  # (the fit's: kept)
            break
        said = "a database outage (the database cannot be reached or is locked)"
        assert (rec.state, rec.owner_job_id, rec.lease_until) == ("pending", None, None)
        assert rec.error == f"job {job_id}'s fit: stopped by {said}"
        assert runtime.try_claim_reconstruction(rec_id, waiting, "alive@host", db, allow_failed=False)
        assert runtime.set_reconstruction(rec_id, waiting, state="pending", owner_job_id=None)  # (let the first refit)


def test_a_fit_stopped_by_a_database_outage_is_handed_back_once_the_database_answers_again(db, monkeypatch):
    """A database outage stopped the fit, and lasted through its hand-back: the hand-back was tried once, while the
    job's own give-back was tried again until the database answered. The job went back to the queue, but its fit
    stayed running, owned by it, and a job waiting on it waited out the fit's lease (two minutes by default),
    "fitted by" a job that fitted nothing. The hand-back is tried again as the give-back is: the fit is pending,
    saying why, and the waiting job takes it over at once."""
    import sqlite3

    from sqlalchemy.exc import OperationalError

    from worker import runtime, tasks

    scene = add_scene()
    rec_id = add_reconstruction(scene, params={"route": "voxelize"})
    job_id = add_job(scene, "queued", 0, reconstruction_id=rec_id)
    waiting = add_job(scene, "running", 0, "alive@host", "reconstruct", reconstruction_id=rec_id)
    monkeypatch.setattr(tasks, "_check_job_can_start", lambda job, settings: None)
    monkeypatch.setattr(tasks, "DATABASE_RETRY_S", (0.0, 0.0, 0.0))
    down = sqlite3.OperationalError("database is locked")
    set_reconstruction, refused = runtime.set_reconstruction, []

    def the_outage_stops_the_fit(*args):
        raise OperationalError("UPDATE jobs", {}, down)

    def down_for_two_tries(*args, **values):
        if len(refused) < 2:
            refused.append(values)
            raise OperationalError("UPDATE reconstructions", {}, down)
        return set_reconstruction(*args, **values)

    monkeypatch.setattr(tasks, "_voxelize", the_outage_stops_the_fit)
    monkeypatch.setattr(runtime, "set_reconstruction", down_for_two_tries)
    result = tasks.reconstruct_task.apply(args=(job_id,))
    assert result.state == "REJECTED" and result.result.requeue, result.result
    rec = runtime.load_reconstruction(rec_id)
    said = "a database outage (the database cannot be reached or is locked)"
    assert (rec.state, rec.owner_job_id, rec.lease_until, rec.error) == (
        "pending", None, None, f"job {job_id}'s fit: stopped by {said}")
    assert len(refused) == 2
    assert runtime.try_claim_reconstruction(rec_id, waiting, "alive@host", db, allow_failed=False)

def test_a_fit_whose_success_was_recorded_before_the_worker_ran_out_of_memory_stays_succeeded(db, monkeypatch):
    """The grid's record committed and then the same call raised out of memory (not an outage): the fit's hand-back
    for an out-of-memory worker checked ownership alone and handed the succeeded fit back, pending for the job waiting
    on it to fit all over again (a reviewer's reproduction). It hands back only a fit still running."""
    from conftest import make_sphere_grid
    from voxe_service.storage import get_storage
    from worker import runtime, tasks

    scene = add_scene()
    rec_id = add_reconstruction(scene, params={"route": "voxelize"})
    job_id = add_job(scene, "queued", 0, reconstruction_id=rec_id)
    add_job(scene, "running", 0, "alive@host", "reconstruct", reconstruction_id=rec_id)  # waiting on the fit
    monkeypatch.setattr(tasks, "_check_job_can_start", lambda job, settings: None)
    monkeypatch.setattr(tasks, "_voxelize", lambda *args: make_sphere_grid(8))
    set_reconstruction = runtime.set_reconstruction

    def recorded_then_out_of_memory(*args, **values):
        done = set_reconstruction(*args, **values)
        if values.get("state") == "succeeded":
            raise MemoryError("after the commit")
        return done

    monkeypatch.setattr(runtime, "set_reconstruction", recorded_then_out_of_memory)
    tasks.reconstruct_task.apply(args=(job_id,))
    rec = runtime.load_reconstruction(rec_id)
    assert (rec.state, rec.owner_job_id, rec.error) == ("succeeded", job_id, None)
    assert rec.grid_key in get_storage(db).list(f"reconstructions/{rec_id}/grid-")  # (kept: the fit's)


@pytest.mark.parametrize("stopped", ["its record met a database outage", "its upload's answer was lost"])
def test_a_fit_lost_as_its_grid_was_stored_and_stopped_by_an_outage_leaves_no_grid_of_its_own(db, monkeypatch,
                                                                                                tmp_path, stopped):
    """A run whose lease lapsed as it stored its grid: another job took the fit over and succeeded, its cleanup of
    stray grids done, and then this run's upload landed, its record meeting a database outage (or the upload's own
    answer lost, a storage outage). Its hand-back found the fit another's, and its grid stayed in the storage for
    good, recorded nowhere. It is deleted once the run learns it lost; the fit and the winner's grid stay as they
    were. A record that went through as its answer was lost keeps the run's grid: it is the fit's."""
    import sqlite3

    from sqlalchemy import update
    from sqlalchemy.exc import OperationalError

    from conftest import make_sphere_grid
    from voxe_service.db import session_scope
    from voxe_service.models import Reconstruction
    from voxe_service.storage import StorageUnavailable, get_storage, reconstruction_storage_key
    from worker import runtime, tasks

    storage, scene = get_storage(db), add_scene()
    rec_id = add_reconstruction(scene, params={"route": "voxelize"})
    job_id = add_job(scene, "queued", 0, reconstruction_id=rec_id)
    winner = add_job(scene, "running", 0, "alive@host", "reconstruct", reconstruction_id=rec_id)
    make_sphere_grid(8).save(tmp_path / "winners.safetensors")
    winners = storage.put_file(reconstruction_storage_key(rec_id, "grid-the-winner.safetensors"),
                               tmp_path / "winners.safetensors")
    monkeypatch.setattr(tasks, "_check_job_can_start", lambda job, settings: None)
    monkeypatch.setattr(tasks, "_voxelize", lambda *args: make_sphere_grid(8))
    monkeypatch.setattr(runtime, "OUTAGE_PAUSE_S", 0.0)

    def the_winner_took_it_and_succeeded():
        with session_scope() as session:
            session.execute(update(Reconstruction).where(Reconstruction.id == rec_id).values(
                state="succeeded", owner_job_id=winner, owner_run_token=None, grid_key=winners.key,
                grid_size=winners.size, grid_sha256=winners.sha256, lease_until=None))

    set_reconstruction, put_file = runtime.set_reconstruction, type(storage).put_file

    def down_as_the_grid_is_recorded(*args, **values):
        if values.get("state") == "succeeded":
            the_winner_took_it_and_succeeded()
            raise OperationalError("UPDATE reconstructions", {}, sqlite3.OperationalError("database is locked"))
        return set_reconstruction(*args, **values)

    def stored_and_its_answer_lost(self, key, path, content_type=None):
        put_file(self, key, path, content_type)
        if "/grid-" in key:
            the_winner_took_it_and_succeeded()
            raise StorageUnavailable(f"S3 bucket 'voxe': timed out when uploading {key}")

    with monkeypatch.context() as outage:
        if stopped == "its record met a database outage":
            outage.setattr(runtime, "set_reconstruction", down_as_the_grid_is_recorded)
        else:
            outage.setattr(type(storage), "put_file", stored_and_its_answer_lost)
        result = tasks.reconstruct_task.apply(args=(job_id,))
    assert result.state == "REJECTED" and result.result.requeue, result.result
    rec = runtime.load_reconstruction(rec_id)
    assert (rec.state, rec.owner_job_id, rec.grid_key) == ("succeeded", winner, winners.key)
    assert storage.list(reconstruction_storage_key(rec_id, "grid-")) == [winners.key]
    assert tasks.reconstruct_task.apply(args=(job_id,)).get()["state"] == "done"  # the redelivery: the winner's fit
    assert runtime.recorded_key(job_id, "initial_grid.safetensors") == winners.key


@pytest.mark.parametrize("outage", ["storage", "database"])
def test_a_fit_handed_back_for_an_outage_says_why_on_its_job_and_its_reconstruction(db, monkeypatch, outage):
    """A fit stopped by a storage outage (its grid's upload throttled) or a database outage went back to the queue
    saying nothing a user polling the job could read: the reconstruction listed pending with no error (as if about
    to run) and the job running with its last progress note. The job's message and the reconstruction's error say
    what stopped it until the redelivery takes it; the fit's next claim clears the error."""
    import sqlite3

    from sqlalchemy.exc import OperationalError

    from api.routes.jobs import job_out
    from conftest import make_sphere_grid
    from service_helpers import failing_uploads
    from voxe_service.db import session_scope
    from voxe_service.models import Job
    from voxe_service.storage import StorageUnavailable, get_storage
    from worker import runtime, tasks

    scene = add_scene()
    rec_id = add_reconstruction(scene, params={"route": "voxelize"})
    job_id = add_job(scene, "queued", 0, reconstruction_id=rec_id)
    monkeypatch.setattr(tasks, "_check_job_can_start", lambda job, settings: None)
    monkeypatch.setattr(runtime, "OUTAGE_PAUSE_S", 0.0)
    with monkeypatch.context() as failing:
        if outage == "storage":
            failing.setattr(tasks, "_voxelize", lambda *args: make_sphere_grid(8))
            failing_uploads(failing, get_storage(db), ".safetensors",
                            StorageUnavailable("S3 bucket 'voxe': SlowDown when uploading"))
            said = "a storage outage (S3 bucket 'voxe': SlowDown when uploading)"
        else:
            def locked(*args):
                raise OperationalError("UPDATE jobs", {}, sqlite3.OperationalError("database is locked"))

            failing.setattr(tasks, "_voxelize", locked)
            said = "a database outage (the database cannot be reached or is locked)"
        result = tasks.reconstruct_task.apply(args=(job_id,))
    assert result.state == "REJECTED" and result.result.requeue, result.result
    with session_scope() as session:
        shown = job_out(session.get(Job, job_id))
        assert (shown.state, shown.error, shown.reconstruction.state) == ("running", None, "pending")
        assert shown.reconstruction.error == f"job {job_id}'s fit: stopped by {said}"
        assert shown.message.startswith(f"re-queued: reconstruct stopped by {said}"), shown.message
    monkeypatch.setattr(tasks, "_voxelize", lambda *args: make_sphere_grid(8))
    assert tasks.reconstruct_task.apply(args=(job_id,)).get()["state"] == "done"  # the redelivery
    rec = runtime.load_reconstruction(rec_id)
    assert (rec.state, rec.error, job_row(job_id).message) == ("succeeded", None, None)


@pytest.mark.parametrize("cause", ["full disk", "storage outage"])
def test_a_stage_given_back_for_a_full_disk_frees_its_scratch_and_keeps_its_stored_checkpoint(db, monkeypatch,
                                                                                                cause):
    """A stage stopped by its worker's full scratch disk goes back to the queue, its stored checkpoint kept for the
    redelivery; its scratch folder (the grids it fetched, its local checkpoint) had stayed, keeping the disk full for
    the next job this worker takes. It goes as the job is given back; a storage outage's is kept (the disk is not
    the fault, and a redelivery here reuses the grids fetched)."""
    import errno
    from pathlib import Path

    from voxe_service.storage import StorageUnavailable, get_storage, job_key
    from worker import runtime, tasks

    job_id = add_job(add_scene(), "queued", 0, completed_stages=["reconstruct"])
    checkpoint = job_key(job_id, "checkpoints/edit.safetensors")
    get_storage(db).put_bytes(checkpoint, b"edit at 600")
    scratch = Path(db.work_dir) / "jobs" / job_id

    def body(job, settings, device, storage):
        (runtime.scratch_dir(job.id, settings) / "initial_grid.safetensors").write_bytes(b"grid" * 1000)
        if cause == "full disk":
            raise OSError(errno.ENOSPC, "No space left on device", str(scratch / "edit_checkpoint.safetensors"))
        raise StorageUnavailable(f"S3 bucket 'voxe': SlowDown when uploading {checkpoint}")

    monkeypatch.setattr(tasks, "_edit", body)
    monkeypatch.setattr(runtime, "OUTAGE_PAUSE_S", 0.0)
    result = tasks.edit_task.apply(args=(job_id,))
    assert result.state == "REJECTED" and result.result.requeue, result.result
    job = job_row(job_id)
    assert (job.state, job.error, job.run_token, job.requeues) == ("running", None, None, int(cause == "full disk"))
    assert get_storage(db).exists(checkpoint)
    assert scratch.is_dir() == (cause == "storage outage")


def test_a_storage_outage_does_not_count_towards_the_requeue_limit_and_its_pauses_grow(db, monkeypatch):
    """A stage stopped by a storage outage (S3 throttling) was given back as a counted re-queue: a job that had been
    re-queued VOXE_JOB_MAX_REQUEUES times (or a minute of throttling met at each run) failed for an outage that every
    job met alike. It is given back uncounted, at the limit too, its ``requeued`` event naming the outage; the pause
    before its message goes back still doubles with each run the storage stopped, so the job does not loop fast."""
    from voxe_service.storage import StorageUnavailable
    from worker import runtime, tasks

    job_id = add_job(add_scene(), "queued", 0, completed_stages=["reconstruct"], requeues=db.job_max_requeues)

    def throttled(job, settings, device, storage):
        raise StorageUnavailable("S3 bucket 'voxe': SlowDown when fetching the grid")

    pauses = []
    monkeypatch.setattr(tasks, "_edit", throttled)
    monkeypatch.setattr(runtime, "pause_after_outage", pauses.append)
    for _ in range(3):
        result = tasks.edit_task.apply(args=(job_id,))
        assert result.state == "REJECTED" and result.result.requeue, result.result
    job = job_row(job_id)
    assert (job.state, job.error, job.run_token, job.requeues, job.storage_outages) == (
        "running", None, None, db.job_max_requeues, 3)
    said = "edit stopped by a storage outage (S3 bucket 'voxe': SlowDown when fetching the grid)"
    assert job.message == f"re-queued: {said}"
    assert [e["detail"] for e in events_of(job_id) if e["kind"] == "requeued"] == [said] * 3
    assert pauses == [db.job_max_requeues, db.job_max_requeues + 1, db.job_max_requeues + 2]


def test_a_storage_outage_met_past_its_bound_fails_the_job_naming_it(db, monkeypatch):
    """A storage object that answers 5xx every time (after botocore's retries) re-ran its stage for ever, as a storage
    outage counts towards no re-queue limit. Its give-backs are counted apart (``Job.storage_outages``), each still
    given back uncounted below their bound; the run after VOXE_STORAGE_OUTAGE_MAX_RETRIES of them that an outage
    stops fails the job, naming the outage and how many times it stopped the job."""
    from voxe_service.storage import StorageUnavailable
    from worker import runtime, tasks

    bound = db.storage_outage_max_retries
    job_id = add_job(add_scene(), "queued", 0, completed_stages=["reconstruct"], storage_outages=bound - 1)

    def broken_object(job, settings, device, storage):
        raise StorageUnavailable("S3 bucket 'voxe': InternalError (503) when fetching the grid")

    pauses = []
    monkeypatch.setattr(tasks, "_edit", broken_object)
    monkeypatch.setattr(runtime, "pause_after_outage", pauses.append)
    given_back = tasks.edit_task.apply(args=(job_id,))
    assert given_back.state == "REJECTED" and given_back.result.requeue, given_back.result
    job = job_row(job_id)
    assert (job.state, job.error, job.requeues, job.storage_outages) == ("running", None, 0, bound)
    assert tasks.edit_task.apply(args=(job_id,)).get()["state"] == "failed"
    job = job_row(job_id)
    assert (job.state, job.requeues, job.storage_outages, pauses) == ("failed", 0, bound, [bound - 1])
    assert job.error == ("edit stopped by a storage outage (S3 bucket 'voxe': InternalError (503) when fetching the "
                         f"grid); storage outages stopped it {bound + 1} times ({bound} retries, the limit: "
                         f"VOXE_STORAGE_OUTAGE_MAX_RETRIES={bound})")


@pytest.mark.parametrize("bound, said", [(0, "once (no retry"), (1, "2 times (1 retry"), (4, "5 times (4 retries")])
def test_the_storage_outage_bounds_message_counts_in_words(bound, said):
    """The bound's message counts its runs and retries in words a person would write: a bound of 0 had read
    "stopped it 1 times (0 retries", and 1 "2 times (1 retries"."""
    from voxe_service.queue import storage_outage_limit_error
    from voxe_service.settings import Settings

    settings = Settings(storage_outage_max_retries=bound)
    if bound:
        assert storage_outage_limit_error(bound - 1, settings, "edit stopped") is None
    assert storage_outage_limit_error(bound, settings, "edit stopped") == (
        f"edit stopped; storage outages stopped it {said}, the limit: VOXE_STORAGE_OUTAGE_MAX_RETRIES={bound})")


def test_a_run_taken_over_that_meets_a_full_disk_leaves_the_new_runs_scratch(db, monkeypatch):
    """A run that stalled past its lease, its job taken over by another run on the same machine (the same scratch
    folder), then stopped by the full disk, had deleted the job's scratch as it gave the job back, which it no longer
    held: the new run's fetched grids and local checkpoint gone mid-stage, failing it. The folder goes only with a
    give-back that takes effect; the other run's hold and its count of re-queues are left as they are."""
    import errno
    from pathlib import Path

    from sqlalchemy import update

    from voxe_service.db import session_scope
    from voxe_service.models import Job
    from worker import runtime, tasks

    job_id = add_job(add_scene(), "queued", 0, completed_stages=["reconstruct"])
    grid = Path(db.work_dir) / "jobs" / job_id / "initial_grid.safetensors"

    def stalled_then_full(job, settings, device, storage):
        with session_scope() as session:  # the lease ran out meanwhile and another run took the job over
            session.execute(update(Job).where(Job.id == job.id).values(run_token="other run"))
        runtime.scratch_dir(job.id, settings)
        grid.write_bytes(b"the other run's grid")
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(tasks, "_edit", stalled_then_full)
    monkeypatch.setattr(runtime, "OUTAGE_PAUSE_S", 0.0)
    tasks.edit_task.apply(args=(job_id,))
    assert grid.read_bytes() == b"the other run's grid"
    job = job_row(job_id)
    assert (job.state, job.run_token, job.requeues, job.message) == ("running", "other run", 0, None)


class WorkerGoingDown(BaseException):
    """Stands in for what ends the worker inside a running task (SystemExit, KeyboardInterrupt)."""


def test_a_worker_going_down_while_the_database_is_down_goes_down_its_message_kept(db, monkeypatch):
    """A stage stopped by its worker going down gives its hold back and lets that through (its message, unacknowledged,
    is delivered again); the database refusing the give-back (going down with the worker: one compose stack) had
    raised in its place, ending the task as failed, its message acknowledged, the job left to the reaper."""
    from sqlalchemy.exc import OperationalError

    from worker import runtime, tasks

    def going_down(*args):
        raise WorkerGoingDown()

    def refused(job_id, run_token):
        raise OperationalError("UPDATE jobs", {}, Exception("connection refused"))

    monkeypatch.setattr(tasks, "_edit", going_down)
    monkeypatch.setattr(runtime, "release_stage", refused)
    job_id = add_job(add_scene(), "queued", 0, completed_stages=["reconstruct"])
    with pytest.raises(WorkerGoingDown):
        tasks.edit_task.apply(args=(job_id,))
    job = job_row(job_id)
    assert (job.state, job.stage, job.error) == ("running", "edit", None) and job.run_token is not None


def test_a_run_that_lost_its_job_publishes_records_and_fits_nothing(db, tmp_path, monkeypatch):
    """A stalled run whose job another run took over (its lease lapsed) comes back: its artifacts and results are
    refused (RunSuperseded; nothing uploaded, listed or merged), and the job's fit, taken by the new run of the
    same job, is no longer its to renew or to change."""
    from voxe_service.storage import get_storage
    from worker import runtime

    monkeypatch.setattr(db, "stage_lease_s", 0.2)
    scene = add_scene()
    job_id = add_job(scene, "queued", 0, completed_stages=["reconstruct"])
    rec_id = add_reconstruction(scene)
    stalled = runtime.begin_stage(job_id, "edit", "a@host", "cpu", db)
    assert runtime.try_claim_reconstruction(rec_id, job_id, "a@host", db, True, run_token=stalled.run_token)
    taken = runtime.begin_stage(job_id, "edit", "b@host", "cpu", db)  # once the stalled run's lease lapsed
    assert runtime.try_claim_reconstruction(rec_id, job_id, "b@host", db, True, run_token=taken.run_token)
    grid = tmp_path / "edited_grid.safetensors"
    grid.write_bytes(b"grid")
    storage = get_storage(db)
    with runtime.holding_job(job_id, stalled.run_token, db):
        with pytest.raises(runtime.RunSuperseded, match="another run took the job over"):
            runtime.publish_artifact(job_id, "edited_grid.safetensors", grid, "grid", storage)
        with pytest.raises(runtime.RunSuperseded):
            runtime.merge_job_result(job_id, {"orbit_centre": [0.0, 0.0, 0.0]})
        stalled_callbacks = runtime.StageCallbacks(stalled, "edit", db, on_checkpoint=lambda path, iteration: (
            storage.put_file(f"jobs/{job_id}/checkpoints/edit.safetensors", path)))
        with pytest.raises(runtime.RunSuperseded):  # its older checkpoint had replaced the new owner's
            stalled_callbacks.on_checkpoint(str(grid))
    assert storage.list(f"jobs/{job_id}/") == [] and runtime.recorded_key(job_id, "edited_grid.safetensors") is None
    assert "checkpoint" not in [e["kind"] for e in events_of(job_id)]
    assert job_row(job_id).result is None
    assert not runtime.renew_lease(rec_id, job_id, db, stalled.run_token)
    assert not runtime.set_reconstruction(rec_id, job_id, stalled.run_token, state="failed")
    with runtime.holding_job(job_id, taken.run_token, db):  # the run holding the job writes as ever
        runtime.publish_artifact(job_id, "edited_grid.safetensors", grid, "grid", storage)
        runtime.merge_job_result(job_id, {"orbit_centre": [0.0, 0.0, 0.0]})
    assert storage.list(f"jobs/{job_id}/") == [f"jobs/{job_id}/edited_grid.safetensors"]
    assert runtime.renew_lease(rec_id, job_id, db, taken.run_token)
    assert runtime.load_reconstruction(rec_id).owner_run_token == taken.run_token


def test_a_fit_lease_runs_out_counted_from_its_claim_not_from_its_keeper():
    """The keeper is made after the claim (the fit's record is read between): counted from the keeper, check() had
    passed after the database's lease ran out, while an outage kept it from being renewed."""
    from sqlalchemy.exc import OperationalError

    from worker.runtime import LeaseKeeper, LeaseLost

    def refused(**values):
        raise OperationalError("UPDATE reconstructions", {}, Exception("connection refused"))

    claimed_at = time.monotonic() - 0.9  # claimed 0.9 s ago, under a lease of 1 s
    with LeaseKeeper(refused, 1.0, "reconstruction r", "another job took the fit over", "voxe-lease-t",
                     claimed_at) as lease:
        lease.check()
        time.sleep(0.2)
        with pytest.raises(LeaseLost, match="^reconstruction r: its lease ran out unrenewed"):
            lease.check()


def test_a_stale_run_of_a_job_cannot_take_the_fit_back_from_the_jobs_newer_run(db, monkeypatch):
    """Two runs of one job: the newer run, which took the job over, takes the fit from the stalled one at once; the
    stalled run coming back claims nothing, neither the fit the newer run holds (the claim had matched the job,
    not its run: the two took it from each other in turn) nor the fit handed back."""
    from worker import runtime

    monkeypatch.setattr(db, "stage_lease_s", 0.2)
    scene = add_scene()
    job_id = add_job(scene, "queued", 0)
    rec_id = add_reconstruction(scene)
    stalled = runtime.begin_stage(job_id, "reconstruct", "a@host", "cpu", db)
    assert runtime.try_claim_reconstruction(rec_id, job_id, "a@host", db, True, run_token=stalled.run_token)
    newer = runtime.begin_stage(job_id, "reconstruct", "b@host", "cpu", db)  # once the stalled run's lease lapsed
    assert runtime.try_claim_reconstruction(rec_id, job_id, "b@host", db, True, run_token=newer.run_token)
    assert not runtime.try_claim_reconstruction(rec_id, job_id, "a@host", db, True, run_token=stalled.run_token)
    rec = runtime.load_reconstruction(rec_id)
    assert (rec.owner_run_token, rec.worker_hostname, rec.run_count) == (newer.run_token, "b@host", 2)
    assert runtime.set_reconstruction(rec_id, job_id, newer.run_token, state="pending", owner_job_id=None,
                                      owner_run_token=None, lease_until=None)  # handed back (canceled)
    assert not runtime.try_claim_reconstruction(rec_id, job_id, "a@host", db, True, run_token=stalled.run_token)
    assert runtime.try_claim_reconstruction(rec_id, job_id, "b@host", db, False, run_token=newer.run_token)


def test_the_worker_acknowledges_a_duplicate_stage_message_without_continuing_its_chain(db, monkeypatch):
    """Through the Celery task: a duplicate raises ``Ignore`` (acknowledged, no result, the chain's next message
    not sent; the holder's own chain carries the job on), and the job is left as its holder has it."""
    from worker import runtime, tasks

    monkeypatch.setattr(db, "stage_lease_s", 2.0)
    job_id = add_job(add_scene(), "queued", 0, completed_stages=["reconstruct"])
    holder = runtime.begin_stage(job_id, "edit", "a@host", "cpu", db)
    with runtime.stage_lease(job_id, holder.run_token, db):
        result = tasks.edit_task.apply(args=(job_id,))
    assert result.state == "IGNORED"
    after = job_row(job_id)
    assert (after.state, after.stage, after.run_token, after.worker_hostname, after.error) == (
        "running", "edit", holder.run_token, "a@host", None)


WORKER_KILLED_TAKING_A_STAGE = """
import os, signal, sys

from worker import runtime
from worker.celery_app import app


def begin_stage(job_id, stage, *args, **kwargs):  # the message taken (its row deleted), the stage not yet begun
    with open(sys.argv[1], "a") as taken:
        taken.write(f"{job_id} {stage}\\n")
    os.kill(os.getpid(), signal.SIGKILL)


runtime.begin_stage = begin_stage
app.worker_main(["worker", "-Q", "gpu,celery", "--pool", "solo", "--without-gossip", "--without-mingle",
                 "--without-heartbeat", "-n", "w@host", "-l", "info"])
"""


def test_a_job_whose_message_a_killed_worker_had_taken_is_sent_again_by_the_next_worker(db, tmp_path):
    """SQL broker, real workers: one SIGKILLed after taking a queued job's message, before its stage took the job,
    lost it (the row goes as it is delivered, and the job, never running, was not re-queued): the next worker finds
    the job queued with no message waiting and sends it again, once (the row it takes is the only one). Neither sent
    the job again while its message waited: the first found it at its start, its consumer not yet polling."""
    import signal
    import subprocess
    import sys

    from service_helpers import REPO
    from voxe_service.broker import waiting_tasks
    from voxe_service.db import session_scope
    from voxe_service.models import Job
    from voxe_service.queue import dispatch_job, get_queue

    job_id = add_job(add_scene(), "queued", 0, task_id=None)
    with session_scope() as session:
        dispatch_job(session, get_queue(), session.get(Job, job_id))
    taken = tmp_path / "taken"

    def worker(n: int) -> list[str]:
        """Run a worker until it is killed taking a stage; the stages taken so far."""
        with open(tmp_path / f"worker-{n}.log", "wb") as log:
            proc = subprocess.Popen([sys.executable, "-c", WORKER_KILLED_TAKING_A_STAGE, str(taken)], cwd=REPO,
                                    env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}, stdout=log,
                                    stderr=subprocess.STDOUT)
            try:
                proc.wait(90 * max(1.0, os.getloadavg()[0] / (os.cpu_count() or 1)))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        assert proc.returncode == -signal.SIGKILL, (tmp_path / f"worker-{n}.log").read_text()[-3000:]
        return taken.read_text().splitlines()

    assert worker(1) == [f"{job_id} reconstruct"]
    assert job_row(job_id).state == "queued" and waiting_tasks(db.broker_url) == set()  # gone, not sent twice
    assert worker(2) == [f"{job_id} reconstruct"] * 2, "the next worker never ran the job"
    assert waiting_tasks(db.broker_url) == set()  # sent once: the killed worker took the only copy
    reason = "worker w@host started and the broker held no message for the queued job (a worker killed after " \
             "taking it, before starting it)"
    job = job_row(job_id)
    assert (job.state, job.message) == ("queued", f"re-queued: {reason}") and job.task_id is not None
    assert [(e["kind"], e["detail"]) for e in events_of(job_id)] == [("requeued", reason)]


def test_a_starting_worker_sends_again_only_the_queued_jobs_no_waiting_message_carries(db):
    """SQL broker: a starting worker sends again the queued jobs the broker holds no message for (from their next
    stage; a sweep's evaluation alone once its edit ended), and none whose message waits (its own, or in a chain),
    none never sent (the reaper's), none ended, and no evaluation an unfinished edit's chain will carry."""
    import sqlite3

    from sqlalchemy import update

    from voxe_service.broker import waiting_tasks
    from voxe_service.db import session_scope
    from voxe_service.models import Job
    from voxe_service.queue import dispatch_job, get_queue
    from worker import tasks

    scene = add_scene()
    waiting, edit = add_job(scene, "queued", 0, task_id=None), add_job(scene, "queued", 0, task_id=None, batch_id="b")
    riding = add_job(scene, "queued", 0, task_id=None, mode="evaluate", batch_id="b", source_job_ids=[edit])
    with session_scope() as session:
        for job_id in (waiting, edit):  # (the edit's chain carries the evaluation) ...
            dispatch_job(session, get_queue(), session.get(Job, job_id))
        session.execute(update(Job).where(Job.id == edit).values(state="canceled"))  # ... its message still waiting
    sent_before = {job_id: job_row(job_id).task_id for job_id in (waiting, edit, riding)}
    lost = add_job(scene, "queued", 0)
    lost_between = add_job(scene, "queued", 0, stage="reconstruct", completed_stages=["reconstruct"])
    done_edit = add_job(scene, "succeeded", 0, batch_id="c")
    lost_evaluation = add_job(scene, "queued", 0, mode="evaluate", batch_id="c", source_job_ids=[done_edit])
    running_edit = add_job(scene, "running", 0, "v@host", "edit", batch_id="d", run_token="live")
    carried_later = add_job(scene, "queued", 0, mode="evaluate", batch_id="d", source_job_ids=[running_edit])
    never_sent = add_job(scene, "queued", 0, task_id=None)
    ended = add_job(scene, "failed", 0)

    assert sorted(tasks.resend_lost_queued_jobs("w@host")) == sorted([lost, lost_between, lost_evaluation])
    assert waiting_tasks(db.broker_url) == {
        *((f"voxe.{stage}", job_id) for stage in ("reconstruct", "edit", "export") for job_id in (waiting, edit, lost)),
        ("voxe.evaluate", riding), ("voxe.edit", lost_between), ("voxe.export", lost_between),
        ("voxe.evaluate", lost_evaluation)}
    with sqlite3.connect(db.broker_url.split(":///", 1)[1]) as broker:  # one message a job: none sent twice
        assert broker.execute("SELECT count(*) FROM kombu_message").fetchone()[0] == 5
    assert {job_id: job_row(job_id).task_id for job_id in sent_before} == sent_before
    for job_id in (lost, lost_between, lost_evaluation):
        assert job_row(job_id).task_id not in (None, "task") and [e["kind"] for e in events_of(job_id)] == ["requeued"]
    for job_id in (waiting, riding, carried_later, never_sent, ended):
        assert events_of(job_id) == []
    assert (job_row(carried_later).task_id, job_row(never_sent).task_id, job_row(ended).task_id) == ("task", None,
                                                                                                      "task")


def test_a_starting_worker_sends_again_only_the_ingests_no_worker_took_and_no_waiting_message_carries(db):
    """SQL broker: a processing scene whose ingest message a killed worker had taken, before the ingest took the
    scene, had stayed processing for ever (the reaper fails only scenes whose ingesting worker is gone); a starting
    worker sends its ingest again, and none whose message waits, none a worker took (recover_interrupted_jobs and
    the reaper), none never sent (the reaper's)."""
    import sqlite3

    from voxe_service.broker import waiting_tasks
    from voxe_service.queue import get_queue
    from worker import tasks

    waiting, lost = add_scene("processing"), add_scene("processing")
    get_queue().send_ingest(waiting)
    add_scene("processing", worker="v@host"), add_scene("processing", task_id=None), add_scene("ready")
    get_queue().app.send_task("voxe.ingest", kwargs={"scene_id": waiting}, queue="gpu")  # (`celery call`'s shape)
    assert tasks.resend_lost_ingests("w@host") == [lost]  # (a message of another shape had raised an IndexError)
    assert waiting_tasks(db.broker_url) == {("voxe.ingest", waiting), ("voxe.ingest", lost)}
    with sqlite3.connect(db.broker_url.split(":///", 1)[1]) as broker:  # one message a scene: none sent twice
        assert broker.execute("SELECT count(*) FROM kombu_message").fetchone()[0] == 3


def test_two_workers_starting_together_send_a_lost_ingest_once_and_count_it(db, monkeypatch):
    """SQL broker: two workers starting at once each read the lost ingest's scene and the broker (no message carrying
    it) before either sent it, and each sent it: two copies. The start-up re-send claims the scene first (a
    conditional update of the row as read), as the reaper's does, so one sends it; and it counts the re-send
    (``Scene.lost_ingest_resends``), doubling the reaper's wait before it takes the new message as lost."""
    import sqlite3

    from voxe_service.broker import waiting_tasks as read_broker
    from worker import tasks

    lost = add_scene("processing")
    other_start = []

    def waiting_tasks(url):  # the other worker starts between this one's two reads and sends first
        waiting = read_broker(url)
        if not other_start:
            other_start.append("v@host")
            other_start.append(tasks.resend_lost_ingests("v@host"))
        return waiting

    monkeypatch.setattr(tasks, "waiting_tasks", waiting_tasks)
    assert tasks.resend_lost_ingests("w@host") == [] and other_start == ["v@host", [lost]]
    with sqlite3.connect(db.broker_url.split(":///", 1)[1]) as broker:
        assert broker.execute("SELECT count(*) FROM kombu_message").fetchone()[0] == 1
    scene = scene_row(lost)
    assert (scene.state, scene.worker_hostname, scene.lost_ingest_resends) == ("processing", None, 1)
    assert scene.task_id not in (None, "ingest")


def test_a_resend_the_broker_refuses_keeps_the_job_for_the_next_start(db, monkeypatch):
    """A sweep's evaluation whose re-send the broker refused had been left unsent, and the reaper fails an unsent
    evaluation ("never handed to the broker with its edit"): its task id comes back, and the next start sends it."""
    from voxe_service.queue import QueueUnavailable, TaskQueue
    from worker import tasks

    scene = add_scene()
    done_edit = add_job(scene, "succeeded", 0, batch_id="c")
    evaluation = add_job(scene, "queued", 0, mode="evaluate", batch_id="c", source_job_ids=[done_edit])

    def refused(self, signature):
        raise QueueUnavailable("could not queue the job: ConnectionError: down")

    with monkeypatch.context() as broker_down:
        broker_down.setattr(TaskQueue, "send", refused)
        assert tasks.resend_lost_queued_jobs("w@host") == []
    assert (job_row(evaluation).state, job_row(evaluation).task_id) == ("queued", "task")
    assert tasks.resend_lost_queued_jobs("w@host") == [evaluation]


def test_a_restarted_worker_sends_its_jobs_again_releasing_its_dead_runs_holds_up_to_the_limit(db):
    """SQL broker: a worker back under its name re-queues the jobs its previous process was running, though that
    process's lease has not run out (it is known dead), so the new message takes each job at once; a job sent
    again VOXE_JOB_MAX_REQUEUES times already fails instead of looping. So are the ingests it was running, their holds
    released too."""
    from voxe_service.db import session_scope
    from voxe_service.models import Scene, utcnow
    from worker import runtime, tasks

    scene, lease = add_scene(), utcnow() + timedelta(seconds=60)
    interrupted = add_job(scene, "running", 1, "w@host", "edit", run_token="dead", run_lease_until=lease)
    looping = add_job(scene, "running", 1, "w@host", "edit", requeues=db.job_max_requeues, run_token="dead too",
                      run_lease_until=lease)
    elsewhere = add_job(scene, "running", 1, "v@host", "edit", run_token="live", run_lease_until=lease)
    ingesting = add_scene("processing", worker="w@host", ingest_attempts=1, ingest_token="dead",
                          ingest_lease_until=lease)
    ingesting_elsewhere = add_scene("processing", worker="v@host", ingest_attempts=1, ingest_token="live",
                                    ingest_lease_until=lease)
    assert sorted(tasks.recover_interrupted_jobs("w@host")) == sorted([interrupted, looping, ingesting])
    with session_scope() as session:
        assert session.get(Scene, ingesting).ingest_token is None  # its new message takes it at once
        assert session.get(Scene, ingesting_elsewhere).ingest_token == "live"
    job = job_row(interrupted)
    assert (job.state, job.run_token, job.requeues, job.message) == (
        "queued", None, 1, "re-queued: worker w@host restarted while the job was in edit")
    assert job.task_id not in (None, "task") and [e["kind"] for e in events_of(interrupted)] == ["requeued"]
    assert runtime.begin_stage(interrupted, "edit", "w@host", "cpu", db).state == "running"  # at once
    assert job_row(looping).state == "failed" and job_row(looping).error.endswith(
        f"it was sent again {db.job_max_requeues} time(s) already, the limit "
        f"(VOXE_JOB_MAX_REQUEUES={db.job_max_requeues})")
    assert job_row(elsewhere).run_token == "live" and job_row(elsewhere).requeues == 0


def test_a_fits_lease_is_kept_without_progress_and_its_loss_is_seen(db, monkeypatch):
    """The keeper renews a claimed fit's lease while nothing reports progress (loading images, voxelizing); once
    the lease lapsed and another job claimed the fit, the first job's next renewal finds it gone and ``check``
    raises LeaseLost, so it stops instead of writing the fit's results beside the new owner."""
    import time

    from voxe_service.db import session_scope
    from voxe_service.models import Reconstruction, utcnow
    from worker import runtime

    monkeypatch.setattr(db, "reconstruction_lease_s", 0.4)
    scene = add_scene()
    first, second = (add_job(scene, "running", 0, "w@host", "reconstruct") for _ in range(2))
    rec_id = add_reconstruction(scene)

    def lease_until():
        with session_scope() as session:
            return session.get(Reconstruction, rec_id).lease_until

    assert runtime.try_claim_reconstruction(rec_id, first, "w@host", db, allow_failed=False)
    claimed = lease_until()
    with runtime.fit_lease(rec_id, first, db) as lease:
        time.sleep(1.0)  # no progress reported: only the keeper's thread renews
        assert lease_until() > claimed + timedelta(seconds=0.3) and not lease.lost
        with session_scope() as session:  # a stall outlived the lease, and another job claimed the fit (as
            rec = session.get(Reconstruction, rec_id)  # try_claim_reconstruction does, in one statement)
            rec.owner_job_id, rec.lease_until = second, utcnow() + timedelta(seconds=60)
        for _ in range(50):  # the keeper's next renewal finds the fit gone
            if lease.lost:
                break
            time.sleep(0.05)
        with pytest.raises(runtime.LeaseLost, match="another job took the fit over"):
            lease.check()
    assert not runtime.set_reconstruction(rec_id, first, state="succeeded")  # the owner's alone to change
    with session_scope() as session:
        assert session.get(Reconstruction, rec_id).owner_job_id == second


def test_a_workers_scratch_of_ended_or_deleted_jobs_is_swept_and_a_live_jobs_kept(db):
    """Only the worker running a job's last stage cleans its scratch; the sweep removes what other workers keep of
    jobs that have ended (or been deleted), never a live job's."""
    from pathlib import Path

    from worker.runtime import scratch_dir, sweep_scratch

    scene = add_scene()
    live, ended = add_job(scene, "running", 0, "w@host", "edit"), add_job(scene, "succeeded", 0, "w@host", "export")
    for job_id in (live, ended, "0" * 32):  # the last: a job deleted since
        (scratch_dir(job_id, db) / "edited_grid.safetensors").write_bytes(b"grid")
    assert sorted(sweep_scratch(db)) == sorted([ended, "0" * 32])
    assert [p.name for p in (Path(db.work_dir) / "jobs").iterdir()] == [live]
    assert sweep_scratch(db) == []


def test_a_workers_unpacked_datasets_of_deleted_scenes_are_swept_and_a_ready_scenes_kept(db):
    """Every worker that ran a job on a scene keeps its unpacked dataset (``runtime.scene_dataset``); the sweep
    removes those of scenes deleted (or not ready) since, with the debris of their unpacks, and the debris a job's
    run killed mid-unpack left of a ready scene none of whose jobs runs, never a ready scene's dataset or the unpack
    a running job of it may be making."""
    from pathlib import Path

    from worker.runtime import sweep_scene_datasets

    ready, idle, failed = add_scene(), add_scene(), add_scene("failed")
    add_job(ready, "running", 0, "w@host", "reconstruct")
    add_job(idle, "succeeded", 0, "w@host", "export")
    root = Path(db.work_dir) / "scenes"
    kept = [f"{ready}-{'0' * 12}", f".{ready}-k3j2x9", f"{idle}-{'0' * 12}"]  # an unpack under way beside its dataset
    gone = [f"{'1' * 32}-{'0' * 12}", f".{'1' * 32}-p0q7zz", f"{failed}-{'0' * 12}", f".{idle}-a1b2c3"]
    for name in kept + gone:
        (root / name).mkdir(parents=True)
        (root / name / "transforms_train.json").write_text("{}")
    assert sorted(sweep_scene_datasets(db)) == sorted(gone)
    assert sorted(p.name for p in root.iterdir() if p.is_dir()) == sorted(kept)
    assert sweep_scene_datasets(db) == []


def stored_dataset_scene(settings, tmp_path, name: str):
    """A ready scene (not recorded: what ``runtime.scene_dataset`` reads of it) whose stored archive holds a
    1000-byte file named after it."""
    from voxe_service.datasets import package
    from voxe_service.models import Scene
    from voxe_service.storage import get_storage

    folder = tmp_path / "datasets" / name
    folder.mkdir(parents=True)
    (folder / "transforms_train.json").write_text(name * (1000 // len(name)))
    package(folder, tmp_path / f"{name}.zip")
    scene_id = uuid.uuid4().hex
    stored = get_storage(settings).put_file(f"scenes/{scene_id}/dataset.zip", tmp_path / f"{name}.zip")
    return Scene(id=scene_id, state="ready", storage_key=stored.key, size_bytes=stored.size, sha256=stored.sha256)


def test_unpacked_datasets_past_the_cache_limit_evict_the_least_recently_used_one_no_stage_reads(db, tmp_path):
    """A worker kept every scene's unpacked dataset until the scene was deleted: serving many scenes, it filled its
    disk. Past VOXE_SCENE_CACHE_MAX_BYTES an unpack evicts the least recently used datasets no stage is reading (one
    being read stays, though least recently used), and a job needing an evicted one unpacks it again."""
    from pathlib import Path

    from voxe_service.storage import get_storage
    from worker import runtime

    settings, storage = db.model_copy(update={"scene_cache_max_bytes": 2500}), get_storage(db)  # two of 1002 bytes
    a, b, c = (stored_dataset_scene(db, tmp_path, name) for name in ("a", "b", "c"))
    root = Path(db.work_dir) / "scenes"

    def unpacked() -> set[str]:
        return {p.name.partition("-")[0] for p in root.iterdir() if p.is_dir()}

    def aged(scene, seconds: float) -> None:  # its last use set back (mtimes of one instant would tie)
        complete = root / f"{scene.id}-{scene.sha256[:12]}" / ".complete"
        os.utime(complete, (time.time() - seconds, time.time() - seconds))

    def read(scene) -> str:
        with runtime.scene_dataset(scene, settings, storage) as dataset:
            return (dataset / "transforms_train.json").read_text()

    assert (read(a), read(b)) == ("a" * 1000, "b" * 1000) and unpacked() == {a.id, b.id}
    with runtime.scene_dataset(b, settings, storage) as held:  # a stage reads b ...
        aged(b, 20)  # ... the least recently used, then a
        aged(a, 10)
        assert read(c) == "c" * 1000
        assert unpacked() == {b.id, c.id}  # a went; b stays while it is read
        assert (held / "transforms_train.json").read_text() == "b" * 1000
    assert read(a) == "a" * 1000  # unpacked again; b, no longer read, goes
    assert unpacked() == {a.id, c.id}
    assert runtime.evict_scene_datasets(settings) == []


def test_a_full_dataset_cache_evicts_before_an_unpack_writes_anything(db, tmp_path, monkeypatch):
    """With the cache full (two datasets of 1002 bytes under a limit of 2500), a third scene's unpack wrote its
    dataset beside both and evicted one only after: on a disk the cache filled, it needed first the very space that
    eviction frees. The least recently used dataset goes before the archive is unpacked."""
    from pathlib import Path

    from voxe_service import datasets
    from voxe_service.storage import get_storage
    from worker import runtime

    settings, storage = db.model_copy(update={"scene_cache_max_bytes": 2500}), get_storage(db)
    a, b, c = (stored_dataset_scene(db, tmp_path, name) for name in ("a", "b", "c"))
    root = Path(db.work_dir) / "scenes"
    for scene, age in ((a, 20), (b, 10)):
        with runtime.scene_dataset(scene, settings, storage) as dataset:
            os.utime(dataset / ".complete", (time.time() - age, time.time() - age))
    cached_at_unpack, unpack = [], datasets.unpack

    def unpacked(archive, dest):
        cached_at_unpack.append({p.name.partition("-")[0] for p in root.iterdir()
                                 if p.is_dir() and not p.name.startswith(".")})
        return unpack(archive, dest)

    monkeypatch.setattr(datasets, "unpack", unpacked)
    with runtime.scene_dataset(c, settings, storage) as dataset:
        assert (dataset / "transforms_train.json").read_text() == "c" * 1000
    assert cached_at_unpack == [{b.id}]
    assert {p.name.partition("-")[0] for p in root.iterdir() if p.is_dir()} == {b.id, c.id}


def test_two_unpacks_at_once_leave_the_dataset_cache_within_its_limit(db, tmp_path, monkeypatch):
    """Two unpacks at once (two pool processes of one worker; here two threads): each made room before it wrote,
    neither counting the other's dataset while still unpacked aside, and nothing evicted after, so the cache
    stayed over VOXE_SCENE_CACHE_MAX_BYTES until the next sweep. Room is made again once a dataset is in place: the
    least recently used one goes, the dataset just unpacked stays."""
    import threading
    from pathlib import Path

    from voxe_service import datasets
    from voxe_service.storage import get_storage
    from worker import runtime

    settings, storage = db.model_copy(update={"scene_cache_max_bytes": 2500}), get_storage(db)  # two of 1002 bytes
    a, b, c = (stored_dataset_scene(db, tmp_path, name) for name in ("a", "b", "c"))
    root = Path(db.work_dir) / "scenes"
    with runtime.scene_dataset(a, settings, storage) as dataset:
        os.utime(dataset / ".complete", (time.time() - 20, time.time() - 20))
    unpack = datasets.unpack

    def read_c() -> None:
        with runtime.scene_dataset(c, settings, storage):
            pass

    def c_unpacked_meanwhile(archive, dest):  # b's unpack, its room made: c's unpack runs from start to end
        if dest.parent.name.startswith(f".{b.id}-"):
            other = threading.Thread(target=read_c)
            other.start()
            other.join()
        return unpack(archive, dest)

    monkeypatch.setattr(datasets, "unpack", c_unpacked_meanwhile)
    with runtime.scene_dataset(b, settings, storage) as dataset:
        assert (dataset / "transforms_train.json").read_text() == "b" * 1000
    cached = [p for p in root.iterdir() if p.is_dir() and not p.name.startswith(".")]
    assert {p.name.partition("-")[0] for p in cached} == {b.id, c.id}
    assert sum(runtime._folder_bytes(p) for p in cached) <= settings.scene_cache_max_bytes


def test_datasets_are_evicted_where_an_exclusive_lock_needs_a_file_open_for_writing(db, tmp_path, monkeypatch,
                                                                                  caplog):
    """On NFS, Linux emulates flock with fcntl locks, and an exclusive one needs a descriptor open for writing: the
    eviction locked the folder of datasets (opened to read) and each ``.complete`` (opened to read), was refused
    (EBADF), took it for a filesystem without locks and evicted nothing, silently, the disk filling. It locks files
    open for writing, so it evicts there; and a filesystem without locks at all is said once, as a warning."""
    import errno
    import fcntl
    from pathlib import Path

    from voxe_service.storage import get_storage
    from worker import runtime

    settings, storage = db.model_copy(update={"scene_cache_max_bytes": 1500}), get_storage(db)  # one of 1002 bytes
    a, b = (stored_dataset_scene(db, tmp_path, name) for name in ("a", "b"))
    root = Path(db.work_dir) / "scenes"
    local_flock = fcntl.flock

    def nfs_flock(file, operation):
        fd = file if isinstance(file, int) else file.fileno()
        if operation & fcntl.LOCK_EX and fcntl.fcntl(fd, fcntl.F_GETFL) & os.O_ACCMODE == os.O_RDONLY:
            raise OSError(errno.EBADF, os.strerror(errno.EBADF))
        local_flock(file, operation)

    monkeypatch.setattr(fcntl, "flock", nfs_flock)
    for scene in (a, b):
        with runtime.scene_dataset(scene, settings, storage):
            pass
    assert [p.name.partition("-")[0] for p in root.iterdir() if p.is_dir()] == [b.id]  # a went as b was unpacked

    def no_locks(file, operation):
        raise OSError(errno.ENOLCK, os.strerror(errno.ENOLCK))

    monkeypatch.setattr(fcntl, "flock", no_locks)
    with caplog.at_level(logging.WARNING, logger="voxe.worker"):
        tiny = settings.model_copy(update={"scene_cache_max_bytes": 1})
        assert runtime.evict_scene_datasets(tiny) == runtime.evict_scene_datasets(tiny) == []
    said = [r.getMessage() for r in caplog.records if "takes no file locks" in r.getMessage()]
    assert said == [f"{root} takes no file locks ([Errno {errno.ENOLCK}] {os.strerror(errno.ENOLCK)}): its unpacked "
                    "datasets are never evicted, whatever VOXE_SCENE_CACHE_MAX_BYTES says"]


def test_where_flock_is_a_posix_lock_a_stages_own_process_evicts_no_dataset_it_reads(db, tmp_path, monkeypatch):
    """On NFS, Linux emulates flock with POSIX (fcntl) locks, which belong to the process: the eviction's exclusive
    lock on a ``.complete`` was granted over its own process's shared one, and closing it released the stage's, so
    the dataset a stage had just unpacked (alone over the limit) was deleted from under it. A dataset a stage of the
    process reads is never evicted by it; once no stage reads it, it goes."""
    import fcntl
    from pathlib import Path

    from voxe_service.storage import get_storage
    from worker import runtime

    settings, storage = db.model_copy(update={"scene_cache_max_bytes": 500}), get_storage(db)  # dataset: 1002 bytes
    scene = stored_dataset_scene(db, tmp_path, "a")

    def nfs_flock(file, operation):  # what the NFS client makes of flock(): a whole-file POSIX lock
        fcntl.lockf(file, operation)

    monkeypatch.setattr(fcntl, "flock", nfs_flock)
    with runtime.scene_dataset(scene, settings, storage) as dataset:
        assert runtime.evict_scene_datasets(settings) == []
        assert (dataset / "transforms_train.json").read_text() == "a" * 1000
    assert runtime.evict_scene_datasets(settings) == [dataset.name]
    assert [p for p in Path(db.work_dir, "scenes").iterdir() if p.is_dir()] == []


def test_a_stage_that_waited_on_an_eviction_of_its_dataset_reads_one_it_holds(db, tmp_path):
    """A stage that found its dataset as an eviction took it (the eviction holds its lock while it deletes it) waits
    for the eviction, then reads the dataset as unpacked again (by another stage meanwhile, here), holding that one:
    it had held the deleted folder's lock, and an eviction took the folder it read."""
    import fcntl
    import shutil
    import threading
    from pathlib import Path

    from voxe_service.storage import get_storage
    from worker import runtime

    storage, scene = get_storage(db), stored_dataset_scene(db, tmp_path, "a")
    with runtime.scene_dataset(scene, db, storage) as dataset:
        pass
    read = {}

    def stage():
        with runtime.scene_dataset(scene, db, storage) as again:
            read["evicted"] = runtime.evict_scene_datasets(db.model_copy(update={"scene_cache_max_bytes": 1}))
            read["text"] = (again / "transforms_train.json").read_text()

    with open(dataset / ".complete", "rb") as lock:  # an eviction of it under way
        fcntl.flock(lock, fcntl.LOCK_EX)
        thread = threading.Thread(target=stage)
        thread.start()
        thread.join(0.5)
        assert thread.is_alive() and not read  # waiting for the lock
        doomed = dataset.with_name(f".{dataset.name}-evicted")
        os.rename(dataset, doomed)
        shutil.rmtree(doomed)
        with runtime.scene_dataset(scene, db, storage):  # another stage unpacks it again
            pass
    thread.join(30)
    assert read == {"evicted": [], "text": "a" * 1000}
    assert [p.name for p in Path(db.work_dir, "scenes").iterdir() if p.is_dir()] == [dataset.name]


def test_the_uploads_killed_ingests_left_are_swept_once_their_scenes_are_no_longer_processing(db):
    """An ingest unpacks its upload under ``work/ingest/<scene id>-*`` and removes it as it ends; a run whose
    process was killed left it (up to VOXE_MAX_EXTRACTED_BYTES each). The sweep removes those of scenes ready,
    failed or deleted since, never a processing scene's (a run of it may be decoding there)."""
    from pathlib import Path

    from worker.runtime import sweep_ingest_scratch

    processing, ready, failed = add_scene("processing"), add_scene(), add_scene("failed")
    root = Path(db.work_dir) / "ingest"
    kept = [f"{processing}-a1b2c3", f"{processing}-d4e5f6"]  # a run decoding, and one killed before it
    gone = [f"{ready}-a1b2c3", f"{failed}-a1b2c3", f"{'1' * 32}-a1b2c3"]
    for name in kept + gone:
        (root / name / "data").mkdir(parents=True)
        (root / name / "archive.zip").write_bytes(b"PK")
    assert sorted(sweep_ingest_scratch(db)) == sorted(gone)
    assert sorted(p.name for p in root.iterdir()) == sorted(kept)
    assert sweep_ingest_scratch(db) == []


def test_an_upload_whose_ingest_kills_its_worker_fails_its_scene_at_the_requeue_limit(db, tmp_path, monkeypatch):
    """Each run of an ingest that dies with its process (the OOM killer on a large upload) is sent again (Celery's
    reject on a lost worker, a restarted worker's recovery) and took the scene anew, for ever. The runs are
    counted: the delivery after VOXE_JOB_MAX_REQUEUES re-sends fails the scene naming why, and the jobs waiting
    on it, and frees its upload."""
    import zipfile

    from voxe_service import datasets
    from voxe_service.db import session_scope
    from voxe_service.models import Scene
    from voxe_service.storage import get_storage, scene_key
    from worker import ingest

    class Killed(BaseException):
        """The run's process killed mid-decode: nothing of the ingest's own handling runs."""

    decoded = []

    def killed(root, downsample):
        decoded.append(root)
        raise Killed()

    monkeypatch.setattr(ingest, "decode", killed)
    storage = get_storage(db)
    with zipfile.ZipFile(tmp_path / "upload.zip", "w") as zf:
        zf.writestr("transforms_train.json", "{}")
    scene = add_scene("processing")
    stored = storage.put_file(scene_key(scene, datasets.DATASET_ARCHIVE), tmp_path / "upload.zip")
    with session_scope() as session:  # as the API records an upload: the ingest checks what it fetches by it
        row = session.get(Scene, scene)
        row.storage_key, row.size_bytes, row.sha256 = stored.key, stored.size, stored.sha256
    waiting = add_job(scene, "queued", 0, task_id=None)
    for _ in range(db.job_max_requeues + 1):  # the first run and its re-sends: each decodes
        with pytest.raises(Killed):
            ingest.ingest_scene(scene, db, storage, "w@host")
        expire_ingest_hold(scene)  # (the killed run renews its hold no more: the next takes the scene over)
    assert len(decoded) == db.job_max_requeues + 1
    assert ingest.ingest_scene(scene, db, storage, "w@host") == {"scene_id": scene, "state": "failed"}
    assert len(decoded) == db.job_max_requeues + 1  # not decoded again
    with session_scope() as session:
        row = session.get(Scene, scene)
        reason = (f"ingest: interrupted {db.job_max_requeues + 1} times, its worker process dying each time (killed: "
                  f"out of memory?), a database outage or a full disk stopping it; it was sent again {db.job_max_requeues} time(s) already, the limit "
                  f"(VOXE_JOB_MAX_REQUEUES={db.job_max_requeues})")
        assert (row.state, row.error, row.size_bytes) == ("failed", reason, 0)
    assert job_row(waiting).error == f"the scene's upload failed processing: {reason}"
    assert not storage.exists(stored.key)


def test_an_object_recorded_but_gone_from_the_storage_fails_naming_what_it_was(db, tmp_path):
    """A scene's upload or archive, or a job's grid, recorded but no longer in the storage (deleted there: by hand, a
    bucket's lifecycle rule) had failed the ingest or the stage as "ObjectNotFound: 'scenes/<id>/upload.zip'", a
    KeyError's quoted key, what it was and what became of it unsaid. The error names what was fetched, its key and
    that the storage no longer holds it, and no download or unpacked folder is left behind."""
    import zipfile

    from voxe_service.db import session_scope
    from voxe_service.models import Scene
    from voxe_service.storage import StorageError, StoredObject, get_storage, scene_key
    from worker import ingest, inputs, runtime

    storage = get_storage(db)
    with zipfile.ZipFile(tmp_path / "upload.zip", "w") as zf:
        zf.writestr("transforms_train.json", "{}")
    scene = add_scene("processing")
    stored = storage.put_file(scene_key(scene, "upload.zip"), tmp_path / "upload.zip")
    with session_scope() as session:  # recorded as the API records an upload, then deleted from the storage
        row = session.get(Scene, scene)
        row.storage_key, row.size_bytes, row.sha256 = stored.key, stored.size, stored.sha256
    storage.delete(stored.key)
    gone = f"{stored.key}: not in the storage, deleted there since it was recorded"
    assert ingest.ingest_scene(scene, db, storage, "w@host") == {"scene_id": scene, "state": "failed"}
    assert scene_row(scene).error == f"ingest: StorageError: scene {scene}'s upload {gone}"
    assert list((tmp_path / "work" / "ingest").iterdir()) == []

    with session_scope() as session:  # a ready scene whose archive went: a job's unpack of it
        row = session.get(Scene, scene)
        row.state, row.error = "ready", None
        session.flush()
        session.expunge(row)
    with pytest.raises(StorageError) as unpacked:
        with runtime.scene_dataset(row, db, storage):
            pass
    assert str(unpacked.value) == f"scene {scene}'s archive {gone}"
    assert [p.name for p in (tmp_path / "work" / "scenes").iterdir() if p.name != runtime.EVICTION_LOCK] == []

    grid = StoredObject("jobs/j/edited_grid.safetensors", 10, "0" * 64)  # a job's grid, as its artifact row says
    with pytest.raises(StorageError) as fetched:
        inputs.fetch_grid("j", "edited_grid.safetensors", db, storage, grid)
    assert runtime.failure_text(fetched.value) == (f"StorageError: {grid.key}: not in the storage, deleted there "
                                                   "since it was recorded")
    assert not runtime.scratch_dir("j", db).joinpath("edited_grid.safetensors").exists()


def expire_ingest_hold(scene_id: str) -> None:
    """The lease of the run holding the scene's ingest ran out (its process killed, it is renewed no more)."""
    from sqlalchemy import update

    from voxe_service.db import session_scope
    from voxe_service.models import Scene, utcnow

    with session_scope() as session:
        session.execute(update(Scene).where(Scene.id == scene_id)
                        .values(ingest_lease_until=utcnow() - timedelta(seconds=1)))


def test_a_scratch_copy_is_reused_only_while_it_holds_the_recorded_bytes(tmp_path):
    """A worker's scratch may hold a grid nobody published (a run that lost its job or the fit wrote it there):
    fetch reuses a file only when its size and SHA-256 are the record's, downloads otherwise, and refuses a
    download that is not the recorded object, naming its key."""
    from voxe_service.storage import LocalStorage, StorageError
    from worker.runtime import fetch

    storage = LocalStorage(tmp_path / "store")
    recorded = storage.put_bytes("jobs/j/edited_grid.safetensors", b"the published grid")
    dest = tmp_path / "scratch" / "edited_grid.safetensors"
    dest.parent.mkdir()
    for unpublished in (b"a superseded run's grid", b"the published grix"):  # another size, then the same size
        dest.write_bytes(unpublished)
        assert fetch(storage, recorded, dest).read_bytes() == b"the published grid"
    storage.delete(recorded.key)
    assert fetch(storage, recorded, dest).read_bytes() == b"the published grid"  # the copy holds it: reused
    storage.put_bytes(recorded.key, b"other bytes under the key")
    dest.unlink()
    with pytest.raises(StorageError, match="jobs/j/edited_grid.safetensors: the stored bytes are not the ones"):
        fetch(storage, recorded, dest)
    assert not dest.exists()


def events_of(job_id: str) -> list[dict]:
    from sqlalchemy import select

    from voxe_service.db import session_scope
    from voxe_service.models import JobEvent

    with session_scope() as session:
        return [{"kind": e.kind, "stage": e.stage, "detail": e.detail} for e in
                session.scalars(select(JobEvent).where(JobEvent.job_id == job_id).order_by(JobEvent.id))]


def test_a_database_outage_skips_a_stages_warning_event_and_its_next_progress_write_says_the_warning(db, monkeypatch):
    """A database blip as the edit's warning event was written raised out of the stage (a re-queue counting towards
    job_max_requeues) where a progress write in it is skipped. The event is skipped alike, and the next progress
    write carries the warning as the job's message; a fault that is no outage still raises."""
    import sqlite3

    from sqlalchemy.exc import OperationalError

    from voxe_core.progress import Progress
    from worker import runtime

    job_id = add_job(add_scene(), "queued", 0, completed_stages=["reconstruct"])
    callbacks = runtime.StageCallbacks(runtime.begin_stage(job_id, "edit", "a@host", "cpu", db), "edit", db)
    said = "the reconstruction's density is constant: the 3D regulariser (reg3d) has nothing to correlate and is off"
    blip = OperationalError("SELECT jobs", {}, Exception("server closed the connection unexpectedly"))

    def down(*args, **kwargs):
        raise blip

    with monkeypatch.context() as outage:
        outage.setattr(runtime, "locked", down)
        callbacks.callbacks.warning("edit", said)  # skipped: the stage goes on
    callbacks.on_progress(Progress("edit", 1, 10))
    assert job_row(job_id).message == said
    assert [e for e in events_of(job_id) if e["kind"] == "warning"] == []
    blip = OperationalError("SELECT jobs", {}, sqlite3.OperationalError("no such column: jobs.message"))
    monkeypatch.setattr(runtime, "locked", down)
    with pytest.raises(OperationalError, match="no such column"):
        callbacks.callbacks.warning("edit", said)


def test_a_database_outage_as_a_checkpoint_that_cannot_be_gone_on_from_is_started_over_skips_its_warning(db,
                                                                                                       monkeypatch,
                                                                                                       tmp_path):
    """The warning that a stored checkpoint could not be gone on from was written straight to the database: a blip
    there raised out of the stage (a counted re-queue) after the checkpoint was discarded, so the redelivery started
    over with nothing said. It goes through the callbacks' warning: the event skipped, the stage started over, the
    next progress write saying why."""
    from sqlalchemy.exc import OperationalError

    from voxe_core.progress import Progress
    from voxe_core.tensorio import FormatError
    from voxe_service.storage import get_storage
    from worker import runtime, tasks

    job_id = add_job(add_scene(), "queued", 0, completed_stages=["reconstruct"])
    callbacks = runtime.StageCallbacks(runtime.begin_stage(job_id, "edit", "a@host", "cpu", db), "edit", db)
    storage, key = get_storage(db), f"jobs/{job_id}/checkpoints/edit.safetensors"
    (tmp_path / "c").write_bytes(b"x")
    storage.put_file(key, tmp_path / "c", "application/octet-stream")

    def run(resume):
        if resume is not None:
            raise FormatError("checkpoint was made against other input views")
        return "started over"

    def down(*args, **kwargs):
        raise OperationalError("SELECT jobs", {}, Exception("server closed the connection unexpectedly"))

    with monkeypatch.context() as outage:
        outage.setattr(runtime, "locked", down)
        outage.setattr(runtime, "update_job", down)
        assert tasks._resumed_or_started_over(run, tmp_path / "c", job_id, "edit", callbacks, storage, key,
                                              functools.partial(runtime.forget_checkpoint, job_id)) == "started over"
    assert not storage.exists(key) and [e for e in events_of(job_id) if e["kind"] == "warning"] == []
    callbacks.on_progress(Progress("edit", 1, 10))
    assert job_row(job_id).message == ("the stored edit checkpoint could not be gone on from (checkpoint was made "
                                       "against other input views): started over")


@pytest.mark.parametrize("then", ["canceled", "taken over"])
def test_a_stalled_runs_progress_writes_nothing_on_a_job_it_no_longer_holds(db, then):
    """A run stalled past its lease wrote its progress over the job all the same: over a cancel's ending (its reason
    erased, the canceled job at the stalled run's iteration), or over the progress of the run that took it over.
    Its progress (and the last report written as it stops) is written only while it holds the job."""
    from sqlalchemy import update

    from api.services.jobs import request_cancel
    from voxe_core.progress import Progress
    from voxe_service.db import session_scope
    from voxe_service.models import Job, utcnow
    from worker import runtime

    job_id = add_job(add_scene(), "queued", 0, completed_stages=["reconstruct"])
    stalled = runtime.StageCallbacks(runtime.begin_stage(job_id, "edit", "a@host", "cpu", db), "edit", db)
    if then == "canceled":
        with session_scope() as session:
            request_cancel(session=session, job_ids=[job_id])
    long_ago = utcnow() - timedelta(seconds=2 * db.job_stale_timeout_s)
    with session_scope() as session:
        session.execute(update(Job).where(Job.id == job_id).values(run_lease_until=long_ago))
    if then == "canceled":
        with pytest.raises(runtime.JobSkipped, match="canceled"):
            runtime.begin_stage(job_id, "edit", "b@host", "cpu", db)
    else:
        taker = runtime.StageCallbacks(runtime.begin_stage(job_id, "edit", "b@host", "cpu", db), "edit", db)
        taker.on_progress(Progress("edit", 5, 100))
    before = job_row(job_id)
    stalled.on_progress(Progress("edit", 77, 100))  # the stalled run wakes
    stalled._last_check = -math.inf
    stalled.on_progress(Progress("edit", 78, 100))  # (held back by the write interval) then asks: it stops
    assert stalled.should_cancel()
    after = job_row(job_id)
    assert (after.state, after.message, after.iteration) == (before.state, before.message, before.iteration)
    assert after.iteration == (0 if then == "canceled" else 5)


@contextlib.contextmanager
def holding(job_id: str, run_token: str):
    """This thread runs a stage of ``job_id`` as the run ``run_token`` (its hold, with no lease renewed)."""
    from worker import runtime

    mark = runtime._HOLDING.set((job_id, run_token))
    try:
        yield
    finally:
        runtime._HOLDING.reset(mark)


def _ended_by_another_worker(db, job_id: str, stage: str) -> None:
    """The job canceled and its lease lapsed, a redelivery on another worker ending it as it starts (run from a
    stalled run's storage call, as another worker would, outside its hold)."""
    from sqlalchemy import update

    from api.services.jobs import request_cancel
    from voxe_service.db import session_scope
    from voxe_service.models import Job, utcnow
    from worker import runtime

    outside = runtime._HOLDING.set(None)
    try:
        with session_scope() as session:
            request_cancel(session=session, job_ids=[job_id])
            session.execute(update(Job).where(Job.id == job_id).values(run_lease_until=utcnow() - timedelta(hours=1)))
        with pytest.raises(runtime.JobSkipped, match="canceled"):
            runtime.begin_stage(job_id, stage, "b@host", "cpu", db)
    finally:
        runtime._HOLDING.reset(outside)


def test_a_stalled_runs_upload_or_checkpoint_meeting_its_jobs_ending_leaves_nothing_after_it(db, tmp_path,
                                                                                            monkeypatch):
    """A stalled run whose job another worker ended while it uploaded an artifact kept the bytes at the artifact's
    fixed key (kept for a new owner, which an ended job has not): stored, listed by no row. One ended while it
    stored a checkpoint recorded a ``checkpoint`` event after the ending. Neither now."""
    from voxe_core.progress import Progress
    from voxe_service.storage import get_storage
    from worker import runtime

    storage = get_storage(db)
    job_id = add_job(add_scene(), "queued", 0, completed_stages=["reconstruct", "edit"])
    stalled = runtime.begin_stage(job_id, "export", "a@host", "cpu", db)
    real_put = storage.put_file

    def put_while_ended(key, path, *args, **kwargs):
        stored = real_put(key, path, *args, **kwargs)
        _ended_by_another_worker(db, job_id, "export")
        return stored

    monkeypatch.setattr(storage, "put_file", put_while_ended)
    (tmp_path / "turntable.mp4").write_bytes(b"video")
    with holding(job_id, stalled.run_token), pytest.raises(runtime.RunSuperseded):
        runtime.publish_artifact(job_id, "turntable.mp4", tmp_path / "turntable.mp4", "video", storage)
    assert storage.list(f"jobs/{job_id}/") == []

    job_id = add_job(add_scene(), "queued", 0, completed_stages=["reconstruct"])
    stalled = runtime.begin_stage(job_id, "edit", "a@host", "cpu", db)
    callbacks = runtime.StageCallbacks(stalled, "edit", db, on_checkpoint=lambda path, iteration: (
        _ended_by_another_worker(db, job_id, "edit")))
    callbacks.on_progress(Progress("edit", 10, 100))
    with holding(job_id, stalled.run_token), pytest.raises(runtime.RunSuperseded):
        callbacks.on_checkpoint(str(tmp_path / "checkpoint"))
    assert [e["kind"] for e in events_of(job_id)][-1] == "canceled"


def _take_over_lapsed(db, job_id: str, stage: str):
    """Another worker's run takes the job's lapsed hold over (run outside the stalled run's hold); its job row."""
    from sqlalchemy import update

    from voxe_service.db import session_scope
    from voxe_service.models import Job, utcnow
    from worker import runtime

    outside = runtime._HOLDING.set(None)
    try:
        with session_scope() as session:
            session.execute(update(Job).where(Job.id == job_id).values(run_lease_until=utcnow() - timedelta(hours=1)))
        return runtime.begin_stage(job_id, stage, "b@host", "cpu", db)
    finally:
        runtime._HOLDING.reset(outside)


def _run_checkpoint_store(storage, job):
    """What the edit stores a checkpoint with (worker.tasks._edit): the run's own key."""
    from worker import runtime

    return lambda path, iteration: storage.put_file(runtime.run_checkpoint_key(job, "edit", iteration), path)


@pytest.mark.parametrize("then", ["ended", "taken over"])
def test_a_stalled_runs_refused_checkpoint_goes_unless_it_is_the_jobs_live_one(db, tmp_path, then):
    """A stalled run whose checkpoint's event was refused (RunSuperseded: the job ended, or another run took it over,
    as it stored the checkpoint) left the bytes behind: an ended job's cleanup had run already, so they stayed, listed
    nowhere, until the job was deleted. They go, as the bytes of a run that took over no longer share its key; the
    job's live checkpoint (none here) is kept."""
    from voxe_core.progress import Progress
    from voxe_service.storage import get_storage
    from worker import runtime

    storage, job_id = get_storage(db), add_job(add_scene(), "queued", 0, completed_stages=["reconstruct"])
    stalled = runtime.begin_stage(job_id, "edit", "a@host", "cpu", db)
    store = _run_checkpoint_store(storage, stalled)

    def store_as_it_loses_the_job(path, iteration):
        stored = store(path, iteration)
        if then == "ended":
            _ended_by_another_worker(db, job_id, "edit")
        else:
            _take_over_lapsed(db, job_id, "edit")
        return stored

    callbacks = runtime.StageCallbacks(stalled, "edit", db, on_checkpoint=store_as_it_loses_the_job)
    callbacks.on_progress(Progress("edit", 10, 100))
    (tmp_path / "checkpoint").write_bytes(b"the edit at 10")
    with holding(job_id, stalled.run_token), pytest.raises(runtime.RunSuperseded):
        callbacks.on_checkpoint(str(tmp_path / "checkpoint"))
    assert storage.list(f"jobs/{job_id}/checkpoints/") == [] and job_row(job_id).checkpoint_key is None
    assert "checkpoint" not in [e["kind"] for e in events_of(job_id)]


def test_a_stalled_runs_late_checkpoint_never_replaces_the_checkpoint_of_the_run_that_took_its_job_over(db,
                                                                                                      tmp_path):
    """A run stalled past its lease, its job taken over, passed its ownership check and then stored its checkpoint
    after the new run had stored its own, at the same fixed key: the new run's checkpoint was replaced by the stalled
    run's older state, which the job's next run resumed from. Each run stores at a key of its own and records it as
    the job's live checkpoint only while it holds the job: the stalled run's late bytes are refused and deleted, the
    new run's stay where the job's next run reads them; the replaced one (the stalled run's earlier) goes."""
    from voxe_core.progress import Progress
    from voxe_service.storage import get_storage
    from worker import runtime

    storage, job_id = get_storage(db), add_job(add_scene(), "queued", 0, completed_stages=["reconstruct"])
    stalled = runtime.begin_stage(job_id, "edit", "a@host", "cpu", db)
    stalled_callbacks = runtime.StageCallbacks(stalled, "edit", db,
                                               on_checkpoint=_run_checkpoint_store(storage, stalled))
    (tmp_path / "old").write_bytes(b"the stalled run's edit at 10")
    stalled_callbacks.on_progress(Progress("edit", 10, 100))
    with holding(job_id, stalled.run_token):
        stalled_callbacks.on_checkpoint(str(tmp_path / "old"))  # its last checkpoint while it held the job

    def taken_over_and_checkpointed_first(path, iteration):  # the stalled run passed its check, then stalled
        taken = _take_over_lapsed(db, job_id, "edit")
        assert taken.checkpoint_key == runtime.run_checkpoint_key(stalled, "edit", 10)  # what the new run resumes from
        new_callbacks = runtime.StageCallbacks(taken, "edit", db, on_checkpoint=_run_checkpoint_store(storage, taken))
        (tmp_path / "new").write_bytes(b"the new run's edit at 30")
        new_callbacks.on_progress(Progress("edit", 30, 100))
        with holding(job_id, taken.run_token):
            new_callbacks.on_checkpoint(str(tmp_path / "new"))
        return _run_checkpoint_store(storage, stalled)(path, iteration)  # ... and only then uploads

    stalled_callbacks._store_checkpoint = taken_over_and_checkpointed_first
    (tmp_path / "late").write_bytes(b"the stalled run's edit at 12")
    stalled_callbacks.on_progress(Progress("edit", 12, 100))
    with holding(job_id, stalled.run_token), pytest.raises(runtime.RunSuperseded):
        stalled_callbacks.on_checkpoint(str(tmp_path / "late"))

    live = job_row(job_id).checkpoint_key
    assert b"".join(storage.open_range(live)) == b"the new run's edit at 30"
    assert storage.list(f"jobs/{job_id}/checkpoints/") == [live]  # the stalled run's, early and late, gone
    assert [e["kind"] for e in events_of(job_id)].count("checkpoint") == 2  # the stalled run's first, the new run's


def test_a_fit_owner_that_lost_the_fit_never_replaces_the_new_owners_checkpoint(db, tmp_path):
    """The fit's owner stored its checkpoint at the reconstruction's one fixed key and then recorded it, a record
    refused once another run owned the fit but the upload not: an owner stalled past its lease, storing after the new
    owner had stored, replaced the new owner's checkpoint with its older state. Each run stores under its own name
    and records it only while it owns the fit: the stalled owner's late bytes go and it stops (LeaseLost)."""
    from voxe_service.storage import get_storage, reconstruction_storage_key
    from worker import runtime, tasks

    storage, scene = get_storage(db), add_scene()
    job_id, rec_id = add_job(scene, "queued", 0), add_reconstruction(scene)
    stalled = runtime.begin_stage(job_id, "reconstruct", "a@host", "cpu", db)
    assert runtime.try_claim_reconstruction(rec_id, job_id, "a@host", db, True, run_token=stalled.run_token)
    for name in ("old", "new", "late"):
        (tmp_path / name).write_bytes(f"the {name} fit checkpoint".encode())
    tasks._store_fit_checkpoint(stalled, rec_id, storage, tmp_path / "old", 10)

    taken = _take_over_lapsed(db, job_id, "reconstruct")  # the stalled run's job, and then its fit, taken over
    assert runtime.try_claim_reconstruction(rec_id, job_id, "b@host", db, True, run_token=taken.run_token)
    resumed_from = runtime.load_reconstruction(rec_id).checkpoint_key
    assert b"".join(storage.open_range(resumed_from)) == b"the old fit checkpoint"
    tasks._store_fit_checkpoint(taken, rec_id, storage, tmp_path / "new", 30)
    with pytest.raises(runtime.LeaseLost):  # the stalled owner wakes and stores
        tasks._store_fit_checkpoint(stalled, rec_id, storage, tmp_path / "late", 12)

    recorded = runtime.load_reconstruction(rec_id).checkpoint_key
    assert b"".join(storage.open_range(recorded)) == b"the new fit checkpoint"
    assert storage.list(reconstruction_storage_key(rec_id, "checkpoint")) == [recorded]


def _set_row(model, row_id: str, **values) -> None:
    from sqlalchemy import update

    from voxe_service.db import session_scope

    with session_scope() as session:
        session.execute(update(model).where(model.id == row_id).values(**values))


def test_a_start_over_clears_the_jobs_checkpoint_record_only_for_its_holder_and_only_while_it_names_that_key(db):
    """forget_checkpoint clears jobs.checkpoint_key for the stage starting over: a stalled run whose job another
    run took over is refused (the checkpoint is the new run's), and a record naming another key (a newer checkpoint)
    is left as it is."""
    from voxe_service.models import Job
    from worker import runtime

    job_id = add_job(add_scene(), "running", 0)
    _set_row(Job, job_id, run_token="new", checkpoint_key="K")
    with holding(job_id, "old"), pytest.raises(runtime.RunSuperseded):
        runtime.forget_checkpoint(job_id, "K")
    assert job_row(job_id).checkpoint_key == "K"
    with holding(job_id, "new"):
        runtime.forget_checkpoint(job_id, "another key")
        assert job_row(job_id).checkpoint_key == "K"
        runtime.forget_checkpoint(job_id, "K")
    assert job_row(job_id).checkpoint_key is None


def test_a_start_over_clears_the_fits_checkpoint_record_only_for_its_owner_and_only_while_it_names_that_key(db):
    """forget_fit_checkpoint clears reconstructions.checkpoint_key for the fit starting over: a run that no longer
    owns the fit gets LeaseLost (the checkpoint is the new owner's), and a record naming another key is kept."""
    from voxe_service.models import Reconstruction
    from worker import runtime

    scene = add_scene()
    rec_id = add_reconstruction(scene)
    job_id = add_job(scene, "running", 0, reconstruction_id=rec_id)
    _set_row(Reconstruction, rec_id, state="running", owner_job_id=job_id, owner_run_token="owner", checkpoint_key="K")
    with pytest.raises(runtime.LeaseLost):
        runtime.forget_fit_checkpoint(rec_id, job_id, "stalled", "K")
    assert runtime.load_reconstruction(rec_id).checkpoint_key == "K"
    runtime.forget_fit_checkpoint(rec_id, job_id, "owner", "another key")
    assert runtime.load_reconstruction(rec_id).checkpoint_key == "K"
    runtime.forget_fit_checkpoint(rec_id, job_id, "owner", "K")
    assert runtime.load_reconstruction(rec_id).checkpoint_key is None


def test_a_database_outage_as_a_start_over_clears_the_checkpoint_record_skips_the_clearing(db, monkeypatch):
    """Either record's clearing meeting a database outage is skipped, as a progress write is: raised, the start
    over had become a counted re-queue (a later run finds the record's object gone and starts from the start)."""
    import sqlite3
    from sqlalchemy.exc import OperationalError

    from worker import runtime

    @contextlib.contextmanager
    def down():
        raise OperationalError("UPDATE", {}, sqlite3.OperationalError("database is locked"))
        yield

    monkeypatch.setattr(runtime, "session_scope", down)
    runtime.forget_fit_checkpoint("a reconstruction", "a job", "a run", "K")
    with holding("a job", "a run"):
        runtime.forget_checkpoint("a job", "K")


def test_a_recorded_checkpoint_with_nothing_stored_is_logged_and_its_stage_starts_from_the_start(db, tmp_path,
                                                                                                 caplog):
    """A run's recorded checkpoint key naming nothing stored (a start over's record a database blip kept, or 0019's
    old fixed key) is not gone on from, and the log says so; a stored one is, and no record says nothing."""
    from voxe_service.storage import get_storage
    from worker import tasks

    storage = get_storage(db)
    (tmp_path / "c").write_bytes(b"x")
    storage.put_file("jobs/j/checkpoints/stored", tmp_path / "c", "application/octet-stream")
    with caplog.at_level(logging.INFO, logger=tasks.log.name):
        assert tasks._recorded_checkpoint_stored(storage, "jobs/j/checkpoints/stored", "job j", "edit checkpoint")
        assert not tasks._recorded_checkpoint_stored(storage, None, "job j", "edit checkpoint")
        assert not caplog.records
        assert not tasks._recorded_checkpoint_stored(storage, "jobs/j/checkpoints/gone", "job j", "edit checkpoint")
    assert caplog.messages == ["job j: its recorded edit checkpoint jobs/j/checkpoints/gone is not stored; starting "
                               "from the start"]


def test_a_checkpoint_whose_record_failed_leaves_the_recorded_checkpoints_bytes_as_they_were(db, tmp_path,
                                                                                             monkeypatch):
    """A run stored every checkpoint at one key: one whose record then failed (the database out of reach as it
    recorded the checkpoint at 20) had overwritten the recorded checkpoint's bytes (at 10), which the redelivery
    resumed from as if they were 10's. Each checkpoint has a key of its own: the recorded one keeps its bytes and the
    unrecorded one goes."""
    from sqlalchemy.exc import OperationalError

    from voxe_core.progress import Progress
    from voxe_service.storage import get_storage
    from worker import runtime

    storage, job_id = get_storage(db), add_job(add_scene(), "queued", 0, completed_stages=["reconstruct"])
    run = runtime.begin_stage(job_id, "edit", "a@host", "cpu", db)
    callbacks = runtime.StageCallbacks(run, "edit", db, on_checkpoint=_run_checkpoint_store(storage, run))
    for iteration in (10, 20):
        (tmp_path / f"at{iteration}").write_bytes(f"the edit at {iteration}".encode())
    with holding(job_id, run.run_token):
        callbacks.on_progress(Progress("edit", 10, 100))
        callbacks.on_checkpoint(str(tmp_path / "at10"))

        def out_of_reach(*args, **kwargs):
            raise OperationalError("INSERT INTO job_events", {}, Exception("database is locked"))

        monkeypatch.setattr(runtime, "record_event", out_of_reach)
        callbacks.on_progress(Progress("edit", 20, 100))
        with pytest.raises(OperationalError):
            callbacks.on_checkpoint(str(tmp_path / "at20"))
    recorded = job_row(job_id).checkpoint_key
    assert b"".join(storage.open_range(recorded)) == b"the edit at 10"
    assert storage.list(f"jobs/{job_id}/checkpoints/") == [recorded]


def _owned_fit(db, job_id: str, rec_id: str, host: str, take_over: bool = False):
    """A run of the job's reconstruct stage (one that took the stalled one's lapsed hold over, with ``take_over``)
    owning the fit; its job row."""
    from worker import runtime

    run = (_take_over_lapsed(db, job_id, "reconstruct") if take_over
           else runtime.begin_stage(job_id, "reconstruct", host, "cpu", db))
    assert runtime.try_claim_reconstruction(rec_id, job_id, host, db, True, run_token=run.run_token)
    return run


def test_a_refused_fit_checkpoint_leaves_the_recorded_checkpoints_bytes_as_they_were(db, tmp_path):
    """A fit owner stored each of its checkpoints at one key: stalled past its lease after recording one, the fit
    taken over and resumed from that one, its late upload (refused) had overwritten the bytes the new owner resumed
    from, and the next one resumed from its later state. Each checkpoint has a key of its own: the refused one goes
    and the recorded one keeps its bytes."""
    from voxe_service.storage import get_storage, reconstruction_storage_key
    from worker import runtime, tasks

    storage, scene = get_storage(db), add_scene()
    job_id, rec_id = add_job(scene, "queued", 0), add_reconstruction(scene)
    for name in ("recorded", "late"):
        (tmp_path / name).write_bytes(f"the {name} fit checkpoint".encode())
    stalled = _owned_fit(db, job_id, rec_id, "a@host")
    tasks._store_fit_checkpoint(stalled, rec_id, storage, tmp_path / "recorded", 10)
    _owned_fit(db, job_id, rec_id, "b@host", take_over=True)
    with pytest.raises(runtime.LeaseLost):
        tasks._store_fit_checkpoint(stalled, rec_id, storage, tmp_path / "late", 20)
    recorded = runtime.load_reconstruction(rec_id).checkpoint_key
    assert b"".join(storage.open_range(recorded)) == b"the recorded fit checkpoint"
    assert storage.list(reconstruction_storage_key(rec_id, "checkpoint")) == [recorded]


def test_a_fit_checkpoint_whose_record_meets_a_database_outage_is_deleted_and_the_fit_resumes_from_the_last(
        db, monkeypatch):
    """The database out of reach as the fit records its checkpoint's key (runtime.record_fit_checkpoint): the bytes
    just uploaded go (recorded nowhere, they had stayed for good under their run's own name), the checkpoint
    recorded before keeps its record and bytes, and the run stops as an outage stops a fit: the fit pending saying
    why, the job back in the queue, nothing failed. Its redelivery resumes the fit from the checkpoint recorded."""
    import sqlite3

    from sqlalchemy.exc import OperationalError

    from conftest import make_sphere_grid
    from voxe_core.progress import Progress
    from voxe_service.storage import get_storage, reconstruction_storage_key
    from worker import runtime, tasks

    storage, scene = get_storage(db), add_scene()
    rec_id = add_reconstruction(scene)
    job_id = add_job(scene, "queued", 0, reconstruction_id=rec_id)
    monkeypatch.setattr(tasks, "_check_job_can_start", lambda job, settings: None)
    monkeypatch.setattr(runtime, "OUTAGE_PAUSE_S", 0.0)
    resumed_from = []

    def fit_checkpointing_at_10_and_20(job, rec, settings, storage, lease, callbacks, checkpoint, device):
        if rec.checkpoint_key is not None:  # the redelivery
            resumed_from.append(b"".join(storage.open_range(rec.checkpoint_key)))
            return make_sphere_grid(8), 100
        for iteration in (10, 20):
            checkpoint.write_bytes(f"the fit at {iteration}".encode())
            callbacks.on_progress(Progress("reconstruct", iteration, 100))
            callbacks.callbacks.on_checkpoint(str(checkpoint))
        raise AssertionError("the fit went on past the checkpoint its record failed")

    record = runtime.record_fit_checkpoint

    def down_as_20_is_recorded(rec_id, job_id, run_token, key):
        if key.endswith("-20.safetensors"):
            raise OperationalError("UPDATE reconstructions", {}, sqlite3.OperationalError("database is locked"))
        return record(rec_id, job_id, run_token, key)

    monkeypatch.setattr(tasks, "_fit_grid", fit_checkpointing_at_10_and_20)
    with monkeypatch.context() as outage:
        outage.setattr(runtime, "record_fit_checkpoint", down_as_20_is_recorded)
        result = tasks.reconstruct_task.apply(args=(job_id,))
    assert result.state == "REJECTED" and result.result.requeue, result.result
    rec, said = runtime.load_reconstruction(rec_id), "a database outage (the database cannot be reached or is locked)"
    assert storage.list(reconstruction_storage_key(rec_id, "checkpoint")) == [rec.checkpoint_key]
    assert rec.checkpoint_key.endswith("-10.safetensors")
    assert (rec.state, rec.owner_job_id, rec.error) == ("pending", None, f"job {job_id}'s fit: stopped by {said}")
    job = job_row(job_id)
    assert (job.state, job.error) == ("running", None)
    assert job.message.startswith(f"re-queued: reconstruct stopped by {said}"), job.message
    assert tasks.reconstruct_task.apply(args=(job_id,)).get()["state"] == "done"  # the redelivery
    assert resumed_from == [b"the fit at 10"]
    assert storage.list(reconstruction_storage_key(rec_id, "checkpoint")) == []


def test_a_canceled_fit_whose_checkpoint_at_the_cancel_met_its_lost_fit_writes_no_warning_on_its_job(db,
                                                                                                       monkeypatch):
    """A fit canceled after another job took it over (its lease lapsed): the checkpoint a canceled stage takes
    (voxe_core's checkpoint_at_cancel) was refused, LeaseLost, and said on the job as a warning "the checkpoint at
    the cancel could not be written (LeaseLost: ...): the earlier checkpoint stands", where the new owner's
    checkpoint stands, not this run's earlier one. A run that lost its fit says no warning on the job; the job ends
    canceled, the fit and its checkpoint are the new owner's."""
    from sqlalchemy import select, update

    from voxe_core.progress import Progress
    from voxe_core.reconstruct import checkpoint_at_cancel
    from voxe_service.db import session_scope
    from voxe_service.models import Job, JobEvent, Reconstruction
    from voxe_service.storage import get_storage, reconstruction_storage_key
    from worker import runtime, tasks

    storage, scene = get_storage(db), add_scene()
    rec_id = add_reconstruction(scene)
    job_id = add_job(scene, "queued", 0, reconstruction_id=rec_id)
    new_owner = add_job(scene, "running", 0, "alive@host", "reconstruct", reconstruction_id=rec_id)
    theirs = storage.put_bytes(reconstruction_storage_key(rec_id, "checkpoint-theirs-30.safetensors"), b"30").key
    monkeypatch.setattr(tasks, "_check_job_can_start", lambda job, settings: None)

    def fit_taken_over_then_canceled(job, rec, settings, storage, lease, callbacks, checkpoint, device):
        callbacks.on_progress(Progress("reconstruct", 10, 100))
        with session_scope() as session:
            session.execute(update(Reconstruction).where(Reconstruction.id == rec_id).values(
                owner_job_id=new_owner, owner_run_token="theirs", checkpoint_key=theirs))
            session.execute(update(Job).where(Job.id == job_id).values(cancel_requested=True))
        checkpoint.write_bytes(b"the fit at 10")
        checkpoint_at_cancel(callbacks.callbacks, "reconstruct",
                             lambda: callbacks.callbacks.checkpoint_written(str(checkpoint)))
        callbacks.callbacks.check_cancel("reconstruct")
        raise AssertionError("the canceled fit went on")

    monkeypatch.setattr(tasks, "_fit_grid", fit_taken_over_then_canceled)
    tasks.reconstruct_task.apply(args=(job_id,))
    job = job_row(job_id)
    assert (job.state, job.message) == ("canceled", "canceled during reconstruct")
    with session_scope() as session:
        warnings = session.scalars(select(JobEvent.detail).where(JobEvent.job_id == job_id,
                                                                 JobEvent.kind == "warning")).all()
    assert warnings == []
    rec = runtime.load_reconstruction(rec_id)
    assert (rec.state, rec.owner_job_id, rec.checkpoint_key) == ("running", new_owner, theirs)
    assert storage.list(reconstruction_storage_key(rec_id, "checkpoint")) == [theirs]


def test_a_fit_checkpoint_replaced_by_the_next_owners_is_deleted(db, tmp_path):
    """The edit deleted the checkpoint a new one replaced, the fit did not: a fit taken over kept its killed owner's
    last checkpoint until the fit succeeded, and for good when it failed. It goes once the new owner records its
    own."""
    from voxe_service.storage import get_storage, reconstruction_storage_key
    from worker import runtime, tasks

    storage, scene = get_storage(db), add_scene()
    job_id, rec_id = add_job(scene, "queued", 0), add_reconstruction(scene)
    for name in ("killed", "new"):
        (tmp_path / name).write_bytes(f"the {name} owner's fit checkpoint".encode())
    killed = _owned_fit(db, job_id, rec_id, "a@host")
    tasks._store_fit_checkpoint(killed, rec_id, storage, tmp_path / "killed", 10)
    taken = _owned_fit(db, job_id, rec_id, "b@host", take_over=True)
    tasks._store_fit_checkpoint(taken, rec_id, storage, tmp_path / "new", 30)
    recorded = runtime.load_reconstruction(rec_id).checkpoint_key
    assert b"".join(storage.open_range(recorded)) == b"the new owner's fit checkpoint"
    assert storage.list(reconstruction_storage_key(rec_id, "checkpoint")) == [recorded]


def test_a_stalled_owners_checkpoint_stored_after_the_fit_succeeded_is_deleted(db, tmp_path):
    """A fit owner stalled past its lease, the fit taken over and finished (every checkpoint deleted), whose late
    upload then landed kept its bytes: its refusal deleted them only when they were not the recorded checkpoint,
    which they were (the key it had recorded before it stalled, shared by all its checkpoints). A succeeded fit
    records no checkpoint, and the late one, refused, goes."""
    from voxe_service.storage import get_storage, reconstruction_storage_key
    from worker import runtime, tasks

    storage, scene = get_storage(db), add_scene()
    job_id, rec_id = add_job(scene, "queued", 0), add_reconstruction(scene)
    for name in ("recorded", "late"):
        (tmp_path / name).write_bytes(f"the {name} fit checkpoint".encode())
    stalled = _owned_fit(db, job_id, rec_id, "a@host")
    tasks._store_fit_checkpoint(stalled, rec_id, storage, tmp_path / "recorded", 10)
    taken = _owned_fit(db, job_id, rec_id, "b@host", take_over=True)
    assert runtime.set_reconstruction(rec_id, job_id, taken.run_token, state="succeeded", lease_until=None)
    tasks._discard_unrecorded(storage, rec_id, "checkpoint", None)  # (as the fit's end does)
    with pytest.raises(runtime.LeaseLost):
        tasks._store_fit_checkpoint(stalled, rec_id, storage, tmp_path / "late", 20)
    assert storage.list(reconstruction_storage_key(rec_id, "checkpoint")) == []


def test_a_checkpoint_stored_as_its_job_was_deleted_is_deleted(db, tmp_path):
    """A run whose job was canceled and deleted (rows, then stored objects) as it uploaded a checkpoint found no job
    row to record it on and went on as if recorded: the bytes stayed, under a job no longer listed anywhere. The
    record is refused (RunSuperseded) and the bytes go."""
    from voxe_core.progress import Progress
    from voxe_service.db import session_scope
    from voxe_service.models import Scene
    from voxe_service.storage import get_storage, job_key
    from worker import runtime

    storage, scene = get_storage(db), add_scene()
    job_id = add_job(scene, "queued", 0, completed_stages=["reconstruct"])
    run = runtime.begin_stage(job_id, "edit", "a@host", "cpu", db)
    store = _run_checkpoint_store(storage, run)

    def deleted_as_it_uploads(path, iteration):  # as the API deletes a scene: its rows, then its stored objects
        _ended_by_another_worker(db, job_id, "edit")
        outside = runtime._HOLDING.set(None)
        try:
            with session_scope() as session:
                session.delete(session.get(Scene, scene))
            storage.discard_prefixes(job_key(job_id))
        finally:
            runtime._HOLDING.reset(outside)
        return store(path, iteration)

    callbacks = runtime.StageCallbacks(run, "edit", db, on_checkpoint=deleted_as_it_uploads)
    callbacks.on_progress(Progress("edit", 10, 100))
    (tmp_path / "checkpoint").write_bytes(b"the edit at 10")
    with holding(job_id, run.run_token), pytest.raises(runtime.RunSuperseded):
        callbacks.on_checkpoint(str(tmp_path / "checkpoint"))
    assert storage.list(job_key(job_id)) == []


def test_a_stages_warning_said_again_by_its_next_run_is_one_event_and_one_webhook(db):
    """Each run of an edit (a resume after a re-queue, a redelivery) said its constant-regulariser warning again:
    another ``warning`` event and job.warning webhook per run. The timeline keeps one per stage and text; the
    later run still carries the warning as its progress reports' message, and a new warning is recorded."""
    from sqlalchemy import func, select

    from voxe_core.progress import Progress
    from voxe_service.db import session_scope
    from voxe_service.models import WebhookDelivery
    from worker import runtime

    job_id = add_job(add_scene(), "queued", 0, completed_stages=["reconstruct"],
                     webhook_url="https://hooks.example/voxe", webhook_events=["warning"])
    said = "the reconstruction's density is constant: the 3D regulariser (reg3d) has nothing to correlate and is off"
    first = runtime.begin_stage(job_id, "edit", "a@host", "cpu", db)
    runtime.StageCallbacks(first, "edit", db).callbacks.warning("edit", said)
    runtime.release_stage(job_id, first.run_token)  # (the worker went down; its message redelivered)
    again = runtime.StageCallbacks(runtime.begin_stage(job_id, "edit", "b@host", "cpu", db), "edit", db)
    again.callbacks.warning("edit", said)
    again.on_progress(Progress("edit", 1, 10))
    assert job_row(job_id).message == said
    assert [e["detail"] for e in events_of(job_id) if e["kind"] == "warning"] == [said]
    again.callbacks.warning("edit", colours := "its colour channels are constant")
    assert [e["detail"] for e in events_of(job_id) if e["kind"] == "warning"] == [said, colours]
    with session_scope() as session:  # one job.warning each
        assert session.scalar(select(func.count()).select_from(WebhookDelivery).where(
            WebhookDelivery.job_id == job_id, WebhookDelivery.event_type == "job.warning")) == 2


def test_reaper_sends_again_the_ingests_of_scenes_whose_worker_died_and_fails_those_never_sent(db):
    """A processing scene whose ingesting worker died had been failed ("upload it again"), an accepted upload lost
    to a crash, where a job in that state is sent again. Its ingest is sent again (the scene waits for a worker, the
    jobs on it still queued), unless the SQL broker still holds its message or a live run holds it; one taken
    VOXE_JOB_MAX_REQUEUES + 1 times (each run interrupted) fails instead naming why, and so does one never sent, with
    the jobs waiting on them."""
    import sqlite3

    from api.reaper import reap_orphaned_scenes
    from voxe_service.broker import waiting_tasks
    from voxe_service.db import session_scope
    from voxe_service.models import Scene, utcnow
    from voxe_service.queue import get_queue

    timeout, limit = db.job_stale_timeout_s, db.job_max_requeues
    add_heartbeat("alive@host", age_s=1)
    add_heartbeat("dead@host", age_s=2 * timeout)
    long_ago, later = utcnow() - timedelta(seconds=2 * timeout), utcnow() + timedelta(seconds=60)
    resent = {
        "its worker died": add_scene("processing", 2 * timeout, worker="dead@host", ingest_attempts=1),
        "its worker never heartbeat": add_scene("processing", 2 * timeout, worker="gone@host", ingest_attempts=limit),
        "its run stopped renewing on a live worker": add_scene("processing", 2 * timeout, worker="alive@host",
                                                               ingest_attempts=1, ingest_token="t",
                                                               ingest_lease_until=long_ago),
    }
    failed = {
        "never sent": add_scene("processing", 2 * timeout, task_id=None),
        "interrupted once too often": add_scene("processing", 2 * timeout, worker="dead@host",
                                                ingest_attempts=limit + 1),
    }
    kept = {
        "waiting in the broker for a worker": add_scene("processing", 2 * timeout),
        "its worker alive (a long decode)": add_scene("processing", 2 * timeout, worker="alive@host", ingest_attempts=1,
                                                      ingest_token="t", ingest_lease_until=later),
        "held by a run that renews its lease": add_scene("processing", 2 * timeout, worker="dead@host",
                                                         ingest_attempts=1, ingest_token="t", ingest_lease_until=later),
        "its message waits in the SQL broker": add_scene("processing", 2 * timeout, worker="dead@host",
                                                         ingest_attempts=1),
        "just stored, not yet sent": add_scene("processing", timeout / 2, task_id=None),
        "ready": add_scene("ready", 2 * timeout, task_id=None),
    }
    get_queue().send_ingest(kept["its message waits in the SQL broker"])
    waiting = add_job(resent["its worker died"], "queued", 0, task_id=None)
    doomed = add_job(failed["interrupted once too often"], "queued", 0, task_id=None)

    def rows() -> dict:
        with session_scope() as session:
            return {what: (r.state, r.error, r.task_id, r.worker_hostname, r.ingest_token, r.updated_at) for what, r in
                    ((what, session.get(Scene, i)) for what, i in {**resent, **failed, **kept}.items())}

    before = rows()
    assert sorted(reap_orphaned_scenes(db)) == sorted(failed.values())
    row = rows()
    for what in resent:  # waiting for a worker, held by none, its message the new one
        assert row[what][:2] == ("processing", None) and row[what][3:5] == (None, None), (what, row[what])
        assert row[what][2] not in (None, "ingest"), (what, row[what])
    assert row["never sent"][:2] == ("failed", f"the upload was never handed to a worker (the API stopped while "
                                               f"storing it); failed after {timeout:.0f} s (VOXE_JOB_STALE_TIMEOUT_S): "
                                               "upload it again")
    reason = row["interrupted once too often"][1]
    assert reason == (f"ingest: interrupted {limit + 1} times, the last as worker dead@host stopped while processing "
                      f"the upload: no heartbeat for {timeout:.0f} s (VOXE_JOB_STALE_TIMEOUT_S); it was sent again "
                      f"{limit} time(s) already, the limit (VOXE_JOB_MAX_REQUEUES={limit})")
    assert all(row[what] == before[what] for what in kept), row
    assert (job_row(waiting).state, job_row(waiting).task_id) == ("queued", None)  # the ingest sends it once ready
    assert (job_row(doomed).state, job_row(doomed).error) == ("failed",
                                                              f"the scene's upload failed processing: {reason}")

    carried = {scene for task, scene in waiting_tasks(db.broker_url) if task == "voxe.ingest"}
    assert carried == {*resent.values(), kept["its message waits in the SQL broker"]}
    assert reap_orphaned_scenes(db) == []  # (each just sent: waiting for a worker)
    with sqlite3.connect(db.broker_url.split(":///", 1)[1]) as broker:  # one message a scene: none sent twice
        assert broker.execute("SELECT count(*) FROM kombu_message").fetchone()[0] == len(resent) + 1


def test_reaper_leaves_an_untaken_ingest_waiting_while_no_worker_heartbeats(db, monkeypatch):
    """With no worker heartbeating for VOXE_JOB_STALE_TIMEOUT_S (the fleet down, or scaled to zero), a scene whose
    ingest message no worker took yet (no worker recorded) had been taken for one whose worker died ("worker None
    stopped": a NULL hostname is NOT IN an empty list) and sent again on every pass. It waits for a worker; one whose
    worker died is sent again once, and then waits too."""
    from types import SimpleNamespace

    import api.reaper as reaper
    from voxe_service.db import session_scope
    from voxe_service.models import Scene, utcnow

    sent = []
    monkeypatch.setattr(reaper, "get_queue", lambda: SimpleNamespace(
        send_ingest=lambda scene_id: sent.append(scene_id) or f"task-{len(sent)}"))
    timeout = db.job_stale_timeout_s
    untaken = add_scene("processing", 2 * timeout, task_id="the upload's message")
    orphan = add_scene("processing", 2 * timeout, worker="dead@host", ingest_attempts=1)
    for later in range(3):  # passes while the fleet stays down
        assert reaper.reap_orphaned_scenes(db, now=utcnow() + timedelta(seconds=later * 2 * timeout)) == []
    assert sent == [orphan]
    with session_scope() as session:
        row = session.get(Scene, untaken)
        assert (row.state, row.task_id, row.worker_hostname) == ("processing", "the upload's message", None)


def test_reaper_sends_again_an_ingest_no_worker_took_for_the_lost_message_timeout(db, monkeypatch):
    """A job whose message no worker took for VOXE_JOB_LOST_MESSAGE_TIMEOUT_S is sent again (a broker that lost what it
    had accepted: a Redis restarted without its data); a scene's ingest was not: the scene stayed processing, and the
    jobs on it queued, for good. It is sent again, unless the SQL broker still holds its message, the wait before the
    next doubled (as a job's: below)."""
    from types import SimpleNamespace

    import api.reaper as reaper
    from voxe_service.db import session_scope
    from voxe_service.models import Scene, utcnow
    from voxe_service.queue import get_queue

    lost_after = db.job_lost_message_timeout_s
    lost = add_scene("processing", 2 * lost_after, task_id="the upload's message")
    carried = add_scene("processing", 2 * lost_after, task_id="the upload's message")
    waiting = add_scene("processing", lost_after / 2, task_id="the upload's message")
    get_queue().send_ingest(carried)
    sent = []
    monkeypatch.setattr(reaper, "get_queue", lambda: SimpleNamespace(
        send_ingest=lambda scene_id: sent.append(scene_id) or f"task-{len(sent)}"))
    job = add_job(lost, "queued", 0, task_id=None)
    assert reaper.reap_orphaned_scenes(db) == [] and sent == [lost]
    with session_scope() as session:
        row = session.get(Scene, lost)
        assert (row.state, row.task_id, row.worker_hostname) == ("processing", "task-1", None)
    assert reaper.reap_orphaned_scenes(db) == [] and sent == [lost]  # (just sent: waiting for a worker)
    assert reaper.reap_orphaned_scenes(db, now=utcnow() + timedelta(seconds=1.1 * lost_after)) == []
    assert sent == [lost, waiting]  # (the lost one's wait doubled)
    assert (job_row(job).state, job_row(job).task_id) == ("queued", None)  # the ingest sends it once ready


def test_an_ingest_no_worker_takes_is_sent_again_ever_more_rarely_as_a_jobs_message_is(db, monkeypatch):
    """A scene whose ingest no worker takes (a backlog past VOXE_JOB_LOST_MESSAGE_TIMEOUT_S, or every worker down) had
    been sent again each window, a copy more of its message each time (8 in 8 windows), where a job so placed waits
    twice as long after each such re-send (3). Its re-sends are counted and double its wait as a job's do; one the
    broker refuses leaves the scene as it was read, not counted, and the next pass sends it."""
    from types import SimpleNamespace

    import api.reaper as reaper
    from voxe_service.db import session_scope
    from voxe_service.models import Scene, utcnow
    from voxe_service.queue import QueueUnavailable

    window = db.job_lost_message_timeout_s
    scene = add_scene("processing", 1.01 * window, task_id="the upload's message")
    job = add_job(add_scene(), "queued", 1.01 * window, task_id="the job's message")
    sent, refused = {"scene": [], "job": []}, []

    def send_ingest(scene_id):
        if not refused:  # (the first: the broker down)
            refused.append(scene_id)
            raise QueueUnavailable("the broker refused the message")
        sent["scene"].append(k)
        return f"ingest {k}"

    def send(chain):
        sent["job"].append(k)
        return f"chain {k}"

    monkeypatch.setattr(reaper, "get_queue", lambda: SimpleNamespace(
        send_ingest=send_ingest, send=send, stage_chain=lambda job_id, *_a, **_k: SimpleNamespace(tasks=[job_id])))

    def row():
        with session_scope() as session:
            found = session.get(Scene, scene)
            return found.task_id, found.lost_ingest_resends, found.updated_at

    k, read = 0, row()
    assert reaper.reap_orphaned_scenes(db) == [] and sent["scene"] == []  # refused: as it was read, not counted
    assert row() == read
    start = utcnow()
    for k in range(8):  # a pass every 1.01 windows: 8 windows with no worker taking anything
        now = start + timedelta(seconds=k * 1.01 * window)
        assert reaper.reap_orphaned_scenes(db, now=now) == [] and reaper.reap_orphaned_jobs(db, now=now) == []
    assert sent["scene"] == sent["job"] == [0, 2, 4]  # after 1, 2 and 4 windows: each wait doubled
    assert row()[:2] == ("ingest 4", 3)
    assert job_row(job).state == "queued"


@pytest.mark.parametrize("released_by", ["a restart's recovery", "a run giving it back"])
def test_an_ingest_hold_released_while_the_broker_refuses_is_sent_again_by_the_reaper(db, monkeypatch, released_by):
    """A hold is released so that a new message takes the scene at once: by a restarted worker's recovery before it
    re-sends the ingest, by a run an outage stopped before its message goes back. Released to no lease at all, a
    scene whose message never came (the broker refusing the re-send) stayed processing for good: the reaper sends
    again only a scene whose lease ran out long ago. The lease is left run out: a message takes the scene at once, as
    before, and without one the reaper sends the ingest again after VOXE_JOB_STALE_TIMEOUT_S."""
    from types import SimpleNamespace

    import api.reaper as reaper
    from voxe_service.models import utcnow
    from voxe_service.queue import QueueUnavailable, get_queue
    from worker import ingest, tasks

    timeout, held = db.job_stale_timeout_s, utcnow() + timedelta(seconds=60)
    scenes = [add_scene("processing", 2 * timeout, worker="w@host", ingest_attempts=1, ingest_token=f"run {i}",
                        ingest_lease_until=held) for i in range(2)]

    def refused(scene_id):
        raise QueueUnavailable("the broker refused the message (database is locked)")

    if released_by == "a restart's recovery":
        monkeypatch.setattr(get_queue(), "send_ingest", refused)
        with pytest.raises(QueueUnavailable):
            tasks.recover_interrupted_jobs("w@host")
    else:  # (its message lost on its way back to the queue)
        for i, scene in enumerate(scenes):
            ingest._give_back(scene, f"run {i}")
    later = timeout + 1
    add_heartbeat("w@host", age_s=-later)  # the worker alive, heartbeating until the reaper's later pass

    took = time.monotonic()
    assert not isinstance(ingest._take(scenes[0], "a new message's run", "w@host", db), str)
    assert time.monotonic() - took < db.stage_lease_s / 8  # at once (not after waiting out a lease)

    sent = []
    monkeypatch.setattr(reaper, "get_queue", lambda: SimpleNamespace(
        send_ingest=lambda scene_id: sent.append(scene_id) or "sent again"))
    assert reaper.reap_orphaned_scenes(db) == [] and sent == []  # (its message may yet come)
    assert reaper.reap_orphaned_scenes(db, now=utcnow() + timedelta(seconds=later)) == []
    assert sent == [scenes[1]]  # (the one taken above is held by that run)


def test_an_ingest_held_by_a_live_run_is_dropped_and_one_whose_hold_ran_out_is_taken_over(db, tmp_path):
    """Two workers could ingest one scene at once (a broker's redelivery, or a re-send, beside a live run). The run
    holds the scene under a lease, as a stage's run holds its job: a second message waits, and is dropped once the
    holder renews; a run that lost its hold writes nothing (its final update refused, the stored bytes kept); once the
    lease runs out unrenewed (its process killed) a message takes the scene over."""
    import threading
    import zipfile

    from sqlalchemy import update

    from voxe_service import datasets
    from voxe_service.db import session_scope
    from voxe_service.models import Scene, utcnow
    from voxe_service.storage import get_storage, scene_key
    from worker import ingest

    settings, storage = db.model_copy(update={"stage_lease_s": 0.4}), get_storage(db)
    with zipfile.ZipFile(tmp_path / "upload.zip", "w") as zf:
        zf.writestr("transforms_train.json", "{}")
    scene = add_scene("processing", worker="w1@host", ingest_attempts=1, ingest_token="w1's run",
                      ingest_lease_until=utcnow() + timedelta(seconds=0.4))
    stored = storage.put_file(scene_key(scene, datasets.DATASET_ARCHIVE), tmp_path / "upload.zip")
    with session_scope() as session:
        row = session.get(Scene, scene)
        row.storage_key, row.size_bytes, row.sha256 = stored.key, stored.size, stored.sha256

    def live_run():  # the holder's lease keeper, renewing each 0.1 s for a second
        for _ in range(10):
            time.sleep(0.1)
            with session_scope() as session:
                session.execute(update(Scene).where(Scene.id == scene, Scene.ingest_token == "w1's run")
                                .values(ingest_lease_until=utcnow() + timedelta(seconds=0.4)))

    renewing = threading.Thread(target=live_run)
    renewing.start()
    try:
        assert ingest.ingest_scene(scene, settings, storage, "w2@host") == {
            "scene_id": scene, "skipped": f"scene {scene}: another run holds its ingest (this message is a duplicate)"}
    finally:
        renewing.join()

    def held() -> tuple:
        with session_scope() as session:
            row = session.get(Scene, scene)
            return row.state, row.worker_hostname, row.ingest_token, row.ingest_attempts

    assert held() == ("processing", "w1@host", "w1's run", 1)
    # A run whose hold was taken over ends without a word: neither failed nor ready, the upload kept.
    assert not ingest._fail(scene, "a superseded run", "invalid dataset", storage)
    assert ingest._ready(scene, "a superseded run", {"backbone": "relu_field"}, storage, settings, None) == {
        "scene_id": scene, "skipped": f"scene {scene}: another run took its ingest over"}
    assert held() == ("processing", "w1@host", "w1's run", 1) and storage.exists(stored.key)

    expire_ingest_hold(scene)  # w1 killed: its lease runs out
    assert ingest.ingest_scene(scene, settings, storage, "w2@host") == {"scene_id": scene, "state": "failed"}
    state, worker, _token, attempts = held()
    assert (state, worker, attempts) == ("failed", "w2@host", 2)


@pytest.mark.parametrize("stalled_in", ["render", "package"])
def test_a_superseded_mesh_ingest_leaves_the_winners_archive_as_recorded(db, tmp_path, monkeypatch, stalled_in):
    """A mesh ingest whose hold lapsed (its renewals could not reach the database) went on and stored its rendered
    dataset over the archive of the run that had taken the scene over and made it ready (the zips differ: every job's
    fetch then failed its SHA-256 check). Stalled before it stores, it stops at its lease's check; stalled past that
    check, it stores under a key of its own, which it deletes once its result is refused: the scene keeps the
    winner's archive, as recorded, and nothing else."""
    import threading
    import zipfile

    from celery.exceptions import Reject
    from sqlalchemy.exc import OperationalError

    from voxe_service import datasets
    from voxe_service.db import session_scope
    from voxe_service.models import Scene
    from voxe_service.storage import get_storage, scene_key
    from worker import ingest, runtime

    settings, storage = db.model_copy(update={"stage_lease_s": 0.5}), get_storage(db)
    monkeypatch.setattr("worker.runtime.OUTAGE_PAUSE_S", 0.0)
    stalled, go_on = threading.Event(), threading.Event()

    def stall(where: str) -> None:  # run A stops at ``stalled_in`` until run B made the scene ready
        if threading.current_thread().name == "A" and where == stalled_in:
            stalled.set()
            go_on.wait(10)

    def render_mesh(root, told):  # each run's views its own (a real render's zip differs by its file times)
        stall("render")
        (root / "transforms_train.json").write_text("{}")
        (root / "r_0.png").write_text(threading.current_thread().name)

    package, lease = datasets.package, ingest.ingest_lease

    def stalled_package(root, archive):
        stall("package")
        return package(root, archive)

    def unreachable(**_values):
        raise OperationalError("UPDATE scenes", {}, Exception("server closed the connection unexpectedly"),
                               connection_invalidated=True)

    def a_cut_off(scene_id, token, settings_):  # run A's renewals cannot reach the database
        keeper = lease(scene_id, token, settings_)
        if threading.current_thread().name == "A":
            keeper._renew = unreachable
        return keeper

    scene = _mesh_scene_rendering(storage, monkeypatch, render_mesh)
    monkeypatch.setattr(datasets, "package", stalled_package)
    monkeypatch.setattr(ingest, "ingest_lease", a_cut_off)

    outcome = {}

    def run_a():
        try:
            outcome["A"] = ingest.ingest_scene(scene, settings, storage, "w1@host")
        except Reject as exc:
            outcome["A"] = exc

    a = threading.Thread(target=run_a, name="A")
    a.start()
    try:
        assert stalled.wait(10)
        time.sleep(0.6)  # A's lease runs out unrenewed: B (the reaper's re-send) takes the scene over
        assert ingest.ingest_scene(scene, settings, storage, "w2@host") == {"scene_id": scene, "state": "ready"}
    finally:
        go_on.set()
        a.join()
    with session_scope() as session:
        row = session.get(Scene, scene)
        assert (row.state, row.worker_hostname) == ("ready", "w2@host")
        recorded = runtime.scene_archive(row)
    runtime.fetch(storage, recorded, tmp_path / "job.zip")  # the bytes recorded (raises otherwise)
    with zipfile.ZipFile(tmp_path / "job.zip") as zf:
        assert zf.read("r_0.png") == b"MainThread"  # (B's)
    assert storage.list(scene_key(scene)) == [recorded.key]  # (the upload, packed into it, and A's archive gone)
    if stalled_in == "render":  # stopped before storing: its message goes back (a redelivery finds the scene ready)
        assert isinstance(outcome["A"], Reject)
    else:
        assert outcome["A"] == {"scene_id": scene, "skipped": f"scene {scene}: another run took its ingest over"}


def _mesh_scene_rendering(storage, monkeypatch, render=None) -> str:
    """A processing mesh scene whose ingest renders ``render`` (a view and transforms file by default) and decodes
    as one image: the ingest's storage and database paths run, not its rasteriser."""
    import io
    import zipfile

    from voxe_service import datasets
    from voxe_service.db import session_scope
    from voxe_service.models import Scene
    from voxe_service.storage import scene_key
    from worker import ingest

    scene = add_scene("processing")
    mesh = io.BytesIO()
    with zipfile.ZipFile(mesh, "w") as zf:
        zf.writestr("mesh/mesh.obj", "v 0 0 0\n")
    upload = storage.put_bytes(scene_key(scene, datasets.UPLOAD_ARCHIVE), mesh.getvalue())
    with session_scope() as session:
        row = session.get(Scene, scene)
        row.format, row.storage_key, row.size_bytes, row.sha256 = "mesh", upload.key, upload.size, upload.sha256

    def views(root, told):  # (loaded without nothing)
        (root / "transforms_train.json").write_text("{}")
        (root / "r_0.png").write_text("x" * 1000)
    monkeypatch.setattr(ingest, "render_mesh", render or views)
    monkeypatch.setattr(ingest, "decode", lambda root, downsample: ingest.Decoded(1, "relu_field"))
    return scene


@pytest.mark.parametrize("stopped_by", ["a killed worker", "a database outage"])
def test_a_mesh_ingest_stopped_between_storing_and_marking_leaves_no_archive_once_ready(db, monkeypatch, stopped_by):
    """A run stopped after storing its rendered dataset under its own key and before marking the scene ready (its
    worker killed; the database down at its mark, its message sent back) left that archive behind, never recorded
    nor counted by the upload quota, one more at each such stop, until the scene was deleted: the run that makes the
    scene ready discards them."""
    from celery.exceptions import Reject
    from sqlalchemy.exc import OperationalError

    from voxe_service.db import session_scope
    from voxe_service.models import Scene
    from voxe_service.storage import get_storage, scene_key
    from worker import ingest

    settings, storage = db.model_copy(update={"stage_lease_s": 0.5}), get_storage(db)
    monkeypatch.setattr("worker.runtime.OUTAGE_PAUSE_S", 0.0)
    scene = _mesh_scene_rendering(storage, monkeypatch)
    mark_ready, marks = ingest.mark_ready, []

    def stopped(*args, **kwargs):
        marks.append(1)
        if len(marks) > 1:
            return mark_ready(*args, **kwargs)
        if stopped_by == "a killed worker":
            raise SystemExit("killed")  # (a SIGKILL: nothing after it runs)
        raise OperationalError("UPDATE scenes", {}, Exception("database is locked"))

    monkeypatch.setattr(ingest, "mark_ready", stopped)
    with pytest.raises(SystemExit if stopped_by == "a killed worker" else Reject):
        ingest.ingest_scene(scene, settings, storage, "w1@host")
    if stopped_by == "a killed worker":
        expire_ingest_hold(scene)  # its lease runs out; the redelivery takes the scene over
    assert len(storage.list(scene_key(scene, "dataset-"))) == 1
    assert ingest.ingest_scene(scene, settings, storage, "w1@host")["state"] == "ready"
    with session_scope() as session:
        recorded = session.get(Scene, scene).storage_key
    assert storage.list(scene_key(scene)) == [recorded]


def test_a_mesh_scene_deleted_while_it_renders_is_said_to_be_deleted(db, monkeypatch):
    """A processing mesh scene deleted while its ingest rendered: the renewal finding no row stops the run, which
    had said that another run took the ingest over."""
    from voxe_service.db import session_scope
    from voxe_service.models import Scene
    from voxe_service.storage import get_storage, scene_key
    from worker import ingest

    settings, storage = db.model_copy(update={"stage_lease_s": 0.5}), get_storage(db)
    scene = None

    def deleted_meanwhile(root, told):
        with session_scope() as session:
            session.delete(session.get(Scene, scene))
        storage.delete_prefix(scene_key(scene))  # (as the API's delete does)
        time.sleep(0.4)  # a renewal finds the row gone
        (root / "r_0.png").write_text("x")

    scene = _mesh_scene_rendering(storage, monkeypatch, deleted_meanwhile)
    assert ingest.ingest_scene(scene, settings, storage, "w1@host") == {
        "scene_id": scene, "skipped": f"scene {scene} was deleted or failed meanwhile"}
    assert storage.list(scene_key(scene)) == []


def test_api_startup_reaps_and_deletes_the_orphans_checkpoints(db):
    """The reaper runs in the API process: a restarted API sends again what a dead worker left running, keeping
    its checkpoints to resume from, and fails a job sent again too often, deleting its checkpoints."""
    import time

    from fastapi.testclient import TestClient

    from api.main import create_app
    from voxe_service.models import utcnow
    from voxe_service.storage import get_storage

    scene = add_scene()
    stale = 2 * db.job_stale_timeout_s
    resumed = add_job(scene, "running", stale, "dead@host", "edit")
    orphan = add_job(scene, "running", stale, "dead@host", "edit", requeues=db.job_max_requeues, run_token="t",
                     run_lease_until=utcnow() - timedelta(seconds=stale))
    storage = get_storage(db)
    for job_id in (resumed, orphan):
        storage.put_bytes(f"jobs/{job_id}/checkpoints/edit.safetensors", b"state")
    with TestClient(create_app()) as client:
        deadline = time.monotonic() + 60  # a poll, not a bound: the reaper thread may wait for a busy CPU
        while client.get(f"/v1/jobs/{orphan}").json()["state"] != "failed" and time.monotonic() < deadline:
            time.sleep(0.05)
        job = client.get(f"/v1/jobs/{orphan}").json()
        assert job["state"] == "failed" and "worker dead@host stopped" in job["error"], job
        deadline = time.monotonic() + 60
        while storage.list(f"jobs/{orphan}/") and time.monotonic() < deadline:
            time.sleep(0.05)
        assert storage.list(f"jobs/{orphan}/") == []
        job = client.get(f"/v1/jobs/{resumed}").json()
        assert job["state"] == "queued" and job["message"].startswith("re-queued: worker dead@host stopped"), job
        assert storage.list(f"jobs/{resumed}/") == [f"jobs/{resumed}/checkpoints/edit.safetensors"]


# ---------------------------------------------------------------------------------------------- atomic artifacts
class Crash(Exception):
    """Stands in for a worker dying half way through an upload."""


def listed(job_id: str) -> list[tuple[str, int, str]]:
    from sqlalchemy import select

    from voxe_service.db import session_scope
    from voxe_service.models import Artifact

    with session_scope() as session:
        return [(a.name, a.size, a.sha256) for a in session.scalars(select(Artifact).where(Artifact.job_id == job_id))]


def stored_bytes(storage, job_id: str, name: str) -> bytes:
    from worker.runtime import recorded_artifact

    return b"".join(storage.open_range(recorded_artifact(job_id, name).key))


def test_a_run_taking_over_a_stage_keeps_where_it_got_to_until_it_reports(db):
    """The job's progress had dropped to 0 of 0 while the new run loaded its model, then jumped back on its first
    report from the checkpoint; a run of the next stage starts from 0 as ever."""
    from voxe_service.models import utcnow
    from worker import runtime

    lapsed = utcnow() - timedelta(seconds=1)
    job_id = add_job(add_scene(), "running", 60, "dead@host", "edit", run_token="dead", run_lease_until=lapsed,
                     iteration=4, total=6, completed_stages=["reconstruct"])
    taken = runtime.begin_stage(job_id, "edit", "b@host", "cpu", db)
    assert (taken.iteration, taken.total, taken.worker_hostname) == (4, 6, "b@host") and taken.run_token != "dead"
    runtime.complete_stage(job_id, "edit", taken.run_token)
    assert (runtime.begin_stage(job_id, "export", "b@host", "cpu", db).iteration, job_row(job_id).total) == (0, 0)


def test_a_stage_whose_start_meets_a_database_error_tries_again_then_goes_back_to_the_queue(db, monkeypatch):
    """begin_stage raising (a locked or dropped database) had failed the task, and the broker acknowledged it: the
    accepted job stayed queued (or running between stages) for good, which no reaper pass changed."""
    from sqlalchemy.exc import OperationalError

    from worker import runtime, tasks

    monkeypatch.setattr(tasks, "DATABASE_RETRY_S", (0.0, 0.0))
    job_id = add_job(add_scene(), "queued", 0)
    real, failures = runtime.begin_stage, []

    def flaky(*args, **kwargs):
        if len(failures) < 2:
            failures.append(1)
            raise OperationalError("UPDATE jobs", {}, Exception("database is locked"))
        return real(*args, **kwargs)

    monkeypatch.setattr(runtime, "begin_stage", flaky)
    task = type("Task", (), {"request": type("Request", (), {"hostname": "w@host"})()})()
    assert tasks._begin_stage(task, job_id, "reconstruct", "cpu", db).state == "running"  # the third try takes it

    monkeypatch.setattr(runtime, "begin_stage", lambda *a, **k: (_ for _ in ()).throw(
        OperationalError("UPDATE jobs", {}, Exception("database is locked"))))
    other = add_job(add_scene(), "queued", 0)
    result = tasks.reconstruct_task.apply(args=(other,))
    assert result.state == "REJECTED" and result.result.requeue  # back to the broker, not acknowledged as failed
    assert "reconstruct of job" in str(result.result) and "database is locked" in str(result.result)
    assert job_row(other).state == "queued"  # untouched: the redelivered message takes it


def test_a_stages_start_committed_with_its_answer_lost_is_the_runs_at_once(db, monkeypatch):
    """A dropped connection can lose the answer to the COMMIT that took the job: each try had drawn a new run token,
    so the retry found the job held by one it never learnt, waited out the whole lease and took the job over from
    itself, counting a re-queue. The token is drawn once for all tries: the retry finds the job its own."""
    from sqlalchemy.exc import OperationalError

    from voxe_service.models import utcnow
    from worker import runtime, tasks

    settings = db.model_copy(update={"stage_lease_s": 4.0})
    monkeypatch.setattr(tasks, "DATABASE_RETRY_S", (0.0, 0.0))
    lapsed = add_job(add_scene(), "running", 60, "dead@host", "edit", run_token="dead", requeues=1,
                     run_lease_until=utcnow() - timedelta(seconds=1), completed_stages=["reconstruct"])
    real, tokens = runtime.begin_stage, []

    def committed_then_dropped(*args):
        tokens.append(args[-1])
        job = real(*args)
        if len(tokens) == 1:
            raise OperationalError("COMMIT", {}, Exception("server closed the connection unexpectedly"))
        return job

    monkeypatch.setattr(runtime, "begin_stage", committed_then_dropped)
    task = type("Task", (), {"request": type("Request", (), {"hostname": "w@host"})()})()
    for job_id, stage, requeues in ((add_job(add_scene(), "queued", 0), "reconstruct", 0),  # a fresh start
                                    (lapsed, "edit", 2)):  # a takeover of a dead run's hold: counted once
        tokens.clear()
        started = time.monotonic()
        job = tasks._begin_stage(task, job_id, stage, "cpu", settings)
        assert time.monotonic() - started < settings.stage_lease_s / 2  # no lease waited out
        assert len(tokens) == 2 and tokens[0] == tokens[1] == job.run_token
        assert (job.state, job.stage, job.worker_hostname, job.requeues) == ("running", stage, "w@host", requeues)
        assert [e["kind"] for e in events_of(job_id)] == ["stage_started"]


def test_a_failure_of_a_job_that_ended_meanwhile_is_not_logged_as_its_end(db, caplog):
    """The run's failure finds the job ended (canceled by the reaper, say): its update takes no effect, and the log
    had said "job X failed" of a job that was canceled."""
    import logging

    from voxe_service.db import session_scope
    from voxe_service.models import Job, utcnow
    from worker import tasks

    job_id = add_job(add_scene(), "running", 0, stage="edit", run_token="T",
                     run_lease_until=utcnow() + timedelta(seconds=60))
    with session_scope() as session:
        job = session.get(Job, job_id)
        job.state, job.message = "canceled", "canceled: asked during edit"
    caplog.set_level(logging.INFO, "voxe.worker")
    tasks._end_job(job_id, "edit", "T", "failed", db, error="edit: RuntimeError: boom")
    assert (job_row(job_id).state, job_row(job_id).error) == ("canceled", None)
    assert not [r for r in caplog.records if "failed" in r.getMessage() and r.levelno >= logging.ERROR]


def test_a_start_whose_answer_was_lost_and_every_retry_refused_leaves_the_job_free(db, monkeypatch):
    """The first try takes the job, its answer lost, and every retry is refused: the message goes back to the queue
    (Reject). The hold the lost try left had held the redelivery off for the whole lease, then been counted as a
    dead run's takeover; it is released (this run's token only), so the redelivery takes the job at once."""
    from celery.exceptions import Reject
    from sqlalchemy.exc import OperationalError

    from worker import runtime, tasks

    settings = db.model_copy(update={"stage_lease_s": 4.0})
    monkeypatch.setattr(tasks, "DATABASE_RETRY_S", (0.0, 0.0))
    job_id = add_job(add_scene(), "queued", 0)
    real, tries = runtime.begin_stage, []
    dropped = OperationalError("COMMIT", {}, Exception("server closed the connection unexpectedly"))

    def committed_then_refused(*args):
        tries.append(args)
        if len(tries) == 1:
            real(*args)
        raise dropped

    monkeypatch.setattr(runtime, "begin_stage", committed_then_refused)
    task = type("Task", (), {"request": type("Request", (), {"hostname": "w@host"})()})()
    with pytest.raises(Reject):
        tasks._begin_stage(task, job_id, "reconstruct", "cpu", settings)
    assert len(tries) == 3
    job = job_row(job_id)
    assert (job.run_token, job.run_lease_until, job.requeues) == (None, None, 0)
    monkeypatch.setattr(runtime, "begin_stage", real)
    started = time.monotonic()
    job = tasks._begin_stage(task, job_id, "reconstruct", "cpu", settings)  # the redelivery, the database back
    assert time.monotonic() - started < settings.stage_lease_s / 2  # no lease waited out
    assert (job.state, job.requeues) == ("running", 0)


def test_a_stage_the_database_refuses_to_start_each_time_fails_its_job_at_the_requeue_limit(db, monkeypatch):
    """A start refused each time for this job (a value too long for its column) while the database answers had
    gone back to the queue for ever: each return counts as a re-queue, and the delivery after
    VOXE_JOB_MAX_REQUEUES fails the job naming why. A database that is down or locked counts nothing; SQLite's
    OperationalError for a fault of the schema (a worker newer than its migrations) counts, as PostgreSQL's
    ProgrammingError would."""
    import sqlite3

    from sqlalchemy.exc import DataError, OperationalError

    from worker import runtime, tasks

    monkeypatch.setattr(tasks, "DATABASE_RETRY_S", ())
    refused = DataError("UPDATE jobs", {}, Exception("value too long for type character varying(255)"))
    monkeypatch.setattr(runtime, "begin_stage", lambda *a, **k: (_ for _ in ()).throw(refused))
    limit = db.job_max_requeues
    job_id = add_job(add_scene(), "queued", 0)
    with monkeypatch.context() as outage:  # the count's own write refused too: back to the queue, not counted
        outage.setattr(runtime, "session_scope", lambda: (_ for _ in ()).throw(
            OperationalError("SELECT jobs", {}, Exception("connection refused"))))
        result = tasks.reconstruct_task.apply(args=(job_id,))
    assert result.state == "REJECTED" and result.result.requeue and job_row(job_id).requeues == 0
    with monkeypatch.context() as locked:  # the start refused as the database was locked: an outage, not counted
        locked.setattr(runtime, "begin_stage", lambda *a, **k: (_ for _ in ()).throw(
            OperationalError("UPDATE jobs", {}, sqlite3.OperationalError("database is locked"))))
        result = tasks.reconstruct_task.apply(args=(job_id,))
    assert result.state == "REJECTED" and result.result.requeue and job_row(job_id).requeues == 0
    with monkeypatch.context() as schema:  # SQLite's OperationalError for a fault, not an outage: counted
        schema.setattr(runtime, "begin_stage", lambda *a, **k: (_ for _ in ()).throw(
            OperationalError("UPDATE jobs", {}, sqlite3.OperationalError("no such column: jobs.new_column"))))
        result = tasks.reconstruct_task.apply(args=(job_id,))
    assert result.state == "REJECTED" and job_row(job_id).requeues == 1
    for requeues in range(2, limit + 1):
        result = tasks.reconstruct_task.apply(args=(job_id,))
        assert result.state == "REJECTED" and result.result.requeue
        assert (job_row(job_id).state, job_row(job_id).requeues) == ("queued", requeues)
    result = tasks.reconstruct_task.apply(args=(job_id,)).get()
    assert result["skipped"].startswith(f"job {job_id} failed")
    reason = "reconstruct could not start: DataError: value too long for type character varying(255)"
    job = job_row(job_id)
    assert (job.state, job.requeues) == ("failed", limit) and job.finished_at is not None
    assert job.error == (f"{reason}; it was sent again {limit} time(s) already, the limit "
                         f"(VOXE_JOB_MAX_REQUEUES={limit})")
    schema_fault = "reconstruct could not start: OperationalError: no such column: jobs.new_column"
    assert [(e["kind"], e["detail"]) for e in events_of(job_id)] == [("requeued", schema_fault)] + [
        ("requeued", reason)] * (limit - 1) + [("failed", job.error)]


def test_a_stage_start_refused_names_the_drivers_first_line_not_the_statement(db, monkeypatch):
    """PostgreSQL's words for a statement it refuses quote the statement on their next lines ("LINE 1: UPDATE jobs
    SET ..."): a start refused so (a worker newer than its migrations) had put them on the job's timeline, and in its
    error at the limit. The reason says the driver's first line, as a stage's failure does."""
    from sqlalchemy.exc import ProgrammingError

    from worker import runtime, tasks

    monkeypatch.setattr(tasks, "DATABASE_RETRY_S", ())
    refused = ProgrammingError("UPDATE jobs", {}, Exception(
        'column "new_column" of relation "jobs" does not exist\nLINE 1: UPDATE jobs SET new_column=$1 WHERE '
        'jobs.id = $2\n                         ^'))
    monkeypatch.setattr(runtime, "begin_stage", lambda *a, **k: (_ for _ in ()).throw(refused))
    job_id = add_job(add_scene(), "queued", 0)
    result = tasks.reconstruct_task.apply(args=(job_id,))
    assert result.state == "REJECTED" and job_row(job_id).requeues == 1
    assert [(e["kind"], e["detail"]) for e in events_of(job_id)] == [
        ("requeued", 'reconstruct could not start: ProgrammingError: column "new_column" of relation "jobs" does not '
                     "exist")]


def _ending_edit(ending: str, settings):
    """An edit stage that ends its job by ``ending`` (one of ``ENDINGS``), and the state and the words the job is to
    end with."""
    from celery.exceptions import SoftTimeLimitExceeded

    from voxe_core.progress import StageCancelled
    from worker import runtime

    def edit(job, *_args):
        if ending == "cancel":
            runtime.update_job(job.id, cancel_requested=True)  # (the API's cancel of a running job)
            raise StageCancelled("edit")
        if ending == "time limit":
            raise SoftTimeLimitExceeded()
        raise RuntimeError("the edit diverged")

    return edit, *{"cancel": ("canceled", "canceled during edit"),
                   "time limit": ("failed", f"edit: time limit of {settings.task_soft_time_limit_s} s exceeded"),
                   "failure": ("failed", "edit: RuntimeError: the edit diverged")}[ending]


def _ending_the_job(monkeypatch, answer_lost: bool, refused: int | None = None) -> list:
    """``worker.runtime.finish_job`` refused as a locked database would, its first ``refused`` times (None: every
    time), the first one committed before its answer was lost when ``answer_lost``; the calls made."""
    import sqlite3

    from sqlalchemy.exc import OperationalError

    from worker import runtime

    real, calls = runtime.finish_job, []

    def finish_job(*args, **kwargs):
        calls.append(args)
        if refused is not None and len(calls) > refused:
            return real(*args, **kwargs)
        if answer_lost and len(calls) == 1:
            real(*args, **kwargs)
        raise OperationalError("UPDATE jobs", {}, sqlite3.OperationalError("database is locked"))

    monkeypatch.setattr(runtime, "finish_job", finish_job)
    return calls


ENDINGS = ["failure", "time limit", "cancel"]


@pytest.mark.parametrize("answer_lost", [False, True], ids=["refused", "answer lost"])
@pytest.mark.parametrize("ending", ENDINGS)
def test_a_database_outage_as_a_stage_ends_its_job_is_tried_again(db, monkeypatch, ending, answer_lost):
    """The record of a stage's failure, time limit or cancel had one try: the database locked or out of reach then,
    the task raised, leaving the job running, held by a run gone, for the reaper. It is tried again as the
    stage's end is; a first try that landed with its answer lost ends the job as well."""
    from worker import tasks

    monkeypatch.setattr(tasks, "DATABASE_RETRY_S", (0.0, 0.0, 0.0))
    body, state, words = _ending_edit(ending, db)
    monkeypatch.setattr(tasks, "_edit", body)
    calls = _ending_the_job(monkeypatch, answer_lost, refused=1 if answer_lost else 3)
    job_id = add_job(add_scene(), "running", 0, stage="reconstruct", completed_stages=["reconstruct"])
    assert tasks.edit_task.apply(args=(job_id,)).get() == {"job_id": job_id, "stage": "edit", "state": state}
    assert len(calls) == (2 if answer_lost else 4)
    job = job_row(job_id)
    assert (job.state, job.error if state == "failed" else job.message, job.requeues) == (state, words, 0)
    assert [(e["kind"], e["detail"]) for e in events_of(job_id)] == [("stage_started", None), (state, words)]


@pytest.mark.parametrize("answer_lost", [False, True], ids=["refused", "answer lost"])
@pytest.mark.parametrize("ending", ENDINGS)
def test_a_stages_end_the_database_refuses_at_every_try_goes_back_to_the_queue_to_end_the_job(db, monkeypatch,
                                                                                             ending, answer_lost):
    """Still refused, the message goes back to the queue (not acknowledged as failed with an outage's error) and the
    job is left as it was, its hold handed back: the redelivery finds a cancel before it starts; a failure it runs
    the stage again to meet (or not), the hand-back counted as a re-queue naming the error, so a failure whose
    record is refused every time ends at the re-queue limit. A first try that landed with its answer lost leaves
    the job ended, nothing counted, and the redelivery skips it."""
    from worker import tasks

    monkeypatch.setattr(tasks, "DATABASE_RETRY_S", (0.0, 0.0))
    body, state, words = _ending_edit(ending, db)
    monkeypatch.setattr(tasks, "_edit", body)
    job_id = add_job(add_scene(), "running", 0, stage="reconstruct", completed_stages=["reconstruct"])
    with monkeypatch.context() as outage:
        calls = _ending_the_job(outage, answer_lost)
        result = tasks.edit_task.apply(args=(job_id,))
    assert result.state == "REJECTED" and result.result.requeue, result.result
    assert result.result.reason == (f"edit of job {job_id} stopped by a database outage (the database cannot be "
                                      f"reached or is locked) that kept its end from being recorded ({state}: {words})")
    assert len(calls) == 3
    job = job_row(job_id)
    counted = state == "failed" and not answer_lost
    if answer_lost:
        assert (job.state, job.error if state == "failed" else job.message) == (state, words)
    else:
        assert (job.state, job.error, job.completed_stages) == ("running", None, ["reconstruct"])
        assert (job.run_token, job.run_lease_until) == (None, None)  # the redelivery takes it at once
    assert job.requeues == (1 if counted else 0)
    requeued = [e["detail"] for e in events_of(job_id) if e["kind"] == "requeued"]
    assert requeued == ([f"edit failed, and a database outage (the database cannot be reached or is locked) kept "
                         f"that from being recorded: {words}"] if counted else [])

    redelivered = tasks.edit_task.apply(args=(job_id,)).get()  # the database back; a failure met again
    job = job_row(job_id)
    if answer_lost or state == "canceled":
        assert "skipped" in redelivered
        assert (job.state, job.error if state == "failed" else job.message) == (state, words)  # "during": it ran
    else:
        assert redelivered == {"job_id": job_id, "stage": "edit", "state": "failed"}
        assert (job.state, job.error, job.requeues) == ("failed", words, 1)


def _cold_shutdown_in_pauses(monkeypatch) -> None:
    """Celery's cold shutdown as a solo pool's task meets it, in the pause before its next try of the database: the
    shutdown's flag set, and the pool's refusal to kill the task raised in it."""
    import time as clock

    from celery.worker import state

    def shutdown(_seconds):
        monkeypatch.setattr(state, "should_terminate", 0)  # set by Celery's cold shutdown (its exit code)
        raise NotImplementedError("<class 'celery.concurrency.solo.TaskPool'> does not implement kill_job")

    monkeypatch.setattr(clock, "sleep", shutdown)


@pytest.mark.parametrize("ending", ENDINGS)
def test_a_cold_shutdown_while_a_stages_end_waits_out_an_outage_releases_the_job_and_requeues(db, monkeypatch,
                                                                                              ending):
    """The worker stopped (cold, or a warm shutdown turned cold) while the stage's end was tried again in a database
    outage: what the shutdown raised in the task went through, the message acknowledged as failed, the job left
    running, held by a run gone. The hold is released, nothing counted, and the message goes back: its redelivery
    ends the job as the stage did."""
    from celery.worker import state

    from worker import tasks

    body, ended, words = _ending_edit(ending, db)
    monkeypatch.setattr(tasks, "_edit", body)
    job_id = add_job(add_scene(), "running", 0, stage="reconstruct", completed_stages=["reconstruct"])
    with monkeypatch.context() as stopping:
        _ending_the_job(stopping, answer_lost=False)
        _cold_shutdown_in_pauses(stopping)
        result = tasks.edit_task.apply(args=(job_id,))
    assert result.state == "REJECTED" and result.result.requeue, result.result
    assert result.result.reason == f"edit of job {job_id} stopped by the worker's shutdown"
    job = job_row(job_id)
    assert (job.state, job.run_token, job.run_lease_until, job.requeues) == ("running", None, None, 0)
    assert state.should_terminate is None  # the next worker
    redelivered = tasks.edit_task.apply(args=(job_id,)).get()
    assert redelivered.get("state", ended) == ended  # (a cancel: found as the redelivery starts, "skipped")
    job = job_row(job_id)
    assert (job.state, job.error if ended == "failed" else job.message) == (ended, words)


@pytest.mark.parametrize("where", ["waiting for a hold", "give-back"])
def test_a_cold_shutdown_while_a_stage_waits_to_start_or_to_give_its_job_back_requeues(db, monkeypatch, where):
    """A redelivered message waiting for another run's hold to run out, or a run giving its job back after an outage
    stopped its stage, when the worker stops cold: the message goes back to the queue (it had been acknowledged as
    failed, and the job never ran again), and this run's hold, if it held one, is released; another run's is not
    touched."""
    import sqlite3

    from sqlalchemy import update
    from sqlalchemy.exc import OperationalError

    from voxe_service.db import session_scope
    from voxe_service.models import Job, utcnow
    from worker import runtime, tasks

    job_id = add_job(add_scene(), "running", 0, stage="reconstruct", completed_stages=["reconstruct"])
    locked = OperationalError("UPDATE jobs", {}, sqlite3.OperationalError("database is locked"))
    lease_end = utcnow() + timedelta(seconds=db.stage_lease_s)
    with monkeypatch.context() as stopping:
        if where == "waiting for a hold":
            with session_scope() as session:
                session.execute(update(Job).where(Job.id == job_id).values(run_token="other",
                                                                           run_lease_until=lease_end))
        else:
            stopping.setattr(tasks, "_edit", lambda *args: (_ for _ in ()).throw(locked))
            stopping.setattr(runtime, "give_back_stage", lambda *args: (_ for _ in ()).throw(locked))
        _cold_shutdown_in_pauses(stopping)
        result = tasks.edit_task.apply(args=(job_id,))
    assert result.state == "REJECTED" and result.result.requeue, result.result
    assert result.result.reason == f"edit of job {job_id} stopped by the worker's shutdown"
    job = job_row(job_id)
    held = ("other", lease_end.replace(tzinfo=None)) if where == "waiting for a hold" else (None, None)
    assert (job.state, job.run_token, job.run_lease_until and job.run_lease_until.replace(tzinfo=None),
            job.requeues) == ("running", *held, 0)


def test_a_replaced_artifacts_old_bytes_the_storage_cannot_delete_fail_nothing(db, tmp_path, monkeypatch, caplog):
    """The replacement is recorded before the old object is deleted: a delete the storage refuses then (S3 throttling
    its DELETE) had raised out of publish_artifact and failed the stage (an edit, hours in, republishing its
    preview). The old bytes stay behind, unlisted, and the new version is the one listed."""
    import hashlib

    from voxe_service.storage import StorageUnavailable, get_storage
    from worker import runtime

    storage = get_storage(db)
    job_id = add_job(add_scene(), "running", 0, "w@host", "edit")
    preview = tmp_path / "preview.png"
    preview.write_bytes(b"first")
    first = runtime.publish_artifact(job_id, "preview.png", preview, "preview", storage).key
    preview.write_bytes(b"second")

    def throttled(key):
        raise StorageUnavailable(f"S3 bucket 'voxe': SlowDown when deleting {key}")

    with monkeypatch.context() as refusing:
        refusing.setattr(type(storage), "delete", lambda self, key: throttled(key))
        second = runtime.publish_artifact(job_id, "preview.png", preview, "preview", storage).key
    assert listed(job_id) == [("preview.png", 6, hashlib.sha256(b"second").hexdigest())]
    assert sorted(storage.list(f"jobs/{job_id}/")) == sorted([first, second])
    assert f"could not delete the stored object {first}" in caplog.text


def test_an_artifact_whose_record_fails_leaves_no_bytes_behind(db, tmp_path, monkeypatch):
    """The bytes are uploaded, then the transaction recording them fails (a database error): the upload goes too,
    so an artifact is listed and stored, or neither (it had stayed in storage, unlisted, for good)."""
    from sqlalchemy.exc import OperationalError

    from voxe_service.storage import get_storage
    from worker import runtime

    storage = get_storage(db)
    job_id = add_job(add_scene(), "running", 0, "w@host", "edit")
    grid = tmp_path / "edited_grid.safetensors"
    grid.write_bytes(b"grid" * 100)

    def locked(*_args, **_kwargs):
        raise OperationalError("INSERT INTO job_events", {}, Exception("database is locked"))

    monkeypatch.setattr(runtime, "record_event", locked)
    with pytest.raises(OperationalError):
        runtime.publish_artifact(job_id, "edited_grid.safetensors", grid, "grid", storage)
    assert listed(job_id) == [] and storage.list(f"jobs/{job_id}/") == []
    monkeypatch.undo()
    runtime.publish_artifact(job_id, "edited_grid.safetensors", grid, "grid", storage)
    with monkeypatch.context() as failing:  # a replacement whose record fails: the first version stays, alone
        failing.setattr(runtime, "record_event", locked)
        with pytest.raises(OperationalError):
            runtime.publish_artifact(job_id, "edited_grid.safetensors", grid, "grid", storage)
    assert storage.list(f"jobs/{job_id}/") == [f"jobs/{job_id}/edited_grid.safetensors"]
    assert [name for name, *_ in listed(job_id)] == ["edited_grid.safetensors"]
    with monkeypatch.context() as failing:  # ... and when the database cannot say what is recorded, nothing goes
        failing.setattr(runtime, "record_event", locked)
        calls = []

        def answers_once(*args):  # the read before the upload answers (nothing recorded), the one after fails
            calls.append(args)
            return None if len(calls) == 1 else locked()

        failing.setattr(runtime, "recorded_key", answers_once)
        with pytest.raises(OperationalError):
            runtime.publish_artifact(job_id, "render.png", grid, "render", storage)
    assert f"jobs/{job_id}/render.png" in storage.list(f"jobs/{job_id}/")  # kept: a row might point at it


def test_a_set_whose_storage_fails_part_way_reports_that_failure_not_the_cleanups(db, tmp_path, monkeypatch, caplog):
    """The storage refusing the second file of a set is likely to refuse the delete of the first as well (the same
    outage): that delete is cleanup, logged, and the error raised is the upload's, which the job's error names."""
    from voxe_service.storage import StorageUnavailable, get_storage
    from worker import runtime

    storage = get_storage(db)
    job_id = add_job(add_scene(), "running", 0, "w@host", "export")
    ply, glb = tmp_path / "mesh.ply", tmp_path / "mesh.glb"
    ply.write_bytes(b"ply")
    glb.write_bytes(b"glb")
    put_file = type(storage).put_file

    def outage(what: str, key: str):
        raise StorageUnavailable(f"S3 bucket 'voxe': SlowDown when {what} {key}")

    monkeypatch.setattr(type(storage), "put_file", lambda self, key, path, content_type=None: (
        outage("uploading", key) if key.endswith(".glb") else put_file(self, key, path, content_type)))
    monkeypatch.setattr(type(storage), "delete", lambda self, key: outage("deleting", key))
    with pytest.raises(StorageUnavailable, match="when uploading"):
        runtime.publish_artifacts(job_id, [("mesh.ply", ply, "mesh"), ("mesh.glb", glb, "mesh")], storage)
    assert listed(job_id) == []
    assert f"could not delete the stored object jobs/{job_id}/mesh.ply" in caplog.text


def test_an_upload_failing_mid_write_is_never_listed_and_leaves_no_file(db, tmp_path, monkeypatch):
    from voxe_service.storage import get_storage
    from worker.runtime import publish_artifact

    storage = get_storage(db)
    job_id = add_job(add_scene(), "running", 0, "w@host", "export")
    old, new = tmp_path / "old.bin", tmp_path / "new.bin"
    old.write_bytes(b"first version " * 1000)
    new.write_bytes(b"second, longer version " * 5000)
    job_files = lambda: sorted(p.name for p in (tmp_path / "storage" / "jobs").rglob("*") if p.is_file())  # noqa: E731

    def crash_after_the_bytes(_fd):  # the bytes are in the temporary file; it dies before the rename
        raise Crash()

    monkeypatch.setattr("voxe_service.storage.os.fsync", crash_after_the_bytes)
    with pytest.raises(Crash):
        publish_artifact(job_id, "render_000.png", old, "render", storage)
    assert listed(job_id) == [] and job_files() == []

    monkeypatch.undo()
    publish_artifact(job_id, "render_000.png", old, "render", storage)
    first = ("render_000.png", old.stat().st_size, hashlib.sha256(old.read_bytes()).hexdigest())
    assert listed(job_id) == [first]

    monkeypatch.setattr("voxe_service.storage.os.fsync", crash_after_the_bytes)
    with pytest.raises(Crash):  # replacing it fails half way: the old version stays listed, whole
        publish_artifact(job_id, "render_000.png", new, "render", storage)
    assert listed(job_id) == [first] and stored_bytes(storage, job_id, "render_000.png") == old.read_bytes()
    assert job_files() == ["render_000.png"]

    monkeypatch.undo()
    publish_artifact(job_id, "render_000.png", new, "render", storage)
    data = stored_bytes(storage, job_id, "render_000.png")
    assert data == new.read_bytes()
    assert listed(job_id) == [("render_000.png", len(data), hashlib.sha256(data).hexdigest())]
    assert job_files() == ["render_000.png"]  # the replaced version was deleted


def test_a_writer_killed_mid_write_leaves_nothing_listed_and_deleting_the_job_removes_the_debris(tmp_path):
    """SIGKILL a process whose upload has written every byte to the temporary name but not renamed it."""
    import signal
    import subprocess
    import sys

    from voxe_service.storage import LocalStorage
    from service_helpers import REPO

    source = tmp_path / "edited_grid.safetensors"
    source.write_bytes(os.urandom(3 * 1024 * 1024))
    writer = ("import sys, time\n"
              "import voxe_service.storage as storage\n"
              "storage.os.fsync = lambda fd: (print('written', flush=True), time.sleep(60))\n"
              "storage.LocalStorage(sys.argv[1]).put_file('jobs/j/edited_grid.safetensors', sys.argv[2])\n")
    proc = subprocess.Popen([sys.executable, "-c", writer, str(tmp_path / "store"), str(source)], cwd=REPO,
                            stdout=subprocess.PIPE, env={**os.environ, "PYTHONPATH": str(REPO)})
    try:
        assert proc.stdout.readline().strip() == b"written"
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    store = LocalStorage(tmp_path / "store")
    assert store.list() == [] and not store.exists("jobs/j/edited_grid.safetensors")
    debris = [p for p in (tmp_path / "store").rglob("*") if p.is_file()]
    assert [p.stat().st_size for p in debris] == [source.stat().st_size] and debris[0].name.endswith(".tmp")
    assert store.delete_prefix("jobs/j/") == 0
    assert not (tmp_path / "store" / "jobs").exists()


@contextlib.contextmanager
def s3_server(request, server: str):
    """The variables that point at moto's server (started for the test) or at the session's SeaweedFS."""
    if server == "seaweedfs":
        yield request.getfixturevalue("seaweedfs")
    else:
        from service_helpers import moto_s3

        with moto_s3() as env:
            yield env


@contextlib.contextmanager
def s3_bucket(request, server: str, monkeypatch):
    """An S3Storage on a bucket of its own (moto keeps buckets per process) on ``s3_server``, its credentials set."""
    from voxe_service.storage import S3Storage

    with s3_server(request, server) as env:
        for key in ("AWS_ACCESS_KEY_ID", "AWS_SECRET_ACCESS_KEY", "AWS_DEFAULT_REGION"):
            monkeypatch.setenv(key, env[key])
        yield S3Storage(f"voxe-faults-{uuid.uuid4().hex[:8]}", endpoint_url=env["VOXE_S3_ENDPOINT_URL"],
                        region="us-east-1")


@pytest.mark.parametrize("server", ["moto", "seaweedfs"])
def test_a_multipart_s3_upload_failing_half_way_is_never_listed(db, tmp_path, monkeypatch, request, server):
    """boto3 uploads large files in parts; a part that fails aborts the upload: no object, no row."""
    from worker.runtime import publish_artifact

    with s3_bucket(request, server, monkeypatch) as storage:
        bucket = storage.bucket
        job_id = add_job(add_scene(), "running", 0, "w@host", "edit")
        big = tmp_path / "grid.safetensors"
        big.write_bytes(os.urandom(20 * 1024 * 1024))  # above boto3's 8 MiB multipart threshold
        parts = []

        def fail_the_second_part(**_kwargs):
            parts.append(1)
            if len(parts) == 2:
                raise Crash()

        storage.client.meta.events.register("before-call.s3.UploadPart", fail_the_second_part)
        with pytest.raises(Crash):
            publish_artifact(job_id, "edited_grid.safetensors", big, "grid", storage)
        assert len(parts) >= 2
        assert listed(job_id) == [] and storage.list("jobs/") == []
        assert storage.client.list_multipart_uploads(Bucket=bucket).get("Uploads", []) == []

        storage.client.meta.events.unregister("before-call.s3.UploadPart", fail_the_second_part)
        publish_artifact(job_id, "edited_grid.safetensors", big, "grid", storage)
        data = stored_bytes(storage, job_id, "edited_grid.safetensors")
        assert listed(job_id) == [("edited_grid.safetensors", len(data), hashlib.sha256(data).hexdigest())]
        assert data == big.read_bytes()

def killed_after_its_first_part(storage, source: os.PathLike, key: str) -> None:
    """A process storing ``source`` at ``key`` of ``storage``'s bucket (S3Storage, a multipart upload), SIGKILLed once
    it has uploaded a part: the parts it leaves, as an API or worker killed mid-upload does."""
    import signal
    import subprocess
    import sys

    from service_helpers import REPO

    writer = ("import sys, time\n"
              "from voxe_service.storage import S3Storage\n"
              "storage = S3Storage(sys.argv[1], endpoint_url=sys.argv[2], region='us-east-1')\n"
              "storage.client.meta.events.register('after-call.s3.UploadPart',\n"
              "                                    lambda **_: (print('part', flush=True), time.sleep(60)))\n"
              "storage.put_file(sys.argv[4], sys.argv[3])\n")
    proc = subprocess.Popen([sys.executable, "-c", writer, storage.bucket, storage.client.meta.endpoint_url,
                             str(source), key], cwd=REPO, stdout=subprocess.PIPE,
                            env={**os.environ, "PYTHONPATH": str(REPO)})
    try:
        assert proc.stdout.readline().startswith(b"part")  # (two part threads may print on one line)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)


def multipart_uploads(storage) -> list[str]:
    """The keys of the unfinished multipart uploads in ``storage``'s bucket (sorted: S3 lists them by key, SeaweedFS
    not)."""
    return sorted(u["Key"] for u in storage.client.list_multipart_uploads(Bucket=storage.bucket).get("Uploads", []))


@pytest.mark.parametrize("server", ["moto", "seaweedfs"])
def test_the_parts_an_s3_writer_killed_mid_upload_left_go_with_its_job(tmp_path, monkeypatch, caplog, request, server):
    """SIGKILL a process whose multipart upload has stored a part: S3 keeps the parts (and bills them) under an upload
    no object listing shows, and deleting the job's prefix had left them for ever. They are aborted with it; another
    job's are not touched."""

    source = tmp_path / "edit.safetensors"
    source.write_bytes(os.urandom(20 * 1024 * 1024))  # above boto3's 8 MiB multipart threshold
    with s3_bucket(request, server, monkeypatch) as storage:
        bucket = storage.bucket
        killed_after_its_first_part(storage, source, "jobs/j/checkpoints/edit.safetensors")
        other = storage.client.create_multipart_upload(Bucket=bucket, Key="jobs/other/edit.safetensors")

        def uploads() -> list[str]:
            return multipart_uploads(storage)

        assert storage.list() == [] and uploads() == ["jobs/j/checkpoints/edit.safetensors",
                                                      "jobs/other/edit.safetensors"]
        assert storage.delete_prefix("jobs/j/") == 0
        assert uploads() == ["jobs/other/edit.safetensors"]
        storage.client.abort_multipart_upload(Bucket=bucket, Key=other["Key"], UploadId=other["UploadId"])

        # A role that may not list unfinished uploads (or a store without the call) still deletes the objects: the
        # abort had gone first and raised, and every object of the deleted job stayed.
        from botocore.exceptions import ClientError

        def denied(**_):
            raise ClientError({"Error": {"Code": "AccessDenied", "Message": "Access Denied"}}, "ListMultipartUploads")

        storage.put_file("jobs/k/edit.safetensors", source)
        storage.client.meta.events.register("before-call.s3.ListMultipartUploads", denied)
        with caplog.at_level(logging.WARNING, logger="voxe.storage"):
            assert storage.delete_prefix("jobs/k/") == 1
        assert storage.list() == []
        assert "could not abort the unfinished uploads under 'jobs/k/'" in caplog.text and "AccessDenied" in caplog.text



def test_the_reaper_deletes_an_upload_no_scene_records_once_old_and_keeps_young_and_recorded_ones(db, caplog):
    """An API process killed after storing an upload and before recording its scene (or mid-store: a writer's
    temporary file) left ``scenes/<id>/`` with no row, kept for ever: every cleanup starts from a row. The reaper
    deletes it once last written VOXE_ORPHANED_UPLOAD_AGE_S ago; a younger one (still being stored, or about to be
    recorded) and a recorded scene's objects, however old, stay."""
    from api import reaper
    from voxe_service.models import system_now
    from voxe_service.storage import get_storage, scene_key

    storage = get_storage(db)
    age = db.orphaned_upload_age_s
    old = time.time() - age - 60
    orphan, half_written, young, recorded = uuid.uuid4().hex, uuid.uuid4().hex, uuid.uuid4().hex, add_scene()
    for scene_id in (orphan, young, recorded):
        storage.put_bytes(scene_key(scene_id, "dataset.zip"), b"zip")
    partial = storage.path(scene_key(half_written, ".dataset.zip.0123456789abcdef0123456789abcdef.tmp"))
    partial.parent.mkdir(parents=True)
    partial.write_bytes(b"z")  # a killed writer's temporary file (never listed)
    for scene_id in (orphan, half_written, recorded):
        for path in (storage.root / "scenes" / scene_id).iterdir():
            os.utime(path, (old, old))
    assert reaper.reap_orphaned_uploads(db, now=system_now() - timedelta(seconds=120)) == []  # none that old yet
    with caplog.at_level(logging.WARNING, logger="voxe.reaper"):
        assert sorted(reaper.reap_orphaned_uploads(db)) == sorted(map(scene_key, [orphan, half_written]))
    assert f"deleted the stored objects under scenes/{orphan}/, which no scene records" in caplog.text
    assert dict(storage.written_at("scenes/")).keys() == {scene_key(young, "dataset.zip"),
                                                          scene_key(recorded, "dataset.zip")}
    assert not (storage.root / "scenes" / half_written).exists()



def test_the_reaper_says_it_deleted_only_the_unrecorded_uploads_whose_delete_worked(db, caplog, monkeypatch):
    """The sweep logged "deleted the stored objects under scenes/<id>/" (and returned the prefix) for each orphan,
    also where the delete failed (a role denied DeleteObject, the store down: the cleanup's own warning said so just
    before), every hour, the objects still there. It now names as deleted only those that were; a failed one is
    the cleanup's warning alone, and stays for the next sweep."""
    from api import reaper
    from voxe_service.storage import StorageError, get_storage, scene_key

    storage = get_storage(db)
    old = time.time() - db.orphaned_upload_age_s - 60
    denied, deleted = uuid.uuid4().hex, uuid.uuid4().hex
    for scene_id in (denied, deleted):
        storage.put_bytes(scene_key(scene_id, "dataset.zip"), b"zip")
        os.utime(storage.path(scene_key(scene_id, "dataset.zip")), (old, old))
    delete = storage.delete

    def denying(key):
        if key.startswith(scene_key(denied)):
            raise StorageError(f"AccessDenied: may not delete {key}")
        delete(key)

    monkeypatch.setattr(storage, "delete", denying)
    with caplog.at_level(logging.WARNING):
        assert reaper.reap_orphaned_uploads(db) == [scene_key(deleted)]
    assert f"deleted the stored objects under {scene_key(deleted)}, which no scene records" in caplog.text
    assert f"deleted the stored objects under {scene_key(denied)}" not in caplog.text
    assert f"could not delete the stored objects under {scene_key(denied)}" in caplog.text
    assert storage.list(scene_key(denied)) == [scene_key(denied, "dataset.zip")] and not storage.list(scene_key(deleted))


def test_the_reapers_sweep_of_a_large_bucket_holds_a_page_of_its_listing_not_all_of_it(db, monkeypatch):
    """The hourly sweep for unrecorded uploads lists every stored object: S3's listing had been gathered whole, one
    entry per object (a key and its time: 100,000 of them, ~15 MB; an evaluation's renders alone are 100 objects),
    before any was looked at, in the API process. It now reads the listing a page (1,000 objects) at a time, keeping
    one time per job, scene or reconstruction."""
    import tracemalloc
    from types import SimpleNamespace

    from api import reaper
    from voxe_service.models import system_now
    from voxe_service.storage import S3Storage

    written, pages_served, pages = system_now(), [], [1]

    def objects(Bucket, Prefix):  # noqa: N803 - boto3's parameter names
        for page in range(pages[0] if Prefix == "jobs/" else 0):
            pages_served.append(page)
            yield {"Contents": [{"Key": f"jobs/{page % 10:032x}/ring_{page:03d}_{n:04d}.png", "LastModified": written}
                                for n in range(1000)]}

    listings = {"list_objects_v2": objects, "list_multipart_uploads": lambda Bucket, Prefix: iter([{}])}  # noqa: N803
    client = SimpleNamespace(get_paginator=lambda name: SimpleNamespace(paginate=listings[name]))
    monkeypatch.setattr(reaper, "get_storage", lambda _settings: S3Storage("bucket", client=client,
                                                                           create_bucket=False))
    assert reaper.reap_orphaned_uploads(db) == []  # (a page first: what a first sweep imports is not counted)
    pages[0], pages_served[:] = 100, []
    tracemalloc.start()
    try:
        assert reaper.reap_orphaned_uploads(db) == []  # (all young: nothing looked up, nothing deleted)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert len(pages_served) == 100
    assert peak < 4_000_000, f"the sweep held {peak / 1e6:.1f} MB at its peak"

@pytest.mark.parametrize("server", ["moto", "seaweedfs"])
def test_the_reaper_aborts_the_parts_of_an_upload_whose_api_process_was_killed_mid_store(tmp_path, monkeypatch,
                                                                                        request, server, db):
    """SIGKILL a process storing a scene's upload in parts: S3 keeps the parts under scenes/<id>/ with no object and
    no scene row, and nothing had ever aborted them (a prefix's cleanup starts from a row). Once as old as
    VOXE_ORPHANED_UPLOAD_AGE_S the reaper aborts them; a recorded scene's object stays, and before that age nothing
    goes (SeaweedFS: moto dates its uploads in 2010)."""
    from api import reaper
    from voxe_service.models import system_now

    source = tmp_path / "dataset.zip"
    source.write_bytes(os.urandom(20 * 1024 * 1024))  # above boto3's 8 MiB multipart threshold
    orphan, recorded = uuid.uuid4().hex, add_scene()
    with s3_bucket(request, server, monkeypatch) as storage:
        monkeypatch.setattr(reaper, "get_storage", lambda _settings: storage)
        storage.put_bytes(f"scenes/{recorded}/dataset.zip", b"zip")
        killed_after_its_first_part(storage, source, f"scenes/{orphan}/dataset.zip")

        def uploads() -> list[str]:
            return multipart_uploads(storage)

        assert uploads() == [f"scenes/{orphan}/dataset.zip"]
        if server == "seaweedfs":  # (moto dates every multipart upload 2010-11-10: none is young there)
            assert reaper.reap_orphaned_uploads(db) == []  # young: it may still be being stored
            assert uploads() == [f"scenes/{orphan}/dataset.zip"]
        later = system_now() + timedelta(seconds=db.orphaned_upload_age_s + 60)
        assert reaper.reap_orphaned_uploads(db, now=later) == [f"scenes/{orphan}/"]
        assert uploads() == [] and storage.list() == [f"scenes/{recorded}/dataset.zip"]


@pytest.mark.parametrize("prefix", ["jobs", "reconstructions"])
def test_the_reaper_deletes_a_job_or_reconstructions_objects_no_row_records_once_old_and_keeps_young_and_recorded_ones(
        db, caplog, prefix):
    """A delete whose storage cleanup failed after its rows went (or a crash between a write and its row) left
    ``jobs/<id>/`` or ``reconstructions/<id>/`` with no row, kept for ever as scenes' uploads were: the reaper's sweep
    takes them too once last written VOXE_ORPHANED_UPLOAD_AGE_S ago (a writer's temporary file included); a younger
    one and a recorded job's or reconstruction's objects, however old, stay."""
    from api import reaper
    from voxe_service.models import system_now
    from voxe_service.storage import get_storage

    storage = get_storage(db)
    old = time.time() - db.orphaned_upload_age_s - 60
    scene = add_scene()
    recorded_id = add_job(scene, "succeeded", 0) if prefix == "jobs" else add_reconstruction(scene)
    orphan, half_written, young, recorded = (f"{prefix}/{row_id}/" for row_id in
                                             (uuid.uuid4().hex, uuid.uuid4().hex, uuid.uuid4().hex, recorded_id))
    for key in (orphan, young, recorded):
        storage.put_bytes(key + "grid.safetensors", b"grid")
    partial = storage.path(half_written + ".grid.safetensors.0123456789abcdef0123456789abcdef.tmp")
    partial.parent.mkdir(parents=True)
    partial.write_bytes(b"g")  # a killed writer's temporary file (never listed)
    for key in (orphan, half_written, recorded):
        for path in (storage.root / key).iterdir():
            os.utime(path, (old, old))
    assert reaper.reap_orphaned_uploads(db, now=system_now() - timedelta(seconds=120)) == []  # none that old yet
    kind = prefix.removesuffix("s")
    with caplog.at_level(logging.WARNING, logger="voxe.reaper"):
        assert sorted(reaper.reap_orphaned_uploads(db)) == sorted([orphan, half_written])
    assert f"deleted the stored objects under {orphan}, which no {kind} records" in caplog.text
    assert sorted(storage.list()) == sorted([young + "grid.safetensors", recorded + "grid.safetensors"])
    assert not (storage.root / half_written).exists()


def test_the_reapers_sweep_leaves_an_object_in_no_ids_folder_alone_and_unnamed(db, caplog):
    """An object lying directly under jobs/ (or scenes/, reconstructions/), in no <id>/ folder, was named an orphan
    under jobs/<name>/ at every sweep, said deleted in the log and kept. It is not the service's: left alone, unnamed;
    an orphan beside it still goes."""
    from api import reaper
    from voxe_service.storage import get_storage

    storage = get_storage(db)
    old = time.time() - db.orphaned_upload_age_s - 60
    strays = ["jobs/notes.txt", "scenes/stray.bin", "reconstructions/x"]
    orphan = f"jobs/{uuid.uuid4().hex}/"
    for key in (*strays, orphan + "grid.safetensors"):
        storage.put_bytes(key, b"x")
        os.utime(storage.path(key), (old, old))
    with caplog.at_level(logging.WARNING, logger="voxe.reaper"):
        for _sweep in range(2):
            assert reaper.reap_orphaned_uploads(db) == ([orphan] if _sweep == 0 else [])
    assert [r.getMessage() for r in caplog.records if "deleted the stored objects" in r.getMessage()] == [
        f"reaper: deleted the stored objects under {orphan}, which no job records (a process stopped between storing "
        "and recording them, or their cleanup failed after a delete)"]
    assert sorted(storage.list()) == sorted(strays)


@pytest.mark.parametrize("server", ["local", "moto"])
def test_the_reapers_sweep_deletes_the_old_probe_objects_of_older_versions_and_keeps_the_probes_own(
        db, caplog, monkeypatch, request, server):
    """Readiness probes before _probe/ready each wrote a _probe/<uuid> object and deleted it; where the delete failed
    it stayed, and nothing ever swept _probe/ (the sweep reads scenes/, jobs/ and reconstructions/ alone): one object a
    probe, for good. The sweep now deletes those last written VOXE_ORPHANED_UPLOAD_AGE_S ago; _probe/ready (however
    old), a young one (an older replica's probe still running) and one whose delete fails stay."""
    from api import reaper
    from voxe_service.models import system_now
    from voxe_service.storage import PROBE_KEY, StorageError, get_storage

    old_probes = [f"_probe/{uuid.uuid4().hex}" for _ in range(3)]
    with contextlib.ExitStack() as stack:
        if server == "local":
            storage = get_storage(db)
        else:
            storage = stack.enter_context(s3_bucket(request, server, monkeypatch))
            monkeypatch.setattr(reaper, "get_storage", lambda _settings: storage)
        storage.check_writable()
        for key in old_probes:
            storage.put_bytes(key, b"ok")
        later = system_now() + timedelta(seconds=db.orphaned_upload_age_s + 60)  # (S3 dates objects as written)
        assert reaper.reap_orphaned_uploads(db) == []  # young: an older replica's probe may be reading it back
        young = f"_probe/{uuid.uuid4().hex}"
        if server == "local":
            old = time.time() - db.orphaned_upload_age_s - 60
            for key in (PROBE_KEY, *old_probes):
                os.utime(storage.path(key), (old, old))
            later = None
            storage.put_bytes(young, b"ok")  # (on S3 the young one is the first sweep's)
        delete, denied = storage.delete, old_probes[0]

        def denying(key):
            if key == denied:
                raise StorageError(f"AccessDenied: may not delete {key}")
            delete(key)

        monkeypatch.setattr(storage, "delete", denying)
        with caplog.at_level(logging.WARNING, logger="voxe.reaper"):
            assert sorted(reaper.reap_orphaned_uploads(db, now=later)) == sorted(old_probes[1:])
        assert "deleted 2 objects older versions' readiness probes left under _probe/" in caplog.text
        assert f"could not delete the old readiness probe's object {denied}" in caplog.text
        assert sorted(storage.list("_probe/")) == sorted([PROBE_KEY, denied] + ([young] if server == "local" else []))


@pytest.mark.parametrize("server", ["local", "moto", "seaweedfs"])
def test_the_reapers_sweep_abandons_old_unfinished_writes_under_recorded_rows_and_in_no_ids_folder(
        db, caplog, monkeypatch, request, server):
    """A worker killed mid-upload under a job that lives on (sent again, it succeeds) left its unfinished write: S3's
    multipart parts (billed, in no listing) or a local temporary file, kept until the job was deleted, as was one in
    no <id>/ folder (jobs/stray.bin), for good: the sweep looked only for prefixes no row records. It now abandons
    each one started VOXE_ORPHANED_UPLOAD_AGE_S ago, naming it; the recorded job's objects stay, and a young write
    (still going) stays (SeaweedFS and local: moto dates its uploads in 2010)."""
    from api import reaper
    from voxe_service.models import system_now
    from voxe_service.storage import get_storage

    job = add_job(add_scene(), "succeeded", 0)
    kept = f"jobs/{job}/result.safetensors"
    unfinished = [f"jobs/{job}/grid.safetensors", "jobs/stray.bin"]
    with contextlib.ExitStack() as stack:
        if server == "local":
            storage = get_storage(db)
            writes = [storage.path(f"jobs/{job}/.grid.safetensors.{'1' * 32}.tmp"),
                      storage.path(f"jobs/.stray.bin.{'2' * 32}.tmp")]
            unfinished = [path.relative_to(storage.root).as_posix() for path in writes]
            storage.put_bytes(kept, b"bytes")

            def start_writes():
                for path in writes:
                    path.write_bytes(b"part")

            def uploads() -> list[str]:
                return sorted(path.relative_to(storage.root).as_posix() for path in writes if path.exists())
        else:
            storage = stack.enter_context(s3_bucket(request, server, monkeypatch))
            monkeypatch.setattr(reaper, "get_storage", lambda _settings: storage)
            storage.put_bytes(kept, b"bytes")

            def start_writes():
                for key in unfinished:
                    storage.client.create_multipart_upload(Bucket=storage.bucket, Key=key)

            def uploads() -> list[str]:
                return multipart_uploads(storage)
        start_writes()
        if server != "moto":
            assert reaper.reap_orphaned_uploads(db) == []  # young: they may still be being written
            assert uploads() == sorted(unfinished)
        later = system_now() + timedelta(seconds=db.orphaned_upload_age_s + 60)
        with caplog.at_level(logging.WARNING, logger="voxe.reaper"):
            assert sorted(reaper.reap_orphaned_uploads(db, now=later)) == sorted(unfinished)
        assert uploads() == [] and storage.list() == [kept]
        assert "reaper: abandoned 2 unfinished writes under jobs/ started before" in caplog.text
        assert all(key in caplog.text for key in unfinished)


@pytest.mark.parametrize("server", ["moto", "seaweedfs"])
def test_the_reaper_deletes_s3_objects_and_parts_of_jobs_and_reconstructions_no_row_records(monkeypatch, request,
                                                                                          server, db):
    """On S3 the sweep of jobs/ and reconstructions/ deletes the objects and aborts the unfinished multipart uploads
    no row records, once old; the recorded ones' objects stay, and before the age nothing goes (moto dates its
    multipart uploads in 2010: the young check is SeaweedFS's)."""
    from api import reaper
    from voxe_service.models import system_now

    scene = add_scene()
    job, rec = add_job(scene, "succeeded", 0), add_reconstruction(scene)
    orphan_job, orphan_rec = uuid.uuid4().hex, uuid.uuid4().hex
    with s3_bucket(request, server, monkeypatch) as storage:
        bucket = storage.bucket
        monkeypatch.setattr(reaper, "get_storage", lambda _settings: storage)
        kept = [f"jobs/{job}/result.safetensors", f"reconstructions/{rec}/grid.safetensors"]
        for key in kept + [f"jobs/{orphan_job}/result.safetensors"]:
            storage.put_bytes(key, b"bytes")
        storage.client.create_multipart_upload(Bucket=bucket, Key=f"reconstructions/{orphan_rec}/grid.safetensors")

        def uploads() -> list[str]:
            return sorted(u["Key"] for u in storage.client.list_multipart_uploads(Bucket=bucket).get("Uploads", []))

        if server == "seaweedfs":
            assert reaper.reap_orphaned_uploads(db) == []  # young: they may still be being written or recorded
            assert uploads() == [f"reconstructions/{orphan_rec}/grid.safetensors"]
        later = system_now() + timedelta(seconds=db.orphaned_upload_age_s + 60)
        assert reaper.reap_orphaned_uploads(db, now=later) == [f"jobs/{orphan_job}/", f"reconstructions/{orphan_rec}/"]
        assert uploads() == [] and sorted(storage.list()) == sorted(kept)


# ---------------------------------------------------------------------------------------------- real processes
RECONSTRUCTION = {"preset": "fast", "resolution": 24, "iterations": [10, 10, 20], "rays_per_step": 1024}
EXPORT = {"views": 2, "view_size": 48, "turntable_frames": 8, "turntable_size": 48, "gif": False, "mesh": False}
PARAMS = {"downsample": 16, "max_images": 8, "iterations": 5, "render_size": 48, "reconstruction": RECONSTRUCTION,
          "export": EXPORT}
ARTIFACTS = {"initial_grid.safetensors", "edited_grid.safetensors", "render_000.png", "render_001.png",
             "turntable.mp4", "preview.png"}
# A killed edit's length: long enough that a kill right after its first checkpoint lands well before its end.
EDIT_ITERATIONS = 60


@pytest.fixture(scope="module")
def scene_zip(tmp_path_factory):
    from service_helpers import small_mic, zip_folder

    require_data(MIC)
    folder = tmp_path_factory.mktemp("scene")
    return zip_folder(small_mic(folder / "mic", frames=3), folder / "mic.zip")


class Client:
    """HTTP against a running service, checking its processes stay up while waiting."""

    def __init__(self, svc):
        import httpx

        self.svc, self.http = svc, httpx.Client(base_url=svc.base, timeout=60)

    def upload(self, archive) -> dict:
        with open(archive, "rb") as handle:
            response = self.http.post("/v1/scenes", files={"archive": ("mic.zip", handle, "application/zip")})
        assert response.status_code == 201, response.text
        return response.json()

    def create_job(self, scene: dict, **body) -> dict:
        response = self.http.post("/v1/jobs", json={"scene_id": scene["id"], "prompt": "a yarn doll of a mic",
                                                    "params": PARAMS, **body})
        assert response.status_code == 201, response.text
        return response.json()

    def wait(self, job_id: str, until=None, timeout: float = 240, seen=None) -> dict:
        return poll_job(self.http, self.svc, job_id, until, timeout, seen)

    def diagnostics(self) -> str:
        return self.svc.diagnostics()


@pytest.mark.slow
def test_api_restart_loses_nothing_and_the_reaper_sends_again_a_job_whose_worker_died(tmp_path, scene_zip):
    """SIGKILL the API while jobs run and start it again: every job finishes. Then SIGKILL the worker for
    good: after VOXE_JOB_STALE_TIMEOUT_S, once the dead run's hold has lapsed (VOXE_STAGE_LEASE_S), the restarted
    API's reaper queues its job again, and a worker under another name, started later, resumes it from its
    checkpoint to the end."""
    from service_helpers import service, verify_artifacts

    with service(tmp_path, VOXE_JOB_STALE_TIMEOUT_S="6", VOXE_REAPER_INTERVAL_S="1", VOXE_WORKER_HEARTBEAT_S="1",
                 VOXE_CHECKPOINT_EVERY="10", VOXE_STAGE_LEASE_S="8") as svc:  # (the default 60 s outlasts the wait)
        client = Client(svc)
        scene = client.upload(scene_zip)
        running = client.create_job(scene, params={**PARAMS, "iterations": 20})
        queued = client.create_job(scene, prompt="a wood carving of a mic")
        wait_for_event(client.http, svc, running["id"], entered("edit"), what="the edit stage")
        svc.restart_api()
        for job in (running, queued):
            final = client.wait(job["id"])
            assert final["state"] == "succeeded" and final["error"] is None, f"{final}\n{client.diagnostics()}"
            names = {a["name"] for a in client.http.get(f"/v1/jobs/{job['id']}/artifacts").json()}
            assert ARTIFACTS <= names, names
        listing = client.http.get("/v1/jobs", params={"scene_id": scene["id"]}).json()
        assert sorted(j["id"] for j in listing["items"]) == sorted([running["id"], queued["id"]])

        orphan = client.create_job(scene, params={**PARAMS, "iterations": EDIT_ITERATIONS})
        wait_for_event(client.http, svc, orphan["id"], checkpoint_at_least("edit", 10), what="an edit checkpoint")
        svc.kill_worker()  # never restarted under its name: nothing would redeliver it
        at_kill = job_events(client.http, orphan["id"])
        requeued = client.wait(orphan["id"], until=lambda j: j["state"] == "queued", timeout=60)
        assert requeued["stage"] == "edit" and requeued["message"].startswith("re-queued: worker voxe-test-"), requeued
        assert requeued["message"].endswith("stopped while the job was in edit: no heartbeat and no progress for "
                                            "6 s (VOXE_JOB_STALE_TIMEOUT_S)"), requeued
        svc.start_worker(suffix="-b")
        final = client.wait(orphan["id"])
        assert final["state"] == "succeeded", f"{final}\n{client.diagnostics()}"
        events = job_events(client.http, orphan["id"])
        assert [e["stage"] for e in events if e["kind"] == "requeued"] == ["edit"], events
        check_resumed_from_the_last_checkpoint(at_kill, events, EDIT_ITERATIONS, 10)
        verify_artifacts(client.http, final, ARTIFACTS, tmp_path)


@pytest.mark.slow
def test_redis_restart_keeps_queued_jobs_and_a_killed_worker_task_is_redelivered(tmp_path, scene_zip):
    """A worker SIGKILLed in the middle of an edit, jobs queued behind it, then Redis (append-only persistence)
    restarted: the API reconnects by itself, and a fresh worker gets the killed task redelivered (its message
    was unacknowledged for longer than the visibility timeout), takes the job over once the killed run's hold on
    it has lapsed (VOXE_STAGE_LEASE_S), resumes the edit from its last checkpoint, then runs every queued job."""
    import shutil
    import time
    from datetime import datetime

    from service_helpers import redis_server, service, verify_artifacts

    if shutil.which("redis-server") is None:
        missing("redis-server is not installed (.ci/test installs it)")
    visibility = 5
    with redis_server(tmp_path / "redis") as redis, \
            service(tmp_path, redis.url, VOXE_BROKER_VISIBILITY_TIMEOUT_S=str(visibility),
                    VOXE_CHECKPOINT_EVERY="10", VOXE_STAGE_LEASE_S="4") as svc:
        client = Client(svc)
        scene = client.upload(scene_zip)
        long_job = client.create_job(scene, params={**PARAMS, "iterations": EDIT_ITERATIONS})
        wait_for_event(client.http, svc, long_job["id"], checkpoint_at_least("edit", 10), what="an edit checkpoint")
        svc.kill_worker()
        killed_at = time.monotonic()
        at_kill = job_events(client.http, long_job["id"])
        queued = [client.create_job(scene, prompt="a wood carving of a mic")]
        redis.restart()
        queued.append(client.create_job(scene, prompt="a claymation mic"))  # the API reconnected by itself
        time.sleep(max(0.0, killed_at + visibility + 1 - time.monotonic()))  # the edit's message is overdue now
        svc.start_worker(wait_ready=False)  # a starting worker re-queues overdue unacknowledged messages

        seen: list[dict] = []
        final = client.wait(long_job["id"], seen=seen)
        assert final["state"] == "succeeded", f"{final}\n{client.diagnostics()}"
        events = job_events(client.http, long_job["id"])
        at = check_resumed_from_the_last_checkpoint(at_kill, events, EDIT_ITERATIONS, 10)
        # No edit progress recorded after the resume lies below where it resumed.
        resumed_at = datetime.fromisoformat(next(e["at"] for e in events if e["kind"] == "resumed"))
        later = [j["iteration"] for j in seen if j["stage"] == "edit" and j["total"]
                 and datetime.fromisoformat(j["updated_at"]) >= resumed_at]
        assert min(later, default=at) >= at, (at, later)
        verify_artifacts(client.http, final, ARTIFACTS, tmp_path)
        for job in queued:
            done = client.wait(job["id"])
            assert done["state"] == "succeeded", f"{done}\n{client.diagnostics()}"
            assert ARTIFACTS <= {a["name"] for a in client.http.get(f"/v1/jobs/{job['id']}/artifacts").json()}


@pytest.mark.slow
@pytest.mark.parametrize("pool", ["prefork", "solo"])  # the image's and .ci/serve's; the tests' own
def test_a_worker_stopped_as_its_image_runs_hands_its_stage_back_and_another_resumes_it(tmp_path, scene_zip, pool):
    """SIGTERM (docker stop) to a worker mid-edit, with the worker image's REMAP_SIGTERM: its cold shutdown puts
    the message back in Redis at once, though the visibility timeout is the default hours, and a second worker
    takes the job over once the stopped run's hold lapses (VOXE_STAGE_LEASE_S), resuming from its checkpoint.
    Celery's default warm shutdown would have run the stage to its end, and a kill after the grace period
    had left the message unacknowledged for the reaper. The solo pool cancels the task by raising in it, which had
    failed the job."""
    import re
    import shutil

    from service_helpers import FINISHED, REPO, redis_server, service, verify_artifacts

    if shutil.which("redis-server") is None:
        missing("redis-server is not installed (.ci/test installs it)")
    image = dict(re.findall(r"\b(REMAP_SIGTERM)=(\w+)", (REPO / "docker/worker.Dockerfile").read_text()))
    assert image == {"REMAP_SIGTERM": "SIGQUIT"}, image
    with redis_server(tmp_path / "redis") as redis, \
            service(tmp_path, redis.url, image, pool=pool, VOXE_CHECKPOINT_EVERY="10",
                    VOXE_STAGE_LEASE_S="4") as svc:
        client = Client(svc)
        scene = client.upload(scene_zip)
        job = client.create_job(scene, params={**PARAMS, "iterations": EDIT_ITERATIONS})
        wait_for_event(client.http, svc, job["id"], checkpoint_at_least("edit", 10), what="an edit checkpoint")
        assert svc.stop_worker() < 30  # it did not wait for the stage
        at_stop = job_events(client.http, job["id"])
        assert at_stop[-1]["kind"] not in FINISHED, at_stop
        svc.start_worker(suffix="-b", wait_ready=False)  # under another name: Redis alone gives it the stage
        final = client.wait(job["id"])
        assert final["state"] == "succeeded", f"{final}\n{client.diagnostics()}"
        check_resumed_from_the_last_checkpoint(at_stop, job_events(client.http, job["id"]), EDIT_ITERATIONS, 10)
        verify_artifacts(client.http, final, ARTIFACTS, tmp_path)


# ---------------------------------------------------------------------------------------------- the status hot path
def test_a_job_and_its_reconstruction_load_in_one_query(db):
    """The status poll (bench/service_load.py) reads the job with its reconstruction in a single SELECT."""
    from sqlalchemy import event, update

    from voxe_service.db import get_engine, get_sessionmaker, session_scope
    from voxe_service.models import Job, Reconstruction

    job_id = add_job(add_scene(), "queued", 0)
    with session_scope() as session:
        rec = Reconstruction(scene_id=job_row(job_id).scene_id, params_key="k", params={})
        session.add(rec)
        session.flush()
        session.execute(update(Job).where(Job.id == job_id).values(reconstruction_id=rec.id))
    statements = []
    listener = lambda *args: statements.append(args[2])  # noqa: E731 - (conn, cursor, statement, ...)
    event.listen(get_engine(), "before_cursor_execute", listener)
    try:
        with get_sessionmaker()() as session:
            job = session.get(Job, job_id)
            assert job.reconstruction.params_key == "k"
    finally:
        event.remove(get_engine(), "before_cursor_execute", listener)
    assert len([s for s in statements if s.lstrip().upper().startswith("SELECT")]) == 1, statements


def test_the_sql_broker_keeps_sqlite_in_wal_mode(tmp_path):
    """Publishing (the API) never waits for a polling worker's read, and each commit is one WAL append."""
    import sqlite3

    from kombu import Connection

    from voxe_service.broker import register

    register()
    with Connection(f"sqla+sqlite:///{tmp_path / 'broker.db'}", transport_options={"polling_interval": 0.05}) as conn:
        with conn.SimpleQueue("q") as queue:
            queue.put({"n": 1})
            assert queue.get(timeout=2).payload == {"n": 1}
    with sqlite3.connect(tmp_path / "broker.db") as connection:
        assert connection.execute("PRAGMA journal_mode").fetchone()[0] == "wal"


def test_the_sql_broker_keeps_no_delivered_message_and_delivers_an_unacknowledged_one_again(tmp_path):
    """kombu's SQL transport kept every delivered message (invisible) for ever: the table grew with every stage and
    each poll scanned past them all. A delivered message's row goes; one not acknowledged when its channel closes is
    put back and delivered again; the invisible rows an earlier version left go when a process opens the broker."""
    import sqlite3
    import subprocess
    import sys

    from kombu import Connection

    from voxe_service.broker import register

    register()
    url, path = f"sqla+sqlite:///{tmp_path / 'broker.db'}", tmp_path / "broker.db"

    def rows() -> list:
        with sqlite3.connect(path) as connection:
            return connection.execute("SELECT visible, payload FROM kombu_message").fetchall()

    def consume(ack: bool) -> dict:
        with Connection(url, transport_options={"polling_interval": 0.05}) as conn, conn.SimpleQueue("q") as queue:
            message = queue.get(timeout=2)
            assert rows() == []  # delivered: not kept
            if ack:
                message.ack()
            return message.payload

    with Connection(url) as conn, conn.SimpleQueue("q") as queue:
        queue.put({"n": 1})
    assert consume(ack=False) == {"n": 1}
    assert [visible for visible, _ in rows()] == [1]  # put back as its channel closed
    assert consume(ack=True) == {"n": 1} and rows() == []
    with sqlite3.connect(path) as connection:  # rows an earlier version left delivered, beside one waiting
        queue_id = connection.execute("SELECT id FROM kombu_queue WHERE name = 'q'").fetchone()[0]
        connection.executemany("INSERT INTO kombu_message (visible, timestamp, payload, version, queue_id) "
                               "VALUES (?, datetime('now'), '{}', 1, ?)", [(0, queue_id)] * 3 + [(1, queue_id)])
    opens = f"from kombu import Connection; Connection({url!r}).default_channel.session"  # a process starting
    subprocess.run([sys.executable, "-c", f"from voxe_service.broker import register; register(); {opens}"],
                   check=True, env={**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)})
    assert rows() == [(1, "{}")]


def test_a_sweeps_job_the_reaper_ends_canceled_for_a_revoked_key_keeps_naming_the_revoke(db):
    """revoke-key flags a running sweep job canceled and its worker dies: the reaper ends it canceled naming the
    revoke (voxe_service.jobs.finish_jobs), then sends the evaluation riding in its chain alone, which wrote the
    job's message again as the reaper gave it ("canceled: ..." with nothing of the revoke), and the evaluation's
    failure quoted that."""
    from sqlalchemy import update

    from api.reaper import reap_orphaned_jobs
    from voxe_service.db import session_scope
    from voxe_service.models import ApiKey, Job, utcnow

    with session_scope() as session:
        session.add(ApiKey(id="leaving", name="leaving", revoked_at=utcnow()))
    scene = add_scene()
    add_heartbeat("dead@host", age_s=2 * db.job_stale_timeout_s)
    job_id = add_job(scene, "running", 2 * db.job_stale_timeout_s, "dead@host", "edit", completed_stages=["reconstruct"],
                     cancel_requested=True, batch_id="sweep")
    evaluation = add_job(scene, "queued", 0, mode="evaluate", batch_id="sweep", source_job_ids=[job_id])
    with session_scope() as session:
        session.execute(update(Job).where(Job.id.in_([job_id, evaluation])).values(owner_key_id="leaving"))
    assert reap_orphaned_jobs(db) == [job_id]
    row = job_row(job_id)
    assert row.state == "canceled"
    assert row.message.endswith(": its API key leaving was revoked"), row.message
    assert events_of(job_id)[-1]["detail"].endswith(": its API key leaving was revoked")
    assert job_row(evaluation).task_id is not None
