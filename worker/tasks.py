"""Celery tasks: one per stage of a job, chained reconstruct -> edit -> [refine] -> export, and the ingest
of an upload (``worker/ingest.py``). Task names and messages are the contract of ``voxe_service.queue``.

Each task takes only the job id. It reads the job record, downloads its inputs
from the storage, calls the ``voxe_core`` stage with callbacks that write
progress into the job record (throttled) and poll the job's cancel flag, uploads
what the stage produced, and records it. A stage already recorded as done (a
redelivered message) or a job already finished is skipped, so the chain is
safe to redeliver; a message for a job another live run holds (a duplicate) is
dropped (``runtime.begin_stage``); long stages checkpoint every
``VOXE_CHECKPOINT_EVERY`` iterations into the storage and resume from there.

The reconstruction is shared: every job on the same scene with the same
reconstruction parameters points at one ``reconstructions`` row. The first
task to claim it (a conditional UPDATE) fits it; the others wait for it, and
take it over when the fitter's lease lapses (a dead worker) or it was released
(the fitting job was canceled, ran out of time, or lost the database).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import logging
import os
import socket
import threading
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn

from celery import signals
from celery.exceptions import Ignore, Reject, SoftTimeLimitExceeded
from sqlalchemy import select, update
from sqlalchemy.exc import SQLAlchemyError

from voxe_core.guidance.loading import is_out_of_memory
from voxe_core.presets import edit_config, export_config, fit_backbone, fit_setup, reconstruct_config, refine_config
from voxe_core.progress import Callbacks, Progress, StageCancelled
from voxe_service.broker import waiting_tasks
from voxe_service.db import database_outage, sync_clock
from voxe_service.failing import FailingStreak
from voxe_service.models import (
    CANCELED, EVALUATE, FAILED, PROCESSING, QUEUED, R_FAILED, R_PENDING, R_SUCCEEDED, RUNNING, TERMINAL_STATES, Job,
    Scene, WorkerHeartbeat, utcnow,
)
from voxe_service.model_inventory import (ROLES, check_models, how_to_repair, job_models, missing_message,
                                          model_present, submission_note)
from voxe_service.progress import device_costs, refine_phase_seconds
from voxe_service.queue import (
    INGEST_TASK, QUEUE_UNAVAILABLE, STAGE_TASKS, QueueUnavailable, TaskResult, get_queue, is_sql_broker, job_stages,
    requeue_interrupted, reset_queue, send_evaluations_alone, send_ingest_again, send_queued_again,
)
from voxe_service.settings import get_settings, model_label
from voxe_service.storage import (ObjectNotFound, StorageError, StoredObject, get_storage, job_key,
                                  reconstruction_storage_key)
from worker import runtime
from worker.celery_app import app
from worker.evaluation import EvaluationFailed, run_evaluation
from worker.ingest import ingest_scene, load_stored_mesh_telling
from worker.inputs import fetch_grid, job_scene, load_images, recorded_initial_grid
from worker.runtime import JobSkipped, StageCallbacks, StageCarriedOn, StageHeld

if TYPE_CHECKING:
    import torch

    from voxe_core.edit import EditConfig

log = logging.getLogger("voxe.worker")

PREVIEW = "preview.png"
PREVIEW_SIZE = 128


class ReconstructionFailed(RuntimeError):
    pass


# --------------------------------------------------------------------------- the common frame
DATABASE_RETRY_S = (0.5, 1.0, 2.0, 4.0)
"""Pauses between tries to take a job, or to record its stage done, when the database fails (a lock, a dropped
connection), before the message goes back to the broker."""


def _retried(call, job_id: str, what: str):
    """``call(again)``, tried again after each pause of ``DATABASE_RETRY_S`` while it raises a database error
    (``again``: a try before raised, and its commit may have landed with its answer lost); the last try's error
    raises."""
    for tries, pause in enumerate(DATABASE_RETRY_S):
        try:
            return call(tries > 0)
        except SQLAlchemyError as exc:
            log.warning("job %s: %s (%s); trying again in %.1f s", job_id, what, exc, pause)
            time.sleep(pause)
    return call(True)


def _begin_stage(task, job_id: str, stage: str, device: str, settings):
    """``runtime.begin_stage``, tried again on a database error; still failing, the message is rejected back to the
    queue (``Reject``): acknowledged with a failure it was gone, and the job, accepted, never ran or ended. Such a
    return counts as a re-queue, up to the limit, where the job fails naming why (``runtime.count_unstarted``),
    unless the database was down or locked (an outage must not fail accepted jobs)."""
    hostname = task.request.hostname or socket.gethostname()
    run_token = uuid.uuid4().hex  # one for every try: a try that took the job, its answer lost, is found by it
    try:
        return _retried(lambda _again: runtime.begin_stage(job_id, stage, hostname, device, settings, run_token),
                        job_id, f"{stage} could not start")
    except JobSkipped:
        raise
    except Exception as exc:  # noqa: BLE001 - a cold shutdown raises in the task wherever it waits
        _requeue_if_shut_down(job_id, stage, run_token, exc)  # (a try that took the job, its answer lost: released)
        if not isinstance(exc, SQLAlchemyError):
            raise
        # the driver's words (database is locked, value too long), not the statement and its parameters
        reason = f"{stage} could not start: {runtime.failure_text(exc)}"
        error = None
        with contextlib.suppress(SQLAlchemyError):  # a try that took the job, its answer lost: its hold, unrenewed,
            runtime.release_stage(job_id, run_token)  # had held the redelivery off for the lease (then counted)
        if database_outage(exc) is None:  # down or locked: an outage counts nothing
            with contextlib.suppress(SQLAlchemyError):  # the database went down meanwhile: nothing counted
                error = runtime.count_unstarted(job_id, stage, reason, settings)
        if error:
            log.error("job %s failed: %s", job_id, error)
            raise JobSkipped(f"job {job_id} failed: {error}") from exc
        log.error("job %s: %s could not start (%s); the message goes back to the queue", job_id, stage, exc)
        raise Reject(f"{stage} of job {job_id} could not start: {exc}", requeue=True) from exc


def _run_stage(task, job_id: str, stage: str, body, final: bool = False) -> TaskResult:
    """Run ``body(job, settings, device, storage)`` as one run of ``stage``; what a final stage's body returns is the
    succeeded job's message (None: no word)."""
    settings = get_settings()
    device = settings.resolved_device
    try:
        job = _begin_stage(task, job_id, stage, device, settings)
    except (StageHeld, StageCarriedOn) as held:  # a duplicate message: acknowledged, its chain not continued
        log.info("%s: dropped: %s", stage, held)
        raise Ignore() from None
    except JobSkipped as skipped:
        log.info("%s: skipped: %s", stage, skipped)
        if runtime.has_ended(job_id):  # canceled (or ended) before this stage: nothing resumes it, so nothing is kept
            _cleanup(job_id, settings)
        return {"job_id": job_id, "stage": stage, "skipped": str(skipped)}
    log.info("job %s: %s started on %s", job_id, stage, device)
    token = job.run_token
    try:
        with runtime.holding_job(job_id, token, settings):
            if stage == job_stages(job.mode)[0]:
                _check_job_can_start(job, settings)
            note = body(job, settings, device, get_storage(settings))
        completed = _retried(lambda again: runtime.complete_stage(job_id, stage, token, final=final, again=again,
                                                                  message=note),
                             job_id, f"{stage} could not be recorded done")
    except runtime.RunSuperseded as superseded:
        log.warning("job %s: %s: %s", job_id, stage, superseded)
        _stop_if_taken_over(job_id, stage)
        return {"job_id": job_id, "stage": stage, "skipped": str(superseded)}
    except StageCancelled:
        return _end_job(job_id, stage, token, CANCELED, settings, message=f"canceled during {stage}")
    except SoftTimeLimitExceeded:
        return _end_job(job_id, stage, token, FAILED, settings,
                        error=f"{stage}: time limit of {settings.task_soft_time_limit_s} s exceeded")
    except Exception as exc:  # noqa: BLE001 - every failure ends the job with its message, but these: ...
        _requeue_if_shut_down(job_id, stage, token, exc)  # ... the one a cold shutdown raises in the task ...
        if (why := database_outage(exc)) is not None:  # ... a database outage, no fault of the job's ...
            return _give_back_and_requeue(job_id, stage, token, f"{stage} stopped by a database outage ({why}): "
                                          f"{runtime.failure_text(exc)}", f"a database outage ({why})", exc, settings)
        if (cause := runtime.storage_or_disk_outage(exc)) is not None:  # ... nor a storage's or a full disk's
            # (a full disk: the job's scratch, its grids and local checkpoint, went towards filling it, and goes as
            # the job is given back, while this run holds it; its stored checkpoints stay. A storage outage, which
            # every job meets alike, does not count towards the limit but towards its own; its pause grows with the
            # earlier ones)
            full = runtime.disk_full(exc)
            runs_before = job.requeues + (0 if full else job.storage_outages)
            return _give_back_and_requeue(job_id, stage, token, f"{stage} stopped by {cause}", cause, exc, settings,
                                          pause_after=runs_before, free_scratch=full, storage_outage=not full)
        log.exception("job %s: %s failed", job_id, stage)
        return _end_job(job_id, stage, token, FAILED, settings, error=_error_message(stage, exc, job))
    except BaseException:  # the worker going down: its redelivered message takes the job at once (the database
        with contextlib.suppress(SQLAlchemyError):  # refusing: once the hold runs out), and the worker goes down
            runtime.release_stage(job_id, token)
        raise
    if not completed:
        _stop_if_taken_over(job_id, stage)
        return {"job_id": job_id, "stage": stage, "skipped": f"job {job_id} ended during {stage}"}
    if final:
        _cleanup(job_id, settings)
    log.info("job %s: %s done", job_id, stage)
    return {"job_id": job_id, "stage": stage, "state": "done"}


def _end_job(job_id: str, stage: str, run_token: str, state: str, settings, message: str | None = None,
             error: str | None = None) -> TaskResult:
    """End the job in ``state`` (canceled with ``message``, failed with ``error``) while this run holds it, tried
    again while the database refuses. Still refused in an outage, the message goes back to the queue for its
    redelivery to end the job: a cancel its start finds (the hold released, nothing counted); a failure by running
    the stage again from its checkpoint, to meet it again or not (the hold given back as a counted re-queue naming
    the error, which fails the job at the limit): an accepted job ends with its result or its own error, never with
    an outage's, and never stays running until the reaper finds it."""
    try:
        ended = _retried(lambda _again: runtime.finish_job(job_id, state, message=message, error=error,
                                                           run_token=run_token, settings=settings),
                         job_id, f"{stage} could not record the job {state}")
    except Exception as exc:  # noqa: BLE001 - a cold shutdown raises in the task while its tries wait
        _requeue_if_shut_down(job_id, stage, run_token, exc)
        if not isinstance(exc, SQLAlchemyError) or (why := database_outage(exc)) is None:
            raise
        cause = f"a database outage ({why}) that kept its end from being recorded ({state}: {error or message})"
        if state == CANCELED:
            _release_and_requeue(job_id, stage, run_token, cause, exc)
        return _give_back_and_requeue(job_id, stage, run_token, f"{stage} failed, and a database outage ({why}) "
                                      f"kept that from being recorded: {error}", cause, exc, settings)
    if error and ended:  # recorded by this run (a re-queued failure is not, yet: it may end otherwise)
        log.error("job %s failed: %s", job_id, error)
    return _ended(job_id, stage, state, ended, settings)


def _requeue_if_shut_down(job_id: str, stage: str, run_token: str, exc: Exception) -> None:
    """When ``exc`` is what a cold shutdown raises in a solo pool's task (wherever it is: in the stage, or waiting to
    try the database again at its start or end), release the run's hold and send the message back to the queue:
    no failure of the job's. Raised through, it had acknowledged the message as failed, the job left held."""
    if runtime.worker_in_cold_shutdown():
        _release_and_requeue(job_id, stage, run_token, "the worker's shutdown", exc)


def _release_and_requeue(job_id: str, stage: str, run_token: str, cause: str, exc: Exception) -> NoReturn:
    """Release the run's hold, uncounted, so that the redelivery takes the job at once (refused, the hold runs out
    and the redelivery takes over then), and reject the message back to the queue."""
    with contextlib.suppress(SQLAlchemyError):
        runtime.release_stage(job_id, run_token)
    _requeue(job_id, stage, cause, exc)


def _give_back_and_requeue(job_id: str, stage: str, run_token: str, reason: str, cause: str, exc: Exception,
                           settings, pause_after: int | None = None, free_scratch: bool = False,
                           storage_outage: bool = False) -> TaskResult:
    """Give the run's hold back as a counted re-queue naming ``reason`` (``storage_outage``: counted in the job's
    storage outages instead) and reject the message back to the queue (``cause``); at the limit the job fails
    instead, and the task ends with it. ``pause_after``: the job's runs before this one that were given back
    (counted, or stopped by a storage outage), after which a storage outage or a full disk pauses as an ingest's does
    (``runtime.pause_after_outage``), the hold given back meanwhile: a storage down for a while is not met again at
    once, and a worker whose disk is full takes no job in the pause, while the job's checkpoints are kept for the
    worker its message goes to next. ``free_scratch``: the job's scratch folder goes with the hold
    (``runtime.give_back_stage``), left when the hold is no longer this run's."""
    if error := _give_back(job_id, stage, run_token, reason, settings, free_scratch, storage_outage):
        log.error("job %s failed: %s", job_id, error)
        return _ended(job_id, stage, FAILED, True, settings)
    if pause_after is not None:
        runtime.pause_after_outage(pause_after)
    _requeue(job_id, stage, cause, exc)


def _give_back(job_id: str, stage: str, run_token: str, reason: str, settings, free_scratch: bool = False,
               storage_outage: bool = False) -> str | None:
    """``runtime.give_back_stage`` (a counted re-queue, or storage outage; at the limit the job fails, and why is
    returned), tried again while the database refuses; still refused, the hold runs out unrenewed and the
    redelivery takes the job over then, counting it as it counts any lapsed hold."""
    try:
        return _retried(lambda _again: runtime.give_back_stage(job_id, stage, run_token, reason, settings,
                                                               free_scratch, storage_outage), job_id,
                        f"{stage} could not give the job back")
    except Exception as exc:  # noqa: BLE001 - a cold shutdown raises in the task while its tries wait
        _requeue_if_shut_down(job_id, stage, run_token, exc)
        if not isinstance(exc, SQLAlchemyError):
            raise
        return None


def _requeue(job_id: str, stage: str, cause: str, exc: Exception) -> NoReturn:
    """Reject the message back to the queue: its redelivery resumes the stage from its stored checkpoint."""
    log.warning("job %s: %s stopped by %s; its message goes back to the queue", job_id, stage, cause)
    raise Reject(f"{stage} of job {job_id} stopped by {cause}", requeue=True) from exc


def _ended(job_id: str, stage: str, state: str, ended: bool, settings) -> TaskResult:
    """After the stage ended the job in ``state`` (``ended``: this run's update took effect), or found it ended
    meanwhile, its scratch and checkpoints go."""
    if not ended:
        _stop_if_taken_over(job_id, stage)
    _cleanup(job_id, settings)
    return {"job_id": job_id, "stage": stage, "state": state}


def _stop_if_taken_over(job_id: str, stage: str) -> None:
    """A run that stalled past its lease, while another run took the unfinished job over, drops its outcome and
    stops its chain (``Ignore``), leaving the job, its scratch and checkpoints to that run."""
    if not runtime.has_ended(job_id):
        log.warning("job %s: another run took the job over while this %s stalled; its outcome is dropped",
                    job_id, stage)
        raise Ignore()


class CannotStart(RuntimeError):
    """The job cannot run (found at the start of its chain, before its fit): a model it needs is not on this worker
    or cannot be read there (the message says how to add it), or its prompt is longer than its model reads."""


def _check_job_can_start(job: Job, settings) -> None:
    """Fail before the chain's first stage runs when a model the job will load is not here (no weights read), when
    the tokenizer or text encoder config of a model it prompts (the edit's SDS model, a local edit's attention
    model) cannot be read (a damaged model), or when that tokenizer reads its prompt as longer than that model's
    text encoder does (the API's check is a lower bound: BPE splits some words into several tokens, and a model may
    read fewer than 77), or when that attention model's tokenizer does not find an edit word where the refinement
    will look for it (the API reads the prompt as the tokenizer should, which it may not)."""
    from voxe_core.guidance.loading import load_clip_tokenizer, loading_errors
    from voxe_core.guidance.prompts import check_edit_words_tokens, check_prompt_tokens, tokens_read

    needed = job_models(job.mode, job.sds_model, job.attention_model, job.params or {})
    missing = [missing_message(role, model, "this worker")
               for role, model in needed.items() if not model_present(ROLES[role], model, settings)]
    if missing:
        raise CannotStart("; ".join(missing))
    from transformers import CLIPTextConfig

    # The refinement prompts its attention model as the edit prompts its SDS model: with the SDS model's count
    # alone, a prompt longer than the attention model reads had failed at the refinement, after the whole edit.
    for role in ("sds", "attention"):
        if role not in needed:
            continue
        model = runtime.resolve_model(needed[role], settings)
        try:
            tokenizer = load_clip_tokenizer(model, subfolder="tokenizer", local_files_only=True)
            positions = CLIPTextConfig.from_pretrained(model, subfolder="text_encoder",
                                                       local_files_only=True).max_position_embeddings
        except loading_errors() as exc:  # a damaged model (vocab.json cut short) had failed only at its stage's load
            raise CannotStart(f"the {role} model {model_label(needed[role])!r} on this worker cannot be read "
                              f"({runtime.failure_text(exc)}): {how_to_repair(role, model)}") from None
        view_words = (job.params or {}).get("view_words", True)
        try:
            check_prompt_tokens(job.prompt, tokenizer, tokens_read(tokenizer, positions), view_words)
            if role == "attention":  # where the API's offline reading and the tokenizer disagree ("<|endoftext|>")
                check_edit_words_tokens(job.prompt, job.edit_words, tokenizer, view_words)
        except ValueError as exc:
            raise CannotStart(f"{exc} (the {role} model {needed[role]!r})") from None


def _error_message(stage: str, exc: Exception, job: Job) -> str:
    from voxe_core.guidance.loading import ModelNotAvailableError

    if isinstance(exc, ModelNotAvailableError):  # from the edit's SDS model or the refinement's attention model
        text = str(exc).rstrip()
        role = "attention" if stage == "refine" else "sds"
        return f"{stage}: {text}{'' if text.endswith('.') else '.'} {submission_note(role)}."
    if isinstance(exc, CannotStart):
        return f"{stage}: not started: {exc}"
    if isinstance(exc, (ReconstructionFailed, EvaluationFailed)):
        return str(exc)
    return f"{stage}: {runtime.failure_text(exc)}"


def _cleanup(job_id: str, settings) -> None:
    runtime.cleanup_scratch(job_id, settings)
    get_storage(settings).discard_prefixes(job_key(job_id, "checkpoints/"))


def _preview(job: Job, grid, settings, storage, device: str, image=None, centre=None) -> None:
    """Render (or take) a small front view, looking at ``centre`` (G_i's orbit centre), and publish it as preview.png
    (named the job's preview while its run still holds it)."""
    from voxe_core.export import render_views, save_png, turntable_cameras

    path = runtime.scratch_dir(job.id, settings) / PREVIEW
    if image is None:
        image = render_views(grid, turntable_cameras(1, 20.0, PREVIEW_SIZE, centre=centre), device=device)[0]
    save_png(path, image)
    runtime.publish_artifact(job.id, PREVIEW, path, "preview", storage)
    runtime.update_job(job.id, held_by=job.run_token, preview_artifact=PREVIEW)


def _stored_checkpoint(storage, key: str, path: Path, kind: str, max_version: int, config,
                       forget: Callable[[str], None]) -> tuple[Path | None, dict | None, str | None]:
    """The checkpoint of ``kind`` stored at ``key``, fetched to ``path``, and its header; or (None, None, why), the
    object deleted, its record cleared first (``forget(key)``), for one the stage cannot go on from: unreadable, or
    made with another recipe than ``config``'s (a worker of another version, mid rolling upgrade: the stage refuses
    it). Either would fail every redelivery, so the stage starts over instead. Only the header is read (the stage
    reads the tensors as it resumes): it names a truncated or padded file as unreadable as a whole read does.
    (None, None, None), logged, when the object is gone by the time it is fetched (deleted since it was found stored,
    by hand or a bucket's lifecycle rule): as one recorded and never stored (``_recorded_checkpoint_stored``), the
    stage starts from the start, where that had failed it."""
    from voxe_core.tensorio import FormatError, load_header, recipe_changes

    try:
        resume = storage.get_file(key, path)
    except ObjectNotFound:
        log.info("the checkpoint %s was deleted from the storage as it was fetched; starting from the start", key)
        return None, None, None
    try:
        meta = load_header(resume, kind, max_version)
        changed = recipe_changes(resume, meta, config)
    except FormatError as exc:
        why = f"was unreadable ({exc})"
    else:
        if not changed:
            return resume, meta, None
        why = f"was made with another recipe ({', '.join(changed)}: a worker of another version)"
    forget(key)
    storage.discard(key)  # (a cleanup once no record names it: a storage refusing it fails nothing)
    return None, None, why


# --------------------------------------------------------------------------- reconstruct
def _reconstruct(job: Job, settings, device: str, storage) -> None:
    rec_id = job.reconstruction_id
    if rec_id is None:
        raise RuntimeError("job has no reconstruction record")
    callbacks = StageCallbacks(job, "reconstruct", settings)
    first = True
    ran_here = waiting = refitted = False
    while True:
        rec = runtime.load_reconstruction(rec_id)
        if rec is None:
            raise RuntimeError(f"reconstruction {rec_id} was deleted")
        if rec.state == R_SUCCEEDED:
            try:
                grid_path = _grid_file(job.id, rec, settings, storage)  # fetched and checked against the record once
                break
            except StorageError as exc:
                if refitted or not isinstance(exc.__cause__, ObjectNotFound):
                    raise
            # Its grid deleted from the storage (by hand, a bucket's lifecycle rule): fitted again, where every later
            # job of the scene with these parameters had failed on it for good. Said only by the job that set it back:
            # one that another job's refit beat waits for or reuses that one's fit, as any other job does.
            refitted = True
            if runtime.refit_lost_grid(rec.id, rec.grid_key):
                callbacks.on_warning("reconstruct", f"the scene's reconstruction {rec.id} had its grid {rec.grid_key} "
                                                    "deleted from the storage: fitting it again")
            continue
        claimed_at = time.monotonic()  # the lease runs out lease_s after the claim at the latest
        if runtime.try_claim_reconstruction(rec_id, job.id, job.worker_hostname, settings, allow_failed=first,
                                            run_token=job.run_token):
            try:
                _fit(job, runtime.load_reconstruction(rec_id), settings, storage, device, claimed_at)
                ran_here = True
            except runtime.LeaseLost as exc:  # another job holds the fit now: wait for it, as for any other
                log.warning("job %s: %s", job.id, exc)
            first = False
            continue
        if rec.state == R_FAILED:  # as read before the claim, which may have lost to a job now re-running it
            rec = runtime.load_reconstruction(rec_id) or rec
            if rec.state == R_FAILED:
                raise ReconstructionFailed(f"reconstruct: the scene's reconstruction failed: {rec.error}")
        first = False
        if not waiting and rec.params.get("route") != "voxelize":  # the fit it waits for, weighed as the owner's
            backbone = fit_backbone(rec.params, job_scene(job).backbone)
            if backbone != "auto":
                _record_fit(job, backbone, reconstruct_config(rec.params, backbone=backbone), settings)
        waiting = True
        owner = f" (fitted by job {rec.owner_job_id})" if rec.owner_job_id else ""
        runtime.update_job(job.id, held_by=job.run_token, iteration=rec.iteration, total=rec.total,
                           message=f"waiting for the scene's reconstruction {rec.id}{owner}")
        if callbacks.should_cancel():
            raise StageCancelled("reconstruct canceled while waiting")
        time.sleep(min(1.0, settings.reconstruction_lease_s / 4))

    reused = not ran_here and rec.owner_job_id != job.id
    runtime.update_job(job.id, held_by=job.run_token, reconstruction_reused=reused, iteration=rec.total,
                       total=rec.total, message="reused the scene's reconstruction" if reused else None)
    from voxe_core.backbones import load_grid

    runtime.publish_artifact(job.id, "initial_grid.safetensors", grid_path, "grid", storage, key=rec.grid_key)
    initial = load_grid(grid_path)
    _record_edit_schedule(job, initial.kind, settings)
    _preview(job, initial, settings, storage, device, centre=_record_orbit_centre(job.id, initial))


def _record_fit(job: Job, backbone: str, config, settings) -> None:
    """The fit the job runs or waits for and the edit it leads to, kept in the job's result (one write) for progress
    to weigh them by (``voxe_service.progress.FitWork``): a capture's fit steps cost more than an object's, and its
    edit runs SPEC §5's count."""
    runtime.merge_job_result(job.id, {"fit": {"backbone": backbone, "steps": config.total_iterations,
                                              "rays_per_step": config.rays_per_step},
                                      "edit_schedule": _edit_schedule(job, backbone, settings)[1]})


def _record_edit_schedule(job: Job, kind: str, settings) -> "EditConfig":
    """The edit's config for a G_i of ``kind``, its schedule kept in the job's result from the moment the kind is
    known (the fit's start, or the end of reconstruct for a finished fit reused), so that progress weighs the
    edit by the count it will run (a capture's scene grid: SPEC §5's 5,000 where the parameters say 8,000) before
    it starts."""
    config, schedule = _edit_schedule(job, kind, settings)
    runtime.merge_job_result(job.id, {"edit_schedule": schedule})
    return config


def _edit_schedule(job: Job, kind: str, settings) -> tuple["EditConfig", dict]:
    """The edit's config for a G_i of ``kind`` (its renders marched as this worker's ``fused_marcher`` says) and its
    schedule as the job's result keeps it."""
    config = edit_config(job.params, kind, settings.checkpoint_every)
    config.render.fused = settings.fused_marcher
    return config, {"backbone": kind, "iterations": config.iterations, "i_start": config.schedule.i_start,
                    "every": config.schedule.every, "floor": config.schedule.floor}


def _record_orbit_centre(job_id: str, initial) -> "torch.Tensor":
    """G_i's ``orbit_centre()``, kept in the job's result (float32 -> float is exact) so that later stages, on
    whichever worker, read the very same point without fetching G_i."""
    centre = initial.orbit_centre()
    runtime.merge_job_result(job_id, {"orbit_centre": [float(c) for c in centre]})
    return centre


def _orbit_centre(job: Job, settings, storage) -> "torch.Tensor":
    """G_i's ``orbit_centre()`` for the export's renders and turntable: the point every stage's views of a job look
    at (the edit's poses and the refinement's overlay take it from G_i, which they load anyway). Read from the
    job's result, where its reconstruct stage put it; G_i is fetched only for a job reconstructed before it did."""
    import torch

    stored = (job.result or {}).get("orbit_centre")
    if stored is not None:
        return torch.tensor(stored, dtype=torch.float32)
    rec = runtime.load_reconstruction(job.reconstruction_id)
    initial = fetch_grid(job.id, "initial_grid.safetensors", settings, storage, recorded_initial_grid(job.id, rec))
    return _record_orbit_centre(job.id, initial)


def _grid_file(job_id: str, rec, settings, storage) -> Path:
    return runtime.fetch(storage, runtime.reconstruction_grid(rec),
                         runtime.scratch_dir(job_id, settings) / "initial_grid.safetensors")


def _voxelize(job: Job, rec, settings, storage):
    """Route (b): the mesh scene's uploaded mesh written straight into G_i at the reconstruction's final resolution.
    What the mesh loads without is a ``warning`` event of the stage, as the ingest's are (it had been said in the
    worker's log alone), unless the scene's kept warnings told the job already (at its creation, or its ingest's end):
    a scene ingested before they were kept (migration 0022) tells none. Those said before a load that fails too (as a
    failed ingest keeps its: they may be why)."""
    from voxe_core.mesh_input import VoxelizeConfig, voxelize

    scene, loaded_without = job_scene(job), []
    try:
        with runtime.scene_dataset(scene, settings, storage) as dataset:
            mesh = load_stored_mesh_telling(dataset, loaded_without)
    finally:
        for text in loaded_without:
            if text not in (scene.warnings or ()):
                runtime.record_warning(job.id, "reconstruct", text)
    config = reconstruct_config(rec.params, settings.checkpoint_every)
    return voxelize(mesh, VoxelizeConfig(resolution=config.resolutions[-1], bbox_min=config.bbox_min,
                                         bbox_max=config.bbox_max, seed=rec.params["seed"]))


NOT_THE_FITS_FAILURE = (StageCancelled, runtime.LeaseLost, runtime.RunSuperseded, SoftTimeLimitExceeded)
"""What stops an owner's fit without failing it (and every job waiting on it): its job canceled, its lease or job
taken over, its task's time limit (a job's, which fails the owner's job alone); so do a database outage
(``voxe_service.db.database_outage``), the storage out of reach or the worker's disk full
(``runtime.storage_or_disk_outage``) and its worker out of memory (``is_out_of_memory``: its machine's fault, as
when the OOM killer ends its process and a waiting job takes the lapsed lease over; handed back saying so:
``runtime.hand_back_fit``)."""


def _fit(job: Job, rec, settings, storage, device: str, claimed_at: float) -> None:
    """Make G_i for ``rec`` (claimed by this job at ``time.monotonic()`` ``claimed_at``): voxelize its mesh, or fit,
    resuming from a stored checkpoint."""
    scratch = runtime.scratch_dir(job.id, settings)
    checkpoint = scratch / "reconstruction_checkpoint.safetensors"

    with runtime.fit_lease(rec.id, job.id, settings, job.run_token, claimed_at) as lease:
        def on_checkpoint(path: str, iteration: int) -> None:
            lease.check()
            _store_fit_checkpoint(job, rec.id, storage, path, iteration)

        def on_progress(report: Progress) -> None:
            lease.renew(iteration=report.iteration, total=report.total)
            lease.check()

        callbacks = StageCallbacks(job, "reconstruct", settings, on_progress, on_checkpoint)
        grid = grid_key = None
        try:
            if rec.params.get("route") == "voxelize":  # one step: reported once, at completion
                from voxe_core.devices import PeakMemory

                # with its peak memory, as a fit reports it: a mesh job's result.peak_memory_gb had no reconstruct
                memory = PeakMemory(device).start()
                grid, total = _voxelize(job, rec, settings, storage), 1
                callbacks.on_progress(Progress("reconstruct", total, total, info=memory.info()))
            else:
                grid, total = _fit_grid(job, rec, settings, storage, lease, callbacks, checkpoint, device)
            lease.check()
            path = scratch / "initial_grid.safetensors"
            grid.save(path)
            # Under this run's own name: a run that lost the fit meanwhile never overwrites the recorded grid.
            grid_key = reconstruction_storage_key(rec.id, f"grid-{job.run_token or job.id}.safetensors")
            stored: StoredObject = storage.put_file(grid_key, path)
            done = runtime.set_reconstruction(
                rec.id, job.id, job.run_token, state=R_SUCCEEDED, grid_key=stored.key, grid_size=stored.size,
                grid_sha256=stored.sha256, iteration=total, total=total, lease_until=None, finished_at=utcnow(),
                checkpoint_key=None,  # (none is resumed from any more; every run's goes below)
            )
        except BaseException as exc:  # (each change below applies only while this job still owns the fit)
            outage, out_of_memory, failure = _outage(exc), is_out_of_memory(exc), runtime.failure_text(exc)
            fails_the_job = (isinstance(exc, Exception) and not isinstance(exc, NOT_THE_FITS_FAILURE)
                             and outage is None and not runtime.worker_in_cold_shutdown())
            # Listed while this run owns the fit, so none is a later owner's: should the fit end failed, no grid is its
            # own, and these go (an earlier run's whose record an outage refused had stayed for good)
            strays = _stored(storage, rec.id, "grid-") if fails_the_job or out_of_memory else []

            def hand_back(_again: bool) -> str | bool | None:
                if fails_the_job and grid is None and not out_of_memory:
                    return runtime.set_reconstruction(rec.id, job.id, job.run_token, state=R_FAILED, lease_until=None,
                                                      finished_at=utcnow(), error=failure) and R_FAILED
                if out_of_memory or fails_the_job:  # out of memory, or G_i made and not kept (a storage refusing
                    # it): no failure of the fit's; the error recorded, a job still waiting takes over
                    said = "" if grid is None else "its grid could not be stored: "
                    return runtime.hand_back_fit(rec.id, job.id, job.run_token, f"job {job.id}'s fit: {said}{failure}")
                # Stopped for the owner's sake (NOT_THE_FITS_FAILURE), an outage, a full disk, or the worker going down
                # (SystemExit, KeyboardInterrupt, or what a cold shutdown raises in a solo pool's task): a waiting job,
                # or this one redelivered, takes over from the checkpoint; an outage said (pending with no error, the
                # fit had read as about to run while its jobs waited out the outage). An outage met as the grid was
                # recorded hands it back too, where the fit had stayed running, its waiting jobs waiting out the
                # lease; unless the record went through (its answer lost), which leaves it succeeded.
                return runtime.set_reconstruction(
                    rec.id, job.id, job.run_token, running=True, state=R_PENDING, owner_job_id=None,
                    owner_run_token=None, lease_until=None,
                    **({"error": f"job {job.id}'s fit: stopped by {outage}"} if outage else {}))

            # Tried again while the database refuses, as the job's give-back is: refused once, the fit had stayed
            # running, owned by a job gone back to the queue, its waiting jobs waiting out its lease.
            handed = _retried(hand_back, job.id, "its fit could not be handed back")
            if grid_key is not None and not handed:  # the fit lost meanwhile, its upload maybe stored all the same
                _discard_unless_recorded(storage, rec.id, grid_key)
            if handed == R_FAILED:
                for key in strays:
                    storage.discard(key)
            raise
    if not done:  # (a cleanup: a storage refusing it must not stop the job going on with the fit as it is now)
        storage.discard(stored.key)
        raise runtime.LeaseLost(f"reconstruction {rec.id}: another job took the fit over before it was stored")
    _discard_unrecorded(storage, rec.id, "checkpoint", None)  # (every run's: the fit is done)
    _discard_unrecorded(storage, rec.id, "grid-", stored.key)


def _store_fit_checkpoint(job: Job, rec_id: str, storage, path: str, iteration: int) -> None:
    """Store the fit's checkpoint taken at ``iteration`` under a key of its own (this run's token and the iteration)
    and record it as the fit's only while this run owns the running fit (:func:`runtime.record_fit_checkpoint`); the
    one it replaces goes. An owner that lost the fit (its lease lapsed, another job or run took it, or the fit
    ended) and stored late had overwritten the recorded checkpoint at a shared key: refused, or its record failing
    (the database out of reach), its bytes go, never the recorded ones, and a refused run stops
    (:class:`~worker.runtime.LeaseLost`)."""
    key = reconstruction_storage_key(rec_id, f"checkpoint-{job.run_token or job.id}-{iteration}.safetensors")
    storage.put_file(key, path)
    try:
        replaced = runtime.record_fit_checkpoint(rec_id, job.id, job.run_token, key)
    except Exception:
        storage.discard(key)
        raise
    if replaced is not None and replaced != key:
        storage.discard(replaced)


def _discard_unless_recorded(storage, rec_id: str, key: str) -> None:
    """Delete the grid a run stored at ``key`` (or may have: its upload's answer lost) that learnt, handing the fit
    back, it owns it no more: another job's run took it over, whose success's cleanup of stray grids may be past
    already, which had left this one stored for good. Kept where it is the fit's grid all the same (its record went
    through, its answer lost)."""
    now = runtime.load_reconstruction(rec_id)
    if now is None or now.grid_key != key:
        storage.discard(key)


def _discard_unrecorded(storage, rec_id: str, prefix: str, recorded: str | None) -> None:
    """Delete the reconstruction's stored objects whose names start with ``prefix`` but the one ``recorded``: a run
    whose record of its grid the database refused (down as it was written) left that grid stored under its own name,
    and its fit ran again; once a grid is recorded the fit is done for good, so another grid is such an orphan, or a
    run's that lost the fit (which deletes its own), and no checkpoint is needed any more. A cleanup: a storage
    failing it fails nothing."""
    for key in _stored(storage, rec_id, prefix):
        if key != recorded:
            storage.discard(key)


def _stored(storage, rec_id: str, prefix: str) -> list[str]:
    """The keys of the reconstruction's stored objects whose names start with ``prefix``, for a cleanup: none when the
    storage cannot list them (logged)."""
    try:
        return storage.list(reconstruction_storage_key(rec_id, prefix))
    except Exception:  # noqa: BLE001 - a cleanup's: a storage failing it fails nothing
        log.warning("reconstruction %s: could not list its stored %s objects", rec_id, prefix, exc_info=True)
        return []


def _outage(exc: BaseException) -> str | None:
    """The outage that stopped a fit, as its job's give-back names it: the database's, the storage's or the worker's
    disk full; None for anything else."""
    if (why := database_outage(exc)) is not None:
        return f"a database outage ({why})"
    return runtime.storage_or_disk_outage(exc)


def _fit_grid(job: Job, rec, settings, storage, lease: runtime.LeaseKeeper, callbacks: StageCallbacks,
              checkpoint: Path, device: str):
    """Route (a) and image scenes: G_i fitted to the scene's images on ``device``; returns (grid, total iterations)."""
    from voxe_core.reconstruct import CHECKPOINT_FORMAT_VERSION, CHECKPOINT_KIND, reconstruct

    scene = load_images(job, rec.params, settings, storage)
    backbone, config, cameras, initial = fit_setup(rec.params, scene.alphas, scene.cameras, settings.checkpoint_every,
                                                   scene_backbone=job_scene(job).backbone,  # what the API checked
                                                   split_c2w=scene.split_c2w)
    _record_fit(job, backbone, config, settings)
    lease.renew(total=config.total_iterations)
    resume, checkpoint_key = None, rec.checkpoint_key  # the last owner's, recorded while it owned the fit
    forget = functools.partial(runtime.forget_fit_checkpoint, rec.id, job.id, job.run_token)
    if _recorded_checkpoint_stored(storage, checkpoint_key, f"reconstruction {rec.id}", "checkpoint"):
        resume, _, why = _stored_checkpoint(storage, checkpoint_key, checkpoint, CHECKPOINT_KIND,
                                            CHECKPOINT_FORMAT_VERSION, config, forget)
        if why is not None:
            log.warning("reconstruction %s: the stored checkpoint %s; starting over", rec.id, why)
        elif resume is not None:
            log.info("reconstruction %s: resuming from its checkpoint", rec.id)
            runtime.record_job_event(job.id, "resumed", stage="reconstruct",
                                     detail=f"reconstruction {rec.id} from its stored checkpoint")
    grid = _resumed_or_started_over(
        lambda start: reconstruct(scene.images, cameras, config, callbacks.callbacks, checkpoint, start, initial,
                                  device), resume, job.id, "reconstruct", callbacks, storage, checkpoint_key,
        forget)
    return grid, config.total_iterations


def _recorded_checkpoint_stored(storage, checkpoint_key: str | None, whose: str, what: str) -> bool:
    """Whether the run recorded ``checkpoint_key`` and it is stored, to go on from; a recorded one that is not (a start
    over's record a database blip kept, or 0019's old fixed key with nothing stored there) is logged, as the stage
    starts from the start."""
    if checkpoint_key and not storage.exists(checkpoint_key):
        log.info("%s: its recorded %s %s is not stored; starting from the start", whose, what, checkpoint_key)
        return False
    return bool(checkpoint_key)


def _resumed_or_started_over(run, resume: Path | None, job_id: str, stage: str, callbacks: StageCallbacks, storage,
                             checkpoint_key: str | None, forget: Callable[[str], None]):
    """``run(resume)``; when the stage cannot go on from that checkpoint (a FormatError: another recipe, other views,
    prompt or initial grid, another device's generator it cannot read), ``run(None)``, the stage over from its
    start: refused, it would fail every redelivery. The stored checkpoint goes, its record cleared first
    (``forget(checkpoint_key)``: a redelivery before the new run's first would meet it again), and the job says so,
    as a warning after its "resumed" event, in place of the resumed note its progress reports carried (the
    callbacks' warning: a database blip skips the event, as it skips a progress write, where it had stopped the
    stage, a counted re-queue starting over with nothing said)."""
    from voxe_core.tensorio import FormatError

    try:
        return run(resume)
    except FormatError as exc:
        if resume is None:
            raise
        forget(checkpoint_key)
        storage.discard(checkpoint_key)
        callbacks.note = None  # (the resumed note it replaces)
        callbacks.on_warning(stage, f"the stored {stage} checkpoint could not be gone on from ({exc}): started over")
        with runtime.outage_skipped(f"job {job_id}: {stage}'s iteration set back"):  # (a blip: the next write sets it)
            runtime.update_job(job_id, held_by=callbacks.run_token, iteration=0)
        return run(None)


# --------------------------------------------------------------------------- edit
def _edit(job: Job, settings, device: str, storage) -> None:
    from voxe_core.edit import edit
    from voxe_core.render import fused_marcher_runs_on

    guidance = runtime.get_guidance(job.sds_model, device, settings, job)  # first: a missing model fails fast
    smoke_test = runtime.say_smoke_test_model(job, "edit", "sds", job.sds_model)
    rec = runtime.load_reconstruction(job.reconstruction_id)
    initial = fetch_grid(job.id, "initial_grid.safetensors", settings, storage, recorded_initial_grid(job.id, rec))
    config = _record_edit_schedule(job, initial.kind, settings)  # SPEC §5's schedule for a scene G_i
    if config.render.fused and not fused_marcher_runs_on(device):
        log.warning("job %s: VOXE_FUSED_MARCHER is on, but Triton does not run on %s here (it needs CUDA and the "
                    "triton package): the packed renderer renders", job.id, device)
    scratch = runtime.scratch_dir(job.id, settings)
    checkpoint = scratch / "edit_checkpoint.safetensors"
    checkpoint_key = job.checkpoint_key  # the last run's, recorded while it held the job
    forget = functools.partial(runtime.forget_checkpoint, job.id)
    resume, note = None, None
    if _recorded_checkpoint_stored(storage, checkpoint_key, f"job {job.id}", "edit checkpoint"):  # a redelivery
        from voxe_core.edit import EDIT_CHECKPOINT_KIND, EDIT_CHECKPOINT_VERSION

        resume, meta, why = _stored_checkpoint(storage, checkpoint_key, checkpoint, EDIT_CHECKPOINT_KIND,
                                               EDIT_CHECKPOINT_VERSION, config, forget)
        if why is not None:
            log.warning("job %s: the stored edit checkpoint %s; starting over", job.id, why)
            note = f"the stored edit checkpoint {why}: started over"
        elif resume is not None:
            at = int(meta["iteration"])
            note = f"resumed from the checkpoint at iteration {at}"
            log.info("job %s: edit %s", job.id, note)
            runtime.record_job_event(job.id, "resumed", stage="edit", iteration=at, worker=job.worker_hostname)
        # Where the run goes on from, at once: the row kept what the interrupted run last wrote (begin_stage), which
        # may lie before the checkpoint (progress is written every few seconds, checkpoints every N iterations).
        runtime.update_job(job.id, held_by=job.run_token, message=note,
                           **({"iteration": at} if resume is not None else {}))
    input_views = None
    if config.regulariser.startswith("image_"):
        scene = load_images(job, rec.params, settings, storage)
        input_views = (scene.images, initial.dataset_cameras(scene.cameras))

    last_preview = [0.0]

    def on_preview(iteration: int, image) -> None:
        now = time.monotonic()
        if now - last_preview[0] >= settings.preview_interval_s or iteration >= config.iterations:
            last_preview[0] = now
            _preview(job, None, settings, storage, device, image=image)

    callbacks = StageCallbacks(job, "edit", settings, note=note,
                               on_checkpoint=lambda path, iteration: storage.put_file(
                                   runtime.run_checkpoint_key(job, "edit", iteration), path))
    compiled_before = guidance.encoder_compile_seconds
    grid = _resumed_or_started_over(
        lambda start: edit(initial, job.prompt, guidance, config, callbacks.callbacks, checkpoint, start,
                           input_views=input_views, on_preview=on_preview, device=device),
        resume, job.id, "edit", callbacks, storage, checkpoint_key, forget)
    compiled = guidance.encoder_compile_seconds
    if compiled is not None and compiled != compiled_before:  # this job's first iteration waited for the compile
        log.info("job %s: the VAE encoder compiled in %.1f s", job.id, compiled)
        runtime.merge_job_result(job.id, {"encoder_compile_seconds": compiled})
    path = scratch / "edited_grid.safetensors"
    grid.save(path, notes={"smoke_test": smoke_test} if smoke_test else None)  # (as voxe edit's)
    runtime.publish_artifact(job.id, "edited_grid.safetensors", path, "grid", storage)


# --------------------------------------------------------------------------- refine
def _refine(job: Job, settings, device: str, storage) -> None:
    from voxe_core.export import save_png, turntable_cameras
    from voxe_core.refine.pipeline import refine
    from voxe_core.refine.renders import iter_mask_overlays
    from voxe_core.refine.storage import save_mask, save_probabilities

    guidance = runtime.get_guidance(job.attention_model, device, settings, job)
    smoke_test = [note for note in ((job.result or {}).get("smoke_test", {}).get("sds"),  # (the edit's)
                                    runtime.say_smoke_test_model(job, "refine", "attention", job.attention_model))
                  if note]
    rec = runtime.load_reconstruction(job.reconstruction_id)
    initial = fetch_grid(job.id, "initial_grid.safetensors", settings, storage, recorded_initial_grid(job.id, rec))
    edited = fetch_grid(job.id, "edited_grid.safetensors", settings, storage)
    config = refine_config(job.params, job.attention_model)
    callbacks = StageCallbacks(job, "refine", settings,
                               phase_seconds=refine_phase_seconds(config.fit_views, device_costs(device)))
    result = refine(initial, edited, job.prompt, job.edit_words, guidance, config, callbacks.callbacks, device=device)

    scratch = runtime.scratch_dir(job.id, settings)
    result.refined_grid.save(scratch / "refined_grid.safetensors",
                             notes={"smoke_test": "; ".join(smoke_test)} if smoke_test else None)  # (as voxe refine's)
    save_mask(scratch / "mask.safetensors", result.mask, {"prompt": job.prompt, "edit_words": list(job.edit_words)})
    save_probabilities(scratch / "attention_probabilities.safetensors", result.edit_probability,
                       result.object_probability, result.nodes)
    size = export_config(job.params).view_size
    cameras = turntable_cameras(1, 20.0, size, centre=initial.orbit_centre())  # G_i's, as every stage
    overlay = next(iter_mask_overlays(edited, result.mask, cameras.to(edited.bbox_min.device)))  # (its one view)
    save_png(scratch / "mask_overlay.png", overlay)
    # One set (as voxe refine's files): a storage failing part way had left the refined grid listed without its mask
    runtime.publish_artifacts(job.id, [(name, scratch / name, kind) for name, kind in (
        ("refined_grid.safetensors", "grid"), ("mask.safetensors", "mask"),
        ("attention_probabilities.safetensors", "probabilities"), ("mask_overlay.png", "render"))], storage)
    stats = result.stats  # as voxe refine's refine.json and notes say them
    runtime.merge_job_result(job.id, {"graph_cut": dataclasses.asdict(stats)})
    if (warning := stats.uniform_label()) is not None:
        runtime.record_warning(job.id, "refine", "; ".join([warning, *stats.notes]))


# --------------------------------------------------------------------------- export
def _export(job: Job, settings, device: str, storage) -> str | None:
    from voxe_core.export import VideoWriter, extract_mesh, iter_views, save_mesh, save_png, turntable_cameras

    options = export_config(job.params)
    name = "refined_grid.safetensors" if job.mode == "local" else "edited_grid.safetensors"
    grid = fetch_grid(job.id, name, settings, storage)
    centre = _orbit_centre(job, settings, storage)
    scratch = runtime.scratch_dir(job.id, settings)
    views, frames = options.views, options.turntable_frames
    total = views + frames + (1 if options.mesh else 0)
    callbacks = StageCallbacks(job, "export", settings)

    def offset(base: int) -> Callbacks:
        return Callbacks(
            on_progress=lambda r: callbacks.on_progress(Progress("export", base + r.iteration, total, info=r.info)),
            should_cancel=callbacks.should_cancel,
        )

    # Each view and turntable frame is written as it is rendered, never all held at once (1,000 frames of 2,048²
    # had been 50 GB of floats before the first was written)
    if views:
        ring = turntable_cameras(views, options.elevation, options.view_size, centre=centre)
        renders = []
        for i, image in enumerate(iter_views(grid, ring, callbacks=offset(0), device=device)):
            save_png(scratch / f"render_{i:03d}.png", image)
            renders.append((f"render_{i:03d}.png", scratch / f"render_{i:03d}.png", "render"))
        # One set, as the evaluation's rings: a storage refusing one view had failed the job listing the views before
        runtime.publish_artifacts(job.id, renders, storage)
    videos = [scratch / "turntable.mp4", *([scratch / "turntable.gif"] if options.gif else [])]
    first_frame = None
    with contextlib.ExitStack() as opened:  # the MP4 and the GIF fed by one render of each frame
        writers = [opened.enter_context(VideoWriter(path, frames, options.fps)) for path in videos]
        cameras = turntable_cameras(frames, options.elevation, options.turntable_size, centre=centre)
        for frame in iter_views(grid, cameras, callbacks=offset(views), device=device):
            first_frame = frame if first_frame is None else first_frame
            for writer in writers:
                writer.append(frame)
    # One set, as the mesh formats: a storage refusing the GIF had failed the job listing the MP4 alone
    runtime.publish_artifacts(job.id, [(path.name, path, "video") for path in videos], storage)
    if options.mesh:
        callbacks.callbacks.check_cancel("export")
        try:
            mesh = extract_mesh(grid, resolution=options.mesh_resolution)
        except ValueError as exc:  # no surface at the level: said (by the last progress write, and the job's
            callbacks.note = f"no mesh exported: {exc}"  # success), the other artifacts kept
        else:  # every format written before any is published, and published as one set: one the disk, its writer
            # or the storage refuses lists none
            written = [save_mesh(mesh, scratch / f"mesh.{suffix}") for suffix in ("ply", "glb", "obj")]
            runtime.publish_artifacts(job.id, [(path.name, path, "mesh")  # (mesh.mtl: mesh.obj's material)
                                               for path in (*written, scratch / "mesh.mtl")], storage)
        callbacks.on_progress(Progress("export", total, total))
    _preview(job, grid, settings, storage, device,
             image=first_frame if options.turntable_size <= 512 else None, centre=centre)
    return callbacks.note


# --------------------------------------------------------------------------- tasks
@app.task(name=STAGE_TASKS["reconstruct"].name, bind=True)
def reconstruct_task(self, job_id: str) -> TaskResult:
    return _run_stage(self, job_id, "reconstruct", _reconstruct)


@app.task(name=STAGE_TASKS["edit"].name, bind=True)
def edit_task(self, job_id: str) -> TaskResult:
    return _run_stage(self, job_id, "edit", _edit)


@app.task(name=STAGE_TASKS["refine"].name, bind=True)
def refine_task(self, job_id: str) -> TaskResult:
    return _run_stage(self, job_id, "refine", _refine)


@app.task(name=STAGE_TASKS["export"].name, bind=True)
def export_task(self, job_id: str) -> TaskResult:
    return _run_stage(self, job_id, "export", _export, final=True)


@app.task(name=STAGE_TASKS["evaluate"].name, bind=True)
def evaluate_task(self, job_id: str) -> TaskResult:
    return _run_stage(self, job_id, "evaluate", run_evaluation, final=True)


@app.task(name=INGEST_TASK.name, bind=True)
def ingest_task(self, scene_id: str) -> TaskResult:
    settings = get_settings()
    return ingest_scene(scene_id, settings, get_storage(settings), self.request.hostname or socket.gethostname())


# --------------------------------------------------------------------------- worker lifecycle
_heartbeat_stop = threading.Event()
_heartbeat_write = threading.Lock()
"""Held by a beat writing the heartbeat row and by the shutdown deleting it: a beat the stop overtook had written the
row again after its delete, the stopped worker looking alive one more window."""


SCRATCH_SWEEP_S = 600.0
"""How often the heartbeat thread also sweeps ended jobs' scratch, gone scenes' datasets, killed unpacks, datasets
over the cache's limit and ended ingests' uploads (runtime.sweep_*)."""


def _beat(hostname: str, queues: str, device: str, models: dict) -> None:
    settings = get_settings()
    next_sweep = time.monotonic()  # at start, then every SCRATCH_SWEEP_S
    # (a traceback every beat had filled the log while the database was down: 720 an hour)
    beats = FailingStreak(log, f"worker {hostname}", "heartbeat", "heartbeats")
    model_checks = FailingStreak(log, f"worker {hostname}", "check of its models", "checks of its models")
    while not _heartbeat_stop.is_set():
        sync_clock()  # (a pool process measures its own: _fresh_engine, begin_stage)
        try:
            # Looked at again every beat (a few file lookups): weights downloaded into a running worker's cache
            # are offered without a restart, and weights removed stop being offered.
            models, earlier = check_models(settings), models
            for role, m in models.items():
                if m["present"] != earlier[role]["present"]:
                    log.warning("worker %s: the %s model %s is %s", hostname, role,
                                model_label(m["model"]) or "(default)", "now present" if m["present"] else "gone")
        except Exception as exc:  # noqa: BLE001 - an unreadable model folder: the last answer stands, the beat goes on
            model_checks.note_failure(exc, "; the last answer stands")
        else:
            model_checks.succeeded()
        try:
            with _heartbeat_write:
                if _heartbeat_stop.is_set():  # stopping: its row is deleted, or about to be
                    break
                with runtime.session_scope() as session:
                    row = session.get(WorkerHeartbeat, hostname)
                    if row is None:
                        row = WorkerHeartbeat(hostname=hostname, pid=os.getpid(), queues=queues, device=device)
                        session.add(row)
                    row.pid, row.queues, row.device, row.models, row.last_seen = (
                        os.getpid(), queues, device, models, utcnow())
        except Exception as exc:  # noqa: BLE001 - a missed heartbeat is not fatal
            beats.note_failure(exc)
        else:
            beats.succeeded()
        if time.monotonic() >= next_sweep:
            next_sweep = time.monotonic() + SCRATCH_SWEEP_S
            for sweep, done in ((runtime.sweep_scratch, "removed the scratch of %d ended job(s)"),
                                (runtime.sweep_scene_datasets, "removed %d dataset(s) of deleted scenes, killed "
                                                               "unpacks or over VOXE_SCENE_CACHE_MAX_BYTES"),
                                (runtime.sweep_ingest_scratch, "removed %d upload(s) left by killed ingests")):
                try:
                    if swept := sweep(settings):
                        log.info(done, len(swept))
                except Exception:  # noqa: BLE001 - retried on the next sweep
                    log.warning("%s failed", sweep.__name__, exc_info=True)
        _heartbeat_stop.wait(settings.worker_heartbeat_s)


def recover_interrupted_jobs(hostname: str) -> list[str]:
    """Re-queue the remaining stages of jobs, and the ingests of scenes, this worker was running when it died
    (SQL broker only).

    kombu's SQL transport never redelivers a message whose consumer was killed (it stays
    invisible), so without this a job would stay "running" (a scene "processing") for ever.
    The stages are idempotent (done stages are skipped, long ones resume from their
    checkpoints); an ingest starts over.
    """
    queue, settings = get_queue(), get_settings()
    with runtime.session_scope() as session:
        jobs = list(session.scalars(select(Job).where(Job.state == RUNNING, Job.worker_hostname == hostname)))
        for job in jobs:  # (this worker's earlier process is gone: the hold of its run, if any, is released)
            outcome = requeue_interrupted(session, queue, job, settings,
                                          reason=f"worker {hostname} restarted while the job was in {job.stage}",
                                          where=[Job.worker_hostname == hostname])
            if outcome in (FAILED, CANCELED):
                get_storage(settings).discard_prefixes(job_key(job.id, "checkpoints/"))
            if outcome is not None:
                log.warning("job %s was interrupted in %s: %s", job.id, job.stage, outcome)
        scenes = list(session.scalars(select(Scene.id).where(Scene.state == PROCESSING,
                                                             Scene.worker_hostname == hostname)))
        # (the holds of this worker's earlier process are released too: the new messages take the scenes at once; the
        # lease run out, not none, so the reaper sends again what a broker refusing below leaves with no message)
        session.execute(update(Scene).where(Scene.id.in_(scenes), Scene.worker_hostname == hostname)
                        .values(ingest_token=None, ingest_lease_until=utcnow()))
    for scene_id in scenes:
        queue.send_ingest(scene_id)
        log.warning("the ingest of scene %s was interrupted; re-queued it", scene_id)
    return [job.id for job in jobs] + scenes


def resend_lost_queued_jobs(hostname: str) -> list[str]:
    """Send again the queued jobs whose message the broker no longer holds (SQL broker only, at the worker's start).

    The SQL broker deletes a message's row as it delivers it (``voxe_service.broker``), so a worker killed after
    taking a job's message and before its stage took the job (``runtime.begin_stage``) lost it: the job stayed
    queued for ever (``recover_interrupted_jobs`` sends only running jobs; the reaper, only jobs never sent). The
    embedded broker serves one worker (README's caveat), and ``worker_ready`` comes before its first fetch (the SQL
    transport has no event loop: Celery's ``synloop`` sends it between registering the consumer and its first poll),
    so a sent queued job no waiting message carries (its own, or in the chain of one) was taken by a worker that died.
    The jobs are read before the broker: a job sent meanwhile is found with its message. A sweep's evaluation is sent
    alone only once every edit it scores has ended (a live edit's chain carries it). A copy of a message that still
    lives (a second worker on the same SQL broker took it and has yet to start the stage) is harmless: it finds the
    stage held (dropped) or done (skipped).
    """
    queue, settings = get_queue(), get_settings()
    reason = (f"worker {hostname} started and the broker held no message for the queued job (a worker killed after "
              "taking it, before starting it)")
    stage_names = {spec.name for spec in STAGE_TASKS.values()}
    with runtime.session_scope() as session:
        queued = list(session.scalars(select(Job).where(Job.state == QUEUED, Job.task_id.is_not(None),
                                                        Job.run_token.is_(None))))
        carried = {job_id for task, job_id in waiting_tasks(settings.broker_url) if task in stage_names}
        # (each with the task id read before the broker: a commit below expires the session's copies)
        lost = [(job.id, job.task_id) for job in queued if job.id not in carried and not (
            job.mode == EVALUATE and session.scalar(select(Job.id).where(
                Job.id.in_(job.source_job_ids or []), Job.state.not_in(TERMINAL_STATES)).limit(1)))]
        sent = []
        for job_id, sent_as in lost:
            try:
                if not send_queued_again(session, queue, job_id, sent_as=sent_as, reason=reason,
                                         message=f"re-queued: {reason}", where=[Job.run_token.is_(None)]):
                    continue  # started, ended or sent again since it was read
            except QueueUnavailable:  # its task id back: the next start tries again
                log.warning("job %s: %s; the broker refused it again: the next worker start tries again", job_id,
                            reason)
                continue
            log.warning("job %s: %s; sent it again", job_id, reason)
            sent.append(job_id)
    return sent


def resend_lost_ingests(hostname: str) -> list[str]:
    """Send again the ingests of processing scenes that no worker took and whose message the broker no longer holds
    (SQL broker only, at the worker's start): a worker killed after taking one, before the ingest took its scene, lost
    it, as ``resend_lost_queued_jobs`` says of a job's; the scene stayed processing for ever, and the jobs on it
    queued (the reaper fails a scene only once its ingesting worker is gone, and this one had none). Each re-send is
    the reaper's (``send_ingest_again``): claimed first, so of workers starting together one sends it, and counted as
    a message taken as lost. The scenes are read before the broker: one sent meanwhile is found with its message, or
    its claim fails."""
    settings = get_settings()
    with runtime.session_scope() as session:
        untaken = session.execute(select(Scene.id, Scene.updated_at).where(
            Scene.state == PROCESSING, Scene.task_id.is_not(None), Scene.worker_hostname.is_(None))).all()
        carried = {scene_id for task, scene_id in waiting_tasks(settings.broker_url) if task == INGEST_TASK.name}
        sent = []
        for scene_id, seen_updated_at in untaken:
            if scene_id in carried:
                continue
            try:
                if not send_ingest_again(session, get_queue(), scene_id, seen_updated_at, lost=True):
                    continue  # taken, or sent again by another worker (or a reaper), since it was read
            except QueueUnavailable:
                log.warning("scene %s: the broker refused its lost ingest again: the reaper sends it", scene_id)
                continue
            log.warning("worker %s started and the broker held no ingest message for scene %s (a worker killed after "
                        "taking it, before the ingest began); sent it again", hostname, scene_id)
            sent.append(scene_id)
    return sent


@signals.task_failure.connect
def _next_stage_unsent(sender=None, args=None, **_kwargs) -> None:
    """A stage task that fails after its stage finished failed to hand its chain's next message to the broker
    (Celery's send after the task returns; every failure inside a stage ends the job in ``_run_stage``, or sends
    its message back to the queue). The job, between stages and held by no run, is sent again at once, or left
    queued with no task id for the reaper to send when the broker is back: nothing else would (the reaper cannot
    tell a lost message from one waiting its turn).
    A job that has ended (its last stage done, or failed) had only its sweep's evaluations in that message: they are
    sent alone, or fail with the reason."""
    stage = next((name for name, spec in STAGE_TASKS.items() if spec.name == getattr(sender, "name", None)), None)
    if stage is None or not args:
        return
    # (the broker's own words, an address or SQL, are in the log of the task's failure, not on the job's timeline)
    reason = f"the message of the stage after {stage} could not be sent: {QUEUE_UNAVAILABLE}"
    with runtime.session_scope() as session:
        job = session.get(Job, args[0])
        if job is not None and job.state in TERMINAL_STATES:
            try:  # the job ended (its last stage, or a failure): its sweep's evaluations rode in the lost message
                send_evaluations_alone(session, get_queue(), job, job.message)
            except QueueUnavailable:
                log.warning("job %s: %s; its evaluations failed with the reason", job.id, reason)
            return
        if job is None or job.state != RUNNING or job.run_token is not None or stage not in (job.completed_stages or []):
            return
        try:
            requeue_interrupted(session, get_queue(), job, get_settings(), reason=reason,
                                where=[Job.updated_at == job.updated_at, Job.run_token.is_(None)])
        except QueueUnavailable:  # the broker still refuses: queued with no task id, the reaper sends it
            log.warning("job %s: %s; the reaper sends it once the broker takes it", job.id, reason)


@signals.worker_ready.connect
def _start_heartbeat(sender=None, **_kwargs) -> None:
    hostname = getattr(sender, "hostname", None) or socket.gethostname()
    queues = ",".join(sorted(q.name for q in sender.app.amqp.queues.consume_from.values())) if sender else ""
    # Not settings.resolved_device: torch.cuda.is_available() here would initialise CUDA in the
    # parent of a prefork pool, and forked children could not use it.
    device = get_settings().device
    if is_sql_broker(get_settings().broker_url):
        for recover in (recover_interrupted_jobs, resend_lost_queued_jobs, resend_lost_ingests):
            try:
                recover(hostname)
            except Exception:  # noqa: BLE001 - never keep the worker from starting
                log.exception("%s failed", recover.__name__)
    models = check_models(get_settings())
    _heartbeat_stop.clear()
    threading.Thread(target=_beat, args=(hostname, queues, device, models), name="voxe-heartbeat", daemon=True).start()
    log.info("worker %s ready: queues %s, device %s, models %s", hostname, queues, device,
             ", ".join(f"{role} {model_label(m['model']) or '(default)'} ({'present' if m['present'] else 'MISSING'})"
                       for role, m in models.items()))
    for role, m in models.items():
        if not m["present"]:
            log.warning("worker %s: %s", hostname, missing_message(role, m["model"], "this worker"))


@signals.worker_shutdown.connect
def _stop_heartbeat(sender=None, **_kwargs) -> None:
    _heartbeat_stop.set()
    hostname = getattr(sender, "hostname", None)
    if hostname:
        try:
            with _heartbeat_write, runtime.session_scope() as session:
                row = session.get(WorkerHeartbeat, hostname)
                if row is not None:
                    session.delete(row)
        except Exception:  # noqa: BLE001
            pass


@signals.worker_process_init.connect
def _fresh_engine(**_kwargs) -> None:
    """A forked pool process must not share the parent's database or broker connections."""
    from voxe_service.db import get_engine, get_sessionmaker

    if get_engine.cache_info().currsize:
        get_engine().dispose(close=False)
    get_engine.cache_clear()
    get_sessionmaker.cache_clear()
    reset_queue()
    sync_clock()
