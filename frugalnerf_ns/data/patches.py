"""The k x k pixel patches every training step samples its rays in: training views' patches for the
geometric adaptation's reprojection error (paper Sec. 3.4), 2x2 patches on novel poses for depth smoothness."""

from __future__ import annotations

import torch
from jaxtyping import Int
from torch import Tensor

NOVEL_PATCH = 2  # novel-view rays come in 2x2 patches for the depth smoothness loss


def sample_patches(
    generator: torch.Generator, num_patches: int, num_views: int, height: int, width: int, k: int
) -> Int[Tensor, "rays 3"]:
    """(view, row, col) of ``num_patches`` random k x k patches, patch-major, row-major inside a patch.

    Not nerfstudio's PatchPixelSampler: that one samples from an image batch its dataloader collated and
    draws from the global RNG; training samples every view every step from images held on the device, with
    the datamanager's seeded generator, for the novel poses too (which have no images)."""
    view = torch.randint(num_views, (num_patches,), generator=generator)
    top = torch.randint(height - k + 1, (num_patches,), generator=generator)
    left = torch.randint(width - k + 1, (num_patches,), generator=generator)
    dy, dx = torch.meshgrid(torch.arange(k), torch.arange(k), indexing="ij")
    rows = top[:, None] + dy.flatten()[None]
    cols = left[:, None] + dx.flatten()[None]
    return torch.stack([view[:, None].expand_as(rows), rows, cols], dim=-1).reshape(-1, 3)
