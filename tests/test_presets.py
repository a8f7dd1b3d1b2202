"""One presets module: the CLI's options and the service's job parameters give the same stage configs,
and a real-scene job (scene-backbone G_i) gets SPEC §5's edit schedule through the worker.

The worker tests run the real Celery task bodies in-process (``task.apply``) on a throwaway embedded
service with the random-weight SMOKE-TEST model: they prove which configs the worker builds, never quality.
"""

from __future__ import annotations

import dataclasses
import re
from datetime import timedelta
from types import SimpleNamespace

import pytest
import torch
from fastapi.testclient import TestClient

from api.schemas import JobParams
from needs import require_data
from service_helpers import (
    MIC, TINY_FIT, failing_uploads, ingest, reset_service_caches, service_env, small_mic, zip_folder,
)
from voxe_core import presets
from voxe_core.cli import build_parser
from voxe_core.cli import edit as edit_command
from voxe_core.cli import reconstruct as reconstruct_command
from voxe_core.cli import refine as refine_command
from voxe_core.constants import ATTENTION_MODEL_ID, EDIT_ITERATIONS
from voxe_core.presets import (
    EDIT_SCHEDULES,
    ExportConfig,
    edit_config,
    export_config,
    reconstruct_config,
    reconstruction_key,
    reconstruction_params,
    refine_config,
)
from voxe_core.schedule import AUTHORS_FLOOR, PAPER_FLOOR, TimestepSchedule

# What the worker reads of its guidance around an edit that a test records instead of running: no compile.
NO_MODEL = SimpleNamespace(encoder_compile_seconds=None)

EDIT = ["edit", "g.safetensors", "--prompt", "a dog", "--out", "o"]
REFINE = ["refine", "e.safetensors", "--initial", "g.safetensors", "--prompt", "a dog in a hat", "--edit-words", "hat",
          "--out", "o"]

# (CLI options, the same parameters as the service's JSON); the first of each pair: all defaults.
EDIT_CASES = [
    ([], {}),
    (["--iterations", "120", "--render-size", "64", "--guidance-scale", "7.5", "--lr", "0.01", "--regulariser",
      "volumetric_l2", "--reg-weight", "3", "--schedule", "authors", "--batch-size", "2", "--autocast", "bf16",
      "--seed", "5", "--preview-every", "7", "--no-view-words"],
     {"iterations": 120, "render_size": 64, "guidance_scale": 7.5, "lr": 0.01, "regulariser": "volumetric_l2",
      "regulariser_weight": 3, "timestep_schedule": "authors", "batch_size": 2, "autocast": "bf16", "seed": 5,
      "preview_every": 7, "view_words": False}),
    (["--iterations", str(EDIT_ITERATIONS)], {"iterations": EDIT_ITERATIONS}),
]
REFINE_CASES = [
    ([], {}),
    (["--iterations", "40", "--lr", "0.1", "--tv-weight", "0.5", "--render-size", "96", "--views", "6", "--rays", "512",
      "--edit-seeds", "9", "--object-seeds", "8", "--sigma", "0.3", "--smoothness", "2", "--seed", "4"],
     {"seed": 4, "refine": {"iterations": 40, "lr": 0.1, "tv_weight": 0.5, "render_size": 96, "views": 6,
                            "rays_per_step": 512, "edit_seeds": 9, "object_seeds": 8, "sigma": 0.3, "smoothness": 2}}),
    (["--no-view-words"], {"view_words": False}),  # the attention prompt as the edit's (refine had no such option)
]
RECONSTRUCT_CASES = [
    ([], {}),
    (["--downsample", "8", "--resample", "box", "--max-images", "5", "--preset", "paper", "--resolution", "96",
      "--iterations", "7", "--rays", "1024", "--seed", "3", "--backbone", "scene"],
     {"downsample": 8, "resample": "box", "max_images": 5, "reconstruction": {
         "preset": "paper", "resolution": 96, "iterations": 7, "rays_per_step": 1024, "seed": 3, "backbone": "scene"}}),
    (["--iterations", "3,4,5"], {"reconstruction": {"iterations": [3, 4, 5]}}),
]


def service_json(params: dict) -> dict:
    """The job parameters as the API stores them: validated, every default filled in."""
    return JobParams.model_validate(params).model_dump(mode="json")


@pytest.mark.parametrize("options,params", EDIT_CASES)
@pytest.mark.parametrize("backbone", ["relu_field", "scene"])
def test_the_cli_and_the_service_build_the_same_edit(options, params, backbone):
    args = build_parser().parse_args([*EDIT, *options])
    cli = edit_config(edit_command.job_params(args), backbone, checkpoint_every=25)
    assert cli == edit_config(service_json(params), backbone, checkpoint_every=25)


@pytest.mark.parametrize("options,params", REFINE_CASES)
def test_the_cli_and_the_service_build_the_same_refinement(options, params):
    args = build_parser().parse_args([*REFINE, *options])
    cli = refine_config(refine_command.job_params(args), ATTENTION_MODEL_ID)
    assert cli == refine_config(service_json(params), ATTENTION_MODEL_ID)


@pytest.mark.parametrize("options,params", RECONSTRUCT_CASES)
def test_the_cli_and_the_service_fit_the_same_reconstruction(options, params):
    """Same parameters, same recipe and the same cache key (so a CLI fit could be the service's)."""
    args = build_parser().parse_args(["reconstruct", "data", "--out", "g.safetensors", *options])
    cli = reconstruction_params(reconstruct_command.job_params(args))
    service = reconstruction_params(service_json(params))
    assert cli == service and reconstruction_key(cli) == reconstruction_key(service)
    assert reconstruct_config(cli, 10) == reconstruct_config(service, 10)


def _shared_defaults(cli: dict, service: dict, where: str = "") -> dict:
    """Dotted name -> (CLI default, service default) of every parameter both set (None: left to presets, as the
    refinement's render size that is the edit's)."""
    pairs = {}
    for name, value in cli.items():
        if isinstance(value, dict):
            pairs.update(_shared_defaults(value, service[name], f"{where}{name}."))
        elif value is not None and service[name] is not None:
            pairs[where + name] = (value, service[name])
    return pairs


@pytest.mark.parametrize("command,module", [(EDIT, edit_command), (REFINE, refine_command),
                                            (["reconstruct", "d", "--out", "g.safetensors"], reconstruct_command)])
def test_each_default_the_cli_and_the_job_schema_share_is_the_presets_one(command, module):
    """Defaults live in presets: the CLI's options, the API's schema and the stage configs built from parameters
    that leave one out agree (a literal written in one of them had drifted from the others silently)."""
    service = service_json({})
    shared = _shared_defaults(module.job_params(build_parser().parse_args(command)), service)
    assert shared
    assert {name: cli for name, (cli, _) in shared.items()} == {name: api for name, (_, api) in shared.items()}
    named = {"batch_size": presets.BATCH_SIZE, "view_words": presets.VIEW_WORDS, "seed": presets.SEED,
             "preview_every": presets.PREVIEW_EVERY, "timestep_schedule": presets.TIMESTEP_SCHEDULES[0],
             "downsample": presets.DOWNSAMPLE, "resample": presets.RESAMPLE, "refine.lift_start": presets.LIFT_START,
             "reconstruction.backbone": presets.BACKBONE, "reconstruction.seed": presets.SEED}
    assert {path: value for path, (value, _) in shared.items() if path in named} == {
        path: value for path, value in named.items() if path in shared}
    assert edit_config({}) == edit_config(service)  # the fallbacks of parameters left out
    assert refine_config({}, ATTENTION_MODEL_ID) == refine_config(service, ATTENTION_MODEL_ID)
    assert reconstruction_params({}) == reconstruction_params(service)


def test_the_backbone_choices_are_the_presets_ones_and_the_core_registrys():
    """The kinds presets spell out (it cannot import torch) are the registry's, and the CLI and both schemas offer
    exactly them (each had its own literal tuple)."""
    import typing

    from api.schemas import ReconstructionParams, SceneOut
    from voxe_core.backbones import BACKBONE_CHOICES, BACKBONES

    assert presets.BACKBONE_KINDS == tuple(BACKBONES) and presets.BACKBONE_CHOICES == BACKBONE_CHOICES
    parser = build_parser()
    choices = {action.dest: action.choices for action in parser._subparsers._group_actions[0].choices[
        "reconstruct"]._actions}
    assert tuple(choices["backbone"]) == presets.BACKBONE_CHOICES == ("auto", *BACKBONES)
    assert typing.get_args(ReconstructionParams.model_fields["backbone"].annotation) == presets.BACKBONE_CHOICES
    decided = typing.get_args(SceneOut.model_fields["backbone"].annotation)
    assert typing.get_args(decided[0]) == presets.BACKBONE_KINDS and decided[1] is type(None)


def test_a_submitted_jobs_default_mode_is_the_presets_one():
    from api.schemas import JobCreate

    submit = build_parser().parse_args(["submit", "a dog", "--scene", "s1"])
    assert submit.mode == JobCreate.model_fields["mode"].default == presets.EDIT_MODE


@pytest.mark.parametrize("params,message", [
    ({"resolution": "96"}, "resolution takes whole numbers, got '96'"),  # had been the stages (9, 6)
    ({"iterations": "50"}, "iterations takes whole numbers, got '50'"),  # had been (5, 0)
    ({"resolution": 96.0}, "resolution takes whole numbers, got 96.0"),  # had been a TypeError
    ({"resolution": True}, "resolution takes whole numbers, got True"),
    ({"iterations": [5, 2.5]}, "iterations takes whole numbers, got 2.5"),
    ({"rays_per_step": 2.9}, "rays_per_step takes whole numbers, got 2.9"),  # had been 2
])
def test_a_reconstruction_value_that_is_no_whole_number_is_refused_by_name(params, message):
    with pytest.raises(ValueError, match=message):
        reconstruct_config(params, backbone="scene")
    given = {"resolution": (48, 96), "iterations": [3, 4], "rays_per_step": 64}  # ints, in a list or a tuple
    assert reconstruct_config(given, backbone="scene").resolutions == (48, 96)


def test_default_downsampling_is_the_papers_everywhere():
    parser = build_parser()
    for command in (["reconstruct", "d", "--out", "g.safetensors"], ["render", "g", "--data", "d", "--out", "o"], EDIT,
                    ["evaluate", "g", "--edit", "e", "p", "--object", "mic", "--out", "o"]):
        assert parser.parse_args(command).downsample == 3 == service_json({})["downsample"], command


def test_export_parameters_are_the_export_config():
    assert service_json({})["export"] == dataclasses.asdict(ExportConfig())
    given = {"views": 0, "view_size": 64, "turntable_frames": 5, "turntable_size": 32, "elevation": -10.0, "fps": 12.0,
             "gif": False, "mesh": False, "mesh_resolution": 40}
    assert export_config(service_json({"export": given})) == ExportConfig(**given)
    assert export_config({}) == ExportConfig()
    parser = build_parser()
    turntable = parser.parse_args(["turntable", "g", "--out", "t.mp4"])
    assert (turntable.frames, turntable.size, turntable.elevation, turntable.fps) == (100, 256, 30.0, 30.0)


# ------------------------------------------------------------------ what submission accepts, the stages take
def _limit_cases() -> list[tuple[str, object]]:
    """(dotted field, value) at each numeric bound JobParams' JSON schema states, and just past it (the next integer,
    or the next float), for every field of the parameters and their reconstruction, refine and export sections."""
    import math

    definitions = JobParams.model_json_schema()["$defs"]
    sections = {"": JobParams.model_json_schema(), "reconstruction.": definitions["ReconstructionParams"],
                "refine.": definitions["RefineParams"], "export.": definitions["ExportParams"]}
    cases = []
    for prefix, schema in sections.items():
        for name, field in schema["properties"].items():
            for option in field.get("anyOf", [field]):
                if option.get("type") not in ("integer", "number"):
                    continue
                step = (lambda v, d: v + d) if option["type"] == "integer" else (
                    lambda v, d: math.nextafter(v, d * math.inf))
                for key, inward in (("minimum", 1), ("exclusiveMinimum", 1), ("maximum", -1), ("exclusiveMaximum", -1)):
                    if key in option:
                        at = option[key] if "exclusive" not in key else step(option[key], inward)
                        cases += [(prefix + name, at), (prefix + name, step(at, -inward))]
    return cases


def _params(dotted: str, value, **more) -> dict:
    section, _, name = dotted.rpartition(".")
    given = {name: value} if not section else {section: {name: value}}
    for key, extra in more.items():
        given[key] = {**given.get(key, {}), **extra} if isinstance(extra, dict) else extra
    return given


# Combinations of limits: a preset and its overrides, the refinement's start and fitting, the render size the
# back-projection's stride reads, iteration counts and preview intervals, the slowest and fastest videos, seeds.
COMBINATIONS = [
    *({"reconstruction": {"preset": preset, "resolution": resolution, "iterations": iterations}}
      for preset in ("fast", "paper", "scene") for resolution in (4, 512) for iterations in (0, 1_000_000)),
    {"reconstruction": {"preset": "paper", "iterations": [0, 1, 2, 1_000_000]}},
    {"reconstruction": {"iterations": [1, 2]}}, {"reconstruction": {"iterations": [1, 2, 3]}},
    {"render_size": 8, "mode": "local"}, {"render_size": 8, "refine": {"render_size": 8, "smoothing_sigma": 16}},
    {"refine": {"lift_start": "constant", "iterations": 0}}, {"refine": {"lift_start": "constant", "iterations": 1}},
    {"iterations": 0, "preview_every": 200_000}, {"iterations": 200_000, "preview_every": 1},
    {"export": {"fps": 100 / 65535, "turntable_frames": 1000}}, {"export": {"fps": 120, "turntable_frames": 1}},
    {"seed": 2**32 - 1, "reconstruction": {"seed": 2**32 - 1}}, {"seed": 2**32},
    *({"max_images": count, "reconstruction": {"backbone": backbone}}
      for count in (1, 2) for backbone in ("relu_field", "scene")),
]


def _submitted(params: dict, scene_backbone: str) -> bool:
    """Whether POST /v1/jobs takes ``params`` on a ready scene of ``scene_backbone``: the body's validation, then
    the reconstruction's check against the scene (``api.services.jobs.usable_scene``)."""
    from pydantic import ValidationError

    from api.schemas import JobCreate
    from voxe_core.presets import check_fit

    mode = params.pop("mode", "global")
    words = ["hat"] if mode == "local" else []
    try:
        body = JobCreate(scene_id="s", prompt="a mic wearing a hat", mode=mode, edit_words=words, params=params)
        check_fit(reconstruction_params(body.params.model_dump(mode="json")), scene_backbone)
    except (ValidationError, ValueError):
        return False
    return True


def _every_stage_builds(params: dict, scene_backbone: str) -> None:
    """What the worker builds from a job's parameters, each stage's config (the fit's backbone set up for cameras
    on a ring, as many as max_images keeps) and the export's videos, cameras and rings; raises what it would."""
    from voxe_core.backbones import prepare_backbone
    from voxe_core.export import VideoWriter, turntable_cameras
    from voxe_core.presets import fit_backbone

    params = JobParams.model_validate(params).model_dump(mode="json")
    rec_params = reconstruction_params(params)
    backbone = fit_backbone(rec_params, scene_backbone)
    config = reconstruct_config(rec_params, 1, backbone)
    prepare_backbone(backbone, None, turntable_cameras(min(params["max_images"] or 4, 4), 30.0, 8),
                     config.resolutions[0])
    edit_config(params, backbone, checkpoint_every=1)
    refine_config(params, ATTENTION_MODEL_ID)
    export = export_config(params)
    for suffix in ("mp4", "gif"):
        VideoWriter(f"turntable.{suffix}", export.turntable_frames, export.fps)
    turntable_cameras(export.turntable_frames, export.elevation, export.turntable_size)
    if export.views:
        turntable_cameras(export.views, export.elevation, export.view_size)


@pytest.mark.parametrize("scene_backbone", ["relu_field", "scene"])
def test_parameters_at_and_past_each_limit_are_refused_at_submission_or_build_every_stage(scene_backbone):
    """A job the API accepts must not fail in the worker for its parameters (after its fit, its edit...): each
    value at and just past a bound the schema states, and the combinations above, is either refused at submission
    or builds every stage the worker runs."""
    cases = [_params(dotted, value) for dotted, value in _limit_cases()] + COMBINATIONS
    assert len(cases) > 150  # every section's bounds were found
    accepted = 0
    for given in cases:
        given = {k: (dict(v) if isinstance(v, dict) else v) for k, v in given.items()}
        if not _submitted(dict(given), scene_backbone):
            continue
        given.pop("mode", None)
        try:
            _every_stage_builds(given, scene_backbone)
        except ValueError as exc:
            pytest.fail(f"accepted at submission on a {scene_backbone} scene, refused by the worker: {given}: {exc}")
        accepted += 1
    assert accepted > len(cases) / 2  # the property was not met by refusing everything


def test_a_stage_configs_rule_no_bound_states_is_refused_at_submission_at_its_section(monkeypatch):
    """Submission builds each stage's config as the worker will (``voxe_core.presets.check_stage``): a rule of a
    config that no bound of the job parameters states (RefineConfig's constant start without fitting; made up here:
    render sizes and frame rates in multiples of 8) is a 422 located at the stage's section of the parameters (the
    refinement's had been at ``params``, naming the config's init_value), rather than a job failing after its fit."""
    from pydantic import ValidationError

    from api.schemas import JobCreate
    from voxe_core import presets
    from voxe_core.edit import EditConfig
    from voxe_core.refine.config import RefineConfig

    def refusal(params: dict) -> tuple[tuple, str]:
        with pytest.raises(ValidationError) as refused:
            JobCreate(scene_id="s", prompt="a mic", params=params)
        (error,) = refused.value.errors()
        return error["loc"], error["msg"]

    loc, message = refusal({"refine": {"lift_start": "constant"}})
    assert loc == ("params", "refine")
    assert message.startswith("Value error, refine: lift_start='constant' with iterations=0 leaves both attention "
                              "grids at their constant start") and "init_value" not in message

    def in_eights(real, what: str):
        def stricter(self):
            real(self)
            if getattr(self, what) % 8:
                raise ValueError(f"{what} must be a multiple of 8, got {getattr(self, what)}")
        return stricter

    with monkeypatch.context() as patched:  # the refinement's render size is the edit's by default
        patched.setattr(RefineConfig, "__post_init__", in_eights(RefineConfig.__post_init__, "render_size"))
        assert refusal({"render_size": 100}) == (("params", "refine"),
                                                 "Value error, refine: render_size must be a multiple of 8, got 100")
        assert JobCreate(scene_id="s", prompt="a mic", params={"render_size": 96}).params.render_size == 96
    with monkeypatch.context() as patched:
        patched.setattr(EditConfig, "__post_init__", in_eights(EditConfig.__post_init__, "render_size"))
        assert refusal({"render_size": 100}) == (("params",), "Value error, edit: render_size must be a multiple of 8, "
                                                              "got 100")
    real_fps_check = presets.check_video_fps

    def fps_in_eights(fps: float) -> None:
        real_fps_check(fps)
        if fps % 8:
            raise ValueError(f"fps must be a multiple of 8, got {fps:g}")

    monkeypatch.setattr(presets, "check_video_fps", fps_in_eights)
    assert refusal({"export": {"fps": 12.0}}) == (("params", "export"),
                                                  "Value error, export: fps must be a multiple of 8, got 12")
    assert JobCreate(scene_id="s", prompt="a mic", params={"export": {"fps": 16.0}}).params.export.fps == 16


# ------------------------------------------------------------------ SPEC §5 for real scenes
def test_a_scene_backbone_gets_the_real_scene_schedule_and_objects_keep_the_papers():
    objects, scene = edit_config(service_json({})), edit_config(service_json({}), backbone="scene")
    assert (objects.iterations, objects.schedule) == (8000, TimestepSchedule())
    assert (objects.schedule.i_start, objects.schedule.every) == (4000, 600)
    assert (scene.iterations, scene.schedule.i_start, scene.schedule.every, scene.schedule.floor) == (
        5000, 3000, 400, PAPER_FLOOR)
    assert dataclasses.replace(scene, iterations=8000, schedule=TimestepSchedule()) == objects  # nothing else moves
    authors = edit_config(service_json({"timestep_schedule": "authors"}), backbone="scene")
    assert (authors.schedule.i_start, authors.schedule.every, authors.schedule.floor) == (3000, 400, AUTHORS_FLOOR)
    # An explicit count other than the object default runs as given, with the real-scene annealing.
    short = edit_config(service_json({"iterations": 300}), backbone="scene")
    assert (short.iterations, short.schedule.i_start) == (300, 3000)
    assert EDIT_SCHEDULES["scene"].iterations == 5000
    with pytest.raises(ValueError, match="unknown timestep_schedule 'fast'"):
        edit_config({"timestep_schedule": "fast"})


@pytest.fixture
def service(tmp_path, monkeypatch):
    """An embedded service (no worker process) with a 3-view mic scene; yields (client, scene id)."""
    require_data(MIC)
    for key, value in service_env(tmp_path, VOXE_CHECKPOINT_EVERY=str(CHECKPOINT_EVERY)).items():
        monkeypatch.setenv(key, value)
    reset_service_caches()
    from api.main import create_app

    archive = zip_folder(small_mic(tmp_path / "mic_small"), tmp_path / "mic.zip", prefix="mic_small")
    with TestClient(create_app()) as client:
        with open(archive, "rb") as handle:
            response = client.post("/v1/scenes", files={"archive": ("mic.zip", handle, "application/zip")})
        assert response.status_code == 201, response.text
        scene_id = response.json()["id"]
        assert ingest(scene_id)["state"] == "ready"  # in-process: no worker takes the ingest off the queue
        yield client, scene_id
    reset_service_caches()


CHECKPOINT_EVERY = 50


def _reconstructed_job(client, scene_id: str, backbone: str, job_fields: dict | None = None, **params) -> dict:
    """A job (of "a mic", unless ``job_fields`` say otherwise) whose reconstruct task ran for real (a tiny fit of the
    given backbone)."""
    from worker import tasks

    stages = 2 if backbone == "scene" else 3  # the stage count of the backbone's default preset
    fit = TINY_FIT["reconstruction"]
    body = {**TINY_FIT, **params, "reconstruction": {**fit, "backbone": backbone,
                                                     "iterations": fit["iterations"][-stages:]}}
    job = client.post("/v1/jobs", json={"scene_id": scene_id, "prompt": "a mic", **(job_fields or {}),
                                        "params": body}).json()
    assert tasks.reconstruct_task.apply(args=(job["id"],)).get()["state"] == "done"
    return job


def _stored_edit_checkpoint(job_id: str, data: bytes) -> str:
    """``data`` stored and recorded as the job's live edit checkpoint, as an earlier run holding the job left it; its
    key."""
    from voxe_service.storage import get_storage, job_key
    from worker import runtime

    key = job_key(job_id, "checkpoints/an-earlier-run/edit.safetensors")
    get_storage().put_bytes(key, data)
    runtime.update_job(job_id, checkpoint_key=key)
    return key


def test_the_fit_and_the_edit_it_leads_to_are_recorded_before_the_fit_runs(service, monkeypatch):
    """Progress weighs a capture's fit (its rays cost 17.9x an object's) and its 5,000-iteration edit while it
    fits, not once the fit has ended (voxe_service.progress reads both from the job's result)."""
    import voxe_core.reconstruct
    from worker import tasks

    client, scene_id = service
    body = {**TINY_FIT, "reconstruction": {**TINY_FIT["reconstruction"], "backbone": "scene", "iterations": [2, 3]}}
    job = client.post("/v1/jobs", json={"scene_id": scene_id, "prompt": "a mic", "params": body}).json()
    seen, fit = {}, voxe_core.reconstruct.reconstruct

    def observed(*args, **kwargs):
        seen["result"] = client.get(f"/v1/jobs/{job['id']}").json()["result"]
        return fit(*args, **kwargs)

    monkeypatch.setattr(voxe_core.reconstruct, "reconstruct", observed)
    assert tasks.reconstruct_task.apply(args=(job["id"],)).get()["state"] == "done"
    assert seen["result"]["fit"] == {"backbone": "scene", "steps": 5, "rays_per_step": 64}
    assert (seen["result"]["edit_schedule"]["backbone"], seen["result"]["edit_schedule"]["iterations"]) == ("scene",
                                                                                                           5000)


@pytest.mark.parametrize("backbone,iterations,i_start,every", [("scene", 5000, 3000, 400), ("relu_field", 8000, 4000, 600)])
def test_the_worker_edits_a_scene_grid_with_the_real_scene_schedule(service, monkeypatch, backbone, iterations,
                                                                    i_start, every):
    """Default job parameters through the worker: the edit task builds SPEC §5's config for a scene G_i."""
    import voxe_core.edit
    from worker import runtime, tasks

    client, scene_id = service
    job = _reconstructed_job(client, scene_id, backbone)
    known = client.get(f"/v1/jobs/{job['id']}").json()["result"]["edit_schedule"]  # from the reconstruct stage
    assert (known["backbone"], known["iterations"], known["i_start"], known["every"]) == (backbone, iterations,
                                                                                          i_start, every)
    seen = {}

    def recorded_edit(initial, prompt, guidance, config, *args, **kwargs):
        seen["kind"], seen["config"] = initial.kind, config
        return initial.clone_grid()

    monkeypatch.setattr(runtime, "get_guidance", lambda *args: NO_MODEL)  # the recorded edit needs no model
    monkeypatch.setattr(voxe_core.edit, "edit", recorded_edit)
    assert tasks.edit_task.apply(args=(job["id"],)).get()["state"] == "done"
    config = seen["config"]
    assert seen["kind"] == backbone
    assert (config.iterations, config.schedule.i_start, config.schedule.every) == (iterations, i_start, every)
    assert config == edit_config(service_json({**TINY_FIT, "reconstruction": {**TINY_FIT["reconstruction"],
                                                                              "backbone": backbone}}),
                                 backbone, CHECKPOINT_EVERY)


@pytest.mark.parametrize("tiny", [True, False])
def test_the_workers_edit_with_a_tiny_model_folder_says_it_is_a_smoke_test(service, monkeypatch, tmp_path, tiny):
    """``VOXE_SDS_MODEL`` a folder ``voxe build-tiny-model`` wrote: the job had shown its path alone, nothing saying
    the edit is random-weight plumbing. The worker loading it says so once (its redelivery not again), as a warning
    event and in ``result.smoke_test``; a real-looking folder without the mark, neither."""
    import json

    import voxe_core.edit
    from voxe_core.backbones import grid_notes
    from voxe_core.tiny_sd import build_tiny_stable_diffusion
    from voxe_service.settings import get_settings
    from worker import tasks

    folder = build_tiny_stable_diffusion(tmp_path / "sd")
    if not tiny:
        index = json.loads((folder / "model_index.json").read_text())
        (folder / "model_index.json").write_text(json.dumps({**index, "_name_or_path": "someone/real-sd"}))
        (folder / "README.md").unlink(missing_ok=True)
    monkeypatch.setattr(get_settings(), "sds_model", str(folder))
    client, scene_id = service
    job = _reconstructed_job(client, scene_id, "relu_field")
    monkeypatch.setattr(voxe_core.edit, "edit", lambda initial, *args, **kwargs: initial.clone_grid())
    assert tasks.edit_task.apply(args=(job["id"],)).get()["state"] == "done"
    tasks.edit_task.apply(args=(job["id"],)).get()  # redelivered
    note = (f"SMOKE TEST: the sds model {str(folder)!r} is a random-weight smoke-test Stable Diffusion (voxe "
            "build-tiny-model): what is made with it proves the plumbing only and says nothing about edit quality")
    warnings = [(e["stage"], e["detail"]) for e in client.get(f"/v1/jobs/{job['id']}/events").json()
                if e["kind"] == "warning"]
    result = client.get(f"/v1/jobs/{job['id']}").json()["result"]
    assert warnings == ([("edit", note)] if tiny else [])
    assert result.get("smoke_test") == ({"sds": note} if tiny else None)
    edited = tmp_path / "edited.safetensors"  # the artifact carries it too, as voxe edit's
    edited.write_bytes(client.get(f"/v1/jobs/{job['id']}/artifacts/edited_grid.safetensors").content)
    assert grid_notes(edited) == ({"smoke_test": note} if tiny else {})


@pytest.mark.parametrize("setting", [None, "true"])
def test_the_workers_edit_marches_fused_as_its_setting_says(service, monkeypatch, setting):
    """``VOXE_FUSED_MARCHER`` (a worker's, off by default) reaches the edit's render config, and only it: the rest
    of the config is the job parameters' (the recipe leaves the marcher out, so checkpoints carry over)."""
    import voxe_core.edit
    from voxe_service.settings import get_settings
    from worker import runtime, tasks

    client, scene_id = service
    job = _reconstructed_job(client, scene_id, "relu_field")
    if setting is not None:
        monkeypatch.setenv("VOXE_FUSED_MARCHER", setting)
        get_settings.cache_clear()  # read again, as a worker started with it would
    seen = []

    def recorded_edit(initial, prompt, guidance, config, *args, **kwargs):
        seen.append(config)
        return initial.clone_grid()

    monkeypatch.setattr(runtime, "get_guidance", lambda *args: NO_MODEL)
    monkeypatch.setattr(voxe_core.edit, "edit", recorded_edit)
    assert tasks.edit_task.apply(args=(job["id"],)).get()["state"] == "done"
    (config,) = seen
    expected = edit_config(service_json(TINY_FIT), "relu_field", CHECKPOINT_EVERY)
    assert config.render.fused is (setting == "true") and config.recipe() == expected.recipe()


def test_a_worker_whose_fused_marcher_cannot_run_says_so(service, monkeypatch, caplog):
    """VOXE_FUSED_MARCHER on a CPU worker (no Triton interpreter): the packed renderer renders, and the log says why."""
    import voxe_core.edit
    from voxe_service.settings import get_settings
    from worker import runtime, tasks

    client, scene_id = service
    job = _reconstructed_job(client, scene_id, "relu_field")
    monkeypatch.setenv("VOXE_FUSED_MARCHER", "true")
    monkeypatch.delenv("TRITON_INTERPRET", raising=False)
    get_settings.cache_clear()
    monkeypatch.setattr(runtime, "get_guidance", lambda *args: NO_MODEL)
    monkeypatch.setattr(voxe_core.edit, "edit", lambda initial, *args, **kwargs: initial.clone_grid())
    with caplog.at_level("WARNING", logger="voxe.worker"):
        assert tasks.edit_task.apply(args=(job["id"],)).get()["state"] == "done"
    assert f"job {job['id']}: VOXE_FUSED_MARCHER is on, but Triton does not run on cpu here" in caplog.text


def _edit_checkpoint(path, **recipe) -> bytes:
    """A readable edit checkpoint of EditConfig()'s recipe, with ``recipe``'s fields changed."""
    from voxe_core.edit import EditConfig, save_edit_checkpoint
    from voxe_core.grid import VoxelGrid

    grid = VoxelGrid(4)
    save_edit_checkpoint(path, grid, torch.optim.Adam([grid.flat_features]), {}, 2,
                         {"recipe": {**EditConfig().recipe(), **recipe}})
    return path.read_bytes()


def _checkpoint_of_another_recipe(path) -> bytes:
    """A readable edit checkpoint made with guidance scale 7.5 (a worker of another version's default, say)."""
    return _edit_checkpoint(path, guidance_scale=7.5)


@pytest.mark.parametrize("stored, why", [
    (lambda tmp: b"not a safetensors file", "was unreadable"),
    (lambda tmp: _checkpoint_of_another_recipe(tmp / "other.safetensors"), "was made with another recipe"),
])
def test_a_damaged_or_foreign_edit_checkpoint_is_dropped_and_the_edit_starts_over(service, monkeypatch, tmp_path,
                                                                                    stored, why):
    """A redelivered edit whose stored checkpoint cannot be read, or was made with another recipe (a worker of
    another version, mid rolling upgrade: edit() refuses to resume it), runs from the start instead of failing every
    redelivery: the object is deleted, the job's record of it cleared as the run starts over (it had named the
    deleted object until the run's first checkpoint), and the job says why."""
    import voxe_core.edit
    from voxe_service.storage import get_storage
    from worker import runtime, tasks

    client, scene_id = service
    job = _reconstructed_job(client, scene_id, "relu_field")
    key = _stored_edit_checkpoint(job["id"], stored(tmp_path))
    seen = {}

    def recorded_edit(initial, prompt, guidance, config, callbacks, checkpoint_path, resume_from, **kwargs):
        seen.update(resume_from=resume_from, recorded=runtime.load_job(job["id"]).checkpoint_key)
        return initial.clone_grid()

    monkeypatch.setattr(runtime, "get_guidance", lambda *args: NO_MODEL)
    monkeypatch.setattr(voxe_core.edit, "edit", recorded_edit)
    assert tasks.edit_task.apply(args=(job["id"],)).get()["state"] == "done"
    assert seen == {"resume_from": None, "recorded": None}
    assert not get_storage().exists(key)
    events = client.get(f"/v1/jobs/{job['id']}/events").json()
    assert not any(e["kind"] == "resumed" and e.get("stage") == "edit" for e in events), events
    assert client.get(f"/v1/jobs/{job['id']}").json()["message"].startswith(f"the stored edit checkpoint {why}")


def test_an_edit_that_cannot_go_on_from_its_checkpoint_starts_over(service, monkeypatch, tmp_path):
    """A readable checkpoint of the same recipe that edit() still refuses to resume (other input views, prompt or
    initial grid: a FormatError) had failed the job on every redelivery: the edit runs again from its start, as a
    reconstruction does."""
    import voxe_core.edit
    from voxe_core.progress import Progress
    from voxe_core.tensorio import FormatError
    from voxe_service.storage import get_storage
    from worker import runtime, tasks

    client, scene_id = service
    job = _reconstructed_job(client, scene_id, "relu_field")
    key = _stored_edit_checkpoint(job["id"], _edit_checkpoint(tmp_path / "ours.safetensors"))
    resumed_from, during = [], {}

    def refusing_resume(initial, prompt, guidance, config, callbacks, checkpoint_path, resume_from, **kwargs):
        resumed_from.append(resume_from)
        if resume_from is not None:
            raise FormatError("checkpoint was made against other input views")
        during.update(job=client.get(f"/v1/jobs/{job['id']}").json(), stored=get_storage().exists(key),
                      recorded=runtime.load_job(job["id"]).checkpoint_key)
        callbacks.progress(Progress("edit", 1, 2))  # a report of the run started over carries its note
        during["reported"] = client.get(f"/v1/jobs/{job['id']}").json()["message"]
        return initial.clone_grid()

    monkeypatch.setattr(runtime, "get_guidance", lambda *args: NO_MODEL)
    monkeypatch.setattr(voxe_core.edit, "edit", refusing_resume)
    assert tasks.edit_task.apply(args=(job["id"],)).get()["state"] == "done"
    assert len(resumed_from) == 2 and resumed_from[0] is not None and resumed_from[1] is None
    said = ("the stored edit checkpoint could not be gone on from (checkpoint was made against other input views): "
            "started over")
    assert (during["job"]["message"], during["job"]["iteration"], during["stored"]) == (said, 0, False)
    assert during["recorded"] is None  # (had named the deleted object until the new run's first checkpoint)
    assert during["reported"] == said  # (it had said "resumed from the checkpoint at iteration 2" throughout)
    events = [(e["kind"], e.get("detail")) for e in client.get(f"/v1/jobs/{job['id']}/events").json()
              if e.get("stage") == "edit" and e["kind"] in ("resumed", "warning")]
    assert [kind for kind, _ in events] == ["resumed", "warning"] and events[1][1] == said
    after = client.get(f"/v1/jobs/{job['id']}").json()
    assert after["state"] == "running" and after["error"] is None, after  # on to its next stage


@pytest.mark.parametrize("damage, why", [
    (lambda data: data, None),
    (lambda data: data[:-1], "was unreadable (.*incomplete metadata, file not fully covered)"),
    (lambda data: data[: len(data) // 2], "was unreadable (.*incomplete metadata, file not fully covered)"),
    (lambda data: data + b"\0", "was unreadable (.*incomplete metadata, file not fully covered)"),
    (lambda data: data[:8] + b"x" + data[9:], "was unreadable (.*header)"),
])
def test_a_stored_checkpoint_is_checked_by_its_header_alone(tmp_path, monkeypatch, damage, why):
    """The worker checks a stored checkpoint before a stage resumes from it (which reads its tensors): the header
    alone names a truncated, padded or damaged file as unreadable, as the whole read it had made did, and accepts a
    good one, without reading the tensors twice."""
    import voxe_core.tensorio
    from voxe_core.edit import EDIT_CHECKPOINT_KIND, EDIT_CHECKPOINT_VERSION, EditConfig
    from voxe_service.storage import LocalStorage
    from worker.tasks import _stored_checkpoint

    storage, key = LocalStorage(tmp_path / "store"), "jobs/j/checkpoints/edit.safetensors"
    storage.put_bytes(key, damage(_edit_checkpoint(tmp_path / "made.safetensors")))
    monkeypatch.setattr(voxe_core.tensorio, "load_file", lambda *args: pytest.fail("read the checkpoint's tensors"))
    resume, meta, said = _stored_checkpoint(storage, key, tmp_path / "got.safetensors", EDIT_CHECKPOINT_KIND,
                                            EDIT_CHECKPOINT_VERSION, EditConfig(), lambda key: None)
    if why is None:
        assert resume == tmp_path / "got.safetensors" and meta["iteration"] == 2 and said is None
        assert storage.exists(key)
    else:
        assert resume is None and meta is None and re.match(why, said), said
        assert not storage.exists(key)


@pytest.mark.parametrize("recipe, kind", [(["lr", 0.03], "list"), (None, "NoneType"), ("reg3d", "str")])
def test_a_stored_checkpoint_whose_recipe_is_no_object_is_dropped_as_unreadable(tmp_path, recipe, kind):
    """A checkpoint whose header's recipe is no JSON object (hand-edited, damaged) had raised an AttributeError from
    the recipe comparison, failing the stage on every redelivery: it is unreadable, named so, and deleted."""
    from voxe_core.edit import EDIT_CHECKPOINT_KIND, EDIT_CHECKPOINT_VERSION, EditConfig, save_edit_checkpoint
    from voxe_core.grid import VoxelGrid
    from voxe_service.storage import LocalStorage
    from worker.tasks import _stored_checkpoint

    grid, made = VoxelGrid(4), tmp_path / "made.safetensors"
    save_edit_checkpoint(made, grid, torch.optim.Adam([grid.flat_features]), {}, 2, {"recipe": recipe})
    storage, key = LocalStorage(tmp_path / "store"), "jobs/j/checkpoints/edit.safetensors"
    got = tmp_path / "got.safetensors"
    storage.put_bytes(key, made.read_bytes())
    resume, meta, said = _stored_checkpoint(storage, key, got, EDIT_CHECKPOINT_KIND, EDIT_CHECKPOINT_VERSION,
                                            EditConfig(), lambda key: None)
    assert (resume, meta) == (None, None) and not storage.exists(key)
    assert said == f"was unreadable ({got}: damaged checkpoint: its recipe is a {kind}, not an object)"


def _fit_checkpoint_of_another_recipe(path) -> bytes:
    """A checkpoint TINY_FIT's fit could go on from, but made with lr 0.5 (a worker of another version's preset)."""
    from voxe_core.grid import VoxelGrid
    from voxe_core.reconstruct import make_optimizer, save_checkpoint

    config = reconstruct_config(reconstruction_params(service_json(TINY_FIT)))
    grid = VoxelGrid(config.resolutions[0])
    save_checkpoint(path, grid, make_optimizer(grid, config, config.lr), torch.Generator(), grid.occupancy().cells, 0,
                    1, recipe={**config.recipe(), "lr": 0.5})
    return path.read_bytes()


@pytest.mark.parametrize("stored, why", [
    (lambda tmp: b"not a safetensors file", "was unreadable"),
    (lambda tmp: _fit_checkpoint_of_another_recipe(tmp / "other.safetensors"), "was made with another recipe"),
])
def test_a_damaged_or_foreign_fit_checkpoint_is_dropped_and_the_fit_starts_over(service, monkeypatch, tmp_path,
                                                                                stored, why, caplog):
    """As an edit's: a stored reconstruction checkpoint made with another recipe (reconstruct() refuses to resume it,
    a ValueError that had failed the shared fit for good) or unreadable is deleted and the fit runs from the start,
    the record of it cleared as it starts over (it had named the deleted object until the fit's first checkpoint).
    Finished, the fit records no checkpoint and keeps none stored."""
    from sqlalchemy import update

    import voxe_core.reconstruct
    from voxe_service.db import session_scope
    from voxe_service.models import Reconstruction
    from voxe_service.storage import get_storage, reconstruction_storage_key
    from worker import runtime, tasks

    client, scene_id = service
    job = client.post("/v1/jobs", json={"scene_id": scene_id, "prompt": "a mic", "params": TINY_FIT}).json()
    rec_id = job["reconstruction"]["id"]
    key = reconstruction_storage_key(rec_id, "checkpoint-an-earlier-run.safetensors")
    get_storage().put_bytes(key, stored(tmp_path))
    with session_scope() as session:  # (recorded, as the fit's earlier owner left it)
        session.execute(update(Reconstruction).where(Reconstruction.id == rec_id).values(checkpoint_key=key))
    resumed_from, fit = [], voxe_core.reconstruct.reconstruct

    def recorded_fit(images, cameras, config, callbacks, checkpoint_path, resume_from, *args):
        resumed_from.append((resume_from, runtime.load_reconstruction(rec_id).checkpoint_key))
        return fit(images, cameras, config, callbacks, checkpoint_path, resume_from, *args)

    monkeypatch.setattr(voxe_core.reconstruct, "reconstruct", recorded_fit)
    assert tasks.reconstruct_task.apply(args=(job["id"],)).get()["state"] == "done"
    assert resumed_from == [(None, None)]
    assert f"the stored checkpoint {why}" in caplog.text
    events = client.get(f"/v1/jobs/{job['id']}/events").json()
    assert not any(e["kind"] == "resumed" and e.get("stage") == "reconstruct" for e in events), events
    assert runtime.load_reconstruction(rec_id).checkpoint_key is None
    assert get_storage().list(reconstruction_storage_key(rec_id, "checkpoint")) == []


@pytest.mark.parametrize("stage", ["reconstruct", "edit"])
def test_an_unreadable_checkpoint_the_storage_will_not_delete_still_starts_its_stage_over(service, monkeypatch,
                                                                                          stage, caplog):
    """A stored checkpoint the stage cannot go on from is deleted as the stage starts over, its record cleared first:
    the storage refusing that deletion (a role without delete rights, an outage) had failed the stage ("edit:
    StorageError: ..."; a fit's failed the shared reconstruction, for every job on it) over an object no record names
    any more. The deletion is a cleanup, as the checkpoint's a start over from edit() makes: its failure is logged,
    and the stage starts over."""
    from sqlalchemy import update

    import voxe_core.edit
    from voxe_service.db import session_scope
    from voxe_service.models import Reconstruction
    from voxe_service.storage import StorageError, get_storage, reconstruction_storage_key
    from worker import runtime, tasks

    client, scene_id = service
    if stage == "edit":
        job = _reconstructed_job(client, scene_id, "relu_field")
        key = _stored_edit_checkpoint(job["id"], b"not a safetensors file")
        monkeypatch.setattr(runtime, "get_guidance", lambda *args: NO_MODEL)
        monkeypatch.setattr(voxe_core.edit, "edit", lambda initial, *args, **kwargs: initial.clone_grid())
    else:
        job = client.post("/v1/jobs", json={"scene_id": scene_id, "prompt": "a mic", "params": TINY_FIT}).json()
        key = reconstruction_storage_key(job["reconstruction"]["id"], "checkpoint-an-earlier-run.safetensors")
        get_storage().put_bytes(key, b"not a safetensors file")
        with session_scope() as session:  # (recorded, as the fit's earlier owner left it)
            session.execute(update(Reconstruction).where(Reconstruction.id == job["reconstruction"]["id"])
                            .values(checkpoint_key=key))
    delete = type(get_storage()).delete

    def refusing_the_checkpoints_deletion(self, name):
        if name == key:
            raise StorageError(f"AccessDenied: may not delete {name}")
        return delete(self, name)

    monkeypatch.setattr(type(get_storage()), "delete", refusing_the_checkpoints_deletion)
    result = getattr(tasks, f"{stage}_task").apply(args=(job["id"],)).get()
    assert result["state"] == "done", (result, client.get(f"/v1/jobs/{job['id']}").json()["error"])
    assert f"could not delete the stored object {key}" in caplog.text
    after = client.get(f"/v1/jobs/{job['id']}").json()
    assert after["state"] == "running" and after["error"] is None, after  # on to its next stage


def test_a_fit_taken_over_as_its_grid_is_stored_goes_on_with_the_other_grid_though_its_own_is_not_deleted(
        service, monkeypatch, caplog):
    """A fit taken over by another job between storing its grid (under its run's own key) and recording it deletes
    that grid and goes on with the fit as the other job left it: the storage refusing that deletion (a role without
    delete rights, an outage) had failed the job ("reconstruct: StorageError: ...") or re-queued it over an object
    no record names. It is a cleanup: logged, and the job goes on with the other job's grid."""
    from voxe_service.models import R_SUCCEEDED
    from voxe_service.storage import StorageError, get_storage, reconstruction_storage_key
    from worker import runtime, tasks

    client, scene_id = service
    job = client.post("/v1/jobs", json={"scene_id": scene_id, "prompt": "a mic", "params": TINY_FIT}).json()
    other = client.post("/v1/jobs", json={"scene_id": scene_id, "prompt": "a yarn mic",
                                          "params": TINY_FIT}).json()["id"]
    storage, recorded, ours = get_storage(), runtime.set_reconstruction, []

    def taken_over_as_it_records(rec, job_id, run_token=None, **values):
        if values.get("state") == R_SUCCEEDED and job_id == job["id"]:  # the other job fitted it meanwhile
            ours.append(values["grid_key"])
            grid = storage.put_bytes(reconstruction_storage_key(rec, "grid-the-other-run.safetensors"),
                                     b"".join(storage.open_range(values["grid_key"])))
            runtime.update_job(other, run_token="theirs")
            assert recorded(rec, job_id, run_token, owner_job_id=other, owner_run_token="theirs")
            assert recorded(rec, other, "theirs", **{**values, "grid_key": grid.key})
        return recorded(rec, job_id, run_token, **values)

    delete = type(storage).delete

    def refusing_our_grids_deletion(self, name):
        if name in ours:
            raise StorageError(f"AccessDenied: may not delete {name}")
        return delete(self, name)

    monkeypatch.setattr(runtime, "set_reconstruction", taken_over_as_it_records)
    monkeypatch.setattr(type(storage), "delete", refusing_our_grids_deletion)
    result = tasks.reconstruct_task.apply(args=(job["id"],)).get()
    assert result["state"] == "done", (result, client.get(f"/v1/jobs/{job['id']}").json()["error"])
    assert f"could not delete the stored object {ours[0]}" in caplog.text
    after = client.get(f"/v1/jobs/{job['id']}").json()
    assert after["state"] == "running" and after["error"] is None and after["reconstruction"]["reused"], after


@pytest.mark.parametrize("then", ["resumed", "started over"])
def test_an_edit_run_that_lost_its_job_as_it_resumed_writes_no_resume_on_it(service, monkeypatch, tmp_path, then):
    """An edit run taken over (or its job ended) just after recording its "resumed" event still wrote "resumed from
    the checkpoint at iteration N" and that iteration as the job's message and progress, over the new run's; one
    that could not go on from the checkpoint, taken over just after its warning, still set the job's iteration back
    to 0. Those writes are the held run's only, as its progress writes are."""
    import voxe_core.edit
    from voxe_core.tensorio import FormatError
    from worker import runtime, tasks

    client, scene_id = service
    job = _reconstructed_job(client, scene_id, "relu_field")
    _stored_edit_checkpoint(job["id"], _edit_checkpoint(tmp_path / "ours.safetensors"))
    said = runtime.record_job_event if then == "resumed" else runtime.record_warning

    def said_as_another_run_takes_the_job_over(job_id, *args, **fields):
        said(job_id, *args, **fields)
        runtime.update_job(job_id, run_token="new", message="the new run's words", iteration=1)

    def edit(initial, prompt, guidance, config, callbacks, checkpoint_path, resume_from, **kwargs):
        if resume_from is not None and then == "started over":
            raise FormatError("checkpoint was made against other input views")
        return initial.clone_grid()

    monkeypatch.setattr(runtime, "record_job_event" if then == "resumed" else "record_warning",
                        said_as_another_run_takes_the_job_over)
    monkeypatch.setattr(runtime, "get_guidance", lambda *args: NO_MODEL)
    monkeypatch.setattr(voxe_core.edit, "edit", edit)
    tasks.edit_task.apply(args=(job["id"],))  # (its grid refused: the run no longer holds the job)
    after = client.get(f"/v1/jobs/{job['id']}").json()
    assert (after["message"], after["iteration"]) == ("the new run's words", 1), after


@pytest.mark.parametrize("stage", ["reconstruct", "edit"])
def test_a_checkpoint_deleted_as_it_is_fetched_starts_its_stage_from_the_start(service, monkeypatch, tmp_path, caplog,
                                                                              stage):
    """A recorded checkpoint found stored, then deleted before its download (by hand, by a bucket's lifecycle rule)
    had failed the stage ("edit: ObjectNotFound: '<key>'"; a fit's had failed the shared reconstruction, for every job
    on it), where one recorded and never stored starts it from the start: so does this one, said once in the log."""
    import voxe_core.edit
    import voxe_core.reconstruct
    from sqlalchemy import update

    from voxe_service.db import session_scope
    from voxe_service.models import Reconstruction
    from voxe_service.storage import get_storage, reconstruction_storage_key
    from worker import runtime, tasks

    client, scene_id = service
    resumed_from = []
    if stage == "edit":
        job = _reconstructed_job(client, scene_id, "relu_field")
        key = _stored_edit_checkpoint(job["id"], _edit_checkpoint(tmp_path / "ours.safetensors"))

        def recorded_edit(initial, prompt, guidance, config, callbacks, checkpoint_path, resume_from, **kwargs):
            resumed_from.append(resume_from)
            return initial.clone_grid()

        monkeypatch.setattr(runtime, "get_guidance", lambda *args: NO_MODEL)
        monkeypatch.setattr(voxe_core.edit, "edit", recorded_edit)
    else:
        job = client.post("/v1/jobs", json={"scene_id": scene_id, "prompt": "a mic", "params": TINY_FIT}).json()
        rec_id = job["reconstruction"]["id"]
        key = reconstruction_storage_key(rec_id, "checkpoint-an-earlier-run.safetensors")
        get_storage().put_bytes(key, b"the fit at 10")
        with session_scope() as session:  # (recorded, as the fit's earlier owner left it)
            session.execute(update(Reconstruction).where(Reconstruction.id == rec_id).values(checkpoint_key=key))
        fit = voxe_core.reconstruct.reconstruct

        def recorded_fit(images, cameras, config, callbacks, checkpoint_path, resume_from, *args):
            resumed_from.append(resume_from)
            return fit(images, cameras, config, callbacks, checkpoint_path, resume_from, *args)

        monkeypatch.setattr(voxe_core.reconstruct, "reconstruct", recorded_fit)
    storage_type, exists = type(get_storage()), type(get_storage()).exists

    def deleted_once_found(self, name):
        found = exists(self, name)
        if name == key:
            self.delete(name)
        return found

    monkeypatch.setattr(storage_type, "exists", deleted_once_found)
    with caplog.at_level("INFO", logger="voxe.worker"):
        result = getattr(tasks, f"{stage}_task").apply(args=(job["id"],)).get()
    assert result["state"] == "done", (result, client.get(f"/v1/jobs/{job['id']}").json()["error"])
    assert resumed_from == [None]
    assert [m for m in caplog.messages if key in m] == [
        f"the checkpoint {key} was deleted from the storage as it was fetched; starting from the start"]
    after = client.get(f"/v1/jobs/{job['id']}").json()
    assert after["state"] == "running" and after["error"] is None, after  # on to its next stage


def _storage_refusing(exc):
    """A stored object's put that raises ``exc`` for a checkpoint (and stores anything else)."""
    from voxe_service.storage import get_storage

    put = type(get_storage()).put_file

    def put_file(self, key, *args, **kwargs):
        if "checkpoint" in key:
            raise exc
        return put(self, key, *args, **kwargs)

    return put_file


@pytest.mark.parametrize("refusal", ["the storage refusing it", "a storage outage", "the disk full"])
@pytest.mark.parametrize("stage", ["reconstruct", "edit"])
def test_a_stage_canceled_whose_checkpoint_cannot_be_written_ends_canceled(service, monkeypatch, stage, refusal):
    """A fit or an edit canceled takes a checkpoint of its steps since the last, and the storage refusing it (access
    denied) had failed the job (and a fit's shared reconstruction with it: every job on it), a storage outage or a
    full disk had given the job back to the queue (paused, a counted re-queue) to end canceled only as its redelivery
    began: the cancel stays a cancel, the checkpoint a best effort (the earlier one stands), said as a warning, and a
    fit is handed back, not failed."""
    import errno

    import voxe_core.edit
    import voxe_core.reconstruct
    from test_edit import FakeGuidance
    from voxe_core.constants import MIN_RENDER_SIZE
    from voxe_service.db import session_scope
    from voxe_service.models import Reconstruction
    from voxe_service.storage import StorageError, StorageUnavailable, get_storage
    from worker import runtime, tasks

    client, scene_id = service
    module, saver = ((voxe_core.reconstruct, "save_checkpoint") if stage == "reconstruct"
                     else (voxe_core.edit, "save_edit_checkpoint"))
    if stage == "reconstruct":
        job = client.post("/v1/jobs", json={"scene_id": scene_id, "prompt": "a mic", "params": TINY_FIT}).json()
    else:
        job = _reconstructed_job(client, scene_id, "relu_field", iterations=4, render_size=MIN_RENDER_SIZE,
                                 preview_every=0)
        guidance = FakeGuidance()
        guidance.encoder_compile_seconds = None
        monkeypatch.setattr(runtime, "get_guidance", lambda *args: guidance)
    monkeypatch.setattr(runtime, "OUTAGE_PAUSE_S", 0.0)
    if refusal == "the disk full":
        def disk_full(path, *args, **kwargs):
            raise OSError(errno.ENOSPC, "No space left on device", str(path))

        monkeypatch.setattr(module, saver, disk_full)
    else:
        exc = (StorageError("AccessDenied: the role may not write checkpoints") if refusal.endswith("it")
               else StorageUnavailable("SlowDown: throttled"))
        put = type(get_storage()).put_file

        def put_file(self, key, *args, **kwargs):
            if "checkpoint" in key:
                raise exc
            return put(self, key, *args, **kwargs)

        monkeypatch.setattr(type(get_storage()), "put_file", put_file)
    run, callbacks_at = getattr(module, stage), 3 if stage == "reconstruct" else 4  # (the callbacks' position)

    def canceled_after_its_first_step(*args, **kwargs):
        callbacks, asked = args[callbacks_at], []

        def on_progress(report):
            callbacks.progress(report)
            if not asked:
                asked.append(client.post(f"/v1/jobs/{job['id']}/cancel").status_code)

        canceling = dataclasses.replace(callbacks, on_progress=on_progress,
                                        should_cancel=lambda: bool(asked) or callbacks.should_cancel())
        return run(*args[:callbacks_at], canceling, *args[callbacks_at + 1:], **kwargs)

    monkeypatch.setattr(module, stage, canceled_after_its_first_step)
    result = getattr(tasks, f"{stage}_task").apply(args=(job["id"],))
    after = client.get(f"/v1/jobs/{job['id']}").json()
    assert (after["state"], after["message"], after["error"]) == ("canceled", f"canceled during {stage}", None), (
        result.result, after)
    with session_scope() as session:
        rec = session.get(Reconstruction, job["reconstruction"]["id"])
        assert rec.state == ("pending" if stage == "reconstruct" else "succeeded") and rec.error is None
    warnings = [e["detail"] for e in client.get(f"/v1/jobs/{job['id']}/events").json() if e["kind"] == "warning"]
    assert len(warnings) == 1, warnings
    assert warnings[0].startswith("the checkpoint at the cancel could not be written ("), warnings
    assert warnings[0].endswith("): the earlier checkpoint stands"), warnings
    assert str(tasks.get_settings().work_dir) not in warnings[0]  # (the worker's paths are its log's)
    row = runtime.load_job(job["id"])
    assert (row.requeues, row.storage_outages) == (0, 0)


@pytest.mark.parametrize("canceled", ["between stages", "while re-queued"])
def test_a_job_canceled_before_its_next_stage_keeps_no_checkpoint_and_no_scratch(service, monkeypatch, canceled):
    """The edit's stored checkpoint (its grid and Adam state) outlives the edit for a redelivery. A job canceled
    before its next stage ran (flagged between stages, or ended by the API while re-queued after an interrupted
    edit) had kept it until its scene was deleted: the message that finds the job ended now discards it and this
    worker's scratch, and the job's artifacts stay (a redelivered message of a live job discards nothing)."""
    from pathlib import Path

    from sqlalchemy import update

    import voxe_core.edit
    from voxe_service.db import session_scope
    from voxe_service.models import Job
    from voxe_service.storage import get_storage, job_key
    from worker import runtime, tasks

    client, scene_id = service
    job_id = _reconstructed_job(client, scene_id, "relu_field")["id"]
    storage, checkpoints = get_storage(), job_key(job_id, "checkpoints/")
    if canceled == "between stages":
        monkeypatch.setattr(runtime, "get_guidance", lambda *args: NO_MODEL)
        monkeypatch.setattr(voxe_core.edit, "edit", lambda initial, *args, **kwargs: initial.clone_grid())
        assert tasks.edit_task.apply(args=(job_id,)).get()["state"] == "done"
        storage.put_bytes(f"{checkpoints}edit.safetensors", b"the edit's last checkpoint")
        assert "already done" in tasks.edit_task.apply(args=(job_id,)).get()["skipped"]  # redelivered: kept
        assert storage.list(checkpoints) == [f"{checkpoints}edit.safetensors"]
        next_stage = tasks.export_task
    else:
        storage.put_bytes(f"{checkpoints}edit.safetensors", b"the interrupted edit's checkpoint")
        with session_scope() as session:  # as requeue_interrupted leaves it, its edit message sent again
            session.execute(update(Job).where(Job.id == job_id).values(state="queued", run_token=None))
        next_stage = tasks.edit_task
    assert client.post(f"/v1/jobs/{job_id}/cancel").status_code == 200
    assert "skipped" in next_stage.apply(args=(job_id,)).get()
    assert client.get(f"/v1/jobs/{job_id}").json()["state"] == "canceled"
    assert storage.list(checkpoints) == []
    assert not (Path(tasks.get_settings().work_dir) / "jobs" / job_id).exists()
    assert client.get(f"/v1/jobs/{job_id}/artifacts/initial_grid.safetensors").status_code == 200


def test_the_job_whose_edit_waited_for_the_encoders_compile_says_how_long(service, monkeypatch):
    """A worker compiles its guidance's VAE encoder once, in the first edit it runs: that job's result carries the
    wait (``encoder_compile_seconds``), a later job on the same guidance none."""
    import voxe_core.edit
    from worker import runtime, tasks

    class Guidance:  # what the worker reads of a StableDiffusionGuidance here
        encoder_compile_seconds = None

    guidance = Guidance()

    def compiling_edit(initial, prompt, guidance, *args, **kwargs):
        guidance.encoder_compile_seconds = guidance.encoder_compile_seconds or 38.9
        return initial.clone_grid()

    monkeypatch.setattr(runtime, "get_guidance", lambda *args: guidance)
    monkeypatch.setattr(voxe_core.edit, "edit", compiling_edit)
    client, scene_id = service
    results = []
    for _ in range(2):
        job = _reconstructed_job(client, scene_id, "relu_field")
        assert tasks.edit_task.apply(args=(job["id"],)).get()["state"] == "done"
        results.append(client.get(f"/v1/jobs/{job['id']}").json()["result"])
    assert results[0]["encoder_compile_seconds"] == 38.9 and "encoder_compile_seconds" not in results[1]


@pytest.mark.parametrize("going_down", [SystemExit, KeyboardInterrupt, "cold shutdown"])
def test_a_worker_going_down_mid_fit_hands_the_reconstruction_back_rather_than_failing_it(service, monkeypatch,
                                                                                           going_down):
    """A warm shutdown's SystemExit (or ^C, or the NotImplementedError a cold shutdown raises in a solo pool's task)
    inside the fit is not the fit's failure: the shared reconstruction goes back to pending with no owner, so the
    jobs waiting on it, or this one redelivered, fit it; a real error fails it."""
    from celery.worker import state

    from voxe_service.db import session_scope
    from voxe_service.models import Reconstruction
    from worker import runtime, tasks

    client, scene_id = service

    def rec_of(job_id: str) -> tuple:
        with session_scope() as session:
            rec = session.get(Reconstruction, client.get(f"/v1/jobs/{job_id}").json()["reconstruction"]["id"])
            return rec.state, rec.owner_job_id, rec.error

    def submit() -> str:
        body = {**TINY_FIT, "reconstruction": {**TINY_FIT["reconstruction"], "seed": 7}}
        return client.post("/v1/jobs", json={"scene_id": scene_id, "prompt": "a mic", "params": body}).json()["id"]

    def fit_going_down(*args, **kwargs):
        if going_down == "cold shutdown":
            monkeypatch.setattr(state, "should_terminate", 0)  # set by Celery's cold shutdown (its exit code)
            raise NotImplementedError("<class 'celery.concurrency.solo.TaskPool'> does not implement kill_job")
        raise going_down()

    monkeypatch.setattr(tasks, "_fit_grid", fit_going_down)
    job_id = submit()
    if going_down == "cold shutdown":  # the message is rejected back to the queue (apply records the Reject)
        assert tasks.reconstruct_task.apply(args=(job_id,)).state == "REJECTED"
        monkeypatch.setattr(state, "should_terminate", None)  # the next worker
    else:
        with pytest.raises(going_down):
            tasks.reconstruct_task.apply(args=(job_id,))
    assert rec_of(job_id) == ("pending", None, None)
    held = runtime.load_job(job_id)  # the run gave its hold back: the redelivered message takes the job at once
    assert (held.state, held.stage, held.run_token, held.run_lease_until) == ("running", "reconstruct", None, None)

    def fit_failing(*args, **kwargs):
        raise RuntimeError("the fit diverged")

    monkeypatch.setattr(tasks, "_fit_grid", fit_failing)
    assert tasks.reconstruct_task.apply(args=(submit(),)).get()["state"] == "failed"
    assert rec_of(job_id)[0] == "failed" and rec_of(job_id)[2] == "RuntimeError: the fit diverged"


def _database_error(statement: str, words: str):
    """What SQLAlchemy raises when SQLite answers ``words``: "database is locked" is an outage (database_outage),
    "no such table" a fault of the schema."""
    import sqlite3

    from sqlalchemy.exc import OperationalError

    return OperationalError(statement, {}, sqlite3.OperationalError(words))


def _refusing(monkeypatch, name: str, error, when=lambda *args, **kwargs: True) -> list:
    """``worker.runtime.<name>`` raising ``error`` on each call ``when`` picks; the calls refused."""
    from worker import runtime

    real, refused = getattr(runtime, name), []

    def refusing(*args, **kwargs):
        if when(*args, **kwargs):
            refused.append(args)
            raise error
        return real(*args, **kwargs)

    monkeypatch.setattr(runtime, name, refusing)
    return refused


EDGES = {  # where in the edit stage the database refuses: its checkpoint's event, its grid's record, its end
    "checkpoint event": ("_record_checkpoint", "INSERT INTO job_events", lambda *args: True),
    "artifact record": ("record_event", "INSERT INTO job_events", lambda _, job_id, kind, **__: kind == "artifact"),
    "stage's end": ("complete_stage", "UPDATE jobs", lambda *args, **kwargs: True),
}


@pytest.mark.parametrize("release", ["released", "the release refused too"])
@pytest.mark.parametrize("edge", EDGES)
def test_a_database_outage_at_a_stages_checkpoint_or_end_sends_it_back_to_the_queue_to_resume(service, monkeypatch,
                                                                                               edge, release):
    """A locked or unreachable database as the edit recorded its checkpoint, its grid or its end had failed the job
    (or, at the end, the task, leaving the job to the reaper): an outage is not the job's fault. The run gives the
    job back and the message goes back to the queue; its redelivery resumes from the stored checkpoint and
    completes. When the database refuses the release too, the job stays held until its lease runs out unrenewed,
    and the redelivery takes it over then. Either way the return counts as a re-queue (named by a ``requeued``
    event when the database took the give-back), so an "outage" met every time cannot re-run the stage for ever.
    """
    from voxe_service.models import utcnow
    from worker import runtime, tasks

    client, scene_id = service
    job_id = _reconstructed_job(client, scene_id, "scene", iterations=3, render_size=16, preview_every=0)["id"]
    name, statement, when = EDGES[edge]
    with monkeypatch.context() as outage:
        outage.setattr(tasks, "DATABASE_RETRY_S", (0.0, 0.0))
        refused = _refusing(outage, name, _database_error(statement, "database is locked"), when)
        if release != "released":
            _refusing(outage, "give_back_stage", _database_error("UPDATE jobs", "database is locked"))
        result = tasks.edit_task.apply(args=(job_id,))
    assert result.state == "REJECTED" and result.result.requeue, result.result  # back to the broker
    assert "database" in str(result.result)
    assert len(refused) == (3 if edge == "stage's end" else 1)  # the end tried again after each pause
    job = runtime.load_job(job_id)
    assert (job.state, job.error, job.completed_stages) == ("running", None, ["reconstruct"])
    assert (job.run_token is None) == (release == "released")
    if job.run_token is not None:  # no run renews the hold: its lease runs out
        runtime.update_job(job_id, run_lease_until=utcnow() - timedelta(seconds=1))
    assert tasks.edit_task.apply(args=(job_id,)).get()["state"] == "done"  # the redelivered message
    done = client.get(f"/v1/jobs/{job_id}").json()
    assert (done["state"], done["completed_stages"], done["iteration"]) == ("running", ["reconstruct", "edit"], 3)
    assert runtime.load_job(job_id).requeues == 1
    events = client.get(f"/v1/jobs/{job_id}/events").json()
    requeued = [e["detail"] for e in events if e["kind"] == "requeued"]
    if release == "released":
        assert requeued == ["edit stopped by a database outage (the database cannot be reached or is locked): "
                            "OperationalError: database is locked"], requeued
    else:
        assert requeued == []
    # (from the last checkpoint recorded: one whose record the database refused is no run's, and here none was)
    resumed = [e["iteration"] for e in events if e["kind"] == "resumed" and e["stage"] == "edit"]
    assert resumed == ([] if edge == "checkpoint event" else [3])
    assert client.get(f"/v1/jobs/{job_id}/artifacts/edited_grid.safetensors").status_code == 200


def test_an_outage_met_at_every_try_fails_the_job_at_the_requeue_limit_naming_it(service, monkeypatch):
    """What the database answers as an outage every time (a statement timeout, a full disk) had sent the stage back
    to the queue for ever, each redelivery running it again from its checkpoint: each give-back counts, and at
    ``VOXE_JOB_MAX_REQUEUES`` the job fails naming the outage."""
    from voxe_service.settings import get_settings
    from worker import runtime, tasks

    client, scene_id = service
    job_id = _reconstructed_job(client, scene_id, "scene", iterations=3, render_size=16, preview_every=0)["id"]
    limit = get_settings().job_max_requeues
    monkeypatch.setattr(tasks, "DATABASE_RETRY_S", (0.0,))
    name, statement, when = EDGES["artifact record"]
    _refusing(monkeypatch, name, _database_error(statement, "database is locked"), when)
    outcomes = [tasks.edit_task.apply(args=(job_id,)) for _ in range(limit + 1)]
    assert [outcome.state for outcome in outcomes] == ["REJECTED"] * limit + ["SUCCESS"]
    assert outcomes[-1].get()["state"] == "failed"
    job = runtime.load_job(job_id)
    assert (job.state, job.requeues) == ("failed", limit)
    assert job.error == ("edit stopped by a database outage (the database cannot be reached or is locked): "
                         f"OperationalError: database is locked; it was sent again {limit} time(s) already, the "
                         f"limit (VOXE_JOB_MAX_REQUEUES={limit})")


def _checkpoint_upload_refused(monkeypatch, storage, cause: str, refused_at: set) -> list:
    """The edit's checkpoint refused at the checkpoints numbered in ``refused_at`` (1 for the first): its upload
    throttled by the storage (``cause`` "storage outage"), or its write to the worker's scratch disk, full ("full
    disk"), the same way every time (``refused_at`` empty: from the first on); the checkpoints tried."""
    import errno

    import voxe_core.edit
    from voxe_service.storage import StorageUnavailable

    tried = []
    if cause == "storage outage":
        put_file = type(storage).put_file

        def throttled(self, key, path, content_type=None):
            if key.endswith("/edit.safetensors"):  # (checkpoints/<run token>/<iteration>/edit.safetensors)
                tried.append(key)
                if not refused_at or len(tried) in refused_at:
                    raise StorageUnavailable(f"S3 bucket 'voxe': SlowDown when uploading {key}")
            return put_file(self, key, path, content_type)

        monkeypatch.setattr(type(storage), "put_file", throttled)
    else:
        save_tensors = voxe_core.edit.save_tensors

        def full(path, *args, **kwargs):
            tried.append(path)
            if not refused_at or len(tried) in refused_at:
                raise OSError(errno.ENOSPC, "No space left on device", str(path))
            return save_tensors(path, *args, **kwargs)

        monkeypatch.setattr(voxe_core.edit, "save_tensors", full)
    return tried


OUTAGE_SAID = {"storage outage": "a storage outage (S3 bucket 'voxe': SlowDown when uploading {key})",
               "full disk": "the worker's disk full (OSError: [Errno 28] No space left on device)"}


@pytest.mark.parametrize("cause", OUTAGE_SAID)
def test_an_edit_whose_checkpoint_meets_a_storage_outage_or_a_full_disk_goes_back_to_the_queue_and_resumes(
        service, monkeypatch, cause):
    """The storage throttled or unreachable (S3 SlowDown, a 5xx) as the edit stored a checkpoint, or the worker's
    scratch disk full as it wrote one, had failed the job and deleted its checkpoints: hours of a GPU edit lost to
    a passing outage, and a worker with a full disk failing every job it took. The run gives the job back (the
    hold released: any worker takes it) with a re-queue naming the cause (counted for a full disk), pauses as an
    ingest does, and the message goes back to the queue; the redelivery resumes from the last checkpoint stored."""
    from voxe_service.storage import get_storage
    from worker import runtime, tasks

    client, scene_id = service
    job_id = _reconstructed_job(client, scene_id, "scene", iterations=3, render_size=16, preview_every=0)["id"]
    monkeypatch.setattr(tasks.get_settings(), "checkpoint_every", 1)  # checkpoints at iterations 1, 2 and 3
    storage = get_storage(tasks.get_settings())
    pauses = []
    monkeypatch.setattr(tasks.time, "sleep", pauses.append)
    with monkeypatch.context() as outage:
        tried = _checkpoint_upload_refused(outage, storage, cause, refused_at={2})
        result = tasks.edit_task.apply(args=(job_id,))
    assert result.state == "REJECTED" and result.result.requeue, result.result  # back to the broker
    assert len(tried) == 2 and pauses == [5.0]
    said = OUTAGE_SAID[cause].format(key=tried[-1])
    assert result.result.reason == f"edit of job {job_id} stopped by {said}"
    job = runtime.load_job(job_id)
    assert (job.state, job.error, job.completed_stages, job.run_token, job.requeues) == (
        "running", None, ["reconstruct"], None, int(cause == "full disk"))  # (a storage outage does not count)
    assert storage.exists(runtime.load_job(job_id).checkpoint_key)  # the one of iteration 1, kept
    assert tasks.edit_task.apply(args=(job_id,)).get()["state"] == "done"  # the redelivered message
    done = client.get(f"/v1/jobs/{job_id}").json()
    assert (done["state"], done["completed_stages"], done["iteration"]) == ("running", ["reconstruct", "edit"], 3)
    events = client.get(f"/v1/jobs/{job_id}/events").json()
    assert [e["detail"] for e in events if e["kind"] == "requeued"] == [f"edit stopped by {said}"]
    assert [e["iteration"] for e in events if e["kind"] == "resumed" and e["stage"] == "edit"] == [1]
    assert client.get(f"/v1/jobs/{job_id}/artifacts/edited_grid.safetensors").status_code == 200


@pytest.mark.parametrize("cause", OUTAGE_SAID)
def test_a_full_disk_met_at_every_run_fails_the_job_at_the_requeue_limit_and_a_storage_outage_does_not(
        service, monkeypatch, cause):
    """Given back at each run, a stage its worker's disk refuses every time would run for ever: each return counts,
    its pause doubling (5, 10, 20 s), and at ``VOXE_JOB_MAX_REQUEUES`` the job fails naming the cause, its
    checkpoints deleted. A storage outage, which every job meets alike, does not count: the job waits it out, its
    pause doubling all the same, its checkpoints kept."""
    from voxe_service.settings import get_settings
    from voxe_service.storage import get_storage
    from worker import runtime, tasks

    client, scene_id = service
    job_id = _reconstructed_job(client, scene_id, "scene", iterations=3, render_size=16, preview_every=0)["id"]
    limit = get_settings().job_max_requeues
    storage = get_storage(get_settings())
    pauses = []
    monkeypatch.setattr(tasks.time, "sleep", pauses.append)
    _checkpoint_upload_refused(monkeypatch, storage, cause, refused_at=set())
    outcomes = [tasks.edit_task.apply(args=(job_id,)) for _ in range(limit + 1)]
    if cause == "storage outage":
        assert [outcome.state for outcome in outcomes] == ["REJECTED"] * (limit + 1)
        assert pauses == [5.0 * 2 ** n for n in range(limit + 1)]
        job = runtime.load_job(job_id)
        assert (job.state, job.error, job.requeues) == ("running", None, 0)
        return
    assert [outcome.state for outcome in outcomes] == ["REJECTED"] * limit + ["SUCCESS"]
    assert outcomes[-1].get()["state"] == "failed"
    assert pauses == [5.0 * 2 ** n for n in range(limit)]
    job = runtime.load_job(job_id)
    assert (job.state, job.requeues) == ("failed", limit)
    assert job.error == (f"edit stopped by {OUTAGE_SAID[cause]}; it was sent again {limit} "
                         f"time(s) already, the limit (VOXE_JOB_MAX_REQUEUES={limit})")
    assert storage.list(f"jobs/{job_id}/checkpoints/") == []


def test_a_storage_error_that_is_no_outage_at_a_checkpoint_fails_the_job_naming_it(service, monkeypatch):
    """A storage fault a retry would meet again (access denied, a missing bucket) is no outage: the job fails with
    it at once, not after re-running the stage VOXE_JOB_MAX_REQUEUES times."""
    from service_helpers import failing_uploads
    from voxe_service.storage import StorageError, get_storage
    from worker import runtime, tasks

    client, scene_id = service
    job_id = _reconstructed_job(client, scene_id, "scene", iterations=3, render_size=16, preview_every=0)["id"]
    failing_uploads(monkeypatch, get_storage(tasks.get_settings()), "/edit.safetensors",
                    StorageError("S3 bucket 'voxe': AccessDenied when uploading"))
    assert tasks.edit_task.apply(args=(job_id,)).get()["state"] == "failed"
    job = runtime.load_job(job_id)
    assert (job.state, job.requeues) == ("failed", 0)
    assert job.error == "edit: StorageError: S3 bucket 'voxe': AccessDenied when uploading"


def test_a_stages_end_committed_with_its_answer_lost_goes_on_with_the_chain(service, monkeypatch):
    """A dropped connection can lose the answer to a COMMIT that landed: the end's retry found the job released
    and took it for another run's takeover, stopping the chain (the job left running until the reaper's
    lost-message pass, hours later). The stage found done and the job free counts as this run's."""
    from sqlalchemy.exc import OperationalError

    from worker import runtime, tasks

    client, scene_id = service
    job_id = _reconstructed_job(client, scene_id, "scene", iterations=3, render_size=16, preview_every=0)["id"]
    # released but not done (another run's give-back looks so): no retry takes the stage for recorded
    assert runtime.complete_stage(job_id, "edit", "a-run", again=True) is False
    assert runtime.load_job(job_id).completed_stages == ["reconstruct"]
    monkeypatch.setattr(tasks, "DATABASE_RETRY_S", (0.0, 0.0))
    real, calls = runtime.complete_stage, []

    def committed_then_dropped(*args, **kwargs):
        calls.append(kwargs.get("again"))
        done = real(*args, **kwargs)
        if len(calls) == 1:
            raise OperationalError("COMMIT", {}, Exception("server closed the connection unexpectedly"))
        return done

    monkeypatch.setattr(runtime, "complete_stage", committed_then_dropped)
    assert tasks.edit_task.apply(args=(job_id,)).get()["state"] == "done"
    assert calls == [False, True]
    job = runtime.load_job(job_id)
    assert (job.state, job.completed_stages, job.run_token, job.requeues) == (
        "running", ["reconstruct", "edit"], None, 0)


@pytest.mark.parametrize("edge", EDGES)
def test_a_database_fault_that_is_no_outage_at_a_stages_checkpoint_or_end_fails_the_job_naming_it(service,
                                                                                                   monkeypatch, edge):
    """SQLite's OperationalError for a fault of the schema (a worker newer than its migrations) is no outage: a
    redelivery would meet it again, so the job fails with it, at the checkpoint's event, the grid's record or the
    stage's end; a database that refuses the end once and then answers completes the stage."""
    from worker import runtime, tasks

    client, scene_id = service
    job_id = _reconstructed_job(client, scene_id, "scene", iterations=3, render_size=16, preview_every=0)["id"]
    name, statement, when = EDGES[edge]
    monkeypatch.setattr(tasks, "DATABASE_RETRY_S", (0.0, 0.0))
    if edge == "stage's end":
        other = _reconstructed_job(client, scene_id, "scene", iterations=3, render_size=16, preview_every=0)["id"]
        with monkeypatch.context() as once:
            refused = _refusing(once, name, _database_error(statement, "database is locked"),
                                lambda *args, **kwargs: not refused)
            assert tasks.edit_task.apply(args=(other,)).get()["state"] == "done"
        assert len(refused) == 1 and runtime.load_job(other).completed_stages == ["reconstruct", "edit"]
    _refusing(monkeypatch, name, _database_error(statement, "no such table: jobs_v2"), when)
    assert tasks.edit_task.apply(args=(job_id,)).get()["state"] == "failed"
    job = runtime.load_job(job_id)
    assert job.state == "failed"
    assert job.error == "edit: OperationalError: no such table: jobs_v2"  # the driver's words, not the statement


def test_a_real_scene_edit_runs_through_the_worker_on_the_smoke_test_model(service, tmp_path):
    """A short real edit (the tiny random-weight model) of a scene G_i: the job counts the iterations it ran."""
    from voxe_core.backbones import load_grid
    from worker import tasks

    client, scene_id = service
    job = _reconstructed_job(client, scene_id, "scene", iterations=3, render_size=16, preview_every=0)
    assert tasks.edit_task.apply(args=(job["id"],)).get()["state"] == "done"
    done = client.get(f"/v1/jobs/{job['id']}").json()
    assert (done["iteration"], done["total"]) == (3, 3) and done["completed_stages"] == ["reconstruct", "edit"]
    edited = client.get(f"/v1/jobs/{job['id']}/artifacts/edited_grid.safetensors")
    assert edited.status_code == 200
    (tmp_path / "edited.safetensors").write_bytes(edited.content)
    assert load_grid(tmp_path / "edited.safetensors").kind == "scene"


@pytest.mark.parametrize("density", ["constant", "varying"])
def test_an_edit_whose_regulariser_a_constant_reconstruction_switches_off_says_so_on_the_job(service, monkeypatch,
                                                                                           density):
    """A G_i of constant density (an empty or unfitted reconstruction) leaves L_reg3D nothing to correlate: the edit
    had run unregularised with ``reg`` 1.0 on every report, which reads as a very poor correlation, and the job said
    nothing (a Python warning reaches no user of the service). A real edit (the tiny model) of such a G_i now says it
    as a warning event of the edit (its webhook's job.warning; the CLI's line) and as the message its progress
    reports carry; of a G_i whose density varies, nothing."""
    from worker import runtime, tasks

    client, scene_id = service
    job = _reconstructed_job(client, scene_id, "relu_field", iterations=2, render_size=16, preview_every=0)
    real_fetch_grid = tasks.fetch_grid

    def with_density(job_id, name, *args, **kwargs):
        grid = real_fetch_grid(job_id, name, *args, **kwargs)
        if name == "initial_grid.safetensors":  # the tiny fit's density, made constant or a ramp
            with torch.no_grad():
                ramp = torch.linspace(-1.0, 1.0, grid.features[..., 0].numel()).reshape(grid.features.shape[:3])
                grid.features[..., 0] = 0.5 if density == "constant" else ramp
        return grid

    real_update_job, messages = runtime.update_job, []

    def recorded_update_job(job_id, **fields):
        if "losses" in fields:  # a progress write
            messages.append((fields["losses"]["reg"], fields["message"]))
        return real_update_job(job_id, **fields)

    monkeypatch.setattr(tasks, "fetch_grid", with_density)
    monkeypatch.setattr(runtime, "update_job", recorded_update_job)
    assert tasks.edit_task.apply(args=(job["id"],)).get()["state"] == "done"
    warnings = [(e["stage"], e["detail"]) for e in client.get(f"/v1/jobs/{job['id']}/events").json()
                if e["kind"] == "warning"]
    if density == "varying":
        assert warnings == [] and messages and all(message is None for _, message in messages)
        return
    said = ("the reconstruction's density is constant: the 3D regulariser (reg3d) has nothing to correlate and is off; "
            "the edit runs unregularised, its reg a constant 1.0 (an empty or unfitted reconstruction?)")
    assert warnings == [("edit", said)]
    assert messages and all(report == (1.0, said) for report in messages)  # (a progress write had dropped it)


def test_the_worker_runs_every_stage_on_its_device_and_stores_their_peak_memory(service, monkeypatch):
    """The worker's resolved VOXE_DEVICE (auto: cpu here) reaches each stage as its ``device``; each stage's
    reported peak lands in Job.result."""
    import voxe_core.edit
    import voxe_core.export
    from worker import runtime, tasks

    client, scene_id = service
    job = _reconstructed_job(client, scene_id, "relu_field", export={
        "views": 1, "view_size": 16, "turntable_frames": 2, "turntable_size": 16, "gif": False, "mesh": False})
    seen = {}

    def recorded_edit(initial, prompt, guidance, config, *args, device=None, **kwargs):
        seen["edit"] = device
        return initial.clone_grid()

    real_iter_views = voxe_core.export.iter_views

    def recorded_iter_views(grid, cameras, *args, device=None, **kwargs):
        seen.setdefault("render", set()).add(device)
        return real_iter_views(grid, cameras, *args, device=device, **kwargs)

    monkeypatch.setattr(runtime, "get_guidance", lambda *args: NO_MODEL)
    monkeypatch.setattr(voxe_core.edit, "edit", recorded_edit)
    monkeypatch.setattr(voxe_core.export, "iter_views", recorded_iter_views)
    assert tasks.edit_task.apply(args=(job["id"],)).get()["state"] == "done"
    assert tasks.export_task.apply(args=(job["id"],)).get()["state"] == "done"
    assert seen == {"edit": "cpu", "render": {"cpu"}}
    result = client.get(f"/v1/jobs/{job['id']}").json()["result"]
    assert result["peak_memory_kind"] == "process_rss"
    assert set(result["peak_memory_gb"]) == {"reconstruct", "export"}  # the recorded edit reported nothing
    assert all(0.01 < gb < 64 for gb in result["peak_memory_gb"].values())


def test_the_export_writes_each_view_and_turntable_frame_as_it_is_rendered(service, monkeypatch, tmp_path):
    """Regression: the export rendered the whole turntable (render_views' (N, H, W, 3) floats: 1,000 frames of 2,048²
    are 50 GB) and then wrote the MP4 and the GIF from it, and all ring views before saving the first. Now each
    frame goes to both videos (8-bit pixels for each) before the next is rendered, and each view to its PNG; both
    videos hold every frame."""
    import voxe_core.edit
    import voxe_core.export
    from test_export import decoded_video
    from worker import runtime, tasks

    client, scene_id = service
    job = _reconstructed_job(client, scene_id, "relu_field", export={
        "views": 3, "view_size": 16, "turntable_frames": 12, "turntable_size": 18, "gif": True, "mesh": False})
    monkeypatch.setattr(runtime, "get_guidance", lambda *args: NO_MODEL)
    monkeypatch.setattr(voxe_core.edit, "edit", lambda initial, *args, **kwargs: initial.clone_grid())
    assert tasks.edit_task.apply(args=(job["id"],)).get()["state"] == "done"
    events, real_render_image, real_to_uint8 = [], voxe_core.export.render_image, voxe_core.export.to_uint8

    def recorded_render_image(grid, cameras, *args, **kwargs):
        events.append(("render", cameras.width))
        return real_render_image(grid, cameras, *args, **kwargs)

    def recorded_to_uint8(image):  # what a PNG or a video frame is written from
        events.append(("pixels", tuple(image.shape)))
        return real_to_uint8(image)

    monkeypatch.setattr(voxe_core.export, "render_image", recorded_render_image)
    monkeypatch.setattr(voxe_core.export, "to_uint8", recorded_to_uint8)
    assert tasks.export_task.apply(args=(job["id"],)).get()["state"] == "done"
    views = [("render", 16), ("pixels", (16, 16, 3))] * 3
    turntable = [("render", 18), ("pixels", (18, 18, 3)), ("pixels", (18, 18, 3))] * 12  # the MP4's, the GIF's
    assert events[: len(views) + len(turntable)] == views + turntable
    for name in ("turntable.mp4", "turntable.gif"):
        (tmp_path / name).write_bytes(client.get(f"/v1/jobs/{job['id']}/artifacts/{name}").content)
    frames, _ = decoded_video(tmp_path / "turntable.mp4")
    assert len(frames) == 12 and frames[0].shape == (18, 18, 3)
    assert sum(decoded_video(tmp_path / "turntable.gif")[1]) == 400  # 12 frames at 30 fps


def test_the_export_reads_the_orbit_centre_its_reconstruction_recorded_and_fetches_no_initial_grid(service,
                                                                                                  monkeypatch):
    """On a scale-out, the export may run on a worker that never held G_i: it looks at the centre the reconstruct
    stage recorded (exactly G_i's ``orbit_centre()``) and downloads only the grid it renders."""
    import voxe_core.edit
    import voxe_core.export
    from voxe_core.backbones import load_grid
    from worker import runtime, tasks

    client, scene_id = service
    job = _reconstructed_job(client, scene_id, "scene", export={
        "views": 1, "view_size": 16, "turntable_frames": 2, "turntable_size": 16, "gif": False, "mesh": False})
    initial = load_grid(runtime.scratch_dir(job["id"], tasks.get_settings()) / "initial_grid.safetensors")
    recorded = client.get(f"/v1/jobs/{job['id']}").json()["result"]["orbit_centre"]
    assert recorded == [float(c) for c in initial.orbit_centre()] and any(c != 0.0 for c in recorded)
    monkeypatch.setattr(runtime, "get_guidance", lambda *args: NO_MODEL)
    monkeypatch.setattr(voxe_core.edit, "edit", lambda initial, *args, **kwargs: initial.clone_grid())
    assert tasks.edit_task.apply(args=(job["id"],)).get()["state"] == "done"
    fetched, centres = [], []
    real_fetch_grid, real_turntable_cameras = tasks.fetch_grid, voxe_core.export.turntable_cameras

    def recorded_fetch_grid(job_id, name, *args, **kwargs):
        fetched.append(name)
        return real_fetch_grid(job_id, name, *args, **kwargs)

    def recorded_turntable_cameras(*args, centre=None, **kwargs):
        centres.append(centre)
        return real_turntable_cameras(*args, centre=centre, **kwargs)

    monkeypatch.setattr(tasks, "fetch_grid", recorded_fetch_grid)
    monkeypatch.setattr(voxe_core.export, "turntable_cameras", recorded_turntable_cameras)
    assert tasks.export_task.apply(args=(job["id"],)).get()["state"] == "done"
    assert fetched == ["edited_grid.safetensors"]
    assert centres and all(torch.equal(c, initial.orbit_centre()) for c in centres)



def test_a_jobs_edit_reads_the_initial_grid_its_reconstruct_stage_recorded_not_a_later_fit(service, monkeypatch,
                                                                                            tmp_path):
    """A reconstruction whose grid was deleted from the storage is fitted again by the next job that needs it: a job
    reconstructed from the first fit read the reconstruction's grid in its later stages, so it edited (refined,
    centred its export on) another G_i than the one its reconstruct stage recorded and published. Its stages read the
    G_i it recorded."""
    from sqlalchemy import update

    import voxe_core.edit
    from conftest import make_sphere_grid
    from voxe_core.backbones import load_grid
    from voxe_service.db import session_scope
    from voxe_service.models import Reconstruction
    from voxe_service.storage import get_storage
    from worker import runtime, tasks

    client, scene_id = service
    job = _reconstructed_job(client, scene_id, "scene")
    settings, storage = tasks.get_settings(), get_storage()
    initial = load_grid(runtime.scratch_dir(job["id"], settings) / "initial_grid.safetensors")
    rec_id = runtime.load_job(job["id"]).reconstruction_id
    make_sphere_grid(8).save(tmp_path / "refitted.safetensors")  # the fit made again: another grid recorded
    refitted = storage.put_file(f"reconstructions/{rec_id}/grid-again.safetensors", tmp_path / "refitted.safetensors")
    with session_scope() as session:
        session.execute(update(Reconstruction).where(Reconstruction.id == rec_id).values(
            grid_key=refitted.key, grid_size=refitted.size, grid_sha256=refitted.sha256))
    runtime.cleanup_scratch(job["id"], settings)  # (the edit on another worker)
    monkeypatch.setattr(runtime, "get_guidance", lambda *args: NO_MODEL)
    monkeypatch.setattr(voxe_core.edit, "edit", lambda initial, *args, **kwargs: initial.clone_grid())
    assert tasks.edit_task.apply(args=(job["id"],)).get()["state"] == "done"
    edited = client.get(f"/v1/jobs/{job['id']}/artifacts/edited_grid.safetensors")
    (tmp_path / "edited.safetensors").write_bytes(edited.content)
    edited = load_grid(tmp_path / "edited.safetensors")  # (the edit as G_i unchanged)
    assert (edited.kind, edited.resolution) == (initial.kind, initial.resolution)
    assert torch.equal(edited.features, initial.features)

def _edited_job_exporting_a_mesh(client, scene_id, monkeypatch) -> str:
    """A reconstructed job, its edit run (the initial grid as the edit), whose export will extract a mesh (an
    icosphere: the tiny fit's grid may have no surface at the level); its id."""
    import trimesh

    import voxe_core.edit
    import voxe_core.export
    from worker import runtime, tasks

    job_id = _reconstructed_job(client, scene_id, "relu_field", export={
        "views": 1, "view_size": 16, "turntable_frames": 2, "turntable_size": 16, "gif": False, "mesh": True})["id"]
    monkeypatch.setattr(runtime, "get_guidance", lambda *args: NO_MODEL)
    monkeypatch.setattr(voxe_core.edit, "edit", lambda initial, *args, **kwargs: initial.clone_grid())
    assert tasks.edit_task.apply(args=(job_id,)).get()["state"] == "done"
    surface = trimesh.creation.icosphere(subdivisions=1)
    monkeypatch.setattr(voxe_core.export, "extract_mesh", lambda grid, resolution: surface)
    return job_id


def test_an_export_whose_disk_refuses_one_mesh_format_publishes_no_mesh(service, monkeypatch):
    """The mesh formats (PLY, GLB, OBJ with its MTL) are one set: a full disk writing mesh.glb had failed the job with
    mesh.ply already listed. Every format is written before any is published, so the stopped run lists none; the
    full disk, the worker's state, gives the job back (it had failed it) and the stage run again publishes every
    format."""
    import errno

    import voxe_core.edit
    import voxe_core.export
    from worker import tasks

    client, scene_id = service
    job_id = _edited_job_exporting_a_mesh(client, scene_id, monkeypatch)
    save_mesh = voxe_core.export.save_mesh

    def full_disk_for_glb(mesh, path):
        if path.suffix == ".glb":
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return save_mesh(mesh, path)

    monkeypatch.setattr("worker.runtime.OUTAGE_PAUSE_S", 0.0)
    with monkeypatch.context() as disk:
        disk.setattr(voxe_core.export, "save_mesh", full_disk_for_glb)
        result = tasks.export_task.apply(args=(job_id,))
    assert result.state == "REJECTED" and result.result.requeue, result.result
    assert result.result.reason == (f"export of job {job_id} stopped by the worker's disk full (OSError: [Errno 28] "
                                    "No space left on device)")
    job = client.get(f"/v1/jobs/{job_id}").json()
    assert (job["state"], job["error"]) == ("running", None)
    listed = {a["name"] for a in client.get(f"/v1/jobs/{job_id}/artifacts").json()}
    assert listed == {"initial_grid.safetensors", "edited_grid.safetensors", "preview.png", "render_000.png",
                      "turntable.mp4"}
    assert tasks.export_task.apply(args=(job_id,)).get()["state"] == "done"  # the redelivered message
    listed = {a["name"] for a in client.get(f"/v1/jobs/{job_id}/artifacts").json()}
    assert {"mesh.ply", "mesh.glb", "mesh.obj", "mesh.mtl"} <= listed


def test_an_export_whose_grid_has_no_surface_succeeds_saying_why_it_has_no_mesh(service, monkeypatch):
    """A mesh asked for and not exported (no density crosses the level) is said on the succeeded job: the message was
    written, then blanked by the stage's last progress write and by the job's success, leaving no word of it."""
    import voxe_core.edit
    import voxe_core.export
    from worker import runtime, tasks

    client, scene_id = service
    job_id = _reconstructed_job(client, scene_id, "relu_field", export={
        "views": 1, "view_size": 16, "turntable_frames": 2, "turntable_size": 16, "gif": False, "mesh": True})["id"]
    monkeypatch.setattr(runtime, "get_guidance", lambda *args: NO_MODEL)
    monkeypatch.setattr(voxe_core.edit, "edit", lambda initial, *args, **kwargs: initial.clone_grid())
    assert tasks.edit_task.apply(args=(job_id,)).get()["state"] == "done"

    def no_surface(grid, resolution):
        raise ValueError("no density crosses the level 10.0 (the grid's largest is 3.2)")

    monkeypatch.setattr(voxe_core.export, "extract_mesh", no_surface)
    assert tasks.export_task.apply(args=(job_id,)).get()["state"] == "done"
    job = client.get(f"/v1/jobs/{job_id}").json()
    assert (job["state"], job["error"]) == ("succeeded", None)
    assert job["message"] == "no mesh exported: no density crosses the level 10.0 (the grid's largest is 3.2)"
    listed = {a["name"] for a in client.get(f"/v1/jobs/{job_id}/artifacts").json()}
    assert "turntable.mp4" in listed and not any(name.startswith("mesh.") for name in listed)


class WorkerKilled(BaseException):
    """Stands in for the worker process going down mid-task (what _run_stage hands back to the queue)."""


@pytest.mark.parametrize("failure", ["storage outage", "worker killed"])
def test_an_export_whose_upload_fails_mid_mesh_set_lists_no_mesh_and_its_rerun_publishes_every_format(
        service, monkeypatch, failure):
    """The storage failing after mesh.ply and mesh.glb were uploaded (S3 throttling mesh.obj) had failed the job
    with those two listed; a failure at mesh.mtl, mesh.obj without its material. The set is recorded in one
    transaction once every format is stored: the stopped run (the outage gives the job back) lists none of it and
    leaves none of its bytes, and the stage run again (a redelivery) publishes all four."""
    import hashlib

    from voxe_service.storage import get_storage
    from worker import tasks

    client, scene_id = service
    job_id = _edited_job_exporting_a_mesh(client, scene_id, monkeypatch)
    storage = get_storage(tasks.get_settings())
    failing_name = "mesh.obj" if failure == "storage outage" else "mesh.mtl"
    monkeypatch.setattr("worker.runtime.OUTAGE_PAUSE_S", 0.0)
    with monkeypatch.context() as failing:
        failing_uploads(failing, storage, failing_name, WorkerKilled() if failure == "worker killed" else None)
        if failure == "worker killed":
            with pytest.raises(WorkerKilled):
                tasks.export_task.apply(args=(job_id,))
        else:
            result = tasks.export_task.apply(args=(job_id,))
            assert result.state == "REJECTED" and "SlowDown when uploading" in result.result.reason
    job = client.get(f"/v1/jobs/{job_id}").json()
    assert (job["state"], job["error"]) == ("running", None)
    listed = {a["name"] for a in client.get(f"/v1/jobs/{job_id}/artifacts").json()}
    assert listed == {"initial_grid.safetensors", "edited_grid.safetensors", "preview.png", "render_000.png",
                      "turntable.mp4"}
    assert [key for key in storage.list(f"jobs/{job_id}/") if "mesh" in key] == []
    assert tasks.export_task.apply(args=(job_id,)).get()["state"] == "done"  # the redelivered message
    artifacts = {a["name"]: a for a in client.get(f"/v1/jobs/{job_id}/artifacts").json()}
    assert {"mesh.ply", "mesh.glb", "mesh.obj", "mesh.mtl", "preview.png"} <= set(artifacts)
    for name in ("mesh.ply", "mesh.glb", "mesh.obj", "mesh.mtl"):
        download = client.get(f"/v1/jobs/{job_id}/artifacts/{name}")
        assert download.status_code == 200
        assert hashlib.sha256(download.content).hexdigest() == artifacts[name]["sha256"]


def _edited_job_to_export(service, monkeypatch, *, views: int, gif: bool):
    """(client, job id, storage): a job of the service's scene edited (the edit a copy of its grid), exporting
    ``views`` views of 16 px, a turntable of two frames (and its GIF where ``gif``), no mesh."""
    import voxe_core.edit
    from voxe_service.storage import get_storage
    from worker import runtime, tasks

    client, scene_id = service
    job_id = _reconstructed_job(client, scene_id, "relu_field", export={
        "views": views, "view_size": 16, "turntable_frames": 2, "turntable_size": 16, "gif": gif, "mesh": False})["id"]
    monkeypatch.setattr(runtime, "get_guidance", lambda *args: NO_MODEL)
    monkeypatch.setattr(voxe_core.edit, "edit", lambda initial, *args, **kwargs: initial.clone_grid())
    assert tasks.edit_task.apply(args=(job_id,)).get()["state"] == "done"
    return client, job_id, get_storage(tasks.get_settings())


def _artifacts_of_an_export_refused_for_good(client, job_id: str) -> set[str]:
    """The names a job lists once its export failed on the storage's AccessDenied (no outage: the job fails)."""
    from worker import tasks

    assert tasks.export_task.apply(args=(job_id,)).get()["state"] == "failed"
    job = client.get(f"/v1/jobs/{job_id}").json()
    assert (job["state"], job["error"]) == (
        "failed", "export: StorageError: S3 bucket 'voxe': AccessDenied when uploading")
    return {a["name"] for a in client.get(f"/v1/jobs/{job_id}/artifacts").json()}


def test_an_export_whose_storage_refuses_the_turntable_gif_lists_neither_turntable_file(service, monkeypatch):
    """turntable.mp4 and turntable.gif (one render of each frame feeds both) are one set, as the mesh formats are:
    the storage refusing the GIF for good (access denied, no outage) had failed the job with turntable.mp4 listed
    and stored, the GIF missing. Now the failed job lists neither and the storage keeps neither."""
    from voxe_service.storage import StorageError

    client, job_id, storage = _edited_job_to_export(service, monkeypatch, views=1, gif=True)
    failing_uploads(monkeypatch, storage, "/turntable.gif",
                    StorageError("S3 bucket 'voxe': AccessDenied when uploading"))
    listed = _artifacts_of_an_export_refused_for_good(client, job_id)
    assert listed == {"initial_grid.safetensors", "edited_grid.safetensors", "preview.png", "render_000.png"}
    assert [key for key in storage.list(f"jobs/{job_id}/") if "turntable" in key] == []


def test_an_export_whose_storage_refuses_one_view_lists_none_of_its_views(service, monkeypatch):
    """The export's views (render_000.png ...) are one set, as the evaluation's rings are: the storage refusing
    render_001.png for good (access denied, no outage) had failed the job with render_000.png listed and stored, a
    ring of one view where three were asked for. Now the failed job lists none of them and the storage keeps none."""
    from voxe_service.storage import StorageError

    client, job_id, storage = _edited_job_to_export(service, monkeypatch, views=3, gif=False)
    failing_uploads(monkeypatch, storage, "/render_001.png",
                    StorageError("S3 bucket 'voxe': AccessDenied when uploading"))
    listed = _artifacts_of_an_export_refused_for_good(client, job_id)
    assert listed == {"initial_grid.safetensors", "edited_grid.safetensors", "preview.png"}
    assert [key for key in storage.list(f"jobs/{job_id}/") if "render_" in key] == []


def test_an_export_whose_turntable_gif_upload_fails_after_storing_it_keeps_no_turntable_bytes(service, monkeypatch):
    """An upload can fail after the storage kept its bytes (the PUT's answer lost, a connection reset on the way
    back): the stopped set discarded only the uploads that had returned, leaving turntable.gif stored under the job
    with no row listing it. Every upload begun is discarded unless a row records it."""
    from voxe_service.storage import StorageError
    from worker import tasks

    client, job_id, storage = _edited_job_to_export(service, monkeypatch, views=1, gif=True)
    put_file = type(storage).put_file

    def stored_then_lost(self, key, path, content_type=None):
        stored = put_file(self, key, path, content_type)
        if key.endswith("/turntable.gif"):
            raise StorageError(f"S3 bucket 'voxe': connection reset after uploading {stored.key}")
        return stored

    monkeypatch.setattr(type(storage), "put_file", stored_then_lost)
    assert tasks.export_task.apply(args=(job_id,)).get()["state"] == "failed"
    listed = {a["name"] for a in client.get(f"/v1/jobs/{job_id}/artifacts").json()}
    assert not {"turntable.mp4", "turntable.gif"} & listed
    assert [key for key in storage.list(f"jobs/{job_id}/") if "turntable" in key] == []


def test_the_export_renders_the_published_edit_not_a_superseded_runs_grid_left_in_its_scratch(service, monkeypatch,
                                                                                              tmp_path):
    """An edit run that stalled while another run took its job over has its grid refused, but the file stays in its
    worker's scratch: the job's export, landing on that worker, renders the grid the job published."""
    import hashlib
    from datetime import timedelta

    from sqlalchemy import update

    import voxe_core.edit
    from voxe_service.db import session_scope
    from voxe_service.models import Job, utcnow
    from worker import runtime, tasks

    client, scene_id = service
    job_id = _reconstructed_job(client, scene_id, "relu_field", export={
        "views": 1, "view_size": 16, "turntable_frames": 2, "turntable_size": 16, "gif": False, "mesh": False})["id"]
    settings = tasks.get_settings()
    here = settings.work_dir
    monkeypatch.setattr(runtime, "get_guidance", lambda *args: NO_MODEL)

    def stalled_edit(initial, *args, **kwargs):  # run 1, here: another run takes the job over meanwhile
        with session_scope() as session:
            session.execute(update(Job).where(Job.id == job_id).values(
                run_token="run 2", run_lease_until=utcnow() + timedelta(seconds=600)))
        grid = initial.clone_grid()
        with torch.no_grad():
            grid.features[..., 0] = -10.0
        return grid

    monkeypatch.setattr(voxe_core.edit, "edit", stalled_edit)
    assert tasks.edit_task.apply(args=(job_id,)).state == "IGNORED"  # its grid refused, its file left in scratch
    with session_scope() as session:  # run 2, on another worker, publishes its own grid
        session.execute(update(Job).where(Job.id == job_id).values(run_token=None, run_lease_until=None))
    monkeypatch.setattr(settings, "work_dir", str(tmp_path / "another_worker"))
    monkeypatch.setattr(voxe_core.edit, "edit", lambda initial, *args, **kwargs: initial.clone_grid())
    assert tasks.edit_task.apply(args=(job_id,)).get()["state"] == "done"
    monkeypatch.setattr(settings, "work_dir", here)  # the export lands here
    rendered, real_fetch_grid = {}, tasks.fetch_grid

    def recorded_fetch_grid(job, name, *args, **kwargs):
        grid = real_fetch_grid(job, name, *args, **kwargs)
        rendered[name] = hashlib.sha256((runtime.scratch_dir(job, settings) / name).read_bytes()).hexdigest()
        return grid

    monkeypatch.setattr(tasks, "fetch_grid", recorded_fetch_grid)
    assert tasks.export_task.apply(args=(job_id,)).get()["state"] == "done"
    listed = {a["name"]: a["sha256"] for a in client.get(f"/v1/jobs/{job_id}/artifacts").json()}
    assert rendered == {"edited_grid.safetensors": listed["edited_grid.safetensors"]}


def test_a_job_that_lost_the_fit_goes_on_with_the_recorded_grid_not_its_own(service, monkeypatch, tmp_path):
    """A run whose fit was taken over before it stored its grid (its grid refused) waits for the new owner's, and
    takes that: not the grid it left in its scratch, which its artifact had listed under the winner's key."""
    import threading

    from sqlalchemy import update

    from conftest import make_sphere_grid
    from voxe_service.db import session_scope
    from voxe_service.models import Reconstruction, utcnow
    from voxe_service.storage import file_sha256, get_storage
    from worker import runtime, tasks

    client, scene_id = service
    body = {**TINY_FIT, "reconstruction": {**TINY_FIT["reconstruction"], "seed": 12}}
    a, b = (client.post("/v1/jobs", json={"scene_id": scene_id, "prompt": "a mic", "params": body}).json()["id"]
            for _ in range(2))
    rec_id = runtime.load_job(a).reconstruction_id

    def b_stores_its_fit():
        make_sphere_grid(radius=0.8).save(tmp_path / "b.safetensors")
        stored = get_storage().put_file(f"reconstructions/{rec_id}/grid-b.safetensors", tmp_path / "b.safetensors")
        runtime.set_reconstruction(rec_id, b, state="succeeded", grid_key=stored.key, grid_size=stored.size,
                                   grid_sha256=stored.sha256, iteration=1, total=1, lease_until=None,
                                   finished_at=utcnow())

    def fit_stalled(*args, **kwargs):  # A stalled past its lease: B claimed the fit meanwhile, and stores it later
        with session_scope() as session:
            session.execute(update(Reconstruction).where(Reconstruction.id == rec_id).values(
                owner_job_id=b, owner_run_token="b's run"))
        threading.Timer(1.0, b_stores_its_fit).start()
        return make_sphere_grid(radius=0.3), 1

    monkeypatch.setattr(tasks, "_fit_grid", fit_stalled)
    assert tasks.reconstruct_task.apply(args=(a,)).get()["state"] == "done"
    rec = runtime.load_reconstruction(rec_id)
    listed = {x["name"]: x for x in client.get(f"/v1/jobs/{a}/artifacts").json()}["initial_grid.safetensors"]
    scratch = runtime.scratch_dir(a, tasks.get_settings()) / "initial_grid.safetensors"
    assert listed["sha256"] == rec.grid_sha256 == file_sha256(scratch)[1]


def _locally_edited_job(client, scene_id: str, monkeypatch) -> str:
    """A local job ("hat" of "a mic wearing a hat") whose edit left a dense 4³ block, and nothing else occupied: its
    refine stage has a cut of a known size to make."""
    import voxe_core.edit
    from worker import runtime, tasks

    job_id = _reconstructed_job(client, scene_id, "relu_field",
                                {"prompt": "a mic wearing a hat", "mode": "local", "edit_words": ["hat"]},
                                refine={"views": 2, "render_size": 16, "iterations": 0})["id"]

    def dense_block(initial, *args, **kwargs):
        edited = initial.clone_grid()
        edited.features.data[..., 0] = -1.0  # (what the tiny fit occupied)
        edited.features.data[4:8, 4:8, 4:8, 0] = 5.0
        return edited

    with monkeypatch.context() as recorded_edit:
        recorded_edit.setattr(runtime, "get_guidance", lambda *args: NO_MODEL)
        recorded_edit.setattr(voxe_core.edit, "edit", dense_block)
        assert tasks.edit_task.apply(args=(job_id,)).get()["state"] == "done"
    return job_id


def test_the_workers_refinement_with_a_tiny_model_folder_says_it_is_a_smoke_test(service, monkeypatch, tmp_path):
    """``VOXE_ATTENTION_MODEL`` a folder ``voxe build-tiny-model`` wrote: the refine stage says so (a warning event,
    ``result.smoke_test.attention``) and the refined grid carries the note, as voxe refine's."""
    import voxe_core.refine.pipeline
    from voxe_core.backbones import grid_notes
    from voxe_core.tiny_sd import build_tiny_stable_diffusion
    from voxe_service.settings import get_settings
    from worker import tasks

    folder = build_tiny_stable_diffusion(tmp_path / "sd")
    monkeypatch.setattr(get_settings(), "attention_model", str(folder))
    client, scene_id = service
    job_id = _locally_edited_job(client, scene_id, monkeypatch)
    monkeypatch.setattr(voxe_core.refine.pipeline, "fit_attention_grids", _attention_favouring("some"))
    assert tasks.refine_task.apply(args=(job_id,)).get()["state"] == "done"
    note = (f"SMOKE TEST: the attention model {str(folder)!r} is a random-weight smoke-test Stable Diffusion (voxe "
            "build-tiny-model): what is made with it proves the plumbing only and says nothing about edit quality")
    warnings = [(e["stage"], e["detail"]) for e in client.get(f"/v1/jobs/{job_id}/events").json()
                if e["kind"] == "warning"]
    assert warnings == [("refine", note)]
    assert client.get(f"/v1/jobs/{job_id}").json()["result"]["smoke_test"] == {"attention": note}
    refined = tmp_path / "refined.safetensors"
    refined.write_bytes(client.get(f"/v1/jobs/{job_id}/artifacts/refined_grid.safetensors").content)
    assert grid_notes(refined) == {"smoke_test": note}


def _attention_favouring(kept: str):
    """A stand-in for the attention-grid fit whose grids favour the edit everywhere, nowhere, or at x < 6 ("some":
    half the block's nodes)."""
    def fit(grid, *args, **kwargs):
        edit_field = torch.full((*grid.resolution, 1), 5.0 if kept == "everything" else -5.0)
        if kept == "some":
            edit_field[:6] = 5.0
        return edit_field, -edit_field

    return fit


@pytest.mark.parametrize("kept", ["nothing", "some", "everything"])
def test_a_refinement_whose_cut_keeps_nothing_or_everything_says_so_and_records_the_cuts_statistics(
        service, monkeypatch, kept):
    """A cut that labelled every occupied voxel alike (here: attention grids that favour the object, or the edit,
    everywhere) had let the job succeed with a refined grid equal to G_i (or to G_e), saying nothing, and the
    cut's statistics (which voxe refine writes and prints) were dropped. The job's result keeps them, and a warning
    event and the job's message say what became of the edit, with the cut's notes; a cut that kept some voxels and
    not others warns of nothing."""
    import voxe_core.refine.pipeline
    from voxe_core.backbones import load_grid
    from worker import runtime, tasks

    client, scene_id = service
    job_id = _locally_edited_job(client, scene_id, monkeypatch)
    monkeypatch.setattr(voxe_core.refine.pipeline, "fit_attention_grids", _attention_favouring(kept))
    assert tasks.refine_task.apply(args=(job_id,)).get()["state"] == "done"

    job = client.get(f"/v1/jobs/{job_id}").json()
    cut = job["result"]["graph_cut"]
    taken = {"nothing": 0, "some": 108, "everything": 216}[kept]  # of the block dilated by one (6³, max-pooled)
    assert (cut["nodes"], cut["edit_voxels"]) == (216, taken)
    assert (cut["edit_seeds"], cut["object_seeds"]) == (taken, 216 - taken)  # every node a seed of the label it favours
    assert cut["notes"] == [f"only {taken} of 300 edit seeds qualified",
                            f"only {216 - taken} of 5000 object seeds qualified"]
    warnings = [(e["stage"], e["detail"]) for e in client.get(f"/v1/jobs/{job_id}/events").json()
                if e["kind"] == "warning"]
    if kept == "some":
        assert warnings == [] and job["message"] == "refine: graph_cut"  # (its last progress phase)
        return
    said = ("the graph cut kept none of the edited grid's 216 occupied voxels: the refined grid is the initial "
            "grid, the edit undone" if kept == "nothing" else
            "the graph cut kept all 216 occupied voxels of the edited grid: the edit is not localised (the refined "
            "grid takes the edited grid at every one of them)")
    assert job["message"] == "; ".join([said, *cut["notes"]])
    assert warnings == [("refine", job["message"])]
    scratch = runtime.scratch_dir(job_id, tasks.get_settings())
    refined = load_grid(scratch / "refined_grid.safetensors")
    expected = load_grid(scratch / ("initial_grid.safetensors" if kept == "nothing" else "edited_grid.safetensors"))
    assert torch.equal(refined.features[3:9, 3:9, 3:9], expected.features[3:9, 3:9, 3:9])


@pytest.mark.parametrize("failing_name", ["mask.safetensors", "mask_overlay.png"])
def test_a_refinement_whose_upload_fails_mid_set_lists_none_of_its_files(service, monkeypatch, failing_name):
    """The storage failing after refined_grid.safetensors was uploaded (S3 throttling the mask) had failed the job
    with the refined grid listed without the mask it was merged by; at the overlay, every file but it. The four
    are published as one set: the stopped run (the outage gives the job back) lists none of them and keeps none of
    their bytes."""
    import voxe_core.refine.pipeline
    from voxe_service.storage import get_storage
    from worker import tasks

    client, scene_id = service
    job_id = _locally_edited_job(client, scene_id, monkeypatch)
    monkeypatch.setattr(voxe_core.refine.pipeline, "fit_attention_grids", _attention_favouring("some"))
    storage = get_storage(tasks.get_settings())
    failing_uploads(monkeypatch, storage, failing_name)
    monkeypatch.setattr("worker.runtime.OUTAGE_PAUSE_S", 0.0)
    result = tasks.refine_task.apply(args=(job_id,))
    assert result.state == "REJECTED" and "SlowDown when uploading" in result.result.reason
    job = client.get(f"/v1/jobs/{job_id}").json()
    assert (job["state"], job["error"]) == ("running", None)
    listed = {a["name"] for a in client.get(f"/v1/jobs/{job_id}/artifacts").json()}
    assert listed == {"initial_grid.safetensors", "edited_grid.safetensors", "preview.png"}
    refine_files = ("refined_grid", "mask", "attention_probabilities")
    assert [key for key in storage.list(f"jobs/{job_id}/") if key.rsplit("/", 1)[-1].startswith(refine_files)] == []


def test_the_papers_constant_start_fits_every_pixel_the_default_start_the_codes_positive_ones():
    paper_fit = refine_config({"refine": {"lift_start": "constant", "iterations": 1500}}, ATTENTION_MODEL_ID)
    assert (paper_fit.fit_views, paper_fit.fit_pixels, paper_fit.iterations) == ("fixed", "all", 1500)
    default = refine_config({}, ATTENTION_MODEL_ID)
    assert (default.fit_views, default.fit_pixels) == ("fresh", "rendered_positive")


@pytest.mark.parametrize("view_words", [True, False])
def test_the_refinements_attention_prompt_says_what_the_edits_prompt_said(view_words):
    params = {"view_words": view_words}
    assert edit_config(params).view_words is view_words
    assert refine_config(params, ATTENTION_MODEL_ID).view_word_prompt is view_words


def test_a_job_asking_no_object_seeds_is_refused_at_submission_naming_the_field():
    """The service's cut has no unary term: with ``refine.object_seeds`` 0 nothing pulls a voxel to the object and
    every voxel joined to an edit seed stays edited. It had been accepted (ge=0), the whole refinement run, and the
    job had ended with an edit not localised and a warning."""
    from pydantic import ValidationError

    from api.schemas import JobCreate

    with pytest.raises(ValidationError) as refused:
        JobCreate(scene_id="s", prompt="a mic", params={"refine": {"object_seeds": 0}})
    (error,) = refused.value.errors()
    assert error["loc"] == ("params", "refine", "object_seeds") and error["msg"].endswith("greater than or equal to 1")
    assert "without object seeds it keeps every voxel joined to an edit seed" in (
        JobParams.model_json_schema()["$defs"]["RefineParams"]["properties"]["object_seeds"]["description"])
    job = JobCreate(scene_id="s", prompt="a mic", params={"refine": {"object_seeds": 1}})
    assert refine_config(job.params.model_dump(), "tiny").object_seeds == 1
