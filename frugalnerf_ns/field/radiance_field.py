"""FrugalNeRF's radiance field: a density grid and an appearance grid queried at any of L+1 scales.

Scale ``l`` reads every ``ratio**l``-th entry of the same tensors (see ``tensorial.py``). One appearance
basis matrix and one colour MLP are shared by all scales, so adding scales adds no parameters.
"""

from __future__ import annotations

import contextlib
import math
from typing import Callable, Dict, Iterator, List, Optional, Sequence, Tuple

import torch
import torch.nn.functional as F
from jaxtyping import Bool, Float, Int
from torch import Tensor, nn

from frugalnerf_ns.field.color_mlp import ColorMLP, MLPImplementation, native_bfloat16
from frugalnerf_ns.field.density import BakedDensity, DensityActivation, activate_density
from frugalnerf_ns.field import fused_training_reads
from frugalnerf_ns.field.tensorial import (
    TensorVMGrid,
    read_node_sum,
    strided_length,
    trilinear_rows,
)

BAKED_DENSITY_MAX_ENTRIES = 2**26
"""Largest grid (nodes) whose density is baked into one dense tensor for rendering outside training: 256 MiB
in float32 (a 400^3 grid). The paper preset's 640^3 grid reads its planes instead."""

SHARED_NODES_MAX_ENTRIES = 2**24
"""Largest grid (nodes) whose training steps read density from one node tensor (``shared_density_nodes``); larger
grids read their planes. The node tensor costs a fixed pass over every node per step (its sum, its gradient's
zero-fill and six matrix products back), the plane reads a cost per sample: on 2-view LLFF runs the nodes were
1.26x faster on a 177x193x113 grid (3.9 M nodes) and the planes 1.02-1.24x faster (four pairs) on 353x385x241
(32.7 M, the paper's grid ratio at 1/8 resolution). 2^24 (256^3) lies between the two (not measured there).
frugalnerf-cpu's 320^3 grid is 353x385x241 on fern's box with the spanning sizes (32.7 M nodes): it reads its planes."""

FUSED_READ_MIN_ENTRIES = 2**23
"""Smallest grid (nodes) whose training steps read the planes (density and appearance) with the fused kernels
(``fused_training_reads``); smaller grids read density from the shared nodes and the appearance with torch. In whole fern
and horns 2-view runs the fused density reads made steps at 16.4-17.9 M nodes 8-19 % faster and at 0.1-4.8 M 5-15 %
slower (fixed costs per read: copies, per-core tables, launches); the appearance reads were not tried below it."""

BAKED_FEATURES_MAX_ENTRIES = 2**27
"""Largest node count times appearance features baked for rendering outside training: 512 MiB in float32
(the CPU presets' ~4 M nodes x 27; the paper preset's grid reads its planes)."""


class FrugalNeRFField(nn.Module):
    """Density and appearance VM grids over a box, evaluated at a chosen scale.

    Args:
        aabb: scene box, shape (2, 3).
        resolution: initial voxels along x, y, z.
        density_components: components of the XY, XZ, YZ density planes (paper LLFF: 16/4/4).
        appearance_components: the same for appearance (paper LLFF: 48/12/12).
        appearance_dim: output size of the shared basis matrix (27).
        downsample_ratio: stride ratio between consecutive scales (s = 4).
        num_lower_scales: L, the number of lower scales (2: three scales in all). A lower scale reads each entry
            of its strided view at its place in the full grid (the view may stop short of the box's far faces:
            ``TensorVMGrid.plane_line_products``).
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
        # What ``baked_density`` and ``baked_features`` built, keyed on the versions of what they read.
        self._baked_cache: Tuple[tuple, Dict] = ((), {})
        self._features_cache: Tuple[tuple, Dict] = ((), {})
        self._mask_cache: Tuple[tuple, tuple] = ((), ())
        self._channels_last: Dict[tuple, tuple] = {}  # per stride: (parameter versions, fused kernels' tables)
        # Inside ``shared_density_nodes``: a one-entry list holding the density nodes once the first read made them.
        self._shared_nodes: Optional[List[Optional[Tensor]]] = None
        # Inside ``fused_training_reads``: the forward pass's fused reads of the planes.
        self._step_reads: Optional[fused_training_reads.StepReads] = None

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
        padded, res, strides = self._padded_mask()
        # The nearest mask voxel; one of False around the mask stands for every voxel beyond it, so a single
        # clamped lookup gives "in the mask's box and occupied". In int32 with the flat index summed by hand (half
        # the memory traffic of int64; an index sum would promote to int64): where the box test holds the
        # indices are within the grid, and elsewhere (an overflow, NaN) the box test decides anyway.
        idx = ((positions - mask_aabb[0]) / (mask_aabb[1] - mask_aabb[0]) * (res - 1)).round().to(torch.int32)
        idx = torch.minimum((idx + 1).clamp_min(0), res + 1)
        flat = idx[..., 0] * strides[0] + idx[..., 1] * strides[1] + idx[..., 2]
        return inside_box & padded[flat]

    def mask_lookup(self) -> Optional[Tuple[Tensor, Tensor, Tensor, Tensor]]:
        """What ``inside`` reads of the alpha mask (the padded flat mask, the mask's box, its unpadded shape, the
        padded strides), for kernels that repeat the test; None without a mask."""
        if self.alpha_mask.numel() == 0:
            return None
        padded, res, strides = self._padded_mask()
        return padded, self.alpha_mask_aabb, res, strides

    def _padded_mask(self) -> Tuple[Bool[Tensor, " entries"], Int[Tensor, "3"], Int[Tensor, "3"]]:
        """The alpha mask with one voxel of False on every side, flat, its unpadded shape and the padded
        volume's element strides (cached per mask)."""
        # Keyed on the mask itself (not only its address, which a new mask may reuse) and its in-place version.
        key = (self.alpha_mask, self.alpha_mask._version)
        cached = self._mask_cache[0]
        if not cached or cached[0] is not key[0] or cached[1] != key[1]:
            mask = self.alpha_mask
            padded = F.pad(mask.to(torch.uint8), (1, 1, 1, 1, 1, 1)).bool().reshape(-1)
            res = torch.tensor(mask.shape, device=mask.device, dtype=torch.int32)
            strides = torch.tensor([(res[1] + 2) * (res[2] + 2), res[2] + 2, 1], device=mask.device, dtype=torch.int32)
            self._mask_cache = (key, (padded, res, strides))
        return self._mask_cache[1]

    # ---- queries --------------------------------------------------------------------------------------
    def density(self, positions: Float[Tensor, "n 3"], scale: int = 0) -> Float[Tensor, " n"]:
        coords = self.normalize(positions)
        if self._shared_nodes is not None and not coords.requires_grad:  # the node reads give no position gradient
            nodes = self._shared_nodes[0]
            # Made at the first read with gradients (one made under no_grad would carry none to the planes).
            if nodes is None or (torch.is_grad_enabled() and not nodes.requires_grad):
                nodes = self._shared_nodes[0] = self.density_grid.node_sum()
            raw = read_node_sum(nodes, coords, self.stride(scale))
        else:
            raw = self._fused_read(self.density_grid, coords, scale, features=False)
            if raw is None:
                products = self.density_grid.plane_line_products(coords, self.stride(scale))
                raw = sum(p.sum(dim=-1) for p in products)
        return activate_density(raw, self.density_activation)  # type: ignore[arg-type]

    def fused_reads_pay(self) -> bool:
        """Whether the density grid is large enough for the fused training reads (``FUSED_READ_MIN_ENTRIES``)."""
        return math.prod(self.density_grid.resolution_tuple) >= FUSED_READ_MIN_ENTRIES

    @contextlib.contextmanager
    def fused_training_reads(self, kernels) -> Iterator[None]:
        """Within the block ``density`` (where not from shared nodes) and ``color`` read the planes with the fused
        kernels ``kernels`` (None: torch) on the CPU, with their backward (``fused_training_reads``): equal to float
        rounding. Its reads share the planes' copies made at each grid's first read and one gradient per grid: the
        grids must not change within it (a forward pass)."""
        previous = self._step_reads
        self._step_reads = None if kernels is None else fused_training_reads.StepReads(kernels)
        try:
            yield
        finally:
            if self._step_reads is not None:
                self._step_reads.close()
            self._step_reads = previous

    def _fused_read(self, grid: TensorVMGrid, coords: Tensor, scale: int, features: bool) -> Optional[Tensor]:
        """``grid``'s density or features at ``coords`` ([-1, 1]) read by the fused kernels inside
        ``fused_training_reads``; None elsewhere (and where they do not compile): the caller reads with torch."""
        if self._step_reads is None or coords.requires_grad or not coords.shape[0]:
            return None
        stride = self.stride(scale)
        return self._step_reads.read(grid, grid.view_coords(coords, stride), stride, features)

    @contextlib.contextmanager
    def shared_density_nodes(self, enabled: bool = True) -> Iterator[None]:
        """Within the block, ``density`` reads one ``TensorVMGrid.node_sum`` (made at the first read, with its
        gradient) at every scale (``read_node_sum``): the planes' values and gradients to float rounding, at a
        fixed cost of a few matrix products per block instead of 3 planes x 4 corners x C channels per sample.
        A training step's forward pass is the block: its reads of all scales share the nodes. Grids above
        ``SHARED_NODES_MAX_ENTRIES`` nodes (256^3; the paper preset's 640^3) read the planes: there a pass over
        every node per step costs more than the plane reads at the samples."""
        shared = enabled and math.prod(self.density_grid.resolution_tuple) <= SHARED_NODES_MAX_ENTRIES
        previous, self._shared_nodes = self._shared_nodes, ([None] if shared else None)
        try:
            yield
        finally:
            self._shared_nodes = previous

    def sampling_map(self, stride: int = 1) -> Tuple[Float[Tensor, "3"], Float[Tensor, "3"]]:
        """a, b with ``coords = p * a + b``: the corner-aligned [-1, 1] coordinates at which a scale of this
        stride reads world point p (``normalize`` then ``coords_for_stride``, which is affine per axis:
        x' = (x + 1) k - 1 with k = (R - 1) / (s (n - 1)), or 0 where the view keeps one entry)."""
        a = 2.0 / (self.aabb[1] - self.aabb[0])
        b = -self.aabb[0] * a - 1.0
        if stride == 1:
            return a, b
        res = self.density_grid.resolution_tuple
        k = [0.0 if strided_length(r, stride) == 1 else (r - 1) / (stride * (strided_length(r, stride) - 1)) for r in res]
        k = torch.tensor(k, device=a.device, dtype=a.dtype)
        return a * k, torch.where(k > 0, (b + 1.0) * k - 1.0, torch.zeros_like(b))

    @staticmethod
    def _versions(tensors: Sequence[Tensor]) -> tuple:
        """What identifies the contents of these tensors: storage, in-place version, shape, dtype, device."""
        return tuple((t.data_ptr(), t._version, tuple(t.shape), t.dtype, t.device) for t in tensors)

    @torch.no_grad()
    def baked_density(self, scale: int = 0) -> Optional["BakedDensity"]:
        """The density of a scale as one dense tensor and the alpha mask as a volume (``BakedDensity``), for
        rendering outside training; None for grids above ``BAKED_DENSITY_MAX_ENTRIES`` nodes. Cached, and rebuilt
        when a parameter, the mask or the box changed since (an optimiser step, an upsampling, a mask update, a
        shrink)."""
        res = self.density_grid.resolution_tuple
        if math.prod(res) > BAKED_DENSITY_MAX_ENTRIES:
            return None
        key, baked = self._baked_cache
        current = self._versions([*self.density_grid.planes, *self.density_grid.lines, self.alpha_mask, self.aabb])
        if key != current:
            baked = {1: self.density_grid.node_sum()[None, None]}
            self._baked_cache = (current, baked)
        stride = self.stride(scale)
        if stride not in baked:
            baked[stride] = baked[1][:, :, ::stride, ::stride, ::stride].contiguous()
        if ("lookup", stride) not in baked:
            baked[("lookup", stride)] = BakedDensity.build(self, baked[stride], stride)
        return baked[("lookup", stride)]

    @torch.no_grad()
    def baked_features(self, scale: int = 0) -> Optional[Tuple[Tensor, Tuple[int, int, int], Tensor, Tensor]]:
        """The appearance features on the grid's nodes at a scale (``TensorVMGrid.node_features``, the basis
        applied) as a channels-last [nodes, K] table, its node counts (x, y, z) and the affine map from world
        points to node units (``index = p * a + b``); None above ``BAKED_FEATURES_MAX_ENTRIES``. Cached as
        ``baked_density``, rebuilt when an appearance parameter or the box changed."""
        res = self.appearance_grid.resolution_tuple
        basis = self.appearance_basis.weight
        if math.prod(res) * basis.shape[0] > BAKED_FEATURES_MAX_ENTRIES:
            return None
        current = self._versions([*self.appearance_grid.planes, *self.appearance_grid.lines, basis, self.aabb])
        key, baked = self._features_cache
        if key != current:
            baked = {1: self.appearance_grid.node_features(basis)}
            self._features_cache = (current, baked)
        stride = self.stride(scale)
        if ("table", stride) not in baked:
            nodes = baked[1] if stride == 1 else baked[1][::stride, ::stride, ::stride]
            dims = (nodes.shape[2], nodes.shape[1], nodes.shape[0])
            a, b = self.sampling_map(stride)
            to_index = 0.5 * (torch.tensor(dims, device=a.device, dtype=a.dtype) - 1)
            baked[("table", stride)] = (nodes.reshape(-1, nodes.shape[-1]).contiguous(), dims, a * to_index,
                                        (b + 1.0) * to_index)
        return baked[("table", stride)]

    @torch.no_grad()
    def inference_color(
        self, positions: Float[Tensor, "n 3"], directions: Float[Tensor, "n 3"], scale: int = 0, kernels=None
    ) -> Float[Tensor, "n 3"]:
        """``color`` outside training: the features read from ``baked_features`` (8 row gathers per point
        instead of three planes, three lines and the basis; equal to float rounding). A grid too large to bake
        reads its planes, with ``kernels`` (``fused_kernels.warp_kernels``) in one fused kernel on
        channels-last copies of the scale's planes and lines. With ``kernels`` on a CPU that multiplies bfloat16 in
        hardware the basis and the colour MLP run in bfloat16 (``ColorMLP.forward_bfloat16``: a colour within
        ~2e-3; ``--pipeline.model.kernels torch`` keeps float32)."""
        baked = self.baked_features(scale)
        fused = kernels is not None
        mlp = self.color_mlp
        low = fused and positions.is_cpu and mlp.implementation == "torch" and native_bfloat16()
        if low:
            mlp = mlp.forward_bfloat16  # type: ignore[assignment]
        if baked is None and fused:
            from frugalnerf_ns.field import fused_kernels

            stride = self.stride(scale)
            coords = self.appearance_grid.view_coords(self.normalize(positions), stride)
            key = ("channels last", stride)
            current = self._versions([*self.appearance_grid.planes, *self.appearance_grid.lines])
            if self._channels_last.get(key, (None,))[0] != current:
                self._channels_last[key] = (current, fused_kernels.channels_last(*self.appearance_grid.scale_views(stride)))
            products = fused_kernels.vm_features(kernels, self._channels_last[key][1], coords)
            if products is None:
                return self.color(positions, directions, scale)
            if low:  # the basis too: the MLP rounds its inputs to bfloat16 anyway (~0.07 s less a fern frame)
                features = F.linear(products.to(torch.bfloat16), self.appearance_basis.weight.to(torch.bfloat16))
            else:
                features = self.appearance_basis(products.to(positions.dtype))
            return mlp(features, directions)
        if baked is None:
            return self.color(positions, directions, scale)
        table, dims, a, b = baked
        return mlp(trilinear_rows(table, dims, positions * a + b), directions)

    @torch.no_grad()
    def occupied_density(self, positions: Float[Tensor, "n 3"], scale: int = 0) -> Float[Tensor, " n"]:
        """Density where ``inside`` holds and 0 elsewhere, for rendering outside training: ``inside`` at every
        point (the same rounding to the nearest mask voxel as the training marcher), the density read from
        ``baked_density`` at every point (no selection of the occupied ones first), or, for a grid too large to
        bake, from the planes at the occupied points."""
        occupied = self.inside(positions)
        baked = self.baked_density(scale)
        if baked is not None:
            return torch.where(occupied, baked.read(positions), 0.0)
        density = torch.zeros(positions.shape[0], device=positions.device, dtype=positions.dtype)
        if occupied.any():
            density[occupied] = self.density(positions[occupied], scale).to(density.dtype)
        return density

    def color(
        self, positions: Float[Tensor, "n 3"], directions: Float[Tensor, "n 3"], scale: int = 0
    ) -> Float[Tensor, "n 3"]:
        coords = self.normalize(positions)
        products = self._fused_read(self.appearance_grid, coords, scale, features=True)
        if products is None:
            products = torch.cat(self.appearance_grid.plane_line_products(coords, self.stride(scale)), -1)
        features = self.appearance_basis(products)
        return self.color_mlp(features, directions)

    # ---- schedules (called from training callbacks) ---------------------------------------------------
    def upsample(self, resolution: Sequence[int]) -> None:
        """Resample both grids (``TensorVMGrid.resample``)."""
        self.density_grid.resample(resolution)
        self.appearance_grid.resample(resolution)

    @torch.no_grad()
    def update_alpha_mask(
        self, step_ratio: float, distance_scale: float, threshold: float = 1e-4, chunk: int = 65536,
        seen: Optional[Callable[[Tensor], Tensor]] = None,
    ) -> Float[Tensor, "2 3"]:
        """Evaluate full-resolution alpha on the grid's nodes, dilate (3x3x3 max-pool), threshold.

        ``seen`` (points -> bool, e.g. some training camera sees them) also empties every node that it rejects
        and none of whose neighbours it accepts (the same 3x3x3 dilation): space no photo shows keeps no density.
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
        if seen is not None:
            shown = torch.cat([seen(points[i : i + chunk]) for i in range(0, points.shape[0], chunk)])
            shown = F.max_pool3d(shown.float().view(1, 1, *res), kernel_size=3, padding=1, stride=1).view(*res)
            mask &= shown > 0
        self.alpha_mask = mask
        self.alpha_mask_aabb = self.aabb.clone()
        occupied = points.view(*res, 3)[mask]
        if occupied.shape[0] == 0:
            return self.aabb.clone()
        return torch.stack([occupied.amin(dim=0), occupied.amax(dim=0)])

    @torch.no_grad()
    def shrink(self, new_aabb: Float[Tensor, "2 3"]) -> None:
        """Crop both grids to the voxels covering ``new_aabb``; the box snaps to the kept voxels."""
        res = self.density_grid.resolution.to(self.aabb)
        units = self.voxel_size()
        lower = ((new_aabb[0] - self.aabb[0]) / units).floor().clamp_min(0)
        upper = ((new_aabb[1] - self.aabb[0]) / units).ceil()
        upper = torch.minimum(upper, res - 1)
        # Keep at least two entries per axis, so interpolation stays defined.
        upper = torch.maximum(upper, torch.minimum(lower + 1, res - 1))
        lower = torch.minimum(lower, upper - 1).clamp_min(0)
        lo, hi = lower.long().tolist(), upper.long().tolist()
        self.density_grid.crop(lo, hi)
        self.appearance_grid.crop(lo, hi)
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
