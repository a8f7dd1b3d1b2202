"""Differentiable volume rendering of a voxel grid (NeRF quadrature), sparse where the scene is empty.

Samples are spaced evenly (``step_ratio`` voxels apart) along each ray's
intersection with the box: the grid's box for the dense path, the tight box of
occupied cells when skipping. The samples of all rays are packed into one
list: when skipping, only those in occupied cells are kept; a density-only
pass without gradient then drops those behind the point where a ray's
transmittance falls below ``early_stop``, and only the rest are evaluated and
composited. Cost therefore follows the occupied space a ray actually sees.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch

from voxe_core.cameras import Cameras, camera_rays
from voxe_core.grid import Occupancy, VoxelGrid, gather_3d

SEGMENT = 16  # lattice samples per skipping segment (see _ray_segments)

# Optical depth per sample beyond which alpha is 1 in float32; clamping there keeps
# cumulative sums finite for saturated densities without changing the image.
MAX_SAMPLE_OPTICAL_DEPTH = 1e4


def optical_depth(sigma: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """sigma * delta per sample, clamped to ``MAX_SAMPLE_OPTICAL_DEPTH``."""
    return (sigma * delta).clamp(max=MAX_SAMPLE_OPTICAL_DEPTH)


@dataclass
class RenderConfig:
    step_ratio: float = 0.5  # sample spacing in units of the smallest voxel edge
    background: tuple[float, ...] = (1.0, 1.0, 1.0)
    skip_empty: bool = True
    sigma_threshold: float = 1e-3  # cells whose density stays below this are skipped
    early_stop: float = 1e-4  # transmittance below which a ray's samples are not evaluated
    samples_per_pass: int = 1 << 20  # lattice samples held at once (rays are grouped to fit)
    chunk_rays: int = 32768  # rays per chunk in whole-image renders


@dataclass
class RenderOutput:
    rgb: torch.Tensor  # (N, C), or (H, W, C) from render_image, composited on the background
    opacity: torch.Tensor  # (N,)
    depth: torch.Tensor  # (N,) expected depth, 0 where the ray hit nothing
    samples: int = 0  # grid evaluations
    candidates: int = 0  # samples generated along the rays before the occupancy test
    extras: dict = field(default_factory=dict)


def ray_box_intersection(
    origins: torch.Tensor, directions: torch.Tensor, box_min: torch.Tensor, box_max: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Slab test: (t_near, t_far) with t_near clamped at 0 for cameras inside the box.

    Misses and non-finite rays get t_far <= t_near. Axis-parallel rays use a
    signed tiny reciprocal instead of dividing by zero.
    """
    tiny = torch.full_like(directions, 1e-12)
    safe = torch.where(directions.abs() < 1e-12, torch.where(directions < 0, -tiny, tiny), directions)
    inv = 1.0 / safe
    t0, t1 = (box_min - origins) * inv, (box_max - origins) * inv
    t_near = torch.minimum(t0, t1).amax(-1).clamp_min(0.0)
    t_far = torch.maximum(t0, t1).amin(-1)
    finite = torch.isfinite(origins).all(-1) & torch.isfinite(directions).all(-1) & torch.isfinite(t_far)
    t_far = torch.where(finite & torch.isfinite(t_near), t_far, torch.zeros_like(t_far))
    t_near = torch.where(finite & torch.isfinite(t_near), t_near, torch.zeros_like(t_near))
    return t_near, t_far


def render_rays(
    grid: VoxelGrid,
    origins: torch.Tensor,
    directions: torch.Tensor,
    config: RenderConfig = RenderConfig(),
    occupancy: Occupancy | None = None,
    generator: torch.Generator | None = None,
    color_features: torch.Tensor | None = None,
    sparse_grad: bool = False,
) -> RenderOutput:
    """Render unit-direction rays through ``grid``.

    ``generator`` turns on stratified jitter (one uniform offset per ray, for
    training). ``color_features`` (X, Y, Z, C) replaces the grid's colour with
    other raw features, rendered without activation over the grid's density
    (the 3D attention grids use it). ``sparse_grad``: see ``VoxelGrid.interpolate``.

    Always computes in float32, autocast disabled: cumulative optical depths
    and transmittance products lose too much in bf16/fp16, and mixed dtypes
    would break the scatters. Under autocast the result is the fp32 render.
    """
    if hasattr(grid, "render_rays"):  # a backbone with its own sampling (voxe_core.scene_grid.SceneGrid)
        return grid.render_rays(origins, directions, config, occupancy, generator, color_features, sparse_grad)
    with torch.autocast(origins.device.type, enabled=False):
        return _render_rays(
            grid, origins.float(), directions.float(), config, occupancy, generator, color_features, sparse_grad
        )


def _ray_segments(grid, occupancy, origins, directions, t_near, step, first, last, skip_empty):
    """Per ray, the lattice segments worth sampling, in marching order: (R, S) indices and (R,) counts.

    A segment is ``SEGMENT`` consecutive lattice samples. When skipping, a
    segment survives when its midpoint's block in ``occupancy.dilated_blocks``
    is marked, so every sample of a dropped segment lies in an empty cell and
    dropping it never changes the render; the fine per-cell test then runs only
    on the segments kept.
    """
    seg_first = torch.div(first, SEGMENT, rounding_mode="floor")
    n_segments = torch.where(last > first, torch.div(last - 1, SEGMENT, rounding_mode="floor") - seg_first + 1, 0)
    max_segments = int(n_segments.max()) if n_segments.numel() else 0
    segments = seg_first[:, None] + torch.arange(max_segments, device=origins.device)[None, :]
    if not skip_empty or max_segments == 0:
        return segments, n_segments
    # Every sample of a segment lies within SEGMENT / 2 steps of its midpoint, so within
    # ``size`` cells of it per axis, so in the midpoint's block or one of its neighbours.
    longest = float(directions.norm(dim=-1).nan_to_num(0.0, 0.0, 0.0).max().clamp_min(1.0))
    size = max(1, math.ceil(SEGMENT / 2 * step * longest / float(grid.voxel_size.min())))
    keep = torch.arange(max_segments, device=origins.device)[None, :] < n_segments[:, None]
    mid = t_near[:, None] + (segments * SEGMENT + SEGMENT / 2) * step
    block = grid.cell_index(origins[:, None, :] + mid[..., None] * directions[:, None, :]) // size
    keep &= gather_3d(occupancy.dilated_blocks(size), block)
    # Stable sort puts each ray's kept segments first, still in marching order.
    order = torch.sort((~keep).to(torch.uint8), dim=1, stable=True).indices
    n_kept = keep.sum(1)
    width = int(n_kept.max())
    return segments.gather(1, order[:, :width]), n_kept


def _render_rays(grid, origins, directions, config, occupancy, generator, color_features, sparse_grad) -> RenderOutput:
    device = origins.device
    n_rays = origins.shape[0]
    channels = 3 if color_features is None else color_features.shape[-1]
    background = torch.as_tensor(config.background, dtype=torch.float32, device=device)
    if background.numel() == 1:
        background = background.expand(channels)
    if config.skip_empty and occupancy is None:
        occupancy = grid.occupancy(config.sigma_threshold)
    step = float(config.step_ratio * grid.voxel_size.min())
    # Samples sit on one lattice per ray anchored at the grid box, so skipping
    # only drops samples and never moves them: with ReLU it is exact.
    t_near, t_far = ray_box_intersection(origins, directions, grid.bbox_min, grid.bbox_max)
    n_total = torch.ceil((t_far - t_near) / step).clamp_min(0).long()
    first = torch.zeros_like(n_total)
    last = n_total
    if config.skip_empty:
        tight_near, tight_far = ray_box_intersection(
            origins, directions, occupancy.bbox_min.to(device), occupancy.bbox_max.to(device)
        )
        hit = tight_far > tight_near
        first = torch.where(hit, ((tight_near - t_near) / step).floor().long().clamp_min(0), first)
        last = torch.where(hit, torch.minimum(((tight_far - t_near) / step).ceil().long(), n_total), first)
    candidates = int((last - first).clamp_min(0).sum())
    segments, n_segments = _ray_segments(
        grid, occupancy, origins, directions, t_near, step, first, last, config.skip_empty
    )
    if generator is not None:
        offset = torch.rand(n_rays, generator=generator, device=device)
    else:
        offset = torch.full((n_rays,), 0.5, device=device)

    start = t_near + offset * step  # first lattice sample of each ray
    length = t_far - t_near
    accumulated = torch.zeros(n_rays, channels, device=device)
    opacity = torch.zeros(n_rays, device=device)
    depth = torch.zeros(n_rays, device=device)
    samples = 0
    # Consecutive groups of rays whose lattice samples fit in one pass (bounds memory on dense renders).
    per_ray = n_segments * SEGMENT
    group = torch.div(per_ray.cumsum(0) - per_ray, config.samples_per_pass, rounding_mode="floor")
    ends = torch.unique_consecutive(group, return_counts=True)[1].cumsum(0).tolist()
    for lo, hi in zip([0] + ends[:-1], ends):
        ray, k, t, points = _packed_samples(
            grid, occupancy if config.skip_empty else None, origins, directions, start, step,
            first, last, segments[lo:hi], n_segments[lo:hi], lo,
        )
        # The last sample of a ray is cut at the box exit so path lengths are exact.
        delta = (length.index_select(0, ray) - k * step).clamp(0.0, step)
        if config.early_stop > 0 and ray.numel():
            # Densities without gradient find where each ray's transmittance falls below
            # ``early_stop``; only the samples before that are evaluated for the render.
            with torch.no_grad():
                probe = grid.activate_density(grid.interpolate(points)[:, 0])
                optical = optical_depth(probe, delta)
                reached = _transmittance(optical, ray) > config.early_stop
            samples += ray.numel()
            pick = reached.nonzero().squeeze(1)
            ray, t, points, delta = (x.index_select(0, pick) for x in (ray, t, points, delta))
        if ray.numel() == 0:
            continue
        samples += ray.numel()
        raw = grid.interpolate(points, sparse_grad=sparse_grad)
        sigma = grid.activate_density(raw[:, 0])
        color = grid.activate_color(raw[:, 1:]) if color_features is None else grid.interpolate(points, color_features)
        optical = optical_depth(sigma, delta)
        weights = _transmittance(optical, ray) * (-torch.expm1(-optical))
        accumulated = accumulated.index_add(0, ray, weights[:, None] * color.to(weights.dtype))
        opacity = opacity.index_add(0, ray, weights)
        depth = depth.index_add(0, ray, weights * t)

    rgb = accumulated + (1.0 - opacity)[:, None] * background
    expected_depth = torch.where(opacity > 1e-6, depth / opacity.clamp_min(1e-6), torch.zeros_like(depth))
    return RenderOutput(rgb, opacity, expected_depth, samples, candidates)


def _packed_samples(grid, occupancy, origins, directions, start, step, first, last, segments, n_segments, ray_offset):
    """The samples of the kept segments (in occupied cells when ``occupancy`` is given), packed ray
    by ray in marching order: ray index, lattice index, distance and point of each.

    Work is laid out per segment (16 samples wide) so the per-ray values are
    gathered once per segment, not once per sample.
    """
    kept = torch.arange(segments.shape[1], device=segments.device)[None, :] < n_segments[:, None]
    seg_ray = kept.nonzero()[:, 0] + ray_offset
    k = segments[kept][:, None] * SEGMENT + torch.arange(SEGMENT, device=segments.device)  # (G, SEGMENT)
    inside = (k >= first.index_select(0, seg_ray)[:, None]) & (k < last.index_select(0, seg_ray)[:, None])
    t = start.index_select(0, seg_ray)[:, None] + k * step
    points = origins.index_select(0, seg_ray)[:, None, :] + t[..., None] * directions.index_select(0, seg_ray)[:, None, :]
    if occupancy is not None:
        inside &= occupancy.occupied(grid.cell_index(points))
    pick = inside.reshape(-1).nonzero().squeeze(1)
    ray = seg_ray.index_select(0, torch.div(pick, SEGMENT, rounding_mode="floor"))
    return ray, k.reshape(-1).index_select(0, pick), t.reshape(-1).index_select(0, pick), points.reshape(-1, 3).index_select(0, pick)


def _transmittance(optical, ray):
    """Transmittance in front of each packed sample: exp of minus the optical depth before it on its ray.

    One float64 prefix sum over all rays, minus each ray's value at its first
    sample: in float32 a ray behind rays of large optical depth would lose its own.
    """
    wide = optical.double()
    before = wide.cumsum(0) - wide
    starts = torch.ones_like(ray, dtype=torch.bool)
    starts[1:] = ray[1:] != ray[:-1]
    before = before - before[starts][starts.cumsum(0) - 1]
    return torch.exp(-before).to(optical.dtype)


@torch.no_grad()
def render_image(
    grid: VoxelGrid,
    cameras: Cameras,
    index: int,
    config: RenderConfig = RenderConfig(),
    occupancy: Occupancy | None = None,
) -> RenderOutput:
    """Whole image (H, W, 3) from camera ``index``, rendered in ray chunks to bound memory (float32, as render_rays)."""
    if config.skip_empty and occupancy is None:
        occupancy = grid.occupancy(config.sigma_threshold)
    with torch.autocast(cameras.c2w.device.type, enabled=False):
        origins, directions = camera_rays(cameras, index)
    parts = [
        render_rays(grid, origins[s : s + config.chunk_rays], directions[s : s + config.chunk_rays], config, occupancy)
        for s in range(0, origins.shape[0], config.chunk_rays)
    ]
    shape = (cameras.height, cameras.width)
    return RenderOutput(
        torch.cat([p.rgb for p in parts]).reshape(*shape, -1),
        torch.cat([p.opacity for p in parts]).reshape(shape),
        torch.cat([p.depth for p in parts]).reshape(shape),
        sum(p.samples for p in parts),
        sum(p.candidates for p in parts),
    )
