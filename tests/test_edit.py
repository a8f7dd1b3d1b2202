"""Text-guided editing (SPEC §2): the SDS loop, its regularisers, checkpoints, resume and the CLI.

The real path runs on the tiny random-weight Stable Diffusion (a SMOKE-TEST
MODEL: it proves the plumbing, never edit quality). A fake guidance that
implements the :class:`Guidance` protocol records what the loop sends it
(prompts, image sizes, time steps) where the real model cannot tell us.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import re
import shutil
import time

import numpy as np
import pytest
import torch

import voxe_core.edit as edit_module
from voxe_core.backbones import load_grid
from voxe_core.cameras import Cameras, spherical_poses
from voxe_core.cli import main
from voxe_core.constants import FLOAT32_MAX
from voxe_core.edit import EditConfig, EditDiverged, build_prompt, edit, learning_rate, load_edit_checkpoint
from voxe_core.export import render_views
from voxe_core.grid import VoxelGrid
from voxe_core.guidance import Guidance
from voxe_core.guidance.sds import StableDiffusionGuidance
from voxe_core.progress import Callbacks, StageCancelled
from voxe_core.render import RenderConfig, render_rays
from voxe_core.scene_grid import SceneGrid
from voxe_core.schedule import TimestepSchedule

SIZE = 32  # render size of every test run


@pytest.fixture(autouse=True)
def _single_thread():
    # Tiny ops: OpenMP hand-offs dominate on a shared 2-core box.
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def tiny_guidance(tiny_sd_path) -> StableDiffusionGuidance:
    return StableDiffusionGuidance.from_pretrained(str(tiny_sd_path), device="cpu", local_files_only=True)


@pytest.fixture
def small_sphere(make_sphere_grid) -> VoxelGrid:
    return make_sphere_grid(20)


class FakeGuidance:
    """Implements the Guidance protocol; records prompts per SDS call. Its loss darkens the render."""

    num_train_timesteps = 1000
    dtype = torch.float32

    def __init__(self):
        self.prompts: list[str] = []  # embedding index -> prompt
        self.calls: list[dict] = []

    def encode_prompts(self, prompts):
        out = []
        for p in prompts:
            if p not in self.prompts:
                self.prompts.append(p)
            out.append(torch.full((4, 8), float(self.prompts.index(p))))
        return torch.stack(out)

    def sds_loss(self, images, text_embeddings, timesteps, guidance_scale=100.0, generator=None):
        self.calls.append({
            "prompts": [self.prompts[int(e[0, 0])] for e in text_embeddings],
            "shape": tuple(images.shape),
            "t": timesteps.tolist(),
            "scale": guidance_scale,
        })
        return images.mean(), {}

    def cross_attention_maps(self, image, prompt, timestep=200, resolution_filter=16, generator=None):
        raise NotImplementedError

    def token_spans(self, prompt, words):
        raise NotImplementedError

    def content_token_indices(self, prompt):
        raise NotImplementedError


def named_guidance(model_id: str) -> FakeGuidance:
    """A FakeGuidance whose ``model_id`` (the model an edit checkpoint records) is ``model_id``."""
    named = FakeGuidance()
    named.model_id = model_id
    return named


def _collect(reports):
    return Callbacks(on_progress=reports.append)


# ------------------------------------------------------------------ config / prompts


def test_defaults_are_the_papers():
    c = EditConfig()
    assert (c.iterations, c.lr, c.betas, c.render_size, c.guidance_scale) == (8000, 0.03, (0.9, 0.999), 266, 100.0)
    assert (c.regulariser, c.regulariser_weight, c.schedule.floor, c.batch_size) == ("reg3d", 200.0, 0.35, 1)
    assert (c.radius, round(c.fov_x, 4), c.min_zenith_deg, c.max_zenith_deg) == (4.0311, 0.6911, 15.0, 90.0)
    assert c.render.background == (1.0, 1.0, 1.0) and c.lr_decay and c.view_words
    assert EditConfig.authors().schedule.floor == 0.22
    with pytest.raises(ValueError, match="regulariser"):
        EditConfig(regulariser="tv")
    with pytest.raises(ValueError, match="autocast"):
        EditConfig(autocast_dtype="fp8")


@pytest.mark.parametrize("name", ["lr", "radius"])
@pytest.mark.parametrize("value", [0.0, -4.0311, math.inf, math.nan, 1e39])
def test_a_learning_rate_or_radius_outside_zero_to_infinity_is_refused_by_name(name, value):
    """lr inf had run one step and failed the next with 'its loss is nan ... half precision overflowing?'; a negative
    radius edited from cameras below the object, named 'front' or 'overhead' by the pose above it (0, inf and NaN
    failed in the cameras, naming no setting). 1e39, finite in float64, is inf in the float32 they are used in."""
    with pytest.raises(ValueError, match=rf"^{name} must be positive and finite in float32, got {re.escape(str(value))}$"):
        EditConfig(**{name: value})


@pytest.mark.parametrize("name, rule", [("guidance_scale", "positive"), ("regulariser_weight", ">= 0")])
@pytest.mark.parametrize("value", [1e39, math.inf, math.nan, -1.0])
def test_a_loss_scale_beyond_float32_is_refused_by_name(name, rule, value):
    """A scale of 1e39, finite in float64, was accepted and is inf in the float32 it scales the losses in (a
    regulariser weight of 1e39 had diverged the first step, blamed on half precision or the lr); bounded as lr is."""
    with pytest.raises(ValueError, match=rf"^{name} must be {rule} and finite in float32, got {re.escape(str(value))}$"):
        EditConfig(**{name: value})
    assert getattr(EditConfig(**{name: FLOAT32_MAX}), name) == FLOAT32_MAX


@pytest.mark.parametrize("flag, message", [("--guidance-scale", "--guidance-scale must be positive"),
                                           ("--reg-weight", "--reg-weight must be >= 0")])
def test_voxe_edit_refuses_a_loss_scale_beyond_float32_before_the_model_loads(flag, message, small_sphere, tmp_path,
                                                                              monkeypatch, capsys):
    import voxe_core.cli.edit as edit_command

    monkeypatch.setattr(edit_command, "load_guidance", lambda *args, **kwargs: pytest.fail("loaded the model"))
    small_sphere.save(tmp_path / "g.safetensors")
    assert main(["edit", str(tmp_path / "g.safetensors"), "--prompt", "a dog", "--out", str(tmp_path / "out"),
                 "--device", "cpu", flag, "1e39"]) == 2
    assert capsys.readouterr().err == f"voxe edit: error: {message} and finite in float32, got 1e+39\n"
    assert not (tmp_path / "out").exists()


def test_voxe_edit_and_refine_refuse_an_out_of_range_value_naming_the_option_typed(small_sphere, tmp_path, monkeypatch,
                                                                                  capsys):
    """``voxe edit --reg-weight -1`` had been refused as "regulariser_weight must be >= 0 ...", and ``voxe refine
    --sigma 0`` as "sigma must be positive; smoothness and smoothing_sigma non-negative ... got 0.0, 5.0, 0.5": the
    settings they fill, no option the user typed (as a value that is no finite number now is), and ``--render-size 4``
    / ``--batch-size 17`` as "render_size must be at least 8 px" / "batch_size must be at most 16". The configs' own
    rule is said, by the option's name."""
    import voxe_core.cli.edit as edit_command
    import voxe_core.cli.refine as refine_command

    for module in (edit_command, refine_command):
        monkeypatch.setattr(module, "load_guidance", lambda *args, **kwargs: pytest.fail("loaded the model"))
    small_sphere.save(tmp_path / "g.safetensors")
    grid = str(tmp_path / "g.safetensors")
    edit = ["edit", grid, "--prompt", "a dog", "--out", str(tmp_path / "edit"), "--device", "cpu"]
    refine = ["refine", grid, "--initial", grid, "--prompt", "a dog", "--edit-words", "dog", "--out",
              str(tmp_path / "refine"), "--device", "cpu"]
    for command, option, value, rule in (
            (edit, "--reg-weight", "-1", "must be >= 0 and finite in float32, got -1.0"),
            (edit, "--lr", "0", "must be positive and finite in float32, got 0.0"),
            (edit, "--guidance-scale", "-7.5", "must be positive and finite in float32, got -7.5"),
            (edit, "--render-size", "4", "must be at least 8 px, got 4"),
            (edit, "--batch-size", "17", "must be at most 16 (the service's and the CLI's limit), got 17"),
            (refine, "--render-size", "7", "must be at least 8 px, got 7"),
            (refine, "--sigma", "0", "must be positive and finite, got 0.0"),
            (refine, "--smoothness", "-1", "must be non-negative and at most 3.403e+38, got -1.0"),
            (refine, "--smoothing-sigma", "-0.5", "must be non-negative and finite, got -0.5"),
            (refine, "--lr", "-0.1", "must be positive and finite, got -0.1"),
            (refine, "--tv-weight", "-2", "must be non-negative and finite, got -2.0")):
        assert main([*command, option, value]) == 2
        assert capsys.readouterr().err == f"voxe {command[0]}: error: {option} {rule}\n"


@pytest.mark.parametrize("name", ["front_azimuth_deg", "preview_elevation_deg"])
@pytest.mark.parametrize("angle", [math.nan, math.inf, -math.inf])
def test_an_angle_that_is_no_angle_is_refused_by_name(name, angle):
    """A NaN or infinite angle had been taken and failed only in the poses ("camera positions must be finite"), or
    (a NaN front) read every pose as a side view; refused as RefineConfig refuses its front, by the shared check."""
    with pytest.raises(ValueError, match=rf"^{name} must be a finite angle in degrees, got {angle}$"):
        EditConfig(**{name: angle})


@pytest.mark.parametrize("betas", [(1.0, 0.999), (0.9, 1.5), (-0.1, 0.999), (math.nan, 0.999), (0.9, math.inf),
                                   (0.9,), (0.9, 0.99, 0.999)])
def test_adams_betas_outside_zero_to_one_are_refused_by_name(betas):
    """torch's Adam had refused them only as the edit started, naming no setting ("Invalid beta parameter")."""
    with pytest.raises(ValueError, match=rf"^betas must be Adam's two decay rates, each in \[0, 1\), got "
                                         rf"{re.escape(str(betas))}$"):
        EditConfig(betas=betas)
    assert EditConfig(betas=(0.0, 0.5)).betas == (0.0, 0.5)


@pytest.mark.parametrize("betas", [("0.9", "0.999"), None, 0.9, (False, 0.999), (0.9, None), "09"])
def test_adams_betas_that_are_no_pair_of_numbers_are_refused_by_name(betas):
    """Regression: a pair of strings, None or one number had been a TypeError naming no setting ("'<=' not supported
    between instances of 'int' and 'str'", "object of type 'NoneType' has no len()"), and False had run as 0."""
    with pytest.raises(ValueError, match=rf"^betas must be Adam's two decay rates, each in \[0, 1\), got "
                                         rf"{re.escape(str(betas))}$"):
        EditConfig(betas=betas)
    assert EditConfig(betas=[0.5, 0.9]).betas == [0.5, 0.9]  # a list (JSON's pair) is one too


@pytest.mark.parametrize("name", ["iterations", "render_size", "batch_size", "image_regulariser_rays", "lr_decay_start",
                                  "lr_decay_every", "preview_every", "checkpoint_every", "seed"])
@pytest.mark.parametrize("value", [2.5, math.nan, True, "8"])
def test_a_count_that_is_no_whole_number_is_refused_by_name(name, value):
    """NaN, 2.5 or True had passed the range checks and failed once the edit had begun (a TypeError from range(),
    torch.rand or a reshape) naming no setting, or run (checkpoint_every 0.5 checkpointed every step)."""
    with pytest.raises(ValueError, match=rf"^{name} takes whole numbers, got {re.escape(repr(value))}$"):
        EditConfig(**{name: value})
    assert getattr(EditConfig(**{name: 16}), name) == 16


def test_a_batch_size_past_the_services_limit_is_refused_naming_it():
    """The API capped batch_size at 16 but EditConfig (the CLI's, through presets.edit_config) took any: 1,000 poses
    rendered a step, each held with its autograd graph, ran out of memory only once the model had loaded."""
    from voxe_core import presets
    from voxe_core.constants import MAX_BATCH_SIZE

    assert MAX_BATCH_SIZE == 16 and EditConfig(batch_size=16).batch_size == 16
    for make in (lambda: EditConfig(batch_size=17), lambda: presets.edit_config({"batch_size": 1000})):
        with pytest.raises(ValueError, match=r"^batch_size must be at most 16 \(the service's and the CLI's limit\), "
                                             r"got (17|1000)$"):
            make()


@pytest.mark.parametrize("rays", [2**24 + 1, 2**40, 2**63])
def test_image_regulariser_rays_past_the_largest_steps_renders_are_refused_naming_the_bound(rays):
    """Any count had been taken: 2**40 failed at the first step, once the model had loaded and rendered, allocating
    8 TiB of pixel indices; 2**63 as a TypeError from torch.randint naming no setting."""
    from voxe_core.constants import MAX_IMAGE_REGULARISER_RAYS

    assert MAX_IMAGE_REGULARISER_RAYS == 16 * 1024**2 == 2**24
    assert EditConfig(image_regulariser_rays=2**24).image_regulariser_rays == 2**24
    with pytest.raises(ValueError, match=rf"^image_regulariser_rays must be at most 16777216 \(as many rays as the "
                                         rf"largest step's renders: batch_size 16 of 1024 px\), got {rays}$"):
        EditConfig(image_regulariser_rays=rays)


@pytest.mark.parametrize("name, value, rule", [
    ("batch_size", 0, ">= 1"), ("image_regulariser_rays", -4, ">= 1"), ("lr_decay_every", 0, ">= 1"),
    ("lr_decay_start", -1, ">= 0"), ("preview_every", -1, ">= 0 (0 turns it off)"),
    ("checkpoint_every", -250, ">= 0 (0 turns it off)"), ("lr_decay_factor", 1.5, "in (0, 1]"),
    ("lr_decay_factor", 0.0, "in (0, 1]"), ("lr_decay_factor", math.nan, "in (0, 1]"),
])
def test_a_count_or_decay_out_of_range_is_refused_naming_its_setting_and_value(name, value, rule):
    """They had been refused in pairs and threes naming no value ("lr decay needs every >= 1, start >= 0 and a factor
    in (0, 1]", "batch_size and image_regulariser_rays must be >= 1"): which was wrong, and how, was left to guess."""
    with pytest.raises(ValueError, match=rf"^{name} must be {re.escape(rule)}, got {value}$"):
        EditConfig(**{name: value})


@pytest.mark.parametrize("name, value", [("lr", "0.01"), ("guidance_scale", None), ("regulariser_weight", True),
                                         ("fov_x", None), ("min_zenith_deg", "15"), ("lr_decay_factor", [0.96])])
def test_a_setting_that_is_no_number_is_refused_naming_it(name, value):
    """Regression: a string or None had failed a range test naming no setting ("'<' not supported between instances
    of 'int' and 'str'", a TypeError), and True had run as 1 (RefineConfig shares the check)."""
    with pytest.raises(ValueError, match=f"^{name} must be a number, got {re.escape(repr(value))}$"):
        EditConfig(**{name: value})
    assert EditConfig(lr=np.float32(0.01), guidance_scale=np.float64(7.5), radius=4).radius == 4


@pytest.mark.parametrize("name, value", [("lr", np.float32(0.01)), ("radius", np.float32(4.0)), ("seed", np.int64(3)),
                                         ("render_size", np.int32(16)), ("guidance_scale", np.float64(7.5))])
def test_numpy_numbers_the_config_takes_run_and_checkpoint_as_python_ones(small_sphere, tmp_path, name, value):
    """Regression: EditConfig's checks take numpy numbers, but its recipe (in every run's checkpoint meta) had been
    dumped as JSON as they were: edit() failed as it began, "Object of type float32 is not JSON serializable". The
    recipe holds the Python number, so a resume with the same setting matches it; a numpy seed had failed seeding the
    generators ("an integer is required")."""
    config = EditConfig(**{"iterations": 1, "render_size": 16, name: value})
    assert config.recipe()[name] == (int(value) if isinstance(value, np.integer) else float(value))
    checkpoint = tmp_path / "edit.safetensors"
    edit(small_sphere, "a dog", FakeGuidance(), config, checkpoint_path=checkpoint)
    longer = dataclasses.replace(config, iterations=2)
    edit(small_sphere, "a dog", FakeGuidance(), longer, checkpoint_path=checkpoint, resume_from=checkpoint)
    assert load_edit_checkpoint(checkpoint)[1]["iteration"] == 2


@pytest.mark.parametrize("name, value, message", [
    ("schedule", "authors", "schedule must be a TimestepSchedule, got 'authors'"),
    ("schedule", {"floor": 0.22}, "schedule must be a TimestepSchedule, got {'floor': 0.22}"),
    ("render", {"step_ratio": 0.6}, "render must be a RenderConfig, got {'step_ratio': 0.6}"),
    ("view_words", "false", "view_words takes True or False, got 'false'"),
    ("lr_decay", 0, "lr_decay takes True or False, got 0"),
    ("sync_timing", None, "sync_timing takes True or False, got None"),
    ("prompt_prefix", 5, "prompt_prefix must be a string or None, got 5"),
])
def test_a_setting_of_another_type_is_refused_naming_it(name, value, message):
    """They had been taken: schedule="authors" failed at the edit's first step ("'str' object has no attribute
    'sample'"), a render dict as the edit began, prompt_prefix 5 in the prompt's check, all naming no setting; and
    view_words="false" ran with view words."""
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        EditConfig(**{name: value})
    assert EditConfig(schedule=TimestepSchedule.authors(), view_words=False, prompt_prefix=None).schedule.floor == 0.22


@pytest.mark.parametrize("low, high", [(-5.0, 90.0), (15.0, 200.0), (60.0, 30.0), (math.nan, 90.0)])
def test_a_zenith_range_out_of_order_is_refused_naming_its_fields_and_values(low, high):
    """It had been refused as "need 0 <= min_zenith <= max_zenith <= 180, got 60.0, 30.0": no field of that name, and
    which value was which left to guess."""
    with pytest.raises(ValueError, match=rf"^need 0 <= min_zenith_deg <= max_zenith_deg <= 180 \(degrees from straight "
                                         rf"above\), got min_zenith_deg={low}, max_zenith_deg={high}$"):
        EditConfig(min_zenith_deg=low, max_zenith_deg=high)
    assert (EditConfig(min_zenith_deg=0.0, max_zenith_deg=0.0).max_zenith_deg, EditConfig(max_zenith_deg=180.0)
            .max_zenith_deg) == (0.0, 180.0)


@pytest.mark.parametrize("radius, zeniths, seen", [(1.0, {}, "zenith 15°, azimuth 0°"),
                                                   (2.0, {}, "zenith 41.5°, azimuth 0°"),
                                                   (2.0, {"min_zenith_deg": 80.0}, "zenith 80°, azimuth 40.5°")])
def test_a_radius_that_puts_cameras_inside_the_object_box_is_refused(radius, zeniths, seen, small_sphere):
    """A radius of 1 (or 2, whose poses near the box's diagonals lie in it) had been taken and every such render
    started inside the grid's box [-1.5, 1.5]³, in the object."""
    guidance = FakeGuidance()
    config = EditConfig(iterations=1, render_size=16, radius=radius, **zeniths)
    with pytest.raises(ValueError, match=rf"^radius {radius} puts the edit's cameras inside the grid's object box "
                                         rf"\[-1.5, -1.5, -1.5\] to \[1.5, 1.5, 1.5\] \(one at {seen} about the orbit "
                                         rf"centre \[0.0, 0.0, 0.0\]\): its renders would start inside the object; give "
                                         rf"a radius above 2.598, the box's farthest corner from that centre$"):
        edit(small_sphere, "a dog", guidance, config)
    assert not guidance.prompts  # refused before the guidance encodes anything
    with pytest.raises(ValueError, match=r"^radius 1.0 puts the edit's cameras inside the grid's object box "
                                         r"\[-1.5, -1.5, -1.5\] to \[1.5, 1.5, 1.5\] "):
        edit(SceneGrid(9, init_density=1.0), "a dog", guidance, EditConfig(iterations=1, render_size=16, radius=1.0))


def test_a_radius_outside_the_grids_own_box_edits(make_sphere_grid):
    """The box is the grid's own: a grid in [-0.5, 0.5]³ edits from radius 1.5."""
    small = make_sphere_grid(12, radius=0.3)
    small = VoxelGrid(12, (-0.5,) * 3, (0.5,) * 3, features=small.features.detach().clone())
    guidance = FakeGuidance()
    edited = edit(small, "a dog", guidance, EditConfig(iterations=2, render_size=16, radius=1.5))
    assert len(guidance.calls) == 2 and not torch.equal(edited.features, small.features)


@pytest.mark.parametrize("seed", [-1, 2**32, 2**64 - 1])
def test_a_seed_outside_the_services_range_is_refused(seed):
    """2**64 - 1 had overflowed the device generator's seed + 1 as the edit started; the range is RefineConfig's."""
    with pytest.raises(ValueError, match=rf"^seed must lie in \[0, 4294967295\] .*, got {seed}$"):
        EditConfig(seed=seed)
    assert EditConfig(seed=2**32 - 1).seed == 2**32 - 1


def test_learning_rate_matches_the_authors_loop():
    config = EditConfig()
    lr, used = config.lr, []
    for step in range(1, config.iterations + 1):  # the authors' loop: 1-based steps, decay after the step
        used.append(lr)
        if step % 400 == 0 and step >= 5000:
            lr *= 0.96
    assert [learning_rate(config, i) for i in range(config.iterations)] == pytest.approx(used, rel=1e-12)
    assert learning_rate(config, 5199) == 0.03 and learning_rate(config, 5200) == pytest.approx(0.03 * 0.96)
    off = EditConfig(lr_decay=False)
    assert {learning_rate(off, i) for i in (0, 5200, 7999)} == {0.03}


def test_build_prompt_prefix_and_view():
    assert build_prompt("a dog", "side") == "a render of a dog, side view"
    assert build_prompt("a dog", None, prefix=None) == "a dog"
    assert build_prompt("a dog", "back", prefix="a photo of") == "a photo of a dog, back view"
    with pytest.raises(ValueError, match="^the edit prompt is empty$"):
        build_prompt("   ", None)


@pytest.mark.parametrize("text", ["a photo of", "A Photo of.", "  a  photo   of "])
@pytest.mark.parametrize("prefix", ["a photo of", "a photo of ", " a  photo of"])
def test_a_prompt_of_a_custom_prefix_alone_is_refused(text, prefix):
    """As "a render of" alone is: a prompt that is only the prefix had been doubled ("a photo of a photo of, side
    view"), nothing to edit towards; and a prefix with spaces round or in it had been doubled before any prompt
    ("a photo of  a photo of a dog")."""
    with pytest.raises(ValueError, match=r"^the edit prompt has only the prefix 'a photo of' and no content$"):
        build_prompt(text, "side", prefix)
    assert build_prompt("a photo of a dog", None, prefix) == build_prompt("a dog", None, prefix) == "a photo of a dog"
    assert build_prompt("a photo of", None, "a sketch of") == "a sketch of a photo of"


# ------------------------------------------------------------------ the loop on the real tiny SD


def test_edit_with_tiny_sd_changes_the_grid_with_finite_losses(small_sphere, tiny_guidance):
    reports, previews = [], []
    config = EditConfig(iterations=3, render_size=SIZE, preview_every=2)
    out = edit(small_sphere, "a dog", tiny_guidance, config, _collect(reports),
               on_preview=lambda i, image: previews.append((i, image)))
    assert [r.iteration for r in reports] == [1, 2, 3] and all(r.total == 3 and r.stage == "edit" for r in reports)
    for r in reports:
        assert all(torch.isfinite(torch.tensor(v)) for v in r.losses.values())
        assert r.info["t_min"] <= r.info["t"] <= r.info["t_max"] and r.info["lr"] == 0.03
    assert not torch.equal(out.features, small_sphere.features)
    assert torch.isfinite(out.features).all()
    # the initial grid is untouched (G_e is a copy)
    assert out.flat_features is not small_sphere.flat_features
    assert [i for i, _ in previews] == [0, 2, 3] and previews[0][1].shape == (SIZE, SIZE, 3)
    # preview 0 is the initial grid: the sphere is red on white
    assert previews[0][1][SIZE // 2, SIZE // 2, 0] > 0.8 and previews[0][1][SIZE // 2, SIZE // 2, 1] < 0.2


def test_sds_gradient_reaches_occupied_voxels_only(small_sphere, tiny_guidance):
    # No regulariser: after one Adam step exactly the voxels with a nonzero SDS gradient moved.
    config = EditConfig(iterations=1, render_size=SIZE, regulariser_weight=0.0)
    out = edit(small_sphere, "a dog", tiny_guidance, config)
    moved = (out.features != small_sphere.features).detach()
    cells = small_sphere.occupancy(config.render.sigma_threshold).cells
    near = torch.zeros(small_sphere.resolution, dtype=torch.bool)
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                near[dx:dx + cells.shape[0], dy:dy + cells.shape[1], dz:dz + cells.shape[2]] |= cells
    assert moved[..., 0].sum() > 0 and moved[..., 1:].sum() > 0  # density and colour both get gradient
    assert not moved[~near].any()  # ReLU field: nothing outside the occupied cells' vertices


def test_resume_reproduces_the_uninterrupted_run_bit_for_bit(small_sphere, tiny_guidance, tmp_path):
    config = EditConfig(iterations=5, render_size=SIZE, checkpoint_every=2, seed=3)
    reference = edit(small_sphere, "a wooden dog", tiny_guidance, config)

    checkpoint = tmp_path / "checkpoint.safetensors"
    periodic = tmp_path / "at2.safetensors"
    done = []

    def on_checkpoint(path):
        if done[-1] == 2:
            shutil.copy(path, periodic)

    callbacks = Callbacks(on_progress=lambda r: done.append(r.iteration), should_cancel=lambda: len(done) >= 3,
                          on_checkpoint=on_checkpoint)
    with pytest.raises(StageCancelled):
        edit(small_sphere, "a wooden dog", tiny_guidance, config, callbacks, checkpoint_path=checkpoint)
    _, meta = load_edit_checkpoint(checkpoint)
    assert meta["iteration"] == 3  # written on cancellation
    assert load_edit_checkpoint(periodic)[1]["iteration"] == 2

    for start in (checkpoint, periodic):
        resumed = edit(small_sphere, "a wooden dog", tiny_guidance, config, resume_from=start)
        assert torch.equal(resumed.features, reference.features)
    # a different seed is a different run (the test above is not vacuous)
    other = edit(small_sphere, "a wooden dog", tiny_guidance, EditConfig(iterations=5, render_size=SIZE, seed=4))
    assert not torch.equal(other.features, reference.features)


def test_a_checkpoint_from_another_device_type_resumes_from_a_reseeded_device_generator(small_sphere, tmp_path):
    """A CUDA worker's checkpoint holds a 16-byte Philox state for its device generator, which a CPU generator's
    set_state refused with a RuntimeError (and the reverse): a job moved to another worker failed for good."""
    from voxe_core.edit import EDIT_CHECKPOINT_KIND, EDIT_CHECKPOINT_VERSION
    from voxe_core.tensorio import save_tensors

    checkpoint = tmp_path / "c.safetensors"
    edit(small_sphere, "a dog", FakeGuidance(), EditConfig(iterations=2, render_size=SIZE), checkpoint_path=checkpoint)
    tensors, meta = load_edit_checkpoint(checkpoint)
    assert meta["device"] == "cpu"
    cuda_state = torch.zeros(16, dtype=torch.uint8)
    longer = EditConfig(iterations=4, render_size=SIZE)
    older = {k: v for k, v in meta.items() if k != "device"}  # a checkpoint written before the field: told by its size
    for header in ({**meta, "device": "cuda"}, older):  # as a CUDA worker writes it, now and before
        save_tensors(checkpoint, {**tensors, "rng_device": cuda_state}, EDIT_CHECKPOINT_KIND, EDIT_CHECKPOINT_VERSION,
                     header)
        first, again = (edit(small_sphere, "a dog", FakeGuidance(), longer, resume_from=checkpoint) for _ in range(2))
        assert torch.equal(first.features, again.features)  # reproducible, if not the uninterrupted run
        assert not torch.equal(first.features, small_sphere.features)
    save_tensors(checkpoint, tensors, EDIT_CHECKPOINT_KIND, EDIT_CHECKPOINT_VERSION, older)  # this device's, older
    uninterrupted = edit(small_sphere, "a dog", FakeGuidance(), longer)
    assert torch.equal(edit(small_sphere, "a dog", FakeGuidance(), longer, resume_from=checkpoint).features,
                       uninterrupted.features)


def test_an_initial_grid_with_a_nan_or_an_inf_is_refused_before_any_step(small_sphere, tmp_path):
    """A damaged G_i had made the first step's loss NaN: an EditDiverged blaming half precision or the lr."""
    for channel, value in ((0, math.nan), (2, math.inf)):
        grid = small_sphere.clone_grid()
        with torch.no_grad():
            grid.features[3, 4, 5, channel] = value
        guidance, checkpoint = FakeGuidance(), tmp_path / f"c{channel}.safetensors"
        with pytest.raises(ValueError, match="non-finite .* features at 1 of its 8000 vertices"):
            edit(grid, "a wooden dog", guidance, EditConfig(iterations=2, render_size=SIZE), checkpoint_path=checkpoint)
        assert guidance.calls == [] and not checkpoint.exists()


class DivergingGuidance(FakeGuidance):
    """Its third SDS loss is NaN, as a half-precision UNet's overflow makes it."""

    def sds_loss(self, images, text_embeddings, timesteps, guidance_scale=100.0, generator=None):
        loss, diagnostics = super().sds_loss(images, text_embeddings, timesteps, guidance_scale, generator)
        return (loss * math.nan if len(self.calls) == 3 else loss), diagnostics


def test_a_diverged_step_stops_the_edit_before_its_progress_or_checkpoint(small_sphere, tmp_path):
    """It had gone on: every later step NaN, 8,000 of them, then a NaN grid exported."""
    checkpoint, reports = tmp_path / "c.safetensors", []
    with pytest.raises(EditDiverged, match=r"the edit diverged at iteration 3: its loss is nan \(SDS nan, "):
        edit(small_sphere, "a wooden dog", DivergingGuidance(), EditConfig(iterations=6, render_size=SIZE,
             checkpoint_every=1), _collect(reports), checkpoint_path=checkpoint)
    assert [r.iteration for r in reports if r.stage == "edit"] == [1, 2]
    tensors, meta = load_edit_checkpoint(checkpoint)
    assert meta["iteration"] == 2 and torch.isfinite(tensors["features"]).all()  # a resume starts from before


class OverflowingBackwardGuidance(FakeGuidance):
    """Its second SDS loss is finite (0) but its gradient into the renders infinite, as a float16 VAE encoder's
    backward overflowing makes it."""

    def sds_loss(self, images, text_embeddings, timesteps, guidance_scale=100.0, generator=None):
        loss, diagnostics = super().sds_loss(images, text_embeddings, timesteps, guidance_scale, generator)
        return ((images - images.detach()).sqrt().sum() if len(self.calls) == 2 else loss), diagnostics


def test_a_grid_a_finite_loss_made_nan_is_neither_returned_nor_checkpointed(small_sphere, tmp_path):
    """Only the loss was checked: a last step (or one before a checkpoint) whose gradient overflowed had returned and
    saved a NaN G_e, the job "succeeding" with it."""
    config = EditConfig(iterations=2, render_size=SIZE, checkpoint_every=1)
    checkpoint, reports = tmp_path / "c.safetensors", []
    with pytest.raises(EditDiverged, match="diverged by iteration 2: G_e's features hold infinite or NaN values though "
                                           "every loss was finite"):
        edit(small_sphere, "a dog", OverflowingBackwardGuidance(), config, _collect(reports), checkpoint_path=checkpoint)
    assert [math.isfinite(r.losses["total"]) for r in reports] == [True, True]
    tensors, meta = load_edit_checkpoint(checkpoint)
    assert meta["iteration"] == 1 and torch.isfinite(tensors["features"]).all()  # a resume starts from before
    with pytest.raises(EditDiverged, match="diverged by iteration 2"):  # nor returned where nothing is saved
        edit(small_sphere, "a dog", OverflowingBackwardGuidance(), dataclasses.replace(config, checkpoint_every=0))


FLOAT16_ADVICE = ("float16 overflowing? the guidance runs in float16, its weights' dtype: run it under bf16 autocast "
                  "(a job's autocast \"bf16\", voxe edit --autocast bf16), or try a lower lr")


@pytest.mark.parametrize("guidance_class, iterations, end", [
    (DivergingGuidance, 3, r"; the steps before were finite \({}\)$"),  # its loss NaN at the 3rd step
    (OverflowingBackwardGuidance, 2, r" \(a gradient that overflowed in the backward: {}\); not saved$"),  # G_e NaN
])
@pytest.mark.parametrize("weights, autocast, advice", [
    (torch.float16, None, re.escape(FLOAT16_ADVICE)),  # a CUDA model's weights (from_pretrained's dtype there)
    (torch.float32, None, "try a lower lr"),  # no half precision ran
    (torch.float32, "fp16", "try a lower lr"),  # bfloat16 on the CPU: float32's range
])
def test_a_diverged_edit_is_told_what_to_try_for_the_precision_its_guidance_ran_in(
        guidance_class, iterations, end, weights, autocast, advice, small_sphere):
    """Each had said "half precision overflowing? try autocast off, or a lower lr" to every run: to one with autocast
    off already, whose float16 model (a CUDA worker's, or `voxe edit` there) runs in float16 whatever autocast is
    off, and to a float32 run on the CPU, with no half precision in it."""
    guidance = guidance_class()
    guidance.dtype = weights
    with pytest.raises(EditDiverged, match=end.format(advice)) as raised:
        edit(small_sphere, "a dog", guidance, EditConfig(iterations=iterations, render_size=SIZE,
                                                         autocast_dtype=autocast),
             Callbacks(on_warning=lambda stage, text: None))
    assert "autocast off" not in str(raised.value)


@pytest.mark.parametrize("resumed", [False, True])
def test_a_cancel_after_a_step_that_left_the_grid_nan_stays_a_cancel_keeping_the_earlier_checkpoint(
        resumed, small_sphere, tmp_path):
    """The checkpoint a cancel writes had checked G_e first: a step whose finite loss left it NaN turned the user's
    cancel into an EditDiverged, and the worker ended the job FAILED. The NaN grid is not saved: the file stays the
    one the run resumed from (a fresh run saving only on cancel leaves none)."""
    config = EditConfig(iterations=5, render_size=SIZE)
    checkpoint, reports = tmp_path / "c.safetensors", []
    if resumed:
        edit(small_sphere, "a dog", FakeGuidance(), dataclasses.replace(config, iterations=1), checkpoint_path=checkpoint)
    callbacks = Callbacks(on_progress=reports.append, should_cancel=lambda: len(reports) >= 2)  # the 2nd step NaN
    with pytest.raises(StageCancelled, match="edit canceled"):
        edit(small_sphere, "a dog", OverflowingBackwardGuidance(), config, callbacks, checkpoint_path=checkpoint,
             resume_from=checkpoint if resumed else None)
    assert len(reports) == 2
    if resumed:
        tensors, meta = load_edit_checkpoint(checkpoint)
        assert meta["iteration"] == 1 and torch.isfinite(tensors["features"]).all()
    else:
        assert not checkpoint.exists()


def test_a_preview_on_the_step_that_left_the_grid_nan_is_not_rendered_and_the_edit_stops_there(small_sphere):
    """The preview had been rendered from the NaN grid and handed on (the worker published it as the job's preview)
    before the next step's NaN loss stopped the edit, an iteration late."""
    previews = []
    config = EditConfig(iterations=4, render_size=SIZE, preview_every=2)
    with pytest.raises(EditDiverged, match="diverged by iteration 2: G_e's features hold infinite or NaN values"):
        edit(small_sphere, "a dog", OverflowingBackwardGuidance(), config,
             on_preview=lambda done, image: previews.append(done))
    assert previews == [0]


def _overflowing_unet(guidance, monkeypatch, channels):
    """The tiny guidance's UNet output infinite in ``channels`` of its latent's 4, as a float16 UNet overflowing."""
    eager = guidance._eager_unet

    def overflowing(sample, timestep, text):
        out = eager(sample, timestep, text).clone()
        out[:, channels] = torch.inf
        return out

    monkeypatch.setattr(guidance, "_eager_unet", overflowing)


def test_a_guidance_overflowing_everywhere_stops_the_edit_naming_its_precision(small_sphere, tiny_guidance,
                                                                               monkeypatch):
    """Its gradient, zeroed entry by entry, had left a finite loss, so the edit ran on and "succeeded" unchanged. The
    tiny guidance runs in float32: no float16 overflow (a float16 one: the test below)."""
    _overflowing_unet(tiny_guidance, monkeypatch, slice(None))
    reports, steps = [], edit_module.MAX_NONFINITE_GUIDANCE_STEPS
    with pytest.raises(EditDiverged, match=rf"at iteration {steps}: the guidance's SDS gradient was infinite or NaN in "
                                           rf"every entry for the last {steps} iterations \(zeroed, so the edit stood "
                                           r"still\): no float16 overflow: the guidance runs in float32; its model "
                                           r"damaged\?$"):
        edit(small_sphere, "a dog", tiny_guidance, EditConfig(iterations=steps + 5, render_size=16), _collect(reports))
    assert [r.info["sds_nonfinite_fraction"] for r in reports] == [1.0] * (steps - 1)
    assert all(math.isfinite(r.losses["total"]) for r in reports)


class HalfGuidance(FakeGuidance):
    """A float16 guidance (a CUDA model's weights) whose UNet overflows in ``share`` of its SDS gradient's entries."""

    dtype = torch.float16

    def __init__(self, share):
        super().__init__()
        self.share = share

    def sds_loss(self, images, text_embeddings, timesteps, guidance_scale=100.0, generator=None):
        loss, diagnostics = super().sds_loss(images, text_embeddings, timesteps, guidance_scale, generator)
        return loss, {**diagnostics, "nonfinite_fraction": torch.tensor(self.share)}


@pytest.mark.parametrize("share", [0.25, 1.0])
def test_a_float16_guidance_overflowing_is_told_to_run_under_bf16_autocast(share, small_sphere):
    """Each run had been told "a float16 (fp16) UNet overflowing; run the guidance in float32 or bfloat16": a float32
    one too (the test above), and one on CUDA, whose guidance loads in float16 (autocast off leaves it so), not how:
    float32 is no choice there, bfloat16 autocast is."""
    told = ("a float16 UNet overflowing? the guidance runs in float16, its weights' dtype: run it under bf16 autocast "
            "(a job's autocast \"bf16\", voxe edit --autocast bf16)")
    warnings, steps = [], edit_module.MAX_NONFINITE_GUIDANCE_STEPS
    run = contextlib.nullcontext() if share < 1 else pytest.raises(EditDiverged, match=re.escape(
        f"for the last {steps} iterations (zeroed, so the edit stood still): {told}") + "$")
    with run:
        edit(small_sphere, "a dog", HalfGuidance(share), EditConfig(iterations=steps, render_size=SIZE),
             Callbacks(on_warning=lambda stage, text: warnings.append(text)))
    assert len(warnings) == 1 and f"were infinite or NaN and were zeroed ({told}); the edit goes on" in warnings[0]


def test_a_guidance_overflowing_across_a_resume_stops_where_an_uninterrupted_run_does(small_sphere, tiny_guidance,
                                                                                      monkeypatch, tmp_path):
    """The count of wholly non-finite steps had restarted at a resume: a run overflowing on every step, resumed more
    often than every MAX_NONFINITE_GUIDANCE_STEPS steps (a worker restarted), never stopped. A damaged count (not a
    whole number, more than the steps it ran, or one that would have stopped it) is a FormatError."""
    from voxe_core.tensorio import FormatError, save_tensors

    _overflowing_unet(tiny_guidance, monkeypatch, slice(None))
    steps, checkpoint = edit_module.MAX_NONFINITE_GUIDANCE_STEPS, tmp_path / "c.safetensors"
    config = EditConfig(iterations=steps - 4, render_size=16)
    edit(small_sphere, "a dog", tiny_guidance, config, checkpoint_path=checkpoint)
    assert load_edit_checkpoint(checkpoint)[1]["nonfinite_steps"] == steps - 4
    reports = []
    with pytest.raises(EditDiverged, match=rf"at iteration {steps}: .* for the last {steps} iterations"):
        edit(small_sphere, "a dog", tiny_guidance, dataclasses.replace(config, iterations=steps + 5), _collect(reports),
             checkpoint_path=checkpoint, resume_from=checkpoint)
    assert len(reports) == 3  # steps 7 to 9; the 10th stops it
    tensors, meta = load_edit_checkpoint(checkpoint)
    for damaged in (-1, 2.5, "3", True, meta["iteration"] + 1, steps):  # (more steps than it ran; a stopping count)
        save_tensors(tmp_path / "d.safetensors", tensors, kind=edit_module.EDIT_CHECKPOINT_KIND,
                     version=edit_module.EDIT_CHECKPOINT_VERSION, meta={**meta, "nonfinite_steps": damaged})
        with pytest.raises(FormatError, match=re.escape(f"damaged checkpoint: its nonfinite_steps is {damaged!r},")):
            edit(small_sphere, "a dog", tiny_guidance, dataclasses.replace(config, iterations=steps + 5),
                 resume_from=tmp_path / "d.safetensors")


def test_a_guidance_overflowing_in_part_is_reported_and_edits_on(small_sphere, tiny_guidance, monkeypatch):
    """The zeroed share had been in the progress info alone, which neither a job nor the CLI shows: an edit losing a
    quarter of its gradient on every step ran silently. Its first step is said once, as a warning."""
    _overflowing_unet(tiny_guidance, monkeypatch, 0)
    reports, warnings, steps = [], [], edit_module.MAX_NONFINITE_GUIDANCE_STEPS + 1
    callbacks = Callbacks(on_progress=reports.append, on_warning=lambda stage, text: warnings.append((stage, text)))
    edit(small_sphere, "a dog", tiny_guidance, EditConfig(iterations=steps, render_size=16), callbacks)
    assert [r.info["sds_nonfinite_fraction"] for r in reports] == [0.25] * steps
    assert warnings == [("edit", "iteration 1: 25% of the guidance's SDS gradient entries were infinite or NaN and were "
                                 "zeroed (no float16 overflow: the guidance runs in float32; its model damaged?); "
                                 "the edit goes on (it stops after 10 steps in a row with every entry so), said once (each "
                                 "step's share: its sds_nonfinite_fraction)")]


def test_a_guidance_overflowing_in_part_is_said_once_across_a_resume(small_sphere, tiny_guidance, monkeypatch,
                                                                     tmp_path):
    """A run resumed past its first zeroed step (a worker restarted) had been told again at its next one ("iteration
    4: 25% ..." after "iteration 1: 25% ..."): whether it was said is carried in the checkpoint, as the count of wholly
    non-finite steps is; a damaged value is a FormatError, a checkpoint older than it warns as before."""
    from voxe_core.tensorio import FormatError, save_tensors

    _overflowing_unet(tiny_guidance, monkeypatch, 0)
    checkpoint, warnings = tmp_path / "c.safetensors", []
    callbacks = Callbacks(on_warning=lambda stage, text: warnings.append(text))
    config = EditConfig(iterations=3, render_size=16)
    edit(small_sphere, "a dog", tiny_guidance, config, callbacks, checkpoint_path=checkpoint)
    assert load_edit_checkpoint(checkpoint)[1]["zeroed_said"] is True
    edit(small_sphere, "a dog", tiny_guidance, dataclasses.replace(config, iterations=5), callbacks,
         resume_from=checkpoint)
    assert [text.split(":")[0] for text in warnings] == ["iteration 1"]
    tensors, meta = load_edit_checkpoint(checkpoint)
    for damaged in (1, "true", None):
        save_tensors(tmp_path / "d.safetensors", tensors, kind=edit_module.EDIT_CHECKPOINT_KIND,
                     version=edit_module.EDIT_CHECKPOINT_VERSION, meta={**meta, "zeroed_said": damaged})
        with pytest.raises(FormatError, match=re.escape(f"damaged checkpoint: its zeroed_said is {damaged!r}, not")):
            edit(small_sphere, "a dog", tiny_guidance, dataclasses.replace(config, iterations=5),
                 resume_from=tmp_path / "d.safetensors")
    older = {name: value for name, value in meta.items() if name != "zeroed_said"}
    save_tensors(tmp_path / "o.safetensors", tensors, kind=edit_module.EDIT_CHECKPOINT_KIND,
                 version=edit_module.EDIT_CHECKPOINT_VERSION, meta=older)
    edit(small_sphere, "a dog", tiny_guidance, dataclasses.replace(config, iterations=5), callbacks,
         resume_from=tmp_path / "o.safetensors")
    assert [text.split(":")[0] for text in warnings] == ["iteration 1", "iteration 4"]


def test_a_guidance_that_never_overflows_warns_of_nothing(small_sphere, tiny_guidance):
    warnings = []
    edit(small_sphere, "a dog", tiny_guidance, EditConfig(iterations=2, render_size=16),
         Callbacks(on_warning=lambda stage, text: warnings.append(text)))
    assert warnings == []


def test_a_zero_iteration_edit_writes_a_checkpoint_with_zero_moments(small_sphere, tmp_path):
    """No step taken: Adam holds no moments yet, and the checkpoint still writes (two zero tensors, not one
    shared: safetensors refuses shared memory) beside the unchanged grid."""
    checkpoint = tmp_path / "c.safetensors"
    edited = edit(small_sphere, "a wooden dog", FakeGuidance(), EditConfig(iterations=0, render_size=SIZE),
                  checkpoint_path=checkpoint)
    assert torch.equal(edited.features, small_sphere.features)
    tensors, meta = load_edit_checkpoint(checkpoint)
    assert meta["iteration"] == 0 and int(tensors["adam_step"]) == 0
    assert not tensors["adam_exp_avg"].any() and not tensors["adam_exp_avg_sq"].any()


def test_a_run_that_takes_no_step_reports_one_progress_at_total_of_total(small_sphere, tmp_path):
    """An edit of 0 iterations, or one resumed at its last iteration (a worker redelivered after the last checkpoint),
    had reported no progress at all: the worker's row kept total 0. It reports once, at total of total."""
    def reports(config, **run):
        said = []
        edit(small_sphere, "a dog", FakeGuidance(), config, _collect(said), **run)
        return [(report.stage, report.iteration, report.total, report.losses) for report in said]

    checkpoint, config = tmp_path / "c.safetensors", EditConfig(iterations=2, render_size=SIZE)
    assert reports(dataclasses.replace(config, iterations=0)) == [("edit", 0, 0, {})]
    assert [report[1:3] for report in reports(config, checkpoint_path=checkpoint)] == [(1, 2), (2, 2)]
    assert reports(config, checkpoint_path=checkpoint, resume_from=checkpoint) == [("edit", 2, 2, {})]
    assert [report[1:3] for report in reports(dataclasses.replace(config, iterations=3), resume_from=checkpoint)] == [
        (3, 3)]


def test_a_run_that_takes_no_step_still_leaves_its_own_checkpoint_where_another_runs_was(small_sphere, tmp_path):
    """A file at checkpoint_path that is not the one resumed from is another run's: an edit of 0 iterations, one
    resumed where it had ended, or one cancelled before its first step had left it there (for a later --resume)."""
    config = EditConfig(iterations=2, render_size=SIZE)
    ours, other = tmp_path / "ours.safetensors", tmp_path / "other.safetensors"
    edit(small_sphere, "a dog", FakeGuidance(), config, checkpoint_path=ours)

    def check(meta, prompt, iteration):
        assert (meta["prompt"], meta["iteration"]) == (prompt, iteration)

    runs = [  # (config, resume_from, cancelled)
        (dataclasses.replace(config, iterations=0), None, False),
        (config, ours, False),
        (dataclasses.replace(config, iterations=5), ours, True),
    ]
    for run_config, resume, cancelled in runs:
        edit(small_sphere, "a cat", FakeGuidance(), dataclasses.replace(config, iterations=3), checkpoint_path=other)
        callbacks = Callbacks(should_cancel=lambda: cancelled)
        with pytest.raises(StageCancelled) if cancelled else contextlib.nullcontext():
            edit(small_sphere, "a dog", FakeGuidance(), run_config, callbacks, checkpoint_path=other, resume_from=resume)
        check(load_edit_checkpoint(other)[1], "a dog", 0 if resume is None else 2)
    # resumed in place and ending at once: the file is already where the run stands, and stays as it is
    written = []
    edit(small_sphere, "a dog", FakeGuidance(), config, Callbacks(on_checkpoint=written.append),
         checkpoint_path=ours, resume_from=ours)
    assert written == []


def test_resume_refuses_another_prompt_or_grid(small_sphere, make_sphere_grid, tiny_guidance, tmp_path):
    """A checkpoint the run cannot go on from is a FormatError (the worker then starts the stage over, as it does a
    reconstruction's); asking for fewer iterations than it holds is the request's own ValueError."""
    from voxe_core.tensorio import FormatError

    checkpoint = tmp_path / "c.safetensors"
    config = EditConfig(iterations=1, render_size=SIZE)
    edit(small_sphere, "a dog", tiny_guidance, config, checkpoint_path=checkpoint)
    with pytest.raises(FormatError, match="prompt"):
        edit(small_sphere, "a cat", tiny_guidance, config, resume_from=checkpoint)
    with pytest.raises(FormatError, match="initial grid"):
        edit(make_sphere_grid(20, radius=0.6), "a dog", tiny_guidance, config, resume_from=checkpoint)
    # another recipe (had resumed silently, mixing two runs); a longer run on the same recipe is a resume
    other = dataclasses.replace(config, guidance_scale=50.0, schedule=TimestepSchedule(i_start=10))
    with pytest.raises(FormatError, match=r"another recipe: guidance_scale 100\.0 \(now 50\.0\), schedule \{"):
        edit(small_sphere, "a dog", tiny_guidance, other, resume_from=checkpoint)
    with pytest.raises(ValueError, match="checkpoint is at iteration 1, past the 0 iterations asked for") as refused:
        edit(small_sphere, "a dog", tiny_guidance, dataclasses.replace(config, iterations=0), resume_from=checkpoint)
    assert not isinstance(refused.value, FormatError)
    longer = dataclasses.replace(config, iterations=2,  # and another device's pass size
                                 render=dataclasses.replace(config.render, samples_per_pass=1 << 16))
    edit(small_sphere, "a dog", tiny_guidance, longer, resume_from=checkpoint)


def test_resume_refuses_an_initial_grid_of_the_same_features_that_renders_otherwise(small_sphere, tmp_path):
    """The fingerprint of G_i hashes its features alone: a G_i of the same features in another box, or with another
    activation or density scale (it renders another object), had been resumed against silently, the run going on
    from a G_e of one grid under the regulariser of the other. Refused, naming what differs; a checkpoint of the
    fingerprint's old form (written before these were compared) still resumes where nothing else differs."""
    from voxe_core.tensorio import FormatError

    checkpoint, config = tmp_path / "c.safetensors", EditConfig(iterations=1, render_size=SIZE)
    edit(small_sphere, "a dog", FakeGuidance(), config, checkpoint_path=checkpoint)
    features = small_sphere.features.detach().clone()
    low, high = (corner.tolist() for corner in (small_sphere.bbox_min, small_sphere.bbox_max))
    others = [
        (VoxelGrid(20, [1.25 * v for v in low], [1.25 * v for v in high], features=features.clone(),
                   density_scale=small_sphere.density_scale),
         f"box {[1.25 * v for v in low]} to {[1.25 * v for v in high]} (the checkpoint's {low} to {high})"),
        (VoxelGrid(20, low, high, "softplus", small_sphere.density_scale, features=features.clone()),
         "activation 'softplus' (the checkpoint's 'relu')"),
        (VoxelGrid(20, low, high, density_scale=small_sphere.density_scale * 2, features=features.clone()),
         f"density_scale {small_sphere.density_scale * 2} (the checkpoint's {small_sphere.density_scale})"),
    ]
    longer = dataclasses.replace(config, iterations=2)
    for other, differs in others:
        assert edit_module.initial_fingerprint(other) == edit_module.initial_fingerprint(small_sphere)
        with pytest.raises(FormatError, match=re.escape(f"{checkpoint}: checkpoint was made from an initial grid of "
                                                        f"the same features that renders otherwise: its {differs}")):
            edit(other, "a dog", FakeGuidance(), longer, resume_from=checkpoint)
    same = VoxelGrid(20, low, high, density_scale=small_sphere.density_scale, features=features.clone())
    resumed = edit(same, "a dog", FakeGuidance(), longer, resume_from=checkpoint)
    assert torch.equal(resumed.features, edit(small_sphere, "a dog", FakeGuidance(), longer).features)


@pytest.mark.parametrize("field, value, message", [
    ("resolution", 5, "checkpoint grid is 5, the initial grid (20, 20, 20)"),
    ("resolution", [20, 20], "checkpoint grid is (20, 20), the initial grid (20, 20, 20)"),
    ("iteration", None, "damaged checkpoint: its iteration is None, not a count of steps"),
    ("iteration", "1", "damaged checkpoint: its iteration is '1', not a count of steps"),
    ("iteration", -1, "damaged checkpoint: its iteration is -1, not a count of steps"),
])
def test_a_checkpoint_whose_header_is_damaged_is_refused_as_a_format_error(field, value, message, small_sphere,
                                                                           tmp_path):
    """check_resume reads the header (before any model is loaded): a damaged one is a FormatError the worker starts
    the stage over from, not a TypeError failing the job."""
    from voxe_core.edit import EDIT_CHECKPOINT_KIND, EDIT_CHECKPOINT_VERSION, check_resume
    from voxe_core.tensorio import FormatError, save_tensors

    checkpoint = tmp_path / "c.safetensors"
    config = EditConfig(iterations=1, render_size=SIZE)
    edit(small_sphere, "a dog", FakeGuidance(), config, checkpoint_path=checkpoint)
    tensors, meta = load_edit_checkpoint(checkpoint)
    save_tensors(checkpoint, tensors, EDIT_CHECKPOINT_KIND, EDIT_CHECKPOINT_VERSION, {**meta, field: value})
    with pytest.raises(FormatError, match=f"^{re.escape(f'{checkpoint}: {message}')}"):
        check_resume(checkpoint, small_sphere, "a dog", dataclasses.replace(config, iterations=2), "")
    with pytest.raises(FormatError, match=re.escape(message)):
        edit(small_sphere, "a dog", FakeGuidance(), dataclasses.replace(config, iterations=2), resume_from=checkpoint)


@pytest.mark.parametrize("name, value", [("features", math.nan), ("adam_exp_avg", math.nan),
                                         ("adam_exp_avg_sq", math.nan), ("features", math.inf),
                                         ("adam_exp_avg", -math.inf), ("adam_exp_avg_sq", -math.inf)])
def test_a_checkpoint_holding_a_nan_is_refused_as_one_to_start_afresh_from(name, value, small_sphere, tmp_path):
    """One saved NaN (before G_e's finiteness was checked) had diverged at its first step on every resume, blamed on
    half precision: a FormatError is what the worker starts a stage over from."""
    from voxe_core.edit import EDIT_CHECKPOINT_KIND, EDIT_CHECKPOINT_VERSION
    from voxe_core.tensorio import FormatError, save_tensors

    checkpoint = tmp_path / "c.safetensors"
    edit(small_sphere, "a dog", FakeGuidance(), EditConfig(iterations=1, render_size=SIZE), checkpoint_path=checkpoint)
    tensors, meta = load_edit_checkpoint(checkpoint)
    tensors[name].view(-1)[7] = value
    save_tensors(checkpoint, tensors, EDIT_CHECKPOINT_KIND, EDIT_CHECKPOINT_VERSION, meta)
    with pytest.raises(FormatError, match=rf"checkpoint holds {name} no run leaves \(NaN or infinite features or first "
                                          r"Adam moments, NaN or negative second moments\): saved by a run that had "
                                          r"diverged, or damaged; start afresh"):
        edit(small_sphere, "a dog", FakeGuidance(), EditConfig(iterations=2, render_size=SIZE), resume_from=checkpoint)


@pytest.mark.parametrize("damage, message", [
    ("rng_host", "its rng_host holds nothing, not a generator state"),
    ("rng_device", "its rng_device holds nothing, not a generator state"),
    ("adam_exp_avg", "its adam_exp_avg holds nothing, not shape (8000, 4)"),
    ("adam_step", "its adam_step holds nothing, not shape (1,)"),
    ("features", "its features holds nothing, not shape (20, 20, 20, 4)"),
    (("adam_exp_avg_sq", (7999, 4), torch.float32), "its adam_exp_avg_sq holds shape (7999, 4), not shape (8000, 4)"),
    (("features", (20, 20, 20, 3), torch.float32), "its features holds shape (20, 20, 20, 3), not shape (20, 20, 20, 4)"),
    (("rng_host", (16,), torch.uint8), "its rng_host is no generator state this run can take ("),
    (("adam_step", (2,), torch.float64), "its adam_step holds shape (2,), not shape (1,)"),
])
def test_a_checkpoint_whose_tensors_are_damaged_is_refused_as_a_format_error(damage, message, small_sphere, tmp_path):
    """A checkpoint whose header is intact but a tensor is missing or of the wrong shape had raised a KeyError or a
    RuntimeError (at the load, or at the first step's Adam), which the worker fails the job on: a FormatError, naming
    what is wrong, is what it starts the stage over from, as from an unreadable checkpoint."""
    from voxe_core.edit import EDIT_CHECKPOINT_KIND, EDIT_CHECKPOINT_VERSION
    from voxe_core.tensorio import FormatError, save_tensors

    checkpoint = tmp_path / "c.safetensors"
    edit(small_sphere, "a dog", FakeGuidance(), EditConfig(iterations=1, render_size=SIZE), checkpoint_path=checkpoint)
    tensors, meta = load_edit_checkpoint(checkpoint)
    # (the damage's shape and dtype, not a tensor, in its parameters: one made at collection stays alive through the
    # whole run, where other tests count the tensors alive)
    name, *made = damage if isinstance(damage, tuple) else (damage,)
    if made:
        tensors[name] = torch.zeros(made[0], dtype=made[1])
    else:
        del tensors[name]
    save_tensors(checkpoint, tensors, EDIT_CHECKPOINT_KIND, EDIT_CHECKPOINT_VERSION, meta)
    with pytest.raises(FormatError, match=f"^{re.escape(f'{checkpoint}: damaged checkpoint: {message}')}"):
        edit(small_sphere, "a dog", FakeGuidance(), EditConfig(iterations=2, render_size=SIZE), resume_from=checkpoint)


class HugeGradientGuidance(FakeGuidance):
    """Its first SDS loss is finite with a gradient finite but past float32's square root: Adam's second moment
    overflows to +inf there and those vertices stand still, the grid finite."""

    def sds_loss(self, images, text_embeddings, timesteps, guidance_scale=100.0, generator=None):
        loss, diagnostics = super().sds_loss(images, text_embeddings, timesteps, guidance_scale, generator)
        return (images.sum() * 1e30 if len(self.calls) == 1 else loss), diagnostics


def test_a_checkpoint_whose_second_adam_moment_overflowed_resumes_as_the_run_goes_on(small_sphere, tmp_path):
    """The run goes on from a +inf second moment (Adam tolerates it) and saved it, but its own resume had refused the
    checkpoint as diverged: the worker started the stage over. Resumed, it ends as the uninterrupted run."""
    checkpoint, config = tmp_path / "c.safetensors", EditConfig(iterations=3, render_size=SIZE)
    uninterrupted = edit(small_sphere, "a dog", HugeGradientGuidance(), config)
    edit(small_sphere, "a dog", HugeGradientGuidance(), dataclasses.replace(config, iterations=2),
         checkpoint_path=checkpoint)
    tensors, _ = load_edit_checkpoint(checkpoint)
    assert tensors["adam_exp_avg_sq"].isinf().any() and tensors["features"].isfinite().all()
    resumed = edit(small_sphere, "a dog", FakeGuidance(), config, resume_from=checkpoint)  # past the huge step
    assert torch.equal(resumed.features, uninterrupted.features) and resumed.features.isfinite().all()


def test_resume_refuses_another_model_by_its_name_as_asked_for(small_sphere, tmp_path):
    """The checkpoint had recorded the model and resumed under any other, mixing two models' edits. An older worker's
    checkpoint, which recorded the folder its "tiny" resolved to, is refused as clearly."""
    from voxe_core.edit import EDIT_CHECKPOINT_KIND, EDIT_CHECKPOINT_VERSION
    from voxe_core.tensorio import FormatError, save_tensors

    checkpoint = tmp_path / "c.safetensors"
    config = EditConfig(iterations=1, render_size=SIZE)
    edit(small_sphere, "a dog", named_guidance("org/model-a"), config, checkpoint_path=checkpoint)
    longer = dataclasses.replace(config, iterations=2)
    with pytest.raises(FormatError, match="checkpoint was made with the model 'org/model-a', not 'org/model-b'"):
        edit(small_sphere, "a dog", named_guidance("org/model-b"), longer, resume_from=checkpoint)
    edit(small_sphere, "a dog", named_guidance("org/model-a"), longer, resume_from=checkpoint)

    older = tmp_path / "older.safetensors"
    tensors, meta = load_edit_checkpoint(checkpoint)
    save_tensors(older, tensors, EDIT_CHECKPOINT_KIND, EDIT_CHECKPOINT_VERSION,
                 {**meta, "model": "/var/voxe/models/tiny-stable-diffusion"})
    with pytest.raises(FormatError, match="made with the model '/var/voxe/models/tiny-stable-diffusion', not 'tiny'"):
        edit(small_sphere, "a dog", named_guidance("tiny"), longer, resume_from=older)


def test_a_guidance_loaded_from_a_folder_carries_the_name_it_was_asked_for(tiny_sd_path):
    """The worker resolves "tiny" to a folder of its own machine; the name an edit checkpoint records is "tiny"."""
    assert StableDiffusionGuidance.from_pretrained(str(tiny_sd_path), device="cpu", local_files_only=True,
                                                   name="tiny").model_id == "tiny"


def test_a_revision_is_in_the_name_of_a_hub_model_only(tiny_sd_path, monkeypatch):
    """A folder has no revisions (loading ignores one there): its name had become '<folder>@main', which a checkpoint
    made without the revision then did not match."""
    from voxe_core.guidance import sds

    assert StableDiffusionGuidance.from_pretrained(str(tiny_sd_path), device="cpu", local_files_only=True,
                                                   revision="main").model_id == str(tiny_sd_path)
    load = sds.load_stable_diffusion
    monkeypatch.setattr(sds, "load_stable_diffusion", lambda model, *args: load(str(tiny_sd_path), *args))
    assert StableDiffusionGuidance.from_pretrained("org/model", device="cpu", local_files_only=True,
                                                   revision="v2").model_id == "org/model@v2"


def test_resume_accepts_a_checkpoint_older_than_the_revision_in_the_model_name(small_sphere, tmp_path):
    """A checkpoint recorded "org/model" before the name carried "@revision": it resumes under "org/model@v2". One of
    another model is still refused, and so is a folder's checkpoint under a folder of that name with "@v2" appended
    (a folder's name carries no revision)."""
    from voxe_core.tensorio import FormatError

    config = EditConfig(iterations=1, render_size=SIZE)
    longer = dataclasses.replace(config, iterations=2)
    folder = tmp_path / "model"
    folder.mkdir()
    checkpoints = {recorded: tmp_path / f"{n}.safetensors" for n, recorded in enumerate(("org/model", str(folder)))}
    for recorded, refused in (("org/model", ("org/other@v2", "org/model-v2")), (str(folder), (f"{folder}@v2",))):
        edit(small_sphere, "a dog", named_guidance(recorded), config, checkpoint_path=checkpoints[recorded])
        for model_id in refused:
            with pytest.raises(FormatError, match=f"model '{re.escape(recorded)}', not '{re.escape(model_id)}'"):
                edit(small_sphere, "a dog", named_guidance(model_id), longer, resume_from=checkpoints[recorded])
    resumed = edit(small_sphere, "a dog", named_guidance("org/model@v2"), longer, resume_from=checkpoints["org/model"])
    assert torch.equal(resumed.features, edit(small_sphere, "a dog", named_guidance("org/model"), longer).features)


def test_bf16_autocast_on_cpu_runs(small_sphere, tiny_guidance):
    reports = []
    out = edit(small_sphere, "a dog", tiny_guidance, EditConfig(iterations=2, render_size=SIZE, autocast_dtype="bf16"),
               _collect(reports))
    assert out.features.dtype == torch.float32 and torch.isfinite(out.features).all()
    assert not torch.equal(out.features, small_sphere.features)
    assert all(torch.isfinite(torch.tensor(r.losses["total"])) for r in reports)


# ------------------------------------------------------------------ the loop with a recording guidance


def test_fp16_autocast_run_as_bfloat16_on_the_cpu_is_said_once_through_the_callbacks(small_sphere):
    """The note that fp16 autocast runs as bfloat16 on the CPU was a Python warning every step, which never reaches a
    job's user: it goes through the callbacks' warning once, before the first step (a Python warning only where no
    on_warning is given, as every stage's warning)."""
    import warnings

    config = EditConfig(iterations=3, render_size=16, autocast_dtype="fp16", regulariser_weight=0.0)
    said = "fp16 autocast is not used on the CPU; the guidance runs under bfloat16 autocast"
    reports = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        edit(small_sphere, "a dog", FakeGuidance(), config, Callbacks(
            on_progress=lambda report: reports.append("progress"),
            on_warning=lambda stage, text: reports.append((stage, text))))
    assert reports == [("edit", said)] + ["progress"] * 3 and caught == []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        edit(small_sphere, "a dog", FakeGuidance(), config)
    assert [str(warning.message) for warning in caught] == [f"edit: {said}"]


def test_autocast_on_the_cpu_with_a_float16_model_is_refused_before_any_step(small_sphere, tiny_sd_path):
    """CPU autocast is bfloat16, and a float16 model's GroupNorm failed in it at the first step with torch's "mixed
    dtype (CPU)"; without autocast the float16 model runs (tests/test_hard_cases.py), as a bfloat16 one does with."""
    half = StableDiffusionGuidance.from_pretrained(str(tiny_sd_path), device="cpu", dtype=torch.float16,
                                                   local_files_only=True)
    reports = []
    for autocast in ("bf16", "fp16"):
        with pytest.raises(ValueError, match=r"^autocast on the CPU runs under bfloat16, where a float16 model fails .*"
                                             r"float32 \(from_pretrained's default on the CPU\) or bfloat16, or leave "
                                             r"autocast_dtype None$"):
            edit(small_sphere, "a dog", half, EditConfig(iterations=1, render_size=SIZE, autocast_dtype=autocast),
                 _collect(reports))
    assert reports == []
    edit(small_sphere, "a dog", half, EditConfig(iterations=1, render_size=SIZE), _collect(reports))
    assert len(reports) == 1


def test_fake_guidance_satisfies_the_protocol():
    assert isinstance(FakeGuidance(), Guidance)


class SlowBackward(torch.autograd.Function):
    """Identity whose backward takes 50 ms: a stand-in for the VAE encoder's backward."""

    @staticmethod
    def forward(ctx, images):
        return images.clone()

    @staticmethod
    def backward(ctx, grad):
        time.sleep(0.05)
        return grad


class SlowEncoderGuidance(FakeGuidance):
    def sds_loss(self, images, text_embeddings, timesteps, guidance_scale=100.0, generator=None):
        return SlowBackward.apply(images).mean(), {}


def test_the_backward_time_is_split_where_the_gradient_reaches_the_renders(small_sphere):
    """A slow encoder backward lands on the guidance's side (so would the regulariser's, built after the SDS loss:
    autograd runs it first); the rest is the renders'."""
    reports = []
    edit(small_sphere, "a dog", SlowEncoderGuidance(), EditConfig(iterations=2, render_size=16, sync_timing=True),
         _collect(reports))
    assert len(reports) == 2  # one per iteration: the loop below checks each
    for report in reports:
        info = report.info
        assert info["ms_backward_guidance"] >= 50 > info["ms_backward_render"] > 0
        assert info["ms_backward_guidance"] + info["ms_backward_render"] == pytest.approx(info["ms_backward"])


def test_renders_of_empty_space_edit_with_no_backward_time_on_the_guidance():
    """Rays that meet no occupied cell render the background: no gradient reaches the renders, only the regulariser's
    reaches the grid, and the guidance's share of the backward is nothing. (A grid with no density is refused: its box
    here lies far below every pose, which looks at the origin from near the horizon.)"""
    reports = []
    unseen = VoxelGrid(8, (-0.5, -0.5, -20.0), (0.5, 0.5, -19.0), init_density=1.0)
    edited = edit(unseen, "a dog", SlowEncoderGuidance(), EditConfig(iterations=1, render_size=16, sync_timing=True,
                                                                     min_zenith_deg=80.0), _collect(reports))
    (info,) = [r.info for r in reports]
    assert info["samples_per_ray"] == 0 and info["ms_backward_guidance"] == 0
    assert info["ms_backward_render"] == pytest.approx(info["ms_backward"])
    assert torch.isfinite(edited.features).all()
    # an image regulariser's rays meet nothing either: no gradient at all, where the backward had raised a
    # RuntimeError ("element 0 of tensors does not require grad"), a traceback out of voxe edit and a job's error
    cameras = Cameras.from_fov(spherical_poses(torch.tensor([30.0]), torch.tensor([0.0])), 0.6911, 8, 8)
    config = EditConfig(iterations=2, render_size=16, regulariser="image_l2", min_zenith_deg=80.0)
    edited = edit(unseen, "a dog", SlowEncoderGuidance(), config, input_views=(torch.ones(1, 8, 8, 3), cameras))
    assert torch.equal(edited.features, unseen.features)


def test_a_scene_grids_skip_density_is_built_once_per_edit_and_every_step_skips_as_rebuilding_it_would(monkeypatch):
    """A scene grid's per-cell skip density comes of its lattice, activation and scale, never of the features the
    edit optimises: built once per edit (each step had rebuilt it), every step's occupancy is still the one its
    current features give (``grid.occupancy``), so renders and losses are those of rebuilding it each step, bit for
    bit. The occupancy changes from step to step here, and the threshold is not the default: an occupancy kept
    from an earlier step, or a skip density built for another threshold, would differ."""
    threshold = 3e-3
    initial = SceneGrid(12, activation="softplus")
    raw_at_threshold = math.log(math.expm1(threshold)) / initial.density_scale
    with torch.no_grad():  # density e times more per vertex along x, the threshold's in the middle
        initial.features[..., 0] = raw_at_threshold + (torch.arange(12.0) - 5.5)[:, None, None] / initial.density_scale
    config = EditConfig(iterations=4, render_size=16, render=RenderConfig(step_ratio=0.6, sigma_threshold=threshold))
    unwrapped = SceneGrid.skip_density
    built = []
    monkeypatch.setattr(SceneGrid, "skip_density", lambda grid, sigma: built.append(sigma) or unwrapped(grid, sigma))

    def run(rebuilt_each_step: bool):
        steps = []

        def rendering(grid, origins, directions, render_config, occupancy, generator):
            rebuilt = grid.occupancy_above(unwrapped(grid, render_config.sigma_threshold))  # grid.occupancy, uncounted
            steps.append((occupancy, rebuilt))
            return render_rays(grid, origins, directions, render_config, rebuilt if rebuilt_each_step else occupancy,
                               generator)

        monkeypatch.setattr(edit_module, "render_rays", rendering)
        built.clear()
        reports = []
        edited = edit(initial, "a dog", FakeGuidance(), config, _collect(reports))
        return edited, [r.losses for r in reports], steps, list(built)

    edited, losses, steps, built_once = run(rebuilt_each_step=False)
    assert built_once == [threshold]
    for occupancy, rebuilt in steps:
        assert torch.equal(occupancy.cells, rebuilt.cells)
        assert torch.equal(occupancy.bbox_min, rebuilt.bbox_min) and torch.equal(occupancy.bbox_max, rebuilt.bbox_max)
    assert not torch.equal(steps[0][1].cells, steps[-1][1].cells)  # the edit moves cells across the threshold
    reference, reference_losses, _, _ = run(rebuilt_each_step=True)
    assert losses == reference_losses and torch.equal(edited.features, reference.features)


def test_cancellation_stops_within_one_iteration(small_sphere):
    reports = []
    callbacks = Callbacks(on_progress=reports.append, should_cancel=lambda: len(reports) >= 1)
    with pytest.raises(StageCancelled, match="edit"):
        edit(small_sphere, "a dog", FakeGuidance(), EditConfig(iterations=50, render_size=16), callbacks)
    assert len(reports) == 1


def test_a_prompt_too_long_with_a_view_word_fails_before_the_first_step(small_sphere, tiny_guidance):
    """Each view's prompt is encoded before the loop: one the text encoder cannot read whole fails the edit at
    once, not at the first step that draws that view."""
    words = ["zebra"]
    while len(tiny_guidance.tokenizer(build_prompt(" ".join(words + ["zebra"]), None)).input_ids) <= 77:
        words.append("zebra")
    prompt = " ".join(words)  # fits without a view word, not with one
    reports, previews = [], []
    with pytest.raises(ValueError, match=r" view' is 7\d tokens; the text encoder .* reads 77"):
        edit(small_sphere, prompt, tiny_guidance, EditConfig(iterations=3, render_size=16, preview_every=1),
             _collect(reports), on_preview=lambda done, image: previews.append(done))
    assert not [r for r in reports if r.stage == "edit"] and previews == []  # not even iteration 0's preview


def test_errors_empty_prompt_and_image_regulariser_without_views(small_sphere):
    with pytest.raises(ValueError, match="empty"):
        edit(small_sphere, "  ", FakeGuidance(), EditConfig(iterations=1, render_size=16))
    for kind in ("image_l1", "image_l2"):
        with pytest.raises(ValueError, match="input_views"):
            edit(small_sphere, "a dog", FakeGuidance(), EditConfig(iterations=1, render_size=16, regulariser=kind))


@pytest.mark.parametrize("kind", ["reg3d", "reg3d_plus", "volumetric_l1", "volumetric_l2"])
def test_input_views_under_a_volumetric_regulariser_are_refused_naming_them(small_sphere, kind):
    """Regression: they had been taken and ignored (the edit ran as without them), where a caller passing them meant
    the edit to keep to the images; voxe edit refuses --data there."""
    cameras = Cameras.from_fov(spherical_poses(torch.tensor([30.0]), torch.tensor([0.0])), 0.6911, 8, 8)
    reports = []
    with pytest.raises(ValueError, match=rf"^input_views are read by the image_l1 / image_l2 regularisers only; the "
                                         rf"'{kind}' regulariser compares G_e with G_i"):
        edit(small_sphere, "a dog", FakeGuidance(), EditConfig(iterations=1, render_size=16, regulariser=kind),
             _collect(reports), input_views=(torch.ones(1, 8, 8, 3), cameras))
    assert reports == []


def test_reg3d_is_zero_for_identical_grids_then_grows(small_sphere):
    """The loss is SDS + regulariser_weight · L_reg3D: checked where L_reg3D has grown (at its start, 0, any weight
    gives the same total)."""
    reports = []
    edit(small_sphere, "a dog", FakeGuidance(), EditConfig(iterations=4, render_size=16), _collect(reports))
    assert abs(reports[0].losses["reg"]) < 1e-6
    assert reports[0].losses["total"] == pytest.approx(reports[0].losses["sds"] + 200 * reports[0].losses["reg"])
    # unopposed (weight 0) and with big steps, the fake SDS changes G_e's density and L_reg3D sees it
    for weight in (0.0, 3.0):
        free = []
        edit(small_sphere, "a dog", FakeGuidance(),
             EditConfig(iterations=4, render_size=16, lr=2.0, regulariser_weight=weight), _collect(free))
        losses = free[-1].losses
        assert losses["reg"] > 1e-4
        assert losses["total"] == pytest.approx(losses["sds"] + weight * losses["reg"], rel=1e-6, abs=1e-7)


def test_a_regulariser_a_constant_initial_grid_switches_off_is_said_before_the_first_step(small_sphere):
    """A constant G_i density (an empty or unfitted grid) makes L_reg3D a constant 1 with no gradient: the edit had
    run unregularised, its reg of 1.0 reading as a very poor correlation, saying nothing. The callbacks' warning says
    so, once, before the first step's report; as it does for reg3d_plus's colour channels that are constant (the
    sphere is one red), and for nothing where the regulariser has something to correlate or its weight is 0."""
    def run(grid, **config):
        said = []
        callbacks = Callbacks(on_progress=lambda report: said.append(("progress", report.losses["reg"])),
                              on_warning=lambda stage, text: said.append((stage, text)))
        edit(grid, "a dog", FakeGuidance(), EditConfig(iterations=2, render_size=16, **config), callbacks)
        return said

    unfitted = VoxelGrid(12)  # density 0.01 in every voxel, colour 0
    off = ("the reconstruction's density is constant: the 3D regulariser (reg3d) has nothing to correlate and is off; "
           "the edit runs unregularised, its reg a constant 1.0 (an empty or unfitted reconstruction?)")
    assert run(unfitted) == [("edit", off), ("progress", 1.0), ("progress", 1.0)]
    assert run(unfitted, regulariser="reg3d_plus")[:2] == [
        ("edit", "the reconstruction's density and its red, green and blue colour channels are constant: the 3D "
                 "regulariser (reg3d_plus) has nothing to correlate and is off; the edit runs unregularised, its reg "
                 "a constant 2.0 (an empty or unfitted reconstruction?)"), ("progress", 2.0)]
    assert run(small_sphere, regulariser="reg3d_plus")[0] == (
        "edit", "the reconstruction's red, green and blue colour channels are constant: the 3D regulariser "
                "(reg3d_plus) has nothing to correlate on them: its terms for them are off, adding a constant 1 to "
                "its reg with no gradient (its reg: the density term plus the mean of the red, green and blue terms)")
    one_colour = small_sphere.clone_grid()
    with torch.no_grad():
        one_colour.features[..., 0] = 3.0
        one_colour.features[..., 1] = torch.linspace(-1.0, 1.0, one_colour.features[..., 1].numel()).reshape(
            one_colour.features.shape[:3])
    assert run(one_colour, regulariser="reg3d_plus")[0] == (
        "edit", "the reconstruction's density and its green and blue colour channels are constant: the 3D "
                "regulariser (reg3d_plus) has nothing to correlate on them: its terms for them are off, adding a "
                "constant 5/3 to its reg with no gradient (its reg: the density term plus the mean of the red, green "
                "and blue terms)")
    for grid, config in [(small_sphere, {}), (unfitted, {"regulariser_weight": 0.0}),
                         (unfitted, {"regulariser": "volumetric_l2"})]:
        assert [kind for kind, _ in run(grid, **config)] == ["progress", "progress"], config
    with pytest.warns(UserWarning, match=re.escape(f"edit: {off}")):  # no on_warning: a Python warning says it
        edit(unfitted, "a dog", FakeGuidance(), EditConfig(iterations=1, render_size=16))


def test_a_regulariser_switched_off_is_said_once_across_a_resume(tmp_path):
    """Said again at every resume, each redelivery of a job had added a duplicate warning event: whether it was said
    is carried in the checkpoint, as the zeroed SDS gradient's warning is; a damaged value is a FormatError, a
    checkpoint older than the field says it as before."""
    from voxe_core.tensorio import FormatError, save_tensors

    unfitted, warnings = VoxelGrid(12), []  # a constant density: L_reg3D off
    callbacks = Callbacks(on_warning=lambda stage, text: warnings.append(text))
    checkpoint, config = tmp_path / "c.safetensors", EditConfig(iterations=1, render_size=16)
    edit(unfitted, "a dog", FakeGuidance(), config, callbacks, checkpoint_path=checkpoint)
    for iterations in (2, 3):  # two redeliveries, each resuming from the checkpoint the last one wrote
        edit(unfitted, "a dog", FakeGuidance(), dataclasses.replace(config, iterations=iterations), callbacks,
             checkpoint_path=checkpoint, resume_from=checkpoint)
    assert len(warnings) == 1 and warnings[0].startswith("the reconstruction's density is constant")
    assert load_edit_checkpoint(checkpoint)[1]["regulariser_off_said"] is True
    tensors, meta = load_edit_checkpoint(checkpoint)
    save_tensors(tmp_path / "d.safetensors", tensors, kind=edit_module.EDIT_CHECKPOINT_KIND,
                 version=edit_module.EDIT_CHECKPOINT_VERSION, meta={**meta, "regulariser_off_said": "yes"})
    with pytest.raises(FormatError, match=re.escape("damaged checkpoint: its regulariser_off_said is 'yes', not true "
                                                    "or false")):
        edit(unfitted, "a dog", FakeGuidance(), dataclasses.replace(config, iterations=4),
             resume_from=tmp_path / "d.safetensors")
    older = {name: value for name, value in meta.items() if name != "regulariser_off_said"}
    save_tensors(tmp_path / "o.safetensors", tensors, kind=edit_module.EDIT_CHECKPOINT_KIND,
                 version=edit_module.EDIT_CHECKPOINT_VERSION, meta=older)
    edit(unfitted, "a dog", FakeGuidance(), dataclasses.replace(config, iterations=4), callbacks,
         resume_from=tmp_path / "o.safetensors")
    assert len(warnings) == 2 and warnings[1] == warnings[0]


def test_an_initial_grid_with_no_density_its_renders_sample_is_refused_before_the_first_step():
    """Through a transparent volume (a ReLU field with no positive density, or none above the skip threshold) the
    SDS gradient is 0: the edit had run every iteration and returned the grid it was given. It is refused at once."""
    empty = VoxelGrid(12, init_density=-1.0)
    faint = VoxelGrid(12, init_density=1e-6)  # positive, below the render's sigma_threshold: every cell skipped
    for grid in (empty, faint):
        reports = []
        with pytest.raises(ValueError, match="the initial grid has no density the edit's renders sample"):
            edit(grid, "a dog", FakeGuidance(), EditConfig(iterations=3, render_size=16), _collect(reports))
        assert reports == []
    reports = []  # rendering every cell, the faint density is seen: the edit runs
    every_cell = RenderConfig(step_ratio=0.6, skip_empty=False)
    edit(faint, "a dog", FakeGuidance(), EditConfig(iterations=1, render_size=16, regulariser_weight=0.0,
                                                     render=every_cell), _collect(reports))
    assert len(reports) == 1


def test_the_partly_constant_reg3d_plus_warning_states_what_its_constant_terms_add_to_the_reg():
    """reg3d_plus's reg is the density term plus the MEAN of the three colour terms, so a constant colour channel's
    term (a constant 1) adds 1/3 to it, not 1 as the warning had said ("1 per term in its reg"). For each set of
    constant channels that leaves something to correlate, the constant the warning states is the reg of G_i against
    itself (where the varying channels' terms are 0)."""
    from fractions import Fraction
    from itertools import combinations

    from voxe_core.edit import regulariser_off
    from voxe_core.losses import volumetric_regulariser

    config = EditConfig(regulariser="reg3d_plus")
    for count in (1, 2, 3):
        for constant in combinations(range(4), count):
            grid = VoxelGrid(6)
            with torch.no_grad():
                for channel in range(4):
                    grid.features[..., channel] = 0.5 if channel in constant else torch.randn(6, 6, 6)
            said = regulariser_off(grid, config)
            stated = re.search(r"adding a constant (\S+) to its reg", said or "")
            assert stated, (constant, said)
            reg = float(volumetric_regulariser("reg3d_plus", grid.features)(grid.features))
            assert float(Fraction(stated.group(1))) == pytest.approx(reg, abs=1e-5), (constant, said, reg)


def test_image_regulariser_against_the_grids_own_renders_is_small(small_sphere):
    cameras = Cameras.from_fov(spherical_poses(torch.tensor([30.0, 10.0]), torch.tensor([0.0, 120.0])), 0.6911, 24, 24)
    images = render_views(small_sphere, cameras, EditConfig().render)
    reports = []
    config = EditConfig(iterations=1, render_size=16, regulariser="image_l1", image_regulariser_rays=512)
    edit(small_sphere, "a dog", FakeGuidance(), config, _collect(reports), input_views=(images, cameras))
    # same grid, jittered vs midpoint samples: a few hundredths at most
    assert 0.0 <= reports[0].losses["reg"] < 0.03
    far = (torch.zeros_like(images), cameras)  # black targets: the red-on-white render is far from them
    edit(small_sphere, "a dog", FakeGuidance(), config, _collect(reports), input_views=far)
    assert reports[-1].losses["reg"] > 0.3


def test_an_image_regularised_edit_resumes_only_against_the_input_views_it_was_made_with(small_sphere, tmp_path):
    """Another --data (other images or cameras) had gone on from the checkpoint silently, mixing two runs."""
    from voxe_core.tensorio import FormatError

    cameras = Cameras.from_fov(spherical_poses(torch.tensor([30.0, 10.0]), torch.tensor([0.0, 120.0])), 0.6911, 24, 24)
    images = render_views(small_sphere, cameras, EditConfig().render)
    config = EditConfig(iterations=1, render_size=16, regulariser="image_l1", image_regulariser_rays=512)
    checkpoint = tmp_path / "c.safetensors"
    edit(small_sphere, "a dog", FakeGuidance(), config, checkpoint_path=checkpoint, input_views=(images, cameras))
    longer = dataclasses.replace(config, iterations=2)
    turned = Cameras.from_fov(spherical_poses(torch.tensor([30.0, 10.0]), torch.tensor([0.0, 150.0])), 0.6911, 24, 24)
    for views in ((torch.zeros_like(images), cameras), (images, turned), (images[:1], cameras[:1])):
        with pytest.raises(FormatError, match="checkpoint was made against other input views"):
            edit(small_sphere, "a dog", FakeGuidance(), longer, resume_from=checkpoint, input_views=views)
    edit(small_sphere, "a dog", FakeGuidance(), longer, resume_from=checkpoint, input_views=(images, cameras))


def test_view_word_follows_the_pose(small_sphere, monkeypatch):
    # (elevation, azimuth) -> expected word; the front is the camera on -y (azimuth 270°, the authors' convention)
    script = [(20.0, 270.0, "front"), (20.0, 0.0, "side"), (20.0, 90.0, "back"), (10.0, 180.0, "side"),
              (70.0, 123.0, "overhead"), (30.0, 300.0, "front")]
    poses = iter(script)

    def scripted(n, generator=None, radius=4.0311, min_zenith_deg=15.0, max_zenith_deg=90.0, centre=None):
        e, a, _ = next(poses)
        el, az = torch.tensor([e]), torch.tensor([a])
        torch.rand(2, generator=generator)  # keep the generator moving as the real draw does
        return spherical_poses(el, az, radius, centre), el, az

    monkeypatch.setattr(edit_module, "random_hemisphere_poses", scripted)
    fake, reports = FakeGuidance(), []
    edit(small_sphere, "a dog", fake, EditConfig(iterations=len(script), render_size=24), _collect(reports))
    assert [c["prompts"][0] for c in fake.calls] == [f"a render of a dog, {w} view" for *_, w in script]
    assert [r.info["view"] for r in reports] == [w for *_, w in script]
    assert all(c["shape"] == (1, 3, 24, 24) and c["scale"] == 100.0 and 20 <= c["t"][0] <= 980 for c in fake.calls)
    # one text encoding per distinct prompt (cached per view word)
    assert sorted(p for p in fake.prompts if p) == sorted({f"a render of a dog, {w} view" for *_, w in script})

    monkeypatch.undo()
    fake = FakeGuidance()
    edit(small_sphere, "a dog", fake, EditConfig(iterations=2, render_size=16, view_words=False, prompt_prefix=None))
    assert [c["prompts"][0] for c in fake.calls] == ["a dog", "a dog"]


# ------------------------------------------------------------------ CLI


def test_cli_builds_the_tiny_model_and_edits_with_it(tmp_path, make_sphere_grid, capsys):
    model = tmp_path / "tiny"
    assert main(["build-tiny-model", str(model)]) == 0
    said = capsys.readouterr().out
    assert "SMOKE-TEST" in said and "random" in said.lower() and (model / "model_index.json").is_file()

    grid_file = tmp_path / "sphere.safetensors"
    make_sphere_grid(16).save(grid_file)
    out = tmp_path / "edit"
    common = ["--prompt", "a dog", "--model", str(model), "--render-size", "24", "--device", "cpu", "--quiet",
              "--offline", "--seed", "1"]
    assert main(["edit", str(grid_file), "--out", str(out), "--iterations", "3", "--preview-every", "2",
                 "--checkpoint-every", "2", *common]) == 0
    edited = load_grid(out / "edited.safetensors")
    assert edited.resolution == (16, 16, 16)
    assert not torch.equal(edited.features, load_grid(grid_file).features)
    assert load_edit_checkpoint(out / "checkpoint.safetensors")[1]["iteration"] == 3
    assert sorted(p.name for p in (out / "previews").glob("*.png")) == [
        "preview_00000.png", "preview_00002.png", "preview_00003.png"]

    # --resume continues to a longer run and lands where a straight run does
    assert main(["edit", str(grid_file), "--out", str(out), "--iterations", "4", "--resume",
                 str(out / "checkpoint.safetensors"), *common]) == 0
    straight = tmp_path / "straight"
    assert main(["edit", str(grid_file), "--out", str(straight), "--iterations", "4", *common]) == 0
    assert torch.equal(load_grid(out / "edited.safetensors").features,
                       load_grid(straight / "edited.safetensors").features)

    # cancelled before its first step no checkpoint is written: the hint had named a file that did not exist
    from voxe_core.cli.common import Interrupt

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Interrupt, "__call__", lambda self: True)  # Ctrl-C before the first step
        capsys.readouterr()
        assert main(["edit", str(grid_file), "--out", str(tmp_path / "stopped"), "--iterations", "3", *common]) == 130
    said = capsys.readouterr().err
    assert "voxe: edit cancelled before its first step" in said and "--resume" not in said


def test_cli_checkpoint_every_0_still_writes_one_where_ctrl_c_stops_the_edit_as_its_help_says(tmp_path, tiny_sd_path,
                                                                                              make_sphere_grid, capsys):
    """--checkpoint-every's help had said "0: only at the end", and a Ctrl-C after some steps wrote one there too
    (the edit's checkpoint at a cancel), which the cancel's hint then named to --resume."""
    from voxe_core.cli.common import Interrupt

    make_sphere_grid(8).save(grid_file := tmp_path / "grid.safetensors")
    out, asked = tmp_path / "out", []
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Interrupt, "__call__", lambda self: asked.append(1) or len(asked) > 2)  # Ctrl-C after 2 steps
        assert main(["edit", str(grid_file), "--out", str(out), "--prompt", "a dog", "--model", str(tiny_sd_path),
                     "--render-size", "16", "--device", "cpu", "--quiet", "--offline", "--iterations", "5",
                     "--preview-every", "0", "--checkpoint-every", "0"]) == 130
    assert load_edit_checkpoint(out / "checkpoint.safetensors")[1]["iteration"] == 2
    assert f"resume with --resume {out / 'checkpoint.safetensors'}" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["edit", "--help"])
    said = " ".join(capsys.readouterr().out.split())
    assert "(0: only at the end; Ctrl-C or SIGTERM writes one where it stops the edit, whatever this is)" in said


def test_cli_edit_with_the_tiny_model_says_and_records_it_is_a_smoke_test(tmp_path, tiny_sd_path, make_sphere_grid,
                                                                           capsys):
    """``voxe edit --model`` a folder ``voxe build-tiny-model`` wrote said nothing of its random weights: the edit
    passed for one. It says so once on stderr (even --quiet) and in edited.safetensors' and checkpoint.safetensors'
    headers; a real-looking folder without the tiny model's model_index.json mark, neither."""
    import json

    from voxe_core.gridfile import GRID_FORMAT_VERSION
    from voxe_core.tensorio import load_tensors

    real = shutil.copytree(tiny_sd_path, tmp_path / "real")
    index = {**json.loads((real / "model_index.json").read_text()), "_name_or_path": "CompVis/stable-diffusion-v1-4"}
    (real / "model_index.json").write_text(json.dumps(index))
    (real / "README.md").unlink()
    make_sphere_grid(8).save(tmp_path / "g.safetensors")
    note = (f"{tiny_sd_path} is a random-weight smoke-test Stable Diffusion (voxe build-tiny-model): what is made with "
            "it proves the plumbing only and says nothing about edit quality")
    for model, said in ((tiny_sd_path, [f"voxe edit: SMOKE TEST: {note}"]), (real, [])):
        capsys.readouterr()
        assert main(["edit", str(tmp_path / "g.safetensors"), "--out", str(tmp_path / model.name), "--prompt", "a dog",
                     "--model", str(model), "--render-size", "16", "--device", "cpu", "--quiet", "--offline",
                     "--iterations", "1", "--preview-every", "0"]) == 0
        assert [line for line in capsys.readouterr().err.splitlines() if "SMOKE" in line] == said
        meta = load_tensors(tmp_path / model.name / "edited.safetensors", "voxel_grid", GRID_FORMAT_VERSION)[1]
        assert meta.get("smoke_test") == (note if said else None)
        assert load_grid(tmp_path / model.name / "edited.safetensors").resolution == (8, 8, 8)
        # the checkpoint beside it too (it had carried no mark)
        checkpoint = tmp_path / model.name / "checkpoint.safetensors"
        assert load_edit_checkpoint(checkpoint)[1].get("smoke_test") == (note if said else None)


def test_cli_says_the_regulariser_a_constant_grid_switches_off(tmp_path, tiny_sd_path, make_sphere_grid, capsys):
    """``voxe edit`` of an unfitted grid (constant density) prints what the edit's warning says, even with --quiet;
    of a fitted one, no warning."""
    common = ["--prompt", "a dog", "--model", str(tiny_sd_path), "--render-size", "16", "--device", "cpu", "--quiet",
              "--offline", "--iterations", "1", "--preview-every", "0"]
    for name, grid in [("unfitted", VoxelGrid(8)), ("sphere", make_sphere_grid(8))]:
        grid.save(tmp_path / f"{name}.safetensors")
        capsys.readouterr()
        assert main(["edit", str(tmp_path / f"{name}.safetensors"), "--out", str(tmp_path / name), *common]) == 0
        warned = [line for line in capsys.readouterr().err.splitlines() if "warning" in line]
        assert warned == ([
            "voxe edit: warning: the reconstruction's density is constant: the 3D regulariser (reg3d) has nothing to "
            "correlate and is off; the edit runs unregularised, its reg a constant 1.0 (an empty or unfitted "
            "reconstruction?)"] if name == "unfitted" else [])


def test_cli_refuses_a_bad_resume_or_out_before_loading_the_model(tmp_path, sphere_grid, capsys, monkeypatch):
    """A missing --resume, a grid given as one, or an --out that is a file had been said only after the model loaded
    (or downloaded)."""
    grid_file = tmp_path / "g.safetensors"
    sphere_grid.save(grid_file)

    def no_load(*args, **kwargs):
        raise AssertionError("the model loaded")

    monkeypatch.setattr(StableDiffusionGuidance, "from_pretrained", no_load)
    for resume, message in ((tmp_path / "missing.safetensors", "no such file"),
                            (grid_file, "holds a 'voxel_grid', expected a 'edit_checkpoint'")):
        assert main(["edit", str(grid_file), "--prompt", "a dog", "--out", str(tmp_path / "o"), "--quiet",
                     "--resume", str(resume)]) == 2
        assert f"voxe edit: error: {resume}: {message}" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
    assert main(["edit", str(grid_file), "--prompt", "a dog", "--out", str(grid_file), "--quiet"]) == 2
    assert f"voxe edit: error: cannot write into {grid_file}: it is a file, not a folder" in capsys.readouterr().err


def test_cli_missing_model_exits_2_naming_it(tmp_path, sphere_grid, capsys, monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")  # no network retries in tests
    grid_file = tmp_path / "g.safetensors"
    sphere_grid.save(grid_file)
    code = main(["edit", str(grid_file), "--prompt", "a dog", "--out", str(tmp_path / "o"),
                 "--model", "does-not-exist/anywhere", "--quiet"])
    err = capsys.readouterr().err
    assert code == 2
    assert "does-not-exist/anywhere" in err and "download" in err and "local folder" in err
    assert not (tmp_path / "o" / "edited.safetensors").exists()


def test_cli_image_regulariser_needs_data(tmp_path, sphere_grid, capsys, monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")  # a check that does not refuse reaches the model: no network retries
    grid_file = tmp_path / "g.safetensors"
    sphere_grid.save(grid_file)
    code = main(["edit", str(grid_file), "--prompt", "a dog", "--out", str(tmp_path / "o"),
                 "--regulariser", "image_l2", "--quiet"])
    assert code == 2 and "--data" in capsys.readouterr().err
    # the other way round, --data and the options reading it had been taken and ignored
    for flags, said in ((["--data", str(tmp_path)], "--data gives the input views of --regulariser image_l1 / "
                                                    "image_l2; reg3d reads none"),
                        (["--downsample", "2", "--split", "test"], "--split, --downsample set how --data's images are "
                                                                   "read; without --data none are")):
        assert main(["edit", str(grid_file), "--prompt", "a dog", "--out", str(tmp_path / "o"), *flags]) == 2
        assert said in capsys.readouterr().err
    assert not (tmp_path / "o").exists()
