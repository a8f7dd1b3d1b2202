"""The ReLU-field voxel grid: 1 density + 3 colour features per vertex (SH degree 0), and where its rays are sampled.

Features are raw (pre-activation) values on the vertices of a regular grid
spanning an axis-aligned box; samples interpolate trilinearly, then activate
(density: ReLU as in the paper, or the authors' softplus; colour: sigmoid).
Because interpolation happens before the ReLU, a cell whose eight corners are
all <= 0 has exactly zero density everywhere inside: the occupancy structure
built from corner maxima skips empty space without changing the render.

Sampling is the grid's (as nerfacc's occupancy-grid estimator), compositing the
renderer's (``voxe_core.render``): :meth:`VoxelGrid.ray_samples` places samples
evenly (``step_ratio`` voxels apart) along each ray's intersection with the box,
on one lattice per ray anchored at the box, keeps only those in occupied cells
when given an occupancy, and yields them packed ray by ray
(:class:`RaySamples`); :meth:`VoxelGrid.ray_lattice` says where each ray's lattice
lies, which the fused marcher (``voxe_core.fused_render``) walks itself. Another
backbone (``voxe_core.scene_grid.SceneGrid``) overrides where the samples go and
nothing else (its contracted bins are no lattice: ``lattice_sampled`` False).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar, Iterator, Literal, NamedTuple

import torch
import torch.nn.functional as F

from voxe_core.cameras import Cameras
from voxe_core.devices import full_precision
from voxe_core.gridfile import (
    DEFAULT_MARGIN, GRID_FORMAT_VERSION, MIN_FLOAT_BITS, float_dtype_problem, payload_bytes, sparse_tensors,
)
from voxe_core.tensorio import save_tensors
from voxe_core.volrend import RaySamples, optical_depth, transmittance

GRID_KIND = "voxel_grid"  # the tensorio kind of every saved grid, whatever its backbone
DEFAULT_BOX = ((-1.5, -1.5, -1.5), (1.5, 1.5, 1.5))
DEFAULT_SIGMA_THRESHOLD = 1e-3  # density skipped as empty, measured in the default box (``VoxelGrid.occupancy``)
Activation = Literal["relu", "softplus"]
SEGMENT = 16  # lattice samples per skipping segment (see _ray_segments)
MAX_DIAGONAL_VOXELS = 10_000
"""The most smallest voxel edges a box's diagonal may span (a 160³ cube's spans 276, a 512³ one's 886). The sampler
steps by the smallest edge: a box 2e-6 thin along one axis of 16 cells took ~80 s a ray along it, 1e-12 thin rendered
blank."""

_CORNERS = torch.tensor(
    [[0, 0, 0], [0, 0, 1], [0, 1, 0], [0, 1, 1], [1, 0, 0], [1, 0, 1], [1, 1, 0], [1, 1, 1]]
)


def default_density_scale(bbox_min, bbox_max) -> float:
    """The authors' raw-density multiplier, 100·sqrt(3)/box diagonal (≈33.3 for the 3-unit box).

    It lets Adam at lr 0.03 reach opaque densities in tens of steps, and keeps
    optical depth per voxel independent of the scene's unit.
    """
    diagonal = math.dist(tuple(bbox_min), tuple(bbox_max))
    return 100.0 * math.sqrt(3.0) / diagonal


def _weigh_corners(weights: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """``Σ_k weights[n, k] · values[n, k]``: (N, K) and (N, K, C) -> (N, C), as N (1 × K) @ (K × C) matrix products
    (on this CPU a broadcast multiply and sum instead made the edit render's forward 1.42x slower on an object and
    1.44x on fog; bench/interpolation.py times both, on a device too). ``bmm`` itself: the einsum it was computes
    the same bits through 8 more view operations, 8 more in its backward."""
    return torch.bmm(weights.unsqueeze(1), values).squeeze(1)


class _WeightedGather(torch.autograd.Function):
    """``Σ_k weights[n, k] · table[index[n, k]]``: (M, C) table, (N, K) index and weights -> (N, C).

    The forward is ``F.embedding`` and :func:`_weigh_corners`, as before. The backward adds into the table with one
    ``index_add_`` where ``F.embedding``'s dense backward makes one small add per index on the CPU (each thread
    scanning all N·K of them for its rows) and sorts them on CUDA: on this CPU the edit render's backward takes
    0.56x the time on an object and 0.43x on fog, for the same bits (bench/interpolation.py). On CUDA the atomic
    adds run in any order, so the gradient varies at float32 rounding from run to run (as the compositing's
    ``index_add`` already did) unless ``torch.use_deterministic_algorithms`` is on. The weights get their gradient
    too (first and second order, in their own dtype), though the renderer's carry none.

    Examples:
        >>> table = torch.tensor([[1.0], [10.0]], requires_grad=True)
        >>> out = _WeightedGather.apply(table, torch.tensor([[0, 1]]), torch.tensor([[0.25, 0.75]]))
        >>> out.sum().backward(); out.tolist(), table.grad.flatten().tolist()
        ([[7.75]], [0.25, 0.75])
    """

    @staticmethod
    def forward(ctx, table: torch.Tensor, index: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
        ctx.save_for_backward(index, weights, table if ctx.needs_input_grad[2] else None)
        ctx.table_shape, ctx.table_dtype = table.shape, table.dtype
        return _weigh_corners(weights, F.embedding(index, table).to(weights.dtype))

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        index, weights, table = ctx.saved_tensors
        grad_table = grad_weights = None
        if ctx.needs_input_grad[0]:
            # Summed in float32 at least, then rounded once: a half table's vertices, each the sum of many samples'
            # shares, had been added up in its own precision.
            wide = torch.promote_types(ctx.table_dtype, torch.float32)
            rows = (weights[..., None] * grad[:, None, :]).to(wide).reshape(-1, ctx.table_shape[-1])
            grad_table = grad.new_zeros(ctx.table_shape, dtype=wide).index_add_(0, index.reshape(-1), rows)
            grad_table = grad_table.to(ctx.table_dtype)
        if ctx.needs_input_grad[2]:
            values = F.embedding(index, table).to(weights.dtype)
            grad_weights = torch.bmm(values, grad.to(weights.dtype).unsqueeze(-1)).squeeze(-1)
        return grad_table, None, grad_weights


def unit_directions(directions: torch.Tensor) -> torch.Tensor:
    """Ray directions (N, 3) scaled to unit length, so path lengths and depths are world distances.

    Directions within 1e-6 of unit length (camera rays) are kept bit for bit; zero and NaN ones stay as given
    (no ray). A direction's length had scaled every optical depth by it (twice the length: half the opacity),
    and one of 1e-8 laid 10^8 samples on its ray. Each is divided by its largest component first, so its squares
    neither underflow nor overflow float32: a direction 1e-23 long had come out 1e7 long, one 1e-38 long 1e-8
    (10^8 samples again), and one 1e20 long the zero direction, no ray.

    Examples:
        >>> unit_directions(torch.tensor([[2.0, 0, 0], [0, 0, 0], [0, 0.6, 0.8]])).tolist()
        [[1.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.6000000238418579, 0.800000011920929]]
    """
    largest = directions.abs().amax(dim=-1, keepdim=True)
    scaled = directions / torch.where(largest > 0, largest, torch.ones_like(largest))
    norm = scaled.norm(dim=-1, keepdim=True)
    unit = scaled / torch.where(norm > 0, norm, torch.ones_like(norm))
    return torch.where((norm * largest - 1.0).abs() > 1e-6, unit, directions)


def ray_box_intersection(
    origins: torch.Tensor, directions: torch.Tensor, box_min: torch.Tensor, box_max: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Slab test of rays (N, 3) against a box (3,): (t_near, t_far), each (N,), t_near clamped at 0 for cameras inside.

    Misses, non-finite rays and zero-length directions get t_far <= t_near. Axis-parallel rays use a
    signed tiny reciprocal instead of dividing by zero. The box is closed: a ray lying in one of its faces (a zero
    direction component whose origin is on the lower or the upper face along that axis) meets it, as the face's
    points are inside to :meth:`VoxelGrid.query`. Boxes (B, 3) give (B, N) each, the rays' own work done once
    (``box_min`` and ``box_max`` of one shape and dtype: they are stacked). Half-precision rays and boxes are tested
    in float32 (the ends come back in it).

    Examples:
        >>> near, far = ray_box_intersection(torch.tensor([[0.0, 0, -3]]), torch.tensor([[0.0, 0, 1]]),
        ...                                  -torch.ones(3), torch.ones(3))
        >>> near.tolist(), far.tolist()
        ([2.0], [4.0])
    """
    # In float32 at least: float16's 1e-12 is 0, whose reciprocal's inf times a face's 0 was NaN, and half rays
    # lying in a face of the box had missed it.
    origins, directions, box_min, box_max = (part.float() if part.dtype in (torch.float16, torch.bfloat16) else part
                                             for part in (origins, directions, box_min, box_max))
    magnitude = directions.abs()
    # |d| at least 1e-12, with d's sign (+0.0 for -0.0): 5 dispatches for 8.
    inv = torch.copysign(magnitude.clamp_min(1e-12), directions + 0.0).reciprocal()
    # Both slabs' ends in one product, (..., 2, N, 3), and their order in one reduction.
    entry, exit_ = torch.aminmax((torch.stack([box_min, box_max], -2).unsqueeze(-2) - origins) * inv, dim=-3)
    # A zero component's slab ends are 0 × its reciprocal where the origin lies on a face: on the lower face that 0
    # is an entry (harmless, t_near is clamped at 0), on the upper one an exit at 0, and the ray in that face had
    # missed the box. It is in the slab from end to end, as on the lower face.
    exit_ = exit_.masked_fill((exit_ == 0) & (directions == 0), math.inf)
    t_near = entry.amax(-1).clamp_min(0.0)  # in [0, inf] or NaN
    t_far = exit_.amin(-1)
    # Finite ends imply a finite origin (an infinite or NaN coordinate makes one end infinite or NaN), not a finite
    # direction: an infinite component only zeroes its slab's reciprocal. No direction is no ray either (it would
    # span ~1e12 units from inside). NaN fails every comparison.
    longest = magnitude.amax(-1)
    ray = (t_near < math.inf) & (t_far.abs() < math.inf) & (longest >= 1e-12) & (longest < math.inf)
    return torch.where(ray, t_near, 0.0), torch.where(ray, t_far, 0.0)


@dataclass(frozen=True)
class _Lattice:
    """A grid's lattice constants on one device (what every interpolation would otherwise rebuild): the box's
    extent (3,), ``resolution − 1`` (3,) as floats and ``resolution − 2`` (3,) as the largest cell index (and as
    floats), the flat strides (3,), the 8 corners' flat offsets (8,), the voxel size (3,), and per corner and axis
    (8, 3) the sign and constant that make its linear weight from the fractional coordinate f: 1 − f at a low corner,
    f at a high one."""

    extent: torch.Tensor
    upper: torch.Tensor
    last_cell: torch.Tensor
    last_cell_float: torch.Tensor
    strides: torch.Tensor
    corner_offsets: torch.Tensor
    voxel_size: torch.Tensor
    corner_signs: torch.Tensor
    corner_lows: torch.Tensor


@dataclass
class Occupancy:
    """Which grid cells can hold density, and the tight box around them."""

    cells: torch.Tensor  # (X-1, Y-1, Z-1) bool
    bbox_min: torch.Tensor  # (3,) world coordinates of the occupied cells' box
    bbox_max: torch.Tensor
    _dilated_blocks: dict = field(default_factory=dict, repr=False, compare=False)
    _flat_cells: torch.Tensor | None = field(default=None, repr=False, compare=False)

    def flat_cells(self) -> torch.Tensor:
        """(K,) flat indices into ``cells`` of the occupied cells (cached: one occupancy serves many steps)."""
        if self._flat_cells is None:
            self._flat_cells = self.cells.reshape(-1).nonzero()[:, 0]
        return self._flat_cells

    def dilated_blocks(self, size: int) -> torch.Tensor:
        """Cells pooled into ``size``³ blocks, then dilated by one block (cached per size).

        Block ``b`` is marked when any occupied cell lies in ``b`` or a neighbour:
        a point whose block is unmarked has no occupied cell within ``size``
        cells of it, which lets the renderer drop whole ray segments at once.
        """
        if size not in self._dilated_blocks:
            # Pooled as bytes (a float copy of the cells would be 0.5 GB at 512³); only the
            # small block grid is dilated in float.
            blocks = [-(-n // size) for n in self.cells.shape]
            padded = self.cells.new_zeros([b * size for b in blocks])
            padded[: self.cells.shape[0], : self.cells.shape[1], : self.cells.shape[2]] = self.cells
            pooled = padded.view(blocks[0], size, blocks[1], size, blocks[2], size).any(5).any(3).any(1)
            dilated = F.max_pool3d(pooled[None, None].float(), 3, stride=1, padding=1)[0, 0] > 0
            self._dilated_blocks[size] = dilated
        return self._dilated_blocks[size]

    def occupied(self, cell: torch.Tensor) -> torch.Tensor:
        """Whether each cell index (…, 3), as from ``VoxelGrid.cell_index``, is occupied."""
        return self.cells.to(cell.device)[cell.unbind(-1)]  # one gather (a flat index took 4 more operations)

    @property
    def fraction(self) -> float:
        return self.cells.count_nonzero().item() / self.cells.numel()

    @property
    def empty(self) -> bool:
        return not bool(self.cells.any())


class RayLattice(NamedTuple):
    """Where each of N rays is sampled: sample k stands for the path from ``k·step`` past ``t_near``, of length
    δ_k = ``clamp(length − k·step, 0, step)``, and lies ``offset``·δ_k into it: at ``start + k·step`` but for
    the last, cut at the box's exit, for k in [``first``, ``last``) (int64)."""

    step: float  # world units between samples
    t_near: torch.Tensor  # (N,) where the ray enters the box (0 for a camera inside)
    start: torch.Tensor  # (N,) sample 0: t_near plus the ray's offset within its first step
    length: torch.Tensor  # (N,) the path inside the box
    first: torch.Tensor  # (N,)
    last: torch.Tensor  # (N,)
    offset: torch.Tensor  # (N,) in [0, 1): where within the path it stands for each sample lies

    def candidates(self) -> torch.Tensor:
        """(N,) samples per ray before the occupancy test (a ray that misses has none)."""
        return (self.last - self.first).clamp_min(0)


class VoxelGrid(torch.nn.Module):
    """Dense feature grid ``features[x, y, z, c]``; channel 0 density, 1:4 colour.

    ``kind`` names the backbone in saved headers (``voxe_core.backbones`` finds the class by it).
    """

    kind: ClassVar[str] = "relu_field"
    lattice_sampled: ClassVar[bool] = True  # samples on :meth:`ray_lattice` (what the fused marcher walks)

    def __init__(
        self,
        resolution: int | tuple[int, int, int] = 160,
        bbox_min=DEFAULT_BOX[0],
        bbox_max=DEFAULT_BOX[1],
        activation: Activation = "relu",
        density_scale: float | None = None,
        init_density: float = 0.01,
        features: torch.Tensor | None = None,
    ):
        super().__init__()
        if activation not in ("relu", "softplus"):
            raise ValueError(f"unknown density activation {activation!r}; use 'relu' or 'softplus'")
        res = (resolution,) * 3 if isinstance(resolution, int) else tuple(int(r) for r in resolution)
        if min(res) < 2:
            raise ValueError(f"grid resolution must be >= 2 per axis, got {res}")
        # The box on the host (its scalars below, and ``like`` building grids on any device from it), and as
        # buffers on the device of the features (or of a given box tensor), so every grid's tensors share one.
        device = features.device if features is not None else getattr(bbox_min, "device", torch.device("cpu"))
        try:
            host_min = torch.as_tensor(bbox_min, dtype=torch.float32).cpu()
            host_max = torch.as_tensor(bbox_max, dtype=torch.float32).cpu()
        except (TypeError, ValueError, RuntimeError):
            host_min = host_max = None
        # (two numbers had failed building the lattice, "The size of tensor a (2) must match the size of tensor b
        # (3)", one "'float' object is not iterable", naming no box)
        if host_min is None or host_min.shape != (3,) or host_max.shape != (3,):
            raise ValueError(f"the box's corners must be three numbers each (x, y, z), got min {bbox_min!r} and max "
                             f"{bbox_max!r}")
        if not bool((torch.isfinite(host_min) & torch.isfinite(host_max)).all()):
            raise ValueError(f"the box must be finite: min {host_min.tolist()} max {host_max.tolist()}")
        if not bool((host_max > host_min).all()):
            raise ValueError(f"empty box: min {host_min.tolist()} max {host_max.tolist()}")
        if density_scale is not None and not (math.isfinite(density_scale) and density_scale > 0):
            # (its grid had been saved, and load_grid then refused the file as damaged)
            raise ValueError(f"density_scale must be a positive number, got {density_scale}")
        self._host_box = (host_min, host_max)
        self.register_buffer("bbox_min", host_min.to(device))
        self.register_buffer("bbox_max", host_max.to(device))
        self.activation = activation
        self.density_scale = float(default_density_scale(host_min.tolist(), host_max.tolist())
                                   if density_scale is None else density_scale)
        if features is None:
            features = torch.zeros(*res, 4, device=device)
            features[..., 0] = init_density
        elif tuple(features.shape) != (*res, 4):
            raise ValueError(f"features of shape {tuple(features.shape)} do not fit resolution {res}")
        self._resolution = res
        self._lattices: dict[torch.device, _Lattice] = {}
        # Host copies of the box's scalars: the sampler reads them every call, from the device they would
        # cost a round trip each.
        self.min_voxel_edge = float(self._lattice(torch.device("cpu")).voxel_size.min())
        self.box_diagonal = math.dist(host_min.tolist(), host_max.tolist())
        if not self.box_diagonal <= MAX_DIAGONAL_VOXELS * self.min_voxel_edge:
            axis = "xyz"[int(self._lattice(torch.device("cpu")).voxel_size.argmin())]
            raise ValueError(
                f"the box min {host_min.tolist()} max {host_max.tolist()} is too thin along {axis} for resolution "
                f"{res}: its diagonal spans {self.box_diagonal / self.min_voxel_edge:.3g} of its smallest voxel edge "
                f"({self.min_voxel_edge:.3g}, the step rays are sampled by), at most {MAX_DIAGONAL_VOXELS} "
                "(MAX_DIAGONAL_VOXELS); "
                f"widen the box along {axis} or give it fewer cells along {axis}")
        # Stored flat so a gather can return sparse gradients (see ``interpolate``).
        self.flat_features = torch.nn.Parameter(features.float().reshape(-1, 4).contiguous())

    # ------------------------------------------------------------------ basics
    @property
    def features(self) -> torch.Tensor:
        """The raw features as an (X, Y, Z, 4) view of the flat parameter."""
        return self.flat_features.view(*self._resolution, 4)

    @property
    def resolution(self) -> tuple[int, int, int]:
        return self._resolution

    @property
    def voxel_size(self) -> torch.Tensor:
        return self._lattice(self.bbox_min.device).voxel_size.clone()  # the caller's own: the cached one stays

    def _lattice(self, device: torch.device) -> _Lattice:
        """The lattice constants on ``device``, built once from the host box and resolution (neither ever changes):
        an interpolation on a GPU then launches no copies and no arithmetic on constants."""
        device = torch.device(device)
        if device not in self._lattices:
            host_min, host_max = self._host_box
            res = torch.tensor(self._resolution)
            strides = torch.tensor([self._resolution[1] * self._resolution[2], self._resolution[2], 1])
            self._lattices[device] = _Lattice(
                *(t.to(device) for t in (host_max - host_min, (res - 1).float(), res - 2, (res - 2).float(), strides,
                                         (_CORNERS * strides).sum(-1), (host_max - host_min) / (res - 1).float(),
                                         2.0 * _CORNERS - 1, 1.0 - _CORNERS)))
        return self._lattices[device]

    def check_occupancy(self, occupancy: Occupancy) -> None:
        """ValueError unless ``occupancy`` holds this grid's cells: another grid's had been looked up at this grid's
        cell indices (other cells skipped where it had more, a blank render in the test; an IndexError where fewer;
        past them in the fused kernel)."""
        cells = tuple(n - 1 for n in self._resolution)
        if tuple(occupancy.cells.shape) != cells:
            raise ValueError(f"an occupancy of {tuple(occupancy.cells.shape)} cells does not fit a grid of "
                             f"{self._resolution} vertices ({cells} cells)")

    def like(self, features: torch.Tensor) -> "VoxelGrid":
        """A grid with this one's box and activation, holding ``features``."""
        return VoxelGrid(
            features.shape[:3], *self._host_box, self.activation, self.density_scale, features=features
        )

    def clone_grid(self) -> "VoxelGrid":
        return self.like(self.features.detach().clone())

    def activate_density(self, raw: torch.Tensor) -> torch.Tensor:
        scaled = raw * self.density_scale
        return F.relu(scaled) if self.activation == "relu" else F.softplus(scaled)

    @property
    def empty_raw_density(self) -> float:
        """A raw density that activates to none: 0 under ReLU, far below the softplus knee (< 1e-13) otherwise."""
        return 0.0 if self.activation == "relu" else -30.0 / self.density_scale

    @staticmethod
    def activate_color(raw: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(raw)

    # ---------------------------------------------------------------- sampling
    def interpolate(
        self, points: torch.Tensor, features: torch.Tensor | None = None, sparse_grad: bool = False
    ) -> torch.Tensor:
        """Raw trilinear interpolation at world points (N, 3) -> (N, C), in float32 for half-precision features.

        ``features`` (X, Y, Z, C) defaults to this grid's; attention grids pass
        their own scalar features over the same lattice. Points outside the box
        are clamped onto it (the renderer only samples inside); a point with a
        NaN coordinate interpolates to NaN. ``sparse_grad`` makes the gradient
        of this grid's features a sparse tensor holding only the vertices
        touched, so a step costs what the batch saw, not the grid.
        """
        if features is not None and (features.ndim != 4 or tuple(features.shape[:3]) != self._resolution):
            # (another lattice's had been gathered at this one's flat indices: wrong vertices, or an IndexError)
            raise ValueError(f"features must be (X, Y, Z, C) on this grid's {self._resolution} vertices, got "
                             f"{tuple(features.shape)}")
        feats = self.features if features is None else features
        # Half-precision features are weighed in float32 (their weights too), as the renderer computes: bf16's 8-bit
        # weights had stepped the field between vertices, 0.018 off the float32 interpolation of the same features.
        flat_index, weights = self.trilinear_corners(points, torch.promote_types(feats.dtype, torch.float32))
        table = self.flat_features if features is None else feats.reshape(-1, feats.shape[-1])
        if sparse_grad and features is None:
            return _weigh_corners(weights, F.embedding(flat_index, table, sparse=True).to(weights.dtype))
        return _WeightedGather.apply(table, flat_index, weights)

    def trilinear_corners(self, points: torch.Tensor, dtype: torch.dtype = torch.float32) -> tuple[torch.Tensor, torch.Tensor]:
        """(flat vertex index (N, 8), trilinear weight (N, 8)) of world points (N, 3), clamped into the box.

        What :meth:`interpolate` gathers with, and what a back-projection scatters with. A NaN coordinate makes
        the point's weights NaN, its corners those of the last cell along that axis (every index in the grid).
        """
        lattice = self._lattice(points.device)
        upper = lattice.upper.to(points.dtype)
        u = (points - self.bbox_min) / lattice.extent * upper
        u = torch.minimum(u.clamp_min(0), upper)  # a NaN stays NaN: its weights below are NaN
        # u >= 0: truncation is the floor. fmin caps a NaN's cell at the last one, in the grid: truncated, a NaN had
        # been INT64_MIN, an index out of range (an IndexError, a device-side assert on CUDA, or a wrapped row).
        base = torch.fmin(u, lattice.last_cell_float.to(u.dtype)).long()
        frac = (u - base.to(u.dtype)).to(dtype)
        flat_index = (base * lattice.strides).sum(-1, keepdim=True) + lattice.corner_offsets  # (N, 8)
        # Per corner the product of its three axis weights, 1 − f exactly as a subtraction would round it (f·−1 is
        # exact): three dispatches where broadcasting views of a stacked (N, 3, 2) took fifteen, for an (N, 8, 3)
        # transient. The same bits on the CPU; CUDA's product may pair the factors in another order (and accumulates
        # half precision in float32), which moves a weight by float rounding at most.
        axis_weights = torch.addcmul(lattice.corner_lows.to(dtype), frac.unsqueeze(1), lattice.corner_signs.to(dtype))
        return flat_index, axis_weights.prod(-1)  # (N, 8)

    def cell_index(self, points: torch.Tensor) -> torch.Tensor:
        """Integer (…, 3) index of the cell holding each world point, clamped into the grid."""
        lattice = self._lattice(points.device)
        cell = ((points - self.bbox_min) / lattice.voxel_size).floor().long()
        return torch.minimum(cell.clamp_min(0), lattice.last_cell)

    def query(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Activated (density (N,), colour (N, 3)) at world points; density is 0 outside the box."""
        raw = self.interpolate(points)
        inside = ((points >= self.bbox_min) & (points <= self.bbox_max)).all(-1)
        return self.activate_density(raw[:, 0]) * inside, self.activate_color(raw[:, 1:])

    # ------------------------------------------------------------ rays
    def ray_lattice(
        self,
        origins: torch.Tensor,
        directions: torch.Tensor,
        offsets: torch.Tensor,
        step_ratio: float,
        occupancy: Occupancy | None = None,
    ) -> RayLattice:
        """Each ray's lattice (N,): where its samples lie and which of them are candidates (:class:`RayLattice`).

        Sample k of a ray lies at ``start + k·step`` (the last, cut at the box's exit, ``offset``·δ into what is
        left: :class:`RayLattice`), k in [``first``, ``last``): the box's samples, or, with an
        ``occupancy``, those within its tight box (every one :meth:`ray_samples` may keep, and what the fused
        marcher walks).
        """
        step = step_ratio * self.min_voxel_edge
        if occupancy is None:
            t_near, t_far = ray_box_intersection(origins, directions, self.bbox_min, self.bbox_max)
        else:  # the grid's box and the occupied cells' tight one in one slab test
            device = origins.device
            (t_near, tight_near), (t_far, tight_far) = ray_box_intersection(
                origins, directions, torch.stack([self.bbox_min, occupancy.bbox_min.to(device)]),
                torch.stack([self.bbox_max, occupancy.bbox_max.to(device)]))
        n_total = torch.ceil((t_far - t_near) / step).clamp_min(0).long()
        first = torch.zeros_like(n_total)
        last = n_total
        if occupancy is not None:
            hit = tight_far > tight_near
            first = torch.where(hit, ((tight_near - t_near) / step).floor().long().clamp_min(0), first)
            last = torch.where(hit, torch.minimum(((tight_far - t_near) / step).ceil().long(), n_total), first)
        return RayLattice(step, t_near, t_near + offsets * step, t_far - t_near, first, last, offsets)

    def ray_samples(
        self,
        origins: torch.Tensor,
        directions: torch.Tensor,
        offsets: torch.Tensor,
        step_ratio: float,
        occupancy: Occupancy | None = None,
        samples_per_pass: int = 1 << 20,
        early_stop: float = 0.0,
    ) -> Iterator[RaySamples]:
        """Where the rays (N, 3) are sampled: groups of consecutive rays whose lattice samples fit in ``samples_per_pass``.

        Samples lie ``step_ratio`` smallest voxel edges apart on one lattice per ray
        anchored at the box; ``offsets`` (N,) in [0, 1) places each ray's first sample
        within its first step (0.5: midpoints; uniform: stratified jitter). With an
        ``occupancy``, only samples in its occupied cells inside its tight box are
        kept, so skipping only drops samples and never moves them: with ReLU it is
        exact. The last sample of a ray is cut at the box exit, so path lengths are exact.
        ``early_stop`` > 0: a density pass without gradient drops the samples behind
        the point where a ray's transmittance falls below it (each sample stands for
        at most one step, so what is dropped weighs less than ``early_stop`` in the
        render and in its gradient).

        Examples:
            >>> grid = VoxelGrid(5)
            >>> rays = torch.tensor([[0.0, 0, -3]]), torch.tensor([[0.0, 0, 1]])
            >>> group = next(grid.ray_samples(*rays, torch.full((1,), 0.5), step_ratio=1.0))
            >>> group.points.shape, float(group.delta.sum())  # 4 steps of 0.75 through the 3-unit box
            (torch.Size([4, 3]), 3.0)
        """
        lattice = self.ray_lattice(origins, directions, offsets, step_ratio, occupancy)
        step, t_near, first, last = lattice.step, lattice.t_near, lattice.first, lattice.last
        segments, n_segments = _ray_segments(self, occupancy, origins, directions, t_near, step, first, last)
        if not n_segments.numel():
            return
        # Consecutive groups of rays whose lattice samples fit in one pass (bounds memory on dense renders).
        per_ray = n_segments * SEGMENT
        group = torch.div(per_ray.cumsum(0) - per_ray, samples_per_pass, rounding_mode="floor")
        candidates = lattice.candidates().cumsum(0)
        # Segment width, whether one pass holds every ray (the groups never decrease) and the candidate count
        # reach the host in one read; only several passes need a second, for their ends and counts.
        width, last_group, total = torch.cat([n_segments.amax().reshape(1), group[-1:], candidates[-1:]]).tolist()
        segments = segments[:, :width]
        ends, group_candidates = [n_segments.numel()], [total]
        if last_group:
            ends = torch.unique_consecutive(group, return_counts=True)[1].cumsum(0)
            counts = candidates.index_select(0, ends - 1)
            host = torch.cat([ends, counts.diff(prepend=counts.new_zeros(1))]).tolist()
            ends, group_candidates = host[: len(ends)], host[len(ends) :]
        for lo, hi, n_candidates in zip([0] + ends[:-1], ends, group_candidates):
            ray, t, delta, points = _packed_samples(
                self, occupancy, origins, directions, lattice, segments[lo:hi], n_segments[lo:hi], lo
            )
            samples = RaySamples(ray, t, delta, points, n_candidates)
            yield self._stop_early(samples, early_stop) if early_stop > 0 and ray.numel() else samples

    @torch.no_grad()
    def _stop_early(self, samples: RaySamples, early_stop: float) -> RaySamples:
        """``samples`` up to where each ray's transmittance falls below ``early_stop`` (densities without gradient), in
        float32 whatever autocast says: a caller's bf16 autocast (the back-projection iterates these samples in its own)
        had run the interpolation's bmm in bf16, so rays had stopped at other samples than the render's."""
        with full_precision(samples.points):
            density = self.activate_density(self.interpolate(samples.points)[:, 0])
        # "not at most": a NaN keeps its sample and those behind it, so the render shows it rather than ending there.
        reached = ~(transmittance(optical_depth(density, samples.delta), samples.ray) <= early_stop)
        kept = samples.select(reached.nonzero().squeeze(1))
        kept.probed = samples.ray.numel()
        return kept

    def vertex_positions(self) -> torch.Tensor:
        """Where each lattice vertex sits in this grid's frame, (X·Y·Z, 3) in the features' row order."""
        axes = [torch.linspace(float(lo), float(hi), n, device=self.bbox_min.device)
                for lo, hi, n in zip(self.bbox_min, self.bbox_max, self.resolution)]
        return torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)

    def rows_within(self, centres: torch.Tensor, radii: torch.Tensor) -> torch.Tensor:
        """Feature rows (K,) of the vertices within ``radii`` (M,) of any of ``centres`` (M, 3), in this grid's frame."""
        positions = self.vertex_positions()
        near = torch.zeros(positions.shape[0], dtype=torch.bool, device=positions.device)
        for start in range(0, positions.shape[0], 1 << 16):  # bounds the (chunk, M) distance matrix
            chunk = positions[start : start + (1 << 16)]
            near[start : start + chunk.shape[0]] = (torch.cdist(chunk, centres.to(chunk)) < radii.to(chunk)).any(1)
        return near.nonzero()[:, 0]

    def dataset_cameras(self, cameras: Cameras) -> Cameras:
        """A capture's cameras in the frame this grid lives in: an object grid lives in the capture's own."""
        return cameras

    def foreground_grid(self) -> "VoxelGrid":
        """The object without its background, as a ReLU-field grid (what a mesh is made of): all of an object grid."""
        return self

    def orbit_centre(self) -> torch.Tensor:
        """The point (3,) that turntables and editing's random poses orbit: the origin, where an object box
        centres its object (SPEC §0), so the paper's poses and evaluation ring are kept exactly."""
        return torch.zeros(3)

    def object_vertices(self) -> torch.Tensor:
        """(X, Y, Z) bool: the vertices that can hold the object (a local edit's graph cut is among them): all of them."""
        return torch.ones(self.resolution, dtype=torch.bool, device=self.bbox_min.device)

    @torch.no_grad()
    def matter_centre(self) -> torch.Tensor:
        """Centroid (3,) of the vertices, each weighted by the opacity of one voxel length of it, 1 − exp(−σ·Δ).

        Where the matter is: solid matter counts by its volume however dense it was fitted, a faint
        haze barely at all. The box centre when the grid is empty. On the CPU, where poses are built.
        """
        sigma = self.activate_density(self.features[..., 0].detach())
        weight = -torch.expm1(-sigma * self.min_voxel_edge).double()
        total = float(weight.sum())
        if not total > 0:
            return ((self.bbox_min + self.bbox_max) / 2).cpu()
        centre = []
        for d, n in enumerate(self.resolution):
            axis = torch.linspace(float(self.bbox_min[d]), float(self.bbox_max[d]), n, dtype=torch.float64,
                                  device=weight.device)
            marginal = weight.sum(dim=[e for e in range(3) if e != d])
            centre.append(float((marginal * axis).sum()) / total)
        return torch.tensor(centre, dtype=torch.float32)

    # ----------------------------------------------------------- structure
    def upsampled(self, resolution: int | tuple[int, int, int]) -> "VoxelGrid":
        """Trilinear upsampling of the raw features (coarse-to-fine reconstruction)."""
        res = (resolution,) * 3 if isinstance(resolution, int) else tuple(resolution)
        volume = self.features.detach().permute(3, 0, 1, 2)[None]
        up = F.interpolate(volume, size=res, mode="trilinear", align_corners=True)
        return self.like(up[0].permute(1, 2, 3, 0).contiguous())

    @torch.no_grad()
    def occupancy(self, sigma_threshold: float = DEFAULT_SIGMA_THRESHOLD) -> Occupancy:
        """Cells worth rendering: density above ``sigma_threshold`` as measured in the default 3-unit box.

        The threshold is scaled by (default box diagonal / this box's diagonal),
        as ``default_density_scale`` is, so skipping drops the same optical
        depth along a ray at any scene scale (an absolute 1e-3 would skip an
        opaque object in a box of 1e3 units). The default box uses it as given. A backbone whose
        cells differ in world size lowers it per cell (``SceneGrid.skip_density``).
        """
        return self.occupancy_above(self.skip_density(sigma_threshold))

    def skip_density(self, sigma_threshold: float) -> float | torch.Tensor:
        """The absolute density :meth:`occupancy` skips cells below: one for all cells (another backbone may
        give one per cell, (X-1, Y-1, Z-1))."""
        return sigma_threshold * math.dist(*DEFAULT_BOX) / self.box_diagonal

    @torch.no_grad()
    def occupancy_above(self, density: float | torch.Tensor) -> Occupancy:
        """Cells whose activated density can exceed ``density`` (absolute, 1 / world unit; or one per cell,
        (X-1, Y-1, Z-1)) anywhere inside.

        Trilinear interpolation is bounded by the corner maximum and both
        activations are monotone, so the test is conservative: with ReLU and
        threshold 0 skipping is exact. A cell with a NaN corner is occupied (rendered, so the NaN shows).
        """
        raw = self.features[..., 0]
        corner_max = torch.maximum(raw[:-1], raw[1:])
        corner_max = torch.maximum(corner_max[:, :-1], corner_max[:, 1:])
        corner_max = torch.maximum(corner_max[:, :, :-1], corner_max[:, :, 1:])
        # "not at most": a NaN density counts as occupied, so every render path shows it (``> density`` hid it).
        return self.occupancy_from_cells(~(self.activate_density(corner_max) <= density))

    def occupancy_from_cells(self, cells: torch.Tensor) -> Occupancy:
        """Occupancy for a given cell mask (e.g. one restored from a checkpoint), with its tight box.

        The box is found without reading anything back to the host (the edit loop builds one
        per iteration): per axis, the first and last occupied slice by argmax; an empty mask
        gives an empty box at ``bbox_min``.
        """
        lo, hi = [], []
        for axis in range(3):
            along = cells.any(dim=[a for a in range(3) if a != axis]).to(torch.uint8)  # argmax: first maximum
            lo.append(along.argmax())
            hi.append(along.numel() - along.flip(0).argmax())
        vox = self._lattice(cells.device).voxel_size
        occupied = cells.any()
        # Occupied up to the box's far face: that face itself, not its rounding (bbox_min + 37 · 3/37 is 1.4999998 in
        # float32, at 38 vertices in the default box; rays lying in the face y = 1.5 had missed the tight box and
        # been skipped, blank, where the render without skipping showed the face's density).
        to_face = torch.stack([h == n for h, n in zip(hi, cells.shape)])
        far = torch.where(to_face, self.bbox_max, self.bbox_min + torch.stack(hi) * vox)
        box_min = torch.where(occupied, self.bbox_min + torch.stack(lo) * vox, self.bbox_min)
        box_max = torch.where(occupied, far, self.bbox_min)
        return Occupancy(cells, box_min, box_max)

    # ------------------------------------------------------------- storage
    def state_tensors(self) -> dict[str, torch.Tensor]:
        """The tensors a file holds, float32 as the format says whatever the grid's dtype (a ``.half()`` grid's too).
        ValueError for a float8 grid (its save had failed on "maximum_cpu" not implemented, or written a box rounded
        to 3 bits)."""
        if float_dtype_problem(self.features):
            raise ValueError(f"a {self.features.dtype} grid cannot be saved: grid files hold floats of at least "
                             f"{MIN_FLOAT_BITS} bits; convert it with .float() first")
        return {"features": self.features.detach().float(), "bbox_min": self.bbox_min.float(),
                "bbox_max": self.bbox_max.float()}

    def header(self) -> dict:
        return {"backbone": self.kind, "activation": self.activation, "density_scale": self.density_scale,
                "resolution": list(self.resolution)}

    def save(self, path, dense: bool = False, margin: int = DEFAULT_MARGIN, notes: dict | None = None) -> None:
        """Write the grid file (``voxe_core.gridfile`` documents the format): sparse unless ``dense`` or not smaller.

        The sparse layout keeps the cells that can hold density (with ReLU: raw
        density above 0 at a corner, so a loaded grid renders identically with or
        without empty-space skipping; with softplus: ``occupancy()``'s cells, so
        identically where skipping is at the default threshold or above) plus
        ``margin`` cells around them. ``notes``: header entries on what made the grid (``voxe edit``'s
        ``smoke_test``), which loading passes over.
        """
        tensors, meta = self.state_tensors(), {**(notes or {}), **self.header(), "layout": "dense"}
        if not dense:
            # The cells kept, and the highest raw density those left out may all hold and stay so on loading: 0
            # under ReLU; else the one activating to the lowest skip density of any cell (a scene grid's
            # background lowers its own).
            if self.activation == "relu":
                cells, unoccupied = self.occupancy_above(0.0).cells, 0.0
            else:
                skip = self.skip_density(DEFAULT_SIGMA_THRESHOLD)
                cells, lowest = self.occupancy_above(skip).cells, float(torch.as_tensor(skip).min())
                unoccupied = math.log(math.expm1(lowest)) / self.density_scale if lowest > 0 else -math.inf
            packed, layout = sparse_tensors(tensors["features"], cells, margin, unoccupied)
            if payload_bytes(packed) < payload_bytes({"features": tensors["features"]}):
                tensors = {**{k: v for k, v in tensors.items() if k != "features"}, **packed}
                meta = {**meta, **layout}
        save_tensors(path, tensors, kind=GRID_KIND, version=GRID_FORMAT_VERSION, meta=meta)

    @classmethod
    def from_state(cls, tensors: dict[str, torch.Tensor], meta: dict) -> "VoxelGrid":
        """This class's grid from saved tensors and header (``voxe_core.backbones.load_grid`` picks the class)."""
        return cls(
            tuple(tensors["features"].shape[:3]), tensors["bbox_min"], tensors["bbox_max"],
            meta["activation"], meta["density_scale"], features=tensors["features"],
        )


def _ray_segments(grid, occupancy, origins, directions, t_near, step, first, last):
    """Per ray, the lattice segments worth sampling, in marching order: (R, S) indices (the first ``counts[r]``
    of row r are the kept ones) and (R,) counts.

    A segment is ``SEGMENT`` consecutive lattice samples. With an occupancy, a
    segment survives when its midpoint's block in ``occupancy.dilated_blocks``
    is marked, so every sample of a dropped segment lies in an empty cell and
    dropping it never changes the render; the fine per-cell test then runs only
    on the segments kept.
    """
    seg_first = torch.div(first, SEGMENT, rounding_mode="floor")
    n_segments = torch.where(last > first, torch.div(last - 1, SEGMENT, rounding_mode="floor") - seg_first + 1, 0)
    if not n_segments.numel():
        return seg_first[:, None], n_segments
    # One read for both scalars the layout needs: the widest ray and the longest direction.
    longest_direction = directions.norm(dim=-1).nan_to_num(0.0, 0.0, 0.0).max().clamp_min(1.0)
    max_segments, longest = torch.stack([n_segments.max().to(longest_direction.dtype), longest_direction]).tolist()
    max_segments = int(max_segments)
    segments = seg_first[:, None] + torch.arange(max_segments, device=origins.device)[None, :]
    if occupancy is None or max_segments == 0:
        return segments, n_segments
    # Every sample of a segment lies within SEGMENT / 2 steps of its midpoint, so within
    # ``size`` cells of it per axis, so in the midpoint's block or one of its neighbours.
    size = max(1, math.ceil(SEGMENT / 2 * step * longest / grid.min_voxel_edge))
    keep = torch.arange(max_segments, device=origins.device)[None, :] < n_segments[:, None]
    mid = t_near[:, None] + (segments * SEGMENT + SEGMENT / 2) * step
    block = grid.cell_index(origins[:, None, :] + mid[..., None] * directions[:, None, :]) // size
    keep &= occupancy.dilated_blocks(size)[block.unbind(-1)]
    # Stable sort puts each ray's kept segments first, still in marching order.
    order = torch.sort((~keep).to(torch.uint8), dim=1, stable=True).indices
    return segments.gather(1, order), keep.sum(1)  # the caller trims to the widest kept count


def _packed_samples(grid, occupancy, origins, directions, lattice, segments, n_segments, ray_offset):
    """The samples of the kept segments (in occupied cells when ``occupancy`` is given), packed ray
    by ray in marching order: ray index, distance, path length and point of each (:class:`RayLattice`).

    Work is laid out per segment (16 samples wide) so the per-ray values are
    gathered once per segment, not once per sample.
    """
    kept = torch.arange(segments.shape[1], device=segments.device)[None, :] < n_segments[:, None]
    row, column = kept.nonzero().unbind(1)  # a mask index would find the same entries again, with a host read
    seg_ray = row + ray_offset
    k = segments[row, column][:, None] * SEGMENT + torch.arange(SEGMENT, device=segments.device)  # (G, SEGMENT)
    step = lattice.step
    inside = ((k >= lattice.first.index_select(0, seg_ray)[:, None])
              & (k < lattice.last.index_select(0, seg_ray)[:, None]))
    # k·step formed once, t and the correction below in place: fresh (G, SEGMENT) tensors cost the CPU about as
    # much as their arithmetic (the same operations on the same operands: the same bits).
    t = k * step
    delta = (lattice.length.index_select(0, seg_ray)[:, None] - t).clamp_(0.0, step)
    # The last sample within the path it stands for (the others: step − δ is 0, the same bits). At start + k·step it
    # had lain up to a step past the box's exit, read from the face's far side (interpolation clamps onto the box),
    # where the occupancy's tight box, cut at the exit, dropped it: skipping had changed the render.
    t.add_(lattice.start.index_select(0, seg_ray)[:, None])
    t.sub_((step - delta).mul_(lattice.offset.index_select(0, seg_ray)[:, None]))
    points = origins.index_select(0, seg_ray)[:, None, :] + t[..., None] * directions.index_select(0, seg_ray)[:, None, :]
    if occupancy is not None:
        inside &= occupancy.occupied(grid.cell_index(points))
    pick = inside.reshape(-1).nonzero().squeeze(1)
    ray = seg_ray.index_select(0, torch.div(pick, SEGMENT, rounding_mode="floor"))
    return (ray, t.reshape(-1).index_select(0, pick), delta.reshape(-1).index_select(0, pick),
            points.reshape(-1, 3).index_select(0, pick))
