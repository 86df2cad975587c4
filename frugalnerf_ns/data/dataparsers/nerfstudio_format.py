"""nerfstudio-format (transforms.json) and COLMAP scenes with FrugalNeRF's few-shot selection.

Without few-shot options the data's own split (train/val/test lists, or nerfstudio's eval mode) is kept.
With them, all frames are parsed once (so every split shares one normalisation) and then subset.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import List, Type

import torch
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.data.dataparsers.colmap_dataparser import ColmapDataParser, ColmapDataParserConfig
from nerfstudio.data.dataparsers.nerfstudio_dataparser import Nerfstudio
from nerfstudio.utils.rich_utils import CONSOLE

from frugalnerf_ns.data.downscaled_images import downscaled_all, photo_size_and_factor
from frugalnerf_ns.data.input_checks import CheckedNerfstudio, DataError, FrugalNerfstudioDataParserConfig, check_scene_folder
from frugalnerf_ns.data.dataparsers.common import FewShotDataParserConfig, split_indices
from frugalnerf_ns.data.splits import every_nth


def wants_few_shot(config: FewShotDataParserConfig) -> bool:
    return bool(config.train_views or config.test_views or config.num_train_views is not None)


def subset_outputs(outputs: DataparserOutputs, indices: List[int]) -> DataparserOutputs:
    """The same scene restricted to ``indices`` (per-image metadata lists are subset too)."""
    count = len(outputs.image_filenames)
    pick = lambda items: [items[i] for i in indices]  # noqa: E731
    metadata = {k: pick(v) if isinstance(v, list) and len(v) == count else v for k, v in outputs.metadata.items()}
    return dataclasses.replace(
        outputs,
        image_filenames=pick(outputs.image_filenames),
        cameras=outputs.cameras[torch.tensor(indices)],
        mask_filenames=pick(outputs.mask_filenames) if outputs.mask_filenames else None,
        metadata=metadata,
    )


def few_shot_subset(config: FewShotDataParserConfig, all_outputs: DataparserOutputs, split: str) -> DataparserOutputs:
    names = [Path(p).name for p in all_outputs.image_filenames]
    order = sorted(range(len(names)), key=lambda i: names[i])  # view indices count in filename order
    views = config.split_views(len(names), every_nth(len(names)))
    return subset_outputs(all_outputs, [order[i] for i in split_indices(split, views)])


@dataclass
class FewShotNerfstudioDataParserConfig(FrugalNerfstudioDataParserConfig, FewShotDataParserConfig):
    """nerfstudio-format data (transforms.json), checked, with few-shot view selection."""

    _target: Type = field(default_factory=lambda: FewShotNerfstudio)


class FewShotNerfstudio(CheckedNerfstudio):
    config: FewShotNerfstudioDataParserConfig

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs):
        if not wants_few_shot(self.config):
            return super()._generate_dataparser_outputs(split, **kwargs)
        transforms = check_scene_folder(Path(self.config.data))
        meta = json.loads(transforms.read_text())
        listed = [k for k in ("train_filenames", "val_filenames", "test_filenames") if k in meta]
        if listed:
            raise DataError(
                f"{transforms} defines its own split ({', '.join(listed)}); drop --train-views/--num-train-views/"
                "--test-views or remove those lists"
            )
        everything = Nerfstudio(dataclasses.replace(self.config, eval_mode="all"))._generate_dataparser_outputs("train")
        return few_shot_subset(self.config, everything, split)


@dataclass
class FewShotColmapDataParserConfig(ColmapDataParserConfig, FewShotDataParserConfig):
    """COLMAP output (ns-process-data / colmap: images/ and sparse/0) with few-shot view selection."""

    _target: Type = field(default_factory=lambda: FewShotColmap)


class CachedDownscaleColmap(ColmapDataParser):
    """nerfstudio's COLMAP parser, except for the images it reads at a downscale: nerfstudio picks a factor for
    1600 px, asks on the terminal and writes ffmpeg copies next to the data (a prompt that stops a batch run, a
    binary a machine may lack, a folder that may be read-only). Here the factor is --downscale-factor, or the
    smallest that brings the long side to 640 px or fewer (said in one line); an ``images_<factor>/`` folder
    beside ``images/`` is read when it is complete, else copies are made once into the scene's cache."""

    def _setup_downscale_factor(self, image_filenames, mask_filenames, depth_filenames):
        images_dir = Path(self.config.data) / self.config.images_path
        if self._downscale_factor is None:
            factor = self.config.downscale_factor
            if factor is None:
                width, height, factor = photo_size_and_factor(image_filenames[0])
                if factor > 1:
                    CONSOLE.print(f"frugalnerf: {images_dir} holds {width}x{height} photos: training at 1/{factor} "
                                  f"({width // factor}x{height // factor}); --downscale-factor sets another size")
            if factor < 1:
                raise DataError(f"--downscale-factor must be >= 1 (got {factor})")
            self._downscale_factor = int(factor)
        factor = self._downscale_factor
        if factor == 1:
            return image_filenames, mask_filenames, depth_filenames, factor
        def beside(files: List[Path], folder: Path) -> List[Path]:  # nerfstudio's names: <folder>_<factor>/...
            return [folder.parent / f"{folder.name}_{factor}" / Path(f).relative_to(folder) for f in files]

        if all(f.is_file() for f in beside(image_filenames, images_dir)):
            image_filenames = beside(image_filenames, images_dir)
            for files, sub in ((mask_filenames, self.config.masks_path), (depth_filenames, self.config.depths_path)):
                if files:
                    files[:] = beside(files, Path(self.config.data) / sub)  # type: ignore[operator]
        else:
            for kind, files in (("masks", mask_filenames), ("depths", depth_filenames)):
                if files:
                    raise DataError(f"{images_dir}: {kind} are read at full size only; pass --downscale-factor 1 "
                                    f"or make images_{factor}/ and {kind}_{factor}/ beside them")
            image_filenames = downscaled_all(image_filenames, factor, Path(self.config.data), CONSOLE.print, base=images_dir)
        return image_filenames, mask_filenames, depth_filenames, factor


class FewShotColmap(CachedDownscaleColmap):
    config: FewShotColmapDataParserConfig

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs):
        if not wants_few_shot(self.config):
            return super()._generate_dataparser_outputs(split, **kwargs)
        parser = CachedDownscaleColmap(dataclasses.replace(self.config, eval_mode="all"))
        return few_shot_subset(self.config, parser._generate_dataparser_outputs("train"), split)
