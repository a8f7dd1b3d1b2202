"""The evaluate stage (SPEC §4): score finished edit jobs of one scene on the ring, publish JSON and a table.

An evaluation job lists its source jobs (``source_job_ids``) and carries its settings
in ``params`` (ring, object name, the CLIP and FID models fixed when it was created).
Every source must have succeeded; the edit scored is the refined grid (with its
mask) of a local edit and the edited grid of a global one, against the sources'
shared reconstruction G_i. Results: ``evaluation.json`` (also the job's ``result``),
``evaluation.md`` and, unless disabled, the ring renders ``ring_initial_NNN.png`` and
``ring_<source job id>_NNN.png``.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

from voxe_service.model_inventory import submission_note
from voxe_service.models import SUCCEEDED, Job
from voxe_service.settings import TINY_MODEL, Settings, fid_model_label, model_label, smoke_test_roles
from voxe_service.storage import StoredObject
from worker import runtime
from worker.inputs import fetch_grid, load_images, recorded_initial_grid
from worker.runtime import StageCallbacks

log = logging.getLogger("voxe.worker")

_SCORERS: dict[str, tuple[tuple[str, str], object]] = {}
"""The scorer last loaded of each kind ('clip', 'fid') with its (model, device): one of each per process. Every
(kind, model, device) had stayed loaded, so a worker evaluating with several CLIP or FID models kept them all."""


class EvaluationFailed(RuntimeError):
    """The evaluation cannot run (a source job did not succeed, a model is missing); the message says why."""


def fid_model_path(model: str, settings: Settings) -> str:
    """What ``VOXE_FID_MODEL`` names: a file or folder, ``tiny``, or (empty) the Inception file in the model dir."""
    from voxe_core.evaluate import INCEPTION_FILE

    if model == TINY_MODEL:
        from voxe_core.tiny_eval import build_tiny_inception

        folder = runtime.build_once(settings, "tiny-inception", INCEPTION_FILE,
                                    lambda tmp: build_tiny_inception(Path(tmp) / INCEPTION_FILE))
        return str(folder / INCEPTION_FILE)
    return model or str(Path(settings.model_dir) / INCEPTION_FILE)


def _scorer(kind: str, model: str, device: str, settings: Settings):
    from voxe_core.evaluate import ClipScorer, InceptionFeatures
    from voxe_core.guidance.loading import ModelNotAvailableError

    loaded = _SCORERS.get(kind)
    if loaded is not None and loaded[0] == (model, device):
        return loaded[1]
    if loaded is not None:  # let go before the next one loads: two had been held at once
        del _SCORERS[kind]
        log.info("freeing %s model %s on %s", kind, *loaded[0])
        del loaded
        runtime.give_back_freed_memory()
    try:
        if kind == "clip":
            path = model
            if model == TINY_MODEL:
                from voxe_core.tiny_eval import build_tiny_clip

                path = str(runtime.build_once(settings, "tiny-clip", "config.json", build_tiny_clip))
            scorer = ClipScorer.from_pretrained(path, device=device)
        else:
            scorer = InceptionFeatures.load(fid_model_path(model, settings), device=device)
    except ModelNotAvailableError as exc:
        raise EvaluationFailed(f"evaluate: {exc}. {submission_note(kind)}.") from exc
    _SCORERS[kind] = ((model, device), scorer)
    return scorer


def _sources(job: Job) -> list[Job]:
    jobs = []
    for source_id in job.source_job_ids or []:
        source = runtime.load_job(source_id)
        if source is None:
            raise EvaluationFailed(f"evaluate: source job {source_id} was deleted")
        if source.state != SUCCEEDED:
            why = f": {source.error or source.message}" if (source.error or source.message) else ""
            raise EvaluationFailed(f"evaluate: source job {source_id} {source.state}{why}")
        jobs.append(source)
    if not jobs:
        raise EvaluationFailed("evaluate: the job lists no source jobs")
    if len({s.reconstruction_id for s in jobs}) != 1:
        raise EvaluationFailed("evaluate: the source jobs do not share one reconstruction")
    return jobs


def _initial_grid(sources: list[Job], rec) -> StoredObject:
    """G_i the sources were edited from (``inputs.recorded_initial_grid``): scoring against the reconstruction's grid,
    fitted again since, had measured each edit against a G_i it was not made from."""
    recorded = {recorded_initial_grid(source.id, rec) for source in sources}
    if len(recorded) > 1:
        raise EvaluationFailed(f"evaluate: the source jobs were edited from different fits of their reconstruction "
                               f"{rec.id} (its grid was deleted from the storage and fitted again between them): "
                               "evaluate those of each fit apart")
    if (grid := recorded.pop()) is None:
        raise EvaluationFailed(f"evaluate: the source jobs' reconstruction {rec.id} has no grid ({rec.state})")
    return grid


def run_evaluation(job: Job, settings: Settings, device: str, storage) -> None:
    """The evaluate stage body (called by the task frame in :mod:`worker.tasks`)."""
    from voxe_core.evaluate import EditSample, EvaluateConfig, evaluate, format_table
    from voxe_core.export import save_png
    from voxe_core.refine.storage import load_mask

    params = job.params
    sources = _sources(job)
    clip = _scorer("clip", params["clip_model"], device, settings)
    fid = _scorer("fid", params["fid_model"], device, settings)
    rec = runtime.load_reconstruction(sources[0].reconstruction_id)
    if rec is None:
        raise EvaluationFailed("evaluate: the source jobs' reconstruction is gone")
    initial = fetch_grid(job.id, "initial_grid.safetensors", settings, storage, _initial_grid(sources, rec))
    edits = []
    for source in sources:
        name = "refined_grid.safetensors" if source.mode == "local" else "edited_grid.safetensors"
        grid = fetch_grid(job.id, f"{source.id}_{name}", settings, storage, runtime.recorded_artifact(source.id, name))
        mask = None
        if source.mode == "local":
            mask_path = runtime.fetch(storage, runtime.recorded_artifact(source.id, "mask.safetensors"),
                                      runtime.scratch_dir(job.id, settings) / f"{source.id}_mask.safetensors")
            mask = load_mask(mask_path, initial.resolution)
        edits.append(EditSample(source.id, source.prompt, grid, mask))
    input_images = load_images(sources[0], rec.params, settings, storage).images if params["fid_input"] else None
    config = EvaluateConfig(views=params["views"], elevation=params["elevation"], size=params["size"])
    callbacks = StageCallbacks(job, "evaluate", settings)
    scratch = runtime.scratch_dir(job.id, settings)
    rings = {}  # grid -> its ring's (name, path, kind): one set, below, listed grid by grid as the views come

    def save_ring(source_id: str | None, i: int, view) -> None:
        """Each ring view written as it is scored (every ring had been held to the end of the evaluation)."""
        name = f"ring_{source_id or 'initial'}_{i:03d}.png"
        save_png(scratch / name, view)
        rings.setdefault(source_id, []).append((name, scratch / name, "render"))

    result = evaluate(initial, edits, params["object"], clip, fid, input_images, config, callbacks.callbacks,
                      device=device, on_ring=save_ring if params.get("save_renders", True) else None)
    for row, source in zip(result.rows, sources):  # rows are named by their source job's id
        row.update(job_id=row.pop("name"), scene_id=source.scene_id, object=params["object"])
    smoke_test = smoke_test_roles(params)
    table = format_table(result.rows, extra_columns=("job_id",), smoke_test=smoke_test)
    summary = {**result.summary(), "object": params["object"], "clip_model": model_label(params["clip_model"]),
               "fid_model": fid_model_label(params["fid_model"]), "smoke_test": smoke_test, "reconstruction_id": rec.id,
               "ring": {"views": config.views, "elevation": config.elevation, "size": config.size}, "table": table}
    (scratch / "evaluation.json").write_text(json.dumps(summary, indent=2))
    (scratch / "evaluation.md").write_text(table, encoding="utf-8")
    # One set: a storage failing part way had left a failed job listing some rings, or the JSON without its table
    published = [artifact for ring in rings.values() for artifact in ring]
    runtime.publish_artifacts(job.id, [*published, *((name, scratch / name, "evaluation")
                                                     for name in ("evaluation.json", "evaluation.md"))], storage)
    runtime.merge_job_result(job.id, summary)
    log.info("job %s: evaluated %d edit(s) of scene %s", job.id, len(sources), sources[0].scene_id)
