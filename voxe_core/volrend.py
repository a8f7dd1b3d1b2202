"""Volume-rendering arithmetic shared by the samplers and the compositor (as nerfacc's ``volrend.py``).

Samples are packed: the samples of all rays in one list, ray by ray in marching
order (:class:`RaySamples`). Transmittance comes from one float64 prefix sum over
the list, its rounding errors added back per ray, so a ray behind rays of large
optical depth keeps its own.

Examples:
    >>> ray = torch.tensor([0, 0, 1])
    >>> transmittance(torch.tensor([1.0, 1.0, 2.0]), ray).tolist()  # exp(-optical depth in front of each)
    [1.0, 0.3678794503211975, 1.0]
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

# Optical depth per sample beyond which alpha is 1 in float32; clamping there keeps
# cumulative sums finite for saturated densities without changing the image.
MAX_SAMPLE_OPTICAL_DEPTH = 1e4


@dataclass
class RaySamples:
    """The samples of a group of rays, packed ray by ray in marching order: what a grid's sampler yields.

    ``ray`` (S,) indexes the rays given to the sampler, non-decreasing (the rays in their given order:
    :func:`transmittance` relies on it); ``t`` (S,) is each sample's distance along
    its ray, ``delta`` (S,) the path length it stands for, ``points`` (S, 3) where the field is
    evaluated, in the grid's lattice coordinates (what ``VoxelGrid.interpolate`` takes).
    ``candidates`` counts the samples the group's rays had before the occupancy test, ``probed``
    the density evaluations spent finding where the rays stop (early stopping).
    """

    ray: torch.Tensor
    t: torch.Tensor
    delta: torch.Tensor
    points: torch.Tensor
    candidates: int = 0
    probed: int = 0

    def select(self, index: torch.Tensor) -> "RaySamples":
        """The samples at ``index`` (kept in order), with the same counts."""
        return RaySamples(self.ray.index_select(0, index), self.t.index_select(0, index),
                          self.delta.index_select(0, index), self.points.index_select(0, index),
                          self.candidates, self.probed)


def optical_depth(sigma: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """sigma * delta per sample, clamped to ``MAX_SAMPLE_OPTICAL_DEPTH``; 0 where the path has no length, whatever
    the density (an infinite one, a float32 overflow, had made it inf · 0 = NaN, and the pixel and gradients NaN)."""
    return (torch.where(delta > 0, sigma, 0.0) * delta).clamp(max=MAX_SAMPLE_OPTICAL_DEPTH)


def host_reads_are_free(device: torch.device) -> bool:
    """Whether reading a value back costs nothing on ``device`` (the CPU: it computed it); on CUDA a read waits for
    the queue to drain, which the hot loop avoids."""
    return device.type == "cpu"


def transmittance(optical: torch.Tensor, ray: torch.Tensor) -> torch.Tensor:
    """Transmittance in front of each packed sample (S,): exp of minus the optical depth before it on its ray.

    One float64 prefix sum over all rays, minus each ray's value at its first
    sample, plus what the sum rounded away on the ray (each addition's error, added up in a second prefix sum):
    a segmented scan's result, each ray's own to float64 rounding of its own depths, in two scans.
    Without them, a ray behind 3,000 opaque ones (a running sum near 1e10, rounding ~1e-6 an addition) had been
    3e-6 off in its pixel and up to 8e-4 in a sample's density gradient.
    ``ray`` (S,) is non-decreasing (packed ray by ray), so each sample's ray starts
    at the leftmost position of its value: a binary search per sample, with no host
    read and in parallel on a GPU (a running maximum, ``cummax``, would scan a 1-D
    tensor in one CUDA thread block). A NaN depth stays on its own ray: it is summed as 0 and the samples
    behind it on its ray are NaN (a NaN in the shared sum had turned every later ray of the pass NaN).
    """
    nan = optical.isnan()
    if host_reads_are_free(optical.device) and not bool(nan.any()):  # skips the bookkeeping below: 2.5x the time
        nan = None
    wide = optical.double() if nan is None else optical.double().masked_fill(nan, 0.0)
    running = wide.cumsum(0)
    before = torch.cat([running.new_zeros(1), running])[:-1]  # the sum's value before each sample, as it added
    first = torch.searchsorted(ray, ray)
    with torch.no_grad():  # a constant in the depths' gradient; in place: each 8-byte-a-sample buffer costs time
        # What each addition rounded away, wide - (running - before): exact where the sum before is at least the
        # sample (Fast2Sum), else to the sample's own rounding; then summed in front of each sample, on its ray.
        error_before = wide.new_zeros(wide.shape[0] + 1)
        torch.sub(before, running, out=error_before[1:]).add_(wide)
        error_before = error_before.cumsum_(0)[:-1]
        lost = error_before.index_select(0, first).neg_().add_(error_before)
    t = torch.exp(before.index_select(0, first) - before - lost)
    if nan is not None:
        nans_before = nan.cumsum(0) - nan.long()
        t = t.masked_fill(nans_before > nans_before.index_select(0, first), float("nan"))
    return t.to(optical.dtype)
