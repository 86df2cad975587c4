"""A learned background for rays that leave the scene box: a colour per viewing direction (pure torch).

A capture that converges on an object in a room (a phone circling a table) has its object in a bounded box
and the room far beyond it. A fixed white or black background would make the grid paint the room onto the
box's faces; a colour per direction, as seen from infinitely far away, holds the room instead. The map is
coarse on purpose (a texel spans ~6 degrees at the default 32 x 64): it can hold the far walls' broad
colours but not the object's detail, so the training views cannot be explained by the background alone.

Seen from infinitely far away, the room has no parallax: cameras a few metres apart see the same colour in
the same direction, which a room a few metres beyond the box does not do. With a ``radius``
(``scene_analysis.far_shell``: the triangulated points beyond the box say how far the room is) the map is
painted on a sphere of that radius around the box's centre instead, read where the ray leaves the sphere, and that distance is the depth of what
the ray sees beyond the box (``shell_distance``).
"""

from __future__ import annotations

import math
from typing import Optional, Tuple

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


def shell_distance(
    origins: Float[Tensor, "rays 3"], directions: Float[Tensor, "rays 3"], centre: Float[Tensor, "3"], radius: float
) -> Float[Tensor, " rays"]:
    """Distance along each ray (unit ``directions``) to where it leaves the sphere of ``radius`` around
    ``centre``: the far root of |o + t d - c|^2 = r^2. An origin outside the sphere whose ray misses it gets
    the distance of its closest approach (never negative)."""
    offset = origins - centre
    b = (offset * directions).sum(dim=-1)
    c = (offset * offset).sum(dim=-1) - radius * radius
    return (-b + torch.sqrt((b * b - c).clamp_min(0.0))).clamp_min(0.0)


class FarBackground(nn.Module):
    """Colour per viewing direction: a latitude-longitude texture of logits, bilinearly read, sigmoid; on a
    sphere around ``centre`` when a ``radius`` is given (read in the direction from the centre to where the
    ray leaves it), else infinitely far away (read in the ray's direction)."""

    def __init__(
        self, resolution: Tuple[int, int] = (32, 64), centre: Optional[Tensor] = None, radius: float = 0.0
    ) -> None:
        super().__init__()
        rows, cols = resolution
        if rows < 1 or cols < 1:
            raise ValueError(f"far background resolution must be positive, got {resolution}")
        # Logits 0: mid grey everywhere until the training views say otherwise.
        self.texture = nn.Parameter(torch.zeros(1, 3, rows, cols))
        # Buffers, so a checkpoint restores the sphere (eval tools build the model without the points).
        self.register_buffer("centre", torch.zeros(3) if centre is None else centre.detach().float().reshape(3).clone())
        self.register_buffer("radius", torch.tensor(float(radius)))

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # Checkpoints from before the shell hold only the texture: their background is infinitely far away.
        state_dict.setdefault(prefix + "centre", torch.zeros(3))
        state_dict.setdefault(prefix + "radius", torch.tensor(0.0))
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    @property
    def has_shell(self) -> bool:
        return float(self.radius) > 0.0

    def distance(self, origins: Float[Tensor, "rays 3"], directions: Float[Tensor, "rays 3"]) -> Optional[Tensor]:
        """Where each ray meets the background (None: infinitely far, no shell)."""
        if not self.has_shell:
            return None
        return shell_distance(origins, directions, self.centre.to(origins), float(self.radius))

    def forward(
        self, origins: Float[Tensor, "rays 3"], directions: Float[Tensor, "rays 3"], distance: Optional[Tensor] = None
    ) -> Float[Tensor, "rays 3"]:
        """Colour of each ray's background; ``distance`` is ``self.distance`` of these rays when the caller has
        it already (a training step needs it for L_sd too)."""
        if directions.shape[0] == 0:
            return directions.new_zeros(0, 3)
        if self.has_shell:
            distance = self.distance(origins, directions) if distance is None else distance
            directions = origins + directions * distance[:, None] - self.centre.to(origins)
        grid = direction_to_latlong(directions.to(self.texture.dtype))[None, None]  # [1, 1, rays, 2]
        logits = torch.nn.functional.grid_sample(
            self.texture, grid, mode="bilinear", padding_mode="border", align_corners=False
        )
        return torch.sigmoid(logits[0, :, 0].t())
