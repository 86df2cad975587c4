"""A fixed, deterministic image pair for the LPIPS reference check (no files, no RNG state shared)."""

import torch


def fixed_image_pair() -> tuple[torch.Tensor, torch.Tensor]:
    """Two 2x3x64x64 images in [0, 1]: smooth patterns and a perturbed copy."""
    y, x = torch.meshgrid(torch.linspace(0, 1, 64), torch.linspace(0, 1, 64), indexing="ij")
    base = torch.stack([x, y, 0.5 + 0.5 * torch.sin(8 * x * y)])
    checker = ((torch.floor(x * 8) + torch.floor(y * 8)) % 2).expand(3, 64, 64)
    first = torch.stack([base, 0.3 + 0.4 * checker])
    gen = torch.Generator().manual_seed(0)
    noise = 0.1 * torch.randn(first.shape, generator=gen)
    second = (first.flip(-1) * 0.7 + 0.3 * first + noise).clamp(0, 1)
    return first, second
