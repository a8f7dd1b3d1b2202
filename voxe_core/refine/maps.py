"""Step 1: per-view 2D edit and object maps from the diffusion model's cross-attention (SPEC §3).

Renders of G_e from random upper-hemisphere poses; per token the model's
cross-attention probabilities at t = 200; the edit map is the mean over the
edit words' tokens, the object map the max over the prompt's other content
tokens; each smoothed on the attention lattice, upsampled to the render size
and min-max normalised to [0, 1].
"""

from __future__ import annotations

import math
from typing import Sequence

import torch
import torch.nn.functional as F

from voxe_core.cameras import Cameras, random_hemisphere_poses
from voxe_core.grid import VoxelGrid
from voxe_core.progress import Callbacks, Progress
from voxe_core.refine.config import RefineConfig
from voxe_core.render import RenderConfig, render_image


def gaussian_blur2d(maps: torch.Tensor, sigma: float) -> torch.Tensor:
    """Separable Gaussian blur of (..., H, W) maps, std ``sigma`` pixels, reflect padding, on their device."""
    if sigma <= 0:
        return maps
    radius = max(1, int(math.ceil(3.0 * sigma)))
    x = torch.arange(-radius, radius + 1, device=maps.device, dtype=torch.float32)
    kernel = torch.exp(-0.5 * (x / sigma) ** 2)
    kernel = (kernel / kernel.sum()).to(maps.dtype)
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


def attention_cameras(config: RefineConfig, generator: torch.Generator | None = None,
                      centre: torch.Tensor | None = None) -> Cameras:
    """``config.views`` random upper-hemisphere cameras (SPEC §0) of ``render_size`` pixels, looking at ``centre``
    (the grid's ``orbit_centre()``; None: the origin)."""
    generator = generator or torch.Generator().manual_seed(config.seed)
    c2w, _, _ = random_hemisphere_poses(config.views, generator, centre=centre)
    return Cameras.from_fov(c2w, config.fov_x, config.render_size, config.render_size)


def token_groups(guidance, prompt: str, edit_words: Sequence[str]) -> tuple[list[int], list[int]]:
    """(edit token positions, other content token positions) of ``prompt``.

    Edit positions: every sub-token of every occurrence of each edit word or
    phrase (``guidance.token_spans``). Object positions: the prompt's content
    tokens (no start / end / padding) minus the edit positions.
    """
    if isinstance(edit_words, str):
        edit_words = [edit_words]
    edit_words = [w.strip() for w in edit_words if w and w.strip()]
    if not edit_words:
        raise ValueError("no edit words given: name the word(s) of the prompt that describe the edit")
    edit = guidance.token_spans(prompt, edit_words)
    content = guidance.content_token_indices(prompt)
    others = [i for i in content if i not in set(edit)]
    if not others:
        raise ValueError(f"the prompt {prompt!r} has no words besides the edit words {edit_words}: nothing names the object")
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
def postprocess_maps(maps: torch.Tensor, size: tuple[int, int], sigma: float) -> torch.Tensor:
    """Smooth (in map pixels) -> bilinear upsample to ``size`` -> min-max normalise; (N, h, w) -> (N, H, W)."""
    smoothed = gaussian_blur2d(maps.float(), sigma)
    up = F.interpolate(smoothed[:, None], size=size, mode="bilinear", align_corners=False)[:, 0]
    return normalize_maps(up)


@torch.no_grad()
def attention_maps_2d(
    guidance,
    grid: VoxelGrid,
    cameras: Cameras,
    prompt: str,
    edit_words: Sequence[str],
    config: RefineConfig = RefineConfig(),
    callbacks: Callbacks = Callbacks(),
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-view edit and object maps ``(N, H, W)`` in [0, 1] for renders of ``grid`` (see the module docstring).

    ``prompt`` is used as given (``refine`` adds the "a render of" prefix the
    edit stage used). Renders are composited on white, as the edit stage's.
    """
    edit_tokens, object_tokens = token_groups(guidance, prompt, edit_words)
    device = grid.bbox_min.device
    occupancy = grid.occupancy(RenderConfig().sigma_threshold)
    generator = torch.Generator().manual_seed(config.seed)
    size = (cameras.height, cameras.width)
    edit_maps = torch.empty(len(cameras), *size, device=device)
    object_maps = torch.empty_like(edit_maps)
    for i in range(len(cameras)):
        callbacks.check_cancel("attention_maps")
        image = render_image(grid, cameras, i, RenderConfig(), occupancy).rgb[..., :3]
        maps = guidance.cross_attention_maps(
            image.permute(2, 0, 1)[None], prompt, timestep=config.timestep,
            resolution_filter=config.resolution_filter, generator=generator,
        )
        edit, obj = combine_token_maps(maps, edit_tokens, object_tokens, config.edit_token_reduce)
        both = postprocess_maps(torch.stack([edit, obj]), size, config.smoothing_sigma)
        edit_maps[i], object_maps[i] = both[0].to(device), both[1].to(device)
        callbacks.progress(Progress("attention_maps", i + 1, len(cameras), info={"stage": "attention maps"}))
    return edit_maps, object_maps
