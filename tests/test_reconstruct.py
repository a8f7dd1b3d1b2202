"""Reconstruction: a real fit on mic, determinism, checkpoint/resume and cancellation."""

from __future__ import annotations

import gc
import math
import re
from dataclasses import replace

import pytest
import torch

from voxe_core.cameras import Cameras, look_at
from voxe_core.constants import FLOAT32_MAX
from voxe_core.data import load_scene
from voxe_core.grid import VoxelGrid
from voxe_core.metrics import psnr
from voxe_core.progress import Callbacks, StageCancelled
from voxe_core.reconstruct import (
    CHECKPOINT_FORMAT_VERSION, CHECKPOINT_KIND, FitDiverged, ReconstructConfig, RowSparseAdam, load_checkpoint, ray_batch,
    reconstruct, renders_nothing,
)
from voxe_core.render import RenderConfig, render_image
from voxe_core.tensorio import FormatError, save_tensors

from needs import MIC, needs_data
from references import dense_total_variation

needs_mic = needs_data(MIC)


def tiny_config(**overrides) -> ReconstructConfig:
    base = dict(resolutions=(12, 24), iterations=(15, 15), image_downsample=(2, 1), rays_per_step=256, seed=3)
    base.update(overrides)
    return ReconstructConfig(**base)


def synthetic_views(n=6, size=16):
    """Views of a red sphere rendered from a known grid: a fit has an exact target."""
    truth = VoxelGrid(24)
    axis = torch.linspace(-1.5, 1.5, 24)
    x, y, z = torch.meshgrid(axis, axis, axis, indexing="ij")
    with torch.no_grad():
        truth.features[..., 0] = torch.where((x**2 + y**2 + z**2).sqrt() < 0.7, 2.0, -1.0)
        truth.features[..., 1] = 3.0
        truth.features[..., 2:] = -3.0
    azimuth = torch.arange(n) * (2 * torch.pi / n)
    eye = torch.stack([4 * azimuth.cos(), 4 * azimuth.sin(), torch.full((n,), 1.5)], -1)
    cams = Cameras.from_fov(look_at(eye), 0.8, size, size)
    images = torch.stack([render_image(truth, cams, i).rgb for i in range(n)])
    return images, cams


def test_fit_is_deterministic_under_a_seed_and_reduces_error():
    images, cams = synthetic_views()
    first = reconstruct(images, cams, tiny_config(iterations=(40, 40)))
    second = reconstruct(images, cams, tiny_config(iterations=(40, 40)))
    assert torch.equal(first.features, second.features)
    error_before = (images - 1.0).abs().mean()
    rendered = torch.stack([render_image(first, cams, i).rgb for i in range(len(cams))])
    assert (rendered - images).abs().mean() < 0.35 * error_before
    other = reconstruct(images, cams, tiny_config(iterations=(40, 40), seed=4))
    assert not torch.equal(first.features, other.features)


@pytest.mark.parametrize(
    "stop_after,average_from,occupancy_every,images_per_step",
    [(10, 1.0, 16, 0), (15, 1.0, 16, 0), (22, 1.0, 16, 0),  # mid-stage, stage boundary, second stage
     (22, 0.4, 16, 0), (27, 0.4, 16, 0),  # inside the averaged tail of the final stage
     (8, 1.0, 4, 0), (23, 1.0, 4, 0),  # on an occupancy refresh, in either stage
     (22, 1.0, 16, 2)],  # rays from two of the six images a step
)
def test_resume_from_checkpoint_is_bit_exact(tmp_path, stop_after, average_from, occupancy_every, images_per_step):
    images, cams = synthetic_views()
    config = tiny_config(checkpoint_every=1, average_from=average_from, average_every=2,
                         occupancy_every=occupancy_every, images_per_step=images_per_step)
    uninterrupted = reconstruct(images, cams, config)

    checkpoint = tmp_path / "ckpt.safetensors"
    saved = []

    def cancel_after() -> bool:
        return len(saved) >= stop_after

    with pytest.raises(StageCancelled):
        reconstruct(images, cams, config, Callbacks(should_cancel=cancel_after, on_checkpoint=saved.append),
                    checkpoint_path=checkpoint)
    resumed = reconstruct(images, cams, config, resume_from=checkpoint)
    assert torch.equal(resumed.features, uninterrupted.features)


@pytest.mark.parametrize("stop_after,stage,iteration", [(7, 0, 7), (8, 1, 0), (14, 1, 6)])
def test_a_cancelled_fit_checkpoints_where_it_stopped_and_resumes_from_there(tmp_path, stop_after, stage, iteration):
    """As edit's: the steps since the last periodic checkpoint (every 5 here) are not redone by a resume."""
    images, cams = synthetic_views()
    config = tiny_config(iterations=(8, 8), checkpoint_every=5, average_from=0.5, average_every=2)
    uninterrupted = reconstruct(images, cams, config)
    checkpoint, seen, saved = tmp_path / "ckpt.safetensors", [], []
    with pytest.raises(StageCancelled):
        reconstruct(images, cams, config, Callbacks(on_progress=seen.append, should_cancel=lambda: len(seen) >= stop_after,
                                                    on_checkpoint=saved.append), checkpoint_path=checkpoint)
    meta = load_checkpoint(checkpoint)[1]
    assert (meta["stage"], meta["iteration"]) == (stage, iteration) and len(saved) == stop_after // 5 + 1
    resumed_at = []
    resumed = reconstruct(images, cams, config, Callbacks(on_progress=resumed_at.append), resume_from=checkpoint)
    assert resumed_at[0].iteration == stop_after + 1 and torch.equal(resumed.features, uninterrupted.features)


def _grid_sized_storages(grid_bytes: int) -> dict[int, torch.Tensor]:
    """The live tensors with a storage of at least ``grid_bytes``, one per storage (by its address); tensors without
    real data (an earlier test's fake tensors) left out."""
    gc.collect()
    found = {}
    for t in gc.get_objects():
        if issubclass(type(t), torch.Tensor) and t.layout == torch.strided:
            try:
                storage = t.untyped_storage()
                if storage.nbytes() >= grid_bytes:
                    found.setdefault(storage.data_ptr(), t)
            except (RuntimeError, NotImplementedError):
                continue
    return found


def test_a_resumed_fit_holds_no_copy_of_its_checkpoints_tensors(tmp_path):
    """Features, Adam's two moments and the iterate average: four grid-sized tensors at the end of a fit, resumed or
    not (the checkpoint's own had stayed alive beside the copies made of them: seven). Counted beside what other
    tests keep alive (held here, so no new tensor can take their storage's address)."""
    images, cams = synthetic_views()
    config = tiny_config(resolutions=(16,), iterations=(8,), image_downsample=(1,), checkpoint_every=1,
                         average_from=0.5, average_every=1)
    grid_bytes, counts = 16**3 * 4 * 4, []

    def count_at_the_end(progress):
        if progress.iteration == progress.total:
            counts.append(len(_grid_sized_storages(grid_bytes).keys() - before.keys()))

    checkpoint, saved = tmp_path / "ckpt.safetensors", []
    with pytest.raises(StageCancelled):
        reconstruct(images, cams, config, Callbacks(should_cancel=lambda: len(saved) >= 6, on_checkpoint=saved.append),
                    checkpoint_path=checkpoint)
    before = _grid_sized_storages(grid_bytes)
    reconstruct(images, cams, config, Callbacks(on_progress=count_at_the_end))
    reconstruct(images, cams, config, Callbacks(on_progress=count_at_the_end), resume_from=checkpoint)
    assert counts == [4, 4]


@pytest.fixture(scope="module")
def stopped_fit(tmp_path_factory):
    """A checkpoint of a small fit cancelled in the averaged tail of its final stage: (config, its tensors and meta)."""
    images, cams = synthetic_views()
    config = tiny_config(iterations=(4, 6), checkpoint_every=1, average_from=0.5, average_every=1)
    checkpoint, saved = tmp_path_factory.mktemp("fit") / "ckpt.safetensors", []
    with pytest.raises(StageCancelled):
        reconstruct(images, cams, config, Callbacks(should_cancel=lambda: len(saved) >= 8, on_checkpoint=saved.append),
                    checkpoint_path=checkpoint)
    return config, *load_checkpoint(checkpoint)


def _with_nan(tensor: torch.Tensor) -> torch.Tensor:
    damaged = tensor.clone()
    damaged.view(-1)[100] = math.nan
    return damaged


def _rewritten(path, tensors, meta):
    save_tensors(path, tensors, kind=CHECKPOINT_KIND, version=CHECKPOINT_FORMAT_VERSION, meta=meta)
    return path


def test_a_checkpoint_written_on_another_device_type_resumes_from_a_reseeded_generator(tmp_path, stopped_fit):
    """A CUDA generator's state (16 bytes: seed and Philox offset) cannot set a CPU one's (5,056 bytes): the resume
    had raised a RuntimeError, which failed the worker's fit for good. It goes on, reproducibly."""
    config, tensors, meta = stopped_fit
    assert meta["device"] == "cpu" and tensors["rng_state"].numel() == 5056
    cuda_state = torch.tensor([3, 0, 0, 0, 0, 0, 0, 0, 64, 1, 0, 0, 0, 0, 0, 0], dtype=torch.uint8)
    written_on_cuda = _rewritten(tmp_path / "cuda.safetensors", {**tensors, "rng_state": cuda_state},
                                 {**meta, "device": "cuda"})
    images, cams = synthetic_views()
    first, second = (reconstruct(images, cams, config, resume_from=written_on_cuda) for _ in range(2))
    assert torch.equal(first.features, second.features) and torch.isfinite(first.features).all()


@pytest.mark.parametrize("damage,message", [
    (lambda t, m: ({**t, "rng_state": t["rng_state"][:16]}, m), "damaged checkpoint: RuntimeError: .*state"),
    (lambda t, m: ({k: v for k, v in t.items() if k != "rng_state"}, m), "damaged checkpoint: KeyError: 'rng_state'"),
    (lambda t, m: (t, {k: v for k, v in m.items() if k != "stage"}), "damaged checkpoint: KeyError: 'stage'"),
    (lambda t, m: ({k: v for k, v in t.items() if k != "adam_exp_avg"}, m),
     r"its adam_exp_avg holds nothing, not shape \(13824, 4\)"),
    (lambda t, m: ({**t, "adam_exp_avg_sq": t["adam_exp_avg_sq"][:-1]}, m),
     r"its adam_exp_avg_sq holds shape \(13823, 4\), not shape \(13824, 4\)"),
    (lambda t, m: ({**t, "occupancy": t["occupancy"][1:]}, m), r"its occupancy holds shape \(22, 23, 23\)"),
    (lambda t, m: ({k: v for k, v in t.items() if k != "average_count"}, m), "its average_count holds nothing"),
    # a NaN had been resumed from, and the fit returned a NaN grid as its result
    (lambda t, m: ({**t, "features": _with_nan(t["features"])}, m), "checkpoint holds features no fit leaves"),
    (lambda t, m: ({**t, "adam_exp_avg": _with_nan(t["adam_exp_avg"])}, m), "holds adam_exp_avg no fit leaves"),
    (lambda t, m: ({**t, "adam_exp_avg_sq": -t["adam_exp_avg_sq"] - 1}, m), "holds adam_exp_avg_sq no fit leaves"),
    (lambda t, m: ({**t, "average_total": _with_nan(t["average_total"])}, m), "holds average_total no fit leaves"),
    # a count of 0 had dropped the average, a negative one negated the grid, 2.5 been taken as 2, NaN a ValueError
    *[(lambda t, m, count=count: ({**t, "average_count": torch.tensor([count])}, m), "holds average_count no fit "
       r"leaves \(.* a count of iterates summed that is not a whole number from 1 to the stage's iteration\)")
      for count in (0, -3, 2.5, math.nan, 10_000)],
])
def test_a_checkpoint_that_cannot_be_applied_is_a_format_error(tmp_path, stopped_fit, damage, message):
    """FormatError, which the worker answers by starting the fit over (a KeyError, or a RuntimeError from a
    generator state or deep inside the first step, had failed it for good)."""
    config, tensors, meta = stopped_fit
    damaged = _rewritten(tmp_path / "damaged.safetensors", *damage(dict(tensors), dict(meta)))
    images, cams = synthetic_views()
    with pytest.raises(FormatError, match=message):
        reconstruct(images, cams, config, Callbacks(on_progress=pytest.fail), resume_from=damaged)


def test_resume_refuses_a_checkpoint_of_another_recipe_naming_each_change(tmp_path, stopped_fit):
    """A resume under another seed, lr, averaging... had gone on silently (averaging off, the checkpoint's running
    average was still returned). How often checkpoints are written is no part of it; a checkpoint older than recipes
    resumes, as an edit's."""
    config, tensors, meta = stopped_fit
    images, cams = synthetic_views()
    checkpoint = _rewritten(tmp_path / "ckpt.safetensors", tensors, meta)
    for changed, message in [(dict(seed=99, lr=0.3), r"lr 0.03 \(now 0.3\), seed 3 \(now 99\)"),
                             (dict(average_from=1.0), r"average_from 0.5 \(now 1.0\)"),
                             (dict(tv_density=0.1), r"tv_density 0.0 \(now 0.1\)")]:
        with pytest.raises(ValueError, match=f"checkpoint was made with another recipe: {message}; resume with its"):
            reconstruct(images, cams, replace(config, **changed), resume_from=checkpoint)
    resumed = reconstruct(images, cams, replace(config, checkpoint_every=5), resume_from=checkpoint)
    older = _rewritten(tmp_path / "older.safetensors", tensors, {k: v for k, v in meta.items() if k != "recipe"})
    assert torch.equal(reconstruct(images, cams, config, resume_from=older).features, resumed.features)
    # Averaging leaves the iterates alone: an older checkpoint resumed with it off ends as a fit without it, the
    # checkpoint's running average dropped (it had been returned).
    plain = replace(config, average_from=1.0)
    assert torch.equal(reconstruct(images, cams, plain, resume_from=older).features,
                       reconstruct(images, cams, plain).features)


def test_resume_refuses_a_checkpoint_of_a_fit_to_other_views(tmp_path, stopped_fit):
    """voxe reconstruct --resume with another dataset, split, --downsample or --max-images had gone on from the
    checkpoint's grid as if it were this fit's. FormatError: the worker starts over, the CLI exits 2 saying why. A
    checkpoint older than the views summary resumes, and one of the same views but for their last bits."""
    config, tensors, meta = stopped_fit
    checkpoint = _rewritten(tmp_path / "ckpt.safetensors", tensors, meta)
    images, cams = synthetic_views()
    for other_images, other_cams in [(images * 0.9, cams),  # other images seen from the same cameras
                                     (images, replace(cams, fx=cams.fx * 1.01)),  # the same images, other cameras
                                     (images, replace(cams, c2w=cams.c2w * torch.tensor([1.0, -1.0, -1.0, 1.0]))),
                                     synthetic_views(n=5)]:  # fewer views
        with pytest.raises(FormatError, match="checkpoint is of a fit to other images or cameras"):
            reconstruct(other_images, other_cams, config, Callbacks(on_progress=pytest.fail), resume_from=checkpoint)
    resumed = reconstruct(images, cams, config, resume_from=checkpoint)
    # the same views but for their last bits (another worker's resampling): resumed, as the views themselves are
    nudged = reconstruct(torch.nextafter(images, torch.full_like(images, 0.5)), cams, config, resume_from=checkpoint)
    assert torch.allclose(nudged.features, resumed.features, atol=1e-4)
    older = _rewritten(tmp_path / "older.safetensors", {k: v for k, v in tensors.items() if k != "views"}, meta)
    assert torch.equal(reconstruct(images, cams, config, resume_from=older).features, resumed.features)


def test_resume_refuses_a_recipe_the_checkpoint_is_not_part_of(tmp_path):
    """The checkpoint's grid went on under another recipe (voxe reconstruct --resume with another --resolution had
    written the checkpoint's 16³ grid, announcing 24³)."""
    images, cams = synthetic_views()
    config = tiny_config(checkpoint_every=1)
    checkpoint = tmp_path / "ckpt.safetensors"
    saved = []
    with pytest.raises(StageCancelled):
        reconstruct(images, cams, config, Callbacks(should_cancel=lambda: len(saved) >= 22, on_checkpoint=saved.append),
                    checkpoint_path=checkpoint)  # 22 of 15 + 15 steps: in the second stage
    final = config.resolutions[-1]
    for other in (tiny_config(resolutions=(config.resolutions[0], final + 4)),  # another final resolution
                  tiny_config(resolutions=(12,), iterations=(15,), image_downsample=(1,)),  # fewer stages
                  tiny_config(iterations=(15, 5))):  # a stage shorter than where the checkpoint stands
        with pytest.raises(ValueError, match="which this recipe .* does not reach: resume with the recipe that wrote it"):
            reconstruct(images, cams, other, resume_from=checkpoint)


def test_averaging_returns_the_mean_of_the_final_iterates():
    images, cams = synthetic_views()
    grid = VoxelGrid(24)
    snapshots = []

    def snapshot(progress):
        if progress.iteration > 5:  # iterations 5..9 of 10 (0-based) are averaged
            snapshots.append(grid.flat_features.detach().clone())

    config = tiny_config(resolutions=(24,), iterations=(10,), image_downsample=(1,), average_from=0.5, average_every=1)
    result = reconstruct(images, cams, config, Callbacks(on_progress=snapshot), initial_grid=grid)
    assert len(snapshots) == 5 and not torch.equal(snapshots[0], snapshots[-1])
    assert torch.allclose(result.flat_features, torch.stack(snapshots).mean(0), atol=1e-6)


@pytest.mark.parametrize("field,value,message", [
    ("image_downsample", (2, 0), r"image_downsample must be >= 1 per stage .*got \[2, 0\]"),  # had divided by 0
    ("image_downsample", (2, -1), r"image_downsample must be >= 1 per stage .*got \[2, -1\]"),  # had fitted 1x1
    ("occupancy_every", 0, "occupancy_every must be >= 1 and checkpoint_every >= 0 .*got 0 and 0"),
    ("checkpoint_every", -1, "occupancy_every must be >= 1 and checkpoint_every >= 0 .*got 16 and -1"),
    ("lr", math.nan, "lr must be positive and finite, got nan"),
    ("lr", 0.0, "lr must be positive and finite, got 0.0"),
    ("resolutions", (12, 1), r"grid resolutions must be at least 2, got \[12, 1\]"),
    # as EditConfig's and RefineConfig's: each had been accepted, and failed inside the fit or fitted NaN
    ("rays_per_step", 2.5, r"rays_per_step takes whole numbers, got 2\.5"),
    ("rays_per_step", True, "rays_per_step takes whole numbers, got True"),
    ("iterations", (3, 2.5), r"iterations takes whole numbers, got \(3, 2\.5\)"),
    ("checkpoint_every", 0.5, r"checkpoint_every takes whole numbers, got 0\.5"),
    ("seed", 2**64, r"seed must lie in \[0, 4294967295\]"),
    ("lr", 1e39, "lr must be positive and finite, got 1e\\+39"),
    ("lr_stage_decay", math.nan, r"lr_stage_decay must lie in \(0, 1\]"),
    ("lr_drop_factor", 0.0, r"lr_drop_factor must lie in \(0, 1\]"),
    ("color_lr_scale", math.nan, "color_lr_scale must be >= 0"),
    ("init_density", math.inf, "init_density a number"),
    ("tv_color", math.nan, "tv_density and tv_color must be >= 0 and finite"),
    ("iterations", 500, "iterations takes one whole number per stage, got 500"),  # had been len()'s TypeError
    ("resolutions", "12", "resolutions takes one whole number per stage, got '12'"),
    # each had named no value (nor, for the entries, which setting had how many)
    ("iterations", (15, -1), r"iterations must be >= 0 per stage, got \[15, -1\]"),
    # the untrained grid, a fog of init_density, had been returned (a job's stored and edited) as the fit
    ("iterations", (0, 0), r"^iterations are 0 in every stage \(\[0, 0\]\): the fit would take no step and return "
                           r"its initial grid untrained \(its init_density everywhere, a fog\); give a stage steps$"),
    ("rays_per_step", 0, "rays_per_step must be >= 1, got 0"),
    ("average_from", 1.5, r"average_from must lie in \[0, 1\] and average_every be >= 1, got 1\.5 and 8"),
    ("average_every", 0, r"average_from must lie in \[0, 1\] and average_every be >= 1, got 1\.0 and 0"),
    ("resolutions", (12, 16, 24), r"one entry per stage, got \[12, 16, 24\], \[15, 15\] and \[2, 1\]"),
])
def test_a_config_no_fit_can_run_is_refused_when_it_is_made(field, value, message):
    with pytest.raises(ValueError, match=message):
        tiny_config(**{field: value})


@pytest.mark.parametrize("field, value, message", [
    ("lr", "3e-2", "lr must be a number, got '3e-2'"),  # (YAML 1.1 reads 3e-2 as a string)
    ("lr", True, "lr must be a number, got True"),
    ("tv_density", None, "tv_density must be a number, got None"),
    ("camera_clearance", "0.4", "camera_clearance must be a number, got '0.4'"),
    ("average_from", True, "average_from must be a number, got True"),
    ("render", None, "render must be a RenderConfig, got None"),
])
def test_a_setting_of_another_type_is_refused_naming_it(field, value, message):
    """As RefineConfig's and EditConfig's: a string had failed a range test naming no setting ("'<' not supported
    between instances of 'int' and 'str'"), True had run as 1 (an lr of 1), render=None failed as the fit started."""
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        tiny_config(**{field: value})


def test_a_config_takes_its_stages_as_any_sequence_of_whole_numbers():
    """An array of a stage's entries (numpy's integers) had been refused as 'takes whole numbers'."""
    import numpy as np

    config = tiny_config(resolutions=np.array([12, 16]), iterations=[15, np.int64(15)])
    assert list(config.resolutions) == [12, 16] and list(config.iterations) == [15, 15]


def test_progress_reports_every_iteration_and_cancellation_stops_early():
    images, cams = synthetic_views()
    seen = []
    with pytest.raises(StageCancelled, match="reconstruct canceled"):
        reconstruct(images, cams, tiny_config(),
                    Callbacks(on_progress=seen.append, should_cancel=lambda: len(seen) >= 5))
    assert [p.iteration for p in seen] == [1, 2, 3, 4, 5]
    assert all(p.total == 30 and p.stage == "reconstruct" and p.losses["l1"] > 0 for p in seen)


def test_an_initial_grid_with_non_finite_features_is_refused_naming_them():
    """Its NaN had gone on through every step (a NaN cell is occupied, so rendered) and the fit returned a NaN grid,
    where a resume refuses a NaN checkpoint and an edit a NaN initial grid."""
    images, cams = synthetic_views()
    grid = VoxelGrid(12)
    with torch.no_grad():
        grid.features[3, 4, 5, 0], grid.features[0, 0, 0, 2] = math.nan, math.inf
    with pytest.raises(ValueError, match=r"^the initial grid has non-finite \(NaN or infinite\) features at 2 of its "
                                         "1728 vertices, which its renders would carry into every step"):
        reconstruct(images, cams, tiny_config(), Callbacks(on_progress=pytest.fail), initial_grid=grid)


@pytest.mark.parametrize("field", ["lr", "color_lr_scale"])
def test_a_fit_whose_steps_overflow_float32_is_refused_naming_its_step_not_returned_nan(field):
    """An lr (or colour scale) the config accepts, finite in float32, whose steps overflow it: the fit had returned a
    NaN grid (saved; its edit then refused it as a damaged file). Its first NaN loss stops it, reported by no
    progress."""
    images, cams = synthetic_views()
    seen = []
    config = tiny_config(resolutions=(12,), iterations=(30,), image_downsample=(1,), **{field: FLOAT32_MAX})
    with pytest.raises(FitDiverged, match=r"^the reconstruction diverged by iteration \d+ \(stage 1 of 1\): its "
                                          r"loss is \{'l1': nan\}; its steps overflowed float32: lower lr or "
                                          r"color_lr_scale \(now .*3\.40282e\+38.*\); not saved$") as caught:
        reconstruct(images, cams, config, Callbacks(on_progress=seen.append))
    assert str(caught.value).startswith(f"the reconstruction diverged by iteration {len(seen) + 1} ")


def test_a_fit_whose_last_update_overflows_is_refused_where_its_stage_ends_or_before_its_checkpoint(tmp_path):
    """A step whose loss was finite can overflow its update (its colour steps here): the grid is checked where the
    stage ends, and before a checkpoint, which is then not written."""
    images, cams = synthetic_views()
    last = tiny_config(resolutions=(12,), iterations=(1,), image_downsample=(1,), checkpoint_every=1,
                       color_lr_scale=FLOAT32_MAX)
    for path in (None, tmp_path / "fit.ckpt"):
        with pytest.raises(FitDiverged, match=r"^the reconstruction diverged by iteration 1 \(stage 1 of 1\): the grid "
                                              r"holds NaN or infinite features at \d+ of its 1728 vertices"):
            reconstruct(images, cams, last, checkpoint_path=path)
    assert not (tmp_path / "fit.ckpt").exists()
    asked, warned = [], []  # canceled after that step: its checkpoint is not written, which is said; still a cancel
    with pytest.raises(StageCancelled):
        reconstruct(images, cams, replace(last, iterations=(2,), checkpoint_every=0), checkpoint_path=tmp_path / "fit.ckpt",
                    callbacks=Callbacks(should_cancel=lambda: asked.append(None) or len(asked) > 1,
                                        on_warning=lambda stage, message: warned.append(message)))
    assert not (tmp_path / "fit.ckpt").exists()
    assert "could not be written (FitDiverged: the reconstruction diverged by iteration 1" in warned[-1]


def test_a_fit_under_a_callers_bf16_autocast_is_the_float32_fit():
    """As the renderer (under autocast its render is the float32 one): a fit run under a caller's bf16 autocast had
    cast its rays to bf16 (camera rotations by einsum, up to 0.0075 rad, 9 pixels of an 800 px view, off) and run the
    render's backward products in bf16, and fitted another grid (0.27 apart in raw features after 30 steps)."""
    from voxe_core.cameras import camera_rays

    images, cams = synthetic_views()
    config = tiny_config(tv_density=1e-2, tv_color=1e-2)
    reference = reconstruct(images, cams, config)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        mixed = reconstruct(images, cams, config)
        rays = camera_rays(Cameras.from_fov(cams.c2w, 0.69, 800, 800), 1)
    assert torch.equal(mixed.features, reference.features)
    for made, expected in zip(rays, camera_rays(Cameras.from_fov(cams.c2w, 0.69, 800, 800), 1)):
        assert made.dtype == torch.float32 and torch.equal(made, expected)


def test_progress_names_the_l1_and_the_total_variation_apart():
    """The value named "l1" had been the loss minimised, total variation included: 10^3 times a fit's TV reported as
    its L1 of colours in [0, 1]. Now "l1" is the photometric L1 alone, beside "tv" (its weighted term) and "total"."""
    images, cams = synthetic_views()
    noisy = VoxelGrid(12, features=torch.randn(12, 12, 12, 4, generator=torch.Generator().manual_seed(0)))
    seen = []
    reconstruct(images, cams, tiny_config(iterations=(5,), resolutions=(12,), image_downsample=(1,), tv_density=1e3,
                                          tv_color=1e3), Callbacks(on_progress=seen.append), initial_grid=noisy)
    assert all(p.losses.keys() == {"l1", "tv", "total"} for p in seen)
    assert all(0 < p.losses["l1"] <= 1 for p in seen)  # mean |colour - target|, both in [0, 1]
    assert min(p.losses["tv"] for p in seen) > 1  # a noisy grid's
    for p in seen:
        assert p.losses["total"] == pytest.approx(p.losses["l1"] + p.losses["tv"], rel=1e-6)
    seen.clear()
    reconstruct(images, cams, tiny_config(iterations=(2,), resolutions=(12,), image_downsample=(1,)),
                Callbacks(on_progress=seen.append))
    assert [p.losses.keys() for p in seen] == [{"l1"}] * 2  # no TV: the L1 is the loss


def test_total_variation_smooths_the_fit_and_bad_weights_are_refused():
    images, cams = synthetic_views()
    plain = reconstruct(images, cams, tiny_config(iterations=(40, 40)))
    smooth = reconstruct(images, cams, tiny_config(iterations=(40, 40), tv_density=0.05, tv_color=0.05))

    cells = plain.occupancy().cells | smooth.occupancy().cells  # where either holds matter

    assert (dense_total_variation(smooth.features.detach(), cells)
            < 0.5 * dense_total_variation(plain.features.detach(), cells)).all()
    rendered = torch.stack([render_image(smooth, cams, i).rgb for i in range(len(cams))])
    assert (rendered - images).abs().mean() < 0.35 * (images - 1.0).abs().mean()  # still a fit
    with pytest.raises(ValueError, match="tv_density and tv_color must be >= 0"):
        tiny_config(tv_color=-1.0)


def test_each_steps_rays_come_from_images_per_step_distinct_images():
    cpu, seeded = torch.device("cpu"), lambda: torch.Generator().manual_seed(0)
    config = ReconstructConfig(rays_per_step=4000, images_per_step=3)
    batch = ray_batch(config, 10, 50, seeded(), cpu)  # 10 images of 50 pixels
    assert batch.shape == (4000,) and 0 <= int(batch.min()) and int(batch.max()) < 500
    assert (batch // 50).unique().numel() == 3 and (batch % 50).unique().numel() == 50
    generator = seeded()
    chosen = torch.cat([(ray_batch(config, 10, 50, generator, cpu) // 50).unique() for _ in range(300)])
    assert chosen.numel() == 900 and torch.bincount(chosen, minlength=10).min() > 60  # each image ~90 of 300 steps
    # 0, or at least as many as there are: every image, the stream of one plain draw (what fits were before)
    for every in (0, 10, 12):
        assert torch.equal(ray_batch(replace(config, images_per_step=every), 10, 50, seeded(), cpu),
                           torch.randint(0, 500, (4000,), generator=seeded()))
    with pytest.raises(ValueError, match="images_per_step must be >= 0"):
        ReconstructConfig(images_per_step=-1)
    # the paper recipe and fast() draw from 8 images as the authors' loader; a capture's scene() from every image
    assert (ReconstructConfig().images_per_step, ReconstructConfig.fast().images_per_step,
            ReconstructConfig.scene().images_per_step) == (8, 8, 0)


def test_a_fit_from_two_images_a_step_reduces_error():
    images, cams = synthetic_views()
    two = reconstruct(images, cams, tiny_config(iterations=(40, 40), images_per_step=2))
    rendered = torch.stack([render_image(two, cams, i).rgb for i in range(len(cams))])
    assert (rendered - images).abs().mean() < 0.35 * (images - 1.0).abs().mean()
    every = reconstruct(images, cams, tiny_config(iterations=(40, 40), images_per_step=0))
    assert not torch.equal(two.features, every.features)


def test_mismatched_images_and_cameras_are_rejected():
    images, cams = synthetic_views()
    with pytest.raises(ValueError, match="do not match"):
        reconstruct(images[:3], cams, tiny_config())


@pytest.mark.parametrize("height, width", [(0, 4), (4, 0)])
def test_images_of_no_pixels_are_refused_naming_their_size(height, width):
    """Cameras of a zero side and images to match had passed the checks and failed resampling the first stage's
    images ("adaptive_avg_pool2d(): Expected input to have non-zero size ...", a RuntimeError the CLI shows as a
    bug)."""
    cams = Cameras.from_fov(look_at(torch.tensor([[0.0, -4.0, 1.0], [4.0, 0.0, 1.0]])), 0.7, width, height)
    with pytest.raises(ValueError, match=rf"^images of {height}x{width} pixels hold no pixel to fit$"):
        reconstruct(torch.ones(2, height, width, 3), cams, tiny_config(), Callbacks(on_progress=pytest.fail))


@pytest.mark.parametrize("what,message", [
    ("rgba", r"must be \(N, H, W, 3\) floating-point RGB in \[0, 1\] on white, got \(6, 16, 16, 4\)"),  # a reshape's
    ("grey", r"must be \(N, H, W, 3\) floating-point RGB .* got \(6, 16, 16, 1\)"),  # error, an IndexError
    ("uint8", r"must be \(N, H, W, 3\) floating-point RGB .* got \(6, 16, 16, 3\) torch.uint8"),  # all white
    ("0..255", r"must hold values in \[0, 1\] \(8-bit values divided by 255\), got values from 12 to 255"),
])
def test_images_other_than_rgb_in_0_to_1_are_refused_before_any_work(what, message):
    images, cams = synthetic_views()
    given = {"rgba": torch.cat([images, torch.ones_like(images[..., :1])], -1), "grey": images[..., :1],
             "uint8": (images * 255).round().to(torch.uint8), "0..255": (images * 255).round()}[what]
    with pytest.raises(ValueError, match=message):
        reconstruct(given, cams, tiny_config(), Callbacks(on_progress=pytest.fail))


def test_row_sparse_adam_matches_dense_adam_when_every_row_is_touched():
    torch.manual_seed(0)
    a = torch.nn.Parameter(torch.randn(10, 4))
    b = torch.nn.Parameter(a.detach().clone())
    sparse_opt, dense_opt = RowSparseAdam(a, lr=0.1), torch.optim.Adam([b], lr=0.1)
    for _ in range(5):
        target = torch.randn(10, 4)
        index = torch.arange(10).repeat(2)  # every row, twice: gradients must be summed
        sparse_opt.zero_grad()
        torch.nn.functional.embedding(index, a, sparse=True).sub(target.repeat(2, 1)).pow(2).sum().backward()
        sparse_opt.step()
        dense_opt.zero_grad()
        b[index].sub(target.repeat(2, 1)).pow(2).sum().backward()
        dense_opt.step()
    assert torch.allclose(a, b, atol=1e-5)


def test_row_sparse_adam_scales_each_columns_step():
    grads = torch.randn(5, 4)
    steps = []
    for scale in (None, torch.tensor([1.0, 0.5, 0.5, 0.5])):
        a = torch.nn.Parameter(torch.zeros(5, 4))
        opt = RowSparseAdam(a, lr=0.1, column_lr_scale=scale)
        a.grad = grads.clone()
        opt.step()
        steps.append(a.detach().clone())
    assert torch.allclose(steps[1][:, 0], steps[0][:, 0]) and torch.allclose(steps[1][:, 1:], 0.5 * steps[0][:, 1:])
    assert steps[0].abs().min() > 0.09  # Adam's first step is lr in size


def test_row_sparse_adam_leaves_untouched_rows_alone():
    a = torch.nn.Parameter(torch.zeros(6, 2))
    opt = RowSparseAdam(a, lr=0.1)
    torch.nn.functional.embedding(torch.tensor([1, 4]), a, sparse=True).sum().backward()
    opt.step()
    moved = (a.detach() != 0).any(-1)
    assert moved.tolist() == [False, True, False, False, True, False]


@needs_mic
@pytest.mark.slow
def test_short_real_fit_on_mic_exceeds_a_psnr_floor():
    train = load_scene(MIC, "train", downsample=8)
    test = load_scene(MIC, "test", downsample=8, max_images=4)
    config = ReconstructConfig.fast(resolutions=(32, 64), iterations=(150, 250), image_downsample=(2, 1),
                                    rays_per_step=2048)
    grid = reconstruct(train.images, train.cameras, config)
    scores = [psnr(render_image(grid, test.cameras, i, RenderConfig(step_ratio=0.8)).rgb, test.images[i])
              for i in range(len(test.cameras))]
    assert sum(scores) / len(scores) > 24.0
    occupancy = grid.occupancy()
    assert occupancy.fraction < 0.1  # the microphone fills little of its box


def test_camera_clearance_keeps_the_space_around_each_camera_empty():
    images, cams = synthetic_views()
    grid = VoxelGrid(12, bbox_min=(-4.5,) * 3, bbox_max=(4.5,) * 3)  # a box that holds the cameras (radius ~4.3)
    config = tiny_config(resolutions=(12,), iterations=(20,), image_downsample=(1,), init_density=0.5,
                         camera_clearance=0.3)
    fitted = reconstruct(images, cams, config, initial_grid=grid)
    positions = fitted.vertex_positions()
    centres = cams.c2w[:, :3, 3]
    near = (torch.cdist(positions, centres) < 0.3 * centres.norm(dim=-1)).any(1)
    assert near.sum() > 0 and (fitted.flat_features[near, 0] <= 0).all()
    assert (fitted.flat_features[~near, 0] > 0).any()  # the rest of space is fitted as before
    with pytest.raises(ValueError, match="camera_clearance"):
        tiny_config(camera_clearance=1.0)


@pytest.mark.parametrize("preset,probes", [(ReconstructConfig.fast, False), (ReconstructConfig, False),
                                           (ReconstructConfig.scene, True)])
def test_only_a_scene_fit_pays_for_the_early_stop_density_pass(monkeypatch, preset, probes):
    """An object's rays end a few samples past its surface: the pass kept 92 % of mic's samples and cost more than
    it saved, so object fits go without it; a capture's rays go on through the room (fox: half dropped)."""
    images, cams = synthetic_views()
    probed = []
    stop_early = VoxelGrid._stop_early
    monkeypatch.setattr(VoxelGrid, "_stop_early", lambda grid, *a: probed.append(1) or stop_early(grid, *a))
    config = replace(preset(), resolutions=(12,), iterations=(3,), image_downsample=(1,), rays_per_step=64)
    reconstruct(images, cams, config)
    assert bool(probed) == probes and config.render.early_stop == (1e-4 if probes else 0.0)


TRANSPARENT = ("the fit ends with no density its renders sample (no positive density anywhere, or none above the "
               "render's sigma_threshold): the reconstruction is transparent, every render of it the background "
               "(views that show nothing but the background, or a fit that failed); an edit of it is refused")


def faint_blob(resolution: int = 12) -> VoxelGrid:
    """A faint blob where every view looks, which white views fit away."""
    grid = VoxelGrid(resolution, init_density=-1.0)
    with torch.no_grad():
        grid.features[..., 0][(grid.vertex_positions().norm(dim=-1) < 0.5).reshape((resolution,) * 3)] = 0.05
    return grid


def test_a_fit_from_or_ending_with_no_density_its_renders_sample_is_refused_or_said():
    """A fit from a transparent ReLU field has no gradient (refused before its first step, init_density named only
    where it made the grid); one that ends transparent (white views on white: its second and last step fits the
    blob away) is said through the callbacks' warning, as the edit of it is refused."""
    images, cams = synthetic_views()
    reports = []
    with pytest.raises(ValueError, match=r"the fit's initial grid has no density its renders sample \(a ReLU field "
                       r"with no positive density, or none above the render's sigma_threshold; init_density <= 0\?\)"):
        reconstruct(images, cams, tiny_config(init_density=-0.5), Callbacks(on_progress=reports.append))
    with pytest.raises(ValueError, match=r"or none above the render's sigma_threshold\): no step") as given:
        reconstruct(images, cams, tiny_config(), Callbacks(on_progress=reports.append),
                    initial_grid=VoxelGrid(12, init_density=-0.5))
    assert "init_density" not in str(given.value)
    assert reports == []
    said = []
    reconstruct(torch.ones_like(images), cams, tiny_config(resolutions=(12,), iterations=(2,), image_downsample=(1,)),
                Callbacks(on_warning=lambda stage, text: said.append((stage, text))), initial_grid=faint_blob())
    assert said == [("reconstruct", TRANSPARENT)]
    said.clear()
    reconstruct(images, cams, tiny_config(iterations=(5, 5)), Callbacks(on_warning=lambda *warning: said.append(
        warning)))
    assert said == []


def fit_white_views_from_a_faint_blob(iterations: tuple[int, ...]) -> tuple[VoxelGrid, list[int], list[str]]:
    """A 12³ -> 24³ -> 32³ fit of white views from :func:`faint_blob`, whose second step fits its density away: the
    grid, the steps it reported (of 60) and its warnings."""
    images, cams = synthetic_views()
    reports, said = [], []
    config = tiny_config(resolutions=(12, 24, 32), iterations=iterations, image_downsample=(1, 1, 1))
    grid = reconstruct(torch.ones_like(images), cams, config,
                       Callbacks(on_progress=reports.append, on_warning=lambda stage, text: said.append(text)),
                       initial_grid=faint_blob())
    assert {report.total for report in reports} == {sum(iterations)}
    assert grid.resolution == (32, 32, 32) and renders_nothing(grid, config.render)
    return grid, [report.iteration for report in reports], said


def test_a_fit_turned_transparent_stops_at_the_next_stage_start():
    """Once its steps have fitted every density away, no later step has a gradient: a fit whose stage ends so stops
    at the next stage's start (the remaining stages are the finest, the dearest) and says so, its grid at the final
    resolution."""
    grid, steps, said = fit_white_views_from_a_faint_blob(iterations=(2, 29, 29))
    assert steps == [1, 2]
    assert said == [TRANSPARENT + " (stopped at stage 2 of 3: none of the steps left would have had a gradient)"]


def test_a_fit_turned_transparent_mid_stage_stops_at_the_step_that_finds_it():
    """Nor does the rest of the stage it turns so in: the first step whose batch renders nothing (its second step
    fits the blob away, so its third renders nothing) finds the grid transparent and the fit stops there, 27 steps
    before its first stage's end, and says where."""
    grid, steps, said = fit_white_views_from_a_faint_blob(iterations=(30, 15, 15))
    assert steps == [1, 2, 3]
    assert said == [TRANSPARENT + " (stopped at stage 1 of 3, after 3 of its 30 steps: none of the steps left would "
                    "have had a gradient)"]


def test_a_fit_turned_transparent_while_averaging_its_iterates_runs_its_stage_out():
    """An averaged stage's steps left weigh on the grid it returns, the mean of its iterates (stopped at its third
    step, the mean of three had kept some of the blob's density): it runs to its end."""
    images, cams = synthetic_views()
    reports, said = [], []
    config = tiny_config(resolutions=(12,), iterations=(30,), image_downsample=(1,), average_from=0.0,
                         average_every=1)
    grid = reconstruct(torch.ones_like(images), cams, config,
                       Callbacks(on_progress=reports.append, on_warning=lambda stage, text: said.append(text)),
                       initial_grid=faint_blob())
    assert len(reports) == 30 and said == [TRANSPARENT] and renders_nothing(grid, config.render)
