"""DTU in the IDR/NeuS layout: ``cameras_sphere.npz`` (or ``cameras.npz``), ``image/`` (or ``images/``), ``mask/``
(``000.png`` or ``000000.png``: masks pair with images in filename order); and in
MonoSDF's (``000000_rgb.png`` ... beside ``cameras.npz``: centre crops of the frames the cameras describe).

``world_mat_i`` = K [R | t] projects world points to pixels of the FULL-resolution capture, OpenCV axes;
``scale_mat_i`` maps the unit sphere around the object into the world. We model the unit-sphere frame
(P = world_mat @ scale_mat), convert the cameras to nerfstudio's OpenGL axes, and rescale K to the size of
the images on disk: a whole frame downscaled by an integer factor, or (MonoSDF) its centre crop to the images'
aspect, scaled, with the principal point moved by the crop as MonoSDF's loader does. Cameras that fit their images
neither way stop with one line. Test images carry the object mask so metrics ignore the background (RegNeRF
protocol).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import List, NamedTuple, Optional, Type

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
MONOSDF_SUFFIX = "_rgb.png"
"""MonoSDF's image names (``000000_rgb.png``), in the scene folder itself."""
KNOWN_FRAMES = ((1600, 1200),)
"""Capture frames (width, height) a principal point within 5 % of their centre is taken to describe: DTU's. A
frame is otherwise estimated from the images (a whole frame) or given (``intrinsics_width``, for a crop)."""


@dataclass
class DTUDataParserConfig(FewShotDataParserConfig):
    """IDR/NeuS layout (DTU): camera npz with world_mat_i / scale_mat_i, image/ and mask/ folders."""

    _target: Type = field(default_factory=lambda: DTU)
    intrinsics_width: Optional[int] = None
    """Width of the frame the world matrices' intrinsics refer to (DTU: 1600); default: inferred from the principal
    point (DTU's frame, or an integer multiple of the images' width)."""
    masked_eval: bool = True
    """Evaluate on the object only: test images carry their masks (paper protocol)."""
    scene_radius: float = 1.0
    """Half-size of the modelled box in the unit-sphere frame."""


class DTU(DataParser):
    config: DTUDataParserConfig

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        data = Path(self.config.data)
        camera_file = camera_file_of(data)
        if camera_file is None:
            raise DataError(f"{data} has none of {', '.join(CAMERA_FILES)} (DTU/IDR layout)")
        images = scene_images(data)
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
        fit = fit_to_images(intrinsics[0], width, height, self.config.intrinsics_width, camera_file)

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

        K = torch.tensor(np.stack([fit.apply(intrinsics[i]) for i in indices]), dtype=torch.float32)
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
            if not (data / "mask").is_dir():
                raise DataError(
                    f"mask folder {data / 'mask'} not found: DTU is scored on the object's mask; without masks, "
                    "`frugal-dtu --masked-eval False` trains and scores on whole images"
                )
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


IMAGE_FOLDERS = ("image", "images")
"""Where IDR/NeuS keep the frames (``image/``; NeuS's forks and copies often ``images/``)."""


def scene_images(data: Path) -> List[Path]:
    """``image/`` or ``images/`` (IDR/NeuS and its forks), else MonoSDF's ``*_rgb.png`` in the scene folder, in
    filename order."""
    folder = next((data / name for name in IMAGE_FOLDERS if (data / name).is_dir()), None)
    if folder is None:
        monosdf = sorted(p for p in data.glob(f"*{MONOSDF_SUFFIX}") if p.is_file())
        if monosdf:
            return monosdf
        raise DataError(f"{data} has neither {' nor '.join(f'{n}/' for n in IMAGE_FOLDERS)} nor MonoSDF's "
                        f"*{MONOSDF_SUFFIX} images beside its cameras (DTU/IDR layout)")
    return list_images(folder)


def camera_file_of(data: Path) -> Optional[Path]:
    """The scene's IDR/NeuS camera file (the first of ``CAMERA_FILES`` present), or None."""
    return next((data / name for name in CAMERA_FILES if (data / name).is_file()), None)


def is_dtu_layout(data: Path) -> bool:
    """IDR/NeuS cameras beside its images (``image/``, ``images/`` or MonoSDF's). A folder that also holds another
    layout's cameras (a ``poses_bounds.npy``: NeuS's forks keep LLFF's file beside DTU's; a COLMAP ``sparse/``) is
    DTU only with object masks (``mask/``): cameras npz and masks are what the others lack and DTU's protocol needs."""
    if camera_file_of(data) is None:
        return False
    if not (any((data / name).is_dir() for name in IMAGE_FOLDERS) or any(data.glob(f"*{MONOSDF_SUFFIX}"))):
        return False
    other = (data / "poses_bounds.npy").is_file() or (data / "sparse").is_dir() or (data / "colmap" / "sparse").is_dir()
    return not other or (data / "mask").is_dir()


def infer_intrinsics_width(K: np.ndarray, image_width: int) -> float:
    """The width K refers to: the principal point sits near the centre, so about 2 * cx, snapped to an
    integer multiple of the loaded width (DTU: 1600 for 400-wide images)."""
    ratio = 2.0 * K[0, 2] / image_width
    return image_width * max(1, round(ratio))


class ImageFit(NamedTuple):
    """How a frame's intrinsics become the images': K[0, 2] -= crop_x, K[1, 2] -= crop_y, then K[:2] *= scale."""

    scale: float
    crop_x: float = 0.0
    crop_y: float = 0.0

    def apply(self, K: np.ndarray) -> np.ndarray:
        if not (self.crop_x or self.crop_y):
            return K * self.scale  # a whole frame: as before crops were read (the same numbers to the bit)
        K = K.copy()
        K[0, 2] -= self.crop_x
        K[1, 2] -= self.crop_y
        K[:2] *= self.scale
        return K


def fit_to_images(K: np.ndarray, width: int, height: int, frame_width: Optional[int], source: Path) -> ImageFit:
    """The frame K describes fitted to images of ``width`` x ``height``: a whole frame scaled, or (the images'
    aspect differs from the frame's by over 1 %) its centre crop to their aspect, scaled (MonoSDF's DTU: the
    middle 1200x1200 of 1600x1200, at 384x384). The frame is DTU's when the principal point lies within 5 % of
    its centre, else ``frame_width`` (its height from the principal point's aspect), else, for a whole frame, an
    integer multiple of the images. A principal point outside the middle third of the images it lands in stops
    with one line naming ``source`` and the numbers."""
    cx, cy = float(K[0, 2]), float(K[1, 2])
    known = next((f for f in KNOWN_FRAMES if abs(2 * cx / f[0] - 1) < 0.05 and abs(2 * cy / f[1] - 1) < 0.05), None)
    if frame_width:
        frame = (float(frame_width), round(frame_width * cy / cx))
    elif known:
        frame = (float(known[0]), float(known[1]))
    elif abs((cx / cy) / (width / height) - 1) > 0.15:  # a crop: 4:3 to 1:1 is 33 %; off-centre points a few %
        raise DataError(
            f"{source}: the cameras' principal point ({cx:.1f}, {cy:.1f}) describes a {2 * cx:.0f}x{2 * cy:.0f} frame, "
            f"whose aspect the {width}x{height} images do not have and whose crop to them is unknown; "
            "--pipeline.datamanager.dataparser.intrinsics-width gives the frame's width"
        )
    else:
        frame_w = infer_intrinsics_width(K, width)
        frame = (float(frame_w), frame_w * height / width)
    aspect, frame_aspect = width / height, frame[0] / frame[1]
    if abs(aspect / frame_aspect - 1) <= 0.01:
        fit = ImageFit(width / frame[0])
    elif aspect < frame_aspect:  # narrower images: the frame's full height, its middle columns
        fit = ImageFit(height / frame[1], crop_x=(frame[0] - frame[1] * aspect) / 2)
    else:  # wider images: the full width, the middle rows
        fit = ImageFit(width / frame[0], crop_y=(frame[1] - frame[0] / aspect) / 2)
    u, v = (cx - fit.crop_x) * fit.scale, (cy - fit.crop_y) * fit.scale
    if not (width / 3 <= u <= 2 * width / 3 and height / 3 <= v <= 2 * height / 3):
        raise DataError(
            f"{source}: the cameras do not fit the {width}x{height} images: their principal point lands at "
            f"({u:.1f}, {v:.1f}), outside the images' middle third (a {frame[0]:.0f}x{frame[1]:.0f} frame"
            + (f" cropped by {fit.crop_x:.0f}, {fit.crop_y:.0f}" if fit.crop_x or fit.crop_y else "")
            + f", scaled {fit.scale:.4g}); --pipeline.datamanager.dataparser.intrinsics-width gives the frame's width"
        )
    return fit
