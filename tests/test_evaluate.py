"""The evaluation protocol (SPEC §4): ring geometry, Fréchet distance, CLIP metrics, preservation outside the mask.

CLIP and Inception here are the tiny random-weight SMOKE-TEST models of
voxe_core.tiny_eval: they exercise the real loading and scoring code, never quality.
"""

from __future__ import annotations

import json
import math
import re
import shutil

import numpy as np
import pytest
import torch

from voxe_core.cameras import ring_poses
from voxe_core.constants import NERF_SYNTHETIC_RADIUS
from voxe_core.evaluate import (
    INCEPTION_FILE, INCEPTION_URL, ClipScorer, EditSample, EvaluateConfig, InceptionFeatures, clip_direction,
    clip_similarity, evaluate, evaluation_steps, feature_statistics, fid_from_features, format_table,
    frechet_distance, mask_footprint, paper_protocol, preservation, render_ring,
)
from voxe_core.guidance.loading import ModelNotAvailableError
from voxe_core.metrics import psnr, ssim
from voxe_core.progress import Callbacks, StageCancelled
from voxe_core.refine.pipeline import merge
from voxe_core.scene_grid import SceneGrid


@pytest.fixture(scope="module")
def tiny_clip_path(tmp_path_factory):
    from voxe_core.tiny_eval import build_tiny_clip

    return build_tiny_clip(tmp_path_factory.mktemp("tiny_clip") / "clip")


@pytest.fixture(scope="module")
def tiny_inception_path(tmp_path_factory):
    from voxe_core.tiny_eval import build_tiny_inception

    return build_tiny_inception(tmp_path_factory.mktemp("tiny_inception") / INCEPTION_FILE)


# ------------------------------------------------------------------------------------------ ring
def test_ring_poses_are_evenly_spaced_at_the_radius_and_elevation_looking_at_the_origin():
    poses = ring_poses(100, elevation_deg=25.0)
    eye = poses[:, :3, 3].double()
    assert poses.shape == (100, 4, 4)
    assert torch.allclose(eye.norm(dim=-1), torch.full((100,), NERF_SYNTHETIC_RADIUS, dtype=torch.float64), atol=1e-5)
    elevation = torch.rad2deg(torch.asin(eye[:, 2] / eye.norm(dim=-1)))
    assert torch.allclose(elevation, torch.full((100,), 25.0, dtype=torch.float64), atol=1e-4)
    azimuth = torch.rad2deg(torch.atan2(eye[:, 1], eye[:, 0]))
    steps = torch.remainder(azimuth.roll(-1) - azimuth, 360.0)  # includes the wrap from the last pose to the first
    assert torch.allclose(steps, torch.full((100,), 3.6, dtype=torch.float64), atol=1e-4)
    forward = -poses[:, :3, 2].double()  # OpenGL cameras look down -z
    assert torch.allclose(forward, -eye / eye.norm(dim=-1, keepdim=True), atol=1e-6)
    rotation = poses[:, :3, :3].double()
    assert torch.allclose(rotation.transpose(1, 2) @ rotation, torch.eye(3, dtype=torch.float64).expand(100, 3, 3), atol=1e-6)
    assert bool((poses[:, 2, 1] > 0).all())  # image up tilts towards world +z: no roll, upright views


def test_ring_renders_are_the_ring_cameras(sphere_grid):
    frames = render_ring(sphere_grid, 3, 30.0, 16)
    assert frames.shape == (3, 16, 16, 3)
    # A sphere at the origin looks the same from every azimuth: red centre, white corners.
    assert torch.allclose(frames[0], frames[1], atol=1e-3) and torch.allclose(frames[0], frames[2], atol=1e-3)
    assert frames[0, 8, 8, 0] > 0.9 and frames[0, 8, 8, 1] < 0.1 and bool((frames[:, 0, 0] > 0.99).all())


def test_evaluate_config_refuses_degenerate_rings():
    with pytest.raises(ValueError, match=r"views must be between 2 \(FID needs two samples\) and 360"):
        EvaluateConfig(views=1)
    with pytest.raises(ValueError, match=r"size must be between 11 px \(SSIM's window\) and 1024 px"):
        EvaluateConfig(size=8)
    with pytest.raises(ValueError, match="elevation must lie strictly between -90 and 90"):
        EvaluateConfig(elevation=90.0)


# ------------------------------------------------------------------------------------------ Fréchet distance
def test_frechet_distance_matches_the_closed_form_of_commuting_covariances():
    rng = np.random.default_rng(0)
    d = 6
    mu1, mu2 = rng.normal(size=d), rng.normal(size=d)
    a, b = rng.uniform(0.1, 3.0, size=d), rng.uniform(0.1, 3.0, size=d)
    expected = float(np.sum((mu1 - mu2) ** 2) + np.sum((np.sqrt(a) - np.sqrt(b)) ** 2))
    assert frechet_distance(mu1, np.diag(a), mu2, np.diag(b)) == pytest.approx(expected, rel=1e-10)
    # The same Gaussians in a rotated basis: non-diagonal covariances, same distance.
    q, _ = np.linalg.qr(rng.normal(size=(d, d)))
    rotated = frechet_distance(q @ mu1, q @ np.diag(a) @ q.T, q @ mu2, q @ np.diag(b) @ q.T)
    assert rotated == pytest.approx(expected, rel=1e-9)


def test_frechet_distance_of_singular_covariances_is_finite_and_exact():
    # Zero covariances: only the means differ.
    assert frechet_distance([0.0, 0.0], np.zeros((2, 2)), [3.0, 4.0], np.zeros((2, 2))) == pytest.approx(25.0)
    # Rank-1 against zero: tr(S1) = 4.
    s1 = np.outer([2.0, 0.0], [2.0, 0.0]) / 1.0
    assert frechet_distance([0, 0], s1, [0, 0], np.zeros((2, 2))) == pytest.approx(4.0)
    with pytest.raises(ValueError, match="mismatched Gaussians"):
        frechet_distance([0, 0], np.eye(2), [0, 0, 0], np.eye(3))


def test_fid_of_identical_sets_is_zero_even_with_fewer_samples_than_dimensions():
    rng = np.random.default_rng(1)
    full_rank = rng.normal(size=(200, 16))
    rank_deficient = rng.normal(size=(10, 64))  # covariance of rank 9 in 64 dimensions
    assert fid_from_features(full_rank, full_rank) == pytest.approx(0.0, abs=1e-8)
    assert fid_from_features(rank_deficient, rank_deficient) == pytest.approx(0.0, abs=1e-8)
    shifted = full_rank + 2.0
    assert fid_from_features(full_rank, shifted) == pytest.approx(4.0 * 16, rel=1e-9)  # ||Δmu||², same covariance
    other = rng.normal(size=(200, 16)) * 1.5
    assert fid_from_features(full_rank, other) == pytest.approx(fid_from_features(other, full_rank), rel=1e-9)


def test_fid_refuses_too_few_or_non_finite_features():
    with pytest.raises(ValueError, match="at least 2 feature vectors"):
        feature_statistics(np.ones((1, 4)))
    bad = np.ones((3, 4))
    bad[1, 2] = np.nan
    with pytest.raises(ValueError, match="NaN or inf"):
        feature_statistics(bad)


# ------------------------------------------------------------------------------------------ CLIP metrics
def test_clip_direction_sign_on_synthetic_embeddings():
    e = torch.eye(4)
    source, target = e[0], e[1]  # text directions: "a render of a dog" -> "... wearing sunglasses"
    recon = torch.stack([e[0], e[2]])
    towards = torch.stack([e[0] + e[1], e[2] + e[1]])  # both views gained the target concept
    away = torch.stack([e[0] - e[1], e[2] - e[1]])
    # View 0 turns by 45° from source to target: its change is at 22.5° to the text change. View 1's
    # change is the same turn seen from e2, only half of it (1/√2) along the text change.
    expected = math.cos(math.pi / 8) * (1 + 1 / math.sqrt(2)) / 2
    assert clip_direction(towards, recon, target, source) == pytest.approx(expected, abs=1e-6)
    assert clip_direction(away, recon, target, source) < -0.5
    assert clip_direction(recon, recon, target, source) == 0.0  # no image change: zero, not NaN
    with pytest.raises(ValueError, match="pairs views"):
        clip_direction(towards[:1], recon, target, source)


def test_clip_similarity_is_the_mean_cosine():
    text = torch.tensor([1.0, 0.0])
    images = torch.tensor([[1.0, 0.0], [1.0, math.sqrt(3.0)], [0.0, 5.0]])  # cos 1, 0.5, 0
    assert clip_similarity(images, text) == pytest.approx(0.5, abs=1e-6)


def test_clip_metrics_under_a_callers_bf16_autocast_are_the_float32_ones():
    """Their cosines (a matrix-vector product) had run in bf16 under a caller's autocast: CLIP_sim -0.00098 for
    -0.00094 and CLIP_dir 0.00693 for 0.00686 on these embeddings, at the precision the scores are reported to."""
    generator = torch.Generator().manual_seed(0)
    edits, text, recons, source = (torch.randn(shape, generator=generator) for shape in ((8, 512), 512, (8, 512), 512))
    expected = clip_similarity(edits, text), clip_direction(edits, recons, text, source)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert (clip_similarity(edits, text), clip_direction(edits, recons, text, source)) == expected


def test_clip_metrics_of_half_precision_zero_directions_are_zero_not_nan():
    e = torch.eye(4, dtype=torch.float16)
    recon = torch.stack([e[0], e[2]])
    assert clip_direction(recon, recon, e[1], e[0]) == 0.0  # no image change (1e-12 underflows in fp16)
    assert clip_similarity(recon, torch.zeros(4, dtype=torch.float16)) == 0.0


# ------------------------------------------------------------------------------------------ tiny models
def test_tiny_clip_loads_through_the_real_loader(tiny_clip_path):
    clip = ClipScorer.from_pretrained(str(tiny_clip_path), device="cpu")
    images = torch.rand(3, 40, 50, 3, generator=torch.Generator().manual_seed(0))
    embeddings = clip.image_embeddings(images)
    assert embeddings.shape == (3, 32)
    assert torch.allclose(embeddings.norm(dim=-1), torch.ones(3), atol=1e-5)
    assert torch.allclose(clip.image_embeddings(images[1:2]), embeddings[1:2], atol=1e-5)  # batching changes nothing
    texts = clip.text_embeddings(["a render of a mic", "a render of a mic wearing big sunglasses"])
    assert texts.shape == (2, 32) and not torch.allclose(texts[0], texts[1])


def test_missing_clip_weights_name_the_model(tmp_path, monkeypatch):
    with pytest.raises(ModelNotAvailableError, match="'voxe-test/no-such-clip' are not available"):
        ClipScorer.from_pretrained("voxe-test/no-such-clip", device="cpu", local_files_only=True)
    with pytest.raises(ModelNotAvailableError, match="does not exist"):
        ClipScorer.from_pretrained(str(tmp_path / "absent"), device="cpu")
    monkeypatch.chdir(tmp_path)
    (tmp_path / "models").mkdir()
    with pytest.raises(ModelNotAvailableError, match="'models/clip/base' are not available: that local folder must "
                                                     "hold a whole CLIPModel") as said:  # no hub id: a folder
        ClipScorer.from_pretrained("models/clip/base", device="cpu", local_files_only=True)
    assert "hf download" not in str(said.value)  # (it had been told to download it, which no hub id can be)
    with pytest.raises(ModelNotAvailableError, match=r"'models/clip' are not available \(nor is there a folder "
                                                     r"models/clip: .*models holds no 'clip'\): download them once"):
        ClipScorer.from_pretrained("models/clip", device="cpu", local_files_only=True)


def test_a_clip_folder_without_its_tokenizer_vocabulary_is_refused_naming_it(tiny_clip_path, tmp_path):
    folder = tmp_path / "no_vocab"
    shutil.copytree(tiny_clip_path, folder)
    (folder / "vocab.json").unlink()
    (folder / "merges.txt").unlink()  # transformers 5 then builds a tokenizer of the 2 special tokens
    with pytest.raises(ModelNotAvailableError, match="'.*no_vocab' are not available: that local folder must hold a "
                                                     "whole CLIPModel.*tokenizer has 2 tokens") as said:
        ClipScorer.from_pretrained(str(folder), device="cpu")
    assert "hf download" not in str(said.value)  # (it had been told to download its own path from the hub)


@pytest.mark.parametrize("damaged, content", [("model.safetensors", b"trunc"), ("tokenizer_config.json", b"{bad"),
                                               ("vocab.json", b"{bad"), ("merges.txt", b"garbage")])
def test_damaged_clip_files_are_refused_naming_the_model(tiny_clip_path, tmp_path, damaged, content):
    folder = tmp_path / "damaged"
    shutil.copytree(tiny_clip_path, folder)
    (folder / damaged).write_bytes(content)  # SafetensorError, JSONDecodeError, tokenizers' bare Exception underneath
    with pytest.raises(ModelNotAvailableError, match="CLIP weights '.*damaged' are not available"):
        ClipScorer.from_pretrained(str(folder), device="cpu")


def test_a_machine_out_of_memory_while_loading_clip_is_not_reported_as_a_missing_model(tiny_clip_path, monkeypatch):
    from transformers import CLIPModel

    def short_of_memory(*_args, **_kwargs):
        raise RuntimeError("DefaultCPUAllocator: can't allocate memory: you tried to allocate 605552640 bytes")

    monkeypatch.setattr(CLIPModel, "from_pretrained", short_of_memory)
    with pytest.raises(RuntimeError, match="DefaultCPUAllocator") as raised:
        ClipScorer.from_pretrained(str(tiny_clip_path), device="cpu")
    assert not isinstance(raised.value, ModelNotAvailableError)


def test_inception_loader_tiny_file_and_missing_file(tiny_inception_path, tmp_path):
    features = InceptionFeatures.load(tiny_inception_path.parent, device="cpu", batch_size=2)  # a folder works too
    images = torch.rand(5, 30, 30, 3, generator=torch.Generator().manual_seed(1))
    values = features.features(images)
    assert values.shape == (5, 64) and values.dtype == torch.float64
    assert fid_from_features(values, features.features(images)) == pytest.approx(0.0, abs=1e-9)
    assert fid_from_features(values, features.features(1.0 - images)) > 1e-6
    with pytest.raises(ModelNotAvailableError) as missing:
        InceptionFeatures.load(tmp_path / "nowhere.pt")
    assert "nowhere.pt" in str(missing.value) and INCEPTION_URL in str(missing.value)
    (tmp_path / "junk.pt").write_bytes(b"not torchscript")
    with pytest.raises(ModelNotAvailableError, match="not a TorchScript Inception file"):
        InceptionFeatures.load(tmp_path / "junk.pt")


def test_inception_features_of_uint8_images_are_those_of_their_pixels(tiny_inception_path):
    """Regression: uint8 images were taken as floats in [0, 1], so every pixel above 1 was white: FID_input of 8-bit
    photos was the FID of blank frames, silently."""
    features = InceptionFeatures.load(tiny_inception_path, device="cpu", batch_size=2)
    pixels = torch.randint(0, 256, (3, 30, 30, 3), dtype=torch.uint8, generator=torch.Generator().manual_seed(3))
    assert torch.equal(features.features(pixels), features.features(pixels / 255.0))
    assert not torch.equal(features.features(pixels), features.features(torch.ones(3, 30, 30, 3)))


# ------------------------------------------------------------------------------------------ masked metrics
def test_masked_psnr_and_ssim_ignore_excluded_pixels():
    g = torch.Generator().manual_seed(2)
    a = torch.rand(2, 32, 32, 3, generator=g)
    b = a.clone()
    b[:, 4:12, 20:28] = 1.0 - b[:, 4:12, 20:28]  # changed patch
    keep = torch.ones(2, 32, 32, dtype=torch.bool)
    keep[:, 4:12, 20:28] = False
    assert psnr(a, b, keep=keep).tolist() == [math.inf, math.inf]
    assert ssim(a, b, keep=keep).tolist() == pytest.approx([1.0, 1.0], abs=1e-6)  # no window touches the patch
    assert bool((ssim(a, b) < 0.99).all()) and bool((psnr(a, b) < 30).all())
    everything = torch.ones(2, 32, 32, dtype=torch.bool)
    assert torch.allclose(psnr(a, b, keep=everything), psnr(a, b)) and torch.allclose(ssim(a, b, keep=everything), ssim(a, b))
    assert math.isnan(psnr(a[0], b[0], keep=torch.zeros(32, 32, dtype=torch.bool)))
    with pytest.raises(ValueError, match="bool mask shaped"):
        psnr(a, b, keep=keep.float())


def _local_edit(sphere_grid):
    """G_e: the sphere turned blue with a blob on its +x side; the mask: G_e's occupied voxels beyond x = 0.5."""
    edited = sphere_grid.clone_grid()
    axes = torch.linspace(-1.5, 1.5, sphere_grid.resolution[0])
    x = axes[:, None, None].expand(sphere_grid.resolution)
    with torch.no_grad():
        edited.features[..., 1:] = torch.tensor([-4.0, -4.0, 4.0])
        blob = ((x - 1.0) ** 2 + axes[None, :, None] ** 2 + axes[None, None, :] ** 2).sqrt() < 0.35
        edited.features[..., 0][blob] = 20.0
    mask = (x > 0.5) & (edited.features[..., 0].detach() > 0)
    return edited, mask


def test_preservation_scores_one_view_at_a_time_with_the_values_of_the_whole_ring(sphere_grid, monkeypatch):
    """Regression: PSNR / SSIM took the whole ring at once, and SSIM's float64 filter buffers are ~130 times the
    views' float pixels (3.2 GB for 32 views of 256²). Each view alone gives the same values, bit for bit."""
    import voxe_core.evaluate

    edited, mask = _local_edit(sphere_grid)
    config = EvaluateConfig(views=5, elevation=20.0, size=24)
    recon, images = render_ring(sphere_grid, 5, 20.0, 24), render_ring(edited, 5, 20.0, 24)
    sample = EditSample("e", "x", edited, mask)
    keep = ~mask_footprint(sphere_grid, mask, 5, 20.0, 24)
    views_scored = []

    def recorded(metric):
        def one_call(a, b, keep=None):
            views_scored.append((metric.__name__, len(a)))
            return metric(a, b, keep=keep)
        return one_call

    monkeypatch.setattr(voxe_core.evaluate, "psnr", recorded(psnr))
    monkeypatch.setattr(voxe_core.evaluate, "ssim", recorded(ssim))
    scores = preservation(images, recon, sample, sphere_grid, config)
    assert views_scored == [("psnr", 1), ("ssim", 1)] * 5
    whole_ring = {"psnr": psnr(images, recon, keep=keep), "ssim": ssim(images, recon, keep=keep)}
    assert {name: scores[name] for name in whole_ring} == {name: voxe_core.evaluate._finite_mean(values)
                                                           for name, values in whole_ring.items()}


def test_preservation_outside_the_mask_footprint_is_exact_for_a_merged_grid(sphere_grid):
    edited, mask = _local_edit(sphere_grid)
    refined = merge(sphere_grid, edited, mask)
    config = EvaluateConfig(views=4, elevation=20.0, size=24)
    recon = render_ring(sphere_grid, config.views, config.elevation, config.size)
    footprint = mask_footprint(sphere_grid, mask, config.views, config.elevation, config.size)
    assert 0.0 < footprint.float().mean() < 1.0
    local = preservation(render_ring(refined, 4, 20.0, 24), recon, EditSample("r", "x", refined, mask), sphere_grid, config)
    assert local["region"] == "outside mask" and local["psnr"] > 60.0 and local["ssim"] == pytest.approx(1.0, abs=1e-4)
    # The unrefined edit recoloured the whole sphere: outside the footprint it differs from G_i.
    unrefined = preservation(render_ring(edited, 4, 20.0, 24), recon, EditSample("e", "x", edited, mask), sphere_grid, config)
    assert unrefined["psnr"] < 20.0
    whole = preservation(render_ring(edited, 4, 20.0, 24), recon, EditSample("g", "x", edited), sphere_grid, config)
    assert whole["region"] == "whole image" and whole["kept_fraction"] == 1.0
    empty = mask_footprint(sphere_grid, torch.zeros_like(mask), 2, 20.0, 16)
    assert not bool(empty.any())
    # A mask over the whole grid hides every pixel: nothing is left to compare, and the scores say so.
    everything = torch.ones_like(mask)
    hidden = preservation(recon, recon, EditSample("all", "x", refined, everything), sphere_grid, config)
    assert hidden["kept_fraction"] == 0.0 and hidden["psnr"] is None and hidden["ssim"] is None


def test_the_footprint_on_a_scene_grid_follows_its_contracted_sampling():
    # A red sphere in the scene backbone's foreground; the merged edit turns its +x side blue and adds a shell there.
    initial = SceneGrid(17, foreground_extent=1.5, near_samples=16, far_samples=16, far_ratio=50.0)
    points = initial.vertex_positions().reshape(*initial.resolution, 3)
    radius = torch.nan_to_num(points.norm(dim=-1), nan=math.inf)  # the outer faces lie at infinity
    mask = (points[..., 0] > 0.4) & (radius < 1.2)
    with torch.no_grad():
        initial.features[..., 0] = (40.0 * (0.8 - radius)).clamp_min(-100.0)
        initial.features[..., 1:] = torch.tensor([4.0, -4.0, -4.0])
        edited = initial.clone_grid()
        edited.features[..., 1:] = torch.tensor([-4.0, -4.0, 4.0])
        edited.features[..., 0][mask & (radius > 0.85)] = 30.0
    refined = merge(initial, edited, mask)
    config = EvaluateConfig(views=4, elevation=20.0, size=24)
    centre = initial.orbit_centre()
    recon = render_ring(initial, config.views, config.elevation, config.size, centre=centre)
    images = render_ring(refined, config.views, config.elevation, config.size, centre=centre)
    footprint = mask_footprint(initial, mask, config.views, config.elevation, config.size, centre)
    changed = (images != recon).any(-1)
    assert bool(changed.any()) and not bool((changed & ~footprint).any())  # every changed pixel is in the footprint
    kept = preservation(images, recon, EditSample("hat", "x", refined, mask), initial, config, centre)
    assert kept["psnr"] == 100.0 and kept["ssim"] == 1.0
    from pathlib import Path

    from voxe_core.metrics import PSNR_CAP_DB

    readme = " ".join((Path(__file__).parent.parent / "README.md").read_text().split())
    assert f"counts as {PSNR_CAP_DB:g} dB (`metrics.PSNR_CAP_DB`)" in readme  # (it had not said why 100.00)
    assert kept["kept_fraction"] == pytest.approx(1.0 - float(footprint.float().mean())) and kept["kept_fraction"] > 0.3


# ------------------------------------------------------------------------------------------ end to end
def test_evaluate_scores_edits_and_an_unchanged_grid_scores_as_identical(sphere_grid, tiny_clip_path, tiny_inception_path):
    clip = ClipScorer.from_pretrained(str(tiny_clip_path), device="cpu")
    fid = InceptionFeatures.load(tiny_inception_path, device="cpu")
    edited, mask = _local_edit(sphere_grid)
    refined = merge(sphere_grid, edited, mask)
    inputs = render_ring(sphere_grid, 5, 45.0, 24)
    edits = [EditSample("same", "a claymation ball", sphere_grid), EditSample("hat", "a ball wearing a party hat", refined, mask)]
    reports, rings = [], {}
    result = evaluate(sphere_grid, edits, "ball", clip, fid, inputs, EvaluateConfig(views=4, elevation=20.0, size=24),
                      callbacks=Callbacks(on_progress=reports.append),
                      on_ring=lambda name, i, view: rings.setdefault(name, []).append(view))
    same, hat = result.rows
    assert same["mode"] == "global" and hat["mode"] == "local"
    assert same["fid_rec"] == pytest.approx(0.0, abs=1e-6) and same["clip_dir"] == 0.0
    assert same["psnr"] == 100.0 and same["ssim"] == pytest.approx(1.0)
    assert hat["fid_rec"] > 0 and hat["fid_input"] > 0 and hat["psnr"] > 60.0
    rings = {name: torch.stack(views) for name, views in rings.items()}
    assert list(rings) == [None, "same", "hat"] and torch.equal(rings[None], rings["same"])
    assert torch.equal(rings[None], render_ring(sphere_grid, 4, 20.0, 24))
    expected_sim = clip_similarity(clip.image_embeddings(rings[None]),
                                   clip.text_embeddings(["a render of a claymation ball"])[0])
    assert same["clip_sim"] == pytest.approx(expected_sim, abs=1e-5)
    # Steps: 3 ring renders (G_i's once) and 3 CLIP passes of 4 views, 4 footprint views, FID on the 12 renders and
    # 5 inputs.
    assert evaluation_steps(edits, EvaluateConfig(views=4), fid, inputs) == 45
    assert reports[-1].iteration == 45 and {r.total for r in reports} == {45}
    assert {r.info["stage"] for r in reports} == {"ring renders", "CLIP", "FID", "mask footprints"}
    table = format_table(result.rows, extra_columns=("name",))
    assert "| hat | a ball wearing a party hat | local |" in table and "**mean (2)**" in table
    assert json.loads(json.dumps(result.summary()))["means"]["local"]["count"] == 1


def _chunks_of(views: int, size: int, monkeypatch) -> None:
    """Makes :func:`evaluate` render its rings in chunks of ``views`` views of ``size``²."""
    monkeypatch.setattr("voxe_core.evaluate.RING_CHUNK_BYTES", views * size * size * 3 * 4)


def test_an_evaluation_holds_a_chunk_of_initial_views_and_one_view_of_each_edit_at_a_time(sphere_grid, tiny_clip_path,
                                                                                          monkeypatch):
    """Regression: every edit's ring renders were kept in the Evaluation to its end (60 edits × 360 views of 1,024²
    are 270 GB of floats), then G_i's ring was held to the end beside each edit's (9 GB), then rendered again beside
    each edit's (a CPU time 41-63 % longer). The rings go a chunk of views at a time: G_i's views of the chunk
    rendered once, each edit's scored against them one by one and all let go; CLIP takes each grid's views in its
    batches as 8-bit pixels (a quarter of a float view each): G_i's chunk and a few views' worth per grid are alive
    at any step, not two rings', and each ring is rendered once."""
    from test_export import views_alive

    _chunks_of(4, 16, monkeypatch)
    clip = ClipScorer.from_pretrained(str(tiny_clip_path), device="cpu")
    clip.batch_size = 4
    edited, mask = _local_edit(sphere_grid)
    edits = [EditSample("global", "a claymation ball", edited), EditSample("hat", "a ball wearing a party hat",
                                                                           merge(sphere_grid, edited, mask), mask)]
    alive, stages, handed = [], [], []

    def on_progress(report):
        alive.append(views_alive(16, 16))
        stages.append(report.info["stage"])

    result = evaluate(sphere_grid, edits, "ball", clip, None, None, EvaluateConfig(views=16, size=16),
                      Callbacks(on_progress=on_progress), on_ring=lambda name, i, view: handed.append((name, i)))
    assert handed == [(name, i) for chunk in (0, 4, 8, 12) for name in (None, "global", "hat")
                      for i in range(chunk, chunk + 4)]
    assert stages.count("ring renders") == 3 * 16 and stages.count("mask footprints") == 16
    # CLIP's batch of 4 as 8-bit pixels for each of the 3 grids (3 views' worth), G_i's chunk of 4 views and the
    # edit's view in hand, and a view's worth to spare (it had been 32 and more: two whole rings)
    assert len(alive) > 4 * 16 and max(alive) <= 3 * 4 / 4 + 4 + 2, alive
    assert vars(result).keys() == {"rows"} and len(result.rows) == 2


def test_clip_and_fid_share_one_batch_buffer_per_grid(sphere_grid, tiny_clip_path, tiny_inception_path, monkeypatch):
    """Regression: CLIP and FID each kept their own batch of a grid's views as 8-bit pixels ((32 + 25) views a grid:
    11 GB for 60 edits at 1,024²). They score one buffer per grid, of the larger batch (32 views: 44 % less); the
    rows stay those of the whole rings, bit for bit (test_the_views_scored_one_by_one_give_the_numbers_of_the_whole_
    rings, whose batches wrap around the buffer's end)."""
    from test_export import views_alive

    _chunks_of(1, 16, monkeypatch)  # G_i's view one at a time, as the bound below counts it
    clip = ClipScorer.from_pretrained(str(tiny_clip_path), device="cpu")
    clip.batch_size = 8
    fid = InceptionFeatures.load(tiny_inception_path, device="cpu", batch_size=8)
    edits = [EditSample("global", "a claymation ball", _local_edit(sphere_grid)[0])]
    alive = []
    evaluate(sphere_grid, edits, "ball", clip, fid, None, EvaluateConfig(views=16, size=16),
             Callbacks(on_progress=lambda report: alive.append(views_alive(16, 16))))
    # One buffer of 8 views as 8-bit pixels for each of the 2 grids (4 float views' worth), G_i's view and the edit's
    # in hand, G_i's view before them while its next renders, and a view's worth to spare (a buffer per scorer had
    # been twice that: 8 float views' worth)
    assert len(alive) > 2 * 16 and max(alive) <= 2 * 8 / 4 + 4, alive


def test_a_footprints_progress_is_reported_as_each_view_renders(sphere_grid, monkeypatch):
    """Regression: a footprint's views were rendered a chunk at a time (once, the whole ring) as the chunk's first was
    asked for, and each reported as it was yielded: the chunk's renders came before one report, the others as its
    views were scored, with no work left. Each view is reported as it renders."""
    import voxe_core.evaluate as evaluation

    _chunks_of(3, 16, monkeypatch)  # views 0-1, 2-4
    x = torch.linspace(-1.5, 1.5, sphere_grid.resolution[0])[:, None, None].expand(sphere_grid.resolution)
    mask = (x > 0.2) & (sphere_grid.features[..., 0].detach() > 0)
    rendered, reports = [], []
    real_render = evaluation.render_image
    monkeypatch.setattr(evaluation, "render_image", lambda *args: rendered.append(1) or real_render(*args))
    footprints = evaluation.iter_mask_footprint(sphere_grid, mask, 5, 20.0, 16, callbacks=Callbacks(
        on_progress=lambda report: reports.append((report.stage, report.iteration, report.total, len(rendered)))))
    next(footprints)
    assert reports == [("mask footprint", i, 5, i) for i in (1, 2)], reports  # it had been [(…, 1, 5, 2)]
    assert len(list(footprints)) == 4 and reports == [("mask footprint", i, 5, i) for i in range(1, 6)], reports


def test_masked_edits_hold_one_chunk_of_footprint_views_at_a_time(sphere_grid, tiny_clip_path, monkeypatch):
    """Regression: a masked edit's footprint rendered its whole ring as its first view was asked for and held each
    view's bits until it was scored; an evaluation asks every masked edit for its first view in its first chunk, so
    every masked edit held its whole ring's at once (47 MB an edit for 360 views of 1,024², 2.8 GB for 60). They are
    rendered a chunk at a time: at any step at most one chunk's footprints are rendered and not yet scored, however
    many edits are masked, and the rows are those of each whole footprint."""
    import voxe_core.evaluate as evaluation
    from voxe_core.evaluate import _finite_mean

    _chunks_of(2, 16, monkeypatch)
    clip = ClipScorer.from_pretrained(str(tiny_clip_path), device="cpu")
    edited, mask = _local_edit(sphere_grid)
    edits = [EditSample(f"m{k}", "a blue ball", edited, mask) for k in range(4)]
    rendered, scored, unscored = [], [], []
    real_render, real_footprints = evaluation.render_image, evaluation.iter_mask_footprint

    def render_image(*args, **kwargs):  # (a footprint's: the ring renders go through iter_views)
        rendered.append(1)
        return real_render(*args, **kwargs)

    def iter_mask_footprint(*args, **kwargs):
        for view in real_footprints(*args, **kwargs):
            unscored.append(len(rendered) - len(scored))  # this view's and those rendered after it
            scored.append(1)
            yield view

    monkeypatch.setattr(evaluation, "render_image", render_image)
    monkeypatch.setattr(evaluation, "iter_mask_footprint", iter_mask_footprint)
    rows = evaluate(sphere_grid, edits, "ball", clip, None, None, EvaluateConfig(views=6, elevation=20.0,
                                                                                   size=16)).rows
    monkeypatch.undo()
    assert len(unscored) == 4 * 6 and max(unscored) == 2, unscored  # it had been 18: 4 rings rendered, 6 views scored
    centre = sphere_grid.orbit_centre()
    keep = ~mask_footprint(sphere_grid, mask, 6, 20.0, 16, centre)
    recon = render_ring(sphere_grid, 6, 20.0, 16, centre=centre)
    images = render_ring(edited, 6, 20.0, 16, centre=centre)
    assert {(row["psnr"], row["ssim"], row["kept_fraction"]) for row in rows} == {
        (_finite_mean(psnr(images, recon, keep=keep)), _finite_mean(ssim(images, recon, keep=keep)),
         float(keep.float().mean()))}


@pytest.mark.parametrize("clip_batch, fid_batch", [(3, 2), (2, 3)])  # the shared buffer sized by either
def test_the_views_scored_one_by_one_give_the_numbers_of_the_whole_rings(sphere_grid, tiny_clip_path,
                                                                          tiny_inception_path, clip_batch, fid_batch):
    """Scored view by view, in the scorers' batches, the rows are those of each whole ring scored at once, bit for
    bit (batches that do not divide the ring included, and wrapping the end of the buffer they share;
    ``kept_fraction`` is the exact ratio rounded to float32, which the whole ring's float32 mean equals below 2^24
    pixels, as here)."""
    from voxe_core.evaluate import _finite_mean

    clip = ClipScorer.from_pretrained(str(tiny_clip_path), device="cpu")
    clip.batch_size = clip_batch
    fid = InceptionFeatures.load(tiny_inception_path, device="cpu", batch_size=fid_batch)
    edited, mask = _local_edit(sphere_grid)
    inputs = render_ring(sphere_grid, 5, 45.0, 24)
    edits = [EditSample("global", "a claymation ball", edited), EditSample("masked", "a blue ball", edited, mask)]
    config = EvaluateConfig(views=7, elevation=20.0, size=24)
    rows = evaluate(sphere_grid, edits, "ball", clip, fid, inputs, config).rows
    centre = sphere_grid.orbit_centre()
    recon = render_ring(sphere_grid, 7, 20.0, 24, centre=centre)
    images = render_ring(edited, 7, 20.0, 24, centre=centre)
    texts = clip.text_embeddings(["a render of a ball", "a render of a claymation ball", "a render of a blue ball"])
    footprint = mask_footprint(sphere_grid, mask, 7, 20.0, 24, centre)
    for row, text, keep in zip(rows, texts[1:], (torch.ones_like(footprint), ~footprint)):
        assert row["clip_sim"] == clip_similarity(clip.image_embeddings(images), text)
        assert row["clip_dir"] == clip_direction(clip.image_embeddings(images), clip.image_embeddings(recon), text,
                                                 texts[0])
        assert row["fid_rec"] == fid_from_features(fid.features(images), fid.features(recon))
        assert row["fid_input"] == fid_from_features(fid.features(images), fid.features(inputs))
        assert row["psnr"] == _finite_mean(psnr(images, recon, keep=keep))
        assert row["ssim"] == _finite_mean(ssim(images, recon, keep=keep))
        assert row["kept_fraction"] == float(keep.float().mean())
    assert rows[1]["kept_fraction"] < 1.0 and rows[1]["psnr"] < 20.0  # the mask keeps a part that changed


def _stand_ins_alive(*grids) -> int:
    """How many float storages of ``grids``' feature size (4 floats a vertex) are alive now besides their own: a
    footprint stand-in is one."""
    import gc

    own = {grid.flat_features.untyped_storage().data_ptr() for grid in grids}
    nbytes = grids[0].flat_features.untyped_storage().nbytes()
    alive = set()
    for obj in gc.get_objects():  # type(obj), not isinstance: see test_export.views_alive
        if type(obj) in (torch.Tensor, torch.nn.Parameter) and obj.dtype == torch.float32:
            if obj.untyped_storage().nbytes() == nbytes:
                alive.add(obj.untyped_storage().data_ptr())
    return len(alive - own)


def test_many_masked_edits_hold_no_footprint_stand_in_between_steps(sphere_grid, tiny_clip_path):
    """Regression: view-major, each masked edit's footprint stand-in (4 floats a vertex and its occupancy, ~70 MB at
    160³ on the render device) was held from its edit's first view to the end, all of them at once (~4 GB for 60
    masked edits). Each is now built from its bool mask for the views it renders and let go: none is alive at any
    step but a footprint's (reported as each view renders, from the one stand-in alive), however many masked edits,
    and each edit's row is that of its whole ring, bit for bit."""
    from voxe_core.evaluate import _finite_mean

    clip = ClipScorer.from_pretrained(str(tiny_clip_path), device="cpu")
    edited, _ = _local_edit(sphere_grid)
    x = torch.linspace(-1.5, 1.5, sphere_grid.resolution[0])[:, None, None].expand(sphere_grid.resolution)
    masks = [(x > bound) & (edited.features[..., 0].detach() > 0) for bound in (0.1, 0.3, 0.5, 0.7, 0.9, 1.1)]
    edits = [EditSample(f"m{k}", "a blue ball", edited, mask) for k, mask in enumerate(masks)]
    config = EvaluateConfig(views=3, elevation=20.0, size=16)
    alive = {"mask footprints": [], "other": []}

    def on_progress(report):
        footprint = report.info["stage"] == "mask footprints"
        alive["mask footprints" if footprint else "other"].append(_stand_ins_alive(sphere_grid, edited))

    rows = evaluate(sphere_grid, edits, "ball", clip, None, None, config, Callbacks(on_progress=on_progress)).rows
    assert len(alive["mask footprints"]) == len(edits) * config.views and max(alive["mask footprints"]) == 1, alive
    assert len(alive["other"]) > len(edits) * config.views and max(alive["other"]) == 0, alive  # it had been up to 8
    centre = sphere_grid.orbit_centre()
    recon = render_ring(sphere_grid, 3, 20.0, 16, centre=centre)
    images = render_ring(edited, 3, 20.0, 16, centre=centre)
    for row, mask in zip(rows, masks):
        keep = ~mask_footprint(sphere_grid, mask, 3, 20.0, 16, centre)
        assert (row["psnr"], row["ssim"], row["kept_fraction"]) == (
            _finite_mean(psnr(images, recon, keep=keep)), _finite_mean(ssim(images, recon, keep=keep)),
            float(keep.float().mean()))
    assert len({row["kept_fraction"] for row in rows}) == len(masks)  # six footprints, each edit scored on its own


def test_a_masked_edits_footprint_stand_in_is_built_once_a_chunk_with_the_footprints_of_one_a_view(
        sphere_grid, monkeypatch):
    """Each view of a masked edit's footprint had built its stand-in again (~0.09 s of CPU a view at 160³, 40 % of
    the view's footprint): it is built once for each chunk of the ring's views, let go before the chunk's first view
    is yielded, and the footprints are those of a stand-in built for each view, bit for bit (a width no multiple of
    8 included)."""
    from voxe_core.evaluate import iter_mask_footprint
    from voxe_core.export import turntable_cameras
    from voxe_core.grid import VoxelGrid
    from voxe_core.render import RenderConfig, render_image

    x = torch.linspace(-1.5, 1.5, sphere_grid.resolution[0])[:, None, None].expand(sphere_grid.resolution)
    mask = (x > 0.2) & (sphere_grid.features[..., 0].detach() > 0)
    cameras = turntable_cameras(5, 20.0, 21)
    one_a_view = []
    for i in range(5):
        features = torch.zeros(*sphere_grid.resolution, 4)
        features[..., 0] = mask.float() * 1e3
        stand_in = sphere_grid.like(features)
        one_a_view.append(render_image(stand_in, cameras, i, RenderConfig(sigma_threshold=0.0)).opacity > 0)
    del features, stand_in  # (not counted as the footprint's)
    _chunks_of(2, 21, monkeypatch)  # views 0, 1-2, 3-4
    built, alive, real_like = [], [], VoxelGrid.like
    monkeypatch.setattr(VoxelGrid, "like", lambda grid, features: built.append(1) or real_like(grid, features))
    footprints = []
    for view in iter_mask_footprint(sphere_grid, mask, 5, 20.0, 21):
        alive.append(_stand_ins_alive(sphere_grid))
        footprints.append(view)
    assert len(built) == 3 and alive == [0] * 5, (built, alive)
    assert torch.equal(torch.stack(footprints), torch.stack(one_a_view)) and 0 < int(torch.stack(footprints).sum())


def test_an_edits_grid_is_on_the_render_device_only_while_its_views_of_a_chunk_render(sphere_grid, tiny_clip_path,
                                                                                       monkeypatch):
    """Regression: view-major, each edit's grid moved to the render device at its first view and stayed there with
    its occupancy to the end, all of them at once (~70 MB a grid at 160³: 4 GB for 60 edits). An edit's views of a
    chunk are now rendered from a grid on the device and its occupancy, both let go before the next edit's: at any
    step at most G_i's occupancy and the one edit's being rendered are alive, however many edits; the grids given
    are not moved (``iter_views`` moves the grid it renders in place: each edit's is a grid made on the device)."""
    import gc

    from voxe_core.grid import Occupancy, VoxelGrid

    clip = ClipScorer.from_pretrained(str(tiny_clip_path), device="cpu")
    edited, _ = _local_edit(sphere_grid)
    edits = [EditSample(f"e{k}", "a blue ball", edited) for k in range(5)]
    alive, moved = [], []
    _chunks_of(2, 16, monkeypatch)
    monkeypatch.setattr(VoxelGrid, "to", lambda grid, *args, **kwargs: moved.append(grid) or torch.nn.Module.to(
        grid, *args, **kwargs))
    occupancies = lambda: sum(type(o) is Occupancy for o in gc.get_objects())  # noqa: E731
    gc.collect()
    before = occupancies()  # (an earlier test's, in garbage gc has not collected yet: counted apart)
    evaluate(sphere_grid, edits, "ball", clip, None, None, EvaluateConfig(views=3, size=16),
             Callbacks(on_progress=lambda report: alive.append(occupancies() - before)))
    assert len(alive) > len(edits) * 3 and max(alive) <= 2, alive  # it had been 1 + 5
    assert len(moved) > len(edits) * 2 and not any(grid is edited for grid in moved)  # a grid a chunk, on the device


def test_each_edits_grid_goes_to_the_render_device_and_has_its_occupancy_built_once_a_chunk(
        sphere_grid, tiny_clip_path, monkeypatch):
    """Regression (59dc08b): each view of each edit copied the edit's grid to the render device and built its
    occupancy again (~65 MB copied a view at 160³ on a GPU, ~3 % more CPU time on the CPU). The ring is rendered in
    chunks of views, G_i's views of a chunk held: an edit's grid goes there, and its occupancy is built, once a
    chunk (B times fewer for chunks of B views), and the rows are those of one view at a time, bit for bit."""
    import voxe_core.evaluate as evaluation
    from voxe_core.grid import VoxelGrid

    clip = ClipScorer.from_pretrained(str(tiny_clip_path), device="cpu")
    edited, mask = _local_edit(sphere_grid)
    edits = [EditSample("global", "a blue ball", edited), EditSample("other", "a red ball", edited.clone_grid()),
             EditSample("masked", "a ball wearing a hat", merge(sphere_grid, edited, mask), mask)]
    config = EvaluateConfig(views=6, elevation=20.0, size=16)

    def counted(views_a_chunk: int) -> tuple[list[dict], list[tuple[str, int]], int]:
        """The rows, the grids given to the renderer (of ``edits``' features or G_i, with how many views) and the
        occupancies built, the footprint stand-ins' left out (one for each chunk of the masked edit's ring)."""
        _chunks_of(views_a_chunk, 16, monkeypatch)
        rendered, built = [], []
        real_iter_views, real_occupancy = evaluation.iter_views, VoxelGrid.occupancy
        names = {sample.grid.features.untyped_storage().data_ptr(): sample.name for sample in edits}

        def iter_views(grid, cameras, *args, **kwargs):
            rendered.append((names.get(grid.features.untyped_storage().data_ptr(), "initial"), len(cameras)))
            return real_iter_views(grid, cameras, *args, **kwargs)

        monkeypatch.setattr(evaluation, "iter_views", iter_views)
        monkeypatch.setattr(VoxelGrid, "occupancy", lambda grid, *a, **k: built.append(grid) or real_occupancy(
            grid, *a, **k))
        rows = evaluate(sphere_grid, edits, "ball", clip, None, None, config).rows
        stand_ins = len(evaluation.ring_chunks(config.views, config.size))  # (the masked edit's footprint's)
        monkeypatch.undo()
        return rows, rendered, len(built) - stand_ins

    rows, rendered, built = counted(3)
    assert rendered == [("initial", 6)] + [(sample.name, 3) for sample in edits] * 2 and built == 1 + 3 * 2
    one_by_one, rendered, built = counted(1)
    assert rendered == [("initial", 6)] + [(sample.name, 1) for sample in edits] * 6 and built == 1 + 3 * 6
    assert rows == one_by_one


def _after_the_last_ring_render(reports) -> bool:
    return sum(r.info["stage"] == "ring renders" for r in reports) == 3 * 4


@pytest.mark.parametrize("when", [_after_the_last_ring_render, *(
    lambda reports, stage=stage: reports[-1].info["stage"] == stage for stage in ("mask footprints", "CLIP", "FID"))],
    ids=["after the last ring render", "in the footprint pass", "in a CLIP pass", "in a FID pass"])
def test_a_cancellation_stops_the_evaluation_before_its_next_step(sphere_grid, tiny_clip_path, tiny_inception_path,
                                                                  when):
    clip = ClipScorer.from_pretrained(str(tiny_clip_path), device="cpu")
    fid = InceptionFeatures.load(tiny_inception_path, device="cpu", batch_size=2)
    edited, mask = _local_edit(sphere_grid)
    edits = [EditSample("global", "a claymation ball", edited),
             EditSample("local", "a ball wearing a party hat", merge(sphere_grid, edited, mask), mask)]
    reports, requested_at = [], []

    def on_progress(report):
        reports.append(report)
        if not requested_at and when(reports):
            requested_at.append(len(reports))

    with pytest.raises(StageCancelled):
        evaluate(sphere_grid, edits, "ball", clip, fid, None, EvaluateConfig(views=4, elevation=20.0, size=16),
                 Callbacks(on_progress=on_progress, should_cancel=lambda: bool(requested_at)))
    assert requested_at and len(reports) == requested_at[0]  # not one step more


def test_a_diverged_grid_is_refused_naming_it_rather_than_scored(sphere_grid, tiny_clip_path):
    clip = ClipScorer.from_pretrained(str(tiny_clip_path), device="cpu")
    diverged = sphere_grid.clone_grid()
    with torch.no_grad():
        diverged.features[..., 1:] = math.nan  # the colours: every view of the sphere shows NaN
    config = EvaluateConfig(views=3, elevation=20.0, size=16)
    with pytest.raises(ValueError, match="edit 'nan': ring view 0 of 3 has NaN or infinite pixels"):
        evaluate(sphere_grid, [EditSample("nan", "a claymation ball", diverged)], "ball", clip, None, None, config)
    with pytest.raises(ValueError, match="the initial grid: ring view 0 of 3 has NaN"):
        evaluate(diverged, [EditSample("same", "a claymation ball", sphere_grid)], "ball", clip, None, None, config)


def test_edits_of_one_name_are_refused_before_any_render(sphere_grid, tiny_clip_path):
    """Regression: both were scored, but their renders were kept by name, so the first edit's renders were
    silently replaced by the second's (the service refuses an evaluation listing a job twice, too)."""
    clip = ClipScorer.from_pretrained(str(tiny_clip_path), device="cpu")
    edits = [EditSample("seed", "a claymation ball", sphere_grid), EditSample("seed", "a yarn ball", sphere_grid),
             EditSample("other", "a wood ball", sphere_grid)]
    reports = []
    with pytest.raises(ValueError, match="edit names must differ .*'seed' given more than once"):
        evaluate(sphere_grid, edits, "ball", clip, None, None, EvaluateConfig(views=2, size=16),
                 Callbacks(on_progress=reports.append))
    assert reports == []


def test_an_object_name_longer_than_clip_reads_is_refused_before_any_render(sphere_grid, tiny_clip_path):
    """CLIP's tokenizer had cut the text at its 77 tokens silently: two source texts differing past the cut scored
    alike, the edit's CLIP_dir measured against a text other than the one asked for."""
    clip = ClipScorer.from_pretrained(str(tiny_clip_path), device="cpu")
    long_name = "ball " * 80
    with pytest.raises(ValueError, match=r"^the text 'a render of a ball ball .*' is \d+ tokens; the CLIP text "
                                         r"model of .* reads 77, its start and end tokens included: shorten it$"):
        clip.text_embeddings(["a render of a ball", f"a render of a {long_name}dog"])
    reports = []
    with pytest.raises(ValueError, match="the text 'a render of a ball ball"):
        evaluate(sphere_grid, [EditSample("e", "a claymation ball", sphere_grid)], long_name, clip, None, None,
                 EvaluateConfig(views=2, size=16), Callbacks(on_progress=reports.append))
    assert reports == []


@pytest.mark.parametrize("grid_resolution, mask_shape, message", [
    (None, (10, 12, 12), r"edit 'masked': its mask of shape \(10, 12, 12\) does not fit the grid's \(12, 12, 12\) "
                         "vertices"),
    (10, (10, 10, 10), r"edit 'masked': a masked edit must share the initial grid's resolution \(12, 12, 12\), got "
                       r"\(10, 10, 10\)"),
])
def test_a_masked_edit_that_does_not_fit_the_initial_grid_is_refused_before_any_render(
        tiny_clip_path, make_sphere_grid, grid_resolution, mask_shape, message):
    """Regression: found when that edit's turn came, after G_i's and the earlier edits' renders and scores (the
    mask's shape even after its own edit's)."""
    clip = ClipScorer.from_pretrained(str(tiny_clip_path), device="cpu")
    initial = make_sphere_grid(12)
    edited = make_sphere_grid(grid_resolution) if grid_resolution else initial
    edits = [EditSample("global", "a yarn ball", initial),
             EditSample("masked", "a wood ball", edited, torch.ones(mask_shape, dtype=torch.bool))]
    reports = []
    with pytest.raises(ValueError, match=message):
        evaluate(initial, edits, "ball", clip, None, None, EvaluateConfig(views=2, size=16),
                 Callbacks(on_progress=reports.append))
    assert reports == []


@pytest.mark.parametrize("shape", [(0, 16, 16, 3), (1, 16, 16, 3), (3, 16, 16), (3, 16, 16, 4)])
def test_input_images_fid_cannot_read_are_refused_before_any_render(sphere_grid, tiny_clip_path, tiny_inception_path,
                                                                    shape):
    """Regression: they were found out after every ring render, none or RGBA by a torch.cat or TorchScript error."""
    clip = ClipScorer.from_pretrained(str(tiny_clip_path), device="cpu")
    fid = InceptionFeatures.load(tiny_inception_path, device="cpu")
    reports = []
    with pytest.raises(ValueError, match=rf"FID_input needs at least 2 input images shaped \(N, H, W, 3\), got "
                                         rf"{re.escape(str(shape))}"):
        evaluate(sphere_grid, [EditSample("e", "a yarn ball", sphere_grid)], "ball", clip, fid, torch.rand(shape),
                 EvaluateConfig(views=2, size=16), Callbacks(on_progress=reports.append))
    assert reports == []


def test_a_prompt_holding_a_line_break_stays_in_its_table_row():
    """``voxe evaluate --edit GRID PROMPT`` takes the prompt as the shell gives it, line breaks and tabs included: a
    line break had ended the Markdown row inside its prompt cell, the rest of the row a line of its own."""
    rows = [{"name": "edit00", "prompt": "a claymation\nball", "mode": "global", "clip_sim": 0.25},
            {"name": "edit01", "prompt": "a wood carving\r\nof a | ball", "mode": "global", "clip_sim": 0.5}]
    lines = format_table(rows, extra_columns=("name",)).splitlines()
    assert len(lines) == 2 + len(rows) + 2  # header, rule, the rows, the global and all means
    assert all(line.startswith("|") and line.endswith("|") for line in lines)
    assert lines[2].startswith("| edit00 | a claymation ball | global | 0.2500 |")
    assert lines[3].startswith("| edit01 | a wood carving of a \\| ball | global | 0.5000 |")


def test_paper_protocol_is_six_prompts_with_local_edit_words_in_them():
    edits = paper_protocol(" hot  dog ")
    assert [e.prompt for e in edits] == [
        "a hot dog wearing big sunglasses", "a hot dog wearing a Christmas sweater",
        "a hot dog wearing a birthday party hat", "a yarn doll of a hot dog", "a wood carving of a hot dog",
        "a claymation hot dog",
    ]
    assert [e.mode for e in edits] == ["local"] * 3 + ["global"] * 3
    for e in edits[:3]:
        assert e.edit_words and all(w in e.prompt for w in e.edit_words)
    assert all(not e.edit_words for e in edits[3:])
    with pytest.raises(ValueError, match="object name is empty"):
        paper_protocol("  ")


# ------------------------------------------------------------------------------------------ CLI
def test_cli_evaluate_writes_json_table_and_ring_png_sets(sphere_grid, tiny_clip_path, tiny_inception_path, tmp_path,
                                                         capsys):
    from PIL import Image

    from voxe_core.cli import main
    from voxe_core.refine.storage import save_mask

    edited, mask = _local_edit(sphere_grid)
    sphere_grid.save(tmp_path / "initial.safetensors")
    merge(sphere_grid, edited, mask).save(tmp_path / "refined.safetensors")
    edited.save(tmp_path / "edited.safetensors")
    save_mask(tmp_path / "mask.safetensors", mask)
    out = tmp_path / "eval"
    common = [str(tmp_path / "initial.safetensors"), "--object", "ball", "--out", str(out),
              "--clip-model", str(tiny_clip_path), "--views", "3", "--size", "16", "-q"]
    code = main(["evaluate", *common, "--inception", str(tiny_inception_path),
                 "--edit", str(tmp_path / "refined.safetensors"), "a ball wearing a party hat", str(tmp_path / "mask.safetensors"),
                 "--edit", str(tmp_path / "edited.safetensors"), "a wood carving of a ball"])
    assert code == 0
    summary = json.loads((out / "evaluation.json").read_text())
    assert [r["name"] for r in summary["rows"]] == ["edit00", "edit01"]
    assert [r["mode"] for r in summary["rows"]] == ["local", "global"]
    assert summary["rows"][0]["region"] == "outside mask" and summary["rows"][0]["psnr"] > 60
    assert summary["rows"][1]["fid_input"] is None  # no --data: no input views to compare with
    assert summary["ring"] == {"views": 3, "elevation": 30.0, "size": 16}
    for name in ("initial", "edit00", "edit01"):
        pngs = sorted((out / "ring" / name).glob("*.png"))
        assert [p.name for p in pngs] == ["000.png", "001.png", "002.png"]
        assert Image.open(pngs[0]).size == (16, 16)
    assert (out / "evaluation.md").read_text() in capsys.readouterr().out

    assert main(["evaluate", *common, "--edit", str(tmp_path / "edited.safetensors")]) == 2
    assert "--edit takes EDITED_GRID PROMPT [MASK], got 1 values" in capsys.readouterr().err
    assert main(["evaluate", *common[:-7], "--clip-model", "voxe-test/no-such-clip", "--offline",
                 "--edit", str(tmp_path / "edited.safetensors"), "a wood carving of a ball"]) == 2
    assert "model not available: CLIP weights 'voxe-test/no-such-clip'" in capsys.readouterr().err


def test_cli_evaluate_that_cannot_write_its_results_keeps_the_earlier_ones(sphere_grid, tiny_clip_path, tmp_path,
                                                                          fill_disk, capsys):
    """A full disk while evaluation.json / evaluation.md were written had left them torn under their names, the
    earlier run's destroyed: they are written whole or not at all, both or neither."""
    from voxe_core.cli import main

    sphere_grid.save(tmp_path / "initial.safetensors")
    out = tmp_path / "eval"
    args = ["evaluate", str(tmp_path / "initial.safetensors"), "--object", "ball", "--out", str(out),
            "--clip-model", str(tiny_clip_path), "--views", "2", "--size", "16", "-q",
            "--edit", str(tmp_path / "initial.safetensors"), "a wood carving of a ball"]
    assert main(args) == 0
    earlier = {name: (out / name).read_text() for name in ("evaluation.json", "evaluation.md")}
    fill_disk(lambda path: path.suffix == ".md")  # the table, written second, runs out of space half way
    assert main([*args[:3], "sphere", *args[4:]]) == 1  # (1: a full disk) another object: another evaluation.json
    assert "No space left on device" in capsys.readouterr().err
    assert {name: (out / name).read_text() for name in earlier} == earlier
    assert sorted(p.name for p in out.iterdir()) == ["evaluation.json", "evaluation.md", "ring"]


def test_cli_evaluate_with_the_smoke_test_models_says_so_in_its_table_and_summary(sphere_grid, tiny_clip_path,
                                                                                  tiny_inception_path, tmp_path, capsys):
    """voxe evaluate with the models voxe_core.tiny_eval builds (what its error for --clip-model tiny tells to build)
    printed and wrote a table that read as CLIP and FID scores; the models' mark says what they are, whatever their
    folder is called, and a model without it (a real CLIP) is scored with no note."""
    from voxe_core.cli import main
    from voxe_core.constants import SMOKE_TEST_MARK

    sphere_grid.save(tmp_path / "initial.safetensors")
    unmarked = shutil.copytree(tiny_clip_path, tmp_path / "clip")
    config = json.loads((unmarked / "config.json").read_text())
    assert config.pop(SMOKE_TEST_MARK) is True
    (unmarked / "config.json").write_text(json.dumps(config))
    args = ["evaluate", str(tmp_path / "initial.safetensors"), "--object", "ball", "--views", "2", "--size", "16", "-q",
            "--edit", str(tmp_path / "initial.safetensors"), "a wood carving of a ball"]
    assert main([*args, "--out", str(tmp_path / "tiny"), "--clip-model", str(tiny_clip_path),
                 "--inception", str(tiny_inception_path)]) == 0
    table = (tmp_path / "tiny" / "evaluation.md").read_text()
    assert table.startswith("**SMOKE TEST**: CLIP and FID are random-weight smoke-test models: these numbers prove "
                            "the plumbing only and say nothing about the edits' quality.\n\n| name | prompt |")
    assert table in capsys.readouterr().out
    assert json.loads((tmp_path / "tiny" / "evaluation.json").read_text())["smoke_test"] == ["CLIP", "FID"]
    assert main([*args, "--out", str(tmp_path / "real"), "--clip-model", str(unmarked)]) == 0
    assert (tmp_path / "real" / "evaluation.md").read_text().startswith("| name | prompt |")
    assert json.loads((tmp_path / "real" / "evaluation.json").read_text())["smoke_test"] == []


# ------------------------------------------------------------------------------------------ service
@pytest.fixture
def service(tmp_path, monkeypatch):
    """The API in-process (embedded broker, no worker) with the tiny evaluation models; tasks run via .apply()."""
    from fastapi.testclient import TestClient

    from needs import require_data
    from service_helpers import MIC, ingest, reset_service_caches, service_env, small_mic, zip_folder

    require_data(MIC)
    for key, value in service_env(tmp_path, VOXE_CLIP_MODEL="tiny", VOXE_FID_MODEL="tiny").items():
        monkeypatch.setenv(key, value)
    reset_service_caches()
    from api.main import create_app

    with TestClient(create_app()) as client:
        archive = zip_folder(small_mic(tmp_path / "mic_small"), tmp_path / "mic.zip", prefix="mic_small")
        with open(archive, "rb") as handle:
            scene = client.post("/v1/scenes", files={"archive": ("mic.zip", handle, "application/zip")})
        assert scene.status_code == 201, scene.text
        assert ingest(scene.json()["id"])["state"] == "ready"
        yield client, scene.json()["id"], tmp_path
    reset_service_caches()


def _sweep_with_one_edit_done(service, grid) -> tuple[dict, dict]:
    """A sweep of the ``service`` fixture's scene whose fifth entry's edit is recorded as done, ``grid`` unchanged
    (:func:`_as_if_edited`); the sweep as created and that entry."""
    client, scene_id, root = service
    params = {"iterations": 2, "reconstruction": {"resolution": 8, "iterations": 1}}
    sweep = client.post("/v1/sweeps", json={"scenes": [{"scene_id": scene_id, "object": "mic"}], "params": params,
                                            "evaluation": RING}).json()
    entry = sweep["entries"][4]
    _as_if_edited(entry["edit_job_id"], grid, grid, None, root)
    return sweep, entry


def _as_if_edited(job_id: str, initial, edited, mask=None, scratch=None) -> None:
    """Record ``job_id`` as succeeded with the artifacts its stages publish (the stages have their own tests)."""
    from sqlalchemy import update

    from voxe_service.db import session_scope
    from voxe_service.models import Job, Reconstruction
    from voxe_service.storage import get_storage
    from voxe_core.refine.storage import save_mask
    from worker import runtime

    storage = get_storage()
    job = runtime.load_job(job_id)
    initial.save(scratch / "initial.safetensors")
    stored = storage.put_file(f"reconstructions/{job.reconstruction_id}/grid.safetensors", scratch / "initial.safetensors")
    if mask is None:
        edited.save(scratch / f"{job_id}.safetensors")
        runtime.publish_artifact(job_id, "edited_grid.safetensors", scratch / f"{job_id}.safetensors", "grid", storage)
    else:
        merge(initial, edited, mask).save(scratch / f"{job_id}.safetensors")
        runtime.publish_artifact(job_id, "refined_grid.safetensors", scratch / f"{job_id}.safetensors", "grid", storage)
        save_mask(scratch / f"{job_id}_mask.safetensors", mask)
        runtime.publish_artifact(job_id, "mask.safetensors", scratch / f"{job_id}_mask.safetensors", "mask", storage)
    with session_scope() as session:
        session.execute(update(Reconstruction).where(Reconstruction.id == job.reconstruction_id)
                        .values(state="succeeded", grid_key=stored.key, grid_size=stored.size,
                                grid_sha256=stored.sha256))
        session.execute(update(Job).where(Job.id == job_id).values(state="succeeded"))


RING = {"views": 4, "elevation": 20.0, "size": 24}


def test_evaluation_job_end_to_end_through_the_api(service, sphere_grid):
    from worker import tasks

    client, scene_id, root = service
    edited, mask = _local_edit(sphere_grid)
    local = client.post("/v1/jobs", json={"scene_id": scene_id, "prompt": "a mic wearing a party hat", "mode": "local",
                                          "edit_words": ["hat"]}).json()
    glob = client.post("/v1/jobs", json={"scene_id": scene_id, "prompt": "a wood carving of a mic"}).json()
    body = {"job_ids": [local["id"], glob["id"]], "object": "mic", "params": RING}
    queued = client.post("/v1/evaluations", json=body)
    assert queued.status_code == 409 and f"job {local['id']!r} is queued" in queued.json()["detail"]

    _as_if_edited(local["id"], sphere_grid, edited, mask, root)
    _as_if_edited(glob["id"], sphere_grid, edited, None, root)
    created = client.post("/v1/evaluations", json=body)
    assert created.status_code == 201, created.text
    job = created.json()
    assert job["mode"] == "evaluate" and job["state"] == "queued" and job["source_job_ids"] == body["job_ids"]
    assert job["models"] == {"sds": None, "attention": None, "clip": "tiny (smoke test, random weights)",
                             "fid": "tiny (smoke test, random weights)"}

    assert tasks.evaluate_task.apply(args=(job["id"],)).get()["state"] == "done"
    done = client.get(f"/v1/jobs/{job['id']}").json()
    assert done["state"] == "succeeded" and done["completed_stages"] == ["evaluate"]
    rows = done["result"]["rows"]
    assert [(r["job_id"], r["mode"]) for r in rows] == [(local["id"], "local"), (glob["id"], "global")]
    assert rows[0]["region"] == "outside mask" and rows[0]["psnr"] > 60  # the refined edit kept the rest exactly
    assert rows[1]["psnr"] < rows[0]["psnr"] and all(r["fid_rec"] > 0 and r["fid_input"] > 0 for r in rows)
    names = [a["name"] for a in client.get(f"/v1/jobs/{job['id']}/artifacts").json()]
    # Listed grid by grid (the views come a chunk at a time): G_i's ring, then each edit's
    assert names == [f"ring_{grid}_{i:03d}.png" for grid in ("initial", local["id"], glob["id"]) for i in range(4)] + [
        "evaluation.json", "evaluation.md"]
    table = client.get(f"/v1/jobs/{job['id']}/artifacts/evaluation.md")
    assert table.text == done["result"]["table"] and table.headers["content-type"].startswith("text/markdown")
    assert json.loads(client.get(f"/v1/jobs/{job['id']}/artifacts/evaluation.json").content)["rows"] == rows

    # Bad requests name the problem.
    again = client.post("/v1/evaluations", json={**body, "job_ids": [job["id"]]})
    assert again.status_code == 422 and "is an evaluation, not an edit" in again.json()["detail"]
    assert client.post("/v1/evaluations", json={**body, "job_ids": ["nope"]}).status_code == 404
    blank = client.post("/v1/evaluations", json={**body, "object": "  "})
    assert blank.status_code == 422 and "object name has no words" in blank.text
    twice = client.post("/v1/evaluations", json={**body, "job_ids": [glob["id"], glob["id"]]})
    assert twice.status_code == 422 and "lists a job twice" in twice.text


@pytest.mark.parametrize("failing_name", ["evaluation.md", "ring_initial_002.png"])
def test_an_evaluation_whose_upload_fails_mid_set_lists_none_of_its_results(service, sphere_grid, monkeypatch,
                                                                             failing_name):
    """The storage failing after evaluation.json was uploaded (S3 throttling evaluation.md) had failed the job with
    the JSON listed without its table; at a ring render, the renders before it. The rings, the JSON and the table
    are published as one set: the stopped run (the outage gives the job back) lists none of them and keeps none of
    their bytes."""
    from service_helpers import failing_uploads
    from voxe_service.storage import get_storage
    from worker import tasks

    client, scene_id, root = service
    edit = client.post("/v1/jobs", json={"scene_id": scene_id, "prompt": "a wood carving of a mic"}).json()
    _as_if_edited(edit["id"], sphere_grid, sphere_grid, None, root)
    job = client.post("/v1/evaluations", json={"job_ids": [edit["id"]], "object": "mic", "params": RING}).json()
    storage = get_storage(tasks.get_settings())
    failing_uploads(monkeypatch, storage, failing_name)
    monkeypatch.setattr("worker.runtime.OUTAGE_PAUSE_S", 0.0)
    result = tasks.evaluate_task.apply(args=(job["id"],))
    assert result.state == "REJECTED" and "SlowDown when uploading" in result.result.reason
    stopped = client.get(f"/v1/jobs/{job['id']}").json()
    assert (stopped["state"], stopped["error"]) == ("running", None)
    assert client.get(f"/v1/jobs/{job['id']}/artifacts").json() == []
    assert storage.list(f"jobs/{job['id']}/") == []



@pytest.mark.parametrize("old_grid", ["deleted", "kept"])
def test_an_evaluation_scores_the_edits_against_the_grid_they_were_edited_from_not_a_later_fit(
        service, sphere_grid, make_sphere_grid, old_grid):
    """A reconstruction whose grid was deleted from the storage is fitted again by the next job that needs it, and
    records the new grid: an evaluation of edits made from the first fit read the reconstruction's grid, so it scored
    each edit against a G_i it was not made from (an unchanged edit's PSNR outside the mask fell from exact to that
    of another sphere). It reads the G_i each source recorded: still stored, it scores against it; deleted, the
    evaluation fails naming it."""
    from sqlalchemy import update

    from voxe_service.db import session_scope
    from voxe_service.models import Reconstruction
    from voxe_service.storage import get_storage
    from worker import runtime, tasks

    client, scene_id, root = service
    edit = client.post("/v1/jobs", json={"scene_id": scene_id, "prompt": "a wood carving of a mic"}).json()
    _as_if_edited(edit["id"], sphere_grid, sphere_grid, None, root)  # (its edit: G_i unchanged)
    storage, rec = get_storage(tasks.get_settings()), runtime.load_reconstruction(edit["reconstruction"]["id"])
    runtime.publish_artifact(edit["id"], "initial_grid.safetensors", root / "initial.safetensors", "grid", storage,
                             key=rec.grid_key)  # (as its reconstruct stage records G_i)
    if old_grid == "deleted":
        storage.delete(rec.grid_key)
    make_sphere_grid(radius=0.5).save(root / "refitted.safetensors")
    refitted = storage.put_file(f"reconstructions/{rec.id}/grid-again.safetensors", root / "refitted.safetensors")
    with session_scope() as session:
        session.execute(update(Reconstruction).where(Reconstruction.id == rec.id).values(
            grid_key=refitted.key, grid_size=refitted.size, grid_sha256=refitted.sha256))
    job = client.post("/v1/evaluations", json={"job_ids": [edit["id"]], "object": "mic", "params": RING}).json()
    outcome = tasks.evaluate_task.apply(args=(job["id"],)).get()["state"]
    done = client.get(f"/v1/jobs/{job['id']}").json()
    if old_grid == "deleted":
        assert (outcome, done["error"]) == ("failed", f"evaluate: StorageError: {rec.grid_key}: not in the storage, "
                                                      "deleted there since it was recorded")
    else:
        assert outcome == "done" and done["result"]["rows"][0]["psnr"] > 60

def test_evaluation_of_a_job_that_failed_after_queueing_fails_with_the_reason(service, sphere_grid):
    from sqlalchemy import update

    from voxe_service.db import session_scope
    from voxe_service.models import Job
    from worker import tasks

    client, scene_id, root = service
    edit = client.post("/v1/jobs", json={"scene_id": scene_id, "prompt": "a wood carving of a mic"}).json()
    _as_if_edited(edit["id"], sphere_grid, sphere_grid, None, root)
    job = client.post("/v1/evaluations", json={"job_ids": [edit["id"]], "object": "mic", "params": RING}).json()
    with session_scope() as session:  # e.g. deleted and re-run meanwhile: the source is no longer a success
        session.execute(update(Job).where(Job.id == edit["id"]).values(state="failed", error="edit: boom"))
    assert tasks.evaluate_task.apply(args=(job["id"],)).get()["state"] == "failed"
    failed = client.get(f"/v1/jobs/{job['id']}").json()
    assert failed["error"] == f"evaluate: source job {edit['id']} failed: edit: boom"
    assert client.get(f"/v1/jobs/{job['id']}/artifacts").json() == []  # nothing half written


def test_sweep_submits_the_paper_protocol_as_one_batch_with_one_table(service, sphere_grid):
    from worker import tasks

    from sqlalchemy import func, select, update

    from voxe_service.db import session_scope
    from voxe_service.models import LOCAL_KEY_ID, ApiKey, Job

    client, scene_id, root = service
    params = {"iterations": 2, "reconstruction": {"resolution": 8, "iterations": 1}}
    body = {"scenes": [{"scene_id": scene_id, "object": "mic"}], "params": params, "evaluation": RING}
    with session_scope() as session:  # one job short of the sweep's 6 edits + 6 evaluations
        session.execute(update(ApiKey).where(ApiKey.id == LOCAL_KEY_ID).values(max_active_jobs=11))
    over = client.post("/v1/sweeps", json=body)  # more than the limit alone: never accepted, so not a 429 to retry
    assert over.status_code == 422 and "this request creates 12 jobs but key 'local (authentication off, loopback only)' may have at most 11" in \
        over.json()["detail"] and over.json()["detail"].endswith(
            "can never be accepted: ask for fewer (a sweep over fewer scenes), or raise VOXE_MAX_ACTIVE_JOBS_PER_KEY")
    with session_scope() as session:  # all or nothing: no job of the refused sweep was kept
        assert session.scalar(select(func.count()).select_from(Job)) == 0
        session.execute(update(ApiKey).where(ApiKey.id == LOCAL_KEY_ID).values(max_active_jobs=None))
    long_object = {**body, "scenes": [{"scene_id": scene_id, "object": "a-" * 49 + "ab"}]}  # 100 characters
    refused = client.post("/v1/sweeps", json=long_object)  # its protocol prompts overrun the text encoder: had been 500
    assert refused.status_code == 422 and refused.json()["detail"].startswith("scenes[0].object: the prompt is at least")
    with session_scope() as session:
        assert session.scalar(select(func.count()).select_from(Job)) == 0
    assert {"/v1/evaluations", "/v1/sweeps", "/v1/sweeps/{sweep_id}"} <= set(client.get("/openapi.json").json()["paths"])
    created = client.post("/v1/sweeps", json=body)
    assert created.status_code == 201, created.text
    sweep = created.json()
    assert sweep["state"] == "queued" and sweep["counts"] == {"queued": 12} and sweep["rows"] == []
    entries = sweep["entries"]
    assert [e["prompt"] for e in entries] == [e.prompt for e in paper_protocol("mic")]
    assert [e["mode"] for e in entries] == ["local"] * 3 + ["global"] * 3
    edit_jobs = [client.get(f"/v1/jobs/{e['edit_job_id']}").json() for e in entries]
    assert [j["edit_words"] for j in edit_jobs[:3]] == [["sunglasses"], ["sweater"], ["party hat"]]
    assert {j["batch_id"] for j in edit_jobs} == {sweep["id"]} and edit_jobs[0]["params"]["iterations"] == 2
    assert len({j["reconstruction"]["id"] for j in edit_jobs}) == 1  # one fit shared by the six edits

    from voxe_service.db import session_scope
    from voxe_service.queue import evaluations_waiting_on

    # A worker that died mid-edit re-queues the edit's remaining stages followed by its evaluation.
    with session_scope() as session:
        edit_job, evaluation_job = (session.get(Job, entries[1][k]) for k in ("edit_job_id", "evaluation_job_id"))
        assert evaluations_waiting_on(session, edit_job) == [entries[1]["evaluation_job_id"]]
        assert evaluations_waiting_on(session, evaluation_job) == []

    edited, mask = _local_edit(sphere_grid)
    for entry in (entries[0], entries[4]):  # one local and one global edit finish; their evaluations run
        _as_if_edited(entry["edit_job_id"], sphere_grid, edited, mask if entry["mode"] == "local" else None, root)
        assert tasks.evaluate_task.apply(args=(entry["evaluation_job_id"],)).get()["state"] == "done"
    summary = client.get(f"/v1/sweeps/{sweep['id']}").json()
    assert summary["state"] == "running" and summary["counts"] == {"queued": 8, "succeeded": 4}
    assert [r["prompt"] for r in summary["rows"]] == [entries[0]["prompt"], entries[4]["prompt"]]
    assert summary["means"]["local"]["count"] == 1 and summary["means"]["all"]["count"] == 2
    assert "| mic | a mic wearing big sunglasses | local |" in summary["table"]
    canceled = client.post(f"/v1/sweeps/{sweep['id']}/cancel").json()
    assert canceled["state"] == "canceled" and canceled["counts"] == {"canceled": 8, "succeeded": 4}
    assert len(canceled["rows"]) == 2  # finished evaluations keep their results
    assert client.post("/v1/sweeps/nope/cancel").status_code == 404
    assert client.get("/v1/sweeps/nope").status_code == 404
    bad = client.post("/v1/sweeps", json={"scenes": [{"scene_id": "nope", "object": "mic"}]})
    assert bad.status_code == 404
    control = client.post("/v1/sweeps", json={"scenes": [{"scene_id": scene_id, "object": "mic\u0007"}]})
    assert control.status_code == 422 and "object name contains control characters" in control.text
    twice = client.post("/v1/sweeps", json={"scenes": [{"scene_id": scene_id, "object": "mic"}] * 2})
    assert twice.status_code == 422 and "lists a scene twice" in twice.text


def test_a_sweep_summarises_while_an_evaluation_runs_and_after_one_failed(service, sphere_grid, monkeypatch):
    """An evaluation's result holds its progress (peak memory) long before its rows, and keeps only that when it
    fails: the summary takes rows from succeeded evaluations only (it had answered 500, KeyError 'rows')."""
    import voxe_core.evaluate
    from voxe_core.progress import Progress
    from worker import tasks

    client, _, _ = service
    sweep, entry = _sweep_with_one_edit_done(service, sphere_grid)
    seen = {}

    def evaluate(initial, edits, obj, clip, fid, images, config, callbacks, device=None, on_ring=None):
        callbacks.progress(Progress("evaluate", 1, 10, info={"peak_memory_gb": 0.5, "peak_memory_kind": "process_rss"}))
        seen["running"] = client.get(f"/v1/sweeps/{sweep['id']}")
        raise ValueError("a ring render has a NaN pixel")

    monkeypatch.setattr(voxe_core.evaluate, "evaluate", evaluate)
    assert tasks.evaluate_task.apply(args=(entry["evaluation_job_id"],)).get()["state"] == "failed"
    assert "peak_memory_gb" in client.get(f"/v1/jobs/{entry['evaluation_job_id']}").json()["result"]
    running = seen["running"]
    assert running.status_code == 200 and running.json()["rows"] == [] and running.json()["counts"]["running"] == 1
    failed = client.get(f"/v1/sweeps/{sweep['id']}")
    assert failed.status_code == 200 and failed.json()["rows"] == [] and failed.json()["counts"]["failed"] == 1


def test_the_smoke_test_models_scores_are_labelled_as_such_in_every_table_and_summary(service, sphere_grid):
    """With VOXE_CLIP_MODEL=tiny and VOXE_FID_MODEL=tiny the job record said so, but evaluation.md, evaluation.json
    (clip_model 'tiny') and the sweep's table (what voxe sweep --wait prints) read as CLIP and FID scores."""
    from voxe_service.settings import smoke_test_roles
    from worker import tasks

    client, _, _ = service
    sweep, entry = _sweep_with_one_edit_done(service, sphere_grid)
    assert tasks.evaluate_task.apply(args=(entry["evaluation_job_id"],)).get()["state"] == "done"
    note = ("**SMOKE TEST**: CLIP and FID are random-weight smoke-test models: these numbers prove the plumbing only "
            "and say nothing about the edits' quality.\n\n| job_id | prompt |")
    job = client.get(f"/v1/jobs/{entry['evaluation_job_id']}").json()
    table = client.get(f"/v1/jobs/{job['id']}/artifacts/evaluation.md").text
    summary = json.loads(client.get(f"/v1/jobs/{job['id']}/artifacts/evaluation.json").content)
    assert table.startswith(note) and job["result"]["table"] == summary["table"] == table
    assert (summary["clip_model"], summary["fid_model"]) == ("tiny (smoke test, random weights)",) * 2
    assert job["result"]["clip_model"] == summary["clip_model"] and summary["smoke_test"] == ["CLIP", "FID"]
    swept = client.get(f"/v1/sweeps/{sweep['id']}").json()
    assert swept["table"].startswith(note.replace("job_id", "object")) and len(swept["rows"]) == 1
    # Only the smoke-test model is named, as the settings say (a tiny model built before its mark is labelled too)
    assert smoke_test_roles({"clip_model": "openai/clip-vit-base-patch32", "fid_model": ""}) == []
    assert smoke_test_roles({"clip_model": "openai/clip-vit-base-patch32", "fid_model": "tiny"}) == ["FID"]


def test_an_evaluation_with_the_default_fid_file_names_it_in_its_results_as_its_job_does(service, sphere_grid):
    """VOXE_FID_MODEL unset (its default, VOXE_MODEL_DIR's inception-2015-12-05.pt): the job said fid
    "inception-2015-12-05.pt in VOXE_MODEL_DIR", its evaluation.json and result fid_model "", naming no network."""
    from sqlalchemy import update

    from voxe_core.tiny_eval import build_tiny_inception
    from voxe_service.db import session_scope
    from voxe_service.models import Job
    from worker import tasks

    client, scene_id, root = service
    edit = client.post("/v1/jobs", json={"scene_id": scene_id, "prompt": "a wood carving of a mic"}).json()
    _as_if_edited(edit["id"], sphere_grid, sphere_grid, None, root)
    job = client.post("/v1/evaluations", json={"job_ids": [edit["id"]], "object": "mic", "params": RING}).json()
    with session_scope() as session:  # as created under the default setting (the fixture's is tiny)
        record = session.get(Job, job["id"])
        session.execute(update(Job).where(Job.id == job["id"]).values(params={**record.params, "fid_model": ""}))
    build_tiny_inception(tasks.get_settings().model_dir / INCEPTION_FILE)  # a stand-in for the real file
    assert tasks.evaluate_task.apply(args=(job["id"],)).get()["state"] == "done"
    done = client.get(f"/v1/jobs/{job['id']}").json()
    summary = json.loads(client.get(f"/v1/jobs/{job['id']}/artifacts/evaluation.json").content)
    assert done["models"]["fid"] == "inception-2015-12-05.pt in VOXE_MODEL_DIR"
    assert summary["fid_model"] == done["result"]["fid_model"] == done["models"]["fid"]
    assert summary["clip_model"] == done["models"]["clip"] == "tiny (smoke test, random weights)"


def test_cli_sweep_submits_to_the_service_and_prints_the_sweep_id(service, tmp_path, capsys):
    from service_helpers import api_in_thread
    from voxe_core.cli import main

    client, scene_id, _ = service
    with api_in_thread() as api:
        out = tmp_path / "sweep.json"
        code = main(["sweep", "--api", api, "--scene", f"{scene_id}=mic", "--evaluation", json.dumps(RING),
                     "--params", '{"iterations": 2}', "--out", str(out)])
        assert code == 0
        sweep = json.loads(out.read_text())
        assert len(sweep["entries"]) == 6 and sweep["state"] == "queued"
        assert client.get(f"/v1/sweeps/{sweep['id']}").json()["counts"] == {"queued": 12}
        assert client.get(f"/v1/jobs/{sweep['entries'][0]['edit_job_id']}").json()["params"]["iterations"] == 2
        printed = capsys.readouterr()
        assert printed.out == f"{sweep['id']}\n" and f"sweep {sweep['id']}: 6 edits of 1 scene(s) queued" in printed.err
        assert main(["sweep", "--api", api, "--scene", "nope=mic"]) == 2
        assert "POST /v1/sweeps: HTTP 404: scene 'nope' not found" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["sweep", "--scene", "no-object-given"])
    assert "expected SCENE_ID=OBJECT" in capsys.readouterr().err


def test_the_footprint_of_a_mask_that_is_not_binary_is_refused(sphere_grid):
    """A 0.3 mask (a probability) had the footprint of a 1 mask: its stand-in's 300 was as opaque as 1,000."""
    half = torch.zeros(sphere_grid.resolution)
    half[: half.shape[0] // 2] = 1.0
    with pytest.raises(ValueError, match="the mask must be binary"):
        mask_footprint(sphere_grid, half * 0.3, 2, 20.0, 16)
    # 0 and 1 in another dtype have a bool mask's footprint
    assert torch.equal(mask_footprint(sphere_grid, half, 2, 20.0, 16),
                       mask_footprint(sphere_grid, half.bool(), 2, 20.0, 16))
