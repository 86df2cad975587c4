"""FrugalNeRF's datamanager and dataset.

Every training step returns one ray bundle and a ``TrainBatch`` (``batch.py``) naming its three ray groups:
training rays sampled as k x k pixel patches, novel-view rays in 2x2 patches from spiral poses around the
training cameras (paper Sec. 3.5, generated once), and rays through sparse points triangulated from the
training views (L_sd, ``sparse_points.py``), with per ray the training view it is warped into. The training
images and cameras the warps compare with are set up here once and handed to the model by the pipeline.
Batches are deterministic under ``seed`` (patches: ``patches.py``). What is derived once from the training
views (scene type, fitted box, sparse points, monocular depth) is in ``training_views.py``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, Optional, Tuple, Type

import torch
from jaxtyping import Float, Int
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManager, VanillaDataManagerConfig
from nerfstudio.data.pixel_samplers import PixelSampler, PixelSamplerConfig
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.model_components.ray_generators import RayGenerator
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor

from frugalnerf_ns.cache import cache_file_name, scene_cache_dir
from frugalnerf_ns.data.dataset import FrugalDataset
from frugalnerf_ns.data.input_checks import DataError
from frugalnerf_ns.data.novel_cameras import cameras_at, novel_view_poses
from frugalnerf_ns.data.patches import NOVEL_PATCH, sample_patches
from frugalnerf_ns.data.sparse_points import SparseDepth, TriangulationOptions
from frugalnerf_ns.data.training_points import sparse_point_rays
from frugalnerf_ns.data.training_views import (
    classify_scene,
    fitted_scene_box,
    training_view_mono_depth,
    training_view_points,
)
from frugalnerf_ns.geometry.novel_views import nearest_other_view, spiral_focus_depth
from frugalnerf_ns.geometry.scene_analysis import CameraLayout, SceneType, uninformative_view_notes
from frugalnerf_ns.batch import RAY_GROUP, EvalBatch, TrainBatch, concatenate_ray_bundles, ray_groups
from frugalnerf_ns.scoring.metrics import composite


@dataclass
class FrugalDataManagerConfig(VanillaDataManagerConfig):
    """nerfstudio's vanilla datamanager (no worker processes) sampling training patches and novel-view rays."""

    _target: Type = field(default_factory=lambda: FrugalDataManager)
    patch_size: int = 5
    """Side k of the k x k training-ray patches whose reprojection error selects the pseudo depth (paper: 5;
    the reference code uses 15 for DTU and RealEstate). The batch holds train-num-rays-per-batch // k^2
    patches."""
    novel_views: bool = True
    """Sample rays from novel poses on a spiral around the training cameras (geometric adaptation on novel
    views, Eq. 6-9, and depth smoothness)."""
    num_novel_rays_per_batch: int = 4096
    """Novel-view rays per step, sampled as 2x2 patches (paper: 4096)."""
    num_novel_poses: int = 60
    """Poses on the spiral (supplementary: 60)."""
    spiral_rotations: float = 1.0
    """Turns of the spiral (supplementary: LLFF 1, DTU 4, RealEstate 2)."""
    spiral_radius_scale: float = 1.0
    """Spiral radii as a multiple of the 90th percentile of the training cameras' offsets (LLFF 1.0,
    DTU 0.5, RealEstate 2.0)."""
    spiral_zrate: float = 0.5
    """Speed of the spiral's motion along the viewing axis relative to its angular speed."""
    seed: int = 0
    """Seed of the ray sampling (batches are deterministic)."""
    sparse_depth: bool = True
    """Triangulate SIFT matches between the training views with pycolmap (fixed known cameras, training
    views only) and supervise the rendered depth at those points (L_sd)."""
    num_sparse_rays_per_batch: int = 256
    """Rays through triangulated points per step (every observation when there are fewer)."""
    min_sparse_points: int = 20
    """With fewer triangulated points training goes on without L_sd (and says so once)."""
    triangulation: TriangulationOptions = field(default_factory=TriangulationOptions)
    """Which triangulated points are kept."""
    far_background_shell: bool = True
    """Where the dataparser models only the near part of the scene in a box with a far background (an LLFF split or
    photos without cameras that are not forward-facing): place that background on a sphere at the distance of the sparse points beyond
    the box (``scene_analysis.far_shell``) and keep those points for L_sd, so the rays to them cross the box
    empty. False: the background stays infinitely far away and only the points inside the box are used.
    --pipeline.model.far-background False turns this off too."""
    sparse_cache_dir: Optional[Path] = None
    """Folder of the cached points (default: frugalnerf_cache inside the scene's data folder, or this user's cache
    folder, $XDG_CACHE_HOME/frugalnerf, when the data folder cannot be written). The cache is
    keyed by training views and image size and checked against the images and cameras before use."""
    mono_depth_model: Optional[Path] = None
    """Folder of a transformers depth-estimation model already on disk (DPT, Depth-Anything) for the optional
    monocular depth loss L_d (--pipeline.model.mono-depth-weight); nothing is downloaded. None: off."""
    mono_depth_is_disparity: bool = True
    """The depth model predicts relative inverse depth (DPT and Depth-Anything do)."""
    mono_depth_input_size: int = 384
    """Square input size of the depth model (DPT 384, Depth-Anything 518)."""
    scene_type: Literal["auto", "forward-facing", "object", "360"] = "auto"
    """What the scene is; auto detects it from the training cameras (and an object mask or plain
    background). 360 scenes get no spiral novel rays; only object scenes get the occlusion loss."""
    fit_scene_box: bool = True
    """Shrink a metric scene box (not NDC) to the part of it the training cameras see, joined with the sparse
    points and widened by a margin, so the grid's voxels go where the views constrain the scene. False
    keeps the dataparser's box."""
    fit_box_min_views: int = 1
    """A region is kept when at least this many training cameras see it (1: nothing a training view shows
    is cut; 2: only what two views constrain, smaller but test views may see past it)."""
    fit_box_margin: float = 0.05
    """Margin added on every side of the fitted box, as a fraction of its size."""


class FrugalDataManager(VanillaDataManager[FrugalDataset]):
    """Patch-sampled training rays plus spiral novel-view rays, with everything the warps need."""

    config: FrugalDataManagerConfig
    train_images: Float[Tensor, "views height width channels"]
    warp_images: Float[Tensor, "views height width 3"]
    warp_intrinsics: Float[Tensor, "views 4"]
    train_nearest_view: Int[Tensor, " views"]
    novel_cameras: Optional[Cameras] = None
    novel_nearest_view: Optional[Int[Tensor, " poses"]] = None
    novel_path: str = "spiral"
    """Which path the novel poses follow: "spiral" (the paper's) or "orbit" (objects the cameras surround)."""
    scene_layout: CameraLayout
    scene_type: SceneType
    sparse: Optional[SparseDepth] = None
    mono_depth: Optional[Float[Tensor, "views height width"]] = None

    def setup_train(self) -> None:
        assert self.train_dataset is not None
        if self.config.patch_size < 1:
            raise DataError(f"--pipeline.datamanager.patch-size must be >= 1, got {self.config.patch_size}")
        cameras = self.train_dataset.cameras
        images = [self.train_dataset.get_image_float32(i) for i in range(len(self.train_dataset))]
        sizes = {tuple(image.shape[:2]) for image in images}
        if len(sizes) != 1:
            raise DataError(f"FrugalNeRF needs training images of one size; got {sorted(sizes)}")
        self.train_images = torch.stack(images).to(self.device)
        height, width = self.train_images.shape[1:3]
        if height < self.config.patch_size or width < self.config.patch_size:
            raise DataError(f"training images ({width}x{height}) are smaller than the {self.config.patch_size}-pixel patches")
        # Warps compare colours, so images with alpha are composited on white once, here.
        rgb = self.train_images[..., :3]
        if self.train_images.shape[-1] == 4:
            rgb = composite(rgb, self.train_images[..., 3:])
        self.warp_images = rgb.contiguous()
        self.warp_intrinsics = torch.stack(
            [cameras.fx[:, 0], cameras.fy[:, 0], cameras.cx[:, 0], cameras.cy[:, 0]], dim=-1
        ).float().to(self.device)
        self.warp_camera_to_worlds = cameras.camera_to_worlds.float().to(self.device)
        centers = cameras.camera_to_worlds[:, :3, 3]
        self.train_nearest_view = nearest_other_view(centers, centers, own_view=torch.arange(len(centers))).to(self.device)
        self.scene_layout, self.scene_type = classify_scene(
            cameras, self.warp_images, self.train_images.shape[-1] == 4,
            getattr(self.train_dataparser_outputs, "mask_filenames", None) is not None, self.config.scene_type,
        )
        # What the model needs of the scene; nerfstudio hands the dataset's metadata to the model.
        self.train_dataset.metadata["frugalnerf_scene"] = {
            "scene_type": self.scene_type,
            "num_train_pixels": int(self.train_images.shape[0] * self.train_images.shape[1] * self.train_images.shape[2]),
        }
        if self.test_mode == "val":  # training (eval tools and the viewer build this too: no repeats there)
            names = [Path(f).name for f in self.train_dataparser_outputs.image_filenames]
            for note in uninformative_view_notes(self.warp_images, cameras.camera_to_worlds, names):
                CONSOLE.print(f"[bold yellow]frugalnerf: {note}.")
        if len(centers) < 2:
            CONSOLE.print(
                "[bold yellow]frugalnerf: one training view: training rays have no other view to warp into, so "
                "geometric adaptation runs on novel-view rays only (warped into the one view); no sparse depth."
            )
        self.train_ray_generator = RayGenerator(cameras.to(self.device))
        # Not used for sampling (patches are), but nerfstudio's tools set the batch size through it
        # (ns-export pointcloud sets train_pixel_sampler.num_rays_per_batch), so next_train honours it.
        self.train_pixel_sampler = PixelSamplerConfig(num_rays_per_batch=self.config.train_num_rays_per_batch).setup()
        self.generator = torch.Generator().manual_seed(self.config.seed)
        if self.config.novel_views and self.config.num_novel_rays_per_batch > 0 and self.scene_type != "360":
            self.novel_cameras = self._novel_view_cameras(cameras)
            self.novel_nearest_view = nearest_other_view(self.novel_cameras.camera_to_worlds[:, :3, 3], centers).to(
                self.device
            )
            self.novel_ray_generator = RayGenerator(self.novel_cameras.to(self.device))
        # Only training needs the points (eval and the viewer set the datamanager up in another test_mode).
        if self.test_mode == "val" and self.config.sparse_depth and self.config.num_sparse_rays_per_batch > 0:
            if len(centers) >= 2:
                far_shell_wanted = getattr(self.config, "far_background_shell", False) and bool(
                    (self.train_dataparser_outputs.metadata or {}).get("far_background")
                )
                self.sparse, far_shell, beyond = training_view_points(
                    self.train_dataparser_outputs, cameras, self.warp_images, self.warp_intrinsics,
                    # Configs saved before this option existed load without it (nerfstudio rebuilds them from YAML).
                    getattr(self.config, "triangulation", None) or TriangulationOptions(),
                    self.config.min_sparse_points, self._cache_path("sparse_depth"), self.device, far_shell_wanted,
                )
                if far_shell is not None:
                    self.train_dataset.metadata["frugalnerf_scene"]["far_shell"] = far_shell
                if beyond is not None:  # where the views' content lies: the model's warp regime
                    self.train_dataset.metadata["frugalnerf_scene"]["points_beyond_box"] = beyond
        self.fitted_box = None  # the dataparser's box when a fitted one replaced it
        if getattr(self.config, "fit_scene_box", False):
            box = self.train_dataset.scene_box.aabb.float()
            fitted = fitted_scene_box(self.train_dataparser_outputs, box, cameras, self.warp_images, self.warp_intrinsics,
                                      self.sparse, self.config.fit_box_min_views, self.config.fit_box_margin)
            if fitted is not None:
                self.fitted_box, self.train_dataset.scene_box = box, SceneBox(aabb=fitted)
        model_path = getattr(self.config, "mono_depth_model", None)
        if self.test_mode == "val" and model_path is not None:
            self.mono_depth = training_view_mono_depth(
                Path(model_path), self.config.mono_depth_is_disparity, self.config.mono_depth_input_size,
                self.warp_images, self._cache_path("mono_depth"), self.device,
            )

    def _get_pixel_sampler(self, dataset: FrugalDataset, num_rays_per_batch: int) -> PixelSampler:
        """Per-pixel sampler for the eval batches (training batches come from ``next_train``).

        ``patch_size`` is FrugalNeRF's training patch; nerfstudio's VanillaDataManager would read it as the size
        of its own patch sampler, whose batches must be multiples of k^2 (4096 eval rays are not of 25) and
        which has no use here: eval rays are scored pixel by pixel."""
        return PixelSamplerConfig(num_rays_per_batch=num_rays_per_batch).setup()

    def _cache_path(self, kind: str) -> Path:
        """Cache file for this training split and image size, in the scene's cache (``scene_cache_dir``: next to
        the data, or this user's cache folder when the data cannot be written) or
        --pipeline.datamanager.sparse-cache-dir."""
        height, width = self.warp_images.shape[1:3]
        folder = self.config.sparse_cache_dir or scene_cache_dir(Path(self.config.dataparser.data), CONSOLE.print)
        names = [str(f) for f in self.train_dataparser_outputs.image_filenames]
        return folder / cache_file_name(names, width, height, kind)

    def _sparse_rays(self) -> Tuple[RayBundle, Tensor]:
        assert self.sparse is not None
        return sparse_point_rays(self.sparse, self.config.num_sparse_rays_per_batch, self.generator,
                                 self.train_ray_generator.cameras, self.device)

    def spiral_focus_depth(self) -> float:
        """Depth in front of the average training camera that the spiral looks at (novel rays, videos)."""
        metadata = self.train_dataparser_outputs.metadata or {}
        return spiral_focus_depth(
            self.train_dataset.cameras.camera_to_worlds, near_far=metadata.get("near_far"),
            scene_center=self.train_dataparser_outputs.scene_box.get_center(),
        )

    def _novel_view_cameras(self, cameras: Cameras) -> Cameras:
        poses, self.novel_path = novel_view_poses(
            cameras.camera_to_worlds, self.scene_type, self.scene_layout, self.spiral_focus_depth,
            self.config.num_novel_poses, self.config.spiral_rotations, self.config.spiral_radius_scale,
            self.config.spiral_zrate,
        )
        return cameras_at(poses, cameras)

    def next_train(self, step: int) -> Tuple[RayBundle, TrainBatch]:
        self.train_count += 1
        k = self.config.patch_size
        num_views, height, width = self.train_images.shape[:3]
        num_patches = max(1, self._train_rays_per_batch() // (k * k))
        indices = sample_patches(self.generator, num_patches, num_views, height, width, k)
        indices_dev = indices.to(self.device)
        bundle = self.train_ray_generator(indices_dev)
        view, rows, cols = indices_dev.unbind(-1)
        batch = TrainBatch(
            image=self.train_images[view, rows, cols],
            indices=indices,
            patch_size=k,
            nearest_view=self.train_nearest_view[view],
            mono_depth=None if self.mono_depth is None else self.mono_depth[view, rows, cols],
            step=step,
        )
        if self.novel_cameras is not None and self.novel_nearest_view is not None:
            num_novel = max(1, self.config.num_novel_rays_per_batch // NOVEL_PATCH**2)
            novel_height, novel_width = int(self.novel_cameras.height[0]), int(self.novel_cameras.width[0])
            novel = sample_patches(
                self.generator, num_novel, len(self.novel_cameras), novel_height, novel_width, NOVEL_PATCH
            ).to(self.device)
            novel_bundle = self.novel_ray_generator(novel)
            nearest = self.novel_nearest_view[novel[:, 0]]
            # Novel rays borrow their nearest training camera's index (a valid index for per-image fields).
            novel_bundle.camera_indices = nearest.clamp_min(0)[:, None]
            bundle = concatenate_ray_bundles(bundle, novel_bundle)
            batch.novel_indices = novel
            batch.num_novel = novel.shape[0]
            batch.nearest_view = torch.cat([batch.nearest_view, nearest])
        if self.sparse is not None:
            sparse_bundle, batch.sparse_depth = self._sparse_rays()
            bundle = concatenate_ray_bundles(bundle, sparse_bundle)
        bundle.metadata[RAY_GROUP] = ray_groups(batch, self.device)
        return bundle, batch

    def next_eval(self, step: int) -> Tuple[RayBundle, EvalBatch]:
        """nerfstudio's eval batch (random pixels of a test image), typed."""
        bundle, batch = super().next_eval(step)
        return bundle, EvalBatch(image=batch["image"], indices=batch["indices"], eval_mask=batch.get("eval_mask"), step=step)

    def _train_rays_per_batch(self) -> int:
        sampler = getattr(self, "train_pixel_sampler", None)
        return sampler.num_rays_per_batch if sampler is not None else self.config.train_num_rays_per_batch

    def get_train_rays_per_batch(self) -> int:
        k = self.config.patch_size
        return max(1, self._train_rays_per_batch() // (k * k)) * k * k
