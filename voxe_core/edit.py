"""Stage 2: text-guided editing of a voxel grid with Score Distillation Sampling (paper §3.2, SPEC §2).

The edited grid G_e starts as a copy of the initial grid G_i and all of its
features are optimised with dense Adam (lr 0.03, betas 0.9/0.999; the volumetric
regulariser touches every voxel, so sparse updates would buy nothing). One
iteration:

1. draw a random upper-hemisphere pose (zenith uniform in [15°, 90°], azimuth
   in [0°, 360°), radius 4.0311, looking at the origin; on a capture, at G_i's
   ``orbit_centre()``, where its object sits);
2. render a ``render_size``² image of G_e from it, with gradient, on white,
   with stratified jitter (the guidance resizes it to its own resolution);
3. build the prompt ``"a render of <text>, <view> view"``, the view word
   chosen from the pose (:func:`voxe_core.guidance.prompts.view_word`; embeddings are
   cached per view word);
4. SDS loss from the guidance with ``t`` from the annealed
   :class:`~voxe_core.schedule.TimestepSchedule`, classifier-free guidance 100;
5. plus ``weight × regulariser`` (default L_reg3D, weight 200: 1 − Pearson
   correlation of the raw densities of G_i (fixed) and G_e over all voxels);
6. backward, Adam step. The learning rate decays ×0.96 every 400 iterations
   after iteration 5000, as the authors' code does.

Determinism and resume. All randomness comes from two seeded generators: a
CPU one for poses, time steps and image-regulariser rays, and one on the
compute device for render jitter, the VAE posterior sample and the SDS noise.
Checkpoints (``kind="edit_checkpoint"``, safetensors + JSON header, no pickle)
hold G_e's features, Adam's moments and step, both generator states, the
iteration, how many steps in a row the SDS gradient was wholly non-finite
(:data:`MAX_NONFINITE_GUIDANCE_STEPS` stops a run across resumes), the
guidance's ``model_id`` (a resume with another model is refused)
and, under an image regulariser, a summary of the input views it compares
with, so a run interrupted after k iterations and resumed from its checkpoint
ends with exactly the grid an uninterrupted run would (on CPU; on CUDA only
as far as the kernels are deterministic: scatter-adds with atomics are not;
resumed on another device type, the device generator is reseeded from where
the run stands, its state meaning nothing there). A cancelled run writes a
checkpoint before it stops (unless G_e is no longer finite: the earlier one stays; one that cannot be written is
said as a warning, the cancel staying a cancel).

Mixed precision. ``autocast_dtype`` ("bf16" / "fp16") runs the guidance (VAE
encoder forward and UNet) under ``torch.autocast``; on CPU only bfloat16 is
used (fp16 asked for is said once, through the callbacks' warning), and a
float16 model is refused there (its GroupNorm fails under it). The
volume renderer and the regulariser always run in float32 (both disable
autocast inside: transmittance products and correlations want fp32).
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import numbers
import time
from dataclasses import dataclass, field
from fractions import Fraction
from pathlib import Path
from typing import Callable

import torch

from voxe_core.cameras import (
    Cameras,
    camera_rays,
    check_angle,
    check_render_size,
    check_fov_x,
    check_views,
    pixel_rays,
    random_hemisphere_poses,
    spherical_poses,
)
from voxe_core.constants import (
    DEFAULT_GUIDANCE_SCALE,
    DEFAULT_REGULARISER,
    DEFAULT_REGULARISER_WEIGHT,
    EDIT_ITERATIONS,
    EDIT_LR,
    FLOAT32_MAX,
    MAX_BATCH_SIZE,
    MAX_IMAGE_REGULARISER_RAYS,
    MAX_RENDER_SIZE,
    MAX_SEED,
    NERF_SYNTHETIC_FOV_X,
    NERF_SYNTHETIC_RADIUS,
    RENDER_SIZE,
)
from voxe_core.devices import PeakMemory, resolve_device, same_device, synchronize
from voxe_core.grid import VoxelGrid
from voxe_core.guidance import Guidance
from voxe_core.guidance.loading import local_path, smoke_test_note
from voxe_core.guidance.prompts import (
    AUTHORS_FRONT_AZIMUTH_DEG,
    RENDER_PREFIX,
    VIEW_WORDS,
    edit_prompt,
    pose_view_word,
)
from voxe_core.losses import (
    CORRELATED_CHANNELS,
    IMAGE_REGULARISERS,
    REGULARISERS,
    Regulariser,
    constant_correlated_channels,
    image_l1,
    image_l2,
    volumetric_regulariser,
)
from voxe_core.progress import Callbacks, Progress, StageCancelled
from voxe_core.reconstruct import check_finite_grid, checkpoint_at_cancel, renders_nothing, same_views, views_summary
from voxe_core.render import RenderConfig, render_image, render_rays
from voxe_core.schedule import TimestepSchedule
from voxe_core.tensorio import (
    FormatError,
    check_flags,
    check_numbers,
    config_recipe,
    is_number,
    load_header,
    load_tensors,
    recipe_changes,
    safetensors_name,
    save_tensors,
)

EDIT_CHECKPOINT_KIND = "edit_checkpoint"
EDIT_CHECKPOINT_VERSION = 1
AUTOCAST_DTYPES = {"bf16": torch.bfloat16, "fp16": torch.float16}


class EditDiverged(ArithmeticError):
    """An edit step's loss was NaN or infinite (G_e took a step it cannot recover from), so were G_e's features where
    it was to be saved or returned (a finite loss whose gradient overflowed in the backward), or the guidance's SDS
    gradient was wholly non-finite for :data:`MAX_NONFINITE_GUIDANCE_STEPS` steps in a row (G_e no longer edits)."""


# The guidance zeroes a non-finite SDS gradient, so a UNet whose float16 output overflows on every step leaves a finite
# loss and an edit that changes nothing. One such step can be a rare overflow at a large t; this many in a row is a
# model that cannot run in this precision, and a job would otherwise "succeed" with the object unchanged.
MAX_NONFINITE_GUIDANCE_STEPS = 10


COUNT_FIELDS = ("iterations", "render_size", "batch_size", "image_regulariser_rays", "lr_decay_start", "lr_decay_every",
                "preview_every", "checkpoint_every", "seed")
"""EditConfig's fields that count (iterations, pixels, rays, poses) or seed: whole numbers."""


NOT_RECIPE_FIELDS = ("iterations", "preview_every", "preview_elevation_deg", "checkpoint_every", "autocast_dtype",
                     "sync_timing")
"""EditConfig's fields a resumed run may change (:meth:`EditConfig.recipe`); every other field is its recipe."""


@dataclass
class EditConfig:
    """Editing hyper-parameters; the defaults are the paper's (SPEC §2)."""

    iterations: int = EDIT_ITERATIONS
    lr: float = EDIT_LR
    betas: tuple[float, float] = (0.9, 0.999)
    # authors' code: lr ×0.96 after every 400th iteration from 5000 on (5200, 5600, ...)
    lr_decay: bool = True
    lr_decay_start: int = 5000
    lr_decay_every: int = 400
    lr_decay_factor: float = 0.96
    render_size: int = RENDER_SIZE  # px; < 266 is fine for CPU runs, the guidance resizes to its resolution
    guidance_scale: float = DEFAULT_GUIDANCE_SCALE
    regulariser: Regulariser = DEFAULT_REGULARISER
    regulariser_weight: float = DEFAULT_REGULARISER_WEIGHT
    image_regulariser_rays: int = 4096  # rays per iteration for image_l1 / image_l2 against the input views
    schedule: TimestepSchedule = field(default_factory=TimestepSchedule)  # paper floor 0.35; .authors() for 0.22
    view_words: bool = True  # append ", front/side/back/overhead view" from the pose
    prompt_prefix: str | None = RENDER_PREFIX  # "a render of"; None for the bare prompt
    front_azimuth_deg: float = AUTHORS_FRONT_AZIMUTH_DEG
    # Training renders: white background, stratified jitter (from the seeded generator).
    # step_ratio 0.6 ≈ the authors' 256 samples per ray across the box at 160³.
    render: RenderConfig = field(default_factory=lambda: RenderConfig(step_ratio=0.6))
    batch_size: int = 1  # poses (renders) per iteration
    preview_every: int = 0  # 0: no previews
    preview_elevation_deg: float = 20.0
    checkpoint_every: int = 0  # 0: only on cancellation and at the end (when a checkpoint path is given)
    seed: int = 0
    radius: float = NERF_SYNTHETIC_RADIUS
    fov_x: float = NERF_SYNTHETIC_FOV_X  # NeRF-synthetic camera_angle_x (rad)
    min_zenith_deg: float = 15.0
    max_zenith_deg: float = 90.0
    autocast_dtype: str | None = None  # None | "bf16" | "fp16" (guidance only; CPU uses bf16)
    # Synchronise CUDA around the timed parts so the ms_* diagnostics are true device times;
    # off by default (each sync stalls the GPU queue), bench/ turns it on.
    sync_timing: bool = False

    def recipe(self) -> dict:
        """The fields a resumed run must share with its checkpoint's (JSON values): those that shape every step's
        arithmetic. Left out: the length (a resume may run on), the render's pass sizes and marcher and the autocast
        (the device's: a job may resume on another worker), previews, checkpoints and timing."""
        return config_recipe(self, NOT_RECIPE_FIELDS)

    def __post_init__(self):
        # NaN, 2.5 or True had passed the range checks below and failed once the edit had begun (a TypeError from
        # range(), torch.rand or a reshape), naming no setting, or run (checkpoint_every 0.5: every step); a seed of
        # 2**64 - 1 had overflowed the device generator's seed + 1 there.
        for name in COUNT_FIELDS:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Integral):
                raise ValueError(f"{name} takes whole numbers, got {value!r}")
        check_numbers(self, ("lr", "lr_decay_factor", "guidance_scale", "regulariser_weight", "front_azimuth_deg",
                             "preview_elevation_deg", "radius", "fov_x", "min_zenith_deg", "max_zenith_deg"))
        if not 0 <= self.seed <= MAX_SEED:
            raise ValueError(f"seed must lie in [0, {MAX_SEED}] (the service's and the CLI's range), got {self.seed}")
        if self.iterations < 0:
            raise ValueError(f"iterations must be >= 0, got {self.iterations}")
        # As "not in range": an infinite lr had run a step and diverged on the next (NaN features, blamed on half
        # precision); a radius <= 0 put every camera below the object, its view words those of the pose above.
        for name in ("lr", "radius"):  # (used in float32: 1e39 overflowed as inf had)
            if not 0 < getattr(self, name) <= FLOAT32_MAX:
                raise ValueError(f"{name} must be positive and finite in float32, got {getattr(self, name)}")
        # As "not in range" (NaN fails every comparison): torch's Adam had refused them only as the edit started,
        # naming no setting ("Invalid beta parameter at index 0"); a pair of strings, None or one number had been a
        # TypeError naming none either ("'<=' not supported between instances of 'int' and 'str'").
        if (not isinstance(self.betas, (tuple, list)) or len(self.betas) != 2
                or not all(is_number(beta) and 0 <= beta < 1 for beta in self.betas)):
            raise ValueError(f"betas must be Adam's two decay rates, each in [0, 1), got {self.betas}")
        for name in ("front_azimuth_deg", "preview_elevation_deg"):
            check_angle(name, getattr(self, name))
        check_render_size(self.render_size)
        if self.regulariser not in REGULARISERS:
            raise ValueError(f"unknown regulariser {self.regulariser!r}; expected one of {', '.join(REGULARISERS)}")
        # As "not in range" (NaN fails every comparison), in the float32 they scale the losses in: 1e39 had been inf
        # there, the edit's loss NaN. A NaN scale had zeroed the SDS gradient (nan_to_num), silently.
        if not 0 <= self.regulariser_weight <= FLOAT32_MAX:
            raise ValueError(f"regulariser_weight must be >= 0 and finite in float32, got {self.regulariser_weight}")
        if not 0 < self.guidance_scale <= FLOAT32_MAX:
            raise ValueError(f"guidance_scale must be positive and finite in float32, got {self.guidance_scale}")
        if self.autocast_dtype not in (None, *AUTOCAST_DTYPES):
            raise ValueError(f"autocast_dtype must be None, 'bf16' or 'fp16', got {self.autocast_dtype!r}")
        # Each by its name and value: they had been refused two or three at once, naming no value.
        for name, least in (("batch_size", 1), ("image_regulariser_rays", 1), ("lr_decay_every", 1),
                            ("lr_decay_start", 0), ("preview_every", 0), ("checkpoint_every", 0)):
            if getattr(self, name) < least:
                off = " (0 turns it off)" if name in ("preview_every", "checkpoint_every") else ""
                raise ValueError(f"{name} must be >= {least}{off}, got {getattr(self, name)}")
        # (the CLI had taken any: --batch-size 1000 renders 1,000 poses a step, each held with its autograd graph until
        # the step's backward, far past a GPU's memory, found only once the model had loaded)
        if self.batch_size > MAX_BATCH_SIZE:
            raise ValueError(f"batch_size must be at most {MAX_BATCH_SIZE} (the service's and the CLI's limit), got "
                             f"{self.batch_size}")
        # (any had been taken: 2**40 failed at the first step, once the model had loaded and rendered, allocating its
        # rays' 8 TiB of pixel indices; 2**63 as a TypeError from torch.randint naming no setting)
        if self.image_regulariser_rays > MAX_IMAGE_REGULARISER_RAYS:
            raise ValueError(f"image_regulariser_rays must be at most {MAX_IMAGE_REGULARISER_RAYS} (as many rays as the "
                             f"largest step's renders: batch_size {MAX_BATCH_SIZE} of {MAX_RENDER_SIZE} px), got "
                             f"{self.image_regulariser_rays}")
        if not 0 < self.lr_decay_factor <= 1:  # (NaN too)
            raise ValueError(f"lr_decay_factor must be in (0, 1], got {self.lr_decay_factor}")
        if not 0.0 <= self.min_zenith_deg <= self.max_zenith_deg <= 180.0:  # (NaN too; had named neither field)
            raise ValueError(f"need 0 <= min_zenith_deg <= max_zenith_deg <= 180 (degrees from straight above), got "
                             f"min_zenith_deg={self.min_zenith_deg}, max_zenith_deg={self.max_zenith_deg}")
        check_fov_x(self.fov_x, self.render_size)
        # A value of another type had been taken and failed mid-edit naming no setting (schedule="authors", the CLI's
        # word for TimestepSchedule.authors(): "'str' object has no attribute 'sample'" after the first preview), or
        # run the opposite of what was asked (view_words="false", a true string).
        for name, kind in (("schedule", TimestepSchedule), ("render", RenderConfig)):
            if not isinstance(getattr(self, name), kind):
                raise ValueError(f"{name} must be a {kind.__name__}, got {getattr(self, name)!r}")
        check_flags(self, ("lr_decay", "view_words", "sync_timing"))
        if self.prompt_prefix is not None and not isinstance(self.prompt_prefix, str):
            raise ValueError(f"prompt_prefix must be a string or None, got {self.prompt_prefix!r}")

    @classmethod
    def authors(cls, **overrides) -> "EditConfig":
        """The authors' code where it differs from the paper: time-step floor 0.22."""
        return cls(**{"schedule": TimestepSchedule.authors(), **overrides})


def learning_rate(config: EditConfig, iteration: int) -> float:
    """Learning rate for 0-based ``iteration``.

    As the authors' loop: after each completed (1-based) step ``s`` with
    ``s % every == 0`` and ``s >= start`` the rate is multiplied by the factor.
    With the defaults: 0.03 up to iteration 5199, 0.03·0.96 from 5200, ·0.96² from 5600, ...
    """
    if not config.lr_decay:
        return config.lr
    first = max(1, -(-config.lr_decay_start // config.lr_decay_every))  # first multiple of every >= start
    decays = max(0, iteration // config.lr_decay_every - first + 1)
    return config.lr * config.lr_decay_factor**decays


def build_prompt(text: str, view: str | None, prefix: str | None = RENDER_PREFIX) -> str:
    """The text given to the guidance: ``"<prefix> <text>[, <view> view]"`` (ValueError when empty)."""
    if prefix == RENDER_PREFIX:
        return edit_prompt(text, view)
    body = " ".join(str(text).split()).rstrip(". ").strip()
    if not body:
        raise ValueError("the edit prompt is empty")
    prefix = " ".join(prefix.split()) if prefix else prefix  # (as the text is: "a photo of " had been doubled)
    if prefix and body.lower() == prefix.lower():  # (it had been doubled, "a photo of a photo of": nothing to edit)
        raise ValueError(f"the edit prompt has only the prefix {prefix!r} and no content")
    if prefix and not body.lower().startswith(prefix.lower() + " "):
        body = f"{prefix} {body}"
    if view is not None:
        if view not in VIEW_WORDS:
            raise ValueError(f"unknown view word {view!r}; expected one of {VIEW_WORDS}")
        body = f"{body}, {view} view"
    return body


CAMERA_CHECK_STEP_DEG = 0.5
"""The lattice of zeniths and azimuths :func:`check_cameras_outside` tries the edit's poses on."""


def check_cameras_outside(grid: VoxelGrid, config: EditConfig, centre: torch.Tensor) -> None:
    """ValueError naming ``config.radius`` when a camera of the edit stands inside ``grid``'s object box (its
    ``foreground_grid()``'s: a scene grid's foreground cube), where every render starts inside the object: a training
    pose (zenith in [min_zenith_deg, max_zenith_deg], any azimuth, about ``centre``; tried every
    :data:`CAMERA_CHECK_STEP_DEG`) or the preview's. A radius of 1 had been taken and rendered from within the grid."""
    box = grid.foreground_grid()
    low, high = (corner.detach().cpu().double() for corner in (box.bbox_min, box.bbox_max))
    steps = max(1, math.ceil((config.max_zenith_deg - config.min_zenith_deg) / CAMERA_CHECK_STEP_DEG))
    zenith, azimuth = torch.meshgrid(
        torch.linspace(config.min_zenith_deg, config.max_zenith_deg, steps + 1, dtype=torch.float64),
        torch.arange(0.0, 360.0, CAMERA_CHECK_STEP_DEG, dtype=torch.float64), indexing="ij")
    zenith = torch.cat([zenith.reshape(-1), torch.tensor([90.0 - config.preview_elevation_deg], dtype=torch.float64)])
    azimuth = torch.cat([azimuth.reshape(-1), torch.tensor([config.front_azimuth_deg], dtype=torch.float64)])
    z, a = torch.deg2rad(zenith), torch.deg2rad(azimuth)
    centre = centre.detach().cpu().double().reshape(3)
    eye = centre + config.radius * torch.stack([z.sin() * a.cos(), z.sin() * a.sin(), z.cos()], -1)
    inside = ((eye > low) & (eye < high)).all(-1).nonzero()
    if len(inside):
        at = int(inside[0])
        farthest = float(torch.maximum((low - centre).abs(), (high - centre).abs()).norm())
        shown = [[round(float(v), 4) for v in corner] for corner in (low, high, centre)]
        raise ValueError(f"radius {config.radius} puts the edit's cameras inside the grid's object box {shown[0]} to "
                         f"{shown[1]} (one at zenith {float(zenith[at]):g}°, azimuth {float(azimuth[at]):g}° about the "
                         f"orbit centre {shown[2]}): its renders would start inside the object; give a radius above "
                         f"{farthest:.4g}, the box's farthest corner from that centre")


def initial_fingerprint(grid: VoxelGrid) -> str:
    """Short SHA-256 of G_i's features: a checkpoint only resumes against the grid it started from (its box and
    header, which decide how those features render, :func:`check_resume` compares with the checkpoint's grid's,
    so a checkpoint of this fingerprint's one form resumes where nothing else differs)."""
    data = grid.features.detach().to("cpu", torch.float32).contiguous().numpy().tobytes()
    return hashlib.sha256(data).hexdigest()[:32]


def _sync(device: torch.device, enabled: bool) -> None:
    if enabled:
        synchronize(device)


def _mark(marks: list[float], device: torch.device, sync: bool) -> None:
    """Append the time now (after the device's queued work when ``sync``): a timer a backward hook can call."""
    _sync(device, sync)
    marks.append(time.perf_counter())


def autocast_dtype(device: torch.device, name: str | None, callbacks: Callbacks) -> torch.dtype | None:
    """The dtype the guidance runs under autocast on ``device`` (None: no autocast), decided once before the first
    step: on the CPU bfloat16, where fp16 asked for is said through ``callbacks.warning`` (a Python warning every
    step had never reached a job's user)."""
    if name is None:
        return None
    dtype = AUTOCAST_DTYPES[name]
    if device.type == "cpu" and dtype != torch.bfloat16:
        callbacks.warning("edit", "fp16 autocast is not used on the CPU; the guidance runs under bfloat16 autocast")
        dtype = torch.bfloat16
    return dtype


BF16_AUTOCAST = 'run it under bf16 autocast (a job\'s autocast "bf16", voxe edit --autocast bf16)'
"""What a guidance overflowing float16 is told to do (bfloat16 has float32's range; float32 itself is no choice on
CUDA, where the guidance loads in float16)."""


def half_precision(autocast: torch.dtype | None, weights: torch.dtype) -> str | None:
    """How the guidance runs in float16 (``autocast``: :func:`autocast_dtype`'s, else the model's ``weights``: a CUDA
    model's, from_pretrained's default there), which overflows past 65,504; None where it does not."""
    if (autocast or weights) != torch.float16:
        return None
    return "under fp16 autocast" if autocast is not None else "in float16, its weights' dtype"


def overflow_advice(autocast: torch.dtype | None, weights: torch.dtype) -> str:
    """What an edit whose step overflowed is told to try, by the precision its guidance runs in
    (:func:`half_precision`). "try autocast off" had been said to every run: to one with autocast off, whose float16
    weights run in float16 all the same, and to a float32 one on the CPU, where no half precision ran."""
    runs = half_precision(autocast, weights)
    if not runs:
        return "try a lower lr"
    return f"float16 overflowing? the guidance runs {runs}: {BF16_AUTOCAST}, or try a lower lr"


def unet_overflow_cause(autocast: torch.dtype | None, weights: torch.dtype) -> str:
    """What is said of a guidance whose SDS gradient had infinite or NaN entries (zeroed), by the precision it runs in
    (:func:`half_precision`): a float16 UNet overflowing, told what to do; in bfloat16 or float32, whose range a sound
    model stays within, not that. Every run had been told of "a float16 (fp16) UNet overflowing; run the guidance in
    float32 or bfloat16": a float32 one too, and a CUDA one, whose guidance loads in float16, not how."""
    runs = half_precision(autocast, weights)
    if runs:
        return f"a float16 UNet overflowing? the guidance runs {runs}: {BF16_AUTOCAST}"
    dtype = str(autocast or weights).removeprefix("torch.")
    return f"no float16 overflow: the guidance runs in {dtype}; its model damaged?"


def _make_adam(param: torch.nn.Parameter, config: EditConfig) -> torch.optim.Adam:
    try:
        return torch.optim.Adam([param], lr=config.lr, betas=tuple(config.betas), fused=True)
    except (RuntimeError, TypeError):  # fused kernels missing for this device / dtype
        return torch.optim.Adam([param], lr=config.lr, betas=tuple(config.betas))


def save_edit_checkpoint(
    path, grid: VoxelGrid, optimizer: torch.optim.Adam, generators: dict[str, torch.Generator],
    iteration: int, meta: dict, views: torch.Tensor | None = None,
) -> None:
    """G_e features, Adam moments and step, generator states, the iteration and, for an image regulariser, the
    :func:`~voxe_core.reconstruct.views_summary` of the input views it compares with (tensorio, no pickle)."""
    param = grid.flat_features
    state = optimizer.state.get(param, {})
    step = state.get("step", 0)
    tensors = {  # before the first step Adam holds no moments: two zero tensors (safetensors refuses shared memory)
        **grid.state_tensors(),
        "adam_exp_avg": state["exp_avg"] if "exp_avg" in state else torch.zeros_like(param),
        "adam_exp_avg_sq": state["exp_avg_sq"] if "exp_avg_sq" in state else torch.zeros_like(param),
        "adam_step": torch.as_tensor(step, dtype=torch.float64).reshape(1).cpu(),
        **{f"rng_{name}": gen.get_state() for name, gen in generators.items()},
        **({} if views is None else {"views": views}),
    }
    save_tensors(path, tensors, kind=EDIT_CHECKPOINT_KIND, version=EDIT_CHECKPOINT_VERSION,
                 meta={**grid.header(), **meta, "iteration": int(iteration)})


def load_edit_checkpoint(path) -> tuple[dict[str, torch.Tensor], dict]:
    return load_tensors(path, kind=EDIT_CHECKPOINT_KIND, max_version=EDIT_CHECKPOINT_VERSION)


def _same_model(recorded, current: str) -> bool:
    """Whether a checkpoint recording the model ``recorded`` resumes under the guidance ``model_id`` ``current``: the
    same name, or ``current``'s hub id without its ``@revision`` (a checkpoint older than the revision in the name)."""
    hub_id, at, _ = current.partition("@")  # a hub id holds no "@"
    return recorded == current or (bool(at) and recorded == hub_id and local_path(hub_id) is None)


def check_resume(resume_from, initial_grid: VoxelGrid, prompt: str, config: EditConfig, model: str,
                 input_views: tuple[torch.Tensor, Cameras] | None = None) -> dict:
    """The header of the edit checkpoint ``resume_from``, or a FormatError (ValueError: one past
    ``config.iterations``) for one this run cannot go on from: another grid shape, prompt, initial grid, model
    (``model``: the guidance's ``model_id``, the name asked for), recipe or, under an image regulariser, other
    ``input_views``. Reads the header and the views' summary alone (and hashes G_i), so a caller refuses a
    mismatched resume before it loads the guidance: the CLI had loaded the model first, a slow load and, where it
    was missing, an error about the model instead of the checkpoint's."""
    meta = load_header(resume_from, EDIT_CHECKPOINT_KIND, EDIT_CHECKPOINT_VERSION)
    recorded = meta.get("resolution")  # (G_e's grid.header(); its features' shape is checked as they are read)
    if recorded is not None and recorded != list(initial_grid.resolution):  # (a damaged header's too: no list)
        raise FormatError(f"{resume_from}: checkpoint grid is "
                          f"{tuple(recorded) if isinstance(recorded, list) else recorded!r}, the initial grid "
                          f"{initial_grid.resolution}")
    if meta.get("prompt") != str(prompt):
        raise FormatError(f"{resume_from}: checkpoint was made for the prompt {meta.get('prompt')!r}, not {prompt!r}")
    if meta.get("initial_sha256") != initial_fingerprint(initial_grid):
        raise FormatError(f"{resume_from}: checkpoint was made from a different initial grid")
    if differs := _renders_otherwise(resume_from, meta, initial_grid):
        raise FormatError(f"{resume_from}: checkpoint was made from an initial grid of the same features that renders "
                          f"otherwise: its {', its '.join(differs)}; resume against the grid it was made from, or "
                          "start afresh")
    # The guidance's model_id, its name as asked for (a hub id, a folder as given, the worker's "tiny"): the same
    # on every machine. An older worker's checkpoint, which recorded the folder "tiny" resolved to there, is
    # refused too (the worker starts such a stage over): that folder is no model a run here is asked for.
    if not _same_model(meta.get("model"), str(model)):
        raise FormatError(f"{resume_from}: checkpoint was made with the model {meta.get('model')!r}, not "
                          f"{str(model)!r}; resume with that model, or start afresh")
    if changed := recipe_changes(resume_from, meta, config):
        raise FormatError(f"{resume_from}: checkpoint was made with another recipe: {', '.join(changed)}; "
                          "resume with its settings, or start afresh")
    start = meta.get("iteration")
    if isinstance(start, bool) or not isinstance(start, int) or start < 0:
        raise FormatError(f"{resume_from}: damaged checkpoint: its iteration is {start!r}, not a count of steps")
    if start > config.iterations:  # it would have returned the checkpoint's later grid as the one asked for
        raise ValueError(f"{resume_from}: checkpoint is at iteration {start}, past the {config.iterations} "
                         f"iterations asked for; ask for at least {start}")
    if config.regulariser in IMAGE_REGULARISERS and input_views is not None:
        images, cameras = torch.as_tensor(input_views[0]), input_views[1]
        check_views(images, cameras, "input view images")
        recorded = _recorded(resume_from, "views")["views"]  # (none in a checkpoint older than the record: resumes)
        if recorded is not None and not same_views(recorded, views_summary(images, cameras)):
            raise FormatError(f"{resume_from}: checkpoint was made against other input views (images or cameras) "
                              f"for its {config.regulariser} regulariser; resume with the views it was made from, or "
                              "start afresh")
    return meta


def _recorded(path, *names: str) -> dict[str, torch.Tensor | None]:
    """The tensors ``names`` an edit checkpoint holds (None: not held), read alone: the
    :func:`~voxe_core.reconstruct.views_summary` ``views``, G_e's box."""
    from safetensors import SafetensorError, safe_open

    try:
        with safetensors_name(path) as name, safe_open(name, framework="pt") as handle:
            return {held: handle.get_tensor(held) if held in handle.keys() else None for held in names}
    except (SafetensorError, OSError, ValueError) as exc:
        raise FormatError(f"{path}: not a readable safetensors file ({exc})") from exc


def _renders_otherwise(path, meta: dict, initial_grid: VoxelGrid) -> list[str]:
    """What of ``initial_grid`` beside its features (which :func:`initial_fingerprint` hashes) differs from the G_i the
    edit checkpoint at ``path`` (header ``meta``) started from, each as ``"<what> <G_i's> (the checkpoint's <its>)"``:
    its box and its header's (activation, density scale, kind, a scene grid's extent, samples and frame); G_e keeps
    G_i's, so the checkpoint's own grid says them. What it does not record (older) is taken as G_i's."""
    differs = []
    box = _recorded(path, "bbox_min", "bbox_max")
    if all(corner is not None for corner in box.values()):
        ours = [corner.detach().float().cpu().tolist() for corner in (initial_grid.bbox_min, initial_grid.bbox_max)]
        theirs = [corner.float().tolist() for corner in box.values()]
        if ours != theirs:
            differs.append(f"box {ours[0]} to {ours[1]} (the checkpoint's {theirs[0]} to {theirs[1]})")
    for name, value in initial_grid.header().items():
        if name != "resolution" and meta.get(name, value) != value:  # (the resolution: check_resume's own message)
            differs.append(f"{name} {value!r} (the checkpoint's {meta[name]!r})")
    return differs


def _check_views(input_views, device):
    images, cameras = input_views
    images = torch.as_tensor(images)
    check_views(images, cameras, "input view images")
    return images.reshape(-1, 3).to(device, torch.float32), cameras.to(device), images.shape[1], images.shape[2]


def _checkpoint_holds(checkpoint_path, resume_from, start: int) -> int | None:
    """The iteration of this run the file at ``checkpoint_path`` stands for, before the run writes it: ``start`` when
    the run resumed from that file; 0 (nothing to save before a first step) when a fresh run finds no file there;
    else None, the file being another run's, which a run ending or cancelled before its first write had left there."""
    if checkpoint_path is None:
        return None
    if resume_from is not None:
        return start if Path(resume_from).resolve() == Path(checkpoint_path).resolve() else None
    return None if Path(checkpoint_path).exists() else 0


def _check_tensors(path, tensors: dict[str, torch.Tensor], features: tuple[int, ...], flat: tuple[int, ...]) -> None:
    """FormatError naming the tensor an edit checkpoint whose header is intact lacks or holds in another shape than
    G_e's ``features`` / ``flat`` features: one removed or of the wrong shape had raised a KeyError or RuntimeError
    (at the load, or at the first step's Adam), failing the job where the worker starts the stage over from a
    FormatError, as it does from an unreadable checkpoint."""
    shapes = {"features": features, "adam_exp_avg": flat, "adam_exp_avg_sq": flat, "adam_step": (1,),
              "rng_host": None, "rng_device": None}  # (a generator's state: its size is the generator's to judge)
    for name, shape in shapes.items():
        if name not in tensors or (shape is not None and tuple(tensors[name].shape) != shape):
            found = f"shape {tuple(tensors[name].shape)}" if name in tensors else "nothing"
            wanted = "a generator state" if shape is None else f"shape {shape}"
            raise FormatError(f"{path}: damaged checkpoint: its {name} holds {found}, not {wanted}")


def _listed(words: list[str]) -> str:
    """``a``, ``a and b``, ``a, b and c``."""
    return " and ".join(filter(None, [", ".join(words[:-1]), words[-1]]))


def regulariser_off(initial_grid: VoxelGrid, config: EditConfig) -> str | None:
    """What a constant channel of G_i switches off of the edit's correlation regulariser, said for its user; None
    where nothing is (or the weight is 0: off as asked).

    Such a channel's term is a constant 1 with no gradient (:func:`~voxe_core.losses.constant_correlated_channels`):
    the edit runs on unregularised there, and its ``reg`` of 1.0 throughout had read as a very poor correlation. It
    is said, not refused: an edit without L_reg3D is one of the paper's ablations (SPEC §2), and a one-coloured grid
    under reg3d_plus keeps its density term.
    """
    if config.regulariser_weight == 0:
        return None
    constant = constant_correlated_channels(config.regulariser, initial_grid.features)
    if not constant:
        return None
    colours = [name for name in constant if name != "density"]
    parts = ["density"] if "density" in constant else []
    if colours:
        parts.append(f"{'its ' if parts else ''}{_listed(colours)} colour channel{'s' if len(colours) > 1 else ''}")
    what = _listed(parts)
    are, them, terms = ("is", "it", "term") if len(constant) == 1 else ("are", "them", "terms")
    said = (f"the reconstruction's {what} {are} constant: the 3D regulariser ({config.regulariser}) has nothing to "
            "correlate")
    correlated = CORRELATED_CHANNELS[config.regulariser]
    if len(constant) < len(correlated):  # (reg3d_plus: its reg is the density term + the mean of the colour terms)
        added = ("density" in constant) + Fraction(len(colours), len(correlated) - 1)
        return (f"{said} on {them}: its {terms} for {them} {are} off, adding a constant {added} to its reg with no "
                "gradient (its reg: the density term plus the mean of the red, green and blue terms)")
    return (f"{said} and is off; the edit runs unregularised, its reg a constant {2.0 if colours else 1.0} "
            "(an empty or unfitted reconstruction?)")


def edit(
    initial_grid: VoxelGrid,
    prompt: str,
    guidance: Guidance,
    config: EditConfig = EditConfig(),
    callbacks: Callbacks = Callbacks(),
    checkpoint_path: str | Path | None = None,
    resume_from: str | Path | None = None,
    input_views: tuple[torch.Tensor, Cameras] | None = None,
    on_preview: Callable[[int, torch.Tensor], None] | None = None,
    device: torch.device | str | None = None,
) -> VoxelGrid:
    """Optimise G_e (a copy of ``initial_grid``) towards ``prompt`` under ``guidance``; returns G_e.

    ``input_views`` ``(images (N, H, W, 3) RGB in [0, 1] on white, cameras)`` are needed by the
    image-space regularisers, and refused under the others (which would ignore them). ``on_preview(iteration, image (H, W, 3) CPU)``
    receives a render from a fixed front pose at iteration 0 (fresh runs),
    every ``preview_every`` iterations and at the end; previews draw no random
    numbers, so they never change the result. ``callbacks`` gets a
    ``Progress("edit", done, total, losses, info)`` per iteration (a run that takes no step, of 0 iterations or resumed
    at its last, one with no losses, at ``total`` of ``total``): losses
    ``sds`` (the SDS surrogate; its value means nothing, its gradient is SDS),
    ``reg`` (unweighted regulariser) and ``total`` (sds + weight·reg); info
    ``t``, ``t_min``, ``t_max``, ``lr``, ``view``, ``elevation``, ``azimuth``,
    ``sds_grad_norm`` and per-part milliseconds ``ms_render``, ``ms_vae``
    (VAE encoder forward), ``ms_unet`` (UNet incl. CFG), ``ms_backward``
    (split at the moment the gradient reaches the renders: ``ms_backward_guidance``,
    the VAE encoder's and the resize's backward and, as autograd runs the graph
    built last first, the regulariser's; then ``ms_backward_render``, the renders'),
    ``ms_optimizer``, ``ms_step``, and ``sds_nonfinite_fraction`` (the share of the
    SDS gradient's entries the guidance found infinite or NaN and zeroed). Cancellation is checked before each
    iteration (``StageCancelled``; a checkpoint is written first when
    ``checkpoint_path`` is set and G_e is finite, else the earlier one stays). Info also carries ``peak_memory_gb`` /
    ``peak_memory_kind`` (:class:`voxe_core.devices.PeakMemory`). Before the first step, ``callbacks.warning`` says
    what of the regulariser a constant channel of G_i switches off (:func:`regulariser_off`; once across resumes
    too, as the zeroed SDS gradient below), and that fp16 autocast
    runs as bfloat16 on the CPU (:func:`autocast_dtype`).

    Everything runs on ``device`` (None: ``guidance.device`` when the guidance
    has one, else the initial grid's); G_i, G_e and the input views move there
    once, and the returned grid lives there. A ``device`` other than the
    guidance's is refused at once (every step would copy renders across), as is an initial grid none of whose density
    the renders sample (:func:`~voxe_core.reconstruct.renders_nothing`: the edit would change nothing), and a
    ``config.radius`` that puts a camera inside its object box (:func:`check_cameras_outside`). A step whose
    loss is not finite raises
    :class:`EditDiverged` before its progress is reported or a checkpoint written (its NaN or infinite gradient
    has reached G_e, which no later step recovers); so does a G_e holding an infinite or NaN feature where a
    checkpoint is to be written, a preview rendered or the grid returned (a finite loss whose gradient overflowed);
    and a guidance whose SDS gradient was wholly non-finite
    (``nonfinite_fraction`` 1) for :data:`MAX_NONFINITE_GUIDANCE_STEPS` steps in a row, the last one's progress not
    reported (a float16 UNet overflowing: G_e would take no more SDS steps). The first step whose SDS gradient had
    any entry zeroed is said once (across resumes too), through ``callbacks.warning``: a partly overflowing UNet (a
    share of the gradient lost on every step) had been said only in the progress info, which neither a job nor the CLI
    shows.
    """
    if not str(prompt).strip():
        raise ValueError("the edit prompt is empty")
    build_prompt(prompt, None, config.prompt_prefix)  # validate before any work
    image_reg = config.regulariser in IMAGE_REGULARISERS
    if image_reg and input_views is None:
        raise ValueError(
            f"the {config.regulariser!r} regulariser compares renders with the input views: pass "
            "input_views=(images, cameras), or use a volumetric regulariser such as 'reg3d'"
        )
    if not image_reg and input_views is not None:  # (as voxe edit refuses --data there: they had been ignored)
        raise ValueError(f"input_views are read by the {' / '.join(IMAGE_REGULARISERS)} regularisers only; the "
                         f"{config.regulariser!r} regulariser compares G_e with G_i, not with images: leave them out, "
                         "or choose an image regulariser")
    # Its NaN had made the first step's loss NaN: an EditDiverged blaming half precision or the lr, after a UNet pass.
    check_finite_grid(initial_grid, "its renders and the regulariser")
    centre = initial_grid.orbit_centre()  # G_i's, so a resumed run draws the same poses
    check_cameras_outside(initial_grid, config, centre)

    guidance_device = getattr(guidance, "device", None)
    device = resolve_device(device if device is not None else (guidance_device or initial_grid.flat_features.device))
    if guidance_device is not None and not same_device(guidance_device, device):
        raise ValueError(f"the edit runs on {device} but its guidance model is on {guidance_device}; "
                         "load the guidance on the same device")
    # (torch's "mixed dtype (CPU): expect parameter to have scalar type of Float" from GroupNorm, at the first step)
    if config.autocast_dtype is not None and device.type == "cpu" and guidance.dtype == torch.float16:
        raise ValueError("autocast on the CPU runs under bfloat16, where a float16 model fails (its GroupNorm layers "
                         "get float32 inputs for float16 weights): load the guidance in float32 (from_pretrained's "
                         "default on the CPU) or bfloat16, or leave autocast_dtype None")
    model = str(getattr(guidance, "model_id", ""))
    resumed = None if resume_from is None else check_resume(resume_from, initial_grid, prompt, config, model,
                                                            input_views)
    memory = PeakMemory(device).start()
    sync = config.sync_timing
    volumetric_reg = None if image_reg else volumetric_regulariser(  # G_i's share computed once
        config.regulariser, initial_grid.features.detach().to(device).clone())
    grid = initial_grid.clone_grid().to(device)
    # The density each step's occupancy skips cells below comes of the lattice, activation and scale, never of the
    # features optimised: built once here (a scene grid's, one per cell, had been rebuilt every step).
    skip_density = grid.skip_density(config.render.sigma_threshold) if config.render.skip_empty else None
    # Refused, not said as a constant regulariser is (an ablation that still edits): through a transparent volume the
    # SDS gradient is 0, so the edit had run all its iterations and returned the grid it was given.
    if renders_nothing(grid, config.render, skip_density):
        raise ValueError("the initial grid has no density the edit's renders sample (no positive density anywhere, "
                         "or none above the render's sigma_threshold): every render is the background, with no SDS "
                         "gradient, so the edit would change nothing (an empty reconstruction, or one that fit "
                         "nothing?)")
    param = grid.flat_features
    optimizer = _make_adam(param, config)
    views = _check_views(input_views, device) if image_reg else None
    views_record = (views_summary(torch.as_tensor(input_views[0]), input_views[1])
                    if image_reg and checkpoint_path else None)

    host_gen = torch.Generator().manual_seed(int(config.seed))  # (a numpy seed: "an integer is required")
    device_gen = torch.Generator(device=device).manual_seed(int(config.seed) + 1)
    generators = {"host": host_gen, "device": device_gen}
    fingerprint = (resumed["initial_sha256"] if resumed is not None  # (check_resume found it G_i's)
                   else initial_fingerprint(initial_grid) if checkpoint_path else None)
    run_meta = {"prompt": str(prompt), "seed": int(config.seed), "initial_sha256": fingerprint,
                "regulariser": config.regulariser, "model": model,
                "recipe": config.recipe(), "device": device.type}  # the device generator's
    if (note := smoke_test_note(model)) is not None:  # (as edited.safetensors': the checkpoint had carried no mark)
        run_meta["smoke_test"] = note

    start = 0
    # Consecutive steps whose SDS gradient was wholly non-finite, carried across a resume (in the checkpoint's header):
    # restarted there, a run overflowing on every step that was resumed more often than every 10 steps never stopped.
    nonfinite_steps = 0
    # Whether the first step with zeroed SDS gradient entries was said, carried across a resume as that count: a
    # job resumed past it (a worker restarted) had been told again at its next such step.
    zeroed_said = False
    # Whether what a constant channel of G_i switches off of the regulariser was said (:func:`regulariser_off`),
    # carried the same way: said again at every resume, each redelivery of a job had added a duplicate warning event.
    off_said = False
    if resume_from is not None:
        tensors, meta = load_edit_checkpoint(resume_from)
        if "features" in tensors and tuple(tensors["features"].shape[:3]) != initial_grid.resolution:  # (its header
            # said otherwise, or nothing)
            raise FormatError(f"{resume_from}: checkpoint grid is {tuple(tensors['features'].shape[:3])}, the initial "
                              f"grid {initial_grid.resolution}")
        _check_tensors(resume_from, tensors, tuple(initial_grid.features.shape), tuple(param.shape))
        # One saved before G_e's finiteness was checked (or damaged): its first step had diverged, blamed on half
        # precision, at every resume, where the worker starts a stage over from a checkpoint it cannot go on from.
        # The save's rule, G_e finite, leaves the first moment finite and the second in [0, +inf] (either NaN, or
        # the first infinite, makes the step NaN): +inf, a finite gradient whose square overflowed, Adam goes on from
        # (those vertices stand still), and a resume had refused the run's own checkpoint for it.
        if unresumable := [name for name, ok in (("features", tensors["features"].isfinite().all()),
                                                 ("adam_exp_avg", tensors["adam_exp_avg"].isfinite().all()),
                                                 ("adam_exp_avg_sq", (tensors["adam_exp_avg_sq"] >= 0).all()))
                           if not bool(ok)]:
            raise FormatError(f"{resume_from}: checkpoint holds {', '.join(unresumable)} no run leaves (NaN or "
                              "infinite features or first Adam moments, NaN or negative second moments): saved by a "
                              "run that had diverged, or damaged; start afresh")
        with torch.no_grad():
            param.copy_(tensors["features"].reshape(-1, 4).to(device))
        if int(tensors["adam_step"].item()) > 0:
            groups = optimizer.state_dict()["param_groups"]
            optimizer.load_state_dict({
                "state": {0: {"step": torch.tensor(float(tensors["adam_step"].item())),
                              "exp_avg": tensors["adam_exp_avg"], "exp_avg_sq": tensors["adam_exp_avg_sq"]}},
                "param_groups": groups,
            })
        start = int(meta["iteration"])
        nonfinite_steps = meta.get("nonfinite_steps", 0)  # (a checkpoint older than the field: none counted)
        # at most the steps it ran, and below the count that stops a run (such a run saves no checkpoint)
        most = min(start, MAX_NONFINITE_GUIDANCE_STEPS - 1)
        if isinstance(nonfinite_steps, bool) or not isinstance(nonfinite_steps, int) or not 0 <= nonfinite_steps <= most:
            raise FormatError(f"{resume_from}: damaged checkpoint: its nonfinite_steps is {nonfinite_steps!r}, not a "
                              f"count of steps from 0 to {most} (at iteration {start})")
        zeroed_said = meta.get("zeroed_said", False)  # (a checkpoint older than the field: not said)
        if not isinstance(zeroed_said, bool):
            raise FormatError(f"{resume_from}: damaged checkpoint: its zeroed_said is {zeroed_said!r}, not true or "
                              "false")
        off_said = meta.get("regulariser_off_said", False)  # (a checkpoint older than the field: not said)
        if not isinstance(off_said, bool):
            raise FormatError(f"{resume_from}: damaged checkpoint: its regulariser_off_said is {off_said!r}, not true "
                              "or false")
        state = tensors["rng_device"]
        same_type = meta.get("device") == device.type or ("device" not in meta and  # (older: told by its state's size)
                                                          state.numel() == device_gen.get_state().numel())
        for name, generator in (("rng_host", host_gen), ("rng_device", device_gen)):
            if generator is host_gen or same_type:
                try:
                    generator.set_state(tensors[name])
                except (RuntimeError, TypeError) as exc:  # (a state of another size or dtype)
                    raise FormatError(f"{resume_from}: damaged checkpoint: its {name} is no generator state this run "
                                      f"can take ({exc})") from None
        if not same_type:  # another device type's state (CUDA's 16-byte Philox seed and offset, a CPU's 5,056 bytes)
            # had raised a RuntimeError here, so a job moved to another worker failed for good: reseeded from where
            # the run stands
            device_gen.manual_seed(hash((config.seed + 1, start)) % 2**63)

    def finite() -> bool:
        return bool(param.detach().isfinite().all())

    def check_finite(done: int) -> None:
        """EditDiverged unless G_e is finite: a loss is finite while its gradient overflows (a float16 VAE encoder's
        backward, say), and such a last step, or one just before a checkpoint or preview, had been saved, returned or
        shown NaN."""
        if not finite():
            raise EditDiverged(
                f"the edit diverged by iteration {done}: G_e's features hold infinite or NaN values though every loss "
                f"was finite (a gradient that overflowed in the backward: {advice}); not saved")

    def checkpoint(done: int) -> None:
        check_finite(done)
        save_edit_checkpoint(checkpoint_path, grid, optimizer, generators, done,
                             {**run_meta, "nonfinite_steps": nonfinite_steps, "zeroed_said": zeroed_said,
                              "regulariser_off_said": off_said},
                             views_record)
        callbacks.checkpoint_written(str(checkpoint_path))

    embeddings: dict[str | None, torch.Tensor] = {}

    def embedding(view: str | None) -> torch.Tensor:
        if view not in embeddings:
            embeddings[view] = guidance.encode_prompts([build_prompt(prompt, view, config.prompt_prefix)])
        return embeddings[view]

    for view in VIEW_WORDS if config.view_words else (None,):  # each prompt the loop will use, before its first
        embedding(view)  # step: the guidance refuses one longer than its text encoder reads

    size = config.render_size
    preview_cameras = Cameras.from_fov(
        spherical_poses(torch.tensor([config.preview_elevation_deg]), torch.tensor([config.front_azimuth_deg]),
                        config.radius, centre),
        config.fov_x, size, size,
    ).to(device)

    def preview(done: int) -> None:
        if on_preview is not None and config.preview_every:
            check_finite(done)  # a render of a NaN G_e had been handed on, the edit stopping a step later
            image = render_image(grid, preview_cameras, 0, config.render).rgb[..., :3]
            on_preview(done, image.detach().to("cpu", torch.float32))

    if (off := regulariser_off(initial_grid, config)) is not None and not off_said:  # (where the run starts: after
        off_said = True  # what it refuses)
        callbacks.warning("edit", off)
    guidance_dtype = autocast_dtype(device, config.autocast_dtype, callbacks)
    advice = overflow_advice(guidance_dtype, guidance.dtype)  # (said where a step overflowed)
    cause = unet_overflow_cause(guidance_dtype, guidance.dtype)  # (said where its SDS gradient was not finite)
    T = int(guidance.num_train_timesteps)
    last_checkpoint = _checkpoint_holds(checkpoint_path, resume_from, start)
    if start == 0:
        preview(0)
    done = start
    try:
        for iteration in range(start, config.iterations):
            callbacks.check_cancel("edit")
            lr = learning_rate(config, iteration)
            for group in optimizer.param_groups:
                group["lr"] = lr
            _sync(device, sync)
            t_start = time.perf_counter()

            # ---- random draws from the host generator: poses, time steps, image-regulariser rays
            c2w, elevation, azimuth = random_hemisphere_poses(
                config.batch_size, host_gen, config.radius, config.min_zenith_deg, config.max_zenith_deg, centre
            )
            views_words = [
                pose_view_word(e, a, config.front_azimuth_deg) if config.view_words else None
                for e, a in zip(elevation.tolist(), azimuth.tolist())
            ]
            timesteps = config.schedule.sample(iteration, config.batch_size, T, generator=host_gen)
            text = torch.cat([embedding(v) for v in views_words])

            # ---- render (fp32, with gradient, jitter from the device generator)
            occupancy = grid.occupancy_above(skip_density) if skip_density is not None else None
            cameras = Cameras.from_fov(c2w, config.fov_x, size, size).to(device)
            renders, samples = [], 0
            for b in range(config.batch_size):
                origins, directions = camera_rays(cameras, b)
                out = render_rays(grid, origins, directions, config.render, occupancy, device_gen)
                renders.append(out.rgb.reshape(size, size, 3).permute(2, 0, 1))
                samples += out.samples
            images = torch.stack(renders)
            _sync(device, sync)
            t_render = time.perf_counter()
            reached_renders = []  # when the backward's gradient reaches the renders (renders of empty space have none)
            if images.requires_grad:
                images.register_hook(lambda grad: _mark(reached_renders, device, sync))

            # ---- SDS (optionally under autocast)
            with (contextlib.nullcontext() if guidance_dtype is None else
                  torch.autocast(device_type=device.type, dtype=guidance_dtype)):
                sds, diagnostics = guidance.sds_loss(images, text, timesteps, config.guidance_scale, generator=device_gen)
            _sync(device, sync)
            t_sds = time.perf_counter()

            # ---- regulariser, float32
            if image_reg:
                targets, view_cameras, height, width = views
                pick = torch.randint(0, targets.shape[0], (config.image_regulariser_rays,), generator=host_gen)
                pick = pick.to(device)
                per_view = height * width
                cam_index, pixel = pick // per_view, pick % per_view
                u = (pixel % width).float() + 0.5
                v = (pixel // width).float() + 0.5
                origins, directions = pixel_rays(view_cameras, cam_index, u, v)
                out = render_rays(grid, origins, directions, config.render, occupancy, device_gen)
                compare = image_l1 if config.regulariser == "image_l1" else image_l2
                reg = compare(out.rgb, targets[pick])
            else:
                reg = volumetric_reg(grid.features)
            total = sds.float() + config.regulariser_weight * reg

            optimizer.zero_grad(set_to_none=True)
            _sync(device, sync)
            t_reg = time.perf_counter()
            if total.requires_grad:  # not when nothing was rendered under an image regulariser: no gradient at all
                total.backward()
            _sync(device, sync)
            t_backward = time.perf_counter()
            t_guidance = reached_renders[0] if reached_renders else t_reg  # no gradient into the renders: none spent
            optimizer.step()
            _sync(device, sync)
            t_end = time.perf_counter()
            done = iteration + 1

            # The step's one read: its losses and the guidance's device-side diagnostics together.
            grad_norm = torch.as_tensor(diagnostics.get("grad_norm", math.nan), dtype=torch.float32, device=device)
            nonfinite = torch.as_tensor(diagnostics.get("nonfinite_fraction", 0.0), dtype=torch.float32, device=device)
            # The fused marcher's sample count (a tensor; the packed path's is an int) is read here too, in float64,
            # where it is exact.
            fused = isinstance(samples, torch.Tensor)
            read = [sds.detach(), reg.detach(), total.detach(), grad_norm.reshape(()), nonfinite.reshape(())]
            values = torch.stack([value.double() for value in read + [samples] * fused]).tolist()
            sds_value, reg_value, total_value, grad_norm_value, nonfinite_value = values[:5]
            samples = values[5] if fused else samples
            if not math.isfinite(total_value):
                raise EditDiverged(
                    f"the edit diverged at iteration {done}: its loss is {total_value} (SDS {sds_value}, "
                    f"regulariser {reg_value}); the steps before were finite ({advice})")
            nonfinite_steps = nonfinite_steps + 1 if nonfinite_value >= 1.0 else 0
            if nonfinite_steps >= MAX_NONFINITE_GUIDANCE_STEPS:
                raise EditDiverged(
                    f"the edit diverged at iteration {done}: the guidance's SDS gradient was infinite or NaN in every "
                    f"entry for the last {nonfinite_steps} iterations (zeroed, so the edit stood still): {cause}")
            if nonfinite_value > 0 and not zeroed_said:  # (in the progress info alone, no job or CLI user had seen it)
                zeroed_said = True
                callbacks.warning("edit", f"iteration {done}: {nonfinite_value * 100:.3g}% of the guidance's SDS "
                                          f"gradient entries were infinite or NaN and were zeroed ({cause}); the edit "
                                          f"goes on (it stops after {MAX_NONFINITE_GUIDANCE_STEPS} steps in a row with "
                                          "every entry so), "
                                          "said once (each step's share: its sds_nonfinite_fraction)")
            t_lo, t_hi = config.schedule.bounds(iteration, T)
            callbacks.progress(Progress(
                "edit", done, config.iterations,
                {"sds": sds_value, "reg": reg_value, "total": total_value},
                {
                    "t": timesteps.tolist() if config.batch_size > 1 else int(timesteps[0]),
                    "t_min": t_lo, "t_max": t_hi, "lr": lr,
                    "view": views_words if config.batch_size > 1 else views_words[0],
                    "elevation": elevation.tolist() if config.batch_size > 1 else float(elevation[0]),
                    "azimuth": azimuth.tolist() if config.batch_size > 1 else float(azimuth[0]),
                    "sds_grad_norm": grad_norm_value,
                    "sds_nonfinite_fraction": nonfinite_value,
                    "samples_per_ray": samples / (config.batch_size * size * size),
                    "fused_marcher": fused,  # whether the renders went through voxe_core.fused_render
                    "ms_render": (t_render - t_start) * 1e3,
                    "ms_vae": float(diagnostics.get("vae_encode_ms", math.nan)),
                    "ms_unet": float(diagnostics.get("unet_ms", math.nan)),
                    "ms_sds": (t_sds - t_render) * 1e3,
                    "ms_regulariser": (t_reg - t_sds) * 1e3,
                    "ms_backward": (t_backward - t_reg) * 1e3,
                    "ms_backward_guidance": (t_guidance - t_reg) * 1e3,
                    "ms_backward_render": (t_backward - t_guidance) * 1e3,
                    "ms_optimizer": (t_end - t_backward) * 1e3,
                    "ms_step": (t_end - t_start) * 1e3,
                    **memory.info(),
                },
            ))
            if checkpoint_path is not None and config.checkpoint_every and done % config.checkpoint_every == 0:
                checkpoint(done)
                last_checkpoint = done
            if config.preview_every and done % config.preview_every == 0:
                preview(done)
    except StageCancelled:
        # Saved only where G_e is finite, else the earlier checkpoint stands: a step whose finite loss had left it NaN
        # turned the user's cancel into an EditDiverged here (the job FAILED, not cancelled). A best effort, as a
        # fit's: one the disk or the storage refuses is said, and the cancel stays a cancel.
        if checkpoint_path is not None and done != last_checkpoint and finite():
            checkpoint_at_cancel(callbacks, "edit", lambda: checkpoint(done))
        raise
    check_finite(done)  # before G_e is saved or returned
    if done == start:  # no step taken (0 iterations, or resumed at its last): one report, at total of total; none had
        # left the worker's row at total 0 and the CLI's progress empty
        callbacks.progress(Progress("edit", done, config.iterations, info=memory.info()))
    if checkpoint_path is not None and (done != last_checkpoint or not Path(checkpoint_path).is_file()):
        checkpoint(done)
    if config.preview_every and done % config.preview_every != 0:
        preview(done)
    param.grad = None
    return grid


__all__ = [
    "AUTHORS_FRONT_AZIMUTH_DEG",
    "EDIT_CHECKPOINT_KIND",
    "EDIT_CHECKPOINT_VERSION",
    "EditConfig",
    "EditDiverged",
    "MAX_NONFINITE_GUIDANCE_STEPS",
    "build_prompt",
    "check_cameras_outside",
    "check_resume",
    "edit",
    "initial_fingerprint",
    "learning_rate",
    "load_edit_checkpoint",
    "pose_view_word",
    "save_edit_checkpoint",
]
