"""The training views' sparse points as a run gets them: triangulated once and cached next to the data (keyed by
the pixels, cameras, options and depth bounds), and the share of them a run's scene box keeps for L_sd."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Optional, Sequence, Tuple

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

from frugalnerf_ns.cache import load_keyed_arrays, save_keyed_arrays
from frugalnerf_ns.data.camera_check import CameraCheck, check_matches
from frugalnerf_ns.data.sparse_points import (
    SparseDepth,
    TriangulationOptions,
    points_inside_box,
    training_view_matches,
    triangulate_training_views,
)

if TYPE_CHECKING:
    from nerfstudio.cameras.cameras import Cameras
    from nerfstudio.cameras.rays import RayBundle

CACHE_VERSION = 3  # 2: matching in torch, nearest-camera pairs, feature cap enforced; 3: the camera check kept


def cache_key(
    images: Sequence[np.ndarray],
    camera_to_worlds: Tensor,
    intrinsics: Tensor,
    options: TriangulationOptions,
    depth_bounds: Optional[Tuple[float, float]] = None,
) -> str:
    """Hash of everything the points depend on: pixels, cameras, options and depth bounds."""
    digest = hashlib.sha256()
    bounds = None if depth_bounds is None else [round(float(b), 6) for b in depth_bounds]
    digest.update(json.dumps({"version": CACHE_VERSION, "bounds": bounds, **options.key()}, sort_keys=True).encode())
    for image in images:
        digest.update(str(image.shape).encode())
        digest.update(np.ascontiguousarray(image).tobytes())
    # Cameras are rounded so float noise between runs does not invalidate the cache.
    digest.update(np.round(camera_to_worlds.double().cpu().numpy(), 6).tobytes())
    digest.update(np.round(intrinsics.double().cpu().numpy(), 4).tobytes())
    return digest.hexdigest()


def save_sparse_depth(path: Path, sparse: SparseDepth, key: str, check: Optional[CameraCheck] = None) -> None:
    extra = {} if check is None else {"camera_check": np.array(json.dumps(check.to_dict()))}
    save_keyed_arrays(
        path, key, points=sparse.points.double().numpy(), view=sparse.view.numpy(), point=sparse.point.numpy(),
        pixels=sparse.pixels.double().numpy(), depth=sparse.depth.double().numpy(), **extra,
    )


def load_sparse_depth(path: Path, key: str) -> Tuple[Optional[SparseDepth], str]:
    """(points, "") from a cache file written for ``key``; (None, why) when it is missing, stale or corrupt."""
    arrays, why = load_keyed_arrays(path, key)
    if arrays is None:
        return None, why
    try:
        sparse = SparseDepth(
            torch.from_numpy(arrays["points"]), torch.from_numpy(arrays["view"]).long(),
            torch.from_numpy(arrays["point"]).long(), torch.from_numpy(arrays["pixels"]), torch.from_numpy(arrays["depth"]),
        )
    except (KeyError, TypeError) as err:
        return None, f"corrupt ({type(err).__name__}: {err})"
    n = sparse.view.shape[0]
    shapes_ok = sparse.points.ndim == 2 and sparse.points.shape[-1] == 3 and sparse.pixels.shape == (n, 2)
    shapes_ok = shapes_ok and sparse.point.shape == (n,) and sparse.depth.shape == (n,)
    if not shapes_ok or not all(torch.isfinite(t).all() for t in (sparse.points, sparse.pixels, sparse.depth)):
        return None, "corrupt (inconsistent arrays)"
    if n and (int(sparse.point.max()) >= sparse.points.shape[0] or bool((sparse.depth <= 0).any())):
        return None, "corrupt (inconsistent arrays)"
    return sparse, ""


def all_training_sparse_depth(
    images: Sequence[np.ndarray],
    camera_to_worlds: Float[Tensor, "views 3 4"],
    intrinsics: Float[Tensor, "views 4"],
    options: TriangulationOptions,
    bounds: Optional[Tuple[float, float]],
    cache_path: Path,
    say: Callable[[str], None],
) -> Tuple[SparseDepth, Optional[CameraCheck]]:
    """Every point triangulated between the training views (no box, no minimum) and the camera check of their
    matches (``camera_check``; None for a cache written without it): from the cache when it matches these views
    and options, else triangulated and cached."""
    key = cache_key(images, camera_to_worlds, intrinsics, options, bounds)
    sparse, why = load_sparse_depth(cache_path, key)
    check = load_camera_check(cache_path) if sparse is not None else None
    if sparse is None:
        if why != "missing":
            say(f"[bold yellow]frugalnerf: sparse-depth cache {cache_path} is {why}: rebuilding it.")
        found = training_view_matches(images, camera_to_worlds, options)
        sparse = triangulate_training_views(images, camera_to_worlds, intrinsics, options, bounds, found=found)
        size = (int(images[0].shape[1]), int(images[0].shape[0]))
        check = check_matches(*found, camera_to_worlds, intrinsics, size, options.max_reprojection_error)
        try:
            save_sparse_depth(cache_path, sparse, key, check)
        except OSError as err:
            say(f"frugalnerf: could not cache sparse points in {cache_path} ({err}); they stay in memory.")
    return sparse, check


def load_camera_check(path: Path) -> Optional[CameraCheck]:
    """The camera check a points cache holds (read after its key matched), None when it holds none."""
    try:
        with np.load(path) as arrays:
            return CameraCheck.from_dict(json.loads(str(arrays["camera_check"]))) if "camera_check" in arrays else None
    except (OSError, ValueError, KeyError, TypeError):
        return None


def usable_points(
    sparse: SparseDepth, box: Optional[Float[Tensor, "2 3"]], min_points: int, say: Callable[[str], None], source: str
) -> Optional[SparseDepth]:
    """The points inside a metric ``box`` (None: NDC, no cut), or None, said, when fewer than ``min_points``
    remain (training goes on without L_sd). ``source`` says where they came from."""
    found = sparse.num_points
    if box is not None:
        sparse = points_inside_box(sparse, box)
    # Points beyond a metric box (a room around a focus box, a background behind an object) cannot be
    # rendered there: the count says whether the box or the matching is what left too few.
    outside = "" if found == sparse.num_points else f" ({found - sparse.num_points} more lie outside the scene box)"
    if sparse.num_points < min_points:
        say(
            f"[bold yellow]frugalnerf: {source} found {sparse.num_points} points{outside} "
            f"(fewer than --pipeline.datamanager.min-sparse-points {min_points}): training goes on without the "
            "sparse depth loss."
        )
        return None
    say(f"frugalnerf: {sparse.num_points} sparse points from {source} supervise depth (L_sd){outside}.")
    return sparse


def sparse_point_rays(
    sparse: SparseDepth, num_rays: int, generator: torch.Generator, cameras: "Cameras", device: torch.device
) -> Tuple["RayBundle", Tensor]:
    """Rays through the pixels where ``num_rays`` randomly chosen observations project, and the depths they
    should render (L_sd's rays of one step)."""
    count = sparse.view.shape[0]
    chosen = torch.randperm(count, generator=generator)[: min(count, num_rays)].to(device)
    # nerfstudio's coords are (row, column) in the same continuous pixel units as (u, v).
    coords = sparse.pixels[chosen].flip(-1)
    bundle = cameras.generate_rays(camera_indices=sparse.view[chosen][:, None], coords=coords)
    return bundle, sparse.depth[chosen]
