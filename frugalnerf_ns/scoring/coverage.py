"""A test view's error split by how many training views saw each pixel (``geometry/visibility.py``): the
summary printed by ``scripts/diagnostics/error_by_coverage.py``. Pure torch."""

from __future__ import annotations

import math
from typing import Dict

import torch

GROUPS = ("unseen", "seen_by_1", "seen_by_2_or_more")


def psnr_of(sse: float, count: float) -> float:
    """PSNR in dB of a sum of squared errors over ``count`` colour values (nan when empty)."""
    if count <= 0:
        return float("nan")
    return -10.0 * math.log10(max(sse / count, 1e-10))


def group_masks(seen_by: torch.Tensor) -> Dict[str, torch.Tensor]:
    """Each of ``GROUPS`` as a mask over the pixels, from how many training views see each one."""
    return {"unseen": seen_by == 0, "seen_by_1": seen_by == 1, "seen_by_2_or_more": seen_by >= 2}


def summarise_coverage(seen_by: torch.Tensor, in_frustum: torch.Tensor, squared: torch.Tensor,
                       warp_squared: torch.Tensor) -> Dict[str, object]:
    """``seen_by`` and ``in_frustum`` per pixel, ``squared`` the render's and ``warp_squared`` the warped training
    colour's squared errors per pixel and channel ([pixels, 3]). Per group: share of the pixels, PSNR on them and
    share of the squared error; the PSNR with the unseen pixels' error removed (what a perfect guess of the
    unseen would give: a target above it needs the seen pixels rendered better too); the render's and the warped
    training colour's PSNR on the seen pixels."""
    pixels = seen_by.numel()
    channels = squared.shape[-1]
    total = float(squared.sum())
    masks = group_masks(seen_by)
    summary: Dict[str, object] = {"pixels": pixels, "psnr": psnr_of(total, pixels * channels),
                                  "in_any_frustum_fraction": float(in_frustum.float().mean())}
    for name in GROUPS:
        mask = masks[name]
        sse = float(squared[mask].sum())
        summary[name] = {"fraction": float(mask.float().mean()), "psnr": psnr_of(sse, int(mask.sum()) * channels),
                         "error_share": sse / total if total > 0 else float("nan")}
    seen = seen_by > 0
    summary["psnr_if_unseen_were_perfect"] = psnr_of(float(squared[seen].sum()), pixels * channels)
    summary["seen_psnr"] = psnr_of(float(squared[seen].sum()), int(seen.sum()) * channels)
    summary["seen_psnr_of_warped_training_colour"] = psnr_of(float(warp_squared[seen].sum()), int(seen.sum()) * channels)
    return summary
