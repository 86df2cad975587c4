"""What the datamanager hands the model with each ray bundle: one typed batch for training, one for eval.

A training bundle holds three groups of rays, concatenated in this order, and ``TrainBatch`` names the
slice of each:
- ``train``: training pixels as k x k patches (patch-major), with their colours;
- ``novel``: novel-view rays in 2x2 patches from the spiral poses (geometric adaptation, depth smoothness);
- ``sparse``: rays through triangulated points, with the depth each should render (L_sd).
The bundle's metadata names each ray's group (``RAY_GROUP``: ``ray_groups``), so that rendering can skip
what no loss reads (``objective.color_read``). The training views every warp compares with are not in the batch: the model holds them once
(``FrugalNeRFModel.set_reference_views``, called by the pipeline at set-up).

An eval batch (nerfstudio's eval loss, every ``steps-per-eval-batch``) is single pixels of a test image.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
from jaxtyping import Float, Int
from nerfstudio.cameras.rays import RayBundle
from torch import Tensor


#: ``RayBundle.metadata`` key of a training bundle: each ray's group, [rays, 1] (TRAIN_RAYS, NOVEL_RAYS, SPARSE_RAYS).
RAY_GROUP = "frugalnerf_ray_group"
TRAIN_RAYS, NOVEL_RAYS, SPARSE_RAYS = 0, 1, 2


def ray_groups(batch: "TrainBatch", device: torch.device | str = "cpu") -> Int[Tensor, "rays 1"]:
    """Each ray's group in a training bundle's order: training, then novel, then sparse-depth rays."""
    sizes = [part.stop - part.start for part in (batch.train, batch.novel, batch.sparse)]
    counts = torch.tensor(sizes, device=device)
    groups = torch.tensor([TRAIN_RAYS, NOVEL_RAYS, SPARSE_RAYS], dtype=torch.int8, device=device)
    return groups.repeat_interleave(counts)[:, None]


@dataclass
class TrainBatch:
    image: Float[Tensor, "train_rays channels"]
    """Colours of the training rays (RGB, or RGBA when the images have alpha)."""
    indices: Int[Tensor, "train_rays 3"]
    """(view, row, column) of each training ray."""
    patch_size: int
    """k of the k x k training patches."""
    nearest_view: Int[Tensor, " warped_rays"]
    """Training view each training and novel ray is warped into (-1: none)."""
    num_novel: int = 0
    """Novel-view rays after the training rays (a multiple of 4: 2x2 patches)."""
    novel_indices: Optional[Int[Tensor, "novel_rays 3"]] = None
    """(pose, row, column) of each novel ray on the spiral."""
    sparse_depth: Optional[Float[Tensor, " sparse_rays"]] = None
    """Metric depth each sparse-point ray should render (None: no sparse-depth rays this step)."""
    mono_depth: Optional[Float[Tensor, " train_rays"]] = None
    """Monocular depth prediction at each training ray (None: no depth prior)."""
    step: Optional[int] = None
    """The training step this batch is for: the loss weights' decay is read at it (None: no schedule)."""

    @property
    def num_train(self) -> int:
        return int(self.image.shape[0])

    @property
    def train(self) -> slice:
        return slice(0, self.num_train)

    @property
    def novel(self) -> slice:
        return slice(self.num_train, self.num_train + self.num_novel)

    @property
    def warped(self) -> slice:
        """Training and novel rays: the rays of the cross-scale geometric adaptation."""
        return slice(0, self.num_train + self.num_novel)

    @property
    def sparse(self) -> slice:
        num_sparse = 0 if self.sparse_depth is None else int(self.sparse_depth.shape[0])
        start = self.num_train + self.num_novel
        return slice(start, start + num_sparse)


@dataclass
class EvalBatch:
    image: Float[Tensor, "rays channels"]
    """Colours of the test pixels."""
    indices: Int[Tensor, "rays 3"]
    """(image, row, column) of each pixel."""
    eval_mask: Optional[Tensor] = None
    """Object mask at each pixel (DTU protocol), where the dataparser lists masks."""
    step: Optional[int] = None
    """The step of the evaluation: its losses weigh their terms as training's do at that step."""


def concatenate_ray_bundles(first: RayBundle, second: RayBundle) -> RayBundle:
    """The rays of ``first`` followed by those of ``second`` (1-D bundles with the same fields)."""
    cat = lambda a, b: None if a is None else torch.cat([a, b], dim=0)  # noqa: E731
    metadata = {key: torch.cat([value, second.metadata[key]], dim=0) for key, value in first.metadata.items()}
    return RayBundle(
        origins=cat(first.origins, second.origins),
        directions=cat(first.directions, second.directions),
        pixel_area=cat(first.pixel_area, second.pixel_area),
        camera_indices=cat(first.camera_indices, second.camera_indices),
        nears=cat(first.nears, second.nears),
        fars=cat(first.fars, second.fars),
        metadata=metadata,
        times=cat(first.times, second.times),
    )
