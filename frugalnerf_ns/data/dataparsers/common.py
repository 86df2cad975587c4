"""What every FrugalNeRF dataparser shares: few-shot options, image listing and checks."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional, Sequence, Tuple

from nerfstudio.data.dataparsers.base_dataparser import DataParserConfig

from frugalnerf_ns.data.input_checks import IMAGE_SUFFIXES, DataError, check_image_file
from frugalnerf_ns.data.splits import ViewSplit, select_views

# nerfstudio asks for "val" during training and "test" in ns-eval; both are the few-shot test views.
EVAL_SPLITS = ("val", "test")


@dataclass
class FewShotDataParserConfig(DataParserConfig):
    """Few-shot view selection, the same for every layout."""

    data: Path = Path()
    """Scene folder."""
    train_views: Tuple[int, ...] = ()
    """Training views by index in filename order; empty: the paper's views for known scenes, else uniform."""
    num_train_views: Optional[int] = None
    """Number of training views when train-views is empty (default 2; datasets with their own split: theirs)."""
    test_views: Tuple[int, ...] = ()
    """Test views by index in filename order; empty: the layout's protocol (LLFF every 8th, DTU pixelNeRF list)."""
    scene_name: Optional[str] = None
    """Scene name for the paper's default views in configs/splits.yaml (default: the folder name)."""

    def resolved_scene_name(self) -> str:
        return self.scene_name or Path(self.data).resolve().name

    def split_views(
        self, num_frames: int, default_test: Sequence[int], scene_train_views=None, **kwargs
    ) -> ViewSplit:
        return select_views(
            num_frames,
            default_test,
            train_views=self.train_views,
            num_train_views=self.num_train_views,
            test_views=self.test_views,
            scene_train_views=scene_train_views,
            what=str(self.data),
            **kwargs,
        )


def split_indices(split: str, views: ViewSplit) -> List[int]:
    if split == "train":
        return views.train
    if split in EVAL_SPLITS:
        return views.test
    raise ValueError(f"unknown split {split!r}")


def list_images(folder: Path) -> List[Path]:
    """Images in filename order (the order poses and view indices refer to)."""
    if not folder.is_dir():
        raise DataError(f"image folder {folder} not found")
    images = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not images:
        raise DataError(f"{folder} holds no images")
    return images


def check_images(paths: Sequence[Path]) -> None:
    for path in paths:
        check_image_file(path, path.name)
