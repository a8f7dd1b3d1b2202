"""Step 1: per-view 2D edit and object maps from the diffusion model's cross-attention (SPEC §3).

Renders of G_e from random upper-hemisphere poses; per token the model's
cross-attention probabilities at t = 200, the prompt carrying each pose's view
word (``view_word_prompt``); the edit map is the max (or mean) over the edit
words' tokens, the object map the max over the prompt's other tokens (with the
first end-of-text token: ``object_tokens``); each smoothed on the attention
lattice (and again after the bilinear upsampling to the render size) and
kept as raw probabilities, or min-max normalised to [0, 1] (``map_scale``).
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
import torch.nn.functional as F

from voxe_core.cameras import Cameras, random_hemisphere_poses
from voxe_core.devices import full_precision
from voxe_core.grid import VoxelGrid
from voxe_core.guidance.prompts import check_edit_words_name_an_edit, edit_prompt, pose_view_word, without_view_word
from voxe_core.progress import Callbacks, Progress
from voxe_core.refine.config import RefineConfig, SegmentationError
from voxe_core.render import RenderConfig, render_image


def gaussian_kernel1d(sigma: float, radius: int | None = None, device=None) -> torch.Tensor:
    """Normalised 1D Gaussian taps, std ``sigma``, ``2·radius + 1`` of them (None: radius ceil(3σ), at least 1).

    The 2D kernel is its outer product with itself: radius 1 at σ = 0.5 is the authors' 3×3 kernel. The taps are
    computed in float64: a σ below float32's smallest (1e-45) had become 0 there, and its taps NaN (0 / 0), where
    they are the no blur the Gaussian narrows to.

    Examples:
        >>> [round(float(w), 4) for w in gaussian_kernel1d(0.5, radius=1)]
        [0.1065, 0.787, 0.1065]
    """
    radius = max(1, int(math.ceil(3.0 * sigma))) if radius is None else int(radius)
    x = torch.arange(-radius, radius + 1, device=device, dtype=torch.float64)
    kernel = torch.exp(-0.5 * (x / sigma) ** 2)
    return (kernel / kernel.sum()).float()


def gaussian_blur2d(maps: torch.Tensor, sigma: float, radius: int | None = None) -> torch.Tensor:
    """Separable Gaussian blur of (..., H, W) maps, std ``sigma`` pixels (``radius``: see
    :func:`gaussian_kernel1d`), reflect padding, on their device."""
    if sigma <= 0:
        return maps
    kernel = gaussian_kernel1d(sigma, radius, maps.device).to(maps.dtype)
    radius = (kernel.numel() - 1) // 2
    shape = maps.shape
    flat = maps.reshape(-1, 1, *shape[-2:])
    # reflect padding needs pad < size; fall back to replicate on tiny maps
    mode = "reflect" if min(shape[-2:]) > radius else "replicate"
    flat = F.conv2d(F.pad(flat, (radius, radius, 0, 0), mode=mode), kernel.view(1, 1, 1, -1))
    flat = F.conv2d(F.pad(flat, (0, 0, radius, radius), mode=mode), kernel.view(1, 1, -1, 1))
    return flat.reshape(shape)


def normalize_maps(maps: torch.Tensor) -> torch.Tensor:
    """Min-max normalise each (H, W) map of (N, H, W) to [0, 1]; a constant map becomes 0.

    "Constant" is relative to the map's magnitude (span below 1e-5 of it, ~100
    float32 ulps), so the rounding left by blurring and resampling a flat map
    is not stretched into a full-range pattern of noise.
    """
    lo = maps.amin(dim=(-2, -1), keepdim=True)
    hi = maps.amax(dim=(-2, -1), keepdim=True)
    span = hi - lo
    flat = span <= 1e-5 * torch.maximum(lo.abs(), hi.abs()) + 1e-12
    return torch.where(flat, torch.zeros_like(maps), (maps - lo) / span.clamp_min(1e-12))


def attention_cameras(config: RefineConfig, generator: torch.Generator | None = None, n: int | None = None,
                      centre: torch.Tensor | None = None) -> Cameras:
    """``n`` (default ``config.views``) random upper-hemisphere cameras (SPEC §0) of ``render_size`` pixels, looking
    at ``centre`` (the grid's ``orbit_centre()``; None: the origin)."""
    generator = generator or torch.Generator().manual_seed(int(config.seed))
    c2w, _, _ = random_hemisphere_poses(config.views if n is None else n, generator, centre=centre)
    return Cameras.from_fov(c2w, config.fov_x, config.render_size, config.render_size)


def camera_view_words(cameras: Cameras, front_azimuth_deg: float, centre: torch.Tensor | None = None) -> list[str]:
    """The view word ("front", "side", "back", "overhead") of each camera's position around ``centre`` (the point
    the cameras orbit, as the edit's poses do; None: the origin)."""
    eye = cameras.c2w[:, :3, 3].double()
    if centre is not None:
        eye = eye - centre.to(eye)
    elevation = torch.rad2deg(torch.asin((eye[:, 2] / eye.norm(dim=-1).clamp_min(1e-12)).clamp(-1, 1)))
    azimuth = torch.rad2deg(torch.atan2(eye[:, 1], eye[:, 0]))
    return [pose_view_word(e, a, front_azimuth_deg) for e, a in zip(elevation.tolist(), azimuth.tolist())]


def token_groups(
    guidance, prompt: str, edit_words: Sequence[str], object_tokens: str = "content"
) -> tuple[list[int], list[int]]:
    """(edit token positions, object token positions) of ``prompt``.

    Edit positions: every sub-token of every occurrence of each edit word or
    phrase (``guidance.token_spans``). Object positions: the prompt's content
    tokens (no start / end / padding) minus the edit positions, and with
    ``object_tokens="through_end"`` the first end-of-text token too (the
    authors' token range runs one past the last word).
    """
    if isinstance(edit_words, str):
        edit_words = [edit_words]
    edit_words = [w.strip() for w in edit_words if w and w.strip()]
    if not edit_words:
        raise ValueError("no edit words given: name the word(s) of the prompt that describe the edit")
    edit = guidance.token_spans(prompt, edit_words)
    # A word of the text must be left to name the object (a comma or "!" had been its map), and each edit word
    # must hold one (a comma had been the edit's map).
    check_edit_words_name_an_edit(without_view_word(prompt), edit_words)
    content = guidance.content_token_indices(prompt)
    others = [i for i in content if i not in set(edit)]
    if object_tokens == "through_end":
        others.append(content[-1] + 1)  # the first end-of-text token
    return edit, others


@torch.no_grad()
def combine_token_maps(
    maps: torch.Tensor, edit_tokens: Sequence[int], object_tokens: Sequence[int], reduce: str = "mean"
) -> tuple[torch.Tensor, torch.Tensor]:
    """(tokens, h, w) probabilities -> (edit map, object map), each (h, w), before smoothing."""
    edit_stack = maps[list(edit_tokens)]
    edit = edit_stack.mean(0) if reduce == "mean" else edit_stack.amax(0)
    return edit, maps[list(object_tokens)].amax(0)


@torch.no_grad()
def postprocess_maps(maps: torch.Tensor, size: tuple[int, int], config: RefineConfig = RefineConfig()) -> torch.Tensor:
    """Smooth (in map pixels) -> bilinear upsample to ``size`` [-> smooth again] [-> min-max normalise]: (N, h, w) -> (N, H, W).

    ``config``: ``smoothing_sigma``, ``smoothing_kernel``, ``smooth_upsampled`` and ``map_scale``. In float32 whatever
    autocast says (under a caller's bf16 autocast the blurs' conv2d had returned bf16 maps, up to 0.014 off).
    """
    radius = 1 if config.smoothing_kernel == "3x3" else None
    with full_precision(maps):
        smoothed = gaussian_blur2d(maps.float(), config.smoothing_sigma, radius)
        up = F.interpolate(smoothed[:, None], size=size, mode="bilinear", align_corners=False)[:, 0]
        if config.smooth_upsampled:
            up = gaussian_blur2d(up, config.smoothing_sigma, radius)
        return normalize_maps(up) if config.map_scale == "minmax" else up


@torch.no_grad()
def attention_maps_2d(
    guidance,
    grid: VoxelGrid,
    cameras: Cameras,
    prompt: str,
    edit_words: Sequence[str],
    config: RefineConfig = RefineConfig(),
    callbacks: Callbacks = Callbacks(),
    generator: torch.Generator | None = None,
    centre: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-view edit and object maps ``(N, H, W)`` for renders of ``grid`` (see the module docstring).

    ``prompt`` is used as given (``refine`` adds the "a render of" prefix the
    edit stage used), plus ", <view> view" per pose with ``view_word_prompt``.
    Renders are composited on white, as the edit stage's. The diffusion noise
    comes from ``generator`` (default: seeded with ``config.seed``). ``centre`` (3,): the point the cameras
    orbit, around which their view words are read (None: the origin).
    """
    words = camera_view_words(cameras, config.front_azimuth_deg, centre) if config.view_word_prompt \
        else [None] * len(cameras)
    prompts = [edit_prompt(prompt, word) if word else prompt for word in words]
    groups = {text: token_groups(guidance, text, edit_words, config.object_tokens) for text in set(prompts)}
    device = grid.bbox_min.device
    occupancy = grid.occupancy(RenderConfig().sigma_threshold)
    generator = generator or torch.Generator().manual_seed(int(config.seed))
    size = (cameras.height, cameras.width)
    edit_maps = torch.empty(len(cameras), *size, device=device)
    object_maps = torch.empty_like(edit_maps)
    for i in range(len(cameras)):
        callbacks.check_cancel("attention_maps")
        image = render_image(grid, cameras, i, RenderConfig(), occupancy).rgb[..., :3]
        if not bool(torch.isfinite(image).all()):  # (the model's maps of it had been blamed, "a float16 model?")
            raise SegmentationError(f"the render of the edited grid for view {i + 1} of {len(cameras)} is not finite "
                                    "(NaN or infinite): the grid's colour (or density) is where the view sees it (a "
                                    "diverged edit or a corrupted grid?), so the attention model has nothing to read")
        maps = guidance.cross_attention_maps(
            image.permute(2, 0, 1)[None], prompts[i], timestep=config.timestep,
            resolution_filter=config.resolution_filter, generator=generator,
        )
        edit, obj = combine_token_maps(maps, *groups[prompts[i]], config.edit_token_reduce)
        both = torch.stack([edit, obj])
        if not bool(torch.isfinite(both).all()):  # (had been refused only by the cut, as a "diverged fit")
            raise SegmentationError(f"the attention model's maps of view {i + 1} of {len(cameras)} are not finite "
                                    "(NaN or infinite) at the prompt's tokens: its pass overflowed (a float16 "
                                    "model?), so there is no attention to lift")
        both = postprocess_maps(both, size, config)
        edit_maps[i], object_maps[i] = both[0].to(device), both[1].to(device)
        callbacks.progress(Progress("attention_maps", i + 1, len(cameras), info={"stage": "attention maps"}))
    return edit_maps, object_maps
