"""The grid's box: its slab test (``ray_box_intersection``: a closed box, a ray lying in any of its faces meets it), and
its corners, three numbers each."""

from __future__ import annotations

import math
import re

import pytest
import torch

from needs import require_triton_interpreter
from voxe_core.grid import VoxelGrid, ray_box_intersection
from voxe_core.render import RenderConfig, render_rays

BOX = torch.tensor([-1.0, -2.0, 0.5]), torch.tensor([2.0, 1.0, 3.0])


def _face_rays(box_min, box_max, inset: float = 0.0):
    """A ray in each face of the box (or ``inset`` inside it), per face along both other axes: origins 5 before the
    box, unit directions whose other components are zero of either sign; and each ray's span through the box."""
    centre = (box_min + box_max) / 2
    origins, directions, spans = [], [], []
    for face_axis in range(3):
        for face, inward in ((box_min[face_axis], inset), (box_max[face_axis], -inset)):
            for travel in {0, 1, 2} - {face_axis}:
                origin = centre.clone()
                origin[face_axis], origin[travel] = face + inward, box_min[travel] - 5.0
                direction = torch.tensor([-0.0, -0.0, -0.0]) if travel % 2 else torch.zeros(3)
                direction[travel] = 1.0
                origins.append(origin)
                directions.append(direction)
                spans.append((5.0, 5.0 + float(box_max[travel] - box_min[travel])))
    return torch.stack(origins), torch.stack(directions), torch.tensor(spans)


def test_a_ray_in_any_face_of_the_box_meets_it_as_one_just_inside_does():
    """A ray in the box's upper face along an axis had missed it (its slab's exit 0 × the stand-in reciprocal), one in
    the lower face met it: the test is now the closed box's on every face, for one box or several stacked."""
    origins, directions, spans = _face_rays(*BOX)
    near, far = ray_box_intersection(origins, directions, *BOX)
    assert torch.equal(torch.stack([near, far], -1), spans)  # all twelve faces-and-directions
    inside = ray_box_intersection(*_face_rays(*BOX, inset=1e-3)[:2], *BOX)
    assert torch.equal(torch.stack(inside, -1), spans)
    other = torch.stack([BOX[0] - 1.0, BOX[0]]), torch.stack([BOX[1] + 1.0, BOX[1]])  # (the sampler's two boxes)
    near, far = ray_box_intersection(origins, directions, *other)
    assert torch.equal(torch.stack([near[1], far[1]], -1), spans) and (far[0] > near[0]).all()
    # just outside a face (one float32 step off it): a miss, on either side
    sign = torch.where(spans.new_tensor([i // 2 % 2 for i in range(12)]) == 0, -1.0, 1.0)
    face_axis = torch.arange(12) // 4
    off = origins.clone()
    off[torch.arange(12), face_axis] = torch.nextafter(off[torch.arange(12), face_axis],
                                                       off[torch.arange(12), face_axis] + sign * math.inf)
    near, far = ray_box_intersection(off, directions, *BOX)
    assert (far <= near).all()


@pytest.mark.parametrize("fused", [False, True])
def test_a_ray_grazing_a_face_renders_that_faces_vertices(fused):
    """Uniform density, the vertices of the x faces coloured (lower red, upper blue): a ray along z in either x face
    renders its face's colour at a full path's opacity, where the one in the upper face had rendered the white
    background; with empty-space skipping too (the occupied cells' tight box is the grid's)."""
    if fused:
        require_triton_interpreter()
    features = torch.full((5, 5, 5, 4), -10.0)
    features[..., 0] = 1.0
    features[0, :, :, 1] = features[4, :, :, 3] = 10.0  # red at x = -1.5, blue at x = 1.5
    grid = VoxelGrid(5, features=features)
    origins = torch.tensor([[-1.5, 0.3, -4.0], [1.5, 0.3, -4.0], [0.0, 0.3, -4.0]])
    directions = torch.tensor([[0.0, 0.0, 1.0]] * 3)
    for skip_empty in (False, True):
        out = render_rays(grid, origins, directions, RenderConfig(fused=fused, skip_empty=skip_empty))
        assert isinstance(out.samples, torch.Tensor) == fused  # the marcher asked for ran
        opacity = 1 - math.exp(-float(grid.activate_density(torch.tensor(1.0))) * 3.0)
        torch.testing.assert_close(out.opacity, torch.full((3,), opacity), atol=1e-5, rtol=0)
        colour = torch.sigmoid(torch.tensor(10.0)) * opacity + (1 - opacity)  # on white
        plain = torch.sigmoid(torch.tensor(-10.0)) * opacity + (1 - opacity)
        expected = torch.tensor([[colour, plain, plain], [plain, plain, colour], [plain, plain, plain]])
        torch.testing.assert_close(out.rgb.detach(), expected, atol=1e-5, rtol=0)


@pytest.mark.parametrize("fused", [False, True])
def test_a_ray_in_a_face_of_a_grid_whose_lattice_rounds_inside_it_meets_the_occupied_box(fused):
    """At 38 vertices in the default box the last vertex lies at -1.5 + 37 · 3/37 = 1.4999998 in float32: the occupied
    cells' tight box had ended there, and a ray lying in an upper face (y = 1.5) missed it, skipped as empty and
    rendered blank, where without skipping it rendered the face's density. The tight box ends at the face now."""
    if fused:
        require_triton_interpreter()
    grid = VoxelGrid(38, init_density=0.05)
    occupancy = grid.occupancy(0.0)
    assert torch.equal(occupancy.bbox_min, grid.bbox_min) and torch.equal(occupancy.bbox_max, grid.bbox_max)
    origins, directions, _ = _face_rays(grid.bbox_min, grid.bbox_max)
    opacity = 1 - math.exp(-float(grid.activate_density(torch.tensor(0.05))) * 3.0)
    for skip_empty in (False, True):
        out = render_rays(grid, origins, directions, RenderConfig(fused=fused, skip_empty=skip_empty))
        assert isinstance(out.samples, torch.Tensor) == fused  # the marcher asked for ran
        torch.testing.assert_close(out.opacity, torch.full((12,), opacity), atol=1e-5, rtol=0)


@pytest.mark.parametrize("bbox_min, bbox_max", [((-1.0, -1.0), (1.0, 1.0)), ((-1.0,) * 4, (1.0,) * 4), (-1.5, 1.5),
                                                ("a", "b")])
def test_a_box_whose_corners_are_not_three_numbers_is_refused_naming_it(bbox_min, bbox_max):
    """Two numbers a corner had failed building the lattice ("The size of tensor a (2) must match the size of tensor b
    (3)", a RuntimeError the CLI shows as a bug), one number "'float' object is not iterable"; a fit of such a
    ReconstructConfig box failed so as it started."""
    from voxe_core.cameras import Cameras, look_at
    from voxe_core.reconstruct import ReconstructConfig, reconstruct

    message = (r"^the box's corners must be three numbers each \(x, y, z\), got min " + re.escape(repr(bbox_min))
               + " and max " + re.escape(repr(bbox_max)) + "$")
    with pytest.raises(ValueError, match=message):
        VoxelGrid(4, bbox_min, bbox_max)
    cams = Cameras.from_fov(look_at(torch.tensor([[0.0, -4.0, 1.0]])), 0.7, 4, 4)
    with pytest.raises(ValueError, match=message):
        reconstruct(torch.ones(1, 4, 4, 3), cams, ReconstructConfig(resolutions=(4,), iterations=(1,),
                                                                    image_downsample=(1,), bbox_min=bbox_min,
                                                                    bbox_max=bbox_max))
    assert VoxelGrid(4, [-1, -1, -1], torch.ones(3)).bbox_max.tolist() == [1.0, 1.0, 1.0]


@pytest.mark.parametrize("thickness", [1e-12, 1e-6, 1e-4])
def test_a_box_too_thin_for_its_resolution_is_refused_naming_it(thickness):
    """The sampler steps by the smallest voxel edge: a box 2e-6 thin along z of 16 cells took ~80 s to render a ray
    along it, 2e-12 thin rendered blank (white where the grid was dense); a fit of such a ReconstructConfig box
    started so."""
    from voxe_core.cameras import Cameras, look_at
    from voxe_core.reconstruct import ReconstructConfig, reconstruct

    box = (-1.0, -1.0, -thickness), (1.0, 1.0, thickness)
    message = r"^the box min \[-1\.0, -1\.0, .*\] is too thin along z for resolution \(16, 16, 16\): .*at most 10000"
    with pytest.raises(ValueError, match=message):
        VoxelGrid(16, *box)
    cams = Cameras.from_fov(look_at(torch.tensor([[0.0, -4.0, 1.0]])), 0.7, 4, 4)
    with pytest.raises(ValueError, match=message):
        reconstruct(torch.ones(1, 4, 4, 3), cams, ReconstructConfig(resolutions=(16,), iterations=(1,),
                                                                    image_downsample=(1,), bbox_min=box[0],
                                                                    bbox_max=box[1]))
    grid = VoxelGrid(16, (-1.0, -1.0, -1e-2), (1.0, 1.0, 1e-2), init_density=10.0)  # 2e-2 thin: 2.1e3 edges
    out = render_rays(grid, torch.tensor([[-3.0, 0.05, 0.0]]), torch.tensor([[1.0, 0.0, 0.0]]))
    assert float(out.opacity[0]) > 0.99  # along the slab, through its density


@pytest.mark.parametrize("early_stop", [0.01, 0.1])
def test_rays_sampled_under_a_callers_bf16_autocast_stop_where_the_float32_ones_do(make_sphere_grid, early_stop):
    """The early-stop pass's density interpolation (a bmm) had run in bf16 under a caller's autocast (the
    back-projection iterates ray_samples in its own), so rays through a soft sphere had kept other samples (8,207
    against 8,205 of 11,912 at 0.01) than the render's float32 pass."""
    grid = make_sphere_grid(16, slope=0.3)
    origins = torch.tensor([0.0, 0.0, -3.0]) + 0.5 * torch.randn(400, 3, generator=torch.Generator().manual_seed(0))
    directions, offsets = torch.tensor([[0.0, 0.0, 1.0]]).expand(400, 3), torch.full((400,), 0.5)
    expected = next(grid.ray_samples(origins, directions, offsets, 0.5, early_stop=early_stop))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        samples = next(grid.ray_samples(origins, directions, offsets, 0.5, early_stop=early_stop))
    assert samples.probed == expected.probed and samples.ray.numel() < samples.probed
    assert torch.equal(samples.ray, expected.ray) and torch.equal(samples.points, expected.points)
