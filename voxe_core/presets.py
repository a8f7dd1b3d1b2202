"""Job parameters -> voxe_core stage configs: the one place presets resolve and job-parameter defaults live.

Job parameters are the service's JSON (``api.schemas.JobParams``, whose defaults are read from here
and from ``voxe_core.constants``) and what the options of ``voxe`` build (``voxe_core.cli``); both
go through the functions below, so equal parameters give equal configs. A key left out (or None)
takes its default here. Importing this module loads no torch: each stage module is imported where
its config is built.

Real scenes (SPEC §5): an edit of a scene-backbone G_i (``grid.kind == "scene"``) anneals the
time-step range from iteration 3,000 every 400 (``EDIT_SCHEDULES``) instead of 4,000 / 600, with the
floor ``timestep_schedule`` picks (paper 0.35, authors 0.22), and runs 5,000 iterations where
``iterations`` is left at the paper's object count of 8,000 (the default); any other count runs as given.

Examples:
    >>> edit_config({}).iterations, edit_config({}, backbone="scene").iterations
    (8000, 5000)
    >>> edit_config({"iterations": 300}, backbone="scene").schedule.i_start
    3000
    >>> export_config({"export": {"views": 2}}).views, export_config({}).views
    (2, 8)
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import numbers
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

from voxe_core import constants as paper

if TYPE_CHECKING:  # the stage modules are imported where a config is built, so importing this module stays light
    import torch

    from voxe_core.cameras import Cameras
    from voxe_core.grid import VoxelGrid
    from voxe_core.edit import EditConfig
    from voxe_core.reconstruct import ReconstructConfig
    from voxe_core.refine.config import RefineConfig

# ------------------------------------------------------------------ defaults of the job parameters
DOWNSAMPLE = 3
"""Integer image downsampling on load: the paper edits its 800 px inputs at 266 px (SPEC §1)."""
RESAMPLE = "bilinear"
"""The downsampling's antialiasing filter, as the authors' loader (``voxe_core.data.RESAMPLE_FILTERS``)."""
RECONSTRUCTION_PRESETS = ("fast", "paper", "scene")
"""``ReconstructConfig.fast()`` (the CPU budget), ``ReconstructConfig()`` (the authors' recipe) or
``ReconstructConfig.scene()`` (the CPU budget of a scene-backbone fit, measured on fox)."""
RECONSTRUCTION_PRESET = "fast"
"""The preset of a ReLU-field fit when none is named; a scene-backbone fit gets ``BACKBONE_PRESETS``'."""
BACKBONE_PRESETS = {"scene": "scene"}
"""Backbone kind -> the preset its fits get when none is named (others: ``RECONSTRUCTION_PRESET``)."""
BACKBONE_KINDS = ("relu_field", "scene")
"""What "auto" can resolve to (``voxe_core.backbones.BACKBONES``, spelt out: importing it loads torch)."""
BACKBONE_CHOICES = ("auto", *BACKBONE_KINDS)
"""What a user may ask for ("auto": decided from the images' alpha)."""
BACKBONE = "auto"
"""The backbone of a fit when none is named: decided from the images' alpha."""
TIMESTEP_SCHEDULES = ("paper", "authors")
"""The annealing floor: 0.35 (paper) or 0.22 (authors' code)."""
PREVIEW_EVERY = 100
"""Edit iterations between preview renders (0: none)."""
EDIT_MODES = ("global", "local")
"""A job's edit: of the whole grid, or refined to its edit words' region (SPEC §3)."""
EDIT_MODE = EDIT_MODES[0]
JOB_OPTION_RULES = ("edit_words_required", "edit_words_local_only", "webhook_events_need_url")
"""The rules of a job's fields that no scene or parameter changes, each named: ``broken_job_option_rule``."""
BATCH_SIZE = 1
"""Poses (renders) per edit iteration."""
VIEW_WORDS = True
"""Append ', front view' etc. to the prompt from the pose (the authors' code), in the edit and the attention maps."""
LIFT_STARTS = ("backprojection", "constant")
"""Start of the attention grids: the maps' weighted back-projection (ours), or 0 everywhere (the paper's fit)."""
LIFT_START = LIFT_STARTS[0]
SEED = 0
MAX_SEED = paper.MAX_SEED
"""The largest seed a job or the CLI takes (numpy's seed range)."""
MESH_VIEWS, MESH_VIEW_SIZE = 100, 256
"""Renders of a mesh for route (a) (the paper: 100 upper-hemisphere views): the service stores them at 256 px and
its fit loads them at 1 / ``DOWNSAMPLE``; ``voxe mesh-to-grid --route render`` renders at that size."""


def broken_job_option_rule(mode: str, edit_words, webhook_url, webhook_events) -> str | None:
    """The first of ``JOB_OPTION_RULES`` that a job's fields break, or None. ``POST /v1/jobs`` and ``voxe submit
    --upload`` (before it uploads) both read it, each saying the rule in its own words (fields, options), so the
    two cannot drift apart."""
    if mode == "local" and not edit_words:
        return "edit_words_required"
    if mode != "local" and edit_words:
        return "edit_words_local_only"
    if webhook_events is not None and webhook_url is None:
        return "webhook_events_need_url"
    return None


@dataclass(frozen=True)
class EditSchedule:
    """How long an edit runs and when its time-step range anneals (``TimestepSchedule.i_start`` / ``every``)."""

    iterations: int
    i_start: int
    every: int


EDIT_SCHEDULES: dict[str, EditSchedule] = {"scene": EditSchedule(iterations=5000, i_start=3000, every=400)}
"""Backbone kind -> its edit schedule where it is not SPEC §2's (8,000 iterations, 4,000 / 600): SPEC §5's for scenes."""


VIDEO_MIN_FPS = 100 / 65535
"""The slowest turntable video: a GIF frame's delay is a 16-bit count of centiseconds, at most 655.35 s (the MP4
encoder fails further down, near 1e-6 fps); one floor for both formats, so the job parameters can state it."""


VIDEO_MAX_FPS = 1_000_000
"""The fastest turntable video: ffmpeg writes a faster MP4 at 1,001,000 fps (a longer clip than asked), and
refuses above about 2.1e9 fps, after the whole render; one ceiling for both formats (the API's is 120)."""


def check_video_fps(fps: float) -> None:
    """ValueError for a frame rate no video holds (Pillow overflowed and ffmpeg wrote nothing, after the whole job)."""
    if not (VIDEO_MIN_FPS <= fps <= VIDEO_MAX_FPS):  # (NaN fails both; infinity the ceiling)
        raise ValueError(f"fps must be a finite number of at least {VIDEO_MIN_FPS:.6f} (a frame's delay is at most "
                         f"655.35 s in a GIF) and at most {VIDEO_MAX_FPS:,} (the fastest rate ffmpeg writes in an "
                         f"MP4), got {fps:g}")


@dataclass(frozen=True)
class ExportConfig:
    """What the export stage writes (the job parameters' ``export``): ring PNGs, a turntable video, a mesh."""

    views: int = 8  # PNG renders on a ring around the object (0: none)
    view_size: int = 256
    turntable_frames: int = 100
    turntable_size: int = 256
    elevation: float = 30.0  # degrees above the horizon, of the ring and the turntable
    fps: float = 30.0
    gif: bool = True  # also a looping GIF of the turntable
    mesh: bool = True  # marching-cubes mesh as PLY, GLB and OBJ (+ MTL)
    mesh_resolution: int | None = None  # None: the grid's own vertices


# ------------------------------------------------------------------ reconstruction
def reconstruction_route(params: dict, mesh_scene: bool) -> str:
    """'fit' or 'voxelize': "auto" voxelizes a mesh scene (faster and closer to the mesh, bench/results/mesh_input.json)
    unless the scene backbone was asked for, and fits everything else."""
    rec = params.get("reconstruction") or {}
    route = rec.get("route", "auto")
    if route == "auto":
        return "voxelize" if mesh_scene and rec.get("backbone", BACKBONE) != "scene" else "fit"
    return route


def reconstruction_params(params: dict, mesh_scene: bool = False) -> dict:
    """The part of a job's parameters that determines G_i (the reconstruction cache key)."""
    rec = dict(params.get("reconstruction") or {})
    # "auto" (and route "fit") add nothing, so jobs that leave them out and jobs that name them share a fit.
    backbone = {} if rec.get("backbone", BACKBONE) == "auto" else {"backbone": rec["backbone"]}
    route = reconstruction_route(params, mesh_scene)
    return {
        **backbone,
        **({} if route == "fit" else {"route": route}),
        "split": "train",
        "downsample": int(_given(params, "downsample", DOWNSAMPLE)),
        "resample": _given(params, "resample", RESAMPLE),
        "max_images": params.get("max_images"),
        "preset": rec.get("preset"),  # None: the backbone's default preset (``default_preset``)
        "resolution": rec.get("resolution"),
        "iterations": rec.get("iterations"),
        "rays_per_step": rec.get("rays_per_step"),
        "seed": int(_given(rec, "seed", SEED)),
    }


def reconstruction_key(rec_params: dict) -> str:
    """A hash of the parameters and of the recipe they resolve to today, so that a fit cached
    before voxe_core's presets or defaults changed is refitted rather than reused.

    The backbone "auto" resolves only once the images are loaded, so its key holds the recipe of
    every backbone it can become: a change to either backbone's default preset refits it.
    Raises ValueError for parameters that resolve to no recipe (as ``reconstruct_config``); under
    "auto", only when they fit no backbone's (per-stage lists sized for one preset's stage count).
    """
    backbone = rec_params.get("backbone", BACKBONE)
    recipes, errors = {}, []
    for kind in BACKBONE_KINDS if backbone == "auto" else (backbone,):
        try:  # what is fitted: not how often progress is saved nor how much memory a pass may hold
            recipes[kind] = reconstruct_config(rec_params, backbone=kind).recipe()
        except ValueError as exc:
            errors.append(exc)
    if not recipes:
        raise errors[0]
    payload = {"params": rec_params, "recipe": recipes}
    return hashlib.sha256(json.dumps(payload, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def default_preset(backbone: str) -> str:
    """The preset a fit of a ``backbone`` grid (its resolved kind) gets when the parameters name none."""
    return BACKBONE_PRESETS.get(backbone, RECONSTRUCTION_PRESET)


def reconstruct_config(rec_params: dict, checkpoint_every: int = 0, backbone: str = "relu_field") -> "ReconstructConfig":
    """A preset (named, or ``backbone``'s default: pass the resolved kind, not "auto"), then the final
    resolution and iterations: each one value (the final stage's; earlier resolutions scaled in
    proportion) or one per stage. ValueError for lists that fit no stage count.

    Examples:
        >>> reconstruct_config({}).resolutions, reconstruct_config({}, backbone="scene").resolutions
        ((40, 80, 128), (48, 96))
    """
    from voxe_core.reconstruct import ReconstructConfig

    preset = _given(rec_params, "preset", default_preset(backbone))
    if preset not in RECONSTRUCTION_PRESETS:
        raise ValueError(f"unknown reconstruction preset {preset!r}; use {', '.join(RECONSTRUCTION_PRESETS)}")
    config = {"fast": ReconstructConfig.fast, "scene": ReconstructConfig.scene, "paper": ReconstructConfig}[preset]()
    overrides: dict = {"seed": int(_given(rec_params, "seed", SEED)), "checkpoint_every": checkpoint_every}
    resolution = _per_stage(rec_params.get("resolution"), len(config.resolutions), "resolution")
    if resolution is not None:
        if len(resolution) == 1:
            final = resolution[0]
            resolution = [max(2, round(final * r / config.resolutions[-1])) for r in config.resolutions[:-1]] + [final]
        overrides["resolutions"] = tuple(resolution)
    iterations = _per_stage(rec_params.get("iterations"), len(config.resolutions), "iterations")
    if iterations is not None:
        overrides["iterations"] = tuple([*config.iterations[:-1], *iterations] if len(iterations) == 1 else iterations)
    if rec_params.get("rays_per_step") is not None:
        overrides["rays_per_step"] = _whole(rec_params["rays_per_step"], "rays_per_step")
    return dataclasses.replace(config, **overrides).for_backbone(backbone)


class FitSetup(NamedTuple):
    """What ``voxe_core.reconstruct.reconstruct`` needs beyond the images, for one loaded scene."""

    backbone: str
    """The resolved kind ("auto" decided from the images' alpha)."""
    config: "ReconstructConfig"
    cameras: "Cameras"
    """The scene's cameras, in the canonical frame a scene grid is fitted in."""
    initial: "VoxelGrid | None"
    """The grid to start from (a scene grid carrying that frame), or None for a fresh ReLU field."""


BACKBONE_REASONS = {"relu_field": "its images show an object on a transparent background",
                    "scene": "its images are opaque photos"}
"""Why "auto" became each backbone kind (``voxe_core.backbones.detect_backbone``), said in refusals."""


def fit_backbone(rec_params: dict, scene_backbone: str | None = None) -> str:
    """The backbone a fit of ``rec_params`` asks for, "auto" read as ``scene_backbone`` when the scene's kind is
    known beforehand (the service decides it once per scene, at ingest, from all its training images).

    Examples:
        >>> fit_backbone({}, "scene"), fit_backbone({"backbone": "relu_field"}, "scene"), fit_backbone({})
        ('scene', 'relu_field', 'auto')
    """
    asked = rec_params.get("backbone", BACKBONE)
    return scene_backbone if asked == "auto" and scene_backbone else asked


def check_fit(rec_params: dict, scene_backbone: str | None, image_count: int | None = None) -> None:
    """ValueError, naming what "auto" became and why, for parameters that resolve to no recipe on a scene of kind
    ``scene_backbone`` (None: not known yet, so only what fits no backbone is refused, by ``reconstruction_key``)
    and ``image_count`` training images (None: not known)."""
    backbone = fit_backbone(rec_params, scene_backbone)
    if backbone == "auto":
        return
    try:
        reconstruct_config(rec_params, backbone=backbone)
        _check_views_kept(rec_params, backbone, image_count)
    except ValueError as exc:
        if rec_params.get("backbone", BACKBONE) != "auto":
            raise
        raise ValueError(f"{exc}: backbone 'auto' is {backbone!r} for this scene "
                         f"({BACKBONE_REASONS[backbone]})") from None


def _check_views_kept(rec_params: dict, backbone: str, image_count: int | None) -> None:
    """ValueError for a scene-backbone fit of one image (``max_images`` 1, or a scene of ``image_count`` 1): its
    frame is the centre the cameras orbit, which one camera has none of (``scene_frame``); the worker had found it
    only once it had loaded the images, after the job was accepted."""
    if backbone != "scene":
        return
    if rec_params.get("max_images") == 1:
        raise ValueError("max_images 1 keeps a single image, whose one camera has no centre to orbit: the scene "
                         "backbone needs views from around the object (raise max_images, or leave it out)")
    if image_count == 1:
        raise ValueError("the scene has a single training image, whose one camera has no centre to orbit: the scene "
                         "backbone needs views from around the object (upload them)")


def fit_setup(rec_params: dict, alphas: "torch.Tensor | None", cameras: "Cameras",
              checkpoint_every: int = 0, scene_backbone: str | None = None,
              split_c2w: "torch.Tensor | None" = None) -> FitSetup:
    """The backbone ``rec_params`` asks for (resolved as ``scene_backbone`` when given, else for images with
    ``alphas``), its config and starting point: what the CLI and the worker both run before ``reconstruct``.
    ``split_c2w``: ``Scene.split_c2w``, so that cameras too few to fit from name ``max_images`` when they are.
    Too few cameras for the backbone are refused as a submission is, naming their count: a scene whose "auto" only
    its images decide (one ingested before its backbone was recorded) passed the submission's check unresolved."""
    from voxe_core.backbones import prepare_backbone, resolve_backbone

    backbone = resolve_backbone(fit_backbone(rec_params, scene_backbone), alphas)
    check_fit(rec_params, backbone, len(cameras))  # a refusal says what "auto" became
    config = reconstruct_config(rec_params, checkpoint_every, backbone)  # the backbone's default preset
    _, fit_cameras, initial = prepare_backbone(backbone, alphas, cameras, config.resolutions[0], split_c2w)
    return FitSetup(backbone, config, fit_cameras, initial)


def _whole(value, what: str) -> int:
    """``value`` when it is a whole number; ValueError naming ``what`` for anything else (a bool, a float, a string:
    int() had read 2.9 as 2, and iterating "96" as the stages (9, 6))."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{what} takes whole numbers, got {value!r}")
    return int(value)


def _per_stage(value, n_stages: int, what: str) -> list[int] | None:
    """``value`` (None, one int, or a list or tuple of ints) as a list of one value or one per stage."""
    if value is None:
        return None
    values = [_whole(v, what) for v in (value if isinstance(value, (list, tuple)) else [value])]
    if len(values) not in (1, n_stages):
        raise ValueError(f"{what} takes one value or one per stage ({n_stages} stages), got {len(values)}")
    return values


# ------------------------------------------------------------------ editing and refinement
def edit_config(params: dict, backbone: str = "relu_field", checkpoint_every: int = 0) -> "EditConfig":
    """The edit of a job whose G_i is a ``backbone`` grid (its ``kind``): SPEC §2, or §5 for scenes (module doc)."""
    from voxe_core.edit import EditConfig
    from voxe_core.schedule import TimestepSchedule

    floor = _given(params, "timestep_schedule", TIMESTEP_SCHEDULES[0])
    if floor not in TIMESTEP_SCHEDULES:
        raise ValueError(f"unknown timestep_schedule {floor!r}; use {' or '.join(TIMESTEP_SCHEDULES)}")
    special = EDIT_SCHEDULES.get(backbone)
    timing = {} if special is None else {"i_start": special.i_start, "every": special.every}
    schedule = TimestepSchedule.authors(**timing) if floor == "authors" else TimestepSchedule(**timing)
    iterations = _given(params, "iterations", paper.EDIT_ITERATIONS)
    if special is not None and iterations == paper.EDIT_ITERATIONS:
        iterations = special.iterations
    return EditConfig(
        iterations=iterations,
        render_size=_given(params, "render_size", paper.RENDER_SIZE),
        guidance_scale=_given(params, "guidance_scale", paper.DEFAULT_GUIDANCE_SCALE),
        lr=_given(params, "lr", paper.EDIT_LR),
        regulariser=_given(params, "regulariser", paper.DEFAULT_REGULARISER),
        regulariser_weight=_given(params, "regulariser_weight", paper.DEFAULT_REGULARISER_WEIGHT),
        schedule=schedule,
        view_words=_given(params, "view_words", VIEW_WORDS),
        batch_size=_given(params, "batch_size", BATCH_SIZE),
        autocast_dtype=params.get("autocast"),
        seed=_given(params, "seed", SEED),
        preview_every=_given(params, "preview_every", PREVIEW_EVERY),
        checkpoint_every=checkpoint_every,
    )


def refine_config(params: dict, attention_model: str) -> "RefineConfig":
    """The refinement of a local edit (the job parameters' ``refine``; its render size defaults to the edit's)."""
    from voxe_core.refine.config import PAPER_TEXT_FIT, RefineConfig

    refine = params.get("refine") or {}
    views, render_size, iterations = _refine_work(params)
    lift_start = _given(refine, "lift_start", LIFT_START)
    # The paper's start at 0 takes the paper's fit (fixed views, every pixel): the code's L1 counts only pixels
    # that render positive, and nothing does from 0.
    paper_fit = lift_start == "constant"
    return RefineConfig(
        iterations=iterations,
        lift_start=lift_start,
        fit_views=PAPER_TEXT_FIT["fit_views"] if paper_fit else RefineConfig.fit_views,
        fit_pixels=PAPER_TEXT_FIT["fit_pixels"] if paper_fit else RefineConfig.fit_pixels,
        view_word_prompt=_given(params, "view_words", VIEW_WORDS),  # the attention prompt says what the edit's said
        smoothing_sigma=_given(refine, "smoothing_sigma", paper.SERVICE_SMOOTHING_SIGMA),
        lr=_given(refine, "lr", paper.REFINE_LR),
        tv_weight=_given(refine, "tv_weight", paper.REFINE_TV_WEIGHT),
        render_size=render_size,
        views=views,
        rays_per_step=_given(refine, "rays_per_step", paper.REFINE_RAYS_PER_STEP),
        edit_seeds=_given(refine, "edit_seeds", paper.EDIT_SEEDS),
        object_seeds=_given(refine, "object_seeds", paper.SERVICE_OBJECT_SEEDS),
        sigma=_given(refine, "sigma", paper.CUT_SIGMA),
        smoothness=_given(refine, "smoothness", paper.CUT_SMOOTHNESS),
        seed=_given(params, "seed", SEED),
        attention_model=attention_model,
    )


def _refine_work(params: dict) -> tuple[int, int, int]:
    """(views, render size, fitting steps) of the job parameters' refinement (its render size defaults to the
    edit's)."""
    refine = params.get("refine") or {}
    return (_given(refine, "views", paper.REFINE_VIEWS),
            refine.get("render_size") or _given(params, "render_size", paper.RENDER_SIZE),
            _given(refine, "iterations", paper.SERVICE_REFINE_ITERATIONS))


def refine_phase_units(params: dict) -> dict[str, int]:
    """The units each phase of a local edit's refinement counts on its one progress scale
    (``voxe_core.refine.pipeline.refine``): a pass per view, the back-projection's chunks, the fitting steps and the
    cut, as :func:`refine_config` reads the job parameters; torch-free, so the API weighs the stage by them.

    Examples:
        >>> refine_phase_units({})  # the service's default: 32 views of 266², no fitting steps
        {'attention_maps': 32, 'backprojection': 18, 'attention_grids': 0, 'graph_cut': 1}
    """
    views, render_size, iterations = _refine_work(params)
    chunks = backprojection_chunks(views, render_size, render_size, paper.REFINE_BACKPROJECTION_STRIDE,
                                   paper.RENDER_CHUNK_RAYS)
    return {"attention_maps": views, "backprojection": chunks, "attention_grids": iterations, "graph_cut": 1}


def backprojection_chunks(n_views: int, height: int, width: int, stride: int, chunk_rays: int) -> int:
    """The chunks of ``chunk_rays`` the refinement's back-projection runs at most over ``n_views`` maps of
    ``height`` x ``width`` read every ``stride``-th pixel row and column (every such pixel's ray meeting the
    object): its share of the stage's progress scale, as the attention passes count one a view.

    Examples:
        >>> backprojection_chunks(32, 266, 266, 2, 32768)  # the service's default: 32 x 133² rays
        18
    """
    rays = n_views * math.ceil(height / stride) * math.ceil(width / stride)
    return max(1, math.ceil(rays / chunk_rays))


def export_config(params: dict) -> ExportConfig:
    """The job parameters' ``export`` (None values take the defaults)."""
    export = params.get("export") or {}
    return ExportConfig(**{k: v for k, v in export.items() if v is not None})


STAGE_CHECKS = {"edit": lambda params: [edit_config(params, kind) for kind in BACKBONE_KINDS],
                "refine": lambda params: refine_config(params, paper.ATTENTION_MODEL_ID),
                "export": lambda params: check_video_fps(export_config(params).fps)}
"""Each stage's config built from the job parameters as the worker will: the edit's on either backbone G_i may be,
the refinement's, the export's videos."""


def check_stage(stage: str, params: dict) -> None:
    """ValueError, naming ``stage`` (a key of ``STAGE_CHECKS``), for job parameters its config refuses. The service
    calls it on submission, each stage's at its own section of the parameters, so a rule of a config that the job
    parameters' bounds do not state is a 422 there, not a job failing after its fit."""
    try:
        STAGE_CHECKS[stage](params)
    except ValueError as exc:
        raise ValueError(f"{stage}: {exc}") from None


def _given(params: dict, key: str, default):
    """``params[key]`` unless it is missing or None."""
    value = params.get(key)
    return default if value is None else value
