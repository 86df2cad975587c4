"""A folder of a few photos and nothing else (issue 33): cameras estimated in-process (``photo_poses``), cached,
then modelled as posed LLFF scenes are (``llff.scene_space``): forward-facing photos in NDC along their mean camera,
photos converging on something from wider apart in a metric box around it with a far background beyond; the near
bound from the estimated points.

Training views are every photo that is not a ``--test-views`` photo. Test photos (a benchmark's held-out views)
are registered into the training photos' reconstruction with everything of it fixed, so their renders and
the photos compare in one frame; without test photos, evaluation reads the training photos (and says so).
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Optional, Tuple, Type

import numpy as np
import torch
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataparserOutputs
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image

from frugalnerf_ns.cache import load_keyed_arrays, save_keyed_arrays, scene_cache_dir
from frugalnerf_ns.data.dataparsers.common import FewShotDataParserConfig, EVAL_SPLITS
from frugalnerf_ns.data.dataparsers.llff import forward_facing_outputs, scene_space
from frugalnerf_ns.data.downscaled_images import downscaled_all, factor_for_long_side
from frugalnerf_ns.data.input_checks import IMAGE_SUFFIXES, DataError, check_image_file
from frugalnerf_ns.data.photo_poses import PhotoCameras, PoseEstimationOptions, estimate_cameras, focal_from_35mm
from frugalnerf_ns.data.sparse_points import SparseDepth
from frugalnerf_ns.data.splits import check_indices, uniform_subset
from frugalnerf_ns.geometry.camera_conventions import average_pose
from frugalnerf_ns.geometry.scene_analysis import FOCUS_BOX_SCALE

CACHE_VERSION = 1
EXIF_IFD, EXIF_FOCAL_35MM = 0x8769, 0xA405


def photo_files(data: Path) -> List[Path]:
    """The photos of a photos-only folder in filename order: its own image files, else those of ``images/``."""
    if not data.is_dir():
        return []
    for folder in (data, data / "images"):
        if folder.is_dir():
            found = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES)
            if found:
                return found
    return []


def is_photo_folder(data: Path) -> bool:
    return bool(photo_files(data))


def upright_size_and_focal_35mm(path: Path) -> Tuple[int, int, Optional[float]]:
    """(width, height) after the EXIF orientation and the 35 mm equivalent focal length (None when not said)."""
    check_image_file(path, path.name)
    with Image.open(path) as img:
        width, height = img.size
        exif = img.getexif()
        if exif.get(0x0112, 1) in (5, 6, 7, 8):  # rotated by 90 degrees one way or the other
            width, height = height, width
        focal = exif.get_ifd(EXIF_IFD).get(EXIF_FOCAL_35MM)
    return width, height, (float(focal) if focal else None)


@dataclass
class PhotosDataParserConfig(FewShotDataParserConfig):
    """A folder of 2-4 photos (JPEG/PNG, EXIF orientation honoured) without cameras: cameras estimated with
    pycolmap, cached in the scene's cache."""

    _target: Type = field(default_factory=lambda: Photos)
    downscale_factor: Optional[int] = None
    """Train at 1/factor of the photos' size (default: the smallest factor giving a long side of 640 px or
    fewer). Copies, upright, are made once into the scene's cache."""
    ndc: Optional[bool] = None
    """Model the scene in NDC. Default: as for posed LLFF scenes, NDC when the training photos are forward-facing
    (every viewing direction within 13 degrees of their mean), else a metric box around the point they converge
    on, with a learned far background beyond it. ``False`` on forward-facing photos: a box around their frusta."""
    bd_factor: float = 0.75
    """Scale the scene so the nearest point lands at 1 / bd_factor from the photos (NeRF's LLFF loader)."""
    focus_box_scale: float = FOCUS_BOX_SCALE
    """Metric box of photos that are not forward-facing: a cube on the photos' focus whose half side is this many
    times the farthest training photo's distance to it."""
    poses: PoseEstimationOptions = PoseEstimationOptions()
    """How the cameras are estimated."""


class Photos(DataParser):
    config: PhotosDataParserConfig

    def _split(self, count: int) -> Tuple[List[int], List[int]]:
        what = str(self.config.data)
        test = list(self.config.test_views)
        check_indices(test, count, "test", what)
        candidates = [i for i in range(count) if i not in set(test)]
        if self.config.train_views:
            train = list(self.config.train_views)
        elif self.config.num_train_views is not None:
            if not 2 <= self.config.num_train_views <= len(candidates):
                raise DataError(f"{what}: num-train-views {self.config.num_train_views} (2 to {len(candidates)} photos here)")
            train = uniform_subset(candidates, self.config.num_train_views)
        else:
            train = candidates
        check_indices(train, count, "train", what)
        overlap = sorted(set(train) & set(test))
        if overlap:
            raise DataError(f"{what}: photo(s) {overlap} are both training and test views")
        if len(train) < 2:
            raise DataError(
                f"{what}: {len(train)} training photo(s); estimating cameras needs at least 2 photos of the scene "
                "from different places"
            )
        return train, test

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        data = Path(self.config.data)
        photos = photo_files(data)
        if not photos:
            raise DataError(f"{data} holds no photos ({', '.join(sorted(IMAGE_SUFFIXES))})")
        train, test = self._split(len(photos))
        say = CONSOLE.print if split == "train" else (lambda _: None)
        facts = [upright_size_and_focal_35mm(photos[i]) for i in train + test]
        sizes = sorted({(w, h) for w, h, _ in facts})
        if len(sizes) != 1:
            raise DataError(
                f"{data}: the photos have different sizes after their EXIF orientation ({', '.join(f'{w}x{h}' for w, h in sizes)}); "
                "one camera is estimated for all of them: use photos from one camera, all landscape or all portrait"
            )
        width, height = sizes[0]
        factor = self.config.downscale_factor
        if factor is not None and factor < 1:
            raise DataError(f"--downscale-factor must be >= 1 (got {factor})")
        if self.config.focus_box_scale <= 0:
            raise DataError(f"--focus-box-scale must be positive (got {self.config.focus_box_scale})")
        factor = factor or factor_for_long_side(width, height)
        # Upright working copies, always (also at factor 1): the EXIF orientation is applied once, there.
        files = downscaled_all([photos[i] for i in train + test], factor, data, say, upright=True)
        images = [np.asarray(Image.open(f).convert("RGB")) for f in files]
        work_height, work_width = images[0].shape[:2]
        focals_35mm = {f for _, _, f in facts}
        focal_guess = None
        if len(focals_35mm) == 1 and None not in focals_35mm:
            focal_guess = focal_from_35mm(work_width, work_height, focals_35mm.pop())
        cameras = self._cameras(data, images, [photos[i].name for i in train + test], len(train), focal_guess, say)
        if split == "train":
            say(
                f"frugalnerf: {data}: {len(train)} training photo(s)"
                + (f" and {len(test)} test photo(s) registered with the training cameras fixed" if test else "")
                + f", {width}x{height} trained at {work_width}x{work_height}"
            )
            if not test:
                say("frugalnerf: no --test-views: evaluation (ns-eval, eval images) reads the training photos")
        return self._outputs(cameras, files[: len(train)], files[len(train):], split)

    def _cameras(self, data: Path, images, names, num_train: int, focal_guess, say) -> PhotoCameras:
        """The estimate for these photos and options, from the cache when it was made for them."""
        digest = hashlib.sha256(
            json.dumps({"version": CACHE_VERSION, "train": num_train, "focal": focal_guess, **self.config.poses.key()},
                       sort_keys=True).encode()
        )
        for image in images:
            digest.update(str(image.shape).encode())
            digest.update(np.ascontiguousarray(image).tobytes())
        key = digest.hexdigest()
        path = scene_cache_dir(data, say) / f"photo_cameras_{key[:16]}.npz"
        arrays, why = load_keyed_arrays(path, key)
        if arrays is not None:
            try:
                return cameras_from_arrays(arrays)
            except (KeyError, ValueError, TypeError) as err:
                why = f"corrupt ({type(err).__name__})"
        if why != "missing":
            say(f"[bold yellow]frugalnerf: camera cache {path} is {why}: estimating again.")
        say(f"frugalnerf: estimating the cameras of {num_train} photos with pycolmap (once; cached in {path.parent})")
        start = time.perf_counter()
        cameras = estimate_cameras(
            images[:num_train], names[:num_train], focal_guess, self.config.poses, images[num_train:], names[num_train:]
        )
        fov = math.degrees(2 * math.atan(0.5 * max(cameras.width, cameras.height) / cameras.focal))
        refined = self.config.poses.focal_is_refined(num_train, bool(focal_guess))
        how = ("from EXIF" if focal_guess else "assumed") + (", refined" if refined else "")
        say(
            f"frugalnerf: cameras estimated in {time.perf_counter() - start:.1f} s: focal length {cameras.focal:.1f} px "
            f"({fov:.1f} deg across the long side, {how}), {cameras.points.num_points} points, mean reprojection "
            f"error {cameras.reprojection_error:.2f} px"
        )
        try:
            save_keyed_arrays(path, key, **cameras_to_arrays(cameras))
        except OSError as err:
            say(f"frugalnerf: could not cache the cameras in {path} ({err}); they stay in memory.")
        return cameras

    def _outputs(self, cameras: PhotoCameras, train_files, test_files, split: str) -> DataparserOutputs:
        c2w_train = cameras.camera_to_worlds.numpy().copy()
        points = cameras.points.points.numpy()
        # Near and far from the points' depths along the training cameras' axes (LLFF's imgs2poses: 0.1 and
        # 99.9 percentiles; a few points make the extreme ones noisy, so 1 and 99 here).
        depths = []
        for view, c2w in enumerate(c2w_train):
            seen = cameras.points.point[cameras.points.view == view].numpy()
            depths.append(-((points[seen] - c2w[:3, 3]) @ c2w[:3, 2]))
        depths = np.concatenate(depths)
        near, far = float(np.percentile(depths, 1.0)), float(np.percentile(depths, 99.0))
        scale = 1.0 / (near * self.config.bd_factor)
        frame = np.eye(4)
        frame[:3] = average_pose(c2w_train)
        to_frame = np.linalg.inv(frame)

        def moved(c2w: np.ndarray) -> np.ndarray:
            out = to_frame[None, :3, :3] @ c2w
            out[:, :, 3] = (out[:, :, 3] + to_frame[:3, 3]) * scale
            return out

        c2w_train = moved(c2w_train)
        c2w_test = moved(cameras.test_camera_to_worlds.numpy()) if len(test_files) else c2w_train
        ndc, box = scene_space(c2w_train, self.config.ndc, self.config.focus_box_scale)
        if split == "train":
            c2w, files = c2w_train, train_files
        elif split in EVAL_SPLITS:
            c2w, files = (c2w_test, test_files) if len(test_files) else (c2w_train, train_files)
        else:
            raise ValueError(f"unknown split {split!r}")
        focal = cameras.focal
        outputs = forward_facing_outputs(
            files, c2w, c2w_train, (focal, focal, cameras.width / 2.0, cameras.height / 2.0),
            (cameras.width, cameras.height), (near * scale, far * scale), ndc, float(scale), box,
        )
        sparse = cameras.points
        world = (points @ to_frame[:3, :3].T + to_frame[:3, 3]) * scale
        outputs.metadata["sparse_depth"] = SparseDepth(
            torch.from_numpy(world), sparse.view, sparse.point, sparse.pixels, sparse.depth * scale
        )
        return outputs


def cameras_to_arrays(cameras: PhotoCameras) -> dict:
    return {
        "camera_to_worlds": cameras.camera_to_worlds.numpy(), "focal": np.array(cameras.focal),
        "size": np.array([cameras.width, cameras.height]), "tests": cameras.test_camera_to_worlds.numpy(),
        "points": cameras.points.points.numpy(), "view": cameras.points.view.numpy(),
        "point": cameras.points.point.numpy(), "pixels": cameras.points.pixels.numpy(),
        "depth": cameras.points.depth.numpy(),
    }


def cameras_from_arrays(arrays: dict) -> PhotoCameras:
    c2w = torch.from_numpy(arrays["camera_to_worlds"])
    sparse = SparseDepth(
        torch.from_numpy(arrays["points"]), torch.from_numpy(arrays["view"]).long(),
        torch.from_numpy(arrays["point"]).long(), torch.from_numpy(arrays["pixels"]), torch.from_numpy(arrays["depth"]),
    )
    if c2w.ndim != 3 or c2w.shape[1:] != (3, 4) or sparse.points.ndim != 2 or not torch.isfinite(c2w).all():
        raise ValueError("inconsistent arrays")
    width, height = (int(v) for v in arrays["size"])
    return PhotoCameras(c2w, float(arrays["focal"]), width, height, sparse, torch.from_numpy(arrays["tests"]))
