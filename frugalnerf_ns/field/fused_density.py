"""A training step's density read from the grid's planes and lines in one fused kernel (NVIDIA Warp) on the CPU, with
its backward in another: what ``TensorVMGrid.plane_line_products`` summed over planes and channels gives, and the
gradient its autograd graph gives the planes and lines, without the graph's per-sample tensors (each plane's and
line's [C, n] reads, their products, the corner weights, and four scattered adds per plane in the backward pass).

The torch reads stay the reference and the path of ``--pipeline.model.kernels torch``. The kernels read channels-last
copies of the full tensors (a corner is one vector of a plane's channels), at the strided view's entries times the
stride, so a lower scale's gradient lands on the full tensors' entries as ``tensorial.sample_plane``'s does. Each
core's launch adds its samples' gradient into tables of its own (Warp's adds on the CPU are plain adds: two launches
adding into one table would race), summed once at the end.
"""

from __future__ import annotations

from typing import Callable, List, Optional, Sequence

import torch
from torch import Tensor

from frugalnerf_ns.field.fused_kernel_source import define_density_read
from frugalnerf_ns.field import fused_kernels
from frugalnerf_ns.field.fused_kernels import WarpKernels, _parts, _rows, on_every_core
from frugalnerf_ns.field.tensorial import strided_length

SPLIT_MIN_SAMPLES = 1 << 16
"""Samples from which a read (and its backward) runs one launch per core. Below it one launch: a fern step's coarsest
scale (~21,000 samples) split over the pool made the torch operations right after it stall (~11 ms a step in
``nonzero`` calls on 2 cores), more than the split saved."""


def _density_kernels(fused: WarpKernels, components: tuple, say: Callable[[str], None] = print):
    """(forward, backward, vector types) for planes of ``components`` channels (``fused_kernels.compile_once``)."""
    return fused_kernels.compile_once(fused, ("density_read", components),
                                      lambda: define_density_read(fused.wp, components),
                                      f"fused training density read for {components} channels", say)


def _tables(planes: Sequence[Tensor], lines: Sequence[Tensor]) -> List[Tensor]:
    """Channels-last float32 copies: each plane [1, C, H, W] as [H*W, C], each line [1, C, L, 1] as [L, C]."""
    tables = []
    for plane, line in zip(planes, lines):
        _, comps, height, width = plane.shape
        tables.append(_rows(plane.detach()[0].permute(1, 2, 0), height * width, comps))
        tables.append(_rows(line.detach()[0, :, :, 0].T, line.shape[2], comps))
    return tables


class _FusedDensityRead(torch.autograd.Function):
    """Density (before its activation) at grid coordinates already mapped into a stride's views (``view_coords``)."""

    @staticmethod
    def forward(ctx, coords: Tensor, stride: int, fused: WarpKernels, compiled, kept: Optional[dict],  # type: ignore[override]
                *tensors: Tensor) -> Tensor:
        planes, lines = tensors[:3], tensors[3:]
        wp = fused.wp
        forward_kernel, _, vectors = compiled
        coords = coords.detach().to(torch.float32).contiguous()
        tables = kept.get("tables") if kept is not None else None
        if tables is None:
            tables = _tables(planes, lines)
            if kept is not None:
                kept["tables"] = tables
        # PLANE_AXES: XY is [1, c, Y, X], XZ [1, c, Z, X]: the full grid's X, Y, Z entries and the planes' widths.
        full = (planes[0].shape[3], planes[0].shape[2], planes[1].shape[2])
        sizes = wp.vec3i(*[strided_length(n, stride) for n in full])
        rows = wp.vec3i(full[0], full[0], full[1])
        shared = [wp.from_torch(table, dtype=vectors[k // 2]) for k, table in enumerate(tables)]
        n = coords.shape[0]
        out = torch.empty(n, dtype=torch.float32)

        def launch(a: int, b: int) -> None:
            wp.launch(forward_kernel, dim=b - a, device="cpu", inputs=[
                wp.from_torch(coords[a:b], dtype=wp.vec3), sizes, rows, stride, *shared, wp.from_torch(out[a:b])])

        on_every_core([(lambda a=a, b=b: launch(a, b)) for a, b in _parts(n, SPLIT_MIN_SAMPLES)])
        ctx.save_for_backward(coords)
        ctx.tables, ctx.launch_args = tables, (fused, compiled, sizes, rows, stride)
        ctx.shapes = [(t.shape, t.dtype) for t in tensors]
        return out.to(planes[0].dtype)

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        (coords,) = ctx.saved_tensors
        fused, compiled, sizes, rows, stride = ctx.launch_args
        wp, backward_kernel, vectors = fused.wp, compiled[1], compiled[2]
        grad = grad.detach().to(torch.float32).contiguous()
        parts = _parts(coords.shape[0], SPLIT_MIN_SAMPLES)
        # One set of gradient tables per launch (see the module's docstring), summed below.
        gradients = [torch.zeros(len(parts), *t.shape, dtype=torch.float32) for t in ctx.tables]
        shared = [wp.from_torch(table, dtype=vectors[k // 2]) for k, table in enumerate(ctx.tables)]

        def launch(part: int, a: int, b: int) -> None:
            own = [wp.from_torch(g[part], dtype=vectors[k // 2]) for k, g in enumerate(gradients)]
            wp.launch(backward_kernel, dim=b - a, device="cpu", inputs=[
                wp.from_torch(coords[a:b], dtype=wp.vec3), sizes, rows, stride, *shared, wp.from_torch(grad[a:b]),
                *own])

        on_every_core([(lambda p=p, a=a, b=b: launch(p, a, b)) for p, (a, b) in enumerate(parts)])
        results = []
        # The tables are plane, line per pair; the tensors the planes, then the lines. [H*W, C] -> [1, C, H, W] and
        # [L, C] -> [1, C, L, 1].
        for (shape, dtype), g in zip(ctx.shapes, [*gradients[0::2], *gradients[1::2]]):
            g = g.sum(dim=0) if g.shape[0] > 1 else g[0]
            results.append(g.T.reshape(shape).to(dtype))
        return (None, None, None, None, None, *results)


def fused_density(fused: WarpKernels, grid, coords: Tensor, stride: int, say: Callable[[str], None] = print,
                  kept: Optional[dict] = None) -> Optional[Tensor]:
    """``sum(grid.plane_line_products(...))`` over planes and channels at coordinates ``coords`` already mapped into
    the stride's views (``TensorVMGrid.view_coords``), with its gradient into the planes and lines, on the CPU; None
    where the kernels do not compile for these component counts (the caller reads with torch). ``kept``: a dict
    that keeps the planes' channels-last copies for the next read, for reads of unchanged tensors only (a training
    step's forward pass: its scales read the same planes; the caller drops it before the tensors change)."""
    compiled = _density_kernels(fused, tuple(grid.components), say)
    if compiled is None:
        return None
    return _FusedDensityRead.apply(coords, stride, fused, compiled, kept, *grid.planes, *grid.lines)
