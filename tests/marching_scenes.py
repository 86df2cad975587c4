"""Fields and rays the marcher tests share: a dense slab over a thin haze (rays turn opaque half-way), with or
without an alpha mask, and rays from in front of the box, some pointing away from it."""

import torch

from frugalnerf_ns.field.radiance_field import FrugalNeRFField

AABB = torch.tensor([[-1.0, -1.2, -0.8], [1.0, 1.2, 0.8]])
SETTINGS = dict(step_ratio=0.5, distance_scale=25.0, max_samples_per_ray=1024, weight_threshold=1e-4)


def opaque_field(seed: int = 0, mask: bool = False) -> FrugalNeRFField:
    """A field with a dense slab (rays become opaque half-way) over a thin random haze."""
    torch.manual_seed(seed)
    field = FrugalNeRFField(AABB, (24, 28, 20), density_components=(4, 2, 2), appearance_components=(6, 2, 2),
                            mlp_hidden_dim=16, mlp_implementation="torch")
    with torch.no_grad():
        for plane in field.density_grid.planes:
            plane.uniform_(0.0, 0.3)
        for line in field.density_grid.lines:
            line.uniform_(0.0, 0.3)
            line[:, :, line.shape[2] // 2 : line.shape[2] // 2 + 3, :] += 6.0  # a slab across each axis' middle
        if mask:
            # Zero density in one corner so the alpha mask leaves it out, then build the mask.
            for plane in field.density_grid.planes:
                plane[:, :, :5, :5] = 0.0
            field.update_alpha_mask(SETTINGS["step_ratio"], SETTINGS["distance_scale"])
    return field


def rays(count: int = 300, seed: int = 1):
    generator = torch.Generator().manual_seed(seed)
    origins = torch.rand(count, 3, generator=generator) * 0.6 - 0.3 + torch.tensor([0.0, 0.0, 2.5])
    directions = torch.randn(count, 3, generator=generator) * 0.35 + torch.tensor([0.0, 0.0, -1.0])
    directions = directions / directions.norm(dim=-1, keepdim=True)
    directions[:20] = torch.tensor([0.0, 0.0, 1.0])  # pointing away: they miss the box
    return origins, directions
