"""FrugalNeRF model for nerfstudio: the config, the multi-scale field, and nerfstudio's model interface.

One training step reads in this order: ``get_outputs`` renders every scale of the batch's rays
(``rendering.py``) and keeps them in a ``StepRender``; ``get_metrics_dict`` and ``get_loss_dict`` take the
``TrainBatch`` from ``FrugalDataManager`` (``batch.py``) and assemble the objective (``objective.py``: Eq.
1 and 10-11, each term one weighted line; the loss functions are in ``losses.py``). Outside training the
model renders rgb / depth / accumulation per scale (plus the viewer's pseudo-GT scale map) and scores test
images (``image_scoring.py``). What happens at given steps (upsampling, alpha mask, loss-weight decay) is the
training schedule (``training_schedule.py``).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass, field
from typing import Callable, Dict, Iterator, List, Optional, Tuple, Type, Union

import torch
from jaxtyping import Float
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackAttributes
from nerfstudio.models.base_model import Model
from nerfstudio.utils.rich_utils import CONSOLE
from nerfstudio.viewer.viewer_elements import ViewerCheckbox
from torch import Tensor
from torch.nn import Parameter
from torch.profiler import record_function

from frugalnerf_ns.errors import UserError
from frugalnerf_ns.model import objective
from frugalnerf_ns.batch import RAY_GROUP, EvalBatch, TrainBatch
from frugalnerf_ns.field.far_background import FarBackground
from frugalnerf_ns.field.outer_space import OuterSpace, depth_through_outer_space
from frugalnerf_ns.field.grid_sizes import log_linear_voxel_counts, resolution_for_voxels, spanning_stride
from frugalnerf_ns.field.radiance_field import FrugalNeRFField
from frugalnerf_ns.model.geometric_adaptation import (ADAPTATION_METRIC, ReferenceViews, ScaleFractionHistory,
                                                      pseudo_ground_truth_scale, scale_choice_colors, scale_statistics)
from frugalnerf_ns.model.image_scoring import ImageScorer
from frugalnerf_ns.scoring.metrics import capped_psnr
from frugalnerf_ns.model.config import FrugalNeRFSettings
from frugalnerf_ns.geometry.ndc import metric_distance_from_ndc, rays_to_ndc
from frugalnerf_ns.geometry.raymarch import intersect_aabb
from frugalnerf_ns.field.fused_kernels import warp_kernels
from frugalnerf_ns.model.rendering import (FUSED_CHUNK_RAYS, StepRender, render_in_chunks, render_scale,
                                           render_scale_inference, scale_suffix)
from frugalnerf_ns.geometry.scene_analysis import grid_side_for_pixels
from frugalnerf_ns.model.training_schedule import ScheduleFactors, schedule_factors, schedule_length, training_callbacks


@dataclass
class FrugalNeRFModelConfig(FrugalNeRFSettings):
    """FrugalNeRF's settings (``model/config.py``) bound to the model they build."""

    _target: Type = field(default_factory=lambda: FrugalNeRFModel)


class FrugalNeRFModel(Model):
    """Weight-sharing multi-scale tensorial radiance field."""

    config: FrugalNeRFModelConfig

    def populate_modules(self) -> None:
        super().populate_modules()
        aabb = self.scene_box.aabb.float()
        resolution = resolution_for_voxels(
            self.config.initial_voxels,
            (aabb[1] - aabb[0]).tolist(),
            spanning_stride(self.config),
        )
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
            self.config.initial_voxels, self.final_voxels, len(self.config.upsample_at)
        )
        metadata = self.kwargs.get("metadata") or {}
        # Forward-facing dataparsers (LLFF, RealEstate) ask for NDC through their metadata.
        self.ndc: Optional[Dict[str, float]] = metadata.get("ndc")
        # A box that holds only the near part of the scene (LLFF layout or photos, cameras converging on an
        # object) comes with a far background: a colour per direction for the rays that leave it.
        self.far_background: Optional[FarBackground] = None
        self.outer_space: Optional[OuterSpace] = None
        if self.config.far_background and metadata.get("far_background"):
            # The sphere it lies on, when the datamanager's points beyond the box say how far it is.
            shell = scene.get("far_shell")
            centre, radius = (None, 0.0) if shell is None else (torch.as_tensor(shell[0]), float(shell[1]))
            if self.config.outer_space_resolution > 0:
                # The room as geometry beyond the box; the map behind it is at infinity (sky, far away).
                self.outer_space = OuterSpace(aabb, self.config.outer_space_resolution,
                                              num_samples=self.config.outer_space_samples,
                                              num_front_samples=self.config.outer_space_front_samples)
                centre, radius = None, 0.0
            self.far_background = FarBackground(tuple(self.config.far_background_resolution), centre, radius)
        # Geometric adaptation or a plain fit (objective.warp_regime), from the datamanager's count of the points.
        beyond = scene.get("points_beyond_box")
        self.warp_regime = objective.warp_regime(self.config, self.has_room, None if beyond is None else tuple(beyond))
        # Test-image scores (PSNR, SSIM, LPIPS, per scale): a plain object, so its LPIPS network stays out of
        # the module tree and out of every checkpoint.
        self.scorer = ImageScorer()
        self._register_load_state_dict_pre_hook(drop_metric_network_keys)
        self._register_load_state_dict_pre_hook(self._refuse_a_checkpoint_without_the_far_background)
        self._register_load_state_dict_pre_hook(self._keep_a_checkpoint_without_the_outer_space)
        # Scales rendered outside training; scoring tools set it to 1 (full scale only) to save time.
        self.num_rendered_scales: Optional[int] = None
        # The geometric adaptation's scale fractions of every training step (get_metrics_dict, at the batch's step).
        self.scale_history = ScaleFractionHistory()
        # Progress lines of a video render (frames, fps, ETA), set by the ns-render hook in video.py.
        self.frame_progress = None
        # Steps of the run's schedule (the trainer's, known when the training callbacks are made; None without a
        # trainer): the loss weights decay along it, computed from each batch's step (``schedule``).
        self.schedule_length: Optional[int] = None
        # The training views every warp compares with: geometric adaptation in training and the pseudo-GT
        # scale map outside it (set_reference_views).
        self.reference_views: Optional[ReferenceViews] = None
        # Viewer panel ("Custom Elements"): the lower scales (and the scale map, which needs them) cost most of
        # a frame's render time on a CPU, so there they start off; on a GPU they start on.
        on_gpu = torch.cuda.is_available()
        self.viewer_lower_scales = ViewerCheckbox(
            "Render lower scales", on_gpu, hint="Render every scale (rgb/depth per scale, pseudo-GT scale map); "
            "off renders only the full scale, faster on a CPU (off by default there)."
        )
        # None: the map is rendered only for a viewer (checkbox on); True/False force it (tests, benchmarks).
        # ns-eval and evaluation during training never show it, so they do not pay for it.
        self.render_scale_map: Optional[bool] = None
        self.viewer_scale_map = ViewerCheckbox(
            "Pseudo-GT scale map", on_gpu, hint="Output pseudo_gt_scale: which scale's depth the geometric "
            "adaptation would take (red full, blue 1, green 2, grey left out)."
        )

    def set_reference_views(
        self,
        images: Float[Tensor, "views height width 3"],
        camera_to_worlds: Float[Tensor, "views 3 4"],
        intrinsics: Float[Tensor, "views 4"],
    ) -> None:
        """Training views that geometric adaptation and the pseudo-GT scale map warp into (FrugalPipeline
        calls this at set-up; without them L_geo is off). Kept out of the state dict: they come from the data,
        not from training."""
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
    def grid_resolution(self, num_voxels: int) -> Tuple[int, int, int]:
        """Grid resolution for ``num_voxels`` over the field's current box (``resolution_for_voxels``)."""
        box = (self.field.aabb[1] - self.field.aabb[0]).tolist()
        return resolution_for_voxels(num_voxels, box, spanning_stride(self.config))

    def _refuse_a_checkpoint_without_the_far_background(self, state_dict, prefix, *args) -> None:
        """Loading hook: a checkpoint trained without a far background cannot fill this model's. nerfstudio's
        pipeline retries a failed strict load without strictness, so the NDC grid of a run saved before its
        layout got the box (LLFF splits, photos) would render silently in the metric box instead: stop with one
        line instead. (torch visits every module of a tree with whatever part of the dict is loaded, the
        pipeline's own keys too: only a dict that holds this model's field is a checkpoint of it.)"""
        if self.far_background is None or not any(k.startswith(f"{prefix}field.") for k in state_dict):
            return
        if not any(k.startswith(f"{prefix}far_background.") for k in state_dict):
            raise UserError(FAR_BACKGROUND_MISSING)

    def _keep_a_checkpoint_without_the_outer_space(self, state_dict, prefix, *args) -> None:
        """Loading hook: a run trained before the space beyond the box became geometry has only the direction
        map (on its sphere). It loads as it was trained: this model's outer space is filled with its own initial
        values and switched off (``OuterSpace.active``), the map keeps the checkpoint's sphere."""
        if self.outer_space is None or not any(k.startswith(f"{prefix}field.") for k in state_dict):
            return
        if any(k.startswith(f"{prefix}outer_space.") for k in state_dict):
            return
        for key, value in self.outer_space.state_dict().items():
            state_dict[f"{prefix}outer_space.{key}"] = value
        state_dict[f"{prefix}outer_space.active"] = torch.tensor(False)
        CONSOLE.print("this run was trained before the space beyond its box was modelled: it renders as trained, "
                      "with the colour-by-direction map only")

    def get_param_groups(self) -> Dict[str, List[Parameter]]:
        # The far background is a texture like the grid's planes: it learns at their rate, as do the outer grids.
        far = [] if self.far_background is None else list(self.far_background.parameters())
        outer_grids = outer_nets = []
        if self.outer_space is not None:
            outer_grids, outer_nets = self.outer_space.grid_parameters(), self.outer_space.network_parameters()
        return {"encodings": self.field.grid_parameters() + far + outer_grids,
                "fields": self.field.network_parameters() + outer_nets}

    def get_training_callbacks(self, training_callback_attributes: TrainingCallbackAttributes) -> List[TrainingCallback]:
        self.schedule_length = schedule_length(training_callback_attributes)
        return training_callbacks(self, training_callback_attributes)

    def schedule(self, step: Optional[int]) -> ScheduleFactors:
        """The decaying loss weights' factors at ``step`` of this run's schedule (all 1 without one)."""
        return schedule_factors(self.config, step, self.schedule_length)

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

    def get_outputs(self, ray_bundle: RayBundle) -> Dict[str, Union[Tensor, StepRender]]:
        shape = ray_bundle.origins.shape[:-1]
        world_origins = ray_bundle.origins.reshape(-1, 3)
        world_directions = ray_bundle.directions.reshape(-1, 3)
        origins, directions, ndc_rays = world_origins, world_directions, None
        if self.ndc is not None:
            ndc_rays = rays_to_ndc(origins, directions, **self.ndc)
            origins, directions = ndc_rays.origins, ndc_rays.directions
        far_depth = None  # where each ray meets the far background's sphere (None: no sphere)
        front = behind = None  # the space outside the box in front of it and behind it (None: not modelled)
        if self.outer_space is not None and self.outer_space.is_active:
            kernels = None if self.training or torch.is_grad_enabled() else self._cpu_kernels(world_origins)
            front, behind = self.outer_space.render(world_origins, world_directions, self.training, self.config.near_plane,
                                                    kernels)
            # Behind the box: the outside, then what it lets through falls on the map at infinity.
            far_map = self.far_background(world_origins, world_directions)  # type: ignore[misc]
            background = behind.rgb + (1.0 - behind.accumulation[:, None]) * far_map
        elif self.far_background is not None:
            far_depth = self.far_background.distance(world_origins, world_directions)
            background = self.far_background(world_origins, world_directions, far_depth)  # per ray, where it meets the map
        else:
            background = self._background(origins.device)
        # All scales march the same box: intersect once.
        segments = intersect_aabb(origins, directions, self.field.aabb, self.config.near_plane)
        cfg = self.config
        renders, metric_depths = [], []
        outputs: Dict[str, Union[Tensor, StepRender]] = {}
        # Without gradients outside training (ns-eval, ns-render, the viewer) only pixels are wanted: the
        # blocked marcher with early termination renders them; training keeps every sample for its losses.
        inference = not self.training and not torch.is_grad_enabled() and self.config.fast_inference
        # A training bundle names each ray's group: colours that no loss reads are not shaded.
        groups = ray_bundle.metadata.get(RAY_GROUP) if self.training and ray_bundle.metadata else None
        groups = None if groups is None else groups.reshape(-1)
        # A training step on the CPU reads a large grid's planes with the fused kernels where they compile, else
        # density from nodes shared by its scales (outside training the marcher bakes them).
        training = self.training and not inference
        read_kernels = self._cpu_kernels(origins) if training and self.field.fused_reads_pay() else None
        shared_nodes = training and cfg.training_density_read == "nodes" and read_kernels is None
        with self.field.shared_density_nodes(shared_nodes), self.field.fused_training_reads(read_kernels):
            for scale in range(self._scales_to_render()):
                with record_function(f"render_scale{scale}"):  # named stages for torch.profiler (frugalnerf-bench profile)
                    args = (self.field, origins, directions, scale, background, segments, cfg.step_ratio,
                            cfg.distance_scale, cfg.max_samples_per_ray, cfg.weight_threshold)
                    if inference:
                        render = render_scale_inference(*args, kernels=self._cpu_kernels(origins))
                    else:
                        shade = detached = None
                        if groups is not None:
                            shade = objective.color_read(cfg, groups, scale, self.occlusion_active)
                            detached = objective.color_read_detached(cfg, groups, scale, self.occlusion_active)
                        render = render_scale(*args, jitter=self.training, shade_rays=shade, detached_rays=detached)
                depth = render.depth[:, 0]
                if ndc_rays is not None:
                    # Depth is reported as metric distance along the world ray (viewer, warping, sparse depth).
                    depth = metric_distance_from_ndc(depth, ndc_rays, self.ndc["near"])
                if front is not None and behind is not None:
                    # The whole ray: the outside in front of the box, the box, the outside behind it.
                    depth = depth_through_outer_space(front, render.accumulation[:, 0], depth, behind)
                    render = render._replace(rgb=front.rgb + (1.0 - front.accumulation[:, None]) * render.rgb)
                renders.append(render)
                metric_depths.append(depth)
                suffix = scale_suffix(scale)
                outputs[f"rgb{suffix}"] = render.rgb.reshape(*shape, 3)
                outputs[f"depth{suffix}"] = depth.reshape(*shape, 1)
                outputs[f"accumulation{suffix}"] = render.accumulation.reshape(*shape, 1)
        if self.training:
            # Everything the losses need, in one typed object (not a tensor: nerfstudio's loops skip it).
            outer_distortion = None if front is None else (front.distortion + behind.distortion).mean()  # type: ignore[union-attr]
            outputs["step"] = StepRender(background, world_origins, world_directions, renders, metric_depths, far_depth,
                                         outer_distortion=outer_distortion)
        elif len(renders) == self.field.num_scales > 1 and self.reference_views is not None and self._scale_map_wanted():
            chosen = pseudo_ground_truth_scale(
                world_origins, world_directions, torch.stack(metric_depths), outputs["rgb"].reshape(-1, 3),
                self.reference_views, cfg.reprojection_threshold,
            )
            outputs["pseudo_gt_scale"] = scale_choice_colors(chosen).reshape(*shape, 3)
        return outputs

    def _cpu_kernels(self, origins: Tensor):
        """The fused kernels where the rays are on the CPU and they compile; on a GPU none (it takes the torch path)."""
        return warp_kernels(self.config.kernels, CONSOLE.print) if origins.is_cpu else None

    def get_outputs_for_camera_ray_bundle(self, camera_ray_bundle: RayBundle) -> Dict[str, Tensor]:
        """nerfstudio's chunked render; where the fused kernels render on the CPU, in chunks of at least
        ``FUSED_CHUNK_RAYS`` (a chunk marches on every core; its memory per ray is small)."""
        if self.training or not self.config.fast_inference or self.device.type != "cpu" or \
                self.field.baked_density(0) is None or warp_kernels(self.config.kernels, CONSOLE.print) is None:
            return super().get_outputs_for_camera_ray_bundle(camera_ray_bundle)
        with torch.no_grad():
            return render_in_chunks(self, camera_ray_bundle, max(self.config.eval_num_rays_per_chunk, FUSED_CHUNK_RAYS))

    def get_outputs_for_camera(self, camera, obb_box=None) -> Dict[str, Tensor]:
        outputs = super().get_outputs_for_camera(camera, obb_box=obb_box)
        if self.frame_progress is not None:  # a video being rendered (video.teach_ns_render_spiral)
            self.frame_progress.tick()
        return outputs

    def _scales_to_render(self) -> int:
        """Training renders every scale (every loss needs them). Outside it: what a tool asked for
        (``num_rendered_scales``); in the viewer, its "Render lower scales" checkbox; the pseudo-GT scale map
        needs every scale; anything else (ns-eval, ns-render, evaluation during training) renders the full
        scale only unless ``eval_all_scales``: the metrics and videos read nothing else."""
        if self.training:
            return self.field.num_scales
        if self.num_rendered_scales is not None:
            return min(self.field.num_scales, self.num_rendered_scales)
        if self.viewer_lower_scales.gui_handle is not None:
            return self.field.num_scales if self.viewer_lower_scales.value else 1
        if self.render_scale_map or self.config.eval_all_scales:
            return self.field.num_scales
        return 1

    def seen_by_training_views(self) -> Optional[Callable[[Tensor], Tensor]]:
        """For the alpha mask (``training_schedule``): ``objective.seen_by_training_views`` of this model's views."""
        return objective.seen_by_training_views(self.config, self.ndc is not None, self.warp_regime, self.reference_views)

    @property
    def has_room(self) -> bool:
        """An object in a metric box with the room beyond it (the scene has a far background: photos circling their
        subject); some losses weigh differently there (``objective.geo_weights``, ``uses_relative_sparse_depth``)."""
        return self.far_background is not None

    # ---- losses and metrics -----------------------------------------------------------------------------
    def get_metrics_dict(self, outputs, batch: Union[TrainBatch, EvalBatch]) -> Dict[str, Tensor]:
        metrics: Dict[str, Tensor] = {}
        if isinstance(batch, TrainBatch):
            step: StepRender = outputs["step"]
            target = objective.target_rgb(batch.image.to(self.device), objective.train_rows(step.background, batch))
            for scale, render in enumerate(step.scales):
                metrics[f"psnr{scale_suffix(scale)}"] = capped_psnr(render.rgb[batch.train].detach(), target)
            adaptation = objective.geometric_adaptation(self.config, step, batch, self.reference_views,
                                                        self.warp_regime.warps)
            if adaptation is not None:
                stats = scale_statistics(adaptation.chosen_scale, self.field.num_scales)
                self.scale_history.record(0 if batch.step is None else batch.step, stats)
                metrics.update({name: torch.tensor(value) for name, value in stats.items()})
                # Handed to get_loss_dict with the metrics, as nerfacto hands its terms (computed once a step);
                # FrugalPipeline takes it out before the metrics are logged.
                metrics[ADAPTATION_METRIC] = adaptation  # type: ignore[assignment]
            return metrics
        target = objective.target_rgb(_check_batch(batch).image.to(self.device), self._eval_background())
        for scale in range(self.field.num_scales):
            if f"rgb{scale_suffix(scale)}" in outputs:
                metrics[f"psnr{scale_suffix(scale)}"] = capped_psnr(outputs[f"rgb{scale_suffix(scale)}"].detach(), target)
        return metrics

    def get_loss_dict(self, outputs, batch: Union[TrainBatch, EvalBatch], metrics_dict=None) -> Dict[str, Tensor]:
        factors = self.schedule(batch.step if isinstance(batch, TrainBatch) else _check_batch(batch).step)
        decay = factors.loss
        if isinstance(batch, TrainBatch):
            step: StepRender = outputs["step"]
            adaptation = (metrics_dict or {}).get(ADAPTATION_METRIC)
            if adaptation is None:  # called without this step's metrics
                adaptation = objective.geometric_adaptation(self.config, step, batch, self.reference_views,
                                                            self.warp_regime.warps)
            terms = objective.training_losses(
                self.config, self.field, step, batch, self.reference_views, decay, self.occlusion_active,
                adaptation=adaptation,
                room=self.has_room, warps=self.warp_regime.warps,
            )
            if self.outer_space is not None and self.outer_space.is_active:
                terms.update(objective.outer_space_regularizers(self.config, self.outer_space, decay))
                distortion = outputs["step"].outer_distortion
                if self.config.outer_distortion_weight > 0 and distortion is not None:
                    terms["outer_distortion"] = self.config.outer_distortion_weight * distortion
            return terms
        return objective.eval_losses(self.config, self.field, outputs, _check_batch(batch), self._eval_background(), decay)

    def get_rgba_image(self, outputs: Dict[str, Tensor], output_name: str = "rgb") -> Tensor:
        """RGB with the accumulation as alpha (ns-export and ns-render's rgba; nerfstudio's default reads a
        renderer module this model does not have)."""
        return torch.cat([outputs[output_name], outputs[output_name.replace("rgb", "accumulation")]], dim=-1)

    def lpips(self, images_0: Tensor, images_1: Tensor) -> Optional[Tensor]:
        """LPIPS distance (``ImageScorer.lpips``); None when LPIPS is unavailable."""
        return self.scorer.lpips(images_0, images_1)

    def get_image_metrics_and_images(
        self, outputs: Dict[str, Tensor], batch: Dict[str, Tensor]
    ) -> Tuple[Dict[str, float], Dict[str, Tensor]]:
        image = objective.target_rgb(batch["image"].to(self.device), self._eval_background())
        mask = batch.get("eval_mask")
        return self.scorer.metrics_and_images(outputs, image, None if mask is None else mask.to(self.device),
                                              self.field.num_scales)


FAR_BACKGROUND_MISSING = (
    "this run's checkpoint has no far background, but its data is now modelled in a box around the cameras' focus "
    "with one (a split that is not forward-facing, read by a parser whose rule changed after the run was saved: it "
    "was trained in NDC); set `ndc: true` under the dataparser in the run's config.yml to load it as it was "
    "trained, or train it again"
)


def drop_metric_network_keys(state_dict, prefix, *args) -> None:
    """Checkpoints written before the LPIPS network left the module tree hold its weights under
    ``lpips.``: drop them so those checkpoints still load strictly."""
    for key in [k for k in state_dict if k.startswith(f"{prefix}lpips.")]:
        del state_dict[key]


def _check_batch(batch) -> EvalBatch:
    """Only FrugalDataManager's typed batches are understood (nerfstudio's dict batches carry no warp context)."""
    if not isinstance(batch, EvalBatch):
        raise TypeError(f"FrugalNeRFModel needs a TrainBatch or EvalBatch from FrugalDataManager, got {type(batch).__name__}")
    return batch
