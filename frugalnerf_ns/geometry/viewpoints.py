"""Where a next photo could be taken, and how to say it to the person holding the camera (pure torch).

The photos of a few-shot capture stand around a subject (an object capture: they converge on it) or side by side
in front of it (a forward-facing capture). ``SubjectFrame`` measures positions around the subject (azimuth about
the photos' mean up, elevation, distance); ``candidate_poses`` lays candidate viewpoints on the surface the photos
span: a ring around the subject at the photos' height and distance, or a grid in the cameras' plane looking where
they look; ``describe`` names a candidate relative to the photos ("between photos 2 and 3, 25 degrees left of
photo 2, same height, 1.1x its distance to the subject"); ``coverage_line`` is the start-up summary of how the
photos cover the subject. Cameras are nerfstudio camera-to-worlds ([n, 3, 4], OpenGL axes: x right, y up, looking
down -z).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import List, Optional, Sequence, Tuple

import torch
from jaxtyping import Float
from torch import Tensor

from frugalnerf_ns.geometry.camera_conventions import average_pose, look_at_poses
from frugalnerf_ns.geometry.scene_analysis import axes_conditioning, focus_point

WELL_COVERED_GAP = 30.0
"""Degrees between neighbouring photos up to which the space between them is seen from both sides well enough:
3 photos within 29 degrees of a phone capture's subject re-render held-out frames at ~25 dB, 38-52 degrees apart
at ~24 dB (bird), 60 degrees apart at ~16 dB, below tensorf (docs/results.md)."""
GUESSED_GAP = 50.0
"""Degrees between neighbouring photos beyond which what lies between them is guessed rather than seen."""


@dataclass(frozen=True)
class SubjectFrame:
    """Positions around the subject the photos look at: azimuth (degrees, counter-clockwise about ``up`` seen from
    above, 0 at the first photo), elevation (degrees above the plane through ``focus`` normal to ``up``) and
    distance to ``focus``."""

    focus: Float[Tensor, "3"]
    up: Float[Tensor, "3"]
    first: Float[Tensor, "3"]
    """Unit horizontal direction of azimuth 0."""

    @property
    def second(self) -> Tensor:
        return torch.linalg.cross(self.up, self.first)

    def _offsets(self, points: Tensor) -> Tuple[Tensor, Tensor]:
        offsets = points.double() - self.focus
        height = offsets @ self.up
        return offsets - height[..., None] * self.up, height

    def azimuths(self, points: Float[Tensor, "n 3"]) -> Float[Tensor, " n"]:
        flat, _ = self._offsets(points)
        return torch.rad2deg(torch.atan2(flat @ self.second, flat @ self.first))

    def elevations(self, points: Float[Tensor, "n 3"]) -> Float[Tensor, " n"]:
        flat, height = self._offsets(points)
        return torch.rad2deg(torch.atan2(height, flat.norm(dim=-1)))

    def distances(self, points: Float[Tensor, "n 3"]) -> Float[Tensor, " n"]:
        return (points.double() - self.focus).norm(dim=-1)

    def positions(self, azimuths: Tensor, elevations: Tensor, distances: Tensor) -> Float[Tensor, "n 3"]:
        """Points at the given azimuths, elevations (degrees) and distances."""
        az, el = torch.deg2rad(azimuths.double()), torch.deg2rad(elevations.double())
        horizontal = az.cos()[:, None] * self.first + az.sin()[:, None] * self.second
        direction = el.cos()[:, None] * horizontal + el.sin()[:, None] * self.up
        return self.focus + distances.double()[:, None] * direction


def subject_focus(camera_to_worlds: Float[Tensor, "views 3 4"]) -> Float[Tensor, "3"]:
    """Where the cameras look: the plain least-squares point nearest their axes where the axes meet well; a small
    ridge keeps nearly parallel axes (forward-facing photos) finite."""
    c2w = camera_to_worlds.detach().cpu().double()
    return focus_point(c2w, ridge=0.0 if axes_conditioning(c2w) >= 5e-4 else 1e-3)


def camera_plane_up(camera_to_worlds: Float[Tensor, "views 3 4"], max_tilt_degrees: float = 30.0) -> Float[Tensor, "3"]:
    """The up of the photos' surroundings: people take photos of a subject at about one height, so the normal of
    the direction square to every camera's x axis where those differ (photos without roll), else the normal of
    the plane through the camera centres (3 or more, not in a line), turned to agree with the cameras' mean up,
    unless it leans more than ``max_tilt_degrees`` from it (photos at several heights); for two cameras, the mean
    up made square to their baseline. Cameras looking down at a subject tilt their own up towards it: their mean
    alone leans to the side they stand on."""
    c2w = camera_to_worlds.double()
    mean_up = c2w[:, :3, 1].mean(0)
    mean_up = mean_up / mean_up.norm() if float(mean_up.norm()) > 1e-9 else torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    # Photos without roll keep their x axis level: up is square to every camera's x axis. Where the x axes differ
    # enough (cameras around a subject) the direction most square to all of them is up.
    rights = c2w[:, :3, 0]
    values, vectors = torch.linalg.eigh(rights.T @ rights)
    if float(values[1]) > 0.05 * len(rights) and float(values[0]) < 0.1 * float(values[1]):
        level = vectors[:, 0] * (1.0 if float(vectors[:, 0] @ mean_up) >= 0 else -1.0)
        if float(level @ mean_up) >= math.cos(math.radians(max_tilt_degrees)):
            return level
    centres = c2w[:, :3, 3]
    if len(centres) == 2:
        baseline = centres[1] - centres[0]
        if float(baseline.norm()) > 1e-9:
            baseline = baseline / baseline.norm()
            square = mean_up - (mean_up @ baseline) * baseline
            if float(square.norm()) > 1e-6:
                return square / square.norm()
        return mean_up
    if len(centres) < 2:
        return mean_up
    singular, vectors = torch.linalg.svd(centres - centres.mean(0), full_matrices=False)[1:]
    if float(singular[1]) < 1e-6 * max(float(singular[0]), 1e-12):  # centres in a line: no plane
        return mean_up
    normal = vectors[-1] * (1.0 if float(vectors[-1] @ mean_up) >= 0 else -1.0)
    if float(normal @ mean_up) < math.cos(math.radians(max_tilt_degrees)):
        return mean_up
    return normal


def subject_frame(camera_to_worlds: Float[Tensor, "views 3 4"], focus: Optional[Tensor] = None) -> SubjectFrame:
    """The frame around where the cameras look (the point nearest every optical axis, unless ``focus`` is given),
    about the cameras' mean up, azimuth 0 at the first camera."""
    c2w = camera_to_worlds.detach().cpu().double()
    focus = subject_focus(c2w) if focus is None else focus.detach().cpu().double()
    up = camera_plane_up(c2w)
    first = c2w[0, :3, 3] - focus
    first = first - (first @ up) * up
    if float(first.norm()) < 1e-9:  # the first camera above the focus: any horizontal direction
        helper = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
        if abs(float(helper @ up)) > 0.9:
            helper = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
        first = torch.linalg.cross(up, helper)
    return SubjectFrame(focus, up, first / first.norm())


def angle_difference(a: Tensor, b: Tensor) -> Tensor:
    """Signed smallest difference a - b of angles in degrees, in [-180, 180)."""
    return (a - b + 180.0) % 360.0 - 180.0


def neighbour_gaps(azimuths: Sequence[float]) -> List[Tuple[float, int, int]]:
    """(gap in degrees, photo before, photo after) for each pair of photos neighbouring in azimuth, going round the
    circle counter-clockwise; the gaps add up to 360. Empty for fewer than 2 photos."""
    if len(azimuths) < 2:
        return []
    order = sorted(range(len(azimuths)), key=lambda i: azimuths[i] % 360.0)
    gaps = []
    for position, index in enumerate(order):
        following = order[(position + 1) % len(order)]
        gaps.append(((azimuths[following] - azimuths[index]) % 360.0 or 360.0, index, following))
    return gaps


@dataclass(frozen=True)
class Candidates:
    camera_to_worlds: Float[Tensor, "n 3 4"]
    layout: str
    """"ring" (around the subject) or "plane" (beside the forward-facing photos)."""
    subject: Float[Tensor, "3"]
    """The point every candidate looks at."""


def candidate_poses(
    camera_to_worlds: Float[Tensor, "views 3 4"],
    forward_facing: bool,
    frame: Optional[SubjectFrame] = None,
    step_degrees: float = 10.0,
    look_at_depth: Optional[float] = None,
    plane_steps: int = 7,
) -> Candidates:
    """Viewpoints on the surface the photos span, looking at what they look at.

    An object or 360 capture: a ring around the subject every ``step_degrees`` of azimuth, at the photos' median
    elevation and median distance (never under the photos' floor, never inside the subject). A forward-facing one:
    a ``plane_steps`` x ``plane_steps`` grid in the plane of the average camera, twice the photos' extent along its
    right and up axes (at least a tenth of the look-at depth), every pose looking at the point ``look_at_depth``
    in front of the average camera, where the training spiral looks."""
    c2w = camera_to_worlds.detach().cpu().double()
    if not forward_facing:
        frame = frame or subject_frame(c2w)
        centres = c2w[:, :3, 3]
        count = max(4, int(round(360.0 / step_degrees)))
        azimuths = torch.arange(count, dtype=torch.float64) * (360.0 / count)
        elevation = frame.elevations(centres).median().expand(count)
        distance = frame.distances(centres).median().expand(count)
        positions = frame.positions(azimuths, elevation, distance)
        return Candidates(look_at_poses(positions, frame.focus, frame.up).float(), "ring", frame.focus)
    mean = torch.from_numpy(average_pose(c2w.numpy()))
    rotation, centre = mean[:, :3], mean[:, 3]
    offsets = (c2w[:, :3, 3] - centre) @ rotation
    if look_at_depth is None:
        look_at_depth = float((c2w[:, :3, 3] - subject_focus(c2w)).norm(dim=-1).mean())
    half = (2.0 * offsets[:, :2].abs().max(0).values).clamp(min=0.1 * look_at_depth)
    steps = torch.linspace(-1.0, 1.0, plane_steps, dtype=torch.float64)
    grid_x, grid_y = torch.meshgrid(steps * half[0], steps * half[1], indexing="xy")
    positions = centre + grid_x.reshape(-1, 1) * rotation[:, 0] + grid_y.reshape(-1, 1) * rotation[:, 1]
    target = centre - rotation[:, 2] * look_at_depth
    return Candidates(look_at_poses(positions, target, rotation[:, 1]).float(), "plane", target)


def separations(
    candidates: Float[Tensor, "n 3 4"], camera_to_worlds: Float[Tensor, "views 3 4"], forward_facing: bool,
    frame: Optional[SubjectFrame] = None,
) -> Float[Tensor, " n"]:
    """How far each candidate stands from the nearest photo, in [0, 1]: around a subject the azimuth difference over
    180 degrees (1: opposite every photo); beside forward-facing photos the distance over their widest baseline,
    clipped at 1. The middle of the largest gap between the photos maximises it."""
    c2w = camera_to_worlds.detach().cpu().double()
    points = candidates.detach().cpu().double()[:, :3, 3]
    if forward_facing:
        centres = c2w[:, :3, 3]
        baseline = max(float(torch.cdist(centres, centres).max()), 1e-9) if len(centres) > 1 else 1.0
        return (torch.cdist(points, centres).min(dim=1).values / baseline).clamp(0.0, 1.0)
    frame = frame or subject_frame(c2w)
    differences = angle_difference(frame.azimuths(points)[:, None], frame.azimuths(c2w[:, :3, 3])[None])
    return differences.abs().min(dim=1).values / 180.0


def _photo_label(names: Sequence[str], index: int) -> str:
    return f"photo {index + 1} ({names[index]})"


def describe(
    candidate: Float[Tensor, "3 4"],
    camera_to_worlds: Float[Tensor, "views 3 4"],
    names: Sequence[str],
    forward_facing: bool,
    frame: Optional[SubjectFrame] = None,
) -> str:
    """Where ``candidate`` stands relative to the photos, in words a person holding the camera can act on.

    Around a subject: between which two photos (neighbours in azimuth), how many degrees left or right of the
    nearest photo as seen from it, its height against that photo's, and its distance to the subject as a multiple
    of the photo's. Beside forward-facing photos: how far right/left and up/down of the nearest photo, in units of
    the photos' widest baseline."""
    c2w = camera_to_worlds.detach().cpu().double()
    point = candidate.detach().cpu().double()[:3, 3]
    centres = c2w[:, :3, 3]
    if forward_facing:
        nearest = int((centres - point).norm(dim=-1).argmin())
        baseline = float(torch.cdist(centres, centres).max()) if len(centres) > 1 else 1.0
        offset = point - centres[nearest]
        across = float(offset @ c2w[nearest, :3, 0]) / max(baseline, 1e-9)
        vertical = float(offset @ c2w[nearest, :3, 1]) / max(baseline, 1e-9)
        parts = [f"{abs(across):.1f} baselines {'right' if across >= 0 else 'left'}" if abs(across) >= 0.05 else "",
                 f"{abs(vertical):.1f} baselines {'up' if vertical >= 0 else 'down'}" if abs(vertical) >= 0.05 else ""]
        where = " and ".join(p for p in parts if p) or "at the same place"
        return f"{where} of {_photo_label(names, nearest)}, facing the same way (a baseline: the widest distance between two photos)"
    frame = frame or subject_frame(c2w)
    photo_az = frame.azimuths(centres)
    az = frame.azimuths(point[None])[0]
    differences = angle_difference(az, photo_az)
    nearest = int(differences.abs().argmin())
    words = []
    for gap, before, after in neighbour_gaps(photo_az.tolist()):
        into = float((az - photo_az[before]) % 360.0)
        if len(centres) >= 2 and 0.0 < into < gap and gap < 360.0:
            words.append(f"between photos {before + 1} and {after + 1}" if gap <= 180.0 else
                         f"on the far side from photos {before + 1} and {after + 1}")
            break
    # Seen from the photo, moving counter-clockwise about up moves the camera to its right.
    side = "right" if float(differences[nearest]) > 0 else "left"
    degrees = abs(float(differences[nearest]))
    words.append(f"{degrees:.0f} degrees {side} of {_photo_label(names, nearest)}" if degrees >= 1.0 else
                 f"where {_photo_label(names, nearest)} stands")
    height = float(frame.elevations(point[None])[0] - frame.elevations(centres[nearest : nearest + 1])[0])
    words.append("same height" if abs(height) < 5.0 else f"{abs(height):.0f} degrees {'higher' if height > 0 else 'lower'}")
    ratio = float(frame.distances(point[None])[0] / frame.distances(centres[nearest : nearest + 1])[0].clamp(min=1e-12))
    words.append(f"{ratio:.1f}x its distance to the subject")
    return ", ".join(words)


def largest_gap_pose(
    camera_to_worlds: Float[Tensor, "views 3 4"], frame: Optional[SubjectFrame] = None, rank: int = 0
) -> Tuple[Float[Tensor, "3 4"], float]:
    """The viewpoint in the middle of the largest azimuth gap between neighbouring photos (at the photos' median
    height and distance, looking at the subject) and that gap in degrees: the simple rule a suggestion must beat.
    ``rank`` 1: the second largest gap (the largest between the photos when the largest is the open side)."""
    c2w = camera_to_worlds.detach().cpu().double()
    frame = frame or subject_frame(c2w)
    centres = c2w[:, :3, 3]
    azimuths = frame.azimuths(centres)
    gaps = sorted(neighbour_gaps(azimuths.tolist()), reverse=True)
    if not gaps:
        middle, size = float(azimuths[0]) + 180.0, 360.0
    else:
        size, before, _ = gaps[min(rank, len(gaps) - 1)]
        middle = float(azimuths[before]) + size / 2.0
    one = torch.tensor([middle], dtype=torch.float64)
    position = frame.positions(one, frame.elevations(centres).median()[None], frame.distances(centres).median()[None])
    return look_at_poses(position, frame.focus, frame.up)[0].float(), size


def coverage_line(
    camera_to_worlds: Float[Tensor, "views 3 4"],
    names: Sequence[str],
    forward_facing: bool,
    num_points: Optional[int] = None,
) -> str:
    """How the photos cover the subject, from the cameras alone, and where a photo would help most.

    Around a subject: the azimuth the photos span and the largest angle between neighbouring photos, judged
    against ``WELL_COVERED_GAP`` and ``GUESSED_GAP``; the advice is the middle of the largest gap (the open side where
    the photos stand on one side of the subject), as ``frugalnerf-next-view`` ranks by default. Forward-facing: the photos see the scene from the front only,
    and their baseline against the distance to what they look at."""
    c2w = camera_to_worlds.detach().cpu().double()
    count = len(c2w)
    points = "" if num_points is None else f"; {num_points} points matched between them"
    if count < 2:
        return f"1 photo: nothing is seen from two sides, depth is guessed everywhere; a second photo helps most{points}"
    if forward_facing:
        centres = c2w[:, :3, 3]
        baseline = float(torch.cdist(centres, centres).max())
        depth = float((centres - subject_focus(c2w)).norm(dim=-1).mean())
        ratio = baseline / max(depth, 1e-9)
        verdict = "good for views between and near them" if ratio >= 0.05 else \
            "a narrow baseline: depth is poorly constrained; a photo further to the side helps most"
        return (f"{count} photos side by side, facing the same way: baseline {ratio:.0%} of the distance to the "
                f"subject: {verdict}; views far beside or behind them are guessed{points}")
    frame = subject_frame(c2w)
    azimuths = frame.azimuths(c2w[:, :3, 3])
    gaps = neighbour_gaps(azimuths.tolist())
    largest, before, after = max(gaps)
    inner = sorted(g for g, _, _ in gaps)[:-1]  # the gaps between photos, without the open side
    span = 360.0 - largest
    between = max(inner) if inner else 0.0
    # The largest gap, also when it is the open side: on our captures a photo there trained as well as or better than
    # the render-based suggestion and random frames (docs/notes/next-view.md); frugalnerf-next-view ranks the same way.
    pose, _ = largest_gap_pose(c2w, frame)
    where = describe(pose, c2w, names, False, frame)
    spread = f"{count} photos over {span:.0f} degrees around the subject"
    if count > 2:
        spread += f", up to {between:.0f} degrees between neighbours"
    if between <= WELL_COVERED_GAP:
        verdict = "good between them; the other side is guessed" if largest > 90.0 else "good"
    elif between <= GUESSED_GAP:
        verdict = "fair: the space between them is seen from both sides only partly"
    else:
        verdict = "the space between them will be guessed"
    advice = f"; a photo {where} helps most" if verdict != "good" else ""
    return f"{spread}: {verdict}{advice}{points}"
