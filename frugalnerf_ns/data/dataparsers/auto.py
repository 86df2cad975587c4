"""The default dataparser of every FrugalNeRF method: detect the layout of --data and parse it."""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Callable, List, Literal, Optional, Tuple, Type

from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataParserConfig, DataparserOutputs
from nerfstudio.utils.rich_utils import CONSOLE

from frugalnerf_ns.data.input_checks import IMAGE_SUFFIXES, DataError
from frugalnerf_ns.data.dataparsers.blender import SPLIT_FILES, BlenderDataParserConfig, is_blender_layout
from frugalnerf_ns.data.dataparsers.common import FewShotDataParserConfig
from frugalnerf_ns.data.dataparsers.dtu import CAMERA_FILES, MONOSDF_SUFFIX, DTUDataParserConfig, is_dtu_layout
from frugalnerf_ns.data.dataparsers.llff import LLFFDataParserConfig
from frugalnerf_ns.data.dataparsers.nerfstudio_format import (
    FewShotColmapDataParserConfig,
    FewShotNerfstudioDataParserConfig,
)
from frugalnerf_ns.data.dataparsers.photos import PhotosDataParserConfig, is_photo_folder
from frugalnerf_ns.data.photo_poses import PoseEstimationOptions
from frugalnerf_ns.data.dataparsers.realestate import REALESTATE_FILES, RealEstateDataParserConfig


def _is_colmap(data: Path) -> bool:
    return any((data / sub / "images.bin").is_file() or (data / sub / "images.txt").is_file()
               for sub in ("sparse/0", "colmap/sparse/0"))


# (name, what it looks for, test, parser config). Order matters: the first match wins.
LAYOUTS: List[Tuple[str, str, Callable[[Path], bool], Type[DataParserConfig]]] = [
    ("nerfstudio", "transforms.json", lambda d: d.suffix == ".json" or (d / "transforms.json").is_file(),
     FewShotNerfstudioDataParserConfig),
    ("NeRF-synthetic files (Blender or a capture)", f"{SPLIT_FILES['train']} and {SPLIT_FILES['test']}", is_blender_layout,
     BlenderDataParserConfig),
    # Before LLFF: NeuS's forks keep a poses_bounds.npy beside DTU's cameras and masks (``is_dtu_layout``).
    ("DTU/IDR", f"{' or '.join(CAMERA_FILES)} with image/ or images/ (or MonoSDF's *{MONOSDF_SUFFIX})",
     is_dtu_layout, DTUDataParserConfig),
    ("LLFF", "poses_bounds.npy", lambda d: (d / "poses_bounds.npy").is_file(), LLFFDataParserConfig),
    ("RealEstate-10K", f"{' and '.join(REALESTATE_FILES)} with rgb/", lambda d: (d / "rgb").is_dir()
     and all((d / f).is_file() for f in REALESTATE_FILES), RealEstateDataParserConfig),
    ("COLMAP", "sparse/0/images.bin (or colmap/sparse/0)", _is_colmap, FewShotColmapDataParserConfig),
    # Last: any folder of images without cameras (the cameras are estimated from the photos).
    ("photos without cameras", "JPEG/PNG photos in the folder or in images/", is_photo_folder, PhotosDataParserConfig),
]


@dataclass
class AutoDataParserConfig(FewShotDataParserConfig):
    """Detects the layout of --data (nerfstudio, Blender, LLFF, DTU/IDR, RealEstate-10K, COLMAP, or photos without
    cameras: estimated with pycolmap) and parses it."""

    _target: Type = field(default_factory=lambda: AutoDataParser)
    downscale_factor: Optional[int] = None
    """Image downscale: LLFF reads images_<factor>/ (default 8; a capture with full-size images/ only: to a long
    side of 640 px or fewer, copies made once into the cache); Blender halves 800x800 frames (default: to 400
    wide); nerfstudio/COLMAP pass it on (default: auto)."""
    center_method: Literal["poses", "focus", "none"] = "poses"
    """nerfstudio/COLMAP data only: how nerfstudio centres the poses (focus: cameras looking at an object)."""
    ndc: Optional[bool] = None
    """LLFF, photos without cameras and RealEstate: model the scene in NDC (True) or in a metric box (False).
    Default: the layout's own rule (LLFF and photos: NDC when the training views are forward-facing, else a box
    around their focus with a far background; RealEstate: NDC)."""
    focus_box_scale: Optional[float] = None
    """LLFF and photos without cameras, splits that are not forward-facing: half the side of the box around the
    focus in farthest-camera distances (default 1.2)."""
    principal_point: Optional[Tuple[float, float]] = None
    """LLFF only: the photos' principal point in pixels of the full-size photos (default: their centre)."""
    near_bound: Optional[float] = None
    """RealEstate only: the closest content's distance in the poses' units (default: from the points triangulated
    between the training views)."""
    poses: PoseEstimationOptions = PoseEstimationOptions()
    """Photos without cameras only: how their cameras are estimated (field of view without EXIF, focal length
    refinement, features, thresholds)."""


def detect_layout(data: Path) -> Tuple[str, Type[DataParserConfig]]:
    if not data.exists():
        raise DataError(f"--data {data} does not exist")
    for name, _, test, config_type in LAYOUTS:
        if test(data):
            return name, config_type
    images = [p for p in data.rglob("*") if p.suffix.lower() in IMAGE_SUFFIXES] if data.is_dir() else []
    looked_for = "; ".join(f"{name}: {what}" for name, what, _, _ in LAYOUTS)
    found = f"{len(images)} images, none where a layout reads them" if images else "no images and no cameras"
    raise DataError(f"{data} has {found} (looked for {looked_for})")


def layout_config(config: AutoDataParserConfig) -> Tuple[str, DataParserConfig]:
    """The detected layout's parser config, carrying over the options it shares with the auto parser."""
    name, config_type = detect_layout(Path(config.data))
    target = config_type()
    names = {f.name for f in fields(target)}
    for f in fields(config):
        if f.name in names and f.name != "_target":
            # A run's config.yml saved before a field existed loads without it: the target's default stays.
            value = getattr(config, f.name, None)
            if value is not None:
                setattr(target, f.name, value)
    if isinstance(target, FewShotColmapDataParserConfig):
        # nerfstudio looks in colmap/sparse/0 (ns-process-data); a plain COLMAP project has sparse/0.
        target.colmap_path = next(p for p in (Path("colmap/sparse/0"), Path("sparse/0")) if (Path(config.data) / p).is_dir())
    return name, target


def layout_note(name: str, data: Path) -> str:
    """Why a folder that another layout would also read was read as ``name`` (empty when nothing else fits)."""
    if name == "DTU/IDR" and (data / "poses_bounds.npy").is_file():
        return (": its cameras npz and mask/ make it DTU (its poses_bounds.npy is not read; `frugal-llff` reads the "
                "folder as LLFF, without masks)")
    return ""


class AutoDataParser(DataParser):
    config: AutoDataParserConfig

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        name, target = layout_config(self.config)
        if split == "train":
            CONSOLE.print(f"frugalnerf: {self.config.data} is {name} data ({type(target).__name__}){layout_note(name, Path(self.config.data))}")
        return target.setup()._generate_dataparser_outputs(split, **kwargs)
