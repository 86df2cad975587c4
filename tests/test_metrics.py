"""The DTU protocol as published (RegNeRF eval.py): PSNR on the object's pixels, SSIM and LPIPS on full images
whose background is set to white in both, checked against values computed by hand."""

import math

import pytest
import torch
from torchmetrics.functional import structural_similarity_index_measure as ssim

from frugalnerf_ns.scoring.metrics import masked_image_metrics, masked_psnr, white_background


def fixture():
    """4x4 images; the object is the 2x2 block at rows 1-2, columns 1-2."""
    mask = torch.zeros(4, 4, 1, dtype=torch.bool)
    mask[1:3, 1:3] = True
    image = torch.full((4, 4, 3), 0.2)
    image[1:3, 1:3] = 0.6
    rgb = torch.full((4, 4, 3), 0.9)  # background wrong everywhere: must not count
    rgb[1:3, 1:3] = 0.5  # object off by 0.1 in every channel
    return rgb, image, mask


def test_white_background_by_hand():
    rgb, image, mask = fixture()
    white = white_background(image, mask)
    assert white[0, 0].tolist() == [1.0, 1.0, 1.0] and white[3, 3].tolist() == [1.0, 1.0, 1.0]
    assert torch.allclose(white[1, 1], torch.tensor([0.6, 0.6, 0.6]))
    # A soft mask blends: 0.25 * 0.2 + 0.75 * 1 = 0.8.
    assert torch.allclose(white_background(torch.full((1, 1, 3), 0.2), torch.full((1, 1, 1), 0.25)), torch.tensor(0.8))


def test_masked_metrics_by_hand():
    rgb, image, mask = fixture()
    # Mean of the whole composited image: 12 white pixels and 4 object pixels, one "image" per call.
    image_mean = lambda a, b: a.mean()  # noqa: E731  (a is the ground truth in our calls)
    metrics = masked_image_metrics(rgb, image, mask, ssim=image_mean, lpips=lambda a, b: b.mean())
    assert metrics["psnr"] == pytest.approx(-10 * math.log10(0.01), abs=1e-4)  # 20 dB: error 0.1 on the object
    assert metrics["ssim"] == pytest.approx((12 * 1.0 + 4 * 0.6) / 16, abs=1e-6)  # ground truth on white
    assert metrics["lpips"] == pytest.approx((12 * 1.0 + 4 * 0.5) / 16, abs=1e-6)  # prediction on white
    assert masked_psnr(rgb, image, mask) == pytest.approx(20.0, abs=1e-4)


def test_ssim_is_that_of_the_white_composites_and_differs_from_black():
    torch.manual_seed(0)
    image = torch.rand(32, 32, 3)
    rgb = (image + 0.2 * torch.randn(32, 32, 3)).clamp(0, 1)
    mask = torch.zeros(32, 32, 1, dtype=torch.bool)
    mask[8:24, 6:26] = True
    nchw = lambda x: torch.moveaxis(x, -1, 0)[None]  # noqa: E731
    metrics = masked_image_metrics(rgb, image, mask, ssim=ssim, lpips=lambda a, b: None)
    on_white = float(ssim(nchw(image * mask + ~mask), nchw(rgb * mask + ~mask)))
    on_black = float(ssim(nchw(image * mask), nchw(rgb * mask)))
    assert metrics["ssim"] == pytest.approx(on_white, abs=1e-6)
    assert abs(on_white - on_black) > 1e-3  # the choice of background changes the number
    assert "lpips" not in metrics  # LPIPS unavailable: left out, not zero


def test_composite_is_the_over_operator_bit_for_bit():
    from frugalnerf_ns.scoring.metrics import composite

    generator = torch.Generator().manual_seed(0)
    rgb, alpha = torch.rand(64, 3, generator=generator), torch.rand(64, 1, generator=generator)
    background = torch.rand(3, generator=generator)
    # The inline formulas it replaced (training target, warp images, masked evaluation), exactly.
    assert torch.equal(composite(rgb, alpha, background), rgb * alpha + background * (1.0 - alpha))
    assert torch.equal(composite(rgb, alpha), rgb * alpha + (1.0 - alpha))
    # Fully covered keeps the colour, uncovered shows the background; a bool mask counts as 0 / 1.
    assert torch.equal(composite(rgb, torch.ones(64, 1), background), rgb)
    assert torch.equal(composite(rgb, torch.zeros(64, 1), background), background.expand(64, 3))
    mask = alpha > 0.5
    assert torch.equal(composite(rgb, mask), torch.where(mask, rgb, torch.ones_like(rgb)))
