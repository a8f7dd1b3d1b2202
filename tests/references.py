"""Dense, obviously correct reference computations that tests hold the library's fast paths to."""

from __future__ import annotations

import torch


def dense_total_variation(features: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
    """Mean over the given cells of the squared forward differences at their lower corners, per channel.

    Args:
        features: (X, Y, Z, C) vertex features.
        cells: (X-1, Y-1, Z-1) bool, the cells to average over.

    Returns:
        (C,) the mean of (Δx² + Δy² + Δz²) / 3 over ``cells``.
    """
    corner = features[:-1, :-1, :-1]
    dx = (features[1:, :-1, :-1] - corner).square()
    dy = (features[:-1, 1:, :-1] - corner).square()
    dz = (features[:-1, :-1, 1:] - corner).square()
    return ((dx + dy + dz) / 3)[cells].mean(0)
