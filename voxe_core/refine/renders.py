"""Pictures of the refinement: raw per-vertex fields (attention, probabilities) and tinted masks over a grid's density."""

from __future__ import annotations

from typing import Sequence

import torch

from voxe_core.cameras import Cameras, camera_rays
from voxe_core.export import render_views
from voxe_core.grid import VoxelGrid
from voxe_core.render import RenderConfig, render_rays


@torch.no_grad()
def render_feature_views(
    grid: VoxelGrid,
    cameras: Cameras,
    features: torch.Tensor,
    background: Sequence[float] = (0.0,),
    config: RenderConfig = RenderConfig(),
) -> torch.Tensor:
    """Render raw per-vertex ``features`` (X, Y, Z, C) over ``grid``'s density: (N, H, W, C)."""
    occupancy = grid.occupancy(config.sigma_threshold) if config.skip_empty else None
    cfg = RenderConfig(**{**config.__dict__, "background": tuple(float(b) for b in background)})
    features, cameras = features.to(grid.bbox_min.device).float(), cameras.to(grid.bbox_min.device)
    frames = torch.empty(len(cameras), cameras.height, cameras.width, features.shape[-1])
    for i in range(len(cameras)):
        origins, directions = camera_rays(cameras, i)
        parts = [
            render_rays(grid, origins[s : s + cfg.chunk_rays], directions[s : s + cfg.chunk_rays], cfg, occupancy,
                        color_features=features).rgb
            for s in range(0, origins.shape[0], cfg.chunk_rays)
        ]
        frames[i] = torch.cat(parts).reshape(cameras.height, cameras.width, -1).cpu()
    return frames


def render_attention(grid: VoxelGrid, values: torch.Tensor, cameras: Cameras) -> torch.Tensor:
    """Grey renders (N, H, W, 3) in [0, 1] of a scalar grid (an attention field or a probability) on black."""
    if values.dim() == 3:
        values = values[..., None]
    grey = render_feature_views(grid, cameras, values, background=(0.0,))
    return grey.clamp(0.0, 1.0).expand(*grey.shape[:3], 3).contiguous()


def render_mask_overlay(
    grid: VoxelGrid, mask: torch.Tensor, cameras: Cameras, tint=(1.0, 0.0, 0.0), strength: float = 0.65
) -> torch.Tensor:
    """Renders (N, H, W, 3) of ``grid`` on white with the masked voxels tinted (red by default)."""
    images = render_views(grid, cameras)
    coverage = render_feature_views(grid, cameras, mask.float()[..., None], background=(0.0,))
    a = (strength * coverage).clamp(0.0, 1.0)
    return images * (1.0 - a) + a * torch.tensor(tint, dtype=images.dtype)
