"""The fast lift (issue 18): the weighted back-projection of the maps is Aᵀ of the raw render, and the fit starts from it."""

from __future__ import annotations

import math
import re

import pytest
import torch

from voxe_core.cameras import Cameras, random_hemisphere_poses
from voxe_core.grid import VoxelGrid
from voxe_core.refine.config import RefineConfig
from voxe_core.refine.lifting import all_camera_rays, backproject, fit_attention_grids
from voxe_core.render import RenderConfig, render_rays


pytestmark = pytest.mark.usefixtures("single_thread")  # tiny tensors: threads cost more than they save


def cloud_grid(res=10, seed=0) -> VoxelGrid:
    """Semi-transparent random density: every ray sees several vertices with unequal weights."""
    grid = VoxelGrid(res)
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        grid.features[..., 0] = torch.rand(grid.resolution, generator=gen) * 2.0 / grid.density_scale
    return grid


def some_rays(n_views=3, size=8, seed=1):
    c2w, _, _ = random_hemisphere_poses(n_views, torch.Generator().manual_seed(seed))
    return all_camera_rays(Cameras.from_fov(c2w, 0.7, size, size))


def test_backprojection_is_the_adjoint_of_the_raw_render():
    # <A v, m> = <v, Aᵀ m>: the numerator equals the gradient of sum(render(v) · m) with respect to v
    grid = cloud_grid()
    origins, directions = some_rays()
    maps = torch.rand(origins.shape[0], 2, generator=torch.Generator().manual_seed(2))
    config = RefineConfig(backprojection_prior=0.3)
    values, weight = backproject(grid, origins, directions, maps, config)
    field = torch.zeros(*grid.resolution, 2, requires_grad=True)
    out = render_rays(grid, origins, directions, config.render, color_features=field)
    (out.rgb * maps).sum().backward()
    numerator = values * (weight + config.backprojection_prior)[..., None]
    assert weight.sum() > 0
    torch.testing.assert_close(numerator, field.grad, rtol=1e-4, atol=1e-5)
    ones = torch.zeros(*grid.resolution, 1, requires_grad=True)
    (render_rays(grid, origins, directions, config.render, color_features=ones).rgb.sum()).backward()
    torch.testing.assert_close(weight, ones.grad[..., 0], rtol=1e-4, atol=1e-5)


def test_backprojection_of_a_linear_map_recovers_it_on_the_surface():
    # opaque half-space z < 0, rays straight down through vertex columns: each surface vertex is seen by
    # exactly one pixel, whose map value is the vertex's x; with no prior it is recovered exactly
    res = 9
    grid = VoxelGrid(res)
    axes = torch.linspace(-1.5, 1.5, res)
    x, y, z = torch.meshgrid(axes, axes, axes, indexing="ij")
    with torch.no_grad():
        grid.features[..., 0] = torch.where(z < 0.1, 50.0, -1.0)
    px, py = torch.meshgrid(axes[1:-1], axes[1:-1], indexing="ij")
    origins = torch.stack([px.reshape(-1), py.reshape(-1), torch.full((px.numel(),), 3.0)], -1)
    directions = torch.tensor([0.0, 0.0, -1.0]).expand_as(origins)
    values, weight = backproject(grid, origins, directions, origins[:, :1].clone(), RefineConfig(backprojection_prior=0.0))
    seen = weight > 1e-3
    assert seen.any() and not seen[..., -1].any()  # the empty top layers are never reached
    torch.testing.assert_close(values[..., 0][seen], x[seen], atol=1e-5, rtol=0)


def test_backprojection_is_linear_and_the_prior_shrinks_toward_no_attention():
    grid = cloud_grid(seed=3)
    origins, directions = some_rays(seed=4)
    gen = torch.Generator().manual_seed(5)
    m1, m2 = torch.rand(origins.shape[0], 1, generator=gen), torch.rand(origins.shape[0], 1, generator=gen)
    config = RefineConfig(backprojection_prior=0.5)
    v1, w = backproject(grid, origins, directions, m1, config)
    v2, _ = backproject(grid, origins, directions, m2, config)
    v12, _ = backproject(grid, origins, directions, 2.0 * m1 - 3.0 * m2, config)
    torch.testing.assert_close(v12, 2.0 * v1 - 3.0 * v2, atol=1e-5, rtol=1e-4)
    constant, _ = backproject(grid, origins, directions, torch.full_like(m1, 0.8), config)
    torch.testing.assert_close(constant[..., 0], 0.8 * w / (w + 0.5))
    exact, _ = backproject(grid, origins, directions, torch.full_like(m1, 0.8), RefineConfig(backprojection_prior=0.0))
    assert torch.allclose(exact[w > 0], torch.tensor(0.8))


def test_fit_from_backprojection_with_no_steps_is_the_backprojection_and_unseen_vertices_stay_zero():
    grid = cloud_grid(seed=6)
    c2w, _, _ = random_hemisphere_poses(2, torch.Generator().manual_seed(7))
    cams = Cameras.from_fov(c2w, 0.7, 8, 8)
    gen = torch.Generator().manual_seed(8)
    edit, obj = torch.rand(2, 8, 8, generator=gen), torch.rand(2, 8, 8, generator=gen)
    config = RefineConfig(iterations=0, backprojection_stride=1)
    e, o = fit_attention_grids(grid, cams, edit, obj, config)
    origins, directions = all_camera_rays(cams)
    values, weight = backproject(grid, origins, directions, torch.stack([edit, obj], -1).reshape(-1, 2), config)
    torch.testing.assert_close(torch.cat([e, o], -1), values)
    # a few steps move only the seen vertices and lower the L1 of the renders
    e2, o2 = fit_attention_grids(grid, cams, edit, obj, RefineConfig(iterations=30, rays_per_step=128, tv_weight=0.0, fit_views="fixed"))
    unseen = weight == 0
    assert unseen.any() and (e2[..., 0][unseen] == 0).all() and (o2[..., 0][unseen] == 0).all()

    @torch.no_grad()
    def l1(field):
        out = render_rays(grid, origins, directions, config.render, color_features=field)
        return float((out.rgb - torch.stack([edit, obj], -1).reshape(-1, 2)).abs().mean())

    assert l1(torch.cat([e2, o2], -1)) < l1(values)


def test_strided_backprojection_covers_every_pixel_once_over_stride_squared_views():
    from voxe_core.refine.lifting import strided_pixels

    picks = strided_pixels(8, 6, 6, 2).view(8, 6, 6)
    assert int(picks.sum()) == 8 * 36 // 4
    assert (picks[:4].sum(0) == 1).all() and (picks[4:].sum(0) == 1).all()
    assert strided_pixels(3, 5, 5, 1).all()


def test_backprojection_reports_each_chunk_and_stops_when_cancelled():
    """The service's default lift is the back-projection alone (no fit steps): 81 s at 160³ on a CPU, during which
    a cancel had waited and progress stood still."""
    from dataclasses import replace

    from voxe_core.progress import Callbacks, StageCancelled

    grid = cloud_grid()
    origins, directions = some_rays()  # 3 views of 8 x 8: 192 rays
    config = RefineConfig()
    config = replace(config, render=replace(config.render, chunk_rays=50))
    reports = []
    backproject(grid, origins, directions, torch.ones(192, 2), config, callbacks=Callbacks(on_progress=reports.append))
    assert [(p.stage, p.iteration, p.total) for p in reports] == [("backprojection", i, 4) for i in (1, 2, 3, 4)]
    asked = []
    stop_at_third = Callbacks(should_cancel=lambda: asked.append(1) or len(asked) == 3)
    with pytest.raises(StageCancelled, match="backprojection"):
        backproject(grid, origins, directions, torch.ones(192, 2), config, callbacks=stop_at_third)
    assert len(asked) == 3


@pytest.mark.parametrize("fit", [dict(fit_views="fixed", iterations=5), dict(lift_start="backprojection",
                                                                              iterations=0)])
def test_views_that_miss_the_object_are_a_segmentation_error_naming_the_cause(fit):
    """Cameras aimed away from the occupied box: a fixed-views fit had failed in torch.randint (low >= high), and the
    back-projection had lifted nothing, for the cut to fail on grids 'equal everywhere'."""
    from voxe_core.refine.config import SegmentationError

    grid = VoxelGrid(10)
    with torch.no_grad():
        grid.features[..., 0] = -1.0
        grid.features[0, 0, 0, 0] = 50.0  # a speck in a corner
    c2w = torch.eye(4)[None].clone()
    c2w[0, :3, 3] = torch.tensor([0.0, 0.0, 4.0])  # on the +z axis, looking down -z at the centre
    cams = Cameras.from_fov(c2w, 0.05, 4, 4)
    maps = torch.rand(1, 4, 4, generator=torch.Generator().manual_seed(0))
    with pytest.raises(SegmentationError, match="none of the 1 views sees the edited object"):
        fit_attention_grids(grid, cams, maps, maps.flip(-1), RefineConfig(**fit))


def test_a_render_background_of_other_than_one_value_is_refused_before_any_map():
    """RefineConfig(render=RenderConfig(step_ratio=0.6)), white by RenderConfig's default, had crashed the fit after
    every attention map: 'The expanded size of the tensor (2) must match the existing size (3)'."""
    with pytest.raises(ValueError, match=r"render.background .* one number for both or one per field .* got "
                                         r"\(1.0, 1.0, 1.0\)"):
        RefineConfig(render=RenderConfig(step_ratio=0.6))
    for background in ((0.0,), (0.0, 0.0)):  # one per field renders as one for both
        assert RefineConfig(render=RenderConfig(step_ratio=0.6, background=background)).render.step_ratio == 0.6


@pytest.mark.parametrize("bad", [dict(lift_start="random"), dict(backprojection_prior=-1.0),
                                 dict(backprojection_prior=math.nan), dict(backprojection_prior=math.inf),
                                 dict(backprojection_prior=1e39),
                                 dict(lr=math.inf), dict(lr=math.nan), dict(lr=0.0), dict(tv_weight=math.inf),
                                 dict(init_value=math.nan)])
def test_lift_options_are_checked(bad):
    """(voxe refine --lr inf had run the whole stage, then failed in the cut on fields 'not finite'; --lr nan in
    torch's optimizer after the model loaded. A NaN backprojection_prior made every back-projected value NaN, an
    infinite one every value 0, and the cut failed on fields 'not finite' or with 'no seeds' after every map.)"""
    with pytest.raises(ValueError, match=next(iter(bad))):
        RefineConfig(**bad)


@pytest.mark.parametrize("stride", [16, 17, 1000])
def test_a_backprojection_stride_of_the_render_size_or_more_is_refused(stride):
    """Every stride-th row and column of a view no wider than the stride is at most one pixel: accepted, such a
    stride had lifted next to nothing, for the cut to fail with 'no seeds' after every attention pass."""
    from voxe_core.refine.lifting import strided_pixels

    assert int(strided_pixels(4, 16, 16, stride).view(4, 16, 16).sum((1, 2)).max()) <= 1
    with pytest.raises(ValueError, match=f"backprojection_stride must be below render_size \\(16 px\\), got {stride}"):
        RefineConfig(render_size=16, backprojection_stride=stride)
    assert RefineConfig(render_size=16, backprojection_stride=15).backprojection_stride == 15


def _speck_grid() -> VoxelGrid:
    grid = VoxelGrid(10)
    with torch.no_grad():
        grid.features[..., 0] = -1.0
        grid.features[5, 5, 5, 0] = 50.0  # one dense vertex at the centre
    return grid


def _camera_on_z(fov: float, size: int) -> Cameras:
    c2w = torch.eye(4)[None].clone()
    c2w[0, :3, 3] = torch.tensor([0.0, 0.0, 4.0])  # on the +z axis, looking down -z at the centre
    return Cameras.from_fov(c2w, fov, size, size)


def test_a_backprojection_whose_pixels_miss_the_object_is_a_segmentation_error_naming_the_stride():
    """An object small in the view, seen by pixels off the default stride's rows and columns: the start had lifted
    nothing, and the grids reached the cut 'equal everywhere' ('too few fitting iterations, or maps that do not tell
    the edit from the object'). Every pixel read (stride 1), it lifts."""
    from voxe_core.refine.config import SegmentationError

    grid, cams = _speck_grid(), _camera_on_z(0.8, 8)  # one pixel, (3, 4), sees the speck's box
    maps = torch.rand(1, 8, 8, generator=torch.Generator().manual_seed(0))
    with pytest.raises(SegmentationError, match=r"^1 pixels of the 1 views see the edited object's box, but none that "
                                                r"the back-projection reads \(one row and column in 2\) meets its "
                                                r"density: .* lower backprojection_stride"):
        fit_attention_grids(grid, cams, maps, maps.flip(-1), RefineConfig(render_size=8))
    every_pixel = RefineConfig(render_size=8, backprojection_stride=1)
    edit, obj = fit_attention_grids(grid, cams, maps, maps.flip(-1), every_pixel)
    assert (edit != 0).any() and not torch.equal(edit, obj)


def test_a_backprojection_reading_every_pixel_that_meets_no_density_blames_the_views_not_the_stride():
    """Two dense specks, and a narrow view whose pixels all cross their occupied box between them: at stride 1 every
    pixel is read, yet the refusal had blamed the stride and said to lower it."""
    from voxe_core.refine.config import SegmentationError

    grid = VoxelGrid(10)
    with torch.no_grad():
        grid.features[..., 0] = -1.0
        grid.features[2, 2, 5, 0] = grid.features[7, 7, 5, 0] = 50.0
    maps = torch.rand(1, 8, 8, generator=torch.Generator().manual_seed(0))
    with pytest.raises(SegmentationError, match=r"^64 pixels of the 1 views see the edited object's box, but each "
                                                r"pixel's ray passes through its empty space, meeting none of its "
                                                r"density: .* aim the views at the object") as refused:
        fit_attention_grids(grid, _camera_on_z(0.05, 8), maps, maps.flip(-1),
                            RefineConfig(render_size=8, backprojection_stride=1))
    assert "stride" not in str(refused.value)


def test_a_constant_start_whose_views_miss_the_object_is_refused_though_fresh_views_would_see_it():
    """The fit moves only the vertices the start's views see: with none, a constant start fitted on fresh views
    had run every step and then blamed its length ('Adam moves both alike ... fit more iterations')."""
    from voxe_core.refine.config import SegmentationError

    grid = _speck_grid()
    away = _camera_on_z(0.05, 8)
    away.c2w[0, :2, 3] = 3.0  # off the axis, still looking down -z: it misses
    seeing, maps = _camera_on_z(0.3, 8), torch.rand(1, 8, 8, generator=torch.Generator().manual_seed(0))
    config = RefineConfig(render_size=8, lift_start="constant", fit_views="fresh", fit_pixels="all", iterations=3)
    steps = []
    with pytest.raises(SegmentationError, match="none of the 1 views sees the edited object"):
        fit_attention_grids(grid, away, maps, maps, config,
                            fresh_view=lambda step: steps.append(step) or (seeing, maps, maps.flip(-1)))
    assert steps == []


@pytest.mark.parametrize("shape", [(3, 8, 8, 1), (8, 8)])
def test_maps_of_another_shape_than_views_height_width_are_refused_naming_it(shape):
    """They had failed unpacking their shape: 'too many values to unpack (expected 3)', naming neither the maps nor
    the shape."""
    cams = Cameras.from_fov(random_hemisphere_poses(3, torch.Generator().manual_seed(1))[0], 0.7, 8, 8)
    maps = torch.rand(shape)
    with pytest.raises(ValueError, match=rf"^the maps must be \(views, height, width\), one scalar per pixel, got edit "
                                         rf"maps of shape {re.escape(str(shape))}$"):
        fit_attention_grids(cloud_grid(), cams, maps, maps, RefineConfig(render_size=8, iterations=0))


@pytest.mark.parametrize("bad", [math.nan, math.inf])
def test_maps_that_are_not_finite_are_refused_before_any_work(bad):
    """A NaN or infinite map pixel had made the back-projected start (and every fitting step) NaN, for the cut to
    blame 'a diverged edit or attention-grid fit?' at the end."""
    from voxe_core.progress import Callbacks
    from voxe_core.refine.config import SegmentationError

    grid = cloud_grid()
    cams = Cameras.from_fov(random_hemisphere_poses(3, torch.Generator().manual_seed(1))[0], 0.7, 8, 8)
    maps = torch.rand(3, 8, 8, generator=torch.Generator().manual_seed(2))
    broken = maps.clone()
    broken[1, 4, 4] = bad
    reports = []
    with pytest.raises(SegmentationError, match=r"^the object maps are not finite \(NaN or infinite\) in 1 of the 3 "
                                                r"views \(the first: view 2\)"):
        fit_attention_grids(grid, cams, maps, broken, RefineConfig(render_size=8),
                            Callbacks(on_progress=reports.append))
    assert reports == []  # refused before the back-projection


@pytest.mark.parametrize("bad", [dict(backprojection_stride=1.5), dict(backprojection_stride=math.nan),
                                 dict(views=2.5), dict(render_size=16.5), dict(iterations=1.5), dict(timestep=200.7),
                                 dict(rays_per_step=True), dict(edit_seeds=300.0)])
def test_counts_that_are_not_whole_numbers_are_refused(bad):
    """A stride of 1.5 had read one pixel row and column in 3 (a lattice it names nowhere), a timestep of 200.7 ran
    at 200, and a NaN stride failed in int() ('cannot convert float NaN to integer'). numpy's integers are whole."""
    import numpy as np

    name, value = next(iter(bad.items()))
    with pytest.raises(ValueError, match=f"^{name} must be a whole number, got {value!r}$"):
        RefineConfig(**bad)
    assert RefineConfig(views=np.int64(3), backprojection_stride=np.int32(3)).backprojection_stride == 3
