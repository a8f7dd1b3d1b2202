"""Database tables: API keys, scenes, their cached reconstructions, jobs and their events, webhook deliveries,
job artifacts, idempotency records and worker heartbeats."""

from __future__ import annotations

import uuid
from datetime import datetime, timedelta, timezone

from sqlalchemy import (
    JSON, BigInteger, Boolean, DateTime, Float, ForeignKey, Index, Integer, String, Text, TypeDecorator,
    UniqueConstraint, false,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship


def system_now() -> datetime:
    """This machine's UTC clock."""
    return datetime.now(timezone.utc)


_clock_offset = timedelta(0)


def utcnow() -> datetime:
    """The service's clock: this machine's plus its offset to the database server's (measured by
    ``voxe_service.db.sync_clock``), so the times different machines write (leases, heartbeats, progress) and
    compare (the reaper, a run taking a job over) are read on one clock. No offset until measured."""
    return system_now() + _clock_offset


def set_clock_offset(offset: timedelta) -> None:
    global _clock_offset
    _clock_offset = offset


BYTE_COUNT = BigInteger().with_variant(Integer(), "sqlite")
"""Sizes in bytes: 2 GiB uploads are allowed, past a 32-bit integer (SQLite's INTEGER is 64-bit already)."""


def new_id() -> str:
    return uuid.uuid4().hex


class UTCDateTime(TypeDecorator):
    """Timezone-aware UTC datetimes on every backend (SQLite stores them naive)."""

    impl = DateTime(timezone=True)
    cache_ok = True

    def process_bind_param(self, value, dialect):
        if value is not None and value.tzinfo is None:
            value = value.replace(tzinfo=timezone.utc)
        return value

    def process_result_value(self, value, dialect):
        if value is not None and value.tzinfo is None:
            value = value.replace(tzinfo=timezone.utc)
        return value


class Base(DeclarativeBase):
    pass


# Job states and stages (strings in the database, enumerated in the API schema).
QUEUED, RUNNING, SUCCEEDED, FAILED, CANCELED = "queued", "running", "succeeded", "failed", "canceled"
TERMINAL_STATES = (SUCCEEDED, FAILED, CANCELED)
STAGES = ("reconstruct", "edit", "refine", "export", "evaluate")
EVALUATE = "evaluate"  # the mode of an evaluation job (SPEC §4): its one stage scores other jobs' edits
# Reconstruction states.
R_PENDING, R_RUNNING, R_SUCCEEDED, R_FAILED = "pending", "running", "succeeded", "failed"
# Scene states: an upload is stored after its cheap checks, then a worker's ingest decodes (and for a mesh
# renders) it: processing -> ready, or failed with the reason.
PROCESSING, READY = "processing", "ready"
SCENE_STATES = (PROCESSING, READY, FAILED)


# The key every request acts as while authentication is off (loopback only); it has no token.
LOCAL_KEY_ID = "local"


class ApiKey(Base):
    """A client's key. Only the sha256 of the token is stored; the token is shown once, at creation.

    Tokens read ``voxe_<id>_<secret>``: the id finds the row, the hash is compared in constant time.
    Quota columns left NULL fall back to the service-wide defaults. A key past ``expires_at`` authenticates no more,
    as a revoked one, but keeps its jobs and scenes (``revoke-key`` cancels and fails them).
    """

    __tablename__ = "api_keys"

    id: Mapped[str] = mapped_column(String(32), primary_key=True)
    name: Mapped[str] = mapped_column(String(255))
    token_sha256: Mapped[str | None] = mapped_column(String(64), nullable=True)  # NULL: cannot authenticate
    max_active_jobs: Mapped[int | None] = mapped_column(Integer, nullable=True)
    max_upload_bytes: Mapped[int | None] = mapped_column(BigInteger, nullable=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    revoked_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    expires_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)  # NULL: never expires
    # Signs the key's webhook deliveries (Standard Webhooks "whsec_<base64>"); made when first needed.
    webhook_secret: Mapped[str | None] = mapped_column(String(64), nullable=True)


class Scene(Base):
    """An uploaded dataset. ``storage_key`` is its archive: the dataset a job reads once ``state`` is ready.

    ``task_id`` records that the ingest was handed to the broker; ``worker_hostname`` the worker
    running it (the reaper sends again the ingest of a scene whose worker died, as it does a job's); ``ingest_attempts``
    how many runs took it (an upload that kills its workers fails once too many were interrupted); ``ingest_token``
    and ``ingest_lease_until`` the one run that holds the ingest, as a job's ``run_token`` holds its stage.
    """

    __tablename__ = "scenes"
    # The listing's order, newest first, read off it (api/paging.py); a cursor's page seeks into it. Led by
    # owner_key_id, it is also the index of every lookup by owner (migration 0015 dropped that column's own).
    __table_args__ = (Index("ix_scenes_owner_created", "owner_key_id", "created_at", "id"),)

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    owner_key_id: Mapped[str] = mapped_column(ForeignKey("api_keys.id"))
    name: Mapped[str] = mapped_column(String(255))
    format: Mapped[str] = mapped_column(String(32))
    image_count: Mapped[int] = mapped_column(Integer)
    width: Mapped[int] = mapped_column(Integer)
    height: Mapped[int] = mapped_column(Integer)
    splits: Mapped[list] = mapped_column(JSON, default=list)
    storage_key: Mapped[str] = mapped_column(String(512))  # the validated dataset, one zip archive
    size_bytes: Mapped[int] = mapped_column(BYTE_COUNT)
    sha256: Mapped[str] = mapped_column(String(64))
    # What reconstruction backbone "auto" means for this scene ("relu_field" | "scene"), decided by its ingest from
    # all its training images; None while processing (and for scenes ingested before it was recorded).
    backbone: Mapped[str | None] = mapped_column(String(16), nullable=True)
    # What its ingest loaded the upload without (a mesh's MeshWarnings, files named as uploaded; [] for none), each a
    # ``warning`` event of stage "ingest" on every edit job of the scene: the ingest's on those waiting for it, the
    # API's on those created once it is ready. None until it is ready (and for scenes ingested before it was recorded).
    warnings: Mapped[list | None] = mapped_column(JSON, nullable=True)
    state: Mapped[str] = mapped_column(String(16), default=PROCESSING, index=True)
    # Why a failed scene failed; while processing, what stopped the ingest's last run, given back (worker.ingest)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    task_id: Mapped[str | None] = mapped_column(String(64), nullable=True)
    worker_hostname: Mapped[str | None] = mapped_column(String(255), nullable=True)
    # Runs of the ingest that took the scene: while it is processing, every earlier one was interrupted (its worker
    # process killed), and past VOXE_JOB_MAX_REQUEUES of them the next fails the scene instead of looping.
    ingest_attempts: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    # Runs of the ingest a storage outage stopped (throttling, a 5xx, the store unreachable): not counted in
    # ingest_attempts (every scene meets one alike), they double the pause before the next run's message goes back,
    # and past VOXE_STORAGE_OUTAGE_MAX_RETRIES of them the next fails the scene.
    ingest_storage_outages: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    # The one run of the ingest that holds the scene (worker.ingest): its token, its lease renewed while it runs; a
    # duplicate message waits for the lease to run out (then takes the scene over) or be renewed (then is dropped).
    ingest_token: Mapped[str | None] = mapped_column(String(32), nullable=True)
    ingest_lease_until: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    # Times the reaper sent the ingest again, no worker having taken its message for VOXE_JOB_LOST_MESSAGE_TIMEOUT_S:
    # each doubles its wait before the next, as a job's such re-sends do (api.reaper).
    lost_ingest_resends: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    updated_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)

    jobs: Mapped[list["Job"]] = relationship(back_populates="scene", passive_deletes=True)
    reconstructions: Mapped[list["Reconstruction"]] = relationship(back_populates="scene", passive_deletes=True)


class Reconstruction(Base):
    """G_i for one scene and one set of reconstruction parameters: fitted once, reused by every job.

    The unique (scene_id, params_key) constraint makes creation race-free; a worker
    claims the fit with a conditional UPDATE (state, lease), so exactly one runs it.
    """

    __tablename__ = "reconstructions"
    # Led by scene_id, its index is also that of every lookup by scene (migration 0015 dropped that column's own).
    __table_args__ = (UniqueConstraint("scene_id", "params_key", name="uq_reconstruction_scene_params"),)

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    scene_id: Mapped[str] = mapped_column(ForeignKey("scenes.id", ondelete="CASCADE"))
    params_key: Mapped[str] = mapped_column(String(64))
    params: Mapped[dict] = mapped_column(JSON)
    state: Mapped[str] = mapped_column(String(16), default=R_PENDING)
    run_count: Mapped[int] = mapped_column(Integer, default=0)  # how many times a fit was started
    owner_job_id: Mapped[str | None] = mapped_column(String(32), nullable=True)
    owner_run_token: Mapped[str | None] = mapped_column(String(32), nullable=True)  # which run of that job
    lease_until: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    iteration: Mapped[int] = mapped_column(Integer, default=0)
    total: Mapped[int] = mapped_column(Integer, default=0)
    grid_key: Mapped[str | None] = mapped_column(String(512), nullable=True)
    grid_size: Mapped[int | None] = mapped_column(BYTE_COUNT, nullable=True)
    grid_sha256: Mapped[str | None] = mapped_column(String(64), nullable=True)
    checkpoint_key: Mapped[str | None] = mapped_column(String(512), nullable=True)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    worker_hostname: Mapped[str | None] = mapped_column(String(255), nullable=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)

    scene: Mapped[Scene] = relationship(back_populates="reconstructions")


class Job(Base):
    __tablename__ = "jobs"
    # The listing's order, newest first, read off it (api/paging.py); a cursor's page seeks into it. Led by
    # owner_key_id, it is also the index of every lookup by owner (migration 0015 dropped that column's own).
    __table_args__ = (Index("ix_jobs_owner_created", "owner_key_id", "created_at", "id"),)

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    scene_id: Mapped[str] = mapped_column(ForeignKey("scenes.id", ondelete="CASCADE"), index=True)
    owner_key_id: Mapped[str] = mapped_column(ForeignKey("api_keys.id"))
    reconstruction_id: Mapped[str | None] = mapped_column(
        ForeignKey("reconstructions.id", ondelete="SET NULL"), nullable=True, index=True
    )
    prompt: Mapped[str] = mapped_column(Text)
    mode: Mapped[str] = mapped_column(String(16))
    edit_words: Mapped[list] = mapped_column(JSON, default=list)
    params: Mapped[dict] = mapped_column(JSON)
    sds_model: Mapped[str] = mapped_column(String(512))
    attention_model: Mapped[str] = mapped_column(String(512))
    device: Mapped[str] = mapped_column(String(32))

    state: Mapped[str] = mapped_column(String(16), default=QUEUED, index=True)
    stage: Mapped[str | None] = mapped_column(String(16), nullable=True)
    iteration: Mapped[int] = mapped_column(Integer, default=0)
    total: Mapped[int] = mapped_column(Integer, default=0)
    eta_seconds: Mapped[float | None] = mapped_column(Float, nullable=True)
    stage_started_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    losses: Mapped[dict] = mapped_column(JSON, default=dict)
    message: Mapped[str | None] = mapped_column(Text, nullable=True)
    error: Mapped[str | None] = mapped_column(Text, nullable=True)
    cancel_requested: Mapped[bool] = mapped_column(Boolean, default=False)
    completed_stages: Mapped[list] = mapped_column(JSON, default=list)
    reconstruction_reused: Mapped[bool | None] = mapped_column(Boolean, nullable=True)
    preview_artifact: Mapped[str | None] = mapped_column(String(255), nullable=True)
    worker_hostname: Mapped[str | None] = mapped_column(String(255), nullable=True)
    task_id: Mapped[str | None] = mapped_column(String(64), nullable=True)
    # The one run of a stage that holds the job (worker.runtime.begin_stage): its token, renewed while it runs;
    # NULL between stages. A duplicate message waits for the lease to run out or be renewed (then it is dropped).
    run_token: Mapped[str | None] = mapped_column(String(32), nullable=True)
    run_lease_until: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    # Where the job's live checkpoint is stored: under the key of the run that stored it, recorded only while that run
    # held the job (worker.runtime.StageCallbacks.on_checkpoint), so a stalled run's late upload replaces nothing.
    checkpoint_key: Mapped[str | None] = mapped_column(String(512), nullable=True)
    requeues: Mapped[int] = mapped_column(Integer, default=0)  # sent again after its worker stopped mid-stage
    # Runs of its stages a storage outage stopped (throttling, a 5xx, the store unreachable): not counted in requeues
    # (every job meets one alike), they double the pause before the next run's message goes back, and past
    # VOXE_STORAGE_OUTAGE_MAX_RETRIES of them the next fails the job.
    storage_outages: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    # Evaluation jobs (mode "evaluate"): the edit jobs scored, the metrics; sweeps: the batch a job belongs to.
    source_job_ids: Mapped[list | None] = mapped_column(JSON, nullable=True)
    result: Mapped[dict | None] = mapped_column(JSON, nullable=True)
    batch_id: Mapped[str | None] = mapped_column(String(32), nullable=True, index=True)
    # Where the job's events are POSTed (voxe_service.webhooks), and which kinds (NULL: the terminal ones).
    webhook_url: Mapped[str | None] = mapped_column(Text, nullable=True)
    webhook_events: Mapped[list | None] = mapped_column(JSON, nullable=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow, index=True)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    updated_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)

    scene: Mapped[Scene] = relationship(back_populates="jobs")
    # Joined: every job read (the status poll above all) needs it, in one query instead of two.
    reconstruction: Mapped[Reconstruction | None] = relationship(lazy="joined")
    artifacts: Mapped[list["Artifact"]] = relationship(
        back_populates="job", passive_deletes=True, order_by="Artifact.id"
    )


class JobEvent(Base):
    """A job's timeline: what happened when, written in the same transaction as the change it records.

    Kinds: ``stage_started`` / ``stage_completed`` (``stage``, the worker), ``checkpoint`` (a resumable
    checkpoint of ``stage`` at ``iteration`` is in the storage: the event is written after the upload),
    ``resumed`` (a redelivered stage went on from the checkpoint at ``iteration``), ``requeued`` (the
    remaining stages were sent again: by a restarted worker, or by the reaper after the worker died), ``warning``
    (``detail`` says what: an edit whose 3D regulariser a constant channel of the reconstruction switches off, a
    refinement whose graph cut kept none or all of the occupied voxels, or ``stage`` started over from a checkpoint it
    could not go on from), ``artifact`` / ``preview`` (``detail``: the name of an
    artifact just published, or of a new preview image), and the terminal ``succeeded`` / ``failed`` /
    ``canceled`` (``detail``: the error or message). Unlike the throttled progress columns of the job,
    every event is kept.
    """

    __tablename__ = "job_events"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"), index=True)
    kind: Mapped[str] = mapped_column(String(32))
    stage: Mapped[str | None] = mapped_column(String(16), nullable=True)
    iteration: Mapped[int | None] = mapped_column(Integer, nullable=True)
    worker_hostname: Mapped[str | None] = mapped_column(String(255), nullable=True)
    detail: Mapped[str | None] = mapped_column(Text, nullable=True)
    at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)


class WebhookDelivery(Base):
    """One job event to POST to the job's webhook: written with the event (an outbox), sent and retried by
    the API's :class:`api.webhooks.WebhookSender`.

    ``id`` is the Standard Webhooks ``webhook-id``, equal across retries so receivers can dedupe;
    ``payload`` is the exact body, fixed at creation, so every attempt sends the same bytes; ``origin`` is the
    receiver ``url`` goes to (``voxe_service.webhooks.webhook_origin``), which the sender's cap counts by (a claim reads
    the earliest due off the index on state and due time, each receiver's earliest off the one with origin too).
    States: ``pending`` (due at ``next_attempt_at``), ``delivered`` (a 2xx), ``failed`` (gave up).
    """

    __tablename__ = "webhook_deliveries"
    # The unique (job_id, event_id), led by job_id, is also the index of every lookup by job (0015 dropped its own).
    __table_args__ = (UniqueConstraint("job_id", "event_id", name="uq_webhook_delivery_event"),
                      Index("ix_webhook_deliveries_state_due", "state", "next_attempt_at"),
                      Index("ix_webhook_deliveries_state_origin_due", "state", "origin", "next_attempt_at"))

    id: Mapped[str] = mapped_column(String(40), primary_key=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"))
    event_id: Mapped[int] = mapped_column(Integer)
    event_type: Mapped[str] = mapped_column(String(40))
    url: Mapped[str] = mapped_column(Text)
    origin: Mapped[str] = mapped_column(Text, server_default="")
    payload: Mapped[str] = mapped_column(Text)
    state: Mapped[str] = mapped_column(String(16), default="pending")
    attempts: Mapped[int] = mapped_column(Integer, default=0)
    next_attempt_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)
    last_status: Mapped[int | None] = mapped_column(Integer, nullable=True)
    last_error: Mapped[str | None] = mapped_column(Text, nullable=True)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    delivered_at: Mapped[datetime | None] = mapped_column(UTCDateTime, nullable=True)


class Artifact(Base):
    __tablename__ = "artifacts"
    # Led by job_id, its index is also that of every lookup by job (migration 0015 dropped that column's own).
    __table_args__ = (UniqueConstraint("job_id", "name", name="uq_artifact_job_name"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    job_id: Mapped[str] = mapped_column(ForeignKey("jobs.id", ondelete="CASCADE"))
    name: Mapped[str] = mapped_column(String(255))
    key: Mapped[str] = mapped_column(String(512))
    size: Mapped[int] = mapped_column(BYTE_COUNT)
    content_type: Mapped[str] = mapped_column(String(128))
    sha256: Mapped[str] = mapped_column(String(64))
    kind: Mapped[str] = mapped_column(String(32))
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)

    job: Mapped[Job] = relationship(back_populates="artifacts")


class IdempotencyRecord(Base):
    """The resource a request with an ``Idempotency-Key`` created, so a retry returns it instead of a twin.

    Unique per (key owner, endpoint, Idempotency-Key); ``request_sha256`` tells a retry from a
    different request reusing the same Idempotency-Key. ``pending`` until that request has answered: the broker
    may still refuse what it created, and the 503 then withdraws it with this record (``api.auth.Idempotency``).
    """

    __tablename__ = "idempotency_records"
    __table_args__ = (UniqueConstraint("owner_key_id", "endpoint", "idempotency_key", name="uq_idempotency"),)

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    owner_key_id: Mapped[str] = mapped_column(ForeignKey("api_keys.id"))
    endpoint: Mapped[str] = mapped_column(String(32))  # "scenes", "jobs", "evaluations" or "sweeps"
    idempotency_key: Mapped[str] = mapped_column(String(255))
    request_sha256: Mapped[str] = mapped_column(String(64))
    resource_id: Mapped[str] = mapped_column(String(32))
    pending: Mapped[bool] = mapped_column(Boolean, default=False, server_default=false())
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)


class WorkerHeartbeat(Base):
    """Workers write here every few seconds; readiness uses it where the broker cannot broadcast a ping."""

    __tablename__ = "worker_heartbeats"

    hostname: Mapped[str] = mapped_column(String(255), primary_key=True)
    pid: Mapped[int] = mapped_column(Integer)
    queues: Mapped[str] = mapped_column(String(255))
    device: Mapped[str] = mapped_column(String(64))
    # role -> {"model", "present"} as voxe_service.model_inventory.check_models found them at the worker's start
    models: Mapped[dict | None] = mapped_column(JSON, nullable=True)
    started_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    last_seen: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
