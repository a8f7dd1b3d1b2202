"""The DVGO-style scene backbone: contraction, ray bins, analytic renders, interface, frames, fitting, editing."""

from __future__ import annotations

import dataclasses
import json
import math
import re

import numpy as np
import pytest
import torch

from voxe_core.backbones import detect_backbone, load_grid, prepare_backbone
from voxe_core.cameras import Cameras, look_at, ring_poses
from voxe_core.edit import EditConfig, edit
from voxe_core.grid import VoxelGrid
from voxe_core.guidance.sds import StableDiffusionGuidance
from voxe_core.metrics import psnr
from voxe_core.presets import edit_config
from voxe_core.reconstruct import ReconstructConfig, reconstruct
from voxe_core.render import RenderConfig, render_image, render_rays
from voxe_core.scene_grid import MAX_NEAR_FAR_SAMPLES, SceneGrid, apply_frame, contract, scene_frame


pytestmark = pytest.mark.usefixtures("single_thread")


def _raw_for_density(grid: SceneGrid, sigma: float) -> float:
    return sigma / grid.density_scale  # ReLU: density = scale · raw


# ----------------------------------------------------------------- contraction
def test_contraction_is_identity_inside_and_bounded_outside():
    inside = torch.tensor([[0.3, -0.9, 1.0], [0.0, 0.0, 0.0]])
    assert torch.equal(contract(inside), inside)
    # ||q||∞ = 2 -> 2 - 1/2 = 1.5 along q / ||q||∞
    assert torch.allclose(contract(torch.tensor([[2.0, 1.0, -0.5]])), torch.tensor([[1.5, 0.75, -0.375]]))
    far = contract(torch.tensor([[1e30, 0.0, 0.0], [math.inf, -math.inf, 1.0], [-math.inf, 0.0, 0.0]]))
    assert torch.isfinite(far).all()
    assert torch.allclose(far, torch.tensor([[2.0, 0.0, 0.0], [2.0, -2.0, 0.0], [-2.0, 0.0, 0.0]]))
    # continuous across the cube face
    a, b = contract(torch.tensor([[1.0 - 1e-6, 0.2, 0.0]])), contract(torch.tensor([[1.0 + 1e-6, 0.2, 0.0]]))
    assert torch.allclose(a, b, atol=1e-5)


def test_ray_bins_partition_the_ray_and_are_linear_in_inverse_depth_beyond():
    grid = SceneGrid(33, foreground_extent=1.5, near_samples=8, far_samples=16, far_ratio=100.0)
    origins = torch.tensor([[4.0, 0.0, 0.0], [0.0, 0.0, 0.0], [4.0, -4.0, 0.0]])
    directions = torch.tensor([[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])  # through, inside, miss
    edges, exists = grid.ray_bins(origins, directions, step_ratio=0.5)
    assert (edges[:, 1:] >= edges[:, :-1]).all() and (edges[:, 0] == 0).all()
    step = 0.5 * float(grid.voxel_size.min()) * 1.5
    # Ray 0: near bins to the cube at t = 2.5, foreground to 5.5, inverse-depth bins out to 100 · 5.5.
    assert torch.allclose(edges[0, 8], torch.tensor(2.5)) and int(exists[0, :8].sum()) == 8
    fg = edges[0, 8 : -16]
    assert torch.allclose(fg[1:][fg[1:] < 5.5] - fg[:-1][fg[1:] < 5.5], torch.tensor(step), atol=1e-5)
    far = edges[0, -17:]
    assert torch.allclose(far[0], torch.tensor(5.5)) and torch.allclose(far[-1], torch.tensor(550.0))
    inverse_steps = (1.0 / far).diff()
    assert torch.allclose(inverse_steps, inverse_steps[0].expand_as(inverse_steps), rtol=1e-4)
    # Ray 1 starts inside the cube: no near bins; ray 2 misses it: far bins from its closest approach (t = 4).
    assert not exists[1, :8].any()
    assert torch.allclose(edges[2, -17], torch.tensor(4.0))


# ----------------------------------------------------------------- rendering
def test_uniform_density_renders_the_analytic_colour():
    grid = SceneGrid(9, far_samples=16, far_ratio=10.0)
    sigma = 0.05
    with torch.no_grad():
        grid.features[..., 0] = _raw_for_density(grid, sigma)
        grid.features[..., 1:] = torch.tensor([2.0, 0.0, -2.0])
    origins, directions = torch.zeros(2, 3), torch.tensor([[1.0, 0.0, 0.0], [0.6, 0.8, 0.0]])
    out = render_rays(grid, origins, directions, RenderConfig(skip_empty=False, background=(0.0, 0.0, 0.0)))
    # path length: far_ratio times the exit distance from the cube of half-extent 1.5
    exit_t = torch.tensor([1.5, 1.5 / 0.8])
    opacity = 1.0 - torch.exp(-sigma * 10.0 * exit_t)
    assert torch.allclose(out.opacity, opacity, atol=1e-5)
    assert torch.allclose(out.rgb, opacity[:, None] * torch.sigmoid(torch.tensor([2.0, 0.0, -2.0])), atol=1e-5)


@pytest.mark.parametrize("name", ["near_samples", "far_samples"])
def test_more_near_or_far_bins_than_a_pass_holds_are_refused_by_name(name):
    """1e12 bins had been taken, and failed the render allocating 4 TB."""
    with pytest.raises(ValueError, match=rf"^{name} must be at most 4194304 \(MAX_NEAR_FAR_SAMPLES\), got 10{{12}}$"):
        SceneGrid(9, **{name: 10**12})
    assert MAX_NEAR_FAR_SAMPLES == 4194304


def test_a_scene_grid_of_many_far_bins_loads_and_samples_fewer_rays_a_pass(tmp_path):
    """A grid of 2048 far bins, as an older version saved (it took any count), had been refused on load as damaged;
    past 2 x 1024 near and far bins a pass samples fewer rays, each ray's samples as in a pass of its own."""
    older = SceneGrid(9, init_density=-1.0)
    older.far_samples = 2048
    older.save(tmp_path / "older.safetensors")
    loaded = load_grid(tmp_path / "older.safetensors")
    assert loaded.far_samples == 2048
    out = render_rays(loaded, torch.tensor([[0.0, 0.0, 4.0]]), torch.tensor([[0.0, 0.0, -1.0]]),
                      RenderConfig(background=(0.2, 0.4, 0.6), skip_empty=False))
    assert torch.allclose(out.rgb, torch.tensor([[0.2, 0.4, 0.6]])) and out.opacity.item() == 0.0

    many = SceneGrid(9, far_samples=2**20)  # 2**23 bins a pass: 7 rays
    origins = torch.tensor([[0.0, 0.0, 4.0]]).repeat(10, 1) + torch.linspace(-0.5, 0.5, 10)[:, None]
    directions = torch.tensor([[0.0, 0.0, -1.0]]).repeat(10, 1)
    offsets = torch.full((10,), 0.5)
    passes = list(many.ray_samples(origins, directions, offsets, step_ratio=0.5))
    assert [int(p.ray.unique().numel()) for p in passes] == [7, 3]
    for i in (0, 8):  # a ray of each pass: its samples as alone
        [alone] = many.ray_samples(origins[i : i + 1], directions[i : i + 1], offsets[i : i + 1], step_ratio=0.5)
        mine = next(p for p in passes if (p.ray == i).any())
        assert torch.equal(mine.t[mine.ray == i], alone.t) and torch.equal(mine.points[mine.ray == i], alone.points)


@pytest.mark.parametrize("far_ratio", [math.inf, math.nan, 1.0, 3e38, 1.1e6])
def test_a_far_ratio_outside_one_to_its_bound_is_refused(far_ratio):
    """An infinite far_ratio made the last far bin infinitely long: a ray through empty space rendered NaN
    (0 density times an infinite path); so did 3e38, its float32 product with the exit distance inf."""
    with pytest.raises(ValueError, match=rf"far_ratio in \(1, 1e\+06\], got 32, 64, {re.escape(str(far_ratio))}$"):
        SceneGrid(9, far_ratio=far_ratio)
    empty = SceneGrid(9, init_density=-1.0, far_ratio=1e6)  # the bound: every bin finite, the background shown
    out = render_rays(empty, torch.zeros(1, 3), torch.tensor([[1.0, 0.0, 0.0]]),
                      RenderConfig(background=(0.2, 0.4, 0.6), skip_empty=False))
    assert torch.allclose(out.rgb, torch.tensor([[0.2, 0.4, 0.6]])) and out.opacity.item() == 0.0


def test_empty_space_skipping_is_exact_and_saturated_density_stays_finite():
    grid = SceneGrid(17)
    generator = torch.Generator().manual_seed(0)
    with torch.no_grad():
        grid.features.copy_(torch.randn(*grid.features.shape, generator=generator))
        grid.features[..., 0] -= 1.0  # most cells empty
        grid.features[8, 8, 8, 0] = 1e9  # a saturated vertex
    cameras = Cameras.from_fov(ring_poses(1, 20.0), 0.7, 12, 10)
    skipped = render_image(grid, cameras, 0, RenderConfig(step_ratio=0.5))
    dense = render_image(grid, cameras, 0, RenderConfig(step_ratio=0.5, skip_empty=False))
    assert torch.isfinite(skipped.rgb).all()
    assert torch.allclose(skipped.rgb, dense.rgb, atol=1e-6) and skipped.samples < dense.samples


def test_skipping_drops_no_more_in_a_far_cell_than_in_a_foreground_cell():
    """One skip density for every cell had skipped far bins hundreds of units long: a uniform density of 3.3e-4
    rendered opacity 0, the analytic 0.84. Each background cell's density is lowered by its world stretch."""
    grid = SceneGrid(33)
    sigma = 3.3e-4  # below the foreground's skip density (7.5e-4): its cells are still skipped
    with torch.no_grad():
        grid.features[..., 0] = _raw_for_density(grid, sigma)
    origins, directions = torch.tensor([[-4.0, 0.0, 0.0]]), torch.tensor([[1.0, 0.0, 0.0]])
    with torch.no_grad():
        skipped = render_rays(grid, origins, directions, RenderConfig())
        dense = render_rays(grid, origins, directions, RenderConfig(skip_empty=False))
    analytic = 1.0 - math.exp(-sigma * 1000.0 * 5.5)  # far_ratio times the exit distance
    assert math.isclose(float(dense.opacity), analytic, abs_tol=1e-4)
    assert math.isclose(float(skipped.opacity), analytic, abs_tol=1e-3) and skipped.samples < dense.samples
    skip_density = grid.skip_density(RenderConfig().sigma_threshold)
    # The foreground cube's cells (contracted [-1, 1]³) keep 1e-3, scaled from the 3-unit box to the 4-unit lattice.
    assert torch.allclose(skip_density[8:24, 8:24, 8:24], torch.tensor(7.5e-4))
    assert (skip_density[-1] == 0).all()  # the outermost shell reaches infinity


def test_a_softplus_scene_grid_keeps_its_occupancy_through_a_sparse_file_and_no_empty_shell(tmp_path):
    """Two flaws of the per-cell skip density: softplus is never 0, so the outermost shell (skipped only at density
    0) counted as occupied wherever it was empty (an object's file 15x larger, nothing culled); and the sparse
    file's fill, the mean of densities just under the foreground's threshold, passed the background cells' lower
    ones, occupying them on loading."""
    n = 33
    grid = SceneGrid(n, activation="softplus")
    axis = torch.linspace(-2, 2, n)
    r = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).abs().amax(-1)
    # vertices at 0.9 of the lowered threshold of any cell they are a corner of; the room beyond 1.5; an object
    below = 0.9 * VoxelGrid.skip_density(grid, 1e-3) * (2 - (r + 4 / (n - 1)).clamp(min=1.0)).clamp(min=0).square()
    density = torch.where(r >= 1.5, 1.0, below).clamp(min=1e-30)
    density[(r <= 0.2)] = 5.0
    with torch.no_grad():
        grid.features[..., 0] = torch.log(torch.expm1(density)) / grid.density_scale
    grid.save(tmp_path / "room.safetensors")
    assert torch.equal(load_grid(tmp_path / "room.safetensors").occupancy(1e-3).cells, grid.occupancy(1e-3).cells)

    with torch.no_grad():  # empty space but the object
        grid.features[..., 0] = torch.where(r <= 0.2, 5.0, grid.empty_raw_density)
    occupancy = grid.occupancy(1e-3)
    assert int(occupancy.cells.sum()) == 4 ** 3 and float(occupancy.bbox_max.abs().max()) < 0.5


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64, torch.float16, torch.bfloat16])
def test_a_softplus_scene_grids_empty_space_is_skipped_in_the_grids_own_dtype(dtype):
    """The skip density's floor, what empty space activates to, is activated as the cells' densities are: in the
    grid's dtype, on its device. Activated once in float32 on the host, it fell a last bit short of a float64 or
    bfloat16 grid's empty space (here at density_scale 10) and the whole outermost shell counted as occupied again,
    the box unbounded (nothing culled)."""
    n = 17
    grid = SceneGrid(n, activation="softplus", density_scale=10.0).to(dtype)
    axis = torch.linspace(-2, 2, n)
    r = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).abs().amax(-1)
    with torch.no_grad():  # empty space but the object
        grid.features[..., 0] = torch.where(r <= 0.2, 5.0, grid.empty_raw_density)
    skip_density = grid.skip_density(1e-3)
    assert skip_density.dtype == torch.promote_types(dtype, torch.float32)
    occupancy = grid.occupancy(1e-3)
    assert int(occupancy.cells.sum()) == 2 ** 3 and float(occupancy.bbox_max.abs().max()) < 0.5


def test_gradients_reach_the_background_shell():
    grid = SceneGrid(9)
    origins, directions = torch.tensor([[0.0, 0.0, 0.0]]), torch.tensor([[1.0, 0.0, 0.0]])
    out = render_rays(grid, origins, directions, RenderConfig(skip_empty=False))
    out.rgb.sum().backward()
    touched = grid.flat_features.grad.abs().sum(-1).view(grid.resolution) > 0
    assert touched[-1].any() and touched[4].any()  # the contracted boundary x = 2 and the centre


def test_rays_with_a_non_finite_or_zero_part_are_no_rays():
    """As in the ReLU field: such a ray samples nothing and shows the background. Regression: non-finite components
    were zeroed, so a zero or NaN direction laid all its bins on the camera's point (opaque in this haze) and a
    NaN or infinite origin component moved the ray onto the axis plane through the haze (opacity 0.71)."""
    grid = SceneGrid(17, init_density=-1.0)
    with torch.no_grad():  # a haze around the origin only
        grid.features[..., 0][(grid.vertex_positions().norm(dim=-1) < 0.6).reshape(grid.resolution)] = 0.05
    nan = float("nan")
    origins = torch.tensor([[0.0, 3.0, 0.0], [0.1, 0.1, 0.0], [0.1, 0.1, 0.0], [0.1, 0.1, 0.0], [nan, 3.0, 0.0],
                            [0.0, 3.0, math.inf]])
    directions = torch.tensor([[0.0, -1.0, 0.0], [0.0, 0.0, 0.0], [nan, 0.0, 0.0], [nan, nan, nan], [0.0, -1.0, 0.0],
                               [0.0, -1.0, 0.0]])
    config = RenderConfig(background=(0.2, 0.4, 0.6))
    out = render_rays(grid, origins, directions, config)
    alone = render_rays(grid, origins[:1], directions[:1], config)
    assert out.opacity[0] > 0.5 and torch.equal(out.rgb[:1], alone.rgb) and out.samples == alone.samples
    assert torch.equal(out.opacity[1:], torch.zeros(5)) and torch.equal(out.depth[1:], torch.zeros(5))
    assert torch.equal(out.rgb[1:], torch.tensor([[0.2, 0.4, 0.6]]).expand(5, 3))


def test_rays_beyond_one_pass_render_as_they_do_alone():
    """A call of more rays than one sampling pass takes (4,096) renders each group as a call of its own. Regression:
    the sampler's name for which rays are rays was reused for the first pass's sample rows, so a fox view at 1/16
    (8,040 rays) failed in its second pass (bench/real_scenes.py --step-cost) or kept the wrong samples."""
    grid = SceneGrid(16)
    with torch.no_grad():
        grid.features.copy_(torch.randn(grid.features.shape, generator=torch.Generator().manual_seed(0)))
    generator = torch.Generator().manual_seed(1)
    n = 4096 + 3000
    origins = torch.randn(n, 3, generator=generator) * 0.1 + torch.tensor([0.0, 0.0, 3.0])
    directions = torch.randn(n, 3, generator=generator) * 0.2 + torch.tensor([0.0, 0.0, -1.0])
    directions[5000] = 0.0  # no ray, in the second pass
    config = RenderConfig(skip_empty=False, background=(0.2, 0.4, 0.6))
    whole = render_rays(grid, origins, directions, config)
    parts = [render_rays(grid, origins[s : s + 4096], directions[s : s + 4096], config) for s in (0, 4096)]
    assert torch.equal(whole.rgb, torch.cat([p.rgb for p in parts]))
    assert torch.equal(whole.opacity, torch.cat([p.opacity for p in parts]))
    assert whole.samples == sum(p.samples for p in parts)
    assert torch.equal(whole.rgb[5000], torch.tensor([0.2, 0.4, 0.6])) and whole.opacity[5000] == 0


# ----------------------------------------------------------------- interface
def test_grid_interface_round_trips_and_keeps_the_backbone(tmp_path):
    frame = torch.diag(torch.tensor([2.0, 2.0, 2.0, 1.0]))
    grid = SceneGrid(8, foreground_extent=1.2, near_samples=4, far_samples=8, far_ratio=50.0, frame=frame)
    with torch.no_grad():
        grid.features.normal_()
    grid.save(tmp_path / "scene.safetensors")
    loaded = load_grid(tmp_path / "scene.safetensors")
    assert isinstance(loaded, SceneGrid) and loaded.header() == grid.header()
    assert torch.equal(loaded.features, grid.features)
    for derived in (grid.clone_grid(), grid.upsampled(12)):
        assert isinstance(derived, SceneGrid) and derived.foreground_extent == 1.2 and torch.equal(derived.frame, frame)
    assert grid.upsampled(12).resolution == (12, 12, 12)


def test_occupancy_box_is_in_the_canonical_frame_or_unbounded():
    grid = SceneGrid(9, foreground_extent=1.5)  # lattice spacing 0.5 in contracted units
    with torch.no_grad():
        grid.features[..., 0] = -1.0
        grid.features[4, 4, 4, 0] = 1.0  # the centre vertex: cells [3, 5)^3, contracted [-0.5, 0.5]
    occupancy = grid.occupancy()
    assert torch.allclose(occupancy.bbox_min, torch.full((3,), -0.75)) and torch.allclose(occupancy.bbox_max, torch.full((3,), 0.75))
    with torch.no_grad():
        grid.features[8, 4, 4, 0] = 1.0  # the background boundary
    assert float(grid.occupancy().bbox_max.min()) > 1e5


# ----------------------------------------------------------------- frames and selection
def test_scene_frame_centres_levels_and_scales_a_tilted_capture():
    tilt = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.8, -0.6], [0.0, 0.6, 0.8]])  # up z -> (0, -0.6, 0.8)
    centre = torch.tensor([3.0, -2.0, 1.0])
    ring = ring_poses(12, 25.0, radius=7.0)
    c2w = ring.clone()
    c2w[:, :3, :3] = tilt @ ring[:, :3, :3]
    c2w[:, :3, 3] = (tilt @ ring[:, :3, 3, None])[..., 0] + centre
    cameras = Cameras.from_fov(c2w, 0.7, 16, 16)
    moved = apply_frame(cameras, scene_frame(cameras, radius=4.0))
    assert torch.allclose(moved.c2w, Cameras.from_fov(ring_poses(12, 25.0, radius=4.0), 0.7, 16, 16).c2w, atol=1e-4)


def test_scene_frame_takes_up_from_the_views_where_the_images_are_rolled_every_way():
    """40 cameras 5-30° off the vertical above the object, each rolled about its axis at random: their image up axes
    cancel out, and their mean (0.20 long, nearly horizontal) had been taken as up, no word said (world +z went to
    (0.20, 0.98, 0) of the scene: the scene on its side). Up is now opposite the mean view direction, with a warning;
    upright rings keep theirs, silently (test_an_upright_ring_high_above_or_below_keeps_its_up_without_a_warning)."""
    import math
    import warnings

    from voxe_core.cameras import spherical_poses

    def canonical_up(c2w):
        linear = scene_frame(Cameras.from_fov(c2w, 0.7, 8, 8))[:3, :3]
        return linear.T[:, 2] / linear.norm(dim=0).mean()  # the world direction the frame takes to +z

    generator = torch.Generator().manual_seed(1)
    c2w = spherical_poses(60 + 25 * torch.rand(40, generator=generator), 360 * torch.rand(40, generator=generator), 4.0)
    for pose, angle in zip(c2w, (2 * math.pi * torch.rand(40, generator=generator)).tolist()):
        roll = torch.tensor([[math.cos(angle), -math.sin(angle), 0.0], [math.sin(angle), math.cos(angle), 0.0],
                             [0.0, 0.0, 1.0]])
        pose[:3, :3] = pose[:3, :3] @ roll
    with pytest.warns(UserWarning, match=r"image up axes cancel out \(their mean is 0\.\d\d long.*: up is taken "
                                         "opposite their mean view direction"):
        up = canonical_up(c2w)
    assert torch.allclose(up, torch.tensor([0.0, 0.0, 1.0]), atol=0.02), up
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert torch.allclose(canonical_up(ring_poses(12, 25.0)), torch.tensor([0.0, 0.0, 1.0]), atol=1e-5)


@pytest.mark.parametrize("cameras", [8, 12, 36])
@pytest.mark.parametrize("elevation", [62.0, 70.0, 80.0, 85.0, -70.0, -80.0])
def test_an_upright_ring_high_above_or_below_keeps_its_up_without_a_warning(cameras, elevation):
    """An upright ring's image up axes are short in the mean only because the views look steeply at the object (cos 70°
    = 0.34): from 62° (8 cameras; 80° for 36) it had been told that they cancel out ("images rolled every way, or a
    capture from straight above"), a normal capture from above. Cameras rolled 20° off upright (either way,
    alternately: opposite cameras alike, so up stays +z) stay silent."""
    import math
    import warnings

    c2w = ring_poses(cameras, elevation)
    for index, pose in enumerate(c2w):
        turn = math.radians(20.0 if index % 2 else -20.0)
        pose[:3, :3] = pose[:3, :3] @ torch.tensor([[math.cos(turn), -math.sin(turn), 0.0],
                                                    [math.sin(turn), math.cos(turn), 0.0], [0.0, 0.0, 1.0]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        linear = scene_frame(Cameras.from_fov(c2w, 0.7, 8, 8))[:3, :3]
    assert torch.allclose(linear.T[:, 2] / linear.norm(dim=0).mean(), torch.tensor([0.0, 0.0, 1.0]), atol=1e-4)


def test_scene_frame_refuses_parallel_axes_and_cameras_on_the_centre():
    forward_facing = torch.eye(4).repeat(5, 1, 1)
    forward_facing[:, 0, 3] = torch.arange(5.0)
    with pytest.raises(ValueError, match="optical axes are \\(nearly\\) parallel"):
        scene_frame(Cameras.from_fov(forward_facing, 0.7, 8, 8))
    centred = look_at(torch.tensor([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]]))
    centred[:, :3, 3] = 0.0
    with pytest.raises(ValueError, match="sit on the point they look at"):
        scene_frame(Cameras.from_fov(centred, 0.7, 8, 8))
    with pytest.raises(ValueError, match="a single camera has no centre to orbit"):
        scene_frame(Cameras.from_fov(look_at(torch.tensor([[4.0, 0, 0]])), 0.7, 8, 8))


def test_scene_frame_takes_up_from_the_images_as_their_exif_orientation_displays_them(tmp_path):
    """Photos stored landscape and tagged to display a quarter (or half) turn round, as a phone's portrait photos
    are: their poses are the stored pixels' (rolled about the optical axis), and up had been the stored images' +y,
    sideways, so the scene's edits and turntables came out rolled 90°. Up is each displayed image's, as the same
    capture's upright cameras with untagged images give it: the tilted ring's own up."""
    from PIL import Image

    from voxe_core.data import load_scene

    tilt = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.8, -0.6], [0.0, 0.6, 0.8]])  # up z -> (0, -0.6, 0.8)
    upright = ring_poses(8, 25.0, radius=5.0)
    upright[:, :3, :3] = tilt @ upright[:, :3, :3]
    upright[:, :3, 3] = (tilt @ upright[:, :3, 3, None])[..., 0]
    # EXIF orientation -> the roll of the stored image's camera about its optical axis: displayed up is the stored
    # left side (-x) for 6, the right (+x) for 8, the bottom for 3
    rolls = {1: 0.0, 6: -90.0, 8: 90.0, 3: 180.0}
    orientations = [6, 6, 8, 6, 3, 6, 1, 6]
    stored = upright.clone()
    tagged, untagged = tmp_path / "tagged", tmp_path / "untagged"
    for root in (tagged, untagged):
        (root / "images").mkdir(parents=True)
    for i, orientation in enumerate(orientations):
        a = math.radians(rolls[orientation])
        roll = torch.tensor([[math.cos(a), -math.sin(a), 0.0], [math.sin(a), math.cos(a), 0.0], [0.0, 0.0, 1.0]])
        stored[i, :3, :3] = upright[i, :3, :3] @ roll
        exif = Image.Exif()
        exif[0x0112] = orientation
        Image.new("RGB", (16, 12), (120, 120, 120)).save(tagged / "images" / f"{i}.png", exif=exif)
        Image.new("RGB", (16, 12), (120, 120, 120)).save(untagged / "images" / f"{i}.png")
    for root, c2w in ((tagged, stored), (untagged, upright)):
        frames = [{"file_path": f"images/{i}.png", "transform_matrix": pose.tolist()} for i, pose in enumerate(c2w)]
        (root / "transforms.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": frames}))
    photos, upright_photos = load_scene(tagged, downsample=2), load_scene(untagged, downsample=2)
    assert torch.allclose(photos.cameras.c2w, stored, atol=1e-6)  # the stored pixels' poses, as given
    frame = scene_frame(photos.cameras)
    level = frame[:3, :3] @ tilt[:, 2]
    assert torch.allclose(level / level.norm(), torch.tensor([0.0, 0.0, 1.0]), atol=1e-5)
    assert torch.allclose(frame, scene_frame(upright_photos.cameras), atol=1e-5)
    assert torch.allclose(scene_frame(photos.cameras[1:]), scene_frame(upright_photos.cameras[1:]), atol=1e-5)
    assert upright_photos.cameras.display_up is None  # untagged images: no per-image up to carry


def _capture(root, c2w: torch.Tensor):
    """An instant-ngp capture of 8x8 grey images from the poses ``c2w``, in this order."""
    from PIL import Image

    (root / "images").mkdir(parents=True)
    for i in range(len(c2w)):
        Image.new("RGB", (8, 8), (120, 120, 120)).save(root / "images" / f"{i:03d}.png")
    frames = [{"file_path": f"images/{i:03d}.png", "transform_matrix": pose.tolist()} for i, pose in enumerate(c2w)]
    (root / "transforms.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": frames}))
    return root


def test_max_images_keeping_too_narrow_a_start_of_a_capture_is_named_as_the_cause(tmp_path, capsys):
    """The first 3 of a 200-frame orbit look nearly one way: the fit had been refused as if the capture were not
    around the object. A capture that is not keeps its own refusal."""
    from voxe_core.cli import main
    from voxe_core.data import load_scene

    orbit = _capture(tmp_path / "orbit", ring_poses(200, 20.0, radius=4.0))
    forward = torch.eye(4).repeat(200, 1, 1)
    forward[:, 0, 3] = torch.linspace(0.0, 2.0, 200)
    forward_facing = _capture(tmp_path / "forward", forward)
    assert torch.allclose(load_scene(orbit, max_images=3).split_c2w, ring_poses(200, 20.0, radius=4.0), atol=1e-6)
    assert load_scene(orbit, max_images=200).split_c2w is None

    fit = ["--resolution", "8", "--iterations", "1", "--rays", "16", "--quiet", "--max-images", "3"]
    assert main(["reconstruct", str(orbit), "--out", str(tmp_path / "g.safetensors"), *fit]) == 2
    assert ("error: max_images keeps the first 3 of the split's 200 frames, too few to fit from where the whole split "
            "would do: raise it, or leave it out (of those 3: the cameras' optical axes are (nearly) parallel"
            ) in capsys.readouterr().err
    assert main(["reconstruct", str(forward_facing), "--out", str(tmp_path / "g.safetensors"), *fit]) == 2
    assert "error: the cameras' optical axes are (nearly) parallel, so they look at no common centre; the scene " \
           "backbone needs a capture around the object\n" in capsys.readouterr().err


def test_backbone_detection_from_alpha():
    with pytest.raises(ValueError, match="unknown backbone .dvgo.; use .auto., .relu_field. or .scene."):
        prepare_backbone("dvgo", None, Cameras.from_fov(ring_poses(3), 0.7, 4, 4), 8)
    assert detect_backbone(None) == "scene"
    assert detect_backbone(torch.ones(2, 8, 8)) == "scene"  # RGBA photos, opaque everywhere
    object_on_transparent = torch.ones(2, 8, 8)
    object_on_transparent[:, :, :4] = 0.0
    assert detect_backbone(object_on_transparent) == "relu_field"


def test_real_scene_edit_preset_is_the_specs():
    config = edit_config({"seed": 3}, backbone="scene")
    assert (config.iterations, config.schedule.i_start, config.schedule.every, config.seed) == (5000, 3000, 400, 3)
    # decays at the multiples of f_a from i_start on (1-based steps 3200, 3600, ...)
    assert config.schedule.max_fraction(3198) == pytest.approx(0.98)
    assert config.schedule.max_fraction(3199) == pytest.approx(0.98 * 0.75)
    assert config.schedule.max_fraction(3599) == pytest.approx(0.98 * 0.75**2)


# ----------------------------------------------------------------- fitting and editing
def _background_scene() -> SceneGrid:
    """Ground truth: a green foreground ball in a blue room far behind it (the contracted shell)."""
    grid = SceneGrid(17)
    axes = torch.linspace(-2.0, 2.0, 17)
    x, y, z = torch.meshgrid(axes, axes, axes, indexing="ij")
    radius = torch.stack([x, y, z], -1).norm(dim=-1)
    norm = torch.stack([x, y, z], -1).abs().amax(-1)
    with torch.no_grad():
        grid.features[..., 0] = torch.where((radius < 0.5) | (norm > 1.9), 1.0, -1.0)
        grid.features[..., 1:] = torch.where((radius < 0.5)[..., None], torch.tensor([-3.0, 3.0, -3.0]),
                                             torch.tensor([-3.0, -3.0, 3.0]))
    return grid


def test_scene_backbone_fits_a_background_the_relu_field_cannot():
    """Capacity, on the training views: rays that miss the object box can only be white for a ReLU field.

    (Generalisation to held-out views is measured on fox in bench/real_scenes.py; from ten
    16-pixel views a background at infinity is ambiguous with paint on the far wall.)
    """
    truth = _background_scene()
    cameras = Cameras.from_fov(ring_poses(10, 20.0), 0.9, 16, 16)
    images = torch.stack([render_image(truth, cameras, i).rgb for i in range(len(cameras))])
    config = ReconstructConfig.fast(resolutions=(17,), iterations=(120,), image_downsample=(1,), rays_per_step=512)
    scene = reconstruct(images, cameras, config, initial_grid=SceneGrid(17))
    relu = reconstruct(images, cameras, config)
    assert isinstance(scene, SceneGrid)
    scene_psnr = float(psnr(torch.stack([render_image(scene, cameras, i).rgb for i in range(10)]), images).mean())
    relu_psnr = float(psnr(torch.stack([render_image(relu, cameras, i).rgb for i in range(10)]), images).mean())
    assert scene_psnr > 25.0 and scene_psnr > relu_psnr + 5.0


def test_edit_and_refinement_run_unchanged_on_a_scene_grid(tiny_sd_path):
    from voxe_core.refine.config import RefineConfig
    from voxe_core.refine.pipeline import merge, refine

    guidance = StableDiffusionGuidance.from_pretrained(str(tiny_sd_path), device="cpu", local_files_only=True)
    initial = _background_scene()
    edited = edit(initial, "a fox", guidance, EditConfig(iterations=2, render_size=32))
    assert isinstance(edited, SceneGrid) and edited.header() == initial.header()
    assert torch.isfinite(edited.features).all() and not torch.equal(edited.features, initial.features)
    config = RefineConfig(views=2, render_size=24, iterations=20, rays_per_step=256, edit_seeds=5, object_seeds=5)
    result = refine(initial, edited, "a fox wearing sunglasses", ["sunglasses"], guidance, config)
    assert isinstance(result.refined_grid, SceneGrid)
    assert torch.equal(result.refined_grid.features, merge(initial, edited, result.mask).features)
    assert not (result.mask & ~initial.object_vertices()).any()  # the room is never part of a local edit


def test_a_local_edits_graph_cut_is_among_the_foregrounds_vertices():
    """The room in the contracted shell is occupied, yet no node of the cut: a local edit is of the object."""
    from voxe_core.refine.cut import node_mask

    grid = _background_scene()
    axes = torch.linspace(-2.0, 2.0, 17)
    lattice = torch.stack(torch.meshgrid(axes, axes, axes, indexing="ij"), -1)
    foreground = lattice.abs().amax(-1) <= 1.0
    assert torch.equal(grid.object_vertices(), foreground) and int(foreground.sum()) == 9**3
    room, ball = lattice.abs().amax(-1) > 1.9, lattice.norm(dim=-1) < 0.5
    for rule in ("alpha", "maxpool"):
        nodes = node_mask(grid, rule=rule)
        assert nodes[ball].all() and not nodes[room].any() and not (nodes & ~foreground).any(), rule
    assert VoxelGrid(4).object_vertices().all()


def test_the_edit_looks_at_an_off_centre_capture_object(tiny_sd_path):
    """G_i's orbit centre is where the edit's poses look: its preview of G_i has the ball in the middle."""
    from test_export import scene_blob

    guidance = StableDiffusionGuidance.from_pretrained(str(tiny_sd_path), device="cpu", local_files_only=True)
    blob = (0.5625, -0.375, 0.1875)
    initial = scene_blob(blob)
    previews = {}
    edit(initial, "a ball", guidance, EditConfig(iterations=1, render_size=32, preview_every=1),
         on_preview=lambda iteration, image: previews.setdefault(iteration, image))
    ball = 1.0 - previews[0][..., 1]  # red on white: green marks where the ball covers the pixel
    ys, xs = torch.meshgrid(torch.arange(32) + 0.5, torch.arange(32) + 0.5, indexing="ij")
    centroid = torch.stack([(ball * xs).sum(), (ball * ys).sum()]) / ball.sum()
    assert float(ball.sum()) > 20 and (centroid - 16).abs().max() < 0.25, centroid


# ----------------------------------------------------------------- CLI
def test_cli_picks_the_scene_backbone_for_photos_and_renders_in_its_frame(tmp_path, capsys):
    from conftest import DATA_ROOT
    from voxe_core.cli import main

    fox, out = DATA_ROOT / "fox", tmp_path / "fox.safetensors"
    small = ["--downsample", "32", "--max-images", "8", "-q"]  # the first 8 frames span enough of the orbit
    assert main(["reconstruct", str(fox), "--out", str(out), *small, "--resolution", "12",
                 "--iterations", "2,2", "--rays", "64"]) == 0
    assert "(scene backbone)" in capsys.readouterr().err
    grid = load_grid(out)
    assert isinstance(grid, SceneGrid) and not torch.equal(grid.frame, torch.eye(4))
    assert main(["render", str(out), "--data", str(fox), "--split", "train", *small, "--out", str(tmp_path / "views")]) == 0
    assert len(list((tmp_path / "views").glob("*.png"))) == 8


# ----------------------------------------------------------------- service parameters
def test_job_parameter_chooses_the_backbone_and_auto_shares_the_default_fit():
    from pydantic import ValidationError

    from api.schemas import ReconstructionParams
    from voxe_core.presets import reconstruction_key, reconstruction_params

    assert ReconstructionParams().backbone == "auto"
    assert ReconstructionParams(backbone="scene").backbone == "scene"
    with pytest.raises(ValidationError, match="backbone"):
        ReconstructionParams(backbone="dvgo")
    default = reconstruction_key(reconstruction_params({}))
    assert reconstruction_key(reconstruction_params({"reconstruction": {"backbone": "auto"}})) == default
    assert reconstruction_params({"reconstruction": {"backbone": "scene"}})["backbone"] == "scene"
    assert reconstruction_key(reconstruction_params({"reconstruction": {"backbone": "relu_field"}})) != default


def test_fit_setup_resolves_the_backbone_from_alpha_and_frames_a_scene_fit():
    """The CLI's and the worker's one set-up: photos get the scene preset in their canonical frame, objects on a
    transparent background a fresh ReLU field with the fast preset and their own cameras."""
    from voxe_core.presets import fit_setup, reconstruction_params

    cameras = Cameras.from_fov(ring_poses(4, 20.0, radius=3.0), 0.7, 8, 8)
    photos = fit_setup(reconstruction_params({}), None, cameras, checkpoint_every=7)
    assert (photos.backbone, photos.config) == ("scene", dataclasses.replace(ReconstructConfig.scene(), checkpoint_every=7))
    assert isinstance(photos.initial, SceneGrid) and photos.initial.resolution == (48, 48, 48)
    assert torch.equal(photos.initial.frame, scene_frame(cameras))
    assert torch.allclose(photos.cameras.c2w, apply_frame(cameras, scene_frame(cameras)).c2w)
    alphas = torch.ones(4, 8, 8)
    alphas[:, :, :4] = 0.0
    objects = fit_setup(reconstruction_params({}), alphas, cameras)
    assert (objects.backbone, objects.config, objects.initial) == ("relu_field", ReconstructConfig.fast(), None)
    assert objects.cameras is cameras
    forced = fit_setup(reconstruction_params({"reconstruction": {"backbone": "relu_field"}}), None, cameras)
    assert forced.backbone == "relu_field" and forced.initial is None
    # A scene whose kind was decided beforehand (the service's ingest, from all its images): "auto" is that kind
    # whatever the loaded subset's alpha says, and a named backbone still wins.
    recorded = fit_setup(reconstruction_params({}), alphas, cameras, scene_backbone="scene")
    assert recorded.backbone == "scene" and isinstance(recorded.initial, SceneGrid)
    named = fit_setup(reconstruction_params({"reconstruction": {"backbone": "relu_field"}}), None, cameras,
                      scene_backbone="scene")
    assert named.backbone == "relu_field"
    with pytest.raises(ValueError, match=r"got 3: backbone 'auto' is 'scene' for this scene \(its images are opaque"):
        fit_setup(reconstruction_params({"reconstruction": {"iterations": [1, 2, 3]}}), None, cameras)


def test_dataset_cameras_move_into_a_scene_grids_frame_only():
    cameras = Cameras.from_fov(ring_poses(2, 10.0, radius=2.0), 0.7, 4, 4)
    frame = torch.diag(torch.tensor([2.0, 2.0, 2.0, 1.0]))
    moved = SceneGrid(4, frame=frame).dataset_cameras(cameras)
    assert torch.allclose(moved.c2w[:, :3, 3], 2 * cameras.c2w[:, :3, 3])
    assert torch.allclose(moved.c2w[:, :3, :3], cameras.c2w[:, :3, :3])
    assert VoxelGrid(4).dataset_cameras(cameras) is cameras


def test_mesh_export_of_a_scene_grid_is_its_foreground_in_the_canonical_frame():
    from voxe_core.export import extract_mesh

    grid = _background_scene()  # ball of contracted radius 0.5 -> 0.75 canonical units; room at infinity
    with torch.no_grad():
        grid.features.add_(0.01 * torch.randn(grid.features.shape, generator=torch.Generator().manual_seed(0)))
    foreground = grid.foreground_grid()
    assert foreground.resolution == (9, 9, 9) and torch.allclose(foreground.bbox_max, torch.full((3,), 1.5))
    points = (torch.rand(200, 3, generator=torch.Generator().manual_seed(1)) * 2 - 1) * 1.5
    assert torch.allclose(foreground.interpolate(points), grid.interpolate(grid.lattice_points(points)), atol=1e-5)
    mesh = extract_mesh(grid)
    assert abs(mesh.vertices).max() < 1.5  # the room is not in it
    assert 0.5 < float(np.linalg.norm(mesh.vertices, axis=1).mean()) < 1.0


def test_a_scene_grids_foreground_taken_under_a_callers_bf16_autocast_is_the_float32_one():
    """Its resampling (VoxelGrid.interpolate's bmm) had run in bf16 under a caller's autocast: raw features 0.011 off,
    and with them the orbit centre every turntable and edit pose circles (3e-4 off), the mesh and the edit's camera
    check (the renderer's float32 under autocast is the rule)."""
    grid = SceneGrid(12, foreground_extent=1.2, near_samples=4, far_samples=8, far_ratio=50.0)
    with torch.no_grad():
        grid.features.normal_(generator=torch.Generator().manual_seed(0))
    expected, centre = grid.foreground_grid(), grid.orbit_centre()
    with torch.autocast("cpu", dtype=torch.bfloat16):
        foreground, orbit_centre = grid.foreground_grid(), grid.orbit_centre()
    assert foreground.features.dtype == torch.float32 and torch.equal(foreground.features, expected.features)
    assert torch.equal(orbit_centre, centre)


def test_a_scene_grid_two_vertices_wide_has_a_foreground_to_orbit_and_mesh():
    """Regression: its foreground grid was 1 vertex wide along that axis, refused as a grid, so its orbit centre (every
    turntable and evaluation ring of it) and its mesh failed with "grid resolution must be >= 2 per axis, got
    (1, 5, 5)": a resolution the user never gave."""
    from voxe_core.export import extract_mesh

    grid = SceneGrid((2, 9, 9))
    with torch.no_grad():
        grid.features[..., 0] = _raw_for_density(grid, 100.0)  # dense everywhere: the mesh is the foreground cube
    foreground = grid.foreground_grid()
    assert foreground.resolution == (2, 5, 5)
    points = (torch.rand(100, 3, generator=torch.Generator().manual_seed(0)) * 2 - 1) * grid.foreground_extent
    assert torch.allclose(foreground.interpolate(points), grid.interpolate(grid.lattice_points(points)), atol=1e-5)
    assert torch.allclose(grid.orbit_centre(), torch.zeros(3), atol=1e-5)
    bounds = extract_mesh(grid).bounds
    assert np.allclose(bounds, [[-1.5] * 3, [1.5] * 3], atol=1e-4)


def test_scene_fits_get_the_scene_preset_by_default_and_their_key_follows_it(monkeypatch):
    """CLI and service resolve a scene-backbone fit to ReconstructConfig.scene() unless a preset is named;
    a change to that preset changes the cache key of every fit that can become a scene fit."""
    from voxe_core.cli import build_parser
    from voxe_core.cli.reconstruct import job_params
    from voxe_core.presets import check_fit, reconstruct_config, reconstruction_key, reconstruction_params

    cli = job_params(build_parser().parse_args(["reconstruct", "fox", "--out", "g.safetensors"]))
    for params in (reconstruction_params(cli), reconstruction_params({})):
        assert reconstruct_config(params, backbone="scene") == ReconstructConfig.scene()
        assert reconstruct_config(params, backbone="relu_field") == ReconstructConfig.fast()
    named = reconstruction_params({"reconstruction": {"preset": "fast"}})
    # ... a named preset is that budget, drawn, rendered, stepped and regularised as a capture needs (the early-stop
    # pass, every image, scene()'s lr and priors), its steps and rays its own
    capture, fast, scene = ReconstructConfig.fast().for_backbone("scene"), ReconstructConfig.fast(), ReconstructConfig.scene()
    assert reconstruct_config(named, backbone="scene") == capture != fast
    as_capture = lambda c: (c.images_per_step, c.lr, c.render.early_stop, c.tv_density, c.tv_color,  # noqa: E731
                            c.camera_clearance)
    assert as_capture(capture) == as_capture(scene) != as_capture(fast)
    assert fast.tv_density == fast.tv_color == fast.camera_clearance == 0  # an object's fit has none of them
    assert (capture.iterations, capture.rays_per_step, capture.resolutions) == (fast.iterations, fast.rays_per_step,
                                                                                fast.resolutions)
    keys = {name: reconstruction_key(reconstruction_params({"reconstruction": {"backbone": name}}))
            for name in ("auto", "scene", "relu_field")}
    named_key = reconstruction_key(named)
    scene = ReconstructConfig.scene
    monkeypatch.setattr(ReconstructConfig, "scene", classmethod(lambda cls, **kw: scene(**{"rays_per_step": 4096, **kw})))
    after = {name: reconstruction_key(reconstruction_params({"reconstruction": {"backbone": name}}))
             for name in keys}
    assert after["auto"] != keys["auto"] and after["scene"] != keys["scene"]
    assert after["relu_field"] == keys["relu_field"] and reconstruction_key(named) == named_key
    # Per-stage iterations sized for one preset are refused only when no backbone "auto" can become takes them.
    reconstruction_key(reconstruction_params({"reconstruction": {"iterations": [1, 2, 3]}}))
    with pytest.raises(ValueError, match="one per stage"):
        reconstruction_key(reconstruction_params({"reconstruction": {"iterations": [1, 2, 3], "backbone": "scene"}}))
    # Once the scene's backbone is known, "auto" is checked as that backbone and the refusal says why.
    three = reconstruction_params({"reconstruction": {"iterations": [1, 2, 3]}})
    check_fit(three, None)
    check_fit(three, "relu_field")
    with pytest.raises(ValueError, match=r"\(2 stages\), got 3: backbone 'auto' is 'scene' for this scene \(its "
                                         r"images are opaque photos\)$"):
        check_fit(three, "scene")
    with pytest.raises(ValueError, match=r"\(2 stages\), got 3$"):  # (named: nothing to explain)
        check_fit(reconstruction_params({"reconstruction": {"iterations": [1, 2, 3], "backbone": "scene"}}), "relu_field")


def test_early_stop_in_the_contracted_shell_changes_the_render_by_less_than_its_threshold():
    """The scene sampler's early stop drops only samples whose transmittance is below the cut."""
    grid = _background_scene()
    origins = torch.tensor([[4.0, 0.3, 0.5]]).expand(64, 3).contiguous()
    directions = torch.nn.functional.normalize(torch.randn(64, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    full = render_rays(grid, origins, directions, RenderConfig(early_stop=0.0))
    cut = render_rays(grid, origins, directions, RenderConfig(early_stop=1e-3))  # capped at EARLY_STOP_CAP
    assert cut.samples - full.samples < full.samples  # counts the probe (all of full's samples), then fewer kept
    assert (cut.rgb - full.rgb).abs().max() <= 2e-6 and (cut.opacity - full.opacity).abs().max() <= 2e-6


def test_vertex_positions_uncontract_the_lattice_and_rows_within_finds_them():
    grid = SceneGrid(9, foreground_extent=1.5)
    positions = grid.vertex_positions()
    finite = torch.isfinite(positions).all(-1)
    lattice = torch.stack(torch.meshgrid(*[torch.linspace(-2, 2, 9)] * 3, indexing="ij"), -1).reshape(-1, 3)
    assert torch.allclose(contract(positions[finite] / 1.5), lattice[finite], atol=1e-6)
    assert not finite[lattice.abs().amax(-1) == 2].any()  # the outer faces lie at infinity
    # Vertex (1.5, 0, 0) in the lattice is at 1.5 · 1/(1.5 · 0.5) = 2 foreground units, 3 canonical ones.
    rows = grid.rows_within(torch.tensor([[3.0, 0.0, 0.0]]), torch.tensor([0.1]))
    assert lattice[rows].tolist() == [[1.5, 0.0, 0.0]]
