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
from frugalnerf_ns.data.sparse_points import (
    SparseDepth,
    build_tracks,
    extract_sift,
    match_descriptors,
    opencv_projection_matrices,
    triangulate_checked,
)
from frugalnerf_ns.geometry.reprojection import project_to_camera
from frugalnerf_ns.geometry.camera_conventions import opencv_to_opengl

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


def world_to_camera_to_opengl(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """COLMAP's cam_from_world (x = R X + t, OpenCV axes) as an OpenGL camera-to-world 3x4."""
    c2w = np.concatenate([rotation.T, (-rotation.T @ translation).reshape(3, 1)], axis=1)
    return opencv_to_opengl(c2w)


def opengl_to_world_to_camera(c2w: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Inverse of ``world_to_camera_to_opengl``: (R, t) of COLMAP's cam_from_world."""
    c2w = opencv_to_opengl(c2w)  # the flip is its own inverse
    rotation = c2w[:3, :3].T
    return rotation, -rotation @ c2w[:3, 3]


def _pycolmap():
    import pycolmap

    return pycolmap


def _camera(width: int, height: int, focal: float, radial: bool = False):
    """One shared pinhole camera, principal point at the centre; ``radial``: with one radial distortion term
    (starting at 0) for the bundle adjustment that refines the focal length."""
    pycolmap = _pycolmap()
    model = "SIMPLE_RADIAL" if radial else "SIMPLE_PINHOLE"
    camera = pycolmap.Camera.create_from_model_name(1, model, float(focal), int(width), int(height))
    camera.params = np.array([focal, width / 2.0, height / 2.0] + ([0.0] if radial else []))
    return camera


def verified_matches(
    keypoints: Sequence[Tensor], descriptors: Sequence[Tensor], width: int, height: int, focal: float,
    options: PoseEstimationOptions, max_ratio: float = 0.8,
) -> Dict[Tuple[int, int], np.ndarray]:
    """Matches of every pair that agree with one essential matrix (calibrated two-view geometry)."""
    pycolmap = _pycolmap()
    camera = _camera(width, height, focal)
    geometry_options = pycolmap.TwoViewGeometryOptions()
    geometry_options.ransac.max_error = options.max_epipolar_error
    geometry_options.ransac.random_seed = options.seed
    geometry_options.min_num_inliers = 8
    # A handful of photos of one scene: a plane (a wall, a table) is a real scene, not a watermark.
    geometry_options.detect_watermark = False
    verified = {}
    count = len(keypoints)
    for i in range(count):
        for j in range(i + 1, count):
            matches = match_descriptors(descriptors[i], descriptors[j], max_ratio).numpy()
            if len(matches) < 8:
                verified[(i, j)] = np.zeros((0, 2), dtype=np.int64)
                continue
            geometry = pycolmap.estimate_calibrated_two_view_geometry(
                camera, keypoints[i].numpy(), camera, keypoints[j].numpy(), matches.astype(np.uint32), geometry_options
            )
            inliers = np.asarray(geometry.inlier_matches, dtype=np.int64).reshape(-1, 2)
            verified[(i, j)] = inliers
    return verified


def check_connected(verified: Dict[Tuple[int, int], np.ndarray], names: Sequence[str], minimum: int) -> None:
    """One line naming the photo that shares too few verified matches with every other photo."""
    for view, name in enumerate(names):
        best = max((len(m) for (i, j), m in verified.items() if view in (i, j)), default=0)
        if best < minimum:
            raise DataError(
                f"photo {name} shares at most {best} verified matches with the other photos (at least {minimum} "
                "needed): is it of the same scene, with enough overlap and texture?"
            )


def _relative_pose(keypoints, pair, matches, width, height, focal, options):
    """cam2_from_cam1 (R, t with |t| = 1) of the starting pair from its verified matches."""
    pycolmap = _pycolmap()
    camera = _camera(width, height, focal)
    i, j = pair
    ransac = pycolmap.RANSACOptions()
    ransac.max_error = options.max_epipolar_error
    ransac.random_seed = options.seed
    result = pycolmap.estimate_relative_pose(
        camera, keypoints[i].numpy()[matches[:, 0]], camera, keypoints[j].numpy()[matches[:, 1]], ransac
    )
    if result is None:
        return None
    pose = result["cam2_from_cam1"]
    rotation = np.asarray(pose.rotation.matrix())
    translation = np.asarray(pose.translation, dtype=np.float64)
    return rotation, translation / max(np.linalg.norm(translation), 1e-12)


def triangulate_tracks_in(
    tracks: List[List[Tuple[int, int]]], keypoints: Sequence[Tensor], poses: Dict[int, np.ndarray], focal: float,
    width: int, height: int, max_error: float, min_angle: float,
) -> Tuple[np.ndarray, np.ndarray]:
    """(points [tracks, 3], valid [tracks]) from each track's observations in the registered ``poses``:
    DLT, then kept when in front of every camera, within ``max_error`` pixels in all and seen under at least
    ``min_angle`` degrees."""
    points = np.full((len(tracks), 3), np.nan)
    valid = np.zeros(len(tracks), dtype=bool)
    registered = sorted(poses)
    if len(registered) < 2:
        return points, valid
    local = {v: k for k, v in enumerate(registered)}
    c2w = torch.from_numpy(np.stack([poses[v] for v in registered]))
    intrinsics = torch.tensor([[focal, focal, width / 2.0, height / 2.0]], dtype=torch.float64).expand(len(registered), 4)
    projections = opencv_projection_matrices(c2w, intrinsics)
    by_length: Dict[int, List[int]] = {}
    for index, track in enumerate(tracks):
        seen = sum(v in local for v, _ in track)
        if seen >= 2:
            by_length.setdefault(seen, []).append(index)
    for indices in by_length.values():
        view = torch.tensor([[local[v] for v, _ in tracks[t] if v in local] for t in indices], dtype=torch.long)
        observed = torch.stack(
            [torch.stack([keypoints[v][f] for v, f in tracks[t] if v in local]) for t in indices]
        ).double()
        xyz, keep, _ = triangulate_checked(projections, c2w, intrinsics, view, observed, max_error, min_angle)
        rows = np.asarray(indices)[keep.numpy()]
        points[rows] = xyz[keep].numpy()
        valid[rows] = True
    return points, valid


def register_view(
    view: int, tracks, keypoints, points: np.ndarray, valid: np.ndarray, width: int, height: int, focal: float,
    options: PoseEstimationOptions,
) -> Tuple[Optional[np.ndarray], int]:
    """(OpenGL camera-to-world of ``view`` from its features' matches to triangulated points by absolute pose,
    or None; the number of 2D-3D matches it had, or of inliers when it succeeded)."""
    points2d, points3d = [], []
    for index, track in enumerate(tracks):
        if not valid[index]:
            continue
        features = dict(track)
        if view in features:
            points2d.append(keypoints[view][features[view]].numpy())
            points3d.append(points[index])
    if len(points2d) < 6:
        return None, len(points2d)
    c2w, inliers = absolute_pose(np.asarray(points2d), np.asarray(points3d), width, height, focal, options)
    return c2w, (len(points2d) if c2w is None else inliers)


def absolute_pose(
    points2d: np.ndarray, points3d: np.ndarray, width: int, height: int, focal: float, options: PoseEstimationOptions
) -> Tuple[Optional[np.ndarray], int]:
    """(OpenGL camera-to-world, inliers) of a camera seeing ``points3d`` at ``points2d`` (P3P in LO-RANSAC,
    then refined; the focal length fixed), or (None, 0)."""
    pycolmap = _pycolmap()
    estimation = pycolmap.AbsolutePoseEstimationOptions()
    estimation.ransac.max_error = 2.0 * options.max_reprojection_error
    estimation.ransac.random_seed = options.seed
    refinement = pycolmap.AbsolutePoseRefinementOptions()
    refinement.refine_focal_length = False
    refinement.refine_extra_params = False
    result = pycolmap.estimate_and_refine_absolute_pose(
        points2d.astype(np.float64), points3d.astype(np.float64), _camera(width, height, focal), estimation, refinement
    )
    if result is None:
        return None, 0
    pose = result["cam_from_world"]
    return world_to_camera_to_opengl(np.asarray(pose.rotation.matrix()), np.asarray(pose.translation)), int(result["num_inliers"])


def bundle_adjust(
    tracks, keypoints, poses: Dict[int, np.ndarray], points: np.ndarray, valid: np.ndarray, focal: float,
    width: int, height: int, refine_focal: bool,
) -> Tuple[Dict[int, np.ndarray], np.ndarray, float]:
    """Poses, points and (``refine_focal``) the focal length refined together (pycolmap's bundle adjustment,
    Cauchy loss; the gauge fixed by two cameras). The focal length is refined together with one radial
    distortion term: phone lenses have some, and without it the focal length absorbs it (on LLFF photos,
    -18 % to +8 % off; with it, -14 % to +2 %, docs/notes/captures.md). Only the focal length is kept: the renderer's
    cameras are pinholes, and the adjustments after this one fit the poses and points to them."""
    pycolmap = _pycolmap()
    reconstruction = pycolmap.Reconstruction()
    reconstruction.add_camera_with_trivial_rig(_camera(width, height, focal, radial=refine_focal))
    image_id = {}
    for view in sorted(poses):
        image = pycolmap.Image(
            name=f"{view}", keypoints=keypoints[view].numpy().astype(np.float64), camera_id=1, image_id=view + 1
        )
        rotation, translation = opengl_to_world_to_camera(poses[view])
        reconstruction.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), translation))
        image_id[view] = view + 1
    point_id = {}
    for index, track in enumerate(tracks):
        if not valid[index]:
            continue
        elements = [pycolmap.TrackElement(image_id[v], f) for v, f in track if v in poses]
        if len(elements) < 2:
            continue
        point_id[index] = reconstruction.add_point3D(points[index], pycolmap.Track(elements))
    config = pycolmap.BundleAdjustmentConfig()
    for view in sorted(poses):
        config.add_image(image_id[view])
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_focal_length = refine_focal
    ba.refine_principal_point = False
    ba.refine_extra_params = refine_focal
    ba.print_summary = False
    ba.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    bundle_adjuster = pycolmap.create_default_bundle_adjuster(ba, config, reconstruction)
    bundle_adjuster.solve()
    refined = {}
    for view in sorted(poses):
        pose = reconstruction.image(image_id[view]).cam_from_world()
        refined[view] = world_to_camera_to_opengl(np.asarray(pose.rotation.matrix()), np.asarray(pose.translation))
    new_points = points.copy()
    for index, pid in point_id.items():
        new_points[index] = np.asarray(reconstruction.point3D(pid).xyz)
    return refined, new_points, float(reconstruction.camera(1).params[0])


def observations(
    tracks, keypoints, poses: Dict[int, np.ndarray], points: np.ndarray, valid: np.ndarray, focal: float,
    width: int, height: int, max_error: float,
) -> Tuple[SparseDepth, np.ndarray, float]:
    """The kept points as ``SparseDepth`` (observations in registered views; a point reprojecting further than
    ``max_error`` from any observation, or behind a camera, is dropped), each kept point's track index and the
    kept observations' mean reprojection error (pixels)."""
    views = sorted(poses)
    c2w = torch.from_numpy(np.stack([poses[v] for v in views]))
    local = {v: k for k, v in enumerate(views)}
    intrinsics = torch.tensor([[focal, focal, width / 2.0, height / 2.0]], dtype=torch.float64)
    kept, obs_view, obs_point, obs_pixels, obs_depth, errors = [], [], [], [], [], []
    for index, track in enumerate(tracks):
        if not valid[index]:
            continue
        seen = [(v, f) for v, f in track if v in local]
        if len(seen) < 2:
            continue
        xyz = torch.from_numpy(points[index]).expand(len(seen), 3)
        cams = c2w[[local[v] for v, _ in seen]]
        proj = project_to_camera(xyz, cams, intrinsics.expand(len(seen), 4))
        observed = torch.stack([keypoints[v][f] for v, f in seen]).double()
        error = (proj.pixels - observed).norm(dim=-1)
        if not bool(proj.in_front.all()) or float(error.max()) > max_error:
            continue
        errors.append(error)
        point = len(kept)
        kept.append(index)
        obs_view += [v for v, _ in seen]
        obs_point += [point] * len(seen)
        obs_pixels.append(proj.pixels)
        obs_depth.append((xyz - cams[:, :3, 3]).norm(dim=-1))
    if not kept:
        empty = torch.zeros(0, dtype=torch.float64)
        none = torch.zeros(0, dtype=torch.long)
        return SparseDepth(empty.reshape(0, 3), none, none, empty.reshape(0, 2), empty), np.zeros(0, dtype=np.int64), math.nan
    sparse = SparseDepth(
        torch.from_numpy(points[kept]), torch.tensor(obs_view), torch.tensor(obs_point), torch.cat(obs_pixels),
        torch.cat(obs_depth),
    )
    return sparse, np.asarray(kept), float(torch.cat(errors).mean())


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
    relative = _relative_pose(keypoints, start, verified[start], width, height, focal, options)
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
