"""Ray marching fused into one GPU kernel (Triton): the packed renderer's render of a ReLU field without its passes.

The packed renderer (``VoxelGrid.ray_samples`` and ``render.composite``) lays
every sample of a pass out in memory and composites it with some 600 tensor
operations and host reads per render; on the H200 that made the edit's render
22 ms of a 61 ms step (bench/gpu.py, section j). Here one program marches a
block of rays through the same lattice (:meth:`VoxelGrid.ray_lattice`: the same
sample points, path lengths and candidates), skips the samples in empty cells
by the same occupancy, stops where the transmittance falls to ``early_stop``,
and composites as it goes: nothing per sample is stored. The backward marches
again and adds each sample's gradient into the grid's features with atomic adds,
the samples behind a point taken from the forward's totals (as instant-ngp's
compositing does), so it too stores nothing per sample.

Only what :func:`voxe_core.render.render_rays` asks of a plain ReLU field with its
own colour is built here (``render.fused_marcher_applies``); everything else
(softplus density, other features, sparse gradients, a scene's contracted bins)
stays on the packed path. The two agree to float32 rounding; each ray's
transmittance, weights and sums are float64 running values here (the packed path
takes float64 prefix sums), so that the gradient behind a nearly opaque point is
a difference of exact sums. The atomic adds make the gradient vary at rounding
from run to run, as the packed path's ``index_add`` does on CUDA.

Triton compiles these kernels for CUDA; its interpreter (``TRITON_INTERPRET=1``
set before this module is imported) runs them on the CPU, which is how the tests
check them against the packed path on a machine without a GPU.

Examples:
    >>> grid = VoxelGrid(8)  # raw density 0.01 everywhere: σ = 1/3 per unit (CUDA tensors, or TRITON_INTERPRET=1)
    >>> origins, directions = torch.tensor([[0.0, 0, -3]]), torch.tensor([[0.0, 0, 1]])
    >>> lattice = grid.ray_lattice(origins, directions, torch.full((1,), 0.5), step_ratio=0.5)
    >>> colour, opacity, depth, samples = march(grid, origins, directions, lattice, None, early_stop=1e-4)
    >>> round(float(opacity.detach()), 4), int(samples)  # 1 − exp(−3 · 1/3); 3 units in steps of half a voxel (3/7)
    (0.6321, 14)
"""

from __future__ import annotations

import contextlib

import torch
import triton
import triton.language as tl

from voxe_core.grid import Occupancy, RayLattice, VoxelGrid
from voxe_core.volrend import MAX_SAMPLE_OPTICAL_DEPTH

RAYS_PER_PROGRAM = 128  # one ray per thread of a 4-warp program; neighbouring pixels march alike


@triton.jit
def _sample_at(ox, oy, oz, dx, dy, dz, start, offset, length, k, step):
    """Lattice sample ``k`` of each ray: its distance, point and the path it stands for (as ``ray_samples``: the last
    within its path, cut at the box's exit)."""
    kf = k.to(tl.float32)
    delta = tl.minimum(tl.maximum(length - kf * step, 0.0), step)
    t = start + kf * step - offset * (step - delta)
    return t, ox + t * dx, oy + t * dy, oz + t * dz, delta


@triton.jit
def _cell(p, lo, voxel, last):
    """The cell index along one axis of a point (``VoxelGrid.cell_index``), clamped into the grid."""
    return tl.minimum(tl.maximum(tl.floor((p - lo) / voxel), 0.0), last).to(tl.int64)


@triton.jit
def _lattice_coordinate(p, lo, extent, upper, last):
    """(base vertex, fraction) of a point along one axis (``VoxelGrid.trilinear_corners``)."""
    u = tl.minimum(tl.maximum((p - lo) / extent * upper, 0.0), upper)
    base = tl.minimum(tl.floor(u), last)
    return base.to(tl.int64), u - base


@triton.jit
def _interpolate(row, stride_x, stride_y, fx, fy, fz, mask):
    """Trilinear interpolation of one channel: ``row`` points at the channel of each sample's base vertex."""
    gx = 1.0 - fx
    gy = 1.0 - fy
    gz = 1.0 - fz
    value = gx * gy * gz * tl.load(row, mask=mask, other=0.0)
    value += gx * gy * fz * tl.load(row + 4, mask=mask, other=0.0)
    value += gx * fy * gz * tl.load(row + 4 * stride_y, mask=mask, other=0.0)
    value += gx * fy * fz * tl.load(row + 4 * (stride_y + 1), mask=mask, other=0.0)
    value += fx * gy * gz * tl.load(row + 4 * stride_x, mask=mask, other=0.0)
    value += fx * gy * fz * tl.load(row + 4 * (stride_x + 1), mask=mask, other=0.0)
    value += fx * fy * gz * tl.load(row + 4 * (stride_x + stride_y), mask=mask, other=0.0)
    value += fx * fy * fz * tl.load(row + 4 * (stride_x + stride_y + 1), mask=mask, other=0.0)
    return value


@triton.jit
def _scatter(row, stride_x, stride_y, fx, fy, fz, grad, mask):
    """The adjoint of :func:`_interpolate`: ``grad`` added into the eight corners by their weights."""
    gx = 1.0 - fx
    gy = 1.0 - fy
    gz = 1.0 - fz
    tl.atomic_add(row, gx * gy * gz * grad, mask=mask, sem="relaxed")
    tl.atomic_add(row + 4, gx * gy * fz * grad, mask=mask, sem="relaxed")
    tl.atomic_add(row + 4 * stride_y, gx * fy * gz * grad, mask=mask, sem="relaxed")
    tl.atomic_add(row + 4 * (stride_y + 1), gx * fy * fz * grad, mask=mask, sem="relaxed")
    tl.atomic_add(row + 4 * stride_x, fx * gy * gz * grad, mask=mask, sem="relaxed")
    tl.atomic_add(row + 4 * (stride_x + 1), fx * gy * fz * grad, mask=mask, sem="relaxed")
    tl.atomic_add(row + 4 * (stride_x + stride_y), fx * fy * gz * grad, mask=mask, sem="relaxed")
    tl.atomic_add(row + 4 * (stride_x + stride_y + 1), fx * fy * fz * grad, mask=mask, sem="relaxed")


@triton.jit
def _march(
    origins, directions, starts, offsets, lengths, firsts, lasts, features, cells, grad_features,
    rgb, opacity, depth, count, totals, grad_rgb, grad_opacity, grad_depth,
    n_rays, step, early_stop, density_scale, max_optical,
    lo_x, lo_y, lo_z, extent_x, extent_y, extent_z, upper_x, upper_y, upper_z,
    voxel_x, voxel_y, voxel_z, last_x, last_y, last_z,
    stride_x, stride_y, cell_stride_x, cell_stride_y,
    SKIP_EMPTY: tl.constexpr, BACKWARD: tl.constexpr, BLOCK: tl.constexpr,
):
    """March BLOCK rays. Forward: write each ray's Σw·colour (3), Σw, Σw·t (float32, and in float64 to ``totals``)
    and its sample count. Backward: add the gradient of L = Σ_ray g_rgb·Σw·c + g_opacity·Σw + g_depth·Σw·t into
    ``grad_features``; the part of L behind each sample is the forward's total less what the samples up to it gave.

    Transmittance, weights and those sums are float64: each weight is T_k − T_{k+1}, so the weights behind a sample
    add up to exactly T_{k+1} − T_end, and the gradient T_{k+1}·v − (the part behind) does not drown in float32
    rounding where the rays are nearly opaque (it had been off by up to 3 % there)."""
    ray = tl.program_id(0) * BLOCK + tl.arange(0, BLOCK)
    lane = ray < n_rays
    ox = tl.load(origins + 3 * ray, mask=lane, other=0.0)
    oy = tl.load(origins + 3 * ray + 1, mask=lane, other=0.0)
    oz = tl.load(origins + 3 * ray + 2, mask=lane, other=0.0)
    dx = tl.load(directions + 3 * ray, mask=lane, other=0.0)
    dy = tl.load(directions + 3 * ray + 1, mask=lane, other=0.0)
    dz = tl.load(directions + 3 * ray + 2, mask=lane, other=0.0)
    start = tl.load(starts + ray, mask=lane, other=0.0)
    offset = tl.load(offsets + ray, mask=lane, other=0.0)
    length = tl.load(lengths + ray, mask=lane, other=0.0)
    k = tl.load(firsts + ray, mask=lane, other=0)
    last = tl.load(lasts + ray, mask=lane, other=0)
    if BACKWARD:
        g_r = tl.load(grad_rgb + 3 * ray, mask=lane, other=0.0).to(tl.float64)
        g_g = tl.load(grad_rgb + 3 * ray + 1, mask=lane, other=0.0).to(tl.float64)
        g_b = tl.load(grad_rgb + 3 * ray + 2, mask=lane, other=0.0).to(tl.float64)
        g_o = tl.load(grad_opacity + ray, mask=lane, other=0.0).to(tl.float64)
        g_d = tl.load(grad_depth + ray, mask=lane, other=0.0).to(tl.float64)
        behind = (g_r * tl.load(totals + 5 * ray, mask=lane, other=0.0)
                  + g_g * tl.load(totals + 5 * ray + 1, mask=lane, other=0.0)
                  + g_b * tl.load(totals + 5 * ray + 2, mask=lane, other=0.0)
                  + g_o * tl.load(totals + 5 * ray + 3, mask=lane, other=0.0)
                  + g_d * tl.load(totals + 5 * ray + 4, mask=lane, other=0.0))
    sum_r = tl.zeros([BLOCK], dtype=tl.float64)
    sum_g = tl.zeros([BLOCK], dtype=tl.float64)
    sum_b = tl.zeros([BLOCK], dtype=tl.float64)
    sum_w = tl.zeros([BLOCK], dtype=tl.float64)
    sum_t = tl.zeros([BLOCK], dtype=tl.float64)
    optical = tl.zeros([BLOCK], dtype=tl.float64)
    transmitted = tl.full([BLOCK], 1.0, dtype=tl.float64)
    samples = tl.zeros([BLOCK], dtype=tl.int32)
    marching = lane & (k < last)
    going = tl.max(marching.to(tl.int32), axis=0)
    while going > 0:
        # "not at most": a NaN transmittance marches on, so the NaN shows (as the packed path's early stop).
        marching = lane & (k < last) & ~(transmitted <= early_stop)
        t, px, py, pz, delta = _sample_at(ox, oy, oz, dx, dy, dz, start, offset, length, k, step)
        alive = marching
        if SKIP_EMPTY:
            cell = (_cell(px, lo_x, voxel_x, last_x) * cell_stride_x + _cell(py, lo_y, voxel_y, last_y) * cell_stride_y
                    + _cell(pz, lo_z, voxel_z, last_z))
            alive = alive & (tl.load(cells + cell, mask=alive, other=0) != 0)
        bx, fx = _lattice_coordinate(px, lo_x, extent_x, upper_x, last_x)
        by, fy = _lattice_coordinate(py, lo_y, extent_y, upper_y, last_y)
        bz, fz = _lattice_coordinate(pz, lo_z, extent_z, upper_z, last_z)
        row = features + 4 * (bx * stride_x + by * stride_y + bz)
        scaled = _interpolate(row, stride_x, stride_y, fx, fy, fz, alive) * density_scale
        sigma = tl.where(scaled < 0.0, 0.0, scaled)  # ReLU keeping a NaN
        free_tau = tl.where(delta > 0.0, sigma, 0.0) * delta  # no path, no depth: not inf · 0 = NaN
        tau = tl.where(alive, tl.where(free_tau > max_optical, max_optical, free_tau), 0.0)
        after = tl.exp(-(optical + tau.to(tl.float64)))  # T_{k+1}; T_k where the sample is not alive
        weight = transmitted - after
        # Colour too where the density is 0: a NaN colour shows there (0 · NaN), as on the packed path.
        red = tl.sigmoid(_interpolate(row + 1, stride_x, stride_y, fx, fy, fz, alive))
        green = tl.sigmoid(_interpolate(row + 2, stride_x, stride_y, fx, fy, fz, alive))
        blue = tl.sigmoid(_interpolate(row + 3, stride_x, stride_y, fx, fy, fz, alive))
        t_wide = t.to(tl.float64)
        if BACKWARD:
            value = tl.where(alive, g_r * red.to(tl.float64) + g_g * green.to(tl.float64)
                             + g_b * blue.to(tl.float64) + g_o + g_d * t_wide, 0.0)
            behind -= weight * value
            d_tau = (after * value - behind).to(tl.float32)
            grads = alive & (scaled > 0.0)
            d_density = tl.where(free_tau <= max_optical, d_tau * delta * density_scale, 0.0)
            w = weight.to(tl.float32)
            grad_row = grad_features + 4 * (bx * stride_x + by * stride_y + bz)
            _scatter(grad_row, stride_x, stride_y, fx, fy, fz, d_density, grads)
            _scatter(grad_row + 1, stride_x, stride_y, fx, fy, fz, w * g_r.to(tl.float32) * red * (1.0 - red), grads)
            _scatter(grad_row + 2, stride_x, stride_y, fx, fy, fz, w * g_g.to(tl.float32) * green * (1.0 - green), grads)
            _scatter(grad_row + 3, stride_x, stride_y, fx, fy, fz, w * g_b.to(tl.float32) * blue * (1.0 - blue), grads)
        else:
            sum_r += tl.where(alive, weight * red.to(tl.float64), 0.0)
            sum_g += tl.where(alive, weight * green.to(tl.float64), 0.0)
            sum_b += tl.where(alive, weight * blue.to(tl.float64), 0.0)
            sum_w += weight
            sum_t += weight * t_wide
            samples += alive.to(tl.int32)
        optical += tau.to(tl.float64)
        transmitted = after
        k += 1
        going = tl.max(marching.to(tl.int32), axis=0)
    if not BACKWARD:
        tl.store(rgb + 3 * ray, sum_r.to(tl.float32), mask=lane)
        tl.store(rgb + 3 * ray + 1, sum_g.to(tl.float32), mask=lane)
        tl.store(rgb + 3 * ray + 2, sum_b.to(tl.float32), mask=lane)
        tl.store(opacity + ray, sum_w.to(tl.float32), mask=lane)
        tl.store(depth + ray, sum_t.to(tl.float32), mask=lane)
        tl.store(count + ray, samples, mask=lane)
        tl.store(totals + 5 * ray, sum_r, mask=lane)
        tl.store(totals + 5 * ray + 1, sum_g, mask=lane)
        tl.store(totals + 5 * ray + 2, sum_b, mask=lane)
        tl.store(totals + 5 * ray + 3, sum_w, mask=lane)
        tl.store(totals + 5 * ray + 4, sum_t, mask=lane)


class _Launch:
    """One render's rays, occupancy and the grid's lattice constants: what the forward and backward kernels share."""

    def __init__(self, grid: VoxelGrid, origins: torch.Tensor, directions: torch.Tensor, lattice: RayLattice,
                 occupancy: Occupancy | None, early_stop: float):
        res = torch.tensor(grid.resolution)
        cells = res - 1
        if occupancy is not None:
            grid.check_occupancy(occupancy)
        self.rays = [origins.contiguous(), directions.contiguous(), lattice.start.contiguous(),
                     lattice.offset.float().contiguous(), lattice.length.contiguous(), lattice.first.to(torch.int32),
                     lattice.last.to(torch.int32)]
        self.cells = (occupancy.cells.to(origins.device).contiguous().view(torch.uint8) if occupancy is not None
                      else torch.zeros(1, dtype=torch.uint8, device=origins.device))
        host_min, host_max = grid._host_box
        extent = host_max - host_min
        upper = (res - 1).float()
        self.constants = [lattice.step, early_stop, grid.density_scale, MAX_SAMPLE_OPTICAL_DEPTH,
                          *host_min.tolist(), *extent.tolist(), *upper.tolist(), *(extent / upper).tolist(),
                          *(res - 2).float().tolist(), int(res[1] * res[2]), int(res[2]), int(cells[1] * cells[2]),
                          int(cells[2])]
        self.skip_empty = occupancy is not None
        self.n_rays = origins.shape[0]

    def run(self, features: torch.Tensor, grad_features: torch.Tensor, outputs: list[torch.Tensor],
            grads: list[torch.Tensor], backward: bool) -> None:
        """One kernel over every ray: outputs (Σw·colour, Σw, Σw·t, count, float64 totals), the incoming gradients."""
        # Triton launches on the current CUDA device: the tensors' own, where a stage runs on "cuda:1".
        with torch.cuda.device(features.device) if features.is_cuda else contextlib.nullcontext():
            _march[(triton.cdiv(self.n_rays, RAYS_PER_PROGRAM),)](
                *self.rays, features, self.cells, grad_features, *outputs, *grads, self.n_rays, *self.constants,
                SKIP_EMPTY=self.skip_empty, BACKWARD=backward, BLOCK=RAYS_PER_PROGRAM, num_warps=4)


class _FusedMarch(torch.autograd.Function):
    """features (M, 4) -> (Σw·colour (N, 3), Σw (N,), Σw·t (N,), samples (N,) int32): see :func:`march`."""

    @staticmethod
    def forward(ctx, features: torch.Tensor, launch: _Launch):
        n, device = launch.n_rays, features.device
        outputs = [torch.zeros(n, 3, device=device), torch.zeros(n, device=device), torch.zeros(n, device=device),
                   torch.zeros(n, dtype=torch.int32, device=device), torch.zeros(n, 5, dtype=torch.float64, device=device)]
        features = features.contiguous()
        if n:
            launch.run(features, features, outputs, outputs[:3], backward=False)
        ctx.launch = launch
        ctx.save_for_backward(features, outputs[4])
        ctx.mark_non_differentiable(outputs[3])
        return tuple(outputs[:4])

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_rgb, grad_opacity, grad_depth, _grad_count):
        features, totals = ctx.saved_tensors
        grad_features = torch.zeros_like(features)
        if ctx.launch.n_rays:
            grads = [g.contiguous() for g in (grad_rgb, grad_opacity, grad_depth)]
            unused = features.new_empty(0)  # the forward's outputs, which the backward does not write
            ctx.launch.run(features, grad_features, [unused, unused, unused, unused, totals], grads, backward=True)
        return grad_features, None


def march(
    grid: VoxelGrid,
    origins: torch.Tensor,
    directions: torch.Tensor,
    lattice: RayLattice,
    occupancy: Occupancy | None,
    early_stop: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Composite rays (N, 3) (unit ``directions``) through ``grid``'s ReLU field along ``lattice``: (Σw·colour (N, 3),
    Σw (N,), Σw·t (N,), density evaluations (0-d int64)), differentiable in ``grid.flat_features``.

    The samples are those of :meth:`VoxelGrid.ray_samples` with the same ``occupancy`` and ``early_stop``; a ray
    stops where its transmittance reaches ``early_stop`` (0: where it underflows, past which no sample weighs
    anything), so a NaN behind that point is not seen (the packed path's density probe of every sample sees it).
    The count is a tensor: reading it would wait for the kernel.
    """
    launch = _Launch(grid, origins, directions, lattice, occupancy, early_stop)
    colour, opacity, depth, count = _FusedMarch.apply(grid.flat_features, launch)
    return colour, opacity, depth, count.sum()
