"""Cameras of a few photos without poses (issue 33), estimated in-process with pycolmap: no COLMAP binary,
nothing downloaded.

COLMAP's own pipeline is built for many photos: incremental mapping initialises only from a pair with 100
verified inliers and 16 degrees of triangulation angle and keeps models of 10 images or more, so 2-4 photos
of one scene rarely come out. Here the steps are the same, with the few-view cases made explicit:

1. SIFT per photo and every pair matched (``sparse_points``: COLMAP's matching rule, in torch);
2. each pair verified with the calibrated two-view geometry (essential matrix, LO-RANSAC) at the shared
   focal length guess; a photo whose best partner shares fewer than ``min_verified_matches`` is an error;
3. the pair with the most verified matches is the start: its relative pose from the essential matrix,
   then its matches triangulated (two photos end here);
4. every other photo registered by absolute pose (P3P, LO-RANSAC) from its matches to the points, more
   points triangulated after each;
5. bundle adjustment over everything: one shared pinhole camera (principal point at the centre) at the focal
   length EXIF says, else from an assumed field of view refined with three or more photos (two do not
   determine it).

Test photos of a benchmark are registered afterwards with ``register_photos``: absolute pose against the
training points, the training cameras, points and focal length fixed.

Conventions are nerfstudio's: camera-to-world 3x4 with OpenGL axes; pixels (u, v) from the top-left corner
with centres at i + 0.5 (COLMAP's keypoints use the same).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Dict, List, NamedTuple, Optional, Sequence, Tuple

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

from frugalnerf_ns.data.input_checks import DataError
from frugalnerf_ns.data.photo_geometry import (
    absolute_pose,
    bundle_adjust,
    observations,
    register_view,
    relative_pose,
    triangulate_tracks_in,
    verified_matches,
    world_to_camera_to_opengl,
)
from frugalnerf_ns.data.sparse_points import (
    SparseDepth,
    build_tracks,
    extract_sift,
    match_descriptors,
)

DEFAULT_FIELD_OF_VIEW = 65.0
"""Degrees across the long side when a photo says nothing of its lens (a phone's main camera: 26 mm
equivalent is 69 degrees; LLFF's phone 64)."""


class FeatureSettings(NamedTuple):
    """SIFT detection and matching of one attempt at registering the photos."""

    peak_threshold: Optional[float] = None
    """The detector's contrast threshold (None: COLMAP's default, 0.0067)."""
    max_ratio: float = 0.8
    """Ratio test of the matching (COLMAP's default 0.8)."""

    def describe(self) -> str:
        return f"SIFT peak threshold {self.peak_threshold}, ratio test {self.max_ratio}"


FEATURE_ATTEMPTS = (FeatureSettings(), FeatureSettings(peak_threshold=0.002, max_ratio=0.9))
"""Tried in order until the photos register: COLMAP's settings, then, for photos taken far apart, features of
lower contrast and a looser ratio test (every pair is still verified by its essential matrix). The juice box's
views 45 13 29 46 (73 degrees, one photo looking down at the box): 16 verified matches for the photo with the
fewest at COLMAP's settings, 63 at the second. Larger images (1280 px: 13) and affine-shape or
domain-size-pooled SIFT (12-17) did not help as much at 640 px (docs/notes/captures.md)."""


@dataclass(frozen=True)
class PoseEstimationOptions:
    """How the cameras of a few photos are estimated. Frozen, so one instance can be a class-level default: a
    run's config.yml saved before a config had these options loads without them and reads the default."""

    max_features: int = 8192
    """SIFT features per photo (the largest-scale ones are kept)."""
    min_verified_matches: int = 30
    """Fewest matches a photo must share, after geometric verification, with its best partner."""
    max_epipolar_error: float = 2.0
    """RANSAC threshold of the two-view verification, in pixels."""
    max_reprojection_error: float = 2.0
    """Points reprojecting further than this from any of their observations are dropped (pixels)."""
    min_triangulation_angle: float = 1.0
    """Smallest angle (degrees) between two rays of a kept point."""
    field_of_view: float = DEFAULT_FIELD_OF_VIEW
    """Field of view across the long side, degrees, where the photos' EXIF gives no focal length (kept as is
    unless refine-focal-length)."""
    refine_focal_length: Optional[bool] = None
    """Refine the shared focal length in bundle adjustment (with three or more photos; two do not determine
    it). Default: refined where EXIF gives no focal length, kept where it does (``focal_is_refined``)."""
    seed: int = 0
    """Seed of the RANSAC draws (the same photos give the same cameras)."""

    def key(self) -> Dict[str, Optional[float]]:
        return {k: None if v is None else float(v) for k, v in self.__dict__.items()}

    def focal_is_refined(self, num_photos: int, focal_from_exif: bool) -> bool:
        if num_photos < 3:
            return False
        return (not focal_from_exif) if self.refine_focal_length is None else self.refine_focal_length


class PhotoCameras(NamedTuple):
    """Estimated cameras of photos of one size and the points they see."""

    camera_to_worlds: Float[Tensor, "views 3 4"]
    """OpenGL camera-to-world of every photo, in the estimate's arbitrary frame and scale."""
    focal: float
    """Shared focal length in pixels (principal point at the image centre)."""
    width: int
    height: int
    points: SparseDepth
    """Points of the verified matches, with their observations (view = index among the photos)."""
    test_camera_to_worlds: Float[Tensor, "tests 3 4"]
    """Test photos registered against the points with everything above fixed (empty without test photos)."""
    reprojection_error: float = math.nan
    """Mean distance (pixels) between the points' projections and their SIFT keypoints."""

    @property
    def intrinsics(self) -> Float[Tensor, "views 4"]:
        views = self.camera_to_worlds.shape[0]
        return torch.tensor([[self.focal, self.focal, self.width / 2.0, self.height / 2.0]], dtype=torch.float64).expand(views, 4)


def focal_from_field_of_view(width: int, height: int, degrees: float) -> float:
    """Focal length in pixels of a pinhole whose long side spans ``degrees``."""
    return 0.5 * max(width, height) / math.tan(math.radians(degrees) / 2.0)


def focal_from_35mm(width: int, height: int, focal_35mm: float) -> float:
    """Focal length in pixels from EXIF's 35 mm equivalent (the long side of a 36 x 24 mm frame is 36 mm)."""
    return focal_35mm * max(width, height) / 36.0


def check_connected(verified: Dict[Tuple[int, int], np.ndarray], names: Sequence[str], minimum: int) -> None:
    """One line naming the photo that shares too few verified matches with every other photo."""
    for view, name in enumerate(names):
        best = max((len(m) for (i, j), m in verified.items() if view in (i, j)), default=0)
        if best < minimum:
            raise DataError(
                f"photo {name} shares at most {best} verified matches with the other photos (at least {minimum} "
                "needed): is it of the same scene, with enough overlap and texture?"
            )


def register_test_photos(
    images: Sequence[np.ndarray], names: Sequence[str], keypoints: Sequence[Tensor], descriptors: Sequence[Tensor],
    point_of_feature: Dict[Tuple[int, int], int], points: np.ndarray, focal: float, width: int, height: int,
    options: PoseEstimationOptions, unregistered_as_nan: bool = False, features: FeatureSettings = FeatureSettings(),
) -> List[np.ndarray]:
    """OpenGL camera-to-world of each test photo, by absolute pose from its matches to the training photos'
    points (``point_of_feature``: (training view, feature) -> row of ``points``). Nothing of the training
    reconstruction changes, so a benchmark's test photos never move the training cameras or points. A photo
    that cannot be registered is an error, or NaN with ``unregistered_as_nan`` (measurements). ``features``: the
    settings the training photos' features were found with."""
    test_keypoints, test_descriptors = extract_sift(images, options.max_features, progress=False,
                                                    peak_threshold=features.peak_threshold)
    minimum = options.min_verified_matches // 2
    poses = []
    for name, kps, desc in zip(names, test_keypoints, test_descriptors):
        pairs: Dict[int, int] = {}  # point -> test feature (the first match found)
        for view in range(len(keypoints)):
            for a, b in match_descriptors(desc, descriptors[view], features.max_ratio).tolist():
                point = point_of_feature.get((view, b))
                if point is not None and point not in pairs:
                    pairs[point] = a
        c2w, found = None, len(pairs)
        if len(pairs) >= max(minimum, 6):
            c2w, inliers = absolute_pose(kps.numpy()[list(pairs.values())], points[list(pairs)], width, height, focal, options)
            found = len(pairs) if c2w is None else inliers
        if c2w is None or found < minimum:
            if unregistered_as_nan:
                poses.append(np.full((3, 4), np.nan))
                continue
            raise DataError(
                f"test photo {name} could not be registered into the training photos' reconstruction: {found} "
                f"consistent matches to their points (at least {minimum} needed)"
            )
        poses.append(c2w)
    return poses


def estimate_cameras(
    images: Sequence[np.ndarray], names: Sequence[str], focal: Optional[float], options: PoseEstimationOptions,
    test_images: Sequence[np.ndarray] = (), test_names: Sequence[str] = (), unregistered_as_nan: bool = False,
) -> PhotoCameras:
    """Cameras of 2 or more photos of one size (uint8 RGB), see the module's steps, with the first of
    ``FEATURE_ATTEMPTS`` that registers every photo; then the test photos registered into that reconstruction
    (``register_test_photos``). ``focal``: the focal length in pixels when the photos say it (EXIF), else None
    (``options.field_of_view``). Raises ``DataError`` with one line naming the photo or the step that failed and
    what was tried."""
    if len(images) < 2:
        raise DataError(f"estimating cameras needs at least 2 photos (got {len(images)}: {', '.join(names)})")
    sizes = {image.shape[:2] for image in images}
    if len(sizes) != 1:
        raise DataError(f"the photos have different sizes ({sorted(sizes)}); one camera is estimated for all of them")
    height, width = images[0].shape[:2]
    refine = options.focal_is_refined(len(images), bool(focal))
    focal = float(focal) if focal else focal_from_field_of_view(width, height, options.field_of_view)
    failures: List[str] = []
    for features in FEATURE_ATTEMPTS:
        try:
            cameras, keypoints, descriptors, point_of_feature = _estimate(images, names, focal, refine, options, features)
            break
        except DataError as err:
            failures.append(str(err).removeprefix("frugalnerf: error: "))
    else:
        retried = "; ".join(f"with {f.describe()}: {why}" for f, why in zip(FEATURE_ATTEMPTS[1:], failures[1:]))
        raise DataError(f"{failures[0]} (also tried {retried})")
    if not len(test_images):
        return cameras
    if {image.shape[:2] for image in test_images} != {(height, width)}:
        raise DataError(f"test photos must have the training photos' size ({width}x{height})")
    tests = torch.from_numpy(np.stack(register_test_photos(
        test_images, test_names, keypoints, descriptors, point_of_feature, cameras.points.points.numpy(),
        cameras.focal, width, height, options, unregistered_as_nan, features,
    )))
    return cameras._replace(test_camera_to_worlds=tests)


def _estimate(
    images: Sequence[np.ndarray], names: Sequence[str], focal: float, refine: bool, options: PoseEstimationOptions,
    features: FeatureSettings,
) -> Tuple[PhotoCameras, List[Tensor], List[Tensor], Dict[Tuple[int, int], int]]:
    """One attempt with one feature setting: (cameras without test photos, the keypoints and descriptors, and
    (view, feature) -> row of the cameras' points, for registering test photos)."""
    height, width = images[0].shape[:2]
    keypoints, descriptors = extract_sift(images, options.max_features, progress=True,
                                          peak_threshold=features.peak_threshold)
    for name, kps in zip(names, keypoints):
        if len(kps) < options.min_verified_matches:
            raise DataError(f"photo {name} has {len(kps)} SIFT features (at least {options.min_verified_matches} needed): "
                            "is it blank, blurred or very dark?")
    verified = verified_matches(keypoints, descriptors, width, height, focal, options, features.max_ratio)
    check_connected(verified, names, options.min_verified_matches)
    tracks = build_tracks(verified, [len(k) for k in keypoints])
    start = max(verified, key=lambda pair: len(verified[pair]))
    relative = relative_pose(keypoints, start, verified[start], width, height, focal, options)
    if relative is None:
        raise DataError(
            f"photos {names[start[0]]} and {names[start[1]]}: no relative pose fits their {len(verified[start])} "
            "verified matches (try photos taken further apart, or with more of the scene in common)"
        )
    poses = {start[0]: world_to_camera_to_opengl(np.eye(3), np.zeros(3)),
             start[1]: world_to_camera_to_opengl(*relative)}
    points, valid = triangulate_tracks_in(tracks, keypoints, poses, focal, width, height,
                                          2.0 * options.max_reprojection_error, options.min_triangulation_angle)
    if valid.sum() < options.min_verified_matches // 2:
        raise DataError(
            f"photos {names[start[0]]} and {names[start[1]]}: only {int(valid.sum())} of their matches triangulate "
            f"at {options.min_triangulation_angle} degrees or more: the photos were taken from (almost) one place; "
            "move the camera between photos, not only turn it"
        )
    poses, points, focal = bundle_adjust(tracks, keypoints, poses, points, valid, focal, width, height, False)
    while len(poses) < len(images):
        candidates = [v for v in range(len(images)) if v not in poses]
        attempts = {v: register_view(v, tracks, keypoints, points, valid, width, height, focal, options) for v in candidates}
        view = max(candidates, key=lambda v: attempts[v][1] if attempts[v][0] is not None else -1)
        c2w, count = attempts[view]
        if c2w is None or count < options.min_verified_matches // 2:
            raise DataError(
                f"photo {names[view]} could not be placed: {count} of its features match triangulated points "
                f"(at least {options.min_verified_matches // 2} needed)"
            )
        poses[view] = c2w
        points, valid = triangulate_tracks_in(tracks, keypoints, poses, focal, width, height,
                                              2.0 * options.max_reprojection_error, options.min_triangulation_angle)
        poses, points, focal = bundle_adjust(tracks, keypoints, poses, points, valid, focal, width, height,
                                             refine and len(poses) >= 3)
    # Passes without the outliers the first adjustments carried; the last one as pinholes at the focal length
    # found (what the renderer's cameras are).
    for final in (False, False, True):
        sparse, kept, _ = observations(tracks, keypoints, poses, points, valid, focal, width, height, options.max_reprojection_error)
        valid = np.zeros_like(valid)
        valid[kept] = True
        poses, points, focal = bundle_adjust(tracks, keypoints, poses, points, valid, focal, width, height,
                                             refine and len(poses) >= 3 and not final)
    sparse, kept, error = observations(tracks, keypoints, poses, points, valid, focal, width, height, options.max_reprojection_error)
    seen = np.bincount(sparse.view.numpy(), minlength=len(images))
    for view in np.flatnonzero(seen < options.min_verified_matches // 2):
        raise DataError(
            f"photo {names[view]} sees {seen[view]} of the estimate's points after the adjustment (at least "
            f"{options.min_verified_matches // 2} needed): its camera is not determined"
        )
    c2w = torch.from_numpy(np.stack([poses[v] for v in range(len(images))]))
    point_of_feature = {(v, f): row for row, index in enumerate(kept) for v, f in tracks[index]}
    cameras = PhotoCameras(c2w, focal, width, height, sparse, torch.zeros(0, 3, 4, dtype=torch.float64), error)
    return cameras, keypoints, descriptors, point_of_feature
