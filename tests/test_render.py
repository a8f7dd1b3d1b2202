"""Renderer against analytic answers: slabs, empty grids, a sphere's silhouette, gradients, skipping."""

from __future__ import annotations

import dataclasses
import math
import re

import pytest
import torch
import torch.nn.functional as F
from torch.utils._python_dispatch import TorchDispatchMode

from voxe_core import grid as grid_module
from voxe_core.backbones import load_grid
from voxe_core.cameras import Cameras, camera_rays, look_at, ring_poses, spherical_poses
from voxe_core.grid import Occupancy, VoxelGrid, _WeightedGather, ray_box_intersection, unit_directions
from voxe_core.render import MIN_STEP_RATIO, RenderConfig, composite, grid_field, render_image, render_rays
from voxe_core.scene_grid import SceneGrid
from voxe_core.tensorio import FormatError, save_tensors
from voxe_core.volrend import RaySamples


def uniform_grid(raw_density: float, resolution: int = 8, color_logit: float = 0.0, **kwargs) -> VoxelGrid:
    grid = VoxelGrid(resolution, init_density=raw_density, **kwargs)
    with torch.no_grad():
        grid.features[..., 1:] = color_logit
    return grid


def sphere_grid(resolution=48, radius=0.8, inside=5.0, outside=-1.0) -> VoxelGrid:
    grid = VoxelGrid(resolution)
    axis = torch.linspace(-1.5, 1.5, resolution)
    x, y, z = torch.meshgrid(axis, axis, axis, indexing="ij")
    inside_mask = (x**2 + y**2 + z**2).sqrt() < radius
    with torch.no_grad():
        grid.features[..., 0] = torch.where(inside_mask, inside, outside)
    return grid


@pytest.mark.parametrize(
    "origin,direction",
    [
        ((-3.0, 0.1, 0.2), (1.0, 0.0, 0.0)),  # axis-parallel, full 3-unit chord
        ((-3.0, -3.0, 0.3), (1.0, 1.0, 0.0)),  # diagonal in a plane
        ((0.2, -0.4, 4.0), (0.0, 0.0, -1.0)),  # from above
    ],
)
def test_uniform_slab_transmittance_is_exp_minus_sigma_length(origin, direction):
    grid = uniform_grid(0.01)
    sigma = 0.01 * grid.density_scale
    o = torch.tensor([origin])
    d = torch.nn.functional.normalize(torch.tensor([direction]), dim=-1)
    t_near, t_far = ray_box_intersection(o, d, grid.bbox_min, grid.bbox_max)
    length = float(t_far - t_near)
    for skip in (True, False):
        out = render_rays(grid, o, d, RenderConfig(background=(0.0, 0.0, 0.0), skip_empty=skip))
        assert out.opacity.item() == pytest.approx(1 - math.exp(-sigma * length), abs=1e-5)
        # Uniform colour logit 0 -> sigmoid 0.5 on a black background.
        assert out.rgb[0, 0].item() == pytest.approx(0.5 * (1 - math.exp(-sigma * length)), abs=1e-5)


@pytest.mark.parametrize("length", [1e-40, 1e-38, 1e-23, 1e-21, 1e-8, 2.0, 1e20, 3e38])
def test_a_direction_of_any_float32_length_renders_as_its_unit_direction(length):
    """unit_directions scales each direction by its largest component before squaring it: its squares had
    underflowed or overflowed float32 (1e-23 long came out 1e7 long, 1e20 long as the zero direction, no ray)."""
    d = torch.tensor([[0.0, 0.6, 0.8]]) * length
    assert torch.allclose(unit_directions(d), torch.tensor([[0.0, 0.6, 0.8]]), atol=1e-6)
    grid, o = uniform_grid(0.01), torch.tensor([[0.2, -3.0, -4.0]])
    out = render_rays(grid, o, d, RenderConfig(background=(0.0, 0.0, 0.0)))
    reference = render_rays(grid, o, torch.tensor([[0.0, 0.6, 0.8]]), RenderConfig(background=(0.0, 0.0, 0.0)))
    assert out.opacity.item() == pytest.approx(reference.opacity.item(), rel=1e-5)
    assert out.opacity.item() > 0.01


def test_slab_chord_lengths_are_exact_for_known_geometry():
    o = torch.tensor([[-3.0, 0.0, 0.0], [0.0, 0.0, 0.0], [-3.0, 2.0, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
    t_near, t_far = ray_box_intersection(o, d, torch.full((3,), -1.5), torch.full((3,), 1.5))
    assert torch.allclose(t_far - t_near, torch.tensor([3.0, 1.5, -2.0]).clamp_min(-10), atol=1e-6) or (
        t_far[2] <= t_near[2]
    )
    assert float(t_far[0] - t_near[0]) == pytest.approx(3.0)
    assert float(t_far[1] - t_near[1]) == pytest.approx(1.5)  # camera inside: starts at 0
    assert t_far[2] <= t_near[2]  # misses the box
    inside_still = ray_box_intersection(torch.tensor([[0.1, 0.2, 0.3]]), torch.zeros(1, 3), torch.full((3,), -1.5),
                                        torch.full((3,), 1.5))
    assert inside_still[1] <= inside_still[0]  # a zero direction from inside is no ray (not a 1e12-unit chord)
    out = render_rays(uniform_grid(0.01), torch.tensor([[0.1, 0.2, 0.3]]), torch.zeros(1, 3),
                      RenderConfig(background=(0.2, 0.4, 0.6)))
    assert out.samples == 0 and torch.equal(out.rgb, torch.tensor([[0.2, 0.4, 0.6]]))


def test_empty_grid_renders_the_background_exactly_with_no_samples():
    grid = uniform_grid(-1.0)
    cams = Cameras.from_fov(look_at(torch.tensor([[0.0, -4.0, 1.0]])), 0.7, 16, 12)
    for background in [(1.0, 1.0, 1.0), (0.2, 0.4, 0.6)]:
        out = render_image(grid, cams, 0, RenderConfig(background=background))
        assert torch.equal(out.rgb, torch.tensor(background).expand(12, 16, 3))
        assert out.samples == 0
        assert torch.equal(out.depth, torch.zeros(12, 16))


def test_sphere_silhouette_matches_the_analytic_disc():
    radius = 0.8
    grid = sphere_grid(radius=radius)
    distance = 4.0
    cams = Cameras.from_fov(look_at(torch.tensor([[0.0, -distance, 0.0]])), 0.8, 48, 48)
    out = render_image(grid, cams, 0, RenderConfig(background=(1.0, 1.0, 1.0)))
    origins, directions = camera_rays(cams, 0)
    # Distance from the sphere centre to each pixel's ray.
    miss_distance = torch.linalg.cross(directions, -origins, dim=-1).norm(dim=-1).reshape(48, 48)
    voxel = float(grid.voxel_size[0])
    inside = miss_distance < radius - 1.5 * voxel
    outside = miss_distance > radius + 1.5 * voxel
    assert inside.sum() > 200 and outside.sum() > 200
    assert out.opacity[inside].min() > 0.99
    assert out.opacity[outside].max() < 1e-6
    # The front surface sits at distance - radius along the central ray.
    assert out.depth[24, 24].item() == pytest.approx(distance - radius, abs=1.5 * voxel)


def test_skipping_matches_the_dense_path_on_a_sparse_grid():
    torch.manual_seed(0)
    grid = sphere_grid(resolution=32, radius=0.6)
    with torch.no_grad():
        grid.features[..., 0] += 0.3 * torch.randn(32, 32, 32).clamp_max(0)  # ragged, still sparse
        grid.features[..., 1:] = torch.randn(32, 32, 32, 3)
    cams = Cameras.from_fov(look_at(torch.tensor([[1.0, -3.5, 1.5]])), 0.9, 24, 24)
    exact = RenderConfig(sigma_threshold=0.0, early_stop=0.0)
    dense = render_image(grid, cams, 0, RenderConfig(skip_empty=False, early_stop=0.0))
    sparse = render_image(grid, cams, 0, exact)
    assert sparse.samples * 3 < dense.samples
    assert torch.allclose(sparse.rgb, dense.rgb, atol=2e-5)
    default = render_image(grid, cams, 0, RenderConfig())
    assert torch.allclose(default.rgb, dense.rgb, atol=1e-3)


def _packed_samples_as_d2ce580(grid, occupancy, origins, directions, lattice, segments, n_segments, ray_offset):
    """``voxe_core.grid._packed_samples`` as d2ce580 wrote it, the reference: every sample's t corrected by
    offset·(step − δ), k·step formed twice, each step a fresh tensor."""
    kept = torch.arange(segments.shape[1])[None, :] < n_segments[:, None]
    row, column = kept.nonzero().unbind(1)
    seg_ray = row + ray_offset
    k = segments[row, column][:, None] * grid_module.SEGMENT + torch.arange(grid_module.SEGMENT)
    step = lattice.step
    inside = ((k >= lattice.first.index_select(0, seg_ray)[:, None])
              & (k < lattice.last.index_select(0, seg_ray)[:, None]))
    delta = (lattice.length.index_select(0, seg_ray)[:, None] - k * step).clamp(0.0, step)
    t = lattice.start.index_select(0, seg_ray)[:, None] + k * step \
        - lattice.offset.index_select(0, seg_ray)[:, None] * (step - delta)
    points = (origins.index_select(0, seg_ray)[:, None, :]
              + t[..., None] * directions.index_select(0, seg_ray)[:, None, :])
    if occupancy is not None:
        inside &= occupancy.occupied(grid.cell_index(points))
    pick = inside.reshape(-1).nonzero().squeeze(1)
    ray = seg_ray.index_select(0, torch.div(pick, grid_module.SEGMENT, rounding_mode="floor"))
    return (ray, t.reshape(-1).index_select(0, pick), delta.reshape(-1).index_select(0, pick),
            points.reshape(-1, 3).index_select(0, pick))


@pytest.mark.parametrize("step_ratio", [0.5, 1.0, 1.7])
def test_the_sampler_places_every_sample_as_the_reference_formula_does(step_ratio, monkeypatch):
    """The packed sampler (its last-sample correction computed in place, k·step once) renders and differentiates
    bit for bit as d2ce580's formula: a random scene, jittered, with and without skipping, in one pass and in
    several."""
    torch.manual_seed(5)
    grid = VoxelGrid(20)
    with torch.no_grad():
        grid.features[..., 0] = torch.randn(20, 20, 20) - 0.3
        grid.features[..., 1:] = torch.randn(20, 20, 20, 3)
    grid.flat_features.requires_grad_(True)
    origins, directions = camera_rays(Cameras.from_fov(look_at(torch.tensor([[1.0, -3.5, 1.5]])), 0.9, 16, 16), 0)
    inside = torch.rand(64, 3) * 2.8 - 1.4, torch.randn(64, 3)  # and rays from within the box
    origins, directions = torch.cat([origins, inside[0]]), torch.cat([directions, unit_directions(inside[1])])

    def render(samples_per_pass, skip_empty):
        config = RenderConfig(step_ratio=step_ratio, skip_empty=skip_empty, sigma_threshold=0.05,
                              samples_per_pass=samples_per_pass, early_stop=1e-3)
        out = render_rays(grid, origins, directions, config, generator=torch.Generator().manual_seed(7))
        grid.flat_features.grad = None
        (out.rgb.sum() + out.opacity.sum() + 0.1 * out.depth.sum()).backward()
        return [out.rgb, out.opacity, out.depth, grid.flat_features.grad]

    for samples_per_pass in (None, 2000):
        for skip_empty in (False, True):
            got = render(samples_per_pass, skip_empty)
            with monkeypatch.context() as patched:
                patched.setattr(grid_module, "_packed_samples", _packed_samples_as_d2ce580)
                expected = render(samples_per_pass, skip_empty)
            assert all(torch.equal(a, b) for a, b in zip(got, expected)), (samples_per_pass, skip_empty)
    # the samples themselves
    offsets = torch.rand(origins.shape[0])
    got = list(grid.ray_samples(origins, directions, offsets, step_ratio))
    monkeypatch.setattr(grid_module, "_packed_samples", _packed_samples_as_d2ce580)
    expected = list(grid.ray_samples(origins, directions, offsets, step_ratio))
    assert len(got) == len(expected) == 1
    for name in ("ray", "t", "delta", "points"):
        assert torch.equal(getattr(got[0], name), getattr(expected[0], name)), name


@pytest.mark.parametrize("step_ratio", [0.3, 0.8, 2.5])
def test_segment_skipping_keeps_every_sample_near_isolated_voxels(step_ratio):
    """Scattered single occupied vertices in an anisotropic box: the block test must drop no sample that counts."""
    torch.manual_seed(2)
    grid = VoxelGrid((37, 23, 51), bbox_min=(-1.2, -0.7, -1.5), bbox_max=(1.3, 0.9, 1.4), init_density=-1.0)
    with torch.no_grad():
        picks = torch.randint(0, 37 * 23 * 51, (40,))
        grid.flat_features[picks, 0] = 4.0 * torch.rand(40) + 0.5
        grid.flat_features[:, 1:] = torch.randn(37 * 23 * 51, 3)
    cams = Cameras.from_fov(look_at(torch.tensor([[2.0, -3.0, 1.2]])), 0.9, 40, 40)
    dense = render_image(grid, cams, 0, RenderConfig(step_ratio=step_ratio, skip_empty=False, early_stop=0.0))
    sparse = render_image(grid, cams, 0, RenderConfig(step_ratio=step_ratio, sigma_threshold=0.0, early_stop=0.0))
    assert dense.opacity.max() > 0.05  # the voxels are in view
    assert sparse.samples * 10 < dense.samples
    assert torch.allclose(sparse.rgb, dense.rgb, atol=2e-5)
    assert torch.allclose(sparse.opacity, dense.opacity, atol=2e-5)


def test_packed_transmittance_is_each_rays_own_with_gaps_and_single_samples():
    """Rays with no samples between others, one-sample rays and long ones: each sample sees only its own ray's
    optical depth in front of it (the first sample of every ray sees none)."""
    from voxe_core.volrend import transmittance

    g = torch.Generator().manual_seed(4)
    counts = torch.tensor([3, 0, 1, 0, 0, 7, 1, 1, 12, 0, 2])
    ray = torch.repeat_interleave(torch.arange(len(counts)), counts)
    optical = torch.rand(ray.numel(), generator=g) * 2
    expected = torch.cat([torch.exp(-(torch.cumsum(o.double(), 0) - o.double())).float()
                          for o in optical.split(counts[counts > 0].tolist())])
    assert torch.allclose(transmittance(optical, ray), expected, rtol=1e-6, atol=0)
    assert transmittance(optical[:0], ray[:0]).shape == (0,)


def test_a_ray_packed_behind_saturated_rays_keeps_its_own_transmittance():
    # Rays share one prefix sum of optical depth; ray 1's ~1e6 must not swallow ray 2's ~1e-3 per sample.
    grid = uniform_grid(1e-4, resolution=32)
    with torch.no_grad():
        grid.features[:, :, :16, 0] = 1e3  # z < 0: saturated, optical depth per sample clamped at 1e4
    o = torch.tensor([[-3.0, 0.1, -0.7], [-3.0, 0.1, 0.7]])
    d = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    config = RenderConfig(skip_empty=False, early_stop=0.0)
    both = render_rays(grid, o, d, config)
    alone = render_rays(grid, o[1:], d[1:], config)
    sigma = 1e-4 * grid.density_scale
    assert both.opacity[0].item() == 1.0
    assert both.opacity[1].item() == pytest.approx(1 - math.exp(-sigma * 3.0), rel=1e-5)
    assert torch.equal(both.opacity[1:], alone.opacity) and torch.equal(both.rgb[1:], alone.rgb)


def test_a_ray_composited_behind_thousands_of_opaque_rays_is_the_ray_composited_alone():
    """One pass: 3,000 opaque rays (~330 samples each at the clamped optical depth 1e4, a running sum near 1e10),
    then a faint ray of 500 samples. Its pixel, opacity, depth and density gradients are those it gets alone:
    the prefix sum's rounding near 1e10 (~1e-6 an addition) had put it 3e-6 off in its pixel and up to 8e-4 in a
    sample's density gradient."""
    g = torch.Generator().manual_seed(3)
    lengths = torch.randint(165, 495, (3000,), generator=g)
    n_opaque, n = int(lengths.sum()), 500

    def composite_last_ray(opaque_rays: int):
        hidden = int(lengths[:opaque_rays].sum())
        ray = torch.cat([torch.arange(opaque_rays).repeat_interleave(lengths[:opaque_rays]),
                         torch.full((n,), opaque_rays)])
        t = torch.cat([torch.rand(hidden, generator=torch.Generator().manual_seed(4)), torch.linspace(0.5, 3.0, n)])
        delta = torch.full((hidden + n,), 0.005)
        sigma = torch.cat([torch.full((hidden,), 1e7), 2.0 * faint]).requires_grad_()
        colour = torch.cat([torch.rand(hidden, 3, generator=torch.Generator().manual_seed(5)), faint_colour])
        samples = RaySamples(ray, t, delta, torch.zeros(hidden + n, 3))
        out = composite([samples], lambda points: (sigma, colour), opaque_rays + 1, torch.ones(3))
        (out.rgb[-1].sum() + out.opacity[-1] + 0.1 * out.depth[-1]).backward()
        return out.rgb[-1].detach(), out.opacity[-1].detach(), out.depth[-1].detach(), sigma.grad[hidden:]

    faint, faint_colour = torch.rand(n, generator=g), torch.rand(n, 3, generator=g)
    assert n_opaque > 900_000
    behind, alone = composite_last_ray(3000), composite_last_ray(0)
    assert 0.9 < float(alone[1]) < 0.99  # neither transparent nor opaque: every sample's gradient counts
    for got, expected in zip(behind, alone):
        torch.testing.assert_close(got, expected, rtol=1e-7, atol=0)


def test_a_sample_of_no_length_adds_no_optical_depth_however_dense():
    """A zero path length at an infinite density (a raw 1e38, overflowing once scaled) had made the optical depth
    inf · 0 = NaN, so the pixel and every gradient NaN. The sample weighs nothing: the render and its gradients are
    those of the same samples without it, in front of a ray's other samples and behind them."""
    def render(keep_empty: bool):
        grid = VoxelGrid(4, features=torch.zeros(4, 4, 4, 4))
        with torch.no_grad():
            grid.features[:2, ..., 0] = 1e38  # σ = inf in float32
            grid.features[2:, ..., 0] = 0.02
            grid.features[..., 1:] = torch.linspace(-1.0, 1.0, 4 * 4 * 4 * 3).reshape(4, 4, 4, 3)
        ray = torch.tensor([0, 0, 0, 1, 1, 1])
        t = torch.tensor([0.2, 0.7, 1.2, 0.2, 0.7, 1.2])
        delta = torch.tensor([0.0, 0.5, 0.5, 0.5, 0.5, 0.0])
        points = torch.tensor([[-1.0, 0.2, 1.1], [1.0, 0.3, -0.6], [0.7, 1.2, 0.9],  # x < -0.5: σ = inf
                               [1.1, -0.6, 0.1], [0.9, 1.4, -1.2], [-0.8, -0.2, 1.2]])
        keep = torch.ones(6, dtype=torch.bool) if keep_empty else delta > 0
        samples = RaySamples(ray[keep], t[keep], delta[keep], points[keep])
        out = composite([samples], grid_field(grid), 2, torch.ones(3))
        (out.rgb.sum() + out.opacity.sum() + out.depth.sum()).backward()
        assert bool(grid.activate_density(grid.interpolate(points[[0, 5]])[:, 0]).isinf().all())
        return out.rgb.detach(), out.opacity.detach(), out.depth.detach(), grid.flat_features.grad

    with_empty, without = render(True), render(False)
    assert torch.isfinite(with_empty[0]).all() and torch.isfinite(with_empty[3]).all()
    for got, expected in zip(with_empty, without):
        torch.testing.assert_close(got, expected, rtol=0, atol=0)


def test_early_stopping_changes_a_pixel_by_at_most_the_threshold_and_saves_samples():
    grid = sphere_grid()
    cams = Cameras.from_fov(look_at(torch.tensor([[0.3, -4.0, 0.8]])), 0.6, 24, 24)
    exact = render_image(grid, cams, 0, RenderConfig(early_stop=0.0))
    stopped = render_image(grid, cams, 0, RenderConfig(early_stop=1e-4))
    assert (stopped.rgb - exact.rgb).abs().max() <= 1e-4
    # The density-only pass probes every occupied sample; the evaluated ones stop at the surface.
    assert stopped.samples < 2 * exact.samples


def test_gradient_matches_finite_differences():
    torch.manual_seed(1)
    grid = VoxelGrid(4, activation="softplus")
    with torch.no_grad():
        grid.features.copy_(0.05 * torch.randn(4, 4, 4, 4))
    o = torch.tensor([[-3.0, 0.13, -0.21], [0.31, -3.0, 0.07]])
    d = torch.nn.functional.normalize(torch.tensor([[1.0, 0.1, 0.05], [0.05, 1.0, -0.1]]), dim=-1)
    config = RenderConfig(skip_empty=False, early_stop=0.0)
    weights = torch.tensor([[0.3, -0.7, 0.2], [1.0, 0.4, -0.5]])

    def objective() -> torch.Tensor:
        return (render_rays(grid, o, d, config).rgb * weights).sum()

    objective().backward()
    analytic = grid.flat_features.grad.view(4, 4, 4, 4).clone()
    eps = 1e-3
    flat = grid.flat_features.data.view(-1)
    picks = analytic.view(-1).abs().argsort(descending=True)[:12]
    for index in picks.tolist():
        saved = flat[index].item()
        with torch.no_grad():
            flat[index] = saved + eps
            plus = objective().item()
            flat[index] = saved - eps
            minus = objective().item()
            flat[index] = saved
        numeric = (plus - minus) / (2 * eps)
        assert numeric == pytest.approx(analytic.view(-1)[index].item(), rel=2e-2, abs=1e-4)


def _embedding_interpolation(grid: VoxelGrid, points: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
    """The interpolation through F.embedding's own backward (one add per corner index), as the renderer had it."""
    index, weights = grid.trilinear_corners(points, features.dtype)
    return torch.einsum("nk,nkc->nc", weights, F.embedding(index, features.reshape(-1, features.shape[-1])))


def test_the_interpolation_backward_adds_into_the_grid_with_embeddings_bits():
    """One index_add instead of F.embedding's dense backward: the same values and gradients, bit for bit on the CPU
    (both add in index order), with corners shared by many points and points clamped onto the box; the grid's own
    features and attention-grid features alike. Under bf16 autocast the values keep their bits and the gradients
    come nearer the fp32 ones (the old backward rounded each product to bf16; the gather keeps them in fp32)."""
    g = torch.Generator().manual_seed(3)
    grid = VoxelGrid(6)
    with torch.no_grad():
        grid.features.copy_(torch.randn(6, 6, 6, 4, generator=g))
    points = torch.cat([torch.rand(4000, 3, generator=g) * 3.6 - 1.8, torch.full((50, 3), 0.1)])
    upstream = torch.randn(points.shape[0], 4, generator=g)
    attention = torch.randn(6, 6, 6, 1, generator=g)
    results = {}
    for autocast in (False, True):
        for name, interpolate in (("gather", grid.interpolate), ("embedding", lambda p, f=grid.flat_features:
                                                                  _embedding_interpolation(grid, p, f))):
            grid.flat_features.grad = None
            table = attention.clone().requires_grad_(True)
            with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
                own, scalar = interpolate(points), interpolate(points, table)
            (own.float() * upstream).sum().backward()
            scalar.float().pow(2).sum().backward()
            results[name, autocast] = own, scalar, grid.flat_features.grad, table.grad
    for new, old in zip(results["gather", False], results["embedding", False]):
        assert new.dtype == old.dtype and torch.equal(new, old)
    for new, old in zip(results["gather", True][:2], results["embedding", True][:2]):
        assert new.dtype == old.dtype == torch.bfloat16 and torch.equal(new, old)
    for new, old, exact in zip(results["gather", True][2:], results["embedding", True][2:], results["gather", False][2:]):
        assert (new - exact).abs().max() < (old - exact).abs().max()


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_a_half_precision_grid_renders_as_the_float32_grid_of_its_values(dtype):
    """Regression: render_rays says it computes in float32, but a grid moved to float16 or bfloat16 (``.to(dtype)``)
    had interpolated in its own precision, weights and products: a bf16 sphere's depth came out up to 3.9 units off
    and its colours 1e-3, the interpolated features 0.018. The float32 grid holding the same rounded values renders
    the same pixels now, and the half grid's gradient is that grid's, rounded to its dtype."""
    g = torch.Generator().manual_seed(0)
    x, y, z = torch.meshgrid(*(torch.linspace(-1.5, 1.5, 32),) * 3, indexing="ij")
    features = torch.cat([((1.0 - (x**2 + y**2 + z**2).sqrt()).clamp_min(-0.2) * 0.5)[..., None],
                          torch.randn(32, 32, 32, 3, generator=g)], -1).to(dtype)
    half = VoxelGrid(32, features=features.float()).to(dtype)
    exact = VoxelGrid(32, features=features.float())
    assert half.flat_features.dtype == dtype
    cams = Cameras.from_fov(spherical_poses(torch.tensor([30.0]), torch.tensor([20.0])), 0.69, 32, 32)
    origins, directions = camera_rays(cams, 0)
    renders = [render_rays(grid, origins, directions) for grid in (half, exact)]
    for name in ("rgb", "opacity", "depth"):
        got, want = (getattr(out, name) for out in renders)
        assert got.dtype == torch.float32 and torch.allclose(got, want, rtol=0, atol=1e-6), name
    points = torch.rand(5000, 3, generator=g) * 3.0 - 1.5
    assert torch.equal(half.interpolate(points), exact.interpolate(points))
    for grid in (half, exact):
        render_rays(grid, origins, directions).rgb.sum().backward()
    assert half.flat_features.grad.dtype == dtype
    assert torch.equal(half.flat_features.grad, exact.flat_features.grad.to(dtype))


@pytest.mark.parametrize("distance, dtype", [(1e5, torch.float32), (1e7, torch.float32), (3e7, torch.float32),
                                             (1e9, torch.float64)])
def test_rays_from_far_away_render_the_box_they_pass_through(distance, dtype):
    """Regression: in float32 a far origin's rounding had become the slab test's and the samples' (float32's spacing
    at 1e7 is 1 unit): the opacity through a uniform box was 0.31 off at 1e7 units (the path ~2 units off in 3) and
    rays through the box missed it at 3e7. Their origins are moved to the box in float64 first; the depth is still
    the distance from the given origin, to float32 rounding. float64 rays are moved before they are rounded: from
    1e9 units their float32 origins are 64 units apart."""
    grid = VoxelGrid(16, init_density=0.01)
    sigma = float(grid.activate_density(torch.tensor(0.01)))
    g = torch.Generator().manual_seed(0)
    towards = torch.nn.functional.normalize(torch.randn(300, 3, generator=g, dtype=torch.float64), dim=-1)
    aside = (torch.rand(300, 3, generator=g, dtype=torch.float64) - 0.5) * 2.0
    aside -= (aside * towards).sum(-1, keepdim=True) * towards
    origins, directions = (aside + towards * distance).to(dtype), (-towards).to(dtype)
    out = render_rays(grid, origins, directions)
    near, far = ray_box_intersection(origins.double(), directions.double(), grid.bbox_min.double(),
                                     grid.bbox_max.double())
    path = (far - near).clamp_min(0.0)
    assert (path > 1.0).sum() > 100  # most rays cross the box
    assert torch.allclose(out.opacity.double(), 1.0 - torch.exp(-sigma * path), rtol=0, atol=1e-5)
    crossing = path > 1e-3
    assert ((out.depth.double() - near)[crossing] / path[crossing]).min() >= -1e-6 * distance
    assert (out.depth.double() - far)[crossing].max() <= 1e-6 * distance  # within the box, seen from the origin
    closer = (origins.double() + (distance - 4.0) * directions.double()).float()  # the same lines, 4 units out
    assert torch.allclose(render_rays(grid, closer, directions.float()).rgb, out.rgb, rtol=0, atol=1e-5)



@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16])
def test_half_precision_rays_from_far_away_are_moved_to_the_box_in_float32(dtype):
    """Regression: far rays moved to the box had been rounded back to their own precision there, so half rays from
    20 units entered a uniform box up to 1e-3 off their lines (opacity 9e-5 off, 4e-7 when moved to float32, as
    the renderer computes)."""
    grid = VoxelGrid(16, init_density=0.01)
    sigma = float(grid.activate_density(torch.tensor(0.01)))
    g = torch.Generator().manual_seed(0)
    towards = F.normalize(torch.randn(300, 3, generator=g, dtype=torch.float64), dim=-1)
    aside = (torch.rand(300, 3, generator=g, dtype=torch.float64) - 0.5) * 2.0
    aside -= (aside * towards).sum(-1, keepdim=True) * towards
    origins, directions = (aside + towards * 20.0).to(dtype), (-towards).to(dtype)
    out = render_rays(grid, origins, directions)
    near, far = ray_box_intersection(origins.double(), F.normalize(directions.double(), dim=-1),
                                     grid.bbox_min.double(), grid.bbox_max.double())
    path = (far - near).clamp_min(0.0)
    assert (path > 1.0).sum() > 100
    assert torch.allclose(out.opacity.double(), 1.0 - torch.exp(-sigma * path), rtol=0, atol=2e-6)


def test_rays_of_a_camera_at_the_papers_radius_are_not_moved_though_they_enter_past_the_diagonal():
    """Regression: a camera at radius 4.03 on the box's diagonal enters the far corners of a 3-unit box up to 5.5
    units away, past its 5.2-unit diagonal, and those rays had been moved to the box, their renders changed by
    rounding (up to 6e-6 in colour, 9e-6 in opacity). Only origins farther than the diagonal from the box move: these
    render bit for bit as the rays as given."""
    grid = VoxelGrid(16)
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        grid.flat_features.copy_(torch.randn(grid.flat_features.shape, generator=g))
    targets = torch.rand(20000, 3, generator=g) * 3.0 - 1.5
    corner = torch.tensor([1.5, -1.5, -1.5])  # near the far corner of a face the camera sees
    targets[:2000] = corner + torch.rand(2000, 3, generator=g) * torch.tensor([-0.2, 0.5, 0.5])
    origins = torch.full_like(targets, 4.0311 / math.sqrt(3.0))
    directions = F.normalize(targets - origins, dim=-1)
    near, far = ray_box_intersection(origins.double(), directions.double(), grid.bbox_min.double(),
                                     grid.bbox_max.double())
    assert ((near > grid.box_diagonal) & (far > near)).any()  # rays through the box entering past its diagonal
    config = RenderConfig(skip_empty=False, fused=False)
    out = render_rays(grid, origins, directions, config)
    offsets = torch.full((len(origins),), 0.5)
    samples = grid.ray_samples(origins, directions, offsets, config.step_ratio, None, config.pass_samples("cpu"),
                               config.early_stop)
    want = composite(samples, grid_field(grid), len(origins), torch.tensor(config.background).expand(3))
    for name in ("rgb", "opacity", "depth"):
        assert torch.equal(getattr(out, name), getattr(want, name)), name

class Ops(TorchDispatchMode):
    """The aten operations dispatched inside it, by name (what a launch-bound device pays for, one by one)."""

    def __init__(self):
        super().__init__()
        self.names = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.names.append(func.__name__)
        return func(*args, **(kwargs or {}))


def test_trilinear_weights_are_the_axis_weights_product_in_few_dispatches():
    """Each corner weighs (1 − f or f) per axis, multiplied x·y·z: on the CPU bit for bit in every dtype, for points
    inside, on the box's faces and clamped from outside; they sum to one, reproduce an affine field, and their
    derivative in the points is the product rule's. 15 dispatches build a float32 interpolation's corners (26 through
    a stack and broadcast views of it)."""
    g = torch.Generator().manual_seed(5)
    grid = VoxelGrid(7)
    points = torch.cat([torch.rand(3000, 3, generator=g) * 3.4 - 1.7, torch.tensor([[1.5] * 3, [-1.5] * 3])])
    for dtype in (torch.float32, torch.float16, torch.bfloat16, torch.float64):
        index, weights = grid.trilinear_corners(points, dtype)
        lattice = grid._lattice(points.device)
        u = torch.minimum(((points - grid.bbox_min) / lattice.extent * lattice.upper).clamp_min(0), lattice.upper)
        frac = (u - torch.minimum(u.long(), lattice.last_cell)).to(dtype)
        axis = [(1 - frac[:, i], frac[:, i]) for i in range(3)]
        expected = torch.stack([axis[0][a] * axis[1][b] * axis[2][c] for a in (0, 1) for b in (0, 1) for c in (0, 1)], 1)
        assert weights.dtype == dtype and torch.equal(weights, expected)
        assert (weights >= 0).all() and torch.allclose(weights.double().sum(1), torch.ones(len(points), dtype=torch.float64),
                                                       atol=2e-2 if dtype.itemsize == 2 else 1e-6)
    affine = torch.tensor([0.3, -1.2, 2.0])
    with torch.no_grad():
        x, y, z = torch.meshgrid(*(torch.linspace(-1.5, 1.5, 7),) * 3, indexing="ij")
        grid.features[..., 0] = 0.3 * x - 1.2 * y + 2.0 * z + 0.5
    inside = points.clamp(-1.5, 1.5)
    assert torch.allclose(grid.interpolate(inside)[:, 0], inside @ affine + 0.5, atol=1e-5)
    moving = (torch.rand(20, 3, generator=g, dtype=torch.float64) * 2.8 - 1.4).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: grid.trilinear_corners(p, torch.float64)[1], (moving,))
    with Ops() as ops:
        grid.trilinear_corners(points)
    assert len(ops.names) == 15


def test_a_nan_coordinate_on_any_axis_interpolates_to_nan_inside_the_grid():
    """Regression: a NaN truncated to INT64_MIN as the cell's index. Odd strides (35, 7, 1) kept it out of range on
    every axis: an IndexError on the CPU, a device-side assert on CUDA (even strides wrapped it onto row 0). The
    finite points beside it keep their values (bit for bit) and gradients (the NaN point's corners get 0 · NaN)."""
    g = torch.Generator().manual_seed(2)
    grid = VoxelGrid((6, 5, 7), features=torch.randn(6, 5, 7, 4, generator=g))
    finite = torch.rand(5, 3, generator=g) * 3 - 1.5
    upstream = torch.randn(5, 4, generator=g)
    alone = finite.clone().requires_grad_(True)
    (grid.interpolate(alone) * upstream).sum().backward()
    expected_points, expected_features = alone.grad, grid.flat_features.grad
    for axis in range(3):
        nan_point = torch.zeros(1, 3)
        nan_point[0, axis] = float("nan")
        index, weights = grid.trilinear_corners(nan_point)
        assert 0 <= int(index.min()) and int(index.max()) < grid.flat_features.shape[0] and weights.isnan().all()
        for sparse_grad in (False, True):
            grid.flat_features.grad = None
            moving = torch.cat([finite, nan_point]).requires_grad_(True)
            values = grid.interpolate(moving, sparse_grad=sparse_grad)
            assert values[-1].isnan().all() and torch.equal(values[:-1], grid.interpolate(finite))
            (values[:-1] * upstream).sum().backward()
            assert torch.allclose(moving.grad[:-1], expected_points, rtol=1e-6, atol=0)
            others = torch.ones(len(expected_features), dtype=torch.bool).index_fill_(0, index[0], False)
            assert torch.allclose(grid.flat_features.grad.to_dense()[others], expected_features[others], rtol=1e-6)
        density, colour = grid.query(nan_point)
        assert density.isnan().all() and colour.isnan().all()


def test_the_weighted_gather_backward_scatters_once_and_has_exact_derivatives():
    grid = VoxelGrid(5)
    out = grid.interpolate(torch.rand(300, 3) - 0.5)
    with Ops() as ops:
        out.sum().backward()
    assert "embedding_dense_backward.default" not in ops.names and ops.names.count("index_add_.default") == 1
    g = torch.Generator().manual_seed(0)
    table = torch.randn(7, 3, dtype=torch.float64, generator=g, requires_grad=True)
    index = torch.randint(0, 7, (5, 8), generator=g)
    weights = torch.rand(5, 8, dtype=torch.float64, generator=g, requires_grad=True)
    assert torch.autograd.gradcheck(_WeightedGather.apply, (table, index, weights))
    assert torch.autograd.gradgradcheck(_WeightedGather.apply, (table, index, weights))
    with torch.no_grad():  # points that carry gradient get the embedding path's, through the trilinear weights
        grid.features.copy_(torch.randn(5, 5, 5, 4, generator=g))
    points = torch.rand(300, 3, generator=g) - 0.5
    upstream = torch.randn(300, 4, generator=g)
    gradients = []
    for interpolate in (grid.interpolate, lambda p: _embedding_interpolation(grid, p, grid.flat_features)):
        moving = points.clone().requires_grad_(True)
        (interpolate(moving) * upstream).sum().backward()
        gradients.append(moving.grad)
    assert gradients[0].abs().max() > 0 and torch.allclose(*gradients, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("name, value", [
    ("step_ratio", 0.0), ("step_ratio", -0.5), ("step_ratio", math.nan), ("step_ratio", math.inf),
    ("step_ratio", 1e-9), ("samples_per_pass", 0), ("chunk_rays", 0), ("chunk_rays", 2.5), ("early_stop", 1.0),
    ("early_stop", -1e-4), ("early_stop", math.nan), ("sigma_threshold", -1e-3), ("sigma_threshold", math.nan),
    ("background", (1.0, math.nan, 1.0)),
])
def test_render_settings_that_render_blank_fail_deep_or_exhaust_memory_are_refused_by_name(name, value):
    """Regression: a step of 0, -0.5 or NaN rendered blank, samples_per_pass 0 raised ZeroDivisionError from the sampler
    and a step of 1e-9 took all the memory; nothing checked the settings."""
    with pytest.raises(ValueError, match=rf"^RenderConfig\.{name} must be .*, got {re.escape(repr(value))}$"):
        RenderConfig(**{name: value})
    with pytest.raises(ValueError, match=rf"RenderConfig\.{name}"):
        dataclasses.replace(RenderConfig(), **{name: value})


@pytest.mark.parametrize("name, value", [
    ("step_ratio", "0.5"), ("step_ratio", None), ("step_ratio", True), ("early_stop", "0"),
    ("sigma_threshold", None), ("samples_per_pass", True), ("chunk_rays", False), ("background", None),
    ("background", "white"), ("background", 1.0), ("skip_empty", "no"), ("fused", "false"),
    ("skip_empty", 0),
])
def test_render_settings_of_another_type_are_refused_by_name(name, value):
    """Regression: a string or None had been a TypeError naming no setting ("must be real number, not str", "'<='
    not supported between instances of 'float' and 'str'", "'NoneType' object is not iterable"), skip_empty="no" and
    fused="false" (true strings) had been taken and run as True, and True as a count or a step of 1."""
    with pytest.raises(ValueError, match=rf"^RenderConfig\.{name} must be .*, got {re.escape(repr(value))}$"):
        RenderConfig(**{name: value})
    assert RenderConfig(background=[0.0, 0.0], skip_empty=False, samples_per_pass=4).skip_empty is False


def test_the_render_settings_at_their_limits_render_the_slab():
    edge = RenderConfig(step_ratio=MIN_STEP_RATIO, samples_per_pass=1, chunk_rays=1, early_stop=0.0,
                        sigma_threshold=0.0)
    grid = uniform_grid(0.02)
    out = render_rays(grid, torch.tensor([[-3.0, 0.1, 0.2]]), torch.tensor([[1.0, 0.0, 0.0]]), edge)
    assert out.opacity.item() == pytest.approx(1 - math.exp(-0.02 * grid.density_scale * 3.0), abs=1e-5)


def test_an_int_index_keeps_one_camera_counting_from_the_end_when_negative():
    cams = Cameras.from_fov(look_at(torch.tensor([[3.0, 0, 0], [0, 3.0, 0], [0, 0, 3.0]])), 0.7, 8, 8)
    for index, position in ((0, 0), (2, 2), (-1, 2), (-3, 0)):
        assert len(cams[index]) == 1 and torch.equal(cams[index].c2w, cams.c2w[position:position + 1])
    for index in (3, -4):
        with pytest.raises(IndexError):
            cams[index]


@pytest.mark.parametrize("fov_x", [0.0, math.pi, 4.0, -0.5, math.nan, math.inf])
def test_a_field_of_view_outside_zero_to_pi_is_refused_wherever_it_is_given(fov_x):
    """0 had been a ZeroDivisionError and 4.0 a negative focal (a mirrored camera); the stages' configs and the
    turntable take the same angle."""
    from voxe_core.edit import EditConfig
    from voxe_core.export import turntable_cameras
    from voxe_core.refine.config import RefineConfig

    message = re.escape(f"fov_x must be in (0, pi) radians, got {fov_x}")
    for make in (lambda: Cameras.from_fov(look_at(torch.tensor([[0.0, -4.0, 0.0]])), fov_x, 4, 4),
                 lambda: EditConfig(fov_x=fov_x), lambda: RefineConfig(fov_x=fov_x),
                 lambda: turntable_cameras(1, fov_x=fov_x)):
        with pytest.raises(ValueError, match=message):
            make()
    assert float(Cameras.from_fov(torch.eye(4), math.pi - 1e-3, 4, 4).fx[0]) > 0  # just inside: a positive focal


@pytest.mark.parametrize("fov_x", [5e-324, 1e-300, 1e-40])
def test_a_field_of_view_too_narrow_for_a_float32_focal_is_refused_naming_it(fov_x):
    """Regression: 5e-324's tangent is 0 (a ZeroDivisionError) and 1e-40's focal, 4e40 pixels, overflowed float32
    (a RuntimeError from torch.full naming no setting)."""
    with pytest.raises(ValueError, match=re.escape(f"fov_x {fov_x} radians is too narrow: its focal length across "
                                                   "4 pixels")):
        Cameras.from_fov(torch.eye(4), fov_x, 4, 4)
    narrow = Cameras.from_fov(torch.eye(4), 1e-30, 4, 4)  # 4e30 pixels: held, every ray along the view axis
    assert float(narrow.fx[0]) == pytest.approx(4e30, rel=1e-6)
    assert torch.allclose(camera_rays(narrow, 0)[1], torch.tensor([0.0, 0.0, -1.0]).expand(16, 3))


@pytest.mark.parametrize("fov_x", [5e-324, 1e-40, 5e-37])
def test_the_stages_configs_refuse_a_field_of_view_too_narrow_for_their_renders_as_they_are_made(fov_x):
    """Regression: EditConfig(fov_x=1e-40) and RefineConfig's had been taken, and refused only at the first render
    (after the guidance had loaded), by the cameras. The focal is their render size's: 5e-37's fits 8 pixels, not 266."""
    from voxe_core.edit import EditConfig
    from voxe_core.refine.config import RefineConfig

    for make in (EditConfig, RefineConfig):
        with pytest.raises(ValueError, match=re.escape(f"fov_x {fov_x} radians is too narrow: its focal length "
                                                       "across 266 pixels")):
            make(fov_x=fov_x)
    assert EditConfig(fov_x=5e-37, render_size=8).fov_x == RefineConfig(fov_x=5e-37, render_size=8).fov_x == 5e-37
    assert float(Cameras.from_fov(torch.eye(4), 5e-37, 8, 8).fx[0]) == pytest.approx(1.6e37, rel=1e-6)


@pytest.mark.parametrize("distance", [1e-40, 1e-30, 1.0, 2e19, 1e30, 1e38])
@pytest.mark.parametrize("direction", [(1.0, 1.0, 1.0), (0.0, 0.0, 1.0), (0.0, 0.0, -1.0), (1e-7, 0.0, 1.0)])
def test_look_at_aims_a_rotation_at_its_target_from_any_distance(distance, direction):
    """Regression: float32's norm overflowed past about 1.8e19 and underflowed below 1e-19, and those cameras were
    refused as "at their target". Straight above or below the target (up parallel to the view) too."""
    unit = torch.tensor(direction, dtype=torch.float64)
    unit = unit / unit.norm()
    eye = (distance * unit).float()
    c2w = look_at(eye[None])[0].double()
    rotation = c2w[:3, :3]
    torch.testing.assert_close(rotation.T @ rotation, torch.eye(3, dtype=torch.float64), atol=1e-6, rtol=0)
    assert float(rotation.det()) == pytest.approx(1.0, abs=1e-6)
    torch.testing.assert_close(-rotation[:, 2], -unit, atol=1e-6, rtol=0)  # it looks at the origin
    assert torch.equal(c2w[:3, 3], eye.double())


@pytest.mark.parametrize("make, message", [
    (lambda: look_at(torch.tensor([[1.0, 2.0, 3.0]]), torch.tensor([1.0, 2.0, 3.0])),
     r"a camera at its target has no view direction: eye \[1.0, 2.0, 3.0\]"),
    (lambda: look_at(torch.tensor([[math.nan, 0.0, 4.0]])), r"must be finite, got eye \[\[nan, 0.0, 4.0\]\]"),
    (lambda: look_at(torch.tensor([[0.0, 0.0, 4.0]]), torch.tensor([math.inf, 0.0, 0.0])),
     "must be finite, got target"),
    (lambda: look_at(torch.tensor([[1e39, 0.0, 0.0]], dtype=torch.float64)),
     r"within float32's range \(3.4e38\), got eye"),
    # a float64 target that far: its distance had overflowed to inf, and the pose had come out with no view direction
    (lambda: look_at(torch.zeros(1, 3), torch.tensor([1e160, 0.0, 0.0], dtype=torch.float64)),
     r"within float32's range \(3.4e38\), got target"),
    # a ring of radius 4 around a point 1e7 (1e8) from the origin: float32 had rounded it to other places (to the
    # centre itself: "at its target")
    (lambda: ring_poses(4, 30.0, 4.0, centre=torch.tensor([1e7, 0.0, 0.0])),
     r"a camera at \[10000003.46\d*, 0.0, 2.0\] looking at \[10000000.0, 0.0, 0.0\] from 4 away cannot be placed "
     r"by a float32 pose \(which rounds its position by up to 0.596\): move the scene's origin near its object"),
    (lambda: ring_poses(4, 0.0, 4.0, centre=torch.tensor([1e8, 1e8, 0.0])), "cannot be placed by a float32 pose"),
])
def test_look_at_refuses_a_camera_it_cannot_aim_or_place_naming_why(make, message):
    with pytest.raises(ValueError, match=message):
        make()
    ring = ring_poses(4, 30.0, 4.0, centre=torch.tensor([1e3, -2e3, 50.0]))  # a capture's frame: placed and aimed
    aim = torch.tensor([1e3, -2e3, 50.0]) - ring[:, :3, 3]
    torch.testing.assert_close(-ring[:, :3, 2], aim / aim.norm(dim=-1, keepdim=True), atol=1e-4, rtol=0)


def test_camera_inside_the_box_and_non_finite_rays():
    grid = uniform_grid(0.02)
    sigma = 0.02 * grid.density_scale
    o = torch.tensor([[0.0, 0.0, 0.0], [float("nan"), 0.0, 0.0], [1.5, 0.0, 0.0]])
    d = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]])
    out = render_rays(grid, o, d, RenderConfig(background=(0.0, 0.0, 0.0)))
    assert out.opacity[0].item() == pytest.approx(1 - math.exp(-sigma * 1.5), abs=1e-5)
    assert out.opacity[1].item() == 0.0 and torch.isfinite(out.rgb).all()
    assert out.opacity[2].item() == pytest.approx(1 - math.exp(-sigma * 3.0), abs=1e-5)  # on the surface


def test_a_nan_density_stays_on_the_rays_that_meet_it():
    """Transmittance is one prefix sum over every ray of a pass: one NaN had turned every later ray NaN (the render
    below had 1,451 NaN pixels where 80 rays meet the vertex's cells), in the forward and the backward pass."""
    from voxe_core.volrend import transmittance

    ray = torch.tensor([0, 0, 1, 1, 1, 2, 2])
    optical = torch.tensor([0.5, 1.0, 0.25, float("nan"), 2.0, 1.0, 3.0], requires_grad=True)
    t = transmittance(optical, ray)
    expected = [1.0, math.exp(-0.5), 1.0, math.exp(-0.25), float("nan"), 1.0, math.exp(-1.0)]
    torch.testing.assert_close(t.detach(), torch.tensor(expected), equal_nan=True)
    t[[0, 1, 5, 6]].sum().backward()  # the clean rays' gradients stay finite
    assert torch.isfinite(optical.grad).all() and optical.grad[0] == pytest.approx(-math.exp(-0.5))

    grid = sphere_grid(24)
    cams = Cameras.from_fov(look_at(torch.tensor([[0.3, -3.5, 0.6]]), torch.zeros(1, 3)), 0.6, 64, 64)
    clean = render_image(grid, cams, 0, RenderConfig())
    with torch.no_grad():
        grid.features[12, 8, 12, 0] = float("nan")  # a vertex on the sphere's near side
    poisoned = render_image(grid, cams, 0, RenderConfig())
    bad = poisoned.rgb.isnan().any(-1)
    assert 0 < int(bad.sum()) < 120  # the rays through its 8 cells (80), not the pass behind them (1,451)
    torch.testing.assert_close(poisoned.rgb[~bad], clean.rgb[~bad], rtol=0, atol=1e-6)  # (float64 sums' rounding)


def test_one_slab_test_of_two_boxes_is_two_slab_tests():
    """The sampler intersects the grid's box and the occupied cells' box in one call: the same bits as two calls,
    degenerate rays included (axis-parallel, inside, non-finite, zero direction, missing), in 30 dispatches however
    many boxes (32 before both slabs' ends went through one product and one ``aminmax``, 26 before a ray in the
    box's upper face met it: tests/test_grid.py)."""
    g = torch.Generator().manual_seed(0)
    o = torch.cat([torch.randn(64, 3, generator=g) * 3, torch.tensor(
        [[0.0, 0, 0], [float("nan"), 0, 0], [0.0, 0, -3], [0.0, 0, -3], [5.0, 5, 5]])])
    d = torch.cat([torch.nn.functional.normalize(torch.randn(64, 3, generator=g), dim=-1), torch.tensor(
        [[1.0, 0, 0], [1.0, 0, 0], [0.0, 0, 1], [0.0, 0, 0], [1.0, 0, 0]])])
    boxes = torch.tensor([[-1.5, -1.5, -1.5], [-0.4, -0.2, -0.7]]), torch.tensor([[1.5, 1.5, 1.5], [0.3, 0.9, 0.1]])
    near, far = ray_box_intersection(o, d, *boxes)
    for b in range(2):
        one_near, one_far = ray_box_intersection(o, d, boxes[0][b], boxes[1][b])
        assert torch.equal(near[b], one_near) and torch.equal(far[b], one_far)
    assert (far[:, 64:] <= near[:, 64:])[:, [1, 3, 4]].all()  # non-finite, no direction, missing: no segment
    signed_zero = torch.where(d == 0, -0.0, d)  # a zero component's sign says nothing about the ray
    assert all(torch.equal(a, b) for a, b in zip(ray_box_intersection(o, signed_zero, *boxes), (near, far)))
    for box in (boxes, (boxes[0][0], boxes[1][0])):
        with Ops() as ops:
            ray_box_intersection(o, d, *box)
        assert len(ops.names) == 30


def test_the_slab_test_computes_in_the_rays_dtype_or_float32_for_half_rays():
    """float64 rays are tested in float64; half ones in float32, where float16's stand-in reciprocal had been
    1 / 0 and a ray lying in a face of the box had missed it (inf × 0: NaN), in the lower face as in the upper."""
    box = -torch.ones(3, dtype=torch.float64), torch.ones(3, dtype=torch.float64)
    o, d = torch.tensor([[0.9, 0.0, 0.0]], dtype=torch.float64), torch.tensor([[0.0, 0.0, 1e-12]], dtype=torch.float64)
    near, far = ray_box_intersection(o, d, *box)
    assert far.dtype == torch.float64 and far.item() == (1.0 - 0.9) / 1e-12  # x's stand-in reciprocal, float64's 1e-12
    near, far = ray_box_intersection(o.half(), d.half(), *(b.half() for b in box))
    assert far.dtype == near.dtype == torch.float32 and far.item() == near.item() == 0.0  # 1e-12 is 0 in fp16: no ray
    grazing = torch.tensor([[1.0, 0.0, -3.0], [-1.0, 0.5, -3.0], [0.5, 1.0, -3.0]])  # in the x = ±1 and y = 1 faces
    along_z = torch.tensor([[0.0, 0.0, 1.0]]).expand(3, 3)
    for dtype in (torch.float16, torch.bfloat16):
        for half_box in (False, True):
            box = tuple(b.to(dtype) if half_box else b.float() for b in (-torch.ones(3), torch.ones(3)))
            near, far = ray_box_intersection(grazing.to(dtype), along_z.to(dtype), *box)
            assert near.dtype == far.dtype == torch.float32, (dtype, half_box)
            assert near.tolist() == [2.0] * 3 and far.tolist() == [4.0] * 3, (dtype, half_box)


def test_saturated_density_has_finite_values_and_gradients():
    grid = uniform_grid(1e6)
    o, d = torch.tensor([[-3.0, 0.0, 0.0]]), torch.tensor([[1.0, 0.0, 0.0]])
    out = render_rays(grid, o, d, RenderConfig(background=(1.0, 1.0, 1.0)))
    out.rgb.sum().backward()
    assert out.opacity.item() == pytest.approx(1.0)
    assert out.rgb[0, 0].item() == pytest.approx(0.5, abs=1e-6)
    assert out.depth.item() == pytest.approx(1.5, abs=float(grid.voxel_size[0]))
    assert torch.isfinite(grid.flat_features.grad).all()


@pytest.mark.parametrize("backbone", ["relu_field", "scene"])
def test_a_float64_grid_renders_in_float32_as_its_float32_copy(backbone):
    """A grid cast to float64 (``grid.double()``, as for a reference) renders in float32, as every grid does, its
    gradient reaching the float64 features: its float64 samples had met the float32 sums in ``index_add``, which
    refused them (RuntimeError: self (Float) and source (Double) must have the same scalar type)."""
    grid = SceneGrid(8, init_density=0.01) if backbone == "scene" else uniform_grid(0.01)
    wide = grid.clone_grid().double()
    o, d = torch.tensor([[-3.0, 0.1, 0.2], [0.3, -3.0, 0.1]]), torch.tensor([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    outs = []
    for g in (grid, wide):
        out = render_rays(g, o, d, RenderConfig())
        (out.rgb.sum() + out.opacity.sum() + out.depth.sum()).backward()
        outs.append(out)
    assert wide.flat_features.grad.dtype == torch.float64
    for name in ("rgb", "opacity", "depth"):
        assert getattr(outs[1], name).dtype == torch.float32
        torch.testing.assert_close(getattr(outs[1], name), getattr(outs[0], name), rtol=1e-6, atol=1e-6)
    torch.testing.assert_close(wide.flat_features.grad.float(), grid.flat_features.grad, rtol=1e-5, atol=1e-6)
    if backbone == "relu_field":  # the 3-unit chord through σ = 0.01 · 33.3 per unit
        expected = -math.expm1(-0.01 * grid.density_scale * 3.0)
        assert outs[1].opacity.tolist() == pytest.approx([expected] * 2, abs=1e-6)


def test_occupancy_is_exact_for_relu_and_reports_the_tight_box():
    grid = sphere_grid(resolution=32, radius=0.5)
    occupancy = grid.occupancy(sigma_threshold=0.0)
    assert 0.01 < occupancy.fraction < 0.1
    assert torch.all(occupancy.bbox_min > -0.8) and torch.all(occupancy.bbox_max < 0.8)
    assert torch.all(occupancy.bbox_min < -0.45) and torch.all(occupancy.bbox_max > 0.45)
    # Every point in an unoccupied cell has zero density.
    points = torch.rand(20000, 3) * 3 - 1.5
    sigma, _ = grid.query(points)
    cell = ((points + 1.5) / grid.voxel_size).floor().long().clamp(0, 30)
    unoccupied = ~occupancy.cells[cell[:, 0], cell[:, 1], cell[:, 2]]
    assert unoccupied.sum() > 1000
    assert torch.all(sigma[unoccupied] == 0)


def test_grid_save_load_round_trip_and_version_check(tmp_path):
    grid = sphere_grid(resolution=12)
    grid = VoxelGrid(12, (-2, -1, -1), (2, 1, 1), "softplus", features=grid.features.detach() + 0.25)
    path = tmp_path / "grid.safetensors"
    grid.save(path)
    loaded = load_grid(path)
    assert torch.equal(loaded.features, grid.features)
    assert loaded.activation == "softplus" and loaded.density_scale == grid.density_scale
    assert torch.equal(loaded.bbox_min, grid.bbox_min) and torch.equal(loaded.bbox_max, grid.bbox_max)
    assert path.read_bytes()[:8] != b"\x80\x02\x80\x03"[:8]  # not a pickle
    newer = tmp_path / "newer.safetensors"
    save_tensors(newer, grid.state_tensors(), kind="voxel_grid", version=99, meta=grid.header())
    with pytest.raises(FormatError, match="format version 99 is newer"):
        load_grid(newer)
    junk = tmp_path / "junk.safetensors"
    junk.write_bytes(b"not a tensor file")
    with pytest.raises(FormatError, match="junk.safetensors"):
        load_grid(junk)


def test_upsampling_preserves_trilinear_fields():
    grid = VoxelGrid(5)
    axis = torch.linspace(-1.5, 1.5, 5)
    x, y, z = torch.meshgrid(axis, axis, axis, indexing="ij")
    with torch.no_grad():
        grid.features[..., 0] = 0.1 * x + 0.2 * y - 0.3 * z  # linear: reproduced exactly
    up = grid.upsampled(9)
    points = torch.rand(100, 3) * 3 - 1.5
    assert torch.allclose(up.interpolate(points)[:, 0], grid.interpolate(points)[:, 0], atol=1e-5)
    assert up.resolution == (9, 9, 9)


@pytest.mark.parametrize("shape,size", [((9, 7, 5), 1), ((9, 7, 5), 2), ((13, 4, 10), 3), ((8, 8, 8), 16)])
def test_dilated_blocks_mark_every_block_with_an_occupied_cell_in_reach(shape, size):
    """Block b is marked iff some occupied cell lies in b or one of its 26 neighbours (partial blocks included)."""
    cells = torch.rand(shape, generator=torch.Generator().manual_seed(size)) < 0.03
    blocks = Occupancy(cells, torch.zeros(3), torch.ones(3)).dilated_blocks(size)
    assert blocks.shape == tuple(-(-n // size) for n in shape)
    occupied = cells.nonzero() // size
    for b in torch.cartesian_prod(*(torch.arange(n) for n in blocks.shape)):
        in_reach = bool(((occupied - b).abs() <= 1).all(1).any())
        assert bool(blocks[tuple(b)]) == in_reach, b


@pytest.mark.parametrize("shape", [(12, 12, 12, 2), (6, 6, 6, 2), (9, 9, 9)])
def test_colour_features_of_another_lattice_are_refused(shape):
    """Regression: features of a 12³ lattice had been gathered at the 9³ grid's flat indices (the values of other
    vertices, rendered without a word), those of a 6³ one or without a channel axis had raised an IndexError."""
    with pytest.raises(ValueError, match=rf"^features must be \(X, Y, Z, C\) on this grid's \(9, 9, 9\) vertices, "
                                         rf"got {re.escape(str(shape))}$"):
        render_rays(uniform_grid(0.02, resolution=9), torch.tensor([[0.0, 0.1, -3.0]]), torch.tensor([[0.0, 0.0, 1.0]]),
                    RenderConfig(background=(0.0,)), color_features=torch.rand(shape))


@pytest.mark.parametrize("background, features", [((), None), ((1.0, 1.0), None), ((0.0, 0.0, 0.0, 1.0), None),
                                                  ((0.0, 0.0, 0.0), torch.zeros(8, 8, 8, 2))])
def test_a_background_of_another_channel_count_is_refused_by_name(background, features):
    """Regression: a background of neither one value nor one per rendered channel (RGBA for RGB, RGB for two attention
    fields, none at all) had failed in an expand, 'The expanded size of the tensor (3) must match ...'."""
    channels = 3 if features is None else 2
    with pytest.raises(ValueError, match=rf"^RenderConfig\.background must hold one value or one per rendered channel "
                                         rf"\({channels}\), got {re.escape(repr(background))}$"):
        render_rays(uniform_grid(0.02), torch.tensor([[0.0, 0.1, -3.0]]), torch.tensor([[0.0, 0.0, 1.0]]),
                    RenderConfig(background=background), color_features=features)
