"""Regularisers of the editing stage (paper §3.2 and its ablations, SPEC §2).

* ``reg3d`` (default): L_reg3D = 1 − Pearson correlation between the raw
  density features of the initial (fixed) and edited grids, over all voxels.
* ``reg3d_plus``: L_reg3D++ = L_reg3D + the mean over R, G, B of the same
  correlation loss on each raw colour channel (so the colour term has the
  density term's scale; range [0, 4]).
* ``volumetric_l1`` / ``volumetric_l2``: mean |Δ| / mean Δ² of raw density.
* ``image_l1`` / ``image_l2``: mean |Δ| / mean Δ² between renders of the
  edited grid and the input views (computed by the caller on images with
  :func:`image_l1` / :func:`image_l2`; not volumetric).

Features layout: ``(..., 4)`` with channel 0 the raw density and 1:4 the raw
colour, as ``VoxelGrid.features`` ``(X, Y, Z, 4)``.

All losses compute in float32 with autocast disabled (bf16/fp16 inputs are
upcast); gradients flow back in the inputs' dtype.
"""

from __future__ import annotations

from typing import Callable, Literal, get_args

import torch
import torch.nn.functional as F

from voxe_core.devices import full_precision

Regulariser = Literal["reg3d", "reg3d_plus", "volumetric_l1", "volumetric_l2", "image_l1", "image_l2"]
REGULARISERS: tuple[str, ...] = get_args(Regulariser)
VOLUMETRIC_REGULARISERS: tuple[str, ...] = ("reg3d", "reg3d_plus", "volumetric_l1", "volumetric_l2")
IMAGE_REGULARISERS: tuple[str, ...] = ("image_l1", "image_l2")
CORRELATED_CHANNELS: dict[str, tuple[int, ...]] = {"reg3d": (0,), "reg3d_plus": (0, 1, 2, 3)}
"""The feature channels each correlation regulariser correlates between G_i and G_e."""
CHANNEL_NAMES: tuple[str, ...] = ("density", "red", "green", "blue")


def _standardise(x: torch.Tensor, eps: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Centred, unit-norm version of flattened ``x`` (float32) and whether ``x`` is constant.

    Two detached rescalings make it robust at any magnitude: by the power of two
    at or below max |x| (so values up to float32's limit neither overflow in the
    mean nor in the squares; a power of two, so the division rounds nothing) and,
    after centring, by the range (so tiny-variance grids are as well conditioned
    as any other). Neither changes the exact result, since the standardised
    vector is scale invariant. Centring runs twice: where the values spread over
    a few float32 steps of their magnitude (1e4 ± 1e-3), the first mean's
    rounding is as large as the deviations, and had made the loss 36 % off a
    float64 one of the same values. Constant inputs give the zero vector with
    zero gradient.
    """
    v = x.reshape(-1).float()
    with torch.no_grad():
        m = v.abs().amax()
        m = torch.where((m > 0) & torch.isfinite(m), m, torch.ones_like(m))
        m = torch.ldexp(torch.ones_like(m), torch.frexp(m).exponent - 1)
    v = v / m
    v = v - v.mean()
    v = v - v.mean()
    with torch.no_grad():
        r = v.amax() - v.amin()
        constant = r == 0  # a NaN range (non-finite input) is not "constant": it must propagate
        r = torch.where(constant, torch.ones_like(r), r)
    v = v / r
    v = v / torch.sqrt((v * v).sum() + eps)
    v = torch.where(constant, torch.zeros_like(v), v)
    return v, constant


def correlation_loss(initial_density: torch.Tensor, edited_density: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """L_reg3D = 1 − Pearson correlation of two equally shaped tensors over all elements.

    Computed on the raw values in float32. Invariant to positive affine maps
    ``a·x + b`` (a > 0) of either argument; 0 for identical grids, 2 for a
    grid and its negation. If either input is constant the correlation is
    undefined: the loss is then exactly 1.0 with a zero (finite) gradient.
    Non-finite inputs give a non-finite loss.
    """
    if initial_density.shape != edited_density.shape:
        raise ValueError(
            f"density shapes differ: initial {tuple(initial_density.shape)} vs edited {tuple(edited_density.shape)}"
        )
    with full_precision(initial_density):
        initial = _standardise(initial_density, eps)
    return _correlation_loss_with(initial, edited_density, eps)


def _correlation_loss_with(standardised_initial: tuple[torch.Tensor, torch.Tensor], edited: torch.Tensor,
                           eps: float) -> torch.Tensor:
    """:func:`correlation_loss` against an initial tensor already through :func:`_standardise` (its result).

    For unit vectors 1 − â·b̂ = ½‖â − b̂‖²; the latter keeps float32's precision where the grids nearly correlate
    (as G_e does near G_i), where 1 − â·b̂ had cancelled to rounding noise: 6e-8 or 0 for a true 1.2e-9, -1.2e-7 for
    G_e = G_i, with a gradient of noise. ``mse_loss``'s fused kernels keep its cost near the dot product's.
    """
    a, initial_constant = standardised_initial
    with full_precision(a, edited):
        b, edited_constant = _standardise(edited, eps)
        half_squared_distance = 0.5 * F.mse_loss(b, a, reduction="sum")
        # Either constant (its vector zero): 1 − â·b̂, exactly 1 with a zero gradient (NaN where the other is NaN).
        return torch.where(initial_constant | edited_constant, half_squared_distance * 0 + 1, half_squared_distance)


def correlation_loss_plus_rgb(initial_features: torch.Tensor, edited_features: torch.Tensor, eps: float = 1e-12) -> torch.Tensor:
    """L_reg3D++ = correlation loss on density + mean of the correlation losses of R, G and B.

    ``features`` are ``(..., 4)``: channel 0 raw density, 1:4 raw colour.
    """
    return volumetric_regulariser("reg3d_plus", initial_features, eps)(edited_features)


def volumetric_l1(initial: torch.Tensor, edited: torch.Tensor) -> torch.Tensor:
    """Mean absolute difference of raw values (float32)."""
    with full_precision(initial, edited):
        return (edited.float() - initial.float()).abs().mean()


def volumetric_l2(initial: torch.Tensor, edited: torch.Tensor) -> torch.Tensor:
    """Mean squared difference of raw values (float32)."""
    with full_precision(initial, edited):
        return (edited.float() - initial.float()).square().mean()


def image_l1(render: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean absolute pixel difference between a render and its input view (float32)."""
    if render.shape != target.shape:
        raise ValueError(f"render {tuple(render.shape)} and target {tuple(target.shape)} differ in shape")
    with full_precision(render, target):
        return (render.float() - target.float()).abs().mean()


def image_l2(render: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean squared pixel difference between a render and its input view (float32)."""
    if render.shape != target.shape:
        raise ValueError(f"render {tuple(render.shape)} and target {tuple(target.shape)} differ in shape")
    with full_precision(render, target):
        return (render.float() - target.float()).square().mean()


def _check_features(initial: torch.Size, edited: torch.Size) -> None:
    if initial != edited:
        raise ValueError(f"feature shapes differ: initial {tuple(initial)} vs edited {tuple(edited)}")
    if initial[-1] != 4:
        raise ValueError(f"expected features (..., 4) (density + RGB), got {tuple(initial)}")


def regulariser_loss(kind: Regulariser, initial_features: torch.Tensor, edited_features: torch.Tensor) -> torch.Tensor:
    """The volumetric regulariser ``kind`` between ``(..., 4)`` feature grids (unweighted).

    ``reg3d`` / ``volumetric_l1`` / ``volumetric_l2`` use the density channel
    only; ``reg3d_plus`` adds the colour channels. Image-space kinds need
    renders: use :func:`image_l1` / :func:`image_l2` (ValueError here).
    """
    return volumetric_regulariser(kind, initial_features)(edited_features)


def volumetric_regulariser(
    kind: Regulariser, initial_features: torch.Tensor, eps: float = 1e-12
) -> Callable[[torch.Tensor], torch.Tensor]:
    """``regulariser_loss(kind, initial_features, ·)`` with the initial grid's share computed once.

    An edit evaluates its regulariser every iteration against a G_i that never
    changes; the correlation losses would otherwise standardise G_i's channels
    each time (27 operations and passes over the grid per channel). G_i is
    fixed (no gradient reaches it), and only what the loss reads of it is
    kept: its standardised channels, or its density.

    Examples:
        >>> initial = torch.linspace(0.0, 1.0, 256).reshape(4, 4, 4, 4)
        >>> loss = volumetric_regulariser("reg3d", initial)
        >>> round(float(loss(initial)), 6), round(float(loss(-initial)), 6)  # itself: 0; its negation: 2
        (0.0, 2.0)
    """
    if kind not in REGULARISERS:
        raise ValueError(f"unknown regulariser {kind!r}; expected one of {REGULARISERS}")
    if kind in IMAGE_REGULARISERS:
        raise ValueError(f"{kind!r} is an image-space regulariser: compare renders with image_l1/image_l2")
    shape = initial_features.shape
    _check_features(shape, shape)
    initial_features = initial_features.detach()
    channels = CORRELATED_CHANNELS.get(kind, ())
    with full_precision(initial_features):
        standardised = [_standardise(initial_features[..., c], eps) for c in channels]
    initial_density = None if channels else initial_features[..., 0].clone()

    def loss(edited_features: torch.Tensor) -> torch.Tensor:
        _check_features(shape, edited_features.shape)
        if kind == "volumetric_l1":
            return volumetric_l1(initial_density, edited_features[..., 0])
        if kind == "volumetric_l2":
            return volumetric_l2(initial_density, edited_features[..., 0])
        density, *colour = (_correlation_loss_with(a, edited_features[..., c], eps) for c, a in zip(channels, standardised))
        return density + torch.stack(colour).mean() if colour else density

    return loss


def constant_correlated_channels(kind: Regulariser, initial_features: torch.Tensor) -> tuple[str, ...]:
    """The names (:data:`CHANNEL_NAMES`) of the channels of G_i's ``(..., 4)`` features that the regulariser ``kind``
    correlates and that hold one value in every voxel; none for a regulariser that correlates nothing.

    Against such a channel the correlation is undefined and its loss term is a constant 1 with zero gradient: that
    term regularises nothing (an empty or unfitted grid's density, a one-coloured grid's colour), while the ``reg``
    it reports reads as the worst correlation. The condition is :func:`_standardise`'s own (its range is 0).

    Examples:
        >>> features = torch.zeros(2, 2, 2, 4)
        >>> features[..., 1] = torch.arange(8.0).reshape(2, 2, 2)  # only the red channel varies
        >>> constant_correlated_channels("reg3d", features), constant_correlated_channels("reg3d_plus", features)
        (('density',), ('density', 'green', 'blue'))
    """
    _check_features(initial_features.shape, initial_features.shape)
    with torch.no_grad(), full_precision(initial_features):
        return tuple(CHANNEL_NAMES[c] for c in CORRELATED_CHANNELS.get(kind, ())
                     if bool(_standardise(initial_features[..., c], 1e-12)[1]))


def sampled_total_variation(
    flat_features: torch.Tensor,
    resolution: tuple[int, int, int],
    occupied_cells: torch.Tensor,
    count: int,
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """Total variation of raw features (C,) over ``count`` voxels drawn from the occupied cells.

    ``flat_features`` is ``VoxelGrid.flat_features`` (X·Y·Z, C) of a grid with ``resolution``;
    ``occupied_cells`` (K,) are flat indices into its (X-1, Y-1, Z-1) cells
    (``Occupancy.flat_cells``). Each drawn cell's lower corner is compared with its +x, +y and
    +z neighbours (all inside the lattice), so the estimate is the mean squared forward
    difference per channel over occupied space: it costs 4·``count`` gathers whatever the
    grid's size, and empty space (no cells) costs nothing and returns zeros. The gradient
    reaches ``flat_features`` as a sparse tensor, as the renderer's does.

    Examples:
        >>> grid = torch.arange(27.0).reshape(27, 1)  # 3³ voxels, value 9x + 3y + z
        >>> sampled_total_variation(grid, (3, 3, 3), torch.arange(8), 64)  # (81 + 9 + 1) / 3
        tensor([30.3333])
    """
    channels = flat_features.shape[1]
    if occupied_cells.numel() == 0 or count < 1:
        return flat_features.new_zeros(channels)
    x, y, z = resolution
    pick = torch.randint(0, occupied_cells.numel(), (count,), generator=generator, device=occupied_cells.device)
    cell = occupied_cells[pick]
    i, rest = cell // ((y - 1) * (z - 1)), cell % ((y - 1) * (z - 1))
    j, k = rest // (z - 1), rest % (z - 1)
    corner = (i * y + j) * z + k
    index = torch.stack([corner, corner + y * z, corner + z, corner + 1])
    values = torch.nn.functional.embedding(index, flat_features, sparse=flat_features.requires_grad)
    return (values[1:] - values[:1]).square().mean(dim=(0, 1))
