import pytest
import torch

from frugalnerf_ns.model import losses


def test_multiscale_color_loss_is_the_weighted_sum_of_per_scale_mse():
    target = torch.zeros(4, 3)
    preds = [torch.full((4, 3), 0.1), torch.full((4, 3), 0.2), torch.full((4, 3), 0.3)]
    value = losses.multiscale_color_loss(preds, target, [1.0, 10.0, 10.0])
    assert torch.allclose(value, torch.tensor(0.01 + 10 * 0.04 + 10 * 0.09))
    with pytest.raises(ValueError, match="3 scale predictions but 2"):
        losses.multiscale_color_loss(preds, target, [1.0, 1.0])


def test_total_variation_hand_computed_and_edge_weights():
    plane = torch.tensor([[[[0.0, 1.0], [2.0, 4.0]]]])
    # vertical diffs: 2, 3 -> mean 6.5; horizontal: 1, 2 -> mean 2.5
    assert torch.allclose(losses.total_variation(plane), torch.tensor(9.0))
    line = torch.tensor([[[[0.0], [1.0], [3.0]]]])
    assert torch.allclose(losses.total_variation(line), torch.tensor(2.5))
    # A strong appearance edge between the two columns switches the horizontal term (nearly) off.
    appearance = torch.tensor([[[[0.0, 50.0], [0.0, 50.0]]]])
    weighted = losses.total_variation(plane, losses.edge_weights_from(appearance))
    assert torch.allclose(weighted, torch.tensor(6.5), atol=1e-6)


def test_edge_weights_are_detached():
    appearance = torch.rand(1, 2, 4, 4, requires_grad=True)
    density = torch.rand(1, 2, 4, 4, requires_grad=True)
    losses.grid_tv_loss([density], [], 1.0, 1.0, edge_planes=[appearance]).backward()
    assert appearance.grad is None and density.grad is not None



def _views_tv(planes, lines, plane_weight, line_weight, edge_planes, strides, factors):
    """grid_tv_loss's definition through autograd: total_variation of each stride's slice views, summed."""
    loss = planes[0].new_zeros(())
    for stride, factor in zip(strides, factors):
        for i, plane in enumerate(planes):
            edges = None if edge_planes is None else losses.edge_weights_from(edge_planes[i][:, :, ::stride, ::stride])
            loss = loss + factor * plane_weight * losses.total_variation(plane[:, :, ::stride, ::stride], edges)
        for line in lines:
            loss = loss + factor * line_weight * losses.total_variation(line[:, :, ::stride, :])
    return loss


@pytest.mark.parametrize("edges", [False, True])
@pytest.mark.parametrize("dtype, tolerance", [(torch.float64, 1e-12), (torch.float32, 1e-5)])
def test_strided_grid_tv_equals_autograd_through_the_views(edges, dtype, tolerance):
    """grid_tv_loss over several strides (one full-size gradient per tensor) gives total_variation's value and
    gradients of every stride's view, with and without edge weights; sizes the strides do not divide, a plane one
    entry high and a line of one entry."""
    torch.manual_seed(1)
    shapes = [(1, 5, 37, 29), (1, 3, 1, 37), (1, 2, 21, 29)]
    planes = [torch.randn(*shape, dtype=dtype, requires_grad=True) for shape in shapes]
    lines = [torch.randn(1, c, n, 1, dtype=dtype, requires_grad=True) for c, n in ((5, 21), (3, 1), (2, 37))]
    edge_planes = [torch.randn(1, 4, *shape[2:], dtype=dtype) for shape in shapes] if edges else None
    strides, factors = [1, 4, 16], [1.0, 1 / 16, 1 / 256]
    reference = _views_tv(planes, lines, 0.01, 1e-4, edge_planes, strides, factors)
    # The one-entry line has no difference: the reference leaves it out of the graph, ours gives it zeros.
    expected = [g if g is not None else torch.zeros_like(t)
                for g, t in zip(torch.autograd.grad(reference, planes + lines, allow_unused=True), planes + lines)]
    ours = losses.grid_tv_loss(planes, lines, 0.01, 1e-4, edge_planes=edge_planes, strides=strides, stride_weights=factors)
    got = torch.autograd.grad(ours, planes + lines)
    assert abs(float(ours - reference)) <= tolerance * abs(float(reference))
    for a, b in zip(got, expected):
        assert float((a - b).abs().max()) <= tolerance * float(b.abs().max())
    assert float(expected[0].abs().max()) > 0


def test_density_l1():
    value = losses.density_l1_loss([torch.tensor([[-1.0, 1.0]])], [torch.tensor([[2.0]])])
    assert torch.allclose(value, torch.tensor(3.0))


def _distortion_brute_force(weights, t, step):
    pair = (weights[:, :, None] * weights[:, None, :] * (t[:, :, None] - t[:, None, :]).abs()).sum(dim=(1, 2))
    return (pair + (weights.square() * step).sum(dim=-1) / 3).mean()


def test_distortion_loss_matches_the_quadratic_definition():
    gen = torch.Generator().manual_seed(0)
    weights = torch.rand(7, 20, generator=gen) / 10
    t = torch.arange(20, dtype=torch.float32).expand(7, 20) * 0.1 + 1.0
    fast = losses.distortion_loss(weights, t, 0.1)
    assert torch.allclose(fast, _distortion_brute_force(weights, t, 0.1), rtol=1e-5)


def test_distortion_prefers_concentrated_weights_and_has_finite_gradients():
    t = torch.linspace(0, 1, 10).expand(1, 10)
    spread = torch.full((1, 10), 0.1, requires_grad=True)
    peaked = torch.zeros(1, 10)
    peaked[0, 4] = 1.0
    assert losses.distortion_loss(peaked, t, 0.1) < losses.distortion_loss(spread, t, 0.1)
    losses.distortion_loss(spread, t, 0.1).backward()
    assert torch.isfinite(spread.grad).all()


def test_loss_weight_schedule_follows_the_learning_rate_decay():
    assert losses.loss_weight_schedule(0, 100, 0.025) == 1.0
    assert losses.loss_weight_schedule(100, 100, 0.025) == pytest.approx(0.025)
    assert losses.loss_weight_schedule(50, 100, 0.025) == pytest.approx(0.025**0.5)
    # Past the end (a resumed run trains on) the factor stays at its final value.
    assert losses.loss_weight_schedule(250, 100, 0.025) == pytest.approx(0.025)
    assert losses.loss_weight_schedule(40, 100, 1.0) == 1.0
    with pytest.raises(ValueError, match="positive"):
        losses.loss_weight_schedule(1, 100, 0.0)


def test_occlusion_loss_hand_computed_with_and_without_the_background_prior():
    densities = torch.tensor([[1.0, 2.0, 3.0, 4.0], [5.0, 6.0, 7.0, 8.0]], requires_grad=True)
    colors = torch.full((2, 4, 3), 0.5)
    colors[0, 2] = 1.0  # white sample inside the background range
    colors[1, 3] = 0.0  # black, but beyond it
    # Near samples only: the first one of each ray.
    assert float(losses.occlusion_loss(densities, None, 1, 3).detach()) == pytest.approx((1.0 + 5.0) / 8)
    # With the prior, the white third sample of ray 0 counts too; the black fourth sample of ray 1 does not.
    loss = losses.occlusion_loss(densities, colors, 1, 3)
    assert float(loss.detach()) == pytest.approx((1.0 + 3.0 + 5.0) / 8)
    loss.backward()
    assert torch.equal(densities.grad, torch.tensor([[1.0, 0, 1, 0], [1, 0, 0, 0]]) / 8)
    # Samples whose colour was never evaluated (zeros) are not mistaken for a black background.
    shaded = torch.ones(2, 4, dtype=torch.bool)
    shaded[0, 2] = False
    assert float(losses.occlusion_loss(densities, colors, 1, 3, shaded=shaded).detach()) == pytest.approx(6.0 / 8)
