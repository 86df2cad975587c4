"""A training step's reads of a grid's planes and lines in fused kernels (NVIDIA Warp): the density
(``TensorVMGrid.plane_line_products`` summed over planes and channels) and the appearance features (the products
concatenated), each with its backward in a kernel of its own, without the autograd graph's per-sample tensors (each
plane's and line's [C, n] reads, their products, the corner weights, and four scattered adds per plane backward).

The torch reads stay the reference and the path of ``--pipeline.model.kernels torch``. One forward pass's reads of a
grid (``GridReads``: its three scales, and for the appearance the detached rays too) share
- channels-last copies of the full planes and lines (a corner is one vector load of a plane's channels), read at a
  strided view's entries times the stride, so a lower scale's gradient lands on the full tensors' entries as
  ``tensorial.sample_plane``'s does;
- one set of gradient tables, one per core (on a GPU one: its adds are atomic): each read's backward adds its
  samples' gradient into them (Warp's adds on the CPU are plain adds: two launches adding into one table would
  race), and one autograd node every read
  hangs from (``_GridGradient``) hands their sum to the planes and lines once, after the last read's backward. Read
  by read, each scale's gradient would be a zero-filled tensor of the full planes' size, and autograd would add the
  three.

The model runs them on the CPU; they launch on the tensors' device (``fused_kernels.launch``), and
``bench/kernel_check.py`` runs them on a GPU beside torch's reads.
"""

from __future__ import annotations

from typing import Callable, Dict, List, Optional, Sequence

import torch
from torch import Tensor

from frugalnerf_ns.field.fused_kernels import (WarpKernels, _parts, channels_last, grid_read_kernels, in_parts, launch,
                                              run_jobs)
from frugalnerf_ns.field.tensorial import strided_length

SPLIT_MIN_SAMPLES = 1 << 16
"""Density samples from which a read (and its backward) runs one launch per core. Below it one launch: a fern step's
coarsest scale (~21,000 samples) split over the pool made the torch operations right after it stall (~11 ms a step in
``nonzero`` calls on 2 cores), more than the split saved."""

SPLIT_MIN_FEATURE_SAMPLES = 1 << 16
"""The same for the appearance features (each sample 72 channels at the presets' components, against the density's
24)."""

CHANNELS_FIRST_SPLIT_ROWS = 1 << 15
"""Rows of a gradient table from which its channels-first copy runs one launch per core."""


def _tables(planes: Sequence[Tensor], lines: Sequence[Tensor]) -> List[Tensor]:
    """Channels-last float32 copies (``fused_kernels.channels_last``): each plane [1, C, H, W] as [H*W, C], each line
    [1, C, L, 1] as [L, C], in that order per pair."""
    pairs = channels_last([p.detach() for p in planes], [line.detach() for line in lines])
    return [table for plane, _, _, line in pairs for table in (plane, line)]


class GridReads:
    """One forward pass's fused reads of one grid (``TensorVMGrid``), the grid unchanged throughout: its tables and
    gradient tables (see the module's docstring). ``close`` at the end of the forward pass."""

    def __init__(self, fused: WarpKernels, grid, kernels: dict) -> None:
        self.fused, self.kernels = fused, kernels
        self.parameters = [*grid.planes, *grid.lines]
        self.tables = _tables(grid.planes, grid.lines)
        # PLANE_AXES: XY is [1, c, Y, X], XZ [1, c, Z, X]: the full grid's X, Y, Z entries.
        self.full = (grid.planes[0].shape[3], grid.planes[0].shape[2], grid.planes[1].shape[2])
        self.components = tuple(grid.components)
        self.gradients: Dict[int, List[Tensor]] = {}  # per launch part, made at its first backward
        self._node: Optional[Tensor] = None

    def read(self, coords: Tensor, stride: int, features: bool) -> Tensor:
        """Density [n] (``features`` False) or features [n, sum of components] at coordinates already mapped into the
        stride's views (``TensorVMGrid.view_coords``)."""
        coords = coords.detach().to(torch.float32).contiguous()
        if not torch.is_grad_enabled() or not any(p.requires_grad for p in self.parameters):
            return self.values(coords, stride, features)
        if self._node is None:
            self._node = _GridGradient.apply(self, *self.parameters)
        return _FusedRead.apply(self._node, coords, stride, features, self)

    def close(self) -> None:
        """Let go of the autograd node (it holds this object: no cycle is left for the garbage collector)."""
        self._node = None

    def _arguments(self, stride: int) -> list:
        wp, vectors = self.fused.wp, self.kernels["vectors"]
        sizes = wp.vec3i(*[strided_length(n, stride) for n in self.full])
        rows = wp.vec3i(self.full[0], self.full[0], self.full[1])
        return [sizes, rows, stride, *[wp.from_torch(t, dtype=vectors[k // 2]) for k, t in enumerate(self.tables)]]

    def _kernel(self, features: bool, backward: bool) -> tuple:
        """The kernel, the Warp type of a read's value (and of its gradient) and the samples from which it splits."""
        name = ("feature_read" if features else "density_read") + ("_backward" if backward else "")
        if features:
            return self.kernels[name], self.kernels["row"], SPLIT_MIN_FEATURE_SAMPLES
        return self.kernels[name], self.fused.wp.float32, SPLIT_MIN_SAMPLES

    def values(self, coords: Tensor, stride: int, features: bool) -> Tensor:
        wp, n = self.fused.wp, coords.shape[0]
        shared = self._arguments(stride)
        kernel, dtype, split = self._kernel(features, backward=False)
        out = torch.empty((n, sum(self.components)) if features else (n,), dtype=torch.float32, device=coords.device)

        def launch_part(a: int, b: int) -> None:
            launch(self.fused, kernel, b - a, [
                wp.from_torch(coords[a:b], dtype=wp.vec3), *shared, wp.from_torch(out[a:b], dtype=dtype)], coords.device)

        in_parts(coords.device, n, launch_part, split)
        return out

    def add_gradient(self, coords: Tensor, stride: int, features: bool, grad: Tensor) -> None:
        """Add the planes' and lines' gradient from the read's (``grad``) into the gradient tables."""
        wp, vectors = self.fused.wp, self.kernels["vectors"]
        grad = grad.detach().to(torch.float32).contiguous()
        shared = self._arguments(stride)
        kernel, dtype, split = self._kernel(features, backward=True)
        # On a GPU one launch adds into one set of tables (its adds are atomic there).
        n = coords.shape[0]
        parts = _parts(n, split) if coords.is_cpu else [(0, n)] if n else []
        for part in range(len(parts)):
            if part not in self.gradients:
                self.gradients[part] = [torch.zeros_like(t) for t in self.tables]

        def launch_part(part: int, a: int, b: int) -> None:
            own = [wp.from_torch(g, dtype=vectors[k // 2]) for k, g in enumerate(self.gradients[part])]
            launch(self.fused, kernel, b - a, [
                wp.from_torch(coords[a:b], dtype=wp.vec3), *shared, wp.from_torch(grad[a:b], dtype=dtype), *own],
                coords.device)

        run_jobs(coords.device, [(lambda p=p, a=a, b=b: launch_part(p, a, b)) for p, (a, b) in enumerate(parts)])

    def take_gradients(self) -> List[Optional[Tensor]]:
        """The planes' and lines' gradients in their own shapes (the tables summed), then forget them; None each
        where no read's backward ran."""
        if not self.gradients:
            return [None] * len(self.parameters)
        tables = list(self.gradients.values())
        self.gradients = {}
        wp, vectors = self.fused.wp, self.kernels["vectors"]

        def channels_first(table: Tensor, plane: int, out: Tensor, a: int, b: int) -> None:
            launch(self.fused, self.kernels["channels_first"][plane], b - a,
                   [wp.from_torch(table[a:b], dtype=vectors[plane]), wp.from_torch(out[:, a:b])], table.device)

        results = []
        for k, parts in enumerate(zip(*tables)):
            summed = parts[0]
            for other in parts[1:]:
                summed += other
            out = torch.empty(summed.shape[1], summed.shape[0], dtype=torch.float32, device=summed.device)
            in_parts(summed.device, summed.shape[0],
                     lambda a, b, t=summed, o=out, p=k // 2: channels_first(t, p, o, a, b), CHANNELS_FIRST_SPLIT_ROWS)
            results.append(out)
        # The tables are plane, line per pair; the parameters the planes, then the lines. [H*W, C] -> [1, C, H, W]
        # and [L, C] -> [1, C, L, 1].
        return [g.view(p.shape).to(p.dtype) for p, g in zip(self.parameters, [*results[0::2], *results[1::2]])]


class _GridGradient(torch.autograd.Function):
    """The node every fused read of a forward pass hangs from: its output is a token (a zero scalar) the reads take
    as their input, so the autograd engine runs its backward once, after every read's: it hands the planes and lines
    the gradient the reads added into the tables."""

    @staticmethod
    def forward(ctx, reads: GridReads, *parameters: Tensor) -> Tensor:  # type: ignore[override]
        ctx.reads = reads
        return torch.zeros((), dtype=torch.float32, device=parameters[0].device)

    @staticmethod
    def backward(ctx, _):  # type: ignore[override]
        return (None, *ctx.reads.take_gradients())


class _FusedRead(torch.autograd.Function):
    """A fused read whose backward adds into the grid's gradient tables (``GridReads.add_gradient``)."""

    @staticmethod
    def forward(ctx, node: Tensor, coords: Tensor, stride: int, features: bool,  # type: ignore[override]
                reads: GridReads) -> Tensor:
        ctx.save_for_backward(coords)
        ctx.stride, ctx.features, ctx.reads = stride, features, reads
        return reads.values(coords, stride, features)

    @staticmethod
    def backward(ctx, grad: Tensor):  # type: ignore[override]
        (coords,) = ctx.saved_tensors
        ctx.reads.add_gradient(coords, ctx.stride, ctx.features, grad)
        return torch.zeros((), dtype=torch.float32, device=coords.device), None, None, None, None


class StepReads:
    """A forward pass's fused reads of a field's grids (``FrugalNeRFField.fused_training_reads``): one ``GridReads`` per
    grid, made at its first read."""

    def __init__(self, fused: WarpKernels, say: Callable[[str], None] = print) -> None:
        self.fused, self.say = fused, say
        self.grids: Dict[int, Optional[GridReads]] = {}

    def read(self, grid, coords: Tensor, stride: int, features: bool) -> Optional[Tensor]:
        """``GridReads.read`` of ``grid``; None where the kernels do not compile for its component counts (the
        caller reads with torch)."""
        if id(grid) not in self.grids:
            kernels = grid_read_kernels(self.fused, tuple(grid.components), self.say)
            self.grids[id(grid)] = None if kernels is None else GridReads(self.fused, grid, kernels)
        reads = self.grids[id(grid)]
        return None if reads is None else reads.read(coords, stride, features)

    def close(self) -> None:
        for reads in self.grids.values():
            if reads is not None:
                reads.close()
        self.grids = {}
