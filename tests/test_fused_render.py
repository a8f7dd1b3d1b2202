"""The fused ray marcher (voxe_core.fused_render) against the packed renderer it stands in for.

Triton's interpreter runs the kernels on this CPU (``TRITON_INTERPRET=1``, which tests/conftest.py sets where there is
no CUDA). On a GPU the same kernels compile for CUDA; bench/gpu.py's section l measures them there.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from needs import require_triton_interpreter
from voxe_core.edit import EditConfig, edit
from voxe_core.grid import VoxelGrid, unit_directions
from voxe_core.guidance.sds import StableDiffusionGuidance
from voxe_core.progress import Callbacks
from voxe_core.render import RenderConfig, fused_marcher_applies, render_rays
from voxe_core.scene_grid import SceneGrid


@pytest.fixture(autouse=True)
def _triton_interpreter():
    require_triton_interpreter()


def _rays(n: int, seed: int, radius: float = 3.0) -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` rays from a sphere of ``radius`` towards random points near the centre (directions not unit length)."""
    generator = torch.Generator().manual_seed(seed)
    origins = torch.randn(n, 3, generator=generator)
    origins = origins / origins.norm(dim=-1, keepdim=True) * radius
    return origins, torch.randn(n, 3, generator=generator) * 0.4 - origins


def _field(resolution: int, seed: int, density: float) -> torch.Tensor:
    """Random raw features: colour logits, densities of scale ``density`` half below zero, a slab of empty cells."""
    generator = torch.Generator().manual_seed(seed)
    features = torch.randn(resolution, resolution, resolution, 4, generator=generator)
    features[..., 0] = (torch.rand(resolution, resolution, resolution, generator=generator) - 0.5) * density
    features[: resolution // 3, ..., 0] = -1.0
    return features


def _render_both(features, origins, directions, jitter: bool = False, **render):
    """(packed, fused) renders with gradients of one loss that weighs every output: (RenderOutput, features' grad)."""
    results = []
    for fused in (False, True):
        grid = VoxelGrid(features.shape[0], features=features.clone())
        generator = torch.Generator().manual_seed(7) if jitter else None
        out = render_rays(grid, origins, directions, RenderConfig(fused=fused, **render), generator=generator)
        weights = torch.linspace(-1.0, 1.0, out.rgb.numel()).reshape(out.rgb.shape)
        ((out.rgb * weights).sum() + 0.1 * out.depth.sum() + 0.3 * out.opacity.sum()).backward()
        results.append((out, grid.flat_features.grad))
    return results


def _assert_same_render(packed, fused, grad_tolerance: float = 1e-4):
    (a, grad_a), (b, grad_b) = packed, fused
    assert isinstance(a.samples, int) and isinstance(b.samples, torch.Tensor)  # the fused path ran
    torch.testing.assert_close(b.rgb, a.rgb, atol=1e-5, rtol=0)
    torch.testing.assert_close(b.opacity, a.opacity, atol=1e-5, rtol=0)
    torch.testing.assert_close(b.depth, a.depth, atol=1e-4, rtol=0)
    assert float((grad_b - grad_a).norm() / grad_a.norm()) < grad_tolerance
    assert int(b.candidates) == a.candidates


@pytest.mark.parametrize("early_stop", [1e-4, 0.0])
@pytest.mark.parametrize("skip_empty", [True, False])
def test_the_fused_render_and_its_gradient_are_the_packed_ones(early_stop, skip_empty):
    """Faint and dense cells, rays in every direction, stratified jitter: the same pixels, opacities, depths and
    feature gradient, to float32 rounding."""
    packed, fused = _render_both(_field(12, 0, density=0.6), *_rays(40, 1), jitter=True, step_ratio=0.5,
                                 early_stop=early_stop, skip_empty=skip_empty)
    _assert_same_render(packed, fused)
    opacity = packed[0].opacity.detach()
    assert float(opacity.max()) > 0.99 and float(opacity.min()) < 0.5  # opaque and faint rays


def test_early_stopping_evaluates_only_the_samples_in_front_of_the_stop():
    """Dense matter: rays stop early. The fused march evaluates the kept samples once (the packed path probes every
    candidate for their densities first, then evaluates the kept ones again)."""
    features, (origins, directions) = _field(12, 2, density=4.0), _rays(30, 3)
    packed, fused = _render_both(features, origins, directions, step_ratio=0.5)
    _assert_same_render(packed, fused)
    grid = VoxelGrid(12, features=features)
    groups = list(grid.ray_samples(origins, unit_directions(directions), torch.full((30,), 0.5), 0.5,
                                   grid.occupancy(), early_stop=RenderConfig.early_stop))
    kept, probed = sum(g.ray.numel() for g in groups), sum(g.probed for g in groups)
    assert packed[0].samples == probed + kept and int(fused[0].samples) == kept < probed


def test_saturated_densities_clamp_their_optical_depth_in_both():
    """Densities of 10^4 per unit and more, every other slice of vertices past float32's range (σ = inf): each
    sample's optical depth is clamped (``MAX_SAMPLE_OPTICAL_DEPTH``), which stops its gradient; the render is the
    first sample's colour in both, finite (an infinite depth in the rays' shared sum had made the rays after it
    NaN)."""
    features = _field(10, 4, density=0.5)
    features[..., 0] = features[..., 0].abs() * 1e4 + 1e3
    features[::2, ..., 0] = 1e38
    origins, directions = _rays(20, 5)
    packed, fused = _render_both(features, origins, directions, step_ratio=0.5, early_stop=0.0)
    _assert_same_render(packed, fused)
    grid = VoxelGrid(10, features=features)
    (samples,) = grid.ray_samples(origins, unit_directions(directions), torch.full((20,), 0.5), 0.5)
    first = samples.points[torch.searchsorted(samples.ray, torch.arange(20))]  # every ray enters the box
    for out, grad in (packed, fused):
        assert out.opacity.tolist() == [1.0] * 20
        torch.testing.assert_close(out.rgb, torch.sigmoid(grid.interpolate(first)[:, 1:]), atol=1e-6, rtol=0)
        assert not grad[:, 0].any() and bool(grad[:, 1:].isfinite().all()) and grad[:, 1:].any()


def test_rays_from_inside_the_box_and_rays_that_are_none():
    """Cameras inside the box start at t = 0; a NaN origin and a zero direction render the background."""
    features = _field(10, 6, density=0.6)
    origins, directions = _rays(20, 7)
    _assert_same_render(*_render_both(features, torch.full((20, 3), 0.1), directions, step_ratio=0.5))
    origins[0, 1] = math.nan
    directions[1] = 0.0
    packed, fused = _render_both(features, origins, directions, step_ratio=0.5)
    _assert_same_render(packed, fused)
    assert fused[0].rgb[:2].tolist() == [[1.0, 1.0, 1.0]] * 2 and fused[0].opacity[:2].tolist() == [0.0, 0.0]


@pytest.mark.parametrize("fused", [False, True])
@pytest.mark.parametrize("step_ratio,origin_y,origin_z", [(2.0, 0.5, 1.2), (0.5, 0.72, 1.45)])
def test_a_rays_last_sample_lies_on_its_path_in_the_box(fused, step_ratio, origin_y, origin_z):
    """Density only above y = 0.786 (1/21 of the way from the vertices at y = 0.75, raw -1, to those at 1.5, raw 20);
    the ray leaves the box's top face below it (y 0.65 or 0.745), a partial step after its last full one. That
    sample had been placed a whole step on, past the face, and read the density above y = 0.786 from the face's far
    side where the render with empty-space skipping, culled at the exit, saw none: its path is empty, so both see
    nothing."""
    features = torch.full((5, 5, 5, 4), -1.0)
    features[:, 4, :, 0] = 20.0  # the vertices at y = 1.5
    origins, directions = torch.tensor([[0.0, origin_y, origin_z]]), torch.tensor([[0.0, 1.0, 2.0]])
    grid = VoxelGrid(5, features=features)
    for skip_empty in (False, True):
        config = RenderConfig(step_ratio=step_ratio, skip_empty=skip_empty, sigma_threshold=0.0, fused=fused)
        out = render_rays(grid, origins, directions, config)
        assert out.opacity.tolist() == [0.0] and out.rgb.tolist() == [[1.0, 1.0, 1.0]]
    # every sample within the path it stands for, inside the box (jittered too)
    offsets = torch.tensor([0.0, 0.5, 0.999])
    for samples in grid.ray_samples(origins.expand(3, 3), unit_directions(directions).expand(3, 3), offsets,
                                    step_ratio):
        assert (samples.points.abs() <= 1.5 + 1e-6).all() and samples.delta.sum() > 0


@pytest.mark.parametrize("fused", [False, True])
@pytest.mark.parametrize("sigma", [0.5, 1e-4, 20 / 3])
def test_a_constant_density_slab_gives_the_analytic_opacity_and_gradient(sigma, fused):
    """σ constant in a box of side 3, a ray along an axis through it: opacity 1 − exp(−3σ), depth the mean of the
    exponential distribution truncated at the box's far side (from the box's entry at t = 2). The opacity's
    gradient in every sample's optical depth is the transmittance left at the end, T = exp(−3σ), so the raw densities'
    gradients add up to T · 3 · density_scale; at σ = 20/3 that is 2e-9 of what a float32 running sum of the weights
    would have subtracted it from (on the packed path, float32 weights had made it 34 % short, 8 vertices' gradients
    negative). A faint slab too: each sample's alpha of ~1e-5 must not lose digits."""
    grid = VoxelGrid(9, features=torch.zeros(9, 9, 9, 4))
    grid.flat_features.data[:, 0] = sigma / grid.density_scale
    out = render_rays(grid, torch.tensor([[0.1, 0.2, -3.5]]), torch.tensor([[0.0, 0.0, 1.0]]),
                      RenderConfig(step_ratio=0.05, early_stop=0.0, skip_empty=False, fused=fused))
    out.opacity.sum().backward()
    opacity = 1 - math.exp(-3 * sigma)
    mean_inside = 1 / sigma - 3 * math.exp(-3 * sigma) / opacity
    assert float(out.opacity.detach()) == pytest.approx(opacity, rel=1e-5)
    assert float(out.depth.detach()) == pytest.approx(2.0 + mean_inside, rel=1e-3)  # the quadrature's midpoints
    assert out.rgb[0].tolist() == pytest.approx([1 - 0.5 * opacity] * 3, rel=1e-6)
    grad = grid.flat_features.grad
    assert float(grad[:, 0].sum()) == pytest.approx(math.exp(-3 * sigma) * 3 * grid.density_scale, rel=1e-5)
    assert bool((grad[:, 0] >= 0).all()) and not grad[:, 1:].any()


def test_a_density_of_exactly_zero_passes_no_gradient_through_the_relu():
    """Raw density 0 over half the grid (``init_density=0``, or densities clamped to ``empty_raw_density``): ReLU's
    gradient is 0 there, on both paths (a sample there must not send the optical depth's gradient into it)."""
    features = _field(9, 12, density=0.6)
    features[:5, ..., 0] = 0.0
    packed, fused = _render_both(features, *_rays(16, 13), step_ratio=0.5, skip_empty=False)
    _assert_same_render(packed, fused)
    for _, grad in (packed, fused):  # the cells of x < 4 have no vertex of raw density other than 0
        density_grad = grad.view(9, 9, 9, 4)[..., 0]
        assert not density_grad[:4].any() and density_grad[5:].any()


def test_a_nan_colour_where_nothing_is_dense_shows_in_the_render():
    """A NaN colour at a vertex of no density still makes the pixels through it NaN (0 · NaN), on both paths: the
    edit's finite-loss check must see it."""
    features = torch.zeros(10, 10, 10, 4)
    features[..., 0] = -0.1
    features[5, 5, 5, 1] = math.nan
    grid = VoxelGrid(10, features=features)
    for fused in (False, True):
        out = render_rays(grid, torch.tensor([[0.0, 0.0, -3.0]]), torch.tensor([[0.0, 0.0, 1.0]]),
                          RenderConfig(fused=fused, skip_empty=False))
        assert out.rgb[0, 0].isnan() and out.rgb[0, 1:].tolist() == [1.0, 1.0]


def test_samples_of_no_length_add_no_optical_depth_however_dense():
    """Lattice samples past the ray's path (``length`` ends half a step into sample 6, so samples 7 on stand for none
    of it), from sample 8 on in cells of infinite density (a raw 1e38 overflows once scaled): they add nothing, so the
    render and its gradient are those of the lattice that ends at the path (inf · 0 had made them NaN), as on the
    packed path."""
    from voxe_core.fused_render import march

    features = _field(8, 15, density=0.3)
    features[:, :, 5:, 0] = 1e38  # the cells of z > 0.21 reach it: σ = inf in float32
    grid = VoxelGrid(8, features=features)
    origins, directions = torch.tensor([[0.1, -0.3, -3.0], [-0.4, 0.2, -3.0]]), torch.tensor([[0.0, 0.0, 1.0]] * 2)
    lattice = grid.ray_lattice(origins, directions, torch.full((2,), 0.5), step_ratio=0.5)
    path = lattice._replace(length=torch.full((2,), 6.5 * lattice.step))
    outs = []
    for last in (lattice.last, torch.full((2,), 7)):  # to the box's far side; to the path's end
        grid.flat_features.grad = None
        colour, opacity, depth, _ = march(grid, origins, directions, path._replace(last=last), None, early_stop=0.0)
        (colour.sum() + opacity.sum() + 0.1 * depth.sum()).backward()
        outs.append((colour.detach(), opacity.detach(), depth.detach(), grid.flat_features.grad))
    assert int(lattice.last.min()) > 12  # the rays' lattices reach the infinite cells past the path
    assert all(bool(torch.isfinite(x).all()) for x in outs[0]) and float(outs[1][1].max()) < 0.9
    for got, expected in zip(*outs):
        torch.testing.assert_close(got, expected, rtol=0, atol=0)


@pytest.mark.parametrize("fused", [False, True])
@pytest.mark.parametrize("other", [6, 12])
def test_an_occupancy_of_another_grid_is_refused(fused, other):
    """Cells of another resolution: the kernel would read past fewer; the packed path had looked this grid's cell
    indices up in them, an IndexError where they were fewer and a blank render where more (regression)."""
    grid = VoxelGrid(9)
    cells = rf"\({other - 1}, {other - 1}, {other - 1}\)"
    with pytest.raises(ValueError, match=rf"^an occupancy of {cells} cells does not fit a grid of \(9, 9, 9\) vertices"):
        render_rays(grid, *_rays(4, 14), RenderConfig(fused=fused), occupancy=VoxelGrid(other).occupancy())


def test_a_nan_density_in_front_of_the_stop_shows_in_the_render():
    """A NaN density a ray meets before its transmittance runs out makes its pixel NaN, as on the packed path."""
    features = _field(10, 8, density=0.2)
    features[4:6, 4:6, 4:6, 0] = math.nan
    origins = torch.tensor([[0.0, 0.0, -3.0], [2.5, 2.5, 2.5]])
    directions = torch.tensor([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])  # through the centre; past the box
    grid = VoxelGrid(10, features=features)
    for fused in (False, True):
        out = render_rays(grid, origins, directions, RenderConfig(fused=fused))
        assert out.rgb[0].isnan().all() and out.rgb[1].tolist() == [1.0, 1.0, 1.0]


@pytest.mark.parametrize("case", ["scene grid", "softplus", "float16 grid", "colour features", "sparse gradient",
                                  "rays with gradient", "no Triton device"])
def test_renders_the_fused_marcher_does_not_build_take_the_packed_path(case, monkeypatch):
    """Where the fused marcher would render something else (or cannot run), ``fused=True`` renders as the packed path
    does: the same output (and gradients), counted in ints."""
    grid = SceneGrid(8) if case == "scene grid" else VoxelGrid(8, activation="softplus" if case == "softplus" else "relu")
    if case == "float16 grid":
        grid = grid.half()
    colour = torch.rand(8, 8, 8, 3) if case == "colour features" else None
    if case == "no Triton device":
        monkeypatch.delenv("TRITON_INTERPRET")
    origins, directions = _rays(6, 9)
    origins.requires_grad_(case == "rays with gradient")
    assert not fused_marcher_applies(grid, origins, directions, colour, case == "sparse gradient")
    outs = [render_rays(grid, origins, directions, RenderConfig(fused=fused), color_features=colour,
                        sparse_grad=case == "sparse gradient") for fused in (False, True)]
    assert isinstance(outs[1].samples, int) and torch.equal(outs[1].rgb, outs[0].rgb)


def test_a_box_of_any_shape_and_place_renders_as_on_the_packed_path():
    """A grid of 10 × 13 × 7 vertices over an off-centre box with unequal voxel edges: the same strides, cells and
    corner weights as the packed path (a cubic grid in the default box would hide an axis mixed up)."""
    box = (-0.5, -2.0, 0.25), (2.0, 1.0, 1.0)
    features = torch.randn(10, 13, 7, 4, generator=torch.Generator().manual_seed(10))
    # Density in a ball only: most cells empty, so a cell looked up on the wrong axis skips matter or keeps none.
    centre = torch.tensor([0.9, -0.7, 0.6])
    vertices = VoxelGrid((10, 13, 7), *box).vertex_positions().reshape(10, 13, 7, 3)
    features[..., 0] = 0.5 - (vertices - centre).norm(dim=-1)
    results = []
    for fused in (False, True):
        grid = VoxelGrid((10, 13, 7), *box, features=features.clone())
        origins = centre + torch.randn(30, 3, generator=torch.Generator().manual_seed(11)) * 3
        directions = centre + torch.randn(30, 3, generator=torch.Generator().manual_seed(12)) * 0.2 - origins
        out = render_rays(grid, origins, directions, RenderConfig(step_ratio=0.5, fused=fused))
        (out.rgb * torch.linspace(-1, 1, 90).reshape(30, 3)).sum().backward()
        results.append((out, grid.flat_features.grad))
    _assert_same_render(*results)
    cells = grid.occupancy().cells
    assert float(cells.float().mean()) < 0.2 and float(results[0][0].opacity.detach().max()) > 0.9


def test_an_edit_through_the_fused_marcher_is_the_packed_edit(make_sphere_grid, tiny_sd_path):
    """One SDS iteration on the tiny random-weight model (a SMOKE-TEST MODEL): the same loss, and the same edited grid
    but for the few features whose gradient is rounding-sized (Adam's first step moves any nonzero gradient by ±lr,
    whatever its size, so a sign flipped by rounding is a move of 2·lr); the render's sample count is reported."""
    guidance = StableDiffusionGuidance.from_pretrained(str(tiny_sd_path), device="cpu", local_files_only=True)
    sphere = make_sphere_grid(16)
    edited, reports = [], []
    for fused in (False, True):
        config = EditConfig(iterations=1, render_size=16, seed=3)
        config.render.fused = fused
        edited.append(edit(sphere, "a dog", guidance, config, Callbacks(on_progress=reports.append)).features.detach())
    packed, fused = reports
    assert fused.losses["sds"] == pytest.approx(packed.losses["sds"], rel=1e-5)
    moved = (edited[0] - sphere.features).abs() > 1e-4
    differ = (edited[1] - edited[0]).abs() > 1e-4
    assert float(differ.float().mean()) < 0.01 < float(moved.float().mean())
    # The fused marcher evaluates the kept samples once, the packed path probes them all first.
    assert isinstance(fused.info["samples_per_ray"], float) and 0 < fused.info["samples_per_ray"] < packed.info["samples_per_ray"]


COMPILE_FOR_CUDA = """
import re

import triton
from triton.backends.compiler import GPUTarget
from triton.compiler import ASTSource

from voxe_core.fused_render import RAYS_PER_PROGRAM, _march

pointers = dict.fromkeys(["origins", "directions", "starts", "offsets", "lengths", "features", "grad_features", "rgb",
                          "opacity", "depth", "grad_rgb", "grad_opacity", "grad_depth"], "*fp32")
pointers.update(firsts="*i32", lasts="*i32", count="*i32", cells="*u8", totals="*fp64")
integers = {"n_rays", "stride_x", "stride_y", "cell_stride_x", "cell_stride_y"}
flags = {"SKIP_EMPTY", "BACKWARD", "BLOCK"}
signature = {name: pointers.get(name) or ("i32" if name in integers else "constexpr" if name in flags else "fp32")
             for name in _march.arg_names}
for backward in (False, True):
    for skip_empty in (False, True):
        source = ASTSource(_march, signature, constexprs={"SKIP_EMPTY": skip_empty, "BACKWARD": backward,
                                                          "BLOCK": RAYS_PER_PROGRAM})
        kernel = triton.compile(source, target=GPUTarget("cuda", 90, 32), options={"num_warps": 4})
        ptx = kernel.asm["ptx"]
        atomics = re.findall(r"\\b(?:atom|red)\\.[a-z0-9_.]+", ptx)  # "@%p16 red.global.gpu.relaxed.add.f32 [ ..."
        print(backward, skip_empty, len(atomics), all(a.endswith(".gpu.relaxed.add.f32") for a in atomics))
"""


def test_the_kernels_compile_for_a_hopper_gpu_without_one():
    """Triton compiles both kernels, with and without empty-cell skipping, to PTX and a cubin for sm_90 (the H100 and
    H200) here, with no GPU (a fresh process: this one runs Triton's interpreter). The backward adds into the grid
    with one relaxed atomic per corner and channel (8 × 4), the forward with none."""
    env = {k: v for k, v in os.environ.items() if k != "TRITON_INTERPRET"}
    done = subprocess.run([sys.executable, "-c", COMPILE_FOR_CUDA], capture_output=True, text=True, timeout=300,
                          env={**env, "TRITON_DEFAULT_FP_FUSION": "1", "PYTHONPATH": str(Path(__file__).parents[1])})
    assert done.returncode == 0, done.stderr[-3000:]
    # relaxed (red.global... on Triton 3.9, atom.global... on 3.5): the adds commute; acq_rel had fenced each one
    assert done.stdout.split("\n")[:4] == ["False False 0 True", "False True 0 True", "True False 32 True",
                                           "True True 32 True"]


@pytest.mark.parametrize("fused", [False, True])
@pytest.mark.parametrize("n_origins, n_directions", [(3, 1), (1, 3), (3, 2)])
def test_rays_that_do_not_pair_one_direction_with_each_origin_are_refused(fused, n_origins, n_directions):
    """Regression: one direction for three origins had rendered three rays, the last two blank on the packed path and
    read from past the directions in the fused kernel; one origin for three directions one ray; three origins and two
    directions an IndexError or a RuntimeError from deep in the sampler."""
    origins, directions = _rays(3, 15)
    with pytest.raises(ValueError, match=rf"^origins and directions must be \(N, 3\) each, one direction per origin, "
                                         rf"got \({n_origins}, 3\) and \({n_directions}, 3\)$"):
        render_rays(VoxelGrid(9), origins[:n_origins], directions[:n_directions], RenderConfig(fused=fused))
