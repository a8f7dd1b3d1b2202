import weakref

import pytest
import torch

from voxe_core.losses import (
    REGULARISERS,
    constant_correlated_channels,
    correlation_loss,
    correlation_loss_plus_rgb,
    image_l1,
    image_l2,
    regulariser_loss,
    sampled_total_variation,
    volumetric_l1,
    volumetric_l2,
    volumetric_regulariser,
)

from references import dense_total_variation


def _grid(seed=0, shape=(12, 10, 8)):
    return torch.randn(shape, generator=torch.Generator().manual_seed(seed))


def _pearson64(a, b):
    a = a.double().reshape(-1)
    b = b.double().reshape(-1)
    a = a - a.mean()
    b = b - b.mean()
    return (a * b).sum() / (a.norm() * b.norm())


def test_identical_grids_give_zero():
    g = _grid()
    assert abs(float(correlation_loss(g, g.clone()))) < 1e-6


def test_invariant_to_positive_affine_maps_of_edited():
    a, b = _grid(0), _grid(1)
    base = correlation_loss(a, b)
    assert float(correlation_loss(a, b * 2 + 3)) == pytest.approx(float(base), abs=1e-6)
    assert float(correlation_loss(a, a * 2 + 3)) == pytest.approx(0.0, abs=1e-6)
    assert float(correlation_loss(a, b * 0.001 - 7)) == pytest.approx(float(base), abs=1e-5)


def _loss_and_float64_reference(initial, edited):
    """correlation_loss(initial, edited) and 1 - Pearson's r in float64 of the same values, each with its gradient
    in ``edited``: (loss, reference, gradient, float64 gradient)."""
    edited = edited.detach().requires_grad_(True)
    loss = correlation_loss(initial, edited)
    loss.backward()
    edited64 = edited.detach().double().requires_grad_(True)
    reference = 1 - _pearson64(initial, edited64)
    reference.backward()
    return loss.item(), reference.item(), edited.grad, edited64.grad


def test_matches_float64_pearson_value_and_gradient():
    a = _grid(0)
    b = 0.5 * a + _grid(1)
    loss, ref, grad, grad64 = _loss_and_float64_reference(a, b)
    assert loss == pytest.approx(ref, abs=1e-6)
    torch.testing.assert_close(grad.double(), grad64, rtol=1e-4, atol=1e-7)


@pytest.mark.parametrize("delta", [1e-3, 1e-4])
def test_nearly_equal_grids_match_a_float64_reference_of_the_same_values(delta):
    """G_e near G_i (the edit's start): 1 − â·b̂ in float32 had cancelled to its rounding, 48 times the float64 loss
    at delta 1e-4 (6.0e-8 for 1.24e-9) and 4 % off at 1e-3; ½‖â − b̂‖² keeps float32's relative precision."""
    generator = torch.Generator().manual_seed(0)
    initial = 2 * torch.randn(32, 32, 32, generator=generator) + 1
    edited = initial + delta * torch.randn(initial.shape, generator=generator)
    loss, reference, grad, grad64 = _loss_and_float64_reference(initial, edited)
    assert loss == pytest.approx(reference, rel=1e-3)
    assert float((grad.double() - grad64).norm() / grad64.norm()) < 5e-3
    features = torch.stack([initial, 0.5 * initial, -initial, initial.square()], dim=-1)  # every channel near G_i's
    near = features + delta * torch.randn(features.shape, generator=generator)
    terms = [1 - _pearson64(features[..., c], near[..., c]) for c in range(4)]
    reference = float(terms[0] + torch.stack(terms[1:]).mean())
    assert float(volumetric_regulariser("reg3d_plus", features)(near)) == pytest.approx(reference, rel=1e-3)


@pytest.mark.parametrize("kind", ["reg3d", "reg3d_plus"])
def test_an_edit_starting_at_its_initial_grid_has_a_zero_regulariser_and_gradient(kind):
    """At the first step G_e is G_i: 1 − â·b̂ had been float32's rounding (6.0e-8 here under reg3d_plus; -1.2e-7, a
    negative 1 − r, for other 64³ grids) with a gradient of rounding noise pulling G_e off G_i (here under reg3d too,
    whose loss rounded to 0). Both are exactly 0."""
    features = 2 * torch.randn(64, 64, 64, 4, generator=torch.Generator().manual_seed(0)) + 1
    edited = features.clone().requires_grad_(True)
    loss = volumetric_regulariser(kind, features)(edited)
    loss.backward()
    assert loss.item() == 0.0 and not edited.grad.any()


def test_negated_grid_gives_two():
    g = _grid()
    assert float(correlation_loss(g, -g)) == pytest.approx(2.0, abs=1e-6)


def test_constant_grids_are_finite():
    g = _grid()
    const = torch.full_like(g, 0.37).requires_grad_(True)
    loss = correlation_loss(g, const)
    loss.backward()
    assert loss.item() == 1.0
    assert torch.isfinite(const.grad).all()

    both = torch.full_like(g, 0.1).requires_grad_(True)
    loss = correlation_loss(torch.full_like(g, -2.0), both)
    loss.backward()
    assert loss.item() == 1.0
    assert torch.isfinite(both.grad).all()

    edited = g.clone().requires_grad_(True)
    loss = correlation_loss(torch.zeros_like(g), edited)  # constant initial grid
    loss.backward()
    assert loss.item() == 1.0 and torch.isfinite(edited.grad).all()


@pytest.mark.parametrize("value", [0.0, 0.01, -1e30])
def test_the_channels_a_correlation_regulariser_finds_constant_are_exactly_those_whose_term_is_off(value):
    """A constant channel of G_i makes its correlation term a constant 1 with no gradient (the term is off): those
    are named, exactly; one voxel a float32 step apart, where the term works, is not (nor any channel a regulariser
    that correlates nothing reads)."""
    features = torch.full((6, 5, 4, 4), value)
    features[..., 2] = _grid(shape=(6, 5, 4))  # green varies
    assert constant_correlated_channels("reg3d", features) == ("density",)
    assert constant_correlated_channels("reg3d_plus", features) == ("density", "red", "blue")
    for kind in ("volumetric_l1", "volumetric_l2", "image_l1"):
        assert constant_correlated_channels(kind, features) == ()
    for channel in (0, 1, 3):  # each constant channel's term: 1 whatever G_e, with no gradient
        edited = _grid(1, (6, 5, 4)).requires_grad_(True)
        loss = correlation_loss(features[..., channel], edited)
        loss.backward()
        assert loss.item() == 1.0 and not edited.grad.any()

    features[2, 3, 1, 0] = torch.nextafter(torch.tensor(value), torch.tensor(1.0))  # one step off: not constant
    assert constant_correlated_channels("reg3d", features) == ()
    assert constant_correlated_channels("reg3d_plus", features) == ("red", "blue")
    edited = features[..., 0].clone().requires_grad_(True)
    loss = correlation_loss(features[..., 0], edited)
    loss.backward()
    assert abs(loss.item()) < 1e-6  # its term works: itself correlates fully


def test_tiny_variance_and_huge_values():
    g = _grid()
    tiny = (1e-6 * g).requires_grad_(True)  # variance 1e-12
    loss = correlation_loss(g, tiny)
    loss.backward()
    assert abs(loss.item()) < 1e-5  # scale does not matter
    assert torch.isfinite(tiny.grad).all()

    offset = (5.0 + 1e-3 * g).requires_grad_(True)  # tiny variance around a large mean
    loss = correlation_loss(g, offset)
    loss.backward()
    assert abs(loss.item()) < 1e-3 and torch.isfinite(offset.grad).all()

    huge = (1e30 * g).requires_grad_(True)
    loss = correlation_loss(g, huge)
    loss.backward()
    assert torch.isfinite(loss) and abs(loss.item()) < 1e-5
    assert torch.isfinite(huge.grad).all()
    assert float(correlation_loss(1e30 * g + 1e30, -1e30 * g)) == pytest.approx(2.0, abs=1e-5)


@pytest.mark.parametrize("dtype, offset, spread", [
    *[(torch.float32, *case) for case in [(1e4, 1e-3), (1e4, 1e-2), (-3e5, 1e-2), (1e30, 1e24), (1e-30, 1e-37),
                                          (7.0, 1e-6)]],
    *[(torch.bfloat16, *case) for case in [(1.0, 1e-2), (100.0, 0.5), (-1e4, 64.0), (1e30, 1e28)]],  # a few steps
])
def test_near_constant_grids_match_a_float64_reference_of_the_same_values(dtype, offset, spread):
    """Values spread over a few steps of their dtype at their magnitude: float32 at 1e4 ± 1e-3 had been 36 % off (the
    division by max |x| and the mean's rounding were the size of the deviations), 1e30 ± 1e24 3 %. bf16 inputs are
    upcast to float32, where their few bf16 steps are many float32 ones."""
    generator = torch.Generator().manual_seed(0)
    base = torch.randn(16, 16, 16, generator=generator, dtype=torch.float64)
    initial = (offset + spread * base).to(dtype)
    edited = (offset + spread * (0.6 * base + 0.8 * torch.randn(base.shape, generator=generator,
                                                                dtype=torch.float64))).to(dtype)
    assert 2 <= len(initial.unique()) <= 100  # near-constant, not constant
    loss, reference, grad, grad64 = _loss_and_float64_reference(initial, edited)
    assert loss == pytest.approx(reference, rel=1e-5)
    torch.testing.assert_close(grad.double(), grad64.to(dtype).double(), rtol=1e-2, atol=0.0)


def test_autocast_bf16_inputs_compute_in_float32():
    g = _grid()
    edited = (g + 0.3 * _grid(1)).to(torch.bfloat16).requires_grad_(True)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        loss = correlation_loss(g.to(torch.bfloat16), edited)
    assert loss.dtype == torch.float32
    loss.backward()
    assert edited.grad.dtype == torch.bfloat16 and torch.isfinite(edited.grad).all()
    ref = 1 - _pearson64(g.to(torch.bfloat16).float(), edited.detach().float())
    assert loss.item() == pytest.approx(float(ref), abs=1e-5)
    half = g.half().requires_grad_(True)
    loss = correlation_loss(g.half(), half)
    loss.backward()
    assert abs(loss.item()) < 1e-6 and torch.isfinite(half.grad).all()


def test_shape_mismatch_raises():
    with pytest.raises(ValueError, match=r"^density shapes differ: initial \(3, 3\) vs edited \(9,\)$"):
        correlation_loss(torch.zeros(3, 3), torch.zeros(9))


def test_plus_rgb_adds_mean_colour_correlation():
    init = torch.randn(6, 6, 6, 4, generator=torch.Generator().manual_seed(0))
    edited = init.clone()
    assert abs(float(correlation_loss_plus_rgb(init, edited))) < 1e-6
    edited[..., 1] = -init[..., 1]  # one colour channel anti-correlated: +2/3
    assert float(correlation_loss_plus_rgb(init, edited)) == pytest.approx(2 / 3, abs=1e-5)
    edited[..., 0] = -init[..., 0]  # and density: +2
    assert float(correlation_loss_plus_rgb(init, edited)) == pytest.approx(2 + 2 / 3, abs=1e-5)
    assert float(regulariser_loss("reg3d_plus", init, edited)) == pytest.approx(2 + 2 / 3, abs=1e-5)
    # plain reg3d ignores colour
    edited2 = init.clone()
    edited2[..., 1:] = torch.rand(6, 6, 6, 3)
    assert abs(float(regulariser_loss("reg3d", init, edited2))) < 1e-6


def test_volumetric_and_image_losses():
    init = torch.zeros(4, 4, 4, 4)
    edited = init.clone()
    edited[..., 0] = 2.0  # density differs by 2 everywhere
    edited[..., 1:] = 5.0  # colour must be ignored by the volumetric L1/L2
    assert float(regulariser_loss("volumetric_l1", init, edited)) == pytest.approx(2.0)
    assert float(regulariser_loss("volumetric_l2", init, edited)) == pytest.approx(4.0)
    assert float(volumetric_l1(init[..., 0], edited[..., 0])) == pytest.approx(2.0)
    assert float(volumetric_l2(init[..., 0], edited[..., 0])) == pytest.approx(4.0)
    render = torch.full((1, 3, 4, 4), 0.5)
    target = torch.zeros(1, 3, 4, 4)
    target[..., :2, :] = 1.0  # half the pixels differ by 0.5 one way, half the other way
    assert float(image_l1(render, target)) == pytest.approx(0.5)
    assert float(image_l2(render, target)) == pytest.approx(0.25)
    with pytest.raises(ValueError, match=r"^render \(1, 3, 4, 4\) and target \(1, 3, 4, 2\) differ in shape$"):
        image_l1(render, target[..., :2])


def test_regulariser_kinds():
    assert REGULARISERS == ("reg3d", "reg3d_plus", "volumetric_l1", "volumetric_l2", "image_l1", "image_l2")
    init = torch.randn(3, 3, 3, 4)
    with pytest.raises(ValueError, match="image"):
        regulariser_loss("image_l1", init, init)
    with pytest.raises(ValueError, match="unknown"):
        regulariser_loss("tv", init, init)
    with pytest.raises(ValueError, match=r"^expected features \(\.\.\., 4\) \(density \+ RGB\), got \(3, 3, 3, 3\)$"):
        regulariser_loss("reg3d", init[..., :3], init[..., :3])


def test_a_bound_regulariser_standardises_the_initial_grid_once():
    """What an edit evaluates every iteration: the initial grid's standardised channels are computed at binding, so a
    later change to that tensor no longer reaches the loss, which keeps none of it but what it reads; the values are
    the per-channel correlation losses; G_i is fixed: no gradient reaches it, and each iteration backpropagates."""
    g = torch.Generator().manual_seed(0)
    init = torch.randn(5, 5, 5, 4, generator=g)
    edited = init + 0.3 * torch.randn(5, 5, 5, 4, generator=g)
    expected = {"reg3d": correlation_loss(init[..., 0], edited[..., 0]),
                "reg3d_plus": correlation_loss(init[..., 0], edited[..., 0]) + torch.stack(
                    [correlation_loss(init[..., c], edited[..., c]) for c in (1, 2, 3)]).mean(),
                "volumetric_l1": volumetric_l1(init[..., 0], edited[..., 0])}
    for kind, value in expected.items():
        moving = init.clone().requires_grad_(True)
        loss = volumetric_regulariser(kind, moving)
        with torch.no_grad():
            moving.fill_(float("nan"))
        assert torch.equal(loss(edited), value)
        released = weakref.ref(moving)
        del moving
        assert released() is None  # the loss holds its own copy of what it reads, not G_i's tensor
        param = edited.clone().requires_grad_(True)
        for _ in range(2):  # an edit's iterations: a graph of G_i's would refuse the second backward
            loss(param).backward()
    with pytest.raises(ValueError, match="feature shapes differ"):
        volumetric_regulariser("reg3d", init)(edited[:4])


def test_gradient_flows_into_feature_parameter():
    init = torch.randn(5, 5, 5, 4, generator=torch.Generator().manual_seed(0))
    param = torch.nn.Parameter(init + 0.1 * torch.randn(5, 5, 5, 4, generator=torch.Generator().manual_seed(1)))
    for kind in ("reg3d", "reg3d_plus", "volumetric_l1", "volumetric_l2"):
        param.grad = None
        regulariser_loss(kind, init, param).backward()
        assert torch.isfinite(param.grad).all() and param.grad.abs().sum() > 0
        if kind in ("reg3d", "volumetric_l1", "volumetric_l2"):
            assert param.grad[..., 1:].abs().sum() == 0  # density only


def test_sampled_total_variation_estimates_the_dense_value_over_occupied_cells_only():
    features = torch.randn(7, 6, 5, 4, generator=torch.Generator().manual_seed(0))
    cells = torch.zeros(6, 5, 4, dtype=torch.bool)
    cells[1:4, 2:4, 1:3] = True
    features[~torch.nn.functional.pad(cells, (0, 1, 0, 1, 0, 1))] *= 100  # voxels no occupied cell starts at
    flat_cells = cells.reshape(-1).nonzero()[:, 0]
    estimate = sampled_total_variation(features.reshape(-1, 4), (7, 6, 5), flat_cells, 200_000,
                                       torch.Generator().manual_seed(1))
    exact = dense_total_variation(features, cells)
    assert torch.allclose(estimate, exact, rtol=0.03)
    one_cell = torch.tensor([int(flat_cells[5])])  # a single cell: the estimate is exact
    only = torch.zeros_like(cells).reshape(-1)
    only[one_cell] = True
    assert torch.allclose(sampled_total_variation(features.reshape(-1, 4), (7, 6, 5), one_cell, 3),
                          dense_total_variation(features, only.reshape(cells.shape)))


def test_sampled_total_variation_gradient_is_sparse_and_local():
    flat = torch.nn.Parameter(torch.randn(5 * 5 * 5, 4, generator=torch.Generator().manual_seed(0)))
    cell = 1 * 16 + 2 * 4 + 3  # cell (1, 2, 3) of the 4³ cells; its lower corner is voxel (1, 2, 3)
    sampled_total_variation(flat, (5, 5, 5), torch.tensor([cell]), 10).sum().backward()
    assert flat.grad.is_sparse
    grad = flat.grad.to_dense().reshape(5, 5, 5, 4)
    touched = {tuple(i) for i in grad.abs().sum(-1).nonzero().tolist()}
    assert touched == {(1, 2, 3), (2, 2, 3), (1, 3, 3), (1, 2, 4)}
    value = flat.detach().reshape(5, 5, 5, 4)
    expected = -2 / 3 * (value[2, 2, 3] + value[1, 3, 3] + value[1, 2, 4] - 3 * value[1, 2, 3])  # d/d corner
    assert torch.allclose(grad[1, 2, 3], expected, atol=1e-5)


def test_sampled_total_variation_of_empty_space_is_zero_and_costs_no_gather():
    flat = torch.nn.Parameter(torch.randn(27, 4))
    value = sampled_total_variation(flat, (3, 3, 3), torch.zeros(0, dtype=torch.long), 100)
    assert torch.equal(value, torch.zeros(4)) and not value.requires_grad
