"""Fused kernels (NVIDIA Warp: written once, compiled at first use for the CPU by Warp's bundled Clang and for
CUDA by NVRTC) beside the torch code they replace, which stays the reference every kernel is tested against and
the fallback (``--pipeline.model.kernels``).

``density_march``: the density pass of ``rendering.render_scale_inference`` in one kernel, one thread per ray:
the slots of the ray's occupied groups in order, the box and alpha-mask test, the trilinear read of the baked
density grid (``BakedDensity.read``: grid_sample's corner-aligned, border-clamped rule), the activation, the
optical depth, the compositing weight from the summed optical depths, the faint-sample budget and the
termination, with the torch marcher's rules (a ray ends at the slot where its transmittance falls below the
termination; the faint budget's running sum restarts per block of ``per_block`` groups, as there). It writes each
ray's accumulated weight and weighted t and the samples to shade (t, weight) in the ray's share of one list; the
colour MLP stays in torch. The torch marcher spends most of a frame in a few dozen element-wise passes over every
marched slot and in the bookkeeping of its packed rays; here a slot costs one pass of registers and a ray stops
where it terminates.

Every launch runs on its tensors' device (``launch``): the CPU, or a CUDA device on torch's stream. The model hands
the kernels over on the CPU only; ``bench/kernel_check.py`` runs them on a GPU beside the torch path.

Warp's CPU kernels run on one thread; a launch releases the GIL, so ``on_every_core`` runs launches on a pool of
torch's thread count. That pays only over many rays at once: two threads marching halves of each 4096-ray chunk were
slower than one launch (a fern frame 1.61 -> 2.06 s), because the colour MLP's OpenMP threads keep spinning on the
other core for a while after every matrix product. So outside training the model renders the CPU's frames in large
chunks (``rendering.FUSED_CHUNK_RAYS``): each marches all its rays in blocks of ``MARCH_BLOCK_RAYS`` over the pool
(``density_march_blocks``), then reads the features of its shaded samples in parts (``vm_features``)."""

from __future__ import annotations

import contextlib
from concurrent.futures import ThreadPoolExecutor
import os
import sys
import threading
import time
from typing import Callable, Iterator, NamedTuple, Optional, Tuple

import torch
from torch import Tensor

from frugalnerf_ns.errors import UserError
from frugalnerf_ns.field.fused_kernel_source import define_kernels, define_training_reads

_state: dict = {}
_lock = threading.Lock()

MARCH_BLOCK_RAYS = 4096
"""Rays per ``density_march`` launch in ``density_march_blocks``: a launch allocates each ray's upper bound of samples
to shade (up to ``num_samples`` floats twice per ray), so blocks keep that list to tens of MB at any chunk size."""

CUDA_MARCH_BLOCK_RAYS = 1 << 18
"""The same on a GPU, one block after another: enough rays per launch to fill the device."""

SPLIT_MIN_ROWS = 16384
"""``vm_features`` and ``outer_composite`` split their rows over the pool from this many (below it one launch costs
less than the hand-off)."""


def on_every_core(jobs: list) -> list:
    """The jobs' results, in order, run on a pool of ``torch.get_num_threads()`` threads (one: in this thread).
    For Warp launches on the CPU, which release the GIL and run on one core each."""
    workers = max(1, torch.get_num_threads())
    if workers == 1 or len(jobs) < 2:
        return [job() for job in jobs]
    with _lock:
        pool, size, pid = _state.get("pool", (None, 0, 0))
        # A new pool when torch's thread count changed since the last frame, or in a forked child (which has none
        # of its parent's threads).
        if pool is None or size != workers or pid != os.getpid():
            pool = _start_pool(workers)
            _state["pool"] = (pool, workers, os.getpid())
    return [future.result() for future in [pool.submit(job) for job in jobs]]


def _one_thread() -> None:
    """A pool thread's set-up: torch's own per-thread set-up first (it would otherwise run at the thread's first
    parallel operation and set the process-wide count again), then one thread for this thread's operations."""
    torch.get_num_threads()
    torch.set_num_threads(1)


def _start_pool(workers: int) -> ThreadPoolExecutor:
    """A pool of ``workers`` threads whose torch operations run on one OpenMP thread each. A pool thread running a
    parallel torch operation would otherwise lead an OpenMP team of its own; with more OpenMP threads than cores
    libgomp lets idle threads sleep sooner, and every later parallel region in the main thread pays for waking
    them (the torch path's fern frame went from ~3 to ~5 s after a frame on the pool)."""
    ready = threading.Barrier(workers + 1)
    pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="frugalnerf-fused", initializer=_one_thread)
    started = [pool.submit(ready.wait) for _ in range(workers)]  # every thread started and set up
    ready.wait()
    torch.set_num_threads(workers)  # torch's count for new threads is process-wide: back to this thread's
    for future in started:
        future.result()
    return pool


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
    kernels = define_kernels(wp)
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
                    say(f"frugalnerf: fused kernels unavailable ({_state['why']}): rendering and training on the torch path")
    if _state["warp"] is None and choice == "warp":
        raise UserError(f"--pipeline.model.kernels warp: Warp cannot be used here ({_state['why']})")
    return _state["warp"]


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
    rays, device = o.shape[0], o.device
    num_groups = -(-num_samples // group)
    # A ray shades at most the slots of the groups that start in its segment (one more against rounding).
    in_segment = ((t_far - t_near) / step).floor().clamp(0, num_groups * group - 1).to(torch.int64) + 1
    bound = torch.minimum(-(-in_segment // group) * group, torch.tensor(num_groups * group, device=device))
    starts = torch.zeros(rays + 1, dtype=torch.int64, device=device)
    torch.cumsum(bound, 0, out=starts[1:])
    total = int(starts[-1])
    sums = torch.zeros(rays, 3, dtype=torch.float32, device=device)
    shade_t = torch.empty(max(total, 1), dtype=torch.float32, device=device)
    shade_w = torch.empty(max(total, 1), dtype=torch.float32, device=device)
    grid = baked.grid[0, 0].to(torch.float32).contiguous()
    grid_a, grid_b = (wp.vec3(*[float(v) for v in x]) for x in (baked.grid_a, baked.grid_b))
    if inside_mask is None:
        mask, has_mask = torch.zeros(1, dtype=torch.uint8, device=device), 0
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
            volumes.update({f"occupancy{k}": wp.from_torch(torch.zeros(1, dtype=torch.uint8, device=device)),
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
        launch(fused, kernel, rays, _ordered(kernel, inputs, shared), device)
    if total == 0:
        empty = torch.zeros(0, dtype=torch.float32, device=device)
        return MarchResult(sums[:, 0], sums[:, 1], torch.zeros(0, dtype=torch.int64, device=device), empty, empty)
    # Each ray's rows are the first ``count`` of its share of the list: gathered in O(samples shaded).
    counts = sums[:, 2].to(torch.int64)
    shaded = int(counts.sum())
    ray_of_row = torch.repeat_interleave(torch.arange(rays, device=device), counts, output_size=shaded)
    first_of_ray = torch.cumsum(counts, 0) - counts
    rows = torch.arange(shaded, device=device) + (starts[:-1] - first_of_ray)[ray_of_row]
    return MarchResult(sums[:, 0], sums[:, 1], ray_of_row, shade_t[rows], shade_w[rows])


def density_march_blocks(fused: WarpKernels, baked, aabb: Tensor, inside_mask, o: Tensor, d: Tensor, t_near: Tensor,
                         t_far: Tensor, *settings) -> MarchResult:
    """``density_march`` over blocks of ``MARCH_BLOCK_RAYS`` rays on every core (``on_every_core``; on a GPU blocks
    of ``CUDA_MARCH_BLOCK_RAYS`` in turn), joined in ray order: the same result as one launch over all rays (each
    ray is marched on its own; ``settings`` — the group bounds and the rest of ``density_march``'s arguments — are
    the same for every block)."""
    block_rays = max(1, MARCH_BLOCK_RAYS if o.device.type == "cpu" else CUDA_MARCH_BLOCK_RAYS)
    starts = range(0, o.shape[0], block_rays)
    if len(starts) <= 1:
        return density_march(fused, baked, aabb, inside_mask, o, d, t_near, t_far, *settings)
    parts = run_jobs(o.device, [
        (lambda a=a: density_march(fused, baked, aabb, inside_mask, o[a:a + block_rays], d[a:a + block_rays],
                                   t_near[a:a + block_rays], t_far[a:a + block_rays], *settings))
        for a in starts])
    rays = [part.rays + a for part, a in zip(parts, starts)]
    return MarchResult(*(torch.cat(x) for x in ([p.accumulation for p in parts], [p.weighted_t for p in parts], rays,
                                                 [p.t for p in parts], [p.weights for p in parts])))


def launch(fused: WarpKernels, kernel, dim: int, inputs: list, device: torch.device) -> None:
    """``wp.launch`` on the tensors' ``device``: the CPU, or a CUDA device on torch's current stream there (ordered
    with torch's work on that stream, as a torch operation is)."""
    wp = fused.wp
    if device.type == "cuda":
        wp.launch(kernel, dim=dim, inputs=inputs, device=wp.device_from_torch(device),
                  stream=wp.stream_from_torch(torch.cuda.current_stream(device)))
    else:
        wp.launch(kernel, dim=dim, inputs=inputs, device="cpu")


def run_jobs(device: torch.device, jobs: list) -> list:
    """The jobs' results, in order: on the CPU on every core (``on_every_core``), on a GPU one after another (each
    launch fills the device)."""
    return on_every_core(jobs) if device.type == "cpu" else [job() for job in jobs]


def in_parts(device: torch.device, n: int, launch_part: Callable[[int, int], None],
             min_rows: Optional[int] = None) -> None:
    """``launch_part(a, b)`` over row ranges covering n rows: on the CPU one per core from ``min_rows`` rows
    (``_parts``, on ``on_every_core``), on a GPU one launch (the device runs its threads in parallel itself)."""
    ranges = _parts(n, min_rows) if device.type == "cpu" else [(0, n)] if n > 0 else []
    run_jobs(device, [(lambda a=a, b=b: launch_part(a, b)) for a, b in ranges])


def _ordered(kernel, inputs: dict, shared: dict) -> list:
    """The kernel's arguments in its signature's order, from the per-launch and shared ones by name."""
    every = {**shared, **inputs}
    return [every[arg.label] for arg in kernel.adj.args]


def outer_composite(fused: WarpKernels, table: Tensor, dims, centre: Tensor, half: Tensor, origins: Tensor, directions: Tensor,
                    edges: Tensor, t: Tensor, distance_scale: float, max_optical: float) -> Tensor:
    """Run ``outer_composite`` (``OuterSpace._composite`` without gradients) over the rays, on the CPU in one part
    per core from ``SPLIT_MIN_ROWS`` rays (``in_parts``): [rays, 5] accumulation, colour sum (3), disparity sum."""
    wp, kernel = fused.wp, fused.kernels["outer_composite"]
    rays, device = origins.shape[0], origins.device
    sums = torch.zeros(rays, 5, dtype=torch.float32, device=device)
    o, d = origins.to(torch.float32).contiguous(), directions.to(torch.float32).contiguous()
    edges, t = edges.to(torch.float32).contiguous(), t.to(torch.float32).contiguous()
    table = table.to(torch.float32).contiguous()
    shared = [wp.from_torch(table), wp.vec3i(*[int(v) for v in dims]), wp.vec3(*[float(v) for v in centre]),
              wp.vec3(*[float(v) for v in half]), float(distance_scale), float(max_optical)]

    def launch_part(a: int, b: int) -> None:
        launch(fused, kernel, b - a, [
            wp.from_torch(o[a:b], dtype=wp.vec3), wp.from_torch(d[a:b], dtype=wp.vec3), wp.from_torch(edges[a:b]),
            wp.from_torch(t[a:b]), *shared, wp.from_torch(sums[a:b])], device)

    in_parts(device, rays, launch_part)
    return sums


def channels_last(planes, lines) -> list:
    """Planes [1, C, H, W] and lines [1, C, L, 1] (strided views included) as the [H*W, C] and [L, C] tables
    ``vm_features`` reads (a corner's components side by side)."""
    tables = []
    for plane, line in zip(planes, lines):
        _, comps, height, width = plane.shape
        tables.append((_rows(plane[0].permute(1, 2, 0), height * width, comps), width, height,
                       _rows(line[0, :, :, 0].T, line.shape[2], comps)))
    return tables


def _rows(x: Tensor, rows: int, columns: int) -> Tensor:
    """``x`` as a contiguous float32 [rows, columns] with the strides (columns, 1), also for one column (which
    torch calls contiguous at any stride, and Warp does not read as a vector per row)."""
    return x.to(torch.float32).contiguous().reshape(-1).view(rows, columns)


def vm_features(fused: WarpKernels, tables: list, coords: Tensor) -> Optional[Tensor]:
    """``plane_line_products`` concatenated, at grid coordinates ``coords`` (already mapped for the stride), from
    ``channels_last`` tables (``grid_read_kernels``' ``feature_read``, at stride 1 on the copies of the scale's
    views); on the CPU from ``SPLIT_MIN_ROWS`` rows in one part per core (``in_parts``; each row is read on its own,
    so the parts give the rows one launch gives). None where the kernels for these component counts do not compile
    (said once; the caller reads the planes with torch)."""
    wp = fused.wp
    components = tuple(t[0].shape[1] for t in tables)
    compiled = grid_read_kernels(fused, components)
    if compiled is None:
        return None
    kernel, vectors, row = compiled["feature_read"], compiled["vectors"], compiled["row"]
    n, device = coords.shape[0], coords.device
    out = torch.empty(n, sum(components), dtype=torch.float32, device=device)
    coords = coords.to(torch.float32).contiguous()
    # The views' entries along x, y, z (XY is [Y, X], XZ [Z, X]) and the planes' widths (X, X, Y).
    (_, width_x, height_y, _), (_, _, height_z, _) = tables[0], tables[1]
    shared = [wp.vec3i(width_x, height_y, height_z), wp.vec3i(width_x, width_x, height_y), 1]
    shared += [wp.from_torch(t, dtype=vector) for (plane, _, _, line), vector in zip(tables, vectors) for t in (plane, line)]

    def launch_part(a: int, b: int) -> None:
        launch(fused, kernel, b - a,
               [wp.from_torch(coords[a:b], dtype=wp.vec3), *shared, wp.from_torch(out[a:b], dtype=row)], device)

    in_parts(device, n, launch_part)
    return out


def grid_read_kernels(fused: WarpKernels, components: tuple, say: Callable[[str], None] = print) -> Optional[dict]:
    """``define_training_reads``' kernels for planes of ``components`` channels (``compile_once``): the training reads
    of the density and features with their backward, and the renderer's feature read."""
    return compile_once(fused, ("grid_reads", components), lambda: define_training_reads(fused.wp, components),
                        f"fused grid reads for {components} channels", say)


def compile_once(fused: WarpKernels, key: tuple, define: Callable[[], dict], what: str,
                 say: Callable[[str], None] = print) -> Optional[dict]:
    """``define()``'s kernels (a dict holding them, or lists of them), each kernel's module compiled for the CPU once per
    process and ``key`` (Warp caches the build on disk); the first compile said in one line as ``_load_warp`` says
    the module's; None, said once, where they do not compile (the caller reads the planes with torch). ``what``
    names them in those lines."""
    with _lock:
        if key not in _state:
            try:
                start = time.perf_counter()
                compiled = define()
                parts = [k for part in compiled.values() for k in (part if isinstance(part, list) else [part])]
                for module in {id(k.module): k.module for k in parts if isinstance(k, fused.wp.Kernel)}.values():
                    fused.wp.load_module(module, device="cpu")
                seconds = time.perf_counter() - start
                if seconds > 0.5:
                    say(f"frugalnerf: compiled the {what} in {seconds:.1f} s (once per Warp version)")
            except Exception as err:  # noqa: BLE001 - any compile failure: the torch reads
                compiled = None
                say(f"frugalnerf: {what} unavailable ({type(err).__name__}: "
                    f"{str(err).splitlines()[0] if str(err) else ''}): reading the planes with torch")
            _state[key] = compiled
    return _state[key]


def _parts(n: int, min_rows: Optional[int] = None) -> list:
    """Row ranges [a, b) covering n rows: one per core from ``min_rows`` (default ``SPLIT_MIN_ROWS``) rows, else one
    (none for none)."""
    parts = max(1, torch.get_num_threads()) if n >= (SPLIT_MIN_ROWS if min_rows is None else min_rows) else 1
    bounds = [n * k // parts for k in range(parts + 1)]
    return [(a, b) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]
