"""What the datamanager derives once from the training views before the first step: the kind of scene, the
scene box shrunk to what the views see, the sparse points triangulated between the views (L_sd) and the
optional monocular depth (L_d). Each is a function of the views and the datamanager's settings, so it can be
tested and reused without a datamanager."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional, Tuple

import numpy as np
import torch
from jaxtyping import Float
from nerfstudio.cameras.cameras import Cameras
from nerfstudio.data.dataparsers.base_dataparser import DataparserOutputs
from nerfstudio.utils.rich_utils import CONSOLE
from torch import Tensor

from frugalnerf_ns.data.mono_depth import load_or_predict
from frugalnerf_ns.data.sparse_points import SparseDepth, TriangulationOptions
from frugalnerf_ns.data.training_points import all_training_sparse_depth, usable_points
from frugalnerf_ns.geometry.scene_analysis import (
    CameraLayout,
    SceneType,
    beyond_box,
    classify_camera_layout,
    far_shell,
    fit_scene_box,
    has_plain_background,
    seen_region_box,
)


def classify_scene(
    cameras: Cameras, rgb: Float[Tensor, "views height width 3"], has_alpha: bool, has_masks: bool, option: str
) -> Tuple[CameraLayout, SceneType]:
    """The training cameras' layout and the scene type: detected (``option`` "auto", an object mask or a plain
    background counting as an object's) or the one the option names."""
    layout = classify_camera_layout(
        cameras.camera_to_worlds, has_object_mask=has_alpha or has_masks or has_plain_background(rgb)
    )
    return layout, (layout.scene_type if option == "auto" else option)


def fitted_scene_box(
    outputs: DataparserOutputs, box: Tensor, cameras: Cameras, rgb: Float[Tensor, "views height width 3"],
    intrinsics: Float[Tensor, "views 4"], sparse: Optional[SparseDepth], min_views: int, margin: float,
) -> Optional[Tensor]:
    """``box`` shrunk to what at least ``min_views`` training views see joined with the sparse points and widened
    by ``margin`` (``--pipeline.datamanager.fit-box-*``), or None when unchanged.

    Only metric boxes: an NDC box already spans exactly the forward-facing frustum. A resumed or loaded run
    takes its box from the checkpoint (the field's aabb buffer), whatever is fitted here."""
    metadata = outputs.metadata or {}
    if metadata.get("ndc") is not None:
        return None
    height, width = rgb.shape[1:3]
    near_far = metadata.get("near_far")
    seen = seen_region_box(
        box, cameras.camera_to_worlds.cpu(), intrinsics.cpu(), (width, height),
        None if near_far is None else (float(near_far[0]), float(near_far[1])), min_views,
    )
    points = None if sparse is None else sparse.points.cpu()
    fitted = fit_scene_box(box, seen, points, margin)
    return None if torch.equal(fitted, box) else fitted


def training_view_points(
    outputs: DataparserOutputs, cameras: Cameras, rgb: Float[Tensor, "views height width 3"],
    intrinsics: Float[Tensor, "views 4"], options: TriangulationOptions, min_points: int, cache: Path, device,
    far_shell_wanted: bool = False,
) -> Tuple[Optional[SparseDepth], Optional[Tuple[List[float], float]], Optional[Tuple[int, int]]]:
    """Sparse points of the training views on ``device`` (None when fewer than ``min_points``), the far
    background's sphere ((centre, radius), or None) and, with ``far_shell_wanted`` in a metric box, how many of all
    the points lie beyond the box ((beyond, total), else None; the model's ``objective.warp_regime``): the points the photos' cameras were estimated with
    (metadata ``sparse_depth``), else the training views' triangulated points, from the cache when it matches.

    With ``far_shell_wanted`` (a box holding only the near part of the scene, with a far background) the points
    beyond the box place that sphere (``far_shell``) and are kept: L_sd then asks their rays to cross the box
    empty. Otherwise a metric box drops them as background mismatches."""
    metadata = outputs.metadata or {}
    box = outputs.scene_box.aabb if metadata.get("ndc") is None else None  # NDC boxes are not in world units
    every = metadata.get("sparse_depth")
    how = "estimating the photos' cameras"
    if every is None:
        images = [np.round(image.cpu().numpy() * 255.0).astype(np.uint8) for image in rgb]
        near_far = metadata.get("near_far")
        every, check = all_training_sparse_depth(
            images, cameras.camera_to_worlds.double(), intrinsics.double().cpu(), options,
            None if near_far is None else (float(near_far[0]), float(near_far[1])), cache, CONSOLE.print,
        )
        if outputs.metadata is not None and check is not None:
            outputs.metadata["camera_check"] = check  # the start-up summary reports it (run/pipeline.py)
        how = "triangulating the training views"
    # else photos without cameras: the points their cameras were estimated with (no second triangulation).
    shell = far_shell(every.points, box) if far_shell_wanted and box is not None else None
    counts = None
    if far_shell_wanted and box is not None:
        counts = (int(beyond_box(every.points, box).sum()), int(every.num_points))
    if shell is not None:
        centre, radius = shell
        CONSOLE.print(
            f"frugalnerf: the sparse points beyond the box lie at a median {radius:.3g} from its centre: they supervise "
            "the depth of what lies there, and where the colour map is the only layer beyond the box "
            "(--pipeline.model.outer-space-resolution 0) it lies on a sphere of that radius "
            "(--pipeline.datamanager.far-background-shell False: neither)."
        )
        sparse = usable_points(every, None, min_points, CONSOLE.print, f"{how} (in and beyond the box)")
        return (None if sparse is None else _on(sparse, device)), (centre.tolist(), radius), counts
    sparse = usable_points(every, box, min_points, CONSOLE.print, how)
    return (None if sparse is None else _on(sparse, device)), None, counts


def _on(sparse: SparseDepth, device) -> SparseDepth:
    return SparseDepth(*(t.float().to(device) if t.is_floating_point() else t.to(device) for t in sparse))


def training_view_mono_depth(
    model_path: Path, is_disparity: bool, input_size: int, rgb: Float[Tensor, "views height width 3"], cache: Path,
    device,
) -> Tensor:
    """The depth model's predictions for the training images on ``device``, cached next to the data."""
    depth = load_or_predict(model_path, rgb, cache, is_disparity, input_size)
    CONSOLE.print(f"frugalnerf: monocular depth of {len(depth)} training views from {model_path} (L_d).")
    return depth.to(device)
