"""Sparse depth from the few training views (paper Sec. 3.6, L_sd after DS-NeRF).

The paper runs COLMAP on the training views only (all views would leak the test views' geometry). We do the
same inside the pipeline: SIFT features per training image with pycolmap (no COLMAP binary), COLMAP's
matching rule (ratio test, distance limit, cross-check) in torch, then triangulation with the known, fixed
cameras. Every pair is matched for a few views; with more, each view only with its nearest cameras, so
start-up grows linearly with the views. The geometry (pairs, matches, tracks, DLT triangulation,
reprojection and angle checks, the depth targets) is pure torch.

Conventions are ``reprojection.py``'s: nerfstudio cameras (camera-to-world, OpenGL axes), pixel (u, v) from
the top-left corner with pixel centres at i + 0.5 (COLMAP's keypoints use the same), depth = metric distance
from the camera centre along the unit ray through the pixel.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, NamedTuple, Optional, Sequence, Tuple

import numpy as np
import torch
from jaxtyping import Float, Int
from torch import Tensor

from frugalnerf_ns.progress import Progress
from frugalnerf_ns.geometry.plane_sweep import StereoOptions, stereo_matches
from frugalnerf_ns.geometry.reprojection import project_to_camera
from frugalnerf_ns.geometry.scene_analysis import beyond_box

SIFT_DIMENSIONS = 128


class SparseDepth(NamedTuple):
    """Triangulated points and, per observation, the training pixel and the depth it should render."""

    points: Float[Tensor, "points 3"]
    """World positions of the points."""
    view: Int[Tensor, " obs"]
    """Training view of each observation."""
    point: Int[Tensor, " obs"]
    """Point of each observation."""
    pixels: Float[Tensor, "obs 2"]
    """(u, v) where the point projects in its view (exact, so the pixel's ray passes through the point)."""
    depth: Float[Tensor, " obs"]
    """Metric distance from the view's camera centre to the point."""

    @property
    def num_points(self) -> int:
        return int(self.points.shape[0])


@dataclass
class TriangulationOptions:
    """Which triangulated points are kept."""

    max_reprojection_error: float = 1.5
    """Largest reprojection error in pixels, in every view of the track."""
    min_track_length: int = 2
    """Fewest views a point is seen in."""
    min_triangulation_angle: float = 0.5
    """Smallest angle, in degrees, between two rays of the track (smaller: depth is ill-conditioned)."""
    max_features: int = 8192
    """SIFT features per image (the largest-scale ones are kept); per upsampled image, times ``sift_upsample``^2."""
    sift_upsample: int = 1
    """SIFT runs on the training images enlarged this many times (bicubic), keypoints mapped back: at 1/8 of
    LLFF's size SIFT finds 1.4-3.2k features per image and the finest texture goes unmatched; at 2 it finds
    2.4-8x as many, 2.3-11x the points, as accurate (scripts/diagnostics/triangulate_scenes.py)."""
    match_neighbors: int = 8
    """Each view is matched with this many nearest cameras (every pair when there are at most this + 1 views)."""
    dense_stereo: bool = False
    """Add plane-sweep stereo matches (``geometry/plane_sweep.py``) between each view and its nearest camera to
    SIFT's points: every textured pixel whose match is sharp and passes the left-right check, not only keypoints
    (fern 2-view: 8x the points of SIFT on 2x images, as close to the full capture's COLMAP points;
    scripts/diagnostics/dense_stereo_points.py; trained with, fern and flower 2-view moved by ~0.1 dB either way,
    docs/notes/benchmarks.md). The depth range is the scene's near/far bounds, else SIFT's points' (without either, no
    stereo)."""

    def key(self) -> Dict[str, float]:
        key = {k: float(v) for k, v in self.__dict__.items()}
        # Caches written before an option existed stay valid while it keeps its old behaviour.
        if self.sift_upsample == 1:
            del key["sift_upsample"]
        if not self.dense_stereo:
            del key["dense_stereo"]
        return key


# ---- geometry (pure torch) ----------------------------------------------------------------------------------
def opencv_projection_matrices(
    camera_to_worlds: Float[Tensor, "views 3 4"], intrinsics: Float[Tensor, "views 4"]
) -> Float[Tensor, "views 3 4"]:
    """P = K F [R^T | -R^T t] with F = diag(1, -1, -1): the OpenCV-style projection of an OpenGL camera,
    so u = (P X)_0 / (P X)_2 agrees with ``reprojection.project_to_camera``."""
    rotation, translation = camera_to_worlds[:, :3, :3], camera_to_worlds[:, :3, 3]
    world_to_camera = torch.cat([rotation.transpose(1, 2), -(rotation.transpose(1, 2) @ translation[..., None])], dim=2)
    flip = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=world_to_camera.dtype, device=world_to_camera.device))
    fx, fy, cx, cy = intrinsics.unbind(-1)
    zeros, ones = torch.zeros_like(fx), torch.ones_like(fx)
    k = torch.stack([fx, zeros, cx, zeros, fy, cy, zeros, zeros, ones], dim=-1).reshape(-1, 3, 3)
    return k @ flip @ world_to_camera


def triangulate_dlt(
    projections: Float[Tensor, "views 3 4"], view: Int[Tensor, "points k"], pixels: Float[Tensor, "points k 2"]
) -> Float[Tensor, "points 3"]:
    """Linear (DLT) triangulation of points seen in k views each: the null vector of the stacked rows
    u P_2 - P_0 and v P_2 - P_1, in double precision (the system is badly scaled in pixels)."""
    p = projections.double()[view]  # points k 3 4
    uv = pixels.double()
    rows = torch.cat([uv[..., :1] * p[..., 2, :] - p[..., 0, :], uv[..., 1:] * p[..., 2, :] - p[..., 1, :]], dim=1)
    # Normalise rows so every equation weighs alike whatever the pixel magnitudes.
    rows = rows / rows.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    _, _, vh = torch.linalg.svd(rows)
    homogeneous = vh[:, -1]
    w = homogeneous[:, 3:]
    # A point at infinity (w ~ 0) cannot be placed; it is returned as NaN and dropped by the caller.
    w = torch.where(w.abs() < 1e-12, torch.full_like(w, float("nan")), w)
    return (homogeneous[:, :3] / w).to(pixels.dtype)


def triangulation_angles(
    points: Float[Tensor, "points 3"], centers: Float[Tensor, "points k 3"]
) -> Float[Tensor, " points"]:
    """Largest angle (degrees) between the rays from a point to the centres of the cameras seeing it."""
    rays = torch.nn.functional.normalize(centers - points[:, None], dim=-1)
    cos = torch.einsum("pid,pjd->pij", rays, rays).clamp(-1.0, 1.0)
    return torch.rad2deg(torch.arccos(cos.amin(dim=(1, 2))))


def build_tracks(matches: Dict[Tuple[int, int], np.ndarray], num_features: Sequence[int]) -> List[List[Tuple[int, int]]]:
    """Join pairwise matches into tracks (connected components of (view, feature) nodes). A track that
    holds two features of one view is contradictory and dropped; so are tracks seen in fewer than 2 views."""
    offsets = np.concatenate([[0], np.cumsum(num_features)])
    parent = list(range(int(offsets[-1])))

    def find(a: int) -> int:
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for (i, j), pairs in matches.items():
        for a, b in np.asarray(pairs, dtype=np.int64).reshape(-1, 2):
            ra, rb = find(int(offsets[i] + a)), find(int(offsets[j] + b))
            if ra != rb:
                parent[ra] = rb
    groups: Dict[int, List[Tuple[int, int]]] = {}
    matched = {int(offsets[i] + a) for (i, _), p in matches.items() for a in np.asarray(p).reshape(-1, 2)[:, 0]}
    matched |= {int(offsets[j] + b) for (_, j), p in matches.items() for b in np.asarray(p).reshape(-1, 2)[:, 1]}
    for node in sorted(matched):
        view = int(np.searchsorted(offsets, node, side="right") - 1)
        groups.setdefault(find(node), []).append((view, node - int(offsets[view])))
    tracks = []
    for track in groups.values():
        views = [v for v, _ in track]
        if len(track) >= 2 and len(set(views)) == len(views):
            tracks.append(sorted(track))
    return tracks


def triangulate_checked(
    projections: Float[Tensor, "views 3 4"], camera_to_worlds: Float[Tensor, "views 3 4"],
    intrinsics: Float[Tensor, "views 4"], view: Int[Tensor, "points k"], observed: Float[Tensor, "points k 2"],
    max_error: float, min_angle: float,
):
    """DLT of points seen in k views each and which to keep: finite, in front of every camera, within
    ``max_error`` pixels of every observation and seen under at least ``min_angle`` degrees. Returns (points,
    keep, their projections); a point that cannot be placed is zeros and not kept."""
    points = triangulate_dlt(projections, view, observed)
    finite = torch.isfinite(points).all(dim=-1)
    points = torch.where(finite[:, None], points, torch.zeros_like(points))
    proj = project_to_camera(points[:, None].expand(-1, view.shape[1], -1), camera_to_worlds[view], intrinsics[view])
    error = (proj.pixels - observed).norm(dim=-1)
    angle = triangulation_angles(points, camera_to_worlds[view][..., :3, 3])
    keep = finite & proj.in_front.all(dim=1) & (error <= max_error).all(dim=1) & (angle >= min_angle)
    return points, keep, proj


def triangulate_tracks(
    tracks: List[List[Tuple[int, int]]],
    keypoints: Sequence[Float[Tensor, "features 2"]],
    camera_to_worlds: Float[Tensor, "views 3 4"],
    intrinsics: Float[Tensor, "views 4"],
    options: TriangulationOptions,
    depth_bounds: Optional[Tuple[float, float]] = None,
) -> SparseDepth:
    """Triangulate every track and keep the points in front of all their cameras, reprojecting within
    ``max_reprojection_error`` pixels and seen under at least ``min_triangulation_angle`` degrees.

    ``depth_bounds`` (near, far), when the scene has them (LLFF's come from COLMAP's own points), also drops
    points whose depth along any observing camera's axis falls outside them: with two views a wrong match
    anywhere on the epipolar line triangulates with zero reprojection error, and only the bounds catch it.
    """
    dtype = camera_to_worlds.dtype
    projections = opencv_projection_matrices(camera_to_worlds, intrinsics)
    centers = camera_to_worlds[:, :3, 3]
    kept_points, views, point_ids, pixels, depths = [], [], [], [], []
    by_length: Dict[int, List[List[Tuple[int, int]]]] = {}
    for track in tracks:
        if len(track) >= max(2, options.min_track_length):
            by_length.setdefault(len(track), []).append(track)
    count = 0
    for length, group in sorted(by_length.items()):
        view = torch.tensor([[v for v, _ in t] for t in group], dtype=torch.long)
        observed = torch.stack([torch.stack([keypoints[v][f] for v, f in t]) for t in group]).to(dtype)
        points, keep, proj = triangulate_checked(
            projections, camera_to_worlds, intrinsics, view, observed, options.max_reprojection_error,
            options.min_triangulation_angle,
        )
        if depth_bounds is not None:
            keep &= ((proj.depth >= depth_bounds[0]) & (proj.depth <= depth_bounds[1])).all(dim=1)
        points, view, proj_pixels = points[keep], view[keep], proj.pixels[keep]
        ids = torch.arange(count, count + points.shape[0])[:, None].expand(-1, length)
        kept_points.append(points)
        views.append(view.flatten())
        point_ids.append(ids.flatten())
        pixels.append(proj_pixels.reshape(-1, 2))
        depths.append((points[:, None] - centers[view]).norm(dim=-1).flatten())
        count += points.shape[0]
    if not kept_points:
        return no_points(dtype)
    return SparseDepth(torch.cat(kept_points), torch.cat(views), torch.cat(point_ids), torch.cat(pixels), torch.cat(depths))


def no_points(dtype: torch.dtype) -> SparseDepth:
    empty = torch.zeros(0, dtype=dtype)
    return SparseDepth(empty.reshape(0, 3), torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.long), empty.reshape(0, 2), empty)


def points_inside_box(sparse: SparseDepth, aabb: Float[Tensor, "2 3"]) -> SparseDepth:
    """Only the observations of points inside the scene box (the field cannot render depth outside it; in
    object scenes a point outside is a wrong match on the background). Point indices are renumbered."""
    inside = ~beyond_box(sparse.points, aabb)
    new_index = torch.cumsum(inside.long(), 0) - 1
    keep = inside[sparse.point]
    return SparseDepth(
        sparse.points[inside], sparse.view[keep], new_index[sparse.point[keep]], sparse.pixels[keep], sparse.depth[keep]
    )


# ---- features (pycolmap) and matches ----------------------------------------------------------------------------
def _pycolmap():
    try:
        import pycolmap
    except ImportError as err:  # pragma: no cover - pycolmap is a dependency
        raise ImportError("sparse depth needs pycolmap (pip install pycolmap)") from err
    return pycolmap


def extract_sift(
    images: Sequence[np.ndarray], max_features: int, progress: bool = True, upsample: int = 1,
    peak_threshold: Optional[float] = None,
) -> Tuple[List[Tensor], List[Tensor]]:
    """SIFT keypoints ((u, v) per feature) and unit-length float descriptors of uint8 grey or RGB images, on
    the CPU, at most ``max_features`` per image (the largest-scale ones: they repeat best across views;
    pycolmap's own cap is not applied by its in-memory extractor).

    ``upsample`` > 1 runs SIFT on each image enlarged that many times (bicubic) and keeps up to ``max_features``
    x upsample^2 features; the keypoints are divided back into the image's pixels (COLMAP's and our pixel
    centres both lie at i + 0.5, so the image spans [0, W] at either size and the map is a plain division).
    ``peak_threshold``: the detector's contrast threshold (None: COLMAP's default); lower finds more features
    in low-contrast regions."""
    upsample = int(upsample)
    if upsample < 1:
        raise ValueError(f"sift upsample must be a whole number >= 1, got {upsample}")
    max_features = int(max_features) * upsample * upsample
    pycolmap = _pycolmap()
    options = pycolmap.FeatureExtractionOptions()
    options.sift.max_num_features = max_features
    if peak_threshold is not None:
        options.sift.peak_threshold = float(peak_threshold)
    extractor = pycolmap.FeatureExtractor.create(options, pycolmap.Device.cpu)
    keypoints, descriptors = [], []
    ticker = Progress(len(images), "frugalnerf sparse points: SIFT", "view", "views/s", 5.0, quiet_seconds=3.0) if progress else None
    for image in images:
        grey = image if image.ndim == 2 else np.asarray(image[..., :3].astype(np.float32) @ [0.299, 0.587, 0.114])
        grey = np.clip(grey, 0, 255).astype(np.uint8)
        if upsample > 1:
            from PIL import Image

            height, width = grey.shape
            grey = np.asarray(Image.fromarray(grey).resize((width * upsample, height * upsample), Image.BICUBIC))
        kps, desc = extractor.extract_from_uint8_array(np.ascontiguousarray(grey))
        uv = torch.tensor([[kp.x, kp.y] for kp in kps], dtype=torch.float64).reshape(-1, 2) / upsample
        scale = torch.tensor([abs(kp.a11 * kp.a22 - kp.a12 * kp.a21) for kp in kps], dtype=torch.float64)
        # 128-wide even without features (a blank image), so matching sees an empty (0, 128) set.
        features = torch.from_numpy(np.asarray(desc.data, dtype=np.float32)).reshape(len(kps), SIFT_DIMENSIONS)
        if len(kps) > max_features:
            keep = torch.sort(torch.argsort(scale, descending=True)[:max_features]).values
            uv, features = uv[keep], features[keep]
        keypoints.append(uv)
        descriptors.append(torch.nn.functional.normalize(features, dim=-1))
        if ticker is not None:
            ticker.tick()
    return keypoints, descriptors


def match_descriptors(
    a: Float[Tensor, "n d"], b: Float[Tensor, "m d"], max_ratio: float = 0.8, max_distance: float = 0.7
) -> Int[Tensor, "matches 2"]:
    """COLMAP's SIFT matching rule on unit descriptors: the angle to the nearest descriptor at most
    ``max_distance`` radians and below ``max_ratio`` times the angle to the second nearest, both ways, and
    the two directions agree (cross-check). Returns (index in a, index in b) pairs."""
    if len(a) < 2 or len(b) < 2:
        return torch.zeros(0, 2, dtype=torch.long)

    def one_way(similarity: Tensor) -> Tensor:
        top = similarity.topk(2, dim=1)
        angles = torch.arccos(top.values.clamp(-1.0, 1.0))
        ok = (angles[:, 0] <= max_distance) & (angles[:, 0] < max_ratio * angles[:, 1])
        return torch.where(ok, top.indices[:, 0], torch.full_like(top.indices[:, 0], -1))

    similarity = a @ b.T
    forward, backward = one_way(similarity), one_way(similarity.T)
    rows = torch.nonzero(forward >= 0)[:, 0]
    mutual = backward[forward[rows]] == rows
    return torch.stack([rows[mutual], forward[rows][mutual]], dim=-1)


def neighbour_pairs(camera_to_worlds: Float[Tensor, "views 3 4"], neighbors: int) -> List[Tuple[int, int]]:
    """Pairs (i, j), i < j, joining every view with its ``neighbors`` nearest cameras (by centre distance):
    at most views x neighbors pairs instead of views^2 / 2; every pair when views <= neighbors + 1."""
    count = camera_to_worlds.shape[0]
    if count <= neighbors + 1:
        return [(i, j) for i in range(count) for j in range(i + 1, count)]
    centers = camera_to_worlds[:, :3, 3].double()
    distance = torch.cdist(centers, centers)
    distance.fill_diagonal_(float("inf"))
    nearest = distance.topk(neighbors, dim=1, largest=False).indices
    return sorted({(min(i, int(j)), max(i, int(j))) for i in range(count) for j in nearest[i]})


def match_pairs(
    descriptors: Sequence[Tensor], pairs: Sequence[Tuple[int, int]], progress: bool = True
) -> Dict[Tuple[int, int], np.ndarray]:
    """Matches of each pair of views; no geometric verification here: the known cameras check every match
    when its point is triangulated."""
    ticker = Progress(len(pairs), "frugalnerf sparse points: matching", "pair", "pairs/s", 5.0, quiet_seconds=3.0) if progress else None
    matches = {}
    for i, j in pairs:
        matches[(i, j)] = match_descriptors(descriptors[i], descriptors[j]).numpy()
        if ticker is not None:
            ticker.tick()
    return matches


def training_view_matches(
    images: Sequence[np.ndarray], camera_to_worlds: Float[Tensor, "views 3 4"], options: TriangulationOptions,
    progress: bool = True,
) -> Tuple[List[Tensor], Dict[Tuple[int, int], np.ndarray]]:
    """(keypoints per view, matches per pair of nearby views): SIFT and matching."""
    keypoints, descriptors = extract_sift(images, options.max_features, progress, options.sift_upsample)
    return keypoints, match_pairs(descriptors, neighbour_pairs(camera_to_worlds, options.match_neighbors), progress)


def triangulate_training_views(
    images: Sequence[np.ndarray],
    camera_to_worlds: Float[Tensor, "views 3 4"],
    intrinsics: Float[Tensor, "views 4"],
    options: Optional[TriangulationOptions] = None,
    depth_bounds: Optional[Tuple[float, float]] = None,
    progress: bool = True,
    found: Optional[Tuple[List[Tensor], Dict[Tuple[int, int], np.ndarray]]] = None,
) -> SparseDepth:
    """Sparse points of the training views: SIFT, matching of nearby views and triangulation with the fixed
    cameras (``found``: the ``training_view_matches`` of these images, when the caller has them)."""
    options = options or TriangulationOptions()
    keypoints, matches = found or training_view_matches(images, camera_to_worlds, options, progress)
    tracks = build_tracks(matches, [len(k) for k in keypoints])
    sparse = triangulate_tracks(tracks, keypoints, camera_to_worlds.double(), intrinsics.double(), options, depth_bounds)
    if options.dense_stereo:
        bounds = depth_bounds or z_depth_range(sparse, camera_to_worlds.double(), intrinsics.double())
        if bounds is not None:
            stereo = stereo_points(images, camera_to_worlds.double(), intrinsics.double(), bounds, options, progress)
            sparse = concatenate([sparse, stereo])
    return sparse


def z_depth_range(
    sparse: SparseDepth, camera_to_worlds: Float[Tensor, "views 3 4"], intrinsics: Float[Tensor, "views 4"], margin: float = 1.25
) -> Optional[Tuple[float, float]]:
    """The z-depths of the observations, widened by ``margin`` either way; None without points."""
    if sparse.num_points == 0:
        return None
    z = project_to_camera(sparse.points[sparse.point], camera_to_worlds[sparse.view], intrinsics[sparse.view]).depth
    return float(z.min()) / margin, float(z.max()) * margin


def grey_levels(image: np.ndarray) -> Float[Tensor, "height width"]:
    """A uint8 grey or RGB image as grey levels in [0, 1] (float32)."""
    rgb = torch.from_numpy(np.asarray(image, dtype=np.float32)) / 255.0
    if rgb.ndim == 2:
        return rgb
    return rgb[..., :3] @ torch.tensor([0.299, 0.587, 0.114])


def stereo_points(
    images: Sequence[np.ndarray],
    camera_to_worlds: Float[Tensor, "views 3 4"],
    intrinsics: Float[Tensor, "views 4"],
    bounds: Tuple[float, float],
    options: TriangulationOptions,
    progress: bool = True,
    stereo: Optional[StereoOptions] = None,
) -> SparseDepth:
    """Plane-sweep matches between each view and its nearest camera, as two-view points: in both cameras' depth
    ``bounds`` (z) and seen under at least ``min_triangulation_angle`` degrees."""
    stereo = stereo or StereoOptions()
    pairs = neighbour_pairs(camera_to_worlds, 1)
    ticker = Progress(len(pairs), "frugalnerf sparse points: plane-sweep stereo", "pair", "pairs/s", 5.0, quiet_seconds=3.0) if progress else None
    found = []
    for i, j in pairs:
        pair = torch.tensor([i, j])
        match = stereo_matches((grey_levels(images[i]), grey_levels(images[j])), camera_to_worlds[pair].float(),
                               intrinsics[pair].float(), *bounds, stereo)
        points = match.points.to(camera_to_worlds.dtype)
        view = pair.expand(points.shape[0], 2)
        z = project_to_camera(points[:, None].expand(-1, 2, -1), camera_to_worlds[view], intrinsics[view]).depth
        angle = triangulation_angles(points, camera_to_worlds[view][..., :3, 3])
        keep = ((z >= bounds[0]) & (z <= bounds[1])).all(dim=1) & (angle >= options.min_triangulation_angle)
        n = int(keep.sum())
        points = points[keep]
        pixels = torch.stack([match.reference_pixels[keep], match.source_pixels[keep]], 1).to(camera_to_worlds.dtype)
        depth = (points[:, None] - camera_to_worlds[pair, :3, 3][None]).norm(dim=-1)
        found.append(SparseDepth(points, view[keep].reshape(-1), torch.arange(n)[:, None].expand(n, 2).reshape(-1),
                                 pixels.reshape(-1, 2), depth.reshape(-1)))
        if ticker is not None:
            ticker.tick()
    return concatenate(found)


def concatenate(parts: Sequence[SparseDepth]) -> SparseDepth:
    """One set of points from several, point indices renumbered."""
    if not parts:
        return no_points(torch.float64)
    offsets = np.cumsum([0] + [p.num_points for p in parts])
    return SparseDepth(
        torch.cat([p.points for p in parts]), torch.cat([p.view for p in parts]),
        torch.cat([p.point + int(o) for p, o in zip(parts, offsets)]), torch.cat([p.pixels for p in parts]),
        torch.cat([p.depth for p in parts]),
    )
