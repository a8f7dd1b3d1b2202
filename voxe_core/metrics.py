"""Image-quality metrics for renders against reference views: PSNR and SSIM.

Images are float tensors (..., H, W, 3) in [0, 1] (any channel count works), or uint8 pixels, 255 standing for
``max_val`` / ``data_range`` (as every other reader of images here takes them: ``export.to_uint8``, the evaluation's
scorers). bool images are 0 and 1; other integer images are values on the scale of an explicit ``max_val`` /
``data_range`` (on the default peak of 1 they are refused). Images holding NaN or infinite values are refused, a
masked-out pixel's too.
A single pair (H, W, C) gives a Python float; a batch (N, ..., H, W, C) gives a
tensor with one value per image. SSIM is the standard one of Wang et al. 2004
as scikit-image computes it with ``gaussian_weights=True, sigma=1.5,
use_sample_covariance=False, data_range=1, channel_axis=-1``: an 11-tap
Gaussian window (sigma 1.5), K1 = 0.01, K2 = 0.03, per channel, averaged over
the 'valid' region (pixels at least 5 from the border) and the channels.

Both take an optional ``keep`` mask (..., H, W) bool: the pixels the metric is
about (e.g. outside a local edit). PSNR averages the squared error over kept
pixels; SSIM over the window centres whose whole 11x11 window is kept, so no
excluded pixel leaks into the score. An image with nothing kept gives NaN.
"""

from __future__ import annotations

import math
import numbers

import torch
import torch.nn.functional as F

SSIM_SIGMA = 1.5
SSIM_WINDOW = 11  # 2 * int(3.5 * sigma + 0.5) + 1, scikit-image's truncation
SSIM_K1 = 0.01
SSIM_K2 = 0.03
DEFAULT_PEAK = 1.0
"""The peak (``max_val`` / ``data_range``) of images in [0, 1]."""
PSNR_CAP_DB = 100.0
"""What an average over views counts an infinite PSNR (identical views) as, so one cannot swamp the mean (nor leave
JSON, which has no infinity)."""


def _as_pair(a, b, peak: float | None) -> tuple[torch.Tensor, torch.Tensor, float]:
    """The images as floats on one device, and the peak (``None``: the default, :data:`DEFAULT_PEAK`).

    uint8 pixels are scaled so 255 is the peak (8-bit pixels read with the default peak of 1 had been compared as
    values up to 255: two uint8 images, black and white, scored -48 dB); bool images are 0 and 1, as
    ``export.to_uint8`` reads them; other integer images are values on the scale of an explicit peak, and refused
    on the default one, which says nothing of theirs."""
    if peak is not None and not (isinstance(peak, numbers.Real) and math.isfinite(peak) and peak > 0):
        # (a peak of 0 had scored -inf dB, -1 the PSNR of a peak of 1, NaN a NaN)
        raise ValueError(f"max_val / data_range must be a positive number, the value standing for the peak, "
                         f"got {peak!r}")
    scale = DEFAULT_PEAK if peak is None else peak
    a, b = (_on_scale(torch.as_tensor(image), scale, explicit=peak is not None) for image in (a, b))
    if a.shape != b.shape:
        raise ValueError(f"images differ in shape: {tuple(a.shape)} vs {tuple(b.shape)}")
    if a.dim() < 3:
        raise ValueError(f"expected images shaped (..., H, W, C), got {tuple(a.shape)}")
    if 0 in a.shape[-3:]:  # (PSNR had averaged no pixels into NaN, SSIM failed in a reshape naming no image)
        raise ValueError(f"images have no pixels: shaped {tuple(a.shape)}, (..., H, W, C) with H, W and C at least 1")
    b = b.to(a.device)
    if any(bad := [int((~image.isfinite()).any(-1).sum()) for image in (a, b)]):  # (scored NaN, silently)
        raise ValueError(f"images hold NaN or infinite values, at {bad[0]} pixels of the first and {bad[1]} of the "
                         "second, which no score is defined for (a diverged render?)")
    return a, b, scale


def _on_scale(image: torch.Tensor, peak: float, explicit: bool) -> torch.Tensor:
    if image.dtype == torch.uint8:
        return image.double() * (peak / 255.0)
    if image.is_floating_point():
        return image
    if image.dtype != torch.bool and not explicit:
        raise ValueError(f"{image.dtype} images say no scale: give floats or uint8 pixels, or pass the value that "
                         "stands for the peak (max_val / data_range)")
    return image.double()


def _keep_mask(keep, a: torch.Tensor) -> torch.Tensor | None:
    if keep is None:
        return None
    keep = torch.as_tensor(keep, device=a.device)
    if keep.dtype != torch.bool or tuple(keep.shape) != tuple(a.shape[:-1]):
        raise ValueError(f"keep must be a bool mask shaped {tuple(a.shape[:-1])}, got {keep.dtype} {tuple(keep.shape)}")
    return keep


def _masked_mean(values: torch.Tensor, keep: torch.Tensor | None) -> torch.Tensor:
    """Mean over the last two (pixel) dims, only where ``keep``; NaN where nothing is kept."""
    if keep is None:
        return values.mean(dim=(-2, -1))
    weights = keep.to(values.dtype)
    return (values * weights).sum(dim=(-2, -1)) / weights.sum(dim=(-2, -1))  # 0/0 -> NaN


def _result(values: torch.Tensor, single: bool):
    return float(values.reshape(())) if single else values


def psnr(a, b, max_val: float | None = None, keep=None):
    """Peak signal-to-noise ratio in dB, 10·log10(max_val² / MSE) per image (MSE over ``keep`` pixels).

    (H, W, C) -> float; (..., H, W, C) -> tensor of shape (...). Identical images give inf.
    """
    a, b, max_val = _as_pair(a, b, max_val)
    keep = _keep_mask(keep, a)
    diff = a.double() - b.double()
    mse = _masked_mean(diff.square().mean(-1), keep)
    values = 10.0 * torch.log10(max_val**2 / mse)  # mse 0 -> inf, as it should
    return _result(values.to(torch.float32), a.dim() == 3)


def gaussian_window(size: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA, dtype=torch.float64) -> torch.Tensor:
    """The normalised 1-D Gaussian taps SSIM filters with (separable in x and y)."""
    x = torch.arange(size, dtype=dtype) - (size - 1) / 2
    w = torch.exp(-0.5 * (x / sigma) ** 2)
    return w / w.sum()


def ssim(a, b, data_range: float | None = None, keep=None):
    """Structural similarity, matching ``skimage.metrics.structural_similarity`` (see module doc).

    (H, W, C) -> float; (..., H, W, C) -> tensor of shape (...). Images must be
    at least 11 pixels on each side. ``keep``: average only over windows lying wholly in it.
    """
    a, b, data_range = _as_pair(a, b, data_range)
    keep = _keep_mask(keep, a)
    *batch, h, w, c = a.shape
    if h < SSIM_WINDOW or w < SSIM_WINDOW:
        raise ValueError(f"SSIM needs images of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels, got {w}x{h}")
    # float64 where it is cheap: the variance terms subtract nearly equal numbers.
    dtype = torch.float64 if a.device.type == "cpu" else torch.float32
    # (..., H, W, C) -> (B*C, 1, H, W): every channel is filtered on its own.
    x = a.to(dtype).reshape(-1, h, w, c).permute(0, 3, 1, 2).reshape(-1, 1, h, w)
    y = b.to(dtype).reshape(-1, h, w, c).permute(0, 3, 1, 2).reshape(-1, 1, h, w)
    taps = gaussian_window(dtype=dtype).to(a.device)
    kx, ky = taps.view(1, 1, 1, -1), taps.view(1, 1, -1, 1)

    def blur(t: torch.Tensor) -> torch.Tensor:  # 'valid' separable convolution
        return F.conv2d(F.conv2d(t, kx), ky)

    stack = torch.cat([x, y, x * x, y * y, x * y])
    mu_x, mu_y, xx, yy, xy = blur(stack).chunk(5)
    var_x = xx - mu_x * mu_x
    var_y = yy - mu_y * mu_y
    cov = xy - mu_x * mu_y
    c1, c2 = (SSIM_K1 * data_range) ** 2, (SSIM_K2 * data_range) ** 2
    s = ((2 * mu_x * mu_y + c1) * (2 * cov + c2)) / ((mu_x.square() + mu_y.square() + c1) * (var_x + var_y + c2))
    window_kept = None
    if keep is not None:  # a window is kept when none of its pixels is excluded (an 11x11 min-pool)
        excluded = (~keep).reshape(-1, 1, h, w).to(dtype)
        window_kept = F.max_pool2d(excluded, SSIM_WINDOW, stride=1)[:, 0] == 0
    per_image = _masked_mean(s.reshape(-1, c, *s.shape[-2:]).mean(dim=1), window_kept)
    values = per_image.reshape(batch).to(torch.float32)
    return _result(values, not batch)


__all__ = ["PSNR_CAP_DB", "psnr", "ssim", "gaussian_window"]
