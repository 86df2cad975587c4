"""FrugalNeRF's training objective (paper Eq. 11), assembled in one place: each term is one named, weighted
line in ``training_losses``; the loss functions themselves are in ``losses.py``.

Weights follow the reference code: lower scales' colour terms weigh ``lower_scale_color_weight``; grid and
sample regularisers at scale l are divided by ratio^(2l) (16 and 256 for s = 4); the lower-scale colour,
TV, occlusion, smoothness, sparse and mono depth weights fall with the loss-weight schedule (``decay``, 1 at
the start) while the distortion weight grows with it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Callable, Dict, List, NamedTuple, Optional, Tuple

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor
from torch.profiler import record_function

from frugalnerf_ns.model import losses
from frugalnerf_ns.batch import NOVEL_RAYS, SPARSE_RAYS, TRAIN_RAYS, EvalBatch, TrainBatch
from frugalnerf_ns.field.outer_space import OuterSpace
from frugalnerf_ns.field.radiance_field import FrugalNeRFField
from frugalnerf_ns.model.geometric_adaptation import (
    AdaptationRays,
    AdaptationResult,
    ReferenceViews,
    cross_scale_geometric_adaptation,
    photometric_consistency as photometric_consistency_loss,
)
from frugalnerf_ns.geometry.scene_analysis import views_seeing
from frugalnerf_ns.scoring.metrics import composite
from frugalnerf_ns.model.rendering import StepRender

if TYPE_CHECKING:
    from frugalnerf_ns.model.config import FrugalNeRFSettings


def target_rgb(image: Tensor, background: Tensor) -> Float[Tensor, "rays 3"]:
    """Ground-truth colour; images with alpha are composited on the same background as the render."""
    if image.shape[-1] == 4:
        return composite(image[..., :3], image[..., 3:], background)
    return image[..., :3]


def train_rows(background: Tensor, batch: TrainBatch) -> Tensor:
    """The step's background for its training rays: the one colour, or the training rows of a per-ray one."""
    return background[batch.train] if background.dim() == 2 else background


def on_background(
    rgb: Float[Tensor, "rays 3"], accumulation: Float[Tensor, "rays 1"], rendered_on: Tensor, wanted: Tensor
) -> Float[Tensor, "rays 3"]:
    """A render composited on ``rendered_on`` as it would be on ``wanted``: the background contributes
    (1 - accumulation) of its colour (volume rendering's last term), so swap that share."""
    return rgb + (1.0 - accumulation) * (wanted - rendered_on)


def novel_view_source(
    rgb: Float[Tensor, "rays 3"], accumulation: Float[Tensor, "rays 1"], background: Tensor, white: Tensor
) -> Float[Tensor, "rays 3"]:
    """Eq. 6's source colour of novel-view rays: they have no photo, so their own full-scale render, detached
    (the warp's error trains depth, not colour), stands in for it. The training views it is compared with are
    composited on white, so the render is too: on a step's random background (black half the time) every ray
    with accumulation < 1 would otherwise count as a large error. A learned far background (one colour per ray,
    ``background`` of shape [rays, 3]) is the scene's own colour there: nothing to swap."""
    if background.dim() == 2:
        return rgb.detach()
    return on_background(rgb, accumulation, background, white).detach()


def scale_color_weights(cfg: "FrugalNeRFSettings", num_scales: int, decay: float) -> List[float]:
    """Eq. 1's per-scale weights: the full scale's, then each lower scale's (decaying with the schedule)."""
    return [cfg.full_scale_color_weight] + [cfg.lower_scale_color_weight * decay] * (num_scales - 1)


def color_read(
    cfg: "FrugalNeRFSettings", groups: Int[Tensor, " rays"], scale: int, occlusion_active: bool
) -> Optional[Bool[Tensor, " rays"]]:
    """The rays of a training bundle whose colour at ``scale`` a term of ``training_losses`` reads (None: all).

    Eq. 1 reads the training rays at every scale; Eq. 6 warps the novel rays' full-scale render (detached);
    the sparse-depth rays and the novel rays' lower scales feed only depth terms (L_sd, the depths of Eq. 6-9, depth
    smoothness), so their colours need not be shaded: skipping them changes no loss and no gradient. The
    occlusion loss with its background prior reads every ray's sample colours.
    """
    if _occlusion_reads_every_color(cfg, occlusion_active):
        return None
    if scale == 0:
        return groups != SPARSE_RAYS
    return groups == TRAIN_RAYS


def color_read_detached(
    cfg: "FrugalNeRFSettings", groups: Int[Tensor, " rays"], scale: int, occlusion_active: bool
) -> Optional[Bool[Tensor, " rays"]]:
    """The rays of ``color_read`` whose colour is read only detached (None: none): Eq. 6 warps the novel rays'
    full-scale render as a target (``geometric_adaptation``: ``source`` is detached), so no gradient flows
    back through their colour."""
    if scale != 0 or _occlusion_reads_every_color(cfg, occlusion_active):
        return None
    return groups == NOVEL_RAYS


def _occlusion_reads_every_color(cfg: "FrugalNeRFSettings", occlusion_active: bool) -> bool:
    """The occlusion loss's background prior reads every sample's colour, with gradient."""
    return occlusion_active and cfg.occlusion_weight > 0 and cfg.occlusion_background_prior


def depth_through_box(render: StepRender, scale: int, rows: slice) -> Tensor:
    """A scale's metric depth of the rays ``rows`` as L_sd compares it: the field's depth, and where the scene
    has a far background on a sphere, that sphere's distance behind it in the share the field lets through,
    acc * depth + (1 - acc) * d_sphere (volume rendering's last sample: the ray ends on the background). A point
    triangulated beyond the box then asks for a ray that crosses the box empty, which the field's depth alone,
    ending inside the box, can never give."""
    depth = render.metric_depths[scale][rows]
    if render.background_depth is None:
        return depth
    accumulation = render.scales[scale].accumulation[rows, 0]
    return accumulation * depth + (1.0 - accumulation) * render.background_depth[rows]


def uses_relative_sparse_depth(cfg: "FrugalNeRFSettings", room: bool) -> bool:
    """Whether L_sd weighs depth errors relative to each point's depth (``sparse_depth_error``; "auto": where the
    scene has the room beyond its box, ``room``: the model has a far background; the room's points lie 10-140
    units away)."""
    return cfg.sparse_depth_error == "relative" or (cfg.sparse_depth_error == "auto" and room)


def training_losses(
    cfg: "FrugalNeRFSettings",
    field_: FrugalNeRFField,
    render: StepRender,
    batch: TrainBatch,
    views: Optional[ReferenceViews],
    decay: float,
    occlusion_active: bool,
    adaptation: Optional[AdaptationResult] = None,
    room: bool = False,
    warps: bool = True,
) -> Dict[str, Tensor]:
    """Every term of the objective for one training step (nerfstudio sums them); ``adaptation``: this step's ``geometric_adaptation`` where the metrics computed it (else it
    is computed here); ``room``: the scene has the room beyond its box (``uses_relative_sparse_depth``); ``warps``: the
    split's ``warp_regime`` lets the warp losses act."""
    device = render.background.device
    target = target_rgb(batch.image.to(device), train_rows(render.background, batch))
    predictions = [scale.rgb[batch.train] for scale in render.scales]
    terms = {"rgb_loss": losses.multiscale_color_loss(predictions, target, scale_color_weights(cfg, len(predictions), decay))}
    with record_function("regularizers"):
        terms.update(grid_regularizers(cfg, field_, decay))
        terms.update(sample_regularizers(cfg, field_, render, decay, occlusion_active))
    if adaptation is None:
        adaptation = geometric_adaptation(cfg, render, batch, views, warps)
    if adaptation is not None:  # Eq. 10: training patches and novel rays
        train_weight, novel_weight = geo_weights(cfg, warps)
        if train_weight == novel_weight:  # one weight (the paper): the same float operations as before the split
            geo = train_weight * (adaptation.loss_train + adaptation.loss_novel)
        else:
            geo = train_weight * adaptation.loss_train + novel_weight * adaptation.loss_novel
        terms["geo_loss"] = geo
    if cfg.photometric_weight > 0 and views is not None and warps:
        with record_function("photometric_consistency"):
            terms["photometric"] = cfg.photometric_weight * photometric_consistency(cfg, render, batch, views)
    if cfg.sparse_depth_weight > 0 and batch.sparse_depth is not None:  # L_sd at every scale
        depth_error = losses.relative_disparity_loss if uses_relative_sparse_depth(cfg, room) else losses.inverse_depth_loss
        sparse = sum(
            depth_error(depth_through_box(render, scale, batch.sparse), batch.sparse_depth.to(device))
            for scale in range(len(render.scales))
        )
        terms["sparse_depth"] = cfg.sparse_depth_weight * decay * sparse
    if cfg.mono_depth_weight > 0 and batch.mono_depth is not None:  # L_d at every scale
        view = batch.indices[:, 0].to(device)
        mono = sum(losses.per_view_pearson_loss(d[batch.train], batch.mono_depth.to(device), view) for d in render.metric_depths)
        terms["mono_depth"] = cfg.mono_depth_weight * decay * mono
    if cfg.depth_smoothness_weight > 0 and batch.num_novel >= 4:
        terms["depth_smoothness"] = cfg.depth_smoothness_weight * decay * novel_depth_smoothness(field_, render, batch)
    return terms


def eval_losses(
    cfg: "FrugalNeRFSettings", field_: FrugalNeRFField, outputs: Dict[str, Tensor], batch: EvalBatch,
    background: Tensor, decay: float,
) -> Dict[str, Tensor]:
    """The terms an eval batch (single test pixels, no training context) can have: Eq. 1 over the scales
    that were rendered, and the grid regularisers."""
    from frugalnerf_ns.model.rendering import scale_suffix

    target = target_rgb(batch.image.to(background.device), background)
    rendered = [s for s in range(field_.num_scales) if f"rgb{scale_suffix(s)}" in outputs]
    weights = scale_color_weights(cfg, field_.num_scales, decay)
    terms = {
        "rgb_loss": losses.multiscale_color_loss(
            [outputs[f"rgb{scale_suffix(s)}"] for s in rendered], target, [weights[s] for s in rendered]
        )
    }
    terms.update(grid_regularizers(cfg, field_, decay))
    return terms


def grid_regularizers(cfg: "FrugalNeRFSettings", field_: FrugalNeRFField, decay: float) -> Dict[str, Tensor]:
    """TV on the appearance grid, edge-aware TV and L1 on the density grid, at every scale's view of them (each
    scale's term weighted by 1 / stride^2)."""
    terms: Dict[str, Tensor] = {}
    strides = [field_.stride(scale) for scale in range(field_.num_scales)]
    factors = [1.0 / stride**2 for stride in strides]
    density, appearance = field_.density_grid, field_.appearance_grid
    if cfg.appearance_tv_weight > 0:
        tv = losses.grid_tv_loss(appearance.planes, appearance.lines, cfg.tv_plane_weight, cfg.tv_line_weight,
                                 strides=strides, stride_weights=factors)
        terms["tv_appearance"] = cfg.appearance_tv_weight * decay * tv
    if cfg.density_tv_weight > 0:
        tv = losses.grid_tv_loss(density.planes, density.lines, cfg.tv_plane_weight, cfg.tv_line_weight,
                                 edge_planes=appearance.planes, strides=strides, stride_weights=factors)
        terms["tv_density"] = cfg.density_tv_weight * decay * tv
    if cfg.density_l1_weight > 0:
        for scale, stride in enumerate(strides):
            planes, lines = density.scale_views(stride)
            _add(terms, "l1_density", cfg.density_l1_weight * factors[scale] * losses.density_l1_loss(planes, lines))
    return terms


def outer_space_regularizers(cfg: "FrugalNeRFSettings", outer: OuterSpace, decay: float) -> Dict[str, Tensor]:
    """TV on the grids beyond the box, with the object grid's weights (the room seen from a few places needs the
    same smoothness prior as the object)."""
    terms: Dict[str, Tensor] = {}
    if cfg.appearance_tv_weight > 0:
        tv = losses.grid_tv_loss(outer.appearance_grid.planes, outer.appearance_grid.lines, cfg.tv_plane_weight,
                                 cfg.tv_line_weight)
        terms["tv_outer_appearance"] = cfg.appearance_tv_weight * decay * tv
    if cfg.density_tv_weight > 0:
        tv = losses.grid_tv_loss(outer.density_grid.planes, outer.density_grid.lines, cfg.tv_plane_weight,
                                 cfg.tv_line_weight)
        terms["tv_outer_density"] = cfg.density_tv_weight * decay * tv
    return terms


def sample_regularizers(
    cfg: "FrugalNeRFSettings", field_: FrugalNeRFField, render: StepRender, decay: float, occlusion_active: bool
) -> Dict[str, Tensor]:
    """Distortion (its weight grows with the schedule) and, for object scenes, occlusion, at every scale."""
    terms: Dict[str, Tensor] = {}
    for scale, scale_render in enumerate(render.scales):
        stride = field_.stride(scale)
        factor = 1.0 / stride**2
        if cfg.distortion_weight > 0:
            dist = losses.distortion_loss(scale_render.weights, scale_render.t, field_.sample_step(scale, cfg.step_ratio))
            _add(terms, "distortion", cfg.distortion_weight / decay * factor * dist)
        if cfg.occlusion_weight > 0 and occlusion_active:
            # Lower scales take proportionally fewer samples: the same distance from the camera.
            occ = losses.occlusion_loss(
                scale_render.densities,
                scale_render.colors if cfg.occlusion_background_prior else None,
                max(1, cfg.occlusion_near_samples // stride),
                max(1, cfg.occlusion_background_samples // stride),
                shaded=scale_render.shaded,
                num_slots=scale_render.slots,
            )
            _add(terms, "occlusion", cfg.occlusion_weight * decay * factor * occ)
    return terms


def novel_depth_smoothness(field_: FrugalNeRFField, render: StepRender, batch: TrainBatch) -> Tensor:
    """Depth smoothness of the novel rays' 2x2 patches at every scale (lower scales / ratio^2l), in the depth
    the field renders in (NDC t in NDC scenes)."""
    total = render.background.new_zeros(())
    for scale, scale_render in enumerate(render.scales):
        depth = scale_render.depth[batch.novel, 0]
        patches = depth[: batch.num_novel // 4 * 4].reshape(-1, 2, 2)
        total = total + losses.depth_smoothness_loss(patches) / field_.stride(scale) ** 2
    return total


def photometric_consistency(
    cfg: "FrugalNeRFSettings", render: StepRender, batch: TrainBatch, views: ReferenceViews
) -> Float[Tensor, ""]:
    """The photometric term (``geometric_adaptation.photometric_consistency``) on the step's training patches,
    at the full scale's metric depth with gradient."""
    rows = batch.train
    depth = render.metric_depths[0][rows]
    # The ray's own pixel centre (indices hold camera, row, column).
    indices = batch.indices.to(depth.device)
    return photometric_consistency_loss(
        render.origins[rows], render.directions[rows], depth, indices[:, 0].long(),
        indices[:, [2, 1]].to(depth.dtype) + 0.5, batch.nearest_view[rows], batch.patch_size,
        views, cfg.photometric_levels, cfg.photometric_max_error,
    )


PLAIN_FIT_SHARE_BEYOND_BOX = 0.5
"""``room_warp_losses`` "auto": the share of the training views' triangulated points lying beyond the subject's box
from which a split is fitted without the warp losses. Measured at start-up (docs/notes/captures.md, "Two regimes"):
the juice box's wide and 40-degree splits 0.74 and 0.72 (their room is what the photos share), the bird's 3- and
4-view splits 0.0 (its wall stands in the box)."""

PLAIN_FIT_MIN_POINTS = 10
"""Fewer triangulated points than this say nothing about where a split's content lies: "auto" keeps the warps."""


class WarpRegime(NamedTuple):
    """Whether the losses that warp pixels between training views act (L_geo, the photometric terms), and why, in
    words for the start-up summary."""

    warps: bool
    reason: str


def warp_regime(
    cfg: "FrugalNeRFSettings", room: bool, points_beyond_box: Optional[Tuple[int, int]] = None
) -> WarpRegime:
    """The regime of a split: cross-scale geometric adaptation (the paper's) or a plain fit of the photos.

    Only a scene with the room beyond its box (``room``: the model has a far background) can be fitted plainly.
    There L_geo compares each scale's depth *in the box* (Eq. 5, 9): where what the photos share lies beyond it (the
    room of a capture whose views are 25-45 degrees apart), agreeing scales ask for a surface in the box, and the
    room stays there as streaks (docs/notes/captures.md). ``room_warp_losses`` "on" / "off" force either; "auto"
    fits plainly where at least ``PLAIN_FIT_SHARE_BEYOND_BOX`` of the training views' triangulated points
    (``points_beyond_box``: (beyond, total), the datamanager's count) lie beyond the box. A bool (configs saved
    before "auto") reads as "on" / "off"."""
    mode = {True: "on", False: "off"}.get(cfg.room_warp_losses, cfg.room_warp_losses)  # type: ignore[arg-type]
    if not room:
        return WarpRegime(True, "")
    if mode == "on":
        return WarpRegime(True, "set by --pipeline.model.room-warp-losses")
    if mode == "off":
        return WarpRegime(False, "set by --pipeline.model.room-warp-losses")
    if points_beyond_box is None or points_beyond_box[1] < PLAIN_FIT_MIN_POINTS:
        found = "no" if points_beyond_box is None else f"only {points_beyond_box[1]}"
        return WarpRegime(True, f"{found} triangulated points to tell where the views' content lies")
    beyond, total = points_beyond_box
    share = f"{beyond} of the {total} points the training views triangulate lie beyond the box"
    if beyond >= PLAIN_FIT_SHARE_BEYOND_BOX * total:
        return WarpRegime(False, f"plain fit of the photos: {share}, where depths in the box cannot match them")
    return WarpRegime(True, f"geometric adaptation: {share}")


def carve_unseen_space(cfg: "FrugalNeRFSettings", ndc: bool, regime: WarpRegime) -> bool:
    """Whether the alpha mask empties the space no training camera sees (``carve_unseen``): never in NDC (its box
    is the training frusta), "auto" where the split is fitted plainly (``warp_regime``)."""
    if ndc or cfg.carve_unseen == "off":
        return False
    return cfg.carve_unseen == "on" or not regime.warps


def seen_by_training_views(
    cfg: "FrugalNeRFSettings", ndc: bool, regime: WarpRegime, views: Optional[ReferenceViews]
) -> Optional[Callable[[Tensor], Tensor]]:
    """points -> whether some training camera sees them, for the alpha mask to empty the rest, or None where it
    keeps them (``carve_unseen_space`` says so, or the training views are not known)."""
    if views is None or not carve_unseen_space(cfg, ndc, regime):
        return None
    height, width = views.images.shape[1:3]

    def seen(points: Tensor) -> Tensor:
        return views_seeing(points, views.camera_to_worlds, views.intrinsics, (width, height)) > 0

    return seen


def geo_weights(cfg: "FrugalNeRFSettings", warps: bool = True) -> Tuple[float, float]:
    """lambda_geo of Eq. 10's two summands (training patches, novel rays): geo_weight for both unless
    geo_novel_weight sets the novel rays' own; 0 for both where the split's ``warp_regime`` has no warps."""
    if not warps:
        return 0.0, 0.0
    novel = cfg.geo_weight if cfg.geo_novel_weight is None else cfg.geo_novel_weight
    return cfg.geo_weight, novel


def geometric_adaptation(
    cfg: "FrugalNeRFSettings", render: StepRender, batch: TrainBatch, views: Optional[ReferenceViews], warps: bool = True
) -> Optional[AdaptationResult]:
    """Eq. 2-9 on the step's training and novel rays (Eq. 6's source colour: ``novel_view_source``); the model
    computes it once a step, with the metrics, and hands it to the losses. None when lambda_geo is 0 (both
    summands; ``warps`` as in ``geo_weights``) or there are no training views to warp into."""
    if max(geo_weights(cfg, warps)) <= 0 or views is None:
        return None
    warped = batch.warped
    white = torch.ones(3, device=render.background.device)
    target = target_rgb(batch.image.to(white.device), white)
    full = render.scales[0]
    novel = novel_view_source(full.rgb[batch.novel], full.accumulation[batch.novel], render.background, white)
    source = torch.cat([target, novel])
    with record_function("geometric_adaptation"):
        rays = AdaptationRays(
            render.origins[warped],
            render.directions[warped],
            torch.stack([depth[warped] for depth in render.metric_depths]),
            torch.stack([scale.depth[warped, 0] for scale in render.scales]),
            source,
            batch.nearest_view,
            batch.num_train,
            batch.patch_size,
        )
        return cross_scale_geometric_adaptation(rays, views, cfg.reprojection_threshold)


def _add(terms: Dict[str, Tensor], name: str, value: Tensor) -> None:
    terms[name] = terms.get(name, 0.0) + value
