"""Fused kernels (NVIDIA Warp: written once, compiled at first use for the CPU by Warp's bundled Clang and for
CUDA by NVRTC) beside the torch code they replace, which stays the reference every kernel is tested against and
the fallback (``--pipeline.model.kernels``).

``density_march``: the density pass of ``rendering.render_scale_inference`` in one kernel, one thread per ray:
the slots of the ray's occupied groups in order, the box and alpha-mask test, the trilinear read of the baked
density grid (``BakedDensity.read``: grid_sample's corner-aligned, border-clamped rule), the activation, the
optical depth, the compositing weight from the summed optical depths, the faint-sample budget and the
termination, with the torch marcher's block structure (termination and the faint budget's running sum are
decided per block of ``per_block`` groups, as there). It writes each ray's accumulated weight and weighted t and
the samples to shade (t, weight) in the ray's share of one list; the colour MLP stays in torch. The torch marcher spends most of a
frame in a few dozen element-wise passes over every marched slot and in the bookkeeping of its packed rays;
here a slot costs one pass of registers and a ray stops where it terminates.

Warp's CPU kernels run on one thread, and here two Python threads launching halves of the rays took longer than one
(a fern frame's march 0.43 -> 0.52 s, its feature reads 0.37 -> 0.46 s): each kernel runs on one core while torch's
colour MLP uses all of them."""

from __future__ import annotations

import contextlib
import os
import sys
import threading
import time
from typing import Callable, Iterator, NamedTuple, Optional, Tuple

import torch
from torch import Tensor

from frugalnerf_ns.errors import UserError

_state: dict = {}
_lock = threading.Lock()


class WarpKernels(NamedTuple):
    """Warp (the module) and this file's kernels, compiled for the CPU: what ``warp_kernels`` hands the renderer."""

    wp: object
    kernels: dict


def _load_warp(say: Callable[[str], None]) -> WarpKernels:
    """Warp with this file's kernels compiled for the CPU, or raise with the reason. The kernel cache goes to the
    user's cache folder (``cache.user_cache_root``); a compile (first use of a Warp version) is said in one line
    with its seconds."""
    import warp as wp

    from frugalnerf_ns.cache import user_cache_root

    wp.config.kernel_cache_dir = str(user_cache_root() / "warp")
    wp.config.log_level = 30  # warnings only: no lines per module loaded
    wp.config.verbose_warnings = False
    with _native_stderr_silenced(not torch.cuda.is_available()):
        wp.init()  # without a GPU its driver probe writes a warning on the C stderr: nothing to tell
    kernels = _define_kernels(wp)
    start = time.perf_counter()
    wp.load_module(kernels["module"], device="cpu")
    seconds = time.perf_counter() - start
    if seconds > 0.5:
        say(f"frugalnerf: compiled the fused kernels in {seconds:.1f} s (once per Warp version; cached in "
            f"{wp.config.kernel_cache_dir})")
    return WarpKernels(wp, kernels)


@contextlib.contextmanager
def _native_stderr_silenced(enabled: bool) -> Iterator[None]:
    """File descriptor 2 pointed at the null device within the block (what C code prints there)."""
    if not enabled:
        yield
        return
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def warp_kernels(choice: str, say: Callable[[str], None] = print) -> Optional[WarpKernels]:
    """The compiled kernels for ``--pipeline.model.kernels`` ``choice`` (loaded once per process): None for
    "torch"; for "auto", None with one line when Warp cannot be imported or compiled; for "warp", that failure
    raises."""
    if choice == "torch":
        return None
    with _lock:
        if "warp" not in _state:
            try:
                _state["warp"] = _load_warp(say)
                _state["why"] = ""
            except Exception as err:  # noqa: BLE001 - any import or compile failure falls back to torch
                _state["warp"] = None
                _state["why"] = f"{type(err).__name__}: {err}".splitlines()[0]
                if choice == "auto":
                    say(f"frugalnerf: fused kernels unavailable ({_state['why']}): rendering with the torch path")
    if _state["warp"] is None and choice == "warp":
        raise UserError(f"--pipeline.model.kernels warp: Warp cannot be used here ({_state['why']})")
    return _state["warp"]


def _define_kernels(wp) -> dict:
    """Build the kernels (a function so that importing this module never imports warp)."""
    # Warp evaluates the kernels' annotations (strings under ``from __future__ import annotations``) in this
    # module's globals, some only when a caller is compiled: ``wp`` must be found there.
    globals()["wp"] = wp

    @wp.func
    def corners(coord: wp.float32, size: int):
        # One axis of a corner-aligned, border-clamped read ([-1, 1] over ``size`` entries): the lower entry, the
        # upper one and the weight toward it (tensorial._axis_corners' rule).
        f = wp.clamp((coord + 1.0) * 0.5 * float(size - 1), 0.0, float(size - 1))
        low = wp.min(int(wp.floor(f)), wp.max(size - 2, 0))
        return low, wp.min(low + 1, size - 1), f - float(low)

    @wp.func
    def read_density(grid: wp.array3d(dtype=wp.float32), p: wp.vec3, a: wp.vec3, b: wp.vec3, relu: int) -> wp.float32:
        # grid_sample, align_corners=True, padding_mode="border": coords (x, y, z) in [-1, 1] -> grid[z, y, x].
        x0, x1, tx = corners(p[0] * a[0] + b[0], grid.shape[2])
        y0, y1, ty = corners(p[1] * a[1] + b[1], grid.shape[1])
        z0, z1, tz = corners(p[2] * a[2] + b[2], grid.shape[0])
        c00 = grid[z0, y0, x0] * (1.0 - tx) + grid[z0, y0, x1] * tx
        c01 = grid[z0, y1, x0] * (1.0 - tx) + grid[z0, y1, x1] * tx
        c10 = grid[z1, y0, x0] * (1.0 - tx) + grid[z1, y0, x1] * tx
        c11 = grid[z1, y1, x0] * (1.0 - tx) + grid[z1, y1, x1] * tx
        raw = (c00 * (1.0 - ty) + c01 * ty) * (1.0 - tz) + (c10 * (1.0 - ty) + c11 * ty) * tz
        if relu != 0:
            return wp.max(raw, 0.0)
        x = raw - 10.0  # TensoRF's shifted softplus, as torch's (linear above 20)
        if x > 20.0:
            return x
        y = wp.exp(x)
        if y < 0.01:  # log(1 + y) by its series: 1 + y rounds away y's low bits in float32 (no log1p in Warp)
            return y - 0.5 * y * y + y * y * y / 3.0
        return wp.log(1.0 + y)

    @wp.func
    def occupied(p: wp.vec3, box_min: wp.vec3, box_max: wp.vec3, mask: wp.array(dtype=wp.uint8), has_mask: int,
                 mask_min: wp.vec3, mask_max: wp.vec3, mask_res: wp.vec3i, mask_strides: wp.vec3i) -> bool:
        # FrugalNeRFField.inside: the box, then the nearest voxel of the mask padded by one False voxel.
        for k in range(3):
            if p[k] < box_min[k] or p[k] > box_max[k]:
                return False
        if has_mask == 0:
            return True
        flat = int(0)
        for k in range(3):
            idx = int(wp.rint((p[k] - mask_min[k]) / (mask_max[k] - mask_min[k]) * float(mask_res[k] - 1)))
            idx = wp.min(wp.max(idx + 1, 0), mask_res[k] + 1)
            flat += idx * mask_strides[k]
        return mask[flat] != wp.uint8(0)

    @wp.func
    def group_can_hold(occupancy: wp.array(dtype=wp.uint8), entries: wp.vec3i, a: wp.vec3, b: wp.vec3,
                       to_index: wp.vec3, rounding: int, o: wp.vec3, d: wp.vec3, t: wp.float32) -> bool:
        # BakedDensity.occupied_groups' lookup of one group centre in one dilated volume.
        flat = int(0)
        scale = int(1)
        for k in range(3):
            f = (o[k] * a[k] + b[k] + 1.0) * to_index[k] + d[k] * a[k] * to_index[k] * t
            if rounding != 0:
                f = wp.rint(f)
            else:
                f = wp.floor(f)
            i = wp.min(int(wp.max(f, 0.0)), entries[k] - 1)
            flat += i * scale
            scale *= entries[k]
        return occupancy[flat] != wp.uint8(0)

    @wp.kernel
    def density_march(
        origins: wp.array(dtype=wp.vec3), directions: wp.array(dtype=wp.vec3),
        t_near: wp.array(dtype=wp.float32), t_far: wp.array(dtype=wp.float32),
        outputs_at: wp.array(dtype=wp.int32), num_groups: int, num_bounds: int,
        occupancy0: wp.array(dtype=wp.uint8), entries0: wp.vec3i, a0: wp.vec3, b0: wp.vec3, to_index0: wp.vec3,
        rounding0: int,
        occupancy1: wp.array(dtype=wp.uint8), entries1: wp.vec3i, a1: wp.vec3, b1: wp.vec3, to_index1: wp.vec3,
        rounding1: int,
        grid: wp.array3d(dtype=wp.float32), grid_a: wp.vec3, grid_b: wp.vec3, relu: int,
        box_min: wp.vec3, box_max: wp.vec3,
        mask: wp.array(dtype=wp.uint8), has_mask: int, mask_min: wp.vec3, mask_max: wp.vec3,
        mask_res: wp.vec3i, mask_strides: wp.vec3i,
        step: wp.float32, num_samples: int, group: int, per_block: int, delta: wp.float32,
        weight_threshold: wp.float32, faint_weight: wp.float32, faint_budget: wp.float32,
        stop_optical: wp.float32, max_optical: wp.float32,
        sums: wp.array2d(dtype=wp.float32), shade_t: wp.array(dtype=wp.float32), shade_w: wp.array(dtype=wp.float32),
    ):
        r = wp.tid()
        o = origins[r]
        d = directions[r]
        near = t_near[r]
        far = t_far[r]
        out = outputs_at[r]  # this ray's first row of the shade list (its marched slots bound its rows)
        optical_sum = wp.float32(0.0)
        accumulation = wp.float32(0.0)
        weighted_t = wp.float32(0.0)
        left = wp.float32(0.0)  # weight whose colour was left out (the faint budget)
        running = wp.float32(0.0)
        rank = int(0)
        count = int(0)
        for g in range(num_groups):
            # The group's first slot in the segment, and density possible somewhere in it (occupied_groups).
            wanted = near + (float(g * group) + 0.5) * step < far
            centre = near + (float(g * group) + 0.5 * float(group)) * step
            if wanted and num_bounds > 0:
                wanted = group_can_hold(occupancy0, entries0, a0, b0, to_index0, rounding0, o, d, centre)
            if wanted and num_bounds > 1:
                wanted = group_can_hold(occupancy1, entries1, a1, b1, to_index1, rounding1, o, d, centre)
            if wanted:
                if rank % per_block == 0:
                    if rank > 0 and optical_sum >= stop_optical:
                        break
                    running = left
                rank += 1
                for k in range(group):
                    i = g * group + k
                    t = near + (float(i) + 0.5) * step
                    if i < num_samples and t < far:
                        p = o + d * t
                        density = wp.float32(0.0)
                        if occupied(p, box_min, box_max, mask, has_mask, mask_min, mask_max, mask_res, mask_strides):
                            density = read_density(grid, p, grid_a, grid_b, relu)
                        tau = wp.clamp(density * delta, 0.0, max_optical)
                        w = (1.0 - wp.exp(-tau)) * wp.exp(-optical_sum)
                        optical_sum = optical_sum + tau
                        accumulation = accumulation + w
                        weighted_t = weighted_t + w * t
                        if w > weight_threshold:
                            shade = True
                            if faint_budget > 0.0 and w < faint_weight:
                                running = running + w
                                if running <= faint_budget:
                                    left = left + w
                                    shade = False
                            if shade:
                                shade_t[out + count] = t
                                shade_w[out + count] = w
                                count += 1
        sums[r, 0] = accumulation
        sums[r, 1] = weighted_t
        sums[r, 2] = float(count)

    @wp.func
    def contract_point(p: wp.vec3, centre: wp.vec3, half: wp.vec3) -> wp.vec3:
        # geometry.contraction.contract: box units, the box as it is, beyond it into [-2, 2]^3.
        q = wp.vec3((p[0] - centre[0]) / half[0], (p[1] - centre[1]) / half[1], (p[2] - centre[2]) / half[2])
        norm = wp.max(wp.max(wp.abs(q[0]), wp.abs(q[1])), wp.abs(q[2]))
        if norm > 1.0:
            return q * ((2.0 - 1.0 / norm) / norm)
        return q

    @wp.kernel
    def outer_composite(
        origins: wp.array(dtype=wp.vec3), directions: wp.array(dtype=wp.vec3),
        edges: wp.array2d(dtype=wp.float32), t: wp.array2d(dtype=wp.float32),
        table: wp.array2d(dtype=wp.float32), dims: wp.vec3i, centre: wp.vec3, half: wp.vec3,
        distance_scale: wp.float32, max_optical: wp.float32, sums: wp.array2d(dtype=wp.float32),
    ):
        # OuterSpace._composite outside training: each sample's share of the ray is its bin's length in the
        # contracted space; density and colour logits from the baked node table (trilinear_rows' rule).
        r = wp.tid()
        o = origins[r]
        d = directions[r]
        optical_sum = wp.float32(0.0)
        accumulation = wp.float32(0.0)
        red = wp.float32(0.0)
        green = wp.float32(0.0)
        blue = wp.float32(0.0)
        disparity = wp.float32(0.0)
        previous = contract_point(o + d * edges[r, 0], centre, half)
        for i in range(t.shape[1]):
            edge = contract_point(o + d * edges[r, i + 1], centre, half)
            delta = wp.length(edge - previous)
            previous = edge
            ti = t[r, i]
            c = contract_point(o + d * ti, centre, half) * 0.5  # [-2, 2] to the grid's [-1, 1]
            low = wp.vec3i(0, 0, 0)
            w = wp.vec3(0.0, 0.0, 0.0)
            for k in range(3):
                f = wp.min(wp.max((c[k] + 1.0) * 0.5 * float(dims[k] - 1), 0.0), float(dims[k] - 1))
                lo = wp.min(wp.floor(f), wp.max(float(dims[k] - 2), 0.0))
                low[k] = int(lo)
                w[k] = f - lo
            x_step = int(0)
            y_step = int(0)
            z_step = int(0)
            if dims[0] > 1:
                x_step = 1
            if dims[1] > 1:
                y_step = dims[0]
            if dims[2] > 1:
                z_step = dims[0] * dims[1]
            base = (low[2] * dims[1] + low[1]) * dims[0] + low[0]
            values = wp.vec4(0.0, 0.0, 0.0, 0.0)
            for ch in range(4):
                n0 = table[base, ch] + w[0] * (table[base + x_step, ch] - table[base, ch])
                n1 = table[base + y_step, ch] + w[0] * (table[base + y_step + x_step, ch] - table[base + y_step, ch])
                n2 = table[base + z_step, ch] + w[0] * (table[base + z_step + x_step, ch] - table[base + z_step, ch])
                n3 = table[base + z_step + y_step, ch] + w[0] * (
                    table[base + z_step + y_step + x_step, ch] - table[base + z_step + y_step, ch])
                near_z = n0 + w[1] * (n1 - n0)
                far_z = n2 + w[1] * (n3 - n2)
                values[ch] = near_z + w[2] * (far_z - near_z)
            density = wp.max(values[0], 0.0)
            tau = wp.clamp(density * delta * distance_scale, 0.0, max_optical)
            weight = (1.0 - wp.exp(-tau)) * wp.exp(-optical_sum)
            optical_sum = optical_sum + tau
            accumulation = accumulation + weight
            red = red + weight / (1.0 + wp.exp(-values[1]))
            green = green + weight / (1.0 + wp.exp(-values[2]))
            blue = blue + weight / (1.0 + wp.exp(-values[3]))
            disparity = disparity + weight / ti
        sums[r, 0] = accumulation
        sums[r, 1] = red
        sums[r, 2] = green
        sums[r, 3] = blue
        sums[r, 4] = disparity

    @wp.func
    def plane_line_product(plane: wp.array2d(dtype=wp.float32), width: int, height: int,
                           line: wp.array2d(dtype=wp.float32), x: wp.float32, y: wp.float32, z: wp.float32,
                           out: wp.array2d(dtype=wp.float32), row: int, offset: int):
        # sample_plane (bilinear, align_corners, border) times sample_line (linear) per component, channels last.
        x0, x1, tx = corners(x, width)
        y0, y1, ty = corners(y, height)
        z0, z1, tz = corners(z, line.shape[0])
        r00 = y0 * width + x0
        r01 = y0 * width + x1
        r10 = y1 * width + x0
        r11 = y1 * width + x1
        for c in range(plane.shape[1]):
            value = (plane[r00, c] * (1.0 - tx) + plane[r01, c] * tx) * (1.0 - ty) + (
                plane[r10, c] * (1.0 - tx) + plane[r11, c] * tx) * ty
            out[row, offset + c] = value * (line[z0, c] + tz * (line[z1, c] - line[z0, c]))

    @wp.kernel
    def vm_features(
        coords: wp.array(dtype=wp.vec3),
        plane0: wp.array2d(dtype=wp.float32), width0: int, height0: int, line0: wp.array2d(dtype=wp.float32),
        plane1: wp.array2d(dtype=wp.float32), width1: int, height1: int, line1: wp.array2d(dtype=wp.float32),
        plane2: wp.array2d(dtype=wp.float32), width2: int, height2: int, line2: wp.array2d(dtype=wp.float32),
        out: wp.array2d(dtype=wp.float32),
    ):
        # TensorVMGrid.plane_line_products, concatenated: planes XY, XZ, YZ with lines Z, Y, X (PLANE_AXES).
        i = wp.tid()
        c = coords[i]
        plane_line_product(plane0, width0, height0, line0, c[0], c[1], c[2], out, i, 0)
        plane_line_product(plane1, width1, height1, line1, c[0], c[2], c[1], out, i, plane0.shape[1])
        plane_line_product(plane2, width2, height2, line2, c[1], c[2], c[0], out, i, plane0.shape[1] + plane1.shape[1])

    return {"module": density_march.module, "density_march": density_march, "outer_composite": outer_composite,
            "vm_features": vm_features}


def _bytes(volume: Tensor) -> Tensor:
    """A bool volume as uint8 without a copy (the same bytes; a frame reads the same volumes once per chunk)."""
    volume = volume.contiguous()
    return volume.view(torch.uint8) if volume.dtype == torch.bool else volume.to(torch.uint8)


class MarchResult(NamedTuple):
    accumulation: Tensor
    weighted_t: Tensor
    rays: Tensor
    """Per sample to shade: its ray (index into the marched rays), its t and its weight, rays in order and each
    ray's samples in slot order (the order the torch marcher adds their colours in)."""
    t: Tensor
    weights: Tensor


def density_march(
    fused: WarpKernels, baked, aabb: Tensor, inside_mask: Optional[Tuple[Tensor, Tensor, Tensor, Tensor]],
    o: Tensor, d: Tensor, t_near: Tensor, t_far: Tensor, bounds: list,
    step: float, num_samples: int, group: int, per_block: int, delta: float, weight_threshold: float,
    faint_weight: float, faint_budget: float, stop_optical: float, max_optical: float,
) -> MarchResult:
    """Run ``density_march`` over the rays (float32, on the CPU). ``bounds``: the
    volumes a group is looked up in (``BakedDensity.group_bounds``, at most two); ``inside_mask``: (padded flat
    mask, its aabb, its unpadded shape, the padded strides) or None."""
    wp, kernel = fused.wp, fused.kernels["density_march"]
    rays = o.shape[0]
    num_groups = -(-num_samples // group)
    # A ray shades at most the slots of the groups that start in its segment (one more against rounding).
    in_segment = ((t_far - t_near) / step).floor().clamp(0, num_groups * group - 1).to(torch.int64) + 1
    bound = torch.minimum(-(-in_segment // group) * group, torch.tensor(num_groups * group))
    starts = torch.zeros(rays + 1, dtype=torch.int64)
    torch.cumsum(bound, 0, out=starts[1:])
    total = int(starts[-1])
    sums = torch.zeros(rays, 3, dtype=torch.float32)
    shade_t = torch.empty(max(total, 1), dtype=torch.float32)
    shade_w = torch.empty(max(total, 1), dtype=torch.float32)
    grid = baked.grid[0, 0].to(torch.float32).contiguous()
    grid_a, grid_b = (wp.vec3(*[float(v) for v in x]) for x in (baked.grid_a, baked.grid_b))
    if inside_mask is None:
        mask, has_mask = torch.zeros(1, dtype=torch.uint8), 0
        mask_min = mask_max = wp.vec3(0.0, 0.0, 0.0)
        res = strides = wp.vec3i(1, 1, 1)
    else:
        padded, mask_aabb, shape, pad_strides = inside_mask
        mask, has_mask = _bytes(padded), 1
        mask_min, mask_max = (wp.vec3(*[float(v) for v in x]) for x in (mask_aabb[0], mask_aabb[1]))
        res, strides = wp.vec3i(*[int(v) for v in shape]), wp.vec3i(*[int(v) for v in pad_strides])
    o, d = o.to(torch.float32).contiguous(), d.to(torch.float32).contiguous()
    t_near, t_far = t_near.to(torch.float32).contiguous(), t_far.to(torch.float32).contiguous()
    if len(bounds) > 2:
        raise ValueError(f"density_march reads at most two group bounds, got {len(bounds)}")
    volumes = {}
    for k in range(2):
        if k < len(bounds):
            bound_k = bounds[k]
            volume = _bytes(bound_k.occupancy)
            volumes.update({
                f"occupancy{k}": wp.from_torch(volume), f"entries{k}": wp.vec3i(*[int(v) for v in bound_k.entries]),
                f"a{k}": wp.vec3(*[float(v) for v in bound_k.a]), f"b{k}": wp.vec3(*[float(v) for v in bound_k.b]),
                f"to_index{k}": wp.vec3(*[float(v) for v in bound_k.to_index]), f"rounding{k}": int(bound_k.rounding),
                f"keep{k}": volume,  # alive while the kernel reads it
            })
        else:
            volumes.update({f"occupancy{k}": wp.from_torch(torch.zeros(1, dtype=torch.uint8)),
                            f"entries{k}": wp.vec3i(1, 1, 1), f"a{k}": wp.vec3(0.0, 0.0, 0.0),
                            f"b{k}": wp.vec3(0.0, 0.0, 0.0), f"to_index{k}": wp.vec3(0.0, 0.0, 0.0), f"rounding{k}": 0})
    outputs_at = starts[:-1].to(torch.int32)
    box_min, box_max = (wp.vec3(*[float(v) for v in x]) for x in (aabb[0], aabb[1]))
    shared = dict(
        grid=wp.from_torch(grid), grid_a=grid_a, grid_b=grid_b, relu=int(baked.activation == "relu"),
        num_groups=int(num_groups), num_bounds=len(bounds), **volumes,
        box_min=box_min, box_max=box_max, mask=wp.from_torch(mask), has_mask=has_mask, mask_min=mask_min,
        mask_max=mask_max, mask_res=res, mask_strides=strides, step=float(step), num_samples=int(num_samples),
        group=int(group), per_block=int(per_block), delta=float(delta), weight_threshold=float(weight_threshold),
        faint_weight=float(faint_weight), faint_budget=float(faint_budget), stop_optical=float(min(stop_optical, 3e38)),
        max_optical=float(max_optical), shade_t=wp.from_torch(shade_t),
        shade_w=wp.from_torch(shade_w),
    )

    if rays:
        inputs = dict(
            origins=wp.from_torch(o, dtype=wp.vec3), directions=wp.from_torch(d, dtype=wp.vec3),
            t_near=wp.from_torch(t_near), t_far=wp.from_torch(t_far), outputs_at=wp.from_torch(outputs_at),
            sums=wp.from_torch(sums),
        )
        wp.launch(kernel, dim=rays, inputs=_ordered(kernel, inputs, shared), device="cpu")
    if total == 0:
        empty = torch.zeros(0, dtype=torch.float32)
        return MarchResult(sums[:, 0], sums[:, 1], torch.zeros(0, dtype=torch.int64), empty, empty)
    # Each ray's rows are the first ``count`` of its share of the list: gathered in O(samples shaded).
    counts = sums[:, 2].to(torch.int64)
    shaded = int(counts.sum())
    ray_of_row = torch.repeat_interleave(torch.arange(rays), counts, output_size=shaded)
    first_of_ray = torch.cumsum(counts, 0) - counts
    rows = torch.arange(shaded) + (starts[:-1] - first_of_ray)[ray_of_row]
    return MarchResult(sums[:, 0], sums[:, 1], ray_of_row, shade_t[rows], shade_w[rows])


def _ordered(kernel, inputs: dict, shared: dict) -> list:
    """The kernel's arguments in its signature's order, from the per-launch and shared ones by name."""
    every = {**shared, **inputs}
    return [every[arg.label] for arg in kernel.adj.args]


def outer_composite(fused: WarpKernels, table: Tensor, dims, centre: Tensor, half: Tensor, origins: Tensor, directions: Tensor,
                    edges: Tensor, t: Tensor, distance_scale: float, max_optical: float) -> Tensor:
    """Run ``outer_composite`` (``OuterSpace._composite`` without gradients) over the rays on the CPU:
    [rays, 5] accumulation, colour sum (3), disparity sum."""
    wp, kernel = fused.wp, fused.kernels["outer_composite"]
    rays = origins.shape[0]
    sums = torch.zeros(rays, 5, dtype=torch.float32)
    o, d = origins.to(torch.float32).contiguous(), directions.to(torch.float32).contiguous()
    edges, t = edges.to(torch.float32).contiguous(), t.to(torch.float32).contiguous()
    table = table.to(torch.float32).contiguous()
    shared = [wp.from_torch(table), wp.vec3i(*[int(v) for v in dims]), wp.vec3(*[float(v) for v in centre]),
              wp.vec3(*[float(v) for v in half]), float(distance_scale), float(max_optical)]

    if rays:
        wp.launch(kernel, dim=rays, device="cpu", inputs=[
            wp.from_torch(o, dtype=wp.vec3), wp.from_torch(d, dtype=wp.vec3), wp.from_torch(edges), wp.from_torch(t),
            *shared, wp.from_torch(sums)])
    return sums


def channels_last(planes, lines) -> list:
    """Planes [1, C, H, W] and lines [1, C, L, 1] (strided views included) as the [H*W, C] and [L, C] tables
    ``vm_features`` reads (a corner's components side by side)."""
    tables = []
    for plane, line in zip(planes, lines):
        _, comps, height, width = plane.shape
        tables.append((plane[0].permute(1, 2, 0).reshape(height * width, comps).to(torch.float32).contiguous(),
                       width, height, line[0, :, :, 0].T.to(torch.float32).contiguous()))
    return tables


def vm_features(fused: WarpKernels, tables: list, coords: Tensor) -> Tensor:
    """``plane_line_products`` concatenated, at grid coordinates ``coords`` (already mapped for the stride), from
    ``channels_last`` tables, on the CPU."""
    wp, kernel = fused.wp, fused.kernels["vm_features"]
    n = coords.shape[0]
    out = torch.empty(n, sum(t[0].shape[1] for t in tables), dtype=torch.float32)
    coords = coords.to(torch.float32).contiguous()
    shared = [x for plane, width, height, line in tables for x in (wp.from_torch(plane), width, height, wp.from_torch(line))]

    if n:
        wp.launch(kernel, dim=n, device="cpu", inputs=[wp.from_torch(coords, dtype=wp.vec3), *shared, wp.from_torch(out)])
    return out
