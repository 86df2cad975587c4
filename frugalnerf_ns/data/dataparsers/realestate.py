"""RealEstate-10K scenes in the layout of ViP-NeRF / SimpleNeRF's database folders:

    <scene>/rgb/0000.png ...            frames in filename order
    <scene>/CameraIntrinsics.csv        one row per frame: K (3x3, pixels of these frames) flattened, 9 values
    <scene>/CameraExtrinsics.csv        one row per frame: world-to-camera (4x4, OpenCV axes) flattened, 16 values

Forward-facing, so modelled in NDC like LLFF. The poses are up to scale (SLAM): ``near_bound`` says how far
the closest content is, in the poses' units.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Type

import numpy as np
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataparserOutputs
from PIL import Image

from frugalnerf_ns.geometry.camera_conventions import opencv_to_opengl, recenter
from frugalnerf_ns.data.input_checks import DataError
from frugalnerf_ns.data.dataparsers.common import FewShotDataParserConfig, check_images, list_images, split_indices
from frugalnerf_ns.data.dataparsers.llff import forward_facing_outputs
from frugalnerf_ns.data.splits import every_nth, load_split_table

REALESTATE_FILES = ("CameraIntrinsics.csv", "CameraExtrinsics.csv")


@dataclass
class RealEstateDataParserConfig(FewShotDataParserConfig):
    """RealEstate-10K (ViP-NeRF layout): rgb/, CameraIntrinsics.csv, CameraExtrinsics.csv."""

    _target: Type = field(default_factory=lambda: RealEstate)
    ndc: bool = True
    """Model the scene in normalised device coordinates."""
    near_bound: float = 1.0
    """Distance of the closest content in the poses' units (scaled to 1 / bd_factor, as LLFF's near bound)."""
    far_bound: float = 100.0
    """Distance of the farthest content in the poses' units (only for the metric box when ndc is off)."""
    bd_factor: float = 0.75
    """As for LLFF: the near bound lands at 1 / bd_factor, in front of NDC's near plane at 1."""


def load_csv_rows(path: Path, columns: int) -> np.ndarray:
    if not path.is_file():
        raise DataError(f"{path} not found (RealEstate layout)")
    try:
        rows = np.loadtxt(path, delimiter=",", ndmin=2)
    except ValueError as err:
        raise DataError(f"{path} is not a numeric CSV ({err})") from None
    if rows.shape[1] != columns:
        raise DataError(f"{path} has {rows.shape[1]} columns per row, expected {columns}")
    bad = np.where(~np.isfinite(rows).all(axis=1))[0]
    if bad.size:
        raise DataError(f"{path}: row(s) {bad.tolist()} contain NaN or inf")
    return rows


class RealEstate(DataParser):
    config: RealEstateDataParserConfig

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        data = Path(self.config.data)
        images = list_images(data / "rgb")
        K = load_csv_rows(data / REALESTATE_FILES[0], 9).reshape(-1, 3, 3)
        w2c = load_csv_rows(data / REALESTATE_FILES[1], 16).reshape(-1, 4, 4)
        if not len(K) == len(w2c) == len(images):
            raise DataError(f"{data}: {len(images)} frames in rgb/ but {len(K)} intrinsics and {len(w2c)} extrinsics rows")
        with Image.open(images[0]) as img:
            width, height = img.size
        c2w = opencv_to_opengl(np.linalg.inv(w2c)[:, :3, :4])
        scale = 1.0 / (self.config.near_bound * self.config.bd_factor)
        c2w[:, :, 3] *= scale
        c2w = recenter(c2w)

        table = load_split_table()["realestate"]
        views = self.config.split_views(
            len(images),
            every_nth(len(images), table["test_every"]),
            {int(k): v for k, v in table["train_views"].items()},
            default_test_excludes_train=True,
        )
        indices = split_indices(split, views)
        check_images([images[i] for i in indices])
        k0 = K[0]
        near_far = (self.config.near_bound * scale, self.config.far_bound * scale)
        return forward_facing_outputs(
            [images[i] for i in indices], c2w[indices], c2w[views.train], (k0[0, 0], k0[1, 1], k0[0, 2], k0[1, 2]),
            (width, height), near_far, self.config.ndc, scale,
        )
