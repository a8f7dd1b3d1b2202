"""Spatial refinement (SPEC §3): attention maps, attention-grid lifting, graph cut, merge, storage, CLI.

Token spans (multi-token words, phrases, repeats) and the per-pixel token
distribution of the captured maps are covered in tests/test_guidance.py; here
the tiny random-weight SD (SMOKE-TEST MODEL) only proves the refine plumbing.
"""

from __future__ import annotations

import contextlib
import dataclasses
import errno
import json
import math
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from voxe_core.backbones import load_grid
from voxe_core.cameras import Cameras, random_hemisphere_poses, spherical_poses
from voxe_core.cli import main
from voxe_core.cli.refine import PREVIEW_FRAME
from voxe_core.constants import FLOAT32_MAX
from voxe_core.grid import VoxelGrid
from voxe_core.edit import EditConfig, edit
from voxe_core.guidance import Guidance
from voxe_core.guidance.prompts import VIEW_WORDS, check_edit_words_read, edit_prompt
from voxe_core.guidance.sds import StableDiffusionGuidance
from voxe_core.progress import Callbacks, StageCancelled
from voxe_core.refine.config import (
    AUTHORS_CODE_CUT,
    SERVICE_CUT,
    AUTHORS_CODE_FIT,
    AUTHORS_CODE_MAPS,
    MAX_ATTENTION_LR,
    PAPER_TEXT_CUT,
    PAPER_TEXT_FIT,
    PAPER_TEXT_MAPS,
    SERVICE_MAPS,
    RefineConfig,
    SegmentationError,
)
from voxe_core.refine.cut import (
    graph_cut,
    graph_cut_detailed,
    graph_pieces,
    node_mask,
    object_seed_indices,
    pairwise_weights,
    prefer_neither,
    probabilities,
)
from voxe_core.refine import lifting, renders
from voxe_core.refine.lifting import attention_l1, fit_attention_grids
from voxe_core.refine.maps import (
    attention_maps_2d,
    camera_view_words,
    combine_token_maps,
    gaussian_blur2d,
    gaussian_kernel1d,
    postprocess_maps,
    token_groups,
)
from voxe_core.refine.pipeline import merge, refine
from voxe_core.refine.renders import (
    iter_attention_views, iter_feature_views, iter_mask_overlays, render_feature_views,
)
from voxe_core.refine.storage import load_mask, load_probabilities, save_mask, save_probabilities
from voxe_core.render import RenderConfig, render_image
from voxe_core.tensorio import FormatError, load_tensors, save_tensors


@pytest.fixture(autouse=True)
def _single_thread():
    # tiny tensors: thread hand-offs cost more than they save on the shared 2-core box
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def tiny_model(request, tmp_path_factory):
    """The session's shared tiny SD (conftest ``tiny_sd_path``) when there is one, else a module-local build."""
    try:
        return request.getfixturevalue("tiny_sd_path")
    except pytest.FixtureLookupError:
        from voxe_core.tiny_sd import build_tiny_stable_diffusion

        return build_tiny_stable_diffusion(tmp_path_factory.mktemp("tiny_sd_refine") / "model", seed=0)


@pytest.fixture(scope="module")
def tiny_guidance(tiny_model) -> StableDiffusionGuidance:
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("HF_HUB_OFFLINE", "1")
        return StableDiffusionGuidance.from_pretrained(str(tiny_model), device="cpu")


def box_grid(resolution, boxes, density=5.0, outside=-1.0) -> VoxelGrid:
    """Grid whose vertices inside each (lo, hi, rgb) index box have raw density ``density`` and colour rgb."""
    grid = VoxelGrid(resolution)
    with torch.no_grad():
        grid.features[..., 0] = outside
        grid.features[..., 1:] = 0.0
        for lo, hi, rgb in boxes:
            region = tuple(slice(a, b) for a, b in zip(lo, hi))
            grid.features[region + (0,)] = density
            c = torch.tensor(rgb, dtype=torch.float32).clamp(1e-3, 1 - 1e-3)
            grid.features[region + (slice(1, 4),)] = torch.log(c / (1 - c))
    return grid


def cameras_around(n, size, seed=0) -> Cameras:
    c2w, _, _ = random_hemisphere_poses(n, torch.Generator().manual_seed(seed))
    return Cameras.from_fov(c2w, 0.6911112070083618, size, size)


# ----------------------------------------------------------------- 2D maps


def test_token_groups_split_edit_and_object_tokens(tiny_guidance):
    prompt = "a render of a dog wearing a party hat"
    edit, others = token_groups(tiny_guidance, prompt, ["party hat"])
    content = tiny_guidance.content_token_indices(prompt)
    assert edit == tiny_guidance.token_spans(prompt, ["party hat"]) and len(edit) == 2
    assert set(edit) | set(others) == set(content) and not set(edit) & set(others)
    assert 0 not in others and max(others) < 1 + len(content)  # no start, end or padding token
    with pytest.raises(ValueError, match="nothing names the object"):
        token_groups(tiny_guidance, "sunglasses", ["sunglasses"])
    with pytest.raises(ValueError, match="no edit words"):
        token_groups(tiny_guidance, prompt, [" "])


@pytest.mark.parametrize("prompt, edit_words, refusal", [
    ("big sunglasses, party hat", ["big sunglasses", "party hat"], "nothing names the object"),  # only the comma
    ("sunglasses!", ["sunglasses"], "nothing names the object"),  # only the "!"
    ("a dog, wearing sunglasses", [","], "names nothing: it is punctuation alone"),  # the comma's map as the edit's
    ("a dog's hat", ["'s"], "names nothing"),  # a contraction's ending
    ("sunglasses ^^", ["sunglasses"], "nothing names the object"),  # marks of mathematics or modifiers name nothing
    ("sunglasses +", ["sunglasses"], "nothing names the object"),
    ("a mic | a hat", ["|"], "names nothing"),
])
def test_punctuation_neither_names_the_object_nor_the_edit(tiny_guidance, make_sphere_grid, prompt, edit_words,
                                                          refusal):
    """The object map had been a comma's or an exclamation mark's attention (the edit map a comma's), and the
    refinement had run on it; it is refused before its first attention pass."""
    with pytest.raises(ValueError, match=refusal):
        token_groups(tiny_guidance, prompt, edit_words)
    reports, initial = [], make_sphere_grid(12)
    with pytest.raises(ValueError, match=refusal):
        refine(initial, initial.clone_grid(), prompt, edit_words, tiny_guidance, RefineConfig(views=2, render_size=16),
               Callbacks(on_progress=reports.append))
    assert reports == []


@pytest.mark.parametrize("prompt, edit_words", [("a \U0001f3a9 on a mic", ["\U0001f3a9"]),
                                                ("a mic wearing \U0001f576 and a hat", ["\U0001f576"]),
                                                ("a dog with a \u2665 and a hat", ["\u2665"]),
                                                ("\U0001f436 sunglasses", ["sunglasses"]),
                                                ("a \u20ac on a mic", ["\u20ac"])])
def test_a_symbol_names_an_edit_or_the_object(tiny_guidance, prompt, edit_words):
    """An emoji or symbol the tokenizer finds had been refused as an edit word with no letters or numbers."""
    edit, others = token_groups(tiny_guidance, prompt, edit_words)
    assert edit == tiny_guidance.token_spans(prompt, edit_words) and others


@pytest.mark.parametrize("prompt, word, view_words, found", [
    ("a dog wearing a party hat", "party hat", True, True),
    ("a dog wearing a hat.", "hat.", True, False),  # the full stop is dropped: "hat" ","
    ("a dog wearing a hat!", "hat!", True, False),  # "hat" "!,"
    ("a dog wearing a hat!", "hat!", False, True),  # "hat" "!"
    ("a dog wearing 'hat'", "'hat'", True, False),
    ("a dog wearing a hat- and a scarf", "hat-", True, True),
    ("a dog wearing a cafe\u0301 hat", "cafe", True, False),  # the tokenizer reads "café" (NFC)
    ("a dog wearing a caf\u00e9 hat", "caf\u00e9", True, True),
    ("a dog's hat", "dog's", True, True),
    ("a cafe\u0301\u00bd sign on a dog", "\u00bd", True, True),  # "café" "½": ½ is a number, no letter
    ("a dog wearing a \u00b2hat", "hat", True, True),
])
def test_the_submission_check_of_an_edit_word_is_the_attention_models_token_match(tiny_guidance, prompt, word,
                                                                                 view_words, found):
    """``check_edit_words_read`` (torch-free, the API's) refuses exactly the edit words the refinement's token match
    does not find (after the whole edit)."""
    def matched() -> bool:
        try:
            for view in VIEW_WORDS if view_words else (None,):
                token_groups(tiny_guidance, edit_prompt(prompt, view), [word])
        except ValueError as exc:
            assert "does not occur in the prompt" in str(exc)
            return False
        return True

    assert matched() == found
    if found:
        check_edit_words_read(prompt, [word], view_words)
    else:
        with pytest.raises(ValueError, match=f"edit word {re.escape(repr(word))} does not occur in the prompt as the "
                                             "model reads it"):
            check_edit_words_read(prompt, [word], view_words)


def test_combine_token_maps_mean_of_edit_max_of_others():
    maps = torch.rand(77, 4, 4, generator=torch.Generator().manual_seed(0))
    edit, obj = combine_token_maps(maps, [5, 6], [1, 2, 3, 4])
    torch.testing.assert_close(edit, (maps[5] + maps[6]) / 2)
    torch.testing.assert_close(obj, maps[1:5].amax(0))
    edit_max, _ = combine_token_maps(maps, [5, 6], [1], reduce="max")
    torch.testing.assert_close(edit_max, torch.maximum(maps[5], maps[6]))


def test_gaussian_blur_keeps_constants_and_spreads_a_delta_by_sigma():
    const = torch.full((2, 9, 9), 0.3)
    torch.testing.assert_close(gaussian_blur2d(const, 1.0), const)
    delta = torch.zeros(1, 41, 41)
    delta[0, 20, 20] = 1.0
    out = gaussian_blur2d(delta, 2.0)[0]
    assert abs(float(out.sum()) - 1.0) < 1e-5
    x = torch.arange(41.0) - 20
    std = float((out.sum(0) * x**2).sum().sqrt())
    assert abs(std - 2.0) < 0.05


def test_attention_maps_2d_are_normalised_per_view(tiny_guidance, make_sphere_grid):
    grid = make_sphere_grid(12)
    cams = cameras_around(2, 24)
    config = RefineConfig(render_size=24, views=2, **PAPER_TEXT_MAPS)
    edit, obj = attention_maps_2d(tiny_guidance, grid, cams, "a render of a dog wearing sunglasses", ["sunglasses"], config)
    assert edit.shape == obj.shape == (2, 24, 24)
    for maps in (edit, obj):
        assert torch.isfinite(maps).all()
        torch.testing.assert_close(maps.amin(dim=(1, 2)), torch.zeros(2))
        torch.testing.assert_close(maps.amax(dim=(1, 2)), torch.ones(2))


def test_the_default_attention_layers_follow_the_models_latent_size(tiny_guidance, tiny_model, make_sphere_grid,
                                                                    tmp_path):
    """A fixed 16 had found no layer on a model whose latents are not SD-1.4's (a 768-px SD 2.x: 96/48/24/12): every
    local job failed at its refinement, after its edit. The tiny model at sample size 24 stands in (layers 24, 12)."""
    import shutil

    from voxe_core.presets import refine_config

    other = shutil.copytree(tiny_model, tmp_path / "model_24")
    unet_config = other / "unet" / "config.json"
    unet_config.write_text(json.dumps({**json.loads(unet_config.read_text()), "sample_size": 24}))
    guidance = StableDiffusionGuidance.from_pretrained(str(other), device="cpu", local_files_only=True)
    config = refine_config({}, str(other))  # what the worker builds for every local job
    assert config.resolution_filter == RefineConfig().resolution_filter == "auto"
    image = torch.rand(1, 3, 64, 64, generator=torch.Generator().manual_seed(0))
    assert guidance.cross_attention_maps(image, "a dog", resolution_filter=config.resolution_filter).shape == (77, 24, 24)
    assert guidance.cross_attention_maps(image, "a dog", resolution_filter=12).shape == (77, 12, 12)  # as asked
    edit, _ = attention_maps_2d(guidance, make_sphere_grid(8), cameras_around(1, 16), "a render of a dog wearing a hat",
                                ["hat"], dataclasses.replace(config, render_size=16))
    assert edit.shape == (1, 16, 16) and torch.isfinite(edit).all()
    # the tiny model's default layers are as they were: its 16x16 latents' 16x16 layers
    assert tiny_guidance.cross_attention_maps(image, "a dog").shape == (77, 16, 16)
    with pytest.raises(ValueError, match="resolution_filter must be 'auto', None or a positive number"):
        RefineConfig(resolution_filter="16")


@pytest.mark.parametrize("nonsense", [True, False, 16.0])
def test_a_resolution_filter_that_is_no_whole_number_of_pixels_is_refused_at_config_time(nonsense):
    """Regression: True (an int to isinstance) had been accepted as 1, a 1x1 query map no layer has, refused by the
    model only after the first view's render ('no cross-attention layer has a True x True query map')."""
    with pytest.raises(ValueError, match=rf"resolution_filter must be 'auto', None or a positive number of query-map "
                                         rf"pixels, got {nonsense}$"):
        RefineConfig(resolution_filter=nonsense)
    assert RefineConfig(resolution_filter=np.int64(16)).resolution_filter == 16


def test_the_authors_code_maps_but_normalised_and_its_fit_are_the_default_and_the_text_is_one_replace_away():
    config = RefineConfig()
    assert {k: getattr(config, k) for k in SERVICE_MAPS} == SERVICE_MAPS
    assert SERVICE_MAPS == {**AUTHORS_CODE_MAPS, "map_scale": "minmax"} and AUTHORS_CODE_MAPS["map_scale"] == "raw"
    text = dataclasses.replace(config, **PAPER_TEXT_MAPS)
    assert (text.edit_token_reduce, text.map_scale, text.object_tokens) == ("mean", "minmax", "content")
    assert {k: getattr(config, k) for k in ("fit_pixels", "fit_views")} == {"fit_pixels": "rendered_positive",
                                                                           "fit_views": "fresh"}
    with pytest.raises(ValueError, match="map_scale"):
        RefineConfig(map_scale="sigmoid")
    with pytest.raises(ValueError, match="renders"):  # the masked L1 cannot move a start that renders nothing
        RefineConfig(lift_start="constant", iterations=10, init_value=-20.0, fit_pixels="rendered_positive")
    RefineConfig(**PAPER_TEXT_FIT)
    RefineConfig(**AUTHORS_CODE_FIT)


def _refine_cli(tmp_path, make_sphere_grid, *options: str) -> int:
    """``voxe refine`` of an 8³ sphere against itself into ``tmp_path / "out"`` with ``options``, no model at hand:
    its exit status."""
    make_sphere_grid(8).save(tmp_path / "grid.safetensors")
    return main(["refine", str(tmp_path / "grid.safetensors"), "--initial", str(tmp_path / "grid.safetensors"),
                 "--prompt", "a dog wearing a party hat", "--edit-words", "hat", "--out", str(tmp_path / "out"),
                 "--model", str(tmp_path / "no_model_needed"), "--offline", "--device", "cpu", *options, "--quiet"])


def test_a_constant_start_without_fitting_steps_is_refused_before_any_work(tmp_path, make_sphere_grid, capsys):
    # Both grids would stay at init_value: P_e = P_obj = 1/2 at every voxel, no seed, a SegmentationError at the cut,
    # after every attention pass (a job's: after its whole edit). The service's 0 steps suit only the back-projection.
    with pytest.raises(ValueError, match="lift_start='constant' with iterations=0 .* no seeds"):
        RefineConfig(lift_start="constant", iterations=0, fit_views="fixed", fit_pixels="all")
    RefineConfig(lift_start="backprojection", iterations=0)
    out = tmp_path / "out"
    assert _refine_cli(tmp_path, make_sphere_grid, "--lift-start", "constant") == 2
    assert "no seeds" in capsys.readouterr().err and not out.exists()  # refused before the model is looked for


@pytest.mark.parametrize("timestep", [-1, 1000, 5000])
def test_a_timestep_outside_the_diffusion_schedule_is_refused_at_config_time_naming_the_range(timestep):
    """Regression: accepted, it was refused by the model only after the first view's render ('timesteps must lie in
    [0, 999], got [1000]'), after the edit a job had run."""
    with pytest.raises(ValueError, match=rf"timestep must lie in \[0, 999\] .*got {timestep}$"):
        RefineConfig(timestep=timestep)
    assert RefineConfig(timestep=0).timestep == 0 and RefineConfig(timestep=999).timestep == 999


@pytest.mark.parametrize("name, value, refusal", [
    ("view_word_prompt", "false", "view_word_prompt takes True or False, got 'false'"),
    ("smooth_upsampled", 0, "smooth_upsampled takes True or False, got 0"),
    ("view_word_prompt", None, "view_word_prompt takes True or False, got None"),
    ("render", None, "render must be a RenderConfig, got None"),
])
def test_a_setting_of_another_type_is_refused_naming_it(name, value, refusal):
    """Regression: view_word_prompt="false" (a true string) had put the view words in the attention prompt, the
    opposite of what was asked; render=None failed with "'NoneType' object has no attribute 'background'"."""
    with pytest.raises(ValueError, match=f"^{re.escape(refusal)}$"):
        RefineConfig(**{name: value})
    assert RefineConfig(view_word_prompt=False, smooth_upsampled=False).view_word_prompt is False


@pytest.mark.parametrize("name, value", [("sigma", "0.1"), ("lr", None), ("edit_seed_ratio", "1"), ("fov_x", None),
                                         ("smoothing_sigma", True), ("node_alpha", [0.01])])
def test_a_setting_that_is_no_number_is_refused_naming_it(name, value):
    """Regression: a string or None had failed a range test naming no setting ("'<' not supported between instances
    of 'int' and 'str'", a TypeError), and True had run as 1."""
    with pytest.raises(ValueError, match=f"^{name} must be a number, got {re.escape(repr(value))}$"):
        RefineConfig(**{name: value})
    assert RefineConfig(sigma=np.float32(0.2), lr=np.float64(0.01), smoothness=5).smoothness == 5


@pytest.mark.parametrize("name", ["iterations", "edit_seeds", "object_seeds", "object_seed_fallback"])
def test_a_negative_count_is_refused_naming_the_setting_and_its_value(name):
    """Regression: all four had been refused as 'iterations and seed counts must be non-negative', naming neither."""
    with pytest.raises(ValueError, match=rf"^{name} must be non-negative, got -3$"):
        RefineConfig(**{name: -3})
    assert getattr(RefineConfig(**{name: 0}), name) == 0


@pytest.mark.parametrize("size", [1, 3, 7])
def test_renders_under_8_px_are_refused_before_any_work(tmp_path, make_sphere_grid, capsys, size):
    """Regression: accepted, a 1 px render's min-max maps are 0 everywhere and 2–3 px ones missed a test sphere from
    every pose, found at the cut after every attention pass and fit. 8 px: the edit's and the service's minimum."""
    with pytest.raises(ValueError, match=f"render_size must be at least 8 px, got {size}"):
        RefineConfig(render_size=size)
    assert RefineConfig(render_size=8).render_size == 8
    out = tmp_path / "out"
    assert _refine_cli(tmp_path, make_sphere_grid, "--render-size", str(size)) == 2
    assert capsys.readouterr().err == f"voxe refine: error: --render-size must be at least 8 px, got {size}\n"
    assert not out.exists()


@pytest.mark.parametrize("name, value, message", [
    ("render_size", 1025, "render_size must be at most 1024 px (the service's and the CLI's limit), got 1025"),
    ("render_size", 50000, "render_size must be at most 1024 px (the service's and the CLI's limit), got 50000"),
    ("views", 1001, "views must be at most 1000 (the service's and the CLI's limit), got 1001"),
])
def test_the_stages_configs_refuse_renders_and_views_past_the_services_limits(name, value, message):
    """Regression: the configs had no upper bound where the CLI and the API stop (1024 px, 1000 views):
    EditConfig(render_size=50000) or RefineConfig(views=100000) were taken, to exhaust the memory (2.5e9 rays a
    render) or render and attend every view. The limits themselves pass."""
    from voxe_core.edit import EditConfig

    makers = (RefineConfig, EditConfig) if name == "render_size" else (RefineConfig,)
    for make in makers:
        with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
            make(**{name: value})
        assert getattr(make(**{name: 1024 if name == "render_size" else 1000}), name) in (1024, 1000)


def test_max_over_edit_tokens_is_the_max_of_the_per_token_maps():
    maps = torch.rand(77, 6, 6, generator=torch.Generator().manual_seed(1))
    edit, _ = combine_token_maps(maps, [3, 7, 9], [1], reduce=RefineConfig().edit_token_reduce)
    for k in (3, 7, 9):
        assert (edit >= maps[k]).all()
    assert torch.equal(edit, torch.stack([maps[3], maps[7], maps[9]]).amax(0))


def test_through_end_object_tokens_add_exactly_the_first_end_of_text_token(tiny_guidance):
    prompt = "a render of a dog wearing a party hat"
    edit, content_only = token_groups(tiny_guidance, prompt, ["party hat"], "content")
    _, through_end = token_groups(tiny_guidance, prompt, ["party hat"], "through_end")
    ids = tiny_guidance._tokenize([prompt])[0].tolist()
    assert through_end[:-1] == content_only and len(through_end) == len(content_only) + 1
    assert ids[through_end[-1]] == tiny_guidance.tokenizer.eos_token_id
    assert all(ids[i] != tiny_guidance.tokenizer.eos_token_id for i in content_only + edit)


def test_the_3x3_kernel_is_the_authors_sigma_half_gaussian():
    taps = gaussian_kernel1d(0.5, radius=1)
    e = math.exp(-2.0)  # exp(-1² / (2·0.5²))
    torch.testing.assert_close(taps, torch.tensor([e, 1.0, e]) / (1 + 2 * e))
    kernel2d = taps[:, None] * taps[None, :]
    assert abs(float(kernel2d[1, 1]) - 1 / (1 + 2 * e) ** 2) < 1e-6 and abs(float(kernel2d.sum()) - 1) < 1e-6
    delta = torch.zeros(1, 7, 7)
    delta[0, 3, 3] = 1.0
    blurred = gaussian_blur2d(delta, 0.5, radius=1)[0]
    torch.testing.assert_close(blurred[2:5, 2:5], kernel2d)  # 3x3 support: nothing beyond one cell
    assert float(blurred.sum()) == pytest.approx(1.0) and float(blurred[1].abs().sum()) == 0.0
    assert gaussian_kernel1d(0.5).numel() == 5  # the whole Gaussian (radius ceil(3σ)) for "3sigma"


@pytest.mark.parametrize("sigma", [1e-46, 5e-324])
def test_a_smoothing_sigma_below_float32s_smallest_blurs_nothing(sigma):
    """Such a σ had become 0 in float32 and the taps 0 / 0: every map NaN."""
    for radius in (1, None):
        assert gaussian_kernel1d(sigma, radius).tolist() == [0.0, 1.0, 0.0]
    maps = torch.rand(2, 16, 16, generator=torch.Generator().manual_seed(4))
    config = RefineConfig(smoothing_sigma=sigma, map_scale="raw")
    torch.testing.assert_close(postprocess_maps(maps, (40, 40), config),
                               postprocess_maps(maps, (40, 40), dataclasses.replace(config, smoothing_sigma=0.0)))


@pytest.mark.parametrize("maps_config", [SERVICE_MAPS, AUTHORS_CODE_MAPS, PAPER_TEXT_MAPS])
def test_maps_postprocessed_under_a_callers_bf16_autocast_are_the_float32_ones(maps_config):
    """The blurs' conv2d had run in bf16 under a caller's autocast: bf16 maps up to 0.014 off the float32 ones, which
    the attention grids were then fitted to."""
    maps = torch.rand(2, 16, 16, generator=torch.Generator().manual_seed(0))
    config = RefineConfig(**maps_config)
    reference = postprocess_maps(maps, (266, 266), config)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        mixed = postprocess_maps(maps, (266, 266), config)
    assert mixed.dtype == torch.float32 and torch.equal(mixed, reference)


@pytest.mark.parametrize("sigma", [16 / 3, 1e4, 1e12, FLOAT32_MAX])
def test_a_3sigma_kernel_wider_than_the_maps_is_refused_and_the_3x3_one_takes_any_sigma(sigma):
    """A "3sigma" kernel has 2·ceil(3σ) + 1 taps: σ = 1e4 had taken 38 s a 266 px view (one CPU thread), 1e12 asked
    for 48 TB. The authors' 3x3 kernel of a large σ is a 3x3 box blur."""
    with pytest.raises(ValueError, match=r"smoothing_kernel='3sigma' spans ceil\(3 sigma\) = \d+ px either side .* "
                                         r"past the render_size \(16 px\) maps it smooths: use a smoothing_sigma "
                                         r"of at most 5.0 or smoothing_kernel='3x3'"):
        RefineConfig(render_size=16, smoothing_kernel="3sigma", smoothing_sigma=sigma)
    maps = torch.rand(2, 16, 16, generator=torch.Generator().manual_seed(4))
    if sigma >= 1e4:  # taps e^(-1/2σ²) ≈ 1 on either side of the centre's
        box = RefineConfig(render_size=16, smoothing_sigma=sigma, smooth_upsampled=False, map_scale="raw")
        box_blur = F.avg_pool2d(F.pad(maps[:, None], (1, 1, 1, 1), mode="reflect"), 3, stride=1)[:, 0]
        torch.testing.assert_close(postprocess_maps(maps, (16, 16), box), box_blur)
    widest = RefineConfig(render_size=16, smoothing_kernel="3sigma", smoothing_sigma=5.0)  # 15 px either side
    assert postprocess_maps(maps, (16, 16), widest).isfinite().all()


@pytest.mark.parametrize("render_size, sigma", [(16, 5.2), (17, 5.5), (18, 5.8), (33, 10.7)])
def test_the_3sigma_refusal_advises_the_largest_sigma_it_accepts(render_size, sigma):
    """ceil(3σ) >= render_size is refused, so σ above (render_size - 1)/3: the advice had said "below
    render_size/3", a bound itself refused (and σ between the two refused while below it)."""
    assert (render_size - 1) / 3 < sigma < render_size / 3
    with pytest.raises(ValueError, match="use a smoothing_sigma of at most") as refused:
        RefineConfig(render_size=render_size, smoothing_kernel="3sigma", smoothing_sigma=sigma)
    advised = float(re.search(r"of at most (\S+) or", str(refused.value)).group(1))
    assert advised == (render_size - 1) / 3
    RefineConfig(render_size=render_size, smoothing_kernel="3sigma", smoothing_sigma=advised)  # accepted


def test_raw_maps_keep_the_relative_scale_of_edit_and_object_minmax_does_not():
    cells = torch.rand(1, 16, 16, generator=torch.Generator().manual_seed(2))
    maps = torch.cat([0.2 * cells, cells])  # the edit token takes a fifth of the object's attention
    raw = postprocess_maps(maps, (40, 40), RefineConfig(**AUTHORS_CODE_MAPS))
    torch.testing.assert_close(raw[0], 0.2 * raw[1])  # linear steps: smoothing, upsampling, smoothing
    flat = postprocess_maps(torch.full((1, 16, 16), 0.3), (40, 40), RefineConfig(map_scale="raw"))
    torch.testing.assert_close(flat, torch.full((1, 40, 40), 0.3))  # a constant probability stays what it is
    stretched = postprocess_maps(maps, (40, 40), RefineConfig(map_scale="minmax"))
    torch.testing.assert_close(stretched[0], stretched[1])
    torch.testing.assert_close(stretched.amax(dim=(1, 2)), torch.ones(2))


def test_smoothing_after_upsampling_is_one_more_pass_of_the_same_kernel():
    cells = torch.rand(1, 16, 16, generator=torch.Generator().manual_seed(3))
    once = postprocess_maps(cells, (48, 48), RefineConfig(smooth_upsampled=False, map_scale="raw"))
    twice = postprocess_maps(cells, (48, 48), RefineConfig(map_scale="raw"))
    torch.testing.assert_close(twice, gaussian_blur2d(once, 0.5, radius=1))
    assert not torch.allclose(once, twice)


def test_view_words_follow_the_pose_as_in_the_edit():
    c2w = spherical_poses(torch.tensor([30.0, 30.0, 30.0, 30.0, 75.0]), torch.tensor([270.0, 90.0, 0.0, 180.0, 10.0]))
    cams = Cameras.from_fov(c2w, 0.69, 8, 8)
    assert camera_view_words(cams, 270.0) == ["front", "back", "side", "side", "overhead"]


@pytest.mark.parametrize("angle", [math.nan, math.inf])
def test_a_front_azimuth_that_is_no_angle_is_refused(angle):
    """It had been accepted, and every pose's attention prompt had read ", side view"."""
    with pytest.raises(ValueError, match=f"front_azimuth_deg must be a finite angle in degrees, got {angle}"):
        RefineConfig(front_azimuth_deg=angle)


def test_view_words_are_read_around_the_point_the_cameras_orbit():
    """An off-centre capture's cameras orbit its centre: the words are the edit's for the same pose."""
    elevation, azimuth = torch.tensor([30.0, 30.0, 30.0, 30.0, 75.0]), torch.tensor([270.0, 90.0, 0.0, 180.0, 10.0])
    centre = torch.tensor([1.5, -2.0, 0.5])
    cams = Cameras.from_fov(spherical_poses(elevation, azimuth, centre=centre), 0.69, 8, 8)
    assert camera_view_words(cams, 270.0, centre) == ["front", "back", "side", "side", "overhead"]
    assert camera_view_words(cams, 270.0) != camera_view_words(cams, 270.0, centre)  # around the origin: other words


def test_attention_prompts_carry_each_views_word(tiny_guidance, make_sphere_grid, monkeypatch):
    grid = make_sphere_grid(10)
    c2w = spherical_poses(torch.tensor([30.0, 30.0]), torch.tensor([270.0, 90.0]))
    cams = Cameras.from_fov(c2w, 0.69, 16, 16)
    seen = []
    original = tiny_guidance.cross_attention_maps
    monkeypatch.setattr(tiny_guidance, "cross_attention_maps",
                        lambda image, prompt, **kw: seen.append(prompt) or original(image, prompt, **kw))
    prompt = "a render of a dog wearing sunglasses"
    edit, obj = attention_maps_2d(tiny_guidance, grid, cams, prompt, ["sunglasses"], RefineConfig(render_size=16))
    assert seen == [prompt + ", front view", prompt + ", back view"]
    torch.testing.assert_close(edit.amax(dim=(1, 2)), torch.ones(2))  # min-max normalised (the default)
    seen.clear()
    raw, _ = attention_maps_2d(tiny_guidance, grid, cams, prompt, ["sunglasses"],
                               RefineConfig(render_size=16, view_word_prompt=False, map_scale="raw"))
    assert seen == [prompt, prompt]
    assert float(raw.min()) >= 0 and float(raw.max()) < 1.0  # raw probabilities: one token's share of each pixel


# ----------------------------------------------------------------- lifting


def test_fit_recovers_a_known_field_from_exact_maps(make_sphere_grid):
    # semi-transparent sphere (optical depth ~1.5 through the middle): every voxel is seen,
    # so the field is identifiable from its renders
    res = 12
    grid = make_sphere_grid(res, radius=0.9)
    with torch.no_grad():
        inside = grid.features[..., 0] > 0
        grid.features[..., 0] = torch.where(inside, torch.tensor(1.0 / grid.density_scale), torch.tensor(-1.0))
    axes = torch.linspace(-1.5, 1.5, res)
    x, y, z = torch.meshgrid(axes, axes, axes, indexing="ij")
    truth = (0.5 + 0.45 * torch.tanh(2.0 * (x + 0.5 * z)))[..., None]
    cams = cameras_around(12, 16, seed=3)
    maps = render_feature_views(grid, cams, torch.cat([truth, 1 - truth], -1), background=(0.0,))
    config = RefineConfig(iterations=80, lr=0.08, rays_per_step=512, tv_weight=0.01, fit_views="fixed")
    edit, obj = fit_attention_grids(grid, cams, maps[..., 0], maps[..., 1], config)
    assert edit.shape == obj.shape == (res, res, res, 1)
    # interior vertices (all 6 neighbours inside): boundary ones share their cells with empty space
    core = inside & torch.roll(inside, 1, 0) & torch.roll(inside, -1, 0) & torch.roll(inside, 1, 1) \
        & torch.roll(inside, -1, 1) & torch.roll(inside, 1, 2) & torch.roll(inside, -1, 2)
    assert int(core.sum()) > 50
    err_e = (edit[..., 0] - truth[..., 0])[core].abs().mean()  # from 0.5 at the start
    err_o = (obj[..., 0] - (1 - truth[..., 0]))[core].abs().mean()
    assert err_e < 0.08 and err_o < 0.08, (float(err_e), float(err_o))
    corr = torch.corrcoef(torch.stack([edit[..., 0][core], truth[..., 0][core]]))[0, 1]
    assert corr > 0.95


def test_fit_reports_progress_and_cancels(make_sphere_grid):
    grid = make_sphere_grid(10)
    cams = cameras_around(2, 8)
    maps = torch.zeros(2, 8, 8)
    seen = []
    cb = Callbacks(on_progress=lambda p: seen.append((p.stage, p.iteration)), should_cancel=lambda: len(seen) >= 3)
    with pytest.raises(StageCancelled):
        fit_attention_grids(grid, cams, maps, maps + 0.5,  # (maps equal everywhere are refused before any work)
                            RefineConfig(iterations=10, rays_per_step=64, fit_views="fixed"), cb)
    assert seen == [("backprojection", 1), ("attention_grids", 1), ("attention_grids", 2)]
    with pytest.raises(ValueError, match="do not match"):
        fit_attention_grids(grid, cams, torch.zeros(3, 8, 8), torch.zeros(3, 8, 8), RefineConfig(iterations=1, fit_views="fixed"))


def test_a_constant_start_too_short_to_part_the_grids_is_named_with_its_remedy(make_sphere_grid):
    """From one value, both fields' L1 gradients agree until their renders reach the lower map, so a few steps left
    them equal: a "no seeds" SegmentationError from the cut, blaming no setting. Enough steps part them."""
    grid = make_sphere_grid(10)
    cams = cameras_around(4, 12, seed=1)
    axes = torch.linspace(0.2, 0.9, 12)
    edit_maps = axes.expand(4, 12, 12)  # edit and object maps apart everywhere, both above 0.2
    object_maps = edit_maps.flip(-1)
    config = RefineConfig(lift_start="constant", iterations=2, rays_per_step=256, fit_views="fixed", fit_pixels="all")
    with pytest.raises(SegmentationError, match=r"^the attention grids are still equal everywhere after 2 fitting "
                                                r"iterations from lift_start='constant': .* fit more iterations \(the "
                                                r"paper: 1500\) or use lift_start='backprojection'$"):
        fit_attention_grids(grid, cams, edit_maps, object_maps, config)
    edit, obj = fit_attention_grids(grid, cams, edit_maps, object_maps, dataclasses.replace(config, iterations=40))
    assert not torch.equal(edit, obj)


def test_an_attention_fit_that_diverges_stops_at_the_step_that_finds_it_naming_its_settings(make_sphere_grid,
                                                                                           monkeypatch):
    """An lr the config accepts (1e30) overflowed the grids to inf and NaN by the second step: every step left had run
    (with fresh views a diffusion pass each) and the NaN grids reached the cut, refused there as "a diverged edit or
    attention-grid fit?". The fit now stops at the first step whose loss is not finite, reporting no progress for it,
    and a last step whose update overflowed (its loss finite) is found where the fit ends."""
    grid, cams = make_sphere_grid(10), cameras_around(4, 12, seed=1)
    edit_maps = torch.linspace(0.2, 0.9, 12).expand(4, 12, 12)
    config = RefineConfig(iterations=10, rays_per_step=256, fit_views="fixed", fit_pixels="all", lr=1e30)
    seen = []
    with pytest.raises(SegmentationError, match=r"^the attention-grid fit diverged by iteration 2 of 10: its loss is "
                                                r"(inf|nan) \(L1 .*, TV .*\); its steps overflowed float32: lower lr or "
                                                r"tv_weight \(now 1e\+30 and 0.01\)$"):
        fit_attention_grids(grid, cams, edit_maps, edit_maps.flip(-1), config,
                            Callbacks(on_progress=lambda p: seen.append((p.stage, p.iteration))))
    assert seen[-1] == ("attention_grids", 1)
    step = torch.optim.Adam.step

    def overflowing(self, *args, **kwargs):  # as an update past float32 would leave it
        result = step(self, *args, **kwargs)
        with torch.no_grad():
            self.param_groups[0]["params"][0][0, 1] = math.inf
        return result

    monkeypatch.setattr(torch.optim.Adam, "step", overflowing)
    with pytest.raises(SegmentationError, match=r"^the attention-grid fit diverged by iteration 1 of 1: the grids hold "
                                                r"NaN or infinite values at 1 of their 1000 vertices; its steps overflowed "
                                                r"float32: lower lr or tv_weight \(now 0.035 and 0.01\)$"):
        fit_attention_grids(grid, cams, edit_maps, edit_maps.flip(-1), dataclasses.replace(config, lr=0.035,
                                                                                           iterations=1))
    monkeypatch.undo()
    with torch.no_grad():  # a NaN density makes the loss NaN from the first step: no fault of the lr
        grid.features[5, 5, 5, 0] = math.nan
    for iterations in (0, 5):
        with pytest.raises(SegmentationError, match=r"^the edited grid's density is NaN at 1 of its 1000 vertices, so "
                                                    r"what the views see through it is undefined"):
            fit_attention_grids(grid, cams, edit_maps, edit_maps.flip(-1),
                                dataclasses.replace(config, lr=0.035, iterations=iterations))


@pytest.mark.parametrize("iterations", [0, 10])
def test_attention_grids_fitted_under_a_callers_bf16_autocast_are_the_float32_ones(make_sphere_grid, iterations):
    """The back-projection's density interpolation (a bmm) had run in bf16 under a caller's autocast: grids up to
    0.004 off the float32 ones, the fit going on from its start (the renderer's float32 under autocast is the rule)."""
    grid, cams = make_sphere_grid(10), cameras_around(4, 12, seed=1)
    edit_maps = torch.linspace(0.2, 0.9, 12).expand(4, 12, 12)
    config = RefineConfig(iterations=iterations, rays_per_step=256, fit_views="fixed", fit_pixels="all")
    reference = fit_attention_grids(grid, cams, edit_maps, edit_maps.flip(-1), config)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        mixed = fit_attention_grids(grid, cams, edit_maps, edit_maps.flip(-1), config)
    for made, expected in zip(mixed, reference):
        assert made.dtype == torch.float32 and torch.equal(made, expected)


@pytest.mark.parametrize("cause", ["maps equal", "every fresh view missed", "the paper's iterations"])
def test_a_constant_start_left_equal_names_its_cause(make_sphere_grid, monkeypatch, cause):
    """The error had always said "fit more iterations (the paper: 1500)": wrong for maps that never differ, for fresh
    views that all missed the object (no step fitted) and for a fit of the paper's iterations already."""
    grid = make_sphere_grid(10)
    edit_maps = torch.linspace(0.2, 0.9, 12).expand(4, 12, 12)
    object_maps = edit_maps.clone() if cause == "maps equal" else edit_maps.flip(-1)
    config = RefineConfig(lift_start="constant", iterations=2, rays_per_step=256, fit_views="fixed", fit_pixels="all")
    fresh_view = None
    if cause == "maps equal":  # fresh views' (fixed maps that never differ are refused before the fit)
        config = dataclasses.replace(config, fit_views="fresh")
        fresh_view = lambda step: (cameras_around(1, 12, seed=step), edit_maps[0], edit_maps[0])  # noqa: E731
    elif cause == "every fresh view missed":
        away = torch.eye(4)
        away[:3, :3], away[2, 3] = torch.diag(torch.tensor([1.0, -1.0, -1.0])), 4.0  # at +z, looking up +z
        config = dataclasses.replace(config, fit_views="fresh")
        fresh_view = lambda step: (Cameras.from_fov(away, 0.3, 12, 12), edit_maps[0], object_maps[0])  # noqa: E731
    elif cause == "the paper's iterations":
        monkeypatch.setattr(lifting, "REFINE_ITERATIONS", 2)  # 1500 steps that part nothing, in 2
    expected = {"maps equal": r"the edit and object maps are equal on every pixel fitted: they do not tell the edit "
                              r"from the object .* the cut has no seeds$",
                "every fresh view missed": r"no step fitted them, every fresh view having missed the edited object "
                                           r".* are the fresh poses aimed at it\?$",
                "the paper's iterations": r"which these did not in as many iterations as the paper's \(2\), .* use "
                                          r"lift_start='backprojection', or a larger lr or an init_value nearer the "
                                          r"maps \(now 0.035 and 0.0\)$"}[cause]
    with pytest.raises(SegmentationError, match="^the attention grids are still equal everywhere after 2 fitting "
                                                "iterations from lift_start='constant': ") as raised:
        fit_attention_grids(grid, cameras_around(4, 12, seed=1), edit_maps, object_maps, config, fresh_view=fresh_view)
    assert re.search(expected, str(raised.value)) and "fit more iterations" not in str(raised.value)


@pytest.mark.parametrize("views", ["fixed", "fresh"])
def test_a_constant_start_on_fixed_maps_that_never_differ_is_refused_before_any_work(make_sphere_grid, views):
    """The paper's fit (constant start, fixed views) of edit and object maps equal on every pixel had run all of its
    1,500 steps to end with both grids equal and say so. Fresh views' maps are told step by step: their fit runs."""
    grid = make_sphere_grid(10)
    edit_maps = torch.linspace(0.2, 0.9, 12).expand(4, 12, 12)
    config = RefineConfig(**{**PAPER_TEXT_FIT, "rays_per_step": 64, "fit_views": views})
    reports = []
    on_progress = reports.append if views == "fresh" else lambda p: pytest.fail(f"{p.stage} progress reported")
    fresh_view = lambda step: (cameras_around(1, 12, seed=step), edit_maps[0], edit_maps[0].flip(-1))  # noqa: E731
    if views == "fixed":
        with pytest.raises(SegmentationError, match=r"^the edit and object maps are equal on every pixel of the 4 "
                                                    r"views \(of 4\) that see the edited object: they do not tell "
                                                    r"the edit from the object .* nothing was fitted$"):
            fit_attention_grids(grid, cameras_around(4, 12, seed=1), edit_maps, edit_maps.clone(), config,
                                Callbacks(on_progress=on_progress, should_cancel=lambda: len(reports) >= 3))
        # the views counted are those that see it: two of four turned away
        turned = cameras_around(4, 12, seed=1)
        away = torch.eye(4)
        away[:3, :3], away[2, 3] = torch.diag(torch.tensor([1.0, -1.0, -1.0])), 4.0  # above it, looking up
        turned.c2w[2:] = away
        with pytest.raises(SegmentationError, match=r"every pixel of the 2 views \(of 4\) that see the edited"):
            fit_attention_grids(grid, turned, edit_maps, edit_maps.clone(), config, Callbacks(on_progress=on_progress))
        # maps apart on one pixel's worth: fitted
        object_maps = edit_maps.clone()
        object_maps[:, 6, 6] += 0.05
        with pytest.raises(StageCancelled):
            fit_attention_grids(grid, cameras_around(4, 12, seed=1), edit_maps, object_maps, config,
                                Callbacks(on_progress=reports.append, should_cancel=lambda: len(reports) >= 3))
    else:
        with pytest.raises(StageCancelled):
            fit_attention_grids(grid, cameras_around(4, 12, seed=1), edit_maps, edit_maps.clone(), config,
                                Callbacks(on_progress=on_progress, should_cancel=lambda: len(reports) >= 3),
                                fresh_view=fresh_view)
    assert [p.stage for p in reports] == ["backprojection", "attention_grids", "attention_grids"]


@pytest.mark.parametrize("views, iterations", [("fixed", 20), ("fresh", 0)])
def test_a_backprojection_start_on_maps_that_never_differ_is_refused_before_any_work(make_sphere_grid, views,
                                                                                     iterations):
    """Maps equal on every pixel back-project to two equal grids, which a fit on those same maps (fixed views), or
    none, leaves equal: the back-projection and every step had run for the cut to find no seeds. Refused first."""
    grid = make_sphere_grid(10)
    edit_maps = torch.linspace(0.2, 0.9, 12).expand(4, 12, 12)
    config = RefineConfig(lift_start="backprojection", iterations=iterations, rays_per_step=64, fit_views=views)
    reports = []
    fresh_view = lambda step: (cameras_around(1, 12, seed=step), edit_maps[0], edit_maps[0].flip(-1))  # noqa: E731
    read = "" if iterations else r" the back-projection reads \(one row and column in 2\)"  # (its pixels alone)
    with pytest.raises(SegmentationError, match=rf"^the edit and object maps are equal on every pixel{read} of the 4 "
                                                r"views \(of 4\) that see the edited object: .* from "
                                                r"lift_start='backprojection', and the cut would have no seeds; "
                                                r"nothing was fitted$"):
        fit_attention_grids(grid, cameras_around(4, 12, seed=1), edit_maps, edit_maps.clone(), config,
                            Callbacks(on_progress=reports.append), fresh_view=fresh_view)
    assert reports == []
    object_maps = edit_maps.clone()  # apart on one pixel: back-projected, and fitted
    object_maps[:, 6, 6] += 0.05
    fit_attention_grids(grid, cameras_around(4, 12, seed=1), edit_maps, object_maps, config,
                        Callbacks(on_progress=reports.append), fresh_view=fresh_view)
    assert [p.stage for p in reports] == ["backprojection"] + ["attention_grids"] * iterations


def test_with_no_iterations_maps_apart_only_off_the_backprojections_stride_are_refused_before_any_work(
        make_sphere_grid):
    """With no fitting steps the grids are the back-projection's, which reads every ``backprojection_stride``-th row
    and column: maps apart only on the other pixels had passed the early refusal (it compared every pixel that sees
    the object), been back-projected to two equal grids and reached the cut for its "no seeds"."""
    from voxe_core.refine.lifting import strided_pixels

    grid = make_sphere_grid(10)
    cameras = cameras_around(4, 12, seed=1)
    edit_maps = torch.linspace(0.2, 0.9, 12).expand(4, 12, 12).clone()
    read = strided_pixels(4, 12, 12, 2).view(4, 12, 12)
    off_stride = edit_maps + 0.3 * ~read
    config = RefineConfig(lift_start="backprojection", iterations=0, backprojection_stride=2)
    reports = []
    with pytest.raises(SegmentationError, match=r"^the edit and object maps are equal on every pixel the "
                                                r"back-projection reads \(one row and column in 2\) of the 4 views "
                                                r"\(of 4\) that see the edited object: .* nothing was fitted$"):
        fit_attention_grids(grid, cameras, edit_maps, off_stride, config, Callbacks(on_progress=reports.append))
    assert reports == []
    on_stride = edit_maps + 0.3 * read  # apart on the pixels it reads: back-projected to grids that differ
    edit, obj = fit_attention_grids(grid, cameras, edit_maps, on_stride, config, Callbacks(on_progress=reports.append))
    assert [p.stage for p in reports] == ["backprojection"] and not prefer_neither(edit, obj)


@pytest.mark.parametrize("prior", [1e6, 1e30])
def test_a_backprojection_prior_that_drowns_the_maps_is_named_as_the_cause(make_sphere_grid, prior):
    """A prior far above the pixels' weight divides every vertex's average down to grids equal but for rounding (the
    maps apart everywhere): the cut had said "no seeds ... too few fitting iterations, or maps that do not tell the
    edit from the object", blaming neither the prior nor any setting that was set."""
    grid, cameras = make_sphere_grid(10), cameras_around(4, 12, seed=1)
    edit_maps = torch.linspace(0.2, 0.9, 12).expand(4, 12, 12)
    config = RefineConfig(iterations=0, backprojection_prior=prior)
    with pytest.raises(SegmentationError, match=rf"^the back-projected attention grids are equal everywhere but for "
                                                rf"float32 rounding, though the maps differ .*: backprojection_prior="
                                                rf"{re.escape(f'{prior:g}')} outweighs the pixels' weight .* lower "
                                                rf"backprojection_prior \(the default: 0.1\), or fit iterations > 0$"):
        fit_attention_grids(grid, cameras, edit_maps, edit_maps.flip(-1), config)
    edit, obj = fit_attention_grids(grid, cameras, edit_maps, edit_maps.flip(-1), RefineConfig(iterations=0))
    assert not prefer_neither(edit, obj)  # the default prior's grids differ


def test_a_constant_start_fit_equal_but_for_the_order_its_gradients_are_summed_in_is_still_named(make_sphere_grid,
                                                                                                 monkeypatch):
    """On CUDA the backward's atomic adds sum each channel's terms in any order, so the two grids differ by rounding
    (1e-8): an exact comparison had let the fit through and the cut seed on float noise. Emulated here by summing
    the object channel's gradient in the reverse order."""
    from voxe_core.grid import _WeightedGather

    def reordered_backward(ctx, grad):
        index, weights, _ = ctx.saved_tensors
        rows = (weights[..., None] * grad[:, None, :]).to(ctx.table_dtype).reshape(-1, ctx.table_shape[-1])
        flat = index.reshape(-1)
        table = grad.new_zeros(ctx.table_shape, dtype=ctx.table_dtype)
        table[:, :1].index_add_(0, flat, rows[:, :1])
        table[:, 1:].index_add_(0, flat.flip(0), rows[:, 1:].flip(0))  # the same terms, another order
        return table, None, None

    monkeypatch.setattr(_WeightedGather, "backward", staticmethod(reordered_backward))
    grid = make_sphere_grid(10)
    edit_maps = torch.linspace(0.2, 0.9, 12).expand(4, 12, 12)
    config = RefineConfig(lift_start="constant", iterations=2, rays_per_step=256, fit_views="fixed", fit_pixels="all")
    with pytest.raises(SegmentationError, match="^the attention grids are still equal everywhere after 2 fitting"):
        fit_attention_grids(grid, cameras_around(4, 12, seed=1), edit_maps, edit_maps.flip(-1), config)


def test_fields_equal_but_for_float32_rounding_have_no_seeds():
    """Fields a CUDA fit left equal but for rounding, one ulp apart either way, prefer neither label anywhere: no
    seeds, where the cut had seeded on the noise."""
    grid, _ = two_blobs()
    edit_field = torch.full(grid.resolution, 0.7)
    checker = torch.arange(edit_field.numel()).reshape(grid.resolution) % 2 == 0
    object_field = torch.where(checker, torch.nextafter(edit_field, torch.tensor(1.0)),
                               torch.nextafter(edit_field, torch.tensor(0.0)))
    with pytest.raises(SegmentationError, match="^no seeds: none of the .* occupied voxels is more likely edit"):
        graph_cut(grid, edit_field, object_field)
    assert not prefer_neither(edit_field, object_field + 1e-4) and not prefer_neither(edit_field, edit_field * math.nan)


# ----------------------------------------------------------------- graph cut


def text_cut(**overrides) -> RefineConfig:
    """The paper's text's graph cut (the unary term these tests rely on), with ``overrides``."""
    return dataclasses.replace(RefineConfig(**PAPER_TEXT_CUT), **overrides)


def two_blobs():
    """Two adjacent 6x8x8 boxes, red (edit, x in [3, 9)) and green (object, x in [9, 15))."""
    grid = box_grid(18, [((3, 5, 5), (9, 13, 13), (0.9, 0.1, 0.1)), ((9, 5, 5), (15, 13, 13), (0.1, 0.9, 0.1))])
    truth = torch.zeros(grid.resolution, dtype=torch.bool)
    truth[3:9, 5:13, 5:13] = True
    return grid, truth


def test_graph_cut_two_blobs_gives_the_expected_partition():
    grid, truth = two_blobs()
    g = torch.Generator().manual_seed(0)
    noise = 0.45 * torch.randn(grid.resolution, generator=g)
    e = truth.float() + noise
    o = 1.0 - truth.float() - noise
    nodes = node_mask(grid)
    p_e, _ = probabilities(e, o)
    assert ((p_e > 0.5) != truth)[nodes].sum() > 10  # the unary alone mislabels voxels...
    mask, stats = graph_cut_detailed(grid, e, o, text_cut(edit_seeds=50, object_seeds=50))
    assert torch.equal(mask, truth)  # ...the cut recovers the partition exactly
    assert stats.nodes == 2 * 6 * 8 * 8 and stats.edit_voxels == 6 * 8 * 8
    # 6-neighbour edges along all three axes between occupied vertices: a 12x8x8 box
    a, b, c = 12, 8, 8
    assert stats.edges == (a - 1) * b * c + a * (b - 1) * c + a * b * (c - 1)
    assert stats.edit_seeds == 50 and stats.object_seeds == 50 and not stats.notes


def test_graph_cut_smoothness_uses_the_z_axis_too():
    # a one-voxel-wide column along z: its only neighbours are along z; without z edges
    # the lone mislabelled middle voxel would keep its unary label
    grid = box_grid(12, [((5, 5, 1), (6, 6, 11), (0.5, 0.5, 0.5))])
    e = torch.zeros(grid.resolution)
    e[5, 5, 1:11] = 1.0
    e[5, 5, 6] = -0.3  # slightly prefers "object"
    o = torch.zeros(grid.resolution)
    mask = graph_cut(grid, e, o, text_cut(edit_seeds=3, object_seeds=0))
    assert mask[5, 5, 1:11].all() and int(mask.sum()) == 10


def test_pairwise_weights_text_and_code_formulas():
    # ‖(0.06, 0.08, 0)‖ = 0.1: the code's weight is K·e^(−‖Δc‖/σ) = 5/e (an L1 distance, 0.14, would give 5·e^-1.4)
    diff = np.array([[0.06, 0.08, 0.0], [0.0, 0.0, 0.0]])
    code = pairwise_weights(diff, RefineConfig(pairwise_weight="exp_distance", sigma=0.1, smoothness=5.0))
    text = pairwise_weights(diff, RefineConfig(pairwise_weight="gaussian", sigma=0.1, smoothness=5.0))
    np.testing.assert_allclose(code, [5.0 * math.exp(-1.0), 5.0], rtol=1e-12)
    np.testing.assert_allclose(text, [5.0 * math.exp(-0.5), 5.0], rtol=1e-12)  # 0.01 / (2·0.01)


@pytest.mark.parametrize("kind", ["exp_distance", "gaussian"])
def test_any_positive_sigma_gives_finite_weights_and_the_partition(kind):
    """The weights had been computed in the colours' float32: a σ below its range (σ² for the text's) made equal
    colours 0/0, NaN capacities and every node an edit."""
    grid, truth = two_blobs()
    e = torch.where(truth, 1.0, -1.0)
    config = RefineConfig(pairwise_weight=kind, sigma=1e-160)
    np.testing.assert_allclose(pairwise_weights(np.zeros((1, 3), np.float32), config), [config.smoothness], rtol=1e-12)
    mask, stats = graph_cut_detailed(grid, e, -e, config)
    assert torch.equal(mask, truth) and math.isfinite(stats.flow)
    with warnings.catch_warnings():  # a σ whose quotient overflows: weights 0 (for colours apart) without a warning
        warnings.simplefilter("error")
        for sigma in (1e-160, 1e-310):
            weights = pairwise_weights(np.array([[0.1, 0, 0], [0, 0, 0]], np.float32), RefineConfig(
                pairwise_weight=kind, sigma=sigma))
            assert weights.tolist() == [0.0, config.smoothness]


def test_a_smoothness_beyond_float32_is_refused_and_the_largest_allowed_cuts_with_a_finite_flow():
    """A λ near float64's largest had summed the weights into an infinite seed capacity and flow."""
    with pytest.raises(ValueError, match=r"^smoothness must be non-negative and at most 3.403e\+38, got 1e\+308$"):
        RefineConfig(smoothness=1e308)
    grid = box_grid(10, [((2, 2, 2), (8, 8, 8), (0.5, 0.5, 0.5))])  # one colour: every edge weighs λ
    e = torch.where(torch.arange(10)[:, None, None] < 5, 1.0, -1.0).expand(10, 10, 10)
    mask, stats = graph_cut_detailed(grid, e, -e, text_cut(smoothness=FLOAT32_MAX, edit_seeds=5, object_seeds=5))
    assert math.isfinite(stats.flow) and json.loads(json.dumps(stats.flow)) == stats.flow
    assert 0 < stats.edit_voxels < stats.nodes


@pytest.mark.parametrize("name, largest", [("lr", MAX_ATTENTION_LR), ("init_value", FLOAT32_MAX),
                                           ("tv_weight", FLOAT32_MAX)])
def test_an_attention_fit_setting_beyond_float32_is_refused_and_the_largest_allowed_is_not(name, largest):
    """An lr or init_value of 1e39 (an lr of 1e38, Adam's first step ten times it) had been accepted and failed the
    fit, after every attention pass, as a RuntimeError naming no setting ("value cannot be converted to type float
    without overflow"); a tv_weight of 1e39 had made both grids NaN."""
    rule = ("must be at most 3.403e+37 (Adam's first step, ten times it, finite in float32)" if name == "lr" else
            "must be at most 3.403e+38 in size (finite in float32)")
    for value in (1e39, 1e38) if name == "lr" else (1e39, -1e39) if name == "init_value" else (1e39,):
        with pytest.raises(ValueError, match=f"^{re.escape(f'{name} {rule}, got {value}')}$"):
            RefineConfig(**{name: value})
    assert getattr(RefineConfig(**{name: largest}), name) == largest
    if name == "lr":  # the fit's optimizer takes its first step at the largest lr, and refuses one a hair above it
        for lr, fails in ((largest, False), (largest * (1 + 1e-7), True)):
            values = torch.zeros(3, requires_grad=True)
            values.grad = torch.ones(3)
            with pytest.raises(RuntimeError, match="overflow") if fails else contextlib.nullcontext():
                torch.optim.Adam([values], lr=lr).step()


def test_a_seed_outside_the_services_range_is_refused_and_its_ends_cut():
    """A negative seed had run every attention pass and then failed in the cut's numpy draw ("expected
    non-negative integer")."""
    for seed in (-1, 2**32):
        with pytest.raises(ValueError, match=f"seed must lie in \\[0, 4294967295\\].*got {seed}"):
            RefineConfig(seed=seed)
    grid, truth = two_blobs()
    e = torch.where(truth, 1.0, -1.0)
    for seed in (0, 2**32 - 1):
        assert torch.equal(graph_cut(grid, e, -e, RefineConfig(seed=seed)), truth)


def test_maxpool_node_rule_is_the_occupied_set_dilated_by_one():
    grid = box_grid(7, [((3, 3, 3), (4, 4, 4), (0.5, 0.5, 0.5)), ((0, 0, 0), (1, 1, 1), (0.5, 0.5, 0.5))])
    assert int(node_mask(grid).sum()) == 2
    pooled = node_mask(grid, rule="maxpool")
    assert int(pooled.sum()) == 27 + 8  # a full 3x3x3 block in the middle, 2x2x2 at the corner
    assert pooled[2:5, 2:5, 2:5].all() and pooled[:2, :2, :2].all()


def test_without_unseeded_unary_the_cut_follows_the_colour_edge():
    # a z column, red on z 1..4 and blue on z 5..10; the attention says "edit" on z 1..8
    grid = box_grid(12, [((5, 5, 1), (6, 6, 5), (0.9, 0.1, 0.1)), ((5, 5, 5), (6, 6, 11), (0.1, 0.1, 0.9))])
    e = torch.full(grid.resolution, -10.0)
    e[5, 5, 1:9] = 10.0
    o = -e
    config = text_cut(edit_seeds=1, object_seeds=1)
    with_unary = graph_cut(grid, e, o, config)
    without = graph_cut(grid, e, o, dataclasses.replace(config, unseeded_unary="none"))
    assert with_unary[5, 5, 1:9].all() and int(with_unary.sum()) == 8  # the unary outweighs one blue-blue edge
    assert without[5, 5, 1:5].all() and int(without.sum()) == 4  # only seeds pull: the cheapest edge is red|blue


def test_random_object_seeds_come_from_p_obj_above_p_e_else_the_top_fallback():
    p_o = np.array([0.9, 0.2, 0.6, 0.7, 0.1, 0.8])
    p_e = 1.0 - p_o
    config = RefineConfig(object_seed_rule="random", object_seeds=3, object_seed_fallback=2, seed=4)
    seeds = object_seed_indices(p_e, p_o, config)
    assert len(set(seeds.tolist())) == 3 and set(seeds.tolist()) <= {0, 2, 3, 5}
    np.testing.assert_array_equal(seeds, object_seed_indices(p_e, p_o, config))  # reproducible from config.seed
    all_of_them = object_seed_indices(p_e, p_o, dataclasses.replace(config, object_seeds=10))
    np.testing.assert_array_equal(all_of_them, [0, 2, 3, 5])  # fewer candidates than wanted: every one
    none_qualify = object_seed_indices(np.full(6, 0.5), np.full(6, 0.5) - np.arange(6) * 0.01, config)
    np.testing.assert_array_equal(none_qualify, [0, 1])  # the top object_seed_fallback by P_obj
    with pytest.raises(ValueError, match="object_seed_rule"):
        RefineConfig(object_seed_rule="best")


def test_top_object_seeds_are_the_highest_p_obj_above_one_half_lower_index_first():
    """The paper's text: the ``object_seeds`` highest P_obj among P_obj > 1/2, ties to the lower index; a node of no
    preference (P_obj = P_e = 1/2) is no seed, however few the others."""
    p_o = np.array([0.5, 0.7, 0.9, 0.5, 0.7, 0.6, 0.1])
    config = RefineConfig(object_seed_rule="top", object_seeds=3)
    np.testing.assert_array_equal(object_seed_indices(1.0 - p_o, p_o, config), [2, 1, 4])
    every = object_seed_indices(1.0 - p_o, p_o, dataclasses.replace(config, object_seeds=10))
    np.testing.assert_array_equal(every, [2, 1, 4, 5])
    assert object_seed_indices(1.0 - p_o, p_o, dataclasses.replace(config, object_seeds=0)).size == 0


def test_the_default_cut_is_the_authors_code_but_for_the_seed_margin_and_seedless_pieces_and_recovers_two_blobs():
    assert all(getattr(RefineConfig(), k) == v for k, v in SERVICE_CUT.items())
    differs = {k for k, v in AUTHORS_CODE_CUT.items() if getattr(RefineConfig(), k) != v}
    assert differs == {"object_seed_margin", "unseeded_pieces"}
    assert AUTHORS_CODE_CUT["object_seed_margin"] == 0.0 and AUTHORS_CODE_CUT["unseeded_pieces"] == "edit"
    grid, truth = two_blobs()
    e = truth.float() * 4 - 2
    mask, stats = graph_cut_detailed(grid, e, -e, RefineConfig(edit_seeds=50))
    nodes = node_mask(grid)
    assert torch.equal(mask[nodes], truth[nodes]) and stats.nodes > int(nodes.sum())  # dilated node set


@pytest.mark.filterwarnings("ignore:only .* seeds")
def test_object_seeds_drawn_clear_of_one_half_keep_an_unresolved_inside_with_its_part():
    """The red blob's inside is seen by no view: P_obj = 0.505 there, a hair above P_e. The code's draw (margin 0)
    ties those voxels to the object and cuts the part hollow; with the default margin only the green blob's
    clear P_obj = 0.9 seeds the object, and the colour edge keeps the inside with its part."""
    grid, truth = two_blobs()
    p_e = torch.where(truth, 0.9, 0.1)
    inside = torch.zeros_like(truth)
    inside[4:8, 6:12, 6:12] = True
    p_e[inside] = 0.495
    e, o = torch.log(p_e), torch.log(1 - p_e)  # softmax(e, o) = (p_e, 1 - p_e)
    drawn_all = RefineConfig(object_seeds=10_000)  # more than the candidates: every one is drawn, whatever the seed
    codes = graph_cut(grid, e, o, dataclasses.replace(drawn_all, object_seed_margin=0.0))
    ours = graph_cut(grid, e, o, drawn_all)
    nodes = node_mask(grid)
    assert not codes[inside].any() and torch.equal(codes, truth & ~inside)
    assert torch.equal(ours[nodes], truth[nodes])
    candidates = object_seed_indices(p_e[nodes].numpy(), 1 - p_e[nodes].numpy(), drawn_all)
    assert not inside[nodes].numpy()[candidates].any() and len(candidates) == int((nodes & ~truth).sum())
    with pytest.raises(ValueError, match="object_seed_margin must lie in"):
        RefineConfig(object_seed_margin=1.0)


@pytest.mark.filterwarnings("ignore:only .* seeds")
def test_a_piece_no_seed_reaches_takes_the_label_its_probabilities_favour():
    """A detached green box that favours the object (P_obj 0.8) but holds no seed: with no unary max-flow leaves it
    on the edit side (the code's rule, ``unseeded_pieces="edit"``), and the default gives it to the object. With
    smoothness 0 every node is its own piece and takes its own preference."""
    grid = box_grid(18, [((2, 5, 5), (7, 13, 13), (0.9, 0.1, 0.1)), ((10, 5, 5), (15, 13, 13), (0.1, 0.9, 0.1))])
    red = torch.zeros(grid.resolution, dtype=torch.bool)
    red[:9] = True  # the red box and its max-pooled shell; the green one's nodes start at x = 9
    nodes = node_mask(grid, rule="maxpool")
    p_e = torch.where(red, 0.9, 0.2)
    p_e[12, 9, 9] = 0.7  # one green voxel leans to the edit
    e, o = torch.log(p_e), torch.log(1 - p_e)
    no_object_seeds = RefineConfig(object_seeds=0)
    codes, code_stats = graph_cut_detailed(grid, e, o, dataclasses.replace(no_object_seeds, unseeded_pieces="edit"))
    ours, stats = graph_cut_detailed(grid, e, o, no_object_seeds)
    assert torch.equal(codes[nodes], nodes[nodes]) and code_stats.unseeded_voxels == 0  # all edit, green too
    assert torch.equal(ours[nodes], red[nodes]) and stats.unseeded_voxels == int((nodes & ~red).sum())
    assert stats.edit_voxels == int((nodes & red).sum())
    alone = graph_cut(grid, e, o, dataclasses.replace(no_object_seeds, smoothness=0.0))
    assert torch.equal(alone[nodes], (p_e > 0.5)[nodes])  # the leaning voxel goes with its own P_e
    with pytest.raises(ValueError, match="unseeded_pieces must be one of"):
        RefineConfig(unseeded_pieces="object")


def test_graph_pieces_are_the_graphs_connected_components_on_either_path():
    """All weights positive: the node mask's 6-connected components (a lattice pass) equal the graph's connected
    components; a zero weight cuts its edge (the graph path)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    nodes = np.random.default_rng(0).random((9, 8, 7)) < 0.45
    ids = np.full(nodes.shape, -1)
    ids[nodes] = np.arange(int(nodes.sum()))
    heads, tails = [], []
    for axis in range(3):
        lo, hi = [slice(None)] * 3, [slice(None)] * 3
        lo[axis], hi[axis] = slice(0, -1), slice(1, None)
        pair = nodes[tuple(lo)] & nodes[tuple(hi)]
        heads.append(ids[tuple(lo)][pair])
        tails.append(ids[tuple(hi)][pair])
    heads, tails = np.concatenate(heads), np.concatenate(tails)
    n = int(nodes.sum())
    count, reference = connected_components(coo_matrix((np.ones(heads.size), (heads, tails)), shape=(n, n)),
                                            directed=False)
    pieces = graph_pieces(nodes, heads, tails, np.ones(heads.size))
    assert 1 < count < n and len(set(zip(pieces.tolist(), reference.tolist()))) == count == len(set(pieces.tolist()))
    line = np.zeros((4, 1, 1), bool)
    line[:, 0, 0] = True  # 0 - 1 - 2 - 3, the middle edge of weight 0
    assert graph_pieces(line, np.array([0, 1, 2]), np.array([1, 2, 3]), np.array([1.0, 0.0, 1.0])).tolist() == [
        0, 0, 1, 1]


def test_no_occupied_voxels_is_a_clear_error():
    grid = VoxelGrid(8, init_density=-1.0)
    with pytest.raises(SegmentationError, match="no occupied voxels"):
        graph_cut(grid, torch.zeros(8, 8, 8), torch.zeros(8, 8, 8))


def test_all_equal_probabilities_have_no_seeds():
    grid, _ = two_blobs()
    with pytest.raises(SegmentationError, match="no seeds"):
        graph_cut(grid, torch.full(grid.resolution, 0.7), torch.full(grid.resolution, 0.7))


def test_a_cut_asked_for_no_seeds_is_labelled_by_its_unary_term_or_refused_before_any_work_without_one():
    """Seed counts of 0, which the config takes, had been refused by the cut as "no seeds: none of the occupied
    voxels is more likely edit than object ... the attention grids are equal everywhere", though they differed and
    the paper's energy (its unary term) labels every voxel without seeds. Without a unary term nothing would, so
    that config is refused when it is made."""
    grid, truth = two_blobs()
    e = torch.where(truth, 1.0, -1.0)
    mask, stats = graph_cut_detailed(grid, e, -e, text_cut(edit_seeds=0, object_seeds=0))
    assert (stats.edit_seeds, stats.object_seeds, stats.notes) == (0, 0, [])
    assert torch.equal(mask, truth)
    with pytest.raises(ValueError, match=r"^edit_seeds=0 and object_seeds=0 under edit_seed_rule='top' seed no voxel, "
                                         r"and with unseeded_unary='none' nothing else labels one"):
        text_cut(edit_seeds=0, object_seeds=0, unseeded_unary="none")
    with pytest.raises(SegmentationError, match="no seeds"):  # grids that prefer nothing still cut nothing
        graph_cut(grid, torch.full(grid.resolution, 0.7), torch.full(grid.resolution, 0.7),
                  text_cut(edit_seeds=0, object_seeds=0))


def test_fewer_candidates_than_seeds_uses_what_exists():
    grid, truth = two_blobs()
    e = torch.where(truth, 1.0, -1.0)
    e[3, 5, 5] = e[3, 5, 6] = 0.0  # tie the first two: still candidates of neither label
    with pytest.warns(UserWarning, match="of 500 edit seeds"):  # 384 - 2 voxels prefer "edit"
        mask, stats = graph_cut_detailed(grid, e, -e, text_cut(edit_seeds=500, object_seeds=200))
    n_edit = int(truth.sum()) - 2
    assert stats.edit_seeds == n_edit and stats.object_seeds == 200
    assert any("edit seeds" in n for n in stats.notes)
    assert torch.equal(mask, truth)


def test_huge_logits_give_finite_probabilities_and_a_cut():
    grid, truth = two_blobs()
    e = torch.where(truth, 1e4, -1e4)
    p_e, p_o = probabilities(e, -e)
    assert torch.isfinite(p_e).all() and torch.isfinite(p_o).all()
    torch.testing.assert_close(p_e + p_o, torch.ones_like(p_e))
    assert torch.equal(p_e > 0.5, truth)
    mask, stats = graph_cut_detailed(grid, e[..., None], -e[..., None], text_cut())  # (X, Y, Z, 1) fields work as well
    assert torch.equal(mask, truth) and math.isfinite(stats.flow)


@pytest.mark.parametrize("edit_value, expected", [(2.0, True), (-2.0, False)])
def test_one_voxel_object(edit_value, expected):
    grid = box_grid(6, [((3, 3, 3), (4, 4, 4), (0.5, 0.5, 0.5))])
    e = torch.full(grid.resolution, edit_value)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        mask, stats = graph_cut_detailed(grid, e, torch.zeros(grid.resolution), text_cut())
    assert stats.nodes == 1 and stats.edges == 0
    assert int(mask.sum()) == int(expected) and bool(mask[3, 3, 3]) == expected


# ----------------------------------------------------------------- merge, storage, renders


def test_merge_selects_voxelwise_and_keeps_unmasked_bits():
    g = torch.Generator().manual_seed(1)
    initial = VoxelGrid(9, features=torch.randn(9, 9, 9, 4, generator=g))
    edited = VoxelGrid(9, features=torch.randn(9, 9, 9, 4, generator=g))
    with torch.no_grad():
        initial.features[0, 0, 0, 0] = -0.0  # signed zero and NaN survive bit for bit
        initial.features[0, 0, 1, 1] = float("nan")
    mask = torch.rand(9, 9, 9, generator=g) > 0.6
    mask[0, 0, :2] = False
    merged = merge(initial, edited, mask)
    bits = lambda t: t.detach().view(torch.int32)  # noqa: E731
    assert torch.equal(bits(merged.features)[~mask], bits(initial.features)[~mask])
    assert torch.equal(merged.features[mask], edited.features.detach()[mask])
    assert merged.features.data_ptr() != initial.features.data_ptr()
    with pytest.raises(ValueError, match="mask of shape"):
        merge(initial, edited, mask[:-1])
    with pytest.raises(ValueError, match="initial grid is"):
        merge(VoxelGrid(8), edited, mask)


def test_the_refined_file_is_the_merge_of_the_initial_and_edited_files_saved_differing_only_where_it_drops(
        tiny_guidance, make_sphere_grid, monkeypatch, tmp_path):
    """merge(initial file, edited file, mask file) is not refined_grid.safetensors tensor for tensor (the e2e test's
    mic job, its stages run in process, differed at 11,353 of 13,824 vertices): each sparse file fills the vertices
    it leaves out with their mean, and the refined file leaves out some the initial file stored (where the edit
    thinned the shape), so its fill is neither source's. Every vertex it stores equals the merge, the occupancy and
    renders (skipping or not) are the same, and the merge saved is the refined file byte for byte (the refinement
    merges those very files)."""
    import voxe_core.refine.pipeline
    from voxe_core.gridfile import DEFAULT_MARGIN, stored_vertices

    g = torch.Generator().manual_seed(3)
    initial = make_sphere_grid(24, radius=0.6)
    with torch.no_grad():
        initial.features[..., 1:] = torch.randn(24, 24, 24, 3, generator=g)  # empty space as varied as a fit's
        initial.features[18:20, 10:14, 10:14, 0] = 5.0  # a slab beside the ball
    edited = initial.clone_grid()
    with torch.no_grad():
        edited.features.add_(0.05 * torch.randn(24, 24, 24, 4, generator=g))  # an edit moves every vertex a little
        edited.features[19, 10:14, 10:14, 0] = -1.0  # and thins the slab: the refined file stores less around it
    for name, grid in (("initial", initial), ("edited", edited)):
        grid.save(tmp_path / f"{name}.safetensors")
    downloaded_initial, downloaded_edited = (load_grid(tmp_path / f"{n}.safetensors") for n in ("initial", "edited"))

    def favouring_the_slab(grid, *args, **kwargs):
        edit_field = torch.full((*grid.resolution, 1), -5.0)
        edit_field[17:] = 5.0  # the slab's side
        return edit_field, -edit_field

    monkeypatch.setattr(voxe_core.refine.pipeline, "fit_attention_grids", favouring_the_slab)
    result = refine(downloaded_initial, downloaded_edited, "a ball wearing a hat", ["hat"], tiny_guidance,
                    RefineConfig(views=2, render_size=16, object_seeds=50))
    result.refined_grid.save(tmp_path / "refined.safetensors")  # the files the refine stage publishes
    save_mask(tmp_path / "mask.safetensors", result.mask)
    refined, mask = load_grid(tmp_path / "refined.safetensors"), load_mask(tmp_path / "mask.safetensors")
    assert mask[18:20, 10:14, 10:14].all() and not mask[:16].any()  # the slab, not the ball

    merged = merge(load_grid(tmp_path / "initial.safetensors"), load_grid(tmp_path / "edited.safetensors"), mask)
    cells = refined.occupancy_above(0.0).cells
    stored = stored_vertices(cells, DEFAULT_MARGIN)  # the vertices the refined file holds
    differing = (merged.features != refined.features).any(-1)
    assert differing.any() and not (differing & stored).any()
    assert (merged.features[differing][:, 0] <= 0).all()  # no density, and no occupied cell within the margin
    assert torch.equal(merged.occupancy_above(0.0).cells, cells)
    cameras = cameras_around(3, 32)
    for skip_empty in (True, False):
        config = RenderConfig(skip_empty=skip_empty)
        for view in range(3):
            assert torch.equal(render_image(merged, cameras, view, config).rgb,
                               render_image(refined, cameras, view, config).rgb)
    merged.save(tmp_path / "merged.safetensors")
    assert (tmp_path / "merged.safetensors").read_bytes() == (tmp_path / "refined.safetensors").read_bytes()


@pytest.mark.parametrize("edited, refusal", [
    (lambda: VoxelGrid(8, activation="softplus"), "the initial grid's activation is 'relu' but the edited grid's 'softplus'"),
    (lambda: VoxelGrid(8, density_scale=3.0), r"the initial grid's density_scale is 33.3+ but the edited grid's 3.0"),
])
def test_grids_whose_raw_values_mean_different_densities_are_not_merged(edited, refusal):
    """Same resolution and box had been enough: the merge gave a softplus edit's voxels the ReLU grid's activation
    (a density of 0.87 read as 0.33)."""
    with pytest.raises(ValueError, match=refusal):
        merge(VoxelGrid(8), edited(), torch.ones(8, 8, 8, dtype=torch.bool))


def test_grids_of_different_boxes_are_not_merged_and_the_refusal_names_both_boxes(tmp_path, make_sphere_grid,
                                                                                   capsys):
    """Regression: 'the initial and edited grids span different boxes', naming neither."""
    refusal = (r"the initial grid spans the box \[-1.5, -1.5, -1.5\] to \[1.5, 1.5, 1.5\] but the edited grid "
               r"\[-1.0, -1.5, -1.5\] to \[2.0, 1.5, 1.5\]: is the edit of another reconstruction\?")
    edited = VoxelGrid(8, bbox_min=(-1.0, -1.5, -1.5), bbox_max=(2.0, 1.5, 1.5))
    with pytest.raises(ValueError, match=refusal):
        merge(VoxelGrid(8), edited, torch.ones(8, 8, 8, dtype=torch.bool))
    make_sphere_grid(8).save(tmp_path / "initial.safetensors")
    edited.save(tmp_path / "edited.safetensors")
    assert main(["refine", str(tmp_path / "edited.safetensors"), "--initial", str(tmp_path / "initial.safetensors"),
                 "--prompt", "a dog wearing a party hat", "--edit-words", "hat", "--out", str(tmp_path / "out"),
                 "--model", str(tmp_path / "no_model_needed"), "--offline", "--device", "cpu", "--quiet"]) == 2
    assert re.search(refusal, capsys.readouterr().err) and not (tmp_path / "out").exists()


@pytest.mark.parametrize("changed, refusal", [
    ({"foreground_extent": 4.0}, "the initial grid's foreground_extent is 1.5 but the edited grid's 4.0"),
    ({"frame": [[1, 0, 0, 3], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]}, "the initial grid's frame is"),
    ({"far_ratio": 10.0}, "the initial grid's far_ratio is"),
])
def test_scene_grids_of_another_capture_are_not_merged(changed, refusal):
    """A scene grid's box is always [-2, 2]³: its extent, frame and far samples (the header's) had not been
    compared, so an edit of another capture merged read in the initial grid's frame and extent."""
    from voxe_core.scene_grid import SceneGrid

    initial = SceneGrid(8)
    with pytest.raises(ValueError, match=re.escape(refusal)):
        merge(initial, SceneGrid(8, **{"density_scale": initial.density_scale, **changed}),
              torch.ones(8, 8, 8, dtype=torch.bool))
    merge(initial, initial.clone_grid(), torch.ones(8, 8, 8, dtype=torch.bool))  # as the edit pairs them


def test_the_readme_reader_of_a_downloaded_mask_gives_the_mask_in_the_grid_order(tmp_path):
    """The README's reader of mask.safetensors (safetensors + numpy, no voxe_core), run as written there: the
    artifact list named the file but nothing said what it holds."""
    import re

    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    reader = re.search(r"As a boolean array indexed like the grid's `features`:\n\n```python\n(.*?)```", readme, re.S)[1]
    mask = torch.zeros(5, 6, 7, dtype=torch.bool)
    mask[1, 2, 3] = mask[4, 5, 6] = mask[0, 0, 1] = True  # unequal axes: a transposed or reversed read differs
    save_mask(tmp_path / "mask.safetensors", mask, {"prompt": "a hat", "edit_words": ["hat"]})
    namespace = {"path": str(tmp_path / "mask.safetensors")}
    exec(reader, namespace)  # the README's own code, as a user copies it
    assert namespace["mask"].shape == (5, 6, 7) and namespace["mask"].dtype == bool
    assert np.array_equal(namespace["mask"], mask.numpy())


def test_sparse_mask_and_probabilities_round_trip(tmp_path):
    g = torch.Generator().manual_seed(2)
    mask = torch.rand(20, 18, 16, generator=g) > 0.97
    save_mask(tmp_path / "mask.safetensors", mask)
    assert torch.equal(load_mask(tmp_path / "mask.safetensors"), mask)
    assert (tmp_path / "mask.safetensors").stat().st_size < mask.numel() // 4  # ~3% set: far below a dense byte mask
    where = torch.rand(mask.shape, generator=g) > 0.8
    p = torch.rand(mask.shape, generator=g)
    save_probabilities(tmp_path / "p.safetensors", p, 1 - p, where)
    pe, po, w = load_probabilities(tmp_path / "p.safetensors")
    assert torch.equal(w, where) and torch.equal(pe[where], p[where]) and torch.equal(po[where], (1 - p)[where])
    assert (pe[~where] == 0).all()
    with pytest.raises(FormatError, match="expected a 'edit_mask'"):
        load_mask(tmp_path / "p.safetensors")


def test_a_grid_beyond_int32_voxel_indices_is_refused_before_its_probabilities_are_written(tmp_path):
    """As its mask is: 1291³ voxels pass 2^31, and the int32 indices had wrapped (the last voxel, 2,151,685,170,
    stored as -2,143,282,126), so load_probabilities refused the file it had just written as damaged. The refusal names
    the grid (it had said only 'grid too large for int32 voxel indices')."""
    n = 1291
    where, p = torch.zeros((), dtype=torch.bool).expand(n, n, n), torch.zeros(()).expand(n, n, n)  # nothing allocated
    refusal = (r"a grid of \(1291, 1291, 1291\) voxels \(2,151,685,171\) is too large for the files' int32 voxel "
               r"indices \(fewer than 2,147,483,648 voxels\)")
    for save in (lambda path: save_probabilities(path, p, p, where), lambda path: save_mask(path, where)):
        with pytest.raises(ValueError, match=refusal):
            save(tmp_path / "big.safetensors")
        assert not (tmp_path / "big.safetensors").exists()


@pytest.mark.parametrize("shape", [(2**21,) * 3, (4096,) * 3])
def test_a_damaged_file_claiming_a_grid_beyond_int32_indices_is_a_format_error(tmp_path, shape):
    """Its shape had reached torch.zeros: an overflow TypeError, or a 64 GiB allocation's RuntimeError, where a
    damaged file is a FormatError (voxe evaluate --mask had shown a traceback)."""
    path = tmp_path / "mask.safetensors"
    save_mask(path, torch.zeros(2, 2, 2, dtype=torch.bool))
    tensors, _ = load_tensors(path, kind="edit_mask", max_version=1)
    save_tensors(path, {**tensors, "shape": torch.tensor(shape)}, kind="edit_mask", version=1, meta={})
    with pytest.raises(FormatError, match=r"beyond the int32 voxel indices"):
        load_mask(path)


INDEX_DAMAGES = [
    # indices of no integer dtype had been cut to integers (1.7 read as voxel 1, true as voxel 1)
    (lambda t: {**t, "indices": t["indices"].float() + 0.7}, "'indices' is torch.float32, not integers"),
    (lambda t: {**t, "indices": t["indices"] > 0}, "'indices' is torch.bool, not integers"),
    (lambda t: {**t, "shape": t["shape"].double() + 0.9}, "'shape' is torch.float64, not integers"),
    # a shape not of 3 entries had been a TypeError from int() (a list, or an int not iterable)
    (lambda t: {**t, "shape": t["shape"][None]}, r"bad grid shape \[\[4, 5, 6\]\], not 3 positive voxel counts"),
    (lambda t: {**t, "shape": t["shape"][0]}, "bad grid shape 4, not 3 positive voxel counts"),
    # a voxel given twice had loaded: a probability file's two values for it, one taken as it happened
    (lambda t: {**t, "indices": t["indices"][[0, 1, 1, 2, 2]]}, r"voxel index 9 is given more than once \(2 repeats\)"),
]
PROBABILITY_DAMAGES = [  # had loaded: NaN and 2.5 as probabilities
    (lambda t: {**t, "edit": t["edit"] * float("nan")}, r"'edit' holds values outside \[0, 1\] \(or NaN\)"),
    (lambda t: {**t, "object": t["object"] + 1.5}, r"'object' holds values outside \[0, 1\]"),
]


@pytest.mark.parametrize("kind, damage, message", [
    *(("edit_mask", *case) for case in INDEX_DAMAGES),
    *(("attention_probabilities", *case) for case in INDEX_DAMAGES + PROBABILITY_DAMAGES),
])
def test_a_damaged_mask_or_probability_file_is_a_format_error_naming_the_problem(tmp_path, kind, damage, message):
    where = torch.zeros(4, 5, 6, dtype=torch.bool)
    where.view(-1)[[3, 9, 77]] = True
    path = tmp_path / "file.safetensors"
    save_probabilities(path, torch.full(where.shape, 0.25), torch.full(where.shape, 0.75), where)
    tensors, _ = load_tensors(path, kind="attention_probabilities", max_version=1)
    save_tensors(path, damage(tensors), kind=kind, version=1, meta={})
    with pytest.raises(FormatError, match=message) as error:
        (load_mask if kind == "edit_mask" else load_probabilities)(path)
    assert str(error.value).startswith(str(path))


@contextlib.contextmanager
def zeros_allocated():
    """The shapes given to torch.zeros meanwhile (a list filled as they come): what a reader allocated."""
    allocations = []
    real_zeros = torch.zeros
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(torch, "zeros", lambda *a, **k: allocations.append(a) or real_zeros(*a, **k))
        yield allocations


def test_a_mask_file_claiming_another_grid_is_refused_before_its_voxels_are_allocated(tmp_path):
    """Regression: a 252-byte file claiming 1290³ voxels allocated 2 GB before its caller
    (voxe evaluate --edit ... MASK, the worker's evaluation) found that it did not fit the grid."""
    path = tmp_path / "mask.safetensors"
    save_tensors(path, {"indices": torch.tensor([3], dtype=torch.int32), "shape": torch.tensor([1290] * 3)},
                 kind="edit_mask", version=1, meta={})
    with zeros_allocated() as allocations:
        with pytest.raises(FormatError, match=r"a mask of a grid of \(1290, 1290, 1290\) voxels, where "
                                              r"\(16, 16, 16\) was expected"):
            load_mask(path, (16, 16, 16))
    assert allocations == []
    save_mask(path, torch.ones(16, 16, 16, dtype=torch.bool))
    assert load_mask(path, (16, 16, 16)).all()


def test_a_probability_file_claiming_another_grid_or_damaged_is_refused_before_its_grids_are_allocated(tmp_path):
    """As a mask file is: a 300-byte file claiming 1290³ voxels had allocated two 8.6 GB float grids and a 2 GB
    mask, with no way to say which grid it must fit; a damaged 'object' was found after 'edit''s grid was made, and
    values of the right count but shaped (K, 1) failed as torch's broadcast error after both grids were made."""
    path = tmp_path / "probabilities.safetensors"
    one = {"indices": torch.tensor([3], dtype=torch.int32), "edit": torch.tensor([0.5]), "object": torch.tensor([0.5])}
    save_tensors(path, {**one, "shape": torch.tensor([1290] * 3)}, kind="attention_probabilities", version=1, meta={})
    damaged = tmp_path / "damaged.safetensors"
    save_tensors(damaged, {**one, "shape": torch.tensor([16] * 3), "object": torch.tensor([2.0])},
                 kind="attention_probabilities", version=1, meta={})
    column = tmp_path / "column.safetensors"
    two = {"indices": torch.tensor([3, 4], dtype=torch.int32), "edit": torch.tensor([0.5, 0.5])}
    save_tensors(column, {**two, "shape": torch.tensor([16] * 3), "object": torch.tensor([[0.5], [0.5]])},
                 kind="attention_probabilities", version=1, meta={})
    with zeros_allocated() as allocations:
        with pytest.raises(FormatError, match=r"probabilities of a grid of \(1290, 1290, 1290\) voxels, where "
                                              r"\(16, 16, 16\) was expected \(probabilities are of their initial "
                                              r"grid, whose resolution its edited grid shares\)"):
            load_probabilities(path, (16, 16, 16))
        with pytest.raises(FormatError, match=r"'object' holds values outside \[0, 1\]"):
            load_probabilities(damaged, (16, 16, 16))
        with pytest.raises(FormatError, match=r"'object' values do not match the stored indices"):
            load_probabilities(column, (16, 16, 16))
    assert allocations == []
    where = torch.zeros(16, 16, 16, dtype=torch.bool)
    where[1, 2, 3] = True
    save_probabilities(path, torch.full(where.shape, 0.25), torch.full(where.shape, 0.75), where)
    edit, object_, stored = load_probabilities(path, (16, 16, 16))
    assert torch.equal(stored, where) and float(edit.sum()) == 0.25 and float(object_.sum()) == 0.75


def test_renders_grey_attention_and_red_mask(make_sphere_grid):
    grid = make_sphere_grid(16)
    with torch.no_grad():
        grid.features[..., 1:] = 2.0  # near-white object
    cams = Cameras.from_fov(torch.tensor([[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 4.0], [0, 0, 0, 1]]), 0.69, 24, 24)
    half = torch.zeros(grid.resolution, dtype=torch.bool)
    half[:8] = True  # x < 0: the left of the image for a camera on +z looking down
    grey = next(iter_attention_views(grid, half.float(), cams))
    assert torch.equal(grey[..., 0], grey[..., 1]) and grey[12, 8, 0] > 0.9 and grey[12, 16, 0] < 0.1
    assert grey[0, 0].abs().max() == 0  # black background
    over = next(iter_mask_overlays(grid, half, cams))
    assert over[12, 8, 0] > 0.8 and over[12, 8, 1] < 0.5  # tinted red where the mask is
    assert over[12, 16].min() > 0.8 and over[0, 0].min() == 1.0  # untouched (white) elsewhere


def test_streamed_pictures_are_those_of_the_whole_ring_at_once(make_sphere_grid):
    """One view at a time, each picture is bit for bit the one rendering the whole ring at once gave (the views
    stacked, then tinted / clamped as one tensor)."""
    from voxe_core.export import render_views, turntable_cameras

    grid = make_sphere_grid(12)
    cams = turntable_cameras(4, 30.0, 20)
    field = torch.rand(grid.resolution, generator=torch.Generator().manual_seed(0))
    mask = field > 0.5
    coverage = (0.65 * render_feature_views(grid, cams, mask.float()[..., None])).clamp(0.0, 1.0)
    overlays = render_views(grid, cams) * (1.0 - coverage) + coverage * torch.tensor((1.0, 0.0, 0.0))
    assert torch.equal(torch.stack(list(iter_mask_overlays(grid, mask, cams))), overlays)
    grey = render_feature_views(grid, cams, field[..., None]).clamp(0.0, 1.0).expand(-1, -1, -1, 3)
    assert torch.equal(torch.stack(list(iter_attention_views(grid, field, cams))), grey)
    features = torch.stack([field, 1 - field], -1)
    assert torch.equal(render_feature_views(grid, cams, features),
                       torch.stack(list(iter_feature_views(grid, cams, features))))


def test_cli_refine_saves_each_preview_view_before_rendering_the_next(tmp_path, tiny_model, make_sphere_grid,
                                                                      monkeypatch):
    """Regression: voxe refine rendered all five preview sets whole before it saved the first PNG (the service
    allows 1,000 views of 1,024²: 12.6 GB of floats a set). Each view is saved before the next is rendered: at
    every save at most the view and its sources (an overlay's render and coverage) are alive. The PNGs are those of
    the whole sets."""
    import voxe_core.export
    import voxe_core.refine.pipeline
    from test_export import views_alive
    from voxe_core.export import render_views, turntable_cameras

    grid = make_sphere_grid(12)
    grid.save(tmp_path / "grid.safetensors", dense=True)
    edit_field = torch.where(torch.arange(12)[:, None, None, None] < 6, 5.0, -5.0).expand(12, 12, 12, 1)
    monkeypatch.setattr(voxe_core.refine.pipeline, "fit_attention_grids", lambda *args, **kwargs: (edit_field,
                                                                                                   -edit_field))
    real_save_png, alive = voxe_core.export.save_png, []

    def counting_save_png(path, image):
        alive.append(views_alive(16, 16))
        real_save_png(path, image)

    monkeypatch.setattr(voxe_core.export, "save_png", counting_save_png)
    out = tmp_path / "out"
    assert main(["refine", str(tmp_path / "grid.safetensors"), "--initial", str(tmp_path / "grid.safetensors"),
                 "--prompt", "a dog wearing a party hat", "--edit-words", "party hat", "--out", str(out),
                 "--model", str(tiny_model), "--offline", "--device", "cpu", "--iterations", "1", "--render-size",
                 "16", "--views", "1", "--preview-views", "5", "--quiet"]) == 0
    assert len(alive) == 5 * 5 + 2 and max(alive) <= 3, alive  # five sets of five views, a 2D map of each kind
    mask = load_mask(out / "mask.safetensors")
    assert mask[:6].any()  # the half the attention favoured is tinted
    cams = turntable_cameras(5, 30.0, 16, centre=grid.orbit_centre())
    coverage = (0.65 * render_feature_views(grid, cams, mask.float()[..., None])).clamp(0.0, 1.0)
    whole_sets = {"mask": render_views(grid, cams) * (1.0 - coverage) + coverage * torch.tensor((1.0, 0.0, 0.0)),
                  "attention_edit": render_feature_views(grid, cams, edit_field).clamp(0.0, 1.0).expand(-1, -1, -1, 3)}
    for name, frames in whole_sets.items():
        for i, frame in enumerate(frames):
            real_save_png(tmp_path / "whole" / f"{name}_{i:02d}.png", frame)
            assert (out / "renders" / f"{name}_{i:02d}.png").read_bytes() == \
                (tmp_path / "whole" / f"{name}_{i:02d}.png").read_bytes()


def test_masked_l1_ignores_pixels_whose_rendered_attention_is_not_positive():
    rendered = torch.tensor([[0.4, 0.0], [0.0, -0.2], [0.9, 0.3]], requires_grad=True)
    targets = torch.tensor([[0.0, 1.0], [1.0, 1.0], [0.1, 0.3]])
    loss = attention_l1(rendered, targets, "rendered_positive")
    loss.backward()
    assert float(loss.detach()) == pytest.approx((0.4 + 0.8) / 6)
    assert (rendered.grad[rendered.detach() <= 0] == 0).all() and (rendered.grad[0, 0] > 0)
    assert float(attention_l1(rendered, targets)) == pytest.approx((0.4 + 1 + 1 + 1.2 + 0.8) / 6)


def test_fresh_views_give_every_step_its_own_pose_and_maps(make_sphere_grid):
    grid = make_sphere_grid(10)
    cams = cameras_around(2, 8)
    maps = torch.full((2, 8, 8), 0.5)
    calls = []

    def fresh_view(step):
        calls.append(step)
        return cameras_around(1, 8, seed=100 + step), torch.ones(1, 8, 8), torch.zeros(1, 8, 8)

    config = RefineConfig(iterations=5, fit_views="fresh", fit_pixels="all", lr=0.2)
    e, o = fit_attention_grids(grid, cams, maps, maps, config, fresh_view=fresh_view)
    assert calls == [0, 1, 2, 3, 4]
    seen = e[..., 0] != 0
    assert float(e[..., 0][seen].mean()) > 0.5 > float(o[..., 0][seen].mean())  # pulled towards the fresh maps
    with pytest.raises(ValueError, match="fresh_view"):
        fit_attention_grids(grid, cams, maps, maps, config)


def test_refine_with_the_authors_fresh_fit_runs_one_diffusion_pass_per_step(tiny_guidance, make_sphere_grid, monkeypatch):
    initial = make_sphere_grid(10)
    edited = initial.clone_grid()
    passes = []
    original = tiny_guidance.cross_attention_maps
    monkeypatch.setattr(tiny_guidance, "cross_attention_maps",
                        lambda image, prompt, **kw: passes.append(prompt) or original(image, prompt, **kw))
    config = RefineConfig(views=2, render_size=16, edit_seeds=5, object_seeds=5, **{**AUTHORS_CODE_FIT, "iterations": 3})
    result = refine(initial, edited, "a dog wearing sunglasses", ["sunglasses"], tiny_guidance, config)
    assert len(passes) == 2 + 3 and all(p.endswith(" view") for p in passes)
    assert result.mask.shape == (10, 10, 10)


def test_a_numpy_seed_refines_as_the_python_one(tiny_guidance, make_sphere_grid):
    """Regression: RefineConfig takes numpy whole numbers, but torch's generators refuse them: seed=np.int64(3)
    passed the config and failed the refinement at its first pose ("an integer is required")."""
    initial = make_sphere_grid(10)
    masks = []
    for seed in (np.int64(3), 3):
        config = RefineConfig(views=2, render_size=16, edit_seeds=5, object_seeds=5, seed=seed,
                              **{**AUTHORS_CODE_FIT, "iterations": 2})
        masks.append(refine(initial, initial.clone_grid(), "a dog wearing sunglasses", ["sunglasses"], tiny_guidance,
                            config).mask)
    assert torch.equal(*masks)


# ----------------------------------------------------------------- end to end


class ProtocolOnly:
    """A guidance seen through the :class:`Guidance` protocol only: any other attribute is an AttributeError."""

    MEMBERS = set(Guidance.__annotations__) | {name for name in vars(Guidance) if not name.startswith("_")}

    def __init__(self, guidance):
        self._guidance = guidance

    def __getattr__(self, name):
        if name not in self.MEMBERS:
            raise AttributeError(f"{name!r} is not a member of the Guidance protocol")
        return getattr(self._guidance, name)


def test_a_guidance_with_only_the_protocols_members_edits_and_refines(tiny_guidance, make_sphere_grid):
    """The refinement had also called content_token_indices, which the protocol did not name: a model implementing
    exactly the protocol passed isinstance and then failed the refinement."""
    guidance = ProtocolOnly(tiny_guidance)
    assert isinstance(guidance, Guidance)
    initial = make_sphere_grid(10)
    edited = edit(initial, "a dog wearing sunglasses", guidance, EditConfig(iterations=1, render_size=16))
    config = RefineConfig(views=1, render_size=16, iterations=2, edit_seeds=5, object_seeds=5)
    result = refine(initial, edited, "a dog wearing sunglasses", ["sunglasses"], guidance, config)
    assert result.mask.shape == (10, 10, 10)


def test_a_float16_guidance_seen_through_the_protocol_alone_is_refused_cpu_autocast(tiny_sd_path, make_sphere_grid):
    """The edit read ``dtype`` through getattr, outside the protocol: a float16 model implementing exactly the protocol
    passed the check and failed its first step in GroupNorm with torch's "mixed dtype (CPU)"."""
    half = StableDiffusionGuidance.from_pretrained(str(tiny_sd_path), device="cpu", dtype=torch.float16,
                                                   local_files_only=True)
    with pytest.raises(ValueError, match=r"^autocast on the CPU runs under bfloat16, where a float16 model fails"):
        edit(make_sphere_grid(10), "a dog", ProtocolOnly(half),
             EditConfig(iterations=1, render_size=16, autocast_dtype="bf16"))


def test_refine_end_to_end_with_tiny_model(tiny_guidance, make_sphere_grid):
    initial = make_sphere_grid(12)
    edited = initial.clone_grid()
    with torch.no_grad():
        edited.features[..., 1:] = torch.randn(12, 12, 12, 3, generator=torch.Generator().manual_seed(0))
    config = RefineConfig(views=2, render_size=24, iterations=40, rays_per_step=256, edit_seeds=5, object_seeds=5,
                          render=dataclasses.replace(RefineConfig().render, chunk_rays=50))
    reports = []
    result = refine(initial, edited, "a dog wearing sunglasses", ["sunglasses"], tiny_guidance, config,
                    Callbacks(on_progress=lambda p: reports.append((p.stage, p.iteration, p.total))))
    assert {stage for stage, _, _ in reports} == {"attention_maps", "backprojection", "attention_grids", "graph_cut"}
    # The sub-steps count on one scale (2 views + the back-projection's 6 chunks of 50 of its 2 x 12² rays + 40 fit
    # steps + the cut): only rising, the back-projection's share as a view's per chunk (1 unit had frozen the stage).
    assert {total for _, _, total in reports} == {2 + 6 + 40 + 1}
    done = [iteration for _, iteration, _ in reports]
    assert done == sorted(done) and done[-1] == 49 and reports[1][:2] == ("attention_maps", 2)
    lifting = [iteration for stage, iteration, _ in reports if stage == "backprojection"]
    assert len(set(lifting)) == len(lifting) > 1 and lifting[-1] == 2 + 6
    assert result.info["prompt"] == "a render of a dog wearing sunglasses"
    nodes = node_mask(edited, rule=config.node_rule)  # the mask never leaves the graph's nodes
    assert result.mask.shape == nodes.shape and not (result.mask & ~nodes).any()
    torch.testing.assert_close(result.edit_probability + result.object_probability, torch.ones(12, 12, 12))
    assert torch.equal(result.refined_grid.features, merge(initial, edited, result.mask).features)
    assert result.edit_maps.shape == (2, 24, 24) and result.edit_field.shape == (12, 12, 12, 1)
    with pytest.raises(ValueError, match="does not occur"):
        refine(initial, edited, "a dog", ["zebra"], tiny_guidance, config)


def test_refine_reads_the_edit_words_in_the_users_prompt_not_the_prefix_it_adds(tiny_guidance, make_sphere_grid):
    initial = make_sphere_grid(12)
    reports = []
    config, callbacks = RefineConfig(views=2, render_size=16), Callbacks(on_progress=reports.append)
    # "a render of" is the stage's, not the user's: it neither holds an edit word nor names the object
    with pytest.raises(ValueError, match="'render' does not occur in the prompt 'a dog wearing sunglasses'"):
        refine(initial, initial.clone_grid(), "a dog wearing sunglasses", ["render"], tiny_guidance, config, callbacks)
    for alone in ("sunglasses", "  sunglasses. "):  # (the model never reads a trailing full stop)
        with pytest.raises(ValueError, match="nothing names the object"):
            refine(initial, initial.clone_grid(), alone, ["sunglasses"], tiny_guidance, config, callbacks)
    assert reports == []  # refused before the first attention pass
    # a user who wrote the prefix keeps its words as theirs
    result = refine(initial, initial.clone_grid(), "a render of sunglasses", ["sunglasses"], tiny_guidance, config)
    assert result.info["prompt"] == "a render of sunglasses"


def test_a_nan_density_fails_the_refinement_before_any_attention_map(tiny_guidance, make_sphere_grid):
    initial = make_sphere_grid(12)
    edited = initial.clone_grid()
    with torch.no_grad():
        edited.features[6, 6, 6, 0] = float("nan")
    reports = []
    with pytest.raises(SegmentationError, match="density is NaN at 1 of the 1728 vertices"):
        refine(initial, edited, "a dog wearing sunglasses", ["sunglasses"], tiny_guidance,
               RefineConfig(views=2, render_size=16, iterations=2), Callbacks(on_progress=reports.append))
    assert reports == []  # not after the attention passes, minutes into the stage


def test_attention_maps_that_are_not_finite_are_named_at_their_view(tiny_guidance, make_sphere_grid, monkeypatch):
    """A pass that overflowed (NaN at an edit token of the second view) had been refused only by the cut, after the
    fit, as fields "not finite" from "a diverged edit or attention-grid fit"."""
    original, passes = tiny_guidance.cross_attention_maps, []

    def overflowing(image, prompt, **kw):
        maps = original(image, prompt, **kw)
        passes.append(prompt)
        if len(passes) == 2:
            maps[tiny_guidance.token_spans(prompt, ["sunglasses"])[0], 3, 4] = float("nan")
        return maps

    monkeypatch.setattr(tiny_guidance, "cross_attention_maps", overflowing)
    initial = make_sphere_grid(10)
    with pytest.raises(SegmentationError, match="maps of view 2 of 3 are not finite"):
        refine(initial, initial.clone_grid(), "a dog wearing sunglasses", ["sunglasses"], tiny_guidance,
               RefineConfig(views=3, render_size=16))
    assert len(passes) == 2


def test_an_empty_edited_grid_fails_the_refinement_before_any_attention_map(tiny_guidance, make_sphere_grid):
    """An edit that emptied the grid (or left only density below the render's threshold) had been refused by the
    fit, after every attention pass."""
    reports = []
    for emptied in (VoxelGrid(12, init_density=-1.0), VoxelGrid(12, init_density=1e-6)):
        with pytest.raises(SegmentationError, match="the edited grid has no occupied voxels"):
            refine(make_sphere_grid(12), emptied, "a dog wearing sunglasses", ["sunglasses"], tiny_guidance,
                   RefineConfig(views=2, render_size=16), Callbacks(on_progress=reports.append))
    assert reports == []


def test_a_grid_with_no_node_under_the_cuts_rule_fails_the_refinement_before_any_attention_map(tiny_guidance,
                                                                                             make_sphere_grid):
    """A faint edit, rendered (above the render's threshold) but never 1% opaque a voxel, has no node under the
    text's rule (node_rule="alpha"): it had been refused by the cut, after every attention pass and the lift."""
    faint, reports = VoxelGrid(12, init_density=1e-3), []
    config = RefineConfig(views=2, render_size=16, node_rule="alpha")
    with pytest.raises(SegmentationError, match="no occupied voxels: the edited grid's density never makes a voxel 1% "
                                                "opaque"):
        refine(make_sphere_grid(12), faint, "a dog wearing sunglasses", ["sunglasses"], tiny_guidance, config,
               Callbacks(on_progress=reports.append))
    assert reports == []
    assert not faint.occupancy(config.render.sigma_threshold).empty  # the render's own test passes it


def test_cli_refine_warns_when_the_cut_keeps_nothing(tmp_path, tiny_model, make_sphere_grid, monkeypatch, capsys):
    """A cut that kept none of the voxels (attention favouring the object everywhere) said "0 of N voxels take the
    edit" and nothing more; the service's job warns that the edit is undone, and so does the CLI."""
    import voxe_core.refine.pipeline

    initial = make_sphere_grid(8)
    initial.save(tmp_path / "initial.safetensors", dense=True)
    initial.save(tmp_path / "edited.safetensors", dense=True)

    def favouring_the_object(grid, *args, **kwargs):
        edit_field = torch.full((*grid.resolution, 1), -5.0)
        return edit_field, -edit_field

    monkeypatch.setattr(voxe_core.refine.pipeline, "fit_attention_grids", favouring_the_object)
    assert main(["refine", str(tmp_path / "edited.safetensors"), "--initial", str(tmp_path / "initial.safetensors"),
                 "--prompt", "a dog wearing a party hat", "--edit-words", "party hat", "--out", str(tmp_path / "out"),
                 "--model", str(tiny_model), "--offline", "--device", "cpu", "--iterations", "1", "--render-size",
                 "16", "--views", "1", "--preview-views", "0", "--quiet"]) == 0
    warning = [line for line in capsys.readouterr().err.splitlines() if "warning" in line]
    assert len(warning) == 1 and warning[0].startswith("voxe refine: warning: the graph cut kept none of the edited "
                                                       "grid's "), warning


def test_cli_refine_records_every_setting_it_ran_with(tmp_path, tiny_model, make_sphere_grid, monkeypatch):
    """Regression: refine.json had recorded only the views, render size, iterations and seed, not --sigma,
    --smoothness, --lr, the seed counts or --lift-start: a result could not be reproduced from it."""
    import voxe_core.refine.pipeline

    def favouring_the_object(grid, *args, **kwargs):  # (a fit of one step from a constant seeds nothing)
        edit_field = torch.full((*grid.resolution, 1), -5.0)
        return edit_field, -edit_field

    monkeypatch.setattr(voxe_core.refine.pipeline, "fit_attention_grids", favouring_the_object)
    initial = make_sphere_grid(8)
    initial.save(tmp_path / "initial.safetensors", dense=True)
    initial.save(tmp_path / "edited.safetensors", dense=True)
    out = tmp_path / "out"
    assert main(["refine", str(tmp_path / "edited.safetensors"), "--initial", str(tmp_path / "initial.safetensors"),
                 "--prompt", "a dog wearing a party hat", "--edit-words", "party hat", "--out", str(out),
                 "--model", str(tiny_model), "--offline", "--device", "cpu", "--iterations", "1", "--render-size",
                 "16", "--views", "1", "--preview-views", "0", "--quiet", "--sigma", "0.25", "--smoothness", "3",
                 "--lr", "0.02", "--tv-weight", "0.5", "--edit-seeds", "7", "--object-seeds", "9", "--lift-start",
                 "constant", "--smoothing-sigma", "0", "--rays", "64", "--no-view-words", "--seed", "5"]) == 0
    settings = json.loads((out / "refine.json").read_text())["settings"]
    assert {name: settings[name] for name in ("sigma", "smoothness", "lr", "tv_weight", "edit_seeds", "object_seeds",
                                              "lift_start", "smoothing_sigma", "rays_per_step", "view_word_prompt",
                                              "views", "render_size", "iterations", "seed")} == {
        "sigma": 0.25, "smoothness": 3.0, "lr": 0.02, "tv_weight": 0.5, "edit_seeds": 7, "object_seeds": 9,
        "lift_start": "constant", "smoothing_sigma": 0.0, "rays_per_step": 64, "view_word_prompt": False,
        "views": 1, "render_size": 16, "iterations": 1, "seed": 5}
    assert settings["fit_views"] == "fixed" and settings["attention_model"] == str(tiny_model)  # what they resolved to
    assert RefineConfig(**{**settings, "render": RenderConfig(**settings["render"])}).sigma == 0.25  # a config again


def test_cli_refine_with_the_tiny_model_says_and_records_it_is_a_smoke_test(tmp_path, tiny_model, make_sphere_grid,
                                                                             monkeypatch, capsys):
    """``voxe refine --model`` a folder ``voxe build-tiny-model`` wrote said nothing of its random weights: the mask
    passed for one. It says so once on stderr (even --quiet) and in refine.json's and the refined grid's ``smoke_test``;
    a real-looking folder without the tiny model's model_index.json mark, neither (unless the edited grid has one)."""
    import shutil

    import voxe_core.refine.pipeline
    from voxe_core.backbones import grid_notes

    def favouring_the_object(grid, *args, **kwargs):  # (a fit of one step from a constant seeds nothing)
        edit_field = torch.full((*grid.resolution, 1), -5.0)
        return edit_field, -edit_field

    monkeypatch.setattr(voxe_core.refine.pipeline, "fit_attention_grids", favouring_the_object)
    real = shutil.copytree(tiny_model, tmp_path / "real")
    index = json.loads((real / "model_index.json").read_text())
    (real / "model_index.json").write_text(json.dumps({**index, "_name_or_path": "CompVis/stable-diffusion-v1-4"}))
    (real / "README.md").unlink()
    make_sphere_grid(8).save(tmp_path / "grid.safetensors", dense=True)
    note = (f"{tiny_model} is a random-weight smoke-test Stable Diffusion (voxe build-tiny-model): what is made with "
            "it proves the plumbing only and says nothing about edit quality")
    for model, said in ((Path(tiny_model), [f"voxe refine: SMOKE TEST: {note}"]), (real, [])):
        capsys.readouterr()
        assert main(["refine", str(tmp_path / "grid.safetensors"), "--initial", str(tmp_path / "grid.safetensors"),
                     "--prompt", "a dog wearing a party hat", "--edit-words", "party hat",
                     "--out", str(tmp_path / model.name), "--model", str(model), "--offline", "--device", "cpu",
                     "--iterations", "1", "--render-size", "16", "--views", "1", "--preview-views", "0",
                     "--quiet"]) == 0
        assert [line for line in capsys.readouterr().err.splitlines() if "SMOKE" in line] == said
        summary = json.loads((tmp_path / model.name / "refine.json").read_text())
        assert summary["model"] == str(model) and summary.get("smoke_test") == (note if said else None)
        assert grid_notes(tmp_path / model.name / "refined.safetensors") == ({"smoke_test": note} if said else {})
    # An edited grid a smoke-test edit made (its header's note), refined with a real-looking model: the refinement is
    # of a noise edit, said as the grid's commands say it, and carried into refine.json and the refined grid (both had
    # dropped it)
    make_sphere_grid(8).save(tmp_path / "edited.safetensors", dense=True, notes={"smoke_test": note})
    assert main(["refine", str(tmp_path / "edited.safetensors"), "--initial", str(tmp_path / "grid.safetensors"),
                 "--prompt", "a dog wearing a party hat", "--edit-words", "party hat", "--out", str(tmp_path / "noted"),
                 "--model", str(real), "--offline", "--device", "cpu", "--iterations", "1", "--render-size", "16",
                 "--views", "1", "--preview-views", "0", "--quiet"]) == 0
    assert [line for line in capsys.readouterr().err.splitlines() if "SMOKE" in line] == [
        f"voxe refine: SMOKE TEST: {tmp_path / 'edited.safetensors'} was edited with a smoke-test model: {note}"]
    assert json.loads((tmp_path / "noted" / "refine.json").read_text())["smoke_test"] == note
    assert grid_notes(tmp_path / "noted" / "refined.safetensors") == {"smoke_test": note}


def test_cli_refine_smoke(tmp_path, tiny_model, make_sphere_grid):
    initial = make_sphere_grid(12)
    edited = initial.clone_grid()
    with torch.no_grad():
        edited.features[:, :, 6:, 1:] = torch.tensor([-3.0, -3.0, 3.0])  # a blue top half
    initial.save(tmp_path / "initial.safetensors", dense=True)  # dense in and out: every vertex compared
    edited.save(tmp_path / "edited.safetensors", dense=True)
    out = tmp_path / "out"
    (out / "renders").mkdir(parents=True)
    for earlier in ("mask_07.png", "map2d_edit_11.png", "notes.png"):  # an earlier run's 8+ views, and the user's file
        (out / "renders" / earlier).write_bytes(b"earlier")
    def argv(model=str(tiny_model), words="party hat"):
        return ["refine", str(tmp_path / "edited.safetensors"), "--initial", str(tmp_path / "initial.safetensors"),
                "--prompt", "a dog wearing a party hat", "--edit-words", words, "--out", str(out),
                "--model", model, "--offline", "--device", "cpu", "--iterations", "40", "--render-size", "16",
                "--views", "2", "--preview-views", "1", "--quiet", "--dense"]

    assert main(argv()) == 0
    mask = load_mask(out / "mask.safetensors")
    refined = load_grid(out / "refined.safetensors")
    assert torch.equal(refined.features, merge(initial, edited, mask).features)
    summary = json.loads((out / "refine.json").read_text())
    assert summary["masked_voxels"] == int(mask.sum()) and summary["edit_words"] == ["party hat"]
    pngs = {p.name for p in (out / "renders").glob("*.png")}
    assert {"mask_00.png", "attention_edit_00.png", "attention_object_00.png", "refined_00.png", "map2d_edit_00.png"} <= pngs
    assert "mask_07.png" not in pngs and "map2d_edit_11.png" not in pngs and "notes.png" in pngs  # (had stayed)
    assert all(PREVIEW_FRAME.fullmatch(name) for name in pngs - {"notes.png"})  # every frame it writes it would clear
    _, _, where = load_probabilities(out / "probabilities.safetensors")
    assert torch.equal(where, node_mask(edited, rule=RefineConfig().node_rule))  # the cut's nodes: the default rule's
    assert not (mask & ~where).any()  # every masked voxel has its probabilities

    assert main(argv(model=str(tmp_path / "no_such_model"))) == 2  # ModelNotAvailableError -> exit 2
    assert main(argv(words=" , ")) == 2
    assert main(argv(words="zebra")) == 2  # not in the prompt

    # A disk that fills while refine.json is written (the half of it written, then ENOSPC): the summary had been
    # written into its final name, leaving half a JSON document in place of the earlier run's.
    earlier = (out / "refine.json").read_text()
    real_write_text = Path.write_text

    def disk_fills(path, text, *args, **kwargs):
        if not path.name.endswith(".json"):
            return real_write_text(path, text, *args, **kwargs)
        real_write_text(path, text[: len(text) // 2], *args, **kwargs)
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(Path, "write_text", disk_fills)
        assert main(argv()) == 1  # a full disk: the machine's failure
    assert (out / "refine.json").read_text() == earlier
    assert not list(out.glob(".*"))


def test_a_refinement_failing_part_way_leaves_the_earlier_runs_outputs_as_they_were(tmp_path, tiny_model,
                                                                                   make_sphere_grid, monkeypatch,
                                                                                   capsys):
    """Its outputs had been written straight into --out: one failing while it wrote its previews (a full disk) left
    its own grids and mask beside the earlier run's previews, and refine.json of neither, as if complete. They are
    staged beside --out and moved in once all are written; a second run into the same --out is refused."""
    import fcntl
    import os

    import voxe_core.export

    grid = make_sphere_grid(8)
    grid.save(tmp_path / "grid.safetensors", dense=True)
    out = tmp_path / "out"

    def refine_into_out(iterations: str) -> int:
        return main(["refine", str(tmp_path / "grid.safetensors"), "--initial", str(tmp_path / "grid.safetensors"),
                     "--prompt", "a dog wearing a party hat", "--edit-words", "party hat", "--out", str(out),
                     "--model", str(tiny_model), "--offline", "--device", "cpu", "--iterations", iterations,
                     "--render-size", "16", "--views", "1", "--preview-views", "2", "--quiet"])

    assert refine_into_out("1") == 0
    earlier = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert len([p for p in earlier if p.parent.name == "renders"]) == 5 * 2 + 2 * 1
    real_save_png, saved = voxe_core.export.save_png, []

    def failing_at_the_third(path, image):
        if len(saved) == 2:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        saved.append(path)
        real_save_png(path, image)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(voxe_core.export, "save_png", failing_at_the_third)
        assert refine_into_out("2") == 1  # a full disk: the machine's failure
    assert len(saved) == 2
    assert {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()} == earlier

    assert refine_into_out("0") == 0  # (the same --out again: the staging folder went with the failed run)
    staging = out / ".refine-staging"
    staging.mkdir()
    (staging / ".voxe-staging").write_text("voxe refine's")
    held = os.open(staging, os.O_RDONLY)  # a run writing into the same --out holds it
    try:
        fcntl.flock(held, fcntl.LOCK_EX)
        capsys.readouterr()
        assert refine_into_out("1") == 2
        assert f"another voxe refine is writing into {out}" in capsys.readouterr().err
        assert staging.is_dir()  # that run's left as it was
    finally:
        os.close(held)


def refine_one_view_into(out, grid, model) -> int:
    """``voxe refine`` of ``grid`` against itself into ``out``: one view of 16 px, one preview, one iteration."""
    return main(["refine", str(grid), "--initial", str(grid), "--prompt", "a dog wearing a party hat",
                 "--edit-words", "party hat", "--out", str(out), "--model", str(model), "--offline", "--device", "cpu",
                 "--iterations", "1", "--render-size", "16", "--views", "1", "--preview-views", "1", "--quiet"])


def test_an_output_path_refine_cannot_write_fails_it_at_once_and_a_failed_move_leaves_no_summary(
        tmp_path, tiny_model, make_sphere_grid, monkeypatch, capsys):
    """A folder named as one of its outputs in --out had failed the move after the whole refinement, the earlier
    previews already deleted and some new grids moved in beside the earlier refine.json, which described neither
    run. Every output path is checked before the refinement, and the earlier refine.json goes before the first
    move: refine.json in --out means the set is whole."""
    import voxe_core.refine.pipeline
    from voxe_core.cli.common import staging_folder
    from voxe_core.cli.refine import OUTPUT_FILES, _move_outputs

    grid = make_sphere_grid(8)
    grid.save(tmp_path / "grid.safetensors", dense=True)
    out = tmp_path / "out"
    (out / "renders").mkdir(parents=True)
    for name in OUTPUT_FILES:
        (out / name).write_text("earlier")
    (out / "renders" / "refined_00.png").write_text("earlier")
    (out / "probabilities.safetensors").unlink()
    (out / "probabilities.safetensors").mkdir()  # in the way
    earlier = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    refined = []
    monkeypatch.setattr(voxe_core.refine.pipeline, "refine", lambda *args, **kwargs: refined.append(args))
    capsys.readouterr()
    assert refine_one_view_into(out, tmp_path / "grid.safetensors", tiny_model) == 2
    assert f"cannot write {out / 'probabilities.safetensors'}: it is a folder" in capsys.readouterr().err
    assert refined == []  # failed before the refinement
    assert {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()} == earlier

    with pytest.raises(OSError), staging_folder(out, "refine") as staging:  # a move failing part way all the same
        (staging / "renders").mkdir()
        (staging / "renders" / "refined_00.png").write_text("new")
        for name in OUTPUT_FILES:
            (staging / name).write_text("new")
        _move_outputs(staging, out)
    assert not (out / "refine.json").exists()  # no summary beside the mix


@pytest.mark.parametrize("frame", ["mask_00.png", "map2d_object_00.png"])
def test_a_folder_named_as_a_preview_frame_fails_refine_before_the_refinement(
        tmp_path, make_sphere_grid, monkeypatch, capsys, frame):
    """A folder under renders/ named as a frame this run writes had failed the move after the whole refinement, the
    earlier refine.json already removed: the frames' paths are checked with the other outputs', first."""
    import voxe_core.refine.pipeline
    from voxe_core.cli.refine import OUTPUT_FILES

    make_sphere_grid(8).save(tmp_path / "grid.safetensors", dense=True)
    out = tmp_path / "out"
    (out / "renders" / frame).mkdir(parents=True)  # in the way
    for name in OUTPUT_FILES:
        (out / name).write_text("earlier")
    earlier = {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()}
    refined = []
    monkeypatch.setattr(voxe_core.refine.pipeline, "refine", lambda *args, **kwargs: refined.append(args))
    capsys.readouterr()
    assert refine_one_view_into(out, tmp_path / "grid.safetensors", tmp_path / "no-model") == 2
    assert f"cannot write {out / 'renders' / frame}: it is a folder" in capsys.readouterr().err
    assert refined == []
    assert {p.relative_to(out): p.read_bytes() for p in out.rglob("*") if p.is_file()} == earlier


def test_refine_checks_the_preview_frames_it_writes_and_no_others():
    """Ring previews for every preview view; the 2D maps only for views the refinement has (a folder named as a
    frame of more views is none of this run's business)."""
    from voxe_core.cli.refine import PREVIEW_FRAME, _preview_frames

    frames = _preview_frames(2, 1)
    assert frames == ["attention_edit_00.png", "attention_edit_01.png", "attention_object_00.png",
                      "attention_object_01.png", "probability_edit_00.png", "probability_edit_01.png", "mask_00.png",
                      "mask_01.png", "refined_00.png", "refined_01.png", "map2d_edit_00.png", "map2d_object_00.png"]
    assert all(PREVIEW_FRAME.fullmatch(name) for name in frames)
    assert _preview_frames(0, 4) == []


def test_relative_edit_seeds_take_every_node_near_the_largest_edit_probability():
    # the authors' rule: every node with P_e >= 0.992 max P_e (here 40 nodes), at least edit_seeds by P_e,
    # never a node the object claims more
    grid = box_grid(10, [((2, 2, 2), (8, 8, 8), (0.5, 0.5, 0.5))])
    nodes = node_mask(grid)
    e = torch.zeros(grid.resolution)
    idx = nodes.nonzero()
    e[tuple(idx[:40].T)] = 8.0  # P_e ~ 0.99966, all within 0.992 of the max
    e[tuple(idx[40:45].T)] = 3.0  # P_e ~ 0.95: below the ratio
    o = torch.zeros_like(e)
    _, stats = graph_cut_detailed(grid, e, o, text_cut(edit_seed_rule="relative", edit_seeds=10, object_seeds=0))
    assert stats.edit_seeds == 40
    _, stats = graph_cut_detailed(grid, e, o, text_cut(edit_seed_rule="relative", edit_seeds=43, object_seeds=0))
    assert stats.edit_seeds == 43  # the top-k floor, all of them still more likely edit than object
    _, stats = graph_cut_detailed(grid, e, o, text_cut(edit_seed_rule="relative", edit_seeds=60, object_seeds=0))
    assert stats.edit_seeds == 45  # nodes at P_e = 1/2 are never edit seeds
    with pytest.raises(ValueError, match="edit_seed_rule"):
        RefineConfig(edit_seed_rule="max")


@pytest.mark.parametrize("shape", [(6, 5, 4), (4, 4, 4, 2), (3, 5, 4), (4, 5, 4, 1, 2)])
def test_probabilities_of_another_grid_than_where_are_refused_and_nothing_is_written(tmp_path, shape):
    """``where`` of (4, 5, 4) and grids of 6·5·4 voxels had written the first 80 voxels' values at ``where``'s
    indices, read back as the probabilities of other voxels; smaller grids failed on an IndexError."""
    where = torch.ones(4, 5, 4, dtype=torch.bool)
    right, wrong = torch.full((4, 5, 4), 0.25), torch.rand(shape)
    for edit_probability, object_probability in ((wrong, right), (right, wrong)):
        with pytest.raises(ValueError, match=r"of shape .* is not of the voxels 'where' names, \(4, 5, 4\)"):
            save_probabilities(tmp_path / "p.safetensors", edit_probability, object_probability, where)
        assert not (tmp_path / "p.safetensors").exists()
    save_probabilities(tmp_path / "p.safetensors", right[..., None], 1 - right, where)  # (X, Y, Z, 1): its voxels
    assert torch.equal(load_probabilities(tmp_path / "p.safetensors")[0], right)


def test_fresh_views_without_their_source_are_refused_before_the_backprojection(make_sphere_grid, monkeypatch):
    """The back-projection (81 s at 160³ and 32 views on a CPU) had run first, to be thrown away by this refusal."""
    def no_backprojection(*args, **kwargs):
        raise AssertionError("the back-projection ran")

    monkeypatch.setattr(lifting, "backproject", no_backprojection)
    grid, cams = make_sphere_grid(10), cameras_around(2, 8)
    maps = torch.linspace(0, 1, 8).expand(2, 8, 8)
    with pytest.raises(ValueError, match="fit_views='fresh' needs fresh_view"):
        fit_attention_grids(grid, cams, maps, maps.flip(-1), RefineConfig(iterations=3, fit_views="fresh"))


def test_an_edited_grid_whose_colour_is_nan_is_named_before_any_attention_pass(tiny_guidance, make_sphere_grid,
                                                                              monkeypatch):
    """Its NaN render had reached the model, whose NaN maps were refused as "its pass overflowed (a float16
    model?)": the model blamed for the grid."""
    original, passes = tiny_guidance.cross_attention_maps, []

    def counted(*args, **kwargs):
        passes.append(args)
        return original(*args, **kwargs)

    monkeypatch.setattr(tiny_guidance, "cross_attention_maps", counted)
    initial = make_sphere_grid(12)
    edited = initial.clone_grid()
    with torch.no_grad():
        edited.features[6, 6, 6, 2] = float("nan")
    with pytest.raises(SegmentationError, match=r"^the render of the edited grid for view 1 of 2 is not finite "
                                                r"\(NaN or infinite\): the grid's colour"):
        refine(initial, edited, "a dog wearing sunglasses", ["sunglasses"], tiny_guidance,
               RefineConfig(views=2, render_size=16))
    assert passes == []


def test_a_mask_that_is_not_binary_is_refused_by_the_merge():
    """G_r = M·G_e + (1 − M)·G_i is a selection: a soft mask had been cast to bool, 0.3 (or NaN) taking G_e whole."""
    initial, edited = VoxelGrid(6, init_density=1.0), VoxelGrid(6, init_density=2.0)
    for soft in (torch.full((6, 6, 6), 0.3), torch.full((6, 6, 6), float("nan")), torch.full((6, 6, 6), 2)):
        with pytest.raises(ValueError, match="the mask must be binary"):
            merge(initial, edited, soft)
    ones = torch.zeros(6, 6, 6)
    ones[:3] = 1.0  # 0 and 1 in another dtype select as a bool mask does
    assert torch.equal(merge(initial, edited, ones).features, merge(initial, edited, ones.bool()).features)


def test_a_mask_that_is_not_binary_is_not_saved(tmp_path):
    """As the merge refuses it: a soft mask had been written set wherever it was not 0 (every voxel, for 0.3)."""
    with pytest.raises(ValueError, match="the mask must be binary"):
        save_mask(tmp_path / "mask.safetensors", torch.full((4, 4, 4), 0.3))
    assert not (tmp_path / "mask.safetensors").exists()
    ones = torch.zeros(4, 4, 4)
    ones[1] = 1.0
    save_mask(tmp_path / "mask.safetensors", ones)
    assert torch.equal(load_mask(tmp_path / "mask.safetensors"), ones.bool())


def test_attention_views_of_more_than_one_value_per_vertex_are_refused_naming_the_shape(make_sphere_grid):
    """Two channels (both attention fields at once) had failed in torch's expand, naming no argument."""
    grid = make_sphere_grid(8)
    cams = cameras_around(1, 8)
    with pytest.raises(ValueError, match=r"one scalar per vertex, \(X, Y, Z\) or \(X, Y, Z, 1\), got \(8, 8, 8, 2\)"):
        next(iter_attention_views(grid, torch.zeros(8, 8, 8, 2), cams))
    assert next(iter_attention_views(grid, torch.zeros(8, 8, 8, 1), cams)).shape == (8, 8, 3)


@pytest.mark.parametrize("bad", [3.0, float("nan"), -0.25])
def test_probabilities_the_loader_refuses_are_not_saved(tmp_path, bad):
    """A raw (X, Y, Z, 1) attention field (or NaN) had been written, to be refused by load_probabilities as read."""
    where = torch.ones(4, 5, 4, dtype=torch.bool)
    fine, wrong = torch.full((4, 5, 4, 1), 0.5), torch.full((4, 5, 4, 1), bad)
    for name, edit_probability, object_probability in (("edit", wrong, fine), ("object", fine, wrong)):
        with pytest.raises(ValueError, match=rf"^{name}_probability holds values outside \[0, 1\] \(or NaN\)"):
            save_probabilities(tmp_path / "p.safetensors", edit_probability, object_probability, where)
        assert not (tmp_path / "p.safetensors").exists()
    unstored = fine.clone()
    unstored[0, 0, 0] = bad
    where[0, 0, 0] = False  # only the stored voxels are held to it, as the loader holds them
    save_probabilities(tmp_path / "p.safetensors", unstored, fine, where)
    assert torch.equal(load_probabilities(tmp_path / "p.safetensors")[2], where)


def test_a_where_that_is_not_xyz_is_refused_naming_where(tmp_path):
    """A (4, 5, 4, 1) ``where`` had been refused as "edit_probability of shape (4, 5, 4) is not of the voxels 'where'
    names": the right grid blamed for the wrong mask."""
    grid = torch.full((4, 5, 4), 0.5)
    with pytest.raises(ValueError, match=r"^'where' must be the \(X, Y, Z\) mask .* got shape \(4, 5, 4, 1\)"):
        save_probabilities(tmp_path / "p.safetensors", grid, grid, torch.ones(4, 5, 4, 1, dtype=torch.bool))
    assert not (tmp_path / "p.safetensors").exists()


def test_a_where_that_is_not_binary_is_not_saved(tmp_path):
    """A soft ``where`` (0.3, a probability) had been cast to bool: every voxel stored."""
    grid = torch.full((4, 4, 4), 0.5)
    with pytest.raises(ValueError, match="^'where' must be binary"):
        save_probabilities(tmp_path / "p.safetensors", grid, grid, torch.full((4, 4, 4), 0.3))
    assert not (tmp_path / "p.safetensors").exists()
    where = torch.zeros(4, 4, 4)
    where[1] = 1.0  # 0 and 1 in another dtype store as a bool mask does
    save_probabilities(tmp_path / "p.safetensors", grid, grid, where)
    assert torch.equal(load_probabilities(tmp_path / "p.safetensors")[2], where.bool())


def test_attention_views_of_a_wrong_shape_are_refused_by_the_call_before_any_view(make_sphere_grid, monkeypatch):
    """The refusal had come at the first next(): the CLI builds every preview's views before writing any, so a later
    group's bad grid was refused only after the earlier groups' frames had been written."""
    rendered = []
    real_views = renders.iter_feature_views

    def counted(*args, **kwargs):
        rendered.append(args)
        return real_views(*args, **kwargs)

    monkeypatch.setattr(renders, "iter_feature_views", counted)
    grid, cams = make_sphere_grid(8), cameras_around(1, 8)
    with pytest.raises(ValueError, match=r"one scalar per vertex, \(X, Y, Z\) or \(X, Y, Z, 1\), got \(8, 8, 8, 2\)"):
        iter_attention_views(grid, torch.zeros(8, 8, 8, 2), cams)  # the call, not iteration, refuses it
    assert rendered == []
    assert len(list(iter_attention_views(grid, torch.zeros(8, 8, 8), cams))) == 1
