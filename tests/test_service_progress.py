"""Overall progress and ETA of a job across its stages (voxe_service/progress.py): the weights are the
benchmarks' measured figures, the fraction never goes back across stage boundaries, and the ETA scales the
later stages by the speed the current one shows."""

from __future__ import annotations

import json
from datetime import timedelta
from pathlib import Path

import pytest

from api.schemas import JobParams
from voxe_service.models import Job, Reconstruction, utcnow
from voxe_service.progress import (
    DEVICE_COSTS, NO_FIT, FitWork, device_costs, fit_work, overall, refine_phase_seconds, stage_costs, stage_fraction,
)

RESULTS = Path(__file__).resolve().parents[1] / "bench" / "results"


def test_the_cpu_weights_are_the_benchmarks_figures():
    rows = {r["label"]: r for r in json.loads((RESULTS / "reconstruction.json").read_text())}
    fast_64 = rows["fast-64"]

    def cpu_seconds(family: str) -> float:  # the mean over its seeds
        seeds = [r["cpu_seconds"] for label, r in rows.items() if label == family or label.startswith(f"{family}-seed")]
        return sum(seeds) / len(seeds)
    segmentation = json.loads((RESULTS / "segmentation.json").read_text())
    edit = next(r for r in json.loads((RESULTS / "edit_step.json").read_text()) if r["model"] == "sd2-base-shaped"
                and r["render_size"] == 64)
    cpu = DEVICE_COSTS["cpu"]
    # The sitting's fit (27.47 s at a8fc17f: the preset's 2,000 steps of 4,096 rays, re-run since as
    # preset-fast-4096-rays) times what its 1,000 steps of 8,192 cost over those, the two measured side by side.
    per_step = 27.47 * cpu_seconds("preset-fast") / cpu_seconds("preset-fast-4096-rays") / rows["preset-fast"]["iterations"]
    assert cpu.fit_step == pytest.approx(per_step, rel=1e-3) and cpu.fit_rays == rows["preset-fast"]["rays_per_step"]
    assert cpu.edit == pytest.approx(edit["ms_total"] / 1000, abs=1e-3)
    attention_pass_ms = edit["ms_render"] + edit["ms_vae"] + edit["ms_unet"]  # forward only: no SDS backward
    assert cpu.refine == pytest.approx(attention_pass_ms / 1000, abs=1e-3)
    fixed_step = segmentation["runs"][0]["seconds"] / segmentation["settings"]["iterations"]
    assert cpu.refine_fixed_step == pytest.approx(fixed_step)
    assert cpu.graph_cut == DEVICE_COSTS["cuda"].graph_cut == segmentation["graph_160"]["total_s"]  # on the host
    assert cpu.export == cpu.evaluate == pytest.approx(fast_64["render_seconds_per_view"])
    # A capture's step against an object's, per ray, fitted in one run as jobs fit them (bench/fit_costs.py).
    fits = json.loads((RESULTS / "fit_costs.json").read_text())["runs"]
    per_ray = {}
    for run in fits:
        per_ray.setdefault(run["backbone"], []).append(run["seconds_per_step"] / run["rays_per_step"])
    object_ray = [r["seconds_per_step"] / r["rays_per_step"] for r in fits if r["preset"] == "fast"]
    assert cpu.fit_backbone == {"scene": pytest.approx(per_ray["scene"][0] / (sum(object_ray) / len(object_ray)),
                                                       rel=1e-3)}


def test_the_cuda_weights_are_one_job_through_the_worker_on_the_h200():
    runs = json.loads((RESULTS / "gpu.json").read_text())["runs"]
    job = next(r for r in runs if r["kind"] == "job" and r["device"] == "cuda")
    # The job's fit as it recorded it (bench/gpu.py records it since 2026-12-05); call 5's ran fast's steps of then,
    # as section c's fast row (call 4) did.
    fit_steps = (job.get("fit") or {}).get("steps") or next(
        r for r in runs if r["kind"] == "reconstruction" and r["preset"] == "fast")["iterations"]
    export = {"views": 4, "turntable_frames": 30, "gif": False}  # bench/gpu.py's Profile.full(), the mesh by default
    seconds = dict(stage_costs(mode="local", params={"iterations": job["edit_iterations"], "export": export},
                               fit=FitWork(fit_steps, 4096, "relu_field"), device="cuda"))
    assert seconds == pytest.approx(job["seconds_per_stage"], rel=1e-3)
    cuda = DEVICE_COSTS["cuda"]
    assert cuda.fit_rays is None and cuda.refine_fixed_step == cuda.fit_step  # a step costs its dispatches there
    assert device_costs("cuda:1") is cuda and device_costs("cpu") is device_costs("mps") is DEVICE_COSTS["cpu"]


def test_a_fit_is_weighed_by_its_steps_rays_and_backbone():
    cpu = DEVICE_COSTS["cpu"]
    fast = fit_work({})
    assert fast == FitWork(1000, 8192, "relu_field")
    assert fit_work({"preset": "paper"}) == FitWork(2000, 32768, "relu_field")
    assert fit_work({"iterations": [100, 200]}) == FitWork(300, 2048, "scene")  # only a capture's preset has 2 stages
    assert fit_work({"backbone": "scene", "rays_per_step": 512}) == FitWork(1200, 512, "scene")
    assert fit_work({"backbone": "relu_field", "iterations": [1, 2]}) == fast  # resolves to nothing: the default
    assert fit_work({"iterations": 1.5}) == fit_work({}, {"backbone": "scene"}) == fast  # odd records weigh as it
    assert fit_work({"route": "voxelize"}).steps == 1
    recorded = {"backbone": "scene", "steps": 1200, "rays_per_step": 2048}
    assert fit_work({}, recorded, steps=600) == FitWork(600, 2048, "scene")  # the worker's record, its reported steps
    # A CPU step costs its rays, a capture's more; a GPU step costs the same whatever its rays.
    object_step = cpu.fit_seconds(FitWork(1, 8192, "relu_field"))
    assert cpu.fit_seconds(FitWork(10, 32768, "relu_field")) == pytest.approx(40 * object_step)
    assert cpu.fit_seconds(FitWork(1, 8192, "scene")) == pytest.approx(cpu.fit_backbone["scene"] * object_step)
    cuda = DEVICE_COSTS["cuda"]
    assert cuda.fit_seconds(FitWork(10, 32768, "scene")) == pytest.approx(10 * cuda.fit_step)
    assert cpu.fit_seconds(NO_FIT) == cuda.fit_seconds(NO_FIT) == 0


def test_stages_follow_the_mode_and_the_params():
    assert [s for s, _ in stage_costs(mode="local", params={}, fit=fit_work({}))] == [
        "reconstruct", "edit", "refine", "export"]
    assert [s for s, _ in stage_costs(mode="global", params={}, fit=fit_work({}))] == [
        "reconstruct", "edit", "export"]
    short, long = (dict(stage_costs(mode="global", params={"iterations": n}, fit=fit_work({}, steps=100)))["edit"]
                   for n in (10, 1000))
    assert long == pytest.approx(100 * short)


def test_the_refinement_weighs_each_of_its_phases():
    """An attention pass per view and per fitting step, the back-projection's chunks (of 32,768 strided pixels' rays)
    and the cut: the chunks and the cut had been left out of the stage's cost, a tenth of the default refinement."""
    cpu = DEVICE_COSTS["cpu"]
    per_pass, chunk, cut = cpu.refine, cpu.backprojection_chunk, cpu.graph_cut
    # 32 views of 266² px read every 2nd row and column: 32 x 133² rays, 18 chunks.
    assert dict(stage_costs(mode="local", params={}, fit=NO_FIT))["refine"] == pytest.approx(
        32 * per_pass + 18 * chunk + cut)
    fitted = {"refine": {"views": 8, "iterations": 100}}  # 8 x 133² rays: 5 chunks
    assert dict(stage_costs(mode="local", params=fitted, fit=NO_FIT))["refine"] == pytest.approx(
        108 * per_pass + 5 * chunk + cut)
    small = {"render_size": 64}  # the refinement renders at the edit's size: 32 x 32² rays, one chunk
    assert dict(stage_costs(mode="local", params=small, fit=NO_FIT))["refine"] == pytest.approx(
        32 * per_pass + chunk + cut)
    stored = JobParams().model_dump()  # what a job holds: every default written out
    assert dict(stage_costs(mode="local", params=stored, fit=NO_FIT))["refine"] == pytest.approx(
        (stored["refine"]["views"] + stored["refine"]["iterations"]) * per_pass + 18 * chunk + cut)
    # The paper's fit from a constant reuses its views' maps: 32 passes, then 1,500 cheap steps, not 1,532 passes.
    paper = {"refine": {"lift_start": "constant", "iterations": 1500}}
    assert dict(stage_costs(mode="local", params=paper, fit=NO_FIT))["refine"] == pytest.approx(
        32 * per_pass + 18 * chunk + 1500 * cpu.refine_fixed_step + cut)


def test_an_edit_is_weighed_by_what_its_schedule_runs_once_known():
    """A capture's scene grid edits for 5,000 iterations where the job's parameters say 8,000."""
    from api.routes.jobs import job_out

    params = JobParams().model_dump()
    before = dict(stage_costs(mode="global", params=params, fit=NO_FIT))["edit"]
    known = dict(stage_costs(mode="global", params=params, fit=NO_FIT, edit_iterations=5000))["edit"]
    edit = DEVICE_COSTS["cpu"].edit
    assert before == pytest.approx(8000 * edit) and known == pytest.approx(5000 * edit)
    none_asked = dict(stage_costs(mode="global", params={**params, "iterations": 0}, fit=NO_FIT))["edit"]
    assert none_asked == pytest.approx(edit)  # 0 iterations weigh one, not the default 8,000
    # Through the job resource: a job asking for 10 iterations whose schedule runs 1,000, halfway through its edit.
    params = {**params, "iterations": 10}
    rec = Reconstruction(id="r", scene_id="s", params_key="k", params={}, state="succeeded", owner_job_id="j", total=1)
    running = dict(reconstruction=rec, mode="global", params=params, state="running", stage="edit", iteration=500,
                   total=1000, completed_stages=["reconstruct"], started_at=utcnow(), stage_started_at=utcnow())

    def halfway(edit_iterations):
        costs = dict(stage_costs(mode="global", params=params, fit=fit_work({}, steps=1),
                                 edit_iterations=edit_iterations))
        return (costs["reconstruct"] + costs["edit"] / 2) / sum(costs.values())

    assert job_out(_job(**running)).overall_progress == pytest.approx(halfway(None))  # weighed as 10 iterations
    assert job_out(_job(**running)).stage_started_at == running["stage_started_at"]  # shown, no longer weighed
    scheduled = job_out(_job(**running, result={"edit_schedule": {"iterations": 1000}})).overall_progress
    assert scheduled == pytest.approx(halfway(1000)) and scheduled > halfway(None) + 0.05


def _job(**values) -> Job:
    base = dict(id="j", scene_id="s", owner_key_id="local", prompt="p", mode="local", edit_words=["x"],
                params={"iterations": 100, "refine": {"iterations": 50}}, sds_model="tiny", attention_model="tiny",
                device="cpu", state="queued", iteration=0, total=0, completed_stages=[], cancel_requested=False, created_at=utcnow(),
                updated_at=utcnow())
    base.update(values)
    return Job(**base)


def test_overall_progress_runs_from_0_to_1_and_never_goes_back():
    """A job's records as its stages report (the job resource's view of them)."""
    from api.routes.jobs import job_out

    rec = Reconstruction(id="r", scene_id="s", params_key="k", params={}, state="running", owner_job_id="j", total=200)
    seen = [job_out(_job(reconstruction=rec)).overall_progress]
    done: list[str] = []
    for stage, total in (("reconstruct", 200), ("edit", 100), ("refine", 50), ("export", 10)):
        for iteration in (0, total // 3, total):
            job = _job(reconstruction=rec, state="running", stage=stage, iteration=iteration, total=total,
                       completed_stages=list(done), stage_started_at=utcnow() - timedelta(seconds=5),
                       eta_seconds=1.0, started_at=utcnow())
            seen.append(job_out(job).overall_progress)
        done.append(stage)
        seen.append(job_out(_job(reconstruction=rec, state="running", stage=stage, iteration=total, total=total,
                                 completed_stages=list(done), started_at=utcnow())).overall_progress)
    seen.append(job_out(_job(reconstruction=rec, state="succeeded", stage="export", completed_stages=done,
                             started_at=utcnow(), finished_at=utcnow())).overall_progress)
    assert seen[0] == 0.0 and seen[-1] == 1.0 and all(0 <= p <= 1 for p in seen)
    assert seen == sorted(seen), seen
    # 100 edit iterations (1.7 s each) and 82 attention passes (32 views + 50 steps, 1.35 s each) cost far more than
    # 200 reconstruction iterations (28 ms each) or 109 export renders (93 ms each).
    after_reconstruct, after_edit, after_refine = seen[4], seen[8], seen[12]
    costs = dict(stage_costs(mode="local", params=_job().params, fit=fit_work({}, steps=200)))
    assert after_edit == pytest.approx((costs["reconstruct"] + costs["edit"]) / sum(costs.values()))
    assert after_reconstruct < 0.02 and 0.55 < after_edit < 0.65 and after_refine > 0.95, seen


def test_the_workers_refine_records_a_stage_fraction_that_only_rises(monkeypatch, tiny_sd_path, make_sphere_grid,
                                                                     single_thread):
    """The worker hands voxe_core's refine() its StageCallbacks, and refine() counts its sub-steps (attention maps,
    back-projection, the grids' fit, the cut) on one scale (voxe_core.progress.in_phases): the fraction the job
    records only rises (each sub-step's own i/N had sent it back at every new sub-step), and so does the fraction
    weighed by each sub-step's cost, to 1; the stage's cost counts every sub-step refine() reports."""
    import dataclasses

    from voxe_core.guidance.sds import StableDiffusionGuidance
    from voxe_core.presets import refine_config
    from voxe_core.refine.pipeline import refine
    from voxe_service.settings import Settings
    from worker import runtime

    written = []
    monkeypatch.setattr(runtime, "update_job", lambda job_id, **values: written.append(
        (values["message"], values["iteration"] / values["total"])))
    monkeypatch.setattr(runtime, "record_peak_memory", lambda *args: None)
    callbacks = runtime.StageCallbacks(_job(state="running", stage="refine"), "refine",
                                       Settings(progress_interval_s=1e-9))  # every report written
    params = {"refine": {"views": 3, "render_size": 24, "iterations": 4}}  # the service's refinement, small
    reports = []

    def report(progress):
        reports.append(progress)
        callbacks.callbacks.on_progress(progress)

    grid = make_sphere_grid(12)
    refine(grid, grid.clone_grid(), "a dog wearing sunglasses", ["sunglasses"],
           StableDiffusionGuidance.from_pretrained(str(tiny_sd_path), device="cpu"), refine_config(params, "tiny"),
           dataclasses.replace(callbacks.callbacks, should_cancel=None, on_progress=report))  # (no job row to cancel)
    assert [message for message, _ in written] == (["refine: attention_maps"] * 3 + ["refine: backprojection"]
                                                   + ["refine: attention_grids"] * 4 + ["refine: graph_cut"])
    fractions = [fraction for _, fraction in written]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0, fractions
    # The stage's cost weighs every phase refine() reports, by the units it counts for each: the back-projection
    # and the cut had been left out.
    first = reports[0]  # its units left in each sub-step, and the one it had done
    left = first.info["phase_units_left"]
    scale = {**left, first.stage: left[first.stage] + first.iteration}
    for device in ("cpu", "cuda"):
        table = refine_phase_seconds("fresh", device_costs(device))
        assert scale.keys() == table.keys()
        assert dict(stage_costs(mode="local", params=params, fit=NO_FIT, device=device))["refine"] == pytest.approx(
            sum(units * table[phase] for phase, units in scale.items()))
        weighed = [stage_fraction(stage="refine", params=params, device=device, iteration=r.iteration, total=r.total)
                   for r in reports]
        assert weighed == sorted(weighed) and weighed[-1] == 1.0, weighed


def test_the_workers_stage_eta_counts_the_units_done_since_its_first_report(monkeypatch):
    """The rate is measured from the stage's first report (a model's load before it is no unit of work): the units
    since then over the time since then. The origin had been put one unit before that report, as if its unit had
    taken no time: at the second report a stage running 2 s a unit was timed at 1 s."""
    from types import SimpleNamespace

    from voxe_core.progress import Progress
    from voxe_service.settings import Settings
    from worker import runtime

    now = [100.0]
    written = []
    monkeypatch.setattr(runtime, "time", SimpleNamespace(monotonic=lambda: now[0]))
    monkeypatch.setattr(runtime, "update_job", lambda job_id, **values: written.append(values["eta_seconds"]))
    callbacks = runtime.StageCallbacks(_job(state="running", stage="edit"), "edit", Settings(progress_interval_s=1e-9))
    for iteration in range(1, 11):
        now[0] += 2.0
        callbacks.on_progress(Progress("edit", iteration, 10))
    assert written == [None] + [2.0 * (10 - iteration) for iteration in range(2, 11)]


def test_a_database_outage_skips_a_stages_progress_write_and_cancel_check_and_the_next_ones_try_again(monkeypatch):
    """A database blip (a dropped connection, SQLite locked) during a long stage had failed its job at the next
    progress write or cancel check; each is skipped and the next tries again. A fault that is no outage (SQLite's
    OperationalError for a missing column) still raises."""
    import sqlite3
    from types import SimpleNamespace

    from sqlalchemy.exc import OperationalError

    from voxe_core.progress import Progress
    from voxe_service.settings import Settings
    from worker import runtime

    outage = OperationalError("UPDATE jobs", {}, sqlite3.OperationalError("database is locked"))
    fault = OperationalError("UPDATE jobs", {}, sqlite3.OperationalError("no such column: jobs.eta_seconds"))
    answers = [outage, None, fault]
    written = []

    def update_job(job_id, **values):
        if (answer := answers.pop(0)) is not None:
            raise answer
        written.append(values["iteration"])

    def session_scope():
        raise outage

    monkeypatch.setattr(runtime, "update_job", update_job)
    monkeypatch.setattr(runtime, "session_scope", session_scope)
    monkeypatch.setattr(runtime, "time", SimpleNamespace(monotonic=iter(range(100, 200)).__next__))
    callbacks = runtime.StageCallbacks(_job(state="running", stage="edit"), "edit",
                                       Settings(progress_interval_s=1e-9, cancel_check_interval_s=1e-9))
    callbacks.on_progress(Progress("edit", 1, 10))  # the database locked: skipped
    callbacks.on_progress(Progress("edit", 2, 10))  # written
    assert written == [2]
    assert callbacks.should_cancel() is False and callbacks.should_cancel() is False  # unread: the stage goes on
    with pytest.raises(OperationalError, match="no such column"):
        callbacks.on_progress(Progress("edit", 3, 10))


def test_the_workers_refine_eta_weighs_each_sub_steps_units_by_its_cost(monkeypatch):
    """The paper's fit (``lift_start`` constant) on a CPU: 32 attention passes, then 1,500 fitting steps 1/50 of a
    pass each. The worker's time left had counted every unit left at the current sub-step's rate: ~30x the truth
    while the passes run. A synthetic run whose sub-steps cost known times (each off the table by up to 1.3x, as a
    real machine's are) must be estimated within 2x at every report."""
    from types import SimpleNamespace

    from voxe_core.presets import refine_config
    from voxe_core.progress import Progress, in_phases
    from voxe_service.progress import refine_phase_seconds
    from voxe_service.settings import Settings
    from worker import runtime

    config = refine_config({"refine": {"lift_start": "constant", "iterations": 1500}}, "tiny")
    table = refine_phase_seconds(config.fit_views, DEVICE_COSTS["cpu"])
    true_seconds = {"attention_maps": table["attention_maps"] * 1.2, "backprojection": table["backprojection"] * 1.3,
                    "attention_grids": table["attention_grids"] * 0.8, "graph_cut": table["graph_cut"] * 1.3}
    units = {"attention_maps": config.views, "backprojection": 18, "attention_grids": config.iterations, "graph_cut": 1}
    now = [0.0]
    written = []
    monkeypatch.setattr(runtime, "time", SimpleNamespace(monotonic=lambda: now[0]))
    monkeypatch.setattr(runtime, "update_job", lambda job_id, **values: written.append(values["eta_seconds"]))
    callbacks = runtime.StageCallbacks(_job(state="running", stage="refine"), "refine",
                                       Settings(progress_interval_s=1e-9), phase_seconds=table)
    phases = in_phases(callbacks.callbacks, units)
    truth = []
    for phase, count in units.items():
        for done in range(1, count + 1):
            now[0] += true_seconds[phase]
            phases.progress(Progress(phase, done, count))
            truth.append(true_seconds[phase] * (count - done) + sum(
                true_seconds[later] * units[later] for later in list(units)[list(units).index(phase) + 1:]))
    assert len(written) == len(truth) == sum(units.values())
    assert all(estimate is not None for estimate in written[1:config.views])  # timed from each sub-step's 2nd report
    for estimate, left in zip(written, truth):
        if estimate is not None and left > 0:
            assert left / 2 <= estimate <= 2 * left, (estimate, left)


def test_a_job_that_ended_or_went_back_to_the_queue_keeps_the_fraction_it_reached():
    """A failed, canceled or re-queued job had dropped its current stage's share (a job canceled half way through
    its edit fell from about 0.5 to the reconstruction's share)."""
    from api.routes.jobs import job_out

    rec = Reconstruction(id="r", scene_id="s", params_key="k", params={}, state="succeeded", owner_job_id="j", total=200)
    half = dict(reconstruction=rec, stage="edit", iteration=50, total=100, completed_stages=["reconstruct"],
                started_at=utcnow(), stage_started_at=utcnow())
    running = job_out(_job(state="running", eta_seconds=30.0, **half))
    for state in ("failed", "canceled", "queued"):
        ended = job_out(_job(state=state, finished_at=utcnow() if state != "queued" else None, **half))
        assert ended.overall_progress == pytest.approx(running.overall_progress), state
        assert ended.overall_eta_seconds is None, state
    assert running.overall_eta_seconds is not None and 0.25 < running.overall_progress < 0.6


def test_the_stage_progress_stays_within_0_and_1_as_the_overall_one_does():
    """A row whose iteration had passed its total (or fallen below 0) gave a stage progress past 1 (below 0) beside
    an overall progress held within [0, 1]."""
    from api.routes.jobs import job_out

    rec = Reconstruction(id="r", scene_id="s", params_key="k", params={}, state="succeeded", owner_job_id="j", total=200)
    for iteration, progress in ((120, 1.0), (-5, 0.0), (50, 0.5)):
        job = job_out(_job(reconstruction=rec, state="running", stage="edit", iteration=iteration, total=100,
                           completed_stages=["reconstruct"], started_at=utcnow(), stage_started_at=utcnow()))
        assert job.progress == progress and 0 <= job.overall_progress <= 1, (iteration, job.progress)


def test_a_reused_reconstruction_weighs_nothing():
    from api.routes.jobs import job_out

    fitted_by_another = Reconstruction(id="r", scene_id="s", params_key="k", params={}, state="succeeded",
                                       owner_job_id="other", total=100_000)
    job = _job(reconstruction=fitted_by_another, state="running", stage="edit", iteration=50, total=100,
               completed_stages=["reconstruct"], started_at=utcnow(), stage_started_at=utcnow())
    costs = dict(stage_costs(mode="local", params=job.params, fit=NO_FIT))
    assert costs["reconstruct"] == 0
    expected = (costs["reconstruct"] + costs["edit"] / 2) / sum(costs.values())
    assert job_out(job).overall_progress == pytest.approx(expected)


def test_a_job_that_waited_for_another_jobs_fit_keeps_its_progress_when_the_fit_ends():
    """The job's reconstruct stage follows the other job's fit (iteration of total); once that fit has succeeded the
    waiting job's progress must not fall back as if the fit had been reused for free."""
    from api.routes.jobs import job_out

    began = utcnow() - timedelta(minutes=5)
    fitting = Reconstruction(id="r", scene_id="s", params_key="k", params={}, state="running", owner_job_id="other",
                             iteration=1800, total=2000)
    waiting = _job(reconstruction=fitting, state="running", stage="reconstruct", iteration=1800, total=2000,
                   started_at=began, stage_started_at=began)
    fitted = Reconstruction(id="r", scene_id="s", params_key="k", params={}, state="succeeded", owner_job_id="other",
                            iteration=2000, total=2000, finished_at=utcnow())
    edit_began = _job(reconstruction=fitted, state="running", stage="edit", iteration=0, total=100,
                      completed_stages=["reconstruct"], started_at=began, stage_started_at=utcnow())
    before, after = job_out(waiting).overall_progress, job_out(edit_began).overall_progress
    assert 0 < before <= after, (before, after)
    costs = dict(stage_costs(mode="local", params=waiting.params, fit=fit_work({}, steps=2000)))
    assert after == pytest.approx(costs["reconstruct"] / sum(costs.values()))


def test_a_job_that_reused_a_finished_fit_keeps_its_progress_when_another_job_fits_it_again():
    """A job that reused a fit finished before it began (its edit half done) had fallen back by the whole fit's share
    when another job found the grid deleted from the storage and fitted it again: the reconstruction pending (then
    running) again, and, once fitted, finished after the job began, as if the job had waited for it."""
    from api.routes.jobs import job_out

    began = utcnow() - timedelta(minutes=5)
    reused = dict(state="running", stage="edit", iteration=50, total=100, completed_stages=["reconstruct"],
                  reconstruction_reused=True, started_at=began, stage_started_at=began)
    fitted = Reconstruction(id="r", scene_id="s", params_key="k", params={}, state="succeeded", owner_job_id="other",
                            iteration=2000, total=2000, finished_at=began - timedelta(minutes=5))
    refitting = Reconstruction(id="r", scene_id="s", params_key="k", params={}, state="pending", owner_job_id=None,
                               iteration=0, total=0)
    refitted = Reconstruction(id="r", scene_id="s", params_key="k", params={}, state="succeeded",
                              owner_job_id="third", iteration=2000, total=2000, finished_at=utcnow())
    costs = dict(stage_costs(mode="local", params=_job().params, fit=NO_FIT))
    expected = (costs["edit"] / 2) / sum(costs.values())
    for rec in (fitted, refitting, refitted):
        assert job_out(_job(reconstruction=rec, **reused)).overall_progress == pytest.approx(expected), rec.state


def test_eta_scales_later_stages_by_the_current_stages_speed():
    costs = [("reconstruct", 10.0), ("edit", 80.0), ("export", 10.0)]
    args = dict(costs=costs, completed=["reconstruct"], stage="edit", stage_fraction=0.25, finished=False)
    assert overall(**args, stage_eta_s=60.0) == (0.3, 60.0 + 10.0)  # at the benchmark's speed: 60 s of its 60 left
    assert overall(**args, stage_eta_s=120.0) == (0.3, 120.0 + 20.0)  # twice as slow
    assert overall(**args, stage_eta_s=None) == (0.3, None)
    assert overall(**{**args, "stage_fraction": 0.0}, stage_eta_s=80.0)[1] == 80.0 + 10.0
    assert overall(**args, stage_eta_s=1.0)[0] == overall(**args, stage_eta_s=99.0)[0]  # speed: ETA only
    # The stage's last report (nothing of it left to time): the later stages at the table's speed.
    assert overall(**{**args, "stage_fraction": 1.0}, stage_eta_s=0.0) == (0.9, 10.0)
    assert overall(costs=costs, completed=[], stage=None, stage_fraction=0.0, stage_eta_s=None,
                   finished=True) == (1.0, 0.0)


def test_the_eta_at_a_stages_start_counts_neither_the_models_load_nor_a_resumed_runs_earlier_iterations():
    """The speed is the stage's own rate (the worker measures it from its first report), not the time since the
    stage began: a GPU edit's model load and 39 s encoder compile, timed against its first 10 of 8,000 iterations,
    had put ~1,500 s on the ~450 s left; and a run resuming at iteration 4,000 had timed 4,000 iterations by its
    5 s, leaving nothing for the later stages."""
    from api.routes.jobs import job_out

    rec = Reconstruction(id="r", scene_id="s", params_key="k", params={}, state="succeeded", owner_job_id="j",
                         total=2000)
    params = {"iterations": 8000}
    costs = dict(stage_costs(mode="local", params=params, fit=fit_work({}, steps=2000), device="cuda"))
    per_iteration = costs["edit"] / 8000  # this machine runs at the table's speed
    later = costs["refine"] + costs["export"]
    for iteration, began_s in ((10, 50.5), (4000, 5.0)):
        eta = (8000 - iteration) * per_iteration
        job = _job(reconstruction=rec, params=params, device="cuda", state="running", stage="edit",
                   iteration=iteration, total=8000, eta_seconds=eta, completed_stages=["reconstruct"],
                   started_at=utcnow() - timedelta(minutes=5), stage_started_at=utcnow() - timedelta(seconds=began_s))
        assert job_out(job).overall_eta_seconds == pytest.approx(eta + later), iteration


def test_a_fit_running_slower_than_the_table_does_not_stretch_the_later_stages():
    """A fit step costs what its scene keeps (a capture's ray 17.9x an object's): a slow fit says nothing of the
    edit."""
    costs = [("reconstruct", 10.0), ("edit", 80.0), ("export", 10.0)]
    fitting = dict(costs=costs, completed=[], stage="reconstruct", stage_fraction=0.5, stage_eta_s=50.0,
                   finished=False)
    assert overall(**fitting) == (0.05, 50.0 + 90.0)  # ten times the table's time: no matter
    assert overall(**{**fitting, "stage": "edit", "completed": ["reconstruct"], "stage_eta_s": 400.0}) == (
        0.5, 400.0 + 100.0)  # an edit ten times slower than the table: so is the export


def test_a_gpu_job_is_weighed_and_timed_by_the_gpu_table():
    """A worker on CUDA runs the edit ~34x faster than the CPU table says, the fit about as fast: a job it holds
    must not show the CPU's hours left while it fits, nor weigh its fit as nothing."""
    from api.routes.jobs import job_out

    params = JobParams().model_dump()
    rec = Reconstruction(id="r", scene_id="s", params_key="k", params={}, state="running", owner_job_id="j",
                         iteration=500, total=1000)
    began = utcnow() - timedelta(seconds=7)
    fitting = dict(reconstruction=rec, params=params, state="running", stage="reconstruct", iteration=500,
                   total=1000, eta_seconds=7.0, started_at=began, stage_started_at=began)
    on_gpu, on_cpu = job_out(_job(**fitting, device="cuda:0")), job_out(_job(**fitting, device="cpu"))
    gpu = dict(stage_costs(mode="local", params=params, fit=fit_work({}, steps=1000), device="cuda"))
    assert on_gpu.overall_eta_seconds == pytest.approx(7.0 + gpu["edit"] + gpu["refine"] + gpu["export"])
    assert on_gpu.overall_eta_seconds < 10 * 60 < 4 * 3600 < on_cpu.overall_eta_seconds  # 8,000 edit iterations
    assert on_gpu.overall_progress == pytest.approx(gpu["reconstruct"] / 2 / sum(gpu.values()))
    assert on_gpu.overall_progress > 10 * on_cpu.overall_progress


def test_a_capture_fit_recorded_by_the_worker_weighs_more_than_an_object_fit():
    from api.routes.jobs import job_out

    rec = Reconstruction(id="r", scene_id="s", params_key="k", params={}, state="running", owner_job_id="j",
                         iteration=600, total=1200)
    fitting = dict(reconstruction=rec, state="running", stage="reconstruct", iteration=600, total=1200,
                   started_at=utcnow(), stage_started_at=utcnow())
    recorded = {"fit": {"backbone": "scene", "steps": 1200, "rays_per_step": 2048}}
    capture, unrecorded = job_out(_job(**fitting, result=recorded)), job_out(_job(**fitting))
    costs = dict(stage_costs(mode="local", params=_job().params, fit=FitWork(1200, 2048, "scene")))
    assert capture.overall_progress == pytest.approx(costs["reconstruct"] / 2 / sum(costs.values()))
    assert capture.overall_progress > 2 * unrecorded.overall_progress  # read from params: fast's rays on an object


def test_the_overall_progress_and_eta_of_the_papers_refinement_track_its_time(monkeypatch):
    """The paper's fit (``lift_start`` constant) on a CPU, through the worker's records and the job resource: its
    32 attention passes take half the stage's time and 2% of its units. The overall fraction had counted the
    stage's units, and the time left scaled the later stages by the stage's pace against that count: the fraction
    was off by up to 0.16 of the whole job, the time left from a third short to 6x long. A synthetic run on a
    machine 1.5x slower than the table at every unit must be placed at the share of its time done, and its time
    left must be what is left, at every report (to rounding: while the stage's cost left out its back-projection
    and cut, 5% of it, they were off by up to 0.011 and 5%)."""
    from types import SimpleNamespace

    from api.routes.jobs import job_out
    from voxe_core.presets import refine_config, refine_phase_units
    from voxe_core.progress import Progress, in_phases
    from voxe_service.settings import Settings
    from worker import runtime

    params = {"iterations": 100, "refine": {"lift_start": "constant", "iterations": 1500}}
    config = refine_config(params, "tiny")
    units = refine_phase_units(params)  # as voxe_core.refine.pipeline.refine counts them
    table = refine_phase_seconds(config.fit_views, DEVICE_COSTS["cpu"])
    slower = 1.5
    rec = Reconstruction(id="r", scene_id="s", params_key="k", params={}, state="succeeded", owner_job_id="j", total=1)
    job = _job(reconstruction=rec, params=params, state="running", stage="refine", completed_stages=["reconstruct",
               "edit"], started_at=utcnow())
    costs = dict(stage_costs(mode="local", params=params, fit=fit_work({}, steps=1)))
    before = slower * (costs["reconstruct"] + costs["edit"])
    whole = before + slower * (sum(units[phase] * table[phase] for phase in units) + costs["export"])
    now = [0.0]
    monkeypatch.setattr(runtime, "time", SimpleNamespace(monotonic=lambda: now[0]))
    monkeypatch.setattr(runtime, "update_job", lambda job_id, **values: [setattr(job, key, value)
                                                                         for key, value in values.items()])
    callbacks = runtime.StageCallbacks(job, "refine", Settings(progress_interval_s=1e-9), phase_seconds=table)
    phases = in_phases(callbacks.callbacks, units)
    worst_fraction = worst_eta = 0.0
    for phase, count in units.items():
        for done in range(1, count + 1):
            now[0] += slower * table[phase]
            phases.progress(Progress(phase, done, count))
            shown = job_out(job)
            elapsed = before + now[0]
            worst_fraction = max(worst_fraction, abs(shown.overall_progress - elapsed / whole))
            if shown.overall_eta_seconds is not None:
                worst_eta = max(worst_eta, abs(shown.overall_eta_seconds / (whole - elapsed) - 1))
    assert worst_fraction <= 1e-9 and worst_eta <= 1e-9, (worst_fraction, worst_eta)
