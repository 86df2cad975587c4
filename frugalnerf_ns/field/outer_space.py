"""The room around a captured object as geometry: a coarse VM grid over the contracted space beyond the scene box.

A phone walking around a thing on a table sees the table, the walls and the doors behind it from a few places.
A colour per viewing direction (``far_background.py``) has no parallax, so training used to push that room into
the object's box as streaks. Here the space beyond the box is contracted into the cube shell 1 <= |y|_inf <= 2
(``geometry/contraction.py``) and held by a density and an appearance VM grid over [-2, 2]^3: the shell right
outside the box at the grid's resolution, the far room at falling resolution. A ray is sampled from where it
leaves the box to ``FAR_BOX_HALVES`` box halves away, linearly in disparity (equal steps in the contracted
space), composited there, and what it lets through falls on the direction map (the last layer: sky, infinity).

The result is each ray's background colour and the depth of what it sees beyond the box: the object's field
composites in front of it as it did in front of the map. One scale: the lower scales of the object's field
share it (their background), as they shared the map.
"""

from __future__ import annotations

from typing import NamedTuple, Optional, Tuple

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

from frugalnerf_ns.field.tensorial import TensorVMGrid, trilinear_rows
from frugalnerf_ns.geometry.contraction import contract, disparity_bins, interval_distortion
from frugalnerf_ns.geometry.raymarch import MAX_OPTICAL_DEPTH, intersect_aabb, transmittance_weights

FAR_BOX_HALVES = 1000.0
"""Where the samples beyond the box end, in box halves from its centre (contracted norm 1.999): beyond it only the
direction map."""

OUTER_DISTANCE_SCALE = 25.0
"""Optical depth per unit of contracted length per unit of density (TensoRF's distance scale, in box halves)."""


class OuterRender(NamedTuple):
    rgb: Float[Tensor, "rays 3"]
    """sum_i w_i c_i over the samples beyond the box (no direction map yet)."""
    accumulation: Float[Tensor, " rays"]
    depth: Float[Tensor, " rays"]
    """1 / (sum_i w_i / t_i + (1 - acc) / t_end): metric distance of what the ray sees beyond the box (the expected
    disparity's inverse)."""
    distortion: Float[Tensor, " rays"]
    """``interval_distortion`` of the segment's weights (a training loss against floaters)."""


class OuterSpace(nn.Module):
    """Density and colour beyond ``box``: VM grids over the contracted cube [-2, 2]^3 (the box is its middle
    half, never sampled here: the object's field holds it).

    Args:
        box: the scene box, (2, 3): its centre and half sizes define the contraction.
        resolution: grid nodes per axis over [-2, 2] (a quarter of them span the box, unused).
        density_components, appearance_components: components per plane.
        num_samples: samples per ray behind the box (beyond its exit).
        num_front_samples: samples per ray between a camera outside the box and the box.
    """

    def __init__(
        self,
        box: Float[Tensor, "2 3"],
        resolution: int = 128,
        density_components: int = 8,
        appearance_components: int = 8,
        num_samples: int = 32,
        num_front_samples: int = 16,
    ) -> None:
        super().__init__()
        box = box.detach().float()
        self.register_buffer("box", box.clone())
        self.register_buffer("centre", box.mean(dim=0))
        self.register_buffer("half_size", (box[1] - box[0]) / 2.0)
        # False for a run trained before the outer space existed (its checkpoint has none): it renders as trained.
        self.register_buffer("active", torch.tensor(True))
        self.num_samples = int(num_samples)
        self.num_front_samples = int(num_front_samples)
        self.density_grid = TensorVMGrid((resolution,) * 3, (density_components,) * 3)
        self.appearance_grid = TensorVMGrid((resolution,) * 3, (appearance_components,) * 3)
        self.color_basis = nn.Linear(self.appearance_grid.num_components, 3)
        self._baked: Tuple[tuple, Optional[Tensor]] = ((), None)

    @property
    def is_active(self) -> bool:
        return bool(self.active)

    def segments(self, origins: Float[Tensor, "rays 3"], directions: Float[Tensor, "rays 3"], near: float) -> Tuple[Tensor, Tensor, Tensor]:
        """Per ray, where the outside in front of the box ends (``t_in``: the box's entry, ``near`` for a camera
        inside it), where the outside behind it starts (``t_out``: the box's exit), and ``near``'s floor. A ray that
        misses the box has t_in = t_out at its closest approach to the box's centre: its outside is marched in
        front of that point and behind it."""
        segments = intersect_aabb(origins, directions, self.box, near)
        closest = ((self.centre - origins) * directions).sum(dim=-1).clamp_min(near)
        t_in = torch.where(segments.hit, segments.t_near, closest)
        t_out = torch.where(segments.hit, segments.t_far, closest)
        floor = max(near, 1e-3 * float(self.half_size.min()))
        return t_in, t_out.clamp_min(floor), torch.full_like(t_in, near)

    def _grid_coords(self, points: Float[Tensor, "n 3"]) -> Float[Tensor, "n 3"]:
        return contract(points, self.centre, self.half_size) / 2.0  # [-2, 2] to the grid's [-1, 1]

    def density_and_color(self, points: Float[Tensor, "n 3"]) -> Tuple[Float[Tensor, " n"], Float[Tensor, "n 3"]]:
        """ReLU density and sigmoid colour at world points (the planes read; gradients flow)."""
        coords = self._grid_coords(points)
        raw = sum(p.sum(dim=-1) for p in self.density_grid.plane_line_products(coords))
        features = torch.cat(self.appearance_grid.plane_line_products(coords), dim=-1)
        return F.relu(raw), torch.sigmoid(self.color_basis(features))

    @torch.no_grad()
    def _baked_nodes(self) -> Tensor:
        """Density and colour logits on the grid's nodes, [nodes, 4] channels last (for rendering outside
        training: one trilinear read of 4 channels instead of 6 plane and line reads per grid)."""
        tensors = [*self.density_grid.planes, *self.density_grid.lines, *self.appearance_grid.planes,
                   *self.appearance_grid.lines, self.color_basis.weight, self.color_basis.bias]
        key = tuple((t.data_ptr(), t._version) for t in tensors)
        if self._baked[0] != key or self._baked[1] is None:
            density = self.density_grid.node_sum()[..., None]
            logits = self.appearance_grid.node_features(self.color_basis.weight) + self.color_basis.bias
            self._baked = (key, torch.cat([density, logits], dim=-1).reshape(-1, 4).contiguous())
        return self._baked[1]  # type: ignore[return-value]

    def _read_baked(self, points: Float[Tensor, "n 3"]) -> Tuple[Float[Tensor, " n"], Float[Tensor, "n 3"]]:
        dims = self.density_grid.resolution_tuple[::-1]  # node tables are [z, y, x]: X, Y, Z nodes
        size = torch.tensor(dims, device=points.device, dtype=points.dtype)
        values = trilinear_rows(self._baked_nodes(), dims, (self._grid_coords(points) + 1.0) * 0.5 * (size - 1))
        return F.relu(values[:, 0]), torch.sigmoid(values[:, 1:])

    def _composite(
        self, origins: Tensor, directions: Tensor, edges: Tensor, t: Tensor, kernels=None
    ) -> Tuple[Optional[Tensor], Tensor, Tensor, Tensor]:
        """Weights, accumulation, colour sum and disparity sum of samples ``t`` in bins ``edges`` along each ray;
        each sample's share of the ray is its bin's length in the contracted space. ``kernels`` (outside training;
        the model hands them over on the CPU only): one fused kernel (``field.fused_kernels.outer_composite``), no per-sample weights."""
        rays = origins.shape[0]
        if kernels is not None and not torch.is_grad_enabled():
            from frugalnerf_ns.field.fused_kernels import outer_composite

            dims = self.density_grid.resolution_tuple[::-1]
            sums = outer_composite(kernels, self._baked_nodes(), dims, self.centre, self.half_size, origins, directions,
                                   edges, t, OUTER_DISTANCE_SCALE, MAX_OPTICAL_DEPTH).to(origins.dtype)
            return None, sums[:, 0], sums[:, 1:4], sums[:, 4]
        edge_points = contract(origins[:, None, :] + directions[:, None, :] * edges[..., None], self.centre, self.half_size)
        deltas = (edge_points[:, 1:] - edge_points[:, :-1]).norm(dim=-1)
        points = (origins[:, None, :] + directions[:, None, :] * t[..., None]).reshape(-1, 3)
        if torch.is_grad_enabled():
            density, color = self.density_and_color(points)
        else:
            density, color = self._read_baked(points)
        density, color = density.view(rays, -1), color.view(rays, -1, 3)
        optical = (density * deltas * OUTER_DISTANCE_SCALE).clamp(0.0, MAX_OPTICAL_DEPTH)
        weights, _ = transmittance_weights(optical)
        accumulation = weights.sum(dim=-1)
        return weights, accumulation, (weights[..., None] * color).sum(dim=-2), (weights / t).sum(dim=-1)

    @staticmethod
    def _distortion(weights: Optional[Tensor], rays: Tensor) -> Tensor:
        if weights is None or not torch.is_grad_enabled():
            return rays.new_zeros(rays.shape[0])
        return interval_distortion(weights)

    def render(
        self, origins: Float[Tensor, "rays 3"], directions: Float[Tensor, "rays 3"], jitter: bool, near: float = 0.0,
        kernels=None,
    ) -> Tuple[OuterRender, OuterRender]:
        """Composite the outside in front of the box (cameras outside it; ``num_front_samples`` evenly in t) and
        behind it (``num_samples``, linear in disparity to ``FAR_BOX_HALVES`` box halves) along each ray (unit
        ``directions``): (front, behind). The front's depth is its disparity sum's inverse (infinite where it is
        empty); the behind's counts what it lets through at its far end."""
        t_in, t_out, t_near = self.segments(origins, directions, near)
        far = torch.maximum(torch.full_like(t_out, FAR_BOX_HALVES * float(self.half_size.max())), 2.0 * t_out)
        edges, t = disparity_bins(t_out, far, self.num_samples, jitter)
        weights, acc, rgb, disparity = self._composite(origins, directions, edges, t, kernels)
        # Expected disparity, not distance: the share a ray lets through to the map sits at 1000 box halves, where
        # a distance average would let 5 % of it move the depth by 50 box halves.
        behind = OuterRender(rgb, acc, 1.0 / (disparity + (1.0 - acc) / far), self._distortion(weights, origins))
        # No space in front of the box (the option, or every camera inside it, as with the default box): its
        # samples would all weigh 0, so the grid reads of the training hot path are skipped.
        if self.num_front_samples <= 0 or not bool((t_in > t_near).any()):
            zero = t_in.new_zeros(t_in.shape[0])
            return OuterRender(origins.new_zeros(origins.shape[0], 3), zero, torch.full_like(zero, 1e12), zero), behind
        u = torch.linspace(0.0, 1.0, self.num_front_samples + 1, device=t_in.device, dtype=t_in.dtype)
        front_edges = t_near[:, None] + (t_in - t_near)[:, None] * u[None, :]
        offset = torch.rand_like(front_edges[:, 1:]) if jitter else torch.full_like(front_edges[:, 1:], 0.5)
        front_t = (front_edges[:, :-1] + offset * (front_edges[:, 1:] - front_edges[:, :-1])).clamp_min(1e-6)
        weights, acc, rgb, disparity = self._composite(origins, directions, front_edges, front_t, kernels)
        front = OuterRender(rgb, acc, 1.0 / disparity.clamp_min(1e-12), self._distortion(weights, origins))
        return front, behind

    def grid_parameters(self):
        return list(self.density_grid.parameters()) + list(self.appearance_grid.parameters())

    def network_parameters(self):
        return list(self.color_basis.parameters())


def depth_through_outer_space(
    front: OuterRender, accumulation: Tensor, box_depth: Tensor, behind: OuterRender
) -> Tensor:
    """A ray's whole depth where the space outside the box is modelled (warps, L_sd, the viewer): the outside in
    front of the box, the box's share of what it lets through and the outside behind, composited in disparity as
    the outer space composites its own samples (``OuterSpace.render``):
    1 / depth = 1 / d_front + (1 - acc_front) (acc / d_box + (1 - acc) / d_behind)."""
    dtype = box_depth.dtype
    accumulation, through = accumulation.to(dtype), 1.0 - front.accumulation.to(dtype)
    inside = accumulation / box_depth.clamp_min(1e-6) + (1.0 - accumulation) / behind.depth.to(dtype)
    return 1.0 / (1.0 / front.depth.to(dtype) + through * inside)
