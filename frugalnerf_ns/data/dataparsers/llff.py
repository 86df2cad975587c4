"""LLFF layout (``poses_bounds.npy`` + ``images_N/``): forward-facing splits in NDC as the paper does; splits
whose cameras converge on something from wider apart (a phone circling a table) in a metric box around it."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Tuple, Type

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataparserOutputs
from nerfstudio.data.scene_box import SceneBox
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image

from frugalnerf_ns.geometry.camera_conventions import average_pose, llff_to_opengl, recenter
from frugalnerf_ns.geometry.scene_analysis import (
    FOCUS_BOX_SCALE,
    FORWARD_FACING_MAX_SPREAD,
    classify_camera_layout,
    focus_box,
    largest_angle_to_mean_direction,
)
from frugalnerf_ns.data.downscaled_images import downscaled_all, photo_size_and_factor
from frugalnerf_ns.data.input_checks import DataError
from frugalnerf_ns.data.dataparsers.common import FewShotDataParserConfig, check_images, list_images, split_indices
from frugalnerf_ns.data.splits import every_nth, load_split_table

DEFAULT_FACTOR = 8
"""images_<N>/ read when --downscale-factor is not given and the folder exists."""

# TensoRF's NDC scene box for LLFF (x and y slightly wider than [-1, 1] to cover the image corners).
NDC_AABB = ((-1.5, -1.67, -1.0), (1.5, 1.67, 1.0))


@dataclass
class LLFFDataParserConfig(FewShotDataParserConfig):
    """LLFF layout: poses_bounds.npy (N x 17: 3x5 pose+hwf, near, far) and images_N/ in filename order."""

    _target: Type = field(default_factory=lambda: LLFF)
    downscale_factor: Optional[int] = None
    """Read images_<factor>/ (1: images/); made once from images/ into the scene's cache where only the
    full-size photos exist. Default: images_8/ if present (the paper uses 4; 8 suits a CPU), else images/ at the
    smallest factor that brings the long side to 640 px or fewer."""
    ndc: Optional[bool] = None
    """Model the scene in normalised device coordinates. Default: NDC when the training views are
    forward-facing (the scene analysis' rule: every viewing direction within 13 degrees of their mean), else a
    metric box around the point they converge on, with a learned far background beyond it. ``False`` on a
    forward-facing split: a metric box around the training frusta up to the far bound (the baselines' box)."""
    bd_factor: float = 0.75
    """Scale the scene so the nearest bound lands at 1 / bd_factor (NeRF's LLFF loader)."""
    principal_point: Optional[Tuple[float, float]] = None
    """The photos' principal point (cx cy) in pixels of the full-size photos poses_bounds.npy describes (its H and W),
    where it is not at their centre (LLFF's rows cannot hold it; a COLMAP run of one's own says it). Default: the
    centre."""
    focus_box_scale: float = FOCUS_BOX_SCALE
    """Metric box of a split that is not forward-facing: a cube on the training cameras' focus whose half side is
    this many times the farthest training camera's distance to it (above 1: the cameras inside it)."""


class LLFF(DataParser):
    config: LLFFDataParserConfig

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        data = Path(self.config.data)
        poses, bounds = load_poses_bounds(data / "poses_bounds.npy")
        factor, images, make_copies = self._images(data, poses.shape[0], split)
        if self.config.focus_box_scale <= 0:
            raise DataError(f"--focus-box-scale must be positive (got {self.config.focus_box_scale})")

        c2w = llff_to_opengl(poses[:, :, :4])
        scale = 1.0 / (bounds.min() * self.config.bd_factor)
        c2w[:, :, 3] *= scale
        bounds = bounds * scale
        table = load_split_table()["llff"]
        scene_views = table["scenes"].get(self.config.resolved_scene_name())
        views = self.config.split_views(len(images), every_nth(len(images), table["test_every"]), scene_views)
        # The average camera over all frames defines the frame: it is a choice of coordinates (TensoRF and
        # the paper do the same), no test pixel is used. NDC looks along that camera, so where the training
        # cameras look elsewhere (a phone sweeping 180 degrees around a table, a split at one end of it) NDC
        # would see them from the side: there the training cameras' average defines it.
        off_axis = largest_angle_to_mean_direction(torch.from_numpy(c2w), views.train)
        reference = c2w if off_axis <= FORWARD_FACING_MAX_SPREAD else c2w[views.train]
        transform = data_frame_transform(reference, scale)
        c2w = recenter(c2w, frame=reference)
        if off_axis > FORWARD_FACING_MAX_SPREAD:
            if split == "train":
                CONSOLE.print(
                    f"frugalnerf: {data}: a training camera looks {off_axis:.0f} deg away from the capture's mean "
                    f"direction (forward-facing: <= {FORWARD_FACING_MAX_SPREAD:.0f}): the frame is the training "
                    "cameras' average camera"
                )
        train_c2w = c2w[views.train]
        ndc, box = scene_space(train_c2w, self.config.ndc, self.config.focus_box_scale)
        indices = split_indices(split, views)
        files = [images[i] for i in indices]
        check_images(files)
        if make_copies:
            # Copies named as in images/: the cache then holds an LLFF images_<factor>/ folder.
            files = downscaled_all(files, factor, data, CONSOLE.print, base=data / "images")
        with Image.open(files[0]) as img:
            width, height = img.size
        full_height, full_width, full_focal = poses[0, :, 4]
        focal = float(full_focal) * width / float(full_width)
        centre = (width / 2.0, height / 2.0)
        if self.config.principal_point is not None:
            cx, cy = self.config.principal_point
            if not (0 < cx < full_width and 0 < cy < full_height):
                raise DataError(f"--principal-point {cx} {cy} lies outside the {int(full_width)}x{int(full_height)} "
                                f"photos poses_bounds.npy describes")
            # The focal's ratio for both: a downscale by an exact factor drops an odd last row (753 -> 376).
            # NDC stays valid: its rays are converted from each pixel's ray, whatever the principal point.
            ratio = width / float(full_width)
            centre = (cx * ratio, cy * ratio)

        return forward_facing_outputs(
            files, c2w[indices], train_c2w, (focal, focal, *centre),
            (width, height), (float(bounds.min()), float(bounds.max())), ndc, float(scale), box, transform,
        )


    def _images(self, data: Path, num_poses: int, split: str) -> Tuple[int, list, bool]:
        """(factor, every view's image file, whether they are the full-size photos to downscale by factor)."""
        factor = self.config.downscale_factor
        if factor is not None and factor < 1:
            raise DataError(f"--downscale-factor must be >= 1 (got {factor})")
        folder = data / ("images" if factor == 1 else f"images_{factor or DEFAULT_FACTOR}")
        full = data / "images"
        make_copies = not folder.is_dir() and full.is_dir()
        if not folder.is_dir() and not make_copies:
            available = sorted(p.name for p in data.glob("images*") if p.is_dir())
            raise DataError(f"{folder} not found (available: {', '.join(available) or 'none'}; set --downscale-factor)")
        images = list_images(full if make_copies else folder)
        if len(images) != num_poses:
            raise DataError(
                f"{data / 'poses_bounds.npy'} has {num_poses} poses but {full if make_copies else folder} has "
                f"{len(images)} images"
            )
        if make_copies and factor is None:
            width, height, factor = photo_size_and_factor(images[0])
            if split == "train":
                CONSOLE.print(
                    f"frugalnerf: {data} has full-size photos only ({width}x{height}): training at 1/{factor} "
                    f"({width // factor}x{height // factor}); --downscale-factor sets another size"
                )
        factor = factor or DEFAULT_FACTOR
        return factor, images, make_copies and factor > 1


def scene_space(train_c2w: np.ndarray, ndc: Optional[bool], focus_box_scale: float) -> Tuple[bool, Optional[torch.Tensor]]:
    """(NDC or not, metric box) of an LLFF-like split (posed LLFF, photos with estimated cameras) from its
    training cameras: NDC when they are forward-facing (``ndc`` overrides), else a metric box around the point
    they converge on (``focus_box``; beyond it a far background). ``ndc=False`` on a forward-facing split: no box
    here, ``forward_facing_outputs`` puts one around the training frusta."""
    layout = classify_camera_layout(torch.from_numpy(train_c2w).float())
    ndc = ndc if ndc is not None else layout.scene_type == "forward-facing"
    # Not forward-facing: NDC would look along the cameras' mean direction and see the outer views from the
    # side, and the far bound (~100x the near one on a phone capture) is more than a grid can hold.
    box = None if ndc or layout.scene_type == "forward-facing" else focus_box(
        torch.from_numpy(train_c2w), layout.focus, focus_box_scale
    )
    return ndc, box


def data_frame_transform(scaled_reference: np.ndarray, scale: float) -> torch.Tensor:
    """nerfstudio's ``dataparser_transform`` (3x4) of poses scaled by ``scale`` and then recentred on the average
    camera of ``scaled_reference`` (``recenter``): model = scale x (transform @ data), as ``dataparser_transforms.json``
    records it and ``DataparserOutputs.transform_poses_to_original_space`` inverts it."""
    average = np.eye(4)
    average[:3] = average_pose(scaled_reference)
    inverse = np.linalg.inv(average)
    inverse[:3, 3] /= scale
    return torch.from_numpy(inverse[:3]).float()


def forward_facing_outputs(
    images, c2w: np.ndarray, train_c2w: np.ndarray, intrinsics, size, near_far, ndc: bool, scale: float,
    box: Optional[torch.Tensor] = None, transform: Optional[torch.Tensor] = None,
) -> DataparserOutputs:
    """Outputs of an LLFF-like scene (LLFF, RealEstate, photos): NDC box and NDC parameters, or a metric box:
    ``box`` (the part of an unbounded scene the grid holds; beyond it the model learns a far background,
    metadata ``far_background``) or, without it, the box around the training frusta up to the far bound.
    ``c2w`` are the split's cameras, already recentred and scaled."""
    fx, fy, cx, cy = intrinsics
    width, height = size
    cameras = Cameras(
        camera_to_worlds=torch.from_numpy(c2w).float(),
        fx=fx,
        fy=fy,
        cx=cx,
        cy=cy,
        width=width,
        height=height,
        camera_type=CameraType.PERSPECTIVE,
    )
    metadata = {"near_far": near_far}
    if ndc:
        scene_box = SceneBox(aabb=torch.tensor(NDC_AABB))
        # NDC's warp needs one focal (NeRF and TensoRF's); rays are converted pixel by pixel, so an off-centre
        # principal point only shifts which part of the NDC box the frames cover.
        metadata["ndc"] = {"focal": float(fx), "width": float(width), "height": float(height), "near": 1.0}
    elif box is not None:
        scene_box = SceneBox(aabb=box.float())
        metadata["far_background"] = True
    else:
        scene_box = SceneBox(aabb=frustum_box(train_c2w, float(fx), width, height, near_far[1]))
    return DataparserOutputs(
        image_filenames=list(images), cameras=cameras, scene_box=scene_box, metadata=metadata, dataparser_scale=scale,
        **({} if transform is None else {"dataparser_transform": transform}),
    )


def load_poses_bounds(path: Path):
    """(N, 3, 5) LLFF poses with hwf column and (N, 2) near/far bounds, checked."""
    if not path.is_file():
        raise DataError(f"{path} not found (LLFF layout needs poses_bounds.npy)")
    try:
        array = np.load(path)
    except (ValueError, OSError, EOFError) as err:
        raise DataError(f"{path} is unreadable or truncated ({err})") from None
    if array.ndim != 2 or array.shape[1] != 17:
        raise DataError(f"{path} has shape {array.shape}; LLFF expects N x 17 (3x5 pose and hwf, near, far)")
    bad = np.where(~np.isfinite(array).all(axis=1))[0]
    if bad.size:
        raise DataError(f"{path}: row(s) {bad.tolist()} contain NaN or inf")
    bounds = array[:, 15:]
    if (bounds <= 0).any():
        raise DataError(f"{path}: near/far bounds must be positive")
    return array[:, :15].reshape(-1, 3, 5).astype(np.float64), bounds.astype(np.float64)


def frustum_box(c2w: np.ndarray, focal: float, width: int, height: int, far: float) -> torch.Tensor:
    """Axis-aligned box around the training cameras' frusta up to ``far`` (for metric, non-NDC modelling)."""
    corners = np.array([[x, y, -1.0] for x in (-width / 2, width / 2) for y in (-height / 2, height / 2)])
    corners[:, :2] /= focal
    points = [c2w[:, :3, 3]]
    for pose in c2w:
        points.append((corners * far) @ pose[:3, :3].T + pose[:3, 3])
    points = np.concatenate(points)
    return torch.tensor(np.stack([points.min(axis=0), points.max(axis=0)]), dtype=torch.float32)
