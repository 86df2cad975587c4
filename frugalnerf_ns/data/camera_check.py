"""Do the cameras explain the photos? Features matched between neighbouring training views, each match
triangulated with the cameras as read: right cameras place a match within a pixel or so of where it was seen and
in front of both cameras; a wrong focal length or principal point, the other axis convention, poses of another
scene, or photos turned or cropped after the cameras were made leave most matches pixels away or behind a camera.

What the check cannot see: views that differ by a sideways translation only (a forward-facing rig that does not
turn) explain their matches under any focal length and principal point (the scene stretches in depth to suit), so
on such splits an intrinsics error can pass; a turn between the views is what exposes it.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Dict, List, Sequence, Tuple

import numpy as np
import torch
from jaxtyping import Float
from torch import Tensor

from frugalnerf_ns.data.sparse_points import (
    TriangulationOptions,
    build_tracks,
    opencv_projection_matrices,
    training_view_matches,
    triangulate_dlt,
)
from frugalnerf_ns.geometry.reprojection import project_to_camera

MIN_MATCHES = 12
"""Fewer matches than this between the training views: too little to judge the cameras by (no verdict)."""
MAX_MEDIAN_ERROR = 2.0
"""Median reprojection error (pixels of the training images) above which the cameras do not explain the photos."""
MIN_IN_FRONT = 0.8
"""Share of matches that must triangulate in front of both cameras."""
BETTER_BY = 1.5
"""Other intrinsics that divide the median error by this much (and by over ``BETTER_BY_PIXELS``) point to the file's
being wrong: on the shared scenes as published the best focal length and principal point are the file's own, while a
focal length 0.8x or 1.25x, or a principal point 10 % off, leaves 1.8-50x the error the right one does (the published
scenes' own: at most 1.05x; docs/notes/camera-check.md)."""
BETTER_BY_PIXELS = 0.1
TEXTURED_FEATURES = 300
"""Photos with this many SIFT features (a median) that still give fewer than ``MIN_MATCHES`` matches are flagged: a
textured scene whose photos do not match (fern's 504x378 photos hold ~1400 features; the bird's 272x480 ones ~120,
the procedural test scene's 96x72 ~100)."""
SEARCH_TRACKS = 500
"""Tracks the search over other intrinsics judges them by (``check_tracks``)."""
VERIFY_THRESHOLD = 1.0
"""Pixels from its epipolar line within which a match counts as explained by the pair's fundamental matrix."""


@dataclass(frozen=True)
class CameraCheck:
    """How well the cameras as read explain the training photos' matches."""

    matches: int
    """Matches between neighbouring training views that one epipolar geometry per pair explains (tracks of two or
    more views; ``verified_matches``)."""
    points: int
    """Matches that triangulate within ``max_error`` pixels in every view, in front of every camera."""
    median_error: float
    """Median over the matches of the largest reprojection error in their views (pixels; inf without matches)."""
    in_front: float
    """Share of the matches triangulated in front of every camera that sees them."""
    max_error: float = 1.5
    focal_scale: float = 1.0
    """The multiple of the given focal lengths that explains the matches best (``FOCAL_SCALES``)."""
    focal_error: float = float("inf")
    """The median error with the focal lengths so scaled."""
    centre_shift: Tuple[float, float] = (0.0, 0.0)
    """The principal point shift (fractions of width, height) that explains the matches best (``CENTRE_SHIFTS``)."""
    centre_error: float = float("inf")
    """The median error with the principal point so shifted."""
    features: int = 0
    """SIFT features a training photo holds (the median over the photos)."""

    @property
    def judged(self) -> bool:
        return self.matches >= MIN_MATCHES

    def _better(self, error: float) -> bool:
        return error * BETTER_BY < self.median_error and self.median_error - error > BETTER_BY_PIXELS

    @property
    def causes(self) -> List[str]:
        """What the matches point to, most specific first (empty: the cameras explain the photos)."""
        if not self.judged:
            if self.features < TEXTURED_FEATURES:
                return []
            return [f"almost no matches ({self.matches}) between textured photos (a median {self.features} features "
                    "each): they share little of the scene, or the cameras pair the photos wrongly (their order)"]
        found = []
        if self.in_front < MIN_IN_FRONT:
            found.append(f"{100 * (1 - self.in_front):.0f}% of the matches triangulate behind a camera: the axis "
                         "convention (OpenCV's y down, z forward read as OpenGL's y up, z back, or the reverse) or "
                         "world-to-camera matrices read as camera-to-world")
        if self._better(self.focal_error):
            found.append(f"the focal length: {self.focal_scale:.2f}x the one read explains the matches "
                         f"{self.median_error / max(self.focal_error, 1e-9):.0f}x better ({self.focal_error:.2f} px)")
        if self._better(self.centre_error):
            found.append(f"the principal point (or a crop): moved by {100 * self.centre_shift[0]:+.0f}% of the width "
                         f"and {100 * self.centre_shift[1]:+.0f}% of the height it explains the matches "
                         f"{self.median_error / max(self.centre_error, 1e-9):.0f}x better ({self.centre_error:.2f} px)")
        if not found and self.median_error > MAX_MEDIAN_ERROR:
            found.append("no focal length or principal point explains them: the poses (their scale, another "
                         "scene's or other photos' poses) or images turned or cropped after the cameras were made")
        return found

    @property
    def flagged(self) -> bool:
        return bool(self.causes)

    def facts(self) -> str:
        return (f"{self.matches} matches, {self.points} points within {self.max_error:g} px, median reprojection error "
                f"{self.median_error:.2f} px, {100 * self.in_front:.0f}% in front of the cameras")

    @classmethod
    def from_dict(cls, values: Dict) -> "CameraCheck":
        return cls(int(values["matches"]), int(values["points"]), float(values["median_error"]), float(values["in_front"]),
                   float(values.get("max_error", 1.5)), float(values["focal_scale"]), float(values["focal_error"]),
                   tuple(values["centre_shift"]), float(values["centre_error"]),  # type: ignore[arg-type]
                   int(values.get("features", 0)))

    def to_dict(self) -> Dict[str, float]:
        return {"matches": self.matches, "points": self.points, "median_error": self.median_error, "max_error": self.max_error,
                "in_front": self.in_front, "focal_scale": self.focal_scale, "focal_error": self.focal_error,
                "centre_shift": list(self.centre_shift), "centre_error": self.centre_error, "features": self.features,
                "judged": self.judged,
                "flagged": self.flagged}


class Observations:
    """Tracks grouped by length: per group the views (points x k) and the features' pixels (points x k x 2)."""

    def __init__(self, tracks: List[List[Tuple[int, int]]], keypoints: Sequence[Float[Tensor, "features 2"]]):
        by_length: Dict[int, List[List[Tuple[int, int]]]] = {}
        for track in tracks:
            by_length.setdefault(len(track), []).append(track)
        self.groups = [
            (torch.tensor([[v for v, _ in t] for t in group], dtype=torch.long),
             torch.stack([torch.stack([keypoints[v][f] for v, f in t]) for t in group]).double())
            for group in by_length.values()
        ]
        self.count = sum(int(view.shape[0]) for view, _ in self.groups)

    def errors(self, camera_to_worlds: Tensor, intrinsics: Tensor) -> Tuple[Tensor, Tensor]:
        """Per track: the largest reprojection error of its DLT point in its views (inf where it cannot be placed)
        and whether the point lies in front of every camera that sees it."""
        c2w, K = camera_to_worlds.double(), intrinsics.double()
        projections = opencv_projection_matrices(c2w, K)
        errors, front = [], []
        for view, observed in self.groups:
            points = triangulate_dlt(projections, view, observed)
            finite = torch.isfinite(points).all(dim=-1)
            points = torch.where(finite[:, None], points, torch.zeros_like(points))
            proj = project_to_camera(points[:, None].expand(-1, view.shape[1], -1), c2w[view], K[view])
            error = (proj.pixels - observed).norm(dim=-1).amax(dim=1)
            errors.append(torch.where(finite, error, torch.full_like(error, float("inf"))))
            front.append(finite & proj.in_front.all(dim=1))
        if not errors:
            return torch.zeros(0, dtype=torch.float64), torch.zeros(0, dtype=torch.bool)
        return torch.cat(errors), torch.cat(front)

    def median_error(self, camera_to_worlds: Tensor, intrinsics: Tensor) -> float:
        error, _ = self.errors(camera_to_worlds, intrinsics)
        return float(error.median()) if error.numel() else float("inf")


FOCAL_SCALES = torch.exp(torch.linspace(np.log(0.5), np.log(2.0), 29)).tolist()
"""Focal lengths tried against the file's (x0.5 to x2, 5 % apart)."""
CENTRE_SHIFTS = torch.linspace(-0.2, 0.2, 9).tolist()
"""Principal point shifts tried, as fractions of the image's width (cx) and height (cy)."""


def better_intrinsics(
    observations: Observations, camera_to_worlds: Tensor, intrinsics: Tensor, size: Tuple[int, int]
) -> Tuple[Tuple[float, float], Tuple[Tuple[float, float], float]]:
    """The focal scale (of the given focal lengths) and the principal point shift (fractions of width, height)
    that explain the matches best, each with the median error it leaves: (scale, error), ((dx, dy), error)."""
    focal = []
    for scale in FOCAL_SCALES:
        k = intrinsics.double().clone()
        k[:, :2] *= scale
        focal.append((observations.median_error(camera_to_worlds, k), scale))
    shifts = []
    for dx in CENTRE_SHIFTS:
        for dy in CENTRE_SHIFTS:
            k = intrinsics.double().clone()
            k[:, 2] += dx * size[0]
            k[:, 3] += dy * size[1]
            shifts.append((observations.median_error(camera_to_worlds, k), (dx, dy)))
    best_focal, best_shift = min(focal), min(shifts)
    return (best_focal[1], best_focal[0]), (best_shift[1], best_shift[0])


def check_tracks(
    tracks: List[List[Tuple[int, int]]], keypoints: Sequence[Float[Tensor, "features 2"]],
    camera_to_worlds: Float[Tensor, "views 3 4"], intrinsics: Float[Tensor, "views 4"], size: Tuple[int, int],
    max_error: float = 1.5,
) -> CameraCheck:
    """Every track triangulated (DLT) with the cameras as given, none dropped: how far its projections land from
    its features and whether it lies in front of its cameras; and how much better other intrinsics would do."""
    observations = Observations(tracks, keypoints)
    if observations.count == 0:
        return CameraCheck(0, 0, float("inf"), 0.0, max_error)
    error, in_front = observations.errors(camera_to_worlds, intrinsics)
    points = int(((error <= max_error) & in_front).sum())
    # The search's medians from at most SEARCH_TRACKS tracks, evenly taken: 110 triangulations of thousands of
    # tracks would cost seconds at every start-up, and a median of 500 moves by a few hundredths of a pixel.
    sample = observations if len(tracks) <= SEARCH_TRACKS else Observations(
        tracks[:: -(-len(tracks) // SEARCH_TRACKS)], keypoints)
    (scale, focal_error), (shift, shift_error) = better_intrinsics(sample, camera_to_worlds, intrinsics, size)
    return CameraCheck(int(error.numel()), points, float(error.median()), float(in_front.double().mean()), max_error,
                       scale, focal_error, shift, shift_error)


def verified_matches(
    keypoints: Sequence[Float[Tensor, "features 2"]], matches: Dict[Tuple[int, int], np.ndarray],
    threshold: float = VERIFY_THRESHOLD,
) -> Dict[Tuple[int, int], np.ndarray]:
    """The matches of each pair that one epipolar geometry explains (a fundamental matrix fitted by RANSAC,
    within ``threshold`` pixels), found from the photos alone: what is left when a repeated texture's wrong matches
    are gone, so that the cameras are judged by matches that are right. Pairs with fewer than 8 matches keep none."""
    import cv2  # nerfstudio's dependency

    verified = {}
    for (i, j), pairs in matches.items():
        pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
        if len(pairs) < 8:
            continue
        a, b = keypoints[i][pairs[:, 0]].numpy(), keypoints[j][pairs[:, 1]].numpy()
        _, mask = cv2.findFundamentalMat(a, b, cv2.FM_RANSAC, threshold, 0.999, 2000)
        if mask is not None:
            verified[(i, j)] = pairs[mask.ravel().astype(bool)]
    return verified


def check_matches(
    keypoints: Sequence[Float[Tensor, "features 2"]], matches: Dict[Tuple[int, int], np.ndarray],
    camera_to_worlds: Float[Tensor, "views 3 4"], intrinsics: Float[Tensor, "views 4"], size: Tuple[int, int],
    max_error: float = 1.5,
) -> CameraCheck:
    """``check_tracks`` on the tracks of the ``verified_matches``."""
    verified = verified_matches(keypoints, matches)
    tracks = build_tracks(verified, [len(k) for k in keypoints])
    check = check_tracks(tracks, keypoints, camera_to_worlds, intrinsics, size, max_error)
    return dataclasses.replace(check, features=int(np.median([len(k) for k in keypoints])))


def check_cameras(
    images: Sequence[np.ndarray], camera_to_worlds: Float[Tensor, "views 3 4"], intrinsics: Float[Tensor, "views 4"],
    options: TriangulationOptions = TriangulationOptions(), progress: bool = False,
) -> CameraCheck:
    """The check on uint8 images: SIFT and matching as the sparse points get them, then ``check_matches``."""
    keypoints, matches = training_view_matches(images, camera_to_worlds, options, progress)
    size = (int(images[0].shape[1]), int(images[0].shape[0]))
    return check_matches(keypoints, matches, camera_to_worlds, intrinsics, size, options.max_reprojection_error)
