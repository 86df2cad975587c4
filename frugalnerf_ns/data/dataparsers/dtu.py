"""DTU in the IDR/NeuS layout: ``cameras_sphere.npz`` (or ``cameras.npz``), ``image/``, ``mask/``.

``world_mat_i`` = K [R | t] projects world points to pixels of the FULL-resolution capture, OpenCV axes;
``scale_mat_i`` maps the unit sphere around the object into the world. We model the unit-sphere frame
(P = world_mat @ scale_mat), convert the cameras to nerfstudio's OpenGL axes, and rescale K to the size of
the images on disk. Test images carry the object mask so metrics ignore the background (RegNeRF protocol).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Type

import numpy as np
import torch
from nerfstudio.cameras.cameras import Cameras, CameraType
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataparserOutputs
from nerfstudio.data.scene_box import SceneBox
from PIL import Image

from frugalnerf_ns.geometry.camera_conventions import decompose_projection, opencv_to_opengl
from frugalnerf_ns.data.input_checks import DataError
from frugalnerf_ns.data.dataparsers.common import (
    EVAL_SPLITS,
    FewShotDataParserConfig,
    check_images,
    list_images,
    split_indices,
)
from frugalnerf_ns.data.splits import every_nth, load_split_table

CAMERA_FILES = ("cameras_sphere.npz", "cameras.npz")


@dataclass
class DTUDataParserConfig(FewShotDataParserConfig):
    """IDR/NeuS layout (DTU): camera npz with world_mat_i / scale_mat_i, image/ and mask/ folders."""

    _target: Type = field(default_factory=lambda: DTU)
    intrinsics_width: Optional[int] = None
    """Image width the world matrices' intrinsics refer to (DTU: 1600); default: inferred from the principal point."""
    masked_eval: bool = True
    """Evaluate on the object only: test images carry their masks (paper protocol)."""
    scene_radius: float = 1.0
    """Half-size of the modelled box in the unit-sphere frame."""


class DTU(DataParser):
    config: DTUDataParserConfig

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        data = Path(self.config.data)
        camera_file = next((data / name for name in CAMERA_FILES if (data / name).is_file()), None)
        if camera_file is None:
            raise DataError(f"{data} has none of {', '.join(CAMERA_FILES)} (DTU/IDR layout)")
        images = list_images(data / "image")
        try:
            cams = dict(np.load(camera_file))
        except (ValueError, OSError, EOFError) as err:
            raise DataError(f"{camera_file} is unreadable or truncated ({err})") from None
        with Image.open(images[0]) as img:
            width, height = img.size

        intrinsics, c2ws = [], []
        for i in range(len(images)):
            world, scale = cams.get(f"world_mat_{i}"), cams.get(f"scale_mat_{i}", np.eye(4))
            if world is None:
                raise DataError(f"{camera_file} has no world_mat_{i} for {images[i].name} ({len(images)} images)")
            projection = (world @ scale)[:3, :4]
            if not np.isfinite(projection).all():
                raise DataError(f"{camera_file}: world_mat_{i} / scale_mat_{i} contain NaN or inf")
            K, c2w = decompose_projection(projection)
            intrinsics.append(K)
            c2ws.append(opencv_to_opengl(c2w))
        factor = width / (self.config.intrinsics_width or infer_intrinsics_width(intrinsics[0], width))

        table = load_split_table()["dtu"]
        excluded = set(table["excluded_from_test"])
        # The pixelNeRF protocol is defined for DTU's 49 views; other IDR scenes get the generic rule.
        if len(images) == 49:
            default_test = [i for i in range(len(images)) if i not in excluded]
            known_views = {int(k): v for k, v in table["train_views"].items()}
        else:
            default_test, known_views = every_nth(len(images)), None
        views = self.config.split_views(len(images), default_test, known_views)
        indices = split_indices(split, views)
        metadata = {}
        if split in EVAL_SPLITS and len(images) == 49 and list(views.test) == default_test:
            # Scored beside the pixelNeRF list: RegNeRF's 25 views, as positions in this split.
            regnerf = excluded | set(table["regnerf_also_excluded"])
            metadata["test_subsets"] = {"regnerf25": [n for n, i in enumerate(indices) if i not in regnerf]}
        check_images([images[i] for i in indices])

        K = torch.tensor(np.stack([intrinsics[i] for i in indices]), dtype=torch.float32) * factor
        cameras = Cameras(
            camera_to_worlds=torch.tensor(np.stack([c2ws[i] for i in indices]), dtype=torch.float32),
            fx=K[:, 0, 0:1],
            fy=K[:, 1, 1:2],
            cx=K[:, 0, 2:3],
            cy=K[:, 1, 2:3],
            width=width,
            height=height,
            camera_type=CameraType.PERSPECTIVE,
        )
        if split in EVAL_SPLITS and self.config.masked_eval:
            masks = list_images(data / "mask")
            if len(masks) != len(images):
                raise DataError(f"{data / 'mask'} has {len(masks)} masks for {len(images)} images")
            check_images([masks[i] for i in indices])
            metadata["eval_mask_filenames"] = [masks[i] for i in indices]
        r = self.config.scene_radius
        return DataparserOutputs(
            image_filenames=[images[i] for i in indices],
            cameras=cameras,
            scene_box=SceneBox(aabb=torch.tensor([[-r, -r, -r], [r, r, r]])),
            metadata=metadata,
        )


def infer_intrinsics_width(K: np.ndarray, image_width: int) -> float:
    """The width K refers to: the principal point sits near the centre, so about 2 * cx, snapped to an
    integer multiple of the loaded width (DTU: 1600 for 400-wide images)."""
    ratio = 2.0 * K[0, 2] / image_width
    return image_width * max(1, round(ratio))
