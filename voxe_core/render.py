"""Differentiable volume rendering (NeRF quadrature): compositing the samples a grid places along rays.

Sampling and compositing are apart, as in nerfacc: the grid decides where a
ray's samples lie (``VoxelGrid.ray_samples``: the box lattice of the ReLU
field, skipping empty cells and, with ``early_stop``, the samples behind the
point where a ray's transmittance falls below it; ``SceneGrid`` overrides it
with its contracted bins), and :func:`composite` turns the packed samples and
a field into pixels. The field is passed as a function of the sample points
(:data:`Field`), so the same compositor renders a grid's colour or other
per-vertex features (the 3D attention grids). Cost therefore follows the
occupied space a ray actually sees. Where ``RenderConfig.fused`` asks and it
applies (:func:`fused_marcher_applies`), ``voxe_core.fused_render`` does both in
one GPU kernel instead: the same samples and render, nothing laid out between.
"""

from __future__ import annotations

import importlib.util
import math
import numbers
import os
from dataclasses import asdict, dataclass, field
from typing import Callable, Iterable

import torch

from voxe_core.cameras import Cameras, camera_rays
from voxe_core.constants import RENDER_CHUNK_RAYS
from voxe_core.devices import full_precision
from voxe_core.grid import DEFAULT_SIGMA_THRESHOLD, Occupancy, VoxelGrid, ray_box_intersection, unit_directions
from voxe_core.tensorio import is_number
from voxe_core.volrend import RaySamples, optical_depth, transmittance

Field = Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]
"""Sample points (S, 3) -> (density (S,), values (S, C)): what :func:`composite` integrates."""

MIN_STEP_RATIO = 0.05
"""The finest sample spacing, 1/20 of a voxel: ~5,500 lattice samples per ray along a 160³ grid's diagonal (the
default 0.5: 551), ~17,700 at 512³. The sampler lays out every ray's segments at once, so its memory grows as
1 / ``step_ratio``: 1e-9 asked for ~10^11 samples per ray and took all the memory before placing one."""


@dataclass
class RenderConfig:
    step_ratio: float = 0.5  # sample spacing in units of the smallest voxel edge
    background: tuple[float, ...] = (1.0, 1.0, 1.0)
    skip_empty: bool = True
    sigma_threshold: float = DEFAULT_SIGMA_THRESHOLD  # cells whose density stays below this are skipped
    early_stop: float = 1e-4  # transmittance below which a ray's samples are not evaluated
    # Lattice samples held at once (rays are grouped to fit); None: the device's default (pass_samples).
    samples_per_pass: int | None = None
    chunk_rays: int = RENDER_CHUNK_RAYS  # rays per chunk in whole-image renders
    # March each ray in one Triton kernel where that renders the same (voxe_core.fused_render: a ReLU grid's own
    # colour on CUDA); elsewhere, or False, the packed path.
    fused: bool = False

    def __post_init__(self) -> None:
        """ValueError naming a setting that would render blank (a step of 0 or NaN placed no sample), divide by
        zero deep in the sampler (``samples_per_pass`` 0) or take all the memory (a vanishing step). A value of
        another type is refused so too: a string or None had been a TypeError naming no setting ("must be real
        number, not str"), skip_empty="no" or fused="false" (true strings) had run as True, and True as a count 1."""
        def count(value) -> bool:
            return is_number(value) and isinstance(value, numbers.Integral) and value >= 1

        def finite(value) -> bool:
            return is_number(value) and math.isfinite(value)

        rules = [
            ("step_ratio", finite(self.step_ratio) and self.step_ratio >= MIN_STEP_RATIO,
             f"a finite number of voxels >= {MIN_STEP_RATIO} (MIN_STEP_RATIO)"),
            ("samples_per_pass", self.samples_per_pass is None or count(self.samples_per_pass),
             "an integer >= 1, or None for the device's default"),
            ("chunk_rays", count(self.chunk_rays), "an integer >= 1"),
            ("early_stop", is_number(self.early_stop) and 0.0 <= self.early_stop < 1.0, "a transmittance in [0, 1)"),
            ("sigma_threshold", finite(self.sigma_threshold) and self.sigma_threshold >= 0.0,
             "a finite density >= 0"),
            ("background", isinstance(self.background, (tuple, list)) and all(finite(b) for b in self.background),
             "a tuple of finite values"),
            ("skip_empty", isinstance(self.skip_empty, bool), "True or False"),
            ("fused", isinstance(self.fused, bool), "True or False"),
        ]
        for name, ok, rule in rules:
            if not ok:
                raise ValueError(f"RenderConfig.{name} must be {rule}, got {getattr(self, name)!r}")

    def recipe(self) -> dict:
        """The fields that shape a render (a run's recipe): all but how much a pass or a chunk holds (the device's:
        the render is the same at any size) and which marcher runs it (the same render to float32 rounding)."""
        return {k: v for k, v in asdict(self).items() if k not in ("samples_per_pass", "chunk_rays", "fused")}

    def pass_samples(self, device: torch.device) -> int:
        """``samples_per_pass``, or ``device``'s default: 2^20 on the CPU, 2^22 on an accelerator.

        Larger passes dispatch fewer operations (2^22: 0.50x on the edit's render, one pass instead of five), which
        is what a launch-bound GPU pays for (on the H200: 0.73x the render's time, the edit step 1.13x faster;
        bench/gpu.py, sections h and i), but ran 1.11x slower on this CPU with +0.47 GiB (bench/render_passes.py).
        The render is the same at any size (on a GPU to float32 rounding: its atomic adds run in another order).
        """
        if self.samples_per_pass is not None:
            return self.samples_per_pass
        return 1 << 20 if torch.device(device).type == "cpu" else 1 << 22


@dataclass
class RenderOutput:
    rgb: torch.Tensor  # (N, C), or (H, W, C) from render_image, composited on the background
    opacity: torch.Tensor  # (N,)
    depth: torch.Tensor  # (N,) expected depth, 0 where the ray hit nothing
    # Grid evaluations, and the samples along the rays before the occupancy test: 0-d tensors from the fused
    # marcher (read back, they would wait for its kernel), ints otherwise.
    samples: int | torch.Tensor = 0
    candidates: int | torch.Tensor = 0
    extras: dict = field(default_factory=dict)


def grid_field(grid: VoxelGrid, color_features: torch.Tensor | None = None, sparse_grad: bool = False) -> Field:
    """The field of ``grid``: activated density and colour, or raw ``color_features`` (X, Y, Z, C) over its density."""

    def values(points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        raw = grid.interpolate(points, sparse_grad=sparse_grad)
        colour = grid.activate_color(raw[:, 1:]) if color_features is None else grid.interpolate(points, color_features)
        return grid.activate_density(raw[:, 0]), colour

    return values


def fused_marcher_applies(grid: VoxelGrid, origins: torch.Tensor, directions: torch.Tensor,
                          color_features: torch.Tensor | None, sparse_grad: bool) -> bool:
    """Whether ``voxe_core.fused_render`` renders this: a lattice-sampled float32 ReLU grid's own colour with a dense
    gradient into the grid only (none into the rays), on a device it runs on (:func:`fused_marcher_runs_on`)."""
    return (grid.lattice_sampled and grid.activation == "relu" and grid.flat_features.dtype == torch.float32
            and color_features is None and not sparse_grad and not (origins.requires_grad or directions.requires_grad)
            and fused_marcher_runs_on(origins.device))


def fused_marcher_runs_on(device: torch.device | str) -> bool:
    """Whether Triton runs the fused marcher on ``device``: installed, and CUDA (or its CPU interpreter,
    ``TRITON_INTERPRET=1``, on any device)."""
    return ((torch.device(device).type == "cuda" or os.environ.get("TRITON_INTERPRET") == "1")
            and importlib.util.find_spec("triton") is not None)


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
    """Render rays (N, 3) through ``grid``: rgb (N, C), opacity (N,), depth (N,) (directions of any length: the
    depth is a world distance, ``unit_directions``).

    The grid places the samples (``grid.ray_samples``, stopping early where its
    sampler can), :func:`composite` adds them up. ``generator`` turns on stratified jitter (one uniform offset per
    ray, for training). ``color_features`` (X, Y, Z, C) replaces the grid's
    colour with other raw features, rendered without activation over the
    grid's density (the 3D attention grids use it). ``sparse_grad``: see
    ``VoxelGrid.interpolate``.

    A ReLU field's rays that start farther than its box's diagonal from it are first moved along themselves to it in
    float64 (:func:`_moved_to_the_box`), so a far origin's float32 rounding does not become the samples'.

    Always computes in float32, autocast disabled: cumulative optical depths
    and transmittance products lose too much in bf16/fp16, and mixed dtypes
    would break the scatters. Under autocast the result is the fp32 render.

    Examples:
        >>> grid = VoxelGrid(8, init_density=-1.0)  # empty: every ray sees the background
        >>> out = render_rays(grid, torch.tensor([[0.0, 0, -3]]), torch.tensor([[0.0, 0, 1]]))
        >>> out.rgb.tolist(), out.opacity.tolist()
        ([[1.0, 1.0, 1.0]], [0.0])
    """
    # (Rays that broadcast had rendered as many rays as origins: past the first, blank on the packed path (or an
    # IndexError from its gathers) and read from past the directions by the fused kernel.)
    if origins.ndim != 2 or origins.shape[-1] != 3 or directions.shape != origins.shape:
        raise ValueError(f"origins and directions must be (N, 3) each, one direction per origin, got "
                         f"{tuple(origins.shape)} and {tuple(directions.shape)}")
    with full_precision(origins):
        origins, shift = _moved_to_the_box(grid, origins, directions)  # (before float32 rounds a far origin)
        origins, directions = origins.float(), unit_directions(directions.float())
        device, n_rays = origins.device, origins.shape[0]
        if config.skip_empty and occupancy is None:
            occupancy = grid.occupancy(config.sigma_threshold)
        if generator is not None:
            offsets = torch.rand(n_rays, generator=generator, device=device)
        else:
            offsets = torch.full((n_rays,), 0.5, device=device)
        occupancy = occupancy if config.skip_empty else None
        if occupancy is not None:
            grid.check_occupancy(occupancy)
        channels = 3 if color_features is None else color_features.shape[-1]
        if len(config.background) not in (1, channels):  # (had failed in an expand, naming no setting)
            raise ValueError(f"RenderConfig.background must hold one value or one per rendered channel ({channels}), "
                             f"got {config.background!r}")
        background = torch.as_tensor(config.background, dtype=torch.float32, device=device).expand(channels)
        if config.fused and fused_marcher_applies(grid, origins, directions, color_features, sparse_grad):
            from voxe_core.fused_render import march  # imports Triton

            lattice = grid.ray_lattice(origins, directions, offsets, config.step_ratio, occupancy)
            colour, opacity, depth, samples = march(grid, origins, directions, lattice, occupancy, config.early_stop)
            candidates = lattice.candidates().sum()
            out = _on_background(colour, opacity, depth, background, samples, candidates)
        else:
            samples = grid.ray_samples(origins, directions, offsets, config.step_ratio, occupancy,
                                       config.pass_samples(device), config.early_stop)
            out = composite(samples, grid_field(grid, color_features, sparse_grad), n_rays, background)
        out.depth = torch.where(out.opacity > 1e-6, out.depth + shift, out.depth)  # from the rays' own origins
        return out


def _moved_to_the_box(grid: VoxelGrid, origins: torch.Tensor,
                      directions: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(origins, shift (N,)): the rays of a lattice-sampled grid (the ReLU field) that start farther than its box's
    diagonal from the box, moved along themselves to their entry in float64 by ``shift`` (0 for the others, kept bit
    for bit), before the renderer's float32 (so float64 rays keep their precision).

    The origin's distance from the box decides, not the entry's: a camera at radius 4.03 enters a 3-unit box's far
    corners up to 5.5 units away, past its diagonal, and those rays had been moved, their renders changed by rounding.

    Such a grid samples only inside its box, so the move changes its samples by rounding alone, but in float32 a far
    origin's rounding had become theirs: at 1e7 units (float32's spacing 1) the slab test's path through a 3-unit box
    was ~2 units off, the points as far, the opacity 0.3 off, and at 3e7 rays through the box missed it."""
    if not grid.lattice_sampled:  # a scene grid samples from the camera on (its near bins): left as they are
        return origins, torch.zeros(origins.shape[0], device=origins.device)
    wide = origins.double(), unit_directions(directions.double())  # (float64 rays: as precise as they came)
    box = grid.bbox_min.double(), grid.bbox_max.double()
    near, _ = ray_box_intersection(*wide, *box)
    moved = (wide[0] - wide[0].clamp(*box)).norm(dim=-1) > grid.box_diagonal
    shift = torch.where(moved, near, 0.0)
    at_least_float32 = torch.promote_types(origins.dtype, torch.float32)  # (half rays had lost 1e-3 at the box)
    return torch.where(moved[:, None], (wide[0] + shift[:, None] * wide[1]).to(at_least_float32), origins), shift.float()


def composite(groups: Iterable[RaySamples], values: Field, n_rays: int, background: torch.Tensor) -> RenderOutput:
    """Alpha-composite packed samples of ``n_rays`` rays on ``background`` (C,): rgb (N, C), opacity, depth (N,).

    Weights T·(1 − exp(−σδ)) in float64, the transmittance T from per-ray float64
    prefix sums; ``values`` gives (σ, colour) at the samples' points.

    Examples:
        >>> samples = RaySamples(torch.tensor([0, 0]), torch.tensor([1.0, 2.0]), torch.ones(2), torch.zeros(2, 3))
        >>> red = lambda p: (torch.full((len(p),), 1e9), torch.tensor([[1.0, 0, 0]]).expand(len(p), 3))
        >>> composite([samples], red, 1, torch.ones(3)).rgb.tolist()  # the first sample hides the rest
        [[1.0, 0.0, 0.0]]
    """
    device = background.device
    accumulated = torch.zeros(n_rays, background.numel(), device=device)
    opacity = torch.zeros(n_rays, device=device)
    depth = torch.zeros(n_rays, device=device)
    evaluated = candidates = 0
    for group in groups:
        candidates += group.candidates
        evaluated += group.probed
        if group.ray.numel() == 0:
            continue
        evaluated += group.ray.numel()
        sigma, colour = values(group.points)
        # In float32 whatever the field's dtype: a float64 grid's samples had reached the float32 sums as float64
        # (index_add refuses mixed dtypes); a half grid's are promoted by delta already.
        optical = optical_depth(sigma.float(), group.delta.float()).double()
        # Weights in float64 until the sums: each optical depth's gradient, T·colour less what the samples behind it
        # gave, is then a difference of float64 terms (of float32 ones, it had been off by 34 % behind a ray's
        # transmittance of 2e-9, some of it of the wrong sign), as in the fused marcher.
        weights = (transmittance(optical, group.ray) * (-torch.expm1(-optical))).float()
        accumulated = accumulated.index_add(0, group.ray, weights[:, None] * colour.float())
        opacity = opacity.index_add(0, group.ray, weights)
        depth = depth.index_add(0, group.ray, weights * group.t.float())
    return _on_background(accumulated, opacity, depth, background, evaluated, candidates)


def _on_background(accumulated: torch.Tensor, opacity: torch.Tensor, depth: torch.Tensor, background: torch.Tensor,
                   samples, candidates) -> RenderOutput:
    """The render from its sums over the samples, Σw·colour (N, C), Σw and Σw·t (N,): composited on ``background``
    (C,), the depth made an expectation (0 where the ray hit nothing)."""
    rgb = accumulated + (1.0 - opacity)[:, None] * background
    expected_depth = torch.where(opacity > 1e-6, depth / opacity.clamp_min(1e-6), torch.zeros_like(depth))
    return RenderOutput(rgb, opacity, expected_depth, samples, candidates)


@torch.no_grad()
def render_image(
    grid: VoxelGrid,
    cameras: Cameras,
    index: int,
    config: RenderConfig = RenderConfig(),
    occupancy: Occupancy | None = None,
) -> RenderOutput:
    """Whole image (H, W, 3) from camera ``index``, rendered in ray chunks to bound memory (float32, as render_rays).

    The rays are made on the grid's device, wherever ``cameras`` are (stages build their poses on the host).
    """
    if config.skip_empty and occupancy is None:
        occupancy = grid.occupancy(config.sigma_threshold)
    cameras = cameras.to(grid.bbox_min.device)
    with full_precision(cameras.c2w):
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
        int(sum(p.samples for p in parts)),
        int(sum(p.candidates for p in parts)),
    )
