"""A learned background for rays that leave the scene box: a colour per viewing direction (pure torch).

A capture that converges on an object in a room (a phone circling a table) has its object in a bounded box
and the room far beyond it. A fixed white or black background would make the grid paint the room onto the
box's faces; a colour per direction, as seen from infinitely far away, holds the room instead. The map is
coarse on purpose (a texel spans ~6 degrees at the default 32 x 64): it can hold the far walls' broad
colours but not the object's detail, so the training views cannot be explained by the background alone.
"""

from __future__ import annotations

import math
from typing import Tuple

import torch
from jaxtyping import Float
from torch import Tensor, nn


def direction_to_latlong(directions: Float[Tensor, "rays 3"]) -> Float[Tensor, "rays 2"]:
    """Unit directions to (longitude, latitude) in [-1, 1] (``grid_sample``'s x, y): latitude from the +y axis
    (OpenGL up), longitude around it measured from -z (the cameras' mean viewing direction after recentring),
    so the map's seam lies behind the cameras."""
    unit = torch.nn.functional.normalize(directions, dim=-1)
    x, y, z = unit.unbind(-1)
    longitude = torch.atan2(x, -z) / math.pi
    latitude = -torch.asin(y.clamp(-1.0, 1.0)) / (math.pi / 2)  # row 0 (y = -1 in grid_sample) is straight up
    return torch.stack([longitude, latitude], dim=-1)


class FarBackground(nn.Module):
    """Colour per viewing direction: a latitude-longitude texture of logits, bilinearly read, sigmoid."""

    def __init__(self, resolution: Tuple[int, int] = (32, 64)) -> None:
        super().__init__()
        rows, cols = resolution
        if rows < 1 or cols < 1:
            raise ValueError(f"far background resolution must be positive, got {resolution}")
        # Logits 0: mid grey everywhere until the training views say otherwise.
        self.texture = nn.Parameter(torch.zeros(1, 3, rows, cols))

    def forward(self, directions: Float[Tensor, "rays 3"]) -> Float[Tensor, "rays 3"]:
        if directions.shape[0] == 0:
            return directions.new_zeros(0, 3)
        grid = direction_to_latlong(directions.to(self.texture.dtype))[None, None]  # [1, 1, rays, 2]
        logits = torch.nn.functional.grid_sample(
            self.texture, grid, mode="bilinear", padding_mode="border", align_corners=False
        )
        return torch.sigmoid(logits[0, :, 0].t())
