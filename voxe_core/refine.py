"""Spatial refinement of local edits (paper §3.3, SPEC §3): 3D cross-attention grids, graph cut, merge.

Pipeline (:func:`refine`):

1. :func:`attention_maps_2d` renders views of the edited grid G_e from random
   upper-hemisphere poses and asks the diffusion model for per-token
   cross-attention maps (one UNet pass at t = 200). The *edit* map is the mean
   over the edit words' tokens (every sub-token of every occurrence), the
   *object* map the element-wise max over every other content token of the
   prompt (start, end and padding tokens excluded). Each map is smoothed with a
   small Gaussian on the attention lattice (in its own pixels, on whatever
   device it lives), upsampled bilinearly to the render size and min-max
   normalised to [0, 1].
2. :func:`fit_attention_grids` lifts both sets of maps into two scalar grids
   sharing G_e's frozen density. A field's value is rendered **raw** (no
   activation), as a grey value composited over a black background, and fitted
   by L1 to the maps plus ``tv_weight`` · TV, with Adam.

   Initial value: the authors initialise the feature to −20. Rendered raw, an
   untrained −20 grid renders −20·opacity, far outside the [0, 1] range of the
   targets: Adam at lr 0.035 moves a value about lr per step, so ~570 of the
   1500 steps would be spent climbing back into range. Rendered through a
   sigmoid the −20 start is black but its gradient is sigmoid'(−20) ≈ 2e-9,
   below Adam's epsilon, so it barely moves at all. We therefore render the raw
   value (the fit is then convex: a linear render under an L1 loss) and
   initialise at 0, which *is* the background value: an untrained field renders
   exactly "no attention", and voxels no view ever sees keep 0 in both grids,
   i.e. probability 1/2 each (no evidence either way; the graph cut's
   smoothness term labels them from their neighbours). ``init_value=-20``
   reproduces the authors' start.
3. Per voxel, P_e, P_obj = softmax(edit value, object value), computed in
   log space (finite for any finite logits, e.g. ±1e4).
4. :func:`graph_cut` labels the occupied voxels of G_e (vertices whose
   activated density makes a voxel-length at least ``node_alpha`` opaque) by
   Boykov–Kolmogorov max-flow (PyMaxflow), built vectorised: unary costs
   −log P of the label, seeds tied to their terminal with a capacity larger
   than any finite cut, and 6-neighbour pairwise weights
   λ·exp(−‖c_p − c_q‖² / 2σ²) on G_e's activated colours along all three axes.
5. :func:`merge`: G_r = M·G_e + (1 − M)·G_i voxel-wise on all four features;
   unmasked voxels are bit-identical to G_i.

Storage: :func:`save_mask` keeps only the flat indices (int32) of the set
voxels plus the grid shape; :func:`save_probabilities` keeps the probability
grids at the occupied voxels only (indices + values). Both are versioned
safetensors files (no pickle).
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, field
from typing import Literal, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from voxe_core.cameras import Cameras, camera_rays, random_hemisphere_poses
from voxe_core.constants import NERF_SYNTHETIC_FOV_X
from voxe_core.grid import Occupancy, VoxelGrid
from voxe_core.guidance import ATTENTION_MODEL_ID, DEFAULT_ATTENTION_TIMESTEP, edit_prompt
from voxe_core.progress import Callbacks, Progress
from voxe_core.render import RenderConfig, ray_box_intersection, render_image, render_rays
from voxe_core.tensorio import FormatError, load_tensors, save_tensors

MASK_FORMAT_VERSION = 1
PROBABILITY_FORMAT_VERSION = 1


class SegmentationError(ValueError):
    """The graph cut cannot run: nothing occupied, no seeds, or mismatched inputs."""


@dataclass
class RefineConfig:
    """Defaults are the paper's / the authors' (SPEC §3) unless marked otherwise."""

    # 2D cross-attention maps
    timestep: int = DEFAULT_ATTENTION_TIMESTEP  # t = 200 of 1000
    resolution_filter: int | None = 16  # keep only the 16x16-query cross-attention layers
    smoothing_sigma: float = 1.0  # Gaussian std in pixels of the attention map (16x16); 0 = none
    edit_token_reduce: Literal["mean", "max"] = "mean"  # how the edit words' sub-tokens combine
    render_size: int = 266  # pixels of the renders (paper: 800 px / 3)
    views: int = 32  # random upper-hemisphere poses (ours; the authors use the training views)
    fov_x: float = NERF_SYNTHETIC_FOV_X
    # 3D attention grids
    iterations: int = 1500
    lr: float = 0.035
    tv_weight: float = 0.01
    init_value: float = 0.0  # see the module docstring; the authors use -20
    rays_per_step: int = 8192
    render: RenderConfig = field(default_factory=lambda: RenderConfig(background=(0.0,)))
    # graph cut
    edit_seeds: int = 300
    object_seeds: int = 200
    sigma: float = 0.1  # colour scale of the pairwise weights
    smoothness: float = 5.0  # lambda
    node_alpha: float = 0.01  # a vertex is a node when one voxel of its density is this opaque
    # misc
    seed: int = 0
    attention_model: str = ATTENTION_MODEL_ID

    def __post_init__(self):
        if self.edit_token_reduce not in ("mean", "max"):
            raise ValueError(f"edit_token_reduce must be 'mean' or 'max', got {self.edit_token_reduce!r}")
        for name in ("render_size", "views", "rays_per_step"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        if self.iterations < 0 or self.edit_seeds < 0 or self.object_seeds < 0:
            raise ValueError("iterations and seed counts must be non-negative")
        if self.sigma <= 0 or self.smoothness < 0 or self.smoothing_sigma < 0:
            raise ValueError("sigma must be positive; smoothness and smoothing_sigma non-negative")
        if not 0.0 < self.node_alpha < 1.0:
            raise ValueError(f"node_alpha must lie in (0, 1), got {self.node_alpha}")


@dataclass
class GraphCutStats:
    nodes: int
    edges: int
    edit_seeds: int
    object_seeds: int
    edit_voxels: int
    flow: float
    build_s: float
    solve_s: float
    notes: list[str] = field(default_factory=list)


@dataclass
class RefineResult:
    refined_grid: VoxelGrid
    mask: torch.Tensor  # (X, Y, Z) bool, True = take G_e
    edit_probability: torch.Tensor  # (X, Y, Z) float32
    object_probability: torch.Tensor  # (X, Y, Z) float32
    edit_field: torch.Tensor  # (X, Y, Z, 1) fitted raw values
    object_field: torch.Tensor  # (X, Y, Z, 1)
    cameras: Cameras | None = None  # the poses the maps were taken from
    edit_maps: torch.Tensor | None = None  # (N, H, W) the 2D maps the grids were fitted to
    object_maps: torch.Tensor | None = None
    stats: GraphCutStats | None = None
    info: dict = field(default_factory=dict)


# --------------------------------------------------------------------------- 2D maps


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


def attention_cameras(config: RefineConfig, generator: torch.Generator | None = None) -> Cameras:
    """``config.views`` random upper-hemisphere cameras (SPEC §0) of ``render_size`` pixels."""
    generator = generator or torch.Generator().manual_seed(config.seed)
    c2w, _, _ = random_hemisphere_poses(config.views, generator)
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


# --------------------------------------------------------------------------- 3D grids


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


def _occupied_slices(occupancy: Occupancy) -> tuple[slice, slice, slice]:
    """Vertex index ranges of the occupied cells' box (the only part of a field a render can see)."""
    idx = occupancy.cells.nonzero()
    lo, hi = idx.min(0).values, idx.max(0).values + 2  # cells [i, i+1] use vertices i and i+1
    return tuple(slice(int(a), int(b)) for a, b in zip(lo, hi))


def fit_attention_grids(
    grid: VoxelGrid,
    cameras: Cameras,
    edit_maps: torch.Tensor,
    object_maps: torch.Tensor,
    config: RefineConfig = RefineConfig(),
    callbacks: Callbacks = Callbacks(),
) -> tuple[torch.Tensor, torch.Tensor]:
    """Lift 2D maps to two scalar grids ``(X, Y, Z, 1)`` over ``grid``'s frozen density.

    Both fields are fitted together (one render of a 2-channel field per step)
    on ``rays_per_step`` random pixels of all views, rendered raw over a black
    background, with L1 + ``tv_weight``·TV (TV over the occupied box), Adam at
    ``lr``; stratified jitter along the rays. Pixels whose ray misses the
    occupied box render 0 whatever the field holds and are left out.
    Deterministic for ``config.seed``; reports ``Progress("attention_grids")``
    every step and may be cancelled between steps.
    """
    n_views, height, width = edit_maps.shape
    if object_maps.shape != edit_maps.shape:
        raise ValueError(f"edit maps {tuple(edit_maps.shape)} and object maps {tuple(object_maps.shape)} differ")
    if n_views != len(cameras) or (height, width) != (cameras.height, cameras.width):
        raise ValueError(
            f"{n_views} maps of {height}x{width} do not match {len(cameras)} cameras of {cameras.height}x{cameras.width}"
        )
    device = grid.bbox_min.device
    frozen = frozen_density(grid)
    occupancy = frozen.occupancy(config.render.sigma_threshold)
    if occupancy.empty:
        raise SegmentationError("the edited grid has no occupied voxels: there is nothing to attach attention to")
    origins, directions = all_camera_rays(cameras.to(device))
    targets = torch.stack([edit_maps, object_maps], -1).reshape(-1, 2).to(device=device, dtype=torch.float32)
    near, far = ray_box_intersection(origins, directions, occupancy.bbox_min.to(device), occupancy.bbox_max.to(device))
    keep = (far > near).nonzero().squeeze(-1)
    origins, directions, targets = origins[keep], directions[keep], targets[keep]

    values = torch.full((*grid.resolution, 2), float(config.init_value), device=device, requires_grad=True)
    optimizer = torch.optim.Adam([values], lr=config.lr)
    box = _occupied_slices(occupancy)
    generator = torch.Generator(device=device).manual_seed(config.seed)
    n_rays = origins.shape[0]
    for iteration in range(config.iterations):
        callbacks.check_cancel("attention_grids")
        batch = torch.randint(0, n_rays, (min(config.rays_per_step, n_rays),), generator=generator, device=device)
        out = render_rays(frozen, origins[batch], directions[batch], config.render, occupancy, generator,
                          color_features=values)
        l1 = (out.rgb - targets[batch]).abs().mean()
        tv = total_variation(values[box])
        loss = l1 + config.tv_weight * tv
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        callbacks.progress(Progress("attention_grids", iteration + 1, config.iterations,
                                    {"l1": float(l1.detach()), "tv": float(tv.detach())}, {"stage": "attention grids"}))
    values = values.detach()
    return values[..., 0:1].contiguous(), values[..., 1:2].contiguous()


# --------------------------------------------------------------------------- graph cut


def _scalar_field(values: torch.Tensor, shape: tuple[int, int, int], name: str) -> torch.Tensor:
    if values.dim() == 4 and values.shape[-1] == 1:
        values = values[..., 0]
    if tuple(values.shape) != tuple(shape):
        raise SegmentationError(f"{name} of shape {tuple(values.shape)} does not fit the grid {tuple(shape)}")
    return values


def log_probabilities(edit_field: torch.Tensor, object_field: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(log P_e, log P_obj) = log-softmax of the two values per voxel, in float64 (finite for any finite input)."""
    e = edit_field.double()
    o = object_field.double()
    if e.dim() == 4 and e.shape[-1] == 1:
        e, o = e[..., 0], o[..., 0]
    logs = torch.log_softmax(torch.stack([e, o]), dim=0)
    return logs[0], logs[1]


def probabilities(edit_field: torch.Tensor, object_field: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(P_e, P_obj) float32 per voxel: softmax of the two fields' values."""
    log_e, log_o = log_probabilities(edit_field, object_field)
    return log_e.exp().float(), log_o.exp().float()


def node_mask(grid: VoxelGrid, node_alpha: float = 0.01) -> torch.Tensor:
    """(X, Y, Z) bool: vertices whose activated density would make one voxel length ``node_alpha`` opaque.

    That is σ·Δ ≥ −ln(1 − node_alpha) with Δ the smallest voxel edge, so the
    test means the same at every resolution and box size.
    """
    sigma = grid.activate_density(grid.features[..., 0].detach())
    threshold = -math.log1p(-node_alpha) / float(grid.voxel_size.min())
    return sigma >= threshold


def _top_seeds(score: np.ndarray, candidates: np.ndarray, count: int) -> np.ndarray:
    """Indices of the ``count`` highest ``score`` among ``candidates`` (ties: lower index first)."""
    idx = np.flatnonzero(candidates)
    if idx.size == 0 or count <= 0:
        return idx[:0]
    order = np.lexsort((idx, -score[idx]))  # primary: score descending, then index ascending
    return idx[order[:count]]


def graph_cut_detailed(
    grid: VoxelGrid,
    edit_field: torch.Tensor,
    object_field: torch.Tensor,
    config: RefineConfig = RefineConfig(),
) -> tuple[torch.Tensor, GraphCutStats]:
    """Binary edit mask (X, Y, Z) of the occupied voxels of ``grid`` (G_e), and what the cut did.

    Energy: Σ_p −log P_{l_p}(p) + λ Σ_{p~q, l_p≠l_q} exp(−‖c_p − c_q‖²/2σ²),
    minimised exactly by max-flow. Seeds: the ``edit_seeds`` voxels of highest
    P_e among those with P_e > 1/2 are tied to the edit terminal, the
    ``object_seeds`` of highest P_obj among those with P_obj > 1/2 to the
    object terminal (so the two sets never overlap); when fewer voxels qualify
    the available ones are used and ``stats.notes`` (and a warning) says so.
    Raises :class:`SegmentationError` when no voxel is occupied or when no
    voxel qualifies as a seed of either label (the grids carry no preference
    anywhere, e.g. all-equal probabilities).
    """
    import maxflow

    t0 = time.perf_counter()
    shape = grid.resolution
    edit_field = _scalar_field(edit_field, shape, "edit_field")
    object_field = _scalar_field(object_field, shape, "object_field")
    nodes = node_mask(grid, config.node_alpha).cpu()
    n = int(nodes.sum())
    if n == 0:
        raise SegmentationError(
            f"no occupied voxels: the edited grid's density never makes a voxel {config.node_alpha:.0%} opaque, "
            "so there is nothing to segment (is it an empty or untrained grid?)"
        )
    log_e, log_o = log_probabilities(edit_field.detach().cpu(), object_field.detach().cpu())
    nodes_np = nodes.numpy()
    log_e = log_e.numpy()[nodes_np]
    log_o = log_o.numpy()[nodes_np]
    p_e, p_o = np.exp(log_e), np.exp(log_o)

    notes: list[str] = []
    edit_seeds = _top_seeds(p_e, p_e > 0.5, config.edit_seeds)
    object_seeds = _top_seeds(p_o, p_o > 0.5, config.object_seeds)
    if edit_seeds.size + object_seeds.size == 0:
        raise SegmentationError(
            f"no seeds: none of the {n} occupied voxels is more likely edit than object or the reverse "
            "(the attention grids are equal everywhere: too few fitting iterations, or maps that do not tell "
            "the edit from the object), so the edit region is undefined"
        )
    for label, got, wanted in (("edit", edit_seeds.size, config.edit_seeds), ("object", object_seeds.size, config.object_seeds)):
        if got < wanted:
            notes.append(f"only {got} of {wanted} {label} seeds: {got} occupied voxels are more likely {label}")

    # unary terms: the source side is "edit", so the source edge is cut (paid) when p ends up "object"
    cap_source = -log_o
    cap_sink = -log_e

    # pairwise terms along all three axes between occupied neighbours
    ids = np.full(shape, -1, dtype=np.int64)
    ids[nodes_np] = np.arange(n)
    colors = torch.sigmoid(grid.features[..., 1:4].detach().float()).cpu().numpy()
    two_sigma2 = 2.0 * config.sigma**2
    heads, tails, weights = [], [], []
    for axis in range(3):
        lo = [slice(None)] * 3
        hi = [slice(None)] * 3
        lo[axis], hi[axis] = slice(0, -1), slice(1, None)
        lo, hi = tuple(lo), tuple(hi)
        pair = nodes_np[lo] & nodes_np[hi]
        if not pair.any():
            continue
        diff = colors[lo][pair] - colors[hi][pair]
        heads.append(ids[lo][pair])
        tails.append(ids[hi][pair])
        weights.append(config.smoothness * np.exp(-(diff * diff).sum(-1) / two_sigma2))
    i = np.concatenate(heads) if heads else np.zeros(0, np.int64)
    j = np.concatenate(tails) if tails else np.zeros(0, np.int64)
    w = np.concatenate(weights) if weights else np.zeros(0)

    # "infinite" seed capacity: more than every finite capacity together, so no finite cut severs a seed
    big = float(cap_source.sum() + cap_sink.sum() + 2.0 * w.sum() + 1.0)
    cap_source[edit_seeds], cap_sink[edit_seeds] = big, 0.0
    cap_source[object_seeds], cap_sink[object_seeds] = 0.0, big

    graph = maxflow.Graph[float](n, max(1, i.size))
    node_ids = graph.add_nodes(n)
    if i.size:
        graph.add_edges(i, j, w, w)
    graph.add_grid_tedges(np.asarray(node_ids), cap_source, cap_sink)
    build_s = time.perf_counter() - t0
    t1 = time.perf_counter()
    flow = graph.maxflow()
    in_sink = graph.get_grid_segments(np.asarray(node_ids))  # True: object side
    solve_s = time.perf_counter() - t1

    mask = np.zeros(shape, dtype=bool)
    mask[nodes_np] = ~in_sink
    for note in notes:
        warnings.warn(note, stacklevel=2)
    stats = GraphCutStats(
        nodes=n, edges=int(i.size), edit_seeds=int(edit_seeds.size), object_seeds=int(object_seeds.size),
        edit_voxels=int((~in_sink).sum()), flow=float(flow), build_s=build_s, solve_s=solve_s, notes=notes,
    )
    return torch.from_numpy(mask).to(grid.bbox_min.device), stats


def graph_cut(
    grid: VoxelGrid, edit_field: torch.Tensor, object_field: torch.Tensor, config: RefineConfig = RefineConfig()
) -> torch.Tensor:
    """The edit mask (X, Y, Z) bool of :func:`graph_cut_detailed`."""
    return graph_cut_detailed(grid, edit_field, object_field, config)[0]


# --------------------------------------------------------------------------- merge


def check_compatible(initial_grid: VoxelGrid, edited_grid: VoxelGrid) -> None:
    if initial_grid.resolution != edited_grid.resolution:
        raise ValueError(f"the initial grid is {initial_grid.resolution} but the edited grid {edited_grid.resolution}")
    if not (torch.equal(initial_grid.bbox_min.cpu(), edited_grid.bbox_min.cpu())
            and torch.equal(initial_grid.bbox_max.cpu(), edited_grid.bbox_max.cpu())):
        raise ValueError("the initial and edited grids span different boxes")


@torch.no_grad()
def merge(initial_grid: VoxelGrid, edited_grid: VoxelGrid, mask: torch.Tensor) -> VoxelGrid:
    """G_r = M·G_e + (1 − M)·G_i on all features, as a selection: unmasked voxels are G_i's exact bits."""
    check_compatible(initial_grid, edited_grid)
    if tuple(mask.shape) != tuple(initial_grid.resolution):
        raise ValueError(f"mask of shape {tuple(mask.shape)} does not fit the grids {initial_grid.resolution}")
    m = mask.to(device=initial_grid.features.device, dtype=torch.bool)[..., None]
    merged = torch.where(m, edited_grid.features.detach().to(initial_grid.features.device), initial_grid.features.detach())
    return initial_grid.like(merged)


# --------------------------------------------------------------------------- composition


def refine(
    initial_grid: VoxelGrid,
    edited_grid: VoxelGrid,
    prompt: str,
    edit_words: Sequence[str],
    guidance,
    config: RefineConfig = RefineConfig(),
    callbacks: Callbacks = Callbacks(),
) -> RefineResult:
    """The whole of SPEC §3: maps -> attention grids -> graph cut -> merge.

    ``prompt`` is the edit's text; the "a render of" prefix is added when
    missing (as the edit stage prompts the model). ``edit_words`` name the
    edit (words or phrases of the prompt, e.g. ``["sunglasses"]`` or
    ``["party hat"]``).
    """
    check_compatible(initial_grid, edited_grid)
    text = edit_prompt(prompt)
    token_groups(guidance, text, edit_words)  # fail on a bad word before rendering anything
    cameras = attention_cameras(config)
    edit_maps, object_maps = attention_maps_2d(guidance, edited_grid, cameras, text, edit_words, config, callbacks)
    edit_field, object_field = fit_attention_grids(edited_grid, cameras, edit_maps, object_maps, config, callbacks)
    callbacks.check_cancel("graph_cut")
    mask, stats = graph_cut_detailed(edited_grid, edit_field, object_field, config)
    p_e, p_o = probabilities(edit_field, object_field)
    refined = merge(initial_grid, edited_grid, mask)
    callbacks.progress(Progress("graph_cut", 1, 1, info={"stage": "graph cut", "nodes": stats.nodes,
                                                        "edit_voxels": stats.edit_voxels}))
    return RefineResult(
        refined, mask, p_e, p_o, edit_field, object_field, cameras, edit_maps, object_maps, stats,
        info={"prompt": text, "edit_words": list(edit_words) if not isinstance(edit_words, str) else [edit_words]},
    )


# --------------------------------------------------------------------------- renders


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
    features = features.to(grid.bbox_min.device).float()
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
    from voxe_core.export import render_views

    images = render_views(grid, cameras)
    coverage = render_feature_views(grid, cameras, mask.float()[..., None], background=(0.0,))
    a = (strength * coverage).clamp(0.0, 1.0)
    return images * (1.0 - a) + a * torch.tensor(tint, dtype=images.dtype)


# --------------------------------------------------------------------------- storage


def save_mask(path, mask: torch.Tensor, meta: dict | None = None) -> None:
    """Sparse mask file: flat indices (int32, C order) of the set voxels plus the grid shape."""
    mask = mask.detach().cpu().bool()
    if mask.dim() != 3:
        raise ValueError(f"expected an (X, Y, Z) mask, got shape {tuple(mask.shape)}")
    if mask.numel() >= 2**31:
        raise ValueError("grid too large for int32 voxel indices")
    indices = mask.reshape(-1).nonzero().squeeze(-1).to(torch.int32)
    save_tensors(path, {"indices": indices, "shape": torch.tensor(mask.shape, dtype=torch.int64)},
                 kind="edit_mask", version=MASK_FORMAT_VERSION, meta={"set_voxels": int(indices.numel()), **(meta or {})})


def _indices_and_shape(tensors: dict, path) -> tuple[torch.Tensor, tuple[int, int, int]]:
    if "indices" not in tensors or "shape" not in tensors:
        raise FormatError(f"{path}: missing 'indices' or 'shape'")
    shape = tuple(int(s) for s in tensors["shape"].tolist())
    indices = tensors["indices"].long().reshape(-1)
    if len(shape) != 3 or min(shape) < 1:
        raise FormatError(f"{path}: bad grid shape {shape}")
    total = shape[0] * shape[1] * shape[2]
    if indices.numel() and (int(indices.min()) < 0 or int(indices.max()) >= total):
        raise FormatError(f"{path}: voxel indices outside a grid of {shape}")
    return indices, shape


def load_mask(path) -> torch.Tensor:
    """The (X, Y, Z) bool mask written by :func:`save_mask`."""
    tensors, _ = load_tensors(path, kind="edit_mask", max_version=MASK_FORMAT_VERSION)
    indices, shape = _indices_and_shape(tensors, path)
    mask = torch.zeros(math.prod(shape), dtype=torch.bool)
    mask[indices] = True
    return mask.reshape(shape)


def save_probabilities(path, edit_probability: torch.Tensor, object_probability: torch.Tensor, where: torch.Tensor) -> None:
    """Probability grids stored only at the voxels ``where`` (the graph's nodes): indices + float32 values."""
    where = where.detach().cpu().bool()
    flat = where.reshape(-1).nonzero().squeeze(-1)
    tensors = {
        "indices": flat.to(torch.int32),
        "shape": torch.tensor(where.shape, dtype=torch.int64),
        "edit": edit_probability.detach().cpu().float().reshape(-1)[flat],
        "object": object_probability.detach().cpu().float().reshape(-1)[flat],
    }
    save_tensors(path, tensors, kind="attention_probabilities", version=PROBABILITY_FORMAT_VERSION,
                 meta={"stored_voxels": int(flat.numel())})


def load_probabilities(path) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """(edit, object, where): dense (X, Y, Z) float32 grids, 0 outside ``where`` (the stored voxels)."""
    tensors, _ = load_tensors(path, kind="attention_probabilities", max_version=PROBABILITY_FORMAT_VERSION)
    indices, shape = _indices_and_shape(tensors, path)
    out = []
    for name in ("edit", "object"):
        values = tensors.get(name)
        if values is None or values.numel() != indices.numel():
            raise FormatError(f"{path}: '{name}' values do not match the stored indices")
        dense = torch.zeros(math.prod(shape))
        dense[indices] = values.float()
        out.append(dense.reshape(shape))
    where = torch.zeros(math.prod(shape), dtype=torch.bool)
    where[indices] = True
    return out[0], out[1], where.reshape(shape)


__all__ = [
    "GraphCutStats",
    "RefineConfig",
    "RefineResult",
    "SegmentationError",
    "attention_cameras",
    "attention_maps_2d",
    "combine_token_maps",
    "fit_attention_grids",
    "gaussian_blur2d",
    "graph_cut",
    "graph_cut_detailed",
    "load_mask",
    "load_probabilities",
    "log_probabilities",
    "merge",
    "node_mask",
    "normalize_maps",
    "postprocess_maps",
    "probabilities",
    "refine",
    "render_attention",
    "render_feature_views",
    "render_mask_overlay",
    "save_mask",
    "save_probabilities",
    "token_groups",
]
