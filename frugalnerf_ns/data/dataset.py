"""The dataset of every FrugalNeRF datamanager: nerfstudio's InputDataset with the same channels for every
image of a dataset, and the DTU evaluation mask."""

from __future__ import annotations

from functools import cached_property
from typing import Dict, Optional, Tuple

import numpy as np
import torch
from nerfstudio.data.datasets.base_dataset import InputDataset
from PIL import Image


def image_mode(path) -> Tuple[str, bool]:
    """PIL mode of an image file and whether it carries alpha (RGBA, LA, or a palette with transparency)."""
    with Image.open(path) as img:
        has_alpha = img.mode in ("RGBA", "LA", "PA", "La", "RGBa") or (img.mode == "P" and "transparency" in img.info)
        return img.mode, has_alpha


class FrugalDataset(InputDataset):
    """InputDataset that also loads ``eval_mask`` (bool, H x W x 1) when the dataparser lists eval masks.

    nerfstudio's own ``mask`` would also restrict which pixels are *trained*, and only reads 1-channel
    files; DTU's masks are RGB and must only affect the metrics.
    """

    @cached_property
    def any_image_has_alpha(self) -> bool:
        """Whether an image of this dataset has an alpha channel (PIL reads only the file headers)."""
        return any(image_mode(f)[1] for f in self._dataparser_outputs.image_filenames)

    def get_numpy_image(self, image_idx: int) -> np.ndarray:
        """uint8 RGB, or RGBA for every image when any image of the dataset has alpha (opaque alpha for the
        others), so images stack and the model composites each on the same background. Palette, grey and
        grey-alpha files are converted rather than read as raw channel values."""
        filename = self._dataparser_outputs.image_filenames[image_idx]
        with Image.open(filename) as pil_image:
            image = pil_image.convert("RGBA" if image_mode(filename)[1] else "RGB")
        if self.scale_factor != 1.0:
            width, height = image.size
            newsize = (int(width * self.scale_factor), int(height * self.scale_factor))
            image = image.resize(newsize, resample=Image.Resampling.BILINEAR)
        array = np.array(image, dtype=np.uint8)
        if self.any_image_has_alpha and array.shape[-1] == 3:
            array = np.concatenate([array, np.full_like(array[..., :1], 255)], axis=-1)
        return array

    def get_metadata(self, data: Dict) -> Dict:
        mask = read_eval_mask(self, data["image_idx"])
        return {} if mask is None else {"eval_mask": mask}


def read_eval_mask(dataset: InputDataset, index: int) -> Optional[torch.Tensor]:
    """The evaluation mask (bool, H x W x 1) of image ``index`` where the dataparser lists eval masks, for any
    InputDataset: nerfstudio's own methods (tensorf) use theirs, which does not load it, and the offline
    evaluator must mask them the same way."""
    masks = (dataset.metadata or {}).get("eval_mask_filenames")
    if not masks:
        return None
    with Image.open(masks[index]) as img:
        mask = img.convert("L")
        if dataset.scale_factor != 1.0:
            w, h = mask.size
            mask = mask.resize((int(w * dataset.scale_factor), int(h * dataset.scale_factor)), Image.Resampling.NEAREST)
        array = np.array(mask) > 127
    return torch.from_numpy(array)[..., None]
