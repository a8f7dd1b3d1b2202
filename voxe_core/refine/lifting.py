"""Step 2: the 2D maps lifted into two scalar grids over G_e's frozen density (SPEC §3).

A field's value is rendered raw over a black background and fitted by L1 to
the maps plus ``tv_weight`` · TV, with Adam (see the package docstring for why
raw and why the start at 0).

The render is linear in the field over a frozen density: pixel = Σ_s w_s ·
trilerp(v, x_s) = (A v)_pixel. So the fit starts (``lift_start="backprojection"``)
from the weighted back-projection v = Aᵀm / (Aᵀ1 + prior), the per-vertex
average of the map values of every pixel that sees the vertex, weighted by
how much of that pixel it makes (one pass over all pixels, no gradients), and
Adam then updates only the vertices some pixel sees (the rows of A that are
not empty); the rest keep "no attention" (0) as the start says.
"""

from __future__ import annotations

import math
from typing import Callable

import torch

from voxe_core.cameras import Cameras, camera_rays
from voxe_core.constants import REFINE_ITERATIONS
from voxe_core.devices import full_precision
from voxe_core.grid import Occupancy, VoxelGrid, ray_box_intersection, unit_directions
from voxe_core.progress import Callbacks, Progress
from voxe_core.refine.config import RefineConfig, SegmentationError
from voxe_core.refine.cut import prefer_neither
from voxe_core.render import render_rays
from voxe_core.volrend import optical_depth, transmittance


def frozen_density(grid: VoxelGrid) -> VoxelGrid:
    """A copy of ``grid`` whose features take no gradient (the attention fits never touch G_e)."""
    frozen = grid.like(grid.features.detach().clone())
    frozen.flat_features.requires_grad_(False)
    return frozen


def all_camera_rays(cameras: Cameras) -> tuple[torch.Tensor, torch.Tensor]:
    """Origins and directions of every pixel of every camera, (N*H*W, 3) each, view-major."""
    parts = [camera_rays(cameras, i) for i in range(len(cameras))]
    return torch.cat([p[0] for p in parts]), torch.cat([p[1] for p in parts])


def total_variation(values: torch.Tensor) -> torch.Tensor:
    """Mean squared difference between 6-neighbours, summed over the three axes, of (X, Y, Z, C)."""
    tv = values.new_zeros(())
    for axis in range(3):
        if values.shape[axis] > 1:
            tv = tv + torch.diff(values, dim=axis).pow(2).mean()
    return tv


def attention_occupancy(grid: VoxelGrid, config: RefineConfig) -> Occupancy:
    """The cells of ``grid`` the attention fields are rendered through (``config.render``'s threshold);
    :class:`SegmentationError` when there are none. ``refine`` asks before its first attention pass (an emptied
    edit had been refused only after every pass)."""
    occupancy = grid.occupancy(config.render.sigma_threshold)
    if occupancy.empty:
        raise SegmentationError("the edited grid has no occupied voxels: there is nothing to attach attention to")
    return occupancy


def _occupied_slices(occupancy: Occupancy) -> tuple[slice, slice, slice]:
    """Vertex index ranges of the occupied cells' box (the only part of a field a render can see)."""
    idx = occupancy.cells.nonzero()
    lo, hi = idx.min(0).values, idx.max(0).values + 2  # cells [i, i+1] use vertices i and i+1
    return tuple(slice(int(a), int(b)) for a, b in zip(lo, hi))


@torch.no_grad()
def backproject(
    grid: VoxelGrid,
    origins: torch.Tensor,
    directions: torch.Tensor,
    targets: torch.Tensor,
    config: RefineConfig = RefineConfig(),
    occupancy: Occupancy | None = None,
    callbacks: Callbacks = Callbacks(),
) -> tuple[torch.Tensor, torch.Tensor]:
    """Weighted back-projection of per-ray ``targets`` (N, C) through ``grid``'s density: (values (X, Y, Z, C), weight (X, Y, Z)).

    weight = Aᵀ1 and values = Aᵀ targets / (weight + ``config.backprojection_prior``),
    with A the (rays × vertices) matrix of the raw render (compositing weight
    times trilinear weight, ray midpoints of ``config.render``'s lattice
    steps). A vertex seen fully by k pixels of value m gets k·m / (k + prior). Reports
    ``Progress("backprojection")`` after, and may be cancelled before, each chunk of ``config.render.chunk_rays`` rays
    (at 160³ and 32 views it is the refine stage's longest part on a CPU: 81 s).

    Examples:
        >>> grid = VoxelGrid(8, init_density=5.0)  # opaque everywhere
        >>> o, d = torch.tensor([[0.0, 0.0, -3.0]]), torch.tensor([[0.0, 0.0, 1.0]])
        >>> values, weight = backproject(grid, o, d, torch.tensor([[1.0]]), RefineConfig(backprojection_prior=0.0))
        >>> round(float(values[weight > 0].max()), 4)  # every vertex the ray touches averages to the one value
        1.0
    """
    occupancy = occupancy if occupancy is not None else grid.occupancy(config.render.sigma_threshold)
    n_vertices = grid.flat_features.shape[0]
    numerator = torch.zeros(n_vertices, targets.shape[1], device=targets.device)
    weight = torch.zeros(n_vertices, device=targets.device)
    chunk = config.render.chunk_rays
    chunks = -(-origins.shape[0] // chunk)
    for done, start in enumerate(range(0, origins.shape[0], chunk), 1):
        callbacks.check_cancel("backprojection")
        o, t = origins[start:start + chunk], targets[start:start + chunk]
        d = unit_directions(directions[start:start + chunk])
        offsets = torch.full((o.shape[0],), 0.5, device=o.device)
        for group in grid.ray_samples(o, d, offsets, config.render.step_ratio, occupancy,
                                      config.render.pass_samples(o.device), config.render.early_stop):
            if group.ray.numel() == 0:
                continue
            with full_precision(group.points):  # (a caller's autocast had run the interpolation's bmm in bf16)
                sigma = grid.activate_density(grid.interpolate(group.points)[:, 0])
            optical = optical_depth(sigma, group.delta)
            w = transmittance(optical, group.ray) * (-torch.expm1(-optical))
            index, tri = grid.trilinear_corners(group.points)
            contribution = (w.float()[:, None] * tri).reshape(-1)
            index = index.reshape(-1)
            weight.index_add_(0, index, contribution)
            numerator.index_add_(0, index, contribution[:, None] * t[group.ray].repeat_interleave(8, 0))
        callbacks.progress(Progress("backprojection", done, chunks, info={"stage": "back-projection"}))
    values = numerator / (weight + config.backprojection_prior).clamp_min(1e-12)[:, None]
    return values.reshape(*grid.resolution, -1), weight.reshape(grid.resolution)


def strided_pixels(n_views: int, height: int, width: int, stride: int, device=None) -> torch.Tensor:
    """(N*H*W,) bool, view-major: every ``stride``-th row and column, the lattice shifted from view to view.

    Examples:
        >>> strided_pixels(2, 2, 2, 2).view(2, 2, 2).int().tolist()
        [[[1, 0], [0, 0]], [[0, 1], [0, 0]]]
    """
    view = torch.arange(n_views, device=device)[:, None, None]
    rows = torch.arange(height, device=device)[None, :, None]
    cols = torch.arange(width, device=device)[None, None, :]
    pick = ((rows - view // stride) % stride == 0) & ((cols - view) % stride == 0)
    return pick.reshape(-1)


FreshView = Callable[[int], tuple[Cameras, torch.Tensor, torch.Tensor]]
"""step -> (one camera, its edit map (1, H, W), its object map): a new pose and diffusion pass per fit step."""


def attention_l1(rendered: torch.Tensor, targets: torch.Tensor, pixels: str = "all") -> torch.Tensor:
    """Mean L1 of rendered attention against its targets; ``pixels="rendered_positive"`` counts only the
    entries whose render is > 0 (the authors' mask: where the attention grid renders something), the others 0.

    Examples:
        >>> r, t = torch.tensor([[0.5], [0.0], [-1.0]]), torch.tensor([[0.0], [1.0], [1.0]])
        >>> float(attention_l1(r, t)), float(attention_l1(r, t, "rendered_positive"))
        (1.1666666269302368, 0.1666666716337204)
    """
    error = (rendered - targets).abs()
    if pixels == "rendered_positive":
        error = error * (rendered.detach() > 0)
    return error.mean()


_MAPS_ALIKE = ("they do not tell the edit from the object (the edit words' cross-attention is the rest of the "
              "prompt's), so neither can the grids fitted to them")


def _why_still_equal(config: RefineConfig, fitted: int, maps_differ: bool) -> str:
    """Why a constant start's fit left both grids equal, and what to do: the cut would have said only "no seeds"."""
    if not fitted:
        return ("no step fitted them, every fresh view having missed the edited object (no pixel's ray meets its "
                "occupied box), so no voxel is more likely edit than object and the cut has no seeds; are the fresh "
                "poses aimed at it?")
    if not maps_differ:  # (fresh views' maps: fixed ones are told before the fit)
        return f"the edit and object maps are equal on every pixel fitted: {_MAPS_ALIKE}, and the cut has no seeds"
    alike = "from one value Adam moves both alike until their renders reach the lower of the two maps"
    no_seeds = "so no voxel is more likely edit than object and the cut has no seeds"
    if config.iterations < REFINE_ITERATIONS:
        return (f"{alike}, {no_seeds}; fit more iterations (the paper: {REFINE_ITERATIONS}) or use "
                "lift_start='backprojection'")
    return (f"{alike}, which these did not in as many iterations as the paper's ({REFINE_ITERATIONS}), {no_seeds}; "
            f"use lift_start='backprojection', or a larger lr or an init_value nearer the maps (now {config.lr} and "
            f"{config.init_value})")


def _diverged(config: RefineConfig, iteration: int, what: str) -> str:
    return (f"the attention-grid fit diverged by iteration {iteration} of {config.iterations}: {what}; its steps "
            f"overflowed float32: lower lr or tv_weight (now {config.lr:g} and {config.tv_weight:g})")


def fit_attention_grids(
    grid: VoxelGrid,
    cameras: Cameras,
    edit_maps: torch.Tensor,
    object_maps: torch.Tensor,
    config: RefineConfig = RefineConfig(),
    callbacks: Callbacks = Callbacks(),
    fresh_view: FreshView | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Lift 2D maps to two scalar grids ``(X, Y, Z, 1)`` over ``grid``'s frozen density.

    Start: the weighted back-projection of the maps (:func:`backproject`) over
    every ``backprojection_stride``-th pixel row and column (:func:`strided_pixels`),
    or ``config.init_value`` everywhere with ``lift_start="constant"`` (the
    paper's fit). Then both fields are fitted together (one render of a 2-channel field per step)
    on ``rays_per_step`` random pixels of all views (``fit_views="fixed"``) or on
    every pixel of the one new view ``fresh_view(step)`` gives (``"fresh"``, the
    authors'), rendered raw over a black background, with L1 (over the pixels
    ``fit_pixels`` names: :func:`attention_l1`) + ``tv_weight``·TV (TV over the occupied box), Adam at
    ``lr``; stratified jitter along the rays. Pixels whose ray misses the
    occupied box render 0 whatever the field holds and are left out.
    Deterministic for ``config.seed``; reports ``Progress("attention_grids")``
    every step and may be cancelled between steps. A constant start whose fit ends with both grids still equal
    (:func:`~voxe_core.refine.cut.prefer_neither`) is a SegmentationError naming why (no step fitted, maps that never
    differ, or too few iterations): the cut would find no seeds; maps equal on every pixel are that error before any
    work, from either start, where the fit sees only them (``fit_views="fixed"``), as are maps equal on every pixel
    the back-projection reads with no iterations, and so is a back-projection a ``backprojection_prior`` that
    outweighs the pixels leaves equal but for rounding. So are views that miss the object, and a back-projection whose
    pixels see none of its density (the fit moves only the vertices they see), and a fit that diverges: a step whose
    loss is NaN or infinite stops it, as do grids that are so where it ends (a grid whose density is NaN is refused
    before any work).
    """
    if edit_maps.dim() != 3:  # (had failed unpacking its shape: "too many values to unpack (expected 3)")
        raise ValueError(f"the maps must be (views, height, width), one scalar per pixel, got edit maps of shape "
                         f"{tuple(edit_maps.shape)}")
    n_views, height, width = edit_maps.shape
    if object_maps.shape != edit_maps.shape:
        raise ValueError(f"edit maps {tuple(edit_maps.shape)} and object maps {tuple(object_maps.shape)} differ")
    if n_views != len(cameras) or (height, width) != (cameras.height, cameras.width):
        raise ValueError(
            f"{n_views} maps of {height}x{width} do not match {len(cameras)} cameras of {cameras.height}x{cameras.width}"
        )
    if config.fit_views == "fresh" and config.iterations and fresh_view is None:  # (asked after the back-projection)
        raise ValueError("fit_views='fresh' needs fresh_view: a new pose and its maps for every step")
    for name, maps in (("edit", edit_maps), ("object", object_maps)):  # (the cut had blamed a "diverged fit")
        bad = (~torch.isfinite(maps)).flatten(1).any(1).nonzero().squeeze(-1).tolist()
        if bad:
            raise SegmentationError(f"the {name} maps are not finite (NaN or infinite) in {len(bad)} of the {n_views} "
                                    f"views (the first: view {bad[0] + 1}): there is no attention to lift there")
    # (a step on it had been taken for the fit's divergence: its loss is NaN from the first)
    if nan := int(torch.isnan(grid.features[..., 0].detach()).sum()):
        raise SegmentationError(f"the edited grid's density is NaN at {nan} of its {math.prod(grid.resolution)} "
                                "vertices, so what the views see through it is undefined (a diverged edit or a "
                                "corrupted grid?): there is no attention to lift")
    device = grid.bbox_min.device
    frozen = frozen_density(grid)
    occupancy = attention_occupancy(frozen, config)
    origins, directions = all_camera_rays(cameras.to(device))
    targets = torch.stack([edit_maps, object_maps], -1).reshape(-1, 2).to(device=device, dtype=torch.float32)
    near, far = ray_box_intersection(origins, directions, occupancy.bbox_min.to(device), occupancy.bbox_max.to(device))
    hits = far > near
    keep = hits.nonzero().squeeze(-1)
    # (a constant start fitted on fresh views is no exception: the fit moves only the vertices these views see)
    if keep.numel() == 0:
        raise SegmentationError(f"none of the {n_views} views sees the edited object (no pixel's ray meets its "
                                "occupied box): there is no attention to lift; are the views aimed at it?")
    strided = (hits & strided_pixels(n_views, height, width, config.backprojection_stride, device)).nonzero().squeeze(-1)
    # Maps that never differ on the pixels the grids come from leave both grids equal from either start: the
    # back-projection's two channels are alike, and so is every step on these views (or none is taken). Refused at
    # once, where a constant start had run every step (the paper's 1,500) to say so, and a back-projection's its whole
    # fit for the cut to find no seeds. With no steps the grids are the back-projection's alone, which reads only the
    # strided pixels (maps apart only off the stride had been back-projected to equal grids; no strided pixel that
    # sees the object is the error below).
    compared = keep if config.iterations else strided
    if ((config.fit_views == "fixed" or not config.iterations) and compared.numel()
            and prefer_neither(targets[compared, 0], targets[compared, 1])):
        seeing = int(hits.reshape(n_views, -1).any(-1).sum())
        read = ("" if config.iterations or config.backprojection_stride == 1 else
                f" the back-projection reads (one row and column in {config.backprojection_stride})")
        raise SegmentationError(f"the edit and object maps are equal on every pixel{read} of the {seeing} views (of "
                                f"{n_views}) that see the edited object: {_MAPS_ALIKE} from "
                                f"lift_start={config.lift_start!r}, and the cut would have no seeds; nothing was "
                                "fitted")
    start, seen = backproject(frozen, origins[strided], directions[strided], targets[strided], config, occupancy,
                              callbacks)
    rows = (seen.reshape(-1) > 0).nonzero().squeeze(-1)  # vertices some pixel sees: the only ones L1 moves
    if rows.numel() == 0:  # (as above: the grids had reached the cut "equal everywhere", or a fit moved nothing)
        nothing = "there is no attention to lift (and no voxel the fit may move)"
        if config.backprojection_stride == 1:  # every pixel read: the stride is not why (it had been blamed)
            raise SegmentationError(
                f"{keep.numel()} pixels of the {n_views} views see the edited object's box, but each pixel's ray "
                f"passes through its empty space, meeting none of its density: {nothing}; aim the views at the "
                "object, or render larger views (rays closer together)")
        raise SegmentationError(
            f"{keep.numel()} pixels of the {n_views} views see the edited object's box, but none that the "
            f"back-projection reads (one row and column in {config.backprojection_stride}) meets its density: "
            f"{nothing}; lower backprojection_stride, or render larger views")
    # Maps apart on the pixels read (checked above) back-projected to grids equal but for rounding: the prior, which
    # every vertex's average divides by, drowned what the pixels gave (the cut had blamed the maps or the iterations).
    if config.lift_start == "backprojection" and not config.iterations and prefer_neither(start[..., 0], start[..., 1]):
        raise SegmentationError(
            f"the back-projected attention grids are equal everywhere but for float32 rounding, though the maps "
            f"differ on the pixels it reads: backprojection_prior={config.backprojection_prior:g} outweighs the "
            f"pixels' weight (at most {float(seen.max()):.3g} at a vertex, which gets k·m / (k + prior) from k pixels "
            f"of value m), so the cut would have no seeds; lower backprojection_prior (the default: "
            f"{RefineConfig.backprojection_prior:g}), or fit iterations > 0")
    origins, directions, targets = origins[keep], directions[keep], targets[keep]

    if config.lift_start == "constant":
        start = torch.full_like(start, float(config.init_value))
    flat_start = start.reshape(-1, 2)
    active = flat_start[rows].clone().requires_grad_(True)
    optimizer = torch.optim.Adam([active], lr=config.lr, fused=active.is_cuda or None)  # one kernel per step on CUDA
    box = _occupied_slices(occupancy)
    generator = torch.Generator(device=device).manual_seed(int(config.seed))
    n_rays = origins.shape[0]
    # "fresh" fits other maps than these: whether they differ is told step by step (a constant start's fixed maps
    # that never differ were refused above)
    fitted, maps_differ = 0, config.fit_views == "fixed"
    for iteration in range(config.iterations):
        callbacks.check_cancel("attention_grids")
        values = flat_start.index_copy(0, rows, active).reshape(start.shape)
        if config.fit_views == "fresh":
            view, edit_map, object_map = fresh_view(iteration)
            o, d = all_camera_rays(view.to(device))
            t = torch.stack([edit_map, object_map], -1).reshape(-1, 2).to(device=device, dtype=torch.float32)
            near, far = ray_box_intersection(o, d, occupancy.bbox_min.to(device), occupancy.bbox_max.to(device))
            hit = far > near
            o, d, t = o[hit], d[hit], t[hit]
            if not hit.any():  # the pose missed the object: nothing to fit this step
                continue
            maps_differ = maps_differ or not prefer_neither(t[:, 0], t[:, 1])
        else:
            batch = torch.randint(0, n_rays, (min(config.rays_per_step, n_rays),), generator=generator, device=device)
            o, d, t = origins[batch], directions[batch], targets[batch]
        out = render_rays(frozen, o, d, config.render, occupancy, generator, color_features=values)
        l1 = attention_l1(out.rgb, t, config.fit_pixels)
        tv = total_variation(values[box])
        loss = l1 + config.tv_weight * tv
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        fitted += 1
        l1_value, tv_value, loss_value = torch.stack([l1.detach(), tv.detach(), loss.detach()]).tolist()
        if not math.isfinite(loss_value):  # (every step left had run, fresh views a diffusion pass each, for the cut to
            # refuse the NaN grids as "a diverged edit or attention-grid fit?")
            raise SegmentationError(_diverged(config, iteration + 1, f"its loss is {loss_value} (L1 {l1_value}, TV "
                                                                     f"{tv_value})"))
        callbacks.progress(Progress("attention_grids", iteration + 1, config.iterations,
                                    {"l1": l1_value, "tv": tv_value}, {"stage": "attention grids"}))
    values = flat_start.index_copy(0, rows, active.detach()).reshape(start.shape)
    if nonfinite := int((~values.isfinite()).any(-1).sum()):  # a last step whose loss was finite can overflow its update
        raise SegmentationError(_diverged(config, config.iterations, f"the grids hold NaN or infinite values at "
                                          f"{nonfinite} of their {math.prod(start.shape[:3])} vertices"))
    if config.lift_start == "constant" and prefer_neither(values[..., 0], values[..., 1]):  # the cut has no seeds
        raise SegmentationError(f"the attention grids are still equal everywhere after {config.iterations} fitting "
                                f"iterations from lift_start='constant': {_why_still_equal(config, fitted, maps_differ)}")
    return values[..., 0:1].contiguous(), values[..., 1:2].contiguous()
