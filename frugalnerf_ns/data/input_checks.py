"""Input checks in front of nerfstudio's dataparser: bad data gets one clear line, not a deep traceback."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Type

import torch
from nerfstudio.data.dataparsers.nerfstudio_dataparser import Nerfstudio, NerfstudioDataParserConfig
from PIL import Image, UnidentifiedImageError

from frugalnerf_ns.errors import UserError

IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".exr", ".bmp", ".tif", ".tiff"}


class DataError(UserError):
    """A problem with the user's data."""


def check_scene_folder(data: Path) -> Path:
    """Check a nerfstudio-format scene before parsing; returns the transforms.json path."""
    if not data.exists():
        raise DataError(f"--data {data} does not exist")
    transforms = data if data.suffix == ".json" else data / "transforms.json"
    if not transforms.is_file():
        images = [p for p in data.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES] if data.is_dir() else []
        hint = (
            f"{len(images)} images but no cameras; frugal-auto (the default dataparser) estimates them from the photos"
            if images
            else "no images and no cameras"
        )
        raise DataError(f"{transforms} not found: {data} has {hint}")
    try:
        meta = json.loads(transforms.read_text())
    except json.JSONDecodeError as err:
        raise DataError(f"{transforms} is not valid JSON ({err})") from None
    frames = meta.get("frames", [])
    if len(frames) < 2:
        raise DataError(
            f"{transforms} lists {len(frames)} image(s); FrugalNeRF needs at least 2 posed images "
            "(few-shot still means more than one view)"
        )
    root = transforms.parent
    for frame in frames:
        _check_frame(frame, root, transforms)
    return transforms


def _check_frame(frame: dict, root: Path, transforms: Path) -> None:
    name = frame.get("file_path")
    if name is None:
        raise DataError(f"a frame in {transforms} has no file_path")
    pose = torch.tensor(frame.get("transform_matrix", []), dtype=torch.float64)
    if pose.shape != (4, 4) and pose.shape != (3, 4):
        raise DataError(f"{name}: transform_matrix has shape {tuple(pose.shape)}, expected 4x4")
    if not torch.isfinite(pose).all():
        raise DataError(f"{name}: transform_matrix contains NaN or inf")
    check_image_file(root / name, name)


def check_image_file(path: Path, name: str) -> None:
    """The file exists and decodes as an image (PIL's verify reads the whole stream, catching truncation)."""
    if not path.is_file():
        raise DataError(f"{name}: image file {path} not found")
    try:
        with Image.open(path) as img:
            img.verify()
    except (UnidentifiedImageError, OSError, SyntaxError) as err:
        raise DataError(f"{name}: image file {path} is unreadable or corrupt ({err})") from None


@dataclass
class FrugalNerfstudioDataParserConfig(NerfstudioDataParserConfig):
    """nerfstudio-format data, checked before it is parsed."""

    _target: Type = field(default_factory=lambda: CheckedNerfstudio)


class CheckedNerfstudio(Nerfstudio):
    config: FrugalNerfstudioDataParserConfig

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs):
        check_scene_folder(Path(self.config.data))
        outputs = super()._generate_dataparser_outputs(split, **kwargs)
        if len(outputs.image_filenames) == 0:
            raise DataError(f"the {split} split of {self.config.data} is empty")
        return outputs

