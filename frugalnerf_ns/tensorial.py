"""VM-decomposed feature grid with weight-sharing lower scales (paper Sec. 3.3).

A grid holds three planes (XY, XZ, YZ) and three lines (Z, Y, X), each with its own component count, at a
resolution that need not be cubic. nerfstudio's TensorVMEncoding stores the planes as one (3, C, R, R)
tensor and so can express neither.

Scale ``l`` of the grid is the same tensors read every ``ratio**l``-th entry (a strided view: no copy,
no filtering, no extra parameters), so a gradient through a lower scale lands on the shared
full-resolution entries. The paper's ablation prefers this nearest (strided) downsampling to bilinear.
"""

from __future__ import annotations

import math
from typing import List, Sequence, Tuple

import torch
import torch.nn.functional as F
from jaxtyping import Float
from torch import Tensor, nn

#: (horizontal, vertical) axes of each plane; grid_sample reads x along the width and y along the height.
PLANE_AXES: Tuple[Tuple[int, int], ...] = ((0, 1), (0, 2), (1, 2))
#: the axis each plane's partner line runs along (the one the plane does not span).
LINE_AXES: Tuple[int, ...] = (2, 1, 0)


def strided_length(resolution: int, stride: int) -> int:
    """Number of entries a stride keeps out of ``resolution`` (entries 0, stride, 2*stride, ...)."""
    return math.ceil(resolution / stride)


def coords_for_stride(x: Float[Tensor, "*bs"], resolution: int, stride: int) -> Float[Tensor, "*bs"]:
    """Map a full-grid coordinate in [-1, 1] (align_corners) to the same world point in the strided view.

    The view keeps full-grid entries 0, s, 2s, ..., (n-1)s; when (resolution - 1) is not a multiple of s the
    view stops short of the far face, and points beyond its last entry read that entry (border padding).
    """
    if stride == 1:
        return x
    n = strided_length(resolution, stride)
    if n == 1:
        return torch.zeros_like(x)
    full_index = (x + 1.0) * 0.5 * (resolution - 1)
    return full_index / (stride * (n - 1)) * 2.0 - 1.0


class TensorVMGrid(nn.Module):
    """Three planes and three lines with per-plane component counts and a per-axis resolution.

    Args:
        resolution: voxels along x, y, z.
        components: components of the XY, XZ and YZ planes (and of their Z, Y, X lines).
        init_scale: standard deviation of the Gaussian initialisation.
    """

    def __init__(self, resolution: Sequence[int], components: Sequence[int], init_scale: float = 0.1) -> None:
        super().__init__()
        if len(resolution) != 3 or len(components) != 3:
            raise ValueError(f"resolution and components need 3 entries, got {resolution} and {components}")
        self.components = tuple(int(c) for c in components)
        self.register_buffer("resolution", torch.tensor([int(r) for r in resolution], dtype=torch.long))
        self.planes = nn.ParameterList()
        self.lines = nn.ParameterList()
        for (a, b), line_axis, comps in zip(PLANE_AXES, LINE_AXES, self.components):
            self.planes.append(nn.Parameter(init_scale * torch.randn(1, comps, resolution[b], resolution[a])))
            self.lines.append(nn.Parameter(init_scale * torch.randn(1, comps, resolution[line_axis], 1)))

    @property
    def resolution_tuple(self) -> Tuple[int, int, int]:
        return tuple(int(r) for r in self.resolution.tolist())  # type: ignore[return-value]

    @property
    def num_components(self) -> int:
        return sum(self.components)

    def scale_views(self, stride: int) -> Tuple[List[Tensor], List[Tensor]]:
        """Strided views of the planes and lines: they share storage with the full-resolution tensors."""
        planes = [p[:, :, ::stride, ::stride] for p in self.planes]
        lines = [line[:, :, ::stride, :] for line in self.lines]
        return planes, lines

    def plane_line_products(
        self, coords: Float[Tensor, "n 3"], stride: int = 1
    ) -> List[Float[Tensor, "n comps"]]:
        """Per plane, the component-wise product plane(coords) * line(coords) at the given stride."""
        planes, lines = self.scale_views(stride)
        res = self.resolution_tuple
        mapped = torch.stack([coords_for_stride(coords[:, i], res[i], stride) for i in range(3)], dim=-1)
        products = []
        for plane, line, (a, b), line_axis in zip(planes, lines, PLANE_AXES, LINE_AXES):
            plane_grid = mapped[:, [a, b]].view(1, -1, 1, 2)
            line_grid = torch.stack([torch.zeros_like(mapped[:, line_axis]), mapped[:, line_axis]], dim=-1)
            line_grid = line_grid.view(1, -1, 1, 2)
            plane_feat = F.grid_sample(plane, plane_grid, mode="bilinear", padding_mode="border", align_corners=True)
            line_feat = F.grid_sample(line, line_grid, mode="bilinear", padding_mode="border", align_corners=True)
            products.append((plane_feat * line_feat).view(plane.shape[1], -1).T)
        return products

    @torch.no_grad()
    def resample(self, resolution: Sequence[int]) -> None:
        """Resample every plane and line to a new resolution (bilinear / linear, corners aligned).

        The tensors are replaced by new Parameters (autograd caches a leaf's shape, so resizing one in place
        breaks the next backward); the caller must recreate the optimiser.
        """
        for i, ((a, b), line_axis) in enumerate(zip(PLANE_AXES, LINE_AXES)):
            self.planes[i] = nn.Parameter(
                F.interpolate(self.planes[i].data, size=(resolution[b], resolution[a]), mode="bilinear", align_corners=True)
            )
            self.lines[i] = nn.Parameter(
                F.interpolate(self.lines[i].data, size=(resolution[line_axis], 1), mode="bilinear", align_corners=True)
            )
        self.resolution.copy_(torch.tensor([int(r) for r in resolution]))

    @torch.no_grad()
    def crop(self, lower: Sequence[int], upper: Sequence[int]) -> None:
        """Keep entries lower[i]..upper[i] (inclusive) along each axis (new Parameters, as in ``resample``)."""
        for i, ((a, b), line_axis) in enumerate(zip(PLANE_AXES, LINE_AXES)):
            plane = self.planes[i].data[:, :, lower[b] : upper[b] + 1, lower[a] : upper[a] + 1]
            self.planes[i] = nn.Parameter(plane.contiguous())
            line = self.lines[i].data[:, :, lower[line_axis] : upper[line_axis] + 1, :]
            self.lines[i] = nn.Parameter(line.contiguous())
        self.resolution.copy_(torch.tensor([int(u) - int(lo) + 1 for lo, u in zip(lower, upper)]))

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):  # noqa: D401
        # Upsampling and shrinking change the tensors' shapes during training, so a checkpoint rarely has
        # the shapes this module was constructed with. Resize in place before loading instead of failing on
        # a shape mismatch. In place keeps the Parameter objects, which an optimiser built before a resume
        # refers to; it is safe here because no backward pass has touched these leaves yet.
        for name, params in (("planes", self.planes), ("lines", self.lines)):
            for i, param in enumerate(params):
                saved = state_dict.get(f"{prefix}{name}.{i}")
                if saved is not None and saved.shape != param.shape:
                    param.data = torch.empty(saved.shape, dtype=param.dtype, device=param.device)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

