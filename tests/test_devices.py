"""Every stage runs on the device it is given (issue 17), shown without a GPU.

Three kinds of evidence: a device this machine lacks ("cuda" here) is refused
at once, before a stage does any work (no progress report, no data read); data
given to a stage lands on the device asked for ("meta", which every torch
build has, seen by recording the tensors the stage hands to its first step);
and the peak memory each stage reports is a real high-water mark.
"""

from __future__ import annotations

import pytest
import torch

import voxe_core.export
import voxe_core.reconstruct
from voxe_core.cameras import Cameras, spherical_poses
from voxe_core.devices import DeviceUnavailableError, PeakMemory, resolve_device, same_device
from voxe_core.edit import EditConfig, edit
from voxe_core.evaluate import EditSample, evaluate
from voxe_core.export import render_views, turntable_cameras
from voxe_core.grid import VoxelGrid
from voxe_core.progress import Callbacks
from voxe_core.reconstruct import ReconstructConfig, reconstruct
from voxe_core.refine.pipeline import refine
from voxe_core.scene_grid import SceneGrid

NO_CUDA = not torch.cuda.is_available()
needs_no_cuda = pytest.mark.skipif(not NO_CUDA, reason="shows the refusal of a device this machine lacks")


class Reached(Exception):
    """Raised by a recorder once it has seen what a stage hands to its first step."""


def _views(n: int = 2, size: int = 8):
    cameras = Cameras.from_fov(spherical_poses(torch.full((n,), 30.0), torch.linspace(0, 180, n), 4.0), 0.7, size, size)
    return torch.ones(n, size, size, 3), cameras


def test_resolve_device():
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device(None) == torch.device("cuda" if torch.cuda.is_available() else "cpu")
    assert resolve_device("auto") == resolve_device(None)
    with pytest.raises(DeviceUnavailableError, match="unknown device 'gpu0'"):
        resolve_device("gpu0")
    with pytest.raises(DeviceUnavailableError, match="'mps' is not supported: .* float64"):
        resolve_device("mps")  # refused with its reason whether or not this machine has MPS


def test_devices_are_the_same_only_with_the_same_index():
    assert same_device("cpu", torch.device("cpu")) and same_device("cuda:1", "cuda:1")
    assert not same_device("cuda:0", "cuda:1") and not same_device("cuda:0", "cpu")  # edit refuses these pairs


@needs_no_cuda
def test_missing_cuda_is_named_with_the_fix():
    with pytest.raises(DeviceUnavailableError, match=r"'cuda:1' asked for.*no usable CUDA device.*use device 'cpu'"):
        resolve_device("cuda:1")


@needs_no_cuda
@pytest.mark.parametrize("stage", ["reconstruct", "edit", "refine", "render", "evaluate"])
def test_every_stage_refuses_a_missing_device_before_any_work(stage, make_sphere_grid):
    reports = []
    callbacks = Callbacks(on_progress=reports.append)
    grid = make_sphere_grid(8)
    images, cameras = _views()
    calls = {
        "reconstruct": lambda: reconstruct(images, cameras, ReconstructConfig(resolutions=(8,), iterations=(2,),
                                           image_downsample=(1,), rays_per_step=4), callbacks, device="cuda"),
        "edit": lambda: edit(grid, "a dog", None, EditConfig(iterations=2), callbacks, device="cuda"),
        "refine": lambda: refine(grid, grid.clone_grid(), "a dog", ["dog"], None, callbacks=callbacks, device="cuda"),
        "render": lambda: render_views(grid, cameras, callbacks=callbacks, device="cuda"),
        "evaluate": lambda: evaluate(grid, [EditSample("e", "a dog", grid)], "dog", None, callbacks=callbacks,
                                     device="cuda"),
    }
    with pytest.raises(DeviceUnavailableError, match="'cuda' asked for"):
        calls[stage]()
    assert reports == []
    assert grid.flat_features.device.type == "cpu"


def test_edit_refuses_a_device_other_than_its_guidance(make_sphere_grid):
    class OnCpu:
        device = torch.device("cpu")

    with pytest.raises(ValueError, match="runs on meta but its guidance model is on cpu"):
        edit(make_sphere_grid(8), "a dog", OnCpu(), EditConfig(iterations=1), device="meta")


def test_reconstruct_moves_images_cameras_and_grid_to_its_device(monkeypatch):
    seen = {}

    def occupancy(grid, *args):
        seen["grid"] = grid.flat_features.device
        return None

    def stage_data(images, cameras, downsample):
        seen["images"], seen["cameras"] = images.device, cameras.c2w.device
        raise Reached

    def generator(device, seed):  # meta has no generator: record where it was asked for
        seen["generator"] = device
        return torch.Generator().manual_seed(seed)

    monkeypatch.setattr(VoxelGrid, "occupancy", occupancy)
    monkeypatch.setattr(voxe_core.reconstruct, "_stage_data", stage_data)
    monkeypatch.setattr(voxe_core.reconstruct, "_sampling_generator", generator)
    images, cameras = _views()
    config = ReconstructConfig(resolutions=(8,), iterations=(2,), image_downsample=(1,), rays_per_step=4)
    with pytest.raises(Reached):
        reconstruct(images, cameras, config, device="meta")
    meta = torch.device("meta")
    assert seen == {"generator": meta, "grid": meta, "images": meta, "cameras": meta}
    assert images.device.type == "cpu"  # the caller's tensors stay where they were


def test_render_views_renders_on_its_device(monkeypatch, make_sphere_grid):
    seen = {}

    def render_image(grid, cameras, index, config, occupancy):
        seen["grid"], seen["cameras"] = grid.flat_features.device, cameras.c2w.device
        raise Reached

    monkeypatch.setattr(VoxelGrid, "occupancy", lambda grid, *args: None)
    monkeypatch.setattr(voxe_core.export, "render_image", render_image)
    with pytest.raises(Reached):
        render_views(make_sphere_grid(8), turntable_cameras(2, 20.0, 8), device="meta")
    assert seen == {"grid": torch.device("meta"), "cameras": torch.device("meta")}


def test_peak_memory_sees_an_allocation_made_after_start():
    memory = PeakMemory("cpu").start()
    before = memory.peak_bytes()
    block = torch.ones(64 << 20)  # 256 MiB, written so it is resident
    after = memory.info()
    del block
    assert after["peak_memory_kind"] == "process_rss"
    assert after["peak_memory_gb"] * (1 << 30) >= before + 0.9 * (256 << 20)
    assert PeakMemory("meta").info() == {"peak_memory_gb": None, "peak_memory_kind": None}


def test_stages_report_peak_memory_in_progress(make_sphere_grid):
    reports = []
    render_views(make_sphere_grid(8), turntable_cameras(2, 20.0, 8), callbacks=Callbacks(on_progress=reports.append))
    images, cameras = _views()
    reconstruct(images, cameras, ReconstructConfig(resolutions=(8,), iterations=(2,), image_downsample=(1,),
                                                   rays_per_step=16), Callbacks(on_progress=reports.append))
    assert {r.stage for r in reports} == {"render", "reconstruct"}
    for report in reports:
        assert report.info["peak_memory_kind"] == "process_rss" and report.info["peak_memory_gb"] > 0.01


# ----------------------------------------------------------------- host round trips of the hot loop
HOST_READS = {"item", "tolist", "__bool__", "__int__", "__float__", "nonzero", "unique_consecutive", "cpu", "numpy",
              "mask index"}
ONE_BLOCK_SCANS = {"cummax", "cummin"}  # along a 1-D tensor CUDA runs them in one thread block (ScanUtils.cuh)


class HostReads(torch.overrides.TorchFunctionMode):
    """Counts the tensor operations that make a CUDA stream wait for the host, and the scans that CUDA runs serially
    over a packed sample list (by name)."""

    def __init__(self):
        super().__init__()
        self.calls: dict[str, int] = {}

    def __torch_function__(self, func, types, args=(), kwargs=None):
        name = getattr(func, "__name__", "")
        if name == "__getitem__" and any(isinstance(i, torch.Tensor) and i.dtype == torch.bool
                                         for i in (args[1] if isinstance(args[1], tuple) else (args[1],))):
            name = "mask index"  # its result's size is the mask's count
        if name in HOST_READS | ONE_BLOCK_SCANS:
            self.calls[name] = self.calls.get(name, 0) + 1
        return func(*args, **(kwargs or {}))


def test_the_renderers_hot_loop_reads_the_host_only_where_shapes_depend_on_data(make_sphere_grid):
    """One edit-loop render in one pass: occupancy with no read at all; the sampler's data-dependent sizes in 5
    reads (the segment layout's scalars, the pass layout's, two packings, early stop), not one per scalar; no mask
    indexing and no serial scan (the transmittance finds each ray's first sample by binary search)."""
    from voxe_core import volrend
    from voxe_core.cameras import camera_rays
    from voxe_core.render import RenderConfig, render_rays

    grid = make_sphere_grid(48)
    config = RenderConfig(step_ratio=0.6)
    origins, directions = camera_rays(_views(1, 32)[1], 0)
    with HostReads() as occupancy_reads:
        occupancy = grid.occupancy(config.sigma_threshold)
    with HostReads() as cpu_reads:
        out = render_rays(grid, origins, directions, config, occupancy, torch.Generator().manual_seed(0))
    with pytest.MonkeyPatch.context() as patch:  # as on CUDA, where a read is a sync
        patch.setattr(volrend, "host_reads_are_free", lambda device: False)
        with HostReads() as render_reads:
            cuda_like = render_rays(grid, origins, directions, config, occupancy, torch.Generator().manual_seed(0))
    assert occupancy_reads.calls == {}
    assert render_reads.calls == {"tolist": 2, "nonzero": 3}
    # on the CPU alone, one more per transmittance (early stop's and the compositor's): is any depth NaN?
    assert cpu_reads.calls == {"tolist": 2, "nonzero": 3, "__bool__": 2}
    assert torch.equal(cuda_like.rgb, out.rgb) and out.samples > 0 and out.opacity.max() > 0.5  # the sphere


def test_the_sds_step_leaves_its_diagnostics_on_the_device(tmp_path, monkeypatch):
    """No read inside the SDS step: one would hold the host until the UNet had run, with the backward not yet queued.
    Its device-side diagnostics come back as 0-dim tensors; the edit reads them with its losses, once a step."""
    from voxe_core.guidance.sds import StableDiffusionGuidance
    from voxe_core.tiny_sd import build_tiny_stable_diffusion

    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    guidance = StableDiffusionGuidance.from_pretrained(str(build_tiny_stable_diffusion(tmp_path / "tiny", seed=0)))
    image = torch.rand(1, 3, 32, 32, generator=torch.Generator().manual_seed(0)).requires_grad_(True)
    text = guidance.encode_prompts(["a render of a dog"])
    with HostReads() as reads:
        loss, diagnostics = guidance.sds_loss(image, text, torch.tensor([500]), generator=torch.Generator().manual_seed(1))
        loss.backward()
    assert reads.calls == {"__bool__": 1}  # the time steps' range check, on the tensor the edit drew on the host
    assert all(diagnostics[k].ndim == 0 for k in ("grad_norm", "t_mean", "w_mean"))


def test_sync_free_occupancy_box_matches_the_occupied_cells(make_sphere_grid):
    grid = make_sphere_grid(20, radius=0.5, center=(0.3, -0.2, 0.1))
    occupancy = grid.occupancy()
    index = occupancy.cells.nonzero()
    vox = grid.voxel_size
    torch.testing.assert_close(occupancy.bbox_min, grid.bbox_min + index.min(0).values * vox)
    torch.testing.assert_close(occupancy.bbox_max, grid.bbox_min + (index.max(0).values + 1) * vox)
    empty = grid.occupancy_from_cells(torch.zeros_like(occupancy.cells))
    assert empty.empty and torch.equal(empty.bbox_min, grid.bbox_min) and torch.equal(empty.bbox_max, grid.bbox_min)


def test_peak_memory_survives_a_nested_reset():
    outer = PeakMemory("cpu").start()
    block = torch.ones(64 << 20)
    seen = outer.peak_bytes()
    del block
    PeakMemory("cpu").start()  # a nested stage resets the process counter
    assert outer.peak_bytes() >= seen


@pytest.mark.parametrize("make", [lambda: VoxelGrid(4, (-1, -2, -3), (1, 2, 3)), lambda: SceneGrid(5, 1.5)])
def test_grids_made_from_a_grid_on_a_device_stay_on_it(make):
    """A multi-stage fit upsamples, an edit clones and a cut builds ``like`` grids on the stage's device: their box
    buffers, features and host scalars come from the source grid without a tensor crossing devices."""
    grid = make()
    on_meta = grid.to("meta")
    for made, resolution in ((on_meta.clone_grid(), grid.resolution), (on_meta.upsampled(7), (7, 7, 7)),
                             (on_meta.like(torch.zeros(3, 3, 3, 4, device="meta")), (3, 3, 3))):
        assert type(made) is type(grid) and made.resolution == resolution
        assert {t.device.type for t in (made.bbox_min, made.bbox_max, made.features)} == {"meta"}
        assert made.min_voxel_edge == grid.like(torch.zeros(*resolution, 4)).min_voxel_edge


@pytest.mark.parametrize("renderer", ["render_image", "render_feature_views"])
def test_whole_image_renderers_make_their_rays_on_the_grids_device(renderer, monkeypatch, make_sphere_grid):
    """Stages build poses on the host (refine's attention views, turntables): the renderer takes them to the grid."""
    import voxe_core.refine.renders
    import voxe_core.render

    seen = {}

    def render_rays(grid, origins, directions, *args, **kwargs):
        seen["origins"], seen["directions"] = origins.device, directions.device
        raise Reached

    monkeypatch.setattr(VoxelGrid, "occupancy", lambda grid, *args: None)
    monkeypatch.setattr(voxe_core.render, "render_rays", render_rays)
    monkeypatch.setattr(voxe_core.refine.renders, "render_rays", render_rays)
    grid = make_sphere_grid(8).to("meta")
    cameras = _views()[1]
    calls = {"render_image": lambda: voxe_core.render.render_image(grid, cameras, 0),
             "render_feature_views": lambda: voxe_core.refine.renders.render_feature_views(
                 grid, cameras, torch.zeros(8, 8, 8, 1))}
    with pytest.raises(Reached):
        calls[renderer]()
    assert seen == {"origins": torch.device("meta"), "directions": torch.device("meta")}
    assert cameras.c2w.device.type == "cpu"  # the caller's cameras stay where they were


def test_the_renderers_pass_size_is_the_devices_unless_set(monkeypatch, make_sphere_grid):
    """Passes of 2^20 samples on the CPU (larger ran slower there), 2^22 elsewhere (a launch-bound GPU pays per
    pass); a size given in the config wins on any device."""
    from voxe_core.render import RenderConfig, render_rays

    seen = []

    def ray_samples(grid, origins, directions, offsets, step_ratio, occupancy, samples_per_pass, early_stop):
        seen.append((origins.device.type, samples_per_pass))
        raise Reached

    monkeypatch.setattr(VoxelGrid, "ray_samples", ray_samples)
    grid = make_sphere_grid(8)
    rays = (torch.zeros(4, 3), torch.tensor([[0.0, 0.0, 1.0]]).expand(4, 3))
    for device, config in (("cpu", RenderConfig()), ("meta", RenderConfig(skip_empty=False)),
                           ("meta", RenderConfig(skip_empty=False, samples_per_pass=1 << 16))):
        with pytest.raises(Reached):
            render_rays(grid.to(device), *(r.to(device) for r in rays), config)
    assert seen == [("cpu", 1 << 20), ("meta", 1 << 22), ("meta", 1 << 16)]
