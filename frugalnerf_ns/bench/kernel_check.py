"""The fused kernels (NVIDIA Warp) against the torch path on one device: ``frugalnerf-bench gpu-check --parts kernels``.

The kernels launch on the tensors' device; the model hands them over on the CPU only (a GPU renders and trains on the
torch path). This part runs them on the GPU it is given, beside the torch path there, so the first lent GPU says
whether they compile under NVRTC, whether they compute the torch path's values and how long each takes:

  march     ``render_scale_inference`` of a random field with a dense slab over a haze (rays turn opaque half-way) and an
            alpha mask, on a grid too large to bake its features: the fused density march and feature reads against the
            torch marcher (pixels, the largest difference and PSNR between them), and their time per frame.
  reads     a training step's reads of the density and the appearance features at three scales, forward and backward
            (``FrugalNeRFField.fused_training_reads``) against torch's reads: values and the planes' and lines'
            gradients (largest difference relative to the largest entry), and their time.
  outer     the space beyond a box outside training (``OuterSpace.render``): the fused composite against torch's.

On the CPU (``--dry-run``) the same code runs at small sizes: it tests the part, not the GPU.
"""

from __future__ import annotations

import math
from typing import Any, Callable, Dict, List

import torch

from frugalnerf_ns.bench.device_probes import timed

AABB = ((-1.0, -1.2, -0.8), (1.0, 1.2, 0.8))
SETTINGS = dict(step_ratio=0.5, distance_scale=25.0, max_samples_per_ray=1024, weight_threshold=1e-4)
PIXEL_TOLERANCE = 1.0 / 255.0
GRADIENT_TOLERANCE = 1e-4  # relative to the gradient's largest entry: float32 sums in another order


def slab_field(resolution, device: torch.device, seed: int = 0):
    """A field whose rays turn opaque half-way (a dense slab across each axis' middle over a thin random haze), with
    its alpha mask, at the presets' component counts."""
    from frugalnerf_ns.field.radiance_field import FrugalNeRFField

    torch.manual_seed(seed)
    field = FrugalNeRFField(torch.tensor(AABB), tuple(resolution), density_components=(16, 4, 4),
                            appearance_components=(48, 12, 12), mlp_hidden_dim=128, mlp_implementation="torch")
    with torch.no_grad():
        for plane in field.density_grid.planes:
            plane.uniform_(0.0, 0.3)
        for line in field.density_grid.lines:
            line.uniform_(0.0, 0.3)
            middle = line.shape[2] // 2
            line[:, :, middle : middle + max(3, line.shape[2] // 16), :] += 6.0
    field = field.to(device)
    field.update_alpha_mask(SETTINGS["step_ratio"], SETTINGS["distance_scale"])
    return field


def front_rays(count: int, device: torch.device, seed: int = 1):
    """Rays from in front of the box into it (a twentieth pointing away: they miss it)."""
    generator = torch.Generator().manual_seed(seed)
    origins = torch.rand(count, 3, generator=generator) * 0.6 - 0.3 + torch.tensor([0.0, 0.0, 2.5])
    directions = torch.randn(count, 3, generator=generator) * 0.35 + torch.tensor([0.0, 0.0, -1.0])
    directions = directions / directions.norm(dim=-1, keepdim=True)
    directions[: count // 20] = torch.tensor([0.0, 0.0, 1.0])
    return origins.to(device), directions.to(device)


def _row(what: str, check: Callable[[], Dict[str, Any]]) -> Dict[str, Any]:
    row: Dict[str, Any] = {"part": "kernels", "preset": what}
    try:
        row.update(check())
    except Exception as err:  # a kernel that fails on this device is a row of the table, not the end of the check
        row.update({"ok": False, "error": f"{type(err).__name__}: {str(err).splitlines()[0][:200] if str(err) else ''}"})
    return row


def check_march(fused, device: torch.device, dry_run: bool) -> Dict[str, Any]:
    from frugalnerf_ns.field import radiance_field
    from frugalnerf_ns.geometry.raymarch import intersect_aabb
    from frugalnerf_ns.model.rendering import render_scale_inference

    resolution, count = ((24, 28, 20), 2000) if dry_run else ((320, 384, 256), 1 << 18)
    field = slab_field(resolution, device)
    origins, directions = front_rays(count, device)
    segments = intersect_aabb(origins, directions, field.aabb, 0.0)
    background = torch.tensor([0.2, 0.5, 1.0], device=device)
    low, bake = radiance_field.native_bfloat16, radiance_field.BAKED_FEATURES_MAX_ENTRIES
    radiance_field.native_bfloat16 = lambda: False  # float32 on both paths: the kernels' arithmetic, not the MLP's
    radiance_field.BAKED_FEATURES_MAX_ENTRIES = 0  # the features read from the planes (vm_features), as on large grids

    def render(kernels):
        with torch.no_grad():
            return render_scale_inference(field, origins, directions, 0, background, segments, **SETTINGS,
                                          kernels=kernels).rgb

    try:
        fast, reference = render(fused), render(None)
        repeats, warmup = (2, 1) if dry_run else (5, 2)
        s_torch = timed(lambda: render(None), device, repeats, warmup)
        s_fused = timed(lambda: render(fused), device, repeats, warmup)
    finally:
        radiance_field.native_bfloat16, radiance_field.BAKED_FEATURES_MAX_ENTRIES = low, bake
    largest = float((fast - reference).abs().max())
    mse = float(((fast - reference) ** 2).mean())
    return {"grid": list(resolution), "rays": count, "s_torch": s_torch, "s_fused": s_fused, "speedup": s_torch / s_fused,
            "max_difference": largest, "psnr_between": 10 * math.log10(1.0 / mse) if mse > 0 else float("inf"),
            "ok": largest < PIXEL_TOLERANCE and float(reference.std()) > 0.01}


def check_reads(fused, device: torch.device, dry_run: bool) -> Dict[str, Any]:
    resolution, count = ((24, 28, 20), 3000) if dry_run else ((320, 384, 256), 1 << 19)
    field = slab_field(resolution, device)
    generator = torch.Generator().manual_seed(2)
    low, high = field.aabb[0].cpu(), field.aabb[1].cpu()
    positions = (low + (high - low) * torch.rand(count, 3, generator=generator)).to(device)
    directions = torch.nn.functional.normalize(torch.randn(count, 3, generator=generator), dim=-1).to(device)
    parameters = [*field.density_grid.planes, *field.density_grid.lines, *field.appearance_grid.planes,
                  *field.appearance_grid.lines]
    weights = torch.rand(count, generator=generator).to(device)

    def step(kernels):
        for p in parameters:
            p.grad = None
        with field.fused_training_reads(kernels):
            loss = sum((field.density(positions, scale) * weights).sum() + field.color(positions, directions, scale).sum()
                       for scale in range(3))
        loss.backward()
        return [p.grad.clone() for p in parameters]

    fast, reference = step(fused), step(None)
    relative = max(float((a - b).abs().max()) / max(float(b.abs().max()), 1e-12) for a, b in zip(fast, reference))
    repeats, warmup = (2, 1) if dry_run else (10, 2)
    s_torch = timed(lambda: step(None), device, repeats, warmup)
    s_fused = timed(lambda: step(fused), device, repeats, warmup)
    return {"grid": list(resolution), "samples": count, "s_torch": s_torch, "s_fused": s_fused,
            "speedup": s_torch / s_fused, "max_relative_gradient_difference": relative,
            "ok": relative < GRADIENT_TOLERANCE}


def check_outer(fused, device: torch.device, dry_run: bool) -> Dict[str, Any]:
    from frugalnerf_ns.field.outer_space import OuterSpace

    resolution, count = (16, 2000) if dry_run else (128, 1 << 18)
    torch.manual_seed(3)
    outer = OuterSpace(torch.tensor(AABB), resolution=resolution).to(device)
    with torch.no_grad():
        for grid in (outer.density_grid, outer.appearance_grid):
            for tensor in (*grid.planes, *grid.lines):
                tensor.uniform_(0.0, 0.6)
    origins, directions = front_rays(count, device)

    def render(kernels):
        with torch.no_grad():
            front, behind = outer.render(origins, directions, False, 0.0, kernels)
            return torch.cat([front.rgb, behind.rgb, behind.accumulation.reshape(count, 1)], dim=-1)

    fast, reference = render(fused), render(None)
    largest = float((fast - reference).abs().max())
    repeats, warmup = (2, 1) if dry_run else (5, 2)
    s_torch = timed(lambda: render(None), device, repeats, warmup)
    s_fused = timed(lambda: render(fused), device, repeats, warmup)
    return {"grid": [resolution] * 3, "rays": count, "s_torch": s_torch, "s_fused": s_fused,
            "speedup": s_torch / s_fused, "max_difference": largest,
            "ok": largest < PIXEL_TOLERANCE and float(reference.std()) > 0.01}


def part_kernels(args, device: torch.device, scenes) -> List[Dict[str, Any]]:
    from frugalnerf_ns.field.fused_kernels import warp_kernels

    messages: List[str] = []
    fused = warp_kernels("auto", messages.append)
    if fused is None:
        return [{"part": "kernels", "ok": False, "error": " ".join(messages) or "Warp unavailable"}]
    rows = []
    for what, check in (("march", check_march), ("reads", check_reads), ("outer", check_outer)):
        print(f"gpu_check: kernels: {what} ...", flush=True)
        rows.append(_row(what, lambda check=check: check(fused, device, args.dry_run)))
    return rows
