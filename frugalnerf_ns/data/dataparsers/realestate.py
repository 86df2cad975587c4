"""RealEstate-10K scenes in the layout of ViP-NeRF / SimpleNeRF's database folders:

    <scene>/rgb/0000.png ...            frames in filename order
    <scene>/CameraIntrinsics.csv        one row per frame: K (3x3, pixels of these frames) flattened, 9 values
    <scene>/CameraExtrinsics.csv        one row per frame: world-to-camera (4x4, OpenCV axes) flattened, 16 values

Forward-facing, so modelled in NDC like LLFF, in the frame of the average camera moved back to the rearmost training
camera (a video walks forward: nothing a training camera sees may lie behind NDC's near plane). The poses are up to scale (SLAM): the closest content's distance,
in the poses' units, comes from the points triangulated between the training views unless ``near_bound`` gives it.

Splits: ViP-NeRF's for its 50-frame clips (training frames 10, 20, 30 ...; configs/splits.yaml); a shorter clip
(pixelSplat's frames, a few video frames apart) trains on frames spread over it, first and last included, and tests
on the frames no 2-, 3- or 4-view split trains on, so every view count is scored on the same frames between its
training frames (``splits.spread_split``; the shared clips' splits are written out in configs/splits.yaml).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, List, Optional, Tuple, Type

import numpy as np
from nerfstudio.data.dataparsers.base_dataparser import DataParser, DataparserOutputs
from nerfstudio.utils.rich_utils import CONSOLE
from PIL import Image

from frugalnerf_ns.cache import scene_cache_dir
from frugalnerf_ns.geometry.camera_conventions import opencv_to_opengl, recenter
from frugalnerf_ns.data.input_checks import DataError
from frugalnerf_ns.data.dataparsers.common import FewShotDataParserConfig, check_images, list_images, split_indices
from frugalnerf_ns.data.dataparsers.llff import forward_facing_outputs
from frugalnerf_ns.data.scene_bounds import FAR_OVER_NEAR, near_far_from_points, training_points
from frugalnerf_ns.data.splits import ViewSplit, every_nth, load_split_table, spread_split

REALESTATE_FILES = ("CameraIntrinsics.csv", "CameraExtrinsics.csv")
FAR_MARGIN = 2.0
"""The far bound found from points: this many times the 99th percentile of their depths."""


@dataclass
class RealEstateDataParserConfig(FewShotDataParserConfig):
    """RealEstate-10K (ViP-NeRF layout): rgb/, CameraIntrinsics.csv, CameraExtrinsics.csv."""

    _target: Type = field(default_factory=lambda: RealEstate)
    ndc: bool = True
    """Model the scene in normalised device coordinates."""
    near_bound: Optional[float] = None
    """Distance of the closest content in the poses' units (scaled to 1 / bd_factor, as LLFF's near bound); default:
    the 1st percentile of the depths of the points triangulated between the training views."""
    far_bound: Optional[float] = None
    """Distance of the farthest content in the poses' units (only for the metric box when ndc is off); default: the
    99th percentile of the points' depths, doubled (100x a given near bound)."""
    bd_factor: float = 0.75
    """As for LLFF: the near bound lands at 1 / bd_factor, in front of NDC's near plane at 1."""


def load_csv_rows(path: Path, columns: int) -> np.ndarray:
    if not path.is_file():
        raise DataError(f"{path} not found (RealEstate layout)")
    try:
        rows = np.loadtxt(path, delimiter=",", ndmin=2)
    except ValueError as err:
        raise DataError(f"{path} is not a numeric CSV ({err})") from None
    if rows.shape[1] != columns:
        raise DataError(f"{path} has {rows.shape[1]} columns per row, expected {columns}")
    bad = np.where(~np.isfinite(rows).all(axis=1))[0]
    if bad.size:
        raise DataError(f"{path}: row(s) {bad.tolist()} contain NaN or inf")
    return rows


class RealEstate(DataParser):
    config: RealEstateDataParserConfig

    def _generate_dataparser_outputs(self, split: str = "train", **kwargs) -> DataparserOutputs:
        data = Path(self.config.data)
        images = list_images(data / "rgb")
        K = load_csv_rows(data / REALESTATE_FILES[0], 9).reshape(-1, 3, 3)
        w2c = load_csv_rows(data / REALESTATE_FILES[1], 16).reshape(-1, 4, 4)
        if not len(K) == len(w2c) == len(images):
            raise DataError(f"{data}: {len(images)} frames in rgb/ but {len(K)} intrinsics and {len(w2c)} extrinsics rows")
        with Image.open(images[0]) as img:
            width, height = img.size
        c2w = opencv_to_opengl(np.linalg.inv(w2c)[:, :3, :4])
        views = self._views(len(images))
        indices = split_indices(split, views)
        check_images([images[i] for i in indices])
        say = CONSOLE.print if split == "train" else (lambda _: None)
        near, far = self._bounds(data, views.train, [images[i] for i in views.train], c2w[views.train], K[views.train], say)
        scale = 1.0 / (near * self.config.bd_factor)
        c2w[:, :, 3] *= scale
        c2w = recenter(c2w)
        # NDC's near plane (z = -1 here) must lie in front of everything a training camera sees. A camera walking
        # into a room puts its first frames behind the average camera: the doorway 0.8 units in front of frame 0
        # would lie behind the plane, and frame 0's rays, started at the plane, draw it in front of later views.
        # So the frame's origin moves back along the viewing axis to the rearmost training camera.
        c2w[:, 2, 3] -= c2w[views.train, 2, 3].max()
        k0 = K[0]
        return forward_facing_outputs(
            [images[i] for i in indices], c2w[indices], c2w[views.train], (k0[0, 0], k0[1, 1], k0[0, 2], k0[1, 2]),
            (width, height), (near * scale, far * scale), self.config.ndc, scale,
        )

    def _views(self, num_frames: int) -> ViewSplit:
        table = load_split_table()["realestate"]
        clip = table.get("clips", {}).get(self.config.resolved_scene_name())
        protocol = {int(k): v for k, v in table["train_views"].items()}
        # A clip's own split where the table names it and its frame count is the one the split was made for.
        if clip is not None and max(clip["train_views"][2]) == num_frames - 1:
            train_views, test = {int(k): v for k, v in clip["train_views"].items()}, clip["test"]
        elif num_frames <= max(max(v) for v in protocol.values()):
            # Too short for ViP-NeRF's frames: training frames spread over the clip, the frames between them tested.
            train_views, test = spread_split(num_frames)
        else:
            train_views, test = protocol, every_nth(num_frames, table["test_every"])
        return self.config.split_views(num_frames, test, train_views, default_test_excludes_train=True)

    def _bounds(self, data: Path, train: List[int], files: List[Path], c2w: np.ndarray, K: np.ndarray,
                say: Callable[[str], None]) -> Tuple[float, float]:
        """(near, far) in the poses' units: as given, else from the training views' triangulated points."""
        near, far = self.config.near_bound, self.config.far_bound
        if near is not None and near <= 0:
            raise DataError(f"--near-bound must be positive (got {near})")
        if near is not None:
            return near, far if far is not None else FAR_OVER_NEAR * near
        sparse = training_points(files, c2w, [(k[0, 0], k[1, 1], k[0, 2], k[1, 2]) for k in K],
                                 scene_cache_dir(data, say) / f"realestate_points_{'-'.join(map(str, train))}.npz", say)
        bounds = near_far_from_points(sparse, c2w)
        if bounds is None:
            raise DataError(f"{data}: only {sparse.num_points} points triangulated between the {len(files)} training "
                            "views, too few to tell how near the content is: give --near-bound (the closest content's "
                            "distance in the poses' units)")
        say(f"frugalnerf: {data}: the poses have no scale; the closest content is {bounds[0]:.3g} units from the "
            f"training cameras and the farthest {bounds[1]:.3g} ({sparse.num_points} points triangulated between "
            f"the {len(files)} training views); --near-bound sets it")
        near = bounds[0]
        # Rooms: the points reach the far wall, and a box to 100x the near bound would leave a metric grid (the
        # baselines' ndc False) little for the room; twice the farthest points leave room for what was not matched.
        return near, far if far is not None else FAR_MARGIN * bounds[1]
