"""The pipeline of every FrugalNeRF run: nerfstudio's, plus handing the training views to the model.

Outside training the model renders arbitrary cameras (viewer, ns-render) without a batch, so the warping
context of the cross-scale geometric adaptation (training images and cameras) must come from the
datamanager once, at set-up. Only datamanagers that loaded their training images (training, ns-eval and
the viewer; not ns-render, which opens no images) have it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Type

from nerfstudio.pipelines.base_pipeline import VanillaPipeline, VanillaPipelineConfig


@dataclass
class FrugalPipelineConfig(VanillaPipelineConfig):
    """nerfstudio's pipeline; the model also receives the training views for its viewer outputs."""

    _target: Type = field(default_factory=lambda: FrugalPipeline)


class FrugalPipeline(VanillaPipeline):
    def __init__(self, config: FrugalPipelineConfig, device: str, *args, **kwargs) -> None:
        super().__init__(config, device, *args, **kwargs)
        images = getattr(self.datamanager, "warp_images", None)
        set_views = getattr(self.model, "set_reference_views", None)
        if images is not None and set_views is not None:
            set_views(images, self.datamanager.warp_camera_to_worlds, self.datamanager.warp_intrinsics)
