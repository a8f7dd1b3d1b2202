"""Pictures of the refinement: raw per-vertex fields (attention, probabilities) and tinted masks over a grid's density.

Each is made one view at a time (``iter_*``), so a caller that writes each view as it comes holds one, not the ring
(the service allows 1,000 views of 1,024²: 12.6 GB of float pixels at once).
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Sequence

import torch

from voxe_core.cameras import Cameras, camera_rays
from voxe_core.export import iter_views
from voxe_core.grid import VoxelGrid
from voxe_core.render import RenderConfig, render_rays


@torch.no_grad()
def iter_feature_views(
    grid: VoxelGrid,
    cameras: Cameras,
    features: torch.Tensor,
    background: Sequence[float] = (0.0,),
    config: RenderConfig = RenderConfig(),
) -> Iterator[torch.Tensor]:
    """Render raw per-vertex ``features`` (X, Y, Z, C) over ``grid``'s density, one view at a time: yields each
    (H, W, C), on the CPU. The occupancy structure is built once for all views."""
    occupancy = grid.occupancy(config.sigma_threshold) if config.skip_empty else None
    cfg = RenderConfig(**{**config.__dict__, "background": tuple(float(b) for b in background)})
    features, cameras = features.to(grid.bbox_min.device).float(), cameras.to(grid.bbox_min.device)
    for i in range(len(cameras)):
        origins, directions = camera_rays(cameras, i)
        parts = [
            render_rays(grid, origins[s : s + cfg.chunk_rays], directions[s : s + cfg.chunk_rays], cfg, occupancy,
                        color_features=features).rgb
            for s in range(0, origins.shape[0], cfg.chunk_rays)
        ]
        yield torch.cat(parts).reshape(cameras.height, cameras.width, -1).cpu()


def render_feature_views(
    grid: VoxelGrid,
    cameras: Cameras,
    features: torch.Tensor,
    background: Sequence[float] = (0.0,),
    config: RenderConfig = RenderConfig(),
) -> torch.Tensor:
    """:func:`iter_feature_views`' views all at once: (N, H, W, C), for callers that need them together."""
    frames = torch.empty(len(cameras), cameras.height, cameras.width, features.shape[-1])
    for i, frame in enumerate(iter_feature_views(grid, cameras, features, background, config)):
        frames[i] = frame
    return frames


def iter_attention_views(grid: VoxelGrid, values: torch.Tensor, cameras: Cameras) -> Iterator[torch.Tensor]:
    """Grey renders (H, W, 3) in [0, 1] of a scalar grid (an attention field or a probability) on black, one view
    at a time. ValueError unless ``values`` is (X, Y, Z) or (X, Y, Z, 1) (more channels had failed in an expand),
    raised by the call itself, not by the first view asked for: a caller that builds several sets of views before
    writing any (the CLI's previews) learns of a bad one before it has written the others."""
    if values.dim() == 3:
        values = values[..., None]
    if values.dim() != 4 or values.shape[-1] != 1:
        raise ValueError(f"expected one scalar per vertex, (X, Y, Z) or (X, Y, Z, 1), got {tuple(values.shape)}")
    return (grey.clamp(0.0, 1.0).expand(*grey.shape[:2], 3).contiguous()
            for grey in iter_feature_views(grid, cameras, values, background=(0.0,)))


def iter_mask_overlays(
    grid: VoxelGrid, mask: torch.Tensor, cameras: Cameras, tint=(1.0, 0.0, 0.0), strength: float = 0.65
) -> Iterator[torch.Tensor]:
    """Renders (H, W, 3) of ``grid`` on white with the masked voxels tinted (red by default), one view at a time."""
    coverages = iter_feature_views(grid, cameras, mask.float()[..., None], background=(0.0,))
    for image, coverage in zip(iter_views(grid, cameras), coverages):
        a = (strength * coverage).clamp(0.0, 1.0)
        yield image * (1.0 - a) + a * torch.tensor(tint, dtype=image.dtype)
