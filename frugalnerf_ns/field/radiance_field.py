"""FrugalNeRF's radiance field: a density grid and an appearance grid queried at any of L+1 scales.

Scale ``l`` reads every ``ratio**l``-th entry of the same tensors (see ``tensorial.py``). One appearance
basis matrix and one colour MLP are shared by all scales, so adding scales adds no parameters.
"""

from __future__ import annotations

import math
from typing import List, Literal, Optional, Sequence, Tuple

import torch
import torch.nn.functional as F
from jaxtyping import Bool, Float
from torch import Tensor, nn

from frugalnerf_ns.field.color_mlp import ColorMLP, MLPImplementation
from frugalnerf_ns.field.tensorial import OptimizerState, TensorVMGrid

DensityActivation = Literal["relu", "softplus"]


def activate_density(raw: Tensor, activation: DensityActivation, softplus_shift: float = -10.0) -> Tensor:
    """ReLU for forward-facing scenes; softplus(x - 10) (TensoRF's shifted softplus) for object scenes."""
    if activation == "relu":
        return F.relu(raw)
    return F.softplus(raw + softplus_shift)


def log_linear_voxel_counts(initial: int, final: int, num_upsamples: int) -> List[int]:
    """Voxel counts after each upsampling: from ``initial`` to ``final`` in equal ratios (TensoRF)."""
    if num_upsamples <= 0:
        return []
    log_a, log_b = math.log(initial), math.log(final)
    return [int(round(math.exp(log_a + (log_b - log_a) * (i + 1) / num_upsamples))) for i in range(num_upsamples)]


def resolution_for_voxels(num_voxels: int, box_size: Sequence[float], span_stride: int = 1) -> Tuple[int, int, int]:
    """Per-axis resolution with cubic voxels filling a box of ``box_size`` with about ``num_voxels``.

    ``span_stride`` > 1 rounds each axis to the nearest ``span_stride * k + 1`` entries (k >= 1), so a view
    keeping every ``span_stride``-th entry (a lower scale) ends on the box's far face instead of stopping short
    of it (``coords_for_stride``: points beyond a view's last entry read that entry).
    """
    volume = math.prod(float(s) for s in box_size)
    voxel = (volume / num_voxels) ** (1.0 / 3.0)
    resolution = [max(2, int(float(s) / voxel)) for s in box_size]
    if span_stride > 1:
        resolution = [span_stride * max(1, round((r - 1) / span_stride)) + 1 for r in resolution]
    return tuple(resolution)  # type: ignore[return-value]


class FrugalNeRFField(nn.Module):
    """Density and appearance VM grids over a box, evaluated at a chosen scale.

    Args:
        aabb: scene box, shape (2, 3).
        resolution: initial voxels along x, y, z.
        density_components: components of the XY, XZ, YZ density planes (paper LLFF: 16/4/4).
        appearance_components: the same for appearance (paper LLFF: 48/12/12).
        appearance_dim: output size of the shared basis matrix (27).
        downsample_ratio: stride ratio between consecutive scales (s = 4).
        num_lower_scales: L, the number of lower scales (2: three scales in all).
    """

    def __init__(
        self,
        aabb: Float[Tensor, "2 3"],
        resolution: Sequence[int],
        density_components: Sequence[int] = (16, 4, 4),
        appearance_components: Sequence[int] = (48, 12, 12),
        appearance_dim: int = 27,
        downsample_ratio: int = 4,
        num_lower_scales: int = 2,
        density_activation: DensityActivation = "relu",
        mlp_hidden_dim: int = 128,
        feature_pe: int = 0,
        use_view_dirs: bool = False,
        view_pe: int = 0,
        mlp_implementation: MLPImplementation = "auto",
    ) -> None:
        super().__init__()
        self.register_buffer("aabb", aabb.clone().float())
        self.downsample_ratio = downsample_ratio
        self.num_scales = num_lower_scales + 1
        self.density_activation: DensityActivation = density_activation
        self.density_grid = TensorVMGrid(resolution, density_components)
        self.appearance_grid = TensorVMGrid(resolution, appearance_components)
        self.appearance_basis = nn.Linear(self.appearance_grid.num_components, appearance_dim, bias=False)
        self.color_mlp = ColorMLP(
            appearance_dim,
            hidden_dim=mlp_hidden_dim,
            feature_pe=feature_pe,
            use_view_dirs=use_view_dirs,
            view_pe=view_pe,
            implementation=mlp_implementation,
        )
        # Occupancy of the full-resolution density (None until the first alpha-mask update). Stored as a
        # buffer so checkpoints carry it; an empty (0,0,0) tensor stands for "no mask yet".
        self.register_buffer("alpha_mask", torch.zeros(0, 0, 0, dtype=torch.bool))
        self.register_buffer("alpha_mask_aabb", aabb.clone().float())

    # ---- geometry of the grid -------------------------------------------------------------------------
    def stride(self, scale: int) -> int:
        return self.downsample_ratio**scale

    def voxel_size(self) -> Float[Tensor, "3"]:
        res = self.density_grid.resolution.to(self.aabb)
        return (self.aabb[1] - self.aabb[0]) / (res - 1).clamp_min(1)

    def sample_step(self, scale: int, step_ratio: float = 0.5) -> float:
        """Half a voxel at full resolution, ``ratio``x and ``ratio**2``x coarser at the lower scales."""
        return float(self.voxel_size().mean()) * step_ratio * self.stride(scale)

    def normalize(self, positions: Float[Tensor, "n 3"]) -> Float[Tensor, "n 3"]:
        return (positions - self.aabb[0]) / (self.aabb[1] - self.aabb[0]) * 2.0 - 1.0

    def inside(self, positions: Float[Tensor, "*bs 3"]) -> Bool[Tensor, "*bs"]:
        """In the box and, once an alpha mask exists, in an occupied voxel of it."""
        inside_box = ((positions >= self.aabb[0]) & (positions <= self.aabb[1])).all(dim=-1)
        if self.alpha_mask.numel() == 0:
            return inside_box
        mask_aabb = self.alpha_mask_aabb
        res = torch.tensor(self.alpha_mask.shape, device=positions.device)
        idx = ((positions - mask_aabb[0]) / (mask_aabb[1] - mask_aabb[0]) * (res - 1)).round().long()
        in_mask_box = ((idx >= 0) & (idx < res)).all(dim=-1)
        idx = torch.minimum(idx.clamp_min(0), res - 1)
        occupied = self.alpha_mask[idx[..., 0], idx[..., 1], idx[..., 2]]
        return inside_box & in_mask_box & occupied

    # ---- queries --------------------------------------------------------------------------------------
    def density(self, positions: Float[Tensor, "n 3"], scale: int = 0) -> Float[Tensor, " n"]:
        coords = self.normalize(positions)
        raw = sum(p.sum(dim=-1) for p in self.density_grid.plane_line_products(coords, self.stride(scale)))
        return activate_density(raw, self.density_activation)  # type: ignore[arg-type]

    def color(
        self, positions: Float[Tensor, "n 3"], directions: Float[Tensor, "n 3"], scale: int = 0
    ) -> Float[Tensor, "n 3"]:
        coords = self.normalize(positions)
        products = self.appearance_grid.plane_line_products(coords, self.stride(scale))
        features = self.appearance_basis(torch.cat(products, dim=-1))
        return self.color_mlp(features, directions)

    # ---- schedules (called from training callbacks) ---------------------------------------------------
    def upsample(self, resolution: Sequence[int], optimizer_state: Optional[OptimizerState] = None) -> None:
        """Resample both grids (and, given the grid optimiser's state, its moments: ``TensorVMGrid.resample``)."""
        self.density_grid.resample(resolution, optimizer_state)
        self.appearance_grid.resample(resolution, optimizer_state)

    @torch.no_grad()
    def update_alpha_mask(
        self, step_ratio: float, distance_scale: float, threshold: float = 1e-4, chunk: int = 65536
    ) -> Float[Tensor, "2 3"]:
        """Evaluate full-resolution alpha on the grid's nodes, dilate (3x3x3 max-pool), threshold.

        Returns the box around the occupied voxels (the caller may shrink the grid to it).
        """
        res = self.density_grid.resolution_tuple
        axes = [torch.linspace(float(self.aabb[0, i]), float(self.aabb[1, i]), res[i], device=self.aabb.device)
                for i in range(3)]
        points = torch.stack(torch.meshgrid(*axes, indexing="ij"), dim=-1).reshape(-1, 3)
        step = self.sample_step(0, step_ratio)
        sigma = torch.cat([self.density(points[i : i + chunk]) for i in range(0, points.shape[0], chunk)])
        alpha = (1.0 - torch.exp(-sigma * step * distance_scale)).view(1, 1, *res)
        alpha = F.max_pool3d(alpha, kernel_size=3, padding=1, stride=1).view(*res)
        mask = alpha > threshold
        self.alpha_mask = mask
        self.alpha_mask_aabb = self.aabb.clone()
        occupied = points.view(*res, 3)[mask]
        if occupied.shape[0] == 0:
            return self.aabb.clone()
        return torch.stack([occupied.amin(dim=0), occupied.amax(dim=0)])

    @torch.no_grad()
    def shrink(self, new_aabb: Float[Tensor, "2 3"], optimizer_state: Optional[OptimizerState] = None) -> None:
        """Crop both grids (and the optimiser's moments) to the voxels covering ``new_aabb``; the box snaps to
        the kept voxels."""
        res = self.density_grid.resolution.to(self.aabb)
        units = self.voxel_size()
        lower = ((new_aabb[0] - self.aabb[0]) / units).floor().clamp_min(0)
        upper = ((new_aabb[1] - self.aabb[0]) / units).ceil()
        upper = torch.minimum(upper, res - 1)
        # Keep at least two entries per axis, so interpolation stays defined.
        upper = torch.maximum(upper, torch.minimum(lower + 1, res - 1))
        lower = torch.minimum(lower, upper - 1).clamp_min(0)
        lo, hi = lower.long().tolist(), upper.long().tolist()
        self.density_grid.crop(lo, hi, optimizer_state)
        self.appearance_grid.crop(lo, hi, optimizer_state)
        self.aabb = torch.stack([self.aabb[0] + lower * units, self.aabb[0] + upper * units])

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):  # noqa: D401
        # The alpha mask changes shape during training; take the checkpoint's shape.
        saved = state_dict.get(f"{prefix}alpha_mask")
        if saved is not None:
            self.alpha_mask = torch.zeros(saved.shape, dtype=torch.bool, device=self.aabb.device)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def grid_parameters(self) -> List[nn.Parameter]:
        return list(self.density_grid.parameters()) + list(self.appearance_grid.parameters())

    def network_parameters(self) -> List[nn.Parameter]:
        return list(self.appearance_basis.parameters()) + list(self.color_mlp.parameters())
