"""The pipeline of every FrugalNeRF run: nerfstudio's, plus handing the training views to the model.

Outside training the model renders arbitrary cameras (viewer, ns-render) without a batch, so the warping
context of the cross-scale geometric adaptation (training images and cameras) must come from the
datamanager once, at set-up. Only datamanagers that loaded their training images (training, ns-eval and
the viewer; not ns-render, which opens no images) have it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Type

from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig
from nerfstudio.utils.rich_utils import CONSOLE

from frugalnerf_ns.geometry.viewpoints import coverage_line
from frugalnerf_ns.model.geometric_adaptation import ADAPTATION_METRIC
from frugalnerf_ns.model.objective import carve_unseen_space, geo_weights, uses_relative_sparse_depth
from frugalnerf_ns.run.checkpoints import use_intact_checkpoints_in_eval_tools
from frugalnerf_ns.data.input_checks import DataError
from frugalnerf_ns.errors import one_line_errors
from frugalnerf_ns.tools.video import teach_ns_render_spiral


@dataclass
class FrugalPipelineConfig(VanillaPipelineConfig):
    """nerfstudio's pipeline; the model also receives the training views for its viewer outputs."""

    _target: Type = field(default_factory=lambda: FrugalPipeline)


class FrugalPipeline(VanillaPipeline):
    def __init__(self, config: FrugalPipelineConfig, device: str, *args, **kwargs) -> None:
        # The far background's sphere is placed by the datamanager's points; a model without a far background
        # must not get the points beyond the box either (their rays would pull depth to the box's far side).
        if getattr(config.datamanager, "far_background_shell", False) and not getattr(config.model, "far_background", True):
            config.datamanager.far_background_shell = False
        # Every nerfstudio command that reads data builds the pipeline: bad data ends it with one line.
        with one_line_errors():
            super().__init__(config, device, *args, **kwargs)
        use_intact_checkpoints_in_eval_tools(FrugalPipeline)
        teach_ns_render_spiral(self)
        images = getattr(self.datamanager, "warp_images", None)
        set_views = getattr(self.model, "set_reference_views", None)
        if images is not None and set_views is not None:
            set_views(images, self.datamanager.warp_camera_to_worlds, self.datamanager.warp_intrinsics)
        if self.test_mode == "val" and hasattr(self.datamanager, "scene_layout") and hasattr(self.model, "scene_type"):
            CONSOLE.print(scene_summary(self.datamanager, self.model))

    def get_train_loss_dict(self, step: int):
        """nerfstudio's; the step's geometric adaptation, handed from the model's metrics to its losses, is not a
        number to log: it leaves the metrics here."""
        outputs, loss_dict, metrics_dict = super().get_train_loss_dict(step)
        metrics_dict.pop(ADAPTATION_METRIC, None)
        return outputs, loss_dict, metrics_dict


def scene_summary(datamanager, model) -> str:
    """One short summary of what training will model for this scene, and how to override each choice."""
    layout, dm, cfg = datamanager.scene_layout, datamanager.config, model.config
    detected = "detected" if dm.scene_type == "auto" else "set by --pipeline.datamanager.scene-type"
    views = len(datamanager.warp_images)
    if model.ndc is not None and datamanager.scene_type != "forward-facing":
        # NDC chosen for a split that is not forward-facing (--ndc True; RealEstate's default): say so rather
        # than call the split forward-facing.
        space = (
            "NDC (the data's near/far bounds), although the split is not forward-facing: NDC looks along the "
            "training cameras' mean direction, and views far from it render poorly (without --ndc, LLFF and photos "
            "without cameras model such a split in a box around the focus with a far background; "
            "docs/data.md)"
        )
    elif model.ndc is not None:
        space = "NDC (forward-facing, the data's near/far bounds)"
    else:
        size = model.field.aabb[1] - model.field.aabb[0]
        space = "bounded box " + " x ".join(f"{v:.3g}" for v in size.tolist())
        original = getattr(datamanager, "fitted_box", None)
        if original is not None:
            share = float(size.prod() / (original[1] - original[0]).prod())
            points = "" if datamanager.sparse is None else " and the sparse points"
            space += (
                f" (fitted to what the training views see{points}: {share:.0%} of the dataparser's box; "
                "--pipeline.datamanager.fit-scene-box False keeps it)"
            )
        elif getattr(dm, "fit_scene_box", False):
            space += " (the training views see all of the dataparser's box)"
        if getattr(model, "far_background", None) is not None:
            rows, cols = model.far_background.texture.shape[-2:]
            where = (
                f"on a sphere of radius {float(model.far_background.radius):.3g}, where the sparse points beyond the box lie"
                if model.far_background.has_shell else "infinitely far"
            )
            outer = getattr(model, "outer_space", None)
            if outer is not None and outer.is_active:
                side = outer.density_grid.resolution_tuple[0]
                space += (
                    " around the training cameras' focus (they converge on something in a larger space); beyond it "
                    f"the room as geometry: {side}^3 VM grids over the contracted space (L-infinity, samples linear in "
                    f"disparity), then {rows}x{cols} colours by direction at infinity "
                    "(--pipeline.model.outer-space-resolution 0: the colour map alone)"
                )
            else:
                space += (
                    f" around the training cameras' focus; beyond it a learned far background ({rows}x{cols} colours by "
                    f"direction, {where}; --pipeline.model.far-background False: the fixed background)"
                )
    side = round(model.final_voxels ** (1 / 3))
    pixels = (model.kwargs.get("metadata") or {}).get("frugalnerf_scene", {}).get("num_train_pixels", 0)
    grid = f"{side}^3 final grid " + (
        f"(auto: {pixels:,} training pixels)" if cfg.auto_grid else "(--pipeline.model.final-voxels; --pipeline.model.auto-grid sizes it from the pixels)"
    )
    room = bool(getattr(model, "has_room", False))  # an object in a box with the room beyond it
    if not dm.sparse_depth or dm.num_sparse_rays_per_batch <= 0:
        sparse = "off (option)"
    elif views < 2:
        sparse = "off (one view)"
    elif datamanager.sparse is None:
        sparse = f"off (fewer than {dm.min_sparse_points} points)"
    else:
        relative = ", errors relative to their depth" if uses_relative_sparse_depth(cfg, room) else ""
        sparse = f"on ({datamanager.sparse.num_points} points{relative})"
    if datamanager.novel_cameras is not None:
        novel = f"on ({len(datamanager.novel_cameras)} {datamanager.novel_path} poses)"
    else:
        novel = "off (360 scene)" if datamanager.scene_type == "360" and dm.novel_views else "off (option)"
    if cfg.occlusion_weight <= 0:
        occlusion = "off (weight 0)"
    else:
        occlusion = "on" if model.occlusion_active else "off (not an object scene)"
    regime = getattr(model, "warp_regime", None)
    warps = True if regime is None else regime.warps
    if max(geo_weights(cfg)) <= 0:
        geo = "off (weight 0)"
    elif not warps:
        geo = f"off, the photometric warps too ({regime.reason}; --pipeline.model.room-warp-losses on keeps them)"
    elif views < 2:
        geo = "novel rays only (one view)" if datamanager.novel_cameras is not None else "off (one view, no novel rays)"
    else:
        geo = f"on ({regime.reason}; --pipeline.model.room-warp-losses off: a plain fit)" if regime and regime.reason else "on"
    if model.ndc is None and regime is not None and carve_unseen_space(cfg, False, regime):
        grid += "; the alpha mask empties what no training camera sees (--pipeline.model.carve-unseen off keeps it)"
    return (
        f"frugalnerf scene: {datamanager.scene_type} ({detected}: views within {layout.spread_degrees:.1f} deg of their "
        f"mean, cameras cover {layout.coverage_degrees:.0f} deg around the focus); {views} training views\n"
        f"  space: {space}; {grid}\n"
        f"  losses: geometric adaptation {geo}, novel rays {novel}, sparse depth {sparse}, occlusion {occlusion}\n"
        f"  photos: {photo_coverage(datamanager)}\n"
        f"  cameras: {camera_line(datamanager)}"
    )


CAMERA_FILE_HINTS = {
    "LLFF": "poses_bounds.npy's hwf column (the full-size photos' height, width, focal) and images_<N>/ at 1/N of them",
    "DTU": "the npz's world_mat_i against the images (--pipeline.datamanager.dataparser.intrinsics-width names the frame "
           "K refers to)",
    "Blender": "the transforms files' fl_x / cx / camera_angle_x and transform_matrix (camera-to-world, OpenGL axes; "
               "`frugal-blender --capture True|False` picks the reading)",
    "Nerfstudio": "transforms.json's fl_x / cx and transform_matrix (camera-to-world, OpenGL axes)",
    "Colmap": "the COLMAP model's cameras against the images it was made from",
    "RealEstate": "the clip's intrinsics (3x3, in pixels of its frames) and extrinsics (world-to-camera)",
}


def camera_line(datamanager) -> str:
    """Whether the cameras as read explain the training photos (``data/camera_check.py``), from the sparse points'
    matches; one warning with the likely causes and the file to check when they do not."""
    metadata = datamanager.train_dataparser_outputs.metadata or {}
    check = metadata.get("camera_check")
    if check is None:
        if metadata.get("sparse_depth") is not None:
            return "estimated from these photos (their points and reprojection error are in the lines above)"
        if datamanager.sparse is None and not datamanager.config.sparse_depth:
            return "not checked (the sparse points are off: --pipeline.datamanager.sparse-depth)"
        return "not checked (too few training views, or a points cache written without the check)"
    if not check.flagged:
        verdict = "they explain the photos" if check.judged else "too few matches to judge them"
        return f"{check.facts()}: {verdict}"
    parser = type(datamanager.config.dataparser).__name__
    target = next((hint for name, hint in CAMERA_FILE_HINTS.items() if name.lower() in parser.lower()), None)
    if parser.startswith("Auto"):
        from frugalnerf_ns.data.dataparsers.auto import detect_layout

        try:
            layout = detect_layout(Path(datamanager.config.dataparser.data))[1].__name__
            target = next((hint for name, hint in CAMERA_FILE_HINTS.items() if name.lower() in layout.lower()), target)
        except DataError:  # a hint only
            pass
    return (f"[bold yellow]{check.facts()}: the cameras as read do not explain the training photos; likely "
            f"{'; '.join(check.causes)}. Check {target or 'the cameras file against the photos'}[/bold yellow]")


def photo_coverage(datamanager) -> str:
    """How the training photos cover the subject, from their cameras (and the sparse points' count), and where a
    photo would help most: before training, so a user can retake first (``frugalnerf-next-view`` ranks viewpoints
    with the trained model)."""
    names = [Path(f).name for f in datamanager.train_dataparser_outputs.image_filenames]
    points = None if datamanager.sparse is None else datamanager.sparse.num_points
    return coverage_line(datamanager.train_dataset.cameras.camera_to_worlds, names,
                         datamanager.scene_type == "forward-facing", points)
