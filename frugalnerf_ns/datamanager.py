"""FrugalNeRF's datamanager and dataset.

Every training step returns one ray bundle holding, in this order:
- training rays sampled as k x k pixel patches (patch-major: the k*k rays of a patch are contiguous);
- novel-view rays sampled as 2x2 patches from poses on a spiral around the training cameras (paper
  Sec. 3.4), generated once.
The batch says how many rays are training rays and carries what the model needs to warp (Eq. 2-9): all
training images and their cameras (there are only 2-4) on the model's device, and per ray the index of the
nearest other training camera. Batches are deterministic under ``seed``. The test dataset adds the
evaluation object mask (DTU protocol).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, Optional, Tuple, Type

import numpy as np
import torch
from jaxtyping import Float, Int
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.cameras.rays import RayBundle
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManager, VanillaDataManagerConfig
from nerfstudio.data.datasets.base_dataset import InputDataset
from nerfstudio.model_components.ray_generators import RayGenerator
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image
from torch import Tensor

from frugalnerf_ns.data import DataError
from frugalnerf_ns.novel_views import nearest_training_views, spiral_focus_depth, spiral_poses


class FrugalDataset(InputDataset):
    """InputDataset that also loads ``eval_mask`` (bool, H x W x 1) when the dataparser lists eval masks.

    nerfstudio's own ``mask`` would also restrict which pixels are *trained*, and only reads 1-channel
    files; DTU's masks are RGB and must only affect the metrics.
    """

    def get_metadata(self, data: Dict) -> Dict:
        masks = self.metadata.get("eval_mask_filenames")
        if not masks:
            return {}
        with Image.open(masks[data["image_idx"]]) as img:
            mask = img.convert("L")
            if self.scale_factor != 1.0:
                w, h = mask.size
                mask = mask.resize((int(w * self.scale_factor), int(h * self.scale_factor)), Image.Resampling.NEAREST)
            array = np.array(mask) > 127
        return {"eval_mask": torch.from_numpy(array)[..., None]}


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


NOVEL_PATCH = 2  # novel-view rays come in 2x2 patches for the depth smoothness loss


class FrugalDataManager(VanillaDataManager[FrugalDataset]):
    """Patch-sampled training rays plus spiral novel-view rays, with everything the warps need."""

    config: FrugalDataManagerConfig
    train_images: Float[Tensor, "views height width channels"]
    warp_images: Float[Tensor, "views height width 3"]
    warp_intrinsics: Float[Tensor, "views 4"]
    train_nearest_view: Int[Tensor, "views"]
    novel_cameras: Optional[Cameras] = None
    novel_nearest_view: Optional[Int[Tensor, "poses"]] = None

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
            rgb = rgb * self.train_images[..., 3:] + (1.0 - self.train_images[..., 3:])
        self.warp_images = rgb.contiguous()
        self.warp_intrinsics = torch.stack(
            [cameras.fx[:, 0], cameras.fy[:, 0], cameras.cx[:, 0], cameras.cy[:, 0]], dim=-1
        ).float().to(self.device)
        self.warp_camera_to_worlds = cameras.camera_to_worlds.float().to(self.device)
        centers = cameras.camera_to_worlds[:, :3, 3]
        self.train_nearest_view = nearest_training_views(centers, centers, torch.arange(len(centers))).to(self.device)
        if len(centers) < 2:
            CONSOLE.print(
                "[bold yellow]frugalnerf: one training view: geometric adaptation needs two, so training goes on "
                "without it (colour loss and regularisers only)."
            )
        self.train_ray_generator = RayGenerator(cameras.to(self.device))
        self.generator = torch.Generator().manual_seed(self.config.seed)
        if self.config.novel_views and self.config.num_novel_rays_per_batch > 0:
            self.novel_cameras = self._spiral_cameras(cameras)
            self.novel_nearest_view = nearest_training_views(self.novel_cameras.camera_to_worlds[:, :3, 3], centers).to(
                self.device
            )
            self.novel_ray_generator = RayGenerator(self.novel_cameras.to(self.device))

    def _spiral_cameras(self, cameras: Cameras) -> Cameras:
        """The spiral's poses with the first training camera's intrinsics."""
        metadata = self.train_dataparser_outputs.metadata or {}
        focus = spiral_focus_depth(
            cameras.camera_to_worlds, near_far=metadata.get("near_far"), scene_center=self.train_dataparser_outputs.scene_box.get_center()
        )
        poses = spiral_poses(
            cameras.camera_to_worlds, focus, self.config.num_novel_poses, self.config.spiral_rotations,
            self.config.spiral_radius_scale, self.config.spiral_zrate,
        )
        count = poses.shape[0]
        return Cameras(
            camera_to_worlds=poses, fx=cameras.fx[:1].expand(count, 1), fy=cameras.fy[:1].expand(count, 1),
            cx=cameras.cx[:1].expand(count, 1), cy=cameras.cy[:1].expand(count, 1),
            width=cameras.width[:1].expand(count, 1), height=cameras.height[:1].expand(count, 1),
            camera_type=cameras.camera_type[:1].expand(count, 1),
        )

    def _sample_patches(self, num_patches: int, num_views: int, height: int, width: int, k: int) -> Int[Tensor, "rays 3"]:
        """(view, row, col) of ``num_patches`` random k x k patches, patch-major, row-major inside a patch."""
        gen = self.generator
        view = torch.randint(num_views, (num_patches,), generator=gen)
        top = torch.randint(height - k + 1, (num_patches,), generator=gen)
        left = torch.randint(width - k + 1, (num_patches,), generator=gen)
        dy, dx = torch.meshgrid(torch.arange(k), torch.arange(k), indexing="ij")
        rows = top[:, None] + dy.flatten()[None]
        cols = left[:, None] + dx.flatten()[None]
        return torch.stack([view[:, None].expand_as(rows), rows, cols], dim=-1).reshape(-1, 3)

    def next_train(self, step: int) -> Tuple[RayBundle, Dict]:
        self.train_count += 1
        k = self.config.patch_size
        num_views, height, width = self.train_images.shape[:3]
        num_patches = max(1, self.config.train_num_rays_per_batch // (k * k))
        indices = self._sample_patches(num_patches, num_views, height, width, k)
        indices_dev = indices.to(self.device)
        bundle = self.train_ray_generator(indices_dev)
        view = indices_dev[:, 0]
        batch: Dict = {
            "image": self.train_images[view, indices_dev[:, 1], indices_dev[:, 2]],
            "indices": indices,
            "num_train_rays": indices.shape[0],
            "patch_size": k,
            "nearest_view": self.train_nearest_view[view],
            "warp_images": self.warp_images,
            "warp_camera_to_worlds": self.warp_camera_to_worlds,
            "warp_intrinsics": self.warp_intrinsics,
        }
        if self.novel_cameras is not None and self.novel_nearest_view is not None:
            num_novel = max(1, self.config.num_novel_rays_per_batch // NOVEL_PATCH**2)
            novel_height, novel_width = int(self.novel_cameras.height[0]), int(self.novel_cameras.width[0])
            novel = self._sample_patches(
                num_novel, len(self.novel_cameras), novel_height, novel_width, NOVEL_PATCH
            ).to(self.device)
            novel_bundle = self.novel_ray_generator(novel)
            nearest = self.novel_nearest_view[novel[:, 0]]
            # Novel rays borrow their nearest training camera's index (a valid index for per-image fields).
            novel_bundle.camera_indices = nearest.clamp_min(0)[:, None]
            bundle = concatenate_ray_bundles(bundle, novel_bundle)
            batch["novel_indices"] = novel
            batch["nearest_view"] = torch.cat([batch["nearest_view"], nearest])
        return bundle, batch

    def get_train_rays_per_batch(self) -> int:
        k = self.config.patch_size
        return max(1, self.config.train_num_rays_per_batch // (k * k)) * k * k


def concatenate_ray_bundles(first: RayBundle, second: RayBundle) -> RayBundle:
    """The rays of ``first`` followed by those of ``second`` (1-D bundles with the same fields)."""
    cat = lambda a, b: None if a is None else torch.cat([a, b], dim=0)  # noqa: E731
    metadata = {key: torch.cat([value, second.metadata[key]], dim=0) for key, value in first.metadata.items()}
    return RayBundle(
        origins=cat(first.origins, second.origins),
        directions=cat(first.directions, second.directions),
        pixel_area=cat(first.pixel_area, second.pixel_area),
        camera_indices=cat(first.camera_indices, second.camera_indices),
        nears=cat(first.nears, second.nears),
        fars=cat(first.fars, second.fars),
        metadata=metadata,
        times=cat(first.times, second.times),
    )
