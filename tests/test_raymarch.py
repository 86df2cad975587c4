import math

import pytest
import torch

from frugalnerf_ns.geometry.raymarch import composite_rgb, composite_weights, intersect_aabb, march_steps

AABB = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])


def test_intersect_aabb_hits_misses_and_near_plane():
    origins = torch.tensor([[0.0, 0.0, -3.0], [0.0, 5.0, -3.0], [0.0, 0.0, 0.0]])
    directions = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0]])
    seg = intersect_aabb(origins, directions, AABB, near_plane=0.1)
    assert seg.hit.tolist() == [True, False, True]
    assert torch.allclose(seg.t_near[0], torch.tensor(2.0)) and torch.allclose(seg.t_far[0], torch.tensor(4.0))
    # A miss is an empty segment, never inverted.
    assert seg.t_far[1] == seg.t_near[1]
    # Starting inside the box: the near plane, not a negative distance.
    assert torch.allclose(seg.t_near[2], torch.tensor(0.1)) and torch.allclose(seg.t_far[2], torch.tensor(1.0))
    assert torch.isfinite(seg.t_near).all() and torch.isfinite(seg.t_far).all()


def test_march_steps_spacing_and_validity():
    seg = intersect_aabb(torch.tensor([[0.0, 0.0, -3.0]]), torch.tensor([[0.0, 0.0, 1.0]]), AABB)
    t, valid = march_steps(seg, step=0.5, num_samples=6, jitter=False)
    assert torch.allclose(t[0], torch.tensor([2.25, 2.75, 3.25, 3.75, 4.25, 4.75]))
    assert valid[0].tolist() == [True, True, True, True, False, False]
    t_jit, _ = march_steps(seg, step=0.5, num_samples=6, jitter=True)
    assert torch.allclose(t_jit[0, 1:] - t_jit[0, :-1], torch.full((5,), 0.5))
    assert 2.0 <= float(t_jit[0, 0]) < 2.5


def test_composite_matches_closed_form_for_constant_density():
    sigma, step, scale, n = 0.3, 0.1, 25.0, 8
    densities = torch.full((1, n), sigma)
    t = torch.arange(n, dtype=torch.float32)[None] * step + step / 2
    comp = composite_weights(densities, t, step, scale)
    alpha = 1 - math.exp(-sigma * step * scale)
    expected = torch.tensor([alpha * (1 - alpha) ** i for i in range(n)])
    assert torch.allclose(comp.weights[0], expected, atol=1e-6)
    assert torch.allclose(comp.accumulation[0, 0], torch.tensor(1 - (1 - alpha) ** n), atol=1e-6)


def test_empty_ray_depth_falls_back_inside_segment_and_rgb_is_background():
    densities = torch.zeros(2, 5)
    t = torch.linspace(1, 2, 5).expand(2, 5)
    comp = composite_weights(densities, t, 0.25, 25.0, torch.tensor([1.0, 1.0]), torch.tensor([2.0, 2.0]))
    assert torch.equal(comp.accumulation, torch.zeros(2, 1))
    assert torch.isfinite(comp.depth).all() and (comp.depth >= 1.0).all() and (comp.depth <= 2.0).all()
    rgb = composite_rgb(comp.weights, torch.rand(2, 5, 3), torch.tensor([1.0, 0.5, 0.0]))
    assert torch.allclose(rgb, torch.tensor([[1.0, 0.5, 0.0]] * 2))


def test_opaque_sample_takes_all_weight_and_sets_depth():
    densities = torch.tensor([[0.0, 0.0, 1e6, 1e6, 0.0]], requires_grad=True)
    t = torch.tensor([[1.0, 2.0, 3.0, 4.0, 5.0]])
    comp = composite_weights(densities, t, 0.1, 25.0)
    assert torch.allclose(comp.weights[0], torch.tensor([0.0, 0.0, 1.0, 0.0, 0.0]), atol=1e-6)
    assert torch.allclose(comp.depth, torch.tensor([[3.0]]), atol=1e-4)
    comp.depth.sum().backward()
    assert torch.isfinite(densities.grad).all()


def test_transmittance_weights_continue_block_by_block_as_in_one_pass():
    from frugalnerf_ns.geometry.raymarch import transmittance_weights

    torch.manual_seed(3)
    optical = torch.rand(5, 40, dtype=torch.float64) * torch.tensor([0.0, 0.01, 0.1, 1.0, 10.0], dtype=torch.float64)[:, None]
    whole, total = transmittance_weights(optical)
    first, carried = transmittance_weights(optical[:, :17])
    second, total_blocks = transmittance_weights(optical[:, 17:], carried)
    assert torch.allclose(torch.cat([first, second], dim=1), whole, rtol=1e-12, atol=1e-15)
    assert torch.allclose(total_blocks, total, rtol=1e-12) and torch.allclose(total, optical.sum(dim=1), rtol=1e-12)
    # The weights telescope: they add up to 1 - exp(-total optical depth), never above 1.
    assert torch.allclose(whole.sum(dim=1), 1.0 - torch.exp(-total), rtol=1e-12, atol=1e-15)
    assert whole[0].abs().max() == 0.0 and whole[4, 0] == pytest.approx(1.0 - math.exp(-float(optical[4, 0])))
