"""Cross-scale geometric adaptation on one batch (paper Eq. 2-10), and its per-step statistics.

The datamanager lays the batch out as training rays in k x k patches followed by novel-view rays; this
module warps every ray at every scale into its nearest training view, picks each ray's pseudo depth and
returns L_geo(r_train) and L_geo(r_novel). The geometry itself is in ``reprojection.py``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Dict, List, NamedTuple

import torch
from jaxtyping import Float, Int
from torch import Tensor

from frugalnerf_ns.model import losses
from frugalnerf_ns.geometry.novel_views import nearest_other_view
from frugalnerf_ns.geometry.reprojection import (
    Warp,
    downsample_views,
    patch_reprojection_error,
    sample_images,
    select_pseudo_depth,
    warp_to_views,
)

ADAPTATION_METRIC = "geometric_adaptation"
"""Key of the step's ``AdaptationResult`` in the model's training metrics: computed once with the metrics, read by
the losses, taken out before the metrics are logged (it is not a number)."""


class ReferenceViews(NamedTuple):
    """The training views warps compare with, held once by the model (composited on white)."""

    images: Float[Tensor, "views height width 3"]
    camera_to_worlds: Float[Tensor, "views 3 4"]
    intrinsics: Float[Tensor, "views 4"]


class AdaptationRays(NamedTuple):
    """The rays of one step's cross-scale geometric adaptation: ``num_train`` patch-major training rays (patches
    of ``patch_size``^2 pixels), then novel-view rays."""

    origins: Float[Tensor, "rays 3"]
    directions: Float[Tensor, "rays 3"]
    metric_depths: Float[Tensor, "scales rays"]
    """Each scale's depth as metric distance along the unit world ray: where the warp places the points."""
    loss_depths: Float[Tensor, "scales rays"]
    """Each scale's depth as the model renders it (NDC depth in NDC scenes): what L_geo compares, so lambda_geo
    means what it does in the paper's TensoRF-based code."""
    source_colors: Float[Tensor, "rays 3"]
    """The training pixels' colours, then (Eq. 6) the novel rays' own detached render."""
    nearest_view: Int[Tensor, " rays"]
    """The training view each ray is warped into (-1: none)."""
    num_train: int
    patch_size: int


class AdaptationResult(NamedTuple):
    loss_train: Float[Tensor, ""]
    """Eq. 5: L_geo on training rays."""
    loss_novel: Float[Tensor, ""]
    """Eq. 9: L_geo on novel-view rays (0 without novel rays)."""
    chosen_scale: Int[Tensor, " rays"]
    """Scale whose depth became the pseudo ground truth, -1 where the ray was left out (error above the
    threshold, or no other training view to warp into)."""


def cross_scale_geometric_adaptation(
    rays: AdaptationRays, views: ReferenceViews, threshold: float
) -> AdaptationResult:
    """Eq. 2-10 on a batch of ``rays.num_train`` patch-major training rays followed by novel-view rays, each warped
    at every scale into its nearest one of ``views``.

    Training rays share their patch's error (supp. Sec. B); novel rays use single pixels. The novel rays' source
    colours must come detached (``AdaptationRays.source_colors``).
    """
    origins, directions, metric_depths, loss_depths, source_colors, nearest_view, num_train_rays, patch_size = rays
    images, camera_to_worlds, intrinsics = views
    num_scales, num_rays = metric_depths.shape
    usable = nearest_view >= 0
    target = nearest_view.clamp_min(0)
    warp = warp_to_views(
        origins.repeat(num_scales, 1),
        directions.repeat(num_scales, 1),
        metric_depths.detach().reshape(-1),  # the selection is made without gradient (Eq. 3-4)
        target.repeat(num_scales),
        images,
        camera_to_worlds,
        intrinsics,
    )
    colors = warp.colors.reshape(num_scales, num_rays, 3)
    valid = warp.valid.reshape(num_scales, num_rays)
    pixels = patch_size * patch_size
    num_patches = num_train_rays // pixels
    train_errors = patch_reprojection_error(
        source_colors[:num_train_rays].reshape(1, num_patches, pixels, 3),
        Warp(
            colors[:, :num_train_rays].reshape(num_scales, num_patches, pixels, 3),
            valid[:, :num_train_rays].reshape(num_scales, num_patches, pixels),
        ),
    ).repeat_interleave(pixels, dim=1)
    novel_errors = patch_reprojection_error(
        source_colors[num_train_rays:, None, :][None],
        Warp(colors[:, num_train_rays:, None], valid[:, num_train_rays:, None]),
    )
    errors = torch.cat([train_errors, novel_errors], dim=1)
    # Rays with no other training view to warp into never count as reliable.
    errors = torch.where(usable[None], errors, torch.full_like(errors, float("inf")))
    pseudo = select_pseudo_depth(errors, loss_depths, threshold)
    train, novel = slice(0, num_train_rays), slice(num_train_rays, num_rays)
    loss_train = losses.geometric_adaptation_loss(
        loss_depths[:, train], pseudo._replace(depth=pseudo.depth[train], reliable=pseudo.reliable[train])
    )
    loss_novel = losses.geometric_adaptation_loss(
        loss_depths[:, novel], pseudo._replace(depth=pseudo.depth[novel], reliable=pseudo.reliable[novel])
    )
    chosen = torch.where(pseudo.reliable, pseudo.scale, torch.full_like(pseudo.scale, -1))
    return AdaptationResult(loss_train, loss_novel, chosen)


def photometric_consistency(
    origins: Float[Tensor, "rays 3"],
    directions: Float[Tensor, "rays 3"],
    depth: Float[Tensor, " rays"],
    own_view: Int[Tensor, " rays"],
    own_pixels: Float[Tensor, "rays 2"],
    nearest_view: Int[Tensor, " rays"],
    patch_size: int,
    views: ReferenceViews,
    levels: int,
    max_error: float,
) -> Float[Tensor, ""]:
    """Not a paper term: ``losses.photometric_consistency_loss`` on patch-major training rays, averaged over
    ``levels`` image sizes (full, then 2x, 4x, ... averaged blocks: a depth a few pixels off still sees a slope).

    Each ray's point at ``depth`` (metric, with gradient) is warped into ``nearest_view`` and compared with its
    own view's colour at ``own_pixels`` (u, v) at the same level. A patch counts when every pixel lands inside
    the other image and its coarsest level's RMSE (Eq. 2's measure, detached) is at most ``max_error``: an
    occluded or unseen patch has no depth that explains it, and would only be pulled somewhere wrong.
    """
    images, camera_to_worlds, intrinsics = views
    pixels = patch_size * patch_size
    usable = (nearest_view >= 0).reshape(-1, pixels).all(dim=-1)
    compared = []
    for factor, level_images, level_intrinsics in view_pyramid(images, intrinsics, levels):
        warp = warp_to_views(origins, directions, depth, nearest_view.clamp_min(0), level_images, camera_to_worlds, level_intrinsics)
        source = sample_images(level_images, own_view, own_pixels / factor).colors
        compared.append((source.reshape(-1, pixels, 3), warp.colors.reshape(-1, pixels, 3), warp.valid.reshape(-1, pixels)))
    return mean_over_levels(compared, usable, max_error)


def view_pyramid(images: Float[Tensor, "views height width 3"], intrinsics: Float[Tensor, "views 4"], levels: int):
    """(factor, images, intrinsics) at the images' size and each coarser level of 2x averaged blocks."""
    for level in range(max(1, levels)):
        factor = 2**level
        yield (factor, *downsample_views(images, intrinsics, factor))


def mean_over_levels(compared, usable: Tensor, max_error: float) -> Float[Tensor, ""]:
    """``losses.photometric_consistency_loss`` averaged over the levels of ``compared`` ((source, warped, valid)
    per level, patch-major), on the ``usable`` patches whose coarsest level warps inside the image with an RMSE
    (Eq. 2's measure, detached) of at most ``max_error``."""
    source, warped, valid = compared[-1]
    error = patch_reprojection_error(source.detach(), Warp(warped.detach(), valid))
    kept = usable & valid.all(dim=-1) & (error <= max_error)
    return sum(losses.photometric_consistency_loss(s, w, kept) for s, w, _ in compared) / len(compared)


# Colours of the viewer's "pseudo_gt_scale" output: full scale red, scale 1 blue, scale 2 green, scale 3
# orange; rays left out (no scale within the threshold, or no training view to warp into) dark grey.
SCALE_CHOICE_COLORS = ((0.89, 0.10, 0.11), (0.22, 0.49, 0.72), (0.30, 0.69, 0.29), (1.00, 0.50, 0.00))
LEFT_OUT_COLOR = (0.15, 0.15, 0.15)


def pseudo_ground_truth_scale(
    origins: Float[Tensor, "rays 3"],
    directions: Float[Tensor, "rays 3"],
    metric_depths: Float[Tensor, "scales rays"],
    rendered_colors: Float[Tensor, "rays 3"],
    views: ReferenceViews,
    threshold: float,
) -> Int[Tensor, " rays"]:
    """Eq. 6-8 for any rays (a viewer or render camera): the scale whose depth would become each ray's
    pseudo ground truth, -1 where the ray would be left out.

    The rays are treated as novel-view rays: single pixels, the rendered colour as the source (Eq. 6),
    warped into the nearest training view that is not the ray's own camera.
    """
    # A render camera can sit in a training camera: "own" views are those within 1e-3 of the baseline.
    nearest = nearest_other_view(origins, views.camera_to_worlds[:, :3, 3], same_position_fraction=1e-3)
    rays = AdaptationRays(origins, directions, metric_depths, metric_depths, rendered_colors.detach(), nearest, 0, 1)
    return cross_scale_geometric_adaptation(rays, views, threshold).chosen_scale


def scale_choice_colors(chosen_scale: Int[Tensor, "*shape"]) -> Float[Tensor, "*shape 3"]:
    """One colour per chosen scale (``SCALE_CHOICE_COLORS``), ``LEFT_OUT_COLOR`` for -1."""
    palette = torch.tensor((LEFT_OUT_COLOR,) + SCALE_CHOICE_COLORS, device=chosen_scale.device)
    return palette[(chosen_scale + 1).clamp(0, len(SCALE_CHOICE_COLORS))]


def scale_statistics(chosen_scale: Int[Tensor, " rays"], num_scales: int) -> Dict[str, float]:
    """Fraction of rays whose pseudo depth came from each scale, and of rays left out (paper Fig.
    "Cross-scale geometric adaptation in training"); the fractions sum to 1."""
    total = max(1, chosen_scale.numel())
    # One count and one device-to-host copy per step (this runs every training step).
    counts = torch.bincount(chosen_scale.flatten() + 1, minlength=num_scales + 1).tolist()
    stats = {f"geo_scale{scale}_fraction": counts[scale + 1] / total for scale in range(num_scales)}
    stats["geo_left_out_fraction"] = counts[0] / total
    return stats


class ScaleFractionHistory:
    """Per-step scale fractions kept during training, written as JSON and a PNG plot."""

    def __init__(self) -> None:
        self.steps: List[int] = []
        self.rows: List[Dict[str, float]] = []

    def record(self, step: int, stats: Dict[str, float]) -> None:
        self.steps.append(step)
        self.rows.append(dict(stats))

    def write(self, folder: Path) -> Path:
        """Write ``geometric_adaptation.json`` and ``geometric_adaptation.png`` into ``folder``; returns the PNG."""
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        folder.mkdir(parents=True, exist_ok=True)
        (folder / "geometric_adaptation.json").write_text(json.dumps({"steps": self.steps, "stats": self.rows}))
        figure, axis = plt.subplots(figsize=(6, 3.5))
        keys = sorted({key for row in self.rows for key in row})
        for key in keys:
            label = key.replace("geo_", "").replace("_fraction", "").replace("scale", "scale ")
            axis.plot(self.steps, [row.get(key, float("nan")) for row in self.rows], label=label)
        axis.set_xlabel("training step")
        axis.set_ylabel("fraction of rays")
        axis.set_ylim(0, 1)
        axis.set_title("Pseudo-depth source per scale (cross-scale geometric adaptation)")
        axis.legend(loc="upper right", fontsize="small")
        figure.tight_layout()
        path = folder / "geometric_adaptation.png"
        figure.savefig(path, dpi=100)
        plt.close(figure)
        return path
