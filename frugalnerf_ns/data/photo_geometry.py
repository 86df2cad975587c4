"""The geometric steps of estimating a few photos' cameras, each one call into pycolmap (no COLMAP binary):
pairs verified by their essential matrix, the starting pair's relative pose, tracks triangulated in the
registered cameras, a photo placed by absolute pose, bundle adjustment, and the points kept as sparse depth.
``photo_poses`` runs them in order. Cameras are nerfstudio's (OpenGL camera-to-world 3x4); COLMAP's
cam_from_world (OpenCV axes) is converted at the boundary.
"""

from __future__ import annotations

import math
from typing import Any, Dict, List, Optional, Sequence, Tuple

import numpy as np
import torch
from torch import Tensor

from frugalnerf_ns.data.sparse_points import SparseDepth, match_descriptors, opencv_projection_matrices, triangulate_checked
from frugalnerf_ns.geometry.camera_conventions import opencv_to_opengl
from frugalnerf_ns.geometry.reprojection import project_to_camera

# ``options`` below is ``photo_poses.PoseEstimationOptions`` (typed loosely: that module imports this one).
PoseEstimationOptions = Any


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


def relative_pose(keypoints, pair, matches, width, height, focal, options):
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
