"""FrugalNeRF's datamanager and dataset.

For now the dataset adds the evaluation object mask (DTU protocol) to test batches; the geometric
adaptation's patches, novel-view rays and nearest views (issue 4) will live here too.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Dict, Type

import numpy as np
import torch
from nerfstudio.data.datamanagers.base_datamanager import VanillaDataManager, VanillaDataManagerConfig
from nerfstudio.data.datasets.base_dataset import InputDataset
from PIL import Image


class FrugalDataset(InputDataset):
    """InputDataset that also loads ``eval_mask`` (bool, H x W x 1) when the dataparser lists eval masks.

    nerfstudio's own ``mask`` would also restrict which pixels are *trained*, and only reads 1-channel
    files; DTU's masks are RGB and must only affect the metrics.
    """

    def get_metadata(self, data: Dict) -> Dict:
        masks = self.metadata.get("eval_mask_filenames")
        if not masks:
            return {}
        with Image.open(masks[data["image_idx"]]) as img:
            mask = img.convert("L")
            if self.scale_factor != 1.0:
                w, h = mask.size
                mask = mask.resize((int(w * self.scale_factor), int(h * self.scale_factor)), Image.Resampling.NEAREST)
            array = np.array(mask) > 127
        return {"eval_mask": torch.from_numpy(array)[..., None]}


@dataclass
class FrugalDataManagerConfig(VanillaDataManagerConfig):
    """nerfstudio's vanilla datamanager (no worker processes) with FrugalNeRF's dataset."""

    _target: Type = field(default_factory=lambda: FrugalDataManager)


class FrugalDataManager(VanillaDataManager[FrugalDataset]):
    config: FrugalDataManagerConfig
