"""Few-shot view selection, the same for every layout (pure Python, no nerfstudio).

Indices are positions in filename order. The paper's protocol per layout: LLFF tests on every 8th frame,
DTU on the pixelNeRF list (all 49 views but 9), and the training views come from ``configs/splits.yaml``
for known scenes or are sampled uniformly from the non-test frames.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
import yaml

from frugalnerf_ns.config_files import config_text
from frugalnerf_ns.data.input_checks import DataError


@dataclass(frozen=True)
class ViewSplit:
    train: List[int]
    test: List[int]


def load_split_table() -> Dict[str, Any]:
    """``configs/splits.yaml``: per-layout defaults and the paper's per-scene training views."""
    text = config_text("splits.yaml")
    return yaml.safe_load(text)


def dietnerf_train_views(num_frames: int, count: int, seed: int = 0) -> List[int]:
    """DietNeRF's few-shot Blender views (run_nerf.py: ``np.random.seed(seed)`` then
    ``np.random.choice(i_train, size=count, replace=False)``, default seed 0), which FreeNeRF reuses."""
    return [int(i) for i in np.random.RandomState(seed).choice(num_frames, size=count, replace=False)]


def every_nth(num_frames: int, interval: int = 8) -> List[int]:
    """LLFF's test views: frames 0, 8, 16, ..."""
    return list(range(0, num_frames, interval))


def uniform_subset(candidates: Sequence[int], count: int) -> List[int]:
    """``count`` frames spread evenly over ``candidates`` (first and last included when count >= 2)."""
    if count >= len(candidates):
        return list(candidates)
    if count == 1:
        return [candidates[len(candidates) // 2]]
    step = (len(candidates) - 1) / (count - 1)
    return [candidates[round(i * step)] for i in range(count)]


def select_views(
    num_frames: int,
    default_test: Sequence[int],
    train_views: Sequence[int] = (),
    num_train_views: Optional[int] = None,
    test_views: Sequence[int] = (),
    scene_train_views: Optional[Dict[int, Sequence[int]]] = None,
    what: str = "scene",
    default_test_excludes_train: bool = False,
) -> ViewSplit:
    """Resolve the training and test views of one scene.

    Args:
        num_frames: frames in the scene (filename order).
        default_test: the layout's test views, used when ``test_views`` is empty.
        train_views: explicit training views; wins over everything else.
        num_train_views: how many training views; the scene's paper views when known, else uniform.
        test_views: explicit test views.
        scene_train_views: the paper's training views of this scene, by view count.
        what: names the scene in errors.
        default_test_excludes_train: drop training views from the default test views instead of failing
            (layouts whose default test rule is not disjoint from their training frames, e.g. RealEstate).
    """
    test = list(test_views) if test_views else [i for i in default_test if i < num_frames]
    check_indices(test, num_frames, "test", what)
    if train_views:
        train = list(train_views)
    else:
        count = 2 if num_train_views is None else num_train_views
        if count < 1:
            raise DataError(f"num-train-views must be at least 1 (got {count})")
        known = (scene_train_views or {}).get(count)
        candidates = [i for i in range(num_frames) if i not in set(test)]
        if known is not None:
            train = list(known)
        elif count > len(candidates):
            raise DataError(f"{what}: asked for {count} training views but only {len(candidates)} frames are not test views")
        else:
            train = uniform_subset(candidates, count)
    check_indices(train, num_frames, "train", what)
    if default_test_excludes_train and not test_views:
        test = [i for i in test if i not in set(train)]
    overlap = sorted(set(train) & set(test))
    if overlap:
        raise DataError(f"{what}: view(s) {overlap} are both training and test views")
    if not test:
        raise DataError(f"{what}: no test views (give --test-views)")
    return ViewSplit(train=train, test=test)


def check_indices(indices: Sequence[int], num_frames: int, kind: str, what: str) -> None:
    bad = [i for i in indices if not 0 <= i < num_frames]
    if bad:
        raise DataError(f"{what}: {kind} view(s) {bad} do not exist (the scene has {num_frames} frames: 0..{num_frames - 1})")
    if len(set(indices)) != len(indices):
        raise DataError(f"{what}: {kind} views {list(indices)} repeat a view")


def spread_split(num_frames: int, counts: Sequence[int] = (2, 3, 4)) -> Tuple[Dict[int, List[int]], List[int]]:
    """Splits of a short clip: for each view count, training frames spread evenly over it (first and last included,
    ``uniform_subset``); test frames: every frame none of these splits trains on, so each count is scored on the same
    frames, all between training frames (no extrapolation past the clip's ends)."""
    train = {count: uniform_subset(list(range(num_frames)), count) for count in counts}
    used = {frame for frames in train.values() for frame in frames}
    return train, [frame for frame in range(num_frames) if frame not in used]
