"""Image metrics of test renders: PSNR capped for logs, and the DTU protocol's masked metrics."""

from __future__ import annotations

from typing import Callable, Dict, Optional

import torch
from torch import Tensor

# A perfect fit has infinite PSNR; logs, JSON and averages over views need a number, so PSNR stops at
# 100 dB (MSE 1e-10, far below 8-bit quantisation: 1/255^2 / 12 ~ 1.3e-6 is 59 dB).
PSNR_CAP_DB = 100.0


def capped_psnr(rgb: Tensor, image: Tensor) -> Tensor:
    """PSNR in dB of colours in [0, 1], at most ``PSNR_CAP_DB`` (a 0-d tensor, for nerfstudio's writers)."""
    mse = torch.mean((rgb.float() - image.float()) ** 2)
    return -10.0 * torch.log10(mse.clamp_min(10.0 ** (-PSNR_CAP_DB / 10.0)))


def masked_psnr(rgb: Tensor, image: Tensor, mask: Tensor) -> float:
    """PSNR over the pixels where ``mask`` is set (an empty mask counts as one pixel, never a division by 0),
    capped at ``PSNR_CAP_DB`` like ``capped_psnr``."""
    mask = mask.to(rgb.dtype)
    mse = (((rgb - image) ** 2) * mask).sum() / (mask.sum().clamp_min(1.0) * rgb.shape[-1])
    return float(-10.0 * torch.log10(mse.clamp_min(10.0 ** (-PSNR_CAP_DB / 10.0))))


def composite(rgb: Tensor, alpha: Tensor, background: Tensor | float = 1.0) -> Tensor:
    """``rgb`` over ``background`` with coverage ``alpha`` (the one alpha composite: RGBA training targets,
    the warps' white-composited images and the DTU evaluation's masked images all use it)."""
    alpha = alpha.to(rgb.dtype)
    return rgb * alpha + background * (1.0 - alpha)


def white_background(rgb: Tensor, mask: Tensor) -> Tensor:
    """``rgb * mask + (1 - mask)``: the image with everything outside the object mask set to white (RegNeRF's
    DTU evaluation does this to prediction and ground truth before SSIM and LPIPS)."""
    return composite(rgb, mask)


def masked_image_metrics(
    rgb: Tensor, image: Tensor, mask: Tensor, ssim: Callable, lpips: Callable[[Tensor, Tensor], Optional[Tensor]]
) -> Dict[str, float]:
    """DTU protocol as published (RegNeRF's ``eval.py``, reused by FreeNeRF and SparseNeRF): PSNR over the
    object's pixels only; SSIM and LPIPS on the full images after BOTH have their background set to white
    (``white_background``). ``lpips`` may return None (unavailable): the metric is left out."""
    to_nchw = lambda x: torch.moveaxis(x, -1, 0)[None]  # noqa: E731
    masked_rgb, masked_image = to_nchw(white_background(rgb, mask)), to_nchw(white_background(image, mask))
    metrics = {"psnr": masked_psnr(rgb, image, mask), "ssim": float(ssim(masked_image, masked_rgb))}
    distance = lpips(masked_image, masked_rgb)
    if distance is not None:
        metrics["lpips"] = float(distance)
    return metrics
