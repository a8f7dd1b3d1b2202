"""PSNR against closed forms; SSIM against scikit-image's reference implementation."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from skimage.metrics import structural_similarity

from voxe_core.metrics import gaussian_window, psnr, ssim


def skimage_ssim(a: torch.Tensor, b: torch.Tensor) -> float:
    return structural_similarity(
        a.double().numpy(), b.double().numpy(), gaussian_weights=True, sigma=1.5,
        use_sample_covariance=False, data_range=1, channel_axis=-1,
    )


def smooth_noise(h: int, w: int, seed: int) -> torch.Tensor:
    """Random-ish image: low-frequency structure plus pixel noise, in [0, 1]."""
    g = torch.Generator().manual_seed(seed)
    coarse = torch.rand(1, 3, h // 6 + 2, w // 6 + 2, generator=g)
    smooth = torch.nn.functional.interpolate(coarse, size=(h, w), mode="bilinear", align_corners=False)[0]
    noisy = smooth + 0.08 * torch.randn(3, h, w, generator=g)
    return noisy.permute(1, 2, 0).clamp(0, 1)


def test_psnr_closed_form_and_max_val():
    a = torch.full((8, 9, 3), 0.5)
    b = a + 0.1  # MSE 0.01 -> 20 dB
    assert isinstance(psnr(a, b), float)
    assert psnr(a, b) == pytest.approx(20.0, abs=1e-4)
    # Same error on a 0..255 scale: MSE 0.01·255², max 255 -> still 20 dB.
    assert psnr(a * 255, b * 255, max_val=255.0) == pytest.approx(20.0, abs=1e-4)
    assert psnr(a, a) == math.inf


def test_psnr_batch_gives_one_value_per_image():
    a = torch.zeros(3, 6, 7, 3)
    b = torch.zeros(3, 6, 7, 3)
    b[0] += 0.1  # 20 dB
    b[1] += 0.01  # 40 dB
    b[2, 0, 0, 0] = 1.0  # MSE 1/126 -> 10·log10(126)
    values = psnr(a, b)
    assert isinstance(values, torch.Tensor) and values.shape == (3,)
    assert values.tolist() == pytest.approx([20.0, 40.0, 10 * math.log10(6 * 7 * 3)], abs=1e-3)


def test_gaussian_window_is_sigma_1_5_with_11_taps():
    w = gaussian_window()
    assert w.shape == (11,) and float(w.sum()) == pytest.approx(1.0)
    x = torch.arange(11, dtype=torch.float64) - 5
    expected = torch.exp(-x**2 / (2 * 1.5**2))
    assert torch.allclose(w, expected / expected.sum())


@pytest.mark.parametrize("shape,seed", [((32, 32), 0), ((27, 45), 1), ((64, 40), 2)])
def test_ssim_matches_skimage(shape, seed):
    a = smooth_noise(*shape, seed)
    b = (a + 0.15 * torch.randn(a.shape, generator=torch.Generator().manual_seed(seed + 10))).clamp(0, 1)
    ours = ssim(a, b)
    ref = skimage_ssim(a, b)
    assert isinstance(ours, float)
    assert 0.05 < ref < 0.99  # a meaningful comparison, not a degenerate one
    assert ours == pytest.approx(ref, abs=1e-4)
    # Unrelated images: still matches, and far lower.
    c = smooth_noise(*shape, seed + 100)
    assert ssim(a, c) == pytest.approx(skimage_ssim(a, c), abs=1e-4)
    assert ssim(a, c) < ours


def test_ssim_is_one_for_identical_and_symmetric():
    a = smooth_noise(24, 30, 3)
    assert ssim(a, a) == pytest.approx(1.0, abs=1e-6)
    b = (a * 0.8 + 0.1).clamp(0, 1)
    assert ssim(a, b) == pytest.approx(ssim(b, a), abs=1e-7)
    assert ssim(a, b) < 0.999


def test_ssim_batch_matches_per_image_and_skimage():
    imgs = torch.stack([smooth_noise(20, 22, s) for s in range(3)])
    refs = torch.stack([smooth_noise(20, 22, s + 50) for s in range(3)])
    refs[1] = imgs[1]
    values = ssim(imgs, refs)
    assert values.shape == (3,)
    for i in range(3):
        assert float(values[i]) == pytest.approx(skimage_ssim(imgs[i], refs[i]), abs=1e-4)
    assert float(values[1]) == pytest.approx(1.0, abs=1e-6)


def test_ssim_uses_per_channel_statistics():
    # Swapping colour channels keeps every grey-level statistic but breaks per-channel structure.
    a = smooth_noise(32, 32, 7)
    swapped = a[..., [2, 0, 1]]
    assert ssim(a, swapped) == pytest.approx(skimage_ssim(a, swapped), abs=1e-4)
    assert ssim(a, swapped) < 0.9


def test_uint8_images_are_8_bit_pixels_whose_255_is_the_peak():
    """Read with the default peak of 1 they had been values up to 255: black against white scored -48 dB."""
    black, white = torch.zeros(12, 12, 3, dtype=torch.uint8), torch.full((12, 12, 3), 255, dtype=torch.uint8)
    assert psnr(black, white) == pytest.approx(0.0, abs=1e-6)  # MSE 1 on a peak of 1
    pixels = (smooth_noise(16, 20, 4) * 255).round().to(torch.uint8)
    other = (smooth_noise(16, 20, 5) * 255).round().to(torch.uint8)
    as_floats = pixels.double() / 255, other.double() / 255
    assert psnr(pixels, other) == pytest.approx(psnr(*as_floats), abs=1e-4)
    assert psnr(pixels, as_floats[1]) == pytest.approx(psnr(*as_floats), abs=1e-4)  # one of each
    assert psnr(pixels, other, max_val=255.0) == pytest.approx(psnr(*as_floats), abs=1e-4)  # 255 on a peak of 255
    assert ssim(pixels, other) == pytest.approx(ssim(*as_floats), abs=1e-6)
    assert ssim(pixels, other, data_range=255.0) == pytest.approx(ssim(*as_floats), abs=1e-6)
    with pytest.raises(ValueError, match="int32"):
        psnr(pixels.int(), other.int())


def test_bool_images_are_0_and_1_and_integer_images_are_on_the_scale_they_are_given():
    """53ec9c9 refused every integer image but uint8, bool and explicitly scaled ones too, which had worked."""
    mask = smooth_noise(16, 20, 6) > 0.5
    other = smooth_noise(16, 20, 7) > 0.5
    assert psnr(mask, other) == pytest.approx(psnr(mask.double(), other.double()), abs=1e-4)
    assert ssim(mask, other) == pytest.approx(ssim(mask.double(), other.double()), abs=1e-6)
    assert psnr(mask, mask.float()) == math.inf
    levels = (smooth_noise(16, 20, 4) * 1000).round().int()
    other_levels = (smooth_noise(16, 20, 5) * 1000).round().int()
    as_floats = levels.double() / 1000, other_levels.double() / 1000
    assert psnr(levels, other_levels, max_val=1000) == pytest.approx(psnr(*as_floats), abs=1e-4)
    assert ssim(levels, other_levels, data_range=1000) == pytest.approx(ssim(*as_floats), abs=1e-6)
    assert psnr(levels.long(), other_levels.long(), max_val=1.0) == pytest.approx(psnr(*as_floats) - 60, abs=1e-4)
    with pytest.raises(ValueError, match="int64 images say no scale"):
        ssim(levels.long(), other_levels.long())


def test_metric_input_errors():
    with pytest.raises(ValueError, match="shape"):
        psnr(torch.zeros(4, 4, 3), torch.zeros(4, 5, 3))
    with pytest.raises(ValueError, match="at least 11"):
        ssim(torch.zeros(10, 30, 3), torch.zeros(10, 30, 3))
    assert np.isfinite(ssim(torch.zeros(11, 11, 3), torch.zeros(11, 11, 3)))


@pytest.mark.parametrize("shape", [(0, 0, 3), (4, 0, 3), (16, 16, 0), (2, 0, 16, 3)])
def test_images_without_pixels_are_refused_naming_their_shape(shape):
    # (PSNR of 0x0 images had been NaN, SSIM of images with no channel a RuntimeError from a reshape)
    for metric in (psnr, ssim):
        with pytest.raises(ValueError, match=rf"images have no pixels: shaped \({', '.join(map(str, shape))}\)"):
            metric(torch.zeros(shape), torch.zeros(shape))
    assert psnr(torch.zeros(0, 4, 4, 3), torch.zeros(0, 4, 4, 3)).shape == (0,)  # an empty batch stays an empty result


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_images_holding_nan_or_infinite_pixels_are_refused_naming_how_many(value):
    # (PSNR and SSIM of them had been NaN, silently: a score no caller could tell from a real one, nor write as JSON)
    a, b = smooth_noise(16, 16, 0), smooth_noise(16, 16, 1)
    a[3, 4, 1] = a[5, 6] = value
    keep = torch.ones(16, 16, dtype=torch.bool)
    keep[3, 4] = keep[5, 6] = False  # out of the score, and still refused: its NaN had leaked into PSNR's sum
    for metric in (psnr, ssim):
        with pytest.raises(ValueError, match=r"^images hold NaN or infinite values, at 2 pixels of the first and 0 "
                                             r"of the second, which no score is defined for \(a diverged render\?\)$"):
            metric(a, b)
        with pytest.raises(ValueError, match=r"at 0 pixels of the first and 2 of the second"):  # a batch alike
            metric(b[None], a[None])
        with pytest.raises(ValueError, match=r"at 2 pixels of the first and 0 of the second"):
            metric(a, b, keep=keep)
    assert math.isnan(psnr(a.nan_to_num(0.5, 0.5), b, keep=torch.zeros(16, 16, dtype=torch.bool)))  # none kept: NaN


@pytest.mark.parametrize("peak", [0, -1.0, float("nan"), float("inf"), "1"])
def test_a_peak_that_is_no_positive_number_is_refused(peak):
    # (max_val 0 had scored -inf dB, -1 the PSNR of a peak of 1, a NaN data_range a NaN SSIM)
    a = smooth_noise(16, 16, 0)
    for metric, name in ((psnr, "max_val"), (ssim, "data_range")):
        with pytest.raises(ValueError, match=rf"max_val / data_range must be a positive number.*got {peak!r}"):
            metric(a, a.flip(0), **{name: peak})
    assert psnr(a, a.flip(0), max_val=2) == pytest.approx(psnr(a, a.flip(0)) + 20 * math.log10(2), abs=1e-4)
