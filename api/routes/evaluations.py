"""/v1/evaluations and /v1/sweeps: the paper's evaluation (SPEC §4) as jobs.

An evaluation's result (the metrics, a Markdown table) is the job's ``result`` and its
``evaluation.json`` / ``evaluation.md`` artifacts; ``GET /v1/sweeps/{id}`` gathers a sweep's
evaluations into one summary table.
"""

from __future__ import annotations

from collections import Counter

from fastapi import APIRouter, Response, status
from sqlalchemy.orm import Session

from api.auth import mark_replayed, replayed_answer
from api.deps import CurrentKey, IdempotencyKey, QueueDep, RootPath, SessionDep, SettingsDep
from api.http_semantics import StrictRoute
from api.routes.jobs import job_out
from api.schemas import EvaluationCreate, JobOut, SweepCreate, SweepEntry, SweepOut
from api.services import evaluations
from voxe_core.evaluate import format_table, mean_by_mode
from voxe_service.models import EVALUATE, SUCCEEDED, ApiKey
from voxe_service.settings import smoke_test_roles

router = APIRouter(tags=["evaluation"], route_class=StrictRoute)

_QUOTA = {429: {"description": "the key's quota of queued + running jobs is used up (Retry-After)"},
          503: {"description": "the jobs could not be queued (broker unreachable)"}}


@router.post("/v1/evaluations", status_code=status.HTTP_201_CREATED, response_model=JobOut,
             responses={200: replayed_answer(JobOut, "evaluation"),
                        404: {"description": "a listed job does not exist (or is another key's)"},
                        409: {"description": "a listed job has not succeeded, the workers lack a model it loads, a "
                                             "retry whose Idempotency-Key created an evaluation that has since been "
                                             "deleted, or one sent while that first request has not answered yet "
                                             "(Retry-After); or the evaluation was canceled and deleted with its "
                                             "scene before its creation answered"},
                        422: {"description": "invalid request, an object name whose source text is longer than CLIP "
                                             "reads, an evaluation listed, jobs of different scenes, or an "
                                             "Idempotency-Key reused with a different body"},
                        **_QUOTA},
             summary="Evaluate finished edit jobs of one scene (CLIP_sim, CLIP_dir, FID, PSNR/SSIM outside the mask; "
                     "optionally with an Idempotency-Key header)")
def create_evaluation(body: EvaluationCreate, response: Response, session: SessionDep, settings: SettingsDep,
                      queue: QueueDep, key: CurrentKey, idempotency_key: IdempotencyKey, root: RootPath) -> JobOut:
    """201 with the queued evaluation; 200 with the original one for a retry carrying the same Idempotency-Key."""
    job, replayed = evaluations.create_evaluation(session=session, settings=settings, queue=queue, key=key, body=body,
                                                  idempotency_key=idempotency_key)
    if replayed:
        mark_replayed(response)
    return job_out(job, root)


@router.post("/v1/sweeps", status_code=status.HTTP_201_CREATED, response_model=SweepOut,
             responses={200: replayed_answer(SweepOut, "sweep"),
                        404: {"description": "no such scene (or another key's)"},
                        409: {"description": "a scene failed processing (the reason is named), the workers lack "
                                             "a model the jobs load, a retry whose Idempotency-Key created a sweep "
                                             "whose recorded job has since been deleted, or one sent while that first "
                                             "request has not answered yet (Retry-After)"},
                        422: {"description": "invalid request (the field is named), or an Idempotency-Key reused "
                                             "with a different body"},
                        **_QUOTA,
                        503: {"description": "the broker refused the sweep, maybe part-way: the whole sweep is "
                                             "withdrawn (what was sent is canceled), so a retry repeats none of it"}},
             summary="Submit the paper's protocol: scenes × the six prompts of SPEC §4, each edit then evaluated "
                     "(optionally with an Idempotency-Key header)")
def create_sweep(body: SweepCreate, response: Response, session: SessionDep, settings: SettingsDep, queue: QueueDep,
                 key: CurrentKey, idempotency_key: IdempotencyKey) -> SweepOut:
    """201 with the queued sweep; 200 with the original one for a retry carrying the same Idempotency-Key."""
    sweep_id, replayed = evaluations.create_sweep(session=session, settings=settings, queue=queue, key=key, body=body,
                                                  idempotency_key=idempotency_key)
    if replayed:
        mark_replayed(response)
    return sweep_out(session, sweep_id, key)


@router.get("/v1/sweeps/{sweep_id}", response_model=SweepOut,
            responses={404: {"description": "no such sweep (or another key's)"}},
            summary="A sweep's jobs and, for the evaluations done so far, one summary table")
def get_sweep(sweep_id: str, session: SessionDep, key: CurrentKey) -> SweepOut:
    return sweep_out(session, sweep_id, key)


@router.post("/v1/sweeps/{sweep_id}/cancel", response_model=SweepOut,
             responses={404: {"description": "no such sweep (or another key's)"}},
             summary="Cancel every unfinished job of a sweep (finished ones and their results stay)")
def cancel_sweep(sweep_id: str, session: SessionDep, key: CurrentKey) -> SweepOut:
    evaluations.cancel_sweep(session=session, key=key, sweep_id=sweep_id)
    return sweep_out(session, sweep_id, key)


def sweep_out(session: Session, sweep_id: str, key: ApiKey) -> SweepOut:
    jobs = evaluations.sweep_jobs(session=session, key=key, sweep_id=sweep_id)
    edits = {j.id: j for j in jobs if j.mode != EVALUATE}
    scored = sorted((j for j in jobs if j.mode == EVALUATE), key=lambda j: j.params.get("sweep_index", 0))
    entries, rows = [], []
    for evaluation in scored:
        edit = edits[evaluation.source_job_ids[0]]
        entries.append(SweepEntry(
            scene_id=edit.scene_id, object=evaluation.params["object"], prompt=edit.prompt, mode=edit.mode,
            edit_job_id=edit.id, edit_state=edit.state, evaluation_job_id=evaluation.id,
            evaluation_state=evaluation.state,
        ))
        if evaluation.state == SUCCEEDED:  # a running or failed one's result holds its progress, no rows
            rows.extend(evaluation.result["rows"])
    return SweepOut(
        id=sweep_id, state=evaluations.sweep_state([j.state for j in jobs]),
        counts=dict(Counter(j.state for j in jobs)), entries=entries, rows=rows, means=mean_by_mode(rows),
        table=format_table(rows, extra_columns=("object",), smoke_test=smoke_test_roles(*(j.params for j in scored))),
    )
