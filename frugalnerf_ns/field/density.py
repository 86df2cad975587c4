"""Density: its activation, and one scale's density baked into a dense tensor for rendering outside training
(``BakedDensity``: trilinear reads of the summed nodes, and the empty-space bounds the inference marcher and the
fused kernels look ray groups up in)."""

from __future__ import annotations

from dataclasses import dataclass, field as dataclass_field
from typing import Any, Dict, List, Literal, NamedTuple, Optional, Tuple

import torch
import torch.nn.functional as F
from jaxtyping import Bool, Float
from torch import Tensor

DensityActivation = Literal["relu", "softplus"]


def activate_density(raw: Tensor, activation: DensityActivation, softplus_shift: float = -10.0) -> Tensor:
    """ReLU for forward-facing scenes; softplus(x - 10) (TensoRF's shifted softplus) for object scenes."""
    if activation == "relu":
        return F.relu(raw)
    return F.softplus(raw + softplus_shift)


DILATIONS_KEPT = 8
"""Dilated volumes a ``BakedDensity`` keeps, the most recently used (per radius; its undilated volumes apart)."""


def any_corner(nodes: Bool[Tensor, "z y x"]) -> Bool[Tensor, "z1 y1 x1"]:
    """Per cell of a grid of nodes, whether any of its 8 corner nodes is True (max_pool3d's kernel 2, stride 1,
    on a 0 / 1 volume, in three ORs of bytes)."""
    for axis in range(3):
        size = nodes.shape[axis]
        if size < 2:
            return nodes.new_zeros(*[max(n - 1, 0) for n in nodes.shape])
        nodes = nodes.narrow(axis, 0, size - 1) | nodes.narrow(axis, 1, size - 1)
    return nodes


def dilate_along(volume: Bool[Tensor, "z y x"], axis: int, radius: int) -> Bool[Tensor, "z y x"]:
    """True where any entry within ``radius`` along ``axis`` is (max_pool3d's kernel 2 r + 1, stride 1,
    padding r along that axis, on a 0 / 1 volume): 2 r ORs of shifted bytes, where the pooling of a float volume
    took ~0.3 s a pass on a 257^3 grid."""
    size = volume.shape[axis]
    out = volume.clone()
    for k in range(1, min(radius, size - 1) + 1):
        out.narrow(axis, k, size - k).logical_or_(volume.narrow(axis, 0, size - k))
        out.narrow(axis, 0, size - k).logical_or_(volume.narrow(axis, k, size - k))
    return out


class GroupBound(NamedTuple):
    """One volume of ``BakedDensity.group_bounds``: a group is looked up at index-space point
    ``(p * a + b + 1) * to_index`` (floor for cells, round for nodes), clamped into ``entries`` (x, y, z)."""

    occupancy: Tensor
    """Flat bool volume, x fastest."""
    entries: Tensor
    a: Tensor
    b: Tensor
    to_index: Tensor
    rounding: bool


@dataclass(frozen=True)
class BakedDensity:
    """One scale's density as a dense [1, 1, Z, Y, X] tensor (and the alpha mask as a volume, to bound where
    density can be), with the affine maps from world points to their grid_sample coordinates (``p * a + b``).

    A plane read bilinearly times its line read linearly is a trilinear read of their outer product on the
    nodes, so one trilinear read of ``TensorVMGrid.node_sum`` gives the planes' density (to float rounding) at
    a sixth of the reads.
    """

    grid: Tensor
    grid_a: Tensor
    grid_b: Tensor
    mask: Optional[Tensor]
    mask_a: Tensor
    mask_b: Tensor
    activation: DensityActivation
    _dilated: Dict[tuple, Tensor] = dataclass_field(default_factory=dict, compare=False, repr=False)

    @staticmethod
    def build(field: Any, grid: Tensor, stride: int) -> "BakedDensity":
        """From a ``FrugalNeRFField`` (its sampling map at ``stride``, alpha mask and activation) and its density
        baked at that stride (typed loosely: the field imports this module)."""
        a, b = field.sampling_map(stride)
        if field.alpha_mask.numel():
            mask = field.alpha_mask.permute(2, 1, 0).to(grid.dtype)[None, None].contiguous()
            box = field.alpha_mask_aabb
            mask_a = 2.0 / (box[1] - box[0])
            mask_b = -box[0] * mask_a - 1.0
        else:
            mask, mask_a, mask_b = None, a, b
        return BakedDensity(grid, a, b, mask, mask_a, mask_b, field.density_activation)

    def _dilated_occupancy(self, which: str, radius: Tuple[int, int, int]) -> Tensor:
        """Flat bool volume, dilated by ``radius`` entries (z, y, x): ``"cells"``, the density grid's cells
        whose density can be non-zero (a trilinear read is a convex combination of the cell's 8 nodes and the
        activation is monotone, so a cell whose nodes all activate to 0 reads 0 everywhere; softplus never
        does); ``"mask"``, the alpha mask's occupied voxels; ``"cells in mask"``, the cells that can be non-zero
        and have a corner in the mask (for a mask on the grid's own nodes: a point's nearest mask voxel is one
        of its cell's corners)."""
        key = (which, radius)
        kept = self._dilated.pop(key, None)
        if kept is not None:
            self._dilated[key] = kept  # the most recently used last: what the bound below keeps
            return kept
        if ("base", which) not in self._dilated:
            if which in ("cells", "cells in mask"):
                volume = any_corner(activate_density(self.grid, self.activation)[0, 0] > 0)
                if which == "cells in mask":  # and a corner's mask voxel (the nearest one to any point of the cell)
                    volume &= any_corner(self.mask[0, 0] > 0)  # type: ignore[index]
            else:
                volume = self.mask[0, 0] > 0  # type: ignore[index]
            self._dilated[("base", which)] = volume
        volume = self._dilated[("base", which)]
        for axis, r in enumerate(radius):
            volume = dilate_along(volume, axis, r)
        # A frame's directions set the radii, so a video meets many: keep the last few used (a recompute is a
        # few passes over a byte per entry, ~30-50 ms on a 257^3 grid).
        dilated = [k for k in list(self._dilated) if k[0] != "base"]  # a copy: another thread may render too
        for old in dilated[: max(0, len(dilated) - DILATIONS_KEPT + 1)]:
            self._dilated.pop(old, None)
        self._dilated[key] = volume.reshape(-1)
        return self._dilated[key]

    @staticmethod
    def _group_hits(volume: Tensor, dims: Tensor, f_origin: Tensor, f_direction: Tensor, t: Tensor, rounding: bool) -> Tensor:
        """Look a flat volume of ``dims`` (x, y, z) entries up at index-space points f_origin + t f_direction,
        the entry floor(f) (cells) or round(f) (nodes), clamped into the volume: a point beyond a face clamps
        onto it, no farther from the in-box slots around it than the point itself."""
        index = torch.addcmul(f_origin[:, None, :], f_direction[:, None, :], t[..., None])
        index = index.round() if rounding else index.floor()
        # int32 (baked volumes hold fewer than 2^26 entries): the same indices at half the memory traffic.
        index = torch.minimum(index.clamp_min(0), dims - 1).to(torch.int32)
        flat = (index[..., 2] * int(dims[1]) + index[..., 1]) * int(dims[0]) + index[..., 0]
        return volume[flat]

    def occupied_groups(
        self,
        origins: Float[Tensor, "rays 3"],
        directions: Float[Tensor, "rays 3"],
        t_near: Float[Tensor, " rays"],
        step: float,
        num_samples: int,
        group: int = 8,
    ) -> Bool[Tensor, "rays groups"]:
        """Per ray and group of ``group`` consecutive slots ``t_near + (i + 0.5) step``: False where every slot
        of the group has density exactly 0, so a march may skip the group and composite the same pixels. One
        lookup per group at its centre, in volumes dilated by how far the group's slots (and their nearest
        mask voxels) lie from it: the density grid's cells that can be non-zero (ReLU fields; softplus is
        never 0) and the alpha mask's occupied voxels (``occupied_density`` is 0 outside them). Each bound is
        conservative, so both together are."""
        groups = -(-num_samples // group)
        hit = torch.ones(origins.shape[0], groups, dtype=torch.bool, device=origins.device)
        if origins.shape[0] == 0:
            return hit
        centre = torch.arange(groups, device=origins.device, dtype=origins.dtype) * group + 0.5 * group
        t = t_near[:, None] + centre[None, :] * step
        for bound in self.group_bounds(directions, step, group):
            f_origin, f_direction = (origins * bound.a + bound.b + 1.0) * bound.to_index, directions * bound.a * bound.to_index
            hit &= self._group_hits(bound.occupancy, bound.entries, f_origin, f_direction, t, bound.rounding)
        return hit

    def group_bounds(self, directions: Float[Tensor, "rays 3"], step: float, group: int) -> List["GroupBound"]:
        """The volumes ``occupied_groups`` looks each group up in, for these rays: the density grid's cells that
        can be non-zero (ReLU fields; softplus is never 0) and the alpha mask's occupied voxels (``occupied_density``
        is 0 outside them), each dilated by how far a group's slots (and their nearest mask voxels) lie from its
        centre along these rays. Each bound is conservative, so both together are. No rays: no bounds."""
        if directions.shape[0] == 0:
            return []
        bounds = [("cells", self.grid, self.grid_a, self.grid_b, 1)] if self.activation == "relu" else []
        if self.mask is not None:
            same_nodes = self.mask.shape == self.grid.shape and bool(
                torch.equal(self.mask_a, self.grid_a) and torch.equal(self.mask_b, self.grid_b))
            if bounds and same_nodes:  # both bounds in one volume: one lookup per group, and tighter
                bounds = [("cells in mask", self.grid, self.grid_a, self.grid_b, 1)]
            else:
                bounds.append(("mask", self.mask, self.mask_a, self.mask_b, 0))
        found = []
        for which, volume, a, b, cell in bounds:
            nodes = torch.tensor(volume.shape[2:][::-1], device=directions.device, dtype=directions.dtype)  # x, y, z
            if bool((nodes < 2).any()):
                continue  # a one-entry axis: no cells to bound (the lower scales of a tiny grid)
            to_index = 0.5 * (nodes - 1)  # grid_sample's corner-aligned coordinates in [-1, 1] to entries
            # How far (in entries) a group's slots lie from its centre, plus the half entry between a point and
            # its nearest node and one for rounding.
            reach = (0.5 * group * step) * (directions * a * to_index).abs().amax(dim=0) + (0.0 if cell else 0.5)
            radius = tuple(int(r) + 1 for r in reach.ceil().tolist()[::-1])
            occupancy = self._dilated_occupancy(which, radius)  # type: ignore[arg-type]
            found.append(GroupBound(occupancy, nodes - cell, a, b, to_index, not cell))
        return found

    def read(self, positions: Float[Tensor, "n 3"]) -> Float[Tensor, " n"]:
        """Density at world points from the dense tensor (trilinear, border-clamped; no mask, no box test)."""
        coords = (positions * self.grid_a + self.grid_b).view(1, 1, 1, -1, 3).to(self.grid.dtype)
        raw = F.grid_sample(self.grid, coords, mode="bilinear", padding_mode="border", align_corners=True)
        return activate_density(raw.view(-1), self.activation)
