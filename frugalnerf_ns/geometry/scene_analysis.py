"""What a scene needs, decided from its training cameras and images (pure torch, no nerfstudio).

FrugalNeRF's settings differ by scene kind: forward-facing captures (LLFF) render in NDC and learn from a
spiral of novel poses; object captures with a mask or a plain background (DTU) get the occlusion loss;
360-degree captures need neither a spiral in front of the cameras nor NDC. ``classify_camera_layout``
tells them apart from the camera layout alone; ``grid_side_for_pixels`` sizes the grid by how much the
training images can actually resolve.
"""

from __future__ import annotations

import math
from typing import List, Literal, NamedTuple, Optional, Sequence, Tuple

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from frugalnerf_ns.geometry.reprojection import project_to_camera

SceneType = Literal["forward-facing", "object", "360"]
SCENE_TYPES = ("forward-facing", "object", "360")

FORWARD_FACING_MAX_SPREAD = 13.0
"""Degrees: viewing directions all within this of their mean make a forward-facing capture. Measured on
our scenes: fern views 6/13 spread 1.8, views 6/9/13 9.3; DTU scan65 views 22/25 17.3, 22/25/28 36.0
(object rigs converge on the object). Two close object views can fall under it: an object mask or a
plain background then decides."""
SURROUND_MIN_COVERAGE = 180.0
"""Degrees of azimuth around the focus point the camera centres must cover to count as a 360 capture."""


class CameraLayout(NamedTuple):
    scene_type: SceneType
    spread_degrees: float
    """Largest angle between a camera's viewing direction and the mean viewing direction."""
    coverage_degrees: float
    """Azimuth the camera centres cover around the focus point (360 minus the largest gap)."""
    focus: Float[Tensor, "3"]
    """Point closest to all optical axes (least squares), where the cameras look."""


def viewing_directions(camera_to_worlds: Float[Tensor, "views 3 4"]) -> Float[Tensor, "views 3"]:
    """Unit world direction each camera looks along (OpenGL axes: -z)."""
    return torch.nn.functional.normalize(-camera_to_worlds[:, :3, 2].double(), dim=-1)


def largest_angle_to_mean_direction(
    camera_to_worlds: Float[Tensor, "views 3 4"], subset: Optional[Sequence[int]] = None
) -> float:
    """Largest angle (degrees) between the viewing direction of a camera of ``subset`` (default: all) and the
    mean viewing direction of all the cameras; 180 where the directions cancel out."""
    directions = viewing_directions(camera_to_worlds)
    mean = directions.mean(0)
    if float(mean.norm()) < 1e-9:
        return 180.0
    chosen = directions if subset is None else directions[list(subset)]
    cosines = (chosen @ (mean / mean.norm())).clamp(-1.0, 1.0)
    return math.degrees(float(torch.acos(cosines).max()))


def _axes_system(camera_to_worlds: Float[Tensor, "views 3 4"]) -> Tuple[Tensor, Tensor]:
    """sum_i (I - d_i d_i^T) and sum_i (I - d_i d_i^T) c_i: the normal equations of the point nearest every
    optical axis (camera centre c_i, viewing direction d_i)."""
    centers = camera_to_worlds[:, :3, 3].double()
    directions = viewing_directions(camera_to_worlds)
    projectors = torch.eye(3, dtype=torch.float64) - directions[:, :, None] * directions[:, None, :]
    return projectors.sum(0), (projectors @ centers[:, :, None]).sum(0)[:, 0]


def axes_conditioning(camera_to_worlds: Float[Tensor, "views 3 4"]) -> float:
    """Smallest eigenvalue of the focus point's normal matrix: ~0 when the optical axes are (nearly)
    parallel and no point is nearest to all of them."""
    return float(torch.linalg.eigvalsh(_axes_system(camera_to_worlds)[0])[0])


def focus_point(camera_to_worlds: Float[Tensor, "views 3 4"], ridge: float = 1e-3) -> Float[Tensor, "3"]:
    """Least-squares point nearest every optical axis.

    Nearly parallel axes (a forward-facing capture) make the plain solve ill-conditioned: a small ``ridge``
    towards the point one mean camera distance ahead of the cameras keeps it finite and sensible there
    (0: the plain solve, for callers that check ``axes_conditioning`` first).
    """
    lhs, rhs = _axes_system(camera_to_worlds)
    if ridge > 0:
        centers = camera_to_worlds[:, :3, 3].double()
        spread = (centers - centers.mean(0)).norm(dim=-1).mean()
        scale = float(spread) if spread > 0 else 1.0
        ahead = centers.mean(0) + viewing_directions(camera_to_worlds).mean(0) * scale
        lhs, rhs = lhs + ridge * torch.eye(3, dtype=torch.float64), rhs + ridge * ahead
    return torch.linalg.solve(lhs, rhs)


def azimuth_coverage(
    centers: Float[Tensor, "views 3"], focus: Float[Tensor, "3"], up: Float[Tensor, "3"]
) -> float:
    """Degrees of azimuth around ``focus`` (about ``up``) that the camera centres span: 360 minus the
    largest empty gap between neighbouring cameras. 0 for a single camera."""
    if len(centers) < 2:
        return 0.0
    up = torch.nn.functional.normalize(up.double(), dim=0)
    offsets = centers.double() - focus.double()
    offsets = offsets - (offsets @ up)[:, None] * up[None]
    helper = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    if abs(float(helper @ up)) > 0.9:
        helper = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    first = torch.nn.functional.normalize(torch.linalg.cross(up, helper), dim=0)
    second = torch.linalg.cross(up, first)
    angles = torch.atan2(offsets @ second, offsets @ first).sort().values
    gaps = torch.cat([angles[1:] - angles[:-1], (angles[:1] + 2 * math.pi) - angles[-1:]])
    return math.degrees(2 * math.pi - float(gaps.max()))


def classify_camera_layout(
    camera_to_worlds: Float[Tensor, "views 3 4"],
    has_object_mask: bool = False,
    forward_facing_max_spread: float = FORWARD_FACING_MAX_SPREAD,
    surround_min_coverage: float = SURROUND_MIN_COVERAGE,
) -> CameraLayout:
    """Forward-facing, object or 360 from the training cameras.

    - object: an object mask or plain background (``has_object_mask``), whatever the cameras do;
    - 360: the centres surround the focus point (azimuth coverage >= ``surround_min_coverage``) or the
      cameras look in opposing directions (mean viewing direction shorter than 0.5);
    - forward-facing: every viewing direction within ``forward_facing_max_spread`` degrees of the mean;
    - object: everything else (cameras converging on something).
    """
    resultant = float(viewing_directions(camera_to_worlds).mean(0).norm())
    spread = largest_angle_to_mean_direction(camera_to_worlds)
    focus = focus_point(camera_to_worlds)
    up = camera_to_worlds[:, :3, 1].double().mean(0)
    if float(up.norm()) < 1e-9:
        up = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    coverage = azimuth_coverage(camera_to_worlds[:, :3, 3], focus, up)
    if has_object_mask:
        # A masked object or one on a plain background (DTU, NeRF-synthetic) is an object scene however the
        # cameras stand, also when they surround it: it gets the occlusion loss and its background prior.
        kind: SceneType = "object"
    elif coverage >= surround_min_coverage or resultant < 0.5:
        kind = "360"
    elif spread <= forward_facing_max_spread:
        kind = "forward-facing"
    else:
        kind = "object"
    return CameraLayout(kind, spread, coverage, focus.float())


FOCUS_BOX_SCALE = 1.2
"""Half the side of ``focus_box`` in training-camera distances from the focus point: the cameras stand inside
the box (a ray starts in it), with a fifth of their distance to spare behind the farthest of them."""


def focus_box(
    camera_to_worlds: Float[Tensor, "views 3 4"], focus: Float[Tensor, "3"], scale: float = FOCUS_BOX_SCALE
) -> Float[Tensor, "2 3"]:
    """A cube centred on ``focus`` whose half side is ``scale`` times the largest distance from a training
    camera to it: the bounded part of a scene whose cameras converge on something (an object on a table in a
    room). A box that runs to the data's far bound (~100x the near one on a phone capture) would spend the
    grid on the room and leave the object a few voxels wide; beyond this one the scene is a far background."""
    distance = float((camera_to_worlds[:, :3, 3].double() - focus.double()).norm(dim=-1).max())
    half = scale * max(distance, 1e-6)
    centre = focus.double()
    return torch.stack([centre - half, centre + half]).float()


def beyond_box(points: Float[Tensor, "points 3"], box: Float[Tensor, "2 3"]) -> Bool[Tensor, " points"]:
    """Which ``points`` lie outside the axis-aligned ``box`` (min corner, max corner); its faces count as inside."""
    box = box.to(points.dtype)
    return ~((points >= box[0]) & (points <= box[1])).all(dim=-1)


def far_shell(
    points: Float[Tensor, "points 3"], box: Float[Tensor, "2 3"], min_points: int = 5
) -> Optional[Tuple[Float[Tensor, "3"], float]]:
    """(centre, radius) of the sphere the far background is painted on: centred on ``box``, at the median
    distance of the triangulated ``points`` that lie beyond the box, never inside the box (at least its half
    diagonal, so every ray that leaves the box meets the sphere beyond it). None with fewer than ``min_points``
    points beyond the box: nothing says how far the background is, and it stays infinitely far away."""
    box = box.double()
    centre = box.mean(dim=0)
    points = points.double()
    beyond = points[beyond_box(points, box)]
    if len(beyond) < max(1, min_points):
        return None
    half_diagonal = float((box[1] - box[0]).norm()) / 2.0
    radius = max(float((beyond - centre).norm(dim=-1).median()), half_diagonal)
    return centre.float(), radius


def has_plain_background(images: Float[Tensor, "views height width 3"], tolerance: float = 0.05, fraction: float = 0.9) -> bool:
    """True when at least ``fraction`` of every image's border pixels are one colour (within ``tolerance``
    of their median): the black or white backdrop of an object capture (DTU, synthetic objects)."""
    for image in images:
        border = torch.cat([image[0], image[-1], image[:, 0], image[:, -1]]).float()
        median = border.median(dim=0).values
        close = ((border - median).abs().max(dim=-1).values <= tolerance).float().mean()
        if float(close) < fraction:
            return False
    return len(images) > 0


PAPER_GRID_SIDE_PER_PIXEL_ROOT = 640.0 / math.sqrt(2 * 1008 * 756)
"""The paper's 640^3 LLFF grid for its own input (2 views at 1008x756): grid side per square root of the
number of training pixels (~0.52). A VM grid's planes (most of its parameters) grow with side^2, i.e. with
the pixel count, so keeping this ratio keeps parameters per observed pixel at the paper's."""


def grid_side_for_pixels(num_train_pixels: int, side_per_pixel_root: float = PAPER_GRID_SIDE_PER_PIXEL_ROOT,
                         min_side: int = 32, max_side: int = 640) -> int:
    """Grid side (voxels along the longest axis of a cube) scaled to the training pixels (paper ratio)."""
    side = side_per_pixel_root * math.sqrt(max(1, num_train_pixels))
    return int(min(max_side, max(min_side, round(side))))


def views_seeing(
    points: Float[Tensor, "points 3"],
    camera_to_worlds: Float[Tensor, "views 3 4"],
    intrinsics: Float[Tensor, "views 4"],
    image_size: Tuple[int, int],
    near_far: Optional[Tuple[float, float]] = None,
) -> Int[Tensor, " points"]:
    """How many of the cameras see each point: it projects inside the image (``image_size`` = width, height) in
    front of the camera, and between the near and far bounds when they are known."""
    width, height = image_size
    points = points.double()
    seen = torch.zeros(len(points), dtype=torch.long, device=points.device)
    for c2w, k in zip(camera_to_worlds.double().to(points.device), intrinsics.double().to(points.device)):
        proj = project_to_camera(points, c2w, k)
        u, v = proj.pixels.unbind(-1)
        visible = proj.in_front & (u >= 0) & (u <= width) & (v >= 0) & (v <= height)
        if near_far is not None:
            visible &= (proj.depth >= near_far[0]) & (proj.depth <= near_far[1])
        seen += visible.long()
    return seen


def seen_region_box(
    box: Float[Tensor, "2 3"],
    camera_to_worlds: Float[Tensor, "views 3 4"],
    intrinsics: Float[Tensor, "views 4"],
    image_size: Tuple[int, int],
    near_far: Optional[Tuple[float, float]] = None,
    min_views: int = 1,
    samples_per_axis: int = 64,
) -> Optional[Float[Tensor, "2 3"]]:
    """Bounding box of the part of ``box`` that at least ``min_views`` training cameras see.

    The box is sampled at cell centres; a sample is seen by a camera when it projects inside the image
    (``image_size`` = width, height) in front of the camera, and between the near and far bounds when they
    are known. The result grows by half a cell so that the cells of the kept samples are whole. None when
    no sample is seen (cameras looking away from the box).
    """
    box = box.double()
    width, height = image_size
    steps = [(torch.arange(samples_per_axis, dtype=torch.float64) + 0.5) / samples_per_axis for _ in range(3)]
    grid = torch.stack(torch.meshgrid(*steps, indexing="ij"), dim=-1).reshape(-1, 3)
    points = box[0] + grid * (box[1] - box[0])
    seen = views_seeing(points, camera_to_worlds, intrinsics, image_size, near_far)
    kept = points[seen >= min(min_views, len(camera_to_worlds))]
    if len(kept) == 0:
        return None
    half_cell = (box[1] - box[0]) / (2 * samples_per_axis)
    return torch.stack([kept.min(0).values - half_cell, kept.max(0).values + half_cell]).clamp(box[0], box[1]).float()


def fit_scene_box(
    box: Float[Tensor, "2 3"],
    seen_box: Optional[Float[Tensor, "2 3"]],
    points: Optional[Float[Tensor, "points 3"]] = None,
    margin: float = 0.05,
) -> Float[Tensor, "2 3"]:
    """The dataparser's ``box`` shrunk to what the training views can constrain: the seen region
    (``seen_region_box``) joined with the sparse points inside ``box``, widened by ``margin`` of its size
    on every side and never beyond ``box``. ``box`` itself when nothing is known."""
    parts = [] if seen_box is None else [seen_box.double()]
    if points is not None and len(points) > 0:
        points, lo, hi = points.double(), box[0].double(), box[1].double()
        inside = points[((points >= lo) & (points <= hi)).all(dim=-1)]
        if len(inside) > 0:
            parts.append(torch.stack([inside.min(0).values, inside.max(0).values]))
    if not parts:
        return box.clone()
    lower = torch.stack([p[0] for p in parts]).min(0).values
    upper = torch.stack([p[1] for p in parts]).max(0).values
    pad = (upper - lower) * margin
    fitted = torch.stack([lower - pad, upper + pad])
    return torch.stack([torch.maximum(fitted[0], box[0].double()), torch.minimum(fitted[1], box[1].double())]).to(box.dtype)


def uninformative_view_notes(
    images: Float[Tensor, "views height width 3"],
    camera_to_worlds: Float[Tensor, "views 3 4"],
    names: Sequence[str],
    black_level: float = 2.0 / 255.0,
    same_position: float = 1e-4,
) -> List[str]:
    """One sentence per training-view problem that trains without error but teaches little: an all-black
    image, and two views taken from the same position (no parallax: nothing to triangulate, and a warp into
    the other view matches at every depth). ``same_position`` is relative to the scene's extent (the camera
    spread, or the largest camera distance from the origin when there is none)."""
    notes = []
    black = [name for name, image in zip(names, images) if float(image.max()) <= black_level]
    if black:
        notes.append(
            f"training image(s) {', '.join(black)} are entirely black: no colour to fit, no features for sparse "
            "depth, nothing for geometric adaptation to match"
        )
    centers = camera_to_worlds[:, :3, 3].double()
    if len(centers) >= 2:
        distance = torch.cdist(centers, centers)
        extent = max(float(distance.max()), float(centers.norm(dim=-1).max()), 1e-12)
        for i, j in zip(*torch.triu_indices(len(centers), len(centers), offset=1).tolist()):
            if float(distance[i, j]) <= same_position * extent:
                notes.append(
                    f"training views {names[i]} and {names[j]} were taken from the same position: no parallax "
                    "between them, so sparse depth and geometric adaptation learn no geometry from the pair"
                )
    return notes
