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
from typing import Callable, List, Optional, Sequence, Tuple

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


def strided_view(tensor: Float[Tensor, "1 c h w"], stride: int) -> Float[Tensor, "1 c h2 w2"]:
    """The view of a plane ([1, C, H, W]) or line ([1, C, L, 1]) a lower scale reads: every ``stride``-th entry of
    its spatial axes (a line's width of 1 is kept). No copy: it shares the full tensor's storage."""
    return tensor[:, :, ::stride, ::stride] if tensor.shape[-1] > 1 else tensor[:, :, ::stride, :]


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


def _axis_corners(x: Tensor, length: int):
    """The two entries and the far entry's weight of linear interpolation along one axis of ``length`` entries
    (align_corners=True, border padding)."""
    fx = ((x + 1.0) * 0.5 * (length - 1)).clamp(0, length - 1)
    # The last cell's upper corner is the border entry itself (weight 1 at fx == length - 1).
    low = fx.floor().clamp(max=max(length - 2, 0))
    weight = fx - low
    low = low.long()
    return low, (low + 1).clamp(max=length - 1), weight


def _corners(x: Tensor, y: Tensor, height: int, width: int, stride: int = 1, row_length: Optional[int] = None):
    """Corner indices and weights of bilinear interpolation with align_corners=True and border padding on a
    ``height`` x ``width`` grid, the indices flat in a tensor whose rows hold ``row_length`` entries (default
    ``width``) where the grid is its every ``stride``-th row and column."""
    (x0, x1, wx), (y0, y1, wy) = _axis_corners(x, width), _axis_corners(y, height)
    if stride != 1:
        x0, x1, y0, y1 = x0 * stride, x1 * stride, y0 * stride, y1 * stride
    row = width if row_length is None else row_length
    return ((y0 * row + x0, (1 - wx) * (1 - wy)), (y0 * row + x1, wx * (1 - wy)),
            (y1 * row + x0, (1 - wx) * wy), (y1 * row + x1, wx * wy))


class _BilinearSampleCPU(torch.autograd.Function):
    """grid_sample's forward on a plane's stride-s view, and the full plane's gradient as four index_add_ calls.

    torch's CPU grid_sample backward parallelises over the batch, which is 1 for a grid's plane, and was
    the largest single cost of a training step (frugalnerf-bench profile); index_add_ over the four corners
    computes the same gradient (to float rounding) about 2.4x faster on 2 cores. The corners are added at their
    place in the full plane (the view's index times the stride): autograd's backward of the strided view would
    zero-fill a full-size gradient and copy the view's into it, per plane, scale and step.
    """

    @staticmethod
    def forward(ctx, plane: Tensor, x: Tensor, y: Tensor, stride: int) -> Tensor:  # type: ignore[override]
        view = strided_view(plane, stride)
        grid = torch.stack([x, y], dim=-1).view(1, -1, 1, 2)
        out = F.grid_sample(view, grid, mode="bilinear", padding_mode="border", align_corners=True)
        ctx.save_for_backward(x, y)
        ctx.plane_shape, ctx.plane_dtype, ctx.view_shape, ctx.stride = plane.shape, plane.dtype, view.shape, stride
        return out.view(plane.shape[1], -1)

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        x, y = ctx.saved_tensors
        _, channels, height, width = ctx.plane_shape
        accumulated = torch.zeros(channels, height * width, dtype=grad.dtype, device=grad.device)
        view_height, view_width = ctx.view_shape[2:]
        for index, weight in _corners(x, y, view_height, view_width, ctx.stride, width):
            accumulated.index_add_(1, index, grad * weight.to(grad.dtype))
        return accumulated.view(1, channels, height, width).to(ctx.plane_dtype), None, None, None


def sample_plane(
    plane: Float[Tensor, "1 c h w"], x: Float[Tensor, " n"], y: Float[Tensor, " n"], stride: int = 1
) -> Float[Tensor, "c n"]:
    """Bilinear read of a [1, C, H, W] tensor's stride-``stride`` view (every stride-th row and column) at n points,
    x along the view's width and y along its height in [-1, 1] (align_corners=True, border padding): F.grid_sample
    on the view, with a faster backward on the CPU."""
    if plane.is_cuda or x.requires_grad or y.requires_grad or not torch.is_grad_enabled():
        grid = torch.stack([x, y], dim=-1).view(1, -1, 1, 2)
        view = strided_view(plane, stride)
        return F.grid_sample(view, grid, mode="bilinear", padding_mode="border", align_corners=True).view(plane.shape[1], -1)
    return _BilinearSampleCPU.apply(plane, x, y, stride)


class _LinearSampleCPU(torch.autograd.Function):
    """A line's linear read as two gathers, its gradient as two index_add_ calls: grid_sample on the [1, C, L, 1]
    tensor reads four corners of which two (the zero-width axis) carry no weight, and its backward adds four. A
    stride-s view's entries are read and added at their place in the full line (as ``_BilinearSampleCPU``)."""

    @staticmethod
    def forward(ctx, line: Tensor, y: Tensor, stride: int) -> Tensor:  # type: ignore[override]
        values = line[0, :, :, 0]
        view_length = strided_length(values.shape[1], stride)
        low, high, weight = _axis_corners(y, view_length)
        low, high = low * stride, high * stride
        ctx.save_for_backward(low, high, weight)
        ctx.line_shape, ctx.line_dtype = line.shape, line.dtype
        return torch.lerp(values.index_select(1, low), values.index_select(1, high), weight.to(values.dtype))

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        low, high, weight = ctx.saved_tensors
        _, channels, length, _ = ctx.line_shape
        weight = weight.to(grad.dtype)
        far = grad * weight
        accumulated = torch.zeros(channels, length, dtype=grad.dtype, device=grad.device)
        accumulated.index_add_(1, low, grad - far)
        accumulated.index_add_(1, high, far)
        return accumulated.view(1, channels, length, 1).to(ctx.line_dtype), None, None


def sample_line(line: Float[Tensor, "1 c l 1"], y: Float[Tensor, " n"], stride: int = 1) -> Float[Tensor, "c n"]:
    """Linear read of a [1, C, L, 1] line's stride-``stride`` view at n points in [-1, 1] (align_corners=True,
    border padding): what ``sample_plane(view, 0, y)`` gives, with half its corners on the CPU."""
    if line.is_cuda or y.requires_grad or not torch.is_grad_enabled():
        return sample_plane(strided_view(line, stride), torch.zeros_like(y), y)
    return _LinearSampleCPU.apply(line, y, stride)


def _cell_corners(index: Float[Tensor, "n 3"], size: Float[Tensor, "3"]) -> Tuple[Tensor, Tensor]:
    """Per axis, the lower node of the cell an index-space point falls in and the point's weight toward the upper
    one, clamped to the ``size`` nodes of each axis (corners aligned, border padding)."""
    f = torch.minimum(index.clamp_min(0), size - 1)
    # The last cell's upper corner is the border node itself (weight 1 at f == size - 1).
    low = torch.minimum(f.floor(), (size - 2).clamp_min(0))
    return low.long(), f - low


def trilinear_rows(table: Float[Tensor, "nodes c"], dims: Sequence[int], index: Float[Tensor, "n 3"]) -> Float[Tensor, "n c"]:
    """Trilinear read of a channels-last node table (``dims`` = X, Y, Z nodes, x fastest) at index-space points
    (x, y, z in node units): what grid_sample gives on the [1, C, Z, Y, X] tensor with corners aligned and
    border padding, at 8 row gathers per point (grid_sample reads each channel's 8 nodes separately, C apart
    in memory)."""
    size = torch.tensor([int(n) for n in dims], device=index.device, dtype=index.dtype)
    low, w = _cell_corners(index, size)
    w = w.to(table.dtype)
    x_step, y_step, z_step = (1 if dims[0] > 1 else 0), (dims[0] if dims[1] > 1 else 0), (dims[0] * dims[1] if dims[2] > 1 else 0)
    base = (low[:, 2] * dims[1] + low[:, 1]) * dims[0] + low[:, 0]

    def row(offset: int) -> Tensor:
        return table.index_select(0, base + offset if offset else base)

    wx, wy, wz = w[:, 0:1], w[:, 1:2], w[:, 2:3]
    near_z = torch.lerp(torch.lerp(row(0), row(x_step), wx), torch.lerp(row(y_step), row(y_step + x_step), wx), wy)
    far_z = torch.lerp(torch.lerp(row(z_step), row(z_step + x_step), wx),
                       torch.lerp(row(z_step + y_step), row(z_step + y_step + x_step), wx), wy)
    return torch.lerp(near_z, far_z, wz)


class _NodeSum(torch.autograd.Function):
    """``TensorVMGrid.node_sum`` as three matrix products into one [Z, Y, X] tensor, and its gradient as six: each
    plane-line pair is a rank-C product whose output already has the node tensor's layout, so nothing is
    permuted or copied (einsum's autograd path is about 1.4x slower on 2 cores, mostly in those copies)."""

    @staticmethod
    def forward(ctx, p_xy: Tensor, p_xz: Tensor, p_yz: Tensor, l_z: Tensor, l_y: Tensor, l_x: Tensor) -> Tensor:  # type: ignore[override]
        # Shapes (PLANE_AXES): p_xy [c, Y, X], p_xz [c, Z, X], p_yz [c, Z, Y]; lines [c, Z], [c, Y], [c, X].
        # In the tensors' own dtype, also under autocast: its half-precision matmul output could not take the
        # in-place products of full-precision inputs (and the sum of three products is the value that must not
        # lose precision).
        with torch.autocast(p_xy.device.type, enabled=False):
            size_z, size_y, size_x = p_xz.shape[1], p_xy.shape[1], p_xy.shape[2]
            nodes = (l_z.T @ p_xy.reshape(p_xy.shape[0], -1)).view(size_z, size_y, size_x)
            nodes.baddbmm_(l_y.T.expand(size_z, -1, -1), p_xz.transpose(0, 1))
            nodes.view(size_z * size_y, size_x).addmm_(p_yz.reshape(p_yz.shape[0], -1).T, l_x)
        ctx.save_for_backward(p_xy, p_xz, p_yz, l_z, l_y, l_x)
        return nodes

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        saved = ctx.saved_tensors
        with torch.autocast(grad.device.type, enabled=False):
            return _NodeSum._gradients(grad.to(saved[0].dtype), *saved)

    @staticmethod
    def _gradients(grad: Tensor, p_xy: Tensor, p_xz: Tensor, p_yz: Tensor, l_z: Tensor, l_y: Tensor, l_x: Tensor):
        grad = grad.contiguous()
        size_z, size_y, size_x = grad.shape
        by_z = grad.view(size_z, size_y * size_x)
        by_zy = grad.view(size_z * size_y, size_x)
        d_p_xy = (l_z @ by_z).view_as(p_xy)
        d_l_z = p_xy.reshape(p_xy.shape[0], -1) @ by_z.T
        d_p_xz = torch.matmul(l_y, grad).transpose(0, 1)  # [Z, c, X] -> [c, Z, X]
        d_l_y = torch.bmm(p_xz.transpose(0, 1), grad.transpose(1, 2)).sum(dim=0)  # [Z, c, Y] summed over Z
        d_p_yz = (by_zy @ l_x.T).T.reshape_as(p_yz)
        d_l_x = p_yz.reshape(p_yz.shape[0], -1) @ by_zy
        return d_p_xy, d_p_xz, d_p_yz, d_l_z, d_l_y, d_l_x


class _NodeRead(torch.autograd.Function):
    """Gather 8 corner values per point and blend them with fixed weights; the gradient is one index_add_."""

    @staticmethod
    def forward(ctx, flat_nodes: Tensor, corners: Tensor, weights: Tensor) -> Tensor:  # type: ignore[override]
        ctx.save_for_backward(corners, weights)
        ctx.num_nodes = flat_nodes.shape[0]
        return (flat_nodes.index_select(0, corners.reshape(-1)).view_as(weights) * weights).sum(dim=0)

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        corners, weights = ctx.saved_tensors
        out = torch.zeros(ctx.num_nodes, dtype=grad.dtype, device=grad.device)
        out.index_add_(0, corners.reshape(-1), (weights * grad).reshape(-1))
        return out, None, None


def read_node_sum(
    nodes: Float[Tensor, "z y x"], coords: Float[Tensor, "n 3"], stride: int = 1
) -> Float[Tensor, " n"]:
    """Trilinear read of ``TensorVMGrid.node_sum`` at n points in [-1, 1] (x, y, z; corners aligned, border
    clamped), at a stride: equal (to float rounding) to ``plane_line_products(coords, stride)`` summed
    over planes and components, at 8 reads of one value per point instead of 3 planes x 4 corners x C channels
    and 3 lines x 2 x C (and as many scattered adds in the backward pass).

    The strided view is read in place (its nodes' indices in the full tensor), so its gradient is added straight
    into a full-size tensor: no slice backward that zero-fills and copies one more per scale.
    """
    res = (nodes.shape[2], nodes.shape[1], nodes.shape[0])  # x, y, z
    lengths = [strided_length(r, stride) for r in res]
    # Index along each axis of the strided view: the full grid's index / stride (where the view's entries lie;
    # ``coords_for_stride``).
    per_unit = [0.5 * (r - 1) / stride for r in res]
    device, dtype = coords.device, coords.dtype
    size = torch.tensor(lengths, device=device, dtype=dtype)
    low, weight = _cell_corners((coords + 1.0) * torch.tensor(per_unit, device=device, dtype=dtype), size)
    weight = weight.to(nodes.dtype)
    element_step = torch.tensor([stride, stride * res[0], stride * res[0] * res[1]], device=device)
    base = (low * element_step).sum(dim=-1)
    step = (torch.minimum(low + 1, size.long() - 1) - low) * element_step  # 0 where an axis keeps one entry
    dx, dy, dz = step.unbind(-1)
    corners = torch.stack([base, base + dx, base + dy, base + dy + dx])
    corners = torch.cat([corners, corners + dz])
    wx, wy, wz = weight.unbind(-1)
    ux, uy, uz = 1.0 - wx, 1.0 - wy, 1.0 - wz
    xy = torch.stack([ux * uy, wx * uy, ux * wy, wx * wy])
    weights = torch.cat([xy * uz, xy * wz])
    return _NodeRead.apply(nodes.reshape(-1), corners, weights)


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
        return [strided_view(p, stride) for p in self.planes], [strided_view(line, stride) for line in self.lines]

    def view_coords(self, coords: Float[Tensor, "n 3"], stride: int = 1) -> Float[Tensor, "n 3"]:
        """Where the strided views of ``plane_line_products`` read full-grid coordinates ``coords``."""
        res = self.resolution_tuple
        return torch.stack([coords_for_stride(coords[:, i], res[i], stride) for i in range(3)], dim=-1)

    def plane_line_products(
        self, coords: Float[Tensor, "n 3"], stride: int = 1
    ) -> List[Float[Tensor, "n comps"]]:
        """Per plane, the component-wise product plane(coords) * line(coords) at the given stride.

        A strided view is read where its entries lie in the full grid (``coords_for_stride``)."""
        mapped = self.view_coords(coords, stride)
        products = []
        # The full tensors with the stride: a read's gradient goes straight into the full-size tensor.
        for plane, line, (a, b), line_axis in zip(self.planes, self.lines, PLANE_AXES, LINE_AXES):
            plane_feat = sample_plane(plane, mapped[:, a], mapped[:, b], stride)
            line_feat = sample_line(line, mapped[:, line_axis], stride)
            products.append((plane_feat * line_feat).T)
        return products

    def node_sum(self) -> Float[Tensor, "z y x"]:
        """Every plane times its line, summed over planes and components, at each grid node: [Z, Y, X].

        A plane read bilinearly times its line read linearly is the trilinear interpolation of their outer
        product on the grid's nodes (both with corners aligned and coordinates clamped to the box), and sums
        commute with interpolation: a trilinear read of this tensor is ``sum(plane_line_products(...))`` summed
        over components, to float rounding. A strided view ``[::s, ::s, ::s]`` is the same at stride s.
        """
        (p_xy, p_xz, p_yz), (l_z, l_y, l_x) = [p[0] for p in self.planes], [line[0, :, :, 0] for line in self.lines]
        # PLANE_AXES: the XY plane is [c, y, x] (height y, width x), XZ is [c, z, x], YZ is [c, z, y].
        return _NodeSum.apply(p_xy, p_xz, p_yz, l_z, l_y, l_x)

    def node_features(self, basis: Float[Tensor, "k comps"]) -> Float[Tensor, "z y x k"]:
        """``basis @ cat(plane_line_products)`` at every grid node, [Z, Y, X, K]: the appearance features on the
        nodes, whose trilinear reads equal the planes' and lines' reads times the basis (``node_sum``'s argument:
        the basis is linear)."""
        (p_xy, p_xz, p_yz), (l_z, l_y, l_x) = [p[0] for p in self.planes], [line[0, :, :, 0] for line in self.lines]
        b_xy, b_xz, b_yz = torch.split(basis, list(self.components), dim=1)
        # The basis folded into the lines first ([k, c, line]): one contraction over c per plane.
        nodes = torch.einsum("cyx,kcz->zyxk", p_xy, torch.einsum("kc,cz->kcz", b_xy, l_z))
        nodes += torch.einsum("czx,kcy->zyxk", p_xz, torch.einsum("kc,cy->kcy", b_xz, l_y))
        nodes += torch.einsum("czy,kcx->zyxk", p_yz, torch.einsum("kc,cx->kcx", b_yz, l_x))
        return nodes

    @torch.no_grad()
    def resample(self, resolution: Sequence[int]) -> None:
        """Resample every plane and line to a new resolution (bilinear / linear, corners aligned).

        The tensors are replaced by new Parameters (autograd caches a leaf's shape, so resizing one in place
        breaks the next backward); the caller must recreate the optimiser.
        """
        for i, ((a, b), line_axis) in enumerate(zip(PLANE_AXES, LINE_AXES)):
            plane_size, line_size = (resolution[b], resolution[a]), (resolution[line_axis], 1)
            self.planes[i] = _replaced(self.planes[i], lambda t, size=plane_size: _interpolated(t, size))
            self.lines[i] = _replaced(self.lines[i], lambda t, size=line_size: _interpolated(t, size))
        self.resolution.copy_(torch.tensor([int(r) for r in resolution]))

    @torch.no_grad()
    def crop(self, lower: Sequence[int], upper: Sequence[int]) -> None:
        """Keep entries lower[i]..upper[i] (inclusive) along each axis (new Parameters, as in ``resample``)."""
        for i, ((a, b), line_axis) in enumerate(zip(PLANE_AXES, LINE_AXES)):
            rows, cols = slice(lower[b], upper[b] + 1), slice(lower[a], upper[a] + 1)
            self.planes[i] = _replaced(self.planes[i], lambda t, r=rows, c=cols: t[:, :, r, c].contiguous())
            entries = slice(lower[line_axis], upper[line_axis] + 1)
            self.lines[i] = _replaced(self.lines[i], lambda t, e=entries: t[:, :, e, :].contiguous())
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


def _interpolated(tensor: Tensor, size: Tuple[int, int]) -> Tensor:
    return F.interpolate(tensor, size=size, mode="bilinear", align_corners=True)


def _replaced(param: nn.Parameter, transform: Callable[[Tensor], Tensor]) -> nn.Parameter:
    """A new Parameter holding ``transform(param)``."""
    return nn.Parameter(transform(param.data))
