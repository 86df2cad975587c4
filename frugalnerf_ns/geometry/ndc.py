"""Normalised device coordinates for forward-facing scenes (NeRF / TensoRF), as pure torch functions.

The world frame must look down -z from the cameras (LLFF poses after recentring). A ray is first moved
to the near plane z = -near, then mapped so that z in [near, inf) becomes NDC z in [-1, 1). nerfstudio has
no NDC; the model applies ``rays_to_ndc`` to each ray bundle and reports metric depth through
``metric_distance_from_ndc`` (geometric adaptation warps with metric depth: reference-code bug 2).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from jaxtyping import Float
from torch import Tensor

# Rays almost parallel to the image plane never reach it; this floor on -d_z keeps their NDC finite.
MIN_FORWARD = 1e-6


class NDCRays(NamedTuple):
    origins: Float[Tensor, "*bs 3"]
    """NDC origins (on the NDC near plane z = -1)."""
    directions: Float[Tensor, "*bs 3"]
    """Unit NDC directions."""
    ndc_length: Float[Tensor, "*bs"]
    """Length of the raw NDC direction: NDC parameter t' = (distance along the unit direction) / this."""
    shift: Float[Tensor, "*bs"]
    """Metric distance from the world origin of the ray to the near plane."""
    forward: Float[Tensor, "*bs"]
    """-d_z of the unit world direction (> 0 for rays going into the scene)."""


def rays_to_ndc(
    origins: Float[Tensor, "*bs 3"],
    directions: Float[Tensor, "*bs 3"],
    focal: float,
    width: float,
    height: float,
    near: float = 1.0,
) -> NDCRays:
    """NeRF's ndc_rays (Mildenhall et al. 2020, App. C) with unit-length NDC directions."""
    forward = (-directions[..., 2]).clamp_min(MIN_FORWARD)
    d_z = -forward
    # Use the floored z everywhere, so the shifted origin lands exactly on the near plane (o_z = -near).
    directions = torch.cat([directions[..., :2], d_z[..., None]], dim=-1)
    shift = -(near + origins[..., 2]) / d_z
    o = origins + shift[..., None] * directions
    ax, ay = -2.0 * focal / width, -2.0 * focal / height
    o_z = o[..., 2]
    ndc_o = torch.stack([ax * o[..., 0] / o_z, ay * o[..., 1] / o_z, 1.0 + 2.0 * near / o_z], dim=-1)
    ndc_d = torch.stack(
        [
            ax * (directions[..., 0] / d_z - o[..., 0] / o_z),
            ay * (directions[..., 1] / d_z - o[..., 1] / o_z),
            -2.0 * near / o_z,
        ],
        dim=-1,
    )
    length = ndc_d.norm(dim=-1)
    return NDCRays(ndc_o, ndc_d / length[..., None], length, shift, forward)


def metric_distance_from_ndc(
    ndc_distance: Float[Tensor, "*bs"], rays: NDCRays, near: float = 1.0, max_ndc_t: float = 0.999
) -> Float[Tensor, "*bs"]:
    """Distance along the world ray (from its own origin) of the point at ``ndc_distance`` on the NDC ray.

    With t' the NDC parameter, the shifted ray reaches metric depth near / (1 - t'), i.e. distance
    near * t' / ((1 - t') * forward) past the near plane. t' -> 1 is infinitely far, so t' is capped.
    """
    t_ndc = (ndc_distance / rays.ndc_length).clamp(0.0, max_ndc_t)
    return rays.shift + near * t_ndc / ((1.0 - t_ndc) * rays.forward)


def point_to_ndc(points: Float[Tensor, "*bs 3"], focal: float, width: float, height: float, near: float = 1.0):
    """NDC position of a world point (z < 0): the projective map the rays follow."""
    z = points[..., 2]
    return torch.stack(
        [-2.0 * focal / width * points[..., 0] / z, -2.0 * focal / height * points[..., 1] / z, 1.0 + 2.0 * near / z],
        dim=-1,
    )
