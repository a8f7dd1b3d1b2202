"""Sparse grid files: exact on every stored vertex, identical renders, old dense files, users' own readers."""

from __future__ import annotations

import errno
import json
import os
import signal
from pathlib import Path

import numpy as np
import pytest
import safetensors.torch
import torch
from safetensors import SafetensorError, safe_open
from safetensors.numpy import load_file

from voxe_core.backbones import load_grid
from voxe_core.cli import main
from voxe_core.export import turntable_cameras
from voxe_core.grid import VoxelGrid
from voxe_core.gridfile import dense_tensors, dilate, sparse_tensors, stored_vertices
from voxe_core.render import RenderConfig, render_image
from voxe_core.scene_grid import SceneGrid
from voxe_core.tensorio import FormatError, load_tensors, save_tensors


def noisy_sphere(make_sphere_grid, resolution=40, seed=0) -> VoxelGrid:
    """A small sphere off-centre with random colours and random negative empty space (not one constant)."""
    grid = make_sphere_grid(resolution=resolution, radius=0.5, center=(0.3, -0.2, 0.1))
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        grid.features[..., 1:] = torch.randn(*grid.resolution, 3, generator=gen)
        empty = grid.features[..., 0] <= 0
        grid.features[..., 0][empty] = -torch.rand(int(empty.sum()), generator=gen) * 3
    return grid


def renders(grid: VoxelGrid, skip_empty: bool) -> torch.Tensor:
    cameras = turntable_cameras(3, size=24)
    config = RenderConfig(skip_empty=skip_empty)
    return torch.stack([render_image(grid, cameras, i, config).rgb for i in range(len(cameras))])


def user_reader(path) -> np.ndarray:
    """The README's reader of downloaded grids: safetensors + numpy, no voxe_core."""
    tensors = load_file(str(path))
    with safe_open(str(path), framework="np") as handle:
        meta = json.loads(handle.metadata()["voxe"])["meta"]
    if meta.get("layout", "dense") == "dense":
        return tensors["features"]
    x, y, z = meta["resolution"]
    mask = np.unpackbits(tensors["stored_bits"], count=x * y * z).astype(bool).reshape(x, y, z)
    features = np.broadcast_to(tensors["fill"], (x, y, z, 4)).copy()
    features[mask] = tensors["values"]
    return features


def test_dilation_is_a_cube_of_the_margin_clipped_at_the_edges():
    cells = torch.zeros(11, 11, 11, dtype=torch.bool)
    cells[5, 5, 5] = cells[0, 10, 0] = True
    grown = dilate(cells, 2)
    assert grown[3:8, 3:8, 3:8].all() and grown[:3, 8:, :3].all() and int(grown.sum()) == 5**3 + 3**3
    assert not grown[2, 5, 5] and not grown[5, 5, 8]
    assert torch.equal(dilate(cells, 0), cells)
    # Vertices: the corners of the kept cells, one more per axis.
    assert int(stored_vertices(cells, 0).sum()) == 2 * 8
    assert stored_vertices(cells, 0).shape == (12, 12, 12)


def test_relu_grid_round_trips_exactly_and_renders_identically(tmp_path, make_sphere_grid):
    grid = noisy_sphere(make_sphere_grid)
    sparse, dense = tmp_path / "sparse.safetensors", tmp_path / "dense.safetensors"
    grid.save(sparse)
    grid.save(dense, dense=True)
    assert sparse.stat().st_size < dense.stat().st_size / 3
    loaded = load_grid(sparse)
    kept = stored_vertices(grid.occupancy_above(0.0).cells, 2)
    assert 0 < kept.float().mean() < 0.5
    assert torch.equal(loaded.features[kept], grid.features[kept])  # bit for bit on occupied cells + margin
    assert not torch.equal(loaded.features, grid.features)  # empty space holds one fill value
    assert float(loaded.features.detach()[~kept][:, 0].max()) <= 0  # ... that keeps it empty
    assert torch.equal(loaded.occupancy().cells, grid.occupancy().cells)
    for skip_empty in (True, False):
        assert torch.equal(renders(loaded, skip_empty), renders(grid, skip_empty))
    assert torch.equal(load_grid(dense).features, grid.features)
    assert (loaded.activation, loaded.density_scale) == (grid.activation, grid.density_scale)
    _, meta = load_tensors(sparse, kind="voxel_grid", max_version=2)
    assert (meta["layout"], meta["margin"]) == ("sparse", 2)


@pytest.mark.parametrize("activation", ["relu", "softplus"])
def test_converting_between_layouts_changes_no_value_after_the_first_save(tmp_path, make_sphere_grid, activation):
    """Regression: the fill was float32's mean, which over N copies of a loaded file's fill is not that fill: each
    sparse -> dense -> sparse conversion (``voxe convert-grid``) moved the fill, so every vertex left out, a few ulps
    (a fill of -0.18507251 became -0.18507259)."""
    grid = noisy_sphere(make_sphere_grid, resolution=48)
    grid.activation = activation
    with torch.no_grad():  # empty space below softplus's occupancy threshold too (raw -1 - U(0, 3))
        grid.features[..., 0][grid.features[..., 0] <= 0] -= 1.0
    first, dense, again = (tmp_path / f"{name}.safetensors" for name in ("first", "dense", "again"))
    grid.save(first)
    load_grid(first).save(dense, dense=True)
    load_grid(dense).save(again)
    written, rewritten = (load_tensors(path, kind="voxel_grid", max_version=2)[0] for path in (first, again))
    assert written.keys() == rewritten.keys() and "fill" in written
    for name in written:
        assert torch.equal(written[name], rewritten[name]), name
    assert torch.equal(load_grid(again).features, load_grid(dense).features)


def test_extreme_and_nan_values_in_empty_space_leave_the_fill_finite(tmp_path):
    # regression: the fill was a float32 mean: two colours of 3e38 overflowed it to inf (and a dense render of the
    # loaded grid to NaN), one NaN spread to all 12,824 vertices left out, densities of -1e38 summed to -inf
    grid = VoxelGrid(24, init_density=-1e38)
    with torch.no_grad():
        grid.features[10:14, 10:14, 10:14, 0] = 1.0
        grid.features[0, 0, 0:2, 1] = 3e38
        grid.features[0, 5, 0, 2] = float("nan")
    grid.save(tmp_path / "grid.safetensors")
    tensors, meta = load_tensors(tmp_path / "grid.safetensors", kind="voxel_grid", max_version=2)
    assert meta["layout"] == "sparse"
    dropped = ~stored_vertices(grid.occupancy_above(0.0).cells, 2)
    expected = grid.features.detach()[dropped].double()
    assert torch.isfinite(tensors["fill"]).all()
    assert float(tensors["fill"][0]) == pytest.approx(-1e38, rel=1e-6)  # the empty density stays as empty
    assert float(tensors["fill"][1]) == pytest.approx(float(expected[:, 1].sum()) / dropped.sum().item(), rel=1e-6)
    loaded = load_grid(tmp_path / "grid.safetensors")
    assert torch.isfinite(loaded.features[dropped]).all()
    clean = VoxelGrid(24, features=grid.features.detach().nan_to_num(0.0))  # the NaN lies in empty space
    assert torch.equal(renders(loaded, skip_empty=False), renders(clean, skip_empty=False))


def test_the_fill_stays_within_the_values_it_stands_for():
    """float32's mean of values that are not all one can round past them all (0.3 an ulp lower at one of 48³'s
    left-out vertices: a fill above every left-out density, which could make empty cells occupied at a threshold
    between them)."""
    cells = torch.zeros(47, 47, 47, dtype=torch.bool)
    cells[24, 24, 24] = True
    features = torch.full((48, 48, 48, 4), 0.3)
    lower = torch.nextafter(torch.tensor(0.3), torch.tensor(0.0))
    features[0, 0, 0] = lower
    fill = sparse_tensors(features, cells)[0]["fill"]
    assert bool(((fill >= lower) & (fill <= torch.tensor(0.3))).all()), fill.tolist()


@pytest.mark.parametrize("features, cells, message", [
    ((8, 8, 8, 4), ((8, 8, 8), torch.bool), r"cells must be a bool tensor of shape \(7, 7, 7\) \(one per cell of "
                                             r"features \(8, 8, 8, 4\)\), got torch.bool of shape \(8, 8, 8\)$"),
    ((8, 8, 8, 4), ((7, 7), torch.bool), r"shape \(7, 7, 7\) .* got torch.bool of shape \(7, 7\)$"),
    ((8, 8, 8, 4), ((7, 7, 7), torch.float32), r"shape \(7, 7, 7\) .* got torch.float32 of shape \(7, 7, 7\)$"),
    ((8, 8, 8), ((7, 7, 7), torch.bool), r"^features must be shaped \(X, Y, Z, C\), got \(8, 8, 8\)$"),
])
def test_cells_or_features_of_the_wrong_shape_are_a_value_error_naming_it(features, cells, message):
    """They had failed in the mask's indexing: "IndexError: The shape of the mask [9, 9, 9] at index 0 does not
    match the shape of the indexed tensor [8, 8, 8, 4]", naming neither argument (float cells: NotImplementedError)."""
    with pytest.raises(ValueError, match=message):
        sparse_tensors(torch.zeros(features), torch.zeros(cells[0], dtype=cells[1]), margin=1)


def test_softplus_and_scene_grids_keep_their_occupancy_and_renders(tmp_path, make_sphere_grid):
    sphere = noisy_sphere(make_sphere_grid, resolution=33)
    softplus = VoxelGrid(33, activation="softplus", features=sphere.features.detach() * 10)
    frame = torch.eye(4)
    frame[:3, 3] = torch.tensor([0.1, 0.2, 0.3])
    scene = SceneGrid(33, foreground_extent=1.2, features=sphere.features.detach(), far_ratio=50.0, frame=frame)
    for grid in (softplus, scene):
        path = tmp_path / f"{grid.kind}_{grid.activation}.safetensors"
        grid.save(path, margin=1)
        loaded = load_grid(path)
        assert type(loaded) is type(grid)
        assert torch.equal(loaded.occupancy().cells, grid.occupancy().cells)
        assert torch.equal(renders(loaded, skip_empty=True), renders(grid, skip_empty=True))
    assert torch.equal(loaded.frame, frame) and loaded.far_ratio == 50.0 and loaded.foreground_extent == 1.2


def test_a_softplus_file_renders_identically_where_empty_space_is_skipped_at_the_default_threshold(tmp_path):
    """What the README says of softplus files: a cell left out holds density below the default sigma_threshold
    (positive: softplus), replaced by ``fill``'s. Here it lies just below: renders skipping at that threshold or
    above are identical, a render without skipping differs faintly."""
    gen = torch.Generator().manual_seed(0)
    features = torch.randn(17, 17, 17, 4, generator=gen)
    positions = VoxelGrid(17).vertex_positions().reshape(17, 17, 17, 3)
    empty = -0.21 - 0.05 * torch.rand(17, 17, 17, generator=gen)  # softplus(33.3 * -0.21) = 9.1e-4
    features[..., 0] = torch.where((positions - torch.tensor([0.3, -0.2, 0.1])).norm(dim=-1) < 0.6, 0.5, empty)
    grid = VoxelGrid(17, activation="softplus", features=features)
    grid.save(tmp_path / "softplus.safetensors")
    loaded = load_grid(tmp_path / "softplus.safetensors")
    cameras = turntable_cameras(2, size=16)

    def difference(config: RenderConfig) -> float:
        return max(float((render_image(loaded, cameras, i, config).rgb - render_image(grid, cameras, i, config).rgb)
                         .abs().max()) for i in range(len(cameras)))

    assert difference(RenderConfig()) == 0.0 and difference(RenderConfig(sigma_threshold=1e-2)) == 0.0
    assert 0.0 < difference(RenderConfig(skip_empty=False)) < 1e-3


def test_a_grid_occupied_everywhere_is_written_dense_and_an_empty_one_as_a_mask(tmp_path):
    full, empty = tmp_path / "full.safetensors", tmp_path / "empty.safetensors"
    VoxelGrid(10).save(full)  # init density 0.01 > 0 everywhere: sparse would be larger
    _, meta = load_tensors(full, kind="voxel_grid", max_version=2)
    assert meta["layout"] == "dense"
    assert torch.equal(load_grid(full).features, VoxelGrid(10).features)
    VoxelGrid(10, init_density=-1.0).save(empty)
    tensors, meta = load_tensors(empty, kind="voxel_grid", max_version=2)
    assert meta["layout"] == "sparse" and tensors["values"].shape == (0, 4)
    assert torch.equal(load_grid(empty).features, VoxelGrid(10, init_density=-1.0).features)
    assert load_grid(empty).occupancy().empty


def test_version_1_dense_files_still_load(tmp_path, make_sphere_grid):
    grid = make_sphere_grid(resolution=12)
    old = tmp_path / "v1.safetensors"
    header = {k: v for k, v in grid.header().items()}
    save_tensors(old, grid.state_tensors(), kind="voxel_grid", version=1, meta=header)
    assert torch.equal(load_grid(old).features, grid.features)


def test_damaged_or_unknown_sparse_files_are_named(tmp_path, make_sphere_grid):
    grid = noisy_sphere(make_sphere_grid, resolution=16)
    tensors, layout = sparse_tensors(grid.features, grid.occupancy_above(0.0).cells, 1)
    meta = {**grid.header(), **layout}
    short = tmp_path / "short.safetensors"
    save_tensors(short, {**grid.state_tensors(), **tensors, "values": tensors["values"][:-1]},
                 kind="voxel_grid", version=2, meta=meta)
    with pytest.raises(FormatError, match="damaged sparse grid: the mask marks"):
        load_grid(short)
    odd = tmp_path / "odd.safetensors"
    save_tensors(odd, grid.state_tensors(), kind="voxel_grid", version=2, meta={**meta, "layout": "octree"})
    with pytest.raises(FormatError, match="unknown grid layout 'octree'"):
        load_grid(odd)
    with pytest.raises(ValueError, match="margin must be >= 0"):
        sparse_tensors(grid.features, grid.occupancy().cells, -1)



@pytest.mark.parametrize("damage, message", [
    (lambda t, m: ({**t, "values": t["values"][:, :3].contiguous()}, m), r"values \(\d+, 3\) and fill \(4,\)"),
    (lambda t, m: ({**t, "fill": t["fill"][:3].contiguous()}, m), r"values \(\d+, 4\) and fill \(3,\)"),
    # Values and fill agreeing on another channel count: had been expanded to every vertex (a fill of a million
    # channels, gigabytes) before the dense features' shape was refused.
    (lambda t, m: ({**t, "values": t["values"][:, :3].contiguous(), "fill": t["fill"][:3].contiguous()}, m),
     r"damaged sparse grid: values \(\d+, 3\) and fill \(3,\) are not \(N, 4\) and \(4,\)"),
    (lambda t, m: ({**t, "values": torch.cat([t["values"], t["values"][:, :1]], 1),
                    "fill": torch.cat([t["fill"], t["fill"][:1]])}, m),
     r"damaged sparse grid: values \(\d+, 5\) and fill \(5,\) are not \(N, 4\) and \(4,\)"),
    (lambda t, m: (t, {**m, "resolution": [-16, -16, 16]}), "is not 3 positive vertex counts"),
    (lambda t, m: (t, {**m, "resolution": None}), "resolution None is not 3 positive vertex counts"),  # TypeError
    (lambda t, m: (t, {**m, "resolution": [16, 16, 15.9]}), r"resolution \[16, 16, 15.9\] is not 3"),  # cut to 15
    # Fewer vertices than the mask holds bits for: had loaded, the mask's first 3,840 bits read as a 16x16x15 grid.
    (lambda t, m: (t, {**m, "resolution": [16, 16, 15]}), "stored_bits holds 512 bytes, not the 480 of a 16x16x15"),
    (lambda t, m: ({**t, "bbox_min": t["bbox_min"][:2].contiguous()}, m), r"bbox_min of shape \(2,\), not \(3,\)"),
    (lambda t, m: ({**t, "stored_bits": t["stored_bits"].int()}, m), "stored_bits is torch.int32"),
    (lambda t, m: (t, {**m, "density_scale": float("nan")}), "density_scale nan is not a positive number"),
    (lambda t, m: (t, {**m, "density_scale": "33"}), "density_scale '33' is not a positive number"),
    (lambda t, m: (t, {**m, "density_scale": True}), "density_scale True is not a positive number"),  # had been 1
    # (null had loaded with the default scale: every density other than the grid's)
    (lambda t, m: (t, {**m, "density_scale": None}), "density_scale None is not a positive number"),
    # Past float32 every density is infinite; past float64 (a whole number) Python's "int too large to convert to
    # float" had escaped, naming neither the file nor the field.
    (lambda t, m: (t, {**m, "density_scale": 1e300}), r"density_scale 1e\+300 is not a positive number finite in "),
    (lambda t, m: (t, {**m, "density_scale": 10**400}), "density_scale 10{400} is not a positive number finite in "),
    (lambda t, m: (t, {**m, "activation": "tanh"}), "damaged grid: unknown density activation 'tanh'"),
    (lambda t, m: (t, {**m, "backbone": ["scene"]}), r"header names unknown backbone \['scene'\]"),  # TypeError
    # A tensor or field of the layout missing: the message had been the bare key ("damaged sparse grid: 'fill'").
    (lambda t, m: ({k: v for k, v in t.items() if k != "fill"}, m), "damaged sparse grid: no 'fill' in the file"),
    (lambda t, m: (t, {k: v for k, v in m.items() if k != "resolution"}),
     "damaged sparse grid: no 'resolution' in the file"),
    (lambda t, m: ({**t, "features": t["features"][..., :3].contiguous()}, {**m, "layout": "dense"}),
     r"features of shape \(16, 16, 16, 3\)"),
    # Tensors of no floating-point dtype had been read as features (true as 1.0, a byte's 255 as 255.0).
    (lambda t, m: ({**t, "features": (t["features"] > 0).to(torch.uint8)}, {**m, "layout": "dense"}),
     "damaged grid: features is torch.uint8, not floating point"),
    (lambda t, m: ({**t, "values": t["values"].long()}, m), "damaged sparse grid: values is torch.int64, not floating"),
    (lambda t, m: ({**t, "fill": t["fill"] > 0}, m), "damaged sparse grid: fill is torch.bool, not floating point"),
    (lambda t, m: ({**t, "bbox_max": t["bbox_max"].int()}, m), "damaged grid: bbox_max is torch.int32, not floating"),
    # float8 tensors: a dense file's had loaded (rounded to 3 mantissa bits, or e8m0's no zero), a sparse file's had
    # escaped as NotImplementedError '"index_copy_cpu" not implemented for 'Float8_e4m3fn''.
    (lambda t, m: ({**t, "features": t["features"].to(torch.float8_e4m3fn)}, {**m, "layout": "dense"}),
     "damaged grid: features is torch.float8_e4m3fn, a float of 8 bits"),
    (lambda t, m: ({**t, "values": t["values"].to(torch.float8_e5m2)}, m),
     "damaged sparse grid: values is torch.float8_e5m2, a float of 8 bits"),
    (lambda t, m: ({**t, "fill": t["fill"].to(torch.float8_e4m3fn)}, m),
     "damaged sparse grid: fill is torch.float8_e4m3fn, a float of 8 bits"),
    (lambda t, m: ({**t, "bbox_min": t["bbox_min"].to(torch.float8_e4m3fn)}, m),
     "damaged grid: bbox_min is torch.float8_e4m3fn, a float of 8 bits"),
])
def test_a_grid_file_with_tensors_or_fields_of_the_wrong_shape_or_value_is_a_format_error(
        tmp_path, make_sphere_grid, damage, message):
    """Each had been a RuntimeError or TypeError traceback (voxe convert-grid, a worker's load), or had loaded:
    a NaN density scale makes every density NaN."""
    grid = make_sphere_grid(16)
    sparse, layout = sparse_tensors(grid.features, grid.occupancy().cells, 1)
    tensors = {**grid.state_tensors(), **sparse}
    tensors["features"] = grid.features.detach().clone()
    tensors, meta = damage(tensors, {**grid.header(), **layout})
    if meta.get("layout") == "sparse":
        tensors.pop("features")
    path = tmp_path / "damaged.safetensors"
    save_tensors(path, tensors, kind="voxel_grid", version=2, meta=meta)
    with pytest.raises(FormatError, match=message) as error:
        load_grid(path)
    assert str(error.value).startswith(str(path))


@pytest.mark.parametrize("far_ratio", [1e7, float("inf")])
def test_a_scene_grid_beyond_the_far_ratio_bound_says_so_rather_than_damaged(tmp_path, far_ratio):
    """Older versions saved any far_ratio; such a file had been refused as a "damaged grid"."""
    grid = SceneGrid(9)
    grid.far_ratio = far_ratio  # as an older version built it: the constructor now refuses it
    path = tmp_path / "older.safetensors"
    grid.save(path)
    with pytest.raises(FormatError) as error:
        load_grid(path)
    assert str(error.value) == (f"{path}: far_ratio {far_ratio:g} is above the largest this version supports (1e+06), "
                                "as a scene grid an older version saved may be: refit the scene with this one")


@pytest.mark.parametrize("field, value, message", [
    ("near_samples", 2.9, "near_samples must be a whole number, got 2.9"),  # had been cut to 2
    ("far_samples", 1e300, "far_samples must be a whole number, got 1e+300"),  # the render had failed (an overflow)
    ("near_samples", 10**12, "near_samples must be at most 4194304 (MAX_NEAR_FAR_SAMPLES), got 1000000000000"),  # 4 TB
    ("foreground_extent", 1e300, "foreground_extent must be a positive length, finite in float32, got 1e+300"),
    ("foreground_extent", True, "foreground_extent must be a positive length, finite in float32, got True"),  # 1
    # A string or null had been "'<' not supported between instances of 'int' and 'str'", naming no field; a whole
    # number past float64's range had escaped load_grid as OverflowError "int too large to convert to float".
    ("foreground_extent", "1.5", "foreground_extent must be a positive length, finite in float32, got '1.5'"),
    ("foreground_extent", None, "foreground_extent must be a positive length, finite in float32, got None"),
    ("far_ratio", "1000", "near_samples and far_samples must be >= 1 and far_ratio in (1, 1e+06], got 32, 64, '1000'"),
    ("far_ratio", None, "near_samples and far_samples must be >= 1 and far_ratio in (1, 1e+06], got 32, 64, None"),
    ("far_ratio", 10**400, f"near_samples and far_samples must be >= 1 and far_ratio in (1, 1e+06], got 32, 64, "
                           f"{10**400}"),
])
def test_a_scene_grid_header_it_cannot_render_is_a_format_error(tmp_path, field, value, message):
    """Each had loaded: a sample count of 2.9 cut to 2, JSON's true an extent of 1, and an extent or sample count of
    1e300 failing only as the grid rendered (float32's "cannot be converted without overflow", "Overflow when
    unpacking long long"), a sample count of 1e12 as it allocated 4 TB."""
    grid = SceneGrid(9)
    path = tmp_path / "scene.safetensors"
    save_tensors(path, grid.state_tensors(), kind="voxel_grid", version=2,
                 meta={**grid.header(), "layout": "dense", field: value})
    with pytest.raises(FormatError) as error:
        load_grid(path)
    assert str(error.value) == f"{path}: damaged grid: {message}"


@pytest.mark.parametrize("frame, message", [
    ([float("nan")] * 16, "frame must be finite in float32"),
    ([1e300] + [0.0] * 4 + [1e300] + [0.0] * 4 + [1e300] + [0.0] * 4 + [1.0], "frame must be finite in float32"),
    ([10**400] + [0] * 15, r"frame must be finite in float32, got \[10000"),  # had escaped: "int too large to convert"
    ([0.0] * 15 + [1.0], r"frame must be a similarity \(a positive scale times a rotation"),  # no scale
    ([2.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0], "frame must be a similarity"),  # stretched along x
    ([-1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0], "frame must be a similarity"),  # a mirror
    ([1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 0, 1.0, 0, 0, 0, 5.0, 1.0], "frame must be a similarity"),  # last row
    ([True, False, False, 0, False, True, False, 0, False, False, True, 0, 0, 0, 0, 1],  # read as the identity
     "frame must hold numbers, not booleans"),
    (None, r"frame must be 16 numbers \(a 4x4 matrix\), got None"),  # had loaded as the identity
])
def test_a_scene_grid_whose_frame_is_no_similarity_is_a_format_error(tmp_path, frame, message):
    """Regression: a NaN, infinite or singular frame had loaded, and every camera it moved into the grid's frame
    (``dataset_cameras``) was NaN."""
    grid = SceneGrid(9)
    path = tmp_path / "scene.safetensors"
    save_tensors(path, grid.state_tensors(), kind="voxel_grid", version=2,
                 meta={**grid.header(), "layout": "dense", "frame": frame})
    with pytest.raises(FormatError, match=f"damaged grid: {message}"):
        load_grid(path)
    scaled = [0.5, 0, 0, 0.1, 0, 0, -0.5, 0.2, 0, 0.5, 0, 0.3, 0, 0, 0, 1.0]  # half scale, a quarter turn, a shift
    save_tensors(path, grid.state_tensors(), kind="voxel_grid", version=2,
                 meta={**grid.header(), "layout": "dense", "frame": scaled})
    assert torch.equal(load_grid(path).frame, torch.tensor(scaled).reshape(4, 4))


@pytest.mark.parametrize("backbone", [VoxelGrid, SceneGrid])
@pytest.mark.parametrize("scale", [0.0, -2.0, float("nan"), float("inf")])
def test_a_grid_whose_file_could_not_be_read_back_is_refused_when_built(tmp_path, backbone, scale):
    """Regression: a density scale of -2, NaN or inf was taken (0 became the default), and its grid saved a file that
    ``load_grid`` then refused as damaged."""
    with pytest.raises(ValueError, match=f"density_scale must be a positive number, got {scale}"):
        backbone(8, density_scale=scale)
    assert backbone(8, density_scale=2.5).density_scale == 2.5


@pytest.mark.parametrize("header, message", [
    # a list: had been an AttributeError, then "'list' object has no attribute 'get'"
    ("[1, 2]", r"damaged 'voxe' header \(it is a list, not an object\)$"),
    ("null", r"damaged 'voxe' header \(it is a NoneType, not an object\)$"),
    ('{"kind": "voxel_grid", "format_version": 2, "meta": null}', r"damaged 'voxe' header \(its meta is a NoneType\)"),
    ('{"kind": "voxel_grid", "format_version": "two"}', "damaged 'voxe' header"),
    ("{not json", "damaged 'voxe' header"),  # json's message alone had not named the file
    ("[" * 100_000 + "]" * 100_000, r"damaged 'voxe' header \(its JSON nests too deeply\)$"),  # a RecursionError
    ('{"kind": "voxel_grid", "format_version": 2, "meta": {}}', "damaged grid: no 'features' in the file"),
    ('{"kind": "voxel_grid", "format_version": 0, "meta": {}}', "format version 0 is none a voxe_core wrote"),
    # JSON's true, a string and a fraction had been read as versions 1, 2 and 1 (int() of each)
    ('{"kind": "voxel_grid", "format_version": true, "meta": {}}',
     r"damaged 'voxe' header \(its format_version True is not a whole number\)"),
    ('{"kind": "voxel_grid", "format_version": "2", "meta": {}}', "its format_version '2' is not a whole number"),
    ('{"kind": "voxel_grid", "format_version": 1.5, "meta": {}}', "its format_version 1.5 is not a whole number"),
])
def test_a_damaged_header_is_a_format_error_naming_the_file(tmp_path, header, message):
    from safetensors.torch import save_file

    path = tmp_path / "damaged.safetensors"
    save_file({"other": torch.zeros(1)}, str(path), metadata={"voxe": header})
    with pytest.raises(FormatError, match=message) as error:
        load_grid(path)
    assert str(error.value).startswith(str(path))


def test_a_folder_given_as_a_grid_file_is_named_a_folder(tmp_path):
    with pytest.raises(FormatError) as error:  # it had been "no such file", of a path that is there
        load_grid(tmp_path)
    assert str(error.value) == f"{tmp_path}: is a folder, not a file"


def test_a_fifo_or_device_given_as_a_grid_file_is_named_what_it_is(tmp_path):
    """They had been "no such file", of a path that is there: the refusal says what it is, before anything opens it
    (a reader that opened the FIFO would wait for a writer)."""
    fifo = tmp_path / "grid.safetensors"
    os.mkfifo(fifo)
    for path, what in ((fifo, "a FIFO (named pipe)"), (Path(os.devnull), "a character device")):
        with pytest.raises(FormatError) as error:
            load_grid(path)
        assert str(error.value) == f"{path}: is {what}, not a regular file"


def test_a_grid_file_name_holding_a_null_byte_is_a_format_error():
    """os.stat's ValueError ("embedded null byte") had escaped, no FormatError naming the file."""
    with pytest.raises(FormatError) as error:
        load_grid("grid\0.safetensors")
    assert str(error.value) == "grid\0.safetensors: cannot be read: its name holds a null byte, which no file's can"


@pytest.mark.parametrize("backbone, change, message", [
    # a dense file's header resolution had gone unread: a grid of another size loaded
    ("relu_field", {"resolution": [32, 32, 32]}, r"its header's resolution \[32, 32, 32\] is not its features' "
                                                 r"\[8, 8, 8\]$"),
    # a null one had loaded without that check (as a null density_scale had loaded with a default)
    ("relu_field", {"resolution": None}, r"its header's resolution None is not its features' \[8, 8, 8\]$"),
    # torch's words had been the message: "shape '[4, 4]' is invalid for input of size 3", "too many dimensions 'str'"
    ("scene", {"frame": [1, 0, 0]}, r"frame must be 16 numbers \(a 4x4 matrix\), got \[1, 0, 0\]$"),
    ("scene", {"frame": ["a"] * 16}, r"frame must be 16 numbers \(a 4x4 matrix\), got \['a', "),
])
def test_a_dense_header_that_contradicts_its_tensors_is_refused_naming_the_field(tmp_path, backbone, change, message):
    from voxe_core.backbones import BACKBONES

    path = tmp_path / "grid.safetensors"
    BACKBONES[backbone](8).save(path, dense=True)
    tensors, meta = load_tensors(path, kind="voxel_grid", max_version=2)
    save_tensors(path, tensors, kind="voxel_grid", version=2, meta={**meta, **change})
    with pytest.raises(FormatError, match=message) as error:
        load_grid(path)
    assert str(error.value).startswith(f"{path}: damaged grid: ")


def test_dense_tensors_keeps_the_stored_dtype_and_other_tensors():
    features = torch.randn(5, 5, 5, 4)
    cells = torch.zeros(4, 4, 4, dtype=torch.bool)
    cells[1, 2, 3] = True
    tensors, meta = sparse_tensors(features, cells, margin=0)
    half = {**tensors, "values": tensors["values"].half(), "fill": tensors["fill"].half(), "bbox_min": torch.zeros(3)}
    restored = dense_tensors(half, meta)
    assert restored["features"].dtype == torch.float16 and "bbox_min" in restored
    kept = stored_vertices(cells, 0)
    assert torch.equal(restored["features"][kept], features[kept].half())


def test_a_save_into_a_missing_folder_names_the_file_asked_for_and_leaves_nothing(tmp_path, make_sphere_grid):
    """Regression: the error named the hidden temporary file (``.grid.partial.safetensors``) instead."""
    target = tmp_path / "missing" / "grid.safetensors"
    with pytest.raises(FileNotFoundError) as error:
        make_sphere_grid(8).save(target)
    assert error.value.filename == str(target) and ".partial" not in str(error.value)
    assert list(tmp_path.iterdir()) == []


def test_a_full_disk_while_saving_keeps_its_errno_the_file_asked_for_and_the_earlier_file(tmp_path, monkeypatch):
    """Regression: safetensors' ENOSPC had become an OSError of words alone, no errno (the worker's disk-full
    check missed it) and no filename. The full disk is /dev/full (a real ENOSPC), written by a stand-in for
    safetensors' save_file after half the file is down, which says it in the library's words."""
    target = tmp_path / "grid.safetensors"
    save_tensors(target, {"a": torch.ones(4)}, kind="test", version=1, meta={})

    def write_onto_a_full_disk(tensors, filename, metadata=None):
        data = safetensors.torch.save(tensors, metadata)
        Path(filename).write_bytes(data[: len(data) // 2])
        try:
            with open("/dev/full", "wb", buffering=0) as full:
                full.write(data[len(data) // 2:])
        except OSError as exc:
            words = f"{exc.strerror} (os error {exc.errno})"  # (Rust's, for an io::Error from the system)
            raise SafetensorError(f"Error while serializing: I/O error: {words}") from None

    monkeypatch.setattr("voxe_core.tensorio.save_file", write_onto_a_full_disk)
    with pytest.raises(OSError) as error:
        save_tensors(target, {"a": torch.zeros(1000)}, kind="test", version=1, meta={})
    assert (error.value.errno, error.value.filename) == (errno.ENOSPC, str(target))
    assert "No space left on device" in str(error.value) and ".partial" not in str(error.value)
    assert [p.name for p in tmp_path.iterdir()] == [target.name]
    assert torch.equal(load_tensors(target, "test", 1)[0]["a"], torch.ones(4))


def test_a_write_the_system_refuses_keeps_the_errno_safetensors_reports(tmp_path):
    """safetensors' own words for a write the system refused (here past the process's file size limit, EFBIG) give
    the errno back: its text ends "(os error N)" (what the ENOSPC above is read from)."""
    resource = pytest.importorskip("resource")
    target = tmp_path / "grid.safetensors"
    limits, on_too_large = resource.getrlimit(resource.RLIMIT_FSIZE), signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (64 * 1024, limits[1]))
    try:
        with pytest.raises(OSError) as error:
            save_tensors(target, {"a": torch.zeros(100_000)}, kind="test", version=1, meta={})
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, limits)
        signal.signal(signal.SIGXFSZ, on_too_large)
    assert (error.value.errno, error.value.filename) == (errno.EFBIG, str(target))
    assert isinstance(error.value.__cause__, SafetensorError) and list(tmp_path.iterdir()) == []


def test_users_read_downloads_with_numpy_alone(tmp_path, make_sphere_grid):
    grid = noisy_sphere(make_sphere_grid, resolution=20)
    for dense in (False, True):
        path = tmp_path / f"g{dense}.safetensors"
        grid.save(path, dense=dense)
        assert np.array_equal(user_reader(path), load_grid(path).features.detach().numpy())


@pytest.mark.parametrize("dtype", [torch.float16, torch.bfloat16, torch.float64])
def test_a_grid_of_any_dtype_is_written_in_float32(tmp_path, make_sphere_grid, dtype):
    """Regression: files held the grid's own dtype, though the format says float32: a half grid's dense features
    (8 bytes a vertex) weighed less than float32 values for the 72 % of vertices kept here, so it was written dense;
    numpy cannot read bfloat16."""
    grid = make_sphere_grid(resolution=20, radius=1.1).to(dtype)
    sparse, dense = tmp_path / "sparse.safetensors", tmp_path / "dense.safetensors"
    grid.save(sparse)
    grid.save(dense, dense=True)
    tensors, meta = load_tensors(sparse, kind="voxel_grid", max_version=2)
    assert meta["layout"] == "sparse" and sparse.stat().st_size < dense.stat().st_size
    assert {t.dtype for name, t in tensors.items() if name != "stored_bits"} == {torch.float32}
    assert all(t.dtype == torch.float32 for t in load_tensors(dense, kind="voxel_grid", max_version=2)[0].values())
    for path in (sparse, dense):
        assert user_reader(path).dtype == np.float32
    kept = stored_vertices(grid.occupancy_above(0.0).cells, 2)
    assert torch.equal(load_grid(sparse).features[kept], grid.features.float()[kept])
    assert torch.equal(load_grid(dense).features, grid.features.float())


@pytest.mark.parametrize("dense", [False, True])
def test_a_float8_grid_is_refused_when_saved_and_nothing_is_written(tmp_path, make_sphere_grid, dense):
    """Its sparse save had failed on '"maximum_cpu" not implemented for 'Float8_e4m3fn'', and its dense one written
    the float8-rounded box (1.2 as 1.25)."""
    grid = make_sphere_grid(resolution=8).to(torch.float8_e4m3fn)
    path = tmp_path / "g.safetensors"
    with pytest.raises(ValueError, match=r"a torch.float8_e4m3fn grid cannot be saved: grid files hold floats of at "
                                         r"least 16 bits; convert it with .float\(\) first"):
        grid.save(path, dense=dense)
    assert list(tmp_path.iterdir()) == []


def test_cli_converts_between_layouts(tmp_path, make_sphere_grid, capsys):
    grid = noisy_sphere(make_sphere_grid, resolution=20)
    sparse, dense, back = (tmp_path / f"{n}.safetensors" for n in ("sparse", "dense", "back"))
    grid.save(sparse)
    assert main(["convert-grid", str(sparse), "--out", str(dense), "--dense"]) == 0
    assert "dense" in capsys.readouterr().out
    assert load_tensors(dense, kind="voxel_grid", max_version=2)[1]["layout"] == "dense"
    assert main(["convert-grid", str(dense), "--out", str(back), "--margin", "1"]) == 0
    _, meta = load_tensors(back, kind="voxel_grid", max_version=2)
    assert (meta["layout"], meta["margin"]) == ("sparse", 1)
    assert torch.equal(load_grid(dense).features, load_grid(sparse).features)
    assert main(["convert-grid", str(tmp_path / "missing.safetensors"), "--out", str(back)]) == 2
    assert "no such file" in capsys.readouterr().err


def test_cli_converting_a_grid_in_place_reports_the_size_it_had(tmp_path, make_sphere_grid, capsys):
    """Regression: the input's size was read after the output had replaced it, so an in-place conversion said 1.00x."""
    path = tmp_path / "grid.safetensors"
    noisy_sphere(make_sphere_grid, resolution=20).save(path, dense=True)
    before = path.stat().st_size
    assert main(["convert-grid", str(path), "--out", str(path)]) == 0
    after = path.stat().st_size
    assert after < before / 3 and f"({after / before:.2f}x of grid.safetensors)" in capsys.readouterr().out


def test_commands_write_sparse_grids_unless_asked_for_dense(tmp_path, data_root):
    spot = data_root / "meshes" / "spot"
    written = {}
    for flag in ([], ["--dense"]):
        out = tmp_path / f"spot{len(flag)}.safetensors"
        args = ["mesh-to-grid", str(spot / "spot_triangulated.obj"), "--texture", str(spot / "spot_texture.png"),
                "--resolution", "24", "--out", str(out), *flag]
        assert main(args) == 0
        written[load_tensors(out, kind="voxel_grid", max_version=2)[1]["layout"]] = out
    assert set(written) == {"sparse", "dense"}
    assert written["sparse"].stat().st_size < written["dense"].stat().st_size
    sparse, dense = load_grid(written["sparse"]), load_grid(written["dense"])
    assert torch.equal(renders(sparse, skip_empty=False), renders(dense, skip_empty=False))
